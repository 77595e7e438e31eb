"""``usdface export``: glTF 2.0 (structure, exact float32 round trip, skin), OBJ per shape, flattened USD."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import _usdface

import usdface.io  # noqa: F401  (registers the schemas before a test opens a stage)
from usdface import api
from usdface.cli import main
from usdface.errors import InputFileError, OutputExistsError, UsdFaceError
from usdface.io.flatten import read_avatar_variant
from usdface.io.gltf import read_gltf
from usdface.io.layers import file_digest
from usdface.io.mesh_io import read_obj

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


@pytest.fixture()
def layer(personalized_sample) -> Path:
    return personalized_sample


def _rigs(avatar):
    """{mesh name: (neutral, triangles, names, deltas)} for every mesh, static meshes included."""
    out = {m.name: (m.neutral, m.triangles, m.names, m.deltas) for m in avatar.meshes}
    for prim, (points, tris) in avatar.metadata["static_meshes"].items():
        out[prim.rsplit("/", 1)[-1]] = (points, tris, [], np.zeros((0, len(points), 3)))
    return out


def _validate_gltf(path: Path) -> dict:
    """A structural check of what usdface writes, after the glTF 2.0 spec: every accessor fits its buffer
    view, views fit the buffer, POSITION accessors (targets too) carry exact min/max, index values are in
    range, sparse indices strictly increase, every primitive's targets match its mesh's targetNames and
    weights."""
    import pygltflib

    gltf = pygltflib.GLTF2().load(str(path))
    doc = json.loads(gltf.to_json())
    blob = gltf.binary_blob()
    assert doc["asset"]["version"] == "2.0"
    assert len(blob) >= doc["buffers"][0]["byteLength"]
    sizes = {5126: 4, 5125: 4, 5123: 2, 5121: 1}
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}
    for bv in doc["bufferViews"]:
        assert bv.get("byteOffset", 0) % 4 == 0
        assert bv.get("byteOffset", 0) + bv["byteLength"] <= doc["buffers"][0]["byteLength"]
    for acc in doc["accessors"]:
        need = acc["count"] * width[acc["type"]] * sizes[acc["componentType"]]
        if "bufferView" in acc:
            assert doc["bufferViews"][acc["bufferView"]]["byteLength"] >= need + acc.get("byteOffset", 0)
        if "sparse" in acc:
            sp = acc["sparse"]
            assert 1 <= sp["count"] <= acc["count"]
            idx = _read(gltf, blob, sp["indices"]["bufferView"], sp["indices"]["componentType"], sp["count"])
            assert np.all(np.diff(idx.astype(np.int64)) > 0) and idx.max() < acc["count"]
    data = read_gltf(path)
    for mesh in doc["meshes"]:
        prim = mesh["primitives"][0]
        assert prim["mode"] == 4
        pos = doc["accessors"][prim["attributes"]["POSITION"]]
        n = pos["count"]
        arrays = data[mesh["name"]]
        assert pos["type"] == "VEC3" and pos["componentType"] == 5126
        np.testing.assert_array_equal(pos["min"], arrays["positions"].min(axis=0))
        np.testing.assert_array_equal(pos["max"], arrays["positions"].max(axis=0))
        assert doc["accessors"][prim["attributes"]["NORMAL"]]["count"] == n
        assert doc["accessors"][prim["indices"]]["count"] % 3 == 0
        assert arrays["indices"].max() < n
        names = mesh.get("extras", {}).get("targetNames", [])
        targets = prim.get("targets", [])
        assert len(targets) == len(names) == len(mesh.get("weights", []))
        for k, t in enumerate(targets):
            acc = doc["accessors"][t["POSITION"]]
            assert acc["count"] == n and acc["type"] == "VEC3"
            assert set(t) in ({"POSITION", "NORMAL"}, {"POSITION"}) and set(t) == set(targets[0])
            assert "NORMAL" not in t or doc["accessors"][t["NORMAL"]]["count"] == n
            np.testing.assert_array_equal(acc["min"], arrays["targets"][k].min(axis=0))
            np.testing.assert_array_equal(acc["max"], arrays["targets"][k].max(axis=0))
    return doc


def _read(gltf, blob, view, comp, count):
    bv = gltf.bufferViews[view]
    dtype = {5125: np.uint32, 5123: np.uint16}[comp]
    return np.frombuffer(blob, dtype=dtype, count=count, offset=bv.byteOffset or 0)


@pytest.mark.parametrize("variant", ["personalized", "generic"])
def test_gltf_round_trip_is_exact_float32(layer, tmp_path, variant):
    out = api.export_avatar(layer, gltf=tmp_path / "a.glb", variant=variant)["gltf"]
    doc = _validate_gltf(out)
    data = read_gltf(out)
    expect = _rigs(read_avatar_variant(layer, variant))
    assert set(data) == set(expect)
    for name, (neutral, tris, names, deltas) in expect.items():
        got = data[name]
        np.testing.assert_array_equal(got["positions"], neutral.astype(np.float32))
        np.testing.assert_array_equal(got["indices"], tris)
        assert got["target_names"] == list(names)
        np.testing.assert_array_equal(got["targets"], deltas.astype(np.float32))
    assert doc["scenes"][0]["extras"]["usdface"]["variant"] == variant
    # the sample's deltas are sparse: the writer stores most targets sparse
    head = next(m for m in doc["meshes"] if m["name"] == "Head")
    sparse = sum("sparse" in doc["accessors"][t["POSITION"]] for t in head["primitives"][0]["targets"])
    assert sparse > len(head["primitives"][0]["targets"]) // 2


def test_gltf_variants_differ_and_generic_is_the_input_avatar(layer, samples, tmp_path):
    gen = read_gltf(api.export_avatar(layer, gltf=tmp_path / "g.glb", variant="generic")["gltf"])
    per = read_gltf(api.export_avatar(layer, gltf=tmp_path / "p.gltf")["gltf"])  # JSON + data URI
    source = api.read_avatar(samples / "avatar.usda").mesh("Head")
    np.testing.assert_array_equal(gen["Head"]["targets"], source.subset(gen["Head"]["target_names"]).deltas
                                  .astype(np.float32))
    change = np.abs(per["Head"]["targets"] - gen["Head"]["targets"]).max()
    assert change > 1e-4  # personalization moved the face by more than 0.1 mm somewhere


def test_gltf_targets_carry_the_posed_normals(layer, tmp_path):
    """A user trial (stop 44): the morph targets carried POSITION only, so an engine (three.js, Babylon.js,
    Unity glTFast: each adds NORMAL target deltas when there are any, else keeps the base NORMAL) shaded every
    shape with the neutral's normals: a blink's closed lid, the open jaw's chin and lips lit as at rest
    (dev3's personalized jawOpen turns 2,535 Head normals by more than 10 degrees, up to 129). Each target now
    has NORMAL deltas: neutral normals + delta, normalised, are the posed mesh's own vertex normals."""
    from usdface.mesh import vertex_normals

    data = read_gltf(api.export_avatar(layer, gltf=tmp_path / "n.glb")["gltf"])
    head = read_avatar_variant(layer, "personalized").mesh("Head")
    got = data["Head"]
    assert got["target_normals"].shape == got["targets"].shape
    turned = 0
    for k, name in enumerate(got["target_names"]):
        posed = vertex_normals(head.neutral + head.deltas[head.index(name)], head.triangles)
        blended = got["normals"] + got["target_normals"][k]
        blended /= np.linalg.norm(blended, axis=1, keepdims=True)
        np.testing.assert_allclose(blended, posed, atol=1e-5)
        rest = np.degrees(np.arccos(np.clip((got["normals"] * posed).sum(axis=1), -1, 1)))
        turned = max(turned, rest.max())
        moving = np.any(head.deltas[head.index(name)][head.triangles] != 0, axis=(1, 2))
        still = np.setdiff1d(np.arange(len(posed)), head.triangles[moving])
        assert not got["target_normals"][k][still].any()   # zero where no adjacent triangle moves
    assert turned > 20                                     # the shapes do turn normals a lot (29.8 degrees)


def test_gltf_without_morph_normals_keeps_the_positions_and_halves_the_targets(layer, tmp_path):
    """A TD's option (stop 45): the NORMAL deltas (stop 44) doubled dev1's .glb (8.9 -> 19.7 MB), which an
    engine that recomputes a posed mesh's normals does not need. ``morph_normals=False`` /
    ``--no-morph-normals`` writes POSITION targets only: the same positions, base normals and names; no
    target has a NORMAL; the file is smaller by about the NORMAL deltas' bytes. Refused without a glTF."""
    full = api.export_avatar(layer, gltf=tmp_path / "n.glb")["gltf"]
    lean = tmp_path / "p.glb"
    assert main(["export", str(layer), "--gltf", str(lean), "--no-morph-normals", "-q"]) == 0
    doc = _validate_gltf(lean)
    a, b = read_gltf(full), read_gltf(lean)
    for name in a:
        for key in ("positions", "indices", "normals", "targets"):
            np.testing.assert_array_equal(b[name][key], a[name][key])
        assert b[name]["target_names"] == a[name]["target_names"]
        assert "target_normals" not in b[name]
        assert ("target_normals" in a[name]) == bool(a[name]["target_names"])
    assert not any("NORMAL" in t for m in doc["meshes"] for prim in m["primitives"]
                   for t in prim.get("targets", []))
    assert lean.stat().st_size < 0.75 * full.stat().st_size
    assert main(["export", str(layer), "--obj-dir", str(tmp_path / "objs"), "--no-morph-normals"]) == 2
    assert not (tmp_path / "objs").exists()


def test_gltf_normals_are_unit_at_a_loose_vertex(samples, tmp_path):
    """A user trial (stop 44): a vertex no triangle uses (a loose vertex a DCC keeps after faces were
    deleted) got a zero NORMAL: invalid glTF (the Khronos validator's ACCESSOR_NON_UNIT error), and an engine
    normalising it shades NaN. It now gets a unit normal, in every pose."""
    from usdface.io.avatar_writer import write_rig_usd
    from usdface.model import FaceRig

    rigs = []
    for m in api.read_avatar(samples / "avatar.usda").meshes:
        if m.name == "Head":   # one more vertex, in no triangle, moved by no shape
            m = FaceRig(np.vstack([m.neutral, m.neutral[:1] + 0.001]), m.triangles, m.names,
                        np.concatenate([m.deltas, np.zeros((m.n_shapes, 1, 3))], axis=1), name=m.name)
        rigs.append(m)
    loose = write_rig_usd(rigs, tmp_path / "loose.usda")
    head = read_gltf(api.export_avatar(loose, gltf=tmp_path / "loose.glb")["gltf"])["Head"]
    np.testing.assert_allclose(np.linalg.norm(head["normals"], axis=1), 1.0, atol=1e-6)
    posed = head["normals"][None] + head["target_normals"]
    np.testing.assert_allclose(np.linalg.norm(posed, axis=2), 1.0, atol=1e-6)
    assert not head["target_normals"][:, -1].any()


def _left_handed_copy(source: Path, out: Path) -> Path:
    """``source`` with every mesh's faces reversed and ``orientation = "leftHanded"``: the same surface, its
    outside the same, as USD defines it."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(source))
    stage.GetRootLayer().Export(str(out))
    stage = Usd.Stage.Open(str(out))
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Mesh):
            mesh = UsdGeom.Mesh(prim)
            counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get())
            idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get())
            faces = np.split(idx, np.cumsum(counts)[:-1])
            mesh.GetFaceVertexIndicesAttr().Set(np.concatenate([f[::-1] for f in faces]).tolist())
            mesh.GetOrientationAttr().Set(UsdGeom.Tokens.leftHanded)
    stage.GetRootLayer().Save()
    return out


def test_a_left_handed_avatar_is_read_and_exported_outside_out(samples, tmp_path):
    """A user trial (stop 44): ``orientation = "leftHanded"`` (faces wound clockwise, as some exporters
    write them) was ignored: the avatar was read with its triangles inside out, so its vertex normals (the
    glTF's NORMAL, what personalize's correspondence and eyelid repair use) pointed inwards and an engine
    culled the glTF's front faces. The reader now winds every mesh counter-clockwise seen from outside."""
    from usdface.mesh import vertex_normals

    right = api.read_avatar(samples / "avatar.usda")
    left = api.read_avatar(_left_handed_copy(samples / "avatar.usda", tmp_path / "left.usda"))
    for mesh in ("Head", "Mouth"):
        np.testing.assert_allclose(vertex_normals(left.mesh(mesh).neutral, left.mesh(mesh).triangles),
                                   vertex_normals(right.mesh(mesh).neutral, right.mesh(mesh).triangles),
                                   atol=1e-9)
    eyes = left.metadata["static_meshes"]
    for key, (points, tris) in right.metadata["static_meshes"].items():
        np.testing.assert_allclose(vertex_normals(*eyes[key]), vertex_normals(points, tris), atol=1e-9)
    glb = read_gltf(api.export_avatar(tmp_path / "left.usda", gltf=tmp_path / "left.glb")["gltf"])
    plain = read_gltf(api.export_avatar(samples / "avatar.usda", gltf=tmp_path / "right.glb")["gltf"])
    np.testing.assert_allclose(glb["Head"]["normals"], plain["Head"]["normals"], atol=1e-6)


def test_a_left_handed_avatar_personalizes_as_the_right_handed_one(samples, tmp_path):
    """The same trial: personalize refused the left-handed copy of the sample ('no vertex of the face mesh
    ... lies on the registered capture surface'): its inward normals defeated the correspondence. Wound
    outward, it gives the right-handed sample's offsets."""
    left = _left_handed_copy(samples / "avatar.usda", tmp_path / "left.usda")
    api.personalize_avatar(left, samples / "capture.usda", tmp_path / "l.usda")
    api.personalize_avatar(samples / "avatar.usda", samples / "capture.usda", tmp_path / "r.usda")
    got, want = (read_avatar_variant(tmp_path / f"{s}.usda", "personalized") for s in "lr")
    for mesh in ("Head", "Mouth"):
        np.testing.assert_allclose(got.mesh(mesh).deltas, want.mesh(mesh).deltas, atol=1e-9)


def _textured_sample(samples, out: Path) -> Path:
    """The sample avatar with texture coordinates: per face corner on Head (``faceVarying``, a seam down the
    middle of the face: the corners of the faces left of x = 0 have u + 1), per point on Mouth
    (``vertex``)."""
    from pxr import Sdf, Usd, UsdGeom

    stage = Usd.Stage.Open(str(samples / "avatar.usda"))
    stage.GetRootLayer().Export(str(out))
    stage = Usd.Stage.Open(str(out))
    for name, interpolation in (("Head", UsdGeom.Tokens.faceVarying), ("Mouth", UsdGeom.Tokens.vertex)):
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(f"/Avatar/{name}"))
        points = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64)
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get())
        idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get())
        st = points[:, :2] * 0.01 + 0.5
        if interpolation == UsdGeom.Tokens.faceVarying:
            face = np.repeat(np.arange(len(counts)), counts)
            centre_x = np.bincount(face, points[idx, 0]) / counts
            st = st[idx] + np.column_stack([centre_x[face] < 0, np.zeros(len(idx))])
        UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                interpolation).Set(st.astype(np.float32).tolist())
    stage.GetRootLayer().Save()
    return out


def test_gltf_carries_the_texture_coordinates(samples, tmp_path):
    """A user trial (stop 44): the glTF had no TEXCOORD_0, so a textured avatar arrived in an engine without
    texture coordinates and could not be textured there. The mesh's ``st`` primvar is now written, the
    points split where their corners' coordinates differ (a UV seam), each copy with its point's position,
    offsets and normal."""
    from pxr import Usd, UsdGeom

    from usdface.io.mesh_io import fan_triangulate

    textured = _textured_sample(samples, tmp_path / "textured.usda")
    data = read_gltf(api.export_avatar(textured, gltf=tmp_path / "t.glb")["gltf"])
    avatar = api.read_avatar(textured)
    stage = Usd.Stage.Open(str(textured))
    for name in ("Head", "Mouth"):
        rig, got = avatar.mesh(name), data[name]
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(f"/Avatar/{name}"))
        st = np.asarray(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st").Get())
        counts, idx = mesh.GetFaceVertexCountsAttr().Get(), mesh.GetFaceVertexIndicesAttr().Get()
        per_corner = len(st) == len(idx)
        corner = st[fan_triangulate(counts, np.arange(len(idx)))] if per_corner else st[rig.triangles]
        tris = got["indices"]
        assert len(tris) == len(rig.triangles)
        np.testing.assert_array_equal(got["positions"][tris], rig.neutral.astype(np.float32)[rig.triangles])
        np.testing.assert_array_equal(got["texcoords"][tris][..., 0], corner[..., 0])
        np.testing.assert_allclose(got["texcoords"][tris][..., 1], 1.0 - corner[..., 1], atol=1e-6)
        deltas = rig.deltas.astype(np.float32)
        np.testing.assert_array_equal(got["targets"][:, tris], deltas[:, rig.triangles])
        pairs = len(np.unique(np.column_stack([rig.triangles.ravel(), corner.reshape(-1, 2)]), axis=0))
        assert len(got["positions"]) == pairs
    assert len(data["Head"]["positions"]) > avatar.mesh("Head").n_vertices            # the seam split points
    assert len(data["Mouth"]["positions"]) == avatar.mesh("Mouth").n_vertices          # per point: none
    assert "texcoords" not in data["EyeLeft"]


def test_gltf_skinned_meshes_are_scene_roots(layer, tmp_path):
    """A user trial (stop 44): the skinned mesh nodes were children of the root node, which the Khronos
    glTF-Validator warns of once per mesh (NODE_SKINNED_MESH_NON_ROOT: a skinned mesh is placed by its joints
    alone, its parents' transforms do not apply). They are now root nodes of the scene, without transforms of
    their own; the joints and any unskinned mesh stay under the root node."""
    import pygltflib

    gltf = pygltflib.GLTF2().load(str(api.export_avatar(layer, gltf=tmp_path / "r.glb")["gltf"]))
    parent = {c for n in gltf.nodes for c in (n.children or [])}
    skinned = [i for i, n in enumerate(gltf.nodes) if n.skin is not None]
    assert sorted(gltf.nodes[i].name for i in skinned) == ["EyeLeft", "EyeRight", "Head", "Mouth"]
    for i in skinned:
        node = gltf.nodes[i]
        assert i not in parent and i in gltf.scenes[0].nodes
        assert (node.matrix, node.translation, node.rotation, node.scale) == (None, None, None, None)
        assert node.extras["usdfaceVariant"] == "personalized"
    root = gltf.nodes[gltf.scenes[0].nodes[0]]
    assert root.name == "Avatar" and [gltf.nodes[c].name for c in root.children] == ["root"]
    no_skin = api.export_avatar(layer, gltf=tmp_path / "u.glb", skin=False)["gltf"]
    unskinned = pygltflib.GLTF2().load(str(no_skin))
    assert unskinned.scenes[0].nodes == [0] and len(unskinned.nodes[0].children) == 4


def test_gltf_skin_matches_the_skeleton(layer, tmp_path):
    import pygltflib

    out = api.export_avatar(layer, gltf=tmp_path / "s.glb")["gltf"]
    gltf = pygltflib.GLTF2().load(str(out))
    assert len(gltf.skins) == 1
    skin = gltf.skins[0]
    assert [gltf.nodes[j].name for j in skin.joints] == ["root"]
    data = read_gltf(out)
    for name in ("Head", "Mouth", "EyeLeft", "EyeRight"):  # every sample mesh is bound to the root joint
        np.testing.assert_allclose(data[name]["weights"].sum(axis=1), 1.0, atol=1e-6)
        assert set(np.unique(data[name]["joints"])) == {0}
    # rest pose == bind pose: joint world matrix @ inverse bind = identity
    ibm = np.frombuffer(gltf.binary_blob(), dtype=np.float32, count=16,
                        offset=gltf.bufferViews[gltf.accessors[skin.inverseBindMatrices].bufferView].byteOffset)
    world = np.asarray(gltf.nodes[skin.joints[0]].matrix).reshape(4, 4).T
    np.testing.assert_allclose(world @ ibm.reshape(4, 4).T, np.eye(4), atol=1e-6)
    no_skin = api.export_avatar(layer, gltf=tmp_path / "n.glb", skin=False)["gltf"]
    assert not pygltflib.GLTF2().load(str(no_skin)).skins


def _rest_skinning(path: Path) -> list:
    """Per joint, the glTF joint's world matrix @ its inverse bind matrix (identity when the rest pose leaves
    the vertices where POSITION puts them, as it must for a rest pose equal to the bind pose)."""
    import pygltflib

    gltf = pygltflib.GLTF2().load(str(path))
    skin = gltf.skins[0]
    view = gltf.bufferViews[gltf.accessors[skin.inverseBindMatrices].bufferView]
    ibm = np.frombuffer(gltf.binary_blob(), dtype=np.float32, count=16 * len(skin.joints),
                        offset=view.byteOffset).reshape(-1, 4, 4).transpose(0, 2, 1)
    parent = {c: i for i, n in enumerate(gltf.nodes) for c in (n.children or [])}

    def world(i):
        m = np.asarray(gltf.nodes[i].matrix or np.eye(4).ravel()).reshape(4, 4).T
        while i in parent:
            i = parent[i]
            m = np.asarray(gltf.nodes[i].matrix or np.eye(4).ravel()).reshape(4, 4).T @ m
        return m

    return [world(j) @ ibm[k] for k, j in enumerate(skin.joints)]


def test_gltf_skin_of_a_skeleton_under_a_scaled_turned_prim_rests_in_place(samples, tmp_path):
    """A user trial: the glTF of the bench's Blender round trip (``avatar_blender.usdc``: Z up, metres, the
    SkelRoot and its Skeleton under a prim scaled 0.01 and turned 90 degrees) put the joints' world
    transforms (which include the Skeleton prim's transform) over inverse bind matrices that did not: every
    glTF viewer drew the skinned avatar a hundredth of its size and turned (joint @ inverse bind was the
    prim's 0.01 and rotation, not the identity). The bind transforms now get the Skeleton's transform too."""
    from usdface.io.avatar_writer import write_rig_usd

    avatar = api.read_avatar(samples / "avatar.usda")
    turned = write_rig_usd(avatar.meshes, tmp_path / "turned.usda", up_axis="Z", meters_per_unit=1.0,
                           parents=("root",), parent_scale=0.01, parent_rotate_x_deg=90.0)
    out = api.export_avatar(turned, gltf=tmp_path / "t.glb")["gltf"]
    for product in _rest_skinning(out):
        np.testing.assert_allclose(product, np.eye(4), atol=1e-6)
    data, plain = read_gltf(out), read_gltf(api.export_avatar(samples / "avatar.usda",
                                                              gltf=tmp_path / "p.glb")["gltf"])
    np.testing.assert_allclose(data["Head"]["positions"], plain["Head"]["positions"], atol=1e-6)


def test_obj_dir_holds_one_full_target_per_shape(layer, tmp_path):
    out = api.export_avatar(layer, obj_dir=tmp_path / "objs")["obj_dir"]
    avatar = read_avatar_variant(layer, "personalized")
    head = avatar.mesh("Head")
    neutral, tris = read_obj(out / "Head" / "neutral.obj")
    np.testing.assert_array_equal(neutral, head.neutral)
    np.testing.assert_array_equal(tris, head.triangles)
    assert sorted(p.stem for p in (out / "Head").glob("*.obj")) == sorted(["neutral", *head.names])
    k = head.index("jawOpen")
    target, _ = read_obj(out / "Head" / "jawOpen.obj")
    np.testing.assert_allclose(target - neutral, head.deltas[k], rtol=0, atol=1e-12)
    assert (out / "EyeLeft" / "neutral.obj").is_file()


def test_obj_dir_names_the_objs_as_it_writes_them(layer, tmp_path, monkeypatch, capsys):
    """``--obj-dir`` writes one full mesh per shape (105 OBJs, 1.26 GB for the 225k-vertex bench head, a
    minute): a log names the OBJs as they are written (one line at most every ``USDFACE_PROGRESS_DELAY``
    seconds; here 0, so every one), not only the step "write 105 OBJs" at its start and end."""
    monkeypatch.setenv("USDFACE_PROGRESS", "plain")
    monkeypatch.setenv("USDFACE_PROGRESS_DELAY", "0")
    out = api.export_avatar(layer, obj_dir=tmp_path / "objs")["obj_dir"]
    lines = [ln for ln in capsys.readouterr().err.splitlines() if " > OBJ [" in ln]
    written = sorted(p.relative_to(out).as_posix() for p in out.rglob("*.obj"))
    assert len(lines) == len(written) and lines[-1].startswith(f"usdface: export > OBJ [{len(written)}/")
    assert sorted(ln.split("] ", 1)[1].rsplit(" done", 1)[0] for ln in lines) == written


def test_flatten_to_another_format_names_the_flattened_file(layer, tmp_path):
    """``--flatten f.abc`` is refused before any work naming what it is (it said 'output layer', as for a
    personalize layer), with a USD extension to use instead."""
    from usdface.errors import InputFileError

    with pytest.raises(InputFileError, match="flattened USD file must end in .usda or .usdc or .usd or "
                                             ".usdz") as err:
        api.export_avatar(layer, flatten=tmp_path / "f.abc")
    assert err.value.fix == "name it e.g. f.usda" and not (tmp_path / "f.abc").exists()


def _composed_values(path) -> dict:
    """{attribute path: value as authored on the composed stage (arrays as numpy)} of every prim of the
    stage ``path`` opens, and its root layer's customLayerData."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(path))
    out = {"customLayerData": dict(stage.GetRootLayer().customLayerData)}
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        out[str(prim.GetPath())] = str(prim.GetTypeName())
        for attr in prim.GetAuthoredAttributes():
            value = attr.Get()
            out[str(attr.GetPath())] = np.asarray(value) if hasattr(value, "__len__") and not isinstance(
                value, str) else value
    return out


def test_flatten_packages_a_usdz_that_composes_exactly_as_the_usdc(layer, tmp_path, monkeypatch):
    """A ``.usdz`` flattened export (it was refused: 'must end in .usda', a USD name to use instead) is
    packaged by USD itself (``UsdUtils.CreateNewUsdzPackage``: one ``<stem>.usdc`` inside), atomically and
    refused over an existing file without --force, as the other outputs. Opened with ``Usd.Stage.Open`` it
    composes exactly what the ``.usdc`` export composes: every prim, every attribute (the personalized
    offsets, pointIndices, points), the record of what it is; check passes it and personalize refuses it as
    a personalized avatar, as the ``.usdc``."""
    import zipfile

    from pxr import Usd, UsdSkel

    monkeypatch.chdir(tmp_path)
    assert main(["export", str(layer), "--flatten", "f.usdc", "-q"]) == 0
    assert main(["export", str(layer), "--flatten", "f.usdz", "-q"]) == 0
    assert zipfile.ZipFile(tmp_path / "f.usdz").namelist() == ["f.usdc"]
    flat, packed = _composed_values(tmp_path / "f.usdc"), _composed_values(tmp_path / "f.usdz")
    assert flat.keys() == packed.keys()
    for key, value in flat.items():
        same = np.array_equal(value, packed[key]) if isinstance(value, np.ndarray) else value == packed[key]
        assert same, key
    stage = Usd.Stage.Open(str(tmp_path / "f.usdz"))
    shapes = [UsdSkel.BlendShape(p) for p in stage.Traverse() if p.IsA(UsdSkel.BlendShape)]
    assert len(shapes) > 50 and all(np.asarray(s.GetOffsetsAttr().Get()).size for s in shapes)
    got = api.read_avatar(tmp_path / "f.usdz").mesh("Head")
    expect = read_avatar_variant(layer, "personalized").mesh("Head")
    assert got.names == expect.names
    np.testing.assert_array_equal(got.deltas, expect.deltas)        # the person's shapes, exactly
    before = (tmp_path / "f.usdz").read_bytes()
    assert main(["export", str(layer), "--flatten", "f.usdz", "-q"]) == 2          # exists: --force
    assert (tmp_path / "f.usdz").read_bytes() == before
    assert main(["export", str(layer), "--flatten", "f.usdz", "-q", "--force"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.usdc", "f.usdz"]      # no temporary left
    assert main(["check", "f.usdz"]) == 0
    assert main(["personalize", "f.usdz", str(C), "-o", "q.usda", "-q"]) == 2
    assert not (tmp_path / "q.usda").exists()


_TEXTURED = """#usda 1.0
(
    defaultPrim = "Avatar"
    metersPerUnit = 0.01
    upAxis = "Y"
    subLayers = [@./avatar.usda@]
)
over "Avatar"
{
    def Material "Skin"
    {
        def Shader "Tex"
        {
            uniform token info:id = "UsdUVTexture"
            asset inputs:file = @./tex/skin.png@
        }
    }
}
"""


def test_flatten_keeps_texture_paths_relative(samples, tmp_path):
    """A user trial (stop 44): ``Stage.Flatten`` anchors every asset path, so a flattened export named its
    textures by absolute path (``@/proj/lib/tex/skin.png@``): a delivery copied or mounted elsewhere with its
    textures lost them (or read the old copy). They are now relative to the flattened file by the rule of the
    layer's sublayer path, and a ``.usdz`` still packages them."""
    from pxr import Usd

    lib, deliver = tmp_path / "proj" / "lib", tmp_path / "proj" / "deliver"
    (lib / "tex").mkdir(parents=True)
    (lib / "tex" / "skin.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    shutil.copy(samples / "avatar.usda", lib / "avatar.usda")
    (lib / "hero.usda").write_text(_TEXTURED)
    done = api.export_avatar(lib / "hero.usda", flatten=deliver / "flat.usdc")["flatten"]
    stage = Usd.Stage.Open(str(done))
    assert stage.GetAttributeAtPath("/Avatar/Skin/Tex.inputs:file").Get().path == "../lib/tex/skin.png"
    moved = tmp_path / "elsewhere"
    shutil.copytree(tmp_path / "proj", moved)
    stage = Usd.Stage.Open(str(moved / "deliver" / "flat.usdc"))
    resolved = stage.GetAttributeAtPath("/Avatar/Skin/Tex.inputs:file").Get().resolvedPath
    assert Path(resolved) == moved / "lib" / "tex" / "skin.png"
    package = api.export_avatar(lib / "hero.usda", flatten=deliver / "flat.usdz")["flatten"]
    import zipfile

    assert any(n.endswith("skin.png") for n in zipfile.ZipFile(package).namelist())


@pytest.mark.parametrize("command", ["personalize", "landmarks"])
def test_a_usdz_layer_over_the_avatar_is_refused_with_why_and_the_export_that_packages_it(
        command, tmp_path, capfd, monkeypatch):
    """``personalize -o p.usdz`` was told only to use a USD name. A layer over the avatar stays refused as a
    .usdz (it sublayers the avatar by its path; a package holds its files inside it), now saying why, and
    the fix names the layer to write and the export that packages the result."""
    import shlex

    monkeypatch.chdir(tmp_path)
    argv = [command, str(A), *([str(C)] if command == "personalize" else []), "-o", "my p.usdz", "-q"]
    assert main(argv) == 2
    err = capfd.readouterr().err
    assert "cannot be a .usdz package: the layer sublayers the avatar by its path" in err, err
    # the command as pasted: in parentheses, not in quotes around its own quoted paths (stop 43)
    assert "export it after that (usdface export 'my p.usda' --flatten 'my p.usdz')" in err, err
    assert list(tmp_path.iterdir()) == []
    if command == "personalize":            # the fix, pasted: the layer, then its packaged export
        assert main([command, str(A), str(C), "-o", "my p.usda", "-q", "--method", "dt"]) == 0
        assert main(shlex.split("export 'my p.usda' --flatten 'my p.usdz' -q")) == 0
        assert api.read_avatar(tmp_path / "my p.usdz").mesh("Head").deltas.shape[0] > 50


@pytest.mark.parametrize("variant", ["personalized", "generic"])
def test_flatten_bakes_the_variant(layer, tmp_path, variant):
    from pxr import Sdf

    before = file_digest(layer)
    out = api.export_avatar(layer, flatten=tmp_path / "flat.usdc", variant=variant)["flatten"]
    assert file_digest(layer) == before  # the input is never modified
    flat_layer = Sdf.Layer.FindOrOpen(str(out))
    assert not flat_layer.subLayerPaths
    flat = api.read_avatar(out)
    expect = read_avatar_variant(layer, variant)
    for rig in expect.meshes:
        got = flat.mesh(rig.name)
        assert got.names == rig.names
        np.testing.assert_array_equal(got.deltas, rig.deltas)
        np.testing.assert_array_equal(got.neutral, rig.neutral)


def test_export_refuses_and_validates_before_work(layer, tmp_path, samples):
    glb = tmp_path / "a.glb"
    glb.write_bytes(b"keep")
    with pytest.raises(OutputExistsError, match="a.glb"):
        api.export_avatar(layer, gltf=glb, flatten=tmp_path / "f.usdc")
    assert glb.read_bytes() == b"keep" and not (tmp_path / "f.usdc").exists()
    with pytest.raises(InputFileError, match="glb or .gltf"):
        api.export_avatar(layer, gltf=tmp_path / "a.fbx")
    with pytest.raises(UsdFaceError, match="nothing to export"):
        api.export_avatar(layer)
    with pytest.raises(UsdFaceError, match="unknown variant"):
        api.export_avatar(layer, gltf=tmp_path / "b.glb", variant="mixed")
    with pytest.raises(InputFileError, match="not a usdface layer"):
        api.export_avatar(samples / "avatar.usda", gltf=tmp_path / "c.glb", variant="generic")
    api.export_avatar(layer, gltf=glb, force=True)
    assert glb.read_bytes()[:4] == b"glTF"


@pytest.mark.parametrize("failure", [OSError(28, "No space left on device"), KeyboardInterrupt()])
def test_an_export_that_fails_part_way_leaves_no_new_output(layer, tmp_path, monkeypatch, failure):
    """A user trial: SIGTERM (or a full disk) after the glTF was written left that .glb and the OBJ folder
    without the flattened file, a partial set a pipeline could take for a finished export. The outputs this
    call created go; one it replaced with force stays replaced (its old version is gone either way)."""
    import usdface.io.flatten as flatten_module

    def fail(*_a, **_k):
        raise failure

    monkeypatch.setattr(flatten_module, "flatten_variant", fail)
    glb, objs, flat = tmp_path / "a.glb", tmp_path / "objs", tmp_path / "f.usdc"
    with pytest.raises(type(failure)):
        api.export_avatar(layer, gltf=glb, obj_dir=objs, flatten=flat)
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    old = tmp_path / "old.glb"
    old.write_bytes(b"old")
    with pytest.raises(type(failure)):
        api.export_avatar(layer, gltf=old, obj_dir=objs, flatten=flat, force=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.glb"] and old.read_bytes()[:4] == b"glTF"


def test_export_cli(layer, tmp_path):
    cmd = [sys.executable, "-m", "usdface.cli", "export", str(layer), "--gltf", str(tmp_path / "x.glb"),
           "--variant", "generic"]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    assert "x.glb" in done.stdout and "[generic]" in done.stdout
    again = subprocess.run(cmd, capture_output=True, text=True, check=False)
    assert again.returncode == 2 and "--force" in again.stderr


@pytest.mark.shared
def test_gltf_round_trip_dev1(bench, tmp_path):
    out_layer = tmp_path / "dev1.usda"
    api.personalize_avatar(bench / "dev1" / "avatar.usdc", bench / "dev1" / "capture", out_layer, force=True)
    out = api.export_avatar(out_layer, gltf=tmp_path / "dev1.glb")["gltf"]
    _validate_gltf(out)
    data = read_gltf(out)
    for name, (neutral, _, names, deltas) in _rigs(read_avatar_variant(out_layer, "personalized")).items():
        np.testing.assert_array_equal(data[name]["positions"], neutral.astype(np.float32))
        assert data[name]["target_names"] == list(names)
        np.testing.assert_array_equal(data[name]["targets"],
                                      deltas.astype(np.float32))
    joints = data["Head"]["joints"]
    assert joints.shape == (len(data["Head"]["positions"]), 4)


_BPY = Path(os.environ.get("USDFACE_BPY_PYTHON", Path.home() / ".cache" / "bpy-venv" / "bin" / "python"))

_BLENDER_SCRIPT = """
import json, sys
import bpy
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_scene.gltf(filepath=sys.argv[1])
out = {}
for ob in bpy.data.objects:
    if ob.type == "MESH":
        keys = ob.data.shape_keys
        out[ob.name] = [k.name for k in keys.key_blocks][1:] if keys else []
print("USDFACE_JSON " + json.dumps(out))
"""


def test_gltf_imports_in_blender(layer, tmp_path):
    """Optional: Blender (the ``bpy`` wheel in its own venv, see ../shared/tools/blender_check.py) imports
    the glTF with the ARKit shape keys. Skips when no such venv exists."""
    if not _BPY.is_file():
        pytest.skip(f"no Blender Python at {_BPY} (set USDFACE_BPY_PYTHON; see blender_check.py)")
    out = api.export_avatar(layer, gltf=tmp_path / "b.glb")["gltf"]
    script = tmp_path / "check.py"
    script.write_text(_BLENDER_SCRIPT)
    done = subprocess.run([str(_BPY), str(script), str(out)], capture_output=True, text=True, check=False,
                          timeout=300)
    line = next((x for x in done.stdout.splitlines() if x.startswith("USDFACE_JSON ")), None)
    assert line, done.stdout[-2000:] + done.stderr[-2000:]
    keys = json.loads(line.split(" ", 1)[1])
    head = next(v for k, v in keys.items() if k.startswith("Head"))
    assert head == read_avatar_variant(layer, "personalized").mesh("Head").names
    assert shutil.which  # keeps the import used when Blender is absent


def test_a_flattened_generic_export_personalizes_like_the_avatar(layer, tmp_path, samples):
    """The chain the docs give for a place that takes one file: export --flatten --variant generic, then
    personalize that file. The flattened file is the avatar again (its own BlendShape paths, no usdface
    scope), so the new layer carries its variant set (review and export --variant generic refused it before)
    and gives the same offsets as personalizing the original avatar."""
    from pxr import Usd

    flat = tmp_path / "flat.generic.usdc"
    assert main(["export", str(layer), "--flatten", str(flat), "--variant", "generic", "-q"]) == 0
    stage = Usd.Stage.Open(str(flat))
    assert not [p for p in stage.Traverse() if "usdfaceShapes" in str(p.GetPath())]
    original = api.read_avatar(samples / "avatar.usda")
    again = api.read_avatar(flat)
    for rig in original.meshes:
        np.testing.assert_array_equal(again.mesh(rig.name).deltas, rig.deltas)
    out = tmp_path / "again.usda"
    assert main(["personalize", str(flat), str(samples / "capture.usda"), "-o", str(out), "-q"]) == 0
    assert main(["review", str(out), "-o", str(tmp_path / "r.html"), "-q", "--no-fit-errors"]) == 0
    generic = read_avatar_variant(out, "generic")
    first, second = read_avatar_variant(layer), read_avatar_variant(out)
    for rig in original.meshes:
        np.testing.assert_array_equal(generic.mesh(rig.name).deltas, rig.deltas)
        np.testing.assert_allclose(second.mesh(rig.name).deltas, first.mesh(rig.name).deltas, rtol=0,
                                   atol=1e-9)


def test_a_flattened_generic_export_of_an_avatar_with_dense_shapes_is_valid(samples, tmp_path):
    """An avatar whose shapes are dense (offsets for every point, no pointIndices, as dev1's): the layer
    authors the personalized shapes' sparse pointIndices on the original BlendShape prims, and the generic
    variant's baked shapes kept them: dense offsets with sparse indices, a --variant generic export that
    check refused (BlendShapeOffsets errors) and that no reader could read."""
    from pxr import Sdf, Usd, UsdSkel, Vt

    avatar = tmp_path / "dense.usda"
    assert Sdf.Layer.FindOrOpen(str(samples / "avatar.usda")).Export(str(avatar))
    stage = Usd.Stage.Open(str(avatar))
    n_points = len(stage.GetPrimAtPath("/Avatar/Head").GetAttribute("points").Get())
    for prim in stage.Traverse():
        shape = UsdSkel.BlendShape(prim)
        idx = shape.GetPointIndicesAttr().Get() if prim.IsA(UsdSkel.BlendShape) else None
        if idx and "/Avatar/Head/" in str(prim.GetPath()):
            dense = np.zeros((n_points, 3), np.float32)
            dense[np.asarray(idx)] = np.asarray(shape.GetOffsetsAttr().Get())
            shape.GetOffsetsAttr().Set(Vt.Vec3fArray.FromNumpy(dense))
            prim.RemoveProperty("pointIndices")
    stage.GetRootLayer().Save()
    out, flat = tmp_path / "person.usda", tmp_path / "flat.generic.usdc"
    assert main(["personalize", str(avatar), str(samples / "capture.usda"), "-o", str(out), "-q"]) == 0
    assert main(["export", str(out), "--flatten", str(flat), "--variant", "generic", "-q"]) == 0
    assert [i for i in api.check(flat) if i.severity == "error"] == []
    original, again = api.read_avatar(avatar), api.read_avatar(flat)
    for rig in original.meshes:
        np.testing.assert_array_equal(again.mesh(rig.name).deltas, rig.deltas)


def test_a_flattened_personalized_export_stays_personalized_when_exported_again(layer, samples, tmp_path,
                                                                              capsys):
    """A user trial: exporting a flattened *personalized* file (``export flat.usdc --gltf/--flatten``) printed
    ``[as authored: a plain avatar, not personalized]``, the glTF's extras said ``"authored"``, and flattening
    it again recorded ``variant: authored``, so ``personalize`` took that second file for an avatar and
    stacked the personalization a second time. The variant baked in, and the layer it came from, now carry
    through: the label, the extras and the record say ``personalized``, and personalize refuses it."""
    import pygltflib

    from usdface.errors import AlreadyPersonalizedError
    from usdface.io.usd_rig import flattened_from

    flat, again, glb = tmp_path / "flat.usdc", tmp_path / "sub" / "again.usdc", tmp_path / "again.glb"
    assert main(["export", str(layer), "--flatten", str(flat), "-q"]) == 0
    capsys.readouterr()
    assert main(["export", str(flat), "--flatten", str(again), "--gltf", str(glb), "-q"]) == 0
    out = capsys.readouterr().out
    assert "not personalized" not in out and "[personalized, as baked into flat.usdc" in out
    assert pygltflib.GLTF2().load(str(glb)).scenes[0].extras["usdface"]["variant"] == "personalized"
    record = flattened_from(again)
    assert record["variant"] == "personalized"
    assert (again.parent / record["source"]).resolve() == layer.resolve()   # the layer, not flat.usdc
    with pytest.raises(AlreadyPersonalizedError, match=layer.name):
        api.personalize_avatar(again, samples / "capture.usda", tmp_path / "twice.usda", dry_run=True)
    plain = tmp_path / "plain.usdc"                                          # a plain avatar stays "authored"
    assert main(["export", str(samples / "avatar.usda"), "--flatten", str(plain), "-q"]) == 0
    assert flattened_from(plain)["variant"] == "authored"
    assert "[as authored: a plain avatar, not personalized]" in capsys.readouterr().out


def test_inspect_names_a_flattened_export_for_what_it_is(layer, tmp_path, capsys):
    """A user trial: ``inspect flat.usdc`` of a flattened personalized export reported a ``usdface-layer``
    with its provenance, and nothing said it was one file with the person's shapes baked in (the very thing
    personalize refuses it for). Now its kind is ``usdface-flattened``, with the variant and the layer."""
    from usdface.inspect import format_report, inspect_file

    for variant in ("personalized", "generic"):
        flat = tmp_path / f"flat.{variant}.usdc"
        assert main(["export", str(layer), "--flatten", str(flat), "--variant", variant, "-q"]) == 0
        report = inspect_file(flat)
        assert report["kind"] == "usdface-flattened" and report["flattened"]["variant"] == variant
        text = format_report(report)
        assert f"flattened export (usdface export --flatten) of the {variant} variant of {layer}" in text
    assert "refuses it as the avatar" in format_report(inspect_file(tmp_path / "flat.personalized.usdc"))
    assert inspect_file(layer)["kind"] == "usdface-layer" and "flattened" not in inspect_file(layer)


def test_no_skin_without_gltf_is_refused(samples, tmp_path, capsys):
    """``export LAYER --obj-dir DIR --no-skin`` wrote the OBJs and ignored ``--no-skin`` silently."""
    from usdface.cli import main

    objs = str(tmp_path / "objs")
    assert main(["export", str(samples / "avatar.usda"), "--obj-dir", objs, "--no-skin"]) == 2
    assert "--no-skin applies to the glTF only" in capsys.readouterr().err
    assert not (tmp_path / "objs").exists()


def test_a_flattened_export_elsewhere_keeps_a_provenance_check_can_follow(tmp_path):
    """A flattened file written into another folder copied its provenance paths (relative to the layer's
    folder), so ``check`` found the inputs 'not reachable' and the stale-input check was off."""
    from usdface import api
    from usdface.io.layers import recorded_inputs

    layer = tmp_path / "p.usda"
    api.personalize_avatar(A, C, layer)
    flat = tmp_path / "deliver" / "x" / "flat.usda"
    flat.parent.mkdir(parents=True)
    api.export_avatar(layer, flatten=flat, variant="generic")
    assert set(recorded_inputs(flat)) == {str(A.resolve()), str(C.resolve())}
    issues = api.check(flat)
    assert not [i for i in issues if "not reachable" in i.message], issues


def test_export_names_every_output_the_same_way(tmp_path, monkeypatch):
    """``usdface export LAYER --obj-dir d --flatten f.usda`` printed ``obj_dir: d`` but ``flatten:
    /abs/.../f.usda`` (export_avatar returned the flattened file absolute, the others as given); every output
    comes back absolute now, as from every API function (docs/api.md)."""
    from usdface.api import export_avatar

    monkeypatch.chdir(tmp_path)
    layer = tmp_path / "p.usda"
    assert main(["personalize", str(SAMPLES / "avatar.usda"), str(SAMPLES / "capture.usda"), "-o", str(layer),
                 "-q"]) == 0
    done = export_avatar("p.usda", gltf="g.glb", obj_dir="objs", flatten="f.usda")
    assert done == {"gltf": tmp_path / "g.glb", "obj_dir": tmp_path / "objs", "flatten": tmp_path / "f.usda"}
    assert all(p.exists() for p in done.values())


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


@pytest.mark.parametrize(("option", "where"), [("gltf", "inside"), ("gltf", "same"), ("flatten", "inside")])
def test_export_refuses_a_file_output_in_its_obj_dir_before_writing(personalized_sample, tmp_path, option,
                                                                    where):
    """``export --obj-dir d --gltf d/x.glb`` wrote the glTF, then refused the folder it had just made not
    empty ('output folder exists and is not empty'): exit 2 with x.glb left behind; ``--gltf x.glb
    --obj-dir x.glb`` the same ('exists as a file')."""
    from usdface import api
    from usdface.errors import OptionError

    folder = tmp_path / "d"
    suffix = ".glb" if option == "gltf" else ".usdc"
    out = folder / f"x{suffix}" if where == "inside" else folder
    with pytest.raises(OptionError, match="--obj-dir folder"):
        api.export_avatar(personalized_sample, obj_dir=folder, **{option: out})
    assert list(tmp_path.iterdir()) == []


def test_export_of_a_plain_avatar_says_as_authored(sample_dir, personalized_sample, tmp_path):
    import pygltflib

    res = _usdface("export", sample_dir / "avatar.usda", "--gltf", "a.glb", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "[personalized]" not in res.stdout and "as authored" in res.stdout, res.stdout
    extras = pygltflib.GLTF2().load(str(tmp_path / "a.glb")).scenes[0].extras
    assert extras["usdface"]["variant"] == "authored"
    res = _usdface("export", personalized_sample, "--gltf", "p.glb", cwd=tmp_path)
    assert res.returncode == 0 and "[personalized]" in res.stdout, res.stderr
    extras = pygltflib.GLTF2().load(str(tmp_path / "p.glb")).scenes[0].extras
    assert extras["usdface"]["variant"] == "personalized"


def _matrices(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(joint node matrices[J, 4, 4], inverse bind matrices[J, 4, 4])`` of the first skin (column
    vectors)."""
    import pygltflib

    gltf = pygltflib.GLTF2().load(str(path))
    skin = gltf.skins[0]
    view = gltf.bufferViews[gltf.accessors[skin.inverseBindMatrices].bufferView]
    ibm = np.frombuffer(gltf.binary_blob(), dtype=np.float32, count=16 * len(skin.joints),
                        offset=view.byteOffset).reshape(-1, 4, 4).transpose(0, 2, 1)
    nodes = np.array([np.asarray(gltf.nodes[j].matrix).reshape(4, 4).T for j in skin.joints])
    return nodes, ibm


def test_gltf_skin_of_a_scaled_skeleton_carries_no_scale(samples, tmp_path):
    """A user trial: ``export --gltf`` of a layer over a Blender avatar (its Skeleton under a prim scaled
    0.01, as the bench's ``avatar_blender.usdc``) put the 0.01 in the root joint's node and 100 in the
    inverse bind matrices: valid glTF (joint @ inverse bind is the identity), but Blender's importer builds
    its bind pose from the inverse bind matrices with the scale dropped (edit bones have none) and the mesh
    was 100 times too large without its Armature modifier. The scale cancels in the skinning: each joint's
    is taken out of both, so no joint node and no inverse bind matrix is scaled, and the rest pose and the
    points (metres) are as before."""
    from usdface.io.avatar_writer import write_rig_usd

    avatar = api.read_avatar(samples / "avatar.usda")
    turned = write_rig_usd(avatar.meshes, tmp_path / "turned.usda", up_axis="Z", meters_per_unit=1.0,
                           parents=("root",), parent_scale=0.01, parent_rotate_x_deg=90.0)
    out = api.export_avatar(turned, gltf=tmp_path / "t.glb")["gltf"]
    nodes, ibm = _matrices(out)
    for m in (*nodes, *ibm):       # rotation + translation only: orthonormal 3 x 3
        np.testing.assert_allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-5)
    for product in _rest_skinning(out):
        np.testing.assert_allclose(product, np.eye(4), atol=1e-6)
    plain = read_gltf(api.export_avatar(samples / "avatar.usda", gltf=tmp_path / "p.glb")["gltf"])
    np.testing.assert_allclose(read_gltf(out)["Head"]["positions"], plain["Head"]["positions"], atol=1e-6)


def test_gltf_skin_of_the_bench_blender_avatar_carries_no_scale(bench, tmp_path):
    """The same on the bench's Blender round trip itself (``../shared``; skipped without it)."""
    path = bench / "dev1" / "avatar_blender.usdc"
    if not path.is_file():
        pytest.skip("needs ../shared/data/bench/dev1/avatar_blender.usdc")
    out = api.export_avatar(path, gltf=tmp_path / "b.glb")["gltf"]
    nodes, ibm = _matrices(out)
    for m in (*nodes, *ibm):
        np.testing.assert_allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-5)
    for product in _rest_skinning(out):
        np.testing.assert_allclose(product, np.eye(4), atol=1e-5)
    head = read_gltf(out)["Head"]["positions"]
    assert 0.1 < float(np.ptp(head, axis=0).max()) < 1.0     # a head's size in metres


def test_export_variant_generic_of_a_flattened_export(layer, tmp_path, capsys):
    """A user trial: ``export flat.usdc --variant generic`` of a flattened *personalized* export said 'no
    usdfacePersonalization variant set (not a usdface layer)' of a file usdface wrote; it now says what the
    file is and names the layer it was flattened from. A flattened *generic* export's generic is what is
    baked in (it was refused the same way)."""
    flat, gflat = tmp_path / "flat.usdc", tmp_path / "flat.generic.usdc"
    assert main(["export", str(layer), "--flatten", str(flat), "-q"]) == 0
    assert main(["export", str(layer), "--flatten", str(gflat), "--variant", "generic", "-q"]) == 0
    capsys.readouterr()
    out = tmp_path / "g.glb"
    assert main(["export", str(flat), "--gltf", str(out), "--variant", "generic", "-q"]) == 2
    err = capsys.readouterr().err
    assert "a flattened export of the personalized variant of" in err and "not a usdface layer" not in err
    assert layer.name in err and not out.exists()
    assert main(["export", str(gflat), "--gltf", str(out), "--variant", "generic"]) == 0
    assert "[generic, as baked into flat.generic.usdc" in capsys.readouterr().out
    generic = read_avatar_variant(layer, "generic")
    got = read_gltf(out)
    for rig in generic.meshes:
        np.testing.assert_array_equal(got[rig.name]["targets"], rig.deltas.astype(np.float32))


def test_gltf_skin_keeps_each_vertexs_four_largest_influences_with_their_joints(tmp_path):
    """glTF takes 4 influences a vertex: the 4 largest of the skeleton's, each with its own joint, the
    weights renormalised to 1 (a one-joint skeleton, the only one tested before, cannot tell the joints
    apart)."""
    from usdface.io.gltf import GltfSkin, write_gltf
    from usdface.model import FaceRig

    rng = np.random.default_rng(4)
    pts = rng.normal(size=(5, 3)) * 0.01
    rig = FaceRig(pts, np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4]]), [], np.zeros((0, 5, 3)), name="Face")
    indices = np.array([rng.permutation(7)[:6] for _ in range(5)])
    weights = rng.random((5, 6)) + np.arange(6) * 1e-3                  # no ties
    skin = GltfSkin([f"j{k}" for k in range(7)], [-1] * 7, np.tile(np.eye(4), (7, 1, 1)),
                    np.tile(np.eye(4), (7, 1, 1)), {"Face": (indices, weights)})
    data = read_gltf(write_gltf(tmp_path / "s.glb", [rig], skin=skin))["Face"]
    for v in range(5):
        top = np.argsort(-weights[v])[:4]
        want = dict(zip(indices[v, top].tolist(), (weights[v, top] / weights[v, top].sum()).tolist(),
                        strict=True))
        got = dict(zip(data["joints"][v].tolist(), data["weights"][v].tolist(), strict=True))
        assert got.keys() == want.keys()
        assert all(abs(got[j] - want[j]) < 1e-6 for j in want)


def test_gltf_skins_each_avatar_of_a_shot_by_its_own_skeleton(layer, tmp_path):
    """A user trial (stop 44): a shot with two SkelRoots (the personalized layer referenced twice, the second
    hero moved 30 cm) exported one skin (the first skeleton's) that no mesh used: every mesh placed right but
    unskinned, so posing either skeleton moved nothing. Each skeleton is now its own glTF skin, each mesh
    skinned by the skeleton UsdSkel binds it to, and every skin's joints at rest times its inverse bind
    matrices is the identity (the points stay where POSITION puts them)."""
    import pygltflib

    shot = tmp_path / "shot.usda"
    shot.write_text(f'''#usda 1.0
(
    defaultPrim = "World"
    metersPerUnit = 0.01
    upAxis = "Y"
)
def Xform "World"
{{
    def "HeroA" (prepend references = @{layer.as_posix()}@) {{}}
    def "HeroB" (prepend references = @{layer.as_posix()}@)
    {{
        double3 xformOp:translate = (30, 0, 0)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }}
}}
''')
    path = api.export_avatar(shot, gltf=tmp_path / "two.glb")["gltf"]
    gltf = pygltflib.GLTF2().load(str(path))
    assert len(gltf.skins) == 2
    assert sorted(s.name for s in gltf.skins) == ["World_HeroA_Skel", "World_HeroB_Skel"]
    assert not set(gltf.skins[0].joints) & set(gltf.skins[1].joints)
    for skin in gltf.skins:               # each skeleton under a node of its own: Blender makes 2 armatures
        group = [n for n in gltf.nodes if n.name == skin.name and n.mesh is None]
        assert len(group) == 1 and skin.skeleton in group[0].children
    meshes = [n for n in gltf.nodes if n.mesh is not None]
    assert len(meshes) == 8
    for node in meshes:                                 # every mesh skinned, by its own avatar's skeleton
        hero = node.name.split("_")[1]
        assert node.skin is not None and gltf.skins[node.skin].name == f"World_{hero}_Skel", node.name
    blob = gltf.binary_blob()
    data = read_gltf(path)
    for index, skin in enumerate(gltf.skins):
        ibm = _read_accessor_matrices(gltf, blob, skin.inverseBindMatrices)
        world = np.stack([np.asarray(gltf.nodes[j].matrix).reshape(4, 4).T for j in skin.joints])
        np.testing.assert_allclose(world @ ibm, np.broadcast_to(np.eye(4), world.shape), atol=1e-6)
        shift = 0.3 if gltf.skins[index].name.endswith("HeroB_Skel") else 0.0
        np.testing.assert_allclose(world[0][:3, 3], [shift, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(data["World_HeroB_Head"]["positions"] - data["World_HeroA_Head"]["positions"],
                               np.broadcast_to([0.3, 0, 0], data["World_HeroA_Head"]["positions"].shape),
                               atol=1e-6)


def _read_accessor_matrices(gltf, blob, index) -> np.ndarray:
    from usdface.io.gltf import _read_accessor

    return _read_accessor(gltf, blob, index).reshape(-1, 4, 4).transpose(0, 2, 1)


def _faceted_sample(samples, out: Path) -> Path:
    """The sample avatar turned (``rotateXYZ = (90, 0, 30)`` on its SkelRoot) with authored normals: per
    face corner on Head, each face's corners the normal of its first fan triangle (every edge a hard edge,
    as a DCC's flat shading), none on Mouth; and ``normalOffsets`` on Head's first shape, (0, 0.5, 0) at
    each of its points."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel

    stage = Usd.Stage.Open(str(samples / "avatar.usda"))
    stage.GetRootLayer().Export(str(out))
    stage = Usd.Stage.Open(str(out))
    UsdGeom.Xformable(stage.GetPrimAtPath("/Avatar")).AddRotateXYZOp().Set(Gf.Vec3f(90, 0, 30))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Avatar/Head"))
    points = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get())
    idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get())
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    a, b, c = (points[idx[start + i]] for i in range(3))
    face = np.cross(b - a, c - a)
    face /= np.linalg.norm(face, axis=1, keepdims=True)
    mesh.CreateNormalsAttr().Set(np.repeat(face, counts, axis=0).astype(np.float32).tolist())
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.faceVarying)
    first = UsdSkel.BindingAPI(mesh.GetPrim()).GetBlendShapeTargetsRel().GetForwardedTargets()[0]
    shape = UsdSkel.BlendShape(stage.GetPrimAtPath(first))
    n = len(shape.GetOffsetsAttr().Get())
    shape.CreateNormalOffsetsAttr().Set([(0.0, 0.5, 0.0)] * n)
    assert shape.GetNormalOffsetsAttr().GetTypeName() == Sdf.ValueTypeNames.Vector3fArray
    stage.GetRootLayer().Save()
    return out


def test_gltf_carries_the_authored_normals_and_normal_offsets(samples, tmp_path):
    """A user trial (stop 44): the glTF's NORMALs were computed from the triangles (smooth, area-weighted),
    so an avatar's authored normals (hard edges, a DCC's custom normals) were lost, and a shape's authored
    ``normalOffsets`` too. The authored normals are now the glTF's, in its frame (the avatar turned), split
    at a hard edge as at a UV seam; a shape's ``normalOffsets`` are its target's NORMAL deltas. A mesh
    without normals (Mouth) and a shape without offsets keep the computed ones."""
    from usdface.io.gltf import _unit_normals

    faceted = _faceted_sample(samples, tmp_path / "faceted.usda")
    data = read_gltf(api.export_avatar(faceted, gltf=tmp_path / "f.glb")["gltf"])
    avatar = api.read_avatar(faceted)
    rig, got = avatar.mesh("Head"), data["Head"]
    tris = got["indices"]
    assert len(tris) == len(rig.triangles)
    np.testing.assert_array_equal(got["positions"][tris], rig.neutral.astype(np.float32)[rig.triangles])
    # a face's first fan triangle: its corners carry that triangle's own normal, in the glTF's frame
    p = got["positions"].astype(np.float64)[tris]
    flat = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    flat /= np.linalg.norm(flat, axis=1, keepdims=True)
    normals = got["normals"][tris]
    cos = np.einsum("tcj,tj->tc", normals, flat)
    assert np.median(cos) > 1 - 1e-6                      # most faces are triangles or planar quads
    assert len(got["positions"]) > 2 * rig.n_vertices   # every hard edge split: one vertex per face corner
    np.testing.assert_allclose(np.linalg.norm(got["normals"], axis=1), 1.0, atol=1e-6)
    # the first shape's normalOffsets (0, 0.5, 0) turned as the avatar; the next keeps the computed deltas
    linear = rig.source.to_internal[:3, :3]
    turned = np.array([0.0, 0.5, 0.0]) @ np.linalg.inv(linear) * np.cbrt(np.linalg.det(linear))
    first = got["targets"][0]
    moved = np.zeros(rig.n_vertices, dtype=bool)
    moved[rig.source.point_indices[0]] = True
    split_moved = moved[_points_of(got["positions"], rig.neutral)]
    np.testing.assert_allclose(got["target_normals"][0][split_moved],
                               np.broadcast_to(turned, (split_moved.sum(), 3)), atol=1e-6)
    assert not np.any(got["target_normals"][0][~split_moved])
    assert np.abs(first).max() > 0
    computed = _unit_normals(rig.neutral + rig.deltas[1], rig.triangles) - _unit_normals(rig.neutral,
                                                                                        rig.triangles)
    np.testing.assert_allclose(got["target_normals"][1], computed[_points_of(got["positions"], rig.neutral)],
                               atol=1e-6)
    mouth = avatar.mesh("Mouth")                        # no authored normals: computed, unsplit
    np.testing.assert_allclose(data["Mouth"]["normals"], _unit_normals(mouth.neutral, mouth.triangles),
                               atol=1e-6)


def _points_of(positions: np.ndarray, neutral: np.ndarray) -> np.ndarray:
    """The point of ``neutral`` each (split) glTF vertex is a copy of, by position."""
    from scipy.spatial import cKDTree

    dist, index = cKDTree(neutral).query(positions.astype(np.float64))
    assert dist.max() < 1e-6
    return index


def test_obj_export_writes_the_texture_coordinates(samples, tmp_path):
    """A user trial (stop 44): the OBJs of ``export --obj-dir`` had no ``vt``, so a textured avatar's
    targets arrived in a DCC without texture coordinates. They are now written from the mesh's ``st``
    (OBJ's v is up, as USD's t), one ``vt`` per distinct pair and ``f a/ta ...`` (a seam needs no split
    point); the positions and faces read back exactly, a mesh without coordinates has no ``vt``."""
    from usdface.io.mesh_io import fan_triangulate

    textured = _textured_sample(samples, tmp_path / "textured.usda")
    out = api.export_avatar(textured, obj_dir=tmp_path / "objs")["obj_dir"]
    avatar = api.read_avatar(textured)
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(textured))
    for name in ("Head", "Mouth"):
        rig = avatar.mesh(name)
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(f"/Avatar/{name}"))
        st = np.asarray(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st").Get(), dtype=np.float64)
        counts, idx = mesh.GetFaceVertexCountsAttr().Get(), mesh.GetFaceVertexIndicesAttr().Get()
        per_corner = len(st) == len(idx)
        corner = st[fan_triangulate(counts, np.arange(len(idx)))] if per_corner else st[rig.triangles]
        for file in ("neutral.obj", f"{rig.names[0]}.obj"):
            text = (out / name / file).read_text()
            vt = np.array([line.split()[1:] for line in text.splitlines() if line.startswith("vt ")], float)
            faces = [line.split()[1:] for line in text.splitlines() if line.startswith("f ")]
            pairs = np.array([[c.split("/") for c in f] for f in faces], dtype=np.int64) - 1
            np.testing.assert_array_equal(pairs[..., 0], rig.triangles)
            np.testing.assert_array_equal(vt[pairs[..., 1]], corner.astype(np.float32))
            points, tris = read_obj(out / name / file)
            want = rig.neutral + (rig.deltas[0] if file != "neutral.obj" else 0.0)
            np.testing.assert_array_equal(points, want)
            np.testing.assert_array_equal(tris, rig.triangles)
    assert len(vt) < 3 * len(rig.triangles)                 # shared corners share a vt
    assert "vt " not in (out / "EyeLeft" / "neutral.obj").read_text()


def test_export_and_review_print_json_as_the_other_commands(layer, tmp_path, capsys):
    """User trial (stop 48): a publish script that reads every command's ``--json`` document got ``usdface
    export: error: unrecognized arguments: --json`` from ``export`` and ``review``, the two delivery steps.
    Now one document on stdout naming every output written (absolute) and the warnings, no progress; an
    error is the ``{"ok": false, ...}`` document, as for the other commands."""
    out = tmp_path / "deliver"
    assert main(["export", str(layer), "--gltf", str(out / "p.glb"), "--flatten", str(out / "p.usdc"),
                 "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["ok"] and doc["variant"] == "personalized"
    assert doc["outputs"] == {"gltf": str(out / "p.glb"), "flatten": str(out / "p.usdc")}
    assert (out / "p.glb").is_file() and (out / "p.usdc").is_file()
    assert main(["review", str(layer), "-o", str(out / "p.html"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["ok"] and doc["output"] == str(out / "p.html")
    assert doc["bytes"] == (out / "p.html").stat().st_size
    assert main(["export", str(layer), "--gltf", str(out / "p.glb"), "--json"]) == 2   # exists, no --force
    captured = capsys.readouterr()
    doc = json.loads(captured.out)
    assert not doc["ok"] and doc["error"]["type"] == "OutputExistsError" and "--force" in doc["error"]["fix"]


def test_exporting_a_fit_rig_says_what_it_is(tmp_path, capsys):
    """A user trial (stop 50): ``usdface fit capture -o rig.usda`` then ``usdface export rig.usda --gltf
    rig.glb`` said ``[as authored: a plain avatar, not personalized]`` of the person's own fitted shapes. It
    names the fit rig; a plain avatar is still said to be one."""
    samples = Path(__file__).resolve().parents[1] / "sample_assets"
    rig = tmp_path / "rig.usda"
    assert main(["fit", str(samples / "capture.usda"), "-o", str(rig), "-q", "--reg", "0.01"]) == 0
    capsys.readouterr()
    assert main(["export", str(rig), "--gltf", str(tmp_path / "rig.glb"), "-q"]) == 0
    said = capsys.readouterr().out
    assert "'usdface fit' rig" in said and "not personalized" not in said, said
    assert main(["export", str(rig), "--obj-dir", str(tmp_path / "objs"), "--json", "-q"]) == 0
    assert "'usdface fit' rig" in json.loads(capsys.readouterr().out)["label"]
    assert main(["export", str(samples / "avatar.usda"), "--gltf", str(tmp_path / "a.glb"), "-q"]) == 0
    assert "a plain avatar, not personalized" in capsys.readouterr().out


def test_an_explicit_personalized_variant_of_a_plain_avatar_is_refused(layer, tmp_path, capsys):
    """A user trial (stop 50): ``usdface export AVATAR --variant personalized`` of a plain avatar wrote it as
    authored (said only in the label) while ``--variant generic`` of it was refused: the default and an
    explicit 'personalized' could not be told apart. An explicit variant the file lacks is refused, naming
    the file and the fixes, with nothing written; the default still exports the avatar as authored."""
    samples = Path(__file__).resolve().parents[1] / "sample_assets"
    avatar = samples / "avatar.usda"
    for variant in ("personalized", "generic"):
        out = tmp_path / f"{variant}.glb"
        assert main(["export", str(avatar), "--gltf", str(out), "--variant", variant, "-q"]) == 2
        said = capsys.readouterr().err
        assert str(avatar) in said and "usdfacePersonalization" in said, said
        assert not out.exists()
    assert main(["export", str(avatar), "--gltf", str(tmp_path / "personalized.glb"), "--variant",
                 "personalized", "-q"]) == 2
    said = " ".join(capsys.readouterr().err.split())
    assert "personalize it first" in said and "without --variant" in said, said
    assert main(["export", str(avatar), "--gltf", str(tmp_path / "a.glb"), "-q"]) == 0     # the default
    assert "[as authored: a plain avatar, not personalized]" in capsys.readouterr().out
    # a layer's explicit variant, and a flattened generic export asked for its personalized variant
    assert main(["export", str(layer), "--gltf", str(tmp_path / "p.glb"), "--variant", "personalized",
                 "-q"]) == 0
    assert "[personalized]" in capsys.readouterr().out
    flat = tmp_path / "flat.generic.usdc"
    assert main(["export", str(layer), "--flatten", str(flat), "--variant", "generic", "-q"]) == 0
    capsys.readouterr()
    assert main(["export", str(flat), "--gltf", str(tmp_path / "f.glb"), "--variant", "personalized",
                 "-q"]) == 2
    said = " ".join(capsys.readouterr().err.split())
    assert str(flat) in said and "generic variant" in said, said
    assert not (tmp_path / "f.glb").exists()
