"""The API functions the thin CLI calls (write_fit_rig, evaluate_methods, write_capture,
select_capture_frames, import_livelink_take, pick_mesh, write_landmarks, evaluate_landmarks,
write_retarget_map): what they write reads back exactly, outputs are refused before any work, and the
commands pass their options through."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import usdface
from usdface import api
from usdface.cli import main
from usdface.errors import CaptureError, FitError, InputFileError, LandmarkError, OutputExistsError, RigError


@pytest.fixture(scope="module")
def capture(samples):
    return usdface.read_capture(samples / "capture.usda")


@pytest.fixture(scope="module")
def avatar(samples):
    return usdface.read_avatar(samples / "avatar.usda")


def _forbid(monkeypatch, module, name):
    def fail(*a, **k):
        raise AssertionError(f"{name} must not run when the output is refused")

    monkeypatch.setattr(module, name, fail)


def test_pick_mesh(avatar):
    assert usdface.pick_mesh(avatar).source.prim == "/Avatar/Head"       # most shapes
    assert usdface.pick_mesh(avatar, "Mouth").n_shapes == 5
    assert usdface.pick_mesh(avatar, "/Avatar/Mouth").name == "Mouth"
    with pytest.raises(RigError) as err:
        usdface.pick_mesh(avatar, "Nose")
    assert "avatar.usda" in str(err.value) and "/Avatar/Head" in err.value.fix
    with pytest.raises(RigError, match="no mesh with blend shapes"):
        usdface.pick_mesh(dataclasses.replace(avatar, meshes=[]))


def test_write_capture_round_trips_and_records_the_source(capture, samples, tmp_path):
    folder = usdface.write_capture(capture, tmp_path / "cap")
    usd = usdface.import_capture_folder(folder, tmp_path / "cap.usda")
    again = usdface.read_capture(usd)
    np.testing.assert_array_equal(again.neutral, capture.neutral)     # exact=True: bit-exact
    np.testing.assert_array_equal(again.frames.points, capture.frames.points)
    assert again.names == capture.names and list(again.frames.role) == list(capture.frames.role)
    from pxr import Usd

    from usdface.io.layers import file_digest

    stage = Usd.Stage.Open(str(usd))
    digests = [a.Get() for p in stage.Traverse() for a in p.GetAttributes()
               if a.GetName() == "usdface:capture:sourceDigest"]
    assert digests == [file_digest(folder)]
    with pytest.raises(OutputExistsError):
        usdface.write_capture(capture, usd)
    with pytest.raises(OutputExistsError):
        usdface.write_capture(capture, folder)


def test_fit_capture_writes_the_rig_and_refuses_before_fitting(capture, tmp_path, monkeypatch):
    out = tmp_path / "rig.usda"
    fit = usdface.fit_capture(capture, "dt", out_path=out)
    assert fit.info["out_path"] == out and out.exists()
    rig = usdface.pick_mesh(usdface.read_avatar(out))
    np.testing.assert_allclose(rig.neutral, fit.rig.neutral, atol=1e-6)
    np.testing.assert_allclose(rig.subset(fit.rig.names).deltas, fit.rig.deltas, atol=1e-6)
    import usdface.personalize as personalize

    _forbid(monkeypatch, personalize, "fit_personalized_shapes")
    with pytest.raises(OutputExistsError):
        usdface.fit_capture(capture, "dt", out_path=out)
    again = usdface.write_fit_rig(fit.rig, tmp_path / "rig2.usdc")   # a FaceRig is accepted too
    np.testing.assert_allclose(usdface.pick_mesh(usdface.read_avatar(again)).neutral, rig.neutral, atol=1e-6)


def test_evaluate_methods_matches_evaluate_capture(capture, tmp_path):
    report = usdface.evaluate_methods(capture, ["dt"], json_path=tmp_path / "r.json")
    single = usdface.evaluate_capture(capture, usdface.fit_capture(capture, "dt"))
    np.testing.assert_allclose(report["methods"]["dt"]["rmse_mm"], single["rmse_mm"], rtol=1e-9)
    assert report["_outputs"] == {"json": tmp_path / "r.json"} and (tmp_path / "r.json").exists()
    with pytest.raises(OutputExistsError):
        usdface.evaluate_methods(capture, ["dt"], json_path=tmp_path / "r.json")
    no_test = dataclasses.replace(capture, frames=capture.frames.select("train"))
    with pytest.raises(FitError, match="no test frames"):
        usdface.evaluate_methods(no_test, ["dt"])
    with pytest.raises(InputFileError) as err:
        usdface.evaluate_methods(capture, ["dt"], truth=tmp_path / "missing.npz")
    assert "missing.npz" in str(err.value) and err.value.fix


def _grid_take(tmp_path):
    from test_take_select import SKIP, grid_rigs

    from usdface.io.take import write_take_usd
    from usdface.sample.take import make_take

    person, template = grid_rigs()
    take, _ = make_take(person, template, skip=SKIP, seed=3)
    return write_take_usd(take, tmp_path / "take.usda"), take


def test_select_capture_frames(tmp_path):
    from usdface.take_select import select_frames

    path, take = _grid_take(tmp_path)
    dry = usdface.select_capture_frames(path, threshold=0.5, min_separation=0.5)
    assert dry.capture is None and dry.out_path is None and "jawLeft" in dry.coverage
    expected = select_frames(take.weights, names=take.names, min_separation=max(1, round(0.5 * take.fps)))
    assert dry.selection.train.tolist() == expected.train.tolist()
    out = tmp_path / "cap"
    # (the take's 1 s sweeps: frames 0.5 s from their peaks are rests, never test frames since stop 52)
    res = usdface.select_capture_frames(path, out, test_every=4, min_separation=0.2)
    assert res.out_path == out and (out / "neutral.obj").exists()
    back = usdface.read_capture(out)
    assert len(back.train) == len(res.selection.train) and len(back.test) == len(res.selection.test) > 0
    with pytest.raises(OutputExistsError):
        usdface.select_capture_frames(path, out, test_every=4, min_separation=0.2)
    with pytest.raises((CaptureError, InputFileError)):
        usdface.select_capture_frames(tmp_path / "nope.usda")


def test_import_livelink_take(tmp_path):
    from pxr import Usd

    from usdface.io.livelink import write_livelink_csv
    from usdface.io.usd_anim import read_skel_animation

    rng = np.random.default_rng(2)
    names = ["jawOpen", "eyeBlinkLeft", "mouthSmileRight"]
    weights, times = rng.random((6, 3)), np.arange(6) / 30.0
    csv = write_livelink_csv(tmp_path / "t.csv", names, weights, times, timecode_rate=30.0)
    out, take = usdface.import_livelink_take(csv, tmp_path / "t.usda", timecode_rate=30.0)
    stage = Usd.Stage.Open(str(out))
    got_names, got, codes = read_skel_animation(stage.GetDefaultPrim())
    assert stage.GetTimeCodesPerSecond() == 30
    np.testing.assert_allclose(got[:, [got_names.index(n) for n in names]],
                               take.weights[:, [take.names.index(n) for n in names]], atol=1e-7)
    np.testing.assert_allclose(take.weights[:, [take.names.index(n) for n in names]], weights, atol=1e-3)
    np.testing.assert_array_equal(codes, np.arange(6))
    with pytest.raises(OutputExistsError):
        usdface.import_livelink_take(csv, out, timecode_rate=30.0)


def test_write_landmarks_reads_back(avatar, tmp_path):
    from usdface.io.usd_inspection import read_landmarks

    head = usdface.pick_mesh(avatar)
    rig = head.subset(["jawOpen", "eyeBlinkLeft", "mouthSmileLeft"])
    layout = usdface.compute_landmarks(rig, rays=2, time_limit=10)
    out = usdface.write_landmarks(avatar, rig, layout, tmp_path / "lm.usda")
    assert read_landmarks(out)["/Avatar/Head"].tolist() == np.asarray(layout.vertices).tolist()
    with pytest.raises(OutputExistsError):
        usdface.write_landmarks(avatar, rig, layout, out)


def test_evaluate_methods_that_fail_part_way_leave_no_new_output(capture, tmp_path, monkeypatch):
    """The report, the plot and the error maps are all or nothing: a plot that failed (a full disk, Ctrl-C)
    after the JSON report was written left that report behind, as if the run had finished."""
    import usdface.personalize.report as report_module

    def fail(*_a, **_k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(report_module, "plot_errors", fail)
    with pytest.raises(OSError, match="No space"):
        usdface.evaluate_methods(capture, ["dt"], json_path=tmp_path / "r.json", plot_path=tmp_path / "p.png")
    assert list(tmp_path.iterdir()) == []


def test_evaluate_landmarks_inputs(avatar, tmp_path):
    from usdface.io.livelink import write_livelink_csv

    rig = usdface.pick_mesh(avatar).subset(["jawOpen", "eyeBlinkLeft"])
    with pytest.raises(LandmarkError, match="test weights"):
        usdface.evaluate_landmarks(rig, [])
    bad = tmp_path / "bad.json"
    bad.write_text('{"something": 1}')
    csv = write_livelink_csv(tmp_path / "t.csv", ["jawOpen", "cheekPuff"], np.full((4, 2), 0.5),
                             np.arange(4) / 60)
    with pytest.raises(InputFileError) as err:
        usdface.evaluate_landmarks(rig, [csv], empirical=bad)
    assert "bad.json" in str(err.value) and "idx_to_landmark_verts" in err.value.fix
    from usdface.io.livelink import livelink_weights

    w = livelink_weights([csv, csv], rig.names)
    assert w.shape == (8, 2)
    np.testing.assert_allclose(w[:, 0], 0.5, atol=1e-3)
    assert (w[:, 1] == 0).all()                                   # eyeBlinkLeft absent from the take
    sampled = livelink_weights([csv, csv], rig.names, frames=3)
    np.testing.assert_array_equal(sampled, w[[0, 4, 7]])           # evenly sampled, ends kept


def test_evaluate_landmarks_takes_an_avatar_file_and_one_take_path(samples, tmp_path, monkeypatch):
    """As compute_landmarks, the avatar may be its file; one take may be a bare path (a user trial: the file
    failed with AttributeError "'str' object has no attribute 'names'", a path string was read character
    by character: 'expected one Live Link .csv in the take folder' for '/')."""
    import usdface.landmarks.evaluate as evaluate
    from usdface.io.livelink import write_livelink_csv
    from usdface.model import FaceRig

    csv = write_livelink_csv(tmp_path / "t.csv", ["jawOpen"], np.full((4, 1), 0.5), np.arange(4) / 60)
    seen = {}
    monkeypatch.setattr(evaluate, "evaluate_landmarks",
                        lambda rig, weights, indices, **kw: seen.update(rig=rig, weights=weights))
    for take in (str(csv), csv):
        usdface.evaluate_landmarks(str(samples / "avatar.usda"), take)
        assert isinstance(seen["rig"], FaceRig) and seen["rig"].name == "Head"
        assert seen["weights"].shape == (4, seen["rig"].n_shapes)


def test_evaluate_landmarks_refuses_takes_that_move_none_of_the_shapes(avatar, tmp_path, monkeypatch):
    """A mesh whose channels no take has (Blender's Key_1 against a Live Link take): every test frame was the
    neutral and the sweep scored tracking noise alone, without a word (a user trial)."""
    import usdface.landmarks.evaluate as evaluate
    from usdface.io.livelink import write_livelink_csv

    monkeypatch.setattr(evaluate, "evaluate_landmarks", lambda *a, **k: pytest.fail("evaluated"))
    rig = usdface.pick_mesh(avatar).subset(["eyeBlinkLeft"])
    csv = write_livelink_csv(tmp_path / "t.csv", ["jawOpen"], np.full((4, 1), 0.5), np.arange(4) / 60)
    with pytest.raises(LandmarkError, match=r"the takes \(t.csv\) move none of the mesh's 1 shapes") as err:
        usdface.evaluate_landmarks(rig, [csv])
    assert "--name-map" in err.value.fix


def test_write_retarget_map_refuses_before_work(tmp_path, monkeypatch):
    import usdface.transfer as transfer

    _forbid(monkeypatch, transfer, "personalize_avatar")
    with pytest.raises(InputFileError, match="must end in .json or .csv") as err:
        usdface.write_retarget_map("a.usda", "c.usda", tmp_path / "map.txt")
    assert err.value.fix.startswith("name it e.g. map.json")
    # '-o .json' (a hidden file's name, no extension): the suggestion was '.json.json'
    with pytest.raises(InputFileError, match="must end in .json or .csv") as err:
        usdface.write_retarget_map("a.usda", "c.usda", tmp_path / ".json")
    assert ".json.json" not in err.value.fix and "out.json" in err.value.fix and "hidden" in err.value.fix
    (tmp_path / "map.json").write_text("{}")
    with pytest.raises(OutputExistsError):
        usdface.write_retarget_map("a.usda", "c.usda", tmp_path / "map.json")


def test_commands_call_the_api(monkeypatch, tmp_path, capsys):
    """capture select / anim import parse, call the API function with the options, print."""
    seen = {}
    monkeypatch.chdir(tmp_path)
    for name in ("cap.usda", "take.usda", "t.csv"):   # the commands check their inputs exist before any work
        (tmp_path / name).write_text("")

    # fit: covered end to end by tests/workflows (the command reads the capture before calling the API)

    def fake_select(take, out=None, **kw):
        seen["select"] = (take, out, kw)
        return api.CaptureSelection(None, None, "COVERAGE", None, None)

    monkeypatch.setattr(api, "select_capture_frames", fake_select)
    assert main(["capture", "select", "take.usda", "--threshold", "0.7", "--min-separation", "0.2"]) == 0
    assert seen["select"][0] == "take.usda" and seen["select"][1] is None
    assert seen["select"][2]["threshold"] == 0.7 and seen["select"][2]["min_separation"] == 0.2
    assert "COVERAGE" in capture_out(capsys)

    class Take:
        times, fps, names, name_report = np.array([0.0, 0.5]), 2.0, ["jawOpen"], {"missing": ["x"]}

    def fake_anim(csv, out, **kw):
        seen["anim"] = (csv, out, kw)
        return tmp_path / "t.usda", Take()

    monkeypatch.setattr(api, "import_livelink_take", fake_anim)
    assert main(["anim", "import", "t.csv", "-o", "t.usda", "--timecode-rate", "30", "--force"]) == 0
    assert seen["anim"] == ("t.csv", "t.usda", {"timecode_rate": 30.0, "force": True})
    assert "missing shapes: x" in capture_out(capsys)


def capture_out(capsys) -> str:
    return capsys.readouterr().out


def echo_worker(item: dict) -> None:
    """Batch worker for the test below: writes the item's options to its output."""
    import json
    from pathlib import Path

    Path(item["output"]).parent.mkdir(parents=True, exist_ok=True)
    Path(item["output"]).write_text(json.dumps(item["options"]))


def test_personalize_batch_options_report_and_resume(tmp_path):
    import json

    manifest = tmp_path / "m.csv"
    manifest.write_text("avatar,capture,output,method\na.usdc,a_cap,out/a.usda,dt\nb.usdc,b_cap,out/b.usda,\n")
    report = usdface.personalize_batch(manifest, jobs=1, worker=f"{__name__}:echo_worker",
                                       options={"method": "menzel", "mu": 0.01},
                                       report_path=tmp_path / "r.json")
    assert report.report_path == tmp_path / "r.json"
    assert json.loads(report.report_path.read_text())["done"] == 2
    assert json.loads((tmp_path / "out" / "a.usda").read_text()) == {"method": "dt", "mu": 0.01}  # row wins
    again = usdface.personalize_batch(manifest, jobs=1, worker=f"{__name__}:echo_worker")
    assert again.count("skipped") == 2 and again.report_path == tmp_path / "m.report.json"


def test_inspect_force_keeps_the_old_output_when_the_inspection_fails(samples, tmp_path, monkeypatch):
    """``personalize --inspect --force`` over an existing layer: the inspection data is authored in the
    same atomic write as the layer, so when it fails the old output is untouched, byte for byte (the layer
    used to replace it first and be deleted with it), and nothing is left beside it; when it succeeds one
    layer holds both."""
    import usdface.io.usd_inspection as inspection
    from usdface import api

    out = tmp_path / "p.usda"
    out.write_text("#usda 1.0\n(\n    doc = \"an earlier run\"\n)\n")
    before = out.read_bytes()
    real = inspection.inspection_edit

    def broken(*args, **kwargs):
        raise RuntimeError("inspection failed")

    monkeypatch.setattr(inspection, "inspection_edit", broken)
    with pytest.raises(RuntimeError, match="inspection failed"):
        api.personalize_avatar(samples / "avatar.usda", samples / "capture.usda", out, inspect=True,
                               force=True)
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.usda"]              # nothing left beside it
    monkeypatch.setattr(inspection, "inspection_edit", real)
    api.personalize_avatar(samples / "avatar.usda", samples / "capture.usda", out, inspect=True, force=True)
    from pxr import Usd

    stage = Usd.Stage.Open(str(out))
    assert stage.GetPrimAtPath("/Avatar/Head").GetAttribute("primvars:" + inspection.HEAT_PRIMVAR)


def test_check_takes_a_stage_or_a_layer_and_names_anything_else(samples):
    """``check`` with an ``Sdf.Layer`` (what a host holds as often as a stage) raised an AttributeError from
    deep in the rules; it is checked as the stage it opens, and another object is refused by name."""
    from pxr import Sdf, Usd

    from usdface.errors import UsdFaceError

    path = samples / "avatar.usda"
    rules = ["StageMetadata", "ArkitNames"]
    expected = usdface.check(path, pixar=False, rules=rules)
    assert usdface.check(Usd.Stage.Open(str(path)), pixar=False, rules=rules) == expected
    assert usdface.check(Sdf.Layer.FindOrOpen(str(path)), pixar=False, rules=rules) == expected
    with pytest.raises(UsdFaceError, match="not int"):
        usdface.check(3)


def test_an_avatar_and_a_capture_read_by_relative_paths_survive_the_host_changing_folder(samples, tmp_path,
                                                                                          monkeypatch):
    """``Avatar.file`` and ``Capture.source`` kept a relative path as given: once the host changed folder (a
    DCC opening a scene), personalizing the objects said 'the avatar's file is gone', and with the avatar
    read by an absolute path the layer recorded another capture path, with no digest (check: error)."""
    import os

    monkeypatch.chdir(samples)
    avatar = usdface.read_avatar("avatar.usda")
    capture = usdface.read_capture("capture.usda")
    elsewhere = tmp_path / "scene"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert os.path.samefile(avatar.file, samples / "avatar.usda")
    assert os.path.samefile(capture.source, samples / "capture.usda")
    face = usdface.pick_mesh(avatar)
    layer = usdface.write_landmarks(avatar, face, usdface.compute_landmarks(face), tmp_path / "lm.usda")
    assert not [i for i in usdface.check(layer, pixar=False) if i.severity == "error"]


def _doc_parameters(args: str) -> list[str]:
    """The parameter names of a signature as docs/api.md writes it (``a, b=("x", "y"), *, c=None, **o``)."""
    names, depth, part = [], 0, ""
    for ch in args + ",":
        if ch in "([{":
            depth += 1
        elif ch in ")]}":
            depth -= 1
        if ch == "," and depth == 0:
            name = part.split("=")[0].strip()
            if name and name not in ("*", "...") and not name.startswith("**"):
                names.append(name)
            part = ""
        else:
            part += ch
    return names


def test_the_documented_signatures_name_the_real_parameters():
    """docs/api.md wrote ``personalize_avatar(avatar, capture, out_path, ...)`` and
    ``write_retarget_map(avatar, capture, ...)``; a script calling them with those keywords got a TypeError
    (the parameters are ``avatar_path`` and ``capture_path``)."""
    import inspect
    import re
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[1] / "docs" / "api.md").read_text()
    wrong = {}
    for m in re.finditer(r"^`(\w+)\((.*?)\)(?: -> [^`]*)?`$", doc, re.M):
        params = inspect.signature(getattr(api, m.group(1))).parameters
        unknown = [n for n in _doc_parameters(m.group(2)) if n not in params]
        if unknown:
            wrong[m.group(1)] = unknown
    assert wrong == {}


def test_every_api_function_and_parameter_is_documented():
    """``usdface.write_review``, ``export_avatar`` and ``landmark_diagnostics`` are re-exported as the API
    (``usdface.<name>``) but docs/api.md gave them no entry, and its ``check`` / ``inspect_file`` entries left
    out ``name_map`` (which the page's own text says they take): a TD scripting from the page could not
    find them."""
    import inspect
    import re
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[1] / "docs" / "api.md").read_text()
    documented: dict[str, set] = {}
    for m in re.finditer(r"^`(\w+)\((.*?)\)(?: -> [^`]*)?`", doc, re.M):
        documented.setdefault(m.group(1), set()).update(_doc_parameters(m.group(2)))
    assert sorted(usdface._API - set(documented)) == []
    missing = {}
    for name, names in documented.items():
        params = inspect.signature(getattr(api, name)).parameters.values()
        left = [p.name for p in params
                if p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL) and p.name not in names]
        if left:
            missing[name] = left
    assert missing == {}


def test_plots_leave_the_hosts_matplotlib_backend_and_figures_alone(capture, avatar, tmp_path):
    """``evaluate_methods(plot_path=...)`` (and the landmark plots) called ``matplotlib.use("Agg")`` and drew
    with pyplot: in a host with pyplot imported (a notebook, a DCC) that switched its backend and closed
    every figure it had open."""
    import types

    import matplotlib
    import matplotlib.pyplot as plt

    from usdface.landmarks.plots import plot_layout
    from usdface.render import render_shapes

    before = matplotlib.get_backend()
    plt.switch_backend("svg")                 # the host's backend (any but Agg), with a figure open
    try:
        mine = plt.figure()
        usdface.evaluate_methods(capture, ["dt"], plot_path=tmp_path / "errors.png")
        face = usdface.pick_mesh(avatar)
        layout = types.SimpleNamespace(vertices=[0, 40, 80], rounds=[1, 1, 2], coverage=np.ones((3, 2)),
                                       count=3, epsilon=0.5)
        plot_layout(face.neutral, layout, tmp_path / "layout.png")
        render_shapes(face, ["jawOpen"], tmp_path / "shapes.png")
        assert matplotlib.get_backend() == "svg" and plt.fignum_exists(mine.number)
        assert all((tmp_path / n).stat().st_size > 0 for n in ("errors.png", "layout.png", "shapes.png"))
    finally:
        plt.close("all")
        plt.switch_backend(before)


def test_every_output_path_comes_back_absolute(samples, tmp_path, monkeypatch):
    """Given relative output paths, some functions returned them as given (``write_capture``,
    ``write_fit_rig``, ``write_review``, ``export_avatar``, ``write_retarget_map``, ``import_livelink_take``,
    ``evaluate_methods``' JSON and plot), others absolute (``personalize_avatar``, ``write_landmarks``,
    ``evaluate_methods``' USD): a host that changed folder afterwards found the wrong file. Every one is an
    absolute Path now (docs/api.md)."""
    import json
    import shutil
    import warnings
    from pathlib import Path

    from usdface.io.livelink import write_livelink_csv

    for name in ("avatar.usda", "capture.usda"):
        shutil.copy(samples / name, tmp_path / name)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "out").mkdir()
    got = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        got["personalize_avatar"] = api.personalize_avatar("avatar.usda", "capture.usda",
                                                           "out/p.usda").out_path
        capture = api.read_capture("capture.usda")
        got["write_capture"] = api.write_capture(capture, "out/c.usda", source="capture.usda")
        got["write_capture folder"] = api.write_capture(capture, "out/cap", source="capture.usda")
        got["import_capture_folder"] = api.import_capture_folder("out/cap", "out/imported.usda")
        fit = api.fit_capture(capture, method="dt", out_path="out/fit.usda")
        got["fit_capture"] = fit.info["out_path"]
        got["write_fit_rig"] = api.write_fit_rig(fit, "out/fit2.usda")
        report = api.evaluate_methods("capture.usda", "dt", json_path="out/e.json", plot_path="out/e.png",
                                      usd_path="out/e.usda")
        got.update({f"evaluate_methods {k}": v for k, v in report["_outputs"].items()})
        got["write_retarget_map"] = api.write_retarget_map("avatar.usda", "capture.usda",
                                                           "out/m.json").out_path
        avatar = api.read_avatar("avatar.usda")
        rig = api.pick_mesh(avatar)
        got["write_landmarks"] = api.write_landmarks(avatar, rig, api.compute_landmarks(rig), "out/lm.usda")
        write_livelink_csv(tmp_path / "t.csv", ["jawOpen"], np.full((4, 1), 0.5), np.arange(4) / 30.0)
        got["import_livelink_take"] = api.import_livelink_take("t.csv", "out/t.usda")[0]
        got["write_review"] = api.write_review("out/p.usda", "out/r.html", fit_errors=False)
        got.update({f"export_avatar {k}": v for k, v in api.export_avatar(
            "out/p.usda", gltf="out/x.glb", obj_dir="out/objs", flatten="out/f.usdc").items()})
        (tmp_path / "m.json").write_text(json.dumps([{"avatar": "avatar.usda", "capture": "capture.usda",
                                                      "output": "out/p.usda"}]))
        got["personalize_batch"] = api.personalize_batch("m.json", jobs=1,
                                                         report_path="out/b.json").report_path
    assert len(got) == 17
    wrong = {k: v for k, v in got.items() if not (isinstance(v, Path) and v.is_absolute() and v.exists()
                                                  and v.parent.parent == tmp_path)}
    assert not wrong, wrong


def _an_avatar():
    """An (empty) Avatar: a wrong kind of argument where a capture or its rig goes."""
    from usdface.model import Avatar

    return Avatar(meshes=[], file="avatar.usda")


def _write_landmarks_to_none(usdface):
    """write_landmarks with every argument right but the output: None died with Python's TypeError
    ('expected str, bytes or os.PathLike object, not NoneType') from the layer writer."""
    from usdface.landmarks import LandmarkLayout
    from usdface.model import Avatar, FaceRig

    rig = FaceRig.__new__(FaceRig)
    usdface.write_landmarks(Avatar.__new__(Avatar), rig, LandmarkLayout.__new__(LandmarkLayout), None)


@pytest.mark.parametrize("call, says", [
    (lambda u: u.personalize_avatar(None, "c/", "o.usda"), "the avatar must be the avatar's file or an"),
    (lambda u: u.personalize_avatar("a.usda", 5, "o.usda"), "the capture must be a capture path or a"),
    (lambda u: u.personalize_avatar("a.usda", "c/", "o.usda", face_mesh=3), "face_mesh must be a mesh's"),
    (lambda u: u.personalize_avatar("a.usda", "c/", None, rig="x"), "rig must be a FaceRig"),
    (lambda u: u.personalize_avatar("a.usda", "c/", "o.usda", take=5), "take must be a take's file"),
    (lambda u: u.write_retarget_map(None, "c/", "m.json"), "the avatar must be"),
    (lambda u: u.fit_capture(123), "the capture must be a Capture or a capture path"),
    (lambda u: u.read_capture(None), "read_capture's path must be"),
    (lambda u: u.read_avatar(None), "read_avatar's path must be"),
    (lambda u: u.evaluate_capture("c/", rig="x"), "evaluate_capture's rig must be"),
    (lambda u: u.pick_mesh("a.usdc"), "pick_mesh's avatar must be an Avatar"),
    (lambda u: u.write_capture("c", "c.usda"), "write_capture's capture must be a Capture"),
    (lambda u: u.write_landmarks("a.usdc", None, None, "lm.usda"), "write_landmarks' avatar must be an"),
    (lambda u: u.compute_landmarks(None), "the rig must be a FaceRig, an Avatar or an avatar file"),
    (lambda u: u.compute_landmarks("a.usda", epsilom=0.4), "compute_landmarks does not take epsilom"),
    (lambda u: u.landmark_diagnostics("a.usda", foo=1), "landmark_diagnostics does not take foo"),
    (lambda u: u.evaluate_landmarks("a.usda", "t.csv", noise=1), "evaluate_landmarks does not take noise"),
    # user trial: symmetric="yes" counted as true (and "no" too), frames=0 read every frame, each unremarked
    (lambda u: u.compute_landmarks("a.usda", symmetric="yes"), "bad symmetric 'yes': compute_landmarks'"),
    (lambda u: u.compute_landmarks("a.usda", adaptive="False"), "bad adaptive 'False'"),
    (lambda u: u.evaluate_landmarks("a.usda", "t.csv", symmetric="no"), "bad symmetric 'no'"),
    (lambda u: u.evaluate_landmarks("a.usda", "t.csv", frames=0), "bad frames 0: .* whole number >= 1"),
    (lambda u: u.evaluate_landmarks("a.usda", "t.csv", frames=2.5), "bad frames 2.5"),
    (lambda u: u.evaluate_landmarks("a.usda", "t.csv", frames=True), "bad frames True"),
    (lambda u: u.evaluate_landmarks("a.usda", "t.csv", noise_mm=-1), "bad noise_mm -1"),
    (lambda u: u.landmark_diagnostics(None), "the rig must be a FaceRig, an Avatar or an avatar file"),
    (lambda u: u.evaluate_landmarks(None, "t.csv"), "the rig must be a FaceRig, an Avatar or an avatar"),
    (lambda u: u.write_fit_rig(None, "fit.usda"), "write_fit_rig's fit must be a FitResult or a FaceRig"),
    (lambda u: u.inspect_file(None), "path must be a path"),
    (lambda u: u.export_avatar(None, gltf="x.glb"), "layer_path must be a path"),
    (lambda u: u.write_review(None, "r.html"), "layer_path must be a path"),
    (lambda u: u.import_livelink_take(None, "t.usda"), "csv must be a path"),
    (lambda u: u.select_capture_frames(None), "take must be a path"),
    (lambda u: u.select_capture_frames("t.usda", "c.usda", template=3), "template must be a capture path"),
    (lambda u: u.select_capture_frames("t.usda", "c.usda", template=_an_avatar()),
     "template must be a capture path, a Capture or a FaceRig"),
    (lambda u: u.import_capture_folder("c", None), "out_path must be a path"),
    (lambda u: u.personalize_batch(None), "manifest must be a path"),
    (lambda u: u.fit_capture("c", out_path=5), "out_path must be a path"),
    (lambda u: u.write_retarget_map("a.usdc", "c", None), "out_path must be a path"),
    (_write_landmarks_to_none, "out_path must be a path"),
])
def test_arguments_of_the_wrong_kind_are_option_errors(tmp_path, monkeypatch, call, says):
    """A docs walk-through with wrong kinds of arguments: None for the avatar or a number for the capture
    died with 'expected str, bytes or os.PathLike object, not NoneType', a path for the rig or the Avatar
    with "'str' object has no attribute 'names'" / "... 'meshes'", face_mesh=3 with 'can only concatenate
    str (not "int") to str'. Each is an OptionError naming the argument, what it takes and the fix, before
    any file is read or written."""
    import usdface
    from usdface.errors import OptionError

    monkeypatch.chdir(tmp_path)
    with pytest.raises(OptionError, match=says) as info:
        call(usdface)
    assert info.value.fix and not list(tmp_path.iterdir())


@pytest.mark.parametrize("jobs", [0, -1, "2", 1.5, True])
def test_personalize_batch_refuses_a_job_count_the_command_line_refuses(tmp_path, jobs):
    """``usdface batch -j 0`` is refused; ``personalize_batch(m, jobs=0)`` ran a process per CPU, jobs=-1
    in this process, jobs="2" died with ValueError after the manifest was read."""
    import usdface
    from usdface.errors import OptionError

    manifest = tmp_path / "m.csv"
    manifest.write_text("avatar,capture,output\na.usda,c,o.usda\n")
    with pytest.raises(OptionError, match="jobs must be a whole number >= 1"):
        usdface.personalize_batch(manifest, jobs=jobs)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.csv"]


def test_warnings_name_the_callers_line_not_usdfaces(tmp_path):
    """User trial: a warning of the API named usdface's own line (``usdface/io/take.py:131``, the reader
    several calls down that noticed), so a TD's script that read a hundred takes could not tell which of its
    calls it was. Whatever the depth, the warning names the script's line; its category is UsdFaceWarning
    (a UserWarning), for a filter to silence usdface's alone."""
    import json
    import sys
    import warnings

    from input_helpers import _capture

    from usdface.errors import UsdFaceWarning
    from usdface.io.livelink import write_livelink_csv

    csv = write_livelink_csv(tmp_path / "t.csv", ["jawOpen", "eyeBlinkLeft"],
                             np.array([[0.2, 1.5], [0.4, 0.1]]), np.arange(2) / 30.0, timecode_rate=30.0)
    folder = tmp_path / "cap"
    usdface.write_capture(_capture(), folder)
    first = sorted((folder / "train").glob("*.json"))[0]
    data = json.loads(first.read_text())
    data["blendShapes"]["notAShape"] = 0.5
    first.write_text(json.dumps(data))
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        here = sys._getframe().f_lineno
        usdface.import_livelink_take(csv, tmp_path / "t.usda", timecode_rate=30.0)          # here + 1
        usdface.read_capture(folder)                                                         # here + 2
    where = {("outside [0, 1]" if "outside [0, 1]" in str(w.message) else "notAShape"): (w.filename, w.lineno)
             for w in said if issubclass(w.category, UsdFaceWarning)}
    assert where == {"outside [0, 1]": (__file__, here + 1), "notAShape": (__file__, here + 2)}, \
        [(str(w.message)[:60], w.filename, w.lineno) for w in said]



def test_evaluate_plot_names_the_capture_it_scores(samples, tmp_path, monkeypatch):
    """The bar charts (``evaluate --plot``) did not say which capture they score (a user trial, stop 42): the
    figure's title names the capture as given. Its own loop once shadowed the title with a panel's ('maximum
    vertex error' above the whole figure): the title drawn is the one passed."""
    from matplotlib.figure import Figure

    titles = []
    real = Figure.suptitle
    monkeypatch.setattr(Figure, "suptitle", lambda self, t, **kw: (titles.append(t), real(self, t, **kw))[1])
    capture = str(samples / "capture.usda")
    usdface.evaluate_methods(capture, ["dt"], plot_path=tmp_path / "errors.png")
    assert titles == [f"{capture}: test-frame errors (eq. 5)"]
    assert (tmp_path / "errors.png").stat().st_size > 0
