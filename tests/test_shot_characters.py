"""A shot with two characters (the avatar referenced twice, as a layout artist builds it) has no one face
mesh: until stop 45 ``usdface personalize shot.usda capture -o out.usda`` took the first character in the
file (the two tie) and put the person's shapes on it without a word. It is refused before any output, naming
each character's face mesh; ``--face-mesh`` picks one, and then that one (and only it) is personalized."""

from __future__ import annotations

import numpy as np
import pytest

import usdface.io  # noqa: F401  (schemas before the first stage)
from usdface.cli import main

pxr = pytest.importorskip("pxr")
from pxr import Gf, Usd, UsdGeom  # noqa: E402


def _shot(path, avatar, names=("Extra", "Hero")):
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    UsdGeom.SetStageUpAxis(stage, "Y")
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/Shot").GetPrim())
    for i, name in enumerate(names):
        prim = stage.DefinePrim(f"/Shot/{name}")
        prim.GetReferences().AddReference(str(avatar))
        UsdGeom.Xformable(prim).AddTranslateOp().Set(Gf.Vec3d(60.0 * i, 0, 0))
    stage.Save()
    return path


def test_a_shot_with_two_characters_is_refused_then_personalizes_the_one_named(samples, tmp_path, capsys):
    from usdface.io.usd_rig import read_avatar

    shot = _shot(tmp_path / "shot.usda", samples / "avatar.usda")
    out = tmp_path / "publish" / "hero_anna.usda"
    capture = str(samples / "capture.usda")

    assert main(["personalize", str(shot), capture, "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "2 characters' face rigs" in err and "/Shot/Extra/Head" in err and "/Shot/Hero/Head" in err, err
    assert "--face-mesh" in err
    assert not out.exists() and not any(p.name.startswith(".") for p in tmp_path.rglob("*"))

    assert main(["personalize", str(shot), capture, "-o", str(out), "-q", "--face-mesh", "/Shot/Hero/Head",
                 "--method", "dt"]) == 0
    generic = {m.source.prim: np.asarray(m.deltas) for m in read_avatar(shot).meshes}
    layer = {m.source.prim: np.asarray(m.deltas) for m in read_avatar(out).meshes}
    assert np.abs(layer["/Shot/Hero/Head"] - generic["/Shot/Hero/Head"]).max() > 1e-4   # the one named
    assert np.array_equal(layer["/Shot/Extra/Head"], generic["/Shot/Extra/Head"])       # the other: generic


def test_one_character_in_a_shot_needs_no_face_mesh(samples, tmp_path):
    """The refusal is for several characters only: one avatar referenced into a shot personalizes as
    before."""
    shot = _shot(tmp_path / "shot.usda", samples / "avatar.usda", names=("Hero",))
    out = tmp_path / "hero.usda"
    assert main(["personalize", str(shot), str(samples / "capture.usda"), "-o", str(out), "-q",
                 "--method", "dt"]) == 0
    assert out.exists()


def test_a_mesh_name_two_characters_share_is_refused_naming_their_paths(samples, tmp_path, capsys):
    """'--face-mesh Head' on the two-character shot took the first Head in the file; so did 'render --mesh
    Head' and 'landmarks --mesh Head'. A name several meshes carry is refused, listing their paths; a path
    (or a path's unique tail, 'Extra/Head') picks one."""
    shot = _shot(tmp_path / "shot.usda", samples / "avatar.usda")
    out = tmp_path / "p.usda"
    capture = str(samples / "capture.usda")
    assert main(["personalize", str(shot), capture, "-o", str(out), "-q", "--face-mesh", "Head"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "2 meshes are named 'Head' (/Shot/Extra/Head, /Shot/Hero/Head)" in err, err
    assert not out.exists()
    assert main(["render", str(shot), "-o", str(tmp_path / "r.png"), "--shapes", "jawOpen", "--mesh", "Head",
                 "-q"]) == 2
    assert "2 meshes are named 'Head'" in capsys.readouterr().err
    assert not (tmp_path / "r.png").exists()

    assert main(["personalize", str(shot), capture, "-o", str(out), "-q", "--face-mesh", "Extra/Head",
                 "--method", "dt", "--dry-run"]) == 0
    assert "/Shot/Extra/Head" in capsys.readouterr().out


def test_one_character_split_into_skelroots_is_not_taken_for_two(samples, tmp_path):
    """Blender writes a SkelRoot per mesh with shape keys and no armature: a head and its mouth interior in
    two SkelRoots around one place are one character, personalized as before (the refusal is for face rigs
    apart from each other)."""
    stage = Usd.Stage.CreateNew(str(tmp_path / "split.usda"))
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    UsdGeom.SetStageUpAxis(stage, "Y")
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/root").GetPrim())
    for name, off in (("Head", ("Mouth",)), ("Mouth", ("Head", "EyeLeft", "EyeRight"))):
        prim = stage.DefinePrim(f"/root/{name}")
        prim.GetReferences().AddReference(str(samples / "avatar.usda"))
        for child in off:
            stage.GetPrimAtPath(f"/root/{name}/{child}").SetActive(False)
    stage.Save()
    out = tmp_path / "split_p.usda"
    assert main(["personalize", str(tmp_path / "split.usda"), str(samples / "capture.usda"), "-o", str(out),
                 "-q", "--method", "dt"]) == 0
    assert out.exists()


def test_check_fails_a_two_character_shot_unless_the_face_mesh_is_named(samples, tmp_path, capsys):
    """'usdface check shot.usda' passed the shot personalize then refused (and so did Pyblish's validator):
    the preflight says it now, with the same test, and --face-mesh (face_mesh=) names the one meant; the
    layer personalizing one character checks clean without it."""
    import json

    shot = _shot(tmp_path / "shot.usda", samples / "avatar.usda")
    assert main(["check", str(shot), "--no-pixar", "--json"]) == 1
    issues = json.loads(capsys.readouterr().out)["issues"]
    errors = [i for i in issues if i["severity"] == "error"]
    assert [i["rule"] for i in errors] == ["Readable"], errors
    assert "2 characters' face rigs" in errors[0]["message"]
    assert "/Shot/Extra/Head" in errors[0]["fix"] and "/Shot/Hero/Head" in errors[0]["fix"]
    assert "--face-mesh" in errors[0]["fix"]

    assert main(["check", str(shot), "--no-pixar", "--face-mesh", "/Shot/Hero/Head"]) == 0
    capsys.readouterr()
    assert main(["check", str(shot), "--no-pixar", "--face-mesh", "Head"]) == 1     # two carry it
    assert "2 meshes are named 'Head'" in capsys.readouterr().out

    one = _shot(tmp_path / "one.usda", samples / "avatar.usda", names=("Hero",))
    assert main(["check", str(one), "--no-pixar"]) == 0                             # one character: as before
    out = tmp_path / "hero_p.usda"
    assert main(["personalize", str(shot), str(samples / "capture.usda"), "-o", str(out), "-q",
                 "--face-mesh", "/Shot/Hero/Head", "--method", "dt"]) == 0
    capsys.readouterr()
    assert main(["check", str(out), "--no-pixar"]) == 0, capsys.readouterr().out   # the layer is no input


def test_pyblish_validator_fails_a_two_character_shot_unless_the_face_mesh_is_named(samples, tmp_path):
    pyblish_api = pytest.importorskip("pyblish.api")
    import pyblish.util

    from usdface.pipeline import pyblish_plugins as plugins

    shot = _shot(tmp_path / "shot.usda", samples / "avatar.usda")
    pyblish_api.deregister_all_plugins()
    plugins.register()
    try:
        pyblish_api.deregister_plugin(plugins.ExtractUsdFacePersonalized)
        pyblish_api.deregister_plugin(plugins.ValidateUsdFaceCapture)
        context = pyblish_api.Context()
        item = {"avatar": str(shot), "capture": str(samples / "capture.usda")}
        context.data["usdfaceItems"] = [dict(item, output=str(tmp_path / "any.usda")),
                                        dict(item, output=str(tmp_path / "hero.usda"),
                                             usdfaceOptions={"face_mesh": "/Shot/Hero/Head"})]
        pyblish.util.publish(context)
        results = {(r["plugin"].__name__, None if r["instance"] is None else r["instance"].name): r
                   for r in context.data["results"]}
    finally:
        pyblish_api.deregister_all_plugins()
    failed = results[("ValidateUsdFaceRig", "any")]
    assert not failed["success"] and "2 characters' face rigs" in str(failed["error"]), failed["error"]
    hero = results[("ValidateUsdFaceRig", "hero")]
    assert hero["success"], hero["error"]


def test_landmarks_and_render_without_mesh_refuse_a_two_character_shot(samples, tmp_path, capsys):
    """'landmarks' and 'render' without --mesh took the first character's Head of a shot, without a word;
    they refuse as personalize does, naming the face meshes and --mesh, before writing anything."""
    shot = _shot(tmp_path / "shot.usda", samples / "avatar.usda")
    picture, layout = tmp_path / "r.png", tmp_path / "lm.usda"
    assert main(["render", str(shot), "-o", str(picture), "--shapes", "jawOpen", "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "2 characters' face rigs" in err and "/Shot/Extra/Head, /Shot/Hero/Head" in err, err
    assert "--mesh" in err and not picture.exists()
    assert main(["landmarks", str(shot), "-o", str(layout), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "2 characters' face rigs" in err and "--mesh" in err, err
    assert not layout.exists()

    assert main(["render", str(shot), "-o", str(picture), "--shapes", "jawOpen", "-q",
                 "--mesh", "/Shot/Hero/Head"]) == 0
    assert picture.exists()
    one = _shot(tmp_path / "one.usda", samples / "avatar.usda", names=("Hero",))
    assert main(["render", str(one), "-o", str(tmp_path / "one.png"), "--shapes", "jawOpen", "-q"]) == 0
