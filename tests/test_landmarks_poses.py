"""Eq. 4's poses of shapes authored over another (ARKit's mouthClose over jawOpen): the landmarks see such a
shape in the pose it is used in, not alone where its lips pass through each other."""

from __future__ import annotations

import numpy as np
import pytest

from usdface import api
from usdface.errors import GeometryError
from usdface.landmarks import compute_landmarks
from usdface.landmarks.visibility import POSE_BASES, PoseVisibility, pose_bases
from usdface.model import FaceRig

NX, NY = 21, 9
GAP = 0.01      # metres between the two lips at rest
SHIFT = 0.02    # what jawOpen drops the lower lip and mouthClose lifts it back


def _strip(y0: float, y1: float, z: float = 0.0):
    xs, ys = np.meshgrid(np.linspace(-0.03, 0.03, NX), np.linspace(y0, y1, NY))
    points = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)], axis=1)
    i, j = np.meshgrid(np.arange(NX - 1), np.arange(NY - 1))
    a = (j * NX + i).ravel()
    tri = np.concatenate([np.stack([a, a + 1, a + NX + 1], 1), np.stack([a, a + NX + 1, a + NX], 1)])
    return points, tri


def mouth_rig(names=("jawOpen", "mouthClose", "mouthShrugUpper")) -> tuple[FaceRig, np.ndarray]:
    """Two lips facing +Z, GAP apart: ``jawOpen`` drops the lower lip by SHIFT; ``mouthClose`` (authored over
    jawOpen, as ARKit's) lifts it by SHIFT and 3 mm forward, so alone the lower lip lies over the upper lip's
    skin, 3 mm in front of it; ``mouthShrugUpper`` pushes out a small patch of that skin (its candidates).
    Returns the rig and the upper lip's vertices that mouthClose alone covers."""
    upper, tri_u = _strip(GAP / 2, GAP / 2 + 0.03)
    lower, tri_l = _strip(-GAP / 2 - 0.03, -GAP / 2)
    points = np.concatenate([upper, lower])
    tri = np.concatenate([tri_u, tri_l + len(upper)])
    is_lower = np.arange(len(points)) >= len(upper)
    jaw = np.zeros_like(points)
    jaw[is_lower, 1] = -SHIFT
    close = np.zeros_like(points)
    close[is_lower] = [0.0, SHIFT, 0.003]
    under = points[:, 1] < -GAP / 2 + SHIFT - 0.004          # what the lifted lower lip lies over
    covered = np.flatnonzero(~is_lower & under & (np.abs(points[:, 0]) < 0.02))
    shrug = np.zeros_like(points)
    shrug[~is_lower, 2] = 0.001 * np.exp(-(points[~is_lower, 0] ** 2 + (points[~is_lower, 1] - 0.007) ** 2)
                                         / 2.5e-5)
    return FaceRig(points, tri, list(names), np.stack([jaw, close, shrug])), covered


def test_pose_bases_reads_any_arkit_spelling_and_needs_the_base():
    assert POSE_BASES == {"mouthClose": ("jawOpen",)}
    assert pose_bases(["jawOpen", "mouthClose", "eyeBlinkLeft"]) == [(), (0,), ()]
    assert pose_bases(["mouthShrugUpper", "jawOpen", "mouthClose"]) == [(), (), (1,)]
    assert pose_bases(["MouthClose", "JawOpen"]) == [(1,), ()]           # Live Link Face columns
    assert pose_bases(["mouth_close", "jaw_open"]) == [(1,), ()]
    assert pose_bases(["mouthClose", "eyeBlinkLeft"]) == [(), ()]       # no jawOpen: posed alone
    assert pose_bases(["shapeA", "shapeB"]) == [(), ()]                  # not ARKit: the paper's poses


def test_corrective_shape_is_seen_over_its_base_not_alone():
    """mouthClose alone puts the lower lip 3 mm in front of the upper lip's skin (rays from it start under
    another surface): the upper lip got l ~ 0 from that one pose. Over jawOpen, as it is used, the lips meet
    as at rest and the upper lip is seen as in the neutral and jawOpen poses."""
    rig, covered = mouth_rig()
    alone = PoseVisibility(rig.neutral, rig.triangles, rig.deltas, rays=16)(covered)
    assert alone.max() <= 0.25      # the bug: one non-physical pose hides the upper lip
    over = PoseVisibility(rig.neutral, rig.triangles, rig.deltas, rays=16, bases=pose_bases(rig.names))
    l = over(covered)
    neutral_and_jaw = PoseVisibility(rig.neutral, rig.triangles, rig.deltas[[0, 2]], rays=16)(covered)
    assert l.min() >= 0.5
    assert (l <= neutral_and_jaw).all()     # still a minimum over more poses
    np.testing.assert_allclose(over.pose(1), rig.neutral + rig.deltas[0] + rig.deltas[1])
    np.testing.assert_allclose(over.pose(0), rig.neutral + rig.deltas[0])


def test_layout_and_diagnostics_see_the_same_poses():
    """compute_landmarks (the layout's visibility at the samples and per vertex) and the diagnostics
    (render --landmarks --diagnostics) take the poses from the shape names alike; a rig whose names are not
    ARKit's keeps the paper's single-shape poses."""
    rig, covered = mouth_rig()
    plain, _ = mouth_rig(names=("shapeA", "shapeB", "shapeC"))
    for r, low in ((rig, False), (plain, True)):
        layout = compute_landmarks(r, spacing=None)
        on_lip = layout.coverage[:, 2]          # the landmark of the patch on the upper lip
        assert np.isin(layout.vertices[on_lip], covered).all()
        l_layout = layout.visibility[on_lip]
        l_diag = api.landmark_diagnostics(r).visibility[covered]
        l_diag = l_diag[np.isfinite(l_diag)]   # the diagnosed region: what the patch moves
        assert l_diag.size >= 5
        if low:
            assert l_layout.max() <= 0.25 and l_diag.max() <= 0.25
        else:
            assert l_layout.min() >= 0.5 and l_diag.min() >= 0.5


def test_bad_pose_bases_refused():
    rig, _ = mouth_rig()
    for bad in ([(), (5,), ()], [(0,), (), ()], [()]):
        with pytest.raises(GeometryError, match="pose bases"):
            PoseVisibility(rig.neutral, rig.triangles, rig.deltas, bases=bad)
