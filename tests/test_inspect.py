"""usdface inspect: avatars (names vs ARKit, storage, units), usdface layers (provenance), captures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from test_usd_rig import edit_stage, write_rig

from usdface.cli import main
from usdface.inspect import format_report, inspect_file, names_vs_arkit
from usdface.io.layers import write_avatar_layer
from usdface.io.usd_rig import read_avatar

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


def test_names_vs_arkit():
    got = names_vs_arkit(["eyeBlinkLeft", "eyeBlnkLeft", "jawOpen", "HeadTurn"],
                         {"inexact": [["eyeBlink_L", "eyeBlinkLeft", "spelling"]]})
    assert got["present"] == 2 and len(got["missing"]) == 50
    assert got["extra"] == ["eyeBlnkLeft", "HeadTurn"]
    assert got["misspelt"] == {"eyeBlnkLeft": "eyeBlinkLeft"}
    assert got["renamed"] == [{"given": "eyeBlink_L", "canonical": "eyeBlinkLeft", "how": "spelling"}]
    assert "tongueOut" not in got["missingRequired"] and "tongueOut" in got["missing"]


def test_blender_style_avatar(tmp_path):
    path = tmp_path / "b.usda"
    write_rig(path, "blender")
    report = inspect_file(path)
    assert report["kind"] == "avatar" and report["upAxis"] == "Z" and report["metersPerUnit"] == 1.0
    mouth = next(m for m in report["meshes"] if m["prim"] == "/root/Avatar/Mouth/Mouth")
    renamed = {"given": "eyeBlinkLeft2", "canonical": "eyeBlinkLeft", "how": "fallback"}
    assert renamed in mouth["arkit"]["renamed"]
    assert mouth["storage"]["denseIndexed"] == 3 and mouth["storage"]["sparse"] == 0
    assert mouth["storage"]["inbetweens"] == {"jawOpen": [{"name": "half", "weight": pytest.approx(-0.4)}]}
    assert mouth["vertices"] == 12 and mouth["triangles"] == 12 and mouth["polygons"] == {"3": 2, "4": 5}
    assert mouth["arkit"]["present"] == 3
    text = format_report(report)
    assert "eyeBlinkLeft2 -> eyeBlinkLeft (BlendShape prim name)" in text and "upAxis Z" in text
    json.dumps(report)  # JSON-serialisable


def test_usdface_layer_reports_provenance_and_variants(tmp_path):
    src = tmp_path / "a.usda"
    write_rig(src, "y_cm")
    avatar = read_avatar(src)
    offsets = {m.source.prim: m.deltas * 2 for m in avatar.meshes}
    out = write_avatar_layer(avatar, tmp_path / "p.usda", offsets,
                             provenance={"command": "usdface personalize a.usda cap/ -o p.usda"})
    report = inspect_file(out)
    assert report["kind"] == "usdface-layer" and report["subLayers"] == ["./a.usda"]
    assert report["provenance"]["command"].startswith("usdface personalize")
    assert report["variants"]["/Avatar"]["usdfacePersonalization"]["selection"] == "personalized"
    assert report["schemas"]["/Avatar"] == ["UsdFaceProvenanceAPI"]
    assert "variant set /Avatar:usdfacePersonalization = personalized" in format_report(report)


def test_cli_text_json_and_errors(tmp_path, capsys):
    path = tmp_path / "a.usda"
    write_rig(path, "y_cm")
    edit_stage(path, lambda s: s.GetPrimAtPath("/Avatar/Head").GetAttribute("skel:blendShapes").Set(
        ["eyeBlink_L", "jawOpen", "mouthSmileLeft"]))
    assert main(["inspect", str(path)]) == 0
    out = capsys.readouterr().out
    assert "mesh /Avatar/Head: 30 vertices" in out and "eyeBlink_L -> eyeBlinkLeft (spelling variant)" in out
    assert "metersPerUnit 0.01 (cm)" in out
    assert main(["inspect", "--json", str(path)]) == 0
    data = json.loads(capsys.readouterr().out)
    assert [m["prim"] for m in data["meshes"]] == ["/Avatar/Head", "/Avatar/Mouth"]
    assert main(["inspect", str(tmp_path / "missing.usda")]) == 2
    err = capsys.readouterr().err
    assert "missing.usda" in err and "fix:" in err and "Traceback" not in err
    # -q as every other command takes it (a wrapper passing it to each): the same report, nothing on stderr
    assert main(["inspect", "-q", str(path)]) == 0
    captured = capsys.readouterr()
    assert "mesh /Avatar/Head: 30 vertices" in captured.out and captured.err == ""


def test_bench_avatar_blender_renaming(bench):
    report = inspect_file(bench / "dev1" / "avatar_blender.usdc")
    mouth = next(m for m in report["meshes"] if m["name"] == "Mouth")
    assert len(mouth["arkit"]["renamed"]) == 50
    head = next(m for m in report["meshes"] if m["name"] == "Head")
    assert head["arkit"]["missing"] == ["tongueOut"] and head["storage"]["denseIndexed"] == 51
    plain = inspect_file(bench / "dev1" / "avatar.usdc")
    head = next(m for m in plain["meshes"] if m["name"] == "Head")
    assert head["storage"]["sparse"] + head["storage"]["dense"] == 51 and head["storage"]["sparse"] > 0
    assert np.allclose(head["boundsMetres"][1][1], 1.744, atol=0.01)  # top of the head at ~174 cm


def test_capture_folder_and_usda(bench, tmp_path):
    report = inspect_file(bench / "dev1" / "capture")
    assert report["kind"] == "capture" and report["roles"]["train"]["count"] == 51
    assert report["roles"]["test"]["count"] > 0 and report["arkit"]["missing"] == ["tongueOut"]
    assert "frames:" in format_report(report)
    try:
        from usdface.api import import_capture_folder
        out = import_capture_folder(bench / "dev1" / "capture", tmp_path / "capture.usda")
    except (ImportError, AttributeError):
        pytest.skip("capture.usda writer not available")
    usd_report = inspect_file(out)
    assert usd_report["kind"] == "capture" and usd_report["roles"] == report["roles"]


def test_fit_rig_says_what_it_records_not_none(tmp_path):
    """A user trial: 'inspect rig.usda' of a 'usdface fit' rig printed 'command None, created None' (the rig
    records its version and method only)."""
    from usdface import api
    from usdface.model import FaceRig

    tri = np.array([[0, 1, 2]])
    rig = FaceRig(np.eye(3), tri, ["jawOpen"], np.full((1, 3, 3), 0.01), name="FaceMask")
    text = format_report(inspect_file(api.write_fit_rig(rig, tmp_path / "rig.usda")))
    assert "None" not in text
    assert "usdface layer: version " in text and "method " in text


def test_usdskel_warnings_become_notes_not_terminal_lines(tmp_path, capfd):
    """A user trial: Pixar's ``jointInfluences.usda`` (and any avatar whose joint influences do not agree
    with each other) made every command print UsdSkel's C++ warnings (``Warning: in
    _InitializeJointInfluenceBindings at line 94 of .../skinningQuery.cpp -- jointIndices element size (3)
    != jointWeights element size (1).``) before usdface's own one-line answer. They are the reader's notes
    now: ``inspect`` shows them, nothing reaches the terminal."""
    from pxr import Usd, UsdGeom, UsdSkel, Vt

    from usdface.cli import main
    from usdface.io.avatar_writer import write_rig_usd
    from usdface.model import FaceRig

    neutral = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0.1, 0.1, 0]], dtype=float)
    bump = np.zeros_like(neutral)
    bump[3, 2] = 0.01
    tris = [[0, 1, 2], [1, 3, 2]]
    rigs = [FaceRig(neutral, tris, ["jawOpen"], bump[None], name="Head"),
            FaceRig(neutral + 1.0, tris, [], np.zeros((0, 4, 3)), name="Eye")]
    path = write_rig_usd(rigs, tmp_path / "a.usda")
    stage = Usd.Stage.Open(str(path))
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Mesh):
            UsdSkel.BindingAPI(prim).CreateJointIndicesPrimvar(True, 3).Set(Vt.IntArray([0, 0, 0]))
    stage.GetRootLayer().Save()
    capfd.readouterr()
    assert main(["inspect", str(path)]) == 0
    out, err = capfd.readouterr()
    assert "Warning" not in err and "skinningQuery.cpp" not in err, err
    assert "note: UsdSkel: jointIndices element size (3) != jointWeights element size (1)" in out


def test_an_avatar_with_an_animated_cache_is_not_a_take(tmp_path, capsys):
    """``inspect`` took an avatar whose root layer also holds a time-sampled mesh (a hair cache) for a take
    and failed on it ('no per-frame weights'); read_avatar, check and personalize accept it."""
    from usdface.cli import main
    from usdface.io.take import is_take

    cache = ('def Mesh "HairCache"\n    {\n        int[] faceVertexCounts = [3]\n'
             '        int[] faceVertexIndices = [0, 1, 2]\n'
             '        point3f[] points.timeSamples = {\n'
             '            1: [(0, 0, 0), (1, 0, 0), (0, 1, 0)],\n'
             '            2: [(0, 0, 1), (1, 0, 1), (0, 1, 1)],\n'
             '            3: [(0, 0, 2), (1, 0, 2), (0, 1, 2)],\n        }\n    }\n')
    text = A.read_text()
    at = text.index('def SkelRoot "Avatar"')
    at = text.index("{", at) + 1
    path = tmp_path / "avatar_cache.usda"
    path.write_text(text[:at] + "\n    " + cache + text[at:])
    assert not is_take(path)
    assert main(["inspect", str(path)]) == 0
    assert "avatar" in capsys.readouterr().out.splitlines()[0]


def test_inspect_summarises_a_weights_only_take(weights_take, capsys):
    """``inspect`` refused the take ``anim import`` had just written ('this is a take ..., not an avatar');
    index.md promises a summary: frames, rate, and the shapes never above 0.5."""
    from usdface.cli import main

    assert main(["inspect", str(weights_take)]) == 0
    out = capsys.readouterr().out
    assert "take" in out.splitlines()[0] and "60 frames at 30 fps" in out
    assert "never above 0.5 (51)" in out and "jawOpen" not in out.split("never above")[1].split("\n")[0]


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


def _sample_take():
    from usdface.io import read_capture
    from usdface.model import FaceRig
    from usdface.sample.take import make_take

    capture = read_capture(SAMPLES / "capture.usda")
    ct = np.load(SAMPLES / "truth" / "capture_truth.npz")
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


def test_inspect_summarises_an_error_map_file(tmp_path, capsys):
    """A user trial: 'usdface inspect errors.usda' (written by 'evaluate --usd') stopped with "this is an
    error-map file ..., not an avatar" (exit 2), from the command that summarises avatars, layers, captures
    and takes. It summarises it: per method the test frames, their mean RMSE and the largest vertex error."""
    from usdface.io.usd_error_maps import write_error_maps_usd

    tris = np.array([[0, 1, 2]])
    pts = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]])
    colors = np.zeros((3, 3))
    maps = {"dt": [("000", pts, np.array([1.0, 2.0, 2.0]), colors), ("001", pts, np.array([0.0, 0.0, 3.0]),
                                                                          colors)],
            "menzel paper": [("000", pts, np.array([0.5, 0.5, 0.5]), colors)]}
    out = write_error_maps_usd(tmp_path / "errors.usda", tris, maps)
    report = inspect_file(out)
    assert report["kind"] == "errorMaps" and list(report["methods"]) == ["dt", "menzel_paper"]
    dt = report["methods"]["dt"]
    assert dt["frames"] == 2 and dt["maxMm"] == 3.0
    assert np.isclose(dt["meanRmseMm"], (np.sqrt(3.0) + np.sqrt(3.0)) / 2)
    assert main(["inspect", str(out)]) == 0
    text = capsys.readouterr().out
    assert "error maps" in text and "menzel_paper: 1 test frame(s), mean RMSE 0.500 mm" in text


def test_the_file_inspected_is_named_absolute_whatever_its_kind(weights_take, tmp_path, monkeypatch):
    """A script's ``inspect_file("take.usda")["file"]`` came back as given (``take.usda``) for a take, a Live
    Link CSV and an error-map file, and absolute for an avatar or a capture: a host that changed folder
    afterwards no longer found the file (and ``usdface inspect`` headed one line relative, one absolute)."""
    import shutil

    from usdface.io.usd_error_maps import write_error_maps_usd

    shutil.copy(weights_take, tmp_path / "take.usda")
    (tmp_path / "take.csv").write_text("Timecode,BlendShapeCount,JawOpen\n00:00:00:00.000,1,0.5\n"
                                       "00:00:00:01.000,1,0.2\n")
    tris, pts = np.array([[0, 1, 2]]), np.eye(3) * 0.1
    write_error_maps_usd(tmp_path / "errors.usda", tris, {"dt": [("000", pts, np.ones(3), np.zeros((3, 3)))]})
    monkeypatch.chdir(tmp_path)
    for name in ("take.usda", "take.csv", "errors.usda"):
        assert inspect_file(name)["file"] == str(tmp_path / name), name


def test_inspect_names_a_layers_inspection_animation(tmp_path, capsys):
    """A trial: 'inspect' of a 'personalize --take' layer said nothing of the animation it plays (the
    capture's test expressions, then the take); it names the SkelAnimation, its frames and seconds and the
    take, and a layer without one says nothing."""
    from usdface.io.livelink import write_livelink_csv

    samples = Path(__file__).resolve().parents[1] / "sample_assets"
    w = np.random.default_rng(2).uniform(0, 1, size=(30, 2))
    write_livelink_csv(tmp_path / "take.csv", ["jawOpen", "eyeBlinkLeft"], w, np.arange(30) / 30.0)
    for name, extra in (("p.usda", ["--take", str(tmp_path / "take.csv")]), ("q.usda", [])):
        assert main(["personalize", str(samples / "avatar.usda"), str(samples / "capture.usda"),
                     "-o", str(tmp_path / name), "-q", *extra]) == 0
    capsys.readouterr()
    played = inspect_file(tmp_path / "p.usda")["inspectionAnimation"]
    assert played["prim"].endswith("/usdfaceInspection") and played["frames"] > 30 and played["seconds"] > 1
    assert main(["inspect", str(tmp_path / "p.usda")]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if "inspection animation" in x)
    assert f"{played['frames']} frames" in line and "test expressions, then the take" in line
    assert "take.csv" in line
    assert "inspectionAnimation" not in inspect_file(tmp_path / "q.usda")



def test_inspect_says_a_recorded_take_that_is_gone_is_missing(tmp_path, capsys):
    """A TD's trial: 'inspect' of a layer whose recorded take had been moved away still said 'then the take
    ../take.csv' and listed it as an input, as if it were there. A missing recorded input is a note (text
    and --json, with ``missingInputs``), its input line and the inspection animation's say so; an input that
    is there is not."""
    from usdface.io.livelink import write_livelink_csv

    samples = Path(__file__).resolve().parents[1] / "sample_assets"
    w = np.random.default_rng(2).uniform(0, 1, size=(30, 2))
    write_livelink_csv(tmp_path / "take.csv", ["jawOpen", "eyeBlinkLeft"], w, np.arange(30) / 30.0)
    layer = tmp_path / "out" / "p.usda"
    assert main(["personalize", str(samples / "avatar.usda"), str(samples / "capture.usda"), "-o", str(layer),
                 "-q", "--take", str(tmp_path / "take.csv")]) == 0
    capsys.readouterr()
    assert "missingInputs" not in inspect_file(layer)
    (tmp_path / "take.csv").rename(tmp_path / "moved.csv")
    assert main(["inspect", str(layer)]) == 0
    text = capsys.readouterr().out.splitlines()
    note = [x for x in text if "note:" in x and "missing" in x]
    assert len(note) == 1 and "../take.csv" in note[0] and str(tmp_path / "take.csv") in note[0]
    assert [x for x in text if x.strip().startswith("input ../take.csv")][0].endswith("(missing)")
    assert not [x for x in text if "capture.usda" in x and "missing" in x]
    played = next(x for x in text if "inspection animation" in x)
    assert "then the take ../take.csv (missing now" in played
    assert main(["inspect", str(layer), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["missingInputs"] == ["../take.csv"]
    assert any("../take.csv is missing" in n for n in doc["notes"])


def test_shape_storage_holds_no_copy_of_the_offsets():
    """``usdface inspect`` of a 225k-vertex head peaked at 1.2 GB: the zero-shape test formed
    ``np.linalg.norm`` of every offset at once (a squared [K, n, 3] copy and a [K, n] of norms, 370 MB beside
    the 275 MB rig). It goes shape by shape now: a few per cent of the rig at most."""
    import tracemalloc

    from usdface.inspect import shape_storage
    from usdface.model import FaceRig

    k, n = 8, 20_000
    deltas = np.zeros((k, n, 3))
    deltas[1:, ::7] = 1e-3
    rig = FaceRig(np.random.default_rng(0).normal(size=(n, 3)), np.array([[0, 1, 2]]),
                  [f"s{i}" for i in range(k)], deltas, name="Head")
    tracemalloc.start()
    try:
        storage = shape_storage(rig)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert storage["zeroShapes"] == ["s0"]
    assert peak < 0.2 * deltas.nbytes, peak


def test_a_file_without_blend_shapes_is_described_not_refused(shared, capsys):
    """User trial: ``usdface inspect skintest-blender-4.1.usda`` (a skinned grid, no shape keys) exited 2
    with the avatar reader's refusal, 'no mesh with blend shapes'. inspect describes a file: its meshes,
    skeleton and units, and why it is no face rig (the reader's message and fix, as a note); exit 0."""
    path = shared / "data/usd-real-world/blender/skintest-blender-4.1.usda"
    assert main(["inspect", str(path)]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0] == f"{path}: meshes without blend shapes", out
    assert "mesh /root/Armature/Grid/Grid: 121 vertices, 100 faces, no blend shapes, skinned by " \
           "/root/Armature/Armature_001" in out and "skeleton /root/Armature/Armature_001: 2 joints" in out
    assert "no mesh with blend shapes" in out and "fix: export the avatar with its shape keys" in out
    # as an avatar's (stop 42: 'metersPerUnit 1.0, upAxis Z, defaultPrim root')
    assert "  units: metersPerUnit 1.0 (m), upAxis Z, defaultPrim /root" in out.splitlines()
    assert main(["inspect", "--json", str(path)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["ok"] and doc["kind"] == "meshes without blend shapes" and doc["metersPerUnit"] == 1.0
    assert [m["prim"] for m in doc["meshes"]] == ["/root/Armature/Grid/Grid"]
    assert main(["personalize", str(path), str(C), "-o", "never.usda", "--dry-run"]) == 2   # still no avatar
    assert "no mesh with blend shapes" in capsys.readouterr().err


def test_a_mesh_missing_shapes_another_mesh_carries_does_not_list_them_as_missing():
    """A TD's trial (stop 53): ``inspect`` of the sample avatar listed ``missing (47): eyeBlinkLeft, ...`` for
    its teeth mesh (5 jaw shapes, as a mouth mesh has) beside the Head's 52/52, as if the rig lacked them.
    A mesh's missing shapes that another mesh of the file carries are named as carried there; those no mesh
    carries stay listed as missing."""
    root = Path(__file__).resolve().parents[1]
    text = format_report(inspect_file(root / "sample_assets" / "avatar.usda"))
    mouth = text[text.index("mesh /Avatar/Mouth"):]
    assert "ARKit: 5/52 present (the other 47 on /Avatar/Head)" in mouth, mouth
    assert "missing" not in mouth and "eyeBlinkLeft" not in mouth
    report = inspect_file(root / "sample_assets" / "avatar.usda")
    for mesh in report["meshes"]:                  # a shape no mesh carries: missing on each mesh
        mesh["arkit"]["missing"] = sorted(set(mesh["arkit"]["missing"]) | {"tongueOut"})
    text = format_report(report)
    mouth = text[text.index("mesh /Avatar/Mouth"):]
    assert "missing (1): tongueOut" in mouth and "on /Avatar/Head (47): " in mouth, mouth
    assert "missing (1): tongueOut" in text[:text.index("mesh /Avatar/Mouth")]
