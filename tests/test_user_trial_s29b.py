"""Defects found by a technical director's second trial (session 29): takes, landmarks, review, inspect."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from usdface.cli import main
from usdface.io.livelink import write_livelink_csv

SAMPLE = Path(__file__).resolve().parents[1] / "sample_assets"


def test_a_folder_of_live_link_csvs_is_not_one_take(tmp_path, capsys):
    """'usdface inspect livelinkface/' (four CSVs, no meshes) said 'expected one Live Link .csv in the take
    folder, found 4 (fix: put exactly one Live Link Face CSV next to the OBJ frames)': there are no frames."""
    for name in ("a.csv", "b.csv"):
        write_livelink_csv(tmp_path / name, ["jawOpen"], np.full((4, 1), 0.5), np.arange(4) / 60)
    for args in (["inspect", str(tmp_path)], ["capture", "select", str(tmp_path)]):
        assert main(args) == 2
        err = capsys.readouterr().err
        assert "a folder of 2 Live Link CSVs (a.csv, b.csv) and no OBJ frames" in err, err
        assert f"pass the CSV files themselves, e.g. {tmp_path / 'a.csv'}" in err




def test_capture_import_refuses_a_take(tmp_path, capsys):
    """'capture import take_dir/ -o c.usda' wrote every frame of the take as a capture's training frame: the
    file then fitted as picked frames (no frame weighting; reg 0.0009 against the take's 0.045) and 'fit
    c.usda --every 2' said it 'holds frames picked one per shape'."""
    from test_take_select import grid_rigs

    from usdface import api
    from usdface.errors import CaptureError
    from usdface.io.take import write_take_folder, write_take_usd
    from usdface.sample.take import make_take

    person, template = grid_rigs(n=4)
    take, _ = make_take(person, template, shapes=["jawOpen", "eyeBlinkLeft"], seed=1)
    for src in (write_take_usd(take, tmp_path / "take.usdc"), write_take_folder(take, tmp_path / "take_dir")):
        out = tmp_path / "c.usda"
        assert main(["capture", "import", str(src), "-o", str(out), "-q"]) == 2
        err = capsys.readouterr().err
        assert "a take, not a capture" in err and "usdface capture select TAKE" in err, err
        assert not out.exists()
        with pytest.raises(CaptureError, match="a take, not a capture"):
            api.import_capture_folder(src, out)
        assert not out.exists()


def test_a_landmarks_layer_says_what_it_is(samples, tmp_path):
    """A 'usdface landmarks -o lm.usda' layer documented itself as 'personalized blend shapes over ...', and
    'review lm.usda' (and of a 'usdface fit' rig) called it 'not a usdface layer'."""
    from pxr import Sdf

    from usdface import api
    from usdface.errors import InputFileError
    from usdface.model import FaceRig

    avatar = api.read_avatar(samples / "avatar.usda")
    rig = api.pick_mesh(avatar, "Mouth")
    layout = api.compute_landmarks(rig, spacing=None)
    out = api.write_landmarks(avatar, rig, layout, tmp_path / "lm.usda")
    assert "a landmark layout over" in Sdf.Layer.FindOrOpen(str(out)).documentation
    with pytest.raises(InputFileError, match=r"\(a landmark layout layer \('usdface landmarks'\)\)"):
        api.write_review(out, tmp_path / "lm.html")
    tri = np.array([[0, 1, 2]])
    fit = api.write_fit_rig(FaceRig(np.eye(3), tri, ["jawOpen"], np.full((1, 3, 3), 0.01), name="FaceMask"),
                            tmp_path / "rig.usda")
    with pytest.raises(InputFileError, match=r"\(a 'usdface fit' rig on the capture mesh\)"):
        api.write_review(fit, tmp_path / "rig.html")


def test_inspect_reports_a_take_without_its_template(tmp_path, capsys):
    """'usdface inspect take_dir/' of OBJ frames + CSV without template/ failed ('the take has no template
    rig'): the inspection of a take 'capture select --template' can still use refused to say what it holds."""
    from test_take_select import grid_rigs

    from usdface.inspect import format_report, inspect_file
    from usdface.io.take import write_take_folder, write_take_usd
    from usdface.sample.take import make_take

    person, _ = grid_rigs(n=4)
    take, _ = make_take(person, None, shapes=["jawOpen", "eyeBlinkLeft"], seed=1)
    for src in (write_take_folder(take, tmp_path / "take_dir"), write_take_usd(take, tmp_path / "take.usdc")):
        report = inspect_file(src)
        assert report["kind"] == "take" and report["meshes"] and report["frames"] == len(take)
        assert "meshes but no template rig" in format_report(report)
    assert main(["inspect", str(tmp_path / "take_dir")]) == 0
    assert "--template CAPTURE" in capsys.readouterr().out


def test_select_capture_frames_takes_a_capture_as_template_and_checks_its_numbers(samples, tmp_path):
    """select_capture_frames(template=read_capture(...)) failed with TypeError 'expected str, bytes or
    os.PathLike object, not Capture'; threshold=1.5 gave a table of never-triggered shapes without a word
    (the command line refuses it)."""
    from test_take_select import grid_rigs

    from usdface import api
    from usdface.errors import CaptureError
    from usdface.io.take import write_take_usd
    from usdface.model import Capture, Frames
    from usdface.sample.take import make_take

    person, template = grid_rigs(n=4)
    take, _ = make_take(person, None, shapes=["jawOpen", "eyeBlinkLeft"], seed=1)
    src = write_take_usd(take, tmp_path / "take.usdc")
    empty = Frames(np.zeros((0, *template.neutral.shape)), np.zeros((0, template.n_shapes)), [], [])
    capture = Capture(template.neutral, template.triangles, template, empty, list(template.names))
    sel = api.select_capture_frames(src, tmp_path / "c.usda", template=capture)
    assert sel.out_path is not None and sel.capture.template.n_shapes == template.n_shapes
    for bad in ({"threshold": 1.5}, {"threshold": -0.1}, {"min_separation": -1}):
        with pytest.raises(CaptureError, match="threshold|min_separation"):
            api.select_capture_frames(src, **bad)


def test_evaluate_capture_refuses_a_capture_without_test_frames(tmp_path):
    """evaluate_capture on a take read whole (or a capture picked without --test-every) returned
    mean_rmse_mm NaN without a word; evaluate_methods refuses it with the fix."""
    from test_take_select import grid_rigs

    from usdface import api
    from usdface.errors import FitError
    from usdface.io.take import write_take_usd
    from usdface.sample.take import make_take

    person, template = grid_rigs(n=4)
    take, _ = make_take(person, template, seed=1)
    src = write_take_usd(take, tmp_path / "take.usdc")
    with pytest.raises(FitError, match="no test frames") as err:
        api.evaluate_capture(src)
    assert "--test-every 10" in err.value.fix
    assert np.isfinite(api.evaluate_capture(src, role="train")["mean_rmse_mm"])


@pytest.mark.parametrize("args", [["anim", "import", "{d}/missing.csv", "-o", "{d}/x.usda"],
                                  ["capture", "select", "{d}/missing.csv", "-o", "{d}/x.usda"]])
def test_an_actions_error_names_the_command_as_typed(tmp_path, capsys, args):
    """Errors of the commands with actions said 'usdface anim: error' for 'usdface anim import': they name
    the command as typed."""
    argv = [a.format(d=tmp_path) for a in args]
    assert main(argv) == 2
    assert capsys.readouterr().err.startswith(f"usdface {argv[0]} {argv[1]}: error: "), argv


def test_fit_rig_records_command_parameters_and_capture(tmp_path, monkeypatch):
    """A rig written by ``usdface fit`` says what made it, as a personalized layer does: the command line,
    the options, the capture read (path relative to the rig and its sha256) and when (it recorded only the
    method: which capture and settings a rig came from was lost)."""
    import shutil

    from usdface.cli import main
    from usdface.io.layers import file_digest
    from usdface.io.usd_rig import usdface_layer_data

    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    cap = tmp_path / "cap.usda"
    shutil.copy(SAMPLE / "capture.usda", cap)
    out = tmp_path / "rigs" / "rig.usda"
    monkeypatch.setattr("sys.argv", ["usdface", "fit", str(cap), "-o", str(out), "--reg", "0.05", "-q"])
    assert main(["fit", str(cap), "-o", str(out), "--reg", "0.05", "-q"]) == 0
    data = usdface_layer_data(out)
    assert data["format"] == "fit" and data["method"] == "menzel"
    assert data["command"].startswith("usdface fit ") and "--reg 0.05" in data["command"]
    assert data["parameters"]["reg"] == 0.05 and data["parameters"]["method"] == "menzel"
    assert data["capture"] == "../cap.usda" and data["captureDigest"] == file_digest(cap)
    assert data["createdAt"] == "2023-11-14T22:13:20Z"
    assert data["trainRmseMm"] > 0 and data["reg"] == 0.05


def test_review_plays_the_take_the_layer_was_written_with(tmp_path):
    """``personalize --take`` records the take (relative to the layer, as ``take``) and ``review LAYER``
    plays it without ``--take`` again (the page had only the test expressions); a take moved away is said
    in the page's notes."""
    from usdface.io.livelink import read_livelink_take
    from usdface.io.usd_rig import usdface_layer_data
    from usdface.review.collect import collect_review

    take = tmp_path / "takes" / "t.csv"
    take.parent.mkdir()
    names = ["jawOpen", "eyeBlinkLeft", "mouthSmileLeft"]
    weights = np.array([[0.0, 0.0, 0.0], [0.8, 0.2, 0.1], [0.3, 1.0, 0.6], [0.0, 0.0, 0.0]])
    write_livelink_csv(take, names, weights, np.arange(4) / 30.0)
    assert len(read_livelink_take(take).weights) == 4
    out = tmp_path / "out" / "person.usda"
    assert main(["personalize", str(SAMPLE / "avatar.usda"), str(SAMPLE / "capture.usda"), "-o", str(out),
                 "--take", str(take), "-q"]) == 0
    assert usdface_layer_data(out)["take"] == "../takes/t.csv"
    data = collect_review(out, fit_errors=False)
    played = [s for s in data.sequences if s.title.startswith("take ")]
    assert [s.title for s in played] == ["take t.csv"] and len(played[0].weights) == 4
    # a flattened copy elsewhere (usdface export --flatten) records the take relative to itself
    from usdface.api import export_avatar

    flat = tmp_path / "deliver" / "deep" / "person.flat.usda"
    export_avatar(out, flatten=flat)
    assert usdface_layer_data(flat)["take"] == "../../takes/t.csv"
    take.rename(tmp_path / "moved.csv")
    data = collect_review(out, fit_errors=False)
    assert not [s for s in data.sequences if s.title.startswith("take ")]
    assert any("take recorded" in n and "not found" in n for n in data.notes)


def test_take_frame_rate_is_the_rate_not_float_noise(tmp_path, capsys):
    """``inspect --json`` of a Live Link Face CSV said ``"fps": 30.000000000001705`` (one over the median
    interval of times summed from timecodes); the rate is rounded to 6 decimals, one rule for every take
    reader (the CSV's and the take folder's had the same code twice)."""
    import json

    from usdface.io.livelink import median_fps, read_livelink_take

    names = ["jawOpen", "eyeBlinkLeft"]
    csv = tmp_path / "t.csv"
    write_livelink_csv(csv, names, np.random.default_rng(0).uniform(0, 1, (200, 2)), np.arange(200) / 30.0)
    assert read_livelink_take(csv).fps == 30.0
    assert main(["inspect", str(csv), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["fps"] == 30.0
    assert median_fps(np.arange(5) * (1001 / 30000)) == 29.97003
    assert median_fps([0.0]) == 30.0 and median_fps([1.0, 1.0, 1.0]) == 30.0


def test_landmark_evaluation_summary_without_an_empirical_layout():
    """``landmarks --evaluate --json`` without ``--empirical`` had ``"summary": {}``: it now names this
    method's most compact and most accurate layouts, each beside the baselines at (at most) that count."""
    from usdface.landmarks.evaluate import EvaluationPoint, EvaluationReport, _summary

    pts = [EvaluationPoint("ours", "eps 0.5", 12, 2e-3), EvaluationPoint("ours", "eps 0.9 x4", 40, 1e-3),
           EvaluationPoint("ours", "eps 0.9 x6", 55, 1.1e-3),
           EvaluationPoint("random", "seed 0", 10, 5e-3), EvaluationPoint("random", "seed 1", 10, 4e-3),
           EvaluationPoint("random", "seed 0", 40, 3e-3), EvaluationPoint("pca_kmeans", "", 12, 2.5e-3)]
    s = _summary(EvaluationReport(pts, frames=10, noise=5e-4), None)
    assert s["ours_smallest_count"] == 12 and s["ours_rmse_at_smallest_count"] == 2e-3
    assert s["ours_count_at_best"] == 40 and s["ours_best_rmse"] == 1e-3
    assert s["ours_label_at_best"] == "eps 0.9 x4"
    assert s["random_rmse_at_10"] == 4e-3 and s["random_rmse_at_40"] == 3e-3
    assert s["pca_kmeans_rmse_at_12"] == 2.5e-3 and "delta_cluster_rmse_at_12" not in s
    assert _summary(EvaluationReport([], frames=0, noise=0.0), None) == {}


def _sample_take():
    from usdface.io import read_capture
    from usdface.model import FaceRig
    from usdface.sample.take import make_take

    capture = read_capture(SAMPLE / "capture.usda")
    ct = np.load(SAMPLE / "truth" / "capture_truth.npz")
    names = [str(n) for n in ct["names"]]
    person = FaceRig(ct["neutral"], capture.triangles, names, ct["deltas"])
    return make_take(person, capture.template.subset(names), seed=1, fps=10, sweep_seconds=0.3,
                     rest_seconds=0.1)[0]


def test_a_take_read_whole_is_inspected_as_one_and_not_written_as_a_capture(tmp_path, capsys):
    """``inspect --json`` of a take with meshes said ``"kind": "capture"`` (the text said "take with
    meshes"); ``write_capture`` of a take read whole wrote a capture that read back as 209 picked frames (no
    ``whole_take``: another fit than ``fit TAKE``). It is refused, naming the fix; nothing is written."""
    import json

    from usdface.api import write_capture
    from usdface.errors import CaptureError
    from usdface.io import read_capture
    from usdface.io.take import write_take_usd

    take = write_take_usd(_sample_take(), tmp_path / "take.usdc")
    assert main(["inspect", str(take), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["kind"] == "take with meshes"
    cap = read_capture(take)
    assert cap.whole_take
    for out in (tmp_path / "c.usda", tmp_path / "cfolder"):
        with pytest.raises(CaptureError, match="take read whole") as err:
            write_capture(cap, out)
        assert "write_take_usd" in err.value.fix and "capture select" in err.value.fix
        assert not out.exists()


def test_the_retarget_map_does_not_drive_the_tongue_to_match_a_few_face_rows(tmp_path):
    """``usdface retarget`` on the sample: the ``jawForward`` row took ``tongueOut`` at 0.82 (matching the
    lower lip's face rows; an engine driving every mesh with the map put the tongue out on every jaw slide).
    The map now holds what it drives on the other meshes at the namesake's motion (the Mouth mesh's rows):
    the tongue stays in, the namesake carries the row. With the paper's zero prior the face rows alone
    decide, as eq. (4)."""
    import json

    out = tmp_path / "map.json"
    assert main(["retarget", str(SAMPLE / "avatar.usda"), str(SAMPLE / "capture.usda"), "-o", str(out),
                 "-q"]) == 0
    doc = json.loads(out.read_text())
    row = dict(zip(doc["target"], doc["weights"][doc["source"].index("jawForward")], strict=True))
    assert row["tongueOut"] < 0.1 and row["jawForward"] > 0.95          # was 0.82 and 1.0
    tongue = [doc["weights"][j][doc["target"].index("tongueOut")] for j, s in enumerate(doc["source"])
              if s != "tongueOut"]
    assert max(tongue) < 0.1


def test_api_arguments_of_the_wrong_kind_are_refused_with_the_fix(tmp_path):
    """A docs walk-through: ``select_capture_frames(take, per_shape=1.5)`` / ``test_every="5"`` died with
    numpy's TypeError, ``write_fit_rig("x", out)`` with AttributeError; each is a UsdFaceError naming the
    argument and the fix, before any work."""
    import usdface
    from usdface.errors import CaptureError, UsdFaceError

    take = tmp_path / "t.csv"
    write_livelink_csv(take, ["jawOpen"], np.full((4, 1), 0.5), np.arange(4) / 30.0)
    for kw, word in (({"per_shape": 1.5}, "per_shape"), ({"test_every": "5"}, "test_every"),
                     ({"per_shape": True}, "per_shape"), ({"threshold": "x"}, "threshold"),
                     ({"min_separation": -1}, "min_separation")):
        with pytest.raises(CaptureError, match=word):
            usdface.select_capture_frames(take, **kw)
    with pytest.raises(UsdFaceError, match="FitResult or a FaceRig") as err:
        usdface.write_fit_rig("x", tmp_path / "o.usda")
    assert "fit_capture" in err.value.fix and not (tmp_path / "o.usda").exists()


def test_export_names_every_output_the_same_way(tmp_path, monkeypatch):
    """``usdface export LAYER --obj-dir d --flatten f.usda`` printed ``obj_dir: d`` but ``flatten:
    /abs/.../f.usda`` (export_avatar returned the flattened file absolute, the others as given); every output
    comes back absolute now, as from every API function (docs/api.md)."""
    from usdface.api import export_avatar

    monkeypatch.chdir(tmp_path)
    layer = tmp_path / "p.usda"
    assert main(["personalize", str(SAMPLE / "avatar.usda"), str(SAMPLE / "capture.usda"), "-o", str(layer),
                 "-q"]) == 0
    done = export_avatar("p.usda", gltf="g.glb", obj_dir="objs", flatten="f.usda")
    assert done == {"gltf": tmp_path / "g.glb", "obj_dir": tmp_path / "objs", "flatten": tmp_path / "f.usda"}
    assert all(p.exists() for p in done.values())


def test_review_refuses_a_take_as_capture_without_first_warning_about_it(tmp_path):
    """``review LAYER --capture take.csv`` warned 'take.csv is not among the inputs ... its figures describe
    that file', then refused the CSV (a weights-only take has no test expressions): only the refusal now."""
    import warnings

    from usdface.api import write_review
    from usdface.errors import CaptureError

    layer = tmp_path / "p.usda"
    assert main(["personalize", str(SAMPLE / "avatar.usda"), str(SAMPLE / "capture.usda"), "-o", str(layer),
                 "-q"]) == 0
    take = tmp_path / "t.csv"
    write_livelink_csv(take, ["jawOpen"], np.full((4, 1), 0.5), np.arange(4) / 30.0)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        with pytest.raises(CaptureError, match="--take"):
            write_review(layer, tmp_path / "r.html", capture=take)
    assert not [w for w in seen if "among" in str(w.message)]
    assert not (tmp_path / "r.html").exists()


def test_check_notes_name_map_entries_that_match_no_channel(tmp_path, capsys):
    """``inspect --name-map`` notes map entries that match no channel (a typo in the map); ``check`` with
    the same map said nothing. A map entry naming a channel as it is (``eyeBlinkLeft`` -> ``eyeBlinkLeft``)
    is no 'non-canonical spelling'."""
    import json

    m = tmp_path / "m.json"
    m.write_text(json.dumps({"JawDrop": "jawOpen", "eyeBlinkLeft": "eyeBlinkLeft"}))
    assert main(["check", str(SAMPLE / "avatar.usda"), "--name-map", str(m), "--no-pixar", "--json"]) == 0
    found = [i for i in json.loads(capsys.readouterr().out)["issues"] if "name map" in i["message"]]
    assert len(found) == 1 and "'JawDrop'" in found[0]["message"]
    assert "eyeBlinkLeft" not in found[0]["message"]


def test_evaluate_landmarks_takes_the_empirical_indices_themselves(tmp_path, monkeypatch):
    """``evaluate_landmarks(avatar, take, empirical=[1, 2, 3])`` raised TypeError (it read a path only);
    the indices themselves are a layout, as a JSON file of them is; anything else names the fix."""
    import usdface
    import usdface.landmarks.evaluate as evaluate
    from usdface.errors import LandmarkError

    csv = tmp_path / "t.csv"
    write_livelink_csv(csv, ["jawOpen"], np.full((4, 1), 0.5), np.arange(4) / 60)
    seen = {}
    monkeypatch.setattr(evaluate, "evaluate_landmarks",
                        lambda rig, weights, indices, **kw: seen.update(i=indices))
    usdface.evaluate_landmarks(str(SAMPLE / "avatar.usda"), csv, empirical=[1, 2, 3])
    assert seen["i"] == [1, 2, 3]
    usdface.evaluate_landmarks(str(SAMPLE / "avatar.usda"), csv, empirical=np.array([5, 6]))
    assert seen["i"] == [5, 6]
    for bad in ([1.5, 2.0], [], [[1, 2]]):
        with pytest.raises(LandmarkError, match="no list of vertex indices"):
            usdface.evaluate_landmarks(str(SAMPLE / "avatar.usda"), csv, empirical=bad)
    with pytest.raises(LandmarkError, match="out of range") as err:
        usdface.evaluate_landmarks(str(SAMPLE / "avatar.usda"), csv, empirical=[10 ** 9])
    assert err.value.path is None
