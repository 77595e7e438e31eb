"""UsdSkel avatars -> :class:`usdface.model.Avatar` (one :class:`FaceRig` per skinned mesh with blend shapes).

What is read, the UsdSkel way:

* every ``SkelRoot`` of the stage; its skeleton bindings are resolved with ``UsdSkel.Cache`` (so bindings
  inherited down namespace work), plus any mesh under a SkelRoot that has blend shapes but no skeleton (kept,
  with a note: no client will animate it);
* per mesh: ``skel:blendShapes`` (channel tokens) and ``skel:blendShapeTargets`` (BlendShape prims, a list
  or Blender's single target), dense or sparse ``pointIndices`` (int[] or uint[]), inbetweens (any weight
  except 0 and 1, negative included), ``normalOffsets`` (kept verbatim in :class:`MeshSource` for the writer);
* geometry: points at the default time (time-sampled only: the first sample, with a warning), polygons
  fan-triangulated (the authored ``faceVertexCounts/Indices``
  are kept), and the mesh's full local-to-world transform (every ancestor), the stage's ``metersPerUnit`` and
  ``upAxis`` folded into ``MeshSource.to_internal`` so the rig is in usdface's internal frame: metres, Y up;
* meshes without blend shapes under a SkelRoot (eyes, teeth, props): points and fan triangles only, placed
  the same way, in ``Avatar.metadata["static_meshes"] = {prim path: (points[n,3] internal metres,
  triangles[t,3])}`` (the eyelid repair needs the eyeballs); an unusable one is skipped with a note;
* names: channel tokens mapped to the ARKit 52 with :func:`usdface.arkit.match_names` (a studio name map
  first, then the spellings studios ship: ``eye_blink_left``, ``Eye_Blink_L``, Character Creator names, DCC
  suffixes and node prefixes such as ``eyeBlinkLeft.001`` / ``blendShape1.eyeBlinkLeft``), the BlendShape
  prim name as fallback (Blender renames a second mesh's tokens ``eyeBlinkLeft2``...); how every channel was
  mapped is recorded in ``Avatar.name_report``; of two channels meaning one shape the better mapping keeps it.

Every malformed input raises a :class:`usdface.errors.UsdFaceError` subclass naming the file, the prim and the
fix; nothing is half-read.

Example::

    from usdface.io.usd_rig import read_avatar
    avatar = read_avatar("avatar.usdc")
    head = avatar.mesh("Head")          # FaceRig: neutral[n,3] metres Y-up, deltas[K,n,3]
    weights = np.zeros(head.n_shapes); weights[head.index("jawOpen")] = 1.0
    points = head.evaluate(weights)     # [n,3] metres, Y up
    avatar.name_report                  # {"/Avatar/Mouth": {"inexact": [["eyeBlinkLeft2", ...]], ...}}
"""

from __future__ import annotations

import math
import os
import re
import shlex
import stat
from pathlib import Path

import numpy as np

from .. import arkit
from ..errors import AlreadyPersonalizedError, GeometryError, InputFileError, RigError, UsdFaceError, warn
from ..model import Avatar, FaceRig, Inbetween, MeshSource
from .file_kind import Kind
from .file_kind import plain as _plain
from .mesh_io import fan_triangulate

#: Root-layer metadata that describes how to interpret the stage; a layer written over the avatar repeats it.
#: Variant set (on each SkelRoot) switching the skel binding between personalized and generic shapes
#: (authored by :func:`usdface.io.layers.write_avatar_layer`).
PERSONALIZATION_VARIANT_SET = "usdfacePersonalization"
STAGE_METADATA_KEYS = ("upAxis", "metersPerUnit", "defaultPrim", "startTimeCode", "endTimeCode",
                       "timeCodesPerSecond", "framesPerSecond", "kilogramsPerUnit")

# A rotation taking Z-up world coordinates to Y-up: (x, y, z) -> (x, z, -y) (right-handed, -90 deg about X).
_Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def up_axis_rotation(up_axis: str) -> np.ndarray:
    """``R[3,3]`` rotating a stage's world frame with the given up axis ("Y" or "Z") to Y up."""
    if up_axis == "Y":
        return np.eye(3)
    if up_axis == "Z":
        return _Z_UP_TO_Y_UP.copy()
    raise ValueError(f"unsupported up axis {up_axis!r}")


def stage_to_internal(up_axis: str, meters_per_unit: float) -> np.ndarray:
    """``M[4,4]`` (column vectors) mapping stage world coordinates to internal metres, Y up."""
    m = np.eye(4)
    m[:3, :3] = up_axis_rotation(up_axis) * float(meters_per_unit)
    return m


def gf_matrix_to_numpy(matrix) -> np.ndarray:
    """A ``Gf.Matrix4d`` (USD row-vector convention, ``p' = p M``) as a column-vector ``[4,4]`` array."""
    return np.array(matrix, dtype=np.float64).reshape(4, 4).T


#: Relative deviation (float32 export noise: ~2 ulps) within which a transform counts as an exact one.
SNAP_TOLERANCE = 2e-7


def snap_transform(matrix, tolerance: float = SNAP_TOLERANCE) -> tuple[np.ndarray, float]:
    """Remove float32 export noise from a ``[4,4]`` (column-vector) transform's linear part.

    DCCs write rotations and scales as float32 (Blender 5.0: ``rotateXYZ`` 89.99999237 instead of 90, scale
    0.0099999988 on X and 0.0099999998 on Y/Z), so a re-exported avatar sits up to ~2e-7 m (at 1.6 m) away
    from the original, below the float32 resolution of its points but enough for the non-rigid registration to
    amplify it. When the linear part is, within ``tolerance`` relative per element, a uniform scale ``s``
    times an axis permutation with signs, it is replaced by that exact transform, with ``s`` rounded to 6
    significant digits when that is also within ``tolerance``. Anything else (a real rotation, a non-uniform
    scale) is returned unchanged. Returns ``(matrix[4,4], largest relative change of an element)``.
    """
    m = np.array(matrix, dtype=np.float64)
    linear = m[:3, :3]
    if not np.isfinite(m).all():
        return m, 0.0
    det = float(np.linalg.det(linear))
    if det == 0.0:
        return m, 0.0
    scale = abs(det) ** (1.0 / 3.0)
    axes = np.round(linear / scale)
    if not (np.abs(axes).sum(axis=0) == 1).all() or not (np.abs(axes).sum(axis=1) == 1).all():
        return m, 0.0
    if np.abs(linear / scale - axes).max() > tolerance:
        return m, 0.0
    rounded = float(f"{scale:.6g}")
    if abs(rounded - scale) <= tolerance * scale:
        scale = rounded
    exact = axes * scale
    change = float(np.abs(exact - linear).max() / scale)
    m[:3, :3] = exact
    if np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() <= tolerance:  # geomBindTransform's 1.0000000000000002
        change = max(change, float(np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max()))
        m[3] = [0.0, 0.0, 0.0, 1.0]
    return m, change


def _open_stage(path: Path, what: str = "avatar"):
    """The stage of ``path``; a missing or unreadable file is named as ``what`` (an avatar, a layer, ...)."""
    from .usd_open import open_usd_stage

    return open_usd_stage(path, what, "pass the avatar's .usd/.usda/.usdc file" if what == "avatar"
                          else "check the path (a .usd/.usda/.usdc file)")


def read_stage_metadata(stage, path) -> dict:
    """The authored root-layer metadata of ``STAGE_METADATA_KEYS`` plus resolved ``upAxis``/``metersPerUnit``.

    Raises InputFileError for an unsupported up axis or non-positive / non-finite metersPerUnit.
    """
    from pxr import UsdGeom

    root = stage.GetRootLayer()
    authored = {}
    for key in STAGE_METADATA_KEYS:
        if root.pseudoRoot.HasInfo(key):
            value = root.pseudoRoot.GetInfo(key)
            authored[key] = str(value) if key in ("upAxis", "defaultPrim") else value
    up = str(UsdGeom.GetStageUpAxis(stage))
    if up not in ("Y", "Z"):
        raise InputFileError(f"unsupported upAxis {up!r}", path=path,
                             fix='set the stage upAxis to "Y" or "Z"')
    mpu = float(UsdGeom.GetStageMetersPerUnit(stage))
    if not math.isfinite(mpu) or mpu <= 0:
        raise InputFileError(f"invalid metersPerUnit {mpu!r}", path=path,
                             fix="set the stage metersPerUnit to the size of one unit in metres (cm: 0.01)")
    return {"authored": authored, "upAxis": up, "metersPerUnit": mpu,
            "metersPerUnitAuthored": stage.HasAuthoredMetadata("metersPerUnit"),
            "upAxisAuthored": stage.HasAuthoredMetadata("upAxis")}


def _array(value, dtype, width, what, path, prim) -> np.ndarray:
    """A Vt array as numpy ``[m, width]`` (or ``[m]``), raising RigError on a wrong shape."""
    if value is None:
        return np.zeros((0, width) if width else 0, dtype=dtype)
    try:
        arr = np.array(value, dtype=dtype)
        if width:
            arr = arr.reshape(-1, width)
        else:
            arr = arr.reshape(-1)
    except (ValueError, TypeError):
        raise RigError(f"{what} has an unexpected type or shape", path=path, prim=prim,
                       fix=f"author {what} with the UsdSkel/UsdGeom type") from None
    return arr


def time_sampled_only(attr) -> bool:
    """True when ``attr`` has time samples but no default value, as a cache export writes every attribute.
    UsdSkel reads a blend shape's arrays (``offsets``, ``pointIndices``, ``normalOffsets``, inbetweens) and
    the channel names ``skel:blendShapes`` at the default time only, so such an attribute is unauthored to it;
    usdface reads the rest mesh's topology there too. ``usdface check`` uses the same test."""
    return bool(attr) and attr.GetNumTimeSamples() > 0 and attr.Get() is None


def _default_only(attr, what, path, prim, error=None):
    """Refuse ``attr`` (named ``what``) authored only as time samples (:func:`time_sampled_only`): it reads as
    empty at the default time, and the error that followed named a count mismatch ('71 offsets but 0
    pointIndices') or a mesh without faces instead of the time samples."""
    if time_sampled_only(attr):
        raise (error or RigError)(
            f"{what} are time-sampled only ({attr.GetNumTimeSamples()} sample(s)), with no default value: "
            f"{TIME_SAMPLED_READS.get(what, 'UsdSkel reads the default (they are uniform)')}",
            path=path, prim=prim, fix=time_sampled_fix(what))


def time_sampled_fix(what: str) -> str:
    """The fix for ``what`` authored only as time samples (the reader's refusal and ``check``'s error)."""
    return (f"author {what} as a default value, not time samples (a cache export's setting: export the rest "
            "pose or mark the attribute static)")


TIME_SAMPLED_READS = {"faceVertexCounts": "usdface reads the rest mesh's topology at the default time",
                      "faceVertexIndices": "usdface reads the rest mesh's topology at the default time"}


def _check_finite(arr, what, path, prim):
    if arr.size and not np.isfinite(arr).all():
        bad = int(np.flatnonzero(~np.isfinite(arr).reshape(len(arr), -1).all(axis=1))[0])
        raise GeometryError(f"{what} contains NaN/inf (first at element {bad})", path=path, prim=prim,
                            fix="fix or re-export the asset; usdface cannot use non-finite values")


def _check_indices(idx, n, what, path, prim):
    if idx.size == 0:
        return
    if idx.min() < 0 or idx.max() >= n:
        bad = int(idx[(idx < 0) | (idx >= n)][0])
        raise RigError(f"{what} has index {bad} outside the mesh's {n} points", path=path, prim=prim,
                       fix="re-export the blend shape for this mesh")
    if idx.size > 1 and np.bincount(idx, minlength=n).max() > 1:          # O(n + k), no sort
        raise RigError(f"{what} repeats point indices", path=path, prim=prim,
                       fix="list each point at most once in pointIndices")


def _mesh_geometry(mesh_prim, path):
    """points[n,3] float64 (local, authored units), counts, indices, triangles[t,3]."""
    from pxr import Usd, UsdGeom

    prim = str(mesh_prim.GetPath())
    mesh = UsdGeom.Mesh(mesh_prim)
    attr = mesh.GetPointsAttr()
    points = _array(attr.Get(Usd.TimeCode.Default()), np.float64, 3, "points", path, prim)
    samples = attr.GetTimeSamples() if len(points) == 0 else []
    if len(points) == 0 and samples:
        # a cache export: the points only time-sampled; the first sample is taken as the rest pose

        points = _array(attr.Get(samples[0]), np.float64, 3, "points", path, prim)
        warn(f"{path}, prim {prim}: points have no default value, only {len(samples)} time "
             f"sample(s): the sample at time {samples[0]:g} is read as the rest pose (author the "
             "rest points as a default value to choose it)")
    if len(points) == 0:
        raise GeometryError("mesh has no points (at the default time)", path=path, prim=prim,
                            fix="author the rest-pose points as a default (non time-sampled) value")
    _check_finite(points, "points", path, prim)
    for topology in (mesh.GetFaceVertexCountsAttr(), mesh.GetFaceVertexIndicesAttr()):
        _default_only(topology, topology.GetName(), path, prim, GeometryError)
    counts = _array(mesh.GetFaceVertexCountsAttr().Get(Usd.TimeCode.Default()), np.int64, 0,
                    "faceVertexCounts", path, prim)
    indices = _array(mesh.GetFaceVertexIndicesAttr().Get(Usd.TimeCode.Default()), np.int64, 0,
                     "faceVertexIndices", path, prim)
    if counts.size == 0:
        raise GeometryError("mesh has no faces", path=path, prim=prim,
                            fix="author faceVertexCounts and faceVertexIndices")
    if counts.min() < 3:
        face = int(np.flatnonzero(counts < 3)[0])
        raise GeometryError(f"face {face} has {int(counts[face])} vertices; a polygon needs at least 3",
                            path=path, prim=prim,
                            fix="remove degenerate faces (or triangulate) and re-export")
    if int(counts.sum()) != indices.size:
        raise GeometryError(f"faceVertexCounts sum to {int(counts.sum())} but there are {indices.size} "
                            "faceVertexIndices", path=path, prim=prim, fix="re-export the mesh topology")
    if indices.min() < 0 or indices.max() >= len(points):
        raise GeometryError(f"faceVertexIndices reference points outside 0..{len(points) - 1}", path=path,
                            prim=prim, fix="re-export the mesh topology")
    return points, counts, indices, fan_triangulate(counts, indices)


def outward_triangles(triangles: np.ndarray, mesh_prim, linear: np.ndarray) -> np.ndarray:
    """``triangles`` wound counter-clockwise seen from outside in the internal frame (right-handed, what
    normals, glTF and OBJ assume): reversed for a mesh whose ``orientation`` is ``leftHanded`` (its faces
    wind clockwise) or whose placement ``linear`` mirrors (negative determinant), not for both."""
    from pxr import UsdGeom

    left = UsdGeom.Mesh(mesh_prim).GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded
    return triangles[:, ::-1].copy() if left != bool(np.linalg.det(linear) < 0) else triangles


def _mesh_to_internal(mesh_prim, stage_meta, skinning=None, snapped: list | None = None) -> np.ndarray:
    """``to_internal[4,4]``: mesh-local authored coordinates -> internal metres, Y up (column vectors).

    A mesh skinned by a Skeleton is placed the UsdSkel way, ignoring its own and its ancestors' xformOps:
    ``world = Skeleton local-to-world * geomBindTransform`` (the bind pose). Any other mesh uses its full
    local-to-world transform (every ancestor). Composed in double precision (``Gf.Matrix4d``). With a
    ``snapped`` list, float32 export noise is removed (:func:`snap_transform`) and ``(prim, change)`` appended
    when that changed the matrix.
    """
    from pxr import Usd, UsdGeom

    if skinning is not None:
        query, skel_prim = skinning
        bind = gf_matrix_to_numpy(query.GetGeomBindTransform(Usd.TimeCode.Default()))
        skel_to_world = gf_matrix_to_numpy(
            UsdGeom.Xformable(skel_prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
        local_to_world = skel_to_world @ bind
    else:
        local_to_world = gf_matrix_to_numpy(
            UsdGeom.Xformable(mesh_prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
    to_internal = stage_to_internal(stage_meta["upAxis"], stage_meta["metersPerUnit"]) @ local_to_world
    if snapped is not None:
        to_internal, change = snap_transform(to_internal)
        if change > 0:
            snapped.append((str(mesh_prim.GetPath()), change))
    return to_internal


def _read_mesh(stage, mesh_prim, path, stage_meta, skel_root, skeleton, animation, file_label,
               skinning=None, snapped: list | None = None, name_map: dict | None = None,
               moving_only: bool = False, shapes: bool = True) -> tuple:
    """One mesh with blend shapes -> (FaceRig, name-report entry); ``skinning`` = (SkinningQuery, Skeleton
    prim) when joint influences bind it to a skeleton; ``shapes=False``: no offsets read (see
    :func:`read_avatar`)."""
    from pxr import UsdSkel

    prim = str(mesh_prim.GetPath())
    binding = UsdSkel.BindingAPI(mesh_prim)
    _default_only(binding.GetBlendShapesAttr(), "skel:blendShapes", path, prim)
    tokens_value = binding.GetBlendShapesAttr().Get()
    tokens = [str(t) for t in tokens_value] if tokens_value is not None else []
    targets = [str(t) for t in binding.GetBlendShapeTargetsRel().GetForwardedTargets()]
    if len(tokens) != len(targets):
        raise RigError(f"skel:blendShapes has {len(tokens)} entries but skel:blendShapeTargets has "
                       f"{len(targets)}", path=path, prim=prim,
                       fix="give exactly one BlendShape target per channel token, in the same order")
    if len(set(tokens)) != len(tokens):
        dup = sorted({t for t in tokens if tokens.count(t) > 1})
        raise RigError(f"duplicate shape names in skel:blendShapes: {', '.join(dup)}", path=path, prim=prim,
                       fix="give every blend shape channel a unique name")
    points, counts, indices, triangles = _mesh_geometry(mesh_prim, path)
    n = len(points)
    to_internal = _mesh_to_internal(mesh_prim, stage_meta, skinning, snapped)
    if not np.isfinite(to_internal).all() or abs(np.linalg.det(to_internal[:3, :3])) < 1e-300:
        raise GeometryError("the mesh's world transform is singular or not finite", path=path, prim=prim,
                            fix="fix the xformOps of the mesh and its ancestors")
    linear = to_internal[:3, :3]
    neutral = points @ linear.T + to_internal[:3, 3]
    triangles = outward_triangles(triangles, mesh_prim, linear)

    shape_prims = [stage.GetPrimAtPath(t) for t in targets]
    match = arkit.match_names(tokens, fallbacks=[p.GetName() if p else None for p in shape_prims],
                              name_map=name_map, resolve=True)
    if match.duplicates:  # only when a channel left unmapped is itself named as another channel's shape
        clash = [t for t, c in zip(tokens, match.canonical, strict=True) if c in match.duplicates]
        raise RigError(f"shape names map to the same ARKit shape twice: {', '.join(match.duplicates)} "
                       f"(tokens {', '.join(clash)})", path=path, prim=prim,
                       fix="rename or remove the duplicate blend shapes, or fix the --name-map")

    sparse = []                           # per shape: (indices or None, offsets[k,3] internal metres)
    point_indices, normal_offsets, inbetweens = [], [], {}
    for k, (target, shape_prim) in enumerate(zip(targets, shape_prims, strict=True)):
        if not shape_prim or not shape_prim.IsA(UsdSkel.BlendShape):
            raise RigError(f"blend shape target {target} of channel {tokens[k]!r} is missing or not a "
                           "BlendShape", path=path, prim=prim,
                           fix="point skel:blendShapeTargets at BlendShape prims")
        if not shapes:
            continue
        shape = UsdSkel.BlendShape(shape_prim)
        idx_attr = shape.GetPointIndicesAttr()
        for attr, what in ((idx_attr, "pointIndices"), (shape.GetOffsetsAttr(), "offsets"),
                           (shape.GetNormalOffsetsAttr(), "normalOffsets")):
            _default_only(attr, what, path, target)
        idx = None
        if idx_attr.HasAuthoredValue():
            idx = _array(idx_attr.Get(), np.int64, 0, "pointIndices", path, target)
        if shape.GetOffsetsAttr().HasAuthoredValue():
            offsets = _array(shape.GetOffsetsAttr().Get(), np.float64, 3, "offsets", path, target)
            _check_finite(offsets, "offsets", path, target)
        else:  # a normals-only shape (UsdSkel allows it): no point motion
            offsets = np.zeros((n if idx is None else len(idx), 3))
        if idx is not None:
            if len(idx) != len(offsets):
                raise RigError(f"{len(offsets)} offsets but {len(idx)} pointIndices", path=path, prim=target,
                               fix="give one offset per listed point index")
            _check_indices(idx, n, "pointIndices", path, target)
        else:
            if len(offsets) != n:
                raise RigError(f"{len(offsets)} offsets for a mesh of {n} points and no pointIndices",
                               path=path, prim=target,
                               fix="author one offset per point, or pointIndices listing the moved points")
        sparse.append((idx, offsets @ linear.T))
        normals_attr = shape.GetNormalOffsetsAttr()
        normals = None
        if normals_attr.HasAuthoredValue():
            normals = _array(normals_attr.Get(), np.float32, 3, "normalOffsets", path, target)
            if len(normals) != len(offsets):
                raise RigError(f"{len(normals)} normalOffsets but {len(offsets)} offsets", path=path,
                               prim=target, fix="give one normal offset per offset")
        point_indices.append(idx)
        normal_offsets.append(normals)
        ibs = []
        for ib in shape.GetInbetweens():
            ib_name = ib.GetAttr().GetName()
            weight = ib.GetWeight()
            if weight is None or not math.isfinite(weight) or weight in (0.0, 1.0):
                raise RigError(f"inbetween {ib_name} has invalid weight {weight!r}", path=path, prim=target,
                               fix="give each inbetween a finite weight other than 0 and 1")
            _default_only(ib.GetAttr(), f"{ib_name} offsets", path, target)
            _default_only(ib.GetNormalOffsetsAttr(), f"{ib_name} normalOffsets", path, target)
            ib_offsets = _array(ib.GetOffsets(), np.float64, 3, ib_name, path, target)
            _check_finite(ib_offsets, ib_name, path, target)
            if len(ib_offsets) != len(offsets):
                raise RigError(f"{ib_name} has {len(ib_offsets)} offsets, the shape {len(offsets)}",
                               path=path, prim=target,
                               fix="give the inbetween as many offsets as the primary shape")
            ib_normals = ib.GetNormalOffsets() if ib.GetNormalOffsetsAttr() else None
            ibs.append(Inbetween(ib_name.split(":", 1)[-1], float(weight), ib_offsets @ linear.T,
                                 None if ib_normals is None else np.array(ib_normals, dtype=np.float32)))
        if ibs:
            ws = [b.weight for b in ibs]
            if len(set(ws)) != len(ws):
                raise RigError("two inbetweens share a weight", path=path, prim=target,
                               fix="give each inbetween of a shape a distinct weight")
            inbetweens[match.canonical[k]] = ibs

    if not shapes:                        # every shape unread: a read-only zero array, no memory
        point_indices, normal_offsets = [None] * len(targets), [None] * len(targets)
    source = MeshSource(
        file=file_label, prim=prim, shape_prims=targets, channel_tokens=tokens, point_indices=point_indices,
        normal_offsets=normal_offsets, to_internal=to_internal, face_vertex_counts=counts,
        face_vertex_indices=indices, skel_root=skel_root, skeleton=skeleton, animation=animation)
    if shapes:
        neutral, triangles, deltas, peak = _place_offsets(source, neutral, triangles, sparse, inbetweens,
                                                          match.canonical, moving_only)
    else:
        deltas, peak = np.broadcast_to(np.zeros(3), (len(targets), n, 3)), None
    rig = FaceRig(neutral, triangles, match.canonical, deltas, inbetweens, source, mesh_prim.GetName())
    if peak is not None and rig.deltas.shape == deltas.shape:    # the peak motion the crop measured: kept
        rig.keep_peak(peak)
    report = {"inexact": [list(x) for x in match.inexact], "unknown": list(match.unknown),
              "missing": list(match.missing), "conflicts": [list(x) for x in match.conflicts],
              "channels": [list(x) for x in match.channels]}
    return rig, report


def _place_offsets(source, neutral, triangles, sparse, inbetweens, names, moving_only):
    """The rig's arrays from the shapes as read (``sparse``: per shape ``(indices or None, offsets[k,3])``,
    inbetween offsets in ``inbetweens`` aligned the same way, replaced in place by their placed form):
    ``(neutral, triangles, deltas[K,s,3], peak)`` on every vertex, or with ``moving_only`` on the part some
    shape or inbetween moves and its margin (:func:`usdface.submesh.moving_part`; the crop and the authored
    points outside it are recorded on ``source.region`` / ``source.residue``), never forming ``[K,n,3]`` for
    the rest. ``sparse`` is emptied as the shapes are placed. ``peak[n]``: the largest offset of each vertex
    over the shapes (:meth:`usdface.model.FaceRig.peak_motion` of ``deltas``, the same values) when the crop
    measured it on the whole mesh without inbetweens, else None."""
    from ..submesh import crop, moving_part, outside_offsets, peak_of_shapes

    n = len(neutral)
    ibs_of = [inbetweens.get(name, []) for name in names]
    sub = peak = None
    if moving_only and n:
        shapes = list(sparse) + [(idx, b.offsets) for (idx, _), ibs in zip(sparse, ibs_of, strict=True)
                                 for b in ibs]
        peak = peak_of_shapes(n, shapes)
        keep = moving_part(peak, neutral)
        if keep is not None:
            sub = crop(triangles, keep, neutral)
        if sub is not None or len(shapes) != len(sparse):        # another crop, or inbetweens in it
            peak = None
        del shapes
    vertices = np.arange(n) if sub is None else sub.vertices
    local = np.full(n, -1, dtype=np.int64)
    local[vertices] = np.arange(vertices.size)
    deltas = np.zeros((len(sparse), vertices.size, 3))
    residue = []
    for k, ((idx, off), ibs) in enumerate(zip(sparse, ibs_of, strict=True)):
        sparse[k] = None                  # each shape's read array freed once placed (one [K,n,3] at a time)
        rows = np.arange(n) if idx is None else idx
        at = local[rows]
        inside = at >= 0
        if sub is None and idx is None:
            deltas[k] = off
        elif sub is None:                 # every listed point kept: no masked copies of them
            deltas[k, at] = off
        else:
            deltas[k, at[inside]] = off[inside]
        rest = []
        for b in ibs:
            placed = np.zeros((vertices.size, 3))
            placed[at[inside]] = b.offsets[inside]
            rest.append(b.offsets[~inside])
            b.offsets = placed
        if sub is not None:
            residue.append(outside_offsets(rows[~inside], off[~inside], rest))
    if sub is None:
        return neutral, triangles, deltas, peak
    source.region, source.residue = sub, residue
    return neutral[sub.vertices], sub.triangles, deltas, None


def _skel_roots(stage):
    from pxr import Usd, UsdSkel

    return [p for p in stage.Traverse(Usd.TraverseInstanceProxies()) if p.IsA(UsdSkel.Root)]


def _has_blend_shapes(prim) -> bool:
    from pxr import UsdGeom, UsdSkel

    if not prim.IsA(UsdGeom.Mesh):
        return False
    binding = UsdSkel.BindingAPI(prim)
    tokens = binding.GetBlendShapesAttr()
    return bool((tokens.HasAuthoredValue() and len(tokens.Get() or []) > 0)
                or binding.GetBlendShapeTargetsRel().GetTargets())


def read_avatar(path, *, snap_transforms: bool = True, name_map=None, moving_only: bool = False,
                shapes: bool = True) -> Avatar:
    """Read a UsdSkel avatar: every skinned mesh with blend shapes, in internal metres / Y up.

    Parameters
    ----------
    path : .usd/.usda/.usdc file (the root layer of the avatar).
    snap_transforms : remove float32 export noise from the meshes' world transforms (:func:`snap_transform`;
        a DCC round trip then reads to the same numbers as the original); each snapped mesh gets a note.
    name_map : {studio channel: ARKit name} dict, or a JSON / CSV file of them
        (:func:`usdface.io.name_map.read_name_map`), validated before the file is opened; tried before the
        built-in spellings (:func:`usdface.arkit.match_name`).
    moving_only : keep each mesh with blend shapes only where some shape (or inbetween) moves it, with a
        margin, when that is at most half the mesh (:func:`usdface.submesh.moving_part`): the rig's
        neutral, triangles and deltas are those of the sub-mesh, ``rig.source.region`` the
        :class:`usdface.submesh.SubMesh` (full-mesh indices, vertex count and points) and
        ``rig.source.residue`` the authored float noise outside it; the file's sparse ``pointIndices`` are
        never made dense for the rest of the mesh. What ``personalize`` reads (a full-body mesh whose face
        shapes move 5 % of it costs about 5 %).
    shapes : ``False``: the meshes' neutral, triangles and channel names only, no shape's offsets read (a
        picture of the neutral: ``render --landmarks``); each rig's ``deltas`` is a read-only array of zeros
        that holds no memory, and its inbetweens are empty. The channels and their targets are checked as
        always.

    Returns
    -------
    Avatar with one FaceRig per mesh (``neutral[n,3]`` metres, ``deltas[K,n,3]`` metres, canonical ARKit names
    where the channel maps to one, inbetweens by name), ``up_axis``, ``meters_per_unit``, ``default_prim``,
    ``metadata`` (``stage``: the root layer's authored stage metadata, ``notes``: non-fatal findings,
    ``static_meshes``: {prim path: (points[n,3] metres Y up, triangles[t,3])} for every mesh under a SkelRoot
    without blend shapes, ``static_to_internal``: {prim path: to_internal[4,4]} their placements) and
    ``name_report`` (mesh prim path -> {inexact: [[token, canonical, how]], unknown, missing, conflicts:
    [[token, canonical, kept token]], channels: [[token, canonical or None, how]] for every channel}). When
    two channels of a mesh mean the same ARKit shape the better mapping keeps it (exact, name map,
    spelling, ...: :func:`usdface.arkit.match_names`) and the other keeps its own name, with a note.

    Raises
    ------
    InputFileError (missing/unreadable file, bad units or up axis), RigError (no SkelRoot, no blend shapes,
    inconsistent arrays, duplicate names), GeometryError (empty mesh, NaN/inf, bad faces).
    """
    from pxr import Tf

    from .name_map import read_name_map

    name_map = read_name_map(name_map)
    path = Path(path)
    stage = _open_stage(path)
    if name_map is None:                       # a usdface layer over a studio-named avatar carries its map
        name_map = recorded_name_map(stage)
    try:
        return _read_avatar_stage(stage, path, snap_transforms, name_map, moving_only, shapes)
    except UsdFaceError as exc:
        _refuse_revised_avatar(stage, path, exc)
        raise
    except (Tf.ErrorException, ValueError, TypeError, IndexError, KeyError) as exc:
        _refuse_revised_avatar(stage, path, exc)
        from .usd_open import tf_error_text

        what = tf_error_text(exc, path, 200) if isinstance(exc, Tf.ErrorException) else str(exc).strip()[:200]
        raise RigError(f"malformed UsdSkel data ({type(exc).__name__}: {what})", path=path,
                       fix="re-export the avatar; run `usdface inspect` on it for details") from None


def _refuse_revised_avatar(stage, path: Path, exc: Exception) -> None:
    """A usdface layer the reader refused because its avatar was revised after it was written (a shape added
    or removed: 'skel:blendShapes has 53 entries but skel:blendShapeTargets has 52', fix 'give exactly one
    BlendShape target per channel token', which is no fix for a published layer): that is said instead,
    with the fix (re-run personalize on the revised avatar). Returns for any other refusal."""
    from .layers import avatar_mismatches

    try:
        found = avatar_mismatches(stage)
    except Exception:  # noqa: BLE001  (the reader's own error stands)
        return
    if found:
        prim, message, fix = found[0]
        raise RigError(message, path=path, prim=None if prim == "/" else prim, fix=fix) from exc


#: What :func:`_refuse_non_avatar` says of each kind that is no avatar, and its fix.
_NOT_AVATAR = {
    Kind.CAPTURE: (
        "a usdface capture (written by 'usdface capture import/select'), not an avatar",
        "pass the avatar's file where an avatar is expected (personalize: AVATAR, then CAPTURE)"),
    Kind.TAKE: (
        "a usdface take (a recording), not an avatar",
        "pass the avatar's .usd file; a take goes where a capture goes ('personalize AVATAR TAKE', "
        "'fit TAKE', 'capture select TAKE') or to 'personalize AVATAR CAPTURE --take TAKE'"),
    Kind.WEIGHTS_TAKE: (
        "a take (a SkelAnimation of blend-shape weights, e.g. from 'usdface anim import'), not an avatar",
        "pass the avatar's .usd file; a take goes to 'personalize --take' or is bound to the avatar's "
        "Skeleton with skel:animationSource"),
    Kind.ERROR_MAPS: (
        "an error-map file written by 'usdface evaluate --usd' (each method's per-vertex error on the "
        "capture's test frames), not an avatar",
        "open it in usdview to look at the errors; pass the avatar's .usd file where an avatar is expected"),
}


def refuse_recorded_non_avatar(path) -> None:
    """:func:`_refuse_non_avatar`'s refusal told from the root layer's usdface record alone (no stage
    composed): a capture, take or error-map file usdface wrote, given as the avatar (a manifest's avatar and
    capture columns swapped). ``usdface batch`` asks it of every row before its first item (such a row failed
    only at its turn, after every row before it had run)."""
    from .file_kind import NOT_AVATAR, file_kind

    found = file_kind(path)
    if found.kind in NOT_AVATAR and found.by == "format":
        what, fix = _NOT_AVATAR[found.kind]
        root = found.layer.defaultPrim if found.layer is not None else ""
        raise RigError(f"this is {what}", path=path, prim=f"/{root}" if root else None, fix=fix)


def non_avatar_input(path) -> tuple[Kind, str, str | None] | None:
    """``(kind, what it is, its root prim or None)`` when ``path`` is a file the avatar reader refuses as no
    avatar (:data:`_NOT_AVATAR`, told as :func:`_refuse_non_avatar` tells it), for a command that says so
    with its own fix before any work (``export``); None for anything else (an avatar, a usdface layer, a
    file the readers judge). Reads the root layer; composes only a USD file its root layer leaves open."""
    from .file_kind import NOT_AVATAR, file_kind

    found = file_kind(path)
    if found.kind is Kind.USD and found.by == "nothing" or found.by == "layer specs":
        found = file_kind(path, compose=True)
    if found.kind not in NOT_AVATAR or found.by in ("layer specs", "schema"):
        return None
    root = found.layer.defaultPrim if found.layer is not None else ""
    return found.kind, _NOT_AVATAR[found.kind][0], f"/{root}" if root else None


def _refuse_non_avatar(stage, path: Path) -> None:
    """A capture, take, weights-only take or error-map file passed where an avatar is expected
    (:func:`usdface.io.file_kind.file_kind` on the composed stage): say what the file is (a capture's template
    rig would otherwise be read as a face). Told by the record usdface wrote, usdface's capture/take layout,
    a legacy error-map file or a weights-only stage; a file only the root layer's specs call a take (a mesh
    cache) or only a ``UsdFaceCaptureAPI`` prim calls a capture is left to the reader, which says what it
    lacks."""
    from .file_kind import NOT_AVATAR, file_kind, top_animation

    found = file_kind(path, stage=stage, compose=True)
    if found.kind not in NOT_AVATAR or found.by in ("layer specs", "schema"):
        return
    root = stage.GetDefaultPrim()
    if not root and found.kind is Kind.WEIGHTS_TAKE and found.by == "stage":
        root = top_animation(stage)
    what, fix = _NOT_AVATAR[found.kind]
    raise RigError(f"this is {what}", path=path, prim=root.GetPath() if root else None, fix=fix)


def _from_cwd(path: Path) -> str:
    """``path`` relative to the current folder when it is below or beside it, else absolute (shell-quoted)."""
    absolute = Path(os.path.normpath(Path(path).absolute()))
    try:
        rel = os.path.relpath(absolute)
    except ValueError:      # another drive
        rel = str(absolute)
    return shlex.quote(rel if not rel.startswith(".." + os.sep + "..") else str(absolute))


def flattened_source(path, flat: dict) -> str | None:
    """The usdface layer a flattened export ``path`` (``usdface export --flatten``; ``flat`` its
    ``flattened`` record) was made from, named from the current folder as :func:`_from_cwd` names it; None
    when none is recorded. It is recorded relative to the export: said as recorded, it was 'a flattened
    export of ../p.usda' (and 'export out/../p.usda' in a fix), stop 52."""
    from .layers import recorded_path

    source = flat.get("source")
    return _from_cwd(recorded_path(Path(path).parent, source)) if source else None


def usdface_layer_data(path) -> dict:
    """The root layer's ``customLayerData["usdface"]`` of the file ``path`` (what usdface wrote into it), {}
    for another file or one that cannot be read (the reader that follows says what it is). Reads only the
    root layer (:func:`usdface.io.file_kind.file_kind`)."""
    from .file_kind import file_kind

    return file_kind(path).usdface


def usdface_output_provenance(path) -> dict | None:
    """``customLayerData["usdface"]`` of a layer written by ``usdface personalize`` (it has ``inputs`` and is
    neither a capture, a take nor an error-map file: :attr:`usdface.io.file_kind.FileKind.provenance`), else
    None."""
    from .file_kind import file_kind

    return file_kind(path).provenance


def _has_personalization(path) -> bool:
    """Whether the composed stage of ``path`` carries usdface's personalization variant set (authored by
    ``personalize`` on each SkelRoot, in this layer or one it composes: a landmarks layer over a personalized
    avatar has it, a landmarks layer over the plain avatar has not)."""
    from pxr import Usd

    from .usd_open import quiet_stderr

    with quiet_stderr():    # a missing sublayer: the reader names it in one line later
        stage = Usd.Stage.Open(str(path), Usd.Stage.LoadNone)
    return any(p.GetVariantSets().HasVariantSet(PERSONALIZATION_VARIANT_SET)
               for p in stage.Traverse(Usd.TraverseInstanceProxies()))


# the scope personalize's variant puts under each mesh (layers.SHAPES_SCOPE) and the mark of a flattened
# personalized export (flatten.PERSONALIZED_MARK), as a DCC renames a second one (Blender: usdfaceShapes.001
# for the object, usdfaceShapes_001 for the prim it exports)
_SHAPES_SCOPE_COPY = re.compile(r"usdface(?:Shapes|Personalized)(?:[._]?\d+)?")


def _may_hold_scope_copies(path: Path) -> bool:
    """Cheap pre-test of :func:`dcc_export_marks`: a crate file opens lazily (ms), a text file is opened only
    when it names the scope or an asset (a reference, a sublayer: the scope may come from there)."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return False                          # a pipe or a device: opening it would wait for a writer
        with open(path, "rb") as handle:
            head = handle.read(8)
            if not head.startswith(b"#usda"):
                return True                       # crate, usdz: opening them is cheap
            text = head + handle.read()
    except OSError:
        return False                              # the reader that follows says why
    return any(word in text for word in (b"usdfaceShapes", b"usdfacePersonalized", b"usdfaceVariant", b"@"))


def dcc_export_marks(path) -> list[str]:
    """Prim paths of usdface's ``usdfaceShapes`` scopes and ``usdfacePersonalized`` marks (or a DCC's renamed
    copies: ``usdfaceShapes_001``) under a SkelRoot of the composed stage of ``path`` when it has no
    personalization variant set and is no flattened export (its ``customLayerData`` kept): what a DCC's
    export of a usdface output layer, or of its flattened personalized export, keeps of it. Blender 5
    imports the selected variant (the ``personalized`` one unless switched), turns each scope into an Empty
    and writes it back as an ``Xform`` beside the mesh, and drops the variant set, ``customLayerData`` and
    the provenance schema. [] for any other file (a plain avatar, a usdface layer, a flattened export)."""
    from pxr import Usd

    path = Path(path)
    if not _may_hold_scope_copies(path) or flattened_from(path) is not None:
        return []
    from .usd_open import quiet_stderr

    try:
        with quiet_stderr():                    # a composition error: the reader that follows names it
            stage = Usd.Stage.Open(str(path), Usd.Stage.LoadNone)
    except Exception:                           # noqa: BLE001 - unreadable: the reader names it
        return []
    return dcc_export_marks_in(stage)


#: the glTF's node extras key (``usdface export --gltf``): Blender makes it an object custom property and
#: writes it back to USD as ``userProperties:usdfaceVariant``
VARIANT_PROPERTY = "usdfaceVariant"


def dcc_export_marks_in(stage) -> list[str]:
    """:func:`dcc_export_marks` of an open stage (``usdface check``'s Provenance rule), whatever its root
    layer records; also the ``userProperties:usdfaceVariant = "personalized"`` attributes a DCC's USD export
    of usdface's personalized glTF carries (as property paths)."""
    from pxr import Usd, UsdSkel

    marks = []
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        if prim.GetVariantSets().HasVariantSet(PERSONALIZATION_VARIANT_SET):
            return []                           # a usdface layer (refused as one) or a layer over it
        if _SHAPES_SCOPE_COPY.fullmatch(prim.GetName()) and UsdSkel.Root.Find(prim):
            marks.append(str(prim.GetPath()))
        for name in (f"userProperties:{VARIANT_PROPERTY}", VARIANT_PROPERTY):
            attr = prim.GetAttribute(name)
            if attr and attr.HasAuthoredValue() and str(attr.Get()) == "personalized":
                marks.append(str(attr.GetPath()))
    return marks


def composed_personalization(path) -> tuple[str, str] | None:
    """``(prim, layer)`` when the composed stage of ``path`` (a file that is no usdface layer itself: a
    shot that sublayers or references a published personalized layer) has a SkelRoot whose
    ``usdfacePersonalization`` variant set selects ``personalized``: the prim, and the usdface layer that
    authors the variant set (the one it composes). None for any other file (a plain avatar, a shot over a
    plain avatar, one that selects ``generic``)."""
    from pxr import Usd

    path = Path(path)
    if not _may_hold_scope_copies(path):          # a text file naming no asset composes no other layer
        return None
    from .usd_open import quiet_stderr

    try:
        with quiet_stderr():                      # a composition error: the reader that follows names it
            stage = Usd.Stage.Open(str(path), Usd.Stage.LoadNone)
    except Exception:                             # noqa: BLE001 - unreadable: the reader names it
        return None
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        sets = prim.GetVariantSets()
        if (not sets.HasVariantSet(PERSONALIZATION_VARIANT_SET)
                or sets.GetVariantSelection(PERSONALIZATION_VARIANT_SET) != "personalized"):
            continue
        layers = [spec.layer for spec in prim.GetPrimStack()
                  if PERSONALIZATION_VARIANT_SET in spec.variantSets
                  and "usdface" in (spec.layer.customLayerData or {})]
        source = layers[0].realPath or layers[0].identifier if layers else "?"
        return str(prim.GetPath()), source
    return None


def refuse_dcc_export(path) -> None:
    """Refuse (:class:`~usdface.errors.AlreadyPersonalizedError`) a DCC export of a usdface output layer
    (:func:`dcc_export_marks`): its shapes are the variant the DCC composed, personalized by default, and
    personalizing them again would stack the personalization."""
    if not isinstance(path, str | Path):
        return
    marks = dcc_export_marks(path)
    if not marks:
        return
    shown = ", ".join(marks[:2]) + (f" (+{len(marks) - 2} more)" if len(marks) > 2 else "")
    raise AlreadyPersonalizedError(
        f"this looks like a DCC export (Blender, ...) of a usdface output layer: it has {shown}, which "
        "usdface writes only into a personalized layer (the variant's scopes), its flattened personalized "
        "export or its personalized glTF, but no variant set or provenance (the DCC composed the selected "
        "variant, 'personalized' unless switched, and dropped the rest); personalizing it again would stack "
        "the personalization on the personalized shapes", path=path, prim=marks[0],
        fix="export the original avatar (the one the usdface layer sublayers) from the DCC, or personalize "
            "that avatar itself; if this export holds the generic shapes (the 'generic' variant selected), "
            "delete those prims (or properties) from it first")


def _refuse_composed_personalization(path) -> None:
    """A file that sublayers or references a personalized usdface layer (a shot over the published layer,
    :func:`composed_personalization`) holds the personalized shapes where the avatar's were: personalized
    again, the personalization was stacked on them without a word. Refused naming the layer and the avatar
    under it."""
    found = composed_personalization(path)
    if found is None:
        return
    prim, layer = found
    original = generic_input(layer) if layer != "?" else None
    raise AlreadyPersonalizedError(
        f"this file composes the usdface output layer {layer} (sublayered or referenced; its "
        f"usdfacePersonalization variant on {prim} selects 'personalized'): its shapes are already "
        "personalized, and personalizing them again would stack the personalization", path=path, prim=prim,
        fix=f"pass the original avatar{f' ({original})' if original else ''}, or a shot that composes it "
            "instead of the personalized layer")


def generic_input(layer_path) -> Path | None:
    """The generic avatar under a usdface layer: its first sublayer (resolved), followed down while that is
    itself a personalized layer (a landmarks layer over a personalized avatar compares with the avatar under
    both), or None without a sublayer."""
    from pxr import Sdf

    current, seen = Path(layer_path), set()
    while True:
        layer = Sdf.Layer.FindOrOpen(str(current))
        if layer is None or not layer.subLayerPaths:
            return None if current == Path(layer_path) else current
        # anchored as USD composes it (by name: after a symlinked output folder, '..' is the link's parent;
        # resolving through the link looked for the avatar beside the link's target, and render --compare
        # of a layer published into a linked folder said 'avatar not found', stop 51)
        sub = Path(os.path.normpath(layer.ComputeAbsolutePath(layer.subLayerPaths[0])))
        if sub in seen or not sub.is_file() or not _has_personalization(sub):
            return sub
        seen.add(sub)
        current = sub


def flattened_from(path) -> dict | None:
    """``customLayerData["usdfaceFlatten"]`` of a ``usdface export --flatten`` file: ``source`` (the layer's
    file name) and ``variant`` (``personalized``, ``generic`` or ``authored``: the one baked in), or None
    (:attr:`usdface.io.file_kind.FileKind.flattened`)."""
    from .file_kind import file_kind

    return file_kind(path).flattened


def refuse_usdface_output(path) -> None:
    """Personalizing a usdface output layer again would personalize the personalized shapes (the layer's
    default variant): refuse it (:class:`~usdface.errors.AlreadyPersonalizedError`), naming the original
    avatar recorded in the layer's provenance. A flattened export of the personalized variant (``usdface
    export --flatten``, which records the variant in ``customLayerData["usdfaceFlatten"]``) is refused too;
    one of the generic variant is the avatar's shapes and is accepted.

    A DCC export of such a layer (Blender flattens it and drops ``customLayerData``) is recognised by the
    ``usdfaceShapes`` scopes it keeps (:func:`dcc_export_marks`) and refused too.
    A ``usdface fit`` result (the person's shapes on the capture mesh, ``format: fit``) is refused too: it
    is no avatar (no eyes, no mouth, the capture's topology), and personalizing it ran to the end."""
    from .file_kind import Kind, file_kind
    from .layers import recorded_path

    if not isinstance(path, str | Path):
        return
    found = file_kind(path)             # the root layer, read once
    if found.kind is Kind.FIT:
        raise RigError("this is a 'usdface fit' result (the person's shapes on the capture mesh), not an "
                       "avatar: personalizing it gives the capture mesh back, with no eyes or mouth",
                       path=path, fix="pass the avatar's file as AVATAR ('personalize AVATAR CAPTURE' fits "
                                      "the capture itself; render or inspect the fitted rig as it is)")
    data = found.provenance
    if data is None:
        refuse_dcc_export(path)  # not a usdface layer: but perhaps a DCC's export of one
        _refuse_composed_personalization(path)      # or a shot over a published personalized layer
        return
    flat = found.flattened
    if flat is not None and flat["variant"] == "personalized":
        inputs = data.get("inputs") or []
        # the provenance records the original relative to the flattened file: say it as one can pass it
        # from here
        original = f" ({_from_cwd(recorded_path(Path(path).parent, inputs[0]))})" if inputs else ""
        generic = Path(path).with_name(f"{Path(path).stem}.generic{Path(path).suffix}").name
        source = flattened_source(path, flat)       # from here, as the original: a command one can paste
        raise AlreadyPersonalizedError(
            f"this is a flattened export of the personalized variant of the usdface layer "
            f"{source or '?'}; personalizing it again would stack the personalization on the "
            "personalized shapes", path=path,
            fix=f"flatten the generic variant instead (usdface export {source or 'LAYER'} --flatten "
                f"{shlex.quote(generic)} --variant generic) or pass the original avatar{original}")
    if not _has_personalization(path):
        refuse_dcc_export(path)     # a landmarks layer over a DCC export of a personalized layer
        return          # one that personalizes nothing (a landmarks layer), or a flattened generic one
    original = generic_input(path) or recorded_path(Path(path).parent, data["inputs"][0])
    raise AlreadyPersonalizedError(
        "this is a usdface output layer (already personalized); personalizing it again would stack the "
        "personalization on the personalized shapes", path=path, fix=f"pass the original avatar ({original})")


def _overridden_skel_root(meshes):
    """``(prim path, layer that types it SkelRoot, stronger layer that types it otherwise)`` for the first
    ancestor of ``meshes`` that a weaker layer defines as a SkelRoot and the composed stage does not (a shot
    layer's ``def Xform "Hero"`` over a referenced avatar's SkelRoot), else None."""
    for mesh in meshes:
        prim = mesh.GetParent()
        while prim and not prim.IsPseudoRoot():
            stack = prim.GetPrimStack()                                    # strongest first
            typed = [spec for spec in stack if spec.typeName == "SkelRoot"]
            if typed and prim.GetTypeName() != "SkelRoot":
                strong = next((spec for spec in stack if spec.typeName and spec.typeName != "SkelRoot"),
                              None)
                return (str(prim.GetPath()), typed[0].layer.identifier,
                        strong.layer.identifier if strong is not None else "a stronger layer")
            prim = prim.GetParent()
    return None


def _read_avatar_stage(stage, path: Path, snap_transforms: bool = True,
                       name_map: dict | None = None, moving_only: bool = False,
                       shapes: bool = True) -> Avatar:
    from pxr import Usd, UsdGeom, UsdSkel

    _refuse_non_avatar(stage, path)
    meta = read_stage_metadata(stage, path)
    roots = _skel_roots(stage)
    if not roots:
        loose = [p for p in stage.Traverse() if _has_blend_shapes(p)]
        shown = ", ".join(str(p.GetPath()) for p in loose[:3])
        hint = f" (meshes with blend shapes outside any SkelRoot: {shown})" if loose else ""
        hidden = _overridden_skel_root(loose)
        if hidden is not None:
            prim, typed, strong = hidden
            now = stage.GetPrimAtPath(prim).GetTypeName() or "untyped"
            raise RigError(f"no SkelRoot in the stage{hint}: {prim} is a SkelRoot in {typed} but {strong}, a "
                           f"stronger layer, defines it as {now}", path=path, prim=prim,
                           fix=f"leave the prim's type to the asset: author {prim} in {strong} without a "
                           "type ('over', or 'def' with no type name), or as 'def SkelRoot'")
        raise RigError(f"no SkelRoot in the stage{hint}", path=path,
                       fix="put the skinned meshes and their Skeleton under a SkelRoot prim")
    notes = []
    if not meta["metersPerUnitAuthored"]:
        notes.append(f"metersPerUnit not authored: USD's fallback {meta['metersPerUnit']} (cm) is assumed")
    if not meta["upAxisAuthored"]:
        notes.append(f"upAxis not authored: USD's fallback {meta['upAxis']} is assumed")

    cache = UsdSkel.Cache()
    predicate = Usd.TraverseInstanceProxies()
    found: dict[str, tuple] = {}  # mesh path -> (prim, skel_root, skeleton, animation)
    static: dict[str, tuple] = {}  # mesh path without blend shapes -> (prim, skinning)
    from .usd_open import diagnostic_notes, quiet_stderr

    # UsdSkel's own warnings on malformed bindings (joint influences of another size or interpolation)
    # were printed on the terminal, C++ lines before usdface's one-line answer: kept as the reader's notes
    with quiet_stderr() as said:
        for root_prim in roots:
            root = UsdSkel.Root(root_prim)
            cache.Populate(root, predicate)
            for binding in cache.ComputeSkelBindings(root, predicate):
                skel = binding.GetSkeleton()
                skel_query = cache.GetSkelQuery(skel)
                anim_query = skel_query.GetAnimQuery() if skel_query else None
                anim = str(anim_query.GetPrim().GetPath()) if anim_query else None
                for query in binding.GetSkinningTargets():
                    mesh_prim = query.GetPrim()
                    skinning = (query, skel.GetPrim()) if query.HasJointInfluences() else None
                    if _has_blend_shapes(mesh_prim):
                        found.setdefault(str(mesh_prim.GetPath()), (mesh_prim, str(root_prim.GetPath()),
                                                                    str(skel.GetPath()), anim, skinning))
                    elif mesh_prim.IsA(UsdGeom.Mesh):
                        static.setdefault(str(mesh_prim.GetPath()), (mesh_prim, skinning))
            for prim in Usd.PrimRange(root_prim, predicate):
                key = str(prim.GetPath())
                if key not in found and _has_blend_shapes(prim):
                    found[key] = (prim, str(root_prim.GetPath()), None, None, None)
                    notes.append(f"{key}: blend shapes but no skeleton binding "
                                 "(no UsdSkel client will animate them)")
                elif key not in found and prim.IsA(UsdGeom.Mesh):
                    static.setdefault(key, (prim, None))
    notes += diagnostic_notes(said, "UsdSkel")
    if not found:
        names = ", ".join(str(r.GetPath()) for r in roots)
        raise RigError(f"no mesh with blend shapes under the SkelRoot(s) {names}", path=path,
                       fix="export the avatar with its shape keys / blend shapes")

    order = {str(p.GetPath()): i for i, p in enumerate(stage.Traverse(predicate))}
    meshes, report = [], {}
    snapped: list | None = [] if snap_transforms else None
    for key in sorted(found, key=lambda k: order.get(k, len(order))):
        prim, skel_root, skeleton, anim, skinning = found[key]
        rig, entry = _read_mesh(stage, prim, path, meta, skel_root, skeleton, anim, str(path), skinning,
                                snapped, name_map, moving_only, shapes)
        meshes.append(rig)
        report[key] = entry
        for token, canonical, kept in entry["conflicts"]:
            notes.append(f"{key}: channel {token!r} also means {canonical!r}, which {kept!r} maps to better; "
                         f"{token!r} is kept under its own name and not personalized")
    if name_map:
        unused = arkit.unused_map_entries(name_map, [t for m in meshes for t in m.source.channel_tokens])
        if unused:
            notes.append(f"name map entries that match no channel: {', '.join(unused)}")
    static_meshes, static_to_internal = {}, {}
    for key in sorted(static, key=lambda k: order.get(k, len(order))):
        prim, skinning = static[key]
        try:
            points, _, _, triangles = _mesh_geometry(prim, path)
            to_internal = _mesh_to_internal(prim, meta, skinning, snapped)
        except UsdFaceError as exc:  # an unusable prop mesh must not stop the face from being read
            notes.append(f"{key}: mesh without blend shapes skipped ({exc.message})")
            continue
        static_meshes[key] = (points @ to_internal[:3, :3].T + to_internal[:3, 3],
                              outward_triangles(triangles, prim, to_internal[:3, :3]))
        static_to_internal[key] = to_internal
    _warn_foreign_units([found[k][0] for k in found], meta, path, notes)
    worst = max((c for _, c in snapped or ()), default=0.0)
    # a float32 export's noise is told; a double's (cos 90 degrees = 6e-17: Pixar's test plane) is none
    if worst > 1e-12:
        notes.append(f"world transforms of {', '.join(p for p, _ in snapped)} snapped to exact axis-aligned "
                     f"rotation and scale (float32 export noise, largest change {worst:.1e} relative)")
    default_prim = stage.GetDefaultPrim()
    metadata = {"stage": meta["authored"], "notes": notes, "static_meshes": static_meshes,
                "static_to_internal": static_to_internal,
                "documentation": stage.GetRootLayer().documentation or "",
                "instanced": _instanced([found[k][0] for k in found] + [static[k][0] for k in static]),
                "instanced_targets": _instanced_targets(stage, _shape_targets(meshes)),
                "shared_shapes": _shared_shapes(_shape_targets(meshes)),
                "name_map": dict(name_map) if name_map else None}
    return Avatar(meshes=meshes, file=os.path.abspath(path), up_axis=meta["upAxis"],
                  meters_per_unit=meta["metersPerUnit"],
                  default_prim=str(default_prim.GetPath()) if default_prim else None, metadata=metadata,
                  name_report=report)


def foreign_units(mesh_prims, stage_mpu: float) -> dict:
    """``{(layer identifier, its metersPerUnit, ratio to the stage's): [mesh prim paths]}`` for the meshes
    whose points come from a layer that authors another ``metersPerUnit`` than the stage's and that no
    transform on the way makes up for (the world scale nearer 1 than the ratio). USD does not convert units
    across references or sublayers, so a metres wrapper over a centimetre avatar composes it 100x too
    large; a reference scaled by the ratio (``xformOp:scale``), as USD asks, is not listed."""
    from pxr import Usd, UsdGeom

    cache = UsdGeom.XformCache()
    found: dict = {}
    for prim in mesh_prims:
        stack = prim.GetAttribute("points").GetPropertyStack(Usd.TimeCode.Default())
        layer = stack[0].layer if stack else None
        if layer is None or not layer.pseudoRoot.HasInfo("metersPerUnit"):
            continue
        layer_mpu = float(layer.pseudoRoot.GetInfo("metersPerUnit"))
        if not math.isfinite(layer_mpu) or layer_mpu <= 0:
            continue
        ratio = layer_mpu / float(stage_mpu)
        if abs(math.log(ratio)) < 1e-6:
            continue
        linear = np.array(cache.GetLocalToWorldTransform(prim), dtype=np.float64)[:3, :3]
        scale = abs(np.linalg.det(linear)) ** (1.0 / 3.0)
        if scale > 0 and abs(math.log(scale / ratio)) < abs(math.log(scale)):
            continue                              # a transform makes up for the other unit
        found.setdefault((layer.identifier, layer_mpu, ratio), []).append(str(prim.GetPath()))
    return found


def _warn_foreign_units(mesh_prims, meta, path, notes: list) -> None:
    """Warn (and note) each :func:`foreign_units` entry: unwarned, a metres wrapper over a centimetre avatar
    was read 100x too large and personalized that way (the registration scaled the capture by 100, the
    eyelid repair found no eyeballs of a plausible size)."""

    stage_mpu = float(meta["metersPerUnit"])
    for (layer, layer_mpu, ratio), prims in foreign_units(mesh_prims, stage_mpu).items():
        notes.append(f"{path}: {', '.join(prims)} take their points from {layer} (metersPerUnit "
                     f"{layer_mpu:g}), composed into a stage of metersPerUnit {stage_mpu:g}; USD does not "
                     f"convert units across references or sublayers, so they are read {1.0 / ratio:g}x "
                     f"{'too large' if ratio < 1 else 'too small'} (fix: author metersPerUnit = "
                     f"{layer_mpu:g} in {Path(path).name}, or scale the prim that brings the avatar in by "
                     f"{ratio:g} with an xformOp:scale)")
        warn(notes[-1])


def recorded_name_map(stage) -> dict | None:
    """The studio's name map a usdface layer was written with (``customLayerData["usdface"]["nameMap"]``,
    {channel: ARKit name}) - of the root layer or, for a layer stacked over such a layer, of the first layer
    of its layer stack that has one - so that reading, checking or rendering the layer needs no
    ``--name-map`` again; None when none has one."""
    from .name_map import validate_name_map

    for layer in stage.GetLayerStack(includeSessionLayers=False):
        data = dict(layer.customLayerData).get("usdface") or {}
        recorded = data.get("nameMap") if hasattr(data, "get") else None
        if recorded:
            return validate_name_map(dict(recorded))
    return None


def _instanced(prims) -> dict:
    """{prim path: path of the instanceable prim it is under} for the ``prims`` that are instance proxies:
    USD ignores a layer's overrides there (:func:`refuse_instanced`)."""
    out = {}
    for prim in prims:
        if prim.IsInstanceProxy():
            up = prim.GetParent()
            while up and not up.IsInstance():
                up = up.GetParent()
            out[str(prim.GetPath())] = str(up.GetPath()) if up else ""
    return out


def _shape_targets(meshes) -> dict:
    """{mesh prim path: [its BlendShape target paths]} of a reader's rigs."""
    return {rig.source.prim: list(rig.source.shape_prims) for rig in meshes if rig.source}


def _instanced_targets(stage, targets: dict) -> dict:
    """{mesh prim path: (BlendShape path, instanceable prim)} for the meshes of ``targets`` ({mesh prim path:
    [BlendShape paths]}) one of whose BlendShape targets lies under an instance (the mesh itself may not): a
    layer's ``over`` of that target changes nothing."""
    out = {}
    for mesh, shapes in targets.items():
        for target in shapes:
            prim = stage.GetPrimAtPath(target)
            holder = _instanced([prim]) if prim and prim.IsInstanceProxy() else {}
            if holder:
                out[mesh] = (target, holder[target])
                break
    return out


def _shared_shapes(targets: dict) -> dict:
    """{BlendShape path: [mesh prim paths]} for the targets more than one mesh of ``targets`` ({mesh prim
    path: [BlendShape paths]}) binds."""
    users: dict[str, list[str]] = {}
    for mesh, shapes in targets.items():
        for target in dict.fromkeys(shapes):
            users.setdefault(target, []).append(mesh)
    return {t: ms for t, ms in users.items() if len(ms) > 1}


def refuse_layer_over(path, what: str = "the personalized layer") -> None:
    """What :func:`refuse_instanced` and :func:`refuse_unwritable_shapes` refuse for a layer over every
    mesh of the avatar at ``path`` (raised as they raise it, :class:`RigError`), told from its composed
    stage alone: the meshes with blend shapes under its SkelRoots (through instances, as :func:`read_avatar`
    finds them) and their BlendShape targets, no points or offsets read. For a check before any work: a
    ``personalize --dry-run`` said an instanced avatar's refusal only after the fit (the avatar is read
    inside the work); a real run refuses it when it has read the avatar, before the fit."""
    from pxr import Usd, UsdSkel

    stage = _open_stage(Path(path))
    through = Usd.TraverseInstanceProxies()
    prims = [prim for root in _skel_roots(stage) for prim in Usd.PrimRange(root, through)
             if _has_blend_shapes(prim)]
    prims = list({str(p.GetPath()): p for p in prims}.values())        # (nested SkelRoots: each mesh once)
    targets = {str(p.GetPath()): [str(t) for t in UsdSkel.BindingAPI(p).GetBlendShapeTargetsRel()
                                  .GetForwardedTargets()] for p in prims}
    light = Avatar(meshes=[], file=os.path.abspath(path), metadata={       # what the refusals read
        "instanced": _instanced(prims), "instanced_targets": _instanced_targets(stage, targets),
        "shared_shapes": _shared_shapes(targets)})
    refuse_instanced(light, list(targets), what)
    refuse_unwritable_shapes(light, list(targets), what)


def refuse_unwritable_shapes(avatar, keys=None, what: str = "the personalized layer") -> None:
    """Raise :class:`RigError` when ``what`` would author BlendShape offsets that USD cannot compose as
    meant, for the meshes ``keys`` (default every mesh): a target under an instanceable prim (the ``over`` is
    ignored: nothing would change), or a target bound by two meshes (one prim holds one set of offsets: the
    last mesh written would win for both, in its own local frame). Uses :func:`read_avatar`'s
    ``metadata["instanced_targets"]`` and ``["shared_shapes"]``."""
    meta = avatar.metadata or {}
    keys = [m.key for m in avatar.meshes] if keys is None else list(keys)
    for key in keys:
        if key in (meta.get("instanced_targets") or {}):
            target, holder = meta["instanced_targets"][key]
            raise RigError(f"{key}'s BlendShape {target} is inside the instanceable prim {holder}: USD "
                           f"ignores overrides under an instance, so {what} would not change it",
                           path=avatar.file, prim=target,
                           fix=f"set instanceable = false on {holder}, or keep the mesh's BlendShape prims "
                               "under the mesh")
    for target, users in (meta.get("shared_shapes") or {}).items():
        if any(u in keys for u in users):
            raise RigError(f"the BlendShape {target} is bound by {len(users)} meshes ({', '.join(users)}): "
                           f"one prim holds one set of offsets, so {what} cannot personalize each mesh",
                           path=avatar.file, prim=target,
                           fix="give each mesh its own BlendShape prims (duplicate the shared ones under "
                               "each mesh and point its skel:blendShapeTargets at them)")


def refuse_instanced(avatar, keys=None, what: str = "the output layer") -> None:
    """Raise :class:`RigError` when a mesh of ``avatar`` that ``what`` would write over (``keys``: mesh prim
    paths; default every mesh) lies under an instanceable prim: USD composes no override under an
    instance, so the layer would change nothing there. Uses ``avatar.metadata["instanced"]``
    (:func:`read_avatar`)."""
    instanced = (avatar.metadata or {}).get("instanced") or {}
    keys = list(instanced) if keys is None else [k for k in keys if k in instanced]
    if keys:
        holder = instanced[keys[0]]
        raise RigError(f"{keys[0]} is inside the instanceable prim {holder}: USD ignores overrides under an "
                       f"instance, so {what} would change nothing", path=avatar.file, prim=holder,
                       fix=f"set instanceable = false on {holder} in the file that references the avatar, or "
                           "run on the referenced avatar asset itself")


def read_layer_info(path, revisions: bool = False) -> dict:
    """What a USD file says about itself, for reports: the root layer's authored stage metadata, sublayers,
    documentation, ``customLayerData["usdface"]`` (plain Python values), the prims that carry a usdface API
    schema (with that schema's authored attribute values), the variant selections of usdface variant sets
    and, for a ``usdface export --flatten`` file, what it baked in (``flattened``: ``source``, ``variant``).
    With ``revisions``, for a usdface layer also how its avatar was revised since it was written
    (``avatarRevised``: :func:`usdface.io.layers.avatar_mismatches`; ``neutralNudged``: its neutral's points
    changed by less than the layer's record resolves, a warning as check's) and which recorded inputs changed
    (``staleInputs``: :func:`usdface.io.layers.stale_inputs`), as text, and which are gone (``missingInputs``:
    :func:`usdface.io.layers.missing_inputs`, as recorded).
    """
    from pxr import Usd

    from .file_kind import file_kind

    path = Path(path)
    stage = _open_stage(path, "USD file")
    root = stage.GetRootLayer()
    meta = {k: _plain(root.pseudoRoot.GetInfo(k)) for k in STAGE_METADATA_KEYS if root.pseudoRoot.HasInfo(k)}
    found = file_kind(path, stage=stage)
    schemas_found, variants = {}, {}
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        # as authored: GetAppliedSchemas() leaves out the schemas USD's registry does not know, and it does
        # not know usdface's when a stage was opened before usdface registered them (a DCC): none were listed
        authored = [*prim.GetAppliedSchemas(), *prim.GetPrimTypeInfo().GetAppliedAPISchemas()]
        applied = [s for s in dict.fromkeys(authored) if s.startswith("UsdFace")]
        if applied:
            values = {}
            for attr in prim.GetAttributes():
                if attr.GetName().startswith("usdface:") and attr.HasAuthoredValue():
                    values[attr.GetName()] = _plain(attr.Get())
            schemas_found[str(prim.GetPath())] = {"schemas": applied, "values": values}
        for name in prim.GetVariantSets().GetNames():
            if name.startswith("usdface"):
                variants.setdefault(str(prim.GetPath()), {})[name] = {
                    "selection": prim.GetVariantSets().GetVariantSelection(name),
                    "variants": list(prim.GetVariantSets().GetVariantSet(name).GetVariantNames())}
    from .layers import avatar_mismatches, missing_inputs, stale_inputs

    # a published layer whose avatar was revised since: said, as check's AvatarMatch and Provenance say it
    # (inspect listed the layer's meshes and shapes as if they were its result)
    nudged: list = []
    revised = ([f"{message} (fix: {fix})" for _, message, fix in avatar_mismatches(stage, nudged=nudged)]
               if revisions else [])
    record = found.provenance if revisions else None        # read once, for the stale inputs
    return {"file": str(path), "stage": meta, "subLayers": list(root.subLayerPaths),
            "documentation": root.documentation or "", "usdface": found.usdface, "schemas": schemas_found,
            "variants": variants, "flattened": found.flattened or {},
            "avatarRevised": revised,
            "neutralNudged": [f"{message} (fix: {fix})" for _, message, fix in nudged],
            "staleInputs": stale_inputs(path, record=record) if record else [],
            "missingInputs": missing_inputs(path, found.usdface) if revisions and found.usdface else []}
