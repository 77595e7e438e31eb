"""Code review, session 24: each finding pinned by a test that failed before its fix."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from usdface.cli import main
from usdface.errors import FitError

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


def _capture():
    from usdface.api import read_capture

    return read_capture(C)


@pytest.mark.parametrize("mpu", ["-0.01", "0"])
def test_capture_with_a_bad_unit_is_refused(tmp_path, capsys, mpu):
    """A capture whose metersPerUnit is negative or 0 was fitted as a mirrored or collapsed face (a 'train
    RMSE 0.002 mm' rig); it is refused like an avatar with the same metadata, naming the file."""
    text = C.read_text()
    assert "metersPerUnit = 1\n" in text
    bad = tmp_path / "capture.usda"
    bad.write_text(text.replace("metersPerUnit = 1\n", f"metersPerUnit = {mpu}\n", 1))
    assert main(["fit", str(bad), "-o", str(tmp_path / "rig.usda"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "invalid metersPerUnit" in err and "capture.usda" in err
    assert not (tmp_path / "rig.usda").exists()


def test_weights_that_activate_nothing_are_refused(tmp_path, capsys):
    """Every training weight 0 (weights lost on export) crashed with numpy's 'cannot reshape array of size
    0'; it is a FitError naming the capture and the fix, from the CLI before any output."""
    from usdface.api import write_capture
    from usdface.model import Capture, Frames

    cap = _capture()
    f = cap.frames
    zero = Capture(cap.neutral, cap.triangles, cap.template,
                   Frames(f.points, np.zeros_like(f.weights), f.role, f.label), cap.names)
    path = tmp_path / "zero.usda"
    write_capture(zero, path)
    for argv in (["fit", str(path), "-o", str(tmp_path / "o.usda")],
                 ["personalize", str(A), str(path), "-o", str(tmp_path / "p.usda")]):
        assert main([*argv, "-q"]) == 2
        err = capsys.readouterr().err
        assert "no training frame activates any shape" in err and "zero.usda" in err and "fix:" in err
    assert not any(tmp_path.glob("[op].usda"))


def test_one_frame_fits_and_zero_frame_weights_are_refused():
    """One training frame: the Laplacian fit's 3-fold CV trained on an empty fold (a reshape crash); ebfr
    with beta 0 hit a singular matrix; all-zero frame weights passed the check and crashed later."""
    from usdface.model import Capture, Frames
    from usdface.personalize import fit_personalized_shapes

    cap = _capture()
    f = cap.frames
    one = Capture(cap.neutral, cap.triangles, cap.template,
                  Frames(f.points[:1], f.weights[:1], ["train"], f.label[:1]), cap.names)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = fit_personalized_shapes(one, "laplacian")
        assert np.all(np.isfinite(res.rig.deltas))
        with pytest.raises(FitError, match="bad beta 0"):
            fit_personalized_shapes(one, "ebfr", beta=0.0, align=False)
        with pytest.raises(FitError, match="not all 0"):
            fit_personalized_shapes(cap, frame_weights=np.zeros(len(cap.train)))


def test_a_pose_held_from_the_first_frame_is_a_peak_one_at_the_end_is_named():
    """find_peaks never returns an end sample: a take that starts on a held jawOpen lost it as 'never
    triggered' although it reached 0.95 and then relaxed (the paper's rule: it peaked). A weight still
    rising when the take ends has not peaked; the coverage now says so instead of 'never above 0.5'."""
    from usdface.take_select import format_coverage, select_frames

    w = np.zeros((60, 2))
    w[:10, 0] = 0.95
    w[10:20, 0] = np.linspace(0.9, 0.0, 10)             # held from frame 0, then relaxing
    w[50:, 1] = np.linspace(0.1, 1.0, 10)               # rising to the last frame
    sel = select_frames(w, names=["jawOpen", "eyeBlinkLeft"], min_separation=5)
    assert sel.shapes[0].frames == [4] and sel.missing == ["eyeBlinkLeft"]
    text = format_coverage(sel)
    assert "above 0.5 only at the take's end" in text and "max 1.00" in text


def test_a_capture_with_too_few_shapes_is_named_not_the_avatar(tmp_path, capsys):
    """A capture of jawOpen alone was refused with 'only 1 of the capture's shapes exist on the avatar face
    mesh' naming the avatar, which has all 52; the capture is what is short."""
    from usdface.api import write_capture
    from usdface.model import Capture, Frames

    cap = _capture()
    k = list(cap.names).index("jawOpen")
    f = cap.frames
    one = Capture(cap.neutral, cap.triangles, cap.template.subset(["jawOpen"]),
                  Frames(f.points, f.weights[:, [k]], f.role, f.label), ["jawOpen"])
    path = tmp_path / "jaw_only.usda"
    write_capture(one, path)
    assert main(["personalize", str(A), str(path), "-o", str(tmp_path / "p.usda"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "jaw_only.usda" in err and "the capture has 1 shape(s) (jawOpen)" in err
    assert "avatar.usda" not in err


def test_a_moved_latest_link_is_a_changed_input(tmp_path, capsys):
    """User trial: a layer written from lib/latest/hero.usda (latest -> v003) recorded the resolved v003, so
    after `ln -sfn v004 latest` check, review and export saw nothing (the layer composes over v004 now).
    The input is recorded through the link, as the sublayer path is, and check warns."""
    import os

    (tmp_path / "lib" / "v003").mkdir(parents=True)
    (tmp_path / "lib" / "v004").mkdir()
    text = A.read_text()
    (tmp_path / "lib" / "v003" / "hero.usda").write_text(text)
    (tmp_path / "lib" / "v004" / "hero.usda").write_text(text + "\n")
    os.symlink("v003", tmp_path / "lib" / "latest")
    out = tmp_path / "p.usda"
    assert main(["personalize", str(tmp_path / "lib" / "latest" / "hero.usda"), str(C), "-o", str(out),
                 "--method", "dt", "-q"]) == 0
    assert main(["check", str(out)]) == 0
    assert "changed after" not in capsys.readouterr().out
    os.unlink(tmp_path / "lib" / "latest")
    os.symlink("v004", tmp_path / "lib" / "latest")
    main(["check", str(out)])
    assert "input 'lib/latest/hero.usda' changed after this layer was written" in capsys.readouterr().out


def test_a_name_mapped_layer_reviews_with_arkit_names(tmp_path):
    """User trial: the review page of a layer over a studio-named avatar (ch17_ctrl = jawOpen) played a
    Live Link take with the jaw shut: the variants were read without the name map the layer records (every
    other reader applies it), so no channel drove ch17_ctrl."""
    import json

    from usdface.io.flatten import read_avatar_variant
    from usdface.review.collect import collect_review

    studio = tmp_path / "studio.usda"
    studio.write_text(A.read_text().replace("jawOpen", "ch17_ctrl"))
    (tmp_path / "map.json").write_text(json.dumps({"ch17_ctrl": "jawOpen"}))
    out = tmp_path / "p.usda"
    assert main(["personalize", str(studio), str(C), "--name-map", str(tmp_path / "map.json"), "-o", str(out),
                 "--method", "dt", "-q"]) == 0
    for variant in ("personalized", "generic"):
        assert "jawOpen" in read_avatar_variant(out, variant).mesh("Head").names
    data = collect_review(out, fit_errors=False)
    assert any("jawOpen" in m.names for m in data.meshes)


def test_the_pipeline_doc_validator_snippet_runs_without_warnings(tmp_path):
    """docs/pipeline.md's OpenUSD-validator snippet, copied as written, warned that the schema registry was
    created before usdface registered its schemas: register_validators built the validation registry
    first. Run as the doc gives it (on the sample avatar), in a fresh process, warnings as errors."""
    import re
    import subprocess
    import sys

    doc = (ROOT / "docs" / "pipeline.md").read_text()
    snippet = next(b for b in re.findall(r"```python\n(.*?)```", doc, re.S) if "register_validators()" in b)
    code = snippet.replace('"avatar.usdc"', repr(str(A)))
    done = subprocess.run([sys.executable, "-W", "error::UserWarning", "-c", code], capture_output=True,
                          text=True, cwd=tmp_path, check=False)
    assert done.returncode == 0 and "Warning" not in done.stderr, done.stderr


def test_refusal_of_a_flattened_export_names_the_avatar_as_one_can_pass_it(tmp_path, monkeypatch):
    """User trial: the refusal suggested '(avatar.usda)', the name recorded relative to the layer, which does
    not exist relative to where the user stands; it is now a path from the current folder."""
    import re

    from usdface.errors import AlreadyPersonalizedError
    from usdface.io.usd_rig import refuse_usdface_output

    out = tmp_path / "out"
    out.mkdir()
    assert main(["personalize", str(A), str(C), "-o", str(out / "p.usda"), "--method", "dt", "-q"]) == 0
    assert main(["export", str(out / "p.usda"), "--flatten", str(out / "flat.usdc"), "-q"]) == 0
    elsewhere = tmp_path / "shot"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    with pytest.raises(AlreadyPersonalizedError) as err:
        refuse_usdface_output(Path("../out/flat.usdc"))
    named = re.search(r"pass the original avatar \((.+)\)\)?$", err.value.fix).group(1).rstrip(")")
    assert Path(named).resolve() == A.resolve()


def _two_meshes(shared_under_instance: bool) -> str:
    """Two triangle meshes under one SkelRoot binding jawOpen: one BlendShape prim shared by both, or each
    its own prim under an instanceable Lib."""
    mesh = """
    def Mesh "{name}" (prepend apiSchemas = ["SkelBindingAPI"])
    {{
        point3f[] points = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]
        int[] faceVertexCounts = [1]
        int[] faceVertexIndices = [0, 1, 2]
        rel skel:skeleton = </Root/Skel>
        uniform token[] skel:blendShapes = ["jawOpen"]
        rel skel:blendShapeTargets = [<{target}>]
    }}"""
    shape = """
        def BlendShape "{name}"
        {{
            uniform vector3f[] offsets = [(0, -1, 0), (0, -1, 0), (0, -1, 0)]
        }}"""
    if shared_under_instance:
        meshes = mesh.format(name="Head", target="/Root/Lib/jawOpen").replace("[1]", "[3]")
        lib = ('def Scope "Lib" (instanceable = true\n        references = </Proto>)\n    {\n    }\n}\n'
               'def Scope "Proto"\n{' + shape.format(name="jawOpen") + "\n")
    else:
        meshes = "".join(mesh.format(name=n, target="/Root/Shapes/jawOpen").replace("[1]", "[3]")
                         for n in ("Head", "Mouth"))
        lib = 'def Scope "Shapes"\n    {' + shape.format(name="jawOpen") + "\n    }"
    return ('#usda 1.0\n(\n    defaultPrim = "Root"\n    metersPerUnit = 0.01\n    upAxis = "Y"\n)\n'
            'def SkelRoot "Root"\n{\n    def Skeleton "Skel" {}\n' + meshes + "\n    " + lib + "\n}\n")


@pytest.mark.parametrize("instanced, needle", [(False, "is bound by 2 meshes (/Root/Head, /Root/Mouth)"),
                                                (True, "inside the instanceable prim /Root/Lib")])
def test_blend_shapes_a_layer_cannot_override_are_refused(tmp_path, capsys, instanced, needle):
    """USD review: a BlendShape bound by two meshes got the last mesh's offsets for both (in its own local
    frame), and one under an instanceable prim silently kept its values; personalize and check refuse both
    before any work, naming the BlendShape."""
    from usdface.errors import RigError
    from usdface.io.usd_rig import read_avatar, refuse_unwritable_shapes

    path = tmp_path / "avatar.usda"
    path.write_text(_two_meshes(instanced))
    avatar = read_avatar(path)
    with pytest.raises(RigError, match=re.escape(needle)):
        refuse_unwritable_shapes(avatar)
    main(["check", str(path), "--no-pixar"])
    assert needle in capsys.readouterr().out


def test_check_judges_only_meshes_that_bind_blend_shapes(tmp_path):
    """USD review (Pixar's testUsdSkelCache/populate.usda): skel:blendShapes on a Scope (UsdSkel ignores it
    there) and a mesh that blocks both bindings were reported as 'skel:blendShapes has 1 names but
    skel:blendShapeTargets 0 targets' errors; a mesh with names and no targets still is."""
    from usdface.api import check

    path = tmp_path / "populate.usda"
    path.write_text("""#usda 1.0
(
    defaultPrim = "Root"
    metersPerUnit = 0.01
    upAxis = "Y"
)
def SkelRoot "Root"
{
    def Scope "Scope" (prepend apiSchemas = ["SkelBindingAPI"])
    {
        uniform token[] skel:blendShapes = ["ignored"]
        def Mesh "Block" (prepend apiSchemas = ["SkelBindingAPI"])
        {
            point3f[] points = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]
            int[] faceVertexCounts = [3]
            int[] faceVertexIndices = [0, 1, 2]
            uniform token[] skel:blendShapes = None
            rel skel:blendShapeTargets = None
        }
        def Mesh "Override" (prepend apiSchemas = ["SkelBindingAPI"])
        {
            point3f[] points = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]
            int[] faceVertexCounts = [3]
            int[] faceVertexIndices = [0, 1, 2]
            uniform token[] skel:blendShapes = ["shape"]
        }
    }
}
""")
    arrays = [i.prim for i in check(path, pixar=False) if i.rule == "BlendShapeArrays"]
    assert arrays == ["/Root/Scope/Override"]


def _two_roots() -> str:
    root = """
def SkelRoot "{r}"
{{
    def Skeleton "Skel" {{}}
    def Mesh "Head" (prepend apiSchemas = ["SkelBindingAPI"])
    {{
        point3f[] points = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]
        int[] faceVertexCounts = [3]
        int[] faceVertexIndices = [0, 1, 2]
        rel skel:skeleton = </{r}/Skel>
        uniform token[] skel:blendShapes = ["jawOpen"]
        rel skel:blendShapeTargets = [</{r}/Head/jawOpen>]
        def BlendShape "jawOpen"
        {{
            uniform vector3f[] offsets = [(0, -1, 0), (0, -1, 0), (0, -1, 0)]
            uniform vector3f[] inbetweens:half = [(0, -0.2, 0), (0, -0.2, 0), (0, -0.2, 0)] (weight = 0.5)
        }}
    }}
}}
"""
    return ('#usda 1.0\n(\n    defaultPrim = "A"\n    metersPerUnit = 0.01\n    upAxis = "Y"\n)\n'
            + root.format(r="A") + root.format(r="B"))


def test_export_keeps_one_node_per_mesh_and_says_inbetweens_are_dropped(tmp_path):
    """USD review: two SkelRoots with a Head each gave two glTF nodes named 'Head' (and the OBJ export
    one folder for both); and the glTF/OBJ targets silently dropped inbetweens (a shape with an inbetween
    at 0.5 plays 2.4 cm off there)."""
    import pygltflib

    from usdface import api

    path = tmp_path / "two.usda"
    path.write_text(_two_roots())
    with pytest.warns(UserWarning, match=r"2 shape\(s\) have inbetweens.*A_Head:jawOpen"):
        api.export_avatar(path, gltf=tmp_path / "two.glb", obj_dir=tmp_path / "objs")
    names = [n.name for n in pygltflib.GLTF2().load(str(tmp_path / "two.glb")).nodes]
    assert names == ["A", "A_Head", "B_Head"]
    assert sorted(p.name for p in (tmp_path / "objs").iterdir()) == ["A_Head", "B_Head"]


def test_time_sampled_only_offsets_are_named_as_such(tmp_path):
    """USD review: offsets authored as time samples only (no default) read as '0 offsets for a mesh of 3
    points' and checked as 'BlendShape has no offsets'; both now say what is wrong."""
    from usdface.api import check
    from usdface.errors import RigError
    from usdface.io.usd_rig import read_avatar

    text = _two_meshes(False).replace(
        "uniform vector3f[] offsets = [(0, -1, 0), (0, -1, 0), (0, -1, 0)]",
        "vector3f[] offsets.timeSamples = {1: [(0, -1, 0), (0, -1, 0), (0, -1, 0)]}")
    path = tmp_path / "ts.usda"
    path.write_text(text)
    with pytest.raises(RigError, match="time-sampled only"):
        read_avatar(path)
    assert any("time-sampled only" in i.message for i in check(path, pixar=False))


def test_a_smaller_capture_gives_the_same_personalization(tmp_path):
    """Review: the field's smoothing (and the join of the offset modes) took the capture's mean edge as the
    correspondence measured it on the capture placed on the avatar, then multiplied it by the registration's
    scale again: a capture 10x smaller than its person (a wrong unit) smoothed over 9 rings instead of 2 and
    moved the offsets by 12 % of the personalization. The same capture at a tenth of its size (registration
    scale ~10) now gives the same offsets."""
    import dataclasses

    from usdface.api import read_avatar
    from usdface.model import Capture, FaceRig, Frames
    from usdface.transfer import personalize_avatar

    cap, avatar = _capture(), read_avatar(A)
    s = 0.1
    t, f = cap.template, cap.frames
    small = Capture(cap.neutral * s, cap.triangles,
                    FaceRig(t.neutral * s, t.triangles, list(t.names), t.deltas * s, name=t.name),
                    Frames(f.points * s, f.weights, f.role, f.label), cap.names)
    small = dataclasses.replace(small, metadata=dict(cap.metadata or {}))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = personalize_avatar(avatar, cap, None, method="dt")
        b = personalize_avatar(avatar, small, None, method="dt")
    key = avatar.mesh("Head").key
    change = np.abs(a.offsets[key] - avatar.mesh("Head").deltas).max()
    assert np.abs(a.offsets[key] - b.offsets[key]).max() < 1e-3 * change


@pytest.mark.parametrize("how", ["mm", "z-up"])
def test_a_frame_in_other_units_or_axes_is_refused(how):
    """User trial: one training OBJ exported in millimetres (or Z up) among metre Y-up ones was fitted
    silently ('train RMSE 9690 mm', truth error 0.19 -> 3.5 mm); the frame is named and the fit refused."""
    from usdface.errors import GeometryError
    from usdface.model import Capture, Frames
    from usdface.personalize import fit_personalized_shapes

    cap = _capture()
    f = cap.frames
    points = np.array(f.points)
    k = list(f.role).index("train")
    centre = points[k].mean(axis=0)
    zup = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    points[k] = points[k] * 1000.0 if how == "mm" else (points[k] - centre) @ zup.T + centre
    bad = Capture(cap.neutral, cap.triangles, cap.template, Frames(points, f.weights, f.role, f.label),
                  cap.names)
    with pytest.raises(GeometryError, match=rf"frame '{f.label[k]}' is turned .* not in the neutral's units"):
        fit_personalized_shapes(bad, "dt")


def test_a_capture_in_millimetres_read_as_metres_is_said():
    """User trial: a whole capture in millimetres fitted a rig 1000x too large without a word."""
    from usdface.model import Capture, FaceRig, Frames
    from usdface.personalize import fit_personalized_shapes

    cap = _capture()
    t, f = cap.template, cap.frames
    mm = Capture(cap.neutral * 1000, cap.triangles,
                 FaceRig(t.neutral * 1000, t.triangles, list(t.names), t.deltas * 1000, name=t.name),
                 Frames(f.points * 1000, f.weights, f.role, f.label), cap.names)
    with pytest.warns(UserWarning, match=r"the neutral scan is .* m across .* are its units right"):
        fit_personalized_shapes(mm, "dt")


def test_a_frame_weight_file_without_its_scan_is_refused(tmp_path):
    """User trial: a train/ JSON whose OBJ was missing was skipped silently ('50 train frames'), while an
    OBJ without its JSON is a clear error; both are now."""
    import shutil

    from usdface.api import read_capture, write_capture
    from usdface.errors import CaptureError

    folder = tmp_path / "cap"
    write_capture(_capture(), folder)
    victim = sorted((folder / "train").glob("*.obj"))[3]
    victim.unlink()
    with pytest.raises(CaptureError, match=rf"train/{victim.stem}.json has no scan {victim.name}"):
        read_capture(folder)
    shutil.rmtree(folder)


def test_inspect_of_a_capture_without_test_frames_says_no_animation(tmp_path, capsys):
    """User trial: with an empty test/ folder, personalize --inspect printed 'test-expression SkelAnimation'
    although it wrote none."""
    from usdface.api import write_capture
    from usdface.model import Capture, Frames

    cap = _capture()
    f = cap.frames
    keep = [i for i, r in enumerate(f.role) if r == "train"]
    train_only = Capture(cap.neutral, cap.triangles, cap.template,
                         Frames(f.points[keep], f.weights[keep], ["train"] * len(keep),
                                [f.label[i] for i in keep]), cap.names)
    path = tmp_path / "train_only.usda"
    write_capture(train_only, path)
    assert main(["personalize", str(A), str(path), "-o", str(tmp_path / "p.usda"), "--method", "dt",
                 "--inspect"]) == 0
    out = capsys.readouterr().out
    assert "no SkelAnimation (the capture has no test expressions" in out
    assert "usdfaceInspection" not in (tmp_path / "p.usda").read_text().split("SkelAnimation")[0][-200:]


def test_evaluate_refuses_another_captures_truth(tmp_path):
    """User trial: evaluate --truth printed 'vs truth 0.677' against another person's truth file (its neutral
    6.8 mm from the capture's); a truth whose neutral is not the capture's is refused."""
    from usdface import api
    from usdface.errors import InputFileError

    npz = np.load(SAMPLES / "truth" / "capture_truth.npz")
    other = {k: npz[k] for k in npz.files}
    other["neutral"] = other["neutral"] + np.array([0.0, 0.004, 0.0])          # another face, 4 mm off
    np.savez(tmp_path / "other.npz", **other)
    with pytest.raises(InputFileError, match=r"4.00 mm RMS from the capture's neutral scan"):
        api.evaluate_methods(C, ["dt"], truth=tmp_path / "other.npz")


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


def test_a_misspelt_template_file_is_refused_with_the_rename(tmp_path):
    """User trial: template/jawOpn.obj was accepted with two warnings, every jawOpen weight dropped and
    jawOpn 'never activated'; refused, naming the rename."""
    from usdface.api import read_capture, write_capture
    from usdface.errors import CaptureError

    folder = tmp_path / "cap"
    write_capture(_capture(), folder)
    (folder / "template" / "jawOpen.obj").rename(folder / "template" / "jawOpn.obj")
    with pytest.raises(CaptureError, match=r"rename template/jawOpn.obj to template/jawOpen.obj"):
        read_capture(folder)


def test_json_documents_carry_the_readers_warnings(tmp_path, capsys):
    """User trial: `fit --json` listed the fit's own warnings only; a capture reader's (a frame weight for a
    shape the template lacks) went to stderr alone, so a pipeline reading the document never saw it."""
    import json

    from usdface.api import write_capture

    folder = tmp_path / "cap"
    write_capture(_capture(), folder)
    first = sorted((folder / "train").glob("*.json"))[0]
    data = json.loads(first.read_text())
    data["blendShapes"]["notAShape"] = 0.5
    first.write_text(json.dumps(data))
    for argv in (["fit", str(folder), "-o", str(tmp_path / "r.usda"), "--method", "dt", "--json"],
                 ["personalize", str(A), str(folder), "-o", str(tmp_path / "p.usda"), "--method", "dt",
                  "--json"]):
        assert main(argv) == 0
        doc = json.loads(capsys.readouterr().out)
        assert any("notAShape" in w for w in doc["warnings"]), doc["warnings"]
