"""The benchmark's case names (benchmarks/bench_personalize.py): a bench case whose capture misses frames, a
generated case's settings."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_personalize  # noqa: E402


def test_minus_names_a_bench_case_and_a_step():
    assert bench_personalize._minus("dev1/minus3") == ("dev1", 3)
    assert bench_personalize._minus("dev2/minus2") == ("dev2", 2)
    for other in ("dev1", "sample", "artist:3", "dev1/minus1", "dev1/minus", "dev1/minusx"):
        assert bench_personalize._minus(other) is None


def test_capture_minus_drops_every_kth_requested_frame_and_keeps_the_rest(tmp_path, monkeypatch):
    capture = tmp_path / "bench" / "devX" / "capture"
    (capture / "train").mkdir(parents=True)
    (capture / "template").mkdir()
    (capture / "test").mkdir()
    (capture / "neutral.obj").write_text("v 0 0 0\n")
    for i, name in enumerate(["eyeBlinkLeft", "jawOpen", "mouthClose", "mouthFunnel", "mouthPucker",
                              "browInnerUp", "cheekPuff"]):
        for ext in ("obj", "json"):
            (capture / "train" / f"{i:03d}_{name}.{ext}").write_text(f"{i}\n")
    monkeypatch.setattr(bench_personalize, "BENCH", tmp_path / "bench")
    out = bench_personalize._capture_minus("devX", 3)
    kept = sorted(p.name for p in (out / "train").iterdir())
    numbers = sorted({int(name.split("_")[0]) for name in kept})
    assert numbers == [0, 2, 3, 5, 6]                       # 1 and 4 (1 modulo 3) are gone
    assert len(kept) == 2 * len(numbers)                    # each frame's scan and its weights
    assert sorted(p.name for p in out.iterdir()) == ["neutral.obj", "template", "test", "train"]
    assert (out / "train" / "002_mouthClose.obj").read_text() == "2\n"     # the case's own files
    assert (out / "neutral.obj").resolve() == (capture / "neutral.obj").resolve()


def test_weights_names_a_case_and_a_factor():
    assert bench_personalize._weights("artist:31/weights0.9") == ("artist:31", 0.9)
    assert bench_personalize._weights("dev1/minus3/weights1.1") == ("dev1/minus3", 1.1)
    for other in ("artist:31", "dev1/minus3", "sample/weights", "sample/weightsx", "sample/weights-1",
                  "sample/weights0", "/weights0.9", "sample/weightsnan"):
        assert bench_personalize._weights(other) is None
    assert bench_personalize._known("sample/weights0.8") and bench_personalize._known("artist:2/weights1.2")
    assert not bench_personalize._known("nonexistent-case/weights0.9")


def test_scaled_weights_change_the_training_frames_only_within_the_phones_range():
    import numpy as np

    from usdface.model import Capture, FaceRig, Frames

    tri = np.array([[0, 1, 2]])
    pts = np.eye(3)
    weights = np.array([[0.95, 0.1], [0.5, 0.0], [0.9, 0.6]])
    capture = Capture(pts, tri, FaceRig(pts, tri, ["a", "b"], np.zeros((2, 3, 3))),
                      Frames(np.stack([pts] * 3), weights, ["train", "train", "test"], ["0_a", "1_b", "0"]),
                      ["a", "b"])
    out = bench_personalize.scale_training_weights(capture, 1.2)
    np.testing.assert_array_equal(out.frames.weights, [[1.0, 0.12], [0.6, 0.0], [0.9, 0.6]])
    np.testing.assert_array_equal(capture.frames.weights, weights)          # the input is not changed
    np.testing.assert_array_equal(out.frames.points, capture.frames.points)
    assert out.frames.role == capture.frames.role and out.names == capture.names
    low = bench_personalize.scale_training_weights(capture, 0.5).frames.weights
    np.testing.assert_array_equal(low, [[0.475, 0.05], [0.25, 0.0], [0.9, 0.6]])


def test_template_names_a_bench_case_a_source_and_a_factor():
    assert bench_personalize._template("dev1/template3") == ("dev1", "dev3", 1.0)
    assert bench_personalize._template("dev2/template3x0.5") == ("dev2", "dev3", 0.5)
    assert bench_personalize._template("dev3/template1x-1") == ("dev3", "dev1", -1.0)
    for other in ("dev1", "dev1/template", "dev1/templatex0.5", "dev1/template3xq", "/template3",
                  "dev1/template3xnan", "dev1/templatea"):
        assert bench_personalize._template(other) is None


def test_swapped_template_moves_the_template_only_and_matches_names_in_any_spelling():
    import numpy as np
    import pytest

    from usdface.model import Capture, FaceRig, Frames

    tri = np.array([[0, 1, 2]])
    pts = np.eye(3)
    mine = np.arange(18, dtype=float).reshape(2, 3, 3)
    theirs = -np.arange(18, dtype=float).reshape(2, 3, 3)
    frames = Frames(np.stack([pts] * 2), np.array([[1.0, 0.0], [0.0, 1.0]]), ["train"] * 2, ["0_a", "1_b"])
    capture = Capture(pts, tri, FaceRig(pts, tri, ["eyeBlinkLeft", "jawOpen"], mine), frames,
                      ["eyeBlinkLeft", "jawOpen"])
    # the source names the shapes in ARKit's raw spelling and in another order
    source = Capture(pts, tri, FaceRig(pts, tri, ["jawOpen", "eyeBlink_L"], theirs[::-1]), frames,
                     ["jawOpen", "eyeBlink_L"])
    half = bench_personalize.swap_template(capture, source, 0.5)
    np.testing.assert_allclose(half.template.deltas, np.zeros_like(mine))       # half way from x to -x
    np.testing.assert_array_equal(bench_personalize.swap_template(capture, source, 1.0).template.deltas,
                                  theirs)
    np.testing.assert_array_equal(capture.template.deltas, mine)                # the input is not changed
    assert half.frames is capture.frames and half.names == capture.names
    other_mesh = Capture(pts * 2, tri, FaceRig(pts * 2, tri, ["jawOpen", "eyeBlink_L"], theirs), frames,
                         ["jawOpen", "eyeBlink_L"])
    with pytest.raises(ValueError, match="same mesh"):
        bench_personalize.swap_template(capture, other_mesh, 1.0)


def test_a_generated_cases_name_sets_the_frames_noise_after_its_seed():
    spec = bench_personalize._spec
    assert spec("artist:201") == ("artist", 201, {})
    assert spec("generic:7/scan0.3/wnoise0.06") == ("generic", 7, {"scan_noise_m": 0.3e-3,
                                                                  "weight_noise": 0.06})
    assert spec("artist:7/wnoise0/scan0.05") == ("artist", 7, {"weight_noise": 0.0,
                                                              "scan_noise_m": 0.05e-3})
    # noisy: dev2's regime (0.15 mm, 0.03), either value overridden by a modifier
    assert spec("noisy:3") == ("artist", 3, {"scan_noise_m": 1.5e-4, "weight_noise": 0.03})
    assert spec("noisy:3/wnoise0.01") == ("artist", 3, {"scan_noise_m": 1.5e-4, "weight_noise": 0.01})
    for other in ("dev1", "sample", "artist:x", "other:3", "artist:3/scan", "artist:3/scanx",
                  "artist:3/scan-1", "artist:3/scannan", "artist:3/scan0.1/scan0.2", "artist:3/minus3",
                  "artist:3/weights0.9", "artist:3/wnoise0.1/minus3"):
        assert spec(other) is None, other
    # combinable with the other modifiers, which follow the settings
    assert bench_personalize._minus("artist:3/scan0.3/minus3") == ("artist:3/scan0.3", 3)
    assert (bench_personalize._weights("artist:3/wnoise0.06/minus3/weights1.1")
            == ("artist:3/wnoise0.06/minus3", 1.1))
    for case in ("artist:3/scan0.3", "noisy:3/wnoise0.06/scan0.05", "generic:3/scan0.3/minus3",
                 "artist:3/scan0.3/wnoise0.06/minus3/weights0.9", "artist:3/minus3"):
        assert bench_personalize._known(case), case
    assert not bench_personalize._known("artist:3/scan0.3/other")


def test_the_settings_reach_the_generator(monkeypatch, tmp_path):
    import usdface.sample

    calls = []

    def fake(outdir, seed, template, **noise):
        calls.append((seed, template, noise))
        return tmp_path

    monkeypatch.setattr(usdface.sample, "generate_samples", fake)
    monkeypatch.setattr(bench_personalize, "_MADE", {})
    assert bench_personalize._folder("noisy:5/scan0.3") == tmp_path
    assert bench_personalize._folder("noisy:5/scan0.3") == tmp_path                 # made once per run
    bench_personalize._folder("generic:6/wnoise0.06")
    assert calls == [(5, "artist", {"scan_noise_m": 0.3e-3, "weight_noise": 0.03}),
                     (6, "generic", {"weight_noise": 0.06})]


def test_dropped_frames_of_a_capture_read_from_one_file_are_the_folders_every_kth():
    import numpy as np

    from usdface.model import Capture, FaceRig, Frames

    tri = np.array([[0, 1, 2]])
    pts = np.eye(3)
    labels = ["000_a", "001_b", "002_a", "003_b", "004_a", "000", "001"]
    roles = ["train"] * 5 + ["test"] * 2
    weights = np.arange(14, dtype=float).reshape(7, 2)
    capture = Capture(pts, tri, FaceRig(pts, tri, ["a", "b"], np.zeros((2, 3, 3))),
                      Frames(np.stack([pts * i for i in range(7)]), weights, roles, labels), ["a", "b"])
    out = bench_personalize.drop_training_frames(capture, 3)
    assert out.frames.label == ["000_a", "002_a", "003_b", "000", "001"]      # 1 and 4 gone, the tests kept
    assert out.frames.role == ["train"] * 3 + ["test"] * 2
    np.testing.assert_array_equal(out.frames.weights, weights[[0, 2, 3, 5, 6]])
    np.testing.assert_array_equal(out.frames.points, capture.frames.points[[0, 2, 3, 5, 6]])
    assert len(capture.frames.label) == 7                                  # the input is not changed
