"""Seamless partial deformation transfer (Menzel et al. 2022, sec. 3.3, Fig. 3).

Step 1, :func:`face_deformation_transfer`: deformation transfer (Sumner & Popovic 2004) of each personalized
capture shape B_j onto the avatar's face region only, through the correspondence map.
Step 2, :func:`blend_adjacent`: the adjacent region (vertices that move in the approximation A_j but are not
in the face) is deformed from A_j with the face fixed, so that there is no seam; every other vertex keeps A_j.
:func:`implant_shapes` composes the two for the face-transfer modes other than ``person`` (the paper's
``dt`` and the offset modes).

All arrays are internal metres: ``points[m,3]``, ``triangles[t,3]``, shapes ``[J,m,3]``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..mesh import (
    deformation_gradients,
    gradient_operator,
    mean_edge_length,
    spd_lu,
    triangle_areas,
    vertex_areas,
)
from .correspond import Correspondence
from .options import FACE_TRANSFERS
from .surface import cotangent_laplacian

__all__ = ["deformation_gradients", "face_deformation_transfer", "blend_adjacent", "moving_mask",
           "personalization_support", "implant_shapes", "shape_jacobians"]


def personalization_support(person_deltas, template_deltas, *, low: float = 0.01, high: float = 0.03):
    """Where shape j's personalization ``B_j - T_j`` is meaningful: ``[J,n]`` in [0,1], 1 where the person's
    or the generic shape moves more than ``high`` x its largest motion, 0 below ``low`` (smooth ramp).

    Elsewhere neither shape moves and the difference is fit noise (0.1 mm-level on scans); transferring it
    would make every personalized shape move the whole face a little and densify sparse BlendShapes.
    """
    act = np.maximum(np.linalg.norm(np.asarray(person_deltas), axis=-1),
                     np.linalg.norm(np.asarray(template_deltas), axis=-1))  # [J,n]
    rel = act / np.maximum(act.max(axis=1, keepdims=True), 1e-300)
    t = np.clip((rel - low) / (high - low), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def face_deformation_transfer(points, triangles, face, source_triangle, jacobians, anchors, *, base=None,
                              anchor_weight: float = 0.01) -> np.ndarray:
    """Menzel et al. 2022, sec. 3.3, step 1 (with Sumner & Popović 2004, eq. 5): transfer the deformation
    gradients onto the avatar face region.

    Minimises, for every shape j and over the face vertices' displacements ``d``,
    ``sum_t area_t ||G_t d - P_t J_{c(t)}^T - G_t base||^2 + lambda sum_v area_v ||d_v - anchor_v||^2``
    where t runs over avatar triangles whose three vertices are in the face, ``c(t) = source_triangle[t]``
    its capture triangle, ``P_t = G_t x0`` the tangent projector, ``jacobians[J,tc,3,3]`` the displacement
    Jacobians on the capture triangles (``S - I`` for plain deformation transfer,
    :func:`deformation_gradients`; ``S_B - S_T`` to transfer only the personalization onto ``base`` = the
    avatar's generic shapes), and ``anchors[J,m,3]`` the directly mapped displacements that fix the
    translation (``lambda = anchor_weight / mean_edge^2``).
    One sparse factorization serves every shape and coordinate.

    Returns ``d[J,m,3]`` (zero outside the face).
    """
    x0 = np.asarray(points, dtype=np.float64)
    tri = np.asarray(triangles)
    face = np.asarray(face, dtype=bool)
    anchors = np.asarray(anchors, dtype=np.float64)
    n_shapes = anchors.shape[0]
    out = np.zeros_like(anchors)
    fidx = np.flatnonzero(face)
    if fidx.size == 0:
        return out
    ftri = np.flatnonzero(face[tri].all(axis=1) & (np.asarray(source_triangle) >= 0))
    ttri = tri[ftri]
    g_full = gradient_operator(x0, ttri, allow_degenerate=True)  # [3t, m]
    grad = g_full[:, fidx]  # [3t, F]
    area = triangle_areas(x0, ttri)
    w3 = sp.diags(np.repeat(area, 3))
    vmass = vertex_areas(ttri, area, len(x0))[fidx]
    vmass = np.where(vmass > 0, vmass, area.mean() / 3.0 if area.size else 1.0)
    lam = anchor_weight / mean_edge_length(x0, tri) ** 2
    system = (grad.T @ w3 @ grad + sp.diags(lam * vmass)).tocsc()
    solve = spd_lu(system).solve
    proj = (g_full @ x0).reshape(-1, 3, 3)  # P_t (symmetric)
    jac = np.asarray(jacobians)[:, np.asarray(source_triangle)[ftri]]  # [J,t,3,3]
    target = np.einsum("tab,jtcb->jtac", proj, jac)  # P_t J^T -> [J,t,3(grad),3(coord)]
    target = target.reshape(n_shapes, -1, 3)  # [J,3t,3]
    if base is not None:
        target = target + np.stack([g_full @ b for b in np.asarray(base, dtype=np.float64)])
    gw = (w3 @ grad).T.tocsr()  # [F,3t]
    rhs = np.stack([gw @ target[j] for j in range(n_shapes)]) + lam * vmass[None, :, None] * anchors[:, fidx]
    flat = rhs.transpose(1, 0, 2).reshape(len(fidx), -1)  # [F, J*3]
    sol = solve(flat)
    out[:, fidx] = sol.reshape(len(fidx), n_shapes, 3).transpose(1, 0, 2)
    return out


def moving_mask(shapes, tol: float = 1e-9) -> np.ndarray:
    """``[J,m]`` true where ``|shapes[j,v]| > tol`` (metres): the vertices a shape moves."""
    return np.linalg.norm(np.asarray(shapes), axis=-1) > tol


def blend_adjacent(points, triangles, face, face_displacements, approximations, *, tol: float = 1e-9,
                   falloff: float | None = None, band: float = 8.0, face_weight=None):
    """Menzel et al. 2022, sec. 3.3, step 2: seamless completion from the approximations A_j with the face
    fixed.

    For each shape j the adjacent region ``R_j = moves in A_j and not face`` gets ``A_j + h`` where ``h``
    minimises ``h^T L h + h^T Mass h / falloff^2`` on R_j (cotangent Laplacian L, lumped vertex areas), with
    ``h = d_face - A_j`` on the face and 0 on every other vertex: harmonic (``falloff=None``), or screened so
    that the correction decays over ``falloff`` metres and the adjacent region stays as close to A_j as a
    seamless join allows. With a falloff the correction is solved only within ``band * falloff`` of the face
    (it has decayed to ``exp(-band)`` there; farther adjacent vertices keep A_j), which keeps every
    per-shape system small. Vertices outside face and R_j keep exactly A_j. Shapes with the same free set
    share one sparse factorization.

    ``face_weight[m]`` in [0,1] (optional, default 1 on ``face``): vertices of weight 1 are fixed to
    ``d_face``; on the region's rim (0 < w < 1) ``d_face`` is a soft constraint of weight
    ``w / (1 - w) * area / falloff^2`` (infinite at w = 1, zero at w = 0), so that the result changes
    continuously when a vertex's membership does.

    Returns ``(result[J,m,3], adjacent[J,m] bool)``.
    """
    x0 = np.asarray(points, dtype=np.float64)
    tri = np.asarray(triangles)
    face = np.asarray(face, dtype=bool)
    approx = np.asarray(approximations, dtype=np.float64)
    dface = np.asarray(face_displacements, dtype=np.float64)
    alpha = face.astype(np.float64) if face_weight is None else np.clip(face_weight, 0.0, 1.0) * face
    hard = alpha >= 1.0 - 1e-9
    soft = face & ~hard
    adjacent = moving_mask(approx, tol) & ~face[None, :]
    result = approx.copy()
    result[:, hard] = dface[:, hard]
    lap = cotangent_laplacian(x0, tri)
    area = triangle_areas(x0, tri)
    mass = vertex_areas(tri, area, len(x0))
    length = falloff if falloff else mean_edge_length(x0, tri)
    if falloff:
        lap = (lap + sp.diags(mass / falloff ** 2)).tocsr()
    stiff = np.zeros(len(x0))
    stiff[soft] = alpha[soft] / (1.0 - alpha[soft]) * mass[soft] / length ** 2
    solve_set = adjacent | soft[None, :]
    if falloff and face.any():
        from ..mesh import distances_within

        dist = distances_within(x0[face], x0, band * falloff)
        solve_set = solve_set & np.isfinite(dist)[None, :]
    groups: dict[bytes, list[int]] = {}
    for j in range(approx.shape[0]):
        groups.setdefault(np.packbits(solve_set[j]).tobytes(), []).append(j)
    fidx = np.flatnonzero(hard)
    for js in groups.values():
        free = np.flatnonzero(solve_set[js[0]])
        if free.size == 0:
            continue
        l_ff = lap[free][:, free] + sp.diags(stiff[free])
        l_fb = lap[free][:, fidx]
        # (1 where the diagonal is all 0: vertices in no triangle, which keep A_j; as FieldExtension)
        reg = 1e-12 * float(np.abs(l_ff.diagonal()).mean() or 1.0)
        solve = spd_lu(l_ff + reg * sp.eye(free.size)).solve
        h_face = dface[js][:, fidx] - approx[js][:, fidx]  # [g,F,3]
        h_soft = (dface[js][:, free] - approx[js][:, free]) * stiff[free][None, :, None]  # [g,free,3]
        rhs = h_soft - np.stack([l_fb @ h_face[g] for g in range(len(js))])  # [g,free,3]
        flat = rhs.transpose(1, 0, 2).reshape(free.size, -1)
        h = solve(flat)
        h = h.reshape(free.size, len(js), 3).transpose(1, 0, 2)
        result[np.ix_(js, free)] = approx[np.ix_(js, free)] + h
    return result, adjacent


def shape_jacobians(neutral, deltas, triangles):
    """``[J,t,3,3]``: each shape's deformation gradients on ``triangles`` (``neutral[n,3]``,
    ``deltas[J,n,3]``)."""
    return deformation_gradients(neutral, neutral[None] + deltas, triangles)


def implant_shapes(face_neutral, face_triangles, corr: Correspondence, capture_triangles, person_neutral,
                   person_deltas, template_deltas, avatar_deltas, approx, *, face_transfer: str = "offset",
                   anchor_weight: float = 1.0, falloff: float | None = None, support=(0.01, 0.03)):
    """Steps 5 on arrays: the face region from the personalized shapes, seamlessly joined to ``approx``.

    ``person_neutral[n,3]``, ``person_deltas[J,n,3]``, ``template_deltas[J,n,3]``: capture mesh, already in
    the avatar frame (registered). ``avatar_deltas[J,m,3]`` the avatar's generic shapes for the same J names,
    ``approx[J,m,3]`` what the adjacent region is blended from. ``face_transfer``:

    * ``"offset"`` (default, most accurate on the bench): face = avatar's generic shape + M (B_j - T_j), i.e.
      the person's deviation from the generic template, mapped through the correspondence onto the avatar's
      own generic shape (its detail is kept, only the personalization is transferred);
    * ``"dt"``: deformation transfer of B_j (Sumner & Popovic) onto the face, anchored to M B_j (the paper);
    * ``"dt-offset"``: deformation transfer of the gradients' deviation ``S(B_j) - S(T_j)`` onto the generic
      shape.

    ``support=(low, high)``: for the offset modes, the personalization ``B_j - T_j`` is kept only where B_j or
    T_j moves more than ``low..high`` of its peak (:func:`personalization_support`); None keeps it everywhere.

    Returns ``(result[J,m,3], adjacent[J,m])``.
    """
    # only the face rows of M B_j, M T_j are used (the transfer and the blend read d_face on the face only)
    f = np.flatnonzero(corr.face)

    def on_face(values_face):
        full = np.zeros(avatar_deltas.shape[:1] + (len(corr.face), 3))
        full[:, f] = values_face
        return full

    if face_transfer == "dt":
        dface = face_deformation_transfer(face_neutral, face_triangles, corr.face, corr.source_triangle,
                                          shape_jacobians(person_neutral, person_deltas, capture_triangles)
                                          - np.eye(3),
                                          on_face(corr.apply(person_deltas, capture_triangles, rows=f)),
                                          anchor_weight=anchor_weight)
    elif face_transfer in ("offset", "dt-offset"):
        if support is not None:
            # only the personalization inside the shape's support is transferred (personalization_support)
            keep = personalization_support(person_deltas, template_deltas, low=support[0], high=support[1])
            offset_f = corr.apply((person_deltas - template_deltas) * keep[..., None], capture_triangles,
                                  rows=f)
        else:
            offset_f = (corr.apply(person_deltas, capture_triangles, rows=f)
                        - corr.apply(template_deltas, capture_triangles, rows=f))
        offset = np.array(avatar_deltas, dtype=np.float64, copy=True)
        offset[:, f] += offset_f                                             # avatar_deltas + M B_j - M T_j
        if face_transfer == "offset":
            dface = offset
        else:
            jac = (shape_jacobians(person_neutral, person_deltas, capture_triangles)
                   - shape_jacobians(person_neutral, template_deltas, capture_triangles))
            dface = face_deformation_transfer(face_neutral, face_triangles, corr.face, corr.source_triangle,
                                              jac, offset, base=avatar_deltas,
                                              anchor_weight=anchor_weight)
    else:
        raise ValueError(f"face_transfer must be one of {FACE_TRANSFERS}")
    return blend_adjacent(face_neutral, face_triangles, corr.face, dface, approx, falloff=falloff,
                          face_weight=corr.weight)
