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
* in a shape that moves another mesh rigidly (the teeth, gums and tongue with the jaw) that mesh follows the
  field as one body (:func:`rigid_shapes`, :func:`follow_field`).

Pure numpy/scipy on arrays in internal metres, the avatar frame: ``points[m,3]``, ``deltas[J,m,3]``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..memory import Float32Offsets, release_free_memory
from ..mesh import distances_within, index_set, triangle_areas, vertex_adjacency, vertex_areas, vertex_normals
from ..motion import moving_vertices, peak_motion, shape_norms
from ..personalize.fit import james_stein
from .motion_field import (
    FieldExtension,
    apply_field,
    data_stiffness,
    dilate,
    field_noise,
    motion_weights,
    neighbourhood_matrix,
    pockets,
    reliability,
    rotation_scale,
    smooth_field,
)

#: Shapes handled at once in the field extension (bounds the memory to SHAPE_CHUNK x vertices x 9 doubles).
#: One: the smallest working set (244 MB less at the peak of a 225k-vertex head than 4) and no more CPU (the
#: smoothing reads only the columns the one shape moves; the solves cost per right-hand side).
SHAPE_CHUNK = 1
#: The field is known at the capture's resolution (its smoothing length, one placed capture edge): on a mesh
#: that resolves that length with at least PROXY_MIN_RINGS edge rings, the field's extension is solved on
#: a proxy of the mesh decimated to PROXY_RINGS edges per smoothing length (a bench head's own resolution)
#: and interpolated to the fine vertices (:class:`FieldProxy`): its cost stops growing with the resolution.
PROXY_RINGS = 3
PROXY_MIN_RINGS = 4
#: A proxy vertex takes its known value at the nearest of this many fine vertices that faces its way.
PROXY_NEAREST = 8
#: On a proxy, the field is evaluated at the fine vertices beyond the face that a shape moves (or
#: personalizes) by more than this share of its peak motion: elsewhere it would change the offset by at
#: most this share times the field's turn and scale (the person's shape there is the generic one). A bench
#: head's shape moves about half of it by more than 1e-4 of its peak (dev1: 49 % on average).
STILL = 1e-4

__all__ = ["avatar_shapes_on_capture", "face_personalization", "mapping_outliers", "map_reach", "face_radius",
           "extend_personalization",
           "seam_ramp",
           "attached_shapes", "follow_field", "linear_field", "rigid_shapes", "shape_confidence"]


def avatar_shapes_on_capture(registered, avatar_points, avatar_triangles, avatar_deltas, *, poses=None,
                             surface=None):
    """``G[J,n,3]``: the avatar's generic shapes sampled at the capture vertices (the inverse map N).

    ``registered[n,3]``: the capture face (the template's or the person's neutral) deformed onto the avatar
    face (avatar frame); each capture vertex takes the avatar's motion at its closest avatar surface point,
    found in the semantic ``poses`` too (:class:`usdface.transfer.correspond.PosedSurface`:
    ``(capture_deltas[n,3], avatar_deltas[m,3])`` pairs).
    ``surface``: a :class:`usdface.transfer.correspond.PosedSurface` built for the correspondence, used when
    it is this avatar surface in these poses (:meth:`~usdface.transfer.correspond.PosedSurface.serves`):
    its ray-casting scenes are not built twice.
    Returns ``(G[J,n,3], distance[n])`` in the avatar frame (m).
    """
    from .correspond import PosedSurface

    avatar_poses = [p[1] for p in poses or ()]
    surf = (surface if surface is not None and surface.serves(avatar_points, avatar_triangles, avatar_poses)
            else PosedSurface(avatar_points, avatar_triangles, avatar_poses))
    tri, bary, _, dist = surf.closest_points(registered, [p[0] for p in poses or ()])
    corners = np.asarray(avatar_triangles)[tri]                                   # [n,3]
    d = np.asarray(avatar_deltas, dtype=np.float64)
    g = np.einsum("nk,jnkc->jnc", bary, d[:, corners])
    return g, dist


#: A person's motion at a point differs from an artist's generic motion there by less than this angle and
#: this factor in length (a stronger or tilted smile, not a different motion) ...
MAX_ANGLE_DEG = 60.0
MAX_RATIO = 2.0
#: ... judged where either moves more than this fraction of the shape's peak motion.
SIGNIFICANT = 0.1
#: The motion field's measurements fade out between MAX_RATIO and this factor
#: (:func:`extend_personalization`).
FIELD_RATIO_MAX = 2.0 * MAX_RATIO
#: Where a capture vertex is a mapping outlier, the person's change is taken from its neighbours, fading to
#: none (the generic) over this many capture edges: the resolution the capture measures at (the field's
#: average covers one capture edge too). 0 inside (the first version) left holes, and so creases, in a
#: brow's raise; a harmonic fill without fading carried mismapped lid margins into the blinks.
OUTLIER_FILL_EDGES = 1.0


def _same_motion(a, b, na, nb, max_angle_deg: float, max_ratio: float) -> np.ndarray:
    """``[J,n]`` bool: the motions ``a``, ``b`` (``[J,n,3]``, lengths ``na``, ``nb``) are one motion by the
    person model: directions within ``max_angle_deg``, lengths within ``max_ratio`` of each other."""
    cos = np.einsum("jnc,jnc->jn", a, b) / np.maximum(na * nb, 1e-300)
    ratio = np.maximum(na, nb) / np.maximum(np.minimum(na, nb), 1e-300)
    return (cos >= np.cos(np.radians(max_angle_deg))) & (ratio <= max_ratio)


def mapping_outliers(person_deltas, prior_deltas, template_deltas, *, max_angle_deg: float = MAX_ANGLE_DEG,
                     max_ratio: float = MAX_RATIO, significant: float = SIGNIFICANT, triangles=None,
                     rings: int = 1, avatar=None) -> np.ndarray:
    """``[J,n]`` bool: capture vertices where the prior's motion ``P_j`` (the avatar's generic shape sampled
    through the correspondence) is not the motion of the same point of the face, so ``B_j - P_j`` there is
    a mapping error, not the person.

    Three witnesses of each shape at each capture vertex: the person ``B`` (measured), the capture's template
    ``T`` (another artist, on the capture's own mesh: no correspondence involved) and the avatar's ``P``
    (through the correspondence). A vertex is an outlier when ``P`` is incompatible with the person (their
    directions more than ``max_angle_deg`` apart, or lengths more than ``max_ratio`` apart, where either
    moves more than ``significant`` of the peak) *and* is the odd one out: further from both ``B`` and ``T``
    than those two are from each other (and than ``significant`` of the peak). Where the template is the
    prior (``P = T``) nothing is an outlier. On a coarse phone mesh a lid-margin vertex mapped a millimetre
    off lands where the avatar's lid does not move: its 9 mm "personalization" would tear the blink.
    With the capture's ``triangles``, the vertices within ``rings`` edge rings of an outlier are outliers of
    that shape too (the map's errors are spatially coherent, as on the avatar side).
    With ``avatar = (places[n,3], points[m,3], deltas[J,m,3], radius)`` - where the map puts each capture
    vertex on the avatar, the avatar's vertices and generic shapes, and how far the map may be off (one
    capture edge: the resolution the capture measures at) - a vertex is an outlier only where a map error
    that small could have made the difference: the avatar's generic motion somewhere within ``radius`` of
    the vertex's place differs from ``P`` by at least ``|B - P|`` (:func:`map_reach`). Where the avatar's
    motion is the same all around (a brow raise, smooth over centimetres) and the person moves 2.5 times
    as far, no slip of the map gives the person's motion: that is the person, not the map (the three
    witnesses alone called it a mapping error whenever the template too moved further than the avatar).
    All ``[J,n,3]``, one frame (m).
    """
    b = np.asarray(person_deltas, dtype=np.float64)
    p = np.asarray(prior_deltas, dtype=np.float64)
    t = np.asarray(template_deltas, dtype=np.float64)
    nb, npr = shape_norms(b), shape_norms(p)
    peak = np.maximum(nb.max(axis=1, keepdims=True), npr.max(axis=1, keepdims=True))
    incompatible = ((np.maximum(nb, npr) > significant * peak)
                    & ~_same_motion(b, p, nb, npr, max_angle_deg, max_ratio))
    odd = (np.minimum(shape_norms(p - b), shape_norms(p - t))
           > np.maximum(shape_norms(b - t), significant * peak))
    out = incompatible & odd
    if avatar is not None and out.any():
        places, points, deltas, radius = avatar
        j, v = np.nonzero(out)
        out[j, v] = np.linalg.norm(b[j, v] - p[j, v], axis=-1) <= map_reach(places, p, points, deltas, radius,
                                                                             j, v)
    return dilate(out, triangles, rings) if triangles is not None else out


def map_reach(places, prior_deltas, points, deltas, radius: float, shapes, vertices) -> np.ndarray:
    """``[k]``: for each pair ``(shapes[k], vertices[k])``, the largest change from the prior's motion
    ``prior_deltas[j, v]`` that a map error within ``radius`` could make: ``max |A_j(a) - P_j(v)|`` over the
    avatar vertices ``a`` within ``radius`` of the capture vertex's place ``places[v]`` (0 where none is).
    ``points[m,3]`` and ``deltas[J,m,3]`` the avatar's vertices and generic shapes (any array that indexes
    as ``deltas[j, a]``: read only at the vertices near the places asked about)."""
    from scipy.spatial import cKDTree

    shapes, vertices = np.asarray(shapes, dtype=np.intp), np.asarray(vertices, dtype=np.intp)
    out = np.zeros(len(vertices))
    if not len(vertices):
        return out
    near = cKDTree(np.asarray(points, dtype=np.float64)).query_ball_point(
        np.asarray(places, dtype=np.float64)[vertices], radius)
    counts = np.array([len(n) for n in near])
    pair = np.repeat(np.arange(len(vertices)), counts)                # pair -> the (shape, vertex) asked
    a = np.concatenate([np.asarray(n, dtype=np.intp) for n in near])
    if not len(a):
        return out
    moved = np.asarray(deltas[shapes[pair], a], dtype=np.float64)
    change = np.linalg.norm(moved - np.asarray(prior_deltas, dtype=np.float64)[shapes[pair], vertices[pair]],
                            axis=-1)
    has = counts > 0                  # the pairs come grouped by place: one maximum per non-empty group
    out[has] = np.maximum.reduceat(change, np.cumsum(np.r_[0, counts[:-1]])[has])
    return out


def face_personalization(corr, capture_triangles, person_deltas, prior_deltas, rows, *, support=(0.01, 0.03),
                         outliers=None, matrix=None):
    """``M (s_j (B_j - P_j))`` on the avatar vertices ``rows``: the person's change of each shape,
    interpolated from the capture (``person_deltas``/``prior_deltas`` ``[J,n,3]`` in the avatar frame); at
    the capture vertices ``outliers[J,n]`` (:func:`mapping_outliers`), where the difference is a mapping
    error, the shape's other vertices' interpolated and fading to 0 over :data:`OUTLIER_FILL_EDGES` capture
    edges (:func:`usdface.mesh.harmonic_fill`): the person's change there is unknown, not zero (a zero hole in
    a brow's 3 mm raise is a crease), and known only as far as the capture resolves it.

    ``s_j`` (:func:`usdface.transfer.partial_dt.personalization_support`, ``support=(low, high)`` fractions of
    the shape's peak motion; None = everywhere) keeps the change where the person's or the prior shape moves:
    elsewhere neither moves and the difference is fit noise (0.1 mm-level on scans), which would make every
    shape move the whole face a little. ``matrix``: M on ``rows`` (``corr.matrix(capture_triangles, n,
    face_only=False, rows=rows)``) when the caller has it (several batches of shapes). Returns
    ``[J,len(rows),3]``."""
    b = np.asarray(person_deltas, dtype=np.float64)
    p = np.asarray(prior_deltas, dtype=np.float64)
    diff = b - p
    if support is not None:
        from .partial_dt import personalization_support

        diff = diff * personalization_support(b, p, low=support[0], high=support[1])[..., None]
    if outliers is not None and np.any(outliers):
        from ..mesh import harmonic_fill

        diff = harmonic_fill(diff, outliers, capture_triangles, length=OUTLIER_FILL_EDGES)
    return corr.apply(diff, capture_triangles, rows=rows, matrix=matrix)


def face_radius(points) -> float:
    """RMS distance of ``points[k,3]`` from their centroid (m): the size of the face region."""
    p = np.asarray(points, dtype=np.float64)
    return float(np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1)))) if len(p) else 0.0


def seam_ramp(points, face_weight, band: float) -> np.ndarray:
    """``[m]`` in [0,1]: ``face_weight`` times a smooth ramp from 0 at the region's edge (the nearest vertex
    of weight < 1) to 1 at ``band`` metres inside it: the join between the face and what lies beyond is that
    wide whatever the mesh resolution."""
    w = np.clip(np.asarray(face_weight, dtype=np.float64), 0.0, 1.0)
    inner = w >= 1.0 - 1e-9
    if not inner.any() or inner.all() or band <= 0:
        return w
    pts = np.asarray(points, dtype=np.float64)
    d = np.zeros(len(pts))                          # 0 on the rim (weight < 1): the join starts there
    d[inner] = distances_within(pts[~inner], pts[inner], band)   # inf beyond the band
    t = np.clip(d / band, 0.0, 1.0)
    return w * t * t * (3.0 - 2.0 * t)


def _border_shares(neighbourhood, q_rows, q_cols) -> sp.csc_matrix:
    """``neighbourhood[r,c]`` (a 0/1 CSC matrix, sorted indices) with entry ``(i, j)`` weighted ``1 - q_i (1 -
    q_j)`` (float64; the entries of weight 0 dropped): row ``i`` takes column ``j`` by the share of its value
    not measured past the capture's border (``q_rows[r]``, ``q_cols[c]`` in [0, 1]). Rows with ``q_i = 0``
    keep their ones untouched (``1 - 0 (1 - q_j)`` is 1 exactly), so only the few rows past the border are
    formed: the same matrix, to the bit, as weighting every entry of a 16M-entry neighbourhood."""
    out = sp.csc_matrix(neighbourhood, dtype=np.float64, copy=True)
    at = np.flatnonzero(np.asarray(q_rows)[out.indices] > 0.0)          # the entries of rows past the border
    if at.size:
        col = np.searchsorted(out.indptr, at, side="right") - 1
        out.data[at] = 1.0 - q_rows[out.indices[at]] * (1.0 - q_cols[col])
        out.eliminate_zeros()
    return out


def extend_personalization(points, triangles, generic, person, face_weight, *, length: float | None,
                           band: float = 0.0, rings: int = 2, smoothing: float | None = None, keep_at=None,
                           out=None, overwrite: bool = False, shrink: bool = True, peak=None,
                           border_weight=None):
    """The person's motion on the whole mesh from the face region's.

    ``generic[J,m,3]`` the avatar's shapes, ``person[J,m,3]`` the personalized shapes (meaningful where
    ``face_weight[m] > 0``). The rotation + scale field (:func:`usdface.transfer.motion_field.rotation_scale`)
    is measured where the face weight is above 0, averaged with motion weights times the face weight over
    ``rings`` edge rings, or, given ``smoothing`` metres (the resolution the field was measured at), over as
    many as span it, at least one (the same patch of skin whatever the mesh's resolution; ``rings`` is then
    not used), extended by a screened harmonic solve (``length`` m, one factorization for every shape) that
    takes it as known where the weight is 1 and holds it at the rim's vertices of weight ``0 < w < 1`` by a
    data term of stiffness ``w / (1 - w) / smoothing^2`` per unit area
    (:func:`usdface.transfer.motion_field.data_stiffness`: the known value in the limit ``w -> 1``, so the
    field is continuous in the weight), and applied to the generic motion; the result ramps from ``person`` to
    the field over ``band`` metres inside the face region (:func:`seam_ramp`, which still starts at the first
    vertex of weight below 1). With ``shrink`` (default), what is carried beyond the face (not into the
    sockets behind its holes) is the field times its reliability
    (:func:`usdface.transfer.motion_field.reliability`, the shape's noise estimated on the face by
    :func:`usdface.transfer.motion_field.field_noise`), ramped in over the same ``band`` inside the face, so
    the field stays one continuous function and the join absorbs the difference. Returns ``(result[J,m,3],
    field)``: the field (:class:`FieldOnMesh`, ``.rings`` the smoothing used) kept at the vertices nearest to
    ``keep_at[q,3]`` (the other meshes' points; None: every vertex of the moving part), so a production head
    does not hold ``J x m x 9`` values for a few thousand teeth vertices. ``out``: a float64 ``[J,m,3]`` array
    to hold the result, which may be ``person`` itself (each chunk of shapes is read before it is written):
    one ``[J,m,3]`` array fewer; ``overwrite``: the result written over ``person`` (the same). ``peak[m]``:
    :func:`usdface.motion.peak_motion` of ``generic`` when the caller has it.

    ``border_weight[m]`` in [0,1) (optional; :func:`usdface.transfer.correspond.border_reach`): the vertices
    just past the capture's border whose ``person`` offsets hold the capture's value at the border, and how
    well that value measures them (``r``). Beyond the face and in the sockets behind its holes the field is
    measured there too, with the confidence ``max(w, r)`` (``w`` the face weight); the share of it from past
    the border, ``q = (r - w) / (1 - w)`` where ``r > w``, is averaged with the face's values at ``1 - q``
    only (in full they would make the rim's one-sided average again) and shrunk by its reliability for its
    share ``1 - q`` only (a value the capture measures there is not extrapolated; the sockets are not
    shrunk); all continuous in ``w`` and ``r``. The result there stays the field's (the face region and its
    join are the face weight's). A raise that keeps growing towards the capture's border is then carried
    beyond from what the capture measured there, not from the last avatar vertex inside it, up to one avatar
    edge further in; a lip's margin just past the mouth hole, where the generic motion is largest, takes
    the capture's value there, not the lips' ratio to the generic from around it.

    On a mesh that resolves ``smoothing`` with :data:`PROXY_MIN_RINGS` or more edge rings, the extension is
    solved on a proxy of the mesh decimated to a third of it (:class:`FieldProxy`: the cost of the solve and
    of the smoothing no longer grows with the resolution) and interpolated to the fine vertices, which solve
    it themselves next to the face; the field is then kept at the proxy's vertices. Beyond the face it is
    interpolated and applied only where the shape (or the person's shape) moves by more than :data:`STILL`
    of its peak; elsewhere the result is the person's offset as given.

    Memory (a production head's peak is here): ``generic`` may be a :class:`usdface.memory.Float32Offsets`
    (read shape by shape, half the bytes) and ``person`` a callable that returns the array, called once the
    extension is factorized (the factorization's working memory and the ``[J,m,3]`` array are never
    resident together).
    """
    g = generic if isinstance(generic, Float32Offsets) else np.asarray(generic, dtype=np.float64)
    w0 = np.clip(np.asarray(face_weight, dtype=np.float64), 0.0, 1.0)
    n_shapes, m = g.shape[:2]
    # work on the part of the mesh that moves (a merged head + body mesh: the head): elsewhere the generic
    # motion is float noise at most, and the result keeps it as authored whatever the field
    if peak is None:
        peak = peak_motion(g) if isinstance(g, np.ndarray) else g.peak_motion()
    domain = np.flatnonzero(moving_vertices(peak, points) | (w0 > 0))
    peak = peak[domain]
    local = np.full(m, -1)
    local[domain] = np.arange(domain.size)
    tri = np.asarray(triangles)
    sub_tri = local[tri[(local[tri] >= 0).all(axis=1)]]
    x = np.asarray(points, dtype=np.float64)[domain]
    s = w0[domain]                                   # the face weight: the measured field's confidence
    known = s >= 1.0 - 1e-9
    w = seam_ramp(points, w0, band)[domain]
    data = None
    # the mesh's vertex adjacency, made once for the sockets' pockets and the smoothing's neighbourhoods
    adjacency = vertex_adjacency(sub_tri, domain.size) if len(sub_tri) else None
    # the share of each vertex's measurement that comes from past the capture's border (beyond the face, and
    # in the sockets behind its holes: a lip's margin just past the mouth hole, where the generic motion is
    # largest, took the lips' ratio from around it - generated generic:15's mouthRollLower 2.4x the truth's
    # there, +0.342 mm over generic): qb = (r - w) / (1 - w) where the border's confidence r exceeds the
    # face weight w, so the confidence max(w, r) = w + qb (1 - w) and everything below is continuous in both
    qb = np.zeros(domain.size)
    if border_weight is not None and len(sub_tri) and known.any():
        r = np.clip(np.asarray(border_weight, dtype=np.float64)[domain], 0.0, 1.0 - 1e-6)
        over = (r > s) & ~known
        qb[over] = (r[over] - s[over]) / (1.0 - s[over])
        s = np.where(over, r, s)
    past = qb > 0.0
    if len(sub_tri):
        from ..mesh import mean_edge_length

        edge = mean_edge_length(x, sub_tri)
        if smoothing:
            # the rings that span the capture's resolution, at least the one ring: a floor of ``rings`` (2)
            # averaged a mesh about as coarse as the capture over two capture edges, and at the face's rim,
            # where the average is one-sided, pulled the field carried beyond in from twice as deep inside
            rings = max(1, int(round(smoothing / edge)))
        # the rim's vertices of weight in (0,1) hold their measured field with a stiffness that grows without
        # bound as the weight -> 1 (the known set's Dirichlet value in the limit): continuous in the weight
        soft = (s > 0.0) & ~known
        if soft.any():
            data = data_stiffness(s, smoothing or rings * edge)
    else:
        soft = np.zeros(domain.size, dtype=bool)
    proxy = (_field_proxy(x, sub_tri, known, w, smoothing)
             if smoothing and rings >= PROXY_MIN_RINGS and known.any() and not known.all() else None)
    if proxy is None:
        ext = FieldExtension(x, sub_tri, known, length=length, data=data, adjacency=adjacency)
        beyond, mass = ext.beyond, ext.mass
    else:
        # the sockets behind the face's holes as the whole fine mesh has them (the proxy covers only the
        # face's rim and what lies beyond)
        fine_mass = vertex_areas(sub_tri, triangle_areas(x, sub_tri), domain.size)
        in_pocket = pockets(sub_tri, known, fine_mass, adjacency=adjacency)
        del fine_mass
        beyond = ~known & ~in_pocket
        ext = FieldExtension(proxy.points, proxy.triangles, proxy.known, length=length,
                             in_pocket=~(known | beyond)[proxy.fine],
                             data=None if data is None else data[proxy.fine])
        proxy.near_face(x, sub_tri, known, known | beyond, length, data=data)
    release_free_memory()                            # the factorization's working memory
    if keep_at is None:
        kept = np.arange(domain.size if proxy is None else len(proxy.points))
    else:
        from scipy.spatial import cKDTree

        q = np.asarray(keep_at, dtype=np.float64).reshape(-1, 3)
        on = x if proxy is None else proxy.points
        kept = index_set(cKDTree(on).query(q)[1], len(on)) if len(q) else np.zeros(0, dtype=np.int64)
    field = np.zeros((n_shapes, kept.size, 3, 3), dtype=np.float32)
    if overwrite:
        result = None                                # the person's array, formed below
    elif out is None:
        result = np.zeros(g.shape)
    else:
        if out.shape != g.shape or out.dtype != np.float64:
            raise ValueError(f"out must be float64 {g.shape}, not {out.dtype} {out.shape}")
        result = out
    # how much of the reliability shrink applies: 1 beyond the face, ramping to 0 over the band inside it
    # (and 0 around the sockets: their values are surrounded by the capture and not extrapolated)
    toward = 1.0 - seam_ramp(x, (~beyond).astype(np.float64), band) if shrink else np.zeros(domain.size)
    # past the border, the share of the value the capture measures there is not extrapolated: shrunk for
    # the rest
    toward[past] = np.minimum(toward[past], 1.0 - qb[past])
    # the measured field is used only where the extension reads it (known vertices next to unknown ones),
    # where the result blends it in (the join) and where other meshes follow it: smoothed only there
    if proxy is None:
        touches_free = np.zeros(domain.size, dtype=bool)      # shares a triangle (so an edge) with a free one
        touches_free[sub_tri[(~known)[sub_tri].any(axis=1)].ravel()] = True
        is_kept = np.zeros(domain.size, dtype=bool)
        is_kept[kept] = True
        rows = np.flatnonzero(known & ((w < 1.0) | touches_free | is_kept) | soft)
    else:
        # on the proxy: its known vertices the extension reads, that the join interpolates from and that
        # other meshes follow; each smoothed at its fine vertex, exactly as on the fine mesh
        rows_c = proxy.rows(kept)
        rows = index_set(np.concatenate([proxy.fine[rows_c], proxy.strip_known, proxy.direct,
                                         proxy.strip_soft]), domain.size)
        at_row = np.searchsorted(rows, proxy.fine[rows_c])
        mass = np.zeros(domain.size)
        np.add.at(mass, rows[at_row], ext.mass[rows_c])           # the proxy's area each row stands for
    # the smoothing on the vertices it reads only (the columns of its rows' neighbourhoods), in their order:
    # the same sums as on the whole mesh
    smoother = neighbourhood_matrix(sub_tri, domain.size, rings, rows, adjacency=adjacency).tocsc()
    if past.any():
        # a value measured past the border is averaged with the others measured there: with the face's (up to
        # one avatar edge further in, on one side) it would be the rim's one-sided average again. Row i
        # takes column j at 1 - q_i (1 - q_j): the face's values by the share not measured past the border
        smoother = _border_shares(smoother, qb[rows], qb)
    del adjacency
    reach = np.flatnonzero(np.diff(smoother.indptr) > 0)
    smoother = smoother[:, reach]                               # [rows, reach], column slices per chunk
    s_r = s[reach]                                              # > 0: measured (1 on the known set)
    sel = np.flatnonzero(toward[rows] > 0)                      # the rows whose field is shrunk
    shrunk = rows[sel]
    # (float64 once: a boolean matrix is converted at every product)
    patch = sp.csr_matrix(smoother)[sel].astype(np.float64) if shrunk.size else None
    patch_size = np.asarray(patch.sum(axis=1)).ravel() if shrunk.size else None
    shrunk_r = np.searchsorted(reach, shrunk)
    if proxy is not None:
        # the offsets are read only where they are used (the smoothing's columns, the vertices that read the
        # field, those the field is kept at), and each shape's largest motion over the moving part (the
        # motion weights' scale) from them and the vertices whose peak over the shapes could exceed it
        # ``need`` first: the join reads its rows as the leading slice of each shape's offsets (no gather)
        others = np.ones(domain.size, dtype=bool)
        others[proxy.need] = False
        besides = index_set(np.concatenate([reach, proxy.fine[kept]]), domain.size)
        used = np.concatenate([proxy.need, besides[others[besides]]])
        del besides
        position = np.full(domain.size, -1)
        position[used] = np.arange(used.size)
        at_reach, at_kept = position[reach], position[proxy.fine[kept]]
        del position
        others[used] = False
        others = np.flatnonzero(others)
        used_m, peak_others = domain[used], peak[others]
        n_need = proxy.need.size
        need_m = domain[proxy.need]                         # the join's rows, and their face weight ramp
        wn = w[proxy.need][None, :, None]
        wn_c = 1.0 - wn
        strip_k, direct_r = np.searchsorted(rows, proxy.strip_known), np.searchsorted(rows, proxy.direct)
        at_strip = proxy.need_position[proxy.strip]
        at_strip_out = proxy.need_position[proxy.strip_out] if proxy.strip.size else None
        at_direct = proxy.need_position[proxy.direct]
        soft_r = np.searchsorted(rows, proxy.strip_soft)
        # the join's rows the fine mesh answers itself (the strip, the strip's neighbours it reads, the
        # direct rows) and those in the face's ramp: the field is evaluated there in every shape
        always = index_set(np.concatenate([at_strip, at_strip_out if at_strip_out is not None
                                           else np.zeros(0, dtype=np.int64), at_direct,
                                           np.flatnonzero(w[proxy.need] > 0.0)]), n_need)
    del peak
    release_free_memory()                            # its construction's products
    # the person's array last: the factorization's and the smoother's working memory are gone by then
    p = np.asarray(person() if callable(person) else person, dtype=np.float64)
    if overwrite:
        result = out = p
    # where the face weight is 1 the result is the person's offset (1 pd + 0 outside): written over the
    # person's array, only the join and beyond are formed
    join = np.flatnonzero(w < 1.0) if result is p else None
    if join is not None:
        join_m, w_join = domain[join], w[join][None, :, None]
    skin = np.zeros((n_shapes, kept.size, 3), dtype=np.float32)   # the generic motion where the field is kept
    # the chunk's freed arrays are not handed back to the OS after each shape (trimming them and faulting
    # them back in cost 2.5-4 s of system time on a 225k-vertex head, for the same peak RSS)
    for lo in range(0, n_shapes, SHAPE_CHUNK):                    # bounded memory: a few shapes at a time
        js = slice(lo, min(lo + SHAPE_CHUNK, n_shapes))
        if proxy is None:
            gd, pd = g[js][:, domain], p[js][:, domain]
            gr, pr = gd[:, reach], pd[:, reach]
            mw = motion_weights(gd)[:, reach]
        else:                                                     # gd, pd: at the ``used`` vertices only
            gd, pd = _offsets_at(g, js, used_m), p[js][:, used_m]
            gr, pr = gd[:, at_reach], pd[:, at_reach]
            mag = shape_norms(gd)                                 # (read once: the weights' too)
            top = mag.max(axis=1)                                 # [k] a lower bound of each shape's peak
            cand = others[peak_others >= top.min() * (1.0 - 1e-9)]
            if cand.size:
                top = np.maximum(top, shape_norms(_offsets_at(g, js, domain[cand])).max(axis=1))
            mw = motion_weights(gr, peak=top, norms=mag[:, at_reach])
            # the join's rows the shape moves (or personalizes) by more than STILL of its peak: elsewhere the
            # field would change its offset by at most that share times the field's turn and scale
            floor = STILL * top[:, None]
            moves = (mag[:, :n_need] > floor) | (shape_norms(pd[:, :n_need] - gd[:, :n_need]) > floor)
            act = index_set(np.concatenate([np.flatnonzero(moves.any(axis=0)), always]), n_need)
            del mag, moves
        k = gd.shape[0]
        phi = np.zeros((k, reach.size, 3, 3))
        valid = np.zeros((k, reach.size))
        jj, vv = np.nonzero((mw > 0) & (s_r > 0)[None])   # measured where the person's shape is and moves
        # the person model of :func:`mapping_outliers`: a personalized motion up to MAX_RATIO times longer
        # or shorter than the generic is the person's (dev3's mouthFunnel moves the lips 0.49x the generic),
        # one FIELD_RATIO_MAX times is a mapping error the capture-side test did not catch (its neighbours'
        # field fills in); between, the measurement's weight falls smoothly (a hard cut at MAX_RATIO made
        # neighbours at 0.5005x and 0.4992x all and nothing: a 3.6 mm crease in a trusted mouthFunnel)
        phi[jj, vv], valid[jj, vv] = rotation_scale(gr[jj, vv], pr[jj, vv], max_scale=FIELD_RATIO_MAX,
                                                    full_scale=MAX_RATIO)
        mw = mw * valid * s_r[None]                     # the rim's measurements count as much as they are
        phi = smooth_field(phi, mw, sub_tri, neighbourhood=smoother)          # [k, rows, 3, 3]
        if shrunk.size:
            # the generic motion and the personalization averaged over the patch each value of the field was
            # averaged on (the capture's resolution), where the field was measured; the noise of that
            # average, estimated on the values that are carried beyond the face
            measured = (mw > 0) * s_r[None]                      # (1 on the known set)
            measured = measured[..., None]
            # both averages by one product (the same sums: each output column is summed on its own)
            both = np.concatenate([gr * measured, (pr - gr) * measured], axis=-1)       # [k, reach, 6]
            both = (patch @ both.transpose(1, 0, 2).reshape(reach.size, k * 6)).reshape(shrunk.size, k, 6)
            a_bar, d_bar = (np.ascontiguousarray(both[..., c].transpose(1, 0, 2)) / patch_size[:, None]
                            for c in (slice(0, 3), slice(3, 6)))
            del both
            noise2, spread2 = field_noise(a_bar, d_bar, measured[:, shrunk_r, 0] > 0,
                                          mass[shrunk] * s[shrunk])
            motion2 = np.einsum("jvc,jvc->jv", a_bar, a_bar)
            keep = 1.0 - toward[shrunk] * (1.0 - reliability(motion2, noise2, spread2))
            phi[:, sel] *= keep[..., None, None]
        del gr, pr, mw, valid
        if proxy is None:
            flat = np.zeros((domain.size, k * 9))
            flat[rows] = phi.transpose(1, 0, 2, 3).reshape(rows.size, -1)
            f = ext.extend(flat).reshape(domain.size, k, 3, 3).transpose(1, 0, 2, 3)
            del flat
            field[js] = f[:, kept]
            skin[js] = gd[:, kept]
            if join is None:
                outside = apply_field(gd, f)
                result[js, domain] = w[None, :, None] * pd + (1.0 - w)[None, :, None] * outside
            else:
                outside = apply_field(gd[:, join], f[:, join])
                result[js, join_m] = w_join * pd[:, join] + (1.0 - w_join) * outside
        else:
            flat = np.zeros((len(proxy.points), k * 9))
            flat[rows_c] = phi[:, at_row].transpose(1, 0, 2, 3).reshape(rows_c.size, -1)
            fc = ext.extend(flat)                                 # [p, k*9] on the proxy
            del flat
            field[js] = fc[kept].reshape(kept.size, k, 3, 3).transpose(1, 0, 2, 3)
            skin[js] = gd[:, at_kept]
            at = np.full(n_need, -1)
            at[act] = np.arange(act.size)
            f = proxy.prolong[act] @ fc                           # [act, k*9]
            if proxy.strip.size:                                  # next to the face: the fine solve
                vk = phi[:, strip_k].transpose(1, 0, 2, 3).reshape(strip_k.size, -1)
                rhs = -(proxy.a_sk @ vk + proxy.a_so @ f[at[at_strip_out]])
                if soft_r.size:                                   # the rim's data term
                    rhs[proxy.strip_soft_at] += proxy.strip_data[:, None] * phi[:, soft_r].transpose(
                        1, 0, 2, 3).reshape(soft_r.size, -1)
                f[at[at_strip]] = proxy.strip_solve(rhs)
            if proxy.direct.size:                                 # the join's rim: its own field
                f[at[at_direct]] = phi[:, direct_r].transpose(1, 0, 2, 3).reshape(direct_r.size, -1)
            f = f.reshape(act.size, k, 3, 3).transpose(1, 0, 2, 3)
            outside = apply_field(gd[:, act], f)
            if result is not p:                                   # the person's shapes, then the join's
                result[js, domain] = p[js][:, domain]
            result[js, need_m[act]] = wn[:, act] * pd[:, act] + wn_c[:, act] * outside
            del fc
        del gd, pd, f, outside, phi
    # elsewhere (the generic motion below the float noise floor: :func:`moving_vertices`) the generic
    # offsets as authored: a subdivided head's back carried µm of export noise that the result set to 0,
    # so shapes kept generic came out changed and the count of personalized shapes grew with the resolution
    rest = np.ones(m, dtype=bool)
    rest[domain] = False
    rest = np.flatnonzero(rest)
    if rest.size:
        for k in range(n_shapes):                                 # shape by shape: no [J,rest,3] copy
            result[k, rest] = _offsets_at(g, slice(k, k + 1), rest)[0]
    points_kept = x[kept] if proxy is None else proxy.points[kept]
    return result, FieldOnMesh(points_kept, field, rings, generic=skin)


def _offsets_at(offsets, shapes, vertices) -> np.ndarray:
    """Float64 ``offsets[shapes][:, vertices]`` (``offsets``: an array or a :class:`Float32Offsets`, expanded
    at those vertices only)."""
    if isinstance(offsets, Float32Offsets):
        return offsets.take(shapes, vertices)
    return offsets[shapes][:, vertices]


class FieldProxy:
    """A coarser mesh of the moving part the field is extended on (:func:`_field_proxy`): ``points[p,3]``
    (m), ``triangles[s,3]``; ``fine[p]`` (indices into the fine vertices) the nearest fine vertex facing
    the same way as each of its vertices (where its known value is measured), ``known[p]`` theirs;
    ``need[q]`` the fine vertices whose result reads the field (the face weight ramp below 1) and
    ``prolong[q,p]`` (CSR) the barycentric interpolation to them; ``normals[n,3]`` the fine mesh's vertex
    normals (computed once, for both sides' facing tests). :meth:`near_face` adds where the fine
    mesh answers itself: ``direct[a]``, ``strip[b]`` (fine vertex indices), ``strip_known``/``strip_out``
    (their fine neighbours), the strip's blocks ``a_sk[b, .]``, ``a_so[b, .]`` and its factorized
    ``strip_solve``, and ``need_position[n]`` (a fine vertex's row in ``need``, -1 if none)."""

    def __init__(self, points, triangles, fine, known, need, prolong, normals):
        self.points, self.triangles = points, triangles
        self.fine, self.known = fine, known
        self.need, self.prolong = need, prolong
        self.normals = normals

    def near_face(self, x, triangles, known, fading, length, data=None):
        """Where the proxy's interpolation would mix the face's measured field with the extension's, or
        reads a proxy triangle facing away from the vertex (the other lip), the fine mesh answers itself:

        * ``direct``: the known vertices that read the field (the join) whose proxy triangle has an unknown
          corner or faces away: their own smoothed field, as on the fine mesh;
        * ``strip``: the unknown vertices within one proxy edge of the known ones, or whose proxy triangle
          has a known corner or faces away (the lips' and lids' margins, where the field varies at the
          mesh's own resolution): solved on the fine mesh (the same screened system,
          :class:`usdface.transfer.motion_field.FieldExtension`) from the fine known values next to them
          (``strip_known``) and the proxy's interpolated field around them (``strip_out``).

        ``fading[n]``: the vertices whose screening applies (not the sockets' pockets); ``data[n]`` (1/m^2,
        optional): the data term's stiffness (:func:`usdface.transfer.motion_field.data_stiffness`), held
        on the proxy's vertices as on their fine ones (``soft``) and in the strip (``strip_soft``, the fine
        vertices where it is set, at ``strip_soft_at`` in the strip, with ``strip_data`` its mass-weighted
        diagonal)."""
        from ..mesh import spd_lu, triangle_normals
        from .surface import cotangent_laplacian

        corners = self.prolong.indices.reshape(-1, 3)            # each row: its proxy triangle, in order
        facing = np.einsum("qc,qc->q", self.normals[self.need],
                           triangle_normals(self.points, corners, unit=False)) > 0
        known_corner = self.known[corners]
        known_need = known[self.need]
        self.direct = self.need[known_need & (~known_corner.all(axis=1) | ~facing)]
        free = np.flatnonzero(~known)
        edge = float(np.sqrt(np.mean(np.sum((self.points[self.triangles[:, 0]]
                                             - self.points[self.triangles[:, 1]]) ** 2, axis=1))))
        d = distances_within(x[known], x[free], edge)
        self.strip = np.union1d(free[d < edge],
                                self.need[~known_need & (known_corner.any(axis=1) | ~facing)])
        self.need_position = np.full(len(x), -1)
        self.need_position[self.need] = np.arange(self.need.size)
        self.soft = (np.zeros(len(self.points), dtype=bool) if data is None else data[self.fine] > 0)
        self.strip_soft = self.strip_soft_at = np.zeros(0, dtype=np.int64)
        self.strip_data = np.zeros(0)
        if not self.strip.size:
            self.strip_known = np.zeros(0, dtype=np.int64)
            return
        in_strip = np.zeros(len(x), dtype=bool)
        in_strip[self.strip] = True
        tri = triangles[in_strip[triangles].any(axis=1)]              # the rows of the strip need only these
        lap = cotangent_laplacian(x, tri)
        mass = vertex_areas(tri, triangle_areas(x, tri), len(x))
        if length:
            lap = (lap + sp.diags(np.where(fading, mass, 0.0) / length ** 2)).tocsr()
        rows = lap[self.strip]
        around = np.flatnonzero(np.diff(rows.tocsc().indptr) > 0)
        self.strip_known = around[known[around]]
        self.strip_out = around[~known[around] & ~in_strip[around]]
        self.a_sk, self.a_so = rows[:, self.strip_known].tocsr(), rows[:, self.strip_out].tocsr()
        a_ss = rows[:, self.strip]
        reg = 1e-12 * float(np.abs(a_ss.diagonal()).mean() or 1.0)   # as FieldExtension: a closed pocket
        diag = np.zeros(self.strip.size) if data is None else mass[self.strip] * data[self.strip]
        self.strip_soft_at = np.flatnonzero(diag > 0)
        self.strip_soft, self.strip_data = self.strip[self.strip_soft_at], diag[self.strip_soft_at]
        self.strip_solve = spd_lu((a_ss + sp.diags(diag + reg)).tocsc()).solve

    def rows(self, kept) -> np.ndarray:
        """The proxy's known vertices whose field is read: next to an unknown one (the extension's boundary
        values), in the interpolation of a fine vertex that reads the field, or kept for other meshes."""
        used = np.zeros(len(self.points), dtype=bool)
        used[self.triangles[(~self.known)[self.triangles].any(axis=1)].ravel()] = True
        used[self.prolong.indices] = True
        used[kept] = True
        return np.flatnonzero(self.known & used | self.soft)


def _field_proxy(x, triangles, known, w, smoothing) -> FieldProxy | None:
    """The field's mesh when the avatar's is finer than the field's resolution: decimated to an edge of
    ``smoothing / PROXY_RINGS`` (:func:`usdface.transfer.surface.decimate`); None when that is not
    coarser than ``x[n,3]`` / ``triangles``. ``known[n]``, ``w[n]``: the fine known vertices and the face
    weight ramp (:func:`seam_ramp`)."""
    from scipy.spatial import cKDTree

    from .surface import decimate, prolongation

    edge = smoothing / PROXY_RINGS
    need = np.flatnonzero(w < 1.0)
    # the proxy covers what reads the field and two of its edges around it (the face's inside keeps its own
    # values: the result there is the person's shape)
    region = np.ones(len(x), dtype=bool)
    if need.size < len(x):
        inside = w >= 1.0
        region[inside] = distances_within(x[need], x[inside], 2.0 * edge) < 2.0 * edge
    tri = np.asarray(triangles)
    tri = tri[region[tri].all(axis=1)]
    local = np.cumsum(region) - 1
    xc, tc = decimate(x[region], local[tri], edge)
    if len(tc) == 0 or len(xc) >= region.sum():
        return None
    # each proxy vertex's fine vertex: the nearest on the same side of the surface (where two sheets touch,
    # as closed lips, the nearest may be on the other one)
    k = min(PROXY_NEAREST, len(x))
    near = cKDTree(x).query(xc, k=k)[1].reshape(len(xc), k)                           # [p, k]
    normals = vertex_normals(x, triangles)
    agree = np.einsum("pc,pkc->pk", vertex_normals(xc, tc), normals[near]) > 0
    fine = near[np.arange(len(xc)), np.where(agree.any(axis=1), np.argmax(agree, axis=1), 0)]
    return FieldProxy(xc, tc, fine, known[fine], need, prolongation(xc, tc, x[need]), normals)


class FieldOnMesh:
    """The person's field ``phi[J,d,3,3]`` (float32) at the vertices ``points[d,3]`` where it was computed;
    ``rings`` the edge rings it was averaged over; ``generic[J,d,3]`` (float32, optional) the mesh's generic
    motion there, the skin the field describes (:func:`follow_field` asks whether another mesh moves with it).
    """

    def __init__(self, points, phi, rings: int = 0, generic=None):
        self.points = points
        self.phi = phi
        self.rings = rings
        self.generic = generic

    def nearest(self, queries) -> np.ndarray:
        """``[q]``: the field vertex nearest to each query point ``[q,3]``."""
        from scipy.spatial import cKDTree

        return cKDTree(self.points).query(np.asarray(queries, dtype=np.float64))[1]


def rigid_shapes(points, deltas, *, tolerance: float = 0.1) -> np.ndarray:
    """``[K]`` bool: the shapes that move the mesh ``points[m,3]`` (``deltas[K,m,3]``) as one affine body:
    the residual of the best affine motion of the vertices the shape moves (more than 1e-3 of its peak) is
    below ``tolerance`` of their motion (the lower teeth, gums and tongue under the jaw shapes; not the
    tongue's own shapes)."""
    x = np.column_stack([np.asarray(points, dtype=np.float64), np.ones(len(points))])     # [m,4]
    d = np.asarray(deltas, dtype=np.float64)
    mag = shape_norms(d)                                                                 # [K,m]
    out = np.zeros(len(d), dtype=bool)
    for j in np.flatnonzero(mag.max(axis=1) > 0):                # one small least squares per shape
        moving = mag[j] > 1e-3 * mag[j].max()
        if moving.sum() < 4:
            continue
        coef = np.linalg.lstsq(x[moving], d[j, moving], rcond=None)[0]
        res = np.linalg.norm(x[moving] @ coef - d[j, moving]) / np.linalg.norm(d[j, moving])
        out[j] = res < tolerance
    return out


def attached_shapes(deltas, skin, *, max_angle_deg: float = MAX_ANGLE_DEG, max_ratio: float = MAX_RATIO,
                    significant: float = SIGNIFICANT) -> np.ndarray:
    """``[J]`` bool: the shapes in which another mesh moves with the head skin nearest to it, so the person's
    field of that skin applies to it. ``deltas[J,k,3]``: the mesh's generic motion; ``skin[J,k,3]``: the
    head's generic motion at the nearest head vertex of each of its vertices (m). A vertex moves with the skin
    when the two motions agree as a person's motion agrees with an artist's (:func:`mapping_outliers`' person
    model: within ``max_angle_deg`` and ``max_ratio``); a shape is attached when at least half of its motion
    (squared length, over the vertices moving more than ``significant`` of its peak) does. The lower teeth
    under the jaw shapes are attached to the chin and lips; the tongue in ``tongueOut`` (centimetres past lips
    that barely move) is not, and keeps its generic shape rather than the lips' rotation."""
    d = np.asarray(deltas, dtype=np.float64)
    h = np.asarray(skin, dtype=np.float64)
    nd, nh = shape_norms(d), shape_norms(h)
    agree = _same_motion(d, h, nd, nh, max_angle_deg, max_ratio)
    w = nd * nd * (nd > significant * nd.max(axis=1, keepdims=True))
    return np.sum(w * agree, axis=1) >= 0.5 * np.maximum(np.sum(w, axis=1), 1e-300)


def follow_field(points, deltas, field, *, rigid=False):
    """Another mesh's shapes personalized by the head's field: ``deltas[J,k,3]`` on ``points[k,3]`` (m)
    follow the field (:class:`FieldOnMesh`) read at each vertex's nearest head vertex, as a smooth function
    of position. In a shape that moves the mesh as one body (``rigid``: bool, or ``[J]`` bool from
    :func:`rigid_shapes`) it takes one field, the motion-weighted mean over its vertices, so the jaw's teeth
    and tongue stay one body; in any other shape, the motion-weighted linear function of position closest
    to those readings (:func:`linear_field`). Read vertex by vertex, the field jumped where the nearest head
    vertex changed (the upper lip's field beside the lower lip's): the mesh tore there (stop 42,
    ``benchmarks/bench_artifacts.py``: non-affine steps of 0.6-3.9 mm on the generated Mouth, where the truth
    has 0.05-0.30). With the head's generic motion in the field (``field.generic``), a shape in which the
    mesh does not move with that skin (:func:`attached_shapes`) keeps its generic motion."""
    d = np.asarray(deltas, dtype=np.float64)
    moving = np.flatnonzero(peak_motion(d) > 0)
    out = d.copy()
    if moving.size == 0:
        return out
    x = np.asarray(points, dtype=np.float64)[moving]
    nn = field.nearest(x)
    phi = field.phi[:, nn].astype(np.float64)                                         # [J,k,3,3]
    dm = d[:, moving]
    if field.generic is not None:
        phi[~attached_shapes(dm, field.generic[:, nn])] = 0.0
    w = np.sum(dm * dm, axis=-1)                                                      # [J,k]
    one = np.broadcast_to(np.asarray(rigid, dtype=bool), (len(d),))
    if one.any():
        wo = w[one]
        mean = np.einsum("jk,jkab->jab", wo, phi[one]) / np.maximum(wo.sum(axis=1), 1e-300)[:, None, None]
        phi[one] = mean[:, None]
    rest = ~one & (w.max(axis=1) > 0)
    if rest.any():
        phi[rest] = linear_field(x, phi[rest], w[rest])
    out[:, moving] = apply_field(dm, phi)
    return out


def linear_field(points, phi, weights) -> np.ndarray:
    """``[J,k,3,3]``: per shape, the field ``phi[J,k,3,3]`` read at ``points[k,3]`` (m) replaced by the linear
    function of position ``A_j + sum_c B_jc x_c`` closest to it in the least squares weighted by
    ``weights[J,k]`` (the shape's squared motion: the vertices that move most say most). A field that is
    already linear in position is kept (exact); a constant one stays that constant. Coordinates are centred
    and scaled to the points' extent; a direction the weighted points do not span (a flat or single moving
    piece) gets no slope (the pseudo-inverse's least-norm solution)."""
    x = np.asarray(points, dtype=np.float64)
    f = np.asarray(phi, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    w = w / np.maximum(w.max(axis=1, keepdims=True), 1e-300)
    centre = x.mean(axis=0)
    scale = float(np.abs(x - centre).max()) or 1.0
    X = np.column_stack([np.ones(len(x)), (x - centre) / scale])                      # [k,4]
    # the weighted normal equations by batched matrix products (three-operand einsums are unbuffered
    # loops: 7x the time)
    wXt = np.swapaxes(w[:, :, None] * X[None], 1, 2)                                  # [J,4,k]
    M = wXt @ X                                                                       # [J,4,4]
    B = wXt @ f.reshape(len(f), len(x), 9)                                            # [J,4,9]
    coef = np.linalg.pinv(M, rcond=1e-10, hermitian=True) @ B                         # [J,4,9]
    return (X @ coef).reshape(f.shape)


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
    if moving is None:
        moving = np.ones(d.shape[:2], dtype=bool)
    var = noise_rms ** 2 / np.maximum(np.asarray(excitation, dtype=np.float64), 1e-12)   # [J], per vertex
    return james_stein(d, np.broadcast_to(var, d.shape[1::-1]), np.asarray(moving).T)
