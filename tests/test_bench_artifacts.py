"""The artifact detector's core (benchmarks/bench_artifacts.py) on a synthetic grid: a planted spike and a
planted crease are found, a smooth field is not, and a rigid Mouth body is told from a stretched one."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from synthetic_meshes import grid_triangles

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_artifacts as ba  # noqa: E402

from usdface.mesh import edges  # noqa: E402

N = 30                  # 30 x 30 vertices, 2 mm apart: a 58 mm patch
H = 0.002


def _grid():
    j, i = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
    points = np.column_stack([i.ravel() * H, j.ravel() * H, np.zeros(N * N)])
    return points, grid_triangles(N, N)


def _smooth(points, amplitude=0.002, phase=0.0):
    """``[n,3]`` a smooth bump (m): what an artist's or a person's shape looks like."""
    c = points.mean(axis=0)
    r2 = np.sum((points - c) ** 2, axis=1) / 0.02 ** 2
    z = amplitude * np.exp(-r2) * (1 + 0.2 * np.sin(points[:, 0] / 0.01 + phase))
    return np.column_stack([0.3 * z, np.zeros_like(z), z])


def _three_sets(out_planted):
    points, tri = _grid()
    generic = _smooth(points)[None]
    truth = _smooth(points, 0.0025, 0.7)[None]                 # the person: another smooth shape
    out = 0.5 * (generic + truth) + out_planted[None]
    return points, tri, out, generic, truth


def _flags(points, tri, out, generic, truth):
    e = edges(tri)
    s = {k: ba.edge_strain(points, v, e) for k, v in (("o", out), ("g", generic), ("t", truth))}
    u = {k: ba.umbrella_spike(points, v, tri) for k, v in (("o", out), ("g", generic), ("t", truth))}
    return (e, ba.flag(s["o"][0], s["g"][0], s["t"][0], s["o"][1]),
            ba.flag(u["o"][0], u["g"][0], u["t"][0], u["o"][1]))


def test_a_smooth_field_between_generic_and_truth_is_not_flagged():
    points, tri, out, generic, truth = _three_sets(np.zeros((N * N, 3)))
    out = out * 1.5                                             # even a larger smooth shape
    e, edge_flags, vertex_flags = _flags(points, tri, out, generic, truth)
    assert not edge_flags.any() and not vertex_flags.any()


def test_a_planted_spike_is_found_at_its_vertex():
    spike = np.zeros((N * N, 3))
    v = 12 * N + 17
    spike[v, 2] = 0.5e-3                                       # half a millimetre at one vertex
    points, tri, out, generic, truth = _three_sets(spike)
    e, edge_flags, vertex_flags = _flags(points, tri, out, generic, truth)
    flagged = np.flatnonzero(vertex_flags[0])
    ring = set(e[(e == v).any(axis=1)].ravel())                 # v and its 1-ring (their umbrellas see it)
    assert v in flagged and set(flagged) <= ring
    assert set(e[edge_flags[0]].ravel()) >= {v}                 # its edges jump too
    assert all(v in pair for pair in e[edge_flags[0]])          # ... and only its edges


def test_a_planted_crease_is_found_along_its_line():
    points, tri, out, generic, truth = _three_sets(np.zeros((N * N, 3)))
    crease = np.zeros((N * N, 3))
    crease[points[:, 0] > 14.5 * H, 2] = 0.6e-3                 # a 0.6 mm step across the column x = 14.5
    out = out + crease[None]
    e, edge_flags, _ = _flags(points, tri, out, generic, truth)
    across = (points[e[:, 0], 0] > 14.5 * H) != (points[e[:, 1], 0] > 14.5 * H)
    assert edge_flags[0].any()
    assert across[edge_flags[0]].all()                          # only the edges across the step
    assert edge_flags[0][across].mean() > 0.8                   # and most (not where the bump is steep)


def test_the_same_spike_in_the_truth_is_the_persons_not_flagged():
    spike = np.zeros((N * N, 3))
    spike[12 * N + 17, 2] = 0.5e-3
    points, tri, out, generic, truth = _three_sets(spike)
    _, edge_flags, vertex_flags = _flags(points, tri, out, generic, truth + spike[None])
    assert not edge_flags.any() and not vertex_flags.any()


def test_rigid_residual_is_zero_for_a_rigid_motion_and_sees_a_stretch():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(200, 3)) * 0.02
    a = 0.3
    R = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    rigid = p @ R.T + [0.001, -0.002, 0.003] - p
    groups = np.zeros(200, dtype=int)
    groups[100:] = 1                                            # two bodies, each its own rigid fit
    rigid[100:] = p[100:] @ R + [0.0, 0.004, 0.0] - p[100:]
    assert ba.rigid_residual(p, rigid, groups).max() < 1e-12
    stretched = rigid.copy()
    stretched[:100] += 0.04 * p[:100]                           # 4 % growth of the first body
    res = ba.rigid_residual(p, stretched, groups)
    assert res[:100].max() > 1e-3 and res[100:].max() < 1e-12
    groups[:100] = -1                                           # not scored
    assert ba.rigid_residual(p, stretched, groups)[:100].max() == 0.0


def test_affine_residual_is_zero_for_a_uniform_change_and_sees_a_bend():
    """A jaw that opens 4 % less (an affine map of the generic pose) is no tear; a bend of one body is."""
    rng = np.random.default_rng(1)
    source = rng.normal(size=(300, 3)) * 0.02
    groups = np.repeat([0, 1, 2], 100)
    A = np.array([[0.96, 0.01, 0.0], [0.0, 1.02, 0.03], [0.0, 0.0, 0.99]])
    target = source @ A.T + [0.002, 0.0, -0.001]
    assert ba.affine_residual(source, target, groups).max() < 1e-12
    bent = target.copy()
    bent[200:, 2] += 0.002 * np.sin(source[200:, 0] / 0.01)                      # only the third body
    res = ba.affine_residual(source, bent, groups)
    assert res[:200].max() < 1e-12 and res[200:].max() > 5e-4


def test_the_score_is_above_one_exactly_where_flagged_and_the_spike_is_the_worst():
    spike = np.zeros((N * N, 3))
    v = 12 * N + 17
    spike[v, 2] = 0.5e-3
    points, tri, out, generic, truth = _three_sets(spike)
    o, g, t = (ba.umbrella_spike(points, x, tri) for x in (out, generic, truth))
    sc = ba.score(o[0], g[0], t[0], o[1])
    np.testing.assert_array_equal(sc > 1.0, ba.flag(o[0], g[0], t[0], o[1]))
    worst = ba._worst("vertex", "Head", ["s"], o[0], g[0], t[0], o[1], g[1], t[1], lambda i: "mask", str, 2)
    assert [w.index for w in worst][0] == str(v) and worst[0].owner == "new"
    assert worst[0].out_mm == pytest.approx(o[1][0, v] * 1e3) and worst[0].flagged == int((sc > 1).sum())


def test_the_umbrella_is_the_mesh_modules_laplacian_shape_by_shape():
    from usdface.mesh import uniform_laplacian

    points, tri = _grid()
    rng = np.random.default_rng(2)
    d = rng.normal(size=(3, N * N, 3)) * 1e-3
    _, size = ba.umbrella_spike(points, d, tri)
    L = uniform_laplacian(tri, N * N)
    np.testing.assert_allclose(size, np.stack([np.linalg.norm(L @ d[k], axis=1) for k in range(3)]),
                               rtol=1e-12, atol=1e-18)
