"""The person's motion as a field over the avatar: per shape and vertex, the rotation and scale that turn the
avatar's generic motion into the person's (the personalization beyond what the capture sees).

Inside the face region the capture tells, shape by shape, how the person's motion ``P_j(v)`` differs from the
avatar's generic motion ``A_j(v)``. Outside it (the mouth and eye sockets behind the capture's holes, the
neck, the back of the head, the teeth, gums and tongue of other meshes) there is no measurement, but the
tissue is the same and the motion is continuous. This module models the difference as the smallest local
change that maps one motion onto the other - a rotation and a scale, ``P_j(v) = s R A_j(v)`` - a field that
is smooth over the head and is applied to the avatar's *own* generic motion (so a vertex the generic shape
leaves still stays still and sparse shapes stay sparse):

1. :func:`rotation_scale` - the field on the face: ``Phi_j(v) = s R - I [J,m,3,3]``, unit-free;
2. :func:`smooth_field` - its motion-weighted local average (a vertex that barely moves in a shape says
   little about that shape's field);
3. :func:`field_noise`, :func:`reliability` - how far each vertex's field can be trusted: the part of the
   personalization that does not scale with the generic motion is noise (estimated per shape from the face),
   and where the generic motion is not well above it the field is shrunk towards 0 (the generic motion)
   before it is carried beyond the capture;
4. :func:`extend_field` - screened harmonic extension beyond the face (one sparse factorization for every
   shape and matrix entry): the values around a hole fill the socket behind it, and the field decays to 0
   (the generic motion) over ``length`` metres away from the face;
5. :func:`apply_field` - ``A_j + Phi_j A_j`` on any mesh, with the field sampled where that mesh is.

All arrays internal metres: ``points[m,3]``, ``generic[J,m,3]``, ``person[J,m,3]``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..mesh import cross, spd_lu, triangle_areas, vector_lengths, vertex_adjacency, vertex_areas
from ..motion import shape_norms
from .surface import cotangent_laplacian

__all__ = ["rotation_scale", "scale_weight", "smooth_field", "extend_field", "FieldExtension",
           "data_stiffness", "neighbourhood_matrix", "dilate", "apply_field", "motion_weights", "pockets",
           "field_noise", "reliability"]

#: Below this fraction of a shape's peak motion a vertex's own field is not trusted (noise-level motion).
MOTION_FLOOR = 0.02


def motion_weights(generic, *, floor: float = MOTION_FLOOR, peak=None, norms=None) -> np.ndarray:
    """``[J,m]`` confidence of each vertex's field: ``(|A_j(v)| / peak_j)^2`` ramped to 0 below ``floor``.
    ``peak[J]``: each shape's largest motion when ``generic`` holds only some vertices of the mesh (default:
    the largest over ``generic``); ``norms[J,m]``: :func:`usdface.motion.shape_norms` of ``generic`` when the
    caller has them (``generic`` is then not read)."""
    mag = shape_norms(generic) if norms is None else np.asarray(norms, dtype=np.float64)
    top = mag.max(axis=-1, keepdims=True) if peak is None else np.asarray(peak, dtype=np.float64)[:, None]
    rel = mag / np.maximum(top, 1e-300)
    ramp = np.clip((rel - floor) / floor, 0.0, 1.0)
    return rel * rel * ramp


def rotation_scale(generic, person, *, max_scale: float = 4.0,
                   full_scale: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per shape and vertex the minimal rotation ``R`` (about ``a x p``) and the scale ``s = |p|/|a|`` with
    ``s R a = p`` for ``a = generic[j,v]``, ``p = person[j,v]`` (both ``[J,m,3]``).

    Returns ``(phi[J,m,3,3] = s R - I, valid[J,m])``; ``phi`` is 0 where the generic shape does not move the
    vertex, where the motions point apart by more than 120 degrees (no small change explains it), or where the
    scale leaves ``[1/max_scale, max_scale]``. Without ``full_scale``, ``valid`` is boolean; with it, a float
    weight in [0, 1] (:func:`scale_weight`): 1 within ``[1/full_scale, full_scale]``, falling smoothly in
    ``|log s|`` to 0 at ``max_scale``, so a measurement near the bound counts for little instead of switching
    between all and nothing.
    """
    a = np.asarray(generic, dtype=np.float64)
    p = np.asarray(person, dtype=np.float64)
    na = vector_lengths(a)
    npp = vector_lengths(p)
    ok = (na > 1e-12) & (npp > 1e-12)
    ah = a / np.maximum(na, 1e-300)[..., None]
    ph = p / np.maximum(npp, 1e-300)[..., None]
    cos = np.clip(np.einsum("...c,...c->...", ah, ph), -1.0, 1.0)
    scale = npp / np.maximum(na, 1e-300)
    valid = ok & (cos > -0.5) & (scale < max_scale) & (scale > 1.0 / max_scale)
    if full_scale is not None:
        valid = valid * scale_weight(scale, full_scale, max_scale)
    # Rodrigues for the rotation taking ah onto ph, R = I + [v]x + [v]x^2 / (1 + cos) with v = ah x ph, entry
    # by entry: [v]x^2 = v v^T - |v|^2 I (each entry the same sum of the same products as the 3x3 matrix
    # product, so the same values to the last bit, without the [J,m,3,3] temporaries)
    v = cross(ah, ph)                                             # (np.cross to the bit)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    den = np.maximum(1.0 + cos, 1e-3)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y / den, x * z / den, y * z / den
    phi = np.empty(a.shape + (3,))                               # s R - I
    phi[..., 0, 0] = scale * (1.0 + -(zz + yy) / den) - 1.0
    phi[..., 1, 1] = scale * (1.0 + -(zz + xx) / den) - 1.0
    phi[..., 2, 2] = scale * (1.0 + -(yy + xx) / den) - 1.0
    phi[..., 0, 1], phi[..., 1, 0] = scale * (-z + xy), scale * (z + xy)
    phi[..., 0, 2], phi[..., 2, 0] = scale * (y + xz), scale * (-y + xz)
    phi[..., 1, 2], phi[..., 2, 1] = scale * (-x + yz), scale * (x + yz)
    phi[valid == 0] = 0.0
    return phi, valid


def scale_weight(scale, full_scale: float, max_scale: float) -> np.ndarray:
    """``[...]`` in [0, 1]: 1 where ``scale`` (> 0) is within ``[1/full_scale, full_scale]``, 0 outside
    ``(1/max_scale, max_scale)``, between them a smoothstep in ``|log scale|`` (continuous with its
    derivative, symmetric in a scale and its inverse)."""
    lo, hi = np.log(full_scale), np.log(max_scale)
    t = np.clip((np.abs(np.log(np.maximum(scale, 1e-300))) - lo) / max(hi - lo, 1e-300), 0.0, 1.0)
    return 1.0 - t * t * (3.0 - 2.0 * t)


def neighbourhood_matrix(triangles, n: int, rings: int, rows=None, *, adjacency=None) -> sp.csr_matrix:
    """``[n,n]`` boolean sparse matrix: vertices within ``rings`` edge rings of each other (self included);
    ``rows`` (indices): only those rows, ``[len(rows), n]`` (the cost of the rows that are used). Boolean
    (one byte a value): a 9-ring neighbourhood of a 225k-vertex head holds 16M entries. ``adjacency``: the
    mesh's :func:`usdface.mesh.vertex_adjacency` when the caller has it."""
    adj = vertex_adjacency(triangles, n) if adjacency is None else adjacency
    adj = (adj + sp.eye(n)).astype(bool).tocsr()
    out = adj if rows is None else adj[np.asarray(rows, dtype=np.int64)]
    ring = out                                     # the vertices first reached at the last step (and more)
    for _ in range(rings - 1):                     # grown from the outer ring only: rows x rings, not rings^2
        ring = (ring @ adj).tocsr() > out          # boolean product (or of ands), minus what is reached
        out = (out + ring).tocsr()
    return out


def dilate(mask, triangles, rings: int) -> np.ndarray:
    """``mask[..., n]`` (bool, per vertex; e.g. one row per shape) grown by ``rings`` edge rings."""
    out = np.asarray(mask, dtype=bool)
    if rings <= 0 or not out.any():
        return out
    near = neighbourhood_matrix(triangles, out.shape[-1], rings)
    flat = out.reshape(-1, out.shape[-1]).T.astype(np.float64)                       # [n, rows]
    return ((near @ flat) > 0).T.reshape(out.shape)


def smooth_field(phi, weights, triangles, *, rings: int = 2, neighbourhood=None, rows=None) -> np.ndarray:
    """Motion-weighted local average of ``phi[J,m,3,3]`` over ``rings`` edge rings, weights ``[J,m]``
    (:func:`motion_weights`): ``S(w phi) / S(w)``; 0 where no neighbour moves. ``rows`` (indices): only
    there (0 elsewhere; ``neighbourhood`` is then :func:`neighbourhood_matrix` of those rows, best as CSC:
    only the columns of vertices some shape moves are read, a few tenths of a face for most shapes)."""
    phi = np.asarray(phi, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    n_shapes, m = w.shape
    s = neighbourhood_matrix(triangles, m, rings, rows) if neighbourhood is None else neighbourhood
    r = s.shape[0]
    cols = np.flatnonzero((w > 0).any(axis=0))                  # the other columns of w phi and w are 0
    s = sp.csc_matrix(s)[:, cols]
    wc = w[:, cols]
    both = np.empty((cols.size, n_shapes * 10))             # one product for the sums and the weights
    both[:, :n_shapes * 9] = (wc[..., None] * phi[:, cols].reshape(n_shapes, cols.size, 9)).transpose(
        1, 0, 2).reshape(cols.size, n_shapes * 9)
    both[:, n_shapes * 9:] = wc.T
    both = s @ both
    num, den = both[:, :n_shapes * 9], both[:, n_shapes * 9:]                       # [r, J*9], [r, J]
    out = num.reshape(r, n_shapes, 9) / np.maximum(den, 1e-300)[..., None]
    out[den <= 1e-12] = 0.0
    out = out.transpose(1, 0, 2).reshape(n_shapes, r, 3, 3)
    if rows is None:
        return out
    full = np.zeros((n_shapes, m, 3, 3))
    full[:, np.asarray(rows, dtype=np.int64)] = out
    return full


def field_noise(generic, change, where, mass) -> tuple[np.ndarray, np.ndarray]:
    """Per shape, the noise of the personalization and the spread of the field, from the data themselves.

    Where the person's motion is the generic one turned and scaled (``P = s R A``, :func:`rotation_scale`),
    the personalization ``|P - A|^2 = |Phi A|^2`` grows with the generic motion ``|A|^2``; what does not is
    noise (of the fit, of the correspondence: it shows where the generic shape barely moves). The
    area-weighted least-squares line ``|P - A|^2 = noise^2 + spread^2 |A|^2`` over the vertices
    ``where[J,v]`` gives both, per shape (a method-of-moments estimate, as James-Stein's; each clipped at 0).
    Given motion averaged over a patch of skin, the noise is that of the patch average: noise that averages
    out over the patch does not count, noise shared by the patch does.

    ``generic[J,v,3]`` (``A``) and ``change[J,v,3]`` (``P - A``), m; ``mass[v]`` lumped areas.
    Returns ``(noise2[J] m^2, spread2[J])``.
    """
    g = np.asarray(generic, dtype=np.float64)
    d = np.asarray(change, dtype=np.float64)
    mass = np.asarray(mass, dtype=np.float64)
    noise2, spread2 = np.zeros(len(g)), np.zeros(len(g))
    for j in range(len(g)):
        v = np.flatnonzero(where[j])
        if v.size < 3:
            continue
        a = np.einsum("vc,vc->v", g[j, v], g[j, v])
        u = np.einsum("vc,vc->v", d[j, v], d[j, v])
        sw = np.sqrt(mass[v])
        coef = np.linalg.lstsq(np.column_stack([sw, sw * a]), sw * u, rcond=None)[0]
        noise2[j], spread2[j] = max(float(coef[0]), 0.0), max(float(coef[1]), 0.0)
    return noise2, spread2


def reliability(motion2, noise2, spread2) -> np.ndarray:
    """``[J,m]`` in [0,1]: the Wiener factor ``spread^2 a^2 / (spread^2 a^2 + noise^2)`` of a field measured
    on generic motion of squared length ``motion2[J,m]`` (m^2; of the patch average, as the noise), with
    ``noise2[J]``, ``spread2[J]`` from :func:`field_noise`: the field's expected share of what was measured
    there. 1 where the shape has no noise, 0 where it has no spread."""
    signal = np.asarray(spread2, dtype=np.float64)[:, None] * np.asarray(motion2, dtype=np.float64)
    total = signal + np.asarray(noise2, dtype=np.float64)[:, None]
    return np.where(total > 0, signal / np.maximum(total, 1e-300), 1.0)


def pockets(triangles, known, mass, *, adjacency=None) -> np.ndarray:
    """``[m]`` bool: the unknown vertices of the pockets behind the known region's holes - each connected
    part of the unknown vertices whose area (``mass[m]``, lumped vertex areas) is smaller than the known
    region's (the mouth and eye sockets behind a face; not the rest of the head beyond it). ``adjacency``:
    the mesh's :func:`usdface.mesh.vertex_adjacency` when the caller has it."""
    from scipy.sparse.csgraph import connected_components

    known = np.asarray(known, dtype=bool)
    out = np.zeros(known.shape, dtype=bool)
    free = np.flatnonzero(~known)
    if free.size == 0 or not known.any():
        return out
    adj = (vertex_adjacency(np.asarray(triangles), known.size) if adjacency is None else adjacency).tocsr()
    n_parts, label = connected_components(adj[free][:, free], directed=False)
    part_area = np.bincount(label, weights=np.asarray(mass, dtype=np.float64)[free], minlength=n_parts)
    out[free] = part_area[label] < float(np.sum(np.asarray(mass)[known]))
    return out


class FieldExtension:
    """Screened harmonic extension on one mesh, factorized once: :meth:`extend` maps ``values[m,c]`` given on
    ``known[m]`` (and, as data, where ``data[m] > 0``) to every vertex (see :func:`extend_field`).
    ``mass[m]``: lumped vertex areas; ``beyond[m]``: the unknown vertices outside the :func:`pockets` (where
    the field fades); ``in_pocket[m]`` (bool, optional): the pockets as found on another mesh of the same
    surface (a proxy of it), instead of on this one; ``data[m]`` (1/m^2, optional): the stiffness per unit
    area of a data term at unknown vertices (:func:`data_stiffness`), the same for every right-hand side.
    ``adjacency``: the mesh's :func:`usdface.mesh.vertex_adjacency` when the caller has it (for the
    :func:`pockets`)."""

    def __init__(self, points, triangles, known, *, length: float | None, in_pocket=None, data=None,
                 adjacency=None):
        x0 = np.asarray(points, dtype=np.float64)
        tri = np.asarray(triangles)
        self.known = np.asarray(known, dtype=bool)
        self.n = len(x0)
        self.free = np.flatnonzero(~self.known)
        self.kidx = np.flatnonzero(self.known)
        self.mass = vertex_areas(tri, triangle_areas(x0, tri), len(x0)) if len(tri) else np.zeros(self.n)
        if in_pocket is not None:
            in_pocket = np.asarray(in_pocket, dtype=bool) & ~self.known
        elif len(tri):
            in_pocket = pockets(tri, self.known, self.mass, adjacency=adjacency)
        else:
            in_pocket = np.zeros(self.n, dtype=bool)
        self.beyond = ~self.known & ~in_pocket
        # the data term's diagonal at the unknown vertices (mass-weighted: the same energy at any resolution)
        self.data = (np.zeros(self.free.size) if data is None
                     else self.mass[self.free] * np.asarray(data, dtype=np.float64)[self.free])
        self._solve = None
        if self.free.size == 0 or self.kidx.size == 0 and not self.data.any():
            return
        lap = cotangent_laplacian(x0, tri)
        if length:
            # no fade inside the sockets behind the face's holes: their tissue moves with the lips and lids
            lap = (lap + sp.diags(np.where(in_pocket, 0.0, self.mass) / length ** 2)).tocsr()
        a_ff = lap[self.free][:, self.free]
        reg = 1e-12 * float(np.abs(a_ff.diagonal()).mean() or 1.0)
        self._a_fk = lap[self.free][:, self.kidx].tocsr()
        self._solve = spd_lu((a_ff + sp.diags(self.data + reg)).tocsc()).solve

    def extend(self, values) -> np.ndarray:
        """``values[m,c]``: read on the known vertices and, as the data, where the data term is set."""
        vals = np.asarray(values, dtype=np.float64)
        out = np.zeros((self.n, vals.shape[1]))
        known = vals[self.kidx]                         # (gathered once, by index: not a mask per call)
        out[self.kidx] = known
        if self._solve is not None:
            rhs = -(self._a_fk @ known)
            if self.data.any():
                rhs += self.data[:, None] * vals[self.free]
            out[self.free] = self._solve(rhs)
        return out


def data_stiffness(weight, length: float) -> np.ndarray:
    """``[m]`` (1/m^2): the stiffness per unit area of the data term of a field measured with confidence
    ``weight[m]`` in [0,1] (the face weight): ``w / (1 - w) / length^2``, 0 at ``w = 0`` (no measurement) and
    growing without bound as ``w -> 1`` (the measured value, Dirichlet, in the limit), so the extension's
    value at a vertex is continuous in its weight. ``length`` (m): the resolution the field is measured at;
    where ``w = 1/2`` the data hold the field over that length (the screened problem's healing length
    ``length * sqrt((1 - w) / w)``), at any mesh resolution. Infinite (returned as 0: the caller's known set)
    at ``w >= 1``."""
    w = np.clip(np.asarray(weight, dtype=np.float64), 0.0, 1.0)
    soft = (w > 0.0) & (w < 1.0 - 1e-9)
    out = np.zeros(w.shape)
    out[soft] = w[soft] / (1.0 - w[soft]) / length ** 2
    return out


def extend_field(points, triangles, known, values, *, length: float | None, data=None) -> np.ndarray:
    """Screened harmonic extension of ``values[m,c]`` given on ``known[m]`` to every vertex of the mesh.

    Minimises ``x^T (L + Mass / length^2) x + sum_v mass_v data_v |x_v - values_v|^2`` over the unknown
    vertices with ``x = values`` on ``known`` (cotangent Laplacian ``L``, lumped vertex areas, 0 on the
    :func:`pockets`): the known values fill the pockets behind the region's holes (a mouth or eye socket)
    without fading, and fade to 0 over about ``length`` metres elsewhere; ``length=None`` is plain harmonic.
    ``data[m]`` (1/m^2, optional, :func:`data_stiffness`): a data term at the unknown vertices where it is
    positive (values measured there with less than full confidence).
    One sparse factorization for all ``c`` channels (:class:`FieldExtension`). Returns ``[m,c]``.
    """
    return FieldExtension(points, triangles, known, length=length, data=data).extend(values)


def apply_field(generic, phi) -> np.ndarray:
    """``generic[J,m,3] + phi[J,m,3,3] @ generic``: the person's motion from the avatar's generic motion."""
    g = np.asarray(generic, dtype=np.float64)
    return g + np.einsum("jmab,jmb->jma", np.asarray(phi, dtype=np.float64), g)
