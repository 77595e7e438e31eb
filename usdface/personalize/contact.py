"""Lip and eyelid contact (J. Hable, "Solving face scans for ARKit", Filmic Worlds 2021, future work): pairs
of vertices across the mouth and eye openings that a template shape brings together, a smooth correction that
keeps them together in the person's fitted shapes, and a check that lips do not pass through each other.

Pure numpy/scipy (arrays in, arrays out; metres). The pieces:

* :func:`find_openings` - the holes of the mesh (boundary loops other than the outer rim), each split at its
  two farthest-apart vertices (the corners) into an upper and a lower side, with the neutral's *opening
  direction* ``n`` (unit, from the lower side to the upper, perpendicular to the corner-to-corner axis).
* :func:`signed_gaps` - ``g_p = (X_u - X_l) . n`` per pair ``p = (u, l)`` of a posed shape ``X``: > 0 open,
  0 in contact, < 0 the lower side has passed the upper.
* :func:`find_contact_pairs` - the pair rule: for each contact shape (:data:`CONTACT_SHAPES`: the blinks,
  ``mouthClose`` on top of ``jawOpen`` as ARKit defines it, ``mouthPress*``, ``mouthRoll*``), on every opening
  the shape moves, each vertex of one side is paired with the closest vertex of the other side in the
  *template's* posed shape; a pair is in contact if that distance is at most :data:`CONTACT_RADIUS` x the
  face size (the neutral's bounding-box diagonal) and the shape closes at least :data:`CLOSURE` (90 %) of
  the neutral's gap there. The target of each pair is the template's own signed
  gap there.
* :class:`ContactSolver` - the correction. For shape j with pairs ``P_j`` the corrected deltas are
  ``B_j + s n`` with the scalar field ``s[n]`` minimising (:meth:`ContactSolver.correction`)

      E(s) = ||L s||^2 + eps ||s||^2 + w sum_p (g_p(B_j) + s_u - s_l - t_p)^2

  (``L`` the umbrella Laplacian, so the correction is smooth; ``eps = rings^-4`` keeps it local, its decay
  length is ``rings`` edges; ``w`` large: contact as a soft constraint). One sparse factorisation of
  ``L^T L + eps I`` serves every shape; each shape's few pair rows enter by the Woodbury identity (exact).
* :func:`contact_test` - whether the training frames agree with contact (a likelihood-ratio test).
* :func:`lip_crossings` - item 4 of issue 10: lower-lip vertices of a posed shape (neutral + delta) that
  crossed the upper lip, with their depth.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..arkit import normalize_name
from ..errors import GeometryError
from ..mesh import boundary_loops, spd_lu, uniform_laplacian

__all__ = ["CONTACT_SHAPES", "CONTACT_RADIUS", "CORRECTION_RINGS", "CONTACT_WEIGHT", "Opening",
           "ContactPairs", "find_openings", "signed_gaps", "find_contact_pairs", "ContactSolver",
           "contact_test", "apply_contact", "keep_contact", "lip_crossings", "most_moved_opening",
           "LipCrossings", "face_size", "lip_pairs_from_motion", "LipPairs"]

#: Shapes whose template pose may bring the two sides of an opening together, with the shapes they are
#: posed on top of (ARKit: ``mouthClose`` closes the lips *independent of the jaw*: it is authored on top
#: of ``jawOpen``; alone it pushes the lower lip through the upper one).
CONTACT_SHAPES = {"eyeBlinkLeft": (), "eyeBlinkRight": (), "mouthClose": ("jawOpen",),
                  "mouthPressLeft": (), "mouthPressRight": (), "mouthRollLower": (), "mouthRollUpper": ()}
#: A pair is in contact in the template's pose if its two vertices are at most this x the face size (the
#: neutral's bounding-box diagonal) apart: 1.5 % = 3.6 mm on a 24 cm face mask, well under half a phone face
#: mesh's edge (8 mm) and above a scan's noise.
CONTACT_RADIUS = 0.015
#: ... and the shape must close at least this share of the neutral's gap at the pair
#: (``g_posed <= (1 - CLOSURE) g_neutral``): a blink that leaves the lids 3 mm apart near a corner brings
#: nothing into contact.
CLOSURE = 0.9
#: Decay length of the correction, in edge rings (``eps = rings^-4``): the lips and lids of a phone mesh are
#: one or two rings deep.
CORRECTION_RINGS = 2.0
#: Weight ``w`` of the pair rows against the unit-free smoothness term: 1e8 leaves a 1e-8 relative residual,
#: i.e. a hard constraint in practice (nanometres on a millimetre gap).
CONTACT_WEIGHT = 1e8
#: Share of a shape's largest displacement its mean motion on an opening's vertices must reach for the
#: opening to count as moved by the shape.
OPENING_MOTION = 0.1
#: Significance level of :func:`contact_test`.
CONTACT_ALPHA = 0.05


@dataclass
class Opening:
    """A hole of the mesh: ``loop[m]`` (ordered boundary vertices), ``corners[2]``, ``upper[a]`` and
    ``lower[b]`` (the two sides, corners excluded, in loop order), ``direction[3]`` (unit opening direction
    on the neutral it was found on: from the lower side's centroid to the upper's, perpendicular to the
    corner axis)."""

    loop: np.ndarray
    corners: np.ndarray
    upper: np.ndarray
    lower: np.ndarray
    direction: np.ndarray

    def direction_on(self, neutral: np.ndarray) -> np.ndarray:
        """The opening direction ``[3]`` on another neutral of the same topology (same sides)."""
        return _direction(np.asarray(neutral, dtype=np.float64), self.corners, self.upper, self.lower)


@dataclass
class ContactPairs:
    """The contact pairs of one shape: ``shape`` (index), ``name``, ``opening`` (index into the openings),
    ``upper[m]``/``lower[m]`` (vertex indices), ``target[m]`` (the template's signed gap, metres),
    ``companions`` (indices of the shapes it is posed on, e.g. jawOpen for mouthClose)."""

    shape: int
    name: str
    opening: int
    upper: np.ndarray
    lower: np.ndarray
    target: np.ndarray
    companions: tuple = field(default_factory=tuple)


def _loop_area(points: np.ndarray, loop: np.ndarray) -> float:
    p = points[loop]
    return 0.5 * float(np.linalg.norm(np.cross(p, np.roll(p, -1, axis=0)).sum(axis=0)))


def _direction(points, corners, upper, lower) -> np.ndarray:
    w = points[corners[1]] - points[corners[0]]
    w /= max(np.linalg.norm(w), 1e-300)
    d = points[upper].mean(axis=0) - points[lower].mean(axis=0)
    d -= w * (d @ w)
    return d / max(np.linalg.norm(d), 1e-300)


def find_openings(neutral: np.ndarray, triangles: np.ndarray, *, up=(0.0, 1.0, 0.0),
                  loops: list | None = None) -> list[Opening]:
    """The holes of a mesh (mouth, eyes), each split into its upper and lower side.

    ``neutral[n,3]``, ``triangles[t,3]``. The outer rim (the loop enclosing the largest area) is no opening;
    holes of fewer than 4 vertices are skipped. A hole is split at its two farthest-apart vertices (the
    corners, as :func:`usdface.personalize.dt.zip_loop` does); the side whose centroid lies further along
    ``up`` (the capture format's +Y) is the upper one. Returns the openings in boundary-loop order.
    ``loops``: the mesh's :func:`usdface.mesh.boundary_loops` if the caller has them.
    """
    p = np.asarray(neutral, dtype=np.float64)
    loops = boundary_loops(triangles, len(p)) if loops is None else loops
    if len(loops) < 2:
        return []
    rim = int(np.argmax([_loop_area(p, lp) for lp in loops]))
    up = np.asarray(up, dtype=np.float64)
    out = []
    for i, loop in enumerate(loops):
        if i == rim or len(loop) < 4:
            continue
        q = p[loop]
        d = np.linalg.norm(q[:, None] - q[None], axis=-1)
        a, b = sorted(int(x) for x in np.unravel_index(np.argmax(d), d.shape))
        one, two = loop[a + 1:b], np.concatenate([loop[b + 1:], loop[:a]])
        if len(one) == 0 or len(two) == 0:
            continue
        if p[one].mean(axis=0) @ up < p[two].mean(axis=0) @ up:
            one, two = two, one
        corners = loop[[a, b]]
        out.append(Opening(loop, corners, one, two, _direction(p, corners, one, two)))
    return out


def signed_gaps(posed: np.ndarray, upper: np.ndarray, lower: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """``g[..., m] = (X_u - X_l) . n`` (metres) of posed points ``posed[..., n, 3]`` at pairs ``upper[m]``,
    ``lower[m]`` along the opening direction ``direction[3]``: > 0 open, 0 in contact, < 0 crossed."""
    X = np.asarray(posed, dtype=np.float64)
    return (X[..., upper, :] - X[..., lower, :]) @ np.asarray(direction, dtype=np.float64)


def face_size(neutral: np.ndarray) -> float:
    """The neutral's bounding-box diagonal (metres): the length the contact radius is relative to."""
    p = np.asarray(neutral, dtype=np.float64)
    return float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))


def find_contact_pairs(neutral: np.ndarray, deltas: np.ndarray, triangles: np.ndarray, names, *,
                       radius: float = CONTACT_RADIUS, openings: list[Opening] | None = None,
                       shapes: dict = CONTACT_SHAPES) -> list[ContactPairs]:
    """The pair rule: vertices across an opening that the template shape brings into contact.

    ``neutral[n,3]``, ``deltas[K,n,3]``: the template rig (metres); ``names[K]`` in any ARKit spelling. For
    every shape of ``shapes`` (default :data:`CONTACT_SHAPES`) present, posed as ``neutral + delta`` plus its
    companions (``mouthClose`` on ``jawOpen``), and every opening the shape moves (mean displacement of the
    opening's vertices >= :data:`OPENING_MOTION` x the shape's largest), each vertex of either side is paired
    with the closest vertex of the other side in the posed shape; pairs at most ``radius`` x
    :func:`face_size` apart whose signed gap the shape closes by at least :data:`CLOSURE` of the neutral's
    are kept (each pair once). ``target`` is the template's signed gap
    (:func:`signed_gaps`, direction on the template's neutral). Shapes with no pair are left out.
    """
    p = np.asarray(neutral, dtype=np.float64)
    D = np.asarray(deltas, dtype=np.float64)
    openings = find_openings(p, triangles) if openings is None else openings
    canon = [normalize_name(nm) or str(nm) for nm in names]
    limit = radius * face_size(p)
    out = []
    for name, comps in shapes.items():
        if name not in canon:
            continue
        k = canon.index(name)
        comp = tuple(canon.index(c) for c in comps if c in canon)
        posed = p + D[k] + sum((D[c] for c in comp), np.zeros_like(p))
        mag = np.linalg.norm(D[k], axis=1)
        peak = mag.max()
        if peak <= 0:
            continue
        for oi, op in enumerate(openings):
            if mag[op.loop].mean() < OPENING_MOTION * peak:
                continue
            d = np.linalg.norm(posed[op.upper][:, None] - posed[op.lower][None], axis=-1)     # [a,b]
            a_idx = np.arange(len(op.upper))
            b_idx = np.arange(len(op.lower))
            cand = np.concatenate([np.stack([a_idx, d.argmin(axis=1)], 1),
                                   np.stack([d.argmin(axis=0), b_idx], 1)])
            cand = np.unique(cand, axis=0)
            cand = cand[d[cand[:, 0], cand[:, 1]] <= limit]
            u, low = op.upper[cand[:, 0]], op.lower[cand[:, 1]]
            g = signed_gaps(posed, u, low, op.direction)
            closed = g <= (1.0 - CLOSURE) * signed_gaps(p, u, low, op.direction)
            if closed.any():
                out.append(ContactPairs(k, name, oi, u[closed], low[closed], g[closed], comp))
    return out


#: What :func:`_bilaplacian_lu` keeps for the next fit: ``(key, A, lu)`` of the last mesh topology.
_BILAPLACIAN: list = [None]
#: A factorization is kept only while its ``L`` and ``U`` hold at most this many entries (~12 bytes each:
#: 3M ~ 36 MB); a phone's face mesh (dev1's 1,203 vertices) needs ~0.1M.
BILAPLACIAN_KEEP_MAX_NNZ = 3_000_000


def _bilaplacian_lu(triangles, n: int, eps: float):
    """``(A, lu)``: ``A = L^T L + eps I`` (``L`` the umbrella Laplacian of ``triangles`` on ``n`` vertices,
    CSC) and its sparse LU (:func:`usdface.mesh.spd_lu`). Both depend on the topology only, not on the
    positions: the last one is kept (one entry, while small: :data:`BILAPLACIAN_KEEP_MAX_NNZ`) and returned
    again for the same ``triangles``, ``n`` and ``eps`` - every capture of a phone's face mesh has one
    topology, so a batch worker or a session fitting several captures factorizes it once (the same
    factorization, the same corrections to the bit)."""
    tri = np.ascontiguousarray(triangles, dtype=np.int64)
    key = (int(n), float(eps), tri.shape, hashlib.blake2b(tri.tobytes(), digest_size=16).digest())
    kept = _BILAPLACIAN[0]                           # one read: another thread may replace it
    if kept is not None and kept[0] == key:
        return kept[1], kept[2]
    L = uniform_laplacian(tri, n)
    A = (L.T @ L + eps * sp.identity(n)).tocsc()
    lu = spd_lu(A)
    if lu.nnz <= BILAPLACIAN_KEEP_MAX_NNZ:
        _BILAPLACIAN[0] = (key, A, lu)
    return A, lu


class ContactSolver:
    """The smooth contact correction on one mesh: ``neutral[n,3]``, ``triangles[t,3]``; ``rings`` the
    decay length in edges (``eps = rings^-4``), ``weight`` the pair rows' weight ``w``.

    Factorises ``A = L^T L + eps I`` once (``L`` the umbrella Laplacian, unit-free); :meth:`correction`
    then costs one triangular solve per pair.
    """

    def __init__(self, neutral, triangles, *, rings: float = CORRECTION_RINGS,
                 weight: float = CONTACT_WEIGHT):
        n = len(neutral)
        self.eps = float(rings) ** -4
        self.weight = float(weight)
        self.A, self.lu = _bilaplacian_lu(triangles, n, self.eps)
        self.n = n

    def correction(self, upper, lower, residual, fixed=None) -> np.ndarray:
        """The scalar field ``s[n]`` (metres along the opening direction) minimising
        ``s^T A s + w ||G s - r||^2`` with ``(G s)_p = s_u - s_l`` and ``r = residual[m]`` (target gap minus
        current gap): ``s = A^-1 G^T (I / w + G A^-1 G^T)^-1 r`` (Woodbury, exact). ``fixed`` (vertex
        indices, e.g. an artist's pins) adds rows ``s_v = 0`` of the same weight."""
        upper, lower = np.asarray(upper, dtype=np.int64), np.asarray(lower, dtype=np.int64)
        fixed = np.zeros(0, np.int64) if fixed is None else np.asarray(fixed, dtype=np.int64).ravel()
        m, f = len(upper), len(fixed)
        if m == 0:
            return np.zeros(self.n)
        Gt = np.zeros((self.n, m + f))
        Gt[upper, np.arange(m)] += 1.0
        Gt[lower, np.arange(m)] -= 1.0
        Gt[fixed, m + np.arange(f)] = 1.0
        r = np.concatenate([np.asarray(residual, dtype=np.float64), np.zeros(f)])
        AiGt = self.lu.solve(Gt)                                               # [n,m+f]
        S = Gt.T @ AiGt + np.eye(m + f) / self.weight                         # [m+f,m+f]
        return AiGt @ np.linalg.lstsq(S, r, rcond=None)[0]


def contact_test(weights: np.ndarray, residuals: np.ndarray, correction: np.ndarray, shape: int, dof: int,
                 *, alpha: float = CONTACT_ALPHA, weight_variance=None, deltas=None) -> dict:
    """Do the training frames agree with contact for one shape? A likelihood-ratio test of the fit with the
    correction (``dof`` fewer degrees of freedom: one per pair) against the fit without.

    ``weights[F,K]`` (training weights), ``residuals[F,n,3]`` (frames minus the unconstrained fit, metres),
    ``correction[n,3]`` (added to shape ``shape``). The increase of the fit term,
    ``dE = sum_i ||r_i - w_ij c||^2 - ||r_i||^2``, is compared with ``sigma^2 chi2_{1-alpha}(dof)``, with
    ``sigma^2`` the frames' mean squared residual per coordinate where the correction acts (vertices it moves
    by at least 1 % of its largest: the noise level that matters there, not the static rest). Returns
    ``{"delta_mm2", "threshold_mm2", "agrees"}``: ``agrees`` when the data cannot reject contact (a shape
    the frames barely show always agrees; one they show with the sides apart does not).

    With ``weight_variance[F,K]`` (each reported weight's error variance,
    :func:`.weights.weight_error_variance`) and ``deltas[K,n,3]`` (the fitted shapes, metres) also ``"share"``
    in [0, 1]: how far the frames' evidence for the correction stands above its noise, the positive-part
    James-Stein factor ``max(0, 1 - var b / b^2)`` of its coefficient ``b = sum_i w_i <r_i, c> / E`` (1: the
    residual holds the correction whole), ``E = sum_i w_i^2 |c|^2``, ``var b = (sigma^2 E + sum_i w_i^2 sum_k
    var_ik <B_k, c>^2) / E^2`` from the scans' ``sigma^2`` and the weights' errors (they move frame ``i``'s
    residual by ``-sum_k e_ik B_k``). A test the frames' weight errors make agree (the residual asks for
    closed lips because the phone reported the lip-opening shapes too high; generated person noisy:115's
    ``mouthPressRight``, share 0.30) does not reject contact, but the correction is then the template's, not
    the frames' estimate (:func:`usdface.transfer.trust.shape_trust`).
    """
    from scipy.special import gammaincinv

    w = np.asarray(weights, dtype=np.float64)[:, shape]
    R = np.asarray(residuals, dtype=np.float64)
    c = np.asarray(correction, dtype=np.float64)
    cross = np.einsum("f,fvc,vc->", w, R, c)
    dE = float(np.sum(w ** 2) * np.sum(c ** 2) - 2.0 * cross)
    mag = np.linalg.norm(c, axis=1)
    support = mag >= 0.01 * mag.max() if mag.max() > 0 else np.ones(len(mag), bool)
    sigma2 = float(np.mean(R[:, support] ** 2))
    dof = max(int(dof), 1)
    thr = float(sigma2 * 2.0 * gammaincinv(dof / 2.0, 1.0 - alpha))          # sigma^2 chi2_{1-alpha}(dof)
    out = {"delta_mm2": dE * 1e6, "threshold_mm2": thr * 1e6, "agrees": bool(dE <= thr)}
    energy = float(np.sum(w ** 2) * np.sum(c ** 2))
    if weight_variance is not None and deltas is not None and energy > 0:
        proj = np.einsum("knc,nc->k", np.asarray(deltas, dtype=np.float64), c)             # <B_k, c>
        var_cross = sigma2 * energy + float(np.sum(w[:, None] ** 2 * np.asarray(weight_variance) * proj ** 2))
        beta = cross / energy
        out["share"] = float(max(0.0, 1.0 - var_cross / energy ** 2 / beta ** 2)) if beta > 0 else 0.0
    return out


def apply_contact(neutral, triangles, deltas, pairs: list[ContactPairs], openings: list[Opening], *,
                  mode: str = "auto", weights=None, residuals=None, solver: ContactSolver | None = None,
                  pinned=None, weight_variance=None, unmeasured=None):
    """Keep each contact shape's pairs at the template's gap (:class:`ContactSolver`) in fitted ``deltas``.

    ``neutral[n,3]`` (the person's B0), ``deltas[K,n,3]`` (fitted, metres), ``pairs`` from
    :func:`find_contact_pairs` on the template, ``openings`` of the same topology. ``mode``: ``"on"``
    corrects every shape with pairs; ``"auto"`` only those whose training frames agree with contact
    (:func:`contact_test` on ``weights[F,K]`` and ``residuals[F,n,3]`` = frames minus the fit; without them
    "auto" acts as "on"); ``"off"`` measures only. ``pinned[K,n]`` (bool, optional): vertices the correction
    must not move (artist pins). Gaps are measured on ``neutral + delta`` (+ companions)
    along the opening direction on ``neutral``.

    ``weight_variance[F,K]``: the reported weights' error variances, for :func:`contact_test`'s ``share``;
    ``unmeasured[K,n,3]`` (optional, added to in place): each applied correction times ``1 - share`` (the
    whole correction where there is no share), the part the frames do not carry.

    Returns ``(deltas[K,n,3], report)``; ``report[name]`` = ``{"pairs", "applied", "target_mm" (the
    template's gaps), "gap_before_mm"/"gap_after_mm" (max |gap - target| over the pairs, mm),
    "min_gap_before_mm"/"min_gap_after_mm" (smallest signed gap), "test" (auto only)}``.
    """
    if mode not in ("auto", "on", "off"):
        raise ValueError(f"contact mode {mode!r}")
    p = np.asarray(neutral, dtype=np.float64)
    out = np.array(deltas, dtype=np.float64, copy=True)
    if pairs and mode != "off" and solver is None:
        solver = ContactSolver(p, triangles)
    report = {}
    for pr in pairs:
        n_dir = openings[pr.opening].direction_on(p)
        base = p + sum((out[c] for c in pr.companions), np.zeros_like(p))
        before = signed_gaps(base + out[pr.shape], pr.upper, pr.lower, n_dir)
        entry = {"pairs": int(len(pr.upper)), "applied": False,
                 "target_mm": (pr.target * 1000).round(4).tolist(),
                 "gap_before_mm": float(np.abs(before - pr.target).max() * 1000),
                 "min_gap_before_mm": float(before.min() * 1000)}
        after = before
        if mode != "off":
            fixed = None if pinned is None else np.flatnonzero(pinned[pr.shape])
            s = solver.correction(pr.upper, pr.lower, pr.target - before, fixed)
            c = s[:, None] * n_dir[None]
            apply = True
            if mode == "auto" and weights is not None and residuals is not None:
                entry["test"] = contact_test(weights, residuals, c, pr.shape, len(pr.upper),
                                             weight_variance=weight_variance, deltas=deltas)
                apply = entry["test"]["agrees"]
            if apply:
                out[pr.shape] += c
                if unmeasured is not None:
                    # the part of the correction the frames' evidence does not carry (contact_test's share)
                    unmeasured[pr.shape] += (1.0 - entry.get("test", {}).get("share", 0.0)) * c
                after = signed_gaps(base + out[pr.shape], pr.upper, pr.lower, n_dir)
                entry["applied"] = True
                entry["max_correction_mm"] = float(np.abs(s).max() * 1000)
        entry["gap_after_mm"] = float(np.abs(after - pr.target).max() * 1000)
        entry["min_gap_after_mm"] = float(after.min() * 1000)
        prev = report.get(pr.name)
        if prev is None:
            report[pr.name] = entry
        else:                  # one shape on two openings (corrected one after the other): merge the figures
            prev["pairs"] += entry["pairs"]
            prev["applied"] = prev["applied"] or entry["applied"]
            prev["target_mm"] += entry["target_mm"]
            for key in ("gap_before_mm", "gap_after_mm"):
                prev[key] = max(prev[key], entry[key])
            for key in ("min_gap_before_mm", "min_gap_after_mm"):
                prev[key] = min(prev[key], entry[key])
    return out, report


def keep_contact(neutral, triangles, template_neutral, template_deltas, names, deltas, *, mode: str = "auto",
                 points=None, weights=None, pinned=None, residuals=None, loops=None, weight_variance=None):
    """The fit's contact step: pairs from the template (:func:`find_contact_pairs`), then
    :func:`apply_contact` on the fitted ``deltas[K,n,3]``.

    ``neutral[n,3]`` (the person's B0), ``template_neutral[n,3]``, ``template_deltas[K,n,3]`` (the template
    rig on the same topology), ``names[K]``; ``points[F,n,3]``, ``weights[F,K]``: the training frames the fit
    used (for ``mode="auto"``'s test); ``residuals[F,n,3]``: the frames minus the fit
    (``points - neutral - weights @ deltas``) if the caller has them; ``loops``: the mesh's
    :func:`usdface.mesh.boundary_loops`, likewise; ``weight_variance[F,K]``: the weights' error variances
    (:func:`contact_test`'s share). Returns ``(deltas, {"mode", "shapes": per-shape report, "unmeasured":
    [K,n,3] the corrections' part the frames do not carry, :func:`apply_contact`})``.
    """
    openings = find_openings(template_neutral, triangles, loops=loops)
    pairs = find_contact_pairs(template_neutral, template_deltas, triangles, names, openings=openings)
    if residuals is None and points is not None and weights is not None:
        W = np.asarray(weights, dtype=np.float64)
        D = np.asarray(deltas, dtype=np.float64)
        residuals = (np.asarray(points, dtype=np.float64) - np.asarray(neutral, dtype=np.float64)[None]
                     - (W @ D.reshape(len(D), -1)).reshape((len(W),) + D.shape[1:]))
    unmeasured = np.zeros(np.shape(deltas))
    out, report = apply_contact(neutral, triangles, deltas, pairs, openings, mode=mode, weights=weights,
                                residuals=residuals, pinned=pinned, weight_variance=weight_variance,
                                unmeasured=unmeasured)
    return out, {"mode": mode, "shapes": report, "unmeasured": unmeasured}


@dataclass
class LipCrossings:
    """Result of :func:`lip_crossings`: ``vertices[c]`` (lower-side vertices that crossed), ``depth[c]``
    (metres past the upper side, > 0), ``count`` and ``max_depth`` (metres; 0 when none)."""

    vertices: np.ndarray
    depth: np.ndarray

    @property
    def count(self) -> int:
        return int(len(self.vertices))

    @property
    def max_depth(self) -> float:
        return float(self.depth.max()) if len(self.depth) else 0.0


def _upper_at(neutral, op: Opening):
    """For every lower-side vertex: the two upper-side (incl. corners) neighbours bracketing its position
    along the corner axis on the neutral, and the interpolation weight of the second."""
    chain = np.concatenate([op.corners[:1], op.upper, op.corners[1:]])
    w = neutral[op.corners[1]] - neutral[op.corners[0]]
    w /= max(np.linalg.norm(w), 1e-300)
    x_up = (neutral[chain] - neutral[op.corners[0]]) @ w
    order = np.argsort(x_up, kind="stable")
    chain, x_up = chain[order], x_up[order]
    x_lo = (neutral[op.lower] - neutral[op.corners[0]]) @ w
    j = np.clip(np.searchsorted(x_up, x_lo) - 1, 0, len(chain) - 2)
    t = np.clip((x_lo - x_up[j]) / np.maximum(x_up[j + 1] - x_up[j], 1e-300), 0.0, 1.0)
    return chain[j], chain[j + 1], t


@dataclass
class LipPairs:
    """Lip pairs on a mesh whose lips are joined (no mouth hole): ``upper[m]``, ``lower[m]`` (vertex indices),
    ``direction[m,3]`` (unit, per pair, from the lower vertex towards the upper one as the mouth opens)."""

    upper: np.ndarray
    lower: np.ndarray
    direction: np.ndarray


def lip_pairs_from_motion(neutral: np.ndarray, opening_delta: np.ndarray, *,
                          radius: float | None = None) -> LipPairs:
    """The lips of a mesh without a mouth hole (an avatar head whose lips run into the mouth bag), found by
    what the mouth does: under ``opening_delta[n,3]`` (the rig's ``jawOpen``) the lower lip moves with the
    jaw (at least half the largest displacement) and the upper lip stays (at most a tenth of it). Each
    lower-lip vertex is paired with the closest upper-lip vertex on ``neutral[n,3]``; pairs at most
    ``radius`` apart (default :data:`CONTACT_RADIUS` x :func:`face_size`) are the lip line. The direction of
    a pair is its relative motion under the opening, reversed (lower towards upper).
    """
    from scipy.spatial import cKDTree

    p = np.asarray(neutral, dtype=np.float64)
    d = np.asarray(opening_delta, dtype=np.float64)
    mag = np.linalg.norm(d, axis=1)
    peak = mag.max() if len(mag) else 0.0
    lower, upper = np.flatnonzero(mag >= 0.5 * peak), np.flatnonzero(mag <= 0.1 * peak)
    if peak <= 0 or len(lower) == 0 or len(upper) == 0:
        raise GeometryError("lip check: the opening shape moves nothing (or everything alike)",
                            fix="pass the rig's jawOpen offsets as opening_delta")
    r = CONTACT_RADIUS * face_size(p) if radius is None else float(radius)
    # (searched just past the radius: the same nearest vertex for every pair kept, inf for the others)
    dist, j = cKDTree(p[upper]).query(p[lower], distance_upper_bound=r * (1.0 + 1e-9))
    keep = dist <= r
    lo, up = lower[keep], upper[j[keep]]
    rel = d[up] - d[lo]
    direction = rel / np.maximum(np.linalg.norm(rel, axis=1, keepdims=True), 1e-300)
    return LipPairs(up, lo, direction)


def most_moved_opening(openings: list[Opening], delta: np.ndarray) -> int:
    """Index of the opening whose boundary loop ``delta[n,3]`` moves most on average (the mouth under
    ``jawOpen``; :func:`find_openings`'s order)."""
    mag = np.linalg.norm(np.asarray(delta, dtype=np.float64), axis=1)
    return int(np.argmax([mag[op.loop].mean() for op in openings]))


def lip_crossings(neutral: np.ndarray, triangles: np.ndarray, delta: np.ndarray, *,
                  opening: int | None = None, tolerance: float = 0.0,
                  openings: list[Opening] | None = None, opening_delta: np.ndarray | None = None,
                  radius: float | None = None, pairs: LipPairs | None = None) -> LipCrossings:
    """Lower-lip vertices that passed through the upper lip in the posed shape ``neutral + delta``.

    ``neutral[n,3]``, ``triangles[t,3]``, ``delta[n,3]`` (same units as the neutral). A crossing is a
    signed gap (:func:`signed_gaps`: upper minus lower along the opening direction) below ``-tolerance``;
    its depth is minus the gap.

    * A mesh with a mouth hole (a capture's face mask): the mouth is ``opening`` (an index into
      :func:`find_openings`; default: the opening whose vertices ``delta`` moves most - pass it explicitly
      for a shape that also moves the lids). Each lower-side vertex is paired with the upper side at the same
      position along the corner axis on the neutral (linear between the two upper vertices that bracket it),
      along the neutral's opening direction.
    * A mesh whose lips are joined (an avatar head; or ``openings=[]``): pass ``opening_delta`` (the rig's
      ``jawOpen`` offsets): pairs and per-pair directions from :func:`lip_pairs_from_motion` (``radius``),
      or the ``pairs`` it returned (to check many shapes of one mesh at the cost of one search).

    Raises :class:`GeometryError` for a ``delta`` of the wrong shape, or a mesh with no opening and no
    ``opening_delta``.
    """
    p = np.asarray(neutral, dtype=np.float64)
    d = np.asarray(delta, dtype=np.float64)
    if d.shape != p.shape:
        raise GeometryError(f"lip check: delta has shape {d.shape}, the neutral {p.shape}",
                            fix="pass one shape's offsets for every vertex of the mesh")
    ops = find_openings(p, triangles) if openings is None else openings
    X = p + d
    if not ops:
        if pairs is None and opening_delta is None:
            raise GeometryError("lip check: the mesh has no opening (no boundary loop besides the rim)",
                                fix="pass opening_delta (the rig's jawOpen offsets) to find the lips by "
                                    "their motion")
        if pairs is None:
            pairs = lip_pairs_from_motion(p, opening_delta, radius=radius)
        g = np.einsum("ij,ij->i", X[pairs.upper] - X[pairs.lower], pairs.direction)
        bad = g < -float(tolerance)
        return LipCrossings(pairs.lower[bad], -g[bad])
    op = ops[most_moved_opening(ops, d) if opening is None else opening]
    a, b, t = _upper_at(p, op)
    upper_pt = (1.0 - t)[:, None] * X[a] + t[:, None] * X[b]
    g = (upper_pt - X[op.lower]) @ op.direction_on(p)
    bad = g < -float(tolerance)
    return LipCrossings(op.lower[bad], -g[bad])
