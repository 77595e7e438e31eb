"""`usdface landmarks`: the output layer (primvars, Points prim, schema), CLI behaviour, bad input."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from test_render import grid_rig

from usdface.cli import main
from usdface.errors import LandmarkError, OutputExistsError
from usdface.io.livelink import write_livelink_csv
from usdface.landmarks import compute_landmarks

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"


def _digest(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def layer_run(samples, tmp_path_factory):
    out_dir = tmp_path_factory.mktemp("landmarks")
    avatar = samples / "avatar.usda"
    before = _digest(avatar)
    out, js, png = out_dir / "lm.usda", out_dir / "lm.json", out_dir / "lm.png"
    code = main(["landmarks", str(avatar), "--mesh", "Head", "--rays", "4", "--symmetric",
                 "--multicover", "2", "-o", str(out), "--json", str(js), "--plot", str(png)])
    return avatar, before, out, json.loads(js.read_text()), png, code


def test_cli_writes_layer_json_and_plot(layer_run):
    avatar, before, out, data, png, code = layer_run
    assert code == 0 and out.is_file() and png.stat().st_size > 1000
    assert _digest(avatar) == before  # input untouched
    assert data["status"] == "optimal" and data["gap"] == 0.0 and data["uncoverable"] == []
    assert data["count"] == len(data["vertices"]) == len(data["coverage"])
    assert data["symmetric"] is True


def test_layer_provenance_records_the_radius_and_spacing_used(layer_run):
    """The layer's provenance recorded the options as typed: radius and spacing left out were '' (not
    given), so the layer did not say which exclusion radius and skin sampling its layout was computed with.
    The default radius is relative to the face (2.4 % of its size; the sample's face is 0.26 m): the
    provenance holds the metres used, as the JSON's ``problem.radius`` does."""
    from usdface.io.usd_rig import usdface_layer_data

    _, _, out, data, _, _ = layer_run
    params = usdface_layer_data(out)["parameters"]
    assert params["radius"] == data["problem"]["radius"] and 0.003 < params["radius"] < 0.01
    assert params["spacing"] == data["problem"]["spacing"] > 0


def test_layer_content_round_trips(layer_run):
    from pxr import Usd, UsdGeom

    import usdface.schemas as schemas
    from usdface.io.usd_landmarks import points_prim_path

    avatar, _, out, data, _, _ = layer_run
    stage = Usd.Stage.Open(str(out))
    assert any(p.endswith("avatar.usda") for p in stage.GetRootLayer().subLayerPaths)
    mesh_path = data["mesh"]
    mesh = stage.GetPrimAtPath(mesh_path)
    pv = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("usdface:landmarks")
    assert pv.GetInterpolation() == UsdGeom.Tokens.constant
    assert list(pv.Get()) == data["vertices"]
    coverage = list(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("usdface:landmarkCoverage").Get())
    assert coverage == [",".join(c) for c in data["coverage"]]
    points = stage.GetPrimAtPath(points_prim_path(mesh_path))
    assert points.IsA(UsdGeom.Points) and points.HasAPI(schemas.LANDMARKS_API)
    cache = UsdGeom.XformCache()
    world_pts = np.array(cache.GetLocalToWorldTransform(points), dtype=float)
    world_mesh = np.array(cache.GetLocalToWorldTransform(mesh), dtype=float)
    p = np.array(UsdGeom.Points(points).GetPointsAttr().Get(), dtype=float)
    m = np.array(UsdGeom.Mesh(mesh).GetPointsAttr().Get(), dtype=float)[data["vertices"]]
    homog = np.hstack([p, np.ones((len(p), 1))]) @ world_pts
    expect = np.hstack([m, np.ones((len(m), 1))]) @ world_mesh
    np.testing.assert_allclose(homog, expect, atol=1e-5)  # landmarks sit on the mesh vertices
    assert len(UsdGeom.Points(points).GetWidthsAttr().Get()) == data["count"]
    assert len(UsdGeom.Points(points).GetDisplayColorPrimvar().Get()) == data["count"]
    keys = ("epsilon", "alpha", "solverStatus", "optimalityGap", "count", "symmetric", "multicover")
    attr = {k: points.GetAttribute(f"usdface:landmarks:{k}").Get() for k in keys}
    assert attr == {"epsilon": 0.5, "alpha": 0.5, "solverStatus": "optimal", "optimalityGap": 0.0,
                    "count": data["count"], "symmetric": True, "multicover": 2}
    assert list(points.GetAttribute("usdface:landmarks:vertexIndices").Get()) == data["vertices"]
    assert [str(t) for t in points.GetRelationship("usdface:landmarks:mesh").GetTargets()] == [mesh_path]


def test_refuses_to_overwrite_without_force(layer_run, capsys):
    avatar, _, out, _, _, _ = layer_run
    stamp = out.stat().st_mtime_ns
    assert main(["landmarks", str(avatar), "--rays", "2", "-o", str(out)]) == 2
    assert "--force" in capsys.readouterr().err
    assert out.stat().st_mtime_ns == stamp


def test_symmetric_layout_on_the_sample_head_is_exact(samples):
    from usdface.io.usd_rig import read_avatar
    from usdface.landmarks.symmetry import mirror_pairs

    head = read_avatar(samples / "avatar.usda").mesh("Head")
    layout = compute_landmarks(head, 0.5, symmetric=True, rays=2)
    partner = mirror_pairs(head.neutral)
    assert layout.symmetric and set(partner[layout.vertices].tolist()) == set(layout.vertices.tolist())
    assert layout.coverage.any(axis=0).all()


@pytest.mark.parametrize("argv, text", [(["--epsilon", "1.5"], "epsilon"), (["--mesh", "Nope"], "Nope"),
                                        (["--evaluate"], "--takes"),
                                        # the camera casts one ray per vertex: --rays was silently ignored
                                        (["--camera", "0,1.6,1"], "--camera sees from one point")])
def test_bad_input_exits_2_with_one_line(samples, tmp_path, capsys, argv, text):
    rays = [] if "--evaluate" in argv else ["--rays", "2"]      # refused with --evaluate (it casts none)
    assert main(["landmarks", str(samples / "avatar.usda"), *rays, *argv]) == 2
    err = capsys.readouterr().err
    assert text in err and "fix:" in err and err.count("\n") == 1


def test_api_errors_are_landmark_errors(samples, tmp_path):
    from usdface.io.usd_landmarks import write_landmark_layer
    from usdface.io.usd_rig import read_avatar

    avatar = read_avatar(samples / "avatar.usda")
    head = avatar.mesh("Head")
    with pytest.raises(LandmarkError):
        compute_landmarks(head, alpha=2.0)
    layout = compute_landmarks(head, 0.8, rays=2)
    out = tmp_path / "x.usda"
    out.write_text("#usda 1.0\n")
    with pytest.raises(OutputExistsError):
        write_landmark_layer(avatar, head, layout, out)


def test_spacing_options_sample_the_visibility_and_optionally_the_candidates(samples, tmp_path):
    runs = {}
    for name, argv in (("default", []), ("every", ["--spacing", "0"]), ("sampled", ["--sampled-candidates"])):
        js = tmp_path / f"{name}.json"
        assert main(["landmarks", str(samples / "avatar.usda"), "--mesh", "Head", "--rays", "1", "--json",
                     str(js), "-q", *argv]) == 0
        runs[name] = json.loads(js.read_text())["problem"]
    every, default, sampled = runs["every"], runs["default"], runs["sampled"]
    assert every["spacing"] is None and every["samples"] is None
    # the sample head's face box is smaller than a real head's: 2 % of it rounds to 4 mm
    assert default["spacing"] == sampled["spacing"] == pytest.approx(0.004)
    # by default every vertex stays a candidate and a few samples are ray cast, against a smaller occluder
    assert default["candidates"] == every["candidates"] and default["samples"] < default["candidates"]
    assert default["occluder_triangles"] < every["occluder_triangles"]
    assert sampled["candidates"] < default["candidates"]


def test_evaluate_refuses_rays_it_would_ignore(samples, tmp_path, monkeypatch, capsys):
    """A user trial: ``landmarks AVATAR --evaluate --takes T --rays 64`` ran the sweep with the rays ignored
    (it computes its layouts at alpha 0, casting no ray), and the docs said --rays served both modes. Now
    refused before any work, as the other layout-only options are; --rays still sets up a layout."""
    from usdface import api

    monkeypatch.setattr(api, "read_avatar", lambda *_a, **_k: pytest.fail("work started"))
    monkeypatch.chdir(tmp_path)
    argv = ["landmarks", str(samples / "avatar.usda"), "--evaluate", "--takes", "t.csv", "--rays", "64"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "--rays applies only to the layout" in err and "leave out --rays" in err
    assert list(tmp_path.iterdir()) == []
    monkeypatch.undo()
    assert main(["landmarks", str(samples / "avatar.usda"), "--rays", "4", "-q"]) == 0


def test_alpha_with_count_weighting_is_refused(samples, monkeypatch, capsys):
    """A user trial: ``landmarks AVATAR --weighting count --alpha 0.9`` gave the very layout of ``--alpha 0``
    (the count weighting costs every landmark 1; alpha weighs visibility in eq. 1's quality, which it does
    not use), and the layer recorded alpha 0.9. Now refused before any work."""
    from usdface import api

    monkeypatch.setattr(api, "read_avatar", lambda *_a, **_k: pytest.fail("work started"))
    assert main(["landmarks", str(samples / "avatar.usda"), "--weighting", "count", "--alpha", "0.9"]) == 2
    err = capsys.readouterr().err
    assert "--weighting count does not use" in err and "leave out --alpha" in err and err.count("\n") == 1


def test_inspect_reports_the_authored_layout(layer_run, capsys):
    """A user trial: ``inspect lm.usda`` of a landmarks layer said only 'method landmarks' (its provenance):
    nothing of the layout it holds. It lists each authored layout now: count, epsilon, alpha, multi-cover,
    symmetry, solver status (``--json``: ``landmarks``)."""
    _, _, out, data, _, _ = layer_run
    assert main(["inspect", str(out)]) == 0
    text = capsys.readouterr().out
    assert (f"landmark layout /Avatar/Head_landmarks: {data['count']} landmarks, epsilon 0.5, alpha 0.5, "
            "multi-cover 2, symmetric; solver optimal") in text
    assert main(["inspect", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["landmarks"]["/Avatar/Head_landmarks"]["count"] == data["count"]


def test_a_capture_folder_as_the_avatar_is_not_called_swapped_arguments(sample_capture_folder, capsys):
    """A user trial: ``landmarks capture/`` (one argument) answered 'avatar is a capture (or take) folder, not
    an avatar: arguments swapped? (fix: personalize AVATAR CAPTURE: ...)'. The message says what the folder
    is; the fix asks for the avatar, naming the two-argument commands where a swap is the likely cause."""
    assert main(["landmarks", str(sample_capture_folder)]) == 2
    err = capsys.readouterr().err
    assert "is a capture (or take) folder, not an avatar (fix: pass the avatar's .usd/.usda/.usdc file" in err
    assert "not an avatar: arguments swapped" not in err


def test_an_empty_or_negative_empirical_layout_is_named_for_what_it_is():
    """A user trial: ``--empirical`` with ``[]`` said 'indices out of range' (of an empty list), and one index
    out of 68 outside the mesh said the same without naming it. Now: 'lists no vertex index', or the
    range and the indices outside it."""
    from usdface.landmarks.baselines import empirical_layout

    with pytest.raises(LandmarkError, match="lists no vertex index"):
        empirical_layout([], 100)
    with pytest.raises(LandmarkError, match=r"out of range for a mesh of 100 vertices \(0\.\.99\): -5, 100"):
        empirical_layout([1, 2, -5, 100], 100)
    assert empirical_layout([3, 1, 3], 100).tolist() == [1, 3]


def test_a_failed_picture_takes_the_layer_and_json_of_this_run_with_it(samples, tmp_path, monkeypatch,
                                                                       capsys):
    """A user trial: ``landmarks AVATAR -o lm.usda --json lm.json --plot lm.png`` whose picture failed (a full
    disk, Ctrl-C) left the layer and the JSON behind as if the run had finished (export and evaluate are all
    or nothing). The outputs this run created go with the failure; one replaced with --force stays."""
    import errno

    from usdface.landmarks import plots

    def full_disk(*_a, **_k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(plots, "plot_layout", full_disk)
    out, js, png = tmp_path / "lm.usda", tmp_path / "lm.json", tmp_path / "lm.png"
    argv = ["landmarks", str(samples / "avatar.usda"), "--weighting", "count", "-q",
            "-o", str(out), "--json", str(js), "--plot", str(png)]
    assert main(argv) == 2
    assert "No space left on device" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    js.write_text("{}")                                   # an earlier JSON, replaced with --force: stays
    assert main([*argv, "--force"]) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lm.json"] and js.read_text() != "{}"


def test_shapes_that_move_nothing(samples, tmp_path, capsys):
    """User trial, Pixar's ``blendshapesWithNormals.usda`` (shapes of normal offsets only): ``landmarks
    --skip-static`` ended in a traceback (``IndexError: index 0 is out of bounds`` in the skin sampling: no
    shape was left to cover), and ``render --landmarks --diagnostics`` of a rig with such a shape refused it
    with 'pass --skip-static', an option render does not have. Now: every shape static is one LandmarkError
    line; render's diagnostics lay out the shapes that move (the static ones left out, as --skip-static)."""
    from pxr import Usd, UsdSkel, Vt

    from usdface.model import FaceRig

    avatar = tmp_path / "avatar.usda"
    avatar.write_text((samples / "avatar.usda").read_text())
    stage = Usd.Stage.Open(str(avatar))
    shape = next(UsdSkel.BlendShape(p) for p in stage.Traverse() if p.IsA(UsdSkel.BlendShape)
                 and p.GetName() == "eyeLookOutLeft" and "Head" in str(p.GetPath()))
    shape.GetOffsetsAttr().Set(Vt.Vec3fArray(len(shape.GetOffsetsAttr().Get())))
    stage.GetRootLayer().Save()
    assert main(["landmarks", str(avatar), "-q"]) == 2
    assert "--skip-static" in capsys.readouterr().err
    png = tmp_path / "d.png"
    assert main(["render", str(avatar), "--landmarks", "--diagnostics", "-o", str(png), "-q"]) == 0
    assert "landmarks (computed)" in capsys.readouterr().out and png.is_file()
    rig = FaceRig(np.eye(3), [[0, 1, 2]], ["jawOpen", "eyeBlinkLeft"], np.zeros((2, 3, 3)), name="Plane")
    with pytest.raises(LandmarkError, match="every shape of mesh Plane moves no vertex"):
        compute_landmarks(rig, ignore_static=True)


@pytest.mark.parametrize("extra, named", [
    (["--takes", "take.csv"], "--takes"),
    (["--frames", "100", "--noise", "1"], "--frames/--noise"),
    (["--empirical", "layout.json"], "--empirical"),
    (["--evaluate", "--takes", "take.csv", "-o", "layout.usda"], "-o/--output"),
    (["--evaluate", "--takes", "take.csv", "--epsilon", "0.6", "--alpha", "0.2"], "--epsilon/--alpha"),
    (["--evaluate", "--takes", "take.csv", "--spacing", "0"], "--spacing"),
    (["--evaluate", "--takes", "take.csv", "--multicover", "2", "--no-adaptive"],
     "--multicover/--no-adaptive"),
    (["--radius", "0.02"], "--radius"),                    # a user trial (stop 50): the single cover's layout
    (["--no-adaptive", "--multicover", "1"], "--no-adaptive"),     # as without them
    (["--symmetric", "--radius", "0.02", "--no-adaptive"], "--radius/--no-adaptive"),
])
def test_landmarks_refuses_an_option_of_the_other_mode(tmp_path, monkeypatch, capsys, extra, named):
    """--takes/--frames/--noise/--empirical without --evaluate used to be ignored (a layout was computed and
    written as if they were not there); -o with --evaluate was ignored too; --radius and --no-adaptive, which
    act on the multi-cover's later rounds, with a single cover (stop 50). Now refused before any work
    (the avatar is not even read: the missing take files are not reached), naming the option and the fix."""
    from usdface import api

    monkeypatch.setattr(api, "read_avatar", lambda *_a, **_k: pytest.fail("work started"))
    monkeypatch.chdir(tmp_path)
    assert main(["landmarks", str(SAMPLES / "avatar.usda"), *extra]) == 2
    err = capsys.readouterr().err
    assert "LandmarkError" not in err and named in err and "(fix: " in err
    if named.startswith(("--radius", "--no-adaptive")):
        assert "--multicover is 1" in err and "add --multicover N" in err
    elif "--evaluate" not in extra:
        assert "add --evaluate" in err
    else:
        assert f"leave out {named}" in err or "leave out -o" in err
    assert list(tmp_path.iterdir()) == []


def test_an_empirical_layout_of_another_mesh_names_its_file(tmp_path, capsys):
    """``landmarks --evaluate --empirical vertex_indices.json`` with indices beyond the mesh said "empirical
    layout indices out of range ..." without naming the file (the user gives two files and a mesh)."""
    from usdface.cli import main

    samples = Path(__file__).resolve().parents[1] / "sample_assets"
    layout = tmp_path / "vertex_indices.json"
    layout.write_text("[1, 2, 99999]")
    take = tmp_path / "take.csv"
    take.write_text("Timecode,BlendShapeCount,JawOpen\n00:00:00:00.000,1,0.5\n")
    assert main(["landmarks", str(samples / "avatar.usda"), "--evaluate", "--takes", str(take),
                 "--empirical", str(layout), "-q"]) == 2
    err = capsys.readouterr().err
    assert f"{layout}, prim /Avatar/Head: empirical layout indices out of range" in err


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


def test_landmark_evaluation_json_names_its_units():
    """Stop 43: ``landmarks --evaluate --json`` wrote every RMSE and the noise in metres (``"rmse":
    0.00157``) under keys without a unit, beside a printed summary in mm. The JSON says its units
    (``"units"``); the keys stay as they were, so readers of the old JSON go on working."""
    import json

    from usdface.landmarks.evaluate import EvaluationPoint, EvaluationReport, _summary

    pts = [EvaluationPoint("ours", "eps 0.5", 12, 2e-3), EvaluationPoint("random", "seed 0", 10, 4e-3)]
    report = EvaluationReport(pts, frames=10, noise=5e-4)
    report.summary = _summary(report, None)
    data = json.loads(json.dumps(report.to_dict()))
    assert data["units"] == {"rmse": "m", "noise": "m", "radius": "m"}
    assert data["noise"] == 5e-4 and data["points"][0]["rmse"] == 2e-3            # the keys of before
    lengths = [k for k in data["summary"] if "rmse" in k] + [k for p in data["points"] for k in p
                                                            if k == "rmse"]
    assert lengths and all(any(unit in k for unit in data["units"]) for k in lengths)


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
    usdface.evaluate_landmarks(str(SAMPLES / "avatar.usda"), csv, empirical=[1, 2, 3])
    assert seen["i"] == [1, 2, 3]
    usdface.evaluate_landmarks(str(SAMPLES / "avatar.usda"), csv, empirical=np.array([5, 6]))
    assert seen["i"] == [5, 6]
    for bad in ([1.5, 2.0], [], [[1, 2]]):
        with pytest.raises(LandmarkError, match="no list of vertex indices"):
            usdface.evaluate_landmarks(str(SAMPLES / "avatar.usda"), csv, empirical=bad)
    with pytest.raises(LandmarkError, match="out of range") as err:
        usdface.evaluate_landmarks(str(SAMPLES / "avatar.usda"), csv, empirical=[10 ** 9])
    assert err.value.path is None


def test_landmarks_says_every_file_it_wrote(samples, tmp_path, capsys):
    """landmarks.md's 'usdface landmarks avatar.usdc -o landmarks.usda --json layout.json --plot layout.png'
    printed 'wrote landmarks.usda' only; the JSON and the picture were written without a word (evaluate and
    render name each file they write)."""
    from usdface.cli import main

    out = [tmp_path / "landmarks.usda", tmp_path / "layout.json", tmp_path / "layout.png"]
    assert main(["landmarks", str(samples / "avatar.usda"), "-o", str(out[0]), "--json", str(out[1]),
                 "--plot", str(out[2]), "-q"]) == 0
    said = capsys.readouterr().out
    for path in out:
        assert path.exists() and f"wrote {path}" in said


def test_landmarks_evaluate_reads_a_usd_take(tmp_path):
    """User trial: landmarks --evaluate --takes refused the tool's own `anim import` output ('not a Live
    Link Face CSV (no Timecode column)' for a .usda); it reads USD takes as every take reader does."""
    from usdface.io.livelink import livelink_weights, write_livelink_csv

    names = ["jawOpen", "eyeBlinkLeft"]
    w = np.array([[0.0, 0.1], [0.5, 0.2], [0.9, 0.0]])
    write_livelink_csv(tmp_path / "take.csv", names, w, np.arange(3) / 30.0)
    assert main(["anim", "import", str(tmp_path / "take.csv"), "-o", str(tmp_path / "take.usda"), "-q"]) == 0
    from_csv = livelink_weights([tmp_path / "take.csv"], names)
    from_usd = livelink_weights([tmp_path / "take.usda"], names)
    np.testing.assert_allclose(from_usd, from_csv, atol=1e-6)


def test_landmarks_json_needs_force_and_is_checked_before_work(tmp_path, capfd):
    (tmp_path / "layout.json").write_text("{}")
    code = main(["landmarks", str(SAMPLES / "avatar.usda"), "--json", str(tmp_path / "layout.json")])
    assert code == 2 and "exists" in capfd.readouterr().err
    assert (tmp_path / "layout.json").read_text() == "{}"


def test_evaluate_landmarks_without_takes_names_the_api_argument(tmp_path, capfd):
    """A user trial: ``evaluate_landmarks(rig, None)`` said "--evaluate needs test weights (fix: pass
    --takes ...)", the command line's flags to a script. The API names its argument (the flag in
    parentheses at most); the command line keeps its own words, before the avatar is read."""
    import usdface
    from usdface.errors import OptionError

    avatar = str(SAMPLES / "avatar.usda")
    for takes in (None, 3):
        with pytest.raises(OptionError, match="evaluate_landmarks' takes must be") as err:
            usdface.evaluate_landmarks(avatar, takes)
        assert "--" not in str(err.value).split("(fix:")[0] and "takes=" in err.value.fix
    with pytest.raises(OptionError, match="each of evaluate_landmarks' takes"):
        usdface.evaluate_landmarks(avatar, [None])
    for takes in ([], ()):
        with pytest.raises(LandmarkError, match="takes is empty") as err:
            usdface.evaluate_landmarks(avatar, takes)
        fix = err.value.fix
        assert fix.startswith("pass takes=") and "(usdface landmarks --evaluate --takes" in fix
    assert main(["landmarks", str(tmp_path / "missing.usda"), "--evaluate", "-q"]) == 2
    err = capfd.readouterr().err
    assert "--evaluate needs test weights" in err and "pass --takes" in err and "missing.usda" not in err


def test_evaluation_plot_labels_its_errors_as_plain_millimetres(monkeypatch, tmp_path):
    """The --evaluate plot's log axis read '3x10^-1', '2x10^0' (matplotlib's labels of minor ticks, which
    are most of them on errors spanning a decade): plain numbers now (a user trial)."""
    from usdface.landmarks import plots
    from usdface.landmarks.evaluate import EvaluationPoint, EvaluationReport

    points = [EvaluationPoint("ours", f"l{n}", n, r * 1e-3) for n, r in ((10, 1.5), (20, 0.5), (68, 0.27))]
    points += [EvaluationPoint("random", f"r{n}", n, r * 1e-3) for n, r in ((8, 3.3), (68, 0.75))]
    saved = {}
    monkeypatch.setattr(plots, "_save", lambda fig, path, force: saved.setdefault("fig", fig))
    plots.plot_evaluation(EvaluationReport(points, frames=400, noise=5e-4), tmp_path / "e.png")
    ax = saved["fig"].axes[0]
    saved["fig"].canvas.draw()
    labels = {t.get_text() for minor in (False, True) for t in ax.get_yticklabels(minor=minor)} - {""}
    assert {"0.3", "0.5", "1", "2", "3"} <= labels, labels
    assert not [t for t in labels if "times" in t or "e-" in t or "^" in t], labels


def test_evaluate_says_when_the_takes_hold_fewer_frames_than_asked(samples, tmp_path, capsys):
    """A user trial: ``--evaluate`` with takes shorter than ``--frames`` evaluated fewer test frames without
    a word on the terminal (only the plot's title gave the count)."""
    from usdface.io.livelink import write_livelink_csv

    names = ["jawOpen", "eyeBlinkLeft", "mouthSmileLeft"]
    w = np.random.default_rng(1).uniform(0, 1, size=(12, 3))
    write_livelink_csv(tmp_path / "take.csv", names, w, np.arange(12) / 30.0)
    argv = ["landmarks", str(samples / "avatar.usda"), "--evaluate", "--takes", str(tmp_path / "take.csv")]
    assert main([*argv, "--frames", "8"]) == 0
    assert "test frame(s) evaluated" not in capsys.readouterr().out
    assert main([*argv, "--frames", "50"]) == 0
    out = capsys.readouterr().out
    assert "warning: the takes hold 12 frame(s): 12 test frame(s) evaluated, not 50 (--frames)" in out


def test_layout_plot_says_what_its_numbers_and_rounds_are(samples, tmp_path, monkeypatch):
    """A trial (stop 42): ``landmarks AVATAR --multicover 3 --plot lm.png`` printed a number beside every
    dot with nothing saying what it counts, and its 'multi-cover round' bar read 1.25, 1.75, 2.25 ...; the
    picture now says the number is the shapes a landmark represents, and the bar has whole rounds only."""
    from usdface.landmarks import plots

    figures = []
    monkeypatch.setattr(plots, "_save", lambda fig, path, force: figures.append(fig))
    assert main(["landmarks", str(samples / "avatar.usda"), "--rays", "4", "--symmetric", "--multicover", "3",
                 "--plot", str(tmp_path / "lm.png"), "-q"]) == 0
    (fig,) = figures
    ax = fig.axes[0]
    assert "shapes it represents" in ax.get_xlabel() and "symmetric" in ax.get_xlabel()
    numbers = [int(t.get_text()) for t in ax.texts]
    assert numbers and all(n >= 1 for n in numbers)
    (bar,) = fig.axes[1:]
    ticks = bar.get_yticks()
    assert len(ticks) >= 2 and np.allclose(ticks, np.round(ticks))


def test_layout_plot_of_a_flat_mesh_with_one_landmark_shows_the_mesh(tmp_path, monkeypatch):
    """A trial (stop 42) on Pixar's blend-shape test plane: ``landmarks blendshapes.usda --plot p.png`` drew a
    lone dot on a blank panel: only points in front of the 40th z percentile were drawn (none, or a part, of
    a flat mesh) and the view was framed 0.4 mm around the single landmark. A thin mesh is drawn whole, and
    one landmark is framed with the mesh around it."""
    from usdface.io.avatar_writer import write_rig_usd
    from usdface.landmarks import plots
    from usdface.model import FaceRig

    grid = grid_rig(9)                                     # a flat 9 x 9 sheet, its 'bump' as jawOpen
    neutral, tris = grid.neutral, grid.triangles
    avatar = write_rig_usd(FaceRig(neutral, tris, ["jawOpen"], grid.deltas[:1], name="Plane"),
                           tmp_path / "p.usda")
    figures = []
    monkeypatch.setattr(plots, "_save", lambda fig, path, force: figures.append(fig))
    assert main(["landmarks", str(avatar), "--rays", "4", "--plot", str(tmp_path / "p.png"), "-q"]) == 0
    (fig,) = figures
    ax = fig.axes[0]
    mesh, dots = ax.collections[0], ax.collections[1]
    assert len(dots.get_offsets()) == 1
    assert len(mesh.get_offsets()) == len(neutral)             # the whole plane drawn
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    assert x1 - x0 >= 0.2 and y1 - y0 >= 0.2                    # the view holds the 20 cm plane, not 0.4 mm


def test_layout_plot_of_a_mask_draws_every_point_that_faces_the_viewer(tmp_path, monkeypatch):
    """A trial (stop 42): ``landmarks rig.usda --plot`` of a ``usdface fit`` rig (the capture mask, an open
    surface with no back) drew only the front 60 % of its points in Z, its cheeks half empty. The points drawn
    are those whose normal faces the viewer: all of a mask, the face side of a head."""
    from usdface.io.avatar_writer import write_rig_usd
    from usdface.landmarks import plots
    from usdface.model import FaceRig

    n = 15                                           # a hemispherical cap facing +Z, 10 cm radius
    u, v = np.meshgrid(np.linspace(-0.07, 0.07, n), np.linspace(-0.07, 0.07, n))
    neutral = np.c_[u.ravel(), v.ravel(), np.sqrt(0.01 - u.ravel() ** 2 - v.ravel() ** 2)]
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1))
    a = (j * n + i).ravel()
    tris = np.r_[np.c_[a, a + 1, a + n], np.c_[a + 1, a + n + 1, a + n]]
    shapes = np.zeros((2, n * n, 3))
    shapes[0, :, 2] = 0.01 * (neutral[:, 0] > 0.03)
    shapes[1, :, 2] = 0.01 * (neutral[:, 0] < -0.03)
    rig = FaceRig(neutral, tris, ["eyeBlinkLeft", "eyeBlinkRight"], shapes, name="FaceMask")
    avatar = write_rig_usd(rig, tmp_path / "mask.usda")
    figures = []
    monkeypatch.setattr(plots, "_save", lambda fig, path, force: figures.append(fig))
    assert main(["landmarks", str(avatar), "--rays", "4", "--plot", str(tmp_path / "m.png"), "-q"]) == 0
    (fig,) = figures
    assert len(fig.axes[0].collections[0].get_offsets()) == n * n


@pytest.mark.parametrize("extra, said", [
    (["--one-shot"], "multicover is 1 (--multicover 1)"),
    (["--one-shot", "--multicover", "2", "--radius", "0.01"], "(--one-shot) replaces the adaptive rounds"),
    (["--one-shot", "--multicover", "2", "--no-adaptive"], "(--one-shot) replaces the adaptive rounds"),
    (["--one-shot", "--evaluate", "--takes", "take.csv"], "--one-shot applies only to the layout"),
])
def test_one_shot_refuses_what_it_would_ignore(tmp_path, monkeypatch, capsys, extra, said):
    """``--one-shot`` (the paper's one-ILP multi-cover) without ``--multicover N``, with the adaptive
    rounds' ``--radius``/``--no-adaptive``, or with ``--evaluate``: refused before any work."""
    from usdface import api

    monkeypatch.setattr(api, "read_avatar", lambda *_a, **_k: pytest.fail("work started"))
    monkeypatch.chdir(tmp_path)
    assert main(["landmarks", str(SAMPLES / "avatar.usda"), *extra]) == 2
    err = capsys.readouterr().err
    assert said in err and "(fix: " in err
    if "replaces" in said:       # the fix said "or --one-shot for the adaptive rounds": leave it out
        assert "or leave out one_shot (--one-shot)" in err


def test_one_shot_cli_covers_every_shape_n_times(samples, tmp_path, capsys):
    """``landmarks --multicover 2 --one-shot``: one round, every shape with at least min(2, its candidates)
    landmarks, and the layer's provenance says one-shot (no radius)."""
    from usdface.io.usd_rig import read_avatar, usdface_layer_data
    from usdface.landmarks.candidates import candidate_sets, relative_displacement

    out, js = tmp_path / "lm.usda", tmp_path / "lm.json"
    assert main(["landmarks", str(samples / "avatar.usda"), "--multicover", "2", "--one-shot", "--rays", "4",
                 "-o", str(out), "--json", str(js), "-q"]) == 0
    data = json.loads(js.read_text())
    assert data["problem"]["one_shot"] and data["problem"]["rounds"] == 1 and set(data["rounds"]) == {1}
    rig = read_avatar(samples / "avatar.usda").mesh("Head")
    c = candidate_sets(relative_displacement(np.linalg.norm(rig.deltas, axis=2)), 0.5)
    need = dict(zip(rig.names, np.minimum(2, c.sum(axis=1)).tolist(), strict=True))
    assert all(data["landmarks_per_shape"][k] >= need[k] for k in rig.names)
    params = usdface_layer_data(out)["parameters"]
    assert params["one_shot"] is True and params["radius"] == ""
