"""write_rig_usd: fresh UsdSkel assets that read back exactly (units, up axis, nesting, sparse, inbetween)"""

from __future__ import annotations

import numpy as np
import pytest

from usdface.errors import GeometryError, InputFileError, OutputExistsError, RigError
from usdface.io.avatar_writer import sparse_point_indices, write_rig_usd
from usdface.io.usd_rig import read_avatar
from usdface.model import FaceRig, Inbetween

VARIANTS = {
    "cm_y": dict(),
    "m_y": dict(meters_per_unit=1.0),
    "cm_z": dict(up_axis="Z"),
    # Blender-like: Z up, metres, a 0.01 scale and a rotation on a parent Xform, SkelRoot nested
    "blender": dict(up_axis="Z", meters_per_unit=1.0, parents=("root",), parent_scale=0.01,
                    parent_rotate_x_deg=90.0),
}


def grid_rig(name="Head", n=6, seed=0) -> FaceRig:
    """A small n x n grid (metres, around 1.6 m high) with a local shape, a dense shape and an inbetween."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.linspace(-0.05, 0.05, n), np.linspace(1.55, 1.65, n))
    pts = np.stack([x.ravel(), y.ravel(), 0.1 + 0.01 * rng.standard_normal(n * n)], 1)
    q = np.arange(n * n).reshape(n, n)[:-1, :-1].ravel()
    tris = np.concatenate([np.stack([q, q + 1, q + n + 1], 1), np.stack([q, q + n + 1, q + n], 1)])
    deltas = np.zeros((3, n * n, 3))
    deltas[0, :5] = 0.004 * rng.standard_normal((5, 3))            # local: sparse
    deltas[1] = 0.002 * rng.standard_normal((n * n, 3))            # moves everything: dense
    deltas[2, 3] = [0.0, -0.01, 0.0]
    half = Inbetween("half", 0.5, deltas[2] * 0.7)                 # non-linear: 70% at half weight
    return FaceRig(pts, tris, ["jawOpen", "cheekPuff", "eyeBlinkLeft"], deltas,
                   {"eyeBlinkLeft": [half]}, name=name)


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_round_trip_through_read_avatar(tmp_path, variant):
    rig = grid_rig()
    path = write_rig_usd([rig, grid_rig("Mouth", 4, seed=1)], tmp_path / "a.usda", **VARIANTS[variant])
    avatar = read_avatar(path)
    opts = VARIANTS[variant]
    assert avatar.up_axis == opts.get("up_axis", "Y")
    assert avatar.meters_per_unit == opts.get("meters_per_unit", 0.01)
    head = avatar.mesh("Head")
    assert head.names == rig.names and head.n_vertices == rig.n_vertices
    np.testing.assert_array_equal(head.triangles, rig.triangles)
    # float32 storage: ~1e-7 relative to the coordinates' magnitude in stage units
    np.testing.assert_allclose(head.neutral, rig.neutral, atol=2e-7)
    np.testing.assert_allclose(head.deltas, rig.deltas, atol=1e-8)
    ib = head.inbetweens["eyeBlinkLeft"]
    assert [b.weight for b in ib] == [0.5]
    np.testing.assert_allclose(ib[0].offsets, rig.inbetweens["eyeBlinkLeft"][0].offsets, atol=1e-8)
    for w in ([1, 0, 0.25], [0.3, 1, 0.5], [0, 0, 0.8]):
        np.testing.assert_allclose(head.evaluate(w), rig.evaluate(w), atol=3e-7)
    # sparse pointIndices only where a shape moves < 70% of the mesh
    assert [p is not None for p in head.source.point_indices] == [True, False, True]
    np.testing.assert_array_equal(head.source.point_indices[0], np.arange(5))


def test_blender_like_layout_and_metadata(tmp_path):
    from pxr import Usd, UsdGeom, UsdSkel

    path = write_rig_usd(grid_rig(), tmp_path / "b.usda", **VARIANTS["blender"])
    stage = Usd.Stage.Open(str(path))
    assert stage.GetDefaultPrim().GetPath() == "/root"
    assert UsdGeom.GetStageUpAxis(stage) == "Z" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    root = stage.GetPrimAtPath("/root/Avatar")
    assert root.IsA(UsdSkel.Root)
    ops = [op.GetOpName() for op in UsdGeom.Xformable(stage.GetPrimAtPath("/root")).GetOrderedXformOps()]
    assert ops == ["xformOp:rotateX", "xformOp:scale"]
    mesh = stage.GetPrimAtPath("/root/Avatar/Head")
    binding = UsdSkel.BindingAPI(mesh)
    assert binding.GetSkeletonRel().GetTargets() == ["/root/Avatar/Skel"]
    assert list(binding.GetBlendShapesAttr().Get()) == ["jawOpen", "cheekPuff", "eyeBlinkLeft"]
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/root/Avatar/Skel/Anim"))
    assert list(anim.GetBlendShapesAttr().Get()) == ["jawOpen", "cheekPuff", "eyeBlinkLeft"]
    # authored points are in the mesh's local space: x100 (the 0.01 scale), Y-up rotated to Z-up and back
    local = np.array(UsdGeom.Mesh(mesh).GetPointsAttr().Get())
    assert 150 < np.abs(local).max() < 170


def test_agrees_with_pixar_blend_shape_query(tmp_path):
    from pxr import Usd, UsdSkel, Vt

    rig = grid_rig()
    path = write_rig_usd(rig, tmp_path / "q.usda", meters_per_unit=1.0)
    stage = Usd.Stage.Open(str(path))
    mesh = stage.GetPrimAtPath("/Avatar/Head")
    query = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(mesh))
    weights = [0.4, 0.9, 0.3]
    sub_weights, shape_idx, sub_idx = query.ComputeSubShapeWeights(Vt.FloatArray(weights))
    points = mesh.GetAttribute("points").Get()
    assert query.ComputeDeformedPoints(sub_weights, shape_idx, sub_idx, query.ComputeBlendShapePointIndices(),
                                       query.ComputeSubShapePointOffsets(), points)
    np.testing.assert_allclose(np.array(points), rig.evaluate(weights), atol=2e-6)


def test_zero_shapes_and_shapeless_meshes(tmp_path):
    rig = grid_rig()
    rig.deltas[1] = 0.0
    eye = FaceRig(rig.neutral + [0.1, 0, 0], rig.triangles, [], np.zeros((0, rig.n_vertices, 3)),
                  name="EyeLeft")
    avatar = read_avatar(write_rig_usd([rig, eye], tmp_path / "z.usda"))
    assert avatar.mesh("Head").names == ["jawOpen", "eyeBlinkLeft"]    # an all-zero shape is not authored
    assert [m.name for m in avatar.meshes] == ["Head"]                  # the eye has no shapes (still bound)


def test_sparse_point_indices():
    d = np.zeros((2, 10, 3))
    d[0, [2, 7]] = 1.0
    d[1, 4] = 0.5   # an inbetween moving another point: the union is used
    np.testing.assert_array_equal(sparse_point_indices(d), [2, 4, 7])
    d[0, :8] = 1.0
    assert sparse_point_indices(d) is None


def test_refuses_to_overwrite_and_leaves_no_temp_files(tmp_path):
    path = write_rig_usd(grid_rig(), tmp_path / "a.usda")
    before = path.read_bytes()
    with pytest.raises(OutputExistsError, match="force"):
        write_rig_usd(grid_rig(seed=3), path)
    assert path.read_bytes() == before
    write_rig_usd(grid_rig(seed=3), path, force=True)
    assert path.read_bytes() != before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.usda"]


@pytest.mark.parametrize("break_it, error, words", [
    (lambda r: r.neutral.__setitem__((0, 0), np.nan), GeometryError, "NaN"),
    (lambda r: setattr(r, "name", "my head"), RigError, "prim name"),
    (lambda r: r.triangles.__setitem__((0, 0), 99), GeometryError, "out of range"),
    (lambda r: r.names.__setitem__(1, "jawOpen"), RigError, "duplicate"),
])
def test_bad_rigs_raise_and_write_nothing(tmp_path, break_it, error, words):
    rig = grid_rig()
    break_it(rig)
    out = tmp_path / "bad.usda"
    with pytest.raises(error, match=words) as info:
        write_rig_usd(rig, out)
    assert str(out) in str(info.value) and info.value.fix
    assert not out.exists()


def test_bad_options(tmp_path):
    with pytest.raises(InputFileError, match="up axis"):
        write_rig_usd(grid_rig(), tmp_path / "a.usda", up_axis="X")
    with pytest.raises(InputFileError, match="metersPerUnit"):
        write_rig_usd(grid_rig(), tmp_path / "a.usda", meters_per_unit=0.0)
    with pytest.raises(InputFileError, match="parent"):
        write_rig_usd(grid_rig(), tmp_path / "a.usda", parent_scale=0.01)
    with pytest.raises(InputFileError, match="prim name"):
        write_rig_usd(grid_rig(), tmp_path / "a.usda", root="/My Avatar")
    with pytest.raises(InputFileError):
        write_rig_usd(grid_rig(), tmp_path / "a.obj")
    assert list(tmp_path.iterdir()) == []


def test_written_file_passes_pixar_validators(tmp_path):
    from pxr import Usd, UsdValidation

    path = write_rig_usd([grid_rig(), grid_rig("Mouth", 4)], tmp_path / "v.usda", **VARIANTS["blender"])
    validators = [v for v in UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
                  if not v.GetMetadata().name.startswith("usdface")]
    errors = UsdValidation.ValidationContext(validators).Validate(Usd.Stage.Open(str(path)))
    assert [f"{e.GetName()}: {e.GetMessage()}" for e in errors] == []


def test_sparse_point_indices_at_the_threshold_is_dense():
    """Offsets on 7 of 10 points at the 0.7 threshold are written dense (None), on 6 sparse (their
    indices), an inbetween's points counting too."""
    from usdface.io.avatar_writer import sparse_point_indices

    off = np.zeros((2, 10, 3))
    off[0, :6, 0] = 1e-3
    np.testing.assert_array_equal(sparse_point_indices(off), np.arange(6))
    off[1, 8, 1] = 1e-3
    assert sparse_point_indices(off) is None


def test_a_triangle_index_equal_to_the_point_count_is_refused(tmp_path):
    rig = grid_rig()
    tris = rig.triangles.copy()
    tris[0, 0] = rig.n_vertices
    bad = FaceRig(rig.neutral, tris, rig.names, rig.deltas, name="Head")
    with pytest.raises(GeometryError, match="triangle indices out of range"):
        write_rig_usd([bad], tmp_path / "a.usda")
    assert not (tmp_path / "a.usda").exists()
