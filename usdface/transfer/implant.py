"""The implant (Menzel et al. 2022, sec. 3.3), made to hold when the capture's template rig and the avatar's
generic shapes come from different artists.

The person's shapes ``B_j`` are fitted on the capture with the avatar's own generic shapes, sampled on the
capture mesh (:func:`avatar_shapes_on_capture`, ``G_j = N A_j``), as the prior. What is carried into the
avatar is the person's absolute motion, not a deviation from the capture's template:

* face region (what the capture covers): ``A_j + M (B_j - P_j)`` (:func:`face_personalization`), with
  ``P_j`` the prior the fit shrank towards - where the capture informs a shape, this is the person's motion
  (the coarse part from the capture, the avatar's modelled detail kept); where it does not, ``B_j = P_j`` and
  the avatar keeps its generic shape exactly;
* beyond it, on the same mesh and on every other mesh (teeth, gums, tongue, brows): the person's motion as a
  rotation + scale field of the avatar's generic motion, extended smoothly (:mod:`.motion_field`,
  :func:`extend_personalization`), joined to the face seamlessly (the face-region weight ramps from the
  direct result to the field);
* rigid parts (a mesh whose generic shapes move it rigidly, like the teeth with the jaw) follow the field as
  one body (:func:`follow_field`).

Pure numpy/scipy on arrays in internal metres, the avatar frame: ``points[m,3]``, ``deltas[J,m,3]``.
"""

from __future__ import annotations

import numpy as np

from .motion_field import apply_field, extend_field, motion_weights, rotation_scale, smooth_field

__all__ = ["avatar_shapes_on_capture", "face_personalization", "face_radius", "extend_personalization",
           "seam_ramp",
           "follow_field", "is_rigid_part", "shape_confidence"]


def avatar_shapes_on_capture(registered, avatar_points, avatar_triangles, avatar_deltas, *, poses=None):
    """``G[J,n,3]``: the avatar's generic shapes sampled at the capture vertices (the inverse map N).

    ``registered[n,3]``: the capture template deformed onto the avatar face (avatar frame); each capture
    vertex takes the avatar's motion at its closest avatar surface point, found in the semantic ``poses`` too
    (:class:`usdface.transfer.correspond.PosedSurface`: ``(capture_deltas[n,3], avatar_deltas[m,3])`` pairs).
    Returns ``(G[J,n,3], distance[n])`` in the avatar frame (m).
    """
    from .correspond import PosedSurface

    surf = PosedSurface(avatar_points, avatar_triangles, [p[1] for p in poses or ()])
    tri, bary, _, dist = surf.closest_points(registered, [p[0] for p in poses or ()])
    corners = np.asarray(avatar_triangles)[tri]                                   # [n,3]
    d = np.asarray(avatar_deltas, dtype=np.float64)
    g = np.einsum("nk,jnkc->jnc", bary, d[:, corners])
    return g, dist


def face_personalization(corr, capture_triangles, person_deltas, prior_deltas, rows):
    """``M (B_j - P_j)`` on the avatar vertices ``rows``: the person's change of each shape, interpolated
    from the capture (``person_deltas``/``prior_deltas`` ``[J,n,3]`` in the avatar frame).
    Returns ``[J,len(rows),3]``."""
    diff = np.asarray(person_deltas, dtype=np.float64) - np.asarray(prior_deltas, dtype=np.float64)
    return corr.apply(diff, capture_triangles, rows=rows)


def face_radius(points) -> float:
    """RMS distance of ``points[k,3]`` from their centroid (m): the size of the face region."""
    p = np.asarray(points, dtype=np.float64)
    return float(np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1)))) if len(p) else 0.0


def seam_ramp(points, face_weight, band: float) -> np.ndarray:
    """``[m]`` in [0,1]: ``face_weight`` times a smooth ramp from 0 at the region's edge (the nearest vertex
    of weight < 1) to 1 at ``band`` metres inside it: the join between the face and what lies beyond is that
    wide whatever the mesh resolution."""
    from scipy.spatial import cKDTree

    w = np.clip(np.asarray(face_weight, dtype=np.float64), 0.0, 1.0)
    inner = w >= 1.0 - 1e-9
    if not inner.any() or inner.all() or band <= 0:
        return w
    pts = np.asarray(points, dtype=np.float64)
    d = np.zeros(len(pts))
    d[inner] = cKDTree(pts[~inner]).query(pts[inner])[0]
    t = np.clip(d / band, 0.0, 1.0)
    return w * t * t * (3.0 - 2.0 * t) * inner + w * ~inner * 0.0


def extend_personalization(points, triangles, generic, person, face_weight, *, length: float | None,
                           band: float = 0.0, rings: int = 2):
    """The person's motion on the whole mesh from the face region's.

    ``generic[J,m,3]`` the avatar's shapes, ``person[J,m,3]`` the personalized shapes (meaningful where
    ``face_weight[m] > 0``). The rotation + scale field
    (:func:`usdface.transfer.motion_field.rotation_scale`) is measured where the face weight is 1, averaged
    over ``rings`` edge rings with motion weights, extended by a screened harmonic solve (``length`` m, one
    factorization for every shape) and applied to the generic motion; the result ramps from ``person`` to the
    field over ``band`` metres inside the face region (:func:`seam_ramp`). Returns ``(result[J,m,3],
    field[J,m,3,3])``.
    """
    g = np.asarray(generic, dtype=np.float64)
    p = np.asarray(person, dtype=np.float64)
    w = np.clip(np.asarray(face_weight, dtype=np.float64), 0.0, 1.0)
    known = w >= 1.0 - 1e-9
    n_shapes, m = g.shape[:2]
    phi, valid = rotation_scale(g, p)
    mw = motion_weights(g) * valid * known[None]
    phi = smooth_field(phi * known[None, :, None, None], mw, triangles, rings=rings)
    flat = phi.transpose(1, 0, 2, 3).reshape(m, -1)
    ext = extend_field(points, triangles, known, flat, length=length)
    field = ext.reshape(m, n_shapes, 3, 3).transpose(1, 0, 2, 3)
    outside = apply_field(g, field)
    w = seam_ramp(points, w, band)
    result = w[None, :, None] * p + (1.0 - w)[None, :, None] * outside
    return result, field


def is_rigid_part(points, deltas, *, tolerance: float = 0.1) -> bool:
    """True when every shape moves the mesh ``points[m,3]`` (``deltas[K,m,3]``) as one affine body (residual
    of the best affine motion below ``tolerance`` of the motion, for the shapes that move it): teeth and a
    tongue that follow the jaw, not skin."""
    x = np.column_stack([np.asarray(points, dtype=np.float64), np.ones(len(points))])     # [m,4]
    d = np.asarray(deltas, dtype=np.float64)
    mag = np.linalg.norm(d, axis=-1)
    moving = np.flatnonzero(mag.max(axis=1) > 1e-3 * max(float(mag.max()), 1e-300))
    if moving.size == 0 or len(points) < 4:
        return False
    flat = d[moving].transpose(1, 0, 2).reshape(len(points), -1)                         # [m, k*3]
    coef = np.linalg.lstsq(x, flat, rcond=None)[0]
    res = np.linalg.norm(x @ coef - flat) / max(float(np.linalg.norm(flat)), 1e-300)
    return bool(res < tolerance)


def follow_field(points, deltas, head_points, field, *, rigid: bool):
    """Another mesh's shapes personalized by the head's field: ``deltas[J,k,3]`` on ``points[k,3]`` follow
    ``field[J,m,3,3]`` sampled at the nearest head vertex (``head_points[m,3]``); a ``rigid`` part takes one
    field per shape, the motion-weighted mean over its vertices, so it stays one body."""
    from scipy.spatial import cKDTree

    d = np.asarray(deltas, dtype=np.float64)
    _, nn = cKDTree(np.asarray(head_points, dtype=np.float64)).query(np.asarray(points, dtype=np.float64))
    phi = np.asarray(field)[:, nn]                                                        # [J,k,3,3]
    if rigid:
        w = np.sum(d * d, axis=-1)                                                        # [J,k]
        mean = np.einsum("jk,jkab->jab", w, phi) / np.maximum(w.sum(axis=1), 1e-300)[:, None, None]
        phi = np.broadcast_to(mean[:, None], phi.shape)
    return apply_field(d, phi)


def shape_confidence(personalization, excitation, noise_rms: float, *, moving=None) -> np.ndarray:
    """How far each shape's personalization can be trusted: the positive-part James-Stein factor
    ``c_j = max(0, 1 - var_j / |D_j|^2)`` per shape (Efron & Morris 1973).

    ``personalization[J,n,3]``: ``D_j = B_j - P_j`` (person minus prior, m) on the capture; ``excitation[J]``:
    the training energy of each shape, ``sum_f w_fj^2``; ``noise_rms``: the fit's
    leave-one-frame-out prediction error per vertex (m), so that ``var_j = noise_rms^2 / excitation_j`` is the
    variance of that shape's estimate; ``|D_j|^2`` the mean squared personalization over the vertices the
    shape moves (``moving[J,n]``). A shape the capture barely shows (a jaw slide at weight 0.08) gets
    ``c ~ 0`` and stays the avatar's; a shape shown at full weight keeps its personalization (``c ~ 1``).
    """
    d = np.asarray(personalization, dtype=np.float64)
    sq = np.sum(d * d, axis=-1)                                                           # [J,n]
    if moving is None:
        moving = np.ones(sq.shape, dtype=bool)
    power = np.sum(sq * moving, axis=1) / np.maximum(np.sum(moving, axis=1), 1)
    var = noise_rms ** 2 / np.maximum(np.asarray(excitation, dtype=np.float64), 1e-12)
    return np.clip(1.0 - var / np.maximum(power, 1e-300), 0.0, 1.0)
