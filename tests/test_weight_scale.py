"""Weights on another scale than ARKit's 0..1 (a capture or take converted from a tool that writes percent)
are refused naming the file, the largest weight and the fix, before any output: until stop 45 every weight
above 1 was clipped to 1 with a warning, so a percent capture was fitted as every shape at full strength
(train RMSE 2.0 mm against the same capture's 0.2) and a percent take played every shape at 1."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from usdface.cli import main


def test_a_percent_capture_is_refused_by_fit(sample_capture_folder, tmp_path, capsys):
    capture = tmp_path / "pct"
    shutil.copytree(sample_capture_folder, capture)
    for path in capture.rglob("*.json"):
        data = json.loads(path.read_text())
        data["blendShapes"] = {k: v * 100 for k, v in data["blendShapes"].items()}
        path.write_text(json.dumps(data))
    out = tmp_path / "rig.usda"
    assert main(["fit", str(capture), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "ARKit weights run from 0 to 1" in err and "percent" in err, err
    assert "fix: divide every frame's weights by 100" in err and ".json: weight " in err
    assert not out.exists()


def test_a_percent_live_link_take_is_refused_by_anim_import(shared, tmp_path, capsys):
    src = shared / "data" / "livelinkface" / "alex_rom_4.csv"
    if not src.exists():
        pytest.skip("no Live Link takes in ../shared")
    lines = src.read_text().splitlines()
    header = lines[0].split(",")
    weight_cols = [i for i, name in enumerate(header) if name not in ("Timecode", "BlendShapeCount")][:52]
    rows = [lines[0]]
    for line in lines[1:]:
        cells = line.split(",")
        for i in weight_cols:
            cells[i] = repr(float(cells[i]) * 100)
        rows.append(",".join(cells))
    take = tmp_path / "pct.csv"
    take.write_text("\n".join(rows) + "\n")
    out = tmp_path / "take.usda"
    assert main(["anim", "import", str(take), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "pct.csv: weight " in err and "(percent, 0..100?)" in err, err
    assert "divide the CSV's weights by 100" in err
    assert not out.exists()


def test_an_overshooting_phone_weight_is_still_clipped(sample_capture_folder, tmp_path):
    """A phone's few per cent over 1 (1.059 in the real takes) is clipped with a warning, as before."""
    from usdface.io import read_capture

    capture = tmp_path / "over"
    shutil.copytree(sample_capture_folder, capture)
    js = sorted((capture / "train").glob("*.json"))[0]
    data = json.loads(js.read_text())
    name = next(iter(data["blendShapes"]))
    data["blendShapes"][name] = 1.06
    js.write_text(json.dumps(data))
    with pytest.warns(UserWarning, match="clipped"):
        got = read_capture(capture)
    assert np.max(got.frames.weights) == 1.0


def test_a_percent_usd_take_is_refused_not_played_at_full_strength(shared, tmp_path, capsys):
    """A SkelAnimation take in percent was clipped without a word: every shape played at 1."""
    from pxr import Usd, UsdSkel, Vt

    src = shared / "data" / "livelinkface" / "alex_rom_4.csv"
    if not src.exists():
        pytest.skip("no Live Link takes in ../shared")
    take = tmp_path / "take.usda"
    assert main(["anim", "import", str(src), "-o", str(take), "-q"]) == 0
    stage = Usd.Stage.Open(str(take))
    anim = next(UsdSkel.Animation(p) for p in stage.Traverse() if p.IsA(UsdSkel.Animation))
    attr = anim.GetBlendShapeWeightsAttr()
    for t in attr.GetTimeSamples():
        attr.Set(Vt.FloatArray([w * 100 for w in attr.Get(t)]), t)
    stage.Save()
    del stage
    capsys.readouterr()
    assert main(["capture", "select", str(take), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "take.usda, prim /Take: weight 100 (time " in err, err
    assert "divide the take's weights by 100" in err
