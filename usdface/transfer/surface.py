"""Surface queries the transfer needs on top of :mod:`usdface.mesh`: closest points on a triangle surface
(Open3D ``RaycastingScene``) and deterministic surface samples.

The mesh building blocks (normals, areas, gradient operator, cotangent Laplacian, adjacency, boundary) have
one implementation, in :mod:`usdface.mesh`; they are re-exported here for the transfer modules.
Pure numpy / Open3D on arrays: ``points[n,3]`` (metres), ``triangles[t,3]`` int vertex indices.
"""

from __future__ import annotations

import numpy as np

from ..mesh import (
    boundary_vertices,
    gradient_operator,
    index_set,
    mean_edge_length,
    triangle_areas,
    triangle_normals,
    vector_lengths,
    vertex_adjacency,
    vertex_normals,
)
from ..mesh import (
    cotangent_laplacian as _cotangent_laplacian,
)
from ..natives import open3d

__all__ = ["triangle_normals", "vertex_normals", "triangle_areas", "gradient_operator", "cotangent_laplacian",
           "boundary_vertices", "closest_points", "SurfaceQuery", "mean_edge_length", "vertex_adjacency",
           "surface_samples", "decimate", "spatial_order", "prolongation"]


def cotangent_laplacian(points, triangles):
    """The positive semi-definite cotangent Laplacian the transfer solves with: ``-L`` of
    :func:`usdface.mesh.cotangent_laplacian` with edge weights clamped at ``1e-3`` (well-posed Dirichlet
    problems on obtuse meshes)."""
    return (-_cotangent_laplacian(points, triangles, min_weight=1e-3)).tocsr()


class SurfaceQuery:
    """Closest-point queries on one triangle mesh (Open3D ``RaycastingScene``, built once and reused).

    Computed about the mesh's centroid so that float32 keeps sub-micrometre precision wherever the mesh is
    placed.
    """

    def __init__(self, points, triangles):
        o3d = open3d()

        self._o3d = o3d
        self.points = np.asarray(points, dtype=np.float64)
        self.triangles = np.asarray(triangles)
        self.origin = self.points.mean(axis=0)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor((self.points - self.origin).astype(np.float32)),
                                 o3d.core.Tensor(np.asarray(triangles, dtype=np.uint32)))

    def closest_points(self, queries):
        """``(triangle[q], barycentric[q,3], closest[q,3], distance[q])`` for ``queries[q,3]``;
        ``barycentric`` weighs the triangle's vertices in order."""
        q = np.asarray(queries, dtype=np.float64) - self.origin
        ans = self.scene.compute_closest_points(self._o3d.core.Tensor(q.astype(np.float32)))
        tri = ans["primitive_ids"].numpy().astype(np.int64)
        uv = ans["primitive_uvs"].numpy().astype(np.float64)
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        bary = np.clip(bary, 0.0, 1.0)
        bary /= bary.sum(axis=1, keepdims=True)
        # ``take``: the same gather as ``points[triangles[tri]]``, without fancy indexing's general
        # (multi-dimensional index) path, 2.5x slower on these sizes; 153 calls in a dev1 run
        closest = np.einsum("qk,qkc->qc", bary, self.points.take(self.triangles.take(tri, axis=0), axis=0))
        return tri, bary, closest, vector_lengths(closest - (q + self.origin))


def closest_points(points, triangles, queries):
    """Closest points on a triangle mesh (Open3D ``RaycastingScene.compute_closest_points``): one-off
    :class:`SurfaceQuery`. Returns ``(triangle[q], barycentric[q,3], closest[q,3], distance[q])``."""
    return SurfaceQuery(points, triangles).closest_points(queries)


def surface_samples(points, triangles, subdivisions: int) -> np.ndarray:
    """Deterministic dense samples of a triangle mesh: the barycentric grid of ``subdivisions`` steps on every
    triangle (``(s+1)(s+2)/2`` points each, shared edges repeated). ``subdivisions <= 1`` returns the
    vertices used by the triangles."""
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles)
    s = int(subdivisions)
    if s <= 1:
        return p[index_set(t, len(p))]
    i, j = np.meshgrid(np.arange(s + 1), np.arange(s + 1), indexing="ij")
    keep = (i + j) <= s
    b1, b2 = i[keep] / s, j[keep] / s
    bary = np.stack([1.0 - b1 - b2, b1, b2], axis=1)  # [g,3]
    return np.matmul(bary, p[t]).reshape(-1, 3)                  # [t,g,3]: one batched product


def decimate(points, triangles, edge: float):
    """A coarser mesh of the same surface whose mean edge is about ``edge`` metres: Open3D's quadric edge
    collapse (Garland & Heckbert 1997) down to the triangle count an equilateral mesh of that edge has on the
    surface's area. Edge collapses keep the connectivity (two surfaces that do not share an edge, as closed
    lips, stay apart), and the vertices sit where the quadric error is least, so on a subdivided mesh
    they are the original corners. Returns ``(points[p,3], triangles[s,3])``; the input unchanged when it
    is not finer than that."""
    o3d = open3d()

    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles)
    target = int(np.ceil(triangle_areas(p, t).sum() / (np.sqrt(3.0) / 4.0 * edge * edge)))
    if target >= len(t):
        return p, t
    # the vertices in space-filling-curve order and the triangles by their corners' places in it: the
    # decimation's quadrics, edges and collapses then touch memory in order (a subdivided head lists its
    # midpoints after every original vertex: a sixth of the decimation's 4 CPU-s), and its result no longer
    # depends on how an export numbers the vertices or orders the triangles (collapses of equal cost, a flat
    # patch's, go in this order)
    order = spatial_order(p, 2.0 * edge)
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    t = rank[t]
    by_corner = np.sort(t, axis=1)
    t = t[np.lexsort((by_corner[:, 2], by_corner[:, 1], by_corner[:, 0]))]
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(p[order]),
                                     o3d.utility.Vector3iVector(t.astype(np.int32)))
    coarse = mesh.simplify_quadric_decimation(target)
    coarse.remove_degenerate_triangles()
    coarse.remove_unreferenced_vertices()
    return np.asarray(coarse.vertices, dtype=np.float64), np.asarray(coarse.triangles, dtype=np.int64)


def spatial_order(points, cell: float) -> np.ndarray:
    """``[n]`` an order of ``points[n,3]`` along a Z-order (Morton) curve over ``cell``-sized voxels (m),
    ties by the coordinates: points near each other in space come near each other in the order (memory
    locality for a mesh's vertices), and the order depends on the positions only (up to identical points,
    kept in their order)."""
    p = np.asarray(points, dtype=np.float64)
    if not len(p):
        return np.zeros(0, dtype=np.int64)
    g = np.floor((p - p.min(axis=0)) / max(float(cell), 1e-300)).astype(np.int64)
    g = np.minimum(g, (1 << 21) - 1)                              # 21 bits a coordinate: 63 in all
    code = np.zeros(len(p), dtype=np.int64)
    for bit in range(int(g.max()).bit_length()):
        for axis in range(3):
            code |= ((g[:, axis] >> bit) & 1) << (3 * bit + axis)
    return np.lexsort((p[:, 2], p[:, 1], p[:, 0], code))


def prolongation(coarse_points, coarse_triangles, queries):
    """``[q, p]`` sparse (CSR) linear interpolation from the vertices of a coarse mesh to ``queries[q,3]``:
    each row the barycentric weights of the query's closest point on the coarse surface (3 entries summing
    to 1, in the order of that coarse triangle's corners: ``indices.reshape(-1, 3)`` are the triangles), so
    a field linear over each coarse triangle is reproduced exactly there."""
    import scipy.sparse as sp

    tri, bary, _, _ = SurfaceQuery(coarse_points, coarse_triangles).closest_points(queries)
    q = len(tri)
    cols = np.asarray(coarse_triangles)[tri]
    return sp.csr_matrix((bary.ravel(), cols.ravel(), np.arange(0, 3 * q + 1, 3)),
                         shape=(q, len(coarse_points)))
