"""Author a fresh UsdSkel face asset from :class:`usdface.model.FaceRig` meshes.

The counterpart of :func:`usdface.io.usd_rig.read_avatar` for *new* files (the layered writer,
:mod:`usdface.io.layers`, is for overriding an existing avatar). Used by ``usdface sample`` to write the
sample avatar and its Blender-like / Z-up / metre variants, and by ``usdface fit`` to save a capture-mesh rig.

Layout written (``root="/Avatar"``, ``parents=()``)::

    /Avatar                 SkelRoot (defaultPrim)
      Skel                  Skeleton, one joint "root" (identity bind/rest), skel:animationSource -> Anim
        Anim                SkelAnimation: blendShapes = every shape name, blendShapeWeights = 0
      <mesh>                Mesh + SkelBindingAPI (skel:skeleton, rigid joint influence on "root",
                            skel:blendShapes, skel:blendShapeTargets), displayColor
        <shape>             BlendShape: offsets (+ pointIndices when sparse), inbetweens

With ``parents=("root",)`` the SkelRoot is nested as ``/root/Avatar`` and the first parent Xform carries
``xformOp:rotateX`` and ``xformOp:scale`` (``parent_rotate_x_deg``, ``parent_scale``): the shape of a
Blender export (Z up, metersPerUnit 1, a 0.01 scale and a rotation on the transforms).

Units: the rig is in the internal frame (metres, Y up). A world point ``p`` (internal) is authored as the
stage point ``R_up^T p / metersPerUnit`` mapped through the inverse of the parents' local-to-world
transform, so that :func:`usdface.io.usd_rig.read_avatar` gives back the internal points.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import GeometryError, InputFileError, RigError
from ..model import FaceRig
from .usd_rig import gf_matrix_to_numpy, stage_to_internal

__all__ = ["write_rig_usd", "sparse_point_indices", "DEFAULT_COLORS"]

#: displayColor per mesh name (others get a neutral grey).
DEFAULT_COLORS = {"Head": (0.82, 0.66, 0.56), "Mouth": (0.75, 0.38, 0.40),
                  "EyeLeft": (0.93, 0.93, 0.90), "EyeRight": (0.93, 0.93, 0.90)}


def sparse_point_indices(offsets: np.ndarray, threshold: float = 0.7) -> np.ndarray | None:
    """Points a shape moves, or None when it moves at least ``threshold`` of the mesh (write it dense).

    ``offsets[m, n, 3]`` stacks the primary offsets and the inbetweens' offsets of one shape; a point is
    moved when any of them is non-zero (exactly). Returns sorted ``int32`` indices.
    """
    moved = np.flatnonzero(np.any(offsets != 0.0, axis=(0, 2)))
    if moved.size >= threshold * offsets.shape[1]:
        return None
    return moved.astype(np.int32)


def _check_rigs(rigs: list[FaceRig], path: Path, root: str) -> None:
    from pxr import Sdf

    names = [r.name for r in rigs]
    for r in rigs:
        if not Sdf.Path.IsValidIdentifier(r.name):
            raise RigError(f"mesh name {r.name!r} is not a valid USD prim name", path=path,
                           fix="give every FaceRig a name made of letters, digits and '_'")
        if r.n_vertices == 0 or len(r.triangles) == 0:
            raise GeometryError(f"mesh {r.name!r} is empty", path=path, prim=f"{root}/{r.name}",
                                fix="pass meshes with points and triangles")
        if not (np.isfinite(r.neutral).all() and np.isfinite(r.deltas).all()):
            raise GeometryError(f"mesh {r.name!r} has NaN/inf points or offsets", path=path,
                                prim=f"{root}/{r.name}", fix="repair the rig before writing it")
        if r.triangles.min() < 0 or r.triangles.max() >= r.n_vertices:
            raise GeometryError(f"mesh {r.name!r} has triangle indices out of range", path=path,
                                prim=f"{root}/{r.name}", fix="repair the triangles")
        if len(set(r.names)) != len(r.names):
            raise RigError(f"mesh {r.name!r} has duplicate shape names", path=path, prim=f"{root}/{r.name}",
                           fix="give every shape a unique name")
    if len(set(names)) != len(names) or "Skel" in names:
        raise RigError(f"mesh names must be unique and not 'Skel': {names}", path=path,
                       fix="rename the meshes")


def _stage_matrix(up_axis: str, meters_per_unit: float) -> np.ndarray:
    """[3,3] internal (metres, Y up) -> stage world coordinates."""
    return np.linalg.inv(stage_to_internal(up_axis, meters_per_unit)[:3, :3])


def write_rig_usd(rigs, path, *, up_axis: str = "Y", meters_per_unit: float = 0.01, root: str = "/Avatar",
                  parents=(), parent_scale: float = 1.0, parent_rotate_x_deg: float = 0.0,
                  sparse_threshold: float = 0.7, force: bool = False, layer_data: dict | None = None) -> Path:
    """Write ``rigs`` (one :class:`FaceRig` or a list, one Mesh each) as a new UsdSkel asset at ``path``.

    Parameters
    ----------
    rigs : FaceRig or list of FaceRig; ``rig.name`` is the Mesh prim name; points metres, Y up (internal).
    path : ``.usda`` / ``.usdc`` / ``.usd`` output; written atomically, refused if it exists unless ``force``.
    up_axis, meters_per_unit : stage metadata; points and offsets are converted to them.
    root : SkelRoot prim path's last component (``"/Avatar"``); it is nested under ``parents`` (Xform names).
    parent_scale, parent_rotate_x_deg : uniform scale and X rotation on the first parent (needs ``parents``).
    sparse_threshold : a shape moving fewer than this fraction of the points gets ``pointIndices``.
    layer_data : the root layer's ``customLayerData`` (plain values), e.g. what wrote the file.

    Shapes whose offsets (and inbetweens) are all exactly zero on a mesh are not authored on that mesh.
    Returns the written path.
    """
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt

    from .layers import atomic_save, check_output_path

    path = check_output_path(path, force, over_avatar=False)       # an avatar of its own, no layer over one
    rigs = [rigs] if isinstance(rigs, FaceRig) else list(rigs)
    if not rigs:
        raise RigError("nothing to write: no meshes", path=path, fix="pass at least one FaceRig")
    if up_axis not in ("Y", "Z"):
        raise InputFileError(f"unsupported up axis {up_axis!r}", path=path, fix="use 'Y' or 'Z'")
    if not (np.isfinite(meters_per_unit) and meters_per_unit > 0):
        raise InputFileError(f"invalid metersPerUnit {meters_per_unit!r}", path=path,
                             fix="use a positive number such as 0.01 (cm) or 1 (m)")
    parents = [str(p) for p in parents]
    bad = [n for n in parents + [root.strip("/")] if not Sdf.Path.IsValidIdentifier(n)]
    if bad:
        raise InputFileError(f"invalid prim name(s) for the SkelRoot or its parents: {bad}", path=path,
                             fix="use simple names such as root='/Avatar', parents=('root',)")
    if (parent_scale != 1.0 or parent_rotate_x_deg != 0.0) and not parents:
        raise InputFileError("parent_scale / parent_rotate_x_deg need a parent Xform", path=path,
                             fix="pass parents=('root',)")
    skel_root_path = Sdf.Path("/" + "/".join(parents + [root.strip("/")]))
    _check_rigs(rigs, path, str(skel_root_path))

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up_axis == "Y" else UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, float(meters_per_unit))
    prefix = Sdf.Path.absoluteRootPath
    for i, name in enumerate(parents):
        prefix = prefix.AppendChild(name)
        xf = UsdGeom.Xform.Define(stage, prefix)
        if i == 0 and (parent_rotate_x_deg != 0.0 or parent_scale != 1.0):
            xf.AddRotateXOp().Set(float(parent_rotate_x_deg))
            xf.AddScaleOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(float(parent_scale)))
    skel_root = UsdSkel.Root.Define(stage, skel_root_path)
    top = stage.GetPrimAtPath("/" + (parents[0] if parents else root.strip("/")))
    stage.SetDefaultPrim(top)
    if layer_data:
        stage.GetRootLayer().customLayerData = dict(layer_data)

    # internal -> stage: inverse up axis / units; world (stage units) -> local: inverse of the parents' xform
    local_to_world = gf_matrix_to_numpy(
        UsdGeom.Xformable(skel_root).ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
    world_to_local = np.linalg.inv(local_to_world)
    lin = world_to_local[:3, :3] @ _stage_matrix(up_axis, meters_per_unit)
    trans = world_to_local[:3, 3]

    def to_points(p):
        return p @ lin.T + trans

    def to_offsets(d):
        return d @ lin.T

    skel = UsdSkel.Skeleton.Define(stage, skel_root_path.AppendChild("Skel"))
    skel.CreateJointsAttr(Vt.TokenArray(["root"]))
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
    all_names: list[str] = []

    for rig in rigs:
        mesh = UsdGeom.Mesh.Define(stage, skel_root_path.AppendChild(rig.name))
        pts = to_points(rig.neutral)
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts.astype(np.float32)))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(rig.triangles), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(rig.triangles.astype(np.int32).ravel()))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        f32 = pts.astype(np.float32)
        mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, f32.min(0))),
                                             Gf.Vec3f(*map(float, f32.max(0)))]))
        color = DEFAULT_COLORS.get(rig.name, (0.7, 0.7, 0.7))
        mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(Vt.Vec3fArray([Gf.Vec3f(*color)]))
        binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
        binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
        binding.CreateJointIndicesPrimvar(constant=True, elementSize=1).Set(Vt.IntArray([0]))
        binding.CreateJointWeightsPrimvar(constant=True, elementSize=1).Set(Vt.FloatArray([1.0]))
        binding.CreateGeomBindTransformAttr().Set(Gf.Matrix4d(1))
        tokens, targets = [], []
        for k, name in enumerate(rig.names):
            ibs = sorted(rig.inbetweens.get(name, []), key=lambda b: b.weight)
            stack = np.stack([rig.deltas[k]] + [np.asarray(b.offsets, np.float64) for b in ibs])
            if not np.any(stack != 0.0):
                continue
            prim_name = name if Sdf.Path.IsValidIdentifier(name) else f"shape_{k}"
            shape = UsdSkel.BlendShape.Define(stage, mesh.GetPath().AppendChild(prim_name))
            idx = sparse_point_indices(stack, sparse_threshold)
            sel = slice(None) if idx is None else idx
            shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(to_offsets(rig.deltas[k][sel]).astype(np.float32)))
            if idx is not None:
                shape.CreatePointIndicesAttr(Vt.IntArray.FromNumpy(idx))
            for j, ib in enumerate(ibs):
                ib_name = ib.name if Sdf.Path.IsValidIdentifier(ib.name) else f"inbetween_{j}"
                inb = shape.CreateInbetween(ib_name)
                inb.SetWeight(float(ib.weight))
                inb.SetOffsets(Vt.Vec3fArray.FromNumpy(
                    to_offsets(np.asarray(ib.offsets, np.float64)[sel]).astype(np.float32)))
            tokens.append(name)
            targets.append(shape.GetPath())
            if name not in all_names:
                all_names.append(name)
        binding.CreateBlendShapesAttr(Vt.TokenArray(tokens))
        binding.CreateBlendShapeTargetsRel().SetTargets(targets)

    anim = UsdSkel.Animation.Define(stage, skel.GetPath().AppendChild("Anim"))
    anim.CreateBlendShapesAttr(Vt.TokenArray(all_names))
    anim.CreateBlendShapeWeightsAttr(Vt.FloatArray(len(all_names)))
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
    atomic_save(stage.GetRootLayer(), path, force)
    return path
