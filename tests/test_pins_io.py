"""Artist pins from a file (usdface.io.pins): JSON and USD primvars, spellings, errors, and through
``usdface fit --pins``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from usdface.errors import InputFileError
from usdface.io.pins import read_pins

NAMES = ["eyeBlinkLeft", "jawOpen", "mouthClose"]


def test_json_pins_any_spelling_merged_and_sorted(tmp_path):
    f = tmp_path / "pins.json"
    f.write_text(json.dumps({"pins": {"eyeBlink_L": [5, 2], "EyeBlinkLeft": [2, 9], "jawOpen": []}}))
    pins = read_pins(f, NAMES, 10)
    assert set(pins) == {"eyeBlinkLeft", "jawOpen"}
    assert pins["eyeBlinkLeft"].tolist() == [2, 5, 9] and pins["jawOpen"].size == 0
    f.write_text(json.dumps({"mouthClose": [0]}))                      # the inner mapping alone
    assert read_pins(f, NAMES, 10)["mouthClose"].tolist() == [0]
    f.write_text(json.dumps({"comment": "by Ann", "pins": {"jawOpen": [1]}}))     # other keys: notes
    assert read_pins(f, NAMES, 10)["jawOpen"].tolist() == [1]


@pytest.mark.parametrize("doc, match", [
    ({"pins": {"browInnerUp": [1]}}, "lacks"),
    ({"pins": {"jawOpen": [10]}}, "outside"),
    ({"pins": {"jawOpen": [1.5]}}, "not a list"),
    ([1, 2], "not a mapping"),
    # another JSON file (the retarget map) said "pins name a shape the capture lacks: 'format'"
    ({"format": "usdface.retarget/1", "source": ["jawOpen"]}, "not a pins file"),
    # "pins" as a list said "pins name a shape the capture lacks: 'pins'"
    ({"pins": [1, 2]}, '"pins" is a list, not a mapping'),
    # a shape beside the "pins" mapping was dropped without a word (the artist's jawOpen pins lost)
    ({"jawOpen": [3], "pins": {"mouthClose": [4]}}, "'jawOpen' beside the \"pins\" mapping"),
])
def test_json_pins_errors_name_the_file_and_the_fix(tmp_path, doc, match):
    f = tmp_path / "pins.json"
    f.write_text(json.dumps(doc))
    with pytest.raises(InputFileError, match=match) as err:
        read_pins(f, NAMES, 10)
    assert str(f) in str(err.value) and "fix:" in str(err.value)


def test_missing_or_broken_pins_file(tmp_path):
    with pytest.raises(InputFileError, match="not found"):
        read_pins(tmp_path / "nope.json", NAMES, 10)
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(InputFileError, match="cannot read pins"):
        read_pins(bad, NAMES, 10)


def _usd_with_primvars(path, n, values: dict, interpolation="vertex"):
    from pxr import Sdf, Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(path))
    mesh = UsdGeom.Mesh.Define(stage, "/Capture/Template/Mesh")
    mesh.CreatePointsAttr([(float(i), 0.0, 0.0) for i in range(n)])
    api = UsdGeom.PrimvarsAPI(mesh)
    for name, vals in values.items():
        pv = api.CreatePrimvar(f"usdface:pin:{name}", Sdf.ValueTypeNames.FloatArray, interpolation)
        pv.Set([float(v) for v in vals])
    stage.GetRootLayer().Save()


def test_usd_primvar_pins(tmp_path):
    f = tmp_path / "painted.usda"
    _usd_with_primvars(f, 6, {"jawOpen": [0, 1, 0.2, 0.9, 0, 0], "eyeBlink_L": [1, 0, 0, 0, 0, 1]})
    pins = read_pins(f, NAMES, 6)
    assert pins["jawOpen"].tolist() == [1, 3] and pins["eyeBlinkLeft"].tolist() == [0, 5]
    wrong = tmp_path / "wrong.usda"
    _usd_with_primvars(wrong, 6, {"jawOpen": [0, 1, 0]})
    with pytest.raises(InputFileError, match="expected 6 per vertex") as err:
        read_pins(wrong, NAMES, 6)
    assert "/Capture/Template/Mesh" in str(err.value)
    none = tmp_path / "none.usda"
    _usd_with_primvars(none, 6, {})
    with pytest.raises(InputFileError, match="no usdface:pin"):
        read_pins(none, NAMES, 6)


def test_fit_command_pins_from_a_json_file(samples, tmp_path):
    from usdface.cli import main
    from usdface.io import read_capture
    from usdface.io.usd_rig import read_avatar

    cap = read_capture(samples / "capture.usda")
    k = cap.names.index("jawOpen")
    moving = np.flatnonzero(np.linalg.norm(cap.template.deltas[k], axis=1) > 1e-3)[:20]
    f = tmp_path / "pins.json"
    f.write_text(json.dumps({"pins": {"jawOpen": moving.tolist()}}))
    out = tmp_path / "rig.usda"
    args = ["fit", str(samples / "capture.usda"), "-o", str(out), "--reg", "0.01", "--no-align",
            "--no-reweight", "-q"]
    assert main(args + ["--pins", str(f)]) == 0
    rig = read_avatar(out).meshes[0]
    fitted = rig.deltas[rig.names.index("jawOpen")]
    assert np.abs(fitted[moving] - cap.template.deltas[k, moving]).max() < 1e-6     # float32 file
    assert main(args + ["--force"]) == 0                                            # without pins
    free = read_avatar(out).meshes[0].deltas[rig.names.index("jawOpen")]
    assert np.abs(free[moving] - cap.template.deltas[k, moving]).max() > 1e-4
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"pins": {"jawOpen": [10 ** 6]}}))
    assert main(args + ["--force", "--pins", str(bad)]) == 2


def test_fit_rig_records_its_pins_file_relative_to_the_rig(samples, tmp_path, monkeypatch, capsys):
    """A user trial: ``fit CAPTURE -o sub/rig.usda --pins pins.json`` recorded ``parameters.pins`` as typed
    ('pins.json', relative to the folder the command ran in) beside the capture recorded relative to the rig
    ('../...'): from the rig's folder it named a file that is not there, and no digest said whether the pins
    changed. Recorded as the capture is now: relative to the rig, with ``pinsDigest``."""
    from pxr import Sdf

    from usdface.cli import main
    from usdface.io.layers import file_digest

    f = tmp_path / "pins.json"
    f.write_text(json.dumps({"pins": {"jawOpen": [12, 13]}}))
    (tmp_path / "sub").mkdir()
    monkeypatch.chdir(tmp_path)
    assert main(["fit", str(samples / "capture.usda"), "-o", "sub/rig.usda", "--reg", "0.01", "--no-align",
                 "--no-reweight", "-q", "--pins", "pins.json"]) == 0
    data = Sdf.Layer.FindOrOpen(str(tmp_path / "sub" / "rig.usda")).customLayerData["usdface"]
    assert data["parameters"]["pins"] == "../pins.json"
    assert (tmp_path / "sub" / data["parameters"]["pins"]).resolve() == f.resolve()
    assert data["pinsDigest"] == file_digest(f)
    assert main(["inspect", "sub/rig.usda"]) == 0
    assert f"pins ../pins.json sha256 {file_digest(f)[:16]}" in capsys.readouterr().out


def test_misspelt_pin_shape_names_the_shape_meant(tmp_path):
    """A user trial (stop 52): ``--pins`` with ``jawOpne`` said only "pins name a shape the capture lacks:
    'jawOpne'" where ``render --shapes``, ``--name-map`` and the capture folder's weights name the shape
    meant; an ARKit shape the capture does not have (dev3 has no tongueOut) is told as such, with no guess."""
    f = tmp_path / "pins.json"
    f.write_text(json.dumps({"pins": {"jawOpne": [1]}}))
    with pytest.raises(InputFileError, match=r"did you mean 'jawOpen'") as err:
        read_pins(f, NAMES, 10)
    assert "pins.json" in str(err.value)
    f.write_text(json.dumps({"pins": {"tongueOut": [1]}}))
    with pytest.raises(InputFileError, match="lacks: 'tongueOut'") as err:
        read_pins(f, NAMES, 10)
    assert "did you mean" not in str(err.value) and "eyeBlinkLeft, jawOpen, mouthClose" in str(err.value)
