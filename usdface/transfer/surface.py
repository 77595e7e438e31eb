"""Triangle-mesh building blocks the transfer needs: normals, gradient operator, cotangent Laplacian,
boundary, and closest points on a surface (Open3D ``RaycastingScene``).

Pure numpy / scipy / Open3D on arrays: ``points[n,3]`` (metres), ``triangles[t,3]`` int vertex indices.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["triangle_normals", "vertex_normals", "triangle_areas", "gradient_operator", "cotangent_laplacian",
           "boundary_vertices", "closest_points", "mean_edge_length", "vertex_adjacency"]


def triangle_normals(points, triangles, *, unit=True) -> np.ndarray:
    """Per-triangle normals ``[t,3]`` (unit, or area-weighted ``2 * area`` length when ``unit=False``)."""
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles)
    n = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    if unit:
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    return n


def triangle_areas(points, triangles) -> np.ndarray:
    """Triangle areas ``[t]`` (m^2)."""
    return 0.5 * np.linalg.norm(triangle_normals(points, triangles, unit=False), axis=1)


def vertex_normals(points, triangles) -> np.ndarray:
    """Area-weighted unit vertex normals ``[n,3]`` (zero for isolated vertices)."""
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles)
    fn = triangle_normals(p, t, unit=False)
    vn = np.zeros_like(p)
    for c in range(3):
        np.add.at(vn, t[:, c], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


def mean_edge_length(points, triangles) -> float:
    """Mean length of the triangles' edges (m)."""
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles)
    e = np.concatenate([p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 1]], p[t[:, 0]] - p[t[:, 2]]])
    return float(np.linalg.norm(e, axis=1).mean())


def vertex_adjacency(triangles, n: int) -> sp.csr_matrix:
    """Symmetric 0/1 vertex adjacency ``[n,n]`` of a triangle mesh."""
    t = np.asarray(triangles)
    i = np.concatenate([t[:, 0], t[:, 1], t[:, 2], t[:, 1], t[:, 2], t[:, 0]])
    j = np.concatenate([t[:, 1], t[:, 2], t[:, 0], t[:, 0], t[:, 1], t[:, 2]])
    a = sp.csr_matrix((np.ones(i.size), (i, j)), shape=(n, n))
    a.data[:] = 1.0
    return a


def gradient_operator(points, triangles) -> sp.csr_matrix:
    """Per-triangle gradient of piecewise-linear functions: ``G[3t, n]`` with rows ``3*t + axis``.

    ``(G @ f)[3t:3t+3]`` is the (constant) gradient of the hat-function interpolant of ``f[n]`` on triangle t,
    in 1/m. Applied to the points themselves, ``G @ points`` stacks the tangent-plane projectors ``P_t[3,3]``.
    """
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles)
    v0, v1, v2 = p[t[:, 0]], p[t[:, 1]], p[t[:, 2]]
    nrm = np.cross(v1 - v0, v2 - v0)
    dbl = np.maximum(np.einsum("ij,ij->i", nrm, nrm), 1e-300)  # (2 area)^2
    # grad phi_i = n x e_i / (2A)^2 * |n| with e_i the edge opposite vertex i (counter-clockwise).
    grads = [np.cross(nrm, v2 - v1), np.cross(nrm, v0 - v2), np.cross(nrm, v1 - v0)]
    rows = (3 * np.arange(len(t)))[:, None] + np.arange(3)[None, :]
    data, ri, ci = [], [], []
    for k in range(3):
        g = grads[k] / dbl[:, None]
        data.append(g.ravel())
        ri.append(rows.ravel())
        ci.append(np.repeat(t[:, k], 3))
    return sp.csr_matrix((np.concatenate(data), (np.concatenate(ri), np.concatenate(ci))),
                         shape=(3 * len(t), len(p)))


def cotangent_laplacian(points, triangles) -> sp.csr_matrix:
    """Cotangent Laplacian ``L[n,n]`` (positive semi-definite: ``L = sum w_ij (e_i - e_j)(e_i - e_j)^T``).

    Weights ``w_ij = (cot a + cot b) / 2`` are clamped at a small positive value so that obtuse meshes still
    give a well-posed Dirichlet problem.
    """
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles)
    n = len(p)
    ii, jj, ww = [], [], []
    for k in range(3):
        a, b, c = t[:, k], t[:, (k + 1) % 3], t[:, (k + 2) % 3]
        u, v = p[b] - p[a], p[c] - p[a]
        cot = np.einsum("ij,ij->i", u, v) / np.maximum(np.linalg.norm(np.cross(u, v), axis=1), 1e-300)
        ii.append(b)
        jj.append(c)
        ww.append(0.5 * cot)
    i, j, w = np.concatenate(ii), np.concatenate(jj), np.concatenate(ww)
    w_off = sp.csr_matrix((w, (i, j)), shape=(n, n))
    w_off = w_off + w_off.T
    w_off.data = np.maximum(w_off.data, 1e-3)
    return (sp.diags(np.asarray(w_off.sum(axis=1)).ravel()) - w_off).tocsr()


def boundary_vertices(triangles, n: int) -> np.ndarray:
    """Boolean mask ``[n]`` of vertices on a boundary edge (an edge used by exactly one triangle)."""
    t = np.asarray(triangles)
    e = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(e, axis=0, return_counts=True)
    mask = np.zeros(n, dtype=bool)
    mask[uniq[counts == 1].ravel()] = True
    return mask


def closest_points(points, triangles, queries):
    """Closest points on a triangle mesh (Open3D ``RaycastingScene.compute_closest_points``).

    Returns ``(triangle[q], barycentric[q,3], closest[q,3], distance[q])``; ``barycentric`` weighs the
    triangle's vertices in order. Computed about the mesh's centroid so that float32 keeps sub-micrometre
    precision wherever the mesh is placed.
    """
    import open3d as o3d

    p = np.asarray(points, dtype=np.float64)
    origin = p.mean(axis=0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((p - origin).astype(np.float32)),
                        o3d.core.Tensor(np.asarray(triangles, dtype=np.uint32)))
    q = np.asarray(queries, dtype=np.float64) - origin
    ans = scene.compute_closest_points(o3d.core.Tensor(q.astype(np.float32)))
    tri = ans["primitive_ids"].numpy().astype(np.int64)
    uv = ans["primitive_uvs"].numpy().astype(np.float64)
    bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
    bary = np.clip(bary, 0.0, 1.0)
    bary /= bary.sum(axis=1, keepdims=True)
    closest = np.einsum("qk,qkc->qc", bary, p[np.asarray(triangles)[tri]])
    return tri, bary, closest, np.linalg.norm(closest - (q + origin), axis=1)


def surface_samples(points, triangles, subdivisions: int) -> np.ndarray:
    """Deterministic dense samples of a triangle mesh: the barycentric grid of ``subdivisions`` steps on every
    triangle (``(s+1)(s+2)/2`` points each, shared edges repeated). ``subdivisions <= 1`` returns the
    vertices used by the triangles."""
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles)
    s = int(subdivisions)
    if s <= 1:
        return p[np.unique(t)]
    i, j = np.meshgrid(np.arange(s + 1), np.arange(s + 1), indexing="ij")
    keep = (i + j) <= s
    b1, b2 = i[keep] / s, j[keep] / s
    bary = np.stack([1.0 - b1 - b2, b1, b2], axis=1)  # [g,3]
    return np.einsum("gk,tkc->tgc", bary, p[t]).reshape(-1, 3)
