"""A usdface output given where an avatar goes (a personalized layer or its flattened export) is refused,
naming the file, the avatar it came from as one can pass it, and the fix; a flattened generic export or a
plain avatar is accepted."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from usdface.cli import main

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


@pytest.fixture(scope="module")
def person_layer(tmp_path_factory) -> Path:
    """A usdface layer over the sample avatar (personalized offsets on the Head: the layer carries the
    personalization variant set and the provenance)."""
    from usdface.io.layers import write_avatar_layer
    from usdface.io.usd_rig import read_avatar

    avatar = read_avatar(SAMPLES / "avatar.usda")
    head = avatar.mesh("Head")
    return write_avatar_layer(avatar, tmp_path_factory.mktemp("person") / "person.usda",
                              {head.key: head.deltas * 1.01}, provenance={})


def test_flattened_personalized_export_is_not_personalized_again(person_layer, tmp_path, capsys):
    """A `usdface export --flatten` of the personalized variant lost the variant set the refusal looked for:
    personalize stacked the personalization a second time. Now it is refused (AlreadyPersonalizedError) naming
    the file, the layer it came from and the fix (the generic variant, or the original avatar)."""
    from usdface.io.flatten import flatten_variant

    flat = flatten_variant(person_layer, tmp_path / "flat.usdc", "personalized")
    for command, out in (("personalize", tmp_path / "p2.usda"), ("retarget", tmp_path / "m.json")):
        argv = [command, str(flat), str(SAMPLES / "capture.usda"), "-o", str(out)]
        assert main(argv + (["--json"] if command == "personalize" else [])) == 2
        captured = capsys.readouterr()
        assert "flattened export" in captured.err and str(flat) in captured.err
        assert "--variant generic" in captured.err and "avatar.usda" in captured.err
        if command == "personalize":
            error = json.loads(captured.out)["error"]
            assert error["type"] == "AlreadyPersonalizedError" and error["file"] == str(flat)
            assert "person.usda --flatten flat.generic.usdc --variant generic" in error["fix"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["flat.usdc"]


def test_flattened_generic_export_and_plain_avatar_are_accepted(person_layer, tmp_path):
    """A flattened *generic* export is the avatar's own shapes: accepted. A flattened plain avatar records
    'authored' (it used to record 'personalized', the variant asked for, which it does not have)."""
    from pxr import Sdf

    from usdface.errors import AlreadyPersonalizedError
    from usdface.io.flatten import flatten_variant
    from usdface.io.usd_rig import flattened_from, refuse_usdface_output

    generic = flatten_variant(person_layer, tmp_path / "generic.usdc", "generic")
    flat = flattened_from(generic)            # the source relative to the flattened file (stop 23)
    assert flat["variant"] == "generic"
    assert (generic.parent / flat["source"]).resolve() == person_layer.resolve()
    refuse_usdface_output(generic)                       # no error
    plain = flatten_variant(SAMPLES / "avatar.usda", tmp_path / "plain.usdc", "personalized")
    assert dict(Sdf.Layer.FindOrOpen(str(plain)).customLayerData)["usdfaceFlatten"]["variant"] == "authored"
    refuse_usdface_output(plain)
    with pytest.raises(AlreadyPersonalizedError):        # the layer itself: refused as before
        refuse_usdface_output(person_layer)


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


def test_refusal_of_a_flattened_export_names_its_layer_from_the_current_folder(tmp_path, monkeypatch,
                                                                              capsys):
    """A user trial (stop 52): with the layer in the current folder and its flattened export in out/, the
    refusal said "... of the usdface layer ../p.usda" (the name recorded relative to the export) and its fix
    "usdface export out/../p.usda ..."; both now name the layer as one passes it from here: p.usda."""
    from usdface.errors import AlreadyPersonalizedError
    from usdface.io.usd_rig import refuse_usdface_output

    monkeypatch.chdir(tmp_path)
    assert main(["personalize", str(A), str(C), "-o", "p.usda", "--method", "dt", "-q"]) == 0
    assert main(["export", "p.usda", "--flatten", "out/flat.usdc", "-q"]) == 0
    with pytest.raises(AlreadyPersonalizedError) as err:
        refuse_usdface_output(Path("out/flat.usdc"))
    assert "of the usdface layer p.usda;" in err.value.message, err.value.message
    fix = err.value.fix
    assert "usdface export p.usda --flatten flat.generic.usdc --variant generic" in fix, fix
    assert ".." not in err.value.message + err.value.fix.split(" or pass")[0]
    # export's refusal of its generic variant said "a flattened export of the personalized variant of
    # ../p.usda: ... (fix: export the generic variant of the layer it was flattened from (p.usda) ...)"
    from usdface.errors import InputFileError
    from usdface.io.flatten import flatten_variant

    with pytest.raises(InputFileError) as err:
        flatten_variant(Path("out/flat.usdc"), "generic.usdc", "generic")
    assert "personalized variant of p.usda:" in err.value.message, err.value.message
    assert err.value.path == "out/flat.usdc"          # as given (it was the absolute path)
    # exported again: "[personalized, as baked into flat.usdc (a flattened export of ../p.usda)]"
    capsys.readouterr()
    assert main(["export", "out/flat.usdc", "--obj-dir", "objs", "-q"]) == 0
    assert "as baked into flat.usdc (a flattened export of p.usda)]" in capsys.readouterr().out


def test_usdface_output_is_not_personalized_again(tmp_path, capfd):
    """Issue 10 item 5: personalizing a usdface layer would stack the personalization; name the original."""
    from usdface.io.layers import write_avatar_layer
    from usdface.io.usd_rig import read_avatar

    avatar = read_avatar(SAMPLES / "avatar.usda")
    head = avatar.mesh("Head")          # personalized offsets: the layer carries the personalization variants
    layer = write_avatar_layer(avatar, tmp_path / "person.usda", {head.key: head.deltas * 1.01},
                               provenance={})
    for argv in (["personalize", str(layer), str(SAMPLES / "capture.usda"), "-o", str(tmp_path / "p2.usda")],
                 ["retarget", str(layer), str(SAMPLES / "capture.usda"), "-o", str(tmp_path / "m.json")]):
        assert main(argv) == 2
        err = capfd.readouterr().err
        assert "already personalized" in err and "avatar.usda" in err and str(layer) in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["person.usda"]
    assert read_avatar(layer).mesh("Head").n_shapes  # reading it (check, render, inspect) is still fine


def _dcc_export(layer: Path, out: Path, blender_layout: bool = True) -> Path:
    """What Blender 5 writes back for a usdface layer (the round trip studios make): the composed stage with
    the selected variant baked in, no variant set, no customLayerData, no provenance schema; each
    ``usdfaceShapes`` scope an Empty written back as an ``Xform`` beside the mesh, the second one renamed
    ``usdfaceShapes_001`` (prims as in the real export of the sample's layer)."""
    from pxr import Sdf, Usd

    flat = Usd.Stage.Open(str(layer)).Flatten()
    flat.customLayerData = {}
    flat.subLayerPaths.clear()
    root = flat.GetPrimAtPath("/Avatar")
    if root.HasInfo("apiSchemas"):
        root.ClearInfo("apiSchemas")
    for name in [n for n in root.properties.keys() if n.startswith("usdface:")]:
        root.RemoveProperty(root.properties[name])
    if blender_layout:                  # Blender's second scope, beside the Mouth
        Sdf.PrimSpec(root, "usdfaceShapes_001", Sdf.SpecifierDef, "Xform")
    flat.Export(str(out))
    return out


def test_dcc_export_of_a_personalized_layer_is_not_personalized_again(person_layer, tmp_path, capfd):
    """Blender round trip (h5): Blender's re-export of a personalized layer has neither the variant set nor
    the provenance, so it was personalized again as a plain avatar (the personalization stacked, silently;
    the docs called it undetectable). It keeps the usdfaceShapes scopes (Blender's Empties), and is now
    refused (AlreadyPersonalizedError) naming the file, the scope prim and the fix, before any output."""
    from pxr import Usd

    from usdface.errors import AlreadyPersonalizedError
    from usdface.io.usd_rig import dcc_export_marks, refuse_usdface_output

    export = _dcc_export(person_layer, tmp_path / "blender.usda")
    stage = Usd.Stage.Open(str(export))
    assert not any(p.GetVariantSets().GetNames() for p in stage.Traverse())      # as Blender's export
    marks = dcc_export_marks(export)
    assert "/Avatar/usdfaceShapes_001" in marks and "/Avatar/Head/usdfaceShapes" in marks
    for argv in (["personalize", str(export), str(C), "-o", str(tmp_path / "p2.usda")],
                 ["retarget", str(export), str(C), "-o", str(tmp_path / "m.json")]):
        assert main(argv) == 2
        err = capfd.readouterr().err
        assert "DCC export" in err and "usdfaceShapes" in err and str(export) in err
        assert "export the original avatar" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blender.usda"]
    with pytest.raises(AlreadyPersonalizedError) as caught:
        refuse_usdface_output(str(export))
    assert caught.value.prim == marks[0]
    # a crate export is found the same way
    crate = _dcc_export(person_layer, tmp_path / "blender.usdc", blender_layout=False)
    assert dcc_export_marks(crate) == ["/Avatar/Head/usdfaceShapes"]


def test_plain_avatar_and_usdface_outputs_have_no_dcc_export_marks(person_layer, tmp_path):
    """The marks are only a DCC export's: the avatar has none, the layer itself is refused as a usdface layer
    (its scopes live in its variant), a flattened generic export drops the scopes and is accepted."""
    from usdface.io.flatten import flatten_variant
    from usdface.io.usd_rig import dcc_export_marks, refuse_usdface_output

    generic = flatten_variant(person_layer, tmp_path / "generic.usda", "generic")
    for path in (A, person_layer, generic):
        assert dcc_export_marks(path) == []
    refuse_usdface_output(A)
    refuse_usdface_output(generic)


def test_review_names_a_dcc_export_of_a_personalized_layer(person_layer, tmp_path, capsys):
    """Blender round trip (h5): 'usdface review' of Blender's re-export said 'an avatar that is not
    personalized ... (fix: personalize it first)', advice that stacked the personalization; it now says
    what the file is and points at the usdface layer."""
    export = _dcc_export(person_layer, tmp_path / "blender.usda")
    assert main(["review", str(export), "-o", str(tmp_path / "r.html")]) == 2
    err = capsys.readouterr().err
    assert "DCC export" in err and "usdfaceShapes" in err and "personalize it first" not in err
    assert "review the usdface layer it was exported from" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blender.usda"]


def test_export_names_a_dcc_export_of_a_personalized_layer(person_layer, tmp_path, capsys):
    """Blender round trip (h5): 'usdface export' of Blender's re-export labelled it 'a plain avatar, not
    personalized' (its shapes are the personalized ones), and '--variant generic' said 'not a usdface
    layer, pass a layer written by usdface personalize'. Both now say what it is."""
    export = _dcc_export(person_layer, tmp_path / "blender.usda")
    assert main(["export", str(export), "--gltf", str(tmp_path / "p.glb")]) == 0
    out = capsys.readouterr().out
    assert "DCC export of a usdface layer" in out and "not personalized" not in out
    assert main(["export", str(export), "--gltf", str(tmp_path / "g.glb"), "--variant", "generic"]) == 2
    err = capsys.readouterr().err
    assert "DCC export" in err and "the generic shapes are not in it" in err and "usdfaceShapes" in err
    assert not (tmp_path / "g.glb").exists()


def test_inspect_names_a_dcc_export_of_a_personalized_layer(person_layer, tmp_path, capsys):
    """Blender round trip (h5): 'usdface inspect' called Blender's re-export of a personalized layer a plain
    'avatar' with nothing more; it now says it is a DCC export whose shapes are the personalized ones, in
    the text and the JSON (dccExport); the plain avatar has no such entry."""
    export = _dcc_export(person_layer, tmp_path / "blender.usda")
    assert main(["inspect", str(export)]) == 0
    assert "DCC export of a usdface output layer" in capsys.readouterr().out
    assert main(["inspect", str(export), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert "/Avatar/Head/usdfaceShapes" in report["dccExport"]["usdfaceShapes"]
    assert main(["inspect", str(A), "--json"]) == 0
    assert "dccExport" not in json.loads(capsys.readouterr().out)


def test_flattened_personalized_export_is_marked_for_a_dcc_round_trip(person_layer, tmp_path, capsys):
    """Blender round trip (h5): a flattened export of the personalized variant has no usdfaceShapes scope,
    and a DCC drops its customLayerData record, so its DCC export was a plain avatar again. The flattened
    export now carries an empty Scope usdfacePersonalized under the SkelRoot (a DCC keeps it: Blender
    writes it back as an Xform); without the record (the DCC export) it is refused. The generic export has
    no mark and the flattened file itself is refused by its record, as before."""
    from pxr import Sdf

    from usdface.io.flatten import PERSONALIZED_MARK, flatten_variant
    from usdface.io.usd_rig import dcc_export_marks

    flat = flatten_variant(person_layer, tmp_path / "flat.usda", "personalized")
    generic = flatten_variant(person_layer, tmp_path / "generic.usda", "generic")
    layer = Sdf.Layer.FindOrOpen(str(flat))
    assert layer.GetPrimAtPath(f"/Avatar/{PERSONALIZED_MARK}").typeName == "Scope"
    assert Sdf.Layer.FindOrOpen(str(generic)).GetPrimAtPath(f"/Avatar/{PERSONALIZED_MARK}") is None
    assert dcc_export_marks(flat) == [] and dcc_export_marks(generic) == []
    again = flatten_variant(flat, tmp_path / "again.usda", "personalized")       # kept, not doubled
    assert list(Sdf.Layer.FindOrOpen(str(again)).GetPrimAtPath("/Avatar").nameChildren.keys()).count(
        PERSONALIZED_MARK) == 1
    dcc = tmp_path / "blender.usda"                     # what the DCC keeps: the prims, not the record
    exported = Sdf.Layer.CreateAnonymous(".usda")
    exported.TransferContent(layer)
    exported.customLayerData = {}
    exported.Export(str(dcc))
    assert dcc_export_marks(dcc) == [f"/Avatar/{PERSONALIZED_MARK}"]
    assert main(["personalize", str(dcc), str(C), "-o", str(tmp_path / "p2.usda")]) == 2
    err = capsys.readouterr().err
    assert "DCC export" in err and PERSONALIZED_MARK in err
    assert not (tmp_path / "p2.usda").exists()


def test_personalized_gltf_marks_its_nodes_for_a_dcc_round_trip(person_layer, tmp_path, capsys):
    """Blender round trip (h5): glTF -> Blender -> USD lost what the glTF said of its variant (scene extras,
    which Blender keeps only on its scene), so the export was a plain avatar again. The glTF's root and mesh
    nodes now carry extras {"usdfaceVariant": variant}; Blender makes them object custom properties and its
    USD exporter writes 'userProperties:usdfaceVariant' (seen with bpy 5.0.1), which is refused when it says
    personalized. The generic glTF says generic and is not refused."""
    import pygltflib
    from pxr import Sdf

    for variant in ("personalized", "generic"):
        glb = tmp_path / f"{variant}.glb"
        assert main(["export", str(person_layer), "--gltf", str(glb), "--variant", variant, "-q"]) == 0
        doc = pygltflib.GLTF2().load(str(glb))
        assert all((n.extras or {}).get("usdfaceVariant") == variant for n in doc.nodes
                   if n.mesh is not None or n.name == "Avatar")
    capsys.readouterr()
    from usdface.io.usd_rig import dcc_export_marks

    for value, refused in (("personalized", True), ("generic", False)):
        out = tmp_path / f"blender_{value}.usda"
        layer = Sdf.Layer.CreateNew(str(out))
        layer.TransferContent(Sdf.Layer.FindOrOpen(str(A)))
        attr = Sdf.AttributeSpec(layer.GetPrimAtPath("/Avatar"), "userProperties:usdfaceVariant",
                                 Sdf.ValueTypeNames.String)
        attr.custom, attr.default = True, value
        layer.Save()
        assert bool(dcc_export_marks(out)) is refused
        code = main(["personalize", str(out), str(C), "-o", str(tmp_path / f"p_{value}.usda"), "--dry-run"])
        err = capsys.readouterr().err
        assert code == (2 if refused else 0)
        if refused:
            assert "/Avatar.userProperties:usdfaceVariant" in err and "glTF" in err


def test_render_compare_names_a_dcc_export_of_a_personalized_layer(person_layer, tmp_path, capsys):
    """Blender round trip (h5): 'render --compare' of Blender's re-export said 'not a usdface layer (no
    sublayer to compare with)'; it now says it is a DCC export of one and to pass the original avatar, and
    with the avatar given it draws."""
    export = _dcc_export(person_layer, tmp_path / "blender.usda")
    assert main(["render", str(export), "-o", str(tmp_path / "c.png"), "--compare"]) == 2
    err = capsys.readouterr().err
    assert "DCC export" in err and "--compare AVATAR.usdc" in err and "usdfaceShapes" in err
    assert main(["render", str(export), "-o", str(tmp_path / "c.png"), "--compare", str(A), "-q",
                 "--shapes", "jawOpen"]) == 0


def _shot(folder: Path, layer: Path, how: str, variant: str | None = None) -> Path:
    """A shot layer in ``folder`` that sublayers or references ``layer`` (optionally selecting a variant
    of usdfacePersonalization), as a shot or a character asset brings the published layer in."""
    head = '#usda 1.0\n(\n    defaultPrim = "{}"\n    metersPerUnit = 0.01\n    upAxis = "Y"\n'
    select = (f'    variants = {{\n        string usdfacePersonalization = "{variant}"\n    }}\n'
              if variant else "")
    shot = folder / f"shot_{how}_{variant}_{layer.stem}.usda"
    if how == "subLayers":
        body = head.format("Avatar") + f"    subLayers = [@{layer}@]\n)\n"
        if variant:
            body += f'over "Avatar" (\n{select})\n{{\n}}\n'
    else:
        body = (head.format("World") + ')\ndef Xform "World"\n{\n'
                f'    def "Hero" (\n        prepend references = @{layer}@\n{select}    )\n'
                '    {\n    }\n}\n')
    shot.write_text(body)
    return shot


@pytest.mark.parametrize("how", ["subLayers", "references"])
def test_a_shot_over_a_personalized_layer_is_refused_as_the_avatar(person_layer, tmp_path, how):
    """A shot (or character asset) that sublayers or references the published personalized layer holds the
    personalized shapes where the avatar's were: personalize, retarget and batch took it as a plain avatar
    and stacked the personalization ('46 BlendShapes personalized', no warning). Now refused, naming the
    layer it composes and the original avatar; the same shot over the plain avatar, or selecting the generic
    variant, is still an avatar."""
    from usdface.errors import AlreadyPersonalizedError
    from usdface.io.usd_rig import refuse_usdface_output

    with pytest.raises(AlreadyPersonalizedError) as err:
        refuse_usdface_output(_shot(tmp_path, person_layer, how))
    text = str(err.value)
    assert str(person_layer) in text and "stack the personalization" in text, text
    assert str(A) in err.value.fix and err.value.prim in ("/Avatar", "/World/Hero"), err.value
    refuse_usdface_output(_shot(tmp_path, A, how))                            # the plain avatar: accepted
    refuse_usdface_output(_shot(tmp_path, person_layer, how, "generic"))     # its generic shapes: accepted


def test_personalize_refuses_a_shot_over_a_personalized_layer_at_the_command_line(person_layer, tmp_path,
                                                                                    capsys):
    shot = _shot(tmp_path, person_layer, "references")
    assert main(["personalize", str(shot), str(C), "-o", str(tmp_path / "again.usda")]) == 2
    err = capsys.readouterr().err
    assert "composes the usdface output layer" in err and "pass the original avatar" in err, err
    assert not (tmp_path / "again.usda").exists()
