"""Face-rig rules (usdface.pipeline.check), their OpenUSD validators, the rule-checker object and
``usdface check``: hand-made bad stages each trip exactly the rule meant to catch them."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np
import pytest

import usdface.io  # noqa: F401  (schemas before the first stage)
from usdface.arkit import ARKIT_NAMES
from usdface.cli import main
from usdface.pipeline.check import ERROR, INFO, RULES, WARNING, Issue, check, has_errors
from usdface.pipeline.validators import (
    KEYWORD,
    FaceRigRuleChecker,
    register_validators,
    validate_file,
    validate_stage,
    validator_name,
)

pxr = pytest.importorskip("pxr")
from pxr import Sdf, Usd, UsdGeom, UsdSkel, UsdValidation, Vt  # noqa: E402

NAMES = [n for n in ARKIT_NAMES if n != "tongueOut"]  # 51, like the bench avatars

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


def make_rig(names=NAMES, n_points=4, anim_names=None, metadata=True) -> Usd.Stage:
    """A minimal valid ARKit face rig: SkelRoot /Avatar, Skeleton + SkelAnimation, Mesh /Avatar/Head with one
    sparse BlendShape per name."""
    stage = Usd.Stage.CreateInMemory()
    if metadata:
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    root = UsdSkel.Root.Define(stage, "/Avatar")
    if metadata:
        stage.SetDefaultPrim(root.GetPrim())
    skel = UsdSkel.Skeleton.Define(stage, "/Avatar/Skel")
    UsdSkel.BindingAPI.Apply(skel.GetPrim())
    anim = UsdSkel.Animation.Define(stage, "/Avatar/Skel/Anim")
    anim_names = list(names) if anim_names is None else anim_names
    anim.CreateBlendShapesAttr(anim_names)
    anim.CreateBlendShapeWeightsAttr(Vt.FloatArray([0.0] * len(anim_names)))
    UsdSkel.BindingAPI(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
    mesh = UsdGeom.Mesh.Define(stage, "/Avatar/Head")
    mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0)][:n_points])
    mesh.CreateFaceVertexCountsAttr([3, 3])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 1, 3, 2])
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    targets = []
    for name in names:
        shape = UsdSkel.BlendShape.Define(stage, f"/Avatar/Head/{name}")
        shape.CreateOffsetsAttr([(0, 0, 0.1)])
        shape.CreatePointIndicesAttr([1])
        targets.append(shape.GetPath())
    binding.CreateBlendShapesAttr(list(names))
    binding.CreateBlendShapeTargetsRel().SetTargets(targets)
    return stage


def rules_hit(issues, severity=None):
    return {(i.rule, i.prim) for i in issues if severity is None or i.severity == severity}


def test_valid_rig_is_clean():
    issues = check(make_rig())
    assert issues == []


def test_stage_metadata_missing():
    issues = check(make_rig(metadata=False))
    messages = " ".join(i.message for i in issues if i.rule == "StageMetadata")
    assert {i.severity for i in issues if i.rule == "StageMetadata"} == {ERROR}
    assert "upAxis" in messages and "metersPerUnit" in messages and "defaultPrim" in messages


def test_binding_api_missing_and_not_under_skelroot():
    stage = make_rig()
    stage.GetPrimAtPath("/Avatar/Head").RemoveAPI(UsdSkel.BindingAPI)
    assert ("SkelBinding", "/Avatar/Head") in rules_hit(check(stage), ERROR)
    stage = make_rig()
    stage.GetPrimAtPath("/Avatar").SetTypeName("Xform")
    issues = [i for i in check(stage) if i.rule == "SkelBinding"]
    assert any("SkelRoot" in i.message and i.prim == "/Avatar/Head" for i in issues)


def test_unbound_skeleton():
    stage = make_rig()
    UsdSkel.BindingAPI(stage.GetPrimAtPath("/Avatar/Head")).GetSkeletonRel().ClearTargets(True)
    issues = [i for i in check(stage) if i.rule == "SkelBinding"]
    assert issues and "Skeleton" in issues[0].message and issues[0].fix


def test_blend_shape_array_lengths():
    stage = make_rig()
    UsdSkel.BindingAPI(stage.GetPrimAtPath("/Avatar/Head")).GetBlendShapesAttr().Set(NAMES + ["extra"])
    issues = [i for i in check(stage) if i.rule == "BlendShapeArrays"]
    assert len(issues) == 1 and issues[0].severity == ERROR and "52 names" in issues[0].message


def test_target_not_a_blend_shape():
    stage = make_rig()
    stage.GetPrimAtPath("/Avatar/Head/jawOpen").SetTypeName("Xform")
    issues = [i for i in check(stage) if i.rule == "BlendShapeArrays"]
    assert len(issues) == 1 and "jawOpen" in issues[0].message


def test_offsets_vs_point_indices():
    stage = make_rig()
    shape = UsdSkel.BlendShape(stage.GetPrimAtPath("/Avatar/Head/jawOpen"))
    shape.GetOffsetsAttr().Set([(0, 0, 1), (0, 1, 0)])
    assert rules_hit(check(stage), ERROR) == {("BlendShapeOffsets", "/Avatar/Head/jawOpen")}
    stage = make_rig()  # dense shape with the wrong count
    shape = UsdSkel.BlendShape(stage.GetPrimAtPath("/Avatar/Head/jawOpen"))
    shape.GetPointIndicesAttr().Clear()
    shape.GetOffsetsAttr().Set([(0, 0, 1)] * 3)
    issues = [i for i in check(stage) if i.rule == "BlendShapeOffsets"]
    assert len(issues) == 1 and "points (4)" in issues[0].message
    shape.GetOffsetsAttr().Set([(0, 0, 1)] * 4)  # dense and right: clean
    assert not [i for i in check(stage) if i.rule == "BlendShapeOffsets"]


def test_nan_offsets():
    stage = make_rig()
    shape = UsdSkel.BlendShape(stage.GetPrimAtPath("/Avatar/Head/jawOpen"))
    shape.GetOffsetsAttr().Set([(0, float("nan"), 0)])
    assert any("NaN" in i.message for i in check(stage) if i.rule == "BlendShapeOffsets")


def test_point_indices_range_and_unique():
    stage = make_rig()
    shape = UsdSkel.BlendShape(stage.GetPrimAtPath("/Avatar/Head/jawOpen"))
    shape.GetPointIndicesAttr().Set([7])
    issues = [i for i in check(stage) if i.rule == "PointIndices"]
    assert len(issues) == 1 and "outside [0, 4)" in issues[0].message
    shape.GetPointIndicesAttr().Set([1, 1])
    shape.GetOffsetsAttr().Set([(0, 0, 1), (0, 0, 1)])
    issues = [i for i in check(stage) if i.rule == "PointIndices"]
    assert len(issues) == 1 and "repeated" in issues[0].message and issues[0].severity == ERROR


def test_inbetween_weights():
    stage = make_rig()
    shape = UsdSkel.BlendShape(stage.GetPrimAtPath("/Avatar/Head/jawOpen"))
    shape.CreateInbetween("half").SetWeight(0.5)
    shape.GetInbetween("half").SetOffsets([(0, 0, 0.05)])
    assert not [i for i in check(stage) if i.rule == "Inbetweens"]
    shape.CreateInbetween("over").SetWeight(1.5)
    shape.GetInbetween("over").SetOffsets([(0, 0, 0.2)])
    issues = [i for i in check(stage) if i.rule == "Inbetweens"]
    assert len(issues) == 1 and issues[0].severity == WARNING and "1.5" in issues[0].message
    shape.GetInbetween("half").SetOffsets([(0, 0, 0.05), (0, 0, 0.05)])
    assert any("inbetween" in i.message for i in check(stage) if i.rule == "BlendShapeOffsets")


def test_arkit_names_missing_misspelt_suffix_duplicate():
    names = list(NAMES)
    names[names.index("jawOpen")] = "jawOpn"            # typo
    names[names.index("eyeBlinkLeft")] = "eyeBlinkLeft2"  # Blender suffix
    names[names.index("cheekPuff")] = "CheekPuff"        # Live Link spelling: info only
    stage = make_rig(names=names)
    issues = [i for i in check(stage) if i.rule == "ArkitNames"]
    text = {i.severity: " | ".join(j.message for j in issues if j.severity == i.severity) for i in issues}
    assert "'jawOpn'" in text[WARNING] and "'jawOpen'" in text[WARNING]
    assert "'eyeBlinkLeft2'" in text[WARNING] and "suffix" in text[WARNING]
    assert "'CheekPuff'" in text[INFO]
    assert "jawOpen" in text[ERROR]  # the typo leaves jawOpen missing
    # tongueOut is optional; a second channel meaning the same shape is an error
    stage = make_rig(names=NAMES + ["eyeBlink_L"])
    errors = [i for i in check(stage) if i.rule == "ArkitNames" and i.severity == ERROR]
    assert len(errors) == 1 and "eyeBlinkLeft" in errors[0].message
    assert "usdface uses 'eyeBlinkLeft'" in errors[0].message  # the exact one; eyeBlink_L is left unmapped


def test_completeness_is_per_skeleton():
    """A second mesh with only some shapes (the bench Mouth) is fine: the skeleton's meshes together count."""
    stage = make_rig()
    mouth = UsdGeom.Mesh.Define(stage, "/Avatar/Mouth")
    mouth.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
    mouth.CreateFaceVertexCountsAttr([3])  # a mesh without faces is refused by the reader (rule Readable)
    mouth.CreateFaceVertexIndicesAttr([0, 1, 2])
    b = UsdSkel.BindingAPI.Apply(mouth.GetPrim())
    b.CreateSkeletonRel().SetTargets([Sdf.Path("/Avatar/Skel")])
    shape = UsdSkel.BlendShape.Define(stage, "/Avatar/Mouth/jawOpen")
    shape.CreateOffsetsAttr([(0, 0, 0.1)])
    shape.CreatePointIndicesAttr([0])
    b.CreateBlendShapesAttr(["jawOpen"])
    b.CreateBlendShapeTargetsRel().SetTargets([shape.GetPath()])
    assert check(stage) == []


def test_animation_names():
    anim_names = [n if n != "jawOpen" else "jaw_open" for n in NAMES]
    issues = [i for i in check(make_rig(anim_names=anim_names)) if i.rule == "AnimationNames"]
    assert len(issues) == 1 and issues[0].severity == WARNING and "jawOpen" in issues[0].message
    stage = make_rig()
    UsdSkel.Animation(stage.GetPrimAtPath("/Avatar/Skel/Anim")).GetBlendShapeWeightsAttr().Set(
        Vt.FloatArray([0.0] * 3), 1.0)
    issues = [i for i in check(stage) if i.rule == "AnimationNames"]
    assert len(issues) == 1 and issues[0].severity == ERROR and issues[0].prim == "/Avatar/Skel/Anim"


def _provenance_stage(tmp_path, digest=None):
    avatar = tmp_path / "avatar.usda"
    avatar.write_text("#usda 1.0\n")
    import hashlib

    real = hashlib.sha256(avatar.read_bytes()).hexdigest()
    layer = tmp_path / "out.usda"
    stage = make_rig()
    stage.GetRootLayer().Export(str(layer))
    stage = Usd.Stage.Open(str(layer))
    prim = stage.GetPrimAtPath("/Avatar")
    prim.ApplyAPI("UsdFaceProvenanceAPI")
    prim.GetAttribute("usdface:provenance:version").Set("0.1.0")
    prim.GetAttribute("usdface:provenance:command").Set("usdface personalize avatar.usda capture out.usda")
    prim.GetAttribute("usdface:provenance:inputs").Set(["avatar.usda"])
    prim.GetAttribute("usdface:provenance:inputDigests").Set([digest or real])
    return stage, avatar


def test_provenance(tmp_path):
    stage, avatar = _provenance_stage(tmp_path)
    assert [i for i in check(stage) if i.rule == "Provenance"] == []
    avatar.write_text("#usda 1.0\n# edited\n")  # the input changed after the layer was written
    issues = [i for i in check(stage) if i.rule == "Provenance"]
    assert len(issues) == 1 and issues[0].severity == WARNING and "changed" in issues[0].message
    stage.GetPrimAtPath("/Avatar").GetAttribute("usdface:provenance:inputDigests").Set(["abc", "def"])
    issues = [i for i in check(stage) if i.rule == "Provenance"]
    assert issues[0].severity == ERROR and "inputDigests" in issues[0].message
    stage.GetPrimAtPath("/Avatar").GetAttribute("usdface:provenance:command").Set("")
    assert any("command" in i.message for i in check(stage) if i.rule == "Provenance")


def test_openusd_validators_registered_from_python():
    names = register_validators()
    assert names == register_validators()  # idempotent
    assert validator_name("ArkitNames") in names and len(names) == len(RULES)
    stage = make_rig(anim_names=NAMES + ["tongueOut"])
    UsdSkel.BindingAPI(stage.GetPrimAtPath("/Avatar/Head")).GetBlendShapesAttr().Set(NAMES + ["tongueOut"])
    context = UsdValidation.ValidationContext(keywords=[KEYWORD])
    errors = [e for e in context.Validate(stage) if not e.HasNoError()]
    # the Readable rule (the avatar reader) refuses the same rig; as a separate validator it says so too
    assert {e.GetName() for e in errors} == {"BlendShapeArrays", "Readable"}
    arrays = next(e for e in errors if e.GetName() == "BlendShapeArrays")   # validators run in any order
    assert arrays.GetType() == UsdValidation.ValidationErrorType.Error
    assert [str(s.GetPrim().GetPath()) for s in arrays.GetSites()] == ["/Avatar/Head"]
    assert arrays.GetValidator().GetMetadata().name == validator_name("BlendShapeArrays")


def test_pixar_merge_keeps_duplicates_once():
    issues = validate_stage(make_rig(metadata=False))
    up = [i for i in issues if "upAxis" in i.message]
    assert len(up) == 1 and up[0].source == "usdface"
    stage = make_rig()
    stage.GetPrimAtPath("/Avatar/Skel").RemoveAPI(UsdSkel.BindingAPI)  # animationSource without the API
    pixar = [i for i in validate_stage(stage) if i.source == "pixar"]
    assert any("SkelBindingAPI" in i.rule and i.prim == "/Avatar/Skel" for i in pixar)


def test_rule_checker_object():
    checker = FaceRigRuleChecker()
    assert "ARKit" in checker.GetDescription()
    checker.CheckStage(make_rig(metadata=False))
    assert len(checker.GetFailedChecks()) == 3 and checker.GetErrors() == []
    checker.ResetCaches()             # what a compliance checker calls on every variant it selects
    assert len(checker.GetFailedChecks()) == 3 and len(checker.issues) == 3


def test_rule_checker_keeps_its_findings_through_a_compliance_checkers_variant_walk():
    """UsdUtils.ComplianceChecker (and checkers in its shape) calls CheckStage first, then ResetCaches each
    time it selects a variant; a usdface layer has the usdfacePersonalization variant set, and ResetCaches
    emptied the findings, so the checker reported none on exactly the files usdface writes."""
    stage = make_rig(metadata=False)
    root = stage.GetPrimAtPath("/Avatar")
    variants = root.GetVariantSets().AddVariantSet("usdfacePersonalization")
    for name in ("personalized", "generic"):
        variants.AddVariant(name)
    checker = FaceRigRuleChecker()
    checker.CheckStage(stage)          # the order of ComplianceChecker.CheckCompliance
    checker.CheckDiagnostics([])
    checker.CheckUnresolvedPaths([])
    checker.CheckDependencies(stage, [], [])
    for name in variants.GetVariantNames():
        variants.SetVariantSelection(name)
        checker.ResetCaches()
        for prim in stage.Traverse():
            checker.CheckPrim(prim)
    assert len(checker.GetFailedChecks()) == 3 and checker.GetErrors() == []


def test_issue_is_serialisable():
    i = Issue(ERROR, "X", "/A", "msg", "fix it")
    assert json.loads(json.dumps(i.to_dict()))["fix"] == "fix it" and has_errors([i])
    assert str(i).startswith("ERROR") and "fix it" in str(i)


def test_cli_exit_codes_and_json(tmp_path, capsys):
    good = tmp_path / "good.usda"
    good_stage = make_rig()  # keep the stage alive while exporting its layer
    good_stage.GetRootLayer().Export(str(good))
    assert main(["check", str(good)]) == 0
    bad_stage = make_rig()
    UsdSkel.BlendShape(bad_stage.GetPrimAtPath("/Avatar/Head/jawOpen")).GetPointIndicesAttr().Set([9])
    bad = tmp_path / "bad.usda"
    bad_stage.GetRootLayer().Export(str(bad))
    before = bad.read_bytes()
    capsys.readouterr()
    assert main(["check", str(bad), "--json"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert report["ok"] is False and report["counts"]["error"] == 1
    assert report["issues"][0]["prim"] == "/Avatar/Head/jawOpen" and report["issues"][0]["fix"]
    assert bad.read_bytes() == before  # never modifies its input
    assert main(["check", str(tmp_path / "missing.usda")]) == 2
    junk = tmp_path / "junk.usda"
    junk.write_text("not usd")
    assert main(["check", str(junk)]) == 2
    assert "junk.usda" in capsys.readouterr().err


@pytest.mark.shared
def test_bench_avatars(bench):
    assert validate_file(bench / "dev1" / "avatar.usdc") == []
    assert validate_file(bench / "dev2" / "avatar.usdc") == []
    blender = validate_file(bench / "dev1" / "avatar_blender.usdc")
    assert not has_errors(blender)
    suffixed = [i for i in blender if i.rule == "ArkitNames" and "suffix" in i.message]
    # one line for the 50 renamed channels of one mesh (a user trial: 50 near-identical warnings)
    assert len(suffixed) == 1 and suffixed[0].prim == "/root/Avatar/Mouth/Mouth"
    assert suffixed[0].message.startswith("50 channels look like ARKit names with a DCC numeric suffix: ")
    assert re.search(r"'(\w+)2' -> '\1'", suffixed[0].message) and "(+47 more)" in suffixed[0].message


@pytest.mark.shared
def test_pixar_usdskel_scenes(shared):
    """Pixar's own test scene has inbetweens at 1.5 and -0.499: warnings, found by the Inbetweens rule."""
    scene = (shared / "data/usd-real-world/openusd-usdskel/pxr/usd/usdSkel/testenv/testUsdSkelBakeSkinning"
             / "blendshapes.usda")
    issues = validate_file(scene)
    weights = sorted(i.message.split("weight ")[1].split(",")[0] for i in issues if i.rule == "Inbetweens")
    assert len(weights) == 3 and weights[0].startswith("-0.49")
    assert weights == ["-0.499", "1.5", "1.5"]      # as authored, not the float's -0.49900001287460327


def test_provenance_missing_on_a_result_layer(tmp_path):
    """A layer recorded as a usdface result (inputs, sublayered avatar) without the provenance schema is an
    error; a capture.usda's own record (format, no inputs) is not a result layer."""
    avatar = tmp_path / "avatar.usda"
    base = make_rig()
    base.GetRootLayer().Export(str(avatar))
    from pxr import Sdf

    layer = Sdf.Layer.CreateNew(str(tmp_path / "result.usda"))
    layer.subLayerPaths.append("avatar.usda")
    for key in ("upAxis", "metersPerUnit", "defaultPrim"):
        layer.pseudoRoot.SetInfo(key, base.GetRootLayer().pseudoRoot.GetInfo(key))
    layer.customLayerData = {"usdface": {"inputs": ["avatar.usda"], "inputDigests": ["0" * 64]}}
    layer.Save()
    issues = [i for i in check(Usd.Stage.Open(layer)) if i.rule == "Provenance"]
    assert len(issues) == 1 and issues[0].severity == ERROR and "UsdFaceProvenanceAPI" in issues[0].message
    capture = Sdf.Layer.CreateNew(str(tmp_path / "capture.usda"))
    capture.customLayerData = {"usdface": {"format": "capture", "version": "0.1.0"}}
    capture.Save()
    assert [i for i in check(Usd.Stage.Open(capture)) if i.rule == "Provenance"] == []


def test_readable_refuses_what_personalize_refuses():
    """``check`` never passes a rig personalize then refuses (docs/pipeline.md): blend shapes none of which
    is an ARKit shape (Blender's test files passed with one warning) unless the studio's name map gives them
    ARKit names; meshes without any blend shape (Pixar's skinned arm passed). A file without geometry (an
    animation take) is not an avatar and is not judged as one."""
    studio = check(make_rig(names=["Smile", "Frown", "Blink"]), rules=["Readable"])
    assert [i.message for i in studio if i.severity == ERROR] == [
        "no face-like blend shapes (no ARKit-named shape that moves): personalize finds no face mesh"]
    assert [i.prim for i in studio if i.severity == ERROR] == ["/Avatar/Head"]     # the mesh, not "/"
    mapped = check(make_rig(names=["Smile", "Frown", "Blink"]), rules=["Readable"],
                   name_map={"Smile": "mouthSmileLeft", "Frown": "mouthFrownLeft", "Blink": "eyeBlinkLeft"})
    assert not has_errors(mapped)
    arm = make_rig(names=[])
    arm.GetPrimAtPath("/Avatar/Head").RemoveProperty("skel:blendShapes")
    arm.GetPrimAtPath("/Avatar/Head").RemoveProperty("skel:blendShapeTargets")
    assert "no mesh with blend shapes" in check(arm, rules=["Readable"])[0].message
    take = make_rig()
    take.RemovePrim("/Avatar/Head")
    assert check(take, rules=["Readable"]) == []


def test_usdfaces_own_error_maps_pass_check(tmp_path):
    """``evaluate --usd`` writes error maps (meshes, no skinned rig): not judged as an avatar by Readable."""
    import numpy as np

    from usdface.io.usd_error_maps import write_error_maps_usd

    tri = np.array([[0, 1, 2]])
    points = np.array([[0.0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]])
    path = write_error_maps_usd(tmp_path / "errors.usda", tri,
                                {"dt": [("frame 0", points, np.zeros(3), np.zeros((3, 3)))]})
    assert not has_errors(validate_file(path))


@pytest.mark.parametrize("rules", [",", "", " , "])
def test_cli_rules_that_name_no_rule_are_refused(samples, capsys, rules):
    """``usdface check FILE --rules ,`` ran none of usdface's rules (a broken rig passed them, exit 0) and
    ``--rules ''`` all of them; both name no rule and are refused (exit 2) listing the rules; the empty
    value as every empty argument is, at the command line (an unset variable in a job template)."""
    if not rules:
        with pytest.raises(SystemExit) as done:
            main(["check", str(samples / "avatar.usda"), "--rules", rules])
        assert done.value.code == 2
        assert "argument --rules: empty value" in capsys.readouterr().err
        return
    assert main(["check", str(samples / "avatar.usda"), "--rules", rules]) == 2
    err = capsys.readouterr().err
    assert "names no rule" in err and "ArkitNames" in err


def test_cli_a_misspelt_rule_is_named_with_the_rule_meant(samples, capsys):
    """``--rules ArkitName`` (the rule is ArkitNames) was refused listing all eleven rules: the user had to
    find the one meant. A close name is said with it, case-insensitively; a name like no rule only listed."""
    assert main(["check", str(samples / "avatar.usda"), "--rules", "ArkitName,pointindices,Foo"]) == 2
    err = capsys.readouterr().err
    assert "'ArkitName' (did you mean ArkitNames?)" in err
    assert "'pointindices' (did you mean PointIndices?)" in err
    assert "'Foo' (fix: choose from" in err                        # like no rule: only the list
    assert "choose from" in err


def test_cli_a_rule_named_twice_runs_once(tmp_path, capsys):
    """A user trial: ``check FILE --no-pixar --rules ArkitNames,ArkitNames`` printed every finding twice and
    counted it twice (2 warnings of a file with one)."""
    from usdface.io.avatar_writer import write_rig_usd
    from usdface.model import FaceRig

    tri = np.array([[0, 1, 2]])
    rig = FaceRig(np.array([[0.0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]]), tri, ["Key_1"],
                  np.array([[[0.0, 0, 0.001], [0, 0, 0], [0, 0, 0]]]), name="Head")
    path = write_rig_usd(rig, tmp_path / "cube.usda")
    assert main(["check", str(path), "--no-pixar", "--rules", "ArkitNames"]) in (0, 1)
    once = capsys.readouterr().out
    assert main(["check", str(path), "--no-pixar", "--rules", "ArkitNames,ArkitNames"]) in (0, 1)
    assert capsys.readouterr().out == once
    assert once.count("'Key_1' is not an ARKit shape") == 1


def test_channels_named_arkit_only_by_their_prims_read_as_one_sentence(tmp_path, capsys):
    """Five Head channels renamed (``JawDrop``, ``Blink_L``, ...) with their BlendShape prims left as
    ARKit names were one warning that did not parse: '5 channels look like ARKit names with only its target
    prim is named so' (a user trial)."""
    from pxr import Usd

    renamed = {"jawOpen": "JawDrop", "eyeBlinkLeft": "Blink_L", "eyeBlinkRight": "Blink_R",
               "mouthSmileLeft": "SmileL", "browInnerUp": "BrowsWorry"}
    stage = Usd.Stage.Open(str(Path(__file__).resolve().parents[1] / "sample_assets" / "avatar.usda"))
    head = UsdSkel.BindingAPI(stage.GetPrimAtPath("/Avatar/Head"))
    tokens = head.GetBlendShapesAttr().Get()
    head.GetBlendShapesAttr().Set([renamed.get(t, t) for t in tokens])
    out = tmp_path / "studio.usda"
    stage.Export(str(out))
    issues = [i for i in validate_file(out) if i.rule == "ArkitNames" and i.prim == "/Avatar/Head"]
    grouped = [i.message for i in issues if i.message.startswith("5 channels")]
    assert grouped and grouped[0].startswith(
        "5 channels look like ARKit names only by their BlendShape prims' names: ")
    assert "with only its target prim" not in grouped[0]


def test_missing_arkit_shapes_under_a_studios_own_names_point_to_the_name_map(tmp_path, capsys):
    """A studio rig whose jawOpen is a channel and prim ``JawDrop``: ``check`` said '1 ARKit shape(s)
    missing: jawOpen (fix: add the missing shapes)' and 'channel 'JawDrop' is not an ARKit shape (fix: fine
    for extra shapes)', with no word of ``--name-map``, the fix (a user trial)."""
    sample = Path(__file__).resolve().parents[1] / "sample_assets" / "avatar.usda"
    studio = tmp_path / "studio.usda"
    studio.write_text(sample.read_text().replace("jawOpen", "JawDrop"))
    assert main(["check", str(studio), "--no-pixar", "--rules", "ArkitNames"]) == 1
    out = capsys.readouterr().out
    missing = [line for line in out.splitlines() if "ARKit shape(s) missing: jawOpen" in line]
    assert missing and "'JawDrop'), map them with --name-map FILE" in missing[0]
    assert "map it with --name-map FILE" in out
    (tmp_path / "names.json").write_text('{"JawDrop": "jawOpen"}')
    assert main(["check", str(studio), "--no-pixar", "--name-map", str(tmp_path / "names.json")]) == 0


HERO = 'def "Hero" (\n    instanceable = true\n    prepend references = @AVATAR@\n)\n{\n}\n'


def _shot(tmp_path: Path, header: str) -> Path:
    """A shot file referencing the sample avatar under an instanceable prim ``/Hero``."""
    path = tmp_path / "shot.usda"
    path.write_text(("#usda 1.0\n(\n" + header + ")\n" + HERO).replace("AVATAR", A.as_posix()))
    return path


def test_check_refuses_the_instanced_avatar_personalize_refuses(tmp_path, capsys):
    """``check`` (and so the publish validator) passed a shot that references the avatar under an
    instanceable prim, which personalize then refuses: check runs the refusal too."""
    from usdface.cli import main

    shot = _shot(tmp_path, '    defaultPrim = "Hero"\n    metersPerUnit = 0.01\n    upAxis = "Y"\n')
    assert main(["check", str(shot)]) == 1
    out = capsys.readouterr().out
    assert "[Readable]" in out and "instanceable prim /Hero" in out and "instanceable = false" in out
    assert main(["personalize", str(shot), str(C), "-o", str(tmp_path / "o.usda"), "-q"]) == 2


def test_check_passes_a_crowd_instancing_the_personalized_layer(personalized_sample, tmp_path, capsys):
    """A user trial (stop 44): a shot instancing the published personalized layer (a crowd: ``instanceable``
    references, one selecting ``generic``) failed check with 'the personalized layer would change nothing',
    though every instance shows its variant's offsets (UsdSkel over the instance proxies: the layer's, to
    the bit) and personalize refuses the file as already personalized, as it does without instancing (which
    check passes). An instanced reference that only selects ``generic`` stays refused, as personalize
    refuses it."""
    from usdface.cli import main

    def crowd(*selections):
        body = "".join(f'def "Crowd{i}" (\n    instanceable = true\n'
                       f'    prepend references = @{personalized_sample}@\n'
                       f'    variants = {{ string usdfacePersonalization = "{v}" }}\n)\n{{\n}}\n'
                       for i, v in enumerate(selections))
        path = tmp_path / f"crowd_{'_'.join(selections)}.usda"
        head = '#usda 1.0\n(\n    defaultPrim = "Crowd0"\n    metersPerUnit = 0.01\n    upAxis = "Y"\n)\n'
        path.write_text(head + body)
        return path

    mixed = crowd("personalized", "generic")
    assert main(["check", str(mixed), "--no-pixar"]) == 0, capsys.readouterr().out
    capsys.readouterr()
    assert main(["personalize", str(mixed), str(C), "-o", str(tmp_path / "o.usda"), "-q"]) == 2
    assert "already personalized" in capsys.readouterr().err
    assert main(["check", str(crowd("generic")), "--no-pixar"]) == 1
    assert "instanceable prim /Crowd0" in capsys.readouterr().out
    from usdface import api

    flat = api.export_avatar(mixed, flatten=tmp_path / "crowd_flat.usdc")["flatten"]   # its flattened export
    assert main(["check", str(flat), "--no-pixar"]) == 0, capsys.readouterr().out


def test_check_runs_the_reader_after_an_unrelated_error(tmp_path):
    """A missing metersPerUnit (an error of the StageMetadata rule the reader tolerates) no longer hides what
    the reader refuses: both are told in one run, not the second after the first is fixed."""
    from usdface.api import check as check_file

    inst = _shot(tmp_path, '    defaultPrim = "Hero"\n    upAxis = "Y"\n')
    rules = {i.rule for i in check_file(inst) if i.severity == "error"}
    assert {"StageMetadata", "Readable"} <= rules


def test_check_of_a_take_says_what_it_is(weights_take, capsys):
    """``check`` of an ``anim import`` take printed a bare '0 error(s)' as if it were a valid rig."""
    from usdface.cli import main

    assert main(["check", str(weights_take)]) == 0
    out = capsys.readouterr().out
    assert "this is a take" in out and "1 info" in out


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


BAD_RIGS = {
    "nan_points": "points contains NaN",
    "face_counts": "faceVertexCounts sum",
    "face_indices": "outside",
    "no_faces": "no faces",
    "mpu_zero": "metersPerUnit",
    "mpu_negative": "metersPerUnit",
    "mpu_nan": "metersPerUnit",
    "up_x": "upAxis",
}


def make_bad_rig(kind: str, out: Path) -> Path:
    """The sample avatar with one defect of ``kind`` (see BAD_RIGS), exported to ``out``."""
    from pxr import Sdf, Usd, UsdGeom, Vt

    # edited on a copy: the sample's own layer is USD's cached one for every test in this process (edited in
    # place, the defects piled up in later tests while anything kept it alive: face_counts in face_indices'
    # rig, upAxis X in the next module's sample)
    copy = Sdf.Layer.CreateAnonymous(".usda")
    copy.TransferContent(Sdf.Layer.FindOrOpen(str(SAMPLES / "avatar.usda")))
    stage = Usd.Stage.Open(copy)
    head = UsdGeom.Mesh(stage.GetPrimAtPath("/Avatar/Head"))
    if kind == "nan_points":
        p = np.array(head.GetPointsAttr().Get(), dtype=np.float32)
        p[5] = np.nan
        head.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(p))
    elif kind == "face_counts":
        c = list(head.GetFaceVertexCountsAttr().Get())
        c[0] += 1
        head.GetFaceVertexCountsAttr().Set(c)
    elif kind == "face_indices":
        i = list(head.GetFaceVertexIndicesAttr().Get())
        i[0] = 10 ** 6
        head.GetFaceVertexIndicesAttr().Set(i)
    elif kind == "no_faces":
        head.GetFaceVertexCountsAttr().Set([])
        head.GetFaceVertexIndicesAttr().Set([])
    elif kind.startswith("mpu_"):
        mpu = {"mpu_zero": 0.0, "mpu_negative": -1.0, "mpu_nan": float("nan")}[kind]
        stage.SetMetadata("metersPerUnit", mpu)
    elif kind == "up_x":
        stage.SetMetadata("upAxis", "X")
    elif kind == "time_sampled_points":
        attr = head.GetPointsAttr()
        value = attr.Get()
        attr.Clear()
        attr.Set(value, 1.0)
        attr.Set(value, 2.0)
    stage.GetRootLayer().Export(str(out))
    return out


def test_check_reports_what_the_reader_assumes(tmp_path):
    """Points only time-sampled (a cache export) are read at their first sample (they were refused):
    ``check`` reports that as a warning on the mesh, not as an error, and not silently."""
    import usdface

    path = make_bad_rig("time_sampled_points", tmp_path / "ts.usda")
    issues = usdface.check(path, pixar=False)
    assert not [i for i in issues if i.severity == "error"], issues
    said = [i for i in issues if i.severity == "warning" and "time sample" in i.message]
    assert len(said) == 1 and said[0].prim == "/Avatar/Head"


@pytest.mark.parametrize("kind", sorted(BAD_RIGS))
def test_check_catches_what_the_readers_refuse(tmp_path, kind):
    """``usdface check`` reported 0 errors on rigs every other command refuses."""
    import usdface

    path = make_bad_rig(kind, tmp_path / f"{kind}.usda")
    errors = [i for i in usdface.check(path, pixar=False) if i.severity == "error"]
    assert errors and any(BAD_RIGS[kind] in i.message for i in errors), errors


def test_the_bad_rigs_leave_the_samples_own_layer_untouched(tmp_path):
    """USD caches a layer by path for the whole process: editing the sample's own layer (not a copy) made
    the defects of one case show up in the next and in other modules' tests (upAxis X on the sample)."""
    from pxr import Sdf

    held = Sdf.Layer.FindOrOpen(str(SAMPLES / "avatar.usda"))   # as another test's stage would hold it
    for kind in sorted(BAD_RIGS):
        make_bad_rig(kind, tmp_path / f"{kind}.usda")
        assert not held.dirty, kind


@pytest.mark.parametrize("text", ["<S>/", "pipe.usda", "cycle.usda"])
def test_check_says_what_is_wrong_with_the_file(tmp_path, monkeypatch, capfd, text):
    """A folder or a pipe said 'file not found'; a sublayer cycle printed USD's warnings, then no cause."""
    monkeypatch.chdir(tmp_path)
    os.mkfifo("pipe.usda")
    Path("cycle.usda").write_text('#usda 1.0\n(\n    subLayers = [@other.usda@]\n)\n')
    Path("other.usda").write_text('#usda 1.0\n(\n    subLayers = [@cycle.usda@]\n)\n')
    assert main(["check", text.replace("<S>", str(tmp_path))]) == 2
    err = capfd.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not found" not in err
    assert any(w in err for w in ("folder", "named pipe", "cycles"))


def test_provenance_warns_about_a_dcc_export_of_a_personalized_layer(tmp_path):
    """Blender round trip (h5): Blender's export of a personalized layer passed 'usdface check' with only
    its renamed channels (a warning), though its shapes are the personalized ones and its provenance is
    gone; the Provenance rule now warns, naming the usdfaceShapes prim Blender kept. The plain avatar and a
    Blender export of it (no such prim) stay clean."""
    from pxr import Sdf, Usd

    samples = Path(__file__).resolve().parents[1] / "sample_assets"
    layer = Sdf.Layer.FindOrOpen(str(samples / "avatar.usda"))
    for name, marked in (("blender.usda", True), ("plain.usda", False)):
        out = Sdf.Layer.CreateNew(str(tmp_path / name))
        out.TransferContent(layer)
        if marked:          # Blender writes each variant scope back as an Xform beside the mesh
            Sdf.PrimSpec(out.GetPrimAtPath("/Avatar"), "usdfaceShapes_001", Sdf.SpecifierDef, "Xform")
        out.Save()
        issues = [i for i in check(Usd.Stage.Open(str(tmp_path / name))) if i.rule == "Provenance"]
        if marked:
            assert [(i.severity, i.prim) for i in issues] == [(WARNING, "/Avatar/usdfaceShapes_001")]
            assert "DCC export" in issues[0].message and "export the original avatar" in issues[0].fix
        else:
            assert issues == []


def test_a_reader_warning_that_carries_its_fix_is_told_with_that_fix_once(samples, tmp_path):
    """The reader's unit warning ends in its own '(fix: author metersPerUnit ...)'; the Readable issue added a
    second, generic one after it: '... (fix: author metersPerUnit = 1 ...) (fix: author what the reader
    assumed (see the message), or accept it)'. Now the issue's fix is the reader's own."""
    from pxr import Usd

    wrapper = tmp_path / "wrapper.usda"
    wrapper.write_text(f'#usda 1.0\n(\n    defaultPrim = "Avatar"\n    metersPerUnit = 1\n    upAxis = "Y"\n'
                       f'    subLayers = [@{samples / "avatar.usda"}@]\n)\n')
    issues = [i for i in check(Usd.Stage.Open(str(wrapper)), rules="Readable") if i.severity == WARNING]
    assert issues and "read 100x too large" in issues[0].message, issues
    assert "(fix:" not in issues[0].message and "metersPerUnit" in issues[0].fix, issues[0]
    assert str(issues[0]).count("(fix:") == 1


@pytest.mark.parametrize("how", ["subLayers", "references"])
def test_provenance_inputs_are_checked_from_the_layer_that_records_them(personalized_sample, tmp_path, how):
    """A shot in another folder that sublayers or references the published layer: its recorded inputs
    (paths relative to that layer) were resolved against the shot's folder, so each was 'not reachable from
    here; digest unchecked' (info) and a changed avatar went unnoticed under every shot."""
    shot = tmp_path / "shots" / "sq010" / "shot.usda"
    shot.parent.mkdir(parents=True)
    head = '#usda 1.0\n(\n    defaultPrim = "{}"\n    metersPerUnit = 0.01\n    upAxis = "Y"\n'
    if how == "subLayers":
        shot.write_text(head.format("Avatar") + f"    subLayers = [@{personalized_sample}@]\n)\n")
    else:
        shot.write_text(head.format("World") + ')\ndef Xform "World"\n{\n'
                        f'    def "Hero" (prepend references = @{personalized_sample}@)\n'
                        '    {\n    }\n}\n')
    issues = check(Usd.Stage.Open(str(shot)), rules="Provenance")
    assert issues == [], issues


def test_two_personalized_layers_stacked_in_a_shot_are_warned_about(personalized_sample, tmp_path):
    """A shot that sublayers v002 over v001 of one avatar's personalization checked clean: only v002's
    shapes, provenance and variant set show, v001's inputs go unchecked. Now a Provenance warning names
    both; one personalized layer (or a landmarks layer over it) is no stacking."""
    import shutil

    v1 = tmp_path / "v001" / "person.usda"
    v1.parent.mkdir()
    shutil.copy(personalized_sample, v1)
    text = v1.read_text()
    sub = re.search(r"subLayers = \[\s*@([^@]+)@", text).group(1)
    absolute = (personalized_sample.parent / sub).resolve()
    v1.write_text(text.replace(f"@{sub}@", f"@{absolute}@"))
    head = '#usda 1.0\n(\n    defaultPrim = "Avatar"\n    metersPerUnit = 0.01\n    upAxis = "Y"\n'
    shot = tmp_path / "shot.usda"
    shot.write_text(head + f"    subLayers = [@{personalized_sample}@, @{v1}@]\n)\n")
    found = [i for i in check(Usd.Stage.Open(str(shot)), rules="Provenance") if i.severity == WARNING]
    assert len(found) == 1 and "2 usdface layers personalize /Avatar" in found[0].message, found
    assert str(personalized_sample) in found[0].message and str(v1) in found[0].message, found
    one = tmp_path / "one.usda"
    one.write_text(head + f"    subLayers = [@{personalized_sample}@]\n)\n")
    assert check(Usd.Stage.Open(str(one)), rules="Provenance") == []


def test_check_says_an_error_map_file_is_not_an_avatar(samples, tmp_path, capsys):
    """A trial (stop 42): ``check errors.usda`` of ``evaluate --usd``'s error maps printed '0 error(s),
    0 warning(s), 0 info', a pass of a file that is no avatar, where a take or a capture is said to be one;
    it is told, with the command that summarises it."""
    maps = tmp_path / "errors.usda"
    assert main(["evaluate", str(samples / "capture.usda"), "--methods", "dt", "--usd", str(maps), "-q"]) == 0
    capsys.readouterr()
    assert main(["check", str(maps)]) == 0
    out = capsys.readouterr().out
    assert "error-map file ('usdface evaluate --usd'), not an avatar" in out and "1 info" in out
    assert "usdface inspect FILE" in out
