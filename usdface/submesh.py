"""The part of a mesh its blend shapes move, and back: crop / scatter (pure numpy).

A full-body avatar is often one mesh whose face shapes move 5 % of it; a separate body mesh may move only
its neck. Every step of ``personalize`` works on the moving part only: a vertex no shape moves has zero
generic motion, so the person's field (a rotation + scale of the generic motion, :mod:`.transfer.implant`)
leaves it still, and it can be left out of every solve. The pair used at the edges of the pipeline:

* :func:`crop` - ``keep[n]`` (e.g. :func:`moving_region`) -> a :class:`SubMesh`: the kept vertices (indices
  into the full mesh, ascending) and the triangles among them, re-indexed;
* :func:`scatter` - values on the sub-mesh ``[..., s, c]`` back to the full mesh ``[..., n, c]``;
* :func:`crop_rig` - a :class:`usdface.model.FaceRig` on its sub-mesh (neutral, triangles, deltas and
  inbetweens cropped; the crop is recorded on the rig's source);
* :class:`SparseOffsets` - personalized offsets as indices + values (``vertices[s]``, ``values[K,s,3]``),
  what the layer writer takes without ever forming the dense ``[K, n, 3]`` array.

Units: whatever the arrays are in (metres in usdface). ``crop`` then ``scatter`` is the identity on the kept
vertices (exact: indexing only).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .motion import moving_vertices

__all__ = ["SubMesh", "moving_region", "crop", "scatter", "crop_rig", "rig_on", "SparseOffsets",
           "peak_of_shapes", "outside_offsets", "crop_avatar", "with_margin", "moving_part", "MARGIN",
           "MAX_SHARE", "coincident_vertices", "weld_rig", "WELD_TOLERANCE"]


@dataclass
class SubMesh:
    """A part of a mesh of ``n`` vertices: ``vertices[s]`` int64 ascending indices into the full mesh,
    ``triangles[t,3]`` the full mesh's triangles whose three corners are kept, re-indexed to ``0..s-1``
    (full-mesh order kept), ``points[n,3]`` the full mesh's rest points (None if not known).
    ``copies``: ``(full[d], local[d])`` for a welded part (:func:`weld_rig`): the full-mesh vertices that are
    copies of a kept vertex (split at a UV or normal seam) and that vertex's index in the part; they take
    its values when scattered back. None: no copies."""

    vertices: np.ndarray
    triangles: np.ndarray
    n: int
    points: np.ndarray | None = None
    copies: tuple | None = None

    @property
    def size(self) -> int:
        return int(self.vertices.size)

    @property
    def whole(self) -> bool:
        """True when every vertex is kept (the crop is the identity)."""
        return self.size == self.n


def peak_of_shapes(n: int, shapes) -> np.ndarray:
    """``[n]`` largest offset length of each vertex over sparse ``shapes``: an iterable of
    ``(indices[k] or None, offsets[k,3])`` (None: all ``n`` vertices, in order); no ``[K,n,3]`` array."""
    peak = np.zeros(n)
    for idx, off in shapes:
        off = np.asarray(off, dtype=np.float64)
        norms = np.sqrt(np.einsum("kc,kc->k", off, off))
        if idx is None:
            np.maximum(peak, norms, out=peak)
        elif len(idx):
            np.maximum.at(peak, np.asarray(idx, dtype=np.int64), norms)
    return peak


def moving_region(peak, points=None) -> np.ndarray:
    """``[n]`` bool: the vertices some shape moves, from each vertex's ``peak[n]`` motion over every shape
    (and inbetween) of the mesh, with :func:`usdface.motion.moving_vertices`' tolerance (float noise of an
    export is not motion; ``points[n,3]`` the rest points that noise scales with)."""
    return moving_vertices(peak, points)


#: The part worked on reaches this far beyond what moves, in RMS radii of the moving vertices (about 6 cm
#: on a head): the correspondence takes avatar surface points up to 4 capture edges (3 cm) from the capture,
#: which lies on the moving face but may overhang skin no shape moves (the ears, a hairline), and its
#: closest-point queries should see the same triangles as on the whole head.
MARGIN = 0.75


def with_margin(points, moving, margin: float = MARGIN) -> np.ndarray:
    """``[n]`` bool: ``moving[n]`` plus every vertex of ``points[n,3]`` within ``margin`` RMS radii of the
    moving vertices (their RMS distance from their centroid)."""
    from .mesh import distances_within

    p = np.asarray(points, dtype=np.float64)
    moving = np.asarray(moving, dtype=bool)
    keep = moving.copy()
    if not moving.any() or moving.all() or margin <= 0:
        return keep
    mp = p[moving]
    reach = margin * float(np.sqrt(np.mean(np.sum((mp - mp.mean(axis=0)) ** 2, axis=1))))
    lo, hi = mp.min(axis=0) - reach, mp.max(axis=0) + reach
    cand = np.flatnonzero(~moving & (p >= lo).all(axis=1) & (p <= hi).all(axis=1))
    if cand.size:
        d = distances_within(mp, p[cand], reach)
        keep[cand[np.isfinite(d)]] = True
    return keep


#: A mesh is cropped only when the part kept is at most this share of it: a crop of a head that moves
#: nearly everywhere saves little, and the whole mesh gives the whole-mesh answer to the last bit (the
#: non-rigid registration's solve amplifies float rounding of sums over a different vertex count ~1e8-fold,
#: to ~1e-8 m).
MAX_SHARE = 0.5


def moving_part(peak, points) -> np.ndarray | None:
    """``keep[n]`` bool, the part of a mesh worked on: the vertices some shape moves (:func:`moving_region`
    of ``peak[n]``) and :func:`with_margin` around them; None when that is more than :data:`MAX_SHARE` of
    the mesh (or nothing moves): keep the whole mesh. The margin is not searched when what moves is already
    more than that share (a subdivided head: it only adds vertices)."""
    moving = moving_region(peak, points)
    if moving.sum() > MAX_SHARE * moving.size:
        return None
    keep = with_margin(points, moving)
    if not keep.any() or keep.sum() > MAX_SHARE * keep.size:
        return None
    return keep


def crop(triangles, keep, points=None) -> SubMesh:
    """The sub-mesh of the vertices ``keep`` (``[n]`` bool, or indices into ``n = len(points)`` vertices):
    the triangles whose three corners are kept, re-indexed. ``points[n,3]`` is kept on the result."""
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    keep = np.asarray(keep)
    if keep.dtype == bool:
        n, vertices = keep.size, np.flatnonzero(keep)
    else:
        if points is None:
            raise ValueError("crop: give points (or a bool mask) so the full vertex count is known")
        n, vertices = len(points), np.unique(keep.astype(np.int64))
    mask = np.zeros(n, dtype=bool)
    mask[vertices] = True
    local = np.full(n, -1, dtype=np.int64)
    local[vertices] = np.arange(vertices.size)
    return SubMesh(vertices, local[tri[mask[tri].all(axis=1)]], n,
                   None if points is None else np.asarray(points, dtype=np.float64))


def scatter(values, sub: SubMesh, base=None) -> np.ndarray:
    """``values[..., s, c]`` on the sub-mesh -> ``[..., n, c]`` on the full mesh: a copy of ``base`` (same
    shape, e.g. the generic offsets) with the kept vertices replaced, zeros elsewhere without ``base``."""
    v = np.asarray(values)
    if base is None:
        out = np.zeros(v.shape[:-2] + (sub.n,) + v.shape[-1:], dtype=v.dtype)
    else:
        out = np.array(base, dtype=np.result_type(v.dtype, np.asarray(base).dtype), copy=True)
    out[..., sub.vertices, :] = v
    if sub.copies is not None:
        out[..., sub.copies[0], :] = v[..., sub.copies[1], :]
    return out


def outside_offsets(indices, offsets, inbetweens=()) -> tuple:
    """``(indices[r], offsets[r,3], [inbetween offsets[r,3], ...])`` of the points outside a crop whose
    offset (or an inbetween's) is not exactly zero: what a writer must keep as it was."""
    idx = np.asarray(indices, dtype=np.int64)
    off = np.asarray(offsets, dtype=np.float64).reshape(-1, 3)
    ibs = [np.asarray(b, dtype=np.float64).reshape(-1, 3) for b in inbetweens]
    nonzero = (off != 0).any(axis=1)
    for b in ibs:
        nonzero |= (b != 0).any(axis=1)
    return idx[nonzero], off[nonzero], [b[nonzero] for b in ibs]


def crop_rig(rig, keep, region: SubMesh | None = None):
    """``(FaceRig on the sub-mesh, SubMesh)``: ``rig`` (:class:`usdface.model.FaceRig`) with its neutral,
    deltas and inbetweens on its vertices ``keep`` and the triangles among them; its source (a copy) records
    the crop (``region``) and the non-zero offsets outside it (``residue``). A rig that is itself a part of
    its mesh (``region``: that part) is cropped further, the result again a part of the whole mesh (a welded
    part's copies follow their kept vertex, or join the residue with it). A crop that keeps every vertex
    returns ``rig`` itself (and ``region``, or a whole SubMesh)."""
    sub = crop(rig.triangles, keep, rig.neutral)
    if sub.whole:
        return rig, region if region is not None else sub
    return _part(rig, sub, region, np.zeros(sub.n, dtype=bool), None)


def _part(rig, sub: SubMesh, region: SubMesh | None, copy: np.ndarray, rep: np.ndarray | None):
    """:func:`crop_rig` / :func:`weld_rig`'s common end: ``rig`` on ``sub`` (indices into the rig's
    vertices); ``copy[n]`` the rig's vertices that become copies of ``rep[n]`` (their kept twin)."""
    import dataclasses

    v = sub.vertices
    local = np.full(sub.n, -1, dtype=np.int64)
    local[v] = np.arange(v.size)
    dropped = np.ones(sub.n, dtype=bool)
    dropped[v] = False
    dropped &= ~copy                                        # a copy is written with its twin, not kept
    triangles = sub.triangles
    full_of = (lambda i: i) if region is None else (lambda i: region.vertices[i])
    c_full, c_local = full_of(np.flatnonzero(copy)), (local[rep[copy]] if rep is not None
                                                      else np.zeros(0, dtype=np.int64))
    none = np.zeros(0, dtype=np.int64)
    before_full, before_local = region.copies if region is not None and region.copies is not None else (none,
                                                                                                      none)
    kept = local[before_local] >= 0                         # earlier copies follow their kept twin ...
    c_full = np.concatenate([c_full, before_full[kept]])
    c_local = np.concatenate([c_local, local[before_local[kept]]])
    lost = np.flatnonzero(~kept)                            # ... or join the residue with it
    copies = (c_full, c_local) if c_full.size else None
    sub = SubMesh(full_of(v), triangles, sub.n if region is None else region.n,
                  sub.points if region is None else region.points, copies)
    source = rig.source
    if source is not None:
        residue = []
        for k, name in enumerate(rig.names):
            ibs = rig.inbetweens.get(name, [])
            if region is None:
                authored = source.point_indices[k] if k < len(source.point_indices) else None
                rows = np.flatnonzero(dropped) if authored is None else authored[dropped[authored]]
                out = outside_offsets(rows, rig.deltas[k, rows], [b.offsets[rows] for b in ibs])
            else:
                rows = np.flatnonzero(dropped)
                at = np.concatenate([rows, before_local[lost]])
                out = outside_offsets(np.concatenate([region.vertices[rows], before_full[lost]]),
                                      rig.deltas[k, at], [b.offsets[at] for b in ibs])
                if source.residue:
                    before = source.residue[k]
                    out = (np.concatenate([before[0], out[0]]), np.concatenate([before[1], out[1]]),
                           [np.concatenate([x, y]) for x, y in zip(before[2], out[2], strict=True)])
            residue.append(out)
        source = dataclasses.replace(source, region=sub, residue=residue)
    return rig_on(rig, v, triangles, source, rig.name), sub


#: Two vertices closer than this share of the mesh's bounding-box diagonal are one point of the surface.
WELD_TOLERANCE = 1e-7


def coincident_vertices(points, deltas, inbetweens=(), *, tolerance: float = WELD_TOLERANCE) -> np.ndarray:
    """``rep[n]``: for each vertex of ``points[n,3]`` the lowest-index vertex it is a copy of (itself when
    none): the same rest point and the same offset in every shape ``deltas[K,n,3]`` and inbetween
    (``[n,3]`` arrays), within ``tolerance`` of the bounding-box diagonal. A mesh exported with its vertices
    split along UV or hard-normal seams (glTF, FBX) has such copies; the shapes move both alike, so they are
    one point of the surface. Closed lips or lids whose rest points touch are not copies: some shape parts
    them."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    p = np.asarray(points, dtype=np.float64)
    n = len(p)
    rep = np.arange(n)
    if n < 2:
        return rep
    eps = tolerance * float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))
    # the pairs to compare: every vertex with the first of the vertices at exactly its point (a clump of
    # thousands of parked vertices costs one pair each, not thousands), then the distinct points within
    # ``eps`` of each other
    rows = np.ascontiguousarray(p).view(np.dtype((np.void, p.dtype.itemsize * 3))).ravel()   # a row's bytes
    _, first_at, group = np.unique(rows, return_index=True, return_inverse=True)   # (-0.0, 0.0: the k-d tree)
    twin = first_at[group.reshape(-1)]
    same_point = np.flatnonzero(twin != rep)
    distinct = np.sort(first_at)
    near = cKDTree(p[distinct]).query_pairs(max(eps, 1e-300), output_type="ndarray")       # [pairs, 2]
    i = np.concatenate([twin[same_point], distinct[near[:, 0]]])
    j = np.concatenate([same_point, distinct[near[:, 1]]])
    if not len(i):
        return rep
    same = np.ones(len(i), dtype=bool)
    for d in [np.asarray(deltas, dtype=np.float64).reshape(-1, n, 3), *(np.asarray(b)[None]
                                                                        for b in inbetweens)]:
        for k in range(len(d)):                                   # shape by shape: no [K,pairs,3] array
            same &= np.abs(d[k, i] - d[k, j]).max(axis=1) <= eps
    if not same.any():
        return rep
    graph = coo_matrix((np.ones(int(same.sum())), (i[same], j[same])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    lowest = np.full(label.max() + 1, n)
    np.minimum.at(lowest, label, np.arange(n))
    return lowest[label]


def weld_rig(rig, region: SubMesh | None = None):
    """``(FaceRig, SubMesh or region)``: ``rig`` (:class:`usdface.model.FaceRig`, a part of its mesh when
    ``region`` is given) with the copies of each vertex (:func:`coincident_vertices`) merged into it: the
    triangles re-indexed to the kept vertex, so every step sees one connected surface where the export
    split it, and the region records the copies (``SubMesh.copies``), which take their twin's result when
    written or scattered. Without copies: ``(rig, region)`` unchanged."""
    ibs = [b.offsets for lst in rig.inbetweens.values() for b in lst]
    rep = coincident_vertices(rig.neutral, rig.deltas, ibs)
    copy = rep != np.arange(len(rep))
    if not copy.any():
        return rig, region
    tri = rep[rig.triangles]
    tri = tri[(tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])]
    return _part(rig, crop(tri, ~copy, rig.neutral), region, copy, rep)


def rig_on(rig, vertices, triangles, source, name):
    """``rig`` (:class:`usdface.model.FaceRig`) on its ``vertices[s]`` (indices, ascending) with the
    re-indexed ``triangles[t,3]`` among them: neutral, deltas and inbetweens taken there; ``source`` and
    ``name`` those of the new rig."""
    from .model import FaceRig, Inbetween

    v = np.asarray(vertices, dtype=np.int64)
    ibs = {k: [Inbetween(b.name, b.weight, b.offsets[v], b.normal_offsets) for b in lst]
           for k, lst in rig.inbetweens.items()}
    out = FaceRig(rig.neutral[v], triangles, rig.names, rig.deltas[:, v], ibs, source, name)
    kept = rig.kept_peak()
    if kept is not None:                                    # its peak motion there (a max: the same values)
        out.keep_peak(kept[v])
    return out


class SparseOffsets:
    """Offsets of a ``K``-shape rig on an ``n``-vertex mesh, kept sparse: ``values[K,s,3]`` at the full-mesh
    ``vertices[s]`` (ascending); elsewhere ``base[K,n,3]`` when given (the generic offsets, untouched),
    else 0. ``np.asarray(offsets)`` (and indexing) gives the dense ``[K,n,3]`` array for callers that want
    it; ``offsets[k]`` gives shape ``k``'s ``[n,3]`` row alone (shape-by-shape loops: densifying the whole
    array for each shape was K x 385 MB of copies on the 314k-vertex head + body mesh, 24 s of
    ``personalize --inspect``); :func:`usdface.io.layers.write_avatar_layer` writes it without densifying.
    ``copies``: a welded
    part's ``(full[d], local[d])`` (:attr:`SubMesh.copies`): vertex ``full[i]`` has the values of
    ``vertices[local[i]]``."""

    def __init__(self, vertices, values, n: int, base=None, copies=None):
        self.vertices = np.asarray(vertices, dtype=np.int64)
        self.values = np.asarray(values, dtype=np.float64)
        self.n = int(n)
        self.base = base
        self.copies = copies
        if self.values.ndim != 3 or self.values.shape[1] != self.vertices.size or self.values.shape[2] != 3:
            raise ValueError(f"SparseOffsets: values {self.values.shape} do not fit {self.vertices.size} "
                             "vertices [K,s,3]")
        if base is not None and np.shape(base) != self.shape:
            raise ValueError(f"SparseOffsets: base {np.shape(base)} is not {self.shape}")

    @property
    def shape(self) -> tuple:
        return (self.values.shape[0], self.n, 3)

    def __len__(self) -> int:
        return self.values.shape[0]

    def dense(self) -> np.ndarray:
        """The ``[K,n,3]`` float64 array."""
        out = (np.zeros(self.shape) if self.base is None
               else np.array(self.base, dtype=np.float64, copy=True))
        out[:, self.vertices] = self.values
        if self.copies is not None:
            out[:, self.copies[0]] = self.values[:, self.copies[1]]
        return out

    def __array__(self, dtype=None, copy=None):
        d = self.dense()
        return d if dtype is None else d.astype(dtype)

    def __getitem__(self, item):
        if isinstance(item, int | np.integer):     # one shape: its [n,3] row only, not the dense [K,n,3]
            k = range(len(self))[item]             # negative indices, and IndexError past the end
            out = (np.zeros((self.n, 3)) if self.base is None
                   else np.array(self.base[k], dtype=np.float64, copy=True))
            vertices, values = self.shape_row(k)
            out[vertices] = values
            return out
        return self.dense()[item]

    def shape_row(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Shape ``k`` as ``(vertices[s], values[s,3])`` (a welded part's copies after its vertices)."""
        if self.copies is None:
            return self.vertices, self.values[k]
        return (np.concatenate([self.vertices, self.copies[0]]),
                np.concatenate([self.values[k], self.values[k][self.copies[1]]]))


def crop_avatar(avatar) -> tuple:
    """``(avatar on its moving parts, {mesh key -> SubMesh})``: every mesh with blend shapes of ``avatar``
    (:class:`usdface.model.Avatar`) cropped to the vertices some shape or inbetween moves
    and the margin around them (:func:`moving_part`), unless it is already (read with ``moving_only``) or the
    part is most of the mesh, and welded where the export split its vertices (:func:`weld_rig`). Keys are
    the meshes' prim paths (their names without a source); meshes kept whole have no entry."""
    import dataclasses

    meshes, regions = [], {}
    for m in avatar.meshes:
        key = m.key
        region = None
        if m.source is not None and m.source.region is not None:        # read on its moving part
            region = m.source.region
        else:
            peak = m.peak_motion().copy()          # (kept on the rig for the steps after)
            for ibs in m.inbetweens.values():
                for b in ibs:
                    np.maximum(peak, np.sqrt(np.einsum("nc,nc->n", b.offsets, b.offsets)), out=peak)
            keep = moving_part(peak, m.neutral)
            if keep is not None:
                m, region = crop_rig(m, keep)
        if m.n_shapes:
            m, region = weld_rig(m, region)
        if region is not None:
            regions[key] = region
        meshes.append(m)
    return dataclasses.replace(avatar, meshes=meshes), regions

