"""Avatars usdface did not make: Pixar's and Blender's UsdSkel files (``../shared/data/usd-real-world``) as
avatars, point caches and test scenes, each refused or told for what it is (one line naming the file, the prim
and the fix), never a crash. Tests on ../shared skip cleanly without it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cli_helpers import _no_traceback as _refused
from cli_helpers import _usdface


@pytest.fixture(scope="module")
def real_world(shared) -> Path:
    return shared / "data" / "usd-real-world"


def test_capture_on_pixar_test_plane_is_refused_not_a_crash(real_world, bench, tmp_path):
    """Pixar's 10 cm blend-shape test plane, its six targets named as ARKit shapes with a name map, and
    dev1's capture: the person's registration shrank the capture to a point with residual exactly 0 and was
    accepted; the template's registration from it crashed in Open3D ("Invalid max_correspondence_distance",
    a traceback, exit 1). Now one line naming the collapse, exit 2, nothing written."""
    plane = (real_world / "openusd-usdskel/pxr/usdImaging/usdImagingGL/testenv"
             / "testUsdImagingGLSkelBlendShapes/blendshapes.usda")
    names = tmp_path / "map.json"
    names.write_text(json.dumps({"targetA": "jawOpen", "targetB": "eyeBlinkLeft", "targetC": "eyeBlinkRight",
                                 "targetD": "mouthSmileLeft", "targetE": "mouthSmileRight",
                                 "targetF": "browInnerUp"}))
    res = _usdface("personalize", plane, bench / "dev1" / "capture", "-o", tmp_path / "p.usda",
                   "--name-map", names, cwd=tmp_path)
    _refused(res)
    assert "shrank the capture to a point" in res.stderr and "Open3D" not in res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.json"]

_CACHE = """#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 0.01
    defaultPrim = "Root"
)
def Xform "Root"
{
    def Mesh "Mesh"
    {
        int[] faceVertexCounts = [3]
        int[] faceVertexIndices = [0, 1, 2]
        point3f[] points.timeSamples = {
            1: [(0, 0, 0), (1, 0, 0), (0, 1, 0)],
            2: [(0, 0, 0), (1, 0, 0), (0, 1.5, 0)],
        }
    }
}
"""


def test_check_of_a_point_cache_does_not_call_it_a_take(tmp_path, capsys):
    """Pixar's lbs.baked.usda (baked skinning: time-sampled points, no blend shapes, no weights): ``check``
    said "this is a take ... (fix: usdface inspect FILE summarises the take)", and ``inspect`` then refused
    it as a take without weights. Both now say it is a mesh cache, neither avatar nor take."""
    from usdface.cli import main

    cache = tmp_path / "cache.usda"
    cache.write_text(_CACHE)
    assert main(["check", str(cache), "--no-pixar"]) == 0
    out = capsys.readouterr().out
    assert "mesh cache" in out and "this is a take" not in out and "usdface inspect" not in out, out
    assert main(["inspect", str(cache)]) == 2
    err = capsys.readouterr().err
    assert "mesh cache" in err and "pass the file whose meshes carry the blend shapes" in err, err


def test_check_of_pixar_baked_skinning(real_world, capsys):
    from usdface.cli import main

    baked = (real_world / "openusd-usdskel/pxr/usd/usdSkel/testenv/testUsdSkelBakeSkinning/baseline"
             / "lbs.baked.usda")
    main(["check", str(baked), "--no-pixar"])
    out = capsys.readouterr().out
    assert "mesh cache" in out and "this is a take" not in out, out


def test_no_face_shapes_names_the_prim_the_channels_and_the_unmatched_map(real_world, samples, tmp_path):
    """Blender's cube with one shape key 'Key_1' and a name map for 'Key_2': personalize said only "the
    avatar has no face-like blend shapes ... (fix: the avatar needs ARKit-named BlendShapes)": no prim, no
    channel, nothing about the name map that matched nothing."""
    names = tmp_path / "map.json"
    names.write_text(json.dumps({"Key_2": "jawOpen"}))
    res = _usdface("personalize", real_world / "blender" / "blendshape.usda", samples / "capture.usda",
                   "-o", tmp_path / "p.usda", "--name-map", names, cwd=tmp_path)
    _refused(res)
    assert "prim /root/Cube/Cube" in res.stderr and "Key_1" in res.stderr, res.stderr
    assert "name map entries that match no channel: Key_2" in res.stderr and "--name-map" in res.stderr
    assert not (tmp_path / "p.usda").exists()

def test_arkit_named_shapes_that_move_nothing_are_told_so(real_world, samples, tmp_path):
    """Pixar's normalOffsets-only shapes named as ARKit shapes with a name map: personalize and check said
    "no face-like blend shapes (no ARKit-named shape that moves) (fix: name the face shapes as ARKit does
    ...)" of shapes the map had just named jawOpen, eyeBlinkLeft...: the fix was no fix."""
    from usdface.io.name_map import read_name_map
    from usdface.pipeline.validators import validate_file

    names = tmp_path / "map.json"
    names.write_text(json.dumps({"twirl_a": "jawOpen", "twirl_b": "eyeBlinkLeft", "twirl_c": "eyeBlinkRight",
                                 "twirl_d": "mouthSmileLeft"}))
    plane = (real_world / "openusd-usdskel/pxr/usd/usdSkel/testenv/testUsdSkelBakeSkinning"
             / "blendshapesWithNormals.usda")
    res = _usdface("personalize", plane, samples / "capture.usda", "-o", tmp_path / "p.usda",
                   "--name-map", names, cwd=tmp_path)
    _refused(res)
    assert "ARKit-named blend shapes move no point" in res.stderr and "name the face shapes" not in res.stderr
    issues = validate_file(plane, pixar=False, name_map=read_name_map(names))
    readable = [i for i in issues if i.rule == "Readable"]
    assert [i.prim for i in readable] == ["/TestPlane/Mesh"], readable
    assert "move no point" in readable[0].message and "point offsets" in readable[0].fix


def test_no_snapping_note_for_double_rounding(real_world):
    """``inspect`` of Pixar's usdImagingGL blend-shape plane noted "world transforms of /TestPlane/Mesh
    snapped ... (float32 export noise, largest change 1.2e-16 relative)": a double's cos(90 degrees), not an
    export's noise. Told only at float32 size (dev1's Blender round trip: 1.3e-7)."""
    from usdface.io.usd_rig import read_avatar

    plane = (real_world / "openusd-usdskel/pxr/usdImaging/usdImagingGL/testenv"
             / "testUsdImagingGLSkelBlendShapes/blendshapes.usda")
    assert not any("snapped" in note for note in read_avatar(plane).metadata["notes"])
