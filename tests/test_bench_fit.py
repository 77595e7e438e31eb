"""The fit benchmark's per-shape table (benchmarks/bench_fit.py ``--per-shape``): each shape's truth error
beside its prior's, and how the training frames excite it; and its case names."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_fit  # noqa: E402

from usdface.model import Capture, FaceRig, Frames  # noqa: E402
from usdface.personalize.api import FitResult  # noqa: E402
from usdface.personalize.evaluate import truth_error  # noqa: E402


def _capture(names, labels, weights, n=4):
    """A capture of ``n`` vertices whose training frames carry ``labels`` and ``weights[F,K]``."""
    tri = np.array([[0, 1, 2], [0, 2, 3]])
    pts = np.random.default_rng(0).normal(size=(n, 3)) * 0.05
    F = len(weights)
    return Capture(pts, tri, FaceRig(pts, tri, list(names), np.zeros((len(names), n, 3))),
                   Frames(np.stack([pts] * F), np.asarray(weights, dtype=np.float64), ["train"] * F,
                          list(labels)), list(names))


def test_per_shape_errors_add_up_to_the_truth_error_and_read_the_frames_labels():
    names = ["jawOpen", "jawLeft", "mouthClose"]
    # jawLeft's frame shows jawOpen more strongly (not isolated); mouthClose ties jawOpen in its own
    # (isolated); labels in any of the three spellings
    weights = [[0.9, 0.0, 0.1], [0.2, 0.05, 0.0], [0.5, 0.0, 0.5]]
    cap = _capture(names, ["000_jawOpen", "001_JawLeft", "002_mouthClose"], weights)
    rng = np.random.default_rng(1)
    true = rng.normal(size=(3, 4, 3)) * 1e-3
    offsets = np.array([1.0, 2.0, 0.5]) * 1e-3              # each fitted shape off by this at every vertex
    direction = np.array([0.6, 0.0, 0.8])
    fitted = true + offsets[:, None, None] * direction
    prior = true + 3e-3 * direction                                 # the prior 3 mm off everywhere
    res = FitResult(FaceRig(cap.neutral, cap.triangles, names, fitted),
                    {"prior_deltas": prior, "data_share": np.array([0.9, 0.1, 0.5])})
    rows = bench_fit.per_shape(cap, true, res)
    assert [r["shape"] for r in rows] == names
    np.testing.assert_allclose([r["fit"] for r in rows], [1.0, 2.0, 0.5], atol=1e-9)
    np.testing.assert_allclose([r["prior"] for r in rows], 3.0, atol=1e-9)
    # the RMS over shapes is the benchmark's truth figure, and the shares split its square
    rms = np.sqrt(np.mean([r["fit"] ** 2 for r in rows]))
    assert abs(rms - truth_error(fitted, true)) < 1e-9
    assert abs(sum(r["share"] for r in rows) - 1.0) < 1e-12
    np.testing.assert_allclose([r["share"] for r in rows], np.array([1.0, 4.0, 0.25]) / 5.25)
    # excitation: largest weight, energy, the weight in the frame recorded for the shape
    np.testing.assert_allclose([r["peak"] for r in rows], [0.9, 0.05, 0.5])
    np.testing.assert_allclose([r["energy"] for r in rows], [0.81 + 0.04 + 0.25, 0.0025, 0.01 + 0.25])
    np.testing.assert_allclose([r["own"] for r in rows], [0.9, 0.05, 0.5])
    assert [r["isolated"] for r in rows] == [True, False, True]
    assert np.isnan(rows[0]["reliability"]) and rows[1]["data_share"] == 0.1


def test_a_shape_without_a_frame_of_its_own_is_not_isolated():
    names = ["jawOpen", "cheekPuff"]
    cap = _capture(names, ["000_jawOpen"], [[0.9, 0.3]])
    res = FitResult(FaceRig(cap.neutral, cap.triangles, names, np.zeros((2, 4, 3))), {})
    rows = bench_fit.per_shape(cap, np.zeros((2, 4, 3)), res)
    assert rows[0]["isolated"] and not rows[1]["isolated"] and np.isnan(rows[1]["own"])
    assert rows[0]["share"] == 0.0                      # an exact fit: no error to share


def test_a_derived_cases_truth_is_its_base_cases():
    assert bench_fit.truth_path("dev1/minus3") == bench_fit.truth_path("dev1")
    assert bench_fit.truth_path("dev3/template1x0.5/weights0.9") == bench_fit.truth_path("dev3")
    assert bench_fit.truth_path("sample/weights1.1") == bench_fit.SAMPLE / "truth" / "capture_truth.npz"
    assert bench_fit.known("sample") and bench_fit.known("artist:7") and bench_fit.known("noisy:3/scan0.3")
    assert not bench_fit.known("no-such-case")
