"""Deformation transfer (Sumner & Popović, "Deformation Transfer for Triangle Meshes", SIGGRAPH 2004) of a
blendshape rig onto another neutral of the same topology, with virtual eyelid triangles (Menzel et al. 2022,
sec. 3.2, after Saito) so that transferred blinks close fully.

Building blocks reused by :mod:`usdface.transfer` (seamless partial DT on the avatar):

* :class:`PoissonSolver` - one sparse factorisation of ``G^T A G`` (gradient operator of
  :func:`usdface.mesh.gradient_operator`, triangle areas ``A``) for a target rest mesh, with optional fixed
  vertices; :meth:`PoissonSolver.solve` reconstructs points from target deformation gradients for any number
  of shapes (all right-hand sides through the same factorisation).
* :func:`eyelid_triangles` - virtual triangles bridging eye holes, found from the template's blink shapes.
* :func:`deformation_transfer` - the whole transfer, ``deltas[K,n,3]`` in, ``deltas[K,n,3]`` out.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from ..errors import GeometryError
from ..mesh import (
    boundary_loops,
    frame_vectors,
    gradient_coefficients,
    gradient_operator,
    inverse_rest_frames,
    spd_lu,
    triangle_areas,
)

__all__ = ["PoissonSolver", "eyelid_triangles", "zip_loop", "deformation_transfer"]


#: The bytes :meth:`PoissonSolver.solve_transfer`'s per-triangle arrays of one group of shapes may take.
SHAPE_BLOCK_BYTES = 64e6


def _shapes(values, group: slice):
    """``values[group]`` of per-shape ``values[m,...,3]`` (3-d), else ``values`` itself (None, or one
    ``[n,3]`` array or ``[1,n,3]`` for every shape)."""
    if values is None or np.ndim(values) < 3 or len(values) == 1:
        return values
    return np.asarray(values)[group]


class PoissonSolver:
    """Sumner & Popović (2004), eq. (5): least-squares reconstruction of points from per-triangle
    deformation gradients on a fixed rest mesh (the linear system shared by DT, EBFR and partial DT).

    Solves ``min_X sum_f a_f ||Q_f(X) - Q*_f||_F^2 (+ screen)`` where ``Q_f(X)`` is the deformation
    gradient of triangle f (rest plane part, :func:`usdface.mesh.gradient_operator`) and ``a_f`` its rest
    area.

    Parameters
    ----------
    rest : points[n,3] of the rest (target) mesh, metres.
    triangles : triangles[t,3] (may include virtual triangles).
    fixed : optional vertex indices whose positions are prescribed at solve time (partial transfer); the
        others are solved for. Without fixed vertices the global translation is free; it is pinned by a tiny
        screening term (relative weight ``screen``) that makes the mean displacement match a reference.
    tri_weights : optional extra per-triangle weights[t] (multiplied with the areas).

    One sparse LU (:func:`usdface.mesh.spd_lu`) is computed here and reused by every :meth:`solve`.
    """

    def __init__(self, rest: np.ndarray, triangles: np.ndarray, *, fixed=None, tri_weights=None,
                 screen: float = 1e-7):
        self.rest = np.asarray(rest, dtype=np.float64)
        self.triangles = np.asarray(triangles, dtype=np.int64)
        n = len(self.rest)
        self.C = gradient_coefficients(self.rest, self.triangles)            # [t,3,3], G's entries
        self.G = gradient_operator(self.rest, self.triangles, coefficients=self.C)
        a = triangle_areas(self.rest, self.triangles)
        if tri_weights is not None:
            a = a * np.asarray(tri_weights, dtype=np.float64)
        self.area = a
        self._scatter = None
        self.W = sp.diags(np.repeat(a, 3))
        self.GtW = (self.G.T @ self.W).tocsr()
        A = (self.GtW @ self.G).tocsc()
        # vertex "mass" (one third of incident area), for the screening / translation pin
        mass = np.bincount(self.triangles.ravel(), weights=np.repeat(a / 3.0, 3), minlength=n)
        mass = np.maximum(mass, 1e-12 * max(mass.max(), 1e-300))
        self.mass = mass
        self.fixed = None if fixed is None else np.unique(np.asarray(fixed, dtype=np.int64))
        if self.fixed is None or len(self.fixed) == 0:
            self.fixed = None
            self.free = np.arange(n)
            self.eps = screen * A.diagonal().mean() / mass.mean()
            self._lu = spd_lu(A + sp.diags(self.eps * mass))
        else:
            mask = np.ones(n, bool)
            mask[self.fixed] = False
            self.free = np.flatnonzero(mask)
            self._A_fc = A[self.free][:, self.fixed].tocsr()
            A_ff = A[self.free][:, self.free].tocsc()
            self.eps = 0.0
            try:
                self._lu = splu(A_ff.tocsc())  # default pivoting: reports a singular (unfixed) part
            except RuntimeError as exc:
                raise GeometryError("partial deformation transfer: a free part has no fixed vertex",
                                    fix="fix at least one vertex in every connected part") from exc

    def solve(self, gradients: np.ndarray, *, reference: np.ndarray | None = None,
              fixed_points: np.ndarray | None = None) -> np.ndarray:
        """Points ``[..., n, 3]`` whose deformation gradients best match ``gradients[..., t, 3, 3]``.

        ``reference[..., n, 3]``: positions the screening pulls towards (fixes the free translation: the
        mass-weighted mean of the result equals the reference's); defaults to the rest points.
        ``fixed_points[..., k, 3]``: positions of the fixed vertices (required when built with ``fixed``).
        """
        Q = np.asarray(gradients, dtype=np.float64)
        lead = Q.shape[:-3]
        Q = Q.reshape((-1,) + Q.shape[-3:])
        m, t = Q.shape[0], Q.shape[1]
        # column (shape s, coordinate c) of the right-hand side holds Q^T rows: entry (3f + r) = Q[s, f, c, r]
        rhs = Q.transpose(1, 3, 0, 2).reshape(3 * t, 3 * m)
        B = (self.GtW @ rhs).reshape(-1, m, 3)                                                # [n,m,3]
        return self._solve_rhs(B, reference, fixed_points).reshape(lead + (len(self.rest), 3))

    def solve_transfer(self, source: np.ndarray, deformed: np.ndarray, *, reference: np.ndarray | None = None,
                       fixed_points: np.ndarray | None = None) -> np.ndarray:
        """:meth:`solve` for the deformation gradients ``Q = V~ V^-1`` of ``source[n,3] -> deformed[m,n,3]``
        (Sumner & Popović eq. 3, :func:`usdface.mesh.deformation_gradients`, on this solver's triangles),
        without forming them: ``G^T W Q`` is assembled per triangle as ``V~ (a V^-1 c_k)`` for its three
        vertices k (``c_k`` the gradient coefficients), one sparse scatter for all shapes. Same result as
        ``solve(deformation_gradients(source, deformed, triangles))`` up to rounding. Returns ``[m,n,3]``.

        The shapes go through in groups whose per-triangle arrays (``[t,g,3]``, eight of them) stay within
        :data:`SHAPE_BLOCK_BYTES`: every column is its own (the scatter and the solve act column by column),
        and a 74.5k-vertex capture's 51 shapes took ~1.1 GB at once; dev1-dev3's are one group."""
        tri = self.triangles
        n, t = len(self.rest), len(tri)
        P = np.asarray(deformed, dtype=np.float64).reshape(-1, n, 3)
        m = P.shape[0]
        # u[f,k] = a_f V_f^-1 c_k[f]: the rest-side factor of triangle f's contribution to its vertex k
        u = self.area[:, None, None] * np.einsum("tij,tkj->tki", inverse_rest_frames(source, tri), self.C)
        if self._scatter is None:      # [n, 3t]: contribution (k, f) goes to vertex tri[f, k]
            self._scatter = sp.csr_matrix((np.ones(3 * t), (tri.T.ravel(), np.arange(3 * t))),
                                          shape=(n, 3 * t))
        group = max(1, int(SHAPE_BLOCK_BYTES // (8 * 8 * 3 * max(t, 1))))
        out = []
        for lo in range(0, max(m, 1), group):     # one (empty) group when there are no shapes: [0,n,3]
            g = slice(lo, lo + group)
            e1, e2, e3 = frame_vectors(np.ascontiguousarray(P[g].transpose(1, 0, 2)), tri, axis=0)  # [t,g,3]
            mg = e1.shape[1]
            contrib = np.empty((3, t, mg, 3))
            term = np.empty((t, mg, 3))
            for k in range(3):                # e1 u_k0 + e2 u_k1 + e3 u_k2, summed in that order, in place
                c = contrib[k]
                np.multiply(e1, u[:, k, 0, None, None], out=c)
                c += np.multiply(e2, u[:, k, 1, None, None], out=term)
                c += np.multiply(e3, u[:, k, 2, None, None], out=term)
            del e1, e2, e3, term
            B = (self._scatter @ contrib.reshape(3 * t, 3 * mg)).reshape(n, mg, 3)
            del contrib
            out.append(self._solve_rhs(B, _shapes(reference, g), _shapes(fixed_points, g)))
        return out[0] if len(out) == 1 else np.concatenate(out)

    def _solve_rhs(self, B, reference, fixed_points):
        """Solve ``A X = B`` (``B[n,m,3]`` = ``G^T W Q``) with the screening / fixed vertices -> ``[m,n,3]``.
        """
        n, m = B.shape[0], B.shape[1]
        if self.fixed is None:
            ref = self.rest if reference is None else np.asarray(reference, dtype=np.float64)
            ref = np.broadcast_to(ref.reshape((-1, n, 3)) if ref.ndim > 2 else ref, (m, n, 3))
            B = B + self.eps * self.mass[:, None, None] * ref.transpose(1, 0, 2)
            X = self._lu.solve(B.reshape(n, 3 * m)).reshape(n, m, 3).transpose(1, 0, 2)
            # exact translation pin: mass-weighted mean equals the reference's
            w = self.mass / self.mass.sum()
            X = X + (np.einsum("n,mnc->mc", w, ref) - np.einsum("n,mnc->mc", w, X))[:, None, :]
        else:
            if fixed_points is None:
                raise ValueError("fixed_points required: the solver was built with fixed vertices")
            fp = np.broadcast_to(np.asarray(fixed_points, dtype=np.float64).reshape(-1, len(self.fixed), 3),
                                 (m, len(self.fixed), 3))
            Bf = B[self.free] - (self._A_fc @ fp.transpose(1, 0, 2).reshape(len(self.fixed), 3 * m)
                                 ).reshape(-1, m, 3)
            Xf = self._lu.solve(Bf.reshape(len(self.free), 3 * m)).reshape(-1, m, 3)
            X = np.empty((n, m, 3))
            X[self.free] = Xf
            X[self.fixed] = fp.transpose(1, 0, 2)
            X = X.transpose(1, 0, 2)
        return X


def zip_loop(points: np.ndarray, loop: np.ndarray) -> np.ndarray:
    """Triangulate a hole by zipping its two sides: the loop is split at its two farthest-apart vertices
    (the eye corners) into two chains, which are joined by a triangle strip in order of arc length.
    Returns triangles ``[k,3]`` (vertex indices)."""
    loop = np.asarray(loop, dtype=np.int64)
    p = np.asarray(points)[loop]
    d = np.linalg.norm(p[:, None] - p[None], axis=-1)
    a, b = np.unravel_index(np.argmax(d), d.shape)
    a, b = sorted((int(a), int(b)))
    upper = loop[a:b + 1]
    lower = np.concatenate([loop[b:], loop[:a + 1]])[::-1]      # from corner a to corner b, other side

    def arclen(chain):
        q = np.asarray(points)[chain]
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(q, axis=0), axis=1))])
        return s / max(s[-1], 1e-300)

    su, sl = arclen(upper), arclen(lower)
    tris, i, j = [], 0, 0
    while i < len(upper) - 1 or j < len(lower) - 1:
        adv_upper = j >= len(lower) - 1 or (i < len(upper) - 1 and su[i + 1] <= sl[j + 1])
        if adv_upper:
            tri = (upper[i], upper[i + 1], lower[j])
            i += 1
        else:
            tri = (upper[i], lower[j + 1], lower[j])
            j += 1
        if len(set(tri)) == 3:
            tris.append(tri)
    return np.array(tris, dtype=np.int64).reshape(-1, 3)


def _loop_area(points: np.ndarray, loop: np.ndarray) -> np.ndarray:
    """Vector-area magnitude of a closed loop, for points[..., n, 3] -> [...]."""
    p = points[..., loop, :]
    c = np.cross(p, np.roll(p, -1, axis=-2)).sum(axis=-2)
    return 0.5 * np.linalg.norm(c, axis=-1)


def eyelid_triangles(neutral: np.ndarray, deltas: np.ndarray, triangles: np.ndarray, names=None, *,
                     close_ratio: float = 0.8, loops: list | None = None) -> np.ndarray:
    """Virtual triangles between upper and lower eyelids (Menzel et al. 2022, sec. 3.2), found from the
    template's blink shapes.

    A hole of the mesh (a boundary loop other than the outer rim) is an eye if some blink shape (a name
    containing "blink"; without names, every shape) shrinks the hole's area below ``close_ratio`` of the
    neutral's (phone face meshes keep a slit open even in a full blink, hence the generous default).
    Each eye hole is zipped (:func:`zip_loop`). ``neutral[n,3]``, ``deltas[K,n,3]`` are the
    template's; returns ``[k,3]`` (empty when there is no such hole). ``loops``: the mesh's
    :func:`usdface.mesh.boundary_loops` if the caller has them.
    """
    neutral = np.asarray(neutral, dtype=np.float64)
    deltas = np.asarray(deltas, dtype=np.float64)
    loops = boundary_loops(triangles, len(neutral)) if loops is None else loops
    if len(loops) < 2 or len(deltas) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    rim = int(np.argmax([_loop_area(neutral, lp) for lp in loops]))   # the outer rim encloses the most
    loops = [lp for i, lp in enumerate(loops) if i != rim]
    if not loops:
        return np.zeros((0, 3), dtype=np.int64)
    idx = list(range(len(deltas)))
    if names is not None:
        blink = [k for k, nm in enumerate(names) if "blink" in str(nm).lower()]
        if not blink:
            return np.zeros((0, 3), dtype=np.int64)
        idx = blink
    shapes = neutral[None] + deltas[idx]
    out = []
    for loop in loops:
        if len(loop) < 4:
            continue
        a0 = _loop_area(neutral, loop)
        if a0 <= 0:
            continue
        if np.min(_loop_area(shapes, loop)) < close_ratio * a0:
            out.append(zip_loop(neutral, loop))
    return np.concatenate(out) if out else np.zeros((0, 3), dtype=np.int64)


def deformation_transfer(source_neutral: np.ndarray, source_deltas: np.ndarray, target_neutral: np.ndarray,
                         triangles: np.ndarray, *, extra_triangles: np.ndarray | None = None,
                         names=None, eyelids: bool = True, fixed=None, fixed_deltas=None,
                         solver: PoissonSolver | None = None, loops: list | None = None) -> np.ndarray:
    """Sumner & Popović (2004), eqs. (3)-(5): transfer ``source_deltas[K,n,3]`` (on ``source_neutral[n,3]``)
    onto ``target_neutral[n,3]`` of the same topology; returns target ``deltas[K,n,3]`` (metres).

    Per triangle, the source deformation gradients ``S_j = V~_j V^-1`` (4th-vertex frames) are the targets of
    a least-squares reconstruction on the target rest mesh (one factorisation for all K shapes x 3
    coordinates). The free translation is pinned so that each shape's mass-weighted mean displacement equals
    the source's. ``eyelids=True`` adds :func:`eyelid_triangles` so blinks close fully; ``extra_triangles``
    adds your own virtual triangles. ``fixed`` (vertex indices) with ``fixed_deltas[K,k,3]``: partial
    transfer with prescribed displacements there (seamless partial DT building block). ``loops``: the
    mesh's :func:`usdface.mesh.boundary_loops` for the eyelids, if the caller has them.
    """
    src = np.asarray(source_neutral, dtype=np.float64)
    tgt = np.asarray(target_neutral, dtype=np.float64)
    D = np.asarray(source_deltas, dtype=np.float64)
    if src.shape != tgt.shape or D.shape[1:] != src.shape:
        raise GeometryError(f"deformation transfer: shapes differ (source {src.shape}, target {tgt.shape}, "
                            f"deltas {D.shape})", fix="use meshes of the same topology")
    tris = np.asarray(triangles, dtype=np.int64)
    extra = [] if extra_triangles is None else [np.asarray(extra_triangles, dtype=np.int64).reshape(-1, 3)]
    if eyelids and solver is None:
        extra.append(eyelid_triangles(src, D, tris, names, loops=loops))
    all_tris = np.concatenate([tris] + extra) if extra else tris
    if solver is None:
        solver = PoissonSolver(tgt, all_tris, fixed=fixed)
    else:
        all_tris = solver.triangles
    # the deformation gradients S_j = V~_j V^-1 enter only through G^T W S_j: assembled without forming them
    if solver.fixed is None:
        X = solver.solve_transfer(src, src[None] + D, reference=tgt[None] + D)
    else:
        fd = np.asarray(fixed_deltas, dtype=np.float64).reshape(len(D), -1, 3)
        X = solver.solve_transfer(src, src[None] + D, fixed_points=tgt[solver.fixed][None] + fd)
    return X - tgt[None]
