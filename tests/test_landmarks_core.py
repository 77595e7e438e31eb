"""usdface.landmarks numerical core on small synthetic models (analytic / brute-force checks)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from usdface.errors import LandmarkError
from usdface.landmarks import compute_landmarks
from usdface.landmarks.baselines import delta_cluster_layout, pca_kmeans_layout, random_layout
from usdface.landmarks.candidates import candidate_sets, relative_displacement
from usdface.landmarks.cover import reduce_set_cover, set_cover_costs, solve_set_cover
from usdface.landmarks.layout import lazy_costs
from usdface.landmarks.multicover import shapes_needing_landmarks
from usdface.landmarks.reconstruct import layout_error, solve_weights, tracked_landmarks
from usdface.landmarks.symmetry import mirror_pairs
from usdface.landmarks.visibility import PoseVisibility, ambient_visibility, camera_visibility
from usdface.model import FaceRig

# ----------------------------------------------------------------------------------------------------------
# synthetic models
# ----------------------------------------------------------------------------------------------------------
NX, NY = 21, 15


def grid_mesh(nx: int = NX, ny: int = NY, width: float = 0.1, height: float = 0.08):
    """A gently curved sheet facing +Z, bitwise symmetric about x = 0: (points[n, 3] metres, triangles)."""
    xs = np.linspace(-width / 2, width / 2, nx)
    xs = np.where(np.arange(nx) >= nx // 2, -xs[::-1], xs)
    ys = np.linspace(0.0, height, ny)
    x, y = np.meshgrid(xs, ys)
    z = 0.02 * np.exp(-(x**2) / 0.002)
    points = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1))
    a = (j * nx + i).ravel()
    tri = np.concatenate([np.stack([a, a + 1, a + nx + 1], 1), np.stack([a, a + nx + 1, a + nx], 1)])
    return points, tri


def bump(points, centre, sigma=0.01, amplitude=0.004):
    """Offsets [n, 3] of a Gaussian bump along +Z (metres)."""
    d2 = ((points[:, :2] - np.asarray(centre)[None, :]) ** 2).sum(axis=1)
    out = np.zeros_like(points)
    out[:, 2] = amplitude * np.exp(-d2 / (2 * sigma**2))
    return out


def symmetric_rig():
    """Left/right bump pairs (mirrored exactly) plus mid-line bumps."""
    points, tri = grid_mesh()
    names, deltas = [], []
    for i, (x, y) in enumerate(((0.03, 0.02), (0.025, 0.06), (0.015, 0.04))):
        right = bump(points, (-x, y))
        names += [f"shape{i}Right", f"shape{i}Left"]
        deltas += [right, right.reshape(NY, NX, 3)[:, ::-1].reshape(-1, 3)]
    for i, c in enumerate(((0.0, 0.01), (0.0, 0.07))):
        names.append(f"mid{i}")
        deltas.append(bump(points, c))
    return FaceRig(points, tri, names, np.array(deltas), name="Sheet")


def random_rig(n_shapes: int = 30, seed: int = 0, nx: int = 41, ny: int = 31):
    """Many random bumps of random size and strength."""
    points, tri = grid_mesh(nx, ny)
    rng = np.random.default_rng(seed)
    deltas = [bump(points, (rng.uniform(-0.05, 0.05), rng.uniform(0.0, 0.08)), rng.uniform(0.004, 0.02),
                   rng.uniform(0.001, 0.01)) for _ in range(n_shapes)]
    return FaceRig(points, tri, [f"s{k}" for k in range(n_shapes)], np.array(deltas), name="Sheet")


# ----------------------------------------------------------------------------------------------------------
# candidates (eqs. 2-3)
# ----------------------------------------------------------------------------------------------------------
def test_relative_displacement_and_candidates_analytic():
    mags = np.array([[0.0, 1.0, 2.0, 4.0], [3.0, 3.0, 0.0, 1.5]])
    r = relative_displacement(mags)
    np.testing.assert_allclose(r, [[0, 0.25, 0.5, 1.0], [1.0, 1.0, 0, 0.5]])
    c = candidate_sets(r, 0.5)
    assert c.tolist() == [[False, False, True, True], [True, True, False, True]]
    assert candidate_sets(r, 1.0).sum(axis=1).tolist() == [1, 2]  # eq. 3 uses >=: the peak stays


@pytest.mark.parametrize("eps", [0.0, -0.1, 1.01, float("nan"), "x"])
def test_epsilon_outside_unit_interval_raises(eps):
    with pytest.raises(LandmarkError, match="epsilon") as info:
        compute_landmarks(symmetric_rig(), epsilon=eps, rays=4)
    assert "fix:" in str(info.value)


def test_rig_without_shapes_raises():
    points, tri = grid_mesh()
    rig = FaceRig(points, tri, [], np.zeros((0, len(points), 3)), name="Bare")
    with pytest.raises(LandmarkError, match="no blend shapes"):
        compute_landmarks(rig)


def test_static_shape_raises_or_is_reported():
    rig = symmetric_rig()
    rig = FaceRig(rig.neutral, rig.triangles, rig.names + ["still"],
                  np.concatenate([rig.deltas, np.zeros((1, rig.n_vertices, 3))]), name="Sheet")
    with pytest.raises(LandmarkError, match="still") as info:
        compute_landmarks(rig, rays=4)
    assert "--skip-static" in str(info.value)
    layout = compute_landmarks(rig, rays=4, ignore_static=True)
    assert layout.uncoverable == ["still"] and any("still" in w for w in layout.warnings)


# ----------------------------------------------------------------------------------------------------------
# set cover (eq. 5): reduction keeps the optimum; every backend proves it
# ----------------------------------------------------------------------------------------------------------
def brute_force(c, cost):
    best = np.inf
    n = c.shape[1]
    coverable = c.any(axis=1)
    for m in range(n + 1):
        for sub in itertools.combinations(range(n), m):
            if c[:, list(sub)].any(axis=1)[coverable].all() if sub else not coverable.any():
                best = min(best, cost[list(sub)].sum())
    return best


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000))
def test_reduced_cover_is_optimal_vs_brute_force(seed):
    rng = np.random.default_rng(seed)
    k, n = rng.integers(1, 7), rng.integers(1, 10)
    c = rng.random((k, n)) < rng.uniform(0.15, 0.6)
    cost = rng.choice([1.0, 1.0, 1.5, 2.0], size=n) + rng.random(n) * 0.01
    sol = solve_set_cover(c, cost)
    assert sol.status == "optimal" and sol.gap == 0.0
    assert sol.objective == pytest.approx(brute_force(c, cost), abs=1e-9)
    coverable = c.any(axis=1)
    assert c[:, sol.selected].any(axis=1)[coverable].all()
    assert set(sol.uncovered.tolist()) == set(np.flatnonzero(~coverable).tolist())
    rows, cols = reduce_set_cover(c, cost)
    assert rows.size <= coverable.sum() and cols.size <= n


@pytest.mark.parametrize("backend", ["scip", "cbc", "highs"])
def test_backends_agree(backend):
    rig = random_rig(20, seed=3)
    c = candidate_sets(relative_displacement(np.linalg.norm(rig.deltas, axis=2)), 0.5)
    cost = set_cover_costs(c, np.ones(c.shape), "count")
    ref = solve_set_cover(c, cost, backend="scip")
    sol = solve_set_cover(c, cost, backend=backend)
    assert sol.status == "optimal" and sol.objective == pytest.approx(ref.objective)


def test_quality_costs_never_trade_a_landmark_for_quality():
    """``"quality"``'s tie-break stays below one landmark: two poor landmarks (quality 0, 0.5) that cover four
    shapes beat three perfect ones, and among the two-landmark covers the better one wins (a quality term as
    large as a landmark, delta = 1, chose the three)."""
    c = np.zeros((4, 6), dtype=bool)
    c[[0, 1], 0] = c[[2, 3], 1] = True                     # two poor columns cover everything
    c[0, 2] = c[[1, 2], 3] = c[3, 4] = True                # three perfect ones too
    c[[0, 1], 5] = True                                    # a better twin of column 0
    q = np.where(c, 1.0, 0.0)
    q[:, :2], q[[0, 1], 5] = 0.0, 0.5
    sol = solve_set_cover(c, set_cover_costs(c, q, "quality"))
    assert sol.status == "optimal" and sol.selected.tolist() == [1, 5]
    assert len(solve_set_cover(c, set_cover_costs(c, q, "count")).selected) == 2


def test_quality_weighting_keeps_the_minimum_count():
    rig = random_rig(30, seed=1)
    counts = {w: compute_landmarks(rig, 0.5, weighting=w, rays=8).count
              for w in ("count", "quality", "paper")}
    assert counts["quality"] == counts["count"]  # count first, quality only breaks ties
    assert counts["paper"] >= counts["count"]


def test_lazy_visibility_gives_the_fully_evaluated_costs_optimum():
    rig = random_rig(25, seed=2)
    r = relative_displacement(np.linalg.norm(rig.deltas, axis=2))
    c = candidate_sets(r, 0.4)
    pv = PoseVisibility(rig.neutral, rig.triangles, rig.deltas, rays=8)
    full = set_cover_costs(c, 0.5 * r + 0.5 * pv()[None, :], "quality")
    lazy_pv = PoseVisibility(rig.neutral, rig.triangles, rig.deltas, rays=8)
    lazy = lazy_costs(c, r, 0.5, "quality", None, lambda: lazy_pv.values, lazy_pv)
    assert np.isnan(lazy_pv.values).sum() > 0  # some vertices were never ray cast ...
    a, b = solve_set_cover(c, full), solve_set_cover(c, lazy)
    assert a.objective == pytest.approx(b.objective, abs=1e-12)  # ... and the optimum is the same
    assert a.selected.tolist() == b.selected.tolist()
    # with the neutral visibility as an upper bound, fewer vertices are cast, the optimum is still the same
    bound_pv = PoseVisibility(rig.neutral, rig.triangles, rig.deltas, rays=8)
    bounded = lazy_costs(c, r, 0.5, "quality", None, lambda: bound_pv.values, bound_pv,
                         upper=bound_pv.upper_bound)
    assert np.count_nonzero(~np.isnan(bound_pv.values)) <= np.count_nonzero(~np.isnan(lazy_pv.values))
    d = solve_set_cover(c, bounded)
    assert d.objective == pytest.approx(a.objective, abs=1e-12) and d.selected.tolist() == a.selected.tolist()


# ----------------------------------------------------------------------------------------------------------
# the whole method
# ----------------------------------------------------------------------------------------------------------
def test_every_shape_covered_optimal_and_deterministic():
    rig = random_rig(30, seed=4)
    a = compute_landmarks(rig, 0.5, rays=8)
    b = compute_landmarks(rig, 0.5, rays=8)
    assert a.status == "optimal" and a.gap == 0.0
    assert a.coverage.any(axis=0).all() and a.uncoverable == []
    assert a.vertices.tolist() == b.vertices.tolist()
    np.testing.assert_array_equal(a.visibility, b.visibility)
    assert a.count < rig.n_shapes  # merging: fewer landmarks than shapes


def test_symmetric_layout_is_exactly_symmetric():
    rig = symmetric_rig()
    partner = mirror_pairs(rig.neutral)
    assert (partner >= 0).all()
    for multicover in (1, 3):
        layout = compute_landmarks(rig, 0.6, symmetric=True, multicover=multicover, radius=0.008, rays=8)
        assert layout.symmetric and not layout.warnings
        assert set(partner[layout.vertices].tolist()) == set(layout.vertices.tolist())
        mirrored = layout.positions * [-1, 1, 1]
        assert np.abs(np.sort(mirrored, axis=0) - np.sort(layout.positions, axis=0)).max() < 1e-12
        assert layout.coverage.any(axis=0).all()


def test_a_camera_warning_leaves_a_symmetric_layout_symmetric():
    """``layout.symmetric`` said False (and the layer's ``usdface:landmarks:symmetric`` too) for an exactly
    symmetric layout whenever any warning was given, such as the far camera's, not only the fallback's."""
    rig = symmetric_rig()
    partner = mirror_pairs(rig.neutral)
    layout = compute_landmarks(rig, 0.6, symmetric=True, camera=[0.0, 0.04, 30.0])
    assert any("from afar" in w for w in layout.warnings)
    assert set(partner[layout.vertices].tolist()) == set(layout.vertices.tolist())
    assert layout.symmetric


def test_infeasible_symmetric_problem_falls_back_and_says_so():
    rig = symmetric_rig()
    # a shape that moves only the top right corner, whose mirror image is cut off the mesh
    x, y = rig.neutral[:, 0], rig.neutral[:, 1]
    keep = ~((x < -0.04) & (y > 0.055))
    index = np.cumsum(keep) - 1
    tri = rig.triangles[keep[rig.triangles].all(axis=1)]
    edge = bump(rig.neutral, (0.05, 0.08), sigma=0.002)
    deltas = np.concatenate([rig.deltas, edge[None]])[:, keep]
    cut = FaceRig(rig.neutral[keep], index[tri], rig.names + ["edge"], deltas, name="Cut")
    layout = compute_landmarks(cut, 0.9, symmetric=True, rays=4)
    assert not layout.symmetric
    assert any("fell back" in w and "edge" in w for w in layout.warnings)
    assert layout.coverage.any(axis=0).all()


def test_multicover_adds_landmarks_outside_the_radius():
    rig = random_rig(30, seed=5)
    one = compute_landmarks(rig, 0.5, rays=4)
    more = compute_landmarks(rig, 0.5, multicover=3, adaptive=False, radius=0.01, rays=4)
    assert more.count > one.count and more.rounds.max() > 1
    assert set(one.vertices.tolist()) <= set(more.vertices.tolist())  # round 1 is the single cover
    first, later = more.positions[more.rounds == 1], more.positions[more.rounds > 1]
    d = np.linalg.norm(later[:, None] - first[None], axis=2)
    assert d.min() > 0.01 - 1e-12


def test_ten_percent_heuristic_marks_overloaded_shapes():
    # 20 shapes; landmark 0 serves shapes 0-9 (50%), landmark 1 serves shape 10 only
    c = np.zeros((20, 3), dtype=bool)
    c[:10, 0] = True
    c[10, 1] = True
    c[11:, 2] = True
    need = shapes_needing_landmarks(c, np.array([0, 1]), max_per_shape=5, share=0.1)
    assert need[:10].all() and not need[10]
    assert not shapes_needing_landmarks(c, np.array([0, 1]), max_per_shape=1, share=0.1)[:11].any()


def test_known_camera_excludes_hidden_vertices():
    rig = random_rig(10, seed=6)
    behind = compute_landmarks(rig, 0.5, camera=[0.0, 0.04, -1.0], rays=4)  # camera behind the sheet
    assert behind.count == 0 and len(behind.uncoverable) == rig.n_shapes
    front = compute_landmarks(rig, 0.5, camera=[0.0, 0.04, 1.0], rays=4)
    assert front.uncoverable == [] and (front.visibility == 1.0).all()


# ----------------------------------------------------------------------------------------------------------
# visibility (eq. 4)
# ----------------------------------------------------------------------------------------------------------
def test_ambient_visibility_open_sheet_and_covered_vertex():
    points, tri = grid_mesh(11, 11)
    points[:, 2] = 0.0
    assert np.allclose(ambient_visibility(points, tri, rays=32), 1.0)
    roof = points.copy()
    roof[:, 2] = 0.01
    both = np.concatenate([points, roof])
    l_open = ambient_visibility(both, np.concatenate([tri, tri + len(points)]), [len(points) + 60], 32)
    l_under = ambient_visibility(both, np.concatenate([tri, tri + len(points)]), [60], 32)
    assert l_open[0] == 1.0 and l_under[0] < 0.5  # centre vertex under a 10 x 10 cm roof 1 cm up


def test_camera_visibility_facing_and_occlusion():
    points, tri = grid_mesh(11, 11)
    points[:, 2] = 0.0
    assert camera_visibility(points, tri, [0, 0.04, 1.0]).min() == 1.0
    assert camera_visibility(points, tri, [0, 0.04, -1.0]).max() == 0.0


def _brute_pose_visibility(points, tri, offset, rays=16, camera=None):
    """Eq. 4 for one pose by the definition: a scene of the whole posed mesh, every ray cast (``offset``:
    the ray start offset, the neutral's in PoseVisibility)."""
    import open3d as o3d

    from usdface.landmarks.visibility import _camera_rays, _hemisphere_rays
    from usdface.mesh import vertex_normals

    n = vertex_normals(points, tri)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(points.astype(np.float32)), o3d.core.Tensor(tri.astype(np.uint32)))
    valid = np.linalg.norm(n, axis=1) > 0
    if camera is None:
        hit = scene.test_occlusions(o3d.core.Tensor(_hemisphere_rays(points, n, offset, rays)))
        return np.where(valid, 1.0 - hit.numpy().astype(bool).reshape(-1, rays).mean(axis=1), 0.0)
    r, facing = _camera_rays(points, n, offset, camera)
    hit = scene.test_occlusions(o3d.core.Tensor(r), tfar=1.0).numpy().astype(bool)
    return np.where(valid, (facing & ~hit).astype(float), 0.0)


@pytest.mark.parametrize("strategy", ["full", "union", "auto"])
@pytest.mark.parametrize("camera", [None, [0.3, 0.04, 0.06]])
def test_pose_shortcut_equals_brute_force_minimum(camera, strategy):
    rig = random_rig(15, seed=9)
    rig.neutral[:, 2] += 0.03 * np.sin(60 * rig.neutral[:, 0])  # ripples: real self-occlusion
    pv = PoseVisibility(rig.neutral, rig.triangles, rig.deltas, rays=16, camera=camera)
    pv.strategy = strategy
    half = np.arange(0, rig.n_vertices, 2)
    first = pv(half)  # two calls (lazy callers), the second reusing the kept scenes
    fast = pv()
    np.testing.assert_array_equal(fast[half], first)
    poses = [rig.neutral] + [rig.neutral + d for d in rig.deltas]
    off = pv.offset
    brute = np.min([_brute_pose_visibility(p, rig.triangles, off, 16, camera) for p in poses], axis=0)
    assert 0.2 < (fast < 1).mean() < 1.0
    np.testing.assert_array_equal(fast, brute)
    # the neutral visibility bounds l from above and is what the neutral pose alone gives
    upper = PoseVisibility(rig.neutral, rig.triangles, rig.deltas, rays=16, camera=camera).upper_bound()
    np.testing.assert_array_equal(upper, _brute_pose_visibility(rig.neutral, rig.triangles, off, 16, camera))
    assert (upper >= fast).all() and (upper > fast).any()


def test_global_visibility_is_the_minimum_over_poses():
    points, tri = grid_mesh(11, 11)
    points[:, 2] = 0.0
    # one shape lifts a far corner into a wall over the centre vertex (60)
    wall = np.zeros_like(points)
    wall[:, 2] = np.where(points[:, 0] > 0.02, 0.05, 0.0)
    l = PoseVisibility(points, tri, wall[None], rays=32)([60])
    assert l[0] < 1.0
    assert PoseVisibility(points, tri, np.zeros((1,) + points.shape), rays=32)([60])[0] == 1.0


# ----------------------------------------------------------------------------------------------------------
# reconstruction and baselines
# ----------------------------------------------------------------------------------------------------------
def test_weights_recovered_exactly_without_noise():
    rig = random_rig(12, seed=7)
    layout = compute_landmarks(rig, 0.5, multicover=3, adaptive=False, radius=0.005, rays=4)
    w = np.random.default_rng(0).uniform(0, 1, (5, rig.n_shapes))
    pos = tracked_landmarks(rig.neutral, rig.deltas, layout.vertices, w)
    est = solve_weights(rig.deltas[:, layout.vertices], pos - rig.neutral[layout.vertices][None])
    np.testing.assert_allclose(est, w, atol=1e-6)
    assert layout_error(rig.neutral, rig.deltas, layout.vertices, w, noise=0.0) < 1e-9
    noisy = layout_error(rig.neutral, rig.deltas, layout.vertices, w, noise=0.5e-3)
    assert 0 < noisy < 0.5e-3


def test_weights_respect_bounds_and_tikhonov_shrinks():
    d = np.zeros((2, 1, 3))
    d[0, 0, 0] = 1.0
    d[1, 0, 1] = 1.0
    est = solve_weights(d, np.array([[[2.0, -1.0, 0.0]]]))
    np.testing.assert_allclose(est, [[1.0, 0.0]], atol=1e-12)
    shrunk = solve_weights(d, np.array([[[0.5, 0.5, 0.0]]]), tikhonov=1.0)
    np.testing.assert_allclose(shrunk, [[0.25, 0.25]], atol=1e-9)


def test_baselines_count_and_determinism():
    rig = random_rig(15, seed=8)
    for fn in (pca_kmeans_layout, delta_cluster_layout, random_layout):
        a, b = fn(rig.deltas, 12, seed=1), fn(rig.deltas, 12, seed=1)
        assert a.tolist() == b.tolist() and 1 <= a.size <= 12
        assert len(set(a.tolist())) == a.size
    assert random_layout(rig.deltas, 12, seed=1).size == 12


def test_landmark_quality_weighs_visibility_by_alpha_as_the_paper():
    """Zell & McDonnell eq. 1: q = (1 - alpha) r + alpha l (alpha weighs the visibility)."""
    from usdface.landmarks.candidates import landmark_quality

    r = np.array([[1.0, 0.0]])
    vis = np.array([0.0, 1.0])
    assert np.allclose(landmark_quality(r, vis, 0.2), [[0.8, 0.2]])
    assert np.allclose(landmark_quality(r, vis, 1.0), [[0.0, 1.0]])


def asymmetric_head(n_lon: int = 96, n_lat: int = 60):
    """A head-like surface (ellipsoid open at the crown and neck, a nose, eye sockets, cheeks, ears) bitwise
    mirror-symmetric about x = 0, then made asymmetric as a scan is: a smooth non-rigid warp of a few mm on
    one cheek, the symmetry plane tilted (4 degrees about Y, 3 about Z) and shifted by a centimetre.
    Returns (symmetric points[n, 3], warped points[n, 3], triangles[t, 3], true partner[n]) in metres."""
    phi = 2 * np.pi * np.arange(n_lon) / n_lon
    th, ph = np.meshgrid(np.linspace(0.1 * np.pi, 0.75 * np.pi, n_lat), phi, indexing="ij")
    s, c = np.sin(ph), np.cos(ph)                      # bitwise mirrored: column k <-> column -k
    s[:, n_lon // 2 + 1:] = -s[:, 1:n_lon // 2][:, ::-1]
    s[:, [0, n_lon // 2]] = 0.0
    c[:, n_lon // 2 + 1:] = c[:, 1:n_lon // 2][:, ::-1]
    x, y = 0.072 * np.sin(th) * s, 0.117 * np.cos(th)
    z = 0.09 * np.sin(th) * c * np.where(c > 0, 1.1, 0.7)
    z = z + 0.02 * np.exp(-(x**2 + (y + 0.01) ** 2) / (2 * 0.012**2)) * (z > 0)     # nose
    front = z > 0
    for cx, cy, amp, width in ((0.035, 0.03, -0.012, 0.012), (0.03, -0.06, 0.008, 0.015)):
        for sx in (cx, -cx):                                                        # eye sockets, cheeks
            z = z + amp * np.exp(-((x - sx) ** 2 + (y - cy) ** 2) / (2 * width**2)) * front
    x = x + 0.015 * np.sign(x) * np.exp(-(y**2 + z**2) / (2 * 0.015**2))             # ears
    points = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    i, k = np.meshgrid(np.arange(n_lat - 1), np.arange(n_lon), indexing="ij")
    a, b = (i * n_lon + k).ravel(), (i * n_lon + (k + 1) % n_lon).ravel()
    tri = np.concatenate([np.stack([a, b, b + n_lon], 1), np.stack([a, b + n_lon, a + n_lon], 1)])
    lat, lon = np.divmod(np.arange(len(points)), n_lon)
    truth = lat * n_lon + (-lon) % n_lon
    bulge = np.exp(-((points - [0.05, 0.0, 0.05]) ** 2).sum(axis=1) / (2 * 0.03**2))   # one cheek, 4 mm
    warp = bulge[:, None] * [3e-3, 1.5e-3, 2e-3]
    ay, az = np.radians(4.0), np.radians(3.0)
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    warped = (points + warp) @ (rz @ ry).T + [0.01, -0.005, 0.002]
    return points, warped, tri, truth


def test_mirror_pairs_of_a_scanned_asymmetric_head():
    """A head whose symmetry plane is tilted and shifted and whose one cheek is warped by a few mm (as a
    scan is) still pairs >= 95 % of its vertices, each with its true mirror vertex or one within a vertex
    spacing of it (the plain reflection across x = median paired about a quarter)."""
    from usdface.landmarks.symmetry import mirror_map

    points, warped, _, truth = asymmetric_head()
    assert np.array_equal(mirror_pairs(points), truth)                 # the symmetric head: exactly
    partner = mirror_pairs(warped)
    paired = partner >= 0
    assert paired.mean() >= 0.95
    assert np.array_equal(partner[partner[paired]], np.flatnonzero(paired))     # an involution
    spacing = cKDTree(warped).query(warped, k=2)[0][:, 1]
    off = np.linalg.norm(warped[partner[paired]] - warped[truth[paired]], axis=1)
    assert (off <= spacing[paired] + 1e-12).all()
    image = mirror_map(warped)                                         # the fitted symmetry itself
    assert np.median(np.linalg.norm(image - warped[truth], axis=1)) < 0.1 * np.median(spacing)


@pytest.mark.parametrize("perm", [[0, 1, 2], [1, 2, 0], [2, 0, 1]])
def test_symmetric_layout_on_a_scanned_asymmetric_head(perm):
    """--symmetric on the warped head gives a symmetric layout (no fallback) whose left and right landmarks
    are mirror pairs: each landmark's partner in the layout within a vertex spacing of its true mirror.
    Whatever axis the head's left-right is along (issue 13: the mirror axis detected from the rig, not fixed
    to X): the coordinates turned so that it lies along X, Z or Y."""
    points, warped, tri, truth = asymmetric_head()
    names, deltas = [], []
    for i, centre in enumerate(((0.03, -0.05), (0.035, 0.045), (0.02, -0.085))):
        d2 = ((points[:, :2] - [-centre[0], centre[1]]) ** 2).sum(axis=1)
        right = np.zeros_like(points)
        right[:, 2] = 0.004 * np.exp(-d2 / (2 * 0.01**2)) * (points[:, 2] > 0)
        names += [f"shape{i}Right", f"shape{i}Left"]
        deltas += [right, right[truth] * [-1, 1, 1]]
    names.append("mid")
    deltas.append(bump(points, (0.0, -0.09)) * (points[:, 2] > 0)[:, None])
    warped = warped[:, perm]                      # an even permutation: a rotation, the same orientation
    rig = FaceRig(warped, tri, names, np.array(deltas)[:, :, perm], name="Head")
    layout = compute_landmarks(rig, 0.6, symmetric=True, rays=4)
    assert layout.symmetric and not layout.warnings and layout.coverage.any(axis=0).all()
    partner = mirror_pairs(warped)
    v = layout.vertices
    assert set(partner[v].tolist()) == set(v.tolist())
    spacing = cKDTree(warped).query(warped, k=2)[0][:, 1]
    assert (np.linalg.norm(warped[partner[v]] - warped[truth[v]], axis=1) <= spacing[v] + 1e-12).all()
    assert (v != partner[v]).any()                                     # some landmarks are left/right pairs


def test_mirror_axis_is_detected_from_the_mesh():
    """A left-right symmetric point set mirrored across y (or z) is paired across that axis."""
    from usdface.landmarks.symmetry import mirror_axis, mirror_pairs, primary_side

    rng = np.random.default_rng(0)
    half = rng.uniform([0.01, -0.1, -0.05], [0.08, 0.1, 0.05], size=(60, 3))
    pts = np.vstack([half, half * [-1, 1, 1], rng.uniform([0, -0.1, -0.05], [0, 0.1, 0.05], size=(4, 3))])
    for axis in (0, 1, 2):
        p = np.roll(pts, axis, axis=1)                    # the mirror axis moves to `axis`
        assert mirror_axis(p) == axis
        partner = mirror_pairs(p)
        assert np.array_equal(partner[:60], np.arange(60, 120))
        assert primary_side(p, partner)[:120].sum() == 60


def test_multicover_radius_scales_with_the_face():
    """The default exclusion radius (issue 13: "relative to the face size") is the same share of the face
    whatever the rig's size, epsilon or symmetric mode: a rig twice as large gets the same multi-cover layout,
    and the radius the layout used scales with it (it was an absolute 0.01 m in ``compute_landmarks`` and
    the CLI, and 5 % of the box around the epsilon's candidates in ``adaptive_multicover``)."""
    rig = random_rig(30, seed=5)
    big = FaceRig(rig.neutral * 2.0, rig.triangles, rig.names, rig.deltas * 2.0, name="Sheet")
    kw = dict(multicover=3, adaptive=False, weighting="count")
    a, b = compute_landmarks(rig, 0.5, **kw), compute_landmarks(big, 0.5, **kw)
    assert a.rounds.max() > 1 and a.vertices.tolist() == b.vertices.tolist()
    from usdface.landmarks.multicover import RADIUS_SHARE
    from usdface.landmarks.visibility import face_size

    assert np.isclose(b.problem["radius"], 2.0 * a.problem["radius"])
    moving = np.linalg.norm(rig.deltas, axis=2)
    share = (moving / moving.max(axis=1, keepdims=True)).max(axis=0)
    assert np.isclose(a.problem["radius"], RADIUS_SHARE * face_size(rig.neutral, share))
    # the face, not the candidates: the same radius at every epsilon and in symmetric mode
    sym = symmetric_rig()
    radii = {compute_landmarks(sym, eps, symmetric=s, multicover=2, rays=4).problem["radius"]
             for eps in (0.5, 0.9) for s in (False, True)}
    assert len(radii) == 1
    # an explicit radius is used as given (metres)
    assert compute_landmarks(rig, 0.5, radius=0.004, **kw).problem["radius"] == 0.004


def test_one_shot_multicover_is_the_optimal_n_fold_cover():
    """Every shape gets min(N, |C_k|) landmarks, at the least total cost (brute force on a tiny problem)."""
    from usdface.landmarks.multicover import one_shot_multicover

    rng = np.random.default_rng(3)
    c = rng.uniform(size=(5, 9)) < 0.45
    c[4] = False                                               # a shape without candidates
    cost = rng.uniform(1.0, 2.0, size=9)
    sol = one_shot_multicover(c, cost, 2)
    assert sol.status == "optimal" and sol.uncovered.tolist() == [4]
    need = np.minimum(2, c.sum(axis=1))
    assert np.all(c[:, sol.selected].sum(axis=1) >= need)
    best = min(cost[list(s)].sum() for r in range(10) for s in itertools.combinations(range(9), r)
               if np.all(c[:, list(s)].sum(axis=1) >= need))
    assert np.isclose(cost[sol.selected].sum(), best)


@pytest.mark.parametrize("symmetric", [False, True])
def test_one_shot_layout_covers_every_shape_n_times_with_the_fewest_landmarks(symmetric):
    """Issue 13's one-shot ILP multi-cover, reachable from ``compute_landmarks(one_shot=True)`` (the CLI's
    ``--one-shot``), not only as a function of the candidate matrix: every shape represented by
    ``min(N, |C_k|)`` landmarks, in one round, by as few landmarks as the N-fold cover of the same
    candidates needs (the quality weighting's count still dominates at N = 3: its delta is 1 / (2 N K + 1));
    symmetric layouts stay exactly mirrored."""
    rig = symmetric_rig() if symmetric else random_rig(30, seed=5)
    n = 3
    lay = compute_landmarks(rig, 0.5, multicover=n, one_shot=True, symmetric=symmetric, rays=4)
    assert lay.status == "optimal" and (lay.rounds == 1).all() and lay.problem["one_shot"]
    assert lay.problem["radius"] is None and lay.symmetric == symmetric
    counted = compute_landmarks(rig, 0.5, multicover=n, one_shot=True, symmetric=symmetric,
                                weighting="count")
    assert lay.count == counted.count
    if symmetric:
        partner = mirror_pairs(rig.neutral)
        assert set(partner[lay.vertices].tolist()) == set(lay.vertices.tolist())
        assert lay.coverage.any(axis=0).all()
        return
    c = candidate_sets(relative_displacement(np.linalg.norm(rig.deltas, axis=2)), 0.5)
    assert (lay.coverage.sum(axis=0) >= np.minimum(n, c.sum(axis=1))).all()
    best = solve_set_cover(c, np.ones(c.shape[1]), cover_times=n, reduce=False)
    assert lay.count == best.selected.size
    with pytest.raises(LandmarkError, match="one_shot takes no radius"):
        compute_landmarks(rig, 0.5, multicover=n, one_shot=True, radius=0.01)


def test_one_shot_layout_is_the_one_with_every_visibility_known():
    """The lazy visibility keeps one vertex per candidate set (the single cover's reduction); the one-shot
    multi-cover may take several, so every candidate is ray cast first: the layout is the one computed from
    the visibility known at every vertex (with the skin samples off, ``spacing=None``, where nothing else
    casts them all)."""
    rig = random_rig(30, seed=5)
    kw = dict(multicover=3, one_shot=True, spacing=None)
    lay = compute_landmarks(rig, 0.5, rays=4, **kw)
    assert lay.problem["visibility_evaluated"] >= lay.problem["candidates"]
    known = PoseVisibility(rig.neutral, rig.triangles, rig.deltas, 4)()
    full = compute_landmarks(rig, 0.5, visibility=known, **kw)
    assert lay.vertices.tolist() == full.vertices.tolist()
    np.testing.assert_allclose(lay.objective, full.objective, rtol=1e-9)


def test_symmetric_one_shot_counts_landmarks_not_mirror_pairs():
    """The symmetric one-shot multi-cover asks every shape for ``min(N, |C_k|)`` landmarks, as the adaptive
    rounds count them (``coverage``), not for N mirrored pairs: a pair whose two vertices both serve a
    shape is two of its landmarks. A shape moving both cheeks (no mid-line candidate) took two pairs, four
    landmarks, at N = 2 (the sample head: 38 landmarks at N = 3 where 35 cover every shape three times). So
    no pair (or mid-line vertex) of the layout can be left out without some shape falling below its count."""
    base = symmetric_rig()
    cheeks = bump(base.neutral, (-0.035, 0.075), 0.006) + bump(base.neutral, (0.035, 0.075), 0.006)
    rig = FaceRig(base.neutral, base.triangles, [*base.names, "cheeks"], np.concatenate([base.deltas,
                                                                                      cheeks[None]]),
                  name="Sheet")
    partner = mirror_pairs(rig.neutral)
    n = 2
    c = candidate_sets(relative_displacement(np.linalg.norm(rig.deltas, axis=2)), 0.5)
    need = np.minimum(n, c.sum(axis=1))
    for weighting in ("count", "quality"):
        lay = compute_landmarks(rig, 0.5, multicover=n, one_shot=True, symmetric=True, rays=4,
                                weighting=weighting)
        assert lay.symmetric and set(partner[lay.vertices].tolist()) == set(lay.vertices.tolist())
        assert (c[:, lay.vertices].sum(axis=1) >= need).all()
        for v in lay.vertices:                # irredundant: every pair is needed by some shape
            kept = np.setdiff1d(lay.vertices, [v, partner[v]])
            assert (c[:, kept].sum(axis=1) < need).any(), (weighting, v)


def test_batched_box_least_squares_matches_bvls():
    from scipy.optimize import lsq_linear

    from usdface.bounded_lsq import box_least_squares

    rng = np.random.default_rng(3)
    for m in (5, 9, 16):  # 15-48 rows, 12 unknowns: full column rank
        a = rng.normal(size=(3 * m, 12))
        rhs = rng.uniform(-0.5, 1.5, (40, 12)) @ a.T + 0.1 * rng.normal(size=(40, 3 * m))
        start = np.linalg.lstsq(a, rhs.T, rcond=None)[0].T
        w, converged = box_least_squares(a.T @ a, rhs @ a, 0.0, 1.0, start)
        ref = np.array([lsq_linear(a, r, bounds=(0.0, 1.0), method="bvls").x for r in rhs])
        assert converged.all() and ((w == 0.0) | (w == 1.0)).any()  # bounds really active
        np.testing.assert_allclose(w, ref, atol=1e-10)
    # rank-deficient (9 coordinates, 12 shapes): an optimum (BVLS's objective), of no larger norm than BVLS's
    d = rng.normal(size=(12, 3, 3))
    b = rng.uniform(0.2, 0.8, (6, 12)) @ d.reshape(12, 9) + 0.3 * rng.normal(size=(6, 9))
    a = d.reshape(12, 9).T
    ref = np.array([lsq_linear(a, r, bounds=(0.0, 1.0), method="bvls").x for r in b])
    w = solve_weights(d, b.reshape(6, 3, 3))
    assert ((w >= 0.0) & (w <= 1.0)).all()

    def objective(x):
        return ((x @ a.T - b) ** 2).sum(axis=1)

    np.testing.assert_allclose(objective(w), objective(ref), rtol=1e-6, atol=1e-12)
    assert (np.linalg.norm(w, axis=1) <= np.linalg.norm(ref, axis=1) + 1e-6).all()


def test_solve_weights_admm_start_reaches_the_bvls_optimum():
    """The ADMM warm start only picks the active set: the weights are BVLS's optimum, for every frame."""
    from scipy.optimize import lsq_linear

    from usdface.bounded_lsq import admm_box_start

    rng = np.random.default_rng(7)
    d = rng.normal(size=(12, 8, 3))  # 24 coordinates, 12 shapes: full column rank
    a = d.reshape(12, 24).T
    b = rng.uniform(-0.6, 1.6, (50, 12)) @ a.T + 0.2 * rng.normal(size=(50, 24))
    w = solve_weights(d, b.reshape(50, 8, 3))
    ref = np.array([lsq_linear(a, r, bounds=(0.0, 1.0), method="bvls").x for r in b])
    assert ((ref == 0.0) | (ref == 1.0)).sum() > 100  # many active bounds
    np.testing.assert_allclose(w, ref, atol=1e-10)
    start = admm_box_start(a.T @ a, b @ a, 0.0, 1.0, np.linalg.lstsq(a, b.T, rcond=None)[0].T)
    assert ((start >= 0.0) & (start <= 1.0)).all()
    assert np.mean((start <= 0.0) | (start >= 1.0)) > 0.3  # the bounds it found are exactly on them


def test_ray_offset_is_physical_and_the_same_at_every_resolution():
    """The ray start offset is a share of the face size, not of the edge length: a subdivided copy of the
    same surface (4x the triangles) gets the same offset, and the original vertices the same visibility."""
    import sys
    from pathlib import Path

    from usdface.landmarks.visibility import RAY_OFFSET, face_size

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from scale_avatars import midpoint_subdivide

    points, tri = grid_mesh()
    points[:, 2] += 0.01 * np.sin(80 * points[:, 0])  # ripples: self-occlusion
    deltas = np.stack([bump(points, (0.01, 0.04), amplitude=0.006), bump(points, (-0.02, 0.02))])
    fine_p, fine_t, fine_d = midpoint_subdivide(points, tri, deltas)
    coarse = PoseVisibility(points, tri, deltas, rays=16)
    fine = PoseVisibility(fine_p, fine_t, fine_d, rays=16)
    # the same up to where the 5 % face threshold falls between vertices (a share of the mean edge: 2x apart)
    assert np.isclose(coarse.offset, fine.offset, rtol=0.05)
    mag = np.linalg.norm(deltas, axis=2)
    share = (mag / mag.max(axis=1, keepdims=True)).max(axis=0)
    assert np.isclose(coarse.offset, RAY_OFFSET * face_size(points, share))
    # the original vertices: same position, same normal direction (corner triangles are scaled copies) ->
    # the same rays against the same surface
    inner = np.flatnonzero((np.abs(points[:, 0]) < 0.045) & (points[:, 1] > 0.005) & (points[:, 1] < 0.075))
    a, b = coarse(inner), fine(inner)
    assert (a < 1).mean() > 0.2
    assert np.mean(np.abs(a - b) <= 1 / 16 + 1e-12) > 0.97


def test_baselines_with_precomputed_features_are_the_same_layouts():
    from usdface.landmarks.baselines import moving_vertices, pca_features

    rig = random_rig(12, seed=4)
    feats, moving = pca_features(rig.deltas), moving_vertices(rig.deltas)
    for m in (3, 6):
        assert np.array_equal(pca_kmeans_layout(rig.deltas, m, features=feats),
                              pca_kmeans_layout(rig.deltas, m))
        assert np.array_equal(delta_cluster_layout(rig.deltas, m, moving=moving),
                              delta_cluster_layout(rig.deltas, m))
        assert np.array_equal(random_layout(rig.deltas, m, seed=2, moving=moving),
                              random_layout(rig.deltas, m, seed=2))


def test_no_backend_prints_its_solver_log():
    """User trial: ``usdface landmarks --backend highs`` printed HiGHS's banner ("Running HiGHS 1.12.0 ...")
    on stdout at every solve (into ``--json -`` output and logs; numeric code never prints). Run in a fresh
    process: the solvers write from C++, past Python's capture."""
    import subprocess
    import sys

    code = ("import numpy as np\n"
            "from usdface.landmarks.cover import solve_set_cover\n"
            "rng = np.random.default_rng(0)\n"
            "c, cost = rng.random((30, 60)) < 0.15, rng.random(60) + 0.5\n"
            "for backend in ('highs', 'scip', 'cbc', 'cp-sat'):\n"
            "    for cover_times in (1, 2):\n"
            "        sol = solve_set_cover(c, cost, backend=backend, reduce=False, cover_times=cover_times)\n"
            "        assert sol.status == 'optimal', (backend, sol.status)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == "" and proc.stderr == "", (proc.stdout, proc.stderr)


def _floor_and_panel(panel_x0: float, shift: float, roof: bool = False):
    """A 10 x 10 cm floor at z = 0 (11 x 11 vertices) and, 5 mm above it, a 20 x 4 cm panel from
    x = ``panel_x0`` to ``panel_x0 + 0.04`` (its own 4 vertices); one shape slides the panel by ``shift``
    along x. ``roof``: a still roof 2 cm up over x < 0, above the panel. -> (points, triangles, deltas[1])."""
    floor, tri = grid_mesh(11, 11, width=0.1, height=0.1)
    floor[:, 2] = 0.0
    x0, x1 = panel_x0, panel_x0 + 0.04
    panel = np.array([[x0, -0.05, 0.005], [x1, -0.05, 0.005], [x1, 0.15, 0.005], [x0, 0.15, 0.005]])
    points = np.concatenate([floor, panel])
    n = len(floor)
    tri = np.concatenate([tri, np.array([[n, n + 2, n + 1], [n, n + 3, n + 2]])])
    if roof:
        top = panel.copy()
        top[:, 0] = [-0.2, 0.0, 0.0, -0.2]
        top[:, 2] = 0.02
        points = np.concatenate([points, top])
        tri = np.concatenate([tri, np.array([[0, 2, 1], [0, 3, 2]]) + n + 4])
    deltas = np.zeros((1,) + points.shape)
    deltas[0, n:n + 4, 0] = shift
    return points, tri, deltas


@pytest.mark.parametrize("roof", [False, True])
def test_pose_visibility_recasts_rays_a_moving_occluder_blocked(roof):
    """A panel over the left of a vertex slides over its right: in the neutral the left rays are blocked,
    in the pose the right ones; l is the neutral's (about half free), not both halves blocked at once. A ray
    the neutral found blocked by a triangle the shape moves is cast again in the pose (the exact shortcut
    keeps only rays blocked by triangles the shape leaves in place). With a still roof over the left, the
    pose's left rays are blocked by it (the scene of the triangles no shape moves, with "union"): l ~ 0."""
    points, tri, deltas = _floor_and_panel(-0.04, 0.04, roof)
    v = 5 * 11 + 5                                  # the floor's centre vertex, x = 0
    assert abs(points[v, 0]) < 1e-12
    poses = [points, points + deltas[0]]
    for strategy in ("full", "union"):
        pv = PoseVisibility(points, tri, deltas, rays=32)
        pv.strategy = strategy
        got = pv([v])[0]
        brute = min(_brute_pose_visibility(p, tri, pv.offset, 32)[v] for p in poses)
        assert got == brute
        assert (got < 0.2) if roof else (0.3 < got < 0.7)


def test_camera_visibility_ignores_what_lies_beyond_the_camera():
    """One ray per vertex to the camera, stopped at it: a wall behind the camera (in the neutral and in a
    pose) hides nothing. Seen through, the whole floor read as hidden."""
    floor, tri = grid_mesh(11, 11, width=0.1, height=0.1)
    floor[:, 2] = 0.0
    wall = floor.copy()
    wall[:, :2] *= 20.0                             # 2 x 2 m, 1 m behind a camera 0.5 m above the floor
    wall[:, 2] = 1.5
    points = np.concatenate([floor, wall])
    tris = np.concatenate([tri, tri + len(floor)])
    deltas = np.zeros((1,) + points.shape)
    deltas[0, 60, 2] = 0.002                        # a shape that moves the floor: its poses are cast
    camera = [0.0, 0.05, 0.5]
    floor_v = np.arange(len(floor))
    pv = PoseVisibility(points, tris, deltas, camera=camera)
    np.testing.assert_array_equal(pv.upper_bound(floor_v), 1.0)
    np.testing.assert_array_equal(pv(floor_v), 1.0)


def test_cost_forms_exact_on_a_small_case():
    """Eq. 5a's three forms on 2 shapes x 3 columns, by hand: ``paper`` m sum_k c (2 - q); ``quality``
    m (1 + delta (1 - mean q over the shapes covered)), delta = 1 / (2K + 1); ``count`` m."""
    from usdface.landmarks.cover import set_cover_costs

    c = np.array([[1, 0, 1], [1, 1, 0]], dtype=bool)
    q = np.array([[0.5, 0.3, 1.0], [0.25, 0.9, 0.7]])
    m = np.array([1.0, 2.0, 1.0])
    np.testing.assert_allclose(set_cover_costs(c, q, "paper", m), [3.25, 2.2, 1.0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(set_cover_costs(c, q, "quality", m), [1.125, 2.04, 1.0], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(set_cover_costs(c, q, "count", m), m)


@pytest.mark.parametrize("shapes", [1, 4, 52])
@pytest.mark.parametrize("times", [1, 2, 3, 6])
def test_the_quality_term_of_an_n_fold_cover_stays_below_one_landmark(shapes, times):
    """The quality costs keep the count first for the one-shot N-fold cover too: a minimal N-fold layout has
    at most N K columns, each standing for at most two landmarks (a mirrored pair), and their whole quality
    term at the worst quality (0) stays below one landmark, so a layout with one landmark fewer is always
    the cheaper. With the single cover's delta 1 / (2 K + 1) it reached a landmark from N = 3 on (N = 2 for
    mirrored pairs): reverted, 9 of these 12 fail."""
    from usdface.landmarks.cover import set_cover_costs

    cols = times * shapes
    c = np.ones((shapes, cols), dtype=bool)
    for m in (1.0, 2.0):
        cost = set_cover_costs(c, np.zeros((shapes, cols)), "quality", np.full(cols, m), cover_times=times)
        assert cost.sum() < m * cols + 1.0


def test_multicover_asks_a_shape_with_few_candidates_for_what_it_has():
    """``cover_times = 3``: a shape with one candidate is covered once (min(N, |C_k|)), not made infeasible;
    the shape with four candidates three times."""
    from usdface.landmarks.cover import solve_set_cover

    c = np.array([[1, 1, 1, 1], [1, 0, 0, 0]], dtype=bool)
    sol = solve_set_cover(c, np.array([1.0, 1.0, 1.0, 1.1]), cover_times=3)
    assert sol.status == "optimal"
    np.testing.assert_array_equal(sol.selected, [0, 1, 2])


def test_a_shape_moving_no_more_than_the_tolerance_is_static():
    """``static_shapes``: max |dv| <= tolerance is still (the boundary included), above it moves."""
    from usdface.landmarks.candidates import STATIC_TOLERANCE, static_shapes

    mag = np.array([[0.0, STATIC_TOLERANCE], [0.0, np.nextafter(STATIC_TOLERANCE, 1.0)], [0.0, 0.0]])
    np.testing.assert_array_equal(static_shapes(mag), [0, 2])


def test_tikhonov_weight_is_lambda_not_its_square():
    """min |D w - b|^2 + lambda |w|^2 with unit landmark deltas: w = b / (1 + lambda); at lambda = 4 that is
    0.1 for b = 0.5 (lambda 1 cannot tell lambda from lambda^2)."""
    d = np.zeros((2, 1, 3))
    d[0, 0, 0] = 1.0
    d[1, 0, 1] = 1.0
    np.testing.assert_allclose(solve_weights(d, np.array([[[0.5, 0.5, 0.0]]]), tikhonov=4.0), [[0.1, 0.1]],
                               rtol=0, atol=1e-12)


def test_tracking_noise_is_drawn_for_every_frame():
    """Two frames of the same weights are tracked with independent noise of the given deviation."""
    rig = random_rig(4, seed=1)
    v = np.arange(0, rig.n_vertices, 7)
    pos = tracked_landmarks(rig.neutral, rig.deltas, v, np.full((2, 4), 0.5), noise=1e-3, seed=3)
    diff = (pos[1] - pos[0]).ravel()
    assert 0.8 * np.sqrt(2) * 1e-3 < diff.std() < 1.2 * np.sqrt(2) * 1e-3


def test_evaluation_sweep_and_summary_by_hand():
    """The sweep skips the non-adaptive single cover when share 0.1 is swept (the same layout); the summary's
    match is the smallest layout of this method at most as wrong as the empirical one (a tie counts)."""
    from usdface.landmarks.evaluate import EvaluationPoint, EvaluationReport, _summary, _sweep

    assert _sweep((0.5,), (1, 2), (0.1, None)) == [(0.5, 0.1, 1), (0.5, 0.1, 2), (0.5, None, 2)]
    assert _sweep((0.5,), (1,), (None,)) == [(0.5, None, 1)]
    points = [EvaluationPoint("ours", "a", 8, 2e-3), EvaluationPoint("ours", "b", 12, 1e-3),
              EvaluationPoint("ours", "c", 20, 0.5e-3), EvaluationPoint("empirical", "68 points", 68, 1e-3)]
    s = _summary(EvaluationReport(points, 10, 0.5e-3), 68)
    assert (s["match_count"], s["match_rmse"], s["ours_at_empirical_count"]) == (12, 1e-3, 20)
    points.append(EvaluationPoint("ours", "d", 12, 3e-3))             # a worse layout of the same count
    assert EvaluationReport(points, 10, 0.5e-3).best_per_count() == {8: 2e-3, 12: 1e-3, 20: 0.5e-3}


def test_the_evaluation_records_the_radius_its_layouts_used():
    """``landmarks --evaluate --json`` said the frames and the noise but not the multi-cover's exclusion
    radius, which since stop 54 is relative to the face by default (no longer the 0.01 m the command
    passed): the report holds the radius its layouts used, in metres (``units``), given or the default."""
    from usdface.landmarks.evaluate import evaluate_landmarks

    rig = random_rig(12, seed=3)
    weights = np.random.default_rng(0).uniform(0.0, 1.0, size=(20, rig.n_shapes))
    kw = dict(epsilons=(0.5,), rounds=(2,), shares=(None,), counts=(8,), random_seeds=1)
    default = evaluate_landmarks(rig, weights, **kw).to_dict()
    assert default["units"]["radius"] == "m"
    assert default["radius"] == compute_landmarks(rig, 0.5, multicover=2, alpha=0.0).problem["radius"]
    assert evaluate_landmarks(rig, weights, radius=0.004, **kw).to_dict()["radius"] == 0.004


def test_the_face_is_one_moving_share_for_its_size_samples_radius_and_rays():
    """Stop 54's review (h111): the per-vertex moving share behind the face size (max over shapes of eq. 2's
    r) was computed in four places (``face_samples``, ``compute_landmarks``, ``exclusion_radius``,
    ``PoseVisibility``'s loop over the shapes). One function now (``candidates.moving_share``); each of the
    four gives the face size of that share, with or without the caller's magnitudes, and the share is the
    definition's (|dv| / the shape's peak, maxed over the shapes)."""
    from usdface.landmarks import sampling
    from usdface.landmarks.candidates import displacement_magnitudes, moving_share
    from usdface.landmarks.layout import face_samples
    from usdface.landmarks.multicover import RADIUS_SHARE, exclusion_radius
    from usdface.landmarks.visibility import FACE_SHARE, RAY_OFFSET, face_size

    rig = random_rig(4, seed=5)                  # bumps over two thirds of the sheet
    norms = np.linalg.norm(rig.deltas, axis=2)
    share = moving_share(relative_displacement(displacement_magnitudes(rig.deltas)))
    np.testing.assert_array_equal(share, (norms / norms.max(axis=1, keepdims=True)).max(axis=0))
    assert 0 < (share >= FACE_SHARE).sum() < rig.n_vertices       # the face is a part of the mesh
    size = face_size(rig.neutral, share)
    r = relative_displacement(displacement_magnitudes(rig.deltas))
    assert exclusion_radius(rig.neutral, r) == RADIUS_SHARE * size
    assert face_samples(rig)[0] == face_samples(rig, "auto", r)[0] == sampling.sample_spacing(size)
    for mags in (None, displacement_magnitudes(rig.deltas)):
        vis = PoseVisibility(rig.neutral, rig.triangles, rig.deltas, 4, magnitudes=mags)
        assert vis.offset == max(RAY_OFFSET * size, 1e-9)
    lay = compute_landmarks(rig, 0.5, multicover=2, rays=4)
    assert lay.problem["radius"] == RADIUS_SHARE * size
    assert lay.problem["spacing"] == sampling.sample_spacing(size)
    assert moving_share(np.zeros((0, 4))).tolist() == [0.0] * 4          # no shapes: nothing moves
