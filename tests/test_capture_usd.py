"""capture.usda: exact round trips, a valid UsdSkel template rig, schema applied, bad input, CLI."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
from test_capture_folder import tiny_capture

from usdface.cli import main
from usdface.errors import CaptureError, GeometryError, InputFileError, OutputExistsError
from usdface.io import read_capture
from usdface.io.capture_folder import read_capture_folder, write_capture_folder
from usdface.io.usd_capture import read_capture_usd, write_capture_usd

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


def assert_same_capture(a, b):
    check = np.testing.assert_array_equal
    assert a.names == b.names and a.template.names == b.template.names
    check(a.neutral, b.neutral)
    check(a.triangles, b.triangles)
    check(a.template.neutral, b.template.neutral)
    check(a.template.deltas, b.template.deltas)
    check(a.frames.points, b.frames.points)
    check(a.frames.weights, b.frames.weights)
    assert a.frames.role == b.frames.role and a.frames.label == b.frames.label


@pytest.mark.parametrize("ext", ["usda", "usdc"])
def test_round_trip_exact(tmp_path, ext):
    cap = tiny_capture()
    out = write_capture_usd(cap, tmp_path / f"c.{ext}")
    assert_same_capture(read_capture_usd(out), cap)
    assert_same_capture(read_capture(out), cap)


def test_float32_mode_is_exact_against_quantised_model(tmp_path):
    cap = tiny_capture()
    got = read_capture_usd(write_capture_usd(cap, tmp_path / "c.usda", exact=False))
    q = lambda a: a.astype(np.float32).astype(np.float64)  # noqa: E731
    np.testing.assert_array_equal(got.frames.points, q(cap.frames.points))
    np.testing.assert_array_equal(got.template.deltas, q(cap.template.deltas))
    np.testing.assert_array_equal(got.frames.weights, cap.frames.weights)  # weights stay double
    assert not np.array_equal(got.frames.points, cap.frames.points)


def test_bench_folder_usda_model_exact(bench, tmp_path):
    src = bench / "dev2" / "capture"

    def digest():
        files = sorted(p for p in src.rglob("*") if p.is_file())
        return hashlib.sha256(b"".join(p.read_bytes() for p in files)).digest()

    before = digest()
    folder = read_capture_folder(src)
    assert main(["capture", "import", str(src), "-o", str(tmp_path / "capture.usda")]) == 0
    assert_same_capture(read_capture_usd(tmp_path / "capture.usda"), folder)
    assert digest() == before  # input untouched


def test_usd_layout_is_valid_usdskel(tmp_path):
    """The template rig, posed by UsdSkel itself with frame f's weights, equals FaceRig.evaluate."""
    from pxr import Usd, UsdGeom, UsdSkel

    from usdface import schemas

    cap = tiny_capture()
    out = write_capture_usd(cap, tmp_path / "c.usda")
    stage = Usd.Stage.Open(str(out))
    root = stage.GetDefaultPrim()
    assert root.GetPath() == "/Capture" and root.HasAPI(schemas.CAPTURE_API)
    assert root.GetAttribute("usdface:capture:trainCount").Get() == 3
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0 and UsdGeom.GetStageUpAxis(stage) == "Y"
    assert stage.GetEndTimeCode() == len(cap.frames) - 1
    mesh = stage.GetPrimAtPath("/Capture/Template/Mesh")
    cache = UsdSkel.Cache()
    skel_root = UsdSkel.Root(stage.GetPrimAtPath("/Capture/Template"))
    cache.Populate(skel_root, Usd.PrimDefaultPredicate)
    skel = UsdSkel.Skeleton(stage.GetPrimAtPath("/Capture/Template/Skel"))
    binding = cache.ComputeSkelBinding(skel_root, skel, Usd.PrimDefaultPredicate)
    assert [t.GetPrim().GetPath() for t in binding.GetSkinningTargets()] == [mesh.GetPath()]
    assert cache.GetSkelQuery(skel).GetAnimQuery().GetPrim().GetPath() == "/Capture/Template/Skel/Anim"
    query = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(mesh))
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Capture/Template/Skel/Anim"))
    for f in (0, 3):
        weights = anim.GetBlendShapeWeightsAttr().Get(f)
        sub, shape_idx, sub_idx = query.ComputeSubShapeWeights(weights)
        points = UsdGeom.Mesh(mesh).GetPointsAttr().Get()
        query.ComputeDeformedPoints(sub, shape_idx, sub_idx, query.ComputeBlendShapePointIndices(),
                                    query.ComputeSubShapePointOffsets(), points)
        expected = cap.template.evaluate(cap.frames.weights[f])
        np.testing.assert_allclose(np.asarray(points), expected, atol=1e-6)
    frames = stage.GetPrimAtPath("/Capture/Frames")
    np.testing.assert_allclose(np.asarray(UsdGeom.Mesh(frames).GetPointsAttr().Get(4)), cap.frames.points[4],
                               atol=1e-7)
    assert list(frames.GetAttribute("usdface:frames:role").Get()) == cap.frames.role


def test_edited_points_win_with_warning(tmp_path):
    from pxr import Usd, UsdGeom, Vt

    cap = tiny_capture()
    out = write_capture_usd(cap, tmp_path / "c.usda")
    stage = Usd.Stage.Open(str(out))
    moved = (cap.neutral + 0.01).astype(np.float32)
    UsdGeom.Mesh(stage.GetPrimAtPath("/Capture/Neutral")).GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(moved))
    stage.GetRootLayer().Save()
    with pytest.warns(UserWarning, match="edited"):
        got = read_capture_usd(out)
    np.testing.assert_array_equal(got.neutral, moved.astype(np.float64))


def test_centimetre_stage_converted_to_metres(tmp_path):
    from pxr import Usd, UsdGeom

    cap = tiny_capture()
    out = write_capture_usd(cap, tmp_path / "c.usda")
    stage = Usd.Stage.Open(str(out))
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.GetRootLayer().Save()
    got = read_capture_usd(out)
    np.testing.assert_allclose(got.neutral, cap.neutral * 0.01)
    np.testing.assert_allclose(got.template.deltas, cap.template.deltas * 0.01)


def test_bad_inputs(tmp_path):
    with pytest.raises(InputFileError, match="not found"):
        read_capture_usd(tmp_path / "none.usda")
    junk = tmp_path / "junk.usda"
    junk.write_text("this is not usd")
    with pytest.raises(InputFileError, match="junk.usda"):
        read_capture_usd(junk)
    from pxr import Usd, UsdGeom

    other = tmp_path / "other.usda"
    stage = Usd.Stage.CreateNew(str(other))
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/World").GetPrim())
    stage.Save()
    with pytest.raises(CaptureError) as info:
        read_capture_usd(other)
    assert "other.usda" in str(info.value) and "/World" in str(info.value) and info.value.fix


def test_bad_frame_vertex_count(tmp_path):
    from pxr import Usd, UsdGeom, Vt

    out = write_capture_usd(tiny_capture(), tmp_path / "c.usda")
    stage = Usd.Stage.Open(str(out))
    frames = stage.GetPrimAtPath("/Capture/Frames")
    UsdGeom.Mesh(frames).GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(np.zeros((5, 3), np.float32)), 2)
    frames.GetAttribute("usdface:points").Set(Vt.Vec3dArray.FromNumpy(np.zeros((5, 3))), 2)
    stage.GetRootLayer().Save()
    with pytest.raises(GeometryError) as info:
        read_capture_usd(out)
    assert "/Capture/Frames" in str(info.value)


def test_cli_import_refuses_overwrite_and_reports_errors(tmp_path, capsys):
    src = write_capture_folder(tiny_capture(), tmp_path / "cap")
    out = tmp_path / "capture.usda"
    assert main(["capture", "import", str(src), "-o", str(out)]) == 0
    data = out.read_bytes()
    assert main(["capture", "import", str(src), "-o", str(out)]) == 2
    assert "--force" in capsys.readouterr().err and out.read_bytes() == data
    with pytest.raises(OutputExistsError):
        write_capture_usd(tiny_capture(), out)
    assert main(["capture", "import", str(src), "-o", str(out), "--force"]) == 0
    (src / "neutral.obj").unlink()
    bad_out = tmp_path / "bad.usda"
    assert main(["capture", "import", str(src), "-o", str(bad_out)]) == 2
    assert "neutral.obj" in capsys.readouterr().err and not bad_out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap", "capture.usda"]  # no temp files left


def pixar_validation_errors(path) -> list[str]:
    """Every error/warning of Pixar's own OpenUSD validators (usd-core's UsdValidation registry)."""
    from pxr import Usd, UsdValidation

    validators = [v for v in UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
                  if not v.GetMetadata().name.startswith("usdface")]
    assert len(validators) > 20  # geom, skel, shade, utils ... validators are really there
    errors = UsdValidation.ValidationContext(validators).Validate(Usd.Stage.Open(str(path)))
    return [f"{e.GetName()}: {e.GetMessage()}" for e in errors]


def test_written_files_pass_pixar_validators(tmp_path):
    from test_livelink import write_csv
    from test_take_select import grid_rigs

    from usdface.io.take import write_take_usd
    from usdface.sample.take import make_take

    cap = write_capture_usd(tiny_capture(), tmp_path / "capture.usda")
    person, template = grid_rigs(n=4)
    take, _ = make_take(person, template, shapes=["jawOpen", "eyeBlinkLeft"], seed=1)
    take_path = write_take_usd(take, tmp_path / "take.usdc")
    csv_path = write_csv(tmp_path / "t.csv", np.full((2, 52), 0.25), ["01:00:00:00.0", "01:00:00:02.0"])
    anim = tmp_path / "anim.usda"
    assert main(["anim", "import", str(csv_path), "-o", str(anim)]) == 0
    for path in (cap, take_path, anim):
        assert pixar_validation_errors(path) == [], path


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


def test_an_existing_output_is_named_for_what_it_is(tmp_path, capsys):
    """User trial: ``usdface capture import`` onto an existing ``cap.usda`` said 'cap.usda: output layer
    exists': a capture is no layer over an avatar. The refusal names the file for what it is (a capture
    file or folder, a take file, a fit rig file)."""
    from usdface.io.livelink import write_livelink_csv

    csv = write_livelink_csv(tmp_path / "t.csv", ["jawOpen"], np.full((4, 1), 0.5), np.arange(4) / 30.0)
    for name in ("cap.usda", "take.usda", "rig.usda"):
        (tmp_path / name).write_text("#usda 1.0\n")
    (tmp_path / "capf").mkdir()
    (tmp_path / "capf" / "keep.txt").write_text("x")
    for argv, says in ((["capture", "import", str(C), "-o", str(tmp_path / "cap.usda")],
                        "cap.usda: capture file exists"),
                       (["capture", "import", str(C), "-o", str(tmp_path / "capf")],
                        "capf: capture folder exists"),
                       (["anim", "import", str(csv), "-o", str(tmp_path / "take.usda")],
                        "take.usda: take file exists"),
                       (["fit", str(C), "-o", str(tmp_path / "rig.usda")],
                        "rig.usda: fit rig file exists")):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert says in err and "output layer" not in err and "--force" in err, err


def test_edited_template_offsets_win_over_their_float64_twin(tmp_path):
    """A template blend shape's float32 offsets edited after import (its float64 twin left as written): the
    edited offsets are read, as for the points."""
    from pxr import Usd, UsdSkel, Vt

    cap = tiny_capture()
    out = write_capture_usd(cap, tmp_path / "c.usda")
    stage = Usd.Stage.Open(str(out))
    mesh = stage.GetPrimAtPath("/Capture/Template/Mesh")
    target = UsdSkel.BindingAPI(mesh).GetBlendShapeTargetsRel().GetTargets()[0]
    edited = (cap.template.deltas[0] + 0.001).astype(np.float32)
    UsdSkel.BlendShape(stage.GetPrimAtPath(target)).GetOffsetsAttr().Set(Vt.Vec3fArray.FromNumpy(edited))
    stage.GetRootLayer().Save()
    got = read_capture_usd(out)
    np.testing.assert_array_equal(got.template.deltas[0], edited.astype(np.float64))
    np.testing.assert_array_equal(got.template.deltas[1:], cap.template.deltas[1:])


def test_a_sparse_template_shape_is_read_at_its_point_indices(tmp_path):
    """A template blend shape authored sparse (``pointIndices``, as another tool writes it): its offsets land
    on those points, zero elsewhere."""
    from pxr import Usd, UsdSkel, Vt

    cap = tiny_capture()
    out = write_capture_usd(cap, tmp_path / "c.usda")
    stage = Usd.Stage.Open(str(out))
    mesh = stage.GetPrimAtPath("/Capture/Template/Mesh")
    shape = UsdSkel.BlendShape(stage.GetPrimAtPath(UsdSkel.BindingAPI(mesh).GetBlendShapeTargetsRel()
                                                   .GetTargets()[0]))
    offsets = np.array([[0.001, 0.0, 0.0], [0.0, 0.0, -0.002]], dtype=np.float32)
    shape.GetOffsetsAttr().Set(Vt.Vec3fArray.FromNumpy(offsets))
    shape.CreatePointIndicesAttr().Set(Vt.IntArray([2, 5]))
    stage.GetRootLayer().Save()
    got = read_capture_usd(out).template.deltas[0]
    want = np.zeros_like(got)
    want[[2, 5]] = offsets.astype(np.float64)
    np.testing.assert_array_equal(got, want)


def test_a_point_index_past_the_mesh_is_refused(tmp_path):
    from pxr import Usd, UsdSkel, Vt

    cap = tiny_capture()
    n = len(cap.neutral)
    out = write_capture_usd(cap, tmp_path / "c.usda")
    stage = Usd.Stage.Open(str(out))
    mesh = stage.GetPrimAtPath("/Capture/Template/Mesh")
    shape = UsdSkel.BlendShape(stage.GetPrimAtPath(UsdSkel.BindingAPI(mesh).GetBlendShapeTargetsRel()
                                                   .GetTargets()[0]))
    shape.GetOffsetsAttr().Set(Vt.Vec3fArray.FromNumpy(np.zeros((2, 3), dtype=np.float32)))
    shape.CreatePointIndicesAttr().Set(Vt.IntArray([2, n]))
    stage.GetRootLayer().Save()
    with pytest.raises(CaptureError, match="offsets/pointIndices do not match the mesh"):
        read_capture_usd(out)


def test_a_z_up_capture_is_turned_y_up(tmp_path):
    """Z up: (x, y, z) is read as (x, z, -y), the points and the template's offsets alike."""
    from pxr import Usd, UsdGeom

    cap = tiny_capture()
    out = write_capture_usd(cap, tmp_path / "c.usda")
    stage = Usd.Stage.Open(str(out))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    stage.GetRootLayer().Save()
    got = read_capture_usd(out)

    def turned(a):
        return np.stack([a[..., 0], a[..., 2], -a[..., 1]], axis=-1)

    np.testing.assert_array_equal(got.neutral, turned(cap.neutral))
    np.testing.assert_array_equal(got.frames.points, turned(cap.frames.points))
    np.testing.assert_array_equal(got.template.deltas, turned(cap.template.deltas))


def test_weights_columns_are_matched_to_the_template_by_name(tmp_path):
    """``usdface:frames:names`` in another order than the template's shapes (with the weights in that
    order): each column goes to its shape by name."""
    from pxr import Usd, Vt

    cap = tiny_capture()
    out = write_capture_usd(cap, tmp_path / "c.usda")
    stage = Usd.Stage.Open(str(out))
    frames = stage.GetPrimAtPath("/Capture/Frames")
    names = list(frames.GetAttribute("usdface:frames:names").Get())
    frames.GetAttribute("usdface:frames:names").Set(Vt.TokenArray(names[::-1]))
    w_attr = frames.GetAttribute("usdface:frames:weights")
    for t in w_attr.GetTimeSamples():
        w_attr.Set(Vt.DoubleArray(list(w_attr.Get(t))[::-1]), t)
    stage.GetRootLayer().Save()
    np.testing.assert_array_equal(read_capture_usd(out).frames.weights, cap.frames.weights)


def test_frame_weights_outside_the_unit_interval_are_clipped_with_a_warning(tmp_path):
    from pxr import Usd, Vt

    cap = tiny_capture()
    out = write_capture_usd(cap, tmp_path / "c.usda")
    stage = Usd.Stage.Open(str(out))
    w_attr = stage.GetPrimAtPath("/Capture/Frames").GetAttribute("usdface:frames:weights")
    row = list(w_attr.Get(1))
    row[0], row[-1] = 1.5, -0.25
    w_attr.Set(Vt.DoubleArray(row), 1)
    stage.GetRootLayer().Save()
    with pytest.warns(UserWarning, match=r"outside \[0, 1\] clipped"):
        got = read_capture_usd(out)
    assert got.frames.weights[1, 0] == 1.0 and got.frames.weights[1, -1] == 0.0
    np.testing.assert_array_equal(got.frames.weights[1, 1:-1], cap.frames.weights[1, 1:-1])


def test_a_face_index_past_the_neutrals_points_is_refused(tmp_path):
    from pxr import Usd, UsdGeom, Vt

    cap = tiny_capture()
    out = write_capture_usd(cap, tmp_path / "c.usda")
    stage = Usd.Stage.Open(str(out))
    attr = UsdGeom.Mesh(stage.GetPrimAtPath("/Capture/Neutral")).GetFaceVertexIndicesAttr()
    idx = list(attr.Get())
    idx[0] = len(cap.neutral)
    attr.Set(Vt.IntArray(idx))
    stage.GetRootLayer().Save()
    with pytest.raises(GeometryError, match="face index out of range"):
        read_capture_usd(out)


def test_the_frame_counts_are_per_role(tmp_path):
    got = read_capture_usd(write_capture_usd(tiny_capture(), tmp_path / "c.usda"))
    assert got.metadata["counts"] == {"train": 3, "test": 2}


def test_the_take_selection_record_round_trips(tmp_path):
    """A capture made by ``capture select`` keeps its record: the take's entries and the frames picked,
    each once (the frames not repeated inside the take's entries)."""
    cap = tiny_capture()
    cap.metadata = {"take": {"path": "take.csv", "threshold": 0.5}, "take_frames": [3, 17, 40, 41, 90]}
    got = read_capture_usd(write_capture_usd(cap, tmp_path / "c.usda"))
    assert got.metadata["take"] == {"path": "take.csv", "threshold": 0.5}
    assert got.metadata["take_frames"] == [3, 17, 40, 41, 90]
