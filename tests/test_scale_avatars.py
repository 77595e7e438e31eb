"""The production-size avatar builder of benchmarks/bench_scale.py (benchmarks/scale_avatars.py)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from scale_avatars import body_mesh, midpoint_subdivide, neck_deltas  # noqa: E402

from usdface.mesh import triangle_areas  # noqa: E402


def _tetra():
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    tri = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    deltas = np.random.default_rng(0).normal(size=(2, 4, 3))
    return points, tri, deltas


def test_midpoint_subdivision_keeps_the_original_vertices_and_the_surface():
    points, tri, deltas = _tetra()
    p, t, d = midpoint_subdivide(points, tri, deltas)
    assert len(p) == 4 + 6 and len(t) == 16  # one vertex per edge, four triangles per triangle
    np.testing.assert_array_equal(p[:4], points)
    np.testing.assert_array_equal(d[:, :4], deltas)
    assert np.isclose(triangle_areas(p, t).sum(), triangle_areas(points, tri).sum())
    # every new vertex is the midpoint of two original vertices, in position and in every shape's offset
    for j in range(4, 10):
        pairs = [(a, b) for a in range(4) for b in range(a + 1, 4)
                 if np.allclose(p[j], (points[a] + points[b]) / 2)]
        assert len(pairs) == 1
        a, b = pairs[0]
        np.testing.assert_allclose(d[:, j], (deltas[:, a] + deltas[:, b]) / 2)
    # the posed surfaces are the same: the subdivided pose's area equals the original pose's
    for k in range(2):
        assert np.isclose(triangle_areas(p + d[k], t).sum(), triangle_areas(points + deltas[k], tri).sum())


def test_body_mesh_is_closed_and_its_neck_shapes_sparse():
    points, tri = body_mesh(top=1.4, rows=40, columns=30)
    assert len(points) == 40 * 30 + 2
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 2).all()  # closed: every edge shared by exactly two triangles
    assert points[:, 1].max() <= 1.4
    d = neck_deltas(points, 1.4, ["jawOpen", "eyeBlinkLeft"])
    moved = np.linalg.norm(d, axis=2) > 0
    assert not moved[1].any() and 0 < moved[0].mean() < 0.2  # only the top of the neck moves
