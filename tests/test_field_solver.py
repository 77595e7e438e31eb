"""The field's numerical pieces at production size: the extension's solve, the ring neighbourhoods and the
restricted smoothing give the same numbers as the plain formulas (issue 12, docs/scale.md)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import shortest_path
from synthetic_meshes import grid_triangles

from usdface.mesh import spd_lu, vertex_adjacency
from usdface.transfer.motion_field import FieldExtension, neighbourhood_matrix, smooth_field


def _sheet(n=30, seed=0):
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.linspace(0.0, 0.1, n), np.linspace(0.0, 0.1, n))
    pts = np.stack([xs.ravel(), ys.ravel(), 0.01 * np.sin(30 * xs.ravel())], axis=1)
    pts[:, :2] += rng.uniform(-1e-3, 1e-3, size=(len(pts), 2))          # irregular cotangent weights
    return pts, grid_triangles(n, n)


def test_field_extension_is_the_screened_laplacian_solve():
    pts, tri = _sheet()
    known = pts[:, 0] < 0.04
    ext = FieldExtension(pts, tri, known, length=0.05)
    rng = np.random.default_rng(1)
    vals = rng.normal(size=(len(pts), 7))
    out = ext.extend(vals)
    # the same system assembled by hand and solved directly: same answer to round-off (relative 1e-10)
    from usdface.mesh import triangle_areas
    from usdface.transfer.surface import cotangent_laplacian

    lap = cotangent_laplacian(pts, tri)
    mass = np.bincount(tri.T.ravel(), weights=np.tile(triangle_areas(pts, tri) / 3, 3), minlength=len(pts))
    full = (lap + sp.diags(mass / 0.05 ** 2)).tocsr()
    free = np.flatnonzero(~known)
    a_ff = full[free][:, free]
    ref = spd_lu(a_ff.tocsc()).solve(-(full[free][:, np.flatnonzero(known)] @ vals[known]))
    assert np.allclose(out[free], ref, rtol=0, atol=1e-10 * np.abs(ref).max())
    np.testing.assert_array_equal(out[known], vals[known])


def test_ring_neighbourhood_is_the_edge_distance_ball():
    pts, tri = _sheet(12)
    n = len(pts)
    rows = np.array([0, 5, 77, 143])
    hops = shortest_path(vertex_adjacency(tri, n), unweighted=True, indices=rows)
    for rings in (1, 2, 4):
        near = neighbourhood_matrix(tri, n, rings, rows)
        assert near.dtype == bool
        np.testing.assert_array_equal(near.toarray(), hops <= rings)


def test_smoothing_on_rows_equals_the_dense_weighted_average():
    pts, tri = _sheet(16)
    n = len(pts)
    rng = np.random.default_rng(2)
    phi = rng.normal(size=(3, n, 3, 3))
    w = rng.uniform(size=(3, n)) * (pts[None, :, 0] < np.array([0.03, 0.06, 0.1])[:, None])   # sparse
    rows = np.arange(0, n, 3)
    near = neighbourhood_matrix(tri, n, 3, rows)
    got = smooth_field(phi, w, tri, neighbourhood=near.tocsc(), rows=rows)
    s = near.toarray().astype(float)
    num = np.einsum("rv,jv,jvab->jrab", s, w, phi)
    den = s @ w.T                                                               # [r, J]
    want = np.where(den.T[..., None, None] > 1e-12, num / np.maximum(den.T, 1e-300)[..., None, None], 0.0)
    np.testing.assert_allclose(got[:, rows], want, rtol=1e-12, atol=1e-12)
    others = np.setdiff1d(np.arange(n), rows)
    assert not got[:, others].any()
    assert (den <= 1e-12).any() and (den > 1e-12).any()                    # both branches exercised
