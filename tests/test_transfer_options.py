"""The transfer options as the Python API, ``usdface personalize`` and ``usdface batch`` take them: one rule
for each mode's default approximation, options a mode does not use refused, the provenance of what was
given (user trial findings; each test failed before its fix)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import _no_traceback, _usdface

import usdface.io  # noqa: F401  (registers the schemas before a test opens a stage)
from usdface.cli import main
from usdface.transfer.options import MODE_OPTIONS

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


def _layer_offsets(path) -> dict:
    """{attribute path: offsets[n,3]} of every ``offsets`` the layer authors (both variants)."""
    from pxr import Sdf

    layer, found = Sdf.Layer.FindOrOpen(str(path)), {}

    def visit(p):
        if p.IsPropertyPath() and p.name == "offsets":
            found[str(p)] = np.asarray(layer.GetAttributeAtPath(p).default, dtype=np.float64)

    layer.Traverse("/", visit)
    return found


@pytest.mark.parametrize("mode", ["person", "offset", "dt", "dt-offset"])
def test_every_face_transfer_mode_has_its_default_approximation_in_the_api(mode):
    """``face_transfer='offset'`` (any older mode) without an approximation was refused by the API and by a
    batch row ("'offset' and approximation 'field' do not go together") while the CLI chose 'generic'."""
    from usdface import api
    from usdface.transfer.options import default_approximation

    assert default_approximation(mode) == ("field" if mode == "person" else "generic")
    api.check_personalize_options(face_transfer=mode)           # batch's check of a row: passes


def test_the_api_and_the_cli_give_the_same_layer_for_an_older_mode(tmp_path, capsys):
    """``usdface personalize --face-transfer offset`` and ``usdface.personalize_avatar(...,
    face_transfer='offset')`` write the same offsets and record the same resolved approximation."""
    import usdface
    from usdface.io.usd_rig import usdface_output_provenance

    cli, py = tmp_path / "cli.usda", tmp_path / "api.usda"
    assert main(["personalize", str(A), str(C), "-o", str(cli), "--face-transfer", "offset", "-q"]) == 0
    result = usdface.personalize_avatar(A, C, py, face_transfer="offset")
    assert result.report["options"]["approximation"] == "generic"
    a, b = _layer_offsets(cli), _layer_offsets(py)
    assert a and a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    for layer in (cli, py):
        params = usdface_output_provenance(layer)["parameters"]
        assert params["approximation"] == "generic"
        # the options the mode uses, with their defaults; not the person field's extension_length
        assert params["falloff"] == 0.15 and "support" in params and "extension_length" not in params


def test_the_report_lists_only_the_options_the_mode_uses():
    """The report (and so the provenance's parameters) listed extension_length, falloff and support
    whatever the mode: falloff 0.15 on a person-mode layer, which no falloff shaped."""
    import usdface

    options = usdface.personalize_avatar(A, C, None, dry_run=True).report["options"]
    assert options["extension_length"] == 1.0 and options["support"] == (0.01, 0.03)
    assert "falloff" not in options


# ------------------------------------------------------------------ options a mode (or a command) ignores
@pytest.mark.parametrize("mode, option", [
    ("person", {"falloff": 0.3}),
    ("dt", {"support": (0.01, 0.03)}),
    ("offset", {"extension_length": 2.0}),
    ("dt-offset", {"extension_length": None}),
])
def test_the_api_refuses_an_option_the_mode_does_not_use(tmp_path, monkeypatch, mode, option):
    """``falloff=0.3`` with the default ``person`` transfer was silently ignored (the same layer as without
    it): refused before any work, naming the option and the mode in both spellings and the fix."""
    from usdface import api
    from usdface.errors import OptionError
    from usdface.transfer import pipeline

    monkeypatch.setattr(pipeline, "crop_avatar", lambda *a, **k: pytest.fail("work started"))
    (name,) = option
    flag = {"support": "Python API only"}.get(name, "--" + name.replace("_", "-"))
    for call in (lambda: api.personalize_avatar(A, C, tmp_path / "p.usda", face_transfer=mode, **option),
                 lambda: api.check_personalize_options(face_transfer=mode, **option)):     # a batch row
        with pytest.raises(OptionError) as err:
            call()
        text = str(err.value)
        assert f"{name} ({flag}) is not used by face_transfer (--face-transfer) {mode!r}" in text
        assert "fix: drop" in text and all(m in text.split("fix:")[1] for m, used in
                                           MODE_OPTIONS.items() if name in used)
    assert not (tmp_path / "p.usda").exists()


def test_the_options_each_mode_uses_pass():
    from usdface import api
    from usdface.transfer.options import MODE_OPTIONS

    values = {"extension_length": 2.0, "falloff": 0.3, "support": (0.02, 0.04)}
    for mode, used in MODE_OPTIONS.items():
        api.check_personalize_options(face_transfer=mode, **{k: values[k] for k in used})


def test_the_cli_refuses_an_option_the_mode_does_not_use(tmp_path, capsys, monkeypatch):
    """``usdface personalize --falloff 0.3`` (person) ran as without it; refused (exit 2) before any work.
    The defaults themselves are not "given": the older modes run without ``--falloff``, ``person`` without
    ``--extension-length``."""
    from usdface.transfer import pipeline

    monkeypatch.setattr(pipeline, "crop_avatar", lambda *a, **k: pytest.fail("work started"))
    base = ["personalize", str(A), str(C), "-o", str(tmp_path / "p.usda"), "-q"]
    assert main([*base, "--falloff", "0.3"]) == 2
    err = capsys.readouterr().err
    assert "falloff (--falloff) is not used by face_transfer (--face-transfer) 'person'" in err
    assert main([*base, "--face-transfer", "dt", "--extension-length", "2"]) == 2
    assert "extension_length (--extension-length) is not used by" in capsys.readouterr().err
    assert not (tmp_path / "p.usda").exists()


def test_retarget_offers_and_takes_no_implant_option(tmp_path, capsys):
    """``usdface retarget`` offered --face-transfer, --approximation, --falloff, --extension-length and
    --no-eyelids and ignored them (the map is eq. 4 of the fitted shapes); the writer refuses them from a
    script too."""
    from usdface import api
    from usdface.errors import OptionError

    with pytest.raises(SystemExit):
        main(["retarget", "--help"])
    helptext = capsys.readouterr().out
    for flag in ("--face-transfer", "--approximation", "--falloff", "--extension-length", "--no-eyelids"):
        assert flag not in helptext
    assert "--weight-bounds" in helptext and "--mu" in helptext
    out = tmp_path / "map.json"
    with pytest.raises(SystemExit) as code:
        main(["retarget", str(A), str(C), "-o", str(out), "--falloff", "0.3"])
    assert code.value.code == 2
    assert "unrecognized arguments: --falloff" in capsys.readouterr().err
    with pytest.raises(OptionError, match=r"face_transfer \(--face-transfer\).*not used by the retarget map"):
        api.write_retarget_map(A, C, out, face_transfer="dt")
    assert not out.exists()


# ------------------------------------------------------------------ weight bounds
@pytest.mark.parametrize("bounds", [["0", "inf"], ["nan", "1"], ["0", "Infinity"]])
def test_a_non_finite_weight_bound_points_to_unbounded(tmp_path, capsys, bounds):
    """``--weight-bounds 0 inf`` ("no upper bound") said "bad weight bounds 0 inf (fix: give LO < HI, e.g.
    0 1 (or --unbounded))"; refused by the argument parser, saying that no bounds is ``--unbounded``."""
    for command in ("personalize", "retarget"):
        with pytest.raises(SystemExit) as code:
            main([command, str(A), str(C), "-o", str(tmp_path / "o.json"), "--weight-bounds", *bounds])
        assert code.value.code == 2
        err = capsys.readouterr().err
        assert "--weight-bounds" in err and "for no bounds use --unbounded" in err


@pytest.mark.parametrize("bounds", [(0.0, float("inf")), (float("-inf"), 1.0), (float("nan"), 1.0)])
def test_the_api_refuses_a_non_finite_weight_bound(tmp_path, bounds):
    from usdface import api
    from usdface.errors import OptionError

    for call in (lambda: api.write_retarget_map(A, C, tmp_path / "m.json", weight_bounds=bounds),
                 lambda: api.check_personalize_options(weight_bounds=bounds)):
        with pytest.raises(OptionError, match=r"weight_bounds \(--weight-bounds\) must be finite") as err:
            call()
        assert "for no bounds use weight_bounds=None (--unbounded)" in str(err.value)
    assert not (tmp_path / "m.json").exists()


# ------------------------------------------------------------------ provenance of what the user gave
def test_the_layer_records_the_contact_option_and_the_artist_pins(tmp_path, capsys):
    """A layer personalized with ``--contact on --pins pins.json`` recorded neither: not the contact mode
    among its parameters, not the pins, and not the pins file among its inputs (an edited pins file left the
    layer "up to date"). The pins file is an input with its digest, as the capture is."""
    from usdface.io.layers import file_digest, stale_inputs
    from usdface.io.usd_rig import usdface_output_provenance

    pins = tmp_path / "pins.json"
    pins.write_text('{"pins": {"jawOpen": [0, 1, 2]}}')
    out = tmp_path / "p.usda"
    assert main(["personalize", str(A), str(C), "-o", str(out), "-q", "--contact", "on", "--pins",
                 str(pins)]) == 0
    prov = usdface_output_provenance(out)
    assert prov["parameters"]["contact"] == "on"
    assert dict(prov["pins"]) == {"jawOpen": 3}
    recorded = dict(zip(prov["inputs"], prov["inputDigests"], strict=True))
    assert recorded.get("pins.json") == file_digest(pins)
    assert stale_inputs(out) == []
    pins.write_text('{"pins": {"jawOpen": [0, 1]}}')
    assert any("pins.json" in s for s in stale_inputs(out))


def test_read_pins_remembers_its_file(tmp_path):
    from usdface.io.pins import Pins, read_pins

    pins = tmp_path / "p.json"
    pins.write_text('{"jawOpen": [4, 2]}')
    got = read_pins(pins, ["jawOpen", "eyeBlinkLeft"], 10)
    assert isinstance(got, Pins) and isinstance(got, dict) and got.source == pins
    assert list(got) == ["jawOpen"] and got["jawOpen"].tolist() == [2, 4]


def test_weight_bounds_and_unbounded_are_not_given_together(tmp_path, capsys):
    """``--weight-bounds 0 2 --unbounded`` ran unbounded: the bounds given were dropped without a word."""
    for command in ("personalize", "retarget"):
        with pytest.raises(SystemExit) as code:
            main([command, str(A), str(C), "-o", str(tmp_path / "o.json"), "--weight-bounds", "0", "2",
                  "--unbounded"])
        assert code.value.code == 2
        assert "not allowed with argument" in capsys.readouterr().err


def test_a_batch_wide_join_option_goes_to_the_rows_whose_mode_uses_it(tmp_path, monkeypatch):
    """Review: ``batch --set falloff=0`` over a manifest of ``offset`` and ``person`` rows stopped the whole
    batch (the person row 'gave' falloff). A batch-wide join option now goes to the rows whose mode uses it;
    one that no row uses is refused (it would change nothing); a row's own column is still checked."""
    from usdface import api
    from usdface.errors import InputFileError
    from usdface.pipeline import batch

    manifest = tmp_path / "m.json"
    rows = [{"avatar": str(A), "capture": str(C),
             "output": str(tmp_path / f"{name}.usda"), **extra}
            for name, extra in (("a", {"face_transfer": "offset"}), ("b", {}))]
    manifest.write_text(json.dumps(rows))
    seen = {}

    def fake_run(items, **kw):
        seen["options"] = [dict(item.options) for item in items]
        raise KeyboardInterrupt

    monkeypatch.setattr(batch, "run_batch", fake_run)
    with pytest.raises(KeyboardInterrupt):
        api.personalize_batch(manifest, options={"falloff": 0.0, "mu": 0.01})
    assert seen["options"] == [{"falloff": 0.0, "mu": 0.01, "face_transfer": "offset"}, {"mu": 0.01}]
    with pytest.raises(InputFileError, match="extension_length .* no row's face_transfer uses it") as info:
        api.personalize_batch(manifest, options={"extension_length": 2.0, "face_transfer": "offset"})
    assert "extension_length (--extension-length): person" in info.value.fix
    rows[1]["falloff"] = 0.1                                      # a person row's own falloff: refused
    manifest.write_text(json.dumps(rows))
    with pytest.raises(InputFileError, match="item 2: falloff .* is not used by"):
        api.personalize_batch(manifest)


def test_a_batch_wide_option_every_row_overrides_is_refused(tmp_path):
    """``batch --set falloff=0.2`` over a manifest whose only ``offset`` row has its own ``falloff`` (and
    ``--set method=dt`` where every row names its method) ran the batch with the option reaching no row,
    silently: manifest columns win. Refused before any work, as an option no row's mode uses is."""
    from usdface import api
    from usdface.errors import InputFileError

    manifest = tmp_path / "m.json"
    rows = [{"avatar": str(A), "capture": str(C), "output": str(tmp_path / f"{name}.usda"), **extra}
            for name, extra in (("a", {"face_transfer": "offset", "falloff": 0.3, "method": "menzel"}),
                                ("b", {"method": "menzel"}))]
    manifest.write_text(json.dumps(rows))
    for options, name in (({"falloff": 0.2}, "falloff"), ({"method": "dt"}, "method")):
        with pytest.raises(InputFileError, match=f"--set {name}=.* reaches no row: every row") as info:
            api.personalize_batch(manifest, options=options)
        assert "manifest columns win" in str(info.value)
    assert not list(tmp_path.glob("*.usda"))


def test_personalize_avatar_landmarks_alone_writes_the_landmarks(samples, tmp_path):
    """``personalize_avatar(..., landmarks=True)`` without ``inspect=True`` wrote a layer without landmarks
    and said nothing (so did a batch row or a Pyblish ``usdfaceOptions`` with ``landmarks``), where
    ``usdface personalize --landmarks`` implies ``--inspect``, as ``take=`` does in the API."""
    pytest.importorskip("usdface.transfer")
    from pxr import Usd

    from usdface import api

    out = api.personalize_avatar(samples / "avatar.usda", samples / "capture.usda", tmp_path / "p.usda",
                                 landmarks=True, method="dt").out_path
    stage = Usd.Stage.Open(str(out))
    points = [p for p in stage.Traverse() if p.GetTypeName() == "Points"]
    assert points and points[0].GetName().endswith("_landmarks")


def test_face_mesh_mouth_says_the_capture_collapsed_not_a_perfect_residual(sample_dir, tmp_path):
    res = _usdface("personalize", sample_dir / "avatar.usda", sample_dir / "capture.usda",
                   "--face-mesh", "Mouth", "--dry-run", cwd=tmp_path)
    _no_traceback(res)
    assert "shrank the capture to a point" in res.stderr and "--face-mesh" in res.stderr
    assert "residual 0.00 mm" not in res.stderr and "100% of capture vertices" not in res.stderr


def test_face_mesh_mouth_on_a_production_avatar_names_the_skin_meshes(shared, tmp_path, capfd):
    """User trial: ``--face-mesh Mouth`` on dev1 (the capture registers, but covers none of the mouth
    socket) said "no avatar vertex lies on the registered capture surface (empty face region) (fix: check that
    the capture and the avatar are faces)": they were. The message says the chosen mesh has no vertex the
    capture covers and names the skin mesh to pick."""
    from usdface.cli import main

    bench = shared / "data" / "bench" / "dev1"
    code = main(["personalize", str(bench / "avatar.usdc"), str(bench / "capture"), "--face-mesh", "Mouth",
                 "--dry-run", "-q"])
    err = capfd.readouterr().err
    assert code == 2 and "prim /Avatar/Mouth" in err, err
    assert "empty face region" not in err and "are faces" not in err
    assert "--face-mesh has no vertex the capture covers" in err
    assert "pick the skin mesh with --face-mesh (candidates: /Avatar/Head (" in err
    assert "without --face-mesh usdface picks /Avatar/Head" in err


def test_empty_face_region_error_lists_the_meshes_the_shapes_move(samples):
    from usdface.errors import RigError
    from usdface.io.usd_rig import read_avatar
    from usdface.transfer.pipeline import empty_face_region

    avatar = read_avatar(samples / "avatar.usda")
    names = ["jawOpen", "eyeBlinkLeft", "mouthSmileLeft"]
    chosen = empty_face_region(avatar.file, avatar.meshes, "/Avatar/Mouth", names, chosen=True)
    assert isinstance(chosen, RigError) and chosen.prim == "/Avatar/Mouth"
    assert "no vertex the capture covers" in chosen.message
    assert chosen.fix.startswith("pick the skin mesh with --face-mesh (candidates: /Avatar/Head (")
    assert "/Avatar/Mouth (" not in chosen.fix                          # not the mesh that failed
    auto = empty_face_region(avatar.file, avatar.meshes, "/Avatar/Head", names, chosen=False)
    assert "same face" in auto.fix and "--face-mesh" in auto.fix and "/Avatar/Head (" not in auto.fix


@pytest.mark.parametrize("name, module", [("option_name", "options"), ("FACE_TRANSFERS", "options"),
                                          ("pose_by_length", "face_map"), ("LIP_SHAPES", "report")])
def test_names_moved_out_of_the_pipeline_module_still_import_with_a_warning(name, module):
    """transfer/pipeline.py was split by concept (stop 33): a studio script that imports a moved name from
    ``usdface.transfer.pipeline`` gets the object from its new module, with a DeprecationWarning naming it;
    an unknown name is still an AttributeError."""
    import importlib

    from usdface.transfer import pipeline

    with pytest.warns(DeprecationWarning, match=f"moved to usdface.transfer.{module}.{name}"):
        got = getattr(pipeline, name)
    assert got is getattr(importlib.import_module(f"usdface.transfer.{module}"), name)
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        pipeline.not_a_name  # noqa: B018
