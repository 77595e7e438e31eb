"""Analytic tests of usdface.mesh: frames, deformation gradients, gradient operator, Laplacians, loops."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from usdface.errors import GeometryError
from usdface.mesh import (
    apply_gradient,
    boundary_loops,
    check_triangles,
    cotangent_laplacian,
    cross,
    deformation_gradients,
    display_subset,
    gradient_operator,
    harmonic_fill,
    mesh_scale,
    triangle_areas,
    triangle_frames,
    triangle_normals,
    uniform_laplacian,
)

TRI = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
T1 = np.array([[0, 1, 2]])


def grid(nx=6, ny=5, hole=False):
    """A planar grid mesh (optionally with a square hole in the middle)."""
    xs, ys = np.meshgrid(np.arange(nx, dtype=float), np.arange(ny, dtype=float))
    pts = np.c_[xs.ravel(), ys.ravel(), np.zeros(xs.size)]
    tris = []
    for j in range(ny - 1):
        for i in range(nx - 1):
            if hole and i == nx // 2 - 1 and j == ny // 2 - 1:
                continue
            a, b, c, d = j * nx + i, j * nx + i + 1, (j + 1) * nx + i, (j + 1) * nx + i + 1
            tris += [[a, b, d], [a, d, c]]
    return pts, np.array(tris)


def test_cross_is_numpys_to_the_bit():
    """``mesh.cross`` (the normals', areas', Laplacian's and motion field's cross product) gives
    ``np.cross``'s values bit for bit, broadcast over stacks as ``np.cross`` does."""
    rng = np.random.default_rng(7)
    a, b = rng.normal(size=(4, 50, 3)), rng.normal(size=(50, 3))
    assert np.array_equal(cross(a, b), np.cross(a, b))
    assert np.array_equal(cross(a[0], b), np.cross(a[0], b))


def test_single_triangle_normal_area_frame():
    assert np.allclose(triangle_normals(TRI, T1), [[0, 0, 1]])
    assert np.allclose(triangle_areas(TRI, T1), [0.5])
    V = triangle_frames(TRI, T1)[0]
    assert np.allclose(V[:, 2], [0, 0, 1])          # 4th vertex: normal / sqrt(|e1 x e2|) = 1
    assert np.allclose(V[:, 0], [1, 0, 0]) and np.allclose(V[:, 1], [0, 1, 0])
    # on the unit triangle |e1 x e2| = 1, where a unit normal and Sumner's scaled one agree: legs of 2 tell
    V2 = triangle_frames(2.0 * TRI, T1)[0]
    assert np.allclose(V2[:, 2], [0, 0, 2])         # (e1 x e2) / sqrt(|e1 x e2|) = (0, 0, 4) / 2


def test_uniform_scale_gives_the_scaled_identity():
    # Sumner & Popovic's 4th vertex scales with the edges, so a uniform scale s has Q = s I exactly
    # (a unit normal would leave Q's normal column at 1, and EBFR's |Q - I| would see a stretch as less)
    R = Rotation.from_euler("xyz", [10, 40, -25], degrees=True).as_matrix()
    tri = TRI @ R.T * 0.013                         # a mm-scale triangle, not in a coordinate plane
    Q = deformation_gradients(tri, 1.7 * tri + [0.2, -0.1, 0.3], T1)
    assert np.allclose(Q[0], 1.7 * np.eye(3), atol=1e-12)


def test_known_rotation_gives_the_rotation():
    R = Rotation.from_euler("xyz", [30, -20, 75], degrees=True).as_matrix()
    Q = deformation_gradients(TRI, TRI @ R.T + [3, -1, 2], T1)
    assert np.allclose(Q[0], R, atol=1e-12)


def test_in_plane_affine_map_is_recovered():
    A = np.array([[2.0, 0.5, 0], [0.1, 0.7, 0], [0, 0, 1.0]])
    Q = deformation_gradients(TRI, TRI @ A.T, T1)[0]
    assert np.allclose(Q[:, :2], A[:, :2])          # edges map exactly


def test_degenerate_rest_triangle_raises():
    bad = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])
    with pytest.raises(GeometryError):
        deformation_gradients(bad, bad, T1)
    with pytest.raises(GeometryError, match="degenerate"):
        check_triangles(bad, T1, what="template neutral", path="x.obj")
    with pytest.raises(GeometryError):
        gradient_operator(bad, T1)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=3, max_size=3), st.lists(st.floats(-1, 1), min_size=3, max_size=3))
def test_gradient_operator_matches_frames_for_rigid_motion(angles, shift):
    pts, tris = grid(4, 4)
    pts = pts + np.random.default_rng(0).normal(0, 0.1, pts.shape)   # non-planar
    R = Rotation.from_rotvec(angles).as_matrix()
    G = gradient_operator(pts, tris)
    Q = apply_gradient(G, pts @ R.T + shift)
    E = np.stack([pts[tris[:, 1]] - pts[tris[:, 0]], pts[tris[:, 2]] - pts[tris[:, 0]]], -1)
    assert np.allclose(Q @ E, R @ E, atol=1e-9)                       # in-plane part is the rotation
    assert G.shape == (3 * len(tris), len(pts))
    assert np.allclose(G @ np.ones(len(pts)), 0)                      # translation-invariant


def test_laplacians_annihilate_linear_functions_inside():
    pts, tris = grid(6, 5)
    f = 2 * pts[:, 0] - 3 * pts[:, 1] + 1
    interior = (pts[:, 0] > 0) & (pts[:, 0] < 5) & (pts[:, 1] > 0) & (pts[:, 1] < 4)
    Lc = cotangent_laplacian(pts, tris)
    assert abs(Lc - Lc.T).max() < 1e-12
    assert np.allclose(np.asarray(Lc.sum(axis=1)).ravel(), 0)
    assert np.allclose((Lc @ f)[interior], 0, atol=1e-12)
    Lu = uniform_laplacian(tris, len(pts))
    assert np.allclose(Lu @ np.ones(len(pts)), 0)
    assert np.allclose((Lu @ f)[interior], 0, atol=1e-12)


def test_boundary_loops_outer_rim_then_hole():
    pts, tris = grid(6, 6, hole=True)
    loops = boundary_loops(tris, len(pts))
    assert [len(lp) for lp in loops] == [20, 4]
    # the loops are closed cycles of boundary edges
    hole = loops[1]
    assert set(hole.tolist()) == {14, 15, 20, 21}     # the missing cell (i=2, j=2)
    assert mesh_scale(pts, tris) > 1.0


def test_harmonic_fill_interpolates_fades_and_leaves_the_known_alone():
    """Unknown vertices of a linear field on a regular grid (each vertex the mean of its symmetric
    neighbours) are recovered exactly by the harmonic fill; screened over one edge they fade towards 0 but
    stay between 0 and the harmonic value; an unknown island touching no known vertex is 0; known vertices
    and shapes without unknowns are returned unchanged."""
    pts, tris = grid(9, 9)
    linear = 0.3 + 2.0 * pts[:, 0] - 0.5 * pts[:, 1]                    # > 0 on the grid
    values = np.stack([np.c_[linear, -linear], np.c_[linear, linear]])  # [2, 81, 2]
    unknown = np.zeros((2, 81), dtype=bool)
    inner = (np.abs(pts[:, 0] - 4) <= 1) & (np.abs(pts[:, 1] - 4) <= 1)  # a 3 x 3 patch
    unknown[0, inner] = True
    noisy = values.copy()
    noisy[0, inner] = 99.0
    out = harmonic_fill(noisy, unknown, tris)
    np.testing.assert_allclose(out, values, atol=1e-12)
    faded = harmonic_fill(noisy, unknown, tris, length=1.0)
    assert np.all(faded[0, inner, 0] > 0) and np.all(faded[0, inner, 0] < linear[inner])
    np.testing.assert_array_equal(faded[:, ~inner], values[:, ~inner])
    np.testing.assert_array_equal(faded[1], values[1])
    # the whole mesh unknown for a shape: nothing to interpolate from, 0
    everything = np.zeros((2, 81), dtype=bool)
    everything[1] = True
    np.testing.assert_array_equal(harmonic_fill(values, everything, tris)[1], 0.0)


def test_index_set_is_np_unique():
    from usdface.mesh import index_set

    rng = np.random.default_rng(3)
    t = rng.integers(0, 50, size=(40, 3))
    assert np.array_equal(index_set(t, 60), np.unique(t))
    assert index_set(np.zeros(0, dtype=np.int64), 5).size == 0


def test_cotangent_laplacian_ignores_degenerate_triangles():
    """A repeated corner or collinear corners have no area and no cotangent: the Laplacian is that of the
    mesh without them (they once put 1e300 weights into it and moved a personalized jaw by 0.4 mm)."""
    pts, tris = grid(4, 4)
    clean = cotangent_laplacian(pts, tris)
    row = np.flatnonzero(np.isclose(pts[:, 1], 0))[:3]                 # three collinear grid vertices
    dirty = np.vstack([tris, [[0, 1, 0]], [row], [[5, 5, 5]]])
    L = cotangent_laplacian(pts, dirty)
    assert abs(L - clean).max() < 1e-12


def test_display_subset_cut_to_a_box_keeps_every_vertex_of_what_it_shows():
    """A face on a head-and-body mesh (314k vertices) was decimated whole for a picture framed on the face:
    5.8 of its review page's 10.1 CPU-s went to the body, and the face lost vertices. With ``visible`` (the
    triangles that meet the view's box) the rest is dropped first; when what is left is under the limit it
    is kept whole (every vertex, the same triangles), else it alone is decimated."""
    from synthetic_meshes import grid_triangles

    from usdface.mesh import index_set, triangles_in_box

    n = 60
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 2, n))
    points = np.c_[u.ravel(), v.ravel(), 0.1 * np.sin(3 * u.ravel())]
    tris = grid_triangles(n, n)
    lo, hi = np.array([0.2, 1.7]), np.array([0.8, 1.9])              # a box on the top of the sheet
    visible = triangles_in_box(points, tris, lo, hi)
    corners = points[tris][:, :, :2]
    meets = ((corners.max(axis=1) >= lo) & (corners.min(axis=1) <= hi)).all(axis=1)
    np.testing.assert_array_equal(visible, meets)
    inside = ((corners >= lo) & (corners <= hi)).all(axis=(1, 2))
    assert inside.any() and not visible[~meets].any() and visible[inside].all()
    shown = index_set(tris[visible], len(points))
    keep, cut = display_subset(points, tris, 1000, visible=visible)          # 3,600 vertices, ~360 shown
    np.testing.assert_array_equal(keep, shown)                               # every one of them
    np.testing.assert_array_equal(keep[cut], tris[visible])                  # the same triangles
    keep, small = display_subset(points, tris, len(shown) // 2, visible=visible)   # still over: decimated
    assert len(keep) < len(shown) and np.isin(keep, shown).all() and keep[small].max() == keep.max()
    assert display_subset(points, tris, 0, visible=visible) is None           # no limit: the whole mesh
    assert display_subset(points, tris, n * n, visible=visible) is None       # under it: the whole mesh


def test_display_subset_is_a_decimated_mesh_of_the_meshs_own_vertices():
    """Pictures and the review page of a 225k-vertex head draw a decimated copy: its vertices are a subset
    of the mesh's (so any per-vertex array is drawn as ``a[keep]``), about as many as asked, and its
    triangles are valid and face the same way."""
    from synthetic_meshes import grid_triangles

    n = 50
    u, v = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n))
    points = np.c_[u.ravel(), v.ravel(), 0.2 * np.sin(2 * u.ravel()) * np.cos(v.ravel())]
    tris = grid_triangles(n, n)
    assert display_subset(points, tris, n * n) is None and display_subset(points, tris, 0) is None
    keep, small = display_subset(points, tris, 500)
    assert 300 <= len(keep) <= 600 and np.all(np.diff(keep) > 0) and keep.max() < n * n
    assert small.min() == 0 and small.max() == len(keep) - 1
    assert np.all((small[:, 0] != small[:, 1]) & (small[:, 1] != small[:, 2]) & (small[:, 0] != small[:, 2]))
    up = triangle_normals(points, tris)[:, 2].mean() > 0
    assert (np.mean(triangle_normals(points[keep], small)[:, 2] > 0) > 0.95) == up


def test_vertex_components_are_the_pieces_of_the_vertex_adjacency():
    """Two separate grids, one triangle alone and a vertex in no triangle: four pieces, labelled as
    ``connected_components`` labels the deduplicated adjacency."""
    from scipy.sparse.csgraph import connected_components
    from synthetic_meshes import grid_triangles

    from usdface.mesh import vertex_adjacency, vertex_components

    a = np.asarray(grid_triangles(5, 6))
    tri = np.concatenate([a, a + 30, [[61, 62, 60]]])                  # vertex 63 in no triangle
    count, label = vertex_components(tri, 64)
    want_count, want = connected_components(vertex_adjacency(tri, 64), directed=False)
    assert count == want_count == 4
    assert np.array_equal(label, want)
    assert len(set(label[:30])) == 1 and label[0] != label[30] and label[60] != label[63]
