"""write_avatar_layer: a layer over the untouched avatar; exact round trips, variants, provenance, safety."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest
from test_usd_rig import write_rig

import usdface.io  # noqa: F401
from usdface import schemas
from usdface.cli import main
from usdface.errors import GeometryError, InputFileError, OutputExistsError, RigError
from usdface.io.layers import (
    PERSONALIZATION_VARIANT_SET,
    atomic_save,
    check_output_path,
    effective_point_set,
    file_digest,
    personalization_variant,
    write_avatar_layer,
)
from usdface.io.usd_rig import read_avatar

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


def personalized(avatar, seed=0, scale=0.002):
    """New internal offsets: every shape changed on a random half of the points; shape 2 zero but 3 points."""
    rng = np.random.default_rng(seed)
    out = {}
    for rig in avatar.meshes:
        mask = (rng.random(rig.deltas.shape[:2]) < 0.5)[..., None]
        d = rig.deltas + rng.normal(scale=scale, size=rig.deltas.shape) * mask
        d[2] = 0.0
        d[2, :3] = rng.normal(scale=scale, size=(3, 3))
        out[rig.source.prim] = d
    return out


@pytest.fixture
def rig_file(tmp_path):
    path = tmp_path / "in" / "avatar.usda"
    path.parent.mkdir()
    write_rig(path, "y_cm")
    return path


@pytest.mark.parametrize("style", ["y_cm", "z_m", "blender"])
@pytest.mark.parametrize("ext", [".usda", ".usdc"])
def test_round_trip_exact_and_input_untouched(tmp_path, style, ext):
    src = tmp_path / "in" / "avatar.usda"
    src.parent.mkdir()
    write_rig(src, style)
    before = src.read_bytes()
    avatar = read_avatar(src)
    offsets = personalized(avatar)
    out = write_avatar_layer(avatar, tmp_path / "out" / f"personalized{ext}", offsets,
                             provenance={"command": "pytest", "parameters": {"method": "menzel"}})
    assert src.read_bytes() == before
    assert out.exists() and sorted(p.name for p in out.parent.iterdir()) == [out.name]  # no temp files left
    again = read_avatar(out)
    for rig in avatar.meshes:
        back = again.mesh(rig.name)
        assert back.names == rig.names and back.source.channel_tokens == rig.source.channel_tokens
        scale = np.abs(offsets[rig.source.prim]).max()
        np.testing.assert_allclose(back.deltas, offsets[rig.source.prim], rtol=0, atol=scale * 1e-6)
        np.testing.assert_allclose(back.neutral, rig.neutral, rtol=0, atol=1e-12)
        # inbetweens stay consistent: ib' = ib + w (primary' - primary)
        k = rig.index("jawOpen")
        (ib,), (ib_back,) = rig.inbetweens["jawOpen"], back.inbetweens["jawOpen"]
        expect = ib.offsets + ib.weight * (offsets[rig.source.prim][k] - rig.deltas[k])
        np.testing.assert_allclose(ib_back.offsets, expect, rtol=0, atol=scale * 1e-6)
        assert ib_back.weight == ib.weight
    assert again.up_axis == avatar.up_axis and again.meters_per_unit == avatar.meters_per_unit


def test_layer_structure_metadata_and_provenance(rig_file, tmp_path):
    from pxr import Sdf, Usd, UsdGeom

    avatar = read_avatar(rig_file)
    out = write_avatar_layer(avatar, tmp_path / "p.usda", personalized(avatar),
                             provenance={"command": "usdface personalize a b", "method": "menzel",
                                         "parameters": {"reg": "auto", "epsilon": 0.5},
                                         "timings": {"fit": 1.5}, "registrationScale": 0.01,
                                         "registrationResidual": 0.0004})
    layer = Sdf.Layer.FindOrOpen(str(out))
    assert list(layer.subLayerPaths) == ["./in/avatar.usda"]  # relative
    source = Sdf.Layer.FindOrOpen(str(rig_file))
    for key in ("upAxis", "metersPerUnit", "defaultPrim", "startTimeCode", "endTimeCode",
                "timeCodesPerSecond"):
        assert layer.pseudoRoot.GetInfo(key) == source.pseudoRoot.GetInfo(key), key
    stage = Usd.Stage.Open(str(out))
    assert UsdGeom.GetStageMetersPerUnit(stage) == 0.01 and UsdGeom.GetStageUpAxis(stage) == "Y"
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode(), stage.GetTimeCodesPerSecond()) == (0, 10, 30)
    # every prim of the input keeps its path; the new layer defines nothing at root level
    input_stage = Usd.Stage.Open(str(rig_file))
    assert {str(p.GetPath()) for p in input_stage.Traverse()} <= {str(p.GetPath()) for p in stage.Traverse()}
    assert all(spec.specifier == Sdf.SpecifierOver for spec in layer.rootPrims)

    def local_specs(spec):
        yield spec
        for child in spec.nameChildren:
            yield from local_specs(child)
    assert all(s.specifier == Sdf.SpecifierOver for root in layer.rootPrims for s in local_specs(root))
    # provenance: customLayerData and the applied schema
    data = layer.customLayerData["usdface"]
    assert data["command"] == "usdface personalize a b" and data["parameters"]["reg"] == "auto"
    assert list(data["inputDigests"]) == [hashlib.sha256(rig_file.read_bytes()).hexdigest()]
    assert data["timings"]["fit"] == 1.5 and data["timings"]["write_layer"] > 0
    root = stage.GetPrimAtPath("/Avatar")
    assert root.HasAPI(schemas.PROVENANCE_API)
    assert root.GetAttribute("usdface:provenance:method").Get() == "menzel"
    assert root.GetAttribute("usdface:provenance:registrationScale").Get() == pytest.approx(0.01)
    assert list(root.GetAttribute("usdface:provenance:inputDigests").Get()) == [file_digest(rig_file)]
    assert '"epsilon": 0.5' in root.GetAttribute("usdface:provenance:parameters").Get()


def test_variant_switches_what_the_skel_binding_sees(rig_file, tmp_path):
    """personalized (selected) -> new offsets; generic -> the input's offsets; through UsdSkel's own query."""
    from pxr import Usd, UsdSkel

    avatar = read_avatar(rig_file)
    offsets = personalized(avatar)
    out = write_avatar_layer(avatar, tmp_path / "p.usdc", offsets, provenance={})
    stage = Usd.Stage.Open(str(out))
    generic_stage = Usd.Stage.Open(str(rig_file))
    assert personalization_variant(stage, "/Avatar") == "personalized"

    def seen(stage_, mesh):
        query = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(stage_.GetPrimAtPath(mesh)))
        idx = query.ComputeBlendShapePointIndices()
        sub = query.ComputeSubShapePointOffsets()
        n = len(stage_.GetPrimAtPath(mesh).GetAttribute("points").Get())
        dense = np.zeros((query.GetNumBlendShapes(), n, 3))
        for i in range(query.GetNumSubShapes()):
            if not query.GetInbetween(i) and len(sub[i]):  # the primary (not the null shape at weight 0)
                k = query.GetBlendShapeIndex(i)
                sel = np.array(idx[k]) if len(idx[k]) else slice(None)
                dense[k][sel] = np.array(sub[i])
        return dense

    for rig in avatar.meshes:
        mesh = rig.source.prim
        inv = np.linalg.inv(rig.source.to_internal[:3, :3])
        want_personalized = offsets[mesh] @ inv.T
        want_generic = seen(generic_stage, mesh)
        np.testing.assert_allclose(seen(stage, mesh), want_personalized, atol=1e-5)
        personalization_variant(stage, "/Avatar", "generic")
        np.testing.assert_allclose(seen(stage, mesh), want_generic, atol=0)
        personalization_variant(stage, "/Avatar", "personalized")
        np.testing.assert_allclose(seen(stage, mesh), want_personalized, atol=1e-5)
        assert not np.allclose(want_generic, want_personalized, atol=1e-4)
    # the original BlendShape prims (what pipelines read) carry the personalized offsets in both variants
    personalization_variant(stage, "/Avatar", "generic")
    original = stage.GetPrimAtPath("/Avatar/Head/eyeBlinkLeft").GetAttribute("offsets").Get()
    head = avatar.mesh("Head")
    np.testing.assert_allclose(np.array(original), offsets["/Avatar/Head"][0] * 100.0, atol=1e-4)
    assert stage.GetPrimAtPath("/Avatar").GetVariantSets().GetNames() == [PERSONALIZATION_VARIANT_SET]
    assert head.n_shapes == 3


def test_sparsity_follows_the_effect(rig_file, tmp_path):
    from pxr import Usd

    avatar = read_avatar(rig_file)
    offsets = {m.source.prim: m.deltas.copy() for m in avatar.meshes}
    head = avatar.mesh("Head")
    d = offsets["/Avatar/Head"]
    d[0] = 0.001  # dense (no pointIndices in the input): stays dense, no pointIndices
    d[1] = 0.0
    d[1, [4, 7]] = 0.002  # sparse: exactly the moved points (+ those with normal offsets / inbetweens)
    d[2] = np.where(np.arange(head.n_vertices)[:, None] < 5, 0.003, 0.0)
    out = write_avatar_layer(avatar, tmp_path / "p.usda", offsets, variants=False,
                             provenance={})
    stage = Usd.Stage.Open(str(out))
    shape0 = stage.GetPrimAtPath("/Avatar/Head/eyeBlinkLeft")
    assert not shape0.GetAttribute("pointIndices").HasAuthoredValue()
    assert len(shape0.GetAttribute("offsets").Get()) == head.n_vertices
    back = read_avatar(out).mesh("Head")
    ib_points = np.flatnonzero(np.abs(head.inbetweens["jawOpen"][0].offsets).sum(1) > 0)
    assert set(back.source.point_indices[1]) == {4, 7} | set(ib_points.tolist()) | set(
        head.source.point_indices[1].tolist())  # normal offsets are kept on their points
    # normal offsets untouched per point even though the point set changed
    old = dict(zip(head.source.point_indices[1].tolist(), head.source.normal_offsets[1].tolist(),
                   strict=True))
    new = dict(zip(back.source.point_indices[1].tolist(), back.source.normal_offsets[1].tolist(),
                   strict=True))
    assert all(new[i] == v for i, v in old.items())
    assert all(new[i] == [0, 0, 0] for i in set(new) - set(old))


def test_effective_point_set():
    a = np.zeros((5, 3))
    a[1] = 1.0
    a[3] = 1e-12  # below 1e-9 relative
    assert effective_point_set(a).tolist() == [False, True, False, False, False]
    assert effective_point_set(np.zeros((3, 3))).tolist() == [False] * 3
    b = np.zeros((5, 3))
    b[4] = 2.0
    assert effective_point_set(a, [b]).tolist() == [False, True, False, False, True]


def test_blender_dense_indices_become_sparse_at_blender_paths(tmp_path):
    src = tmp_path / "blender.usda"
    write_rig(src, "blender", normal_offsets=False)
    avatar = read_avatar(src)
    offsets = {m.source.prim: m.deltas for m in avatar.meshes}
    out = write_avatar_layer(avatar, tmp_path / "o.usda", offsets, provenance={})
    again = read_avatar(out)
    for rig in avatar.meshes:
        back = again.mesh(rig.name)
        assert back.source.prim == rig.source.prim and back.source.prim.startswith("/root/Avatar/")
        for k in range(rig.n_shapes):
            moved = np.flatnonzero(np.abs(rig.deltas[k]).sum(1) > 0)
            ibs = rig.inbetweens.get(rig.names[k], [])
            for ib in ibs:
                moved = np.union1d(moved, np.flatnonzero(np.abs(ib.offsets).sum(1) > 0))
            assert back.source.point_indices[k].tolist() == moved.tolist()
    assert again.name_report["/root/Avatar/Mouth/Mouth"]["inexact"][0][0] == "eyeBlinkLeft2"


def test_refuses_to_overwrite_and_writes_nothing_on_error(rig_file, tmp_path):
    avatar = read_avatar(rig_file)
    offsets = personalized(avatar)
    out = tmp_path / "p.usda"
    out.write_text("keep me")
    with pytest.raises(OutputExistsError) as info:
        write_avatar_layer(avatar, out, offsets, provenance={})
    assert str(out) in str(info.value) and "--force" in str(info.value)
    assert out.read_text() == "keep me"
    write_avatar_layer(avatar, out, offsets, provenance={}, force=True)
    first = read_avatar(out).mesh("Head").deltas
    # a second forced write is seen by a reader in the same process (the cached layer is reloaded)
    offsets2 = personalized(avatar, seed=5)
    write_avatar_layer(avatar, out, offsets2, provenance={}, force=True)
    second = read_avatar(out).mesh("Head").deltas
    assert not np.allclose(first, second)
    np.testing.assert_allclose(second, offsets2["/Avatar/Head"], atol=1e-8)

    bad = {"/Avatar/Head": offsets["/Avatar/Head"][:, :-1]}
    with pytest.raises(GeometryError) as info:
        write_avatar_layer(avatar, tmp_path / "q.usda", bad, provenance={})
    assert info.value.prim == "/Avatar/Head"
    nan = {"/Avatar/Head": offsets["/Avatar/Head"] * np.nan}
    with pytest.raises(GeometryError):
        write_avatar_layer(avatar, tmp_path / "q.usda", nan, provenance={})
    with pytest.raises(RigError):
        write_avatar_layer(avatar, tmp_path / "q.usda", {"/Avatar/Nose": offsets["/Avatar/Head"]},
                           provenance={})
    with pytest.raises(InputFileError):
        write_avatar_layer(avatar, tmp_path / "q.obj", offsets, provenance={})
    with pytest.raises(InputFileError):
        write_avatar_layer(avatar, rig_file, offsets, provenance={}, force=True)  # never the input
    assert not (tmp_path / "q.usda").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in", "p.usda"]


def test_check_output_path(tmp_path):
    assert check_output_path(tmp_path / "a.usdc") == tmp_path / "a.usdc"
    (tmp_path / "a.usda").write_text("")
    with pytest.raises(OutputExistsError):
        check_output_path(tmp_path / "a.usda")
    assert check_output_path(tmp_path / "a.usda", force=True)
    with pytest.raises(InputFileError):
        check_output_path(tmp_path, force=True)
    with pytest.raises(InputFileError):
        check_output_path(tmp_path / "a.txt")


def test_atomic_save_and_digest(tmp_path):
    from pxr import Sdf

    layer = Sdf.Layer.CreateAnonymous(".usda")
    Sdf.CreatePrimInLayer(layer, "/A")
    out = atomic_save(layer, tmp_path / "sub" / "x.usda")
    assert out.exists() and [p.name for p in out.parent.iterdir()] == ["x.usda"]
    assert Sdf.Layer.FindOrOpen(str(out)).GetPrimAtPath("/A")
    assert file_digest(out) == hashlib.sha256(out.read_bytes()).hexdigest()
    assert len(file_digest(tmp_path)) == 64
    with pytest.raises(InputFileError):
        file_digest(tmp_path / "missing")


def test_digests_ahead(tmp_path):
    """The inputs' digests computed on a background thread are :func:`file_digest`'s; a path it was not
    given, an empty one (an in-memory input) or a missing one gives None (the writer digests it itself)."""
    from usdface.io.layers import DigestsAhead

    (tmp_path / "cap").mkdir()
    (tmp_path / "cap" / "a.obj").write_text("v 0 0 0\n")
    (tmp_path / "avatar.usda").write_text("#usda 1.0\n")
    given = [tmp_path / "avatar.usda", str(tmp_path / "cap"), "", None, tmp_path / "missing"]
    ahead = DigestsAhead(given)
    assert ahead.get(tmp_path / "avatar.usda") == file_digest(tmp_path / "avatar.usda")
    assert ahead.get(tmp_path / "cap") == file_digest(tmp_path / "cap")
    assert ahead.get(tmp_path / "missing") is None and ahead.get("") is None
    assert ahead.get(tmp_path / "other") is None


def test_primvars_and_edit_callback(rig_file, tmp_path):
    from pxr import Usd, UsdGeom

    avatar = read_avatar(rig_file)
    head = avatar.mesh("Head")
    heat = np.linspace(0, 1, head.n_vertices)
    colors = np.stack([heat, 1 - heat, np.zeros_like(heat)], axis=1)

    def edit(stage):
        UsdGeom.Points.Define(stage, "/Avatar/Head/usdfaceLandmarks").CreatePointsAttr([(0, 0, 0)])

    out = write_avatar_layer(avatar, tmp_path / "p.usda", personalized(avatar), provenance={},
                             primvars={"/Avatar/Head": {"displayColor": (colors, "vertex"),
                                                        "usdface:error": (heat, "vertex")}}, edit=edit)
    stage = Usd.Stage.Open(str(out))
    api = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Avatar/Head"))
    display = api.GetPrimvar("displayColor")
    assert display.GetInterpolation() == "vertex"
    np.testing.assert_allclose(np.array(display.Get()), colors, atol=1e-6)
    np.testing.assert_allclose(np.array(api.GetPrimvar("usdface:error").Get()), heat, atol=1e-6)
    assert stage.GetPrimAtPath("/Avatar/Head/usdfaceLandmarks").IsA(UsdGeom.Points)


def test_bench_avatar_and_blender_get_the_same_local_offsets(bench, tmp_path):
    """Issue 6: the same personalized offsets written over avatar.usdc and avatar_blender.usdc agree in local
    units (1e-5 relative) at each file's own prim paths; the renamed Mouth channels are personalized too."""
    from pxr import Usd

    plain = read_avatar(bench / "dev1" / "avatar.usdc")
    blender = read_avatar(bench / "dev1" / "avatar_blender.usdc")
    new = {m.name: m.deltas * 1.25 for m in plain.meshes}
    out_plain = write_avatar_layer(plain, tmp_path / "plain.usdc",
                                   {m.source.prim: new[m.name] for m in plain.meshes}, provenance={})
    out_blender = write_avatar_layer(blender, tmp_path / "blender.usdc",
                                     {m.source.prim: new[m.name] for m in blender.meshes}, provenance={})
    s_plain, s_blender = Usd.Stage.Open(str(out_plain)), Usd.Stage.Open(str(out_blender))
    for name in ("Head", "Mouth"):
        a, b = plain.mesh(name), blender.mesh(name)
        for k in (0, a.index("jawOpen"), a.n_shapes - 1):
            pa = s_plain.GetPrimAtPath(a.source.shape_prims[k])
            pb = s_blender.GetPrimAtPath(b.source.shape_prims[k])
            dense_a = np.zeros((a.n_vertices, 3))
            dense_b = np.zeros((b.n_vertices, 3))
            for prim, dense in ((pa, dense_a), (pb, dense_b)):
                idx = prim.GetAttribute("pointIndices").Get()
                sel = slice(None) if idx is None else np.array(idx)
                dense[sel] = np.array(prim.GetAttribute("offsets").Get())
            peak = np.abs(dense_a).max()
            np.testing.assert_allclose(dense_b, dense_a, rtol=0, atol=1e-5 * peak)
            np.testing.assert_allclose(dense_a, local_units(a, new[name][k]), rtol=0, atol=1e-6 * peak)
    assert s_blender.GetPrimAtPath("/root/Avatar/Mouth/Mouth/eyeBlinkLeft").GetAttribute("offsets").Get()


def local_units(rig, deltas):
    return deltas @ np.linalg.inv(rig.source.to_internal[:3, :3]).T


def test_provenance_with_nested_values(rig_file, tmp_path):
    from pxr import Sdf

    avatar = read_avatar(rig_file)
    prov = {"command": "x", "registration": {"rotation": np.eye(3), "scale": np.float64(0.01)},
            "retargetMap": [{"shape": "jawOpen", "weights": [0.5, 0.5]}], "warnings": [], "flag": True,
            "inputs": [str(rig_file.parent)], "elapsedSeconds": 3.5}
    out = write_avatar_layer(avatar, tmp_path / "p.usda", personalized(avatar), provenance=prov)
    data = Sdf.Layer.FindOrOpen(str(out)).customLayerData["usdface"]
    assert data["registration"]["scale"] == 0.01 and data["flag"] is True
    assert json.loads(data["registration"]["rotation"]) == np.eye(3).tolist()
    assert json.loads(data["retargetMap"])[0]["shape"] == "jawOpen"
    assert len(data["inputDigests"]) == 2 and all(len(d) == 64 for d in data["inputDigests"])  # file + folder


def test_sample_avatar_z_up_scaled_nested_variant(samples, tmp_path):
    """Issue 6 on the project's own sample avatar: a Z-up, metre, nested variant with a 0.01 scale and a
    rotation on its parent reads to the same internal rig, and the same personalized offsets written over both
    give the same local offsets at each file's own prim paths."""
    writer = pytest.importorskip("usdface.io.avatar_writer")
    plain = read_avatar(samples / "avatar.usda")
    variant_path = writer.write_rig_usd(plain.meshes, tmp_path / "zup.usda", up_axis="Z", meters_per_unit=1.0,
                                        parents=("root",), parent_scale=0.01, parent_rotate_x_deg=90)
    variant = read_avatar(variant_path)
    assert (variant.up_axis, variant.meters_per_unit) == ("Z", 1.0)
    new = personalized(plain, scale=0.001)
    outs = {}
    for label, av in (("plain", plain), ("variant", variant)):
        for rig in av.meshes:
            ref = plain.mesh(rig.name)
            np.testing.assert_allclose(rig.neutral, ref.neutral, atol=1e-7)
            np.testing.assert_allclose(rig.deltas, ref.deltas, atol=1e-8)
        offsets = {m.source.prim: new[plain.mesh(m.name).source.prim] for m in av.meshes}
        outs[label] = read_avatar(write_avatar_layer(av, tmp_path / f"{label}.usdc", offsets, provenance={}))
    assert outs["variant"].mesh("Head").source.prim == "/root/Avatar/Head"
    for rig in plain.meshes:
        a, b = outs["plain"].mesh(rig.name), outs["variant"].mesh(rig.name)
        peak = np.abs(new[rig.source.prim]).max()
        np.testing.assert_allclose(a.deltas, new[rig.source.prim], atol=1e-6 * peak)
        np.testing.assert_allclose(b.deltas, new[rig.source.prim], atol=1e-6 * peak)
        local_a, local_b = local_units(a, a.deltas), local_units(b, b.deltas)  # both cm here
        np.testing.assert_allclose(local_b, local_a, atol=1e-5 * np.abs(local_a).max())


def test_layer_over_a_usdface_output(rig_file, tmp_path):
    """A second usdface layer over a first one: overs go to the original BlendShape prims, so the read-back is
    the newest offsets and the first layer's 'generic' variant still shows the input alone."""
    from pxr import Usd

    avatar = read_avatar(rig_file)
    first = write_avatar_layer(avatar, tmp_path / "first.usda", personalized(avatar, seed=1), provenance={})
    layered = read_avatar(first)
    assert layered.mesh("Head").source.shape_prims[0] == "/Avatar/Head/usdfaceShapes/eyeBlinkLeft"
    newest = personalized(layered, seed=2)
    second = write_avatar_layer(layered, tmp_path / "second.usda", newest, provenance={})
    back = read_avatar(second)
    stage = Usd.Stage.Open(str(second))
    personalization_variant(stage, "/Avatar", "generic")
    flat = tmp_path / "generic.usda"
    stage.Flatten().Export(str(flat))
    generic = read_avatar(flat)
    for rig in avatar.meshes:
        peak = np.abs(newest[rig.source.prim]).max()
        np.testing.assert_allclose(back.mesh(rig.name).deltas, newest[rig.source.prim], atol=1e-6 * peak)
        np.testing.assert_allclose(generic.mesh(rig.name).deltas, rig.deltas, atol=1e-12)
    layer_text = second.read_text()
    assert 'over "eyeBlinkLeft"' in layer_text and "usdfaceShapes" not in layer_text


def test_provenance_inputs_are_recorded_relative_to_the_layer(rig_file, tmp_path, monkeypatch):
    """Inputs given relative to the working directory are stored relative to the layer, so `usdface check`
    verifies their digests from any working directory."""
    from pxr import Sdf, Usd

    from usdface.pipeline.check import check

    monkeypatch.chdir(rig_file.parent)
    out_dir = tmp_path / "out" / "deeper"
    out_dir.mkdir(parents=True)
    avatar = read_avatar(rig_file.name)
    out = write_avatar_layer(avatar, out_dir / "p.usda", personalized(avatar), provenance={"command": "x"})
    data = Sdf.Layer.FindOrOpen(str(out)).customLayerData["usdface"]
    assert (out_dir / data["inputs"][0]).resolve() == rig_file.resolve()
    monkeypatch.chdir(tmp_path)
    issues = [i for i in check(Usd.Stage.Open(str(out))) if i.rule == "Provenance"]
    assert not [i for i in issues if "not reachable" in i.message or i.severity != "info"], issues


def test_the_input_path_is_relative_inside_a_project_and_absolute_across_the_root():
    """A publish whose avatar lies on another mount (only the root in common) was written with
    ``../../../../../work/...``: copied to a folder of another depth it no longer composed (a user trial).
    Relative when the two share a folder below the root (a project moved as a whole keeps composing),
    absolute otherwise."""
    from pathlib import PurePosixPath

    from usdface.io.layers import _relative_asset_path

    if os.name != "posix":
        pytest.skip("POSIX paths")
    assert _relative_asset_path(PurePosixPath("/work/lib/hero.usdc"), PurePosixPath("/tmp/pub")) \
        == "/work/lib/hero.usdc"
    assert _relative_asset_path(PurePosixPath("/proj/lib/hero.usdc"), PurePosixPath("/proj/pub/v1")) \
        == "../../lib/hero.usdc"
    assert _relative_asset_path(PurePosixPath("/proj/pub/hero.usdc"), PurePosixPath("/proj/pub")) \
        == "./hero.usdc"
    # a relative input is judged by where it is (a review: ../../../../work/... kept its dots)
    dotted = PurePosixPath("/tmp/pub/../../work/lib/hero.usdc")
    assert _relative_asset_path(dotted, PurePosixPath("/tmp/pub")) == "/work/lib/hero.usdc"


def test_an_input_on_another_file_system_is_written_absolute(monkeypatch):
    """Mounts often share a top folder (/mnt/lib, /mnt/scratch; /Volumes/...): the same project only when
    the two lie on one file system too."""
    from pathlib import PurePosixPath

    from usdface.io import layers

    if os.name != "posix":
        pytest.skip("POSIX paths")
    monkeypatch.setattr(layers, "_device", lambda path: 1 if str(path).startswith("/mnt/lib") else 2)
    assert layers._relative_asset_path(PurePosixPath("/mnt/lib/hero.usdc"), PurePosixPath("/mnt/scratch")) \
        == "/mnt/lib/hero.usdc"
    assert layers._relative_asset_path(PurePosixPath("/mnt/x/hero.usdc"), PurePosixPath("/mnt/scratch")) \
        == "../x/hero.usdc"


def test_source_date_epoch_makes_the_layer_reproducible(tmp_path, monkeypatch):
    """The same inputs twice gave layers that differed in createdAt and the timings: with SOURCE_DATE_EPOCH
    (the reproducible-builds convention) the bytes are the same, createdAt is that time."""
    from usdface.cli import main

    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    for sub in ("a", "b"):
        (tmp_path / sub).mkdir()
        monkeypatch.chdir(tmp_path / sub)
        assert main(["personalize", str(A), str(C), "-o", "p.usda", "-q"]) == 0
    one, two = (tmp_path / "a" / "p.usda").read_bytes(), (tmp_path / "b" / "p.usda").read_bytes()
    assert one == two and b'createdAt = "2023-11-14T22:13:20Z"' in one
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "yesterday")
    monkeypatch.chdir(tmp_path / "a")
    assert main(["personalize", str(A), str(C), "-o", "q.usda", "-q"]) == 2
    assert not (tmp_path / "a" / "q.usda").exists()


def test_a_bad_source_date_epoch_is_one_line_with_the_fix_in_a_fresh_process(samples, tmp_path):
    """usd-io.md: 'a SOURCE_DATE_EPOCH that is not a whole number is refused before any work'. In a fresh
    process 'usdface personalize' died instead with numpy's f2py traceback ('ValueError: invalid literal for
    int()', exit 1: scipy's import reads the variable); the check ran only at the layer's write. The command
    now refuses it first: one line naming it and the fix, exit 2."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "SOURCE_DATE_EPOCH": "1.5", "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    run = subprocess.run([sys.executable, "-m", "usdface", "personalize", str(samples / "avatar.usda"),
                          str(samples / "capture.usda"), "-o", str(tmp_path / "p.usda")],
                         capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 2, run.stderr[-500:]
    assert "Traceback" not in run.stderr
    assert "SOURCE_DATE_EPOCH='1.5' is not a time" in run.stderr and "fix:" in run.stderr
    assert not (tmp_path / "p.usda").exists()


def test_a_moved_latest_link_is_a_changed_input(tmp_path, capsys, monkeypatch):
    """User trial: a layer written from lib/latest/hero.usda (latest -> v003) recorded the resolved v003, so
    after `ln -sfn v004 latest` check, review and export saw nothing (the layer composes over v004 now).
    The input is recorded through the link, as the sublayer path is, and check warns (naming it through the
    link, from where check runs)."""
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
    monkeypatch.chdir(tmp_path)
    main(["check", str(out)])
    assert "input lib/latest/hero.usda changed after this layer was written" in capsys.readouterr().out


def test_effective_point_set_is_relative_to_each_arrays_peak():
    """The threshold is 1e-9 of the array's own largest offset, whatever the units: on offsets of 0.1 mm a
    point at 1e-12 m (1e-8 of the peak) counts, one at 1e-14 m does not."""
    a = np.zeros((4, 3))
    a[0, 0] = 1e-4
    a[1, 1] = 1e-12
    a[2, 2] = 1e-14
    assert effective_point_set(a).tolist() == [True, True, False, False]
    assert effective_point_set(a * 1e6).tolist() == [True, True, False, False]


def test_sparse_offsets_on_another_part_are_put_on_the_rigs_region():
    """Offsets given on another part of the mesh than the rig's region (a welded part): each region vertex
    takes the value given for it, the rig's own offset where none is; a vertex outside the region may be
    given only its unchanged (base) value."""
    from usdface.errors import GeometryError
    from usdface.io.layers import _on_region
    from usdface.model import FaceRig, MeshSource
    from usdface.submesh import SparseOffsets, SubMesh

    region = SubMesh(np.array([0, 1, 2, 3]), np.array([[0, 1, 2], [1, 3, 2]]), 6)
    own = np.arange(24, dtype=float).reshape(2, 4, 3) * 1e-3
    src = MeshSource(file="a.usda", prim="/A/Head", point_indices=[None, None], normal_offsets=[None, None],
                     region=region)
    rig = FaceRig(np.zeros((4, 3)), region.triangles, ["jawOpen", "mouthClose"], own, source=src, name="Head")
    given = np.full((2, 3, 3), 0.5)
    given[:, 2] = 0.0                                  # vertex 4, outside the region: not moved
    out = _on_region(rig, SparseOffsets(np.array([0, 2, 4]), given, 6), "a.usda")
    np.testing.assert_array_equal(out.vertices, region.vertices)
    np.testing.assert_array_equal(out.values[:, [0, 2]], 0.5)
    np.testing.assert_array_equal(out.values[:, [1, 3]], own[:, [1, 3]])
    given[:, 2] = 0.5
    base = np.zeros((2, 6, 3))
    base[:, 4] = 0.5                                   # vertex 4 given its unchanged value: fine
    _on_region(rig, SparseOffsets(np.array([0, 2, 4]), given, 6, base=base), "a.usda")
    base[:, 4] = 0.25
    with pytest.raises(GeometryError, match="move vertices the rig does not hold"):
        _on_region(rig, SparseOffsets(np.array([0, 2, 4]), given, 6, base=base), "a.usda")


def test_shape_support_on_a_region_adds_residue_and_normal_offset_points_in_order():
    """A rig on part of its mesh (points 0-3 of 6): shape 0's support is its region, the authored point 5
    outside it (kept as it was) and point 4, which has only a normal offset (written with zero motion);
    point 1's normal offset adds nothing (it is in the region). Ascending, each point once."""
    from usdface.io.layers import _shape_support
    from usdface.model import FaceRig, MeshSource
    from usdface.submesh import SparseOffsets, SubMesh

    region = SubMesh(np.array([0, 1, 2, 3]), np.array([[0, 1, 2], [1, 3, 2]]), 6)
    own = np.full((1, 4, 3), 1e-3)
    normals = np.zeros((6, 3))
    normals[[1, 4], 2] = 0.1
    residue = [(np.array([5]), np.array([[2e-3, 0.0, 0.0]]), [])]
    src = MeshSource(file="a.usda", prim="/A/Head", point_indices=[None], normal_offsets=[normals],
                     region=region, residue=residue)
    rig = FaceRig(np.zeros((4, 3)), region.triangles, ["jawOpen"], own, source=src, name="Head")
    new = SparseOffsets(region.vertices, np.full((1, 4, 3), 4e-3), 6)
    points, values_new, values_old, ibs = _shape_support(rig, 0, new)
    np.testing.assert_array_equal(points, [0, 1, 2, 3, 4, 5])
    np.testing.assert_array_equal(values_new[:4], 4e-3)
    np.testing.assert_array_equal(values_new[4], 0.0)
    np.testing.assert_array_equal(values_new[5], [2e-3, 0.0, 0.0])
    np.testing.assert_array_equal(values_old[:4], 1e-3)
    np.testing.assert_array_equal(values_old[5], [2e-3, 0.0, 0.0])
    assert ibs == []


def test_read_layer_info_reads_the_provenance_once_for_the_stale_inputs(rig_file, tmp_path, monkeypatch):
    """``read_layer_info`` holds the layer's provenance (its ``file_kind``), yet ``stale_inputs`` read it
    again from the file (stop 51's read of the change). It takes the record now, as ``missing_inputs`` does:
    the stale input is still told, with no second read; a record given is the one used."""
    import usdface.io.usd_rig as usd_rig
    from usdface.io.layers import stale_inputs
    from usdface.io.usd_rig import read_layer_info

    avatar = read_avatar(rig_file)
    out = write_avatar_layer(avatar, tmp_path / "out" / "p.usda", personalized(avatar),
                             provenance={"command": "x"})
    record = usd_rig.usdface_output_provenance(out)
    assert stale_inputs(out) == [] and stale_inputs(out, record=record) == []
    changed = dict(record, inputDigests=["0" * 64])                       # as if the avatar had changed
    told = stale_inputs(out, record=changed)
    assert len(told) == 1 and "changed after" in told[0]
    rig_file.write_text(rig_file.read_text() + "\n")                       # the avatar edited since

    def read_again(path):
        raise AssertionError(f"provenance of {path} read again")

    monkeypatch.setattr(usd_rig, "usdface_output_provenance", read_again)
    stale = read_layer_info(out, revisions=True)["staleInputs"]
    assert len(stale) == 1 and "avatar.usda" in stale[0] and "changed after" in stale[0]
