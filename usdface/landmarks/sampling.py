"""The face surface sampled at a fixed physical spacing: the same points at every mesh resolution.

A landmark is a point on the skin, and the visibility of eq. 4 (Zell & McDonnell 2022) is a property of the
skin, not of how finely a mesh describes it. Two tools, both on a grid of cubes anchored at the origin of the
rig's frame (the same grid at every resolution):

* **samples** (:func:`surface_points`, :func:`sample_vertices`): per cube whose inscribed ball meets the
  surface, the surface point nearest the cube's centre, written as the mesh's vertex nearest it. The points
  are the surface's own (a subdivided mesh gives the same ones); the vertices the same physical points to
  within the coarser mesh's vertex spacing. :mod:`usdface.landmarks.layout` ray casts them for every vertex
  near them (and, on request, takes them as the only set-cover candidates);
* the **occluder** (:func:`cluster_vertices`, :func:`occluder_triangles`): vertex clustering (Rossignac &
  Borrel 1993) made topology-aware: the vertices of one cube connected by edges inside it form a cluster
  (the two lips or lids in one cube stay two), represented by its vertex nearest the cube's centre; the
  triangles re-indexed to the representatives, degenerate and repeated ones dropped. About two triangles per
  cluster, whatever the resolution, posed by the representatives' own offsets.

All functions are pure numpy/scipy: ``points[n, 3]`` metres, ``triangles[t, 3]`` int.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ..errors import LandmarkError
from ..natives import open3d

#: The candidate spacing as a share of the face size (:func:`usdface.landmarks.visibility.face_size`, the
#: diagonal of the box around the moving vertices), rounded to a power of two millimetres
#: (:func:`sample_spacing`): 8 mm on the dev heads (0.42 m), the resolution of the capture the landmarks are
#: tracked against (the phone's face mesh, ARKit's 1,220-vertex mask: ~7 mm edges): points closer than that
#: are one landmark to the tracker. It is also well above the dev heads' own face vertex spacing (2.8 mm
#: median edge), so the same points are sampled on them as on any finer mesh of their surface (at 4 mm, 15 %
#: of dev1's surface points shared a nearest vertex with another one and were lost).
SPACING_SHARE = 0.02
#: The occluder's clustering spacing as a share of the candidate spacing: 2 mm on a human head, fine enough
#: for a lid's or lip's margin (a 4 mm clustering changed the visibility of lid-margin vertices by up to 0.9,
#: mean 0.037 on the twice-subdivided dev head; 2 mm: mean 0.007, 98.8 % within one ray of 16).
OCCLUDER_SHARE = 0.25


def sample_spacing(face_size: float, share: float = SPACING_SHARE) -> float:
    """The sampling spacing (metres) for a face of ``face_size`` metres: ``share`` of it, rounded to a power
    of two millimetres (8 mm for the dev heads' 0.42 m). The rounding keeps the grid the same when the face
    size itself moves with the resolution (the dev head's box of moving vertices grows by 1.1 % when
    subdivided: its midpoints reach half an edge further)."""
    size = float(face_size) * float(share)
    if not (np.isfinite(size) and size > 0.0):
        raise LandmarkError(f"face size {face_size!r} x share {share!r} is no positive length",
                            fix="check that some shape moves the mesh")
    return 1e-3 * float(2.0 ** np.round(np.log2(size / 1e-3)))


def cluster_vertices(points: np.ndarray, triangles: np.ndarray, spacing: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Topology-aware vertex clustering at ``spacing`` metres.

    ``points[n, 3]`` metres, ``triangles[t, 3]`` -> ``(cluster[n], representative[m])``: each vertex's cluster
    id in [0, m) and each cluster's representative vertex (sorted ascending, so cluster ids follow vertex
    order). A cluster is a set of vertices in one grid cube of side ``spacing`` (grid anchored at the frame's
    origin) connected by mesh edges inside that cube; its representative is its vertex nearest the cube's
    centre (ties: the lowest index). Isolated vertices are clusters of their own cube.
    """
    p = np.asarray(points, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.int64)
    n = len(p)
    h = float(spacing)
    if not (np.isfinite(h) and h > 0.0):
        raise LandmarkError(f"sampling spacing {spacing!r} must be a positive length in metres",
                            fix="pass a spacing > 0 (default: SPACING_SHARE of the face size)")
    if n == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    cell = np.floor(p / h).astype(np.int64)
    span = cell.max(axis=0) - cell.min(axis=0) + 1
    if float(np.prod(span.astype(np.float64))) < 2.0 ** 62:  # one int64 per cube: a fast 1-D unique
        _, cube = np.unique(np.ravel_multi_index((cell - cell.min(axis=0)).T, span), return_inverse=True)
    else:
        _, cube = np.unique(cell, axis=0, return_inverse=True)
    cube = cube.ravel()
    # edges inside one cube join their vertices; the connected components of that graph are the clusters
    e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]).reshape(-1, 2)
    e = e[cube[e[:, 0]] == cube[e[:, 1]]]
    graph = sp.coo_matrix((np.ones(len(e), dtype=np.int8), (e[:, 0], e[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    d2 = (((p - (cell + 0.5) * h) ** 2).sum(axis=1))
    order = np.lexsort((np.arange(n), d2, label))
    first = np.r_[True, label[order][1:] != label[order][:-1]]
    reps = np.sort(order[first])
    # cluster ids in the order of their representatives
    rep_of_label = np.empty(label.max() + 1, dtype=np.int64)
    rep_of_label[label[reps]] = np.arange(len(reps))
    return rep_of_label[label], reps


def surface_points(points: np.ndarray, triangles: np.ndarray, spacing: float,
                   near: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The surface sampled on a grid of side ``spacing`` metres: per grid cube whose inscribed ball (radius
    ``spacing / 2`` around its centre) meets the surface, the surface point nearest the centre.

    Returns ``(q[s, 3]`` metres, ``triangle[s]`` the triangle each lies on, ``bary[s, 3]`` its barycentric
    coordinates there``)``. A property of the surface alone (the grid is anchored at the frame's origin): a
    mesh subdivided without moving its surface (midpoints) gives the same points, to float rounding, and any
    piecewise-linear field (the shapes' offsets) interpolated there the same values. ``near[v]`` restricts
    the cubes to those within one cube of the given vertices (default: of every vertex; the surface must then
    be sampled finer than ``spacing`` for no cube to be missed). Closest points by Open3D's
    ``RaycastingScene.compute_closest_points``.
    """
    o3d = open3d()

    p = np.asarray(points, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.int64)
    h = float(spacing)
    src = p if near is None else p[np.asarray(near, dtype=np.int64)]
    if len(src) == 0 or len(tri) == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    base = np.unique(np.floor(src / h).astype(np.int64), axis=0)
    offsets = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    cubes = np.unique((base[:, None, :] + offsets[None]).reshape(-1, 3), axis=0)
    centres = (cubes + 0.5) * h
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(p, dtype=np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(tri, dtype=np.uint32)))
    closest = scene.compute_closest_points(o3d.core.Tensor(centres.astype(np.float32)))
    tri_id = closest["primitive_ids"].numpy().astype(np.int64)
    uv = closest["primitive_uvs"].numpy().astype(np.float64)
    bary = np.stack([1.0 - uv.sum(axis=1), uv[:, 0], uv[:, 1]], axis=1)
    q = np.einsum("sj,sjx->sx", bary, p[tri[tri_id]])  # float64 points from the float32 query
    ok = np.linalg.norm(q - centres, axis=1) <= 0.5 * h
    return q[ok], tri_id[ok], bary[ok]


def sample_vertices(points: np.ndarray, triangles: np.ndarray, spacing: float,
                    near: np.ndarray | None = None) -> np.ndarray:
    """The vertices nearest the :func:`surface_points` -> ``[m]`` (ascending, unique): the same physical
    points at every resolution, each written as its mesh's nearest vertex (where two points share one, on a
    mesh coarser than ``spacing``, it stands for both)."""
    from scipy.spatial import cKDTree

    q, _, _ = surface_points(points, triangles, spacing, near)
    if len(q) == 0:
        return np.zeros(0, dtype=np.int64)
    _, idx = cKDTree(np.asarray(points, dtype=np.float64)).query(q)
    return np.unique(idx.astype(np.int64))


def occluder_triangles(triangles: np.ndarray, cluster: np.ndarray, representative: np.ndarray,
                       keep: np.ndarray | None = None) -> np.ndarray:
    """The clustered mesh: ``triangles[t, 3]`` with each vertex replaced by its cluster's representative
    (``cluster[n]``, ``representative[m]`` from :func:`cluster_vertices`), triangles with a repeated vertex
    and repeated triangles (the same vertices in any order) dropped -> ``[t', 3]`` vertex indices into the
    original points (posed by the representatives' own positions), the first occurrence's orientation kept.
    ``keep[v]``: vertices that must be vertices of the occluder (e.g. the ray origins): each becomes its
    cluster's representative, or, when its cluster already has one of them, a cluster of its own.
    """
    cluster = np.asarray(cluster, dtype=np.int64).copy()
    rep = np.asarray(representative, dtype=np.int64).copy()
    if keep is not None and len(keep):
        keep = np.unique(np.asarray(keep, dtype=np.int64))
        _, first = np.unique(cluster[keep], return_index=True)
        claim = np.zeros(len(keep), dtype=bool)
        claim[first] = True
        rep[cluster[keep[claim]]] = keep[claim]
        extra = keep[~claim]
        cluster[extra] = len(rep) + np.arange(len(extra))
        rep = np.concatenate([rep, extra])
    tri = rep[cluster[np.asarray(triangles, dtype=np.int64)]]
    ok = (tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 2] != tri[:, 0])
    tri = tri[ok]
    _, first = np.unique(np.sort(tri, axis=1), axis=0, return_index=True)
    return tri[np.sort(first)]
