"""A capture whose Left/Right weights are exchanged (a capture app showing a mirrored selfie view) is named
before the fit learns each side's shape from the other side's motion
(usdface.personalize.api.swapped_sides), through the documented CLI flow."""

from __future__ import annotations

import json
import shutil

import numpy as np

from usdface.arkit import mirror_name


def _swap_folder(src, dst):
    """A copy of the capture folder ``src`` with every frame's Left/Right weight names exchanged."""
    shutil.copytree(src, dst)
    for path in list(dst.glob("train/*.json")) + list(dst.glob("test/*.json")):
        doc = json.loads(path.read_text())
        doc["blendShapes"] = {mirror_name(k): v for k, v in doc["blendShapes"].items()}
        path.write_text(json.dumps(doc))
    return dst


def test_swapped_sides_named_by_capture_import_then_fit(sample_capture_folder, tmp_path, capsys):
    from usdface.cli import main

    swapped = _swap_folder(sample_capture_folder, tmp_path / "swapped")
    for folder, name in ((sample_capture_folder, "reported"), (swapped, "swapped")):
        cap = tmp_path / f"{name}.usda"
        assert main(["capture", "import", str(folder), "-o", str(cap), "-q"]) == 0
        capsys.readouterr()
        assert main(["fit", str(cap), "-o", str(tmp_path / f"{name}_rig.usda"), "--json"]) == 0
        out = capsys.readouterr()
        said = json.loads(out.out)["warnings"]
        hit = [w for w in said if "Left and Right weights look exchanged" in w]
        if name == "reported":
            assert not hit, hit
        else:
            assert len(hit) == 1 and "mirroring" in hit[0], said


def test_swapped_sides_figures():
    """On a synthetic capture: the reported labels are kept when they explain the scans; exchanged ones
    are named with both residuals."""
    from usdface.personalize.api import swapped_sides

    rng = np.random.default_rng(1)
    names = ["eyeBlinkLeft", "eyeBlinkRight", "jawOpen", "mouthSmileLeft", "mouthSmileRight"]
    n = 200
    t = rng.normal(size=(5, n, 3)) * 1e-3
    neutral = rng.normal(size=(n, 3)) * 0.05
    w = np.clip(rng.random((12, 5)) - 0.3, 0.0, 1.0)
    pts = neutral + np.einsum("fk,knc->fnc", w, t) + rng.normal(size=(12, n, 3)) * 1e-5
    assert swapped_sides(pts, neutral, t, w, names) is None
    perm = [names.index(mirror_name(k)) for k in names]
    found = swapped_sides(pts, neutral, t, w[:, perm], names)
    assert found is not None and found["swapped_mm"] < 0.5 * found["reported_mm"]
    assert found["frames_swapped"] >= 3 and found["frames_reported"] == 0
    # no Left/Right pair: nothing to say
    assert swapped_sides(pts, neutral, t, w[:, perm], ["a", "b", "c", "d", "e"]) is None


def test_swapped_sides_seen_through_head_motion(samples):
    """The scans turned by a few degrees and shifted by millimetres between frames (the head moves while
    the phone records): each frame is placed on the neutral first. Before, 5 degrees hid the swap (a
    review)."""
    from scipy.spatial.transform import Rotation

    from usdface.io import read_capture
    from usdface.personalize.api import swapped_sides

    cap = read_capture(samples / "capture.usda")
    names = list(cap.names)
    train = cap.train
    rng = np.random.default_rng(4)
    turn = Rotation.from_rotvec(rng.normal(size=(len(train.weights), 3)) * np.radians(5.0) / np.sqrt(3))
    c = cap.neutral.mean(axis=0)
    moved = (np.einsum("fij,fnj->fni", turn.as_matrix(), train.points - c) + c
             + rng.normal(size=(len(train.weights), 1, 3)) * 0.002)
    perm = [names.index(mirror_name(k)) for k in names]
    assert swapped_sides(moved, cap.neutral, cap.template.deltas, train.weights, names) is None
    found = swapped_sides(moved, cap.neutral, cap.template.deltas, train.weights[:, perm], names)
    assert found is not None and found["swapped_mm"] < 0.5 * found["reported_mm"]

