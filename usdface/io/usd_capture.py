"""capture.usda <-> :class:`usdface.model.Capture`: a capture as a real USD asset one can open and scrub.

Layout (documented in ``docs/capture-format.md``)::

    /Capture                  Xform, defaultPrim, UsdFaceCaptureAPI (counts, shape names, device, digest)
      Neutral                 Mesh: the person's neutral scan
      Template                SkelRoot: the generic template rig as UsdSkel
        Skel                  Skeleton (one root joint), skel:animationSource -> Anim
          Anim                SkelAnimation: blendShapes = names, blendShapeWeights = frame weights
        Mesh                  Mesh + SkelBindingAPI, skel:blendShapes / skel:blendShapeTargets
          <shape>             BlendShape per shape (dense offsets)
      Frames                  Mesh: points time-sampled, frame f at time code f;
                              usdface:frames:weights (double[K], time-sampled), usdface:frames:names token[K],
                              usdface:frames:role token[F], usdface:frames:label string[F]

Stage: metersPerUnit 1, upAxis Y, time codes 0 .. F-1. The Template and Frames prims carry a display-only
``xformOp:translate`` so the three heads sit side by side in a viewer; the reader reads local points.

Exactness: USD geometry is float32 (``point3f[]``, ``vector3f[]``), the model float64. With ``exact=True``
(default) every float32 geometry attribute gets a float64 twin (``double3[] usdface:points``,
``double3[] usdface:offsets``) that the reader prefers while it still matches the float32 value; so
folder -> usda -> model is bit-exact, and if someone edits the points in a DCC (the float32 values no longer
match the twin) the edited points win, with a warning. ``exact=False`` halves the file; the model read back is
then the float32-quantised capture (exactly).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import CaptureError, GeometryError, InputFileError, warn
from ..model import Capture, FaceRig, Frames
from .capture_folder import ROLES, refuse_weights_scale, refuse_whole_take
from .mesh_io import fan_triangulate

__all__ = ["write_capture_usd", "read_capture_usd", "author_template", "author_frames", "CAPTURE_PRIM",
           "DISPLAY_SPACING"]

CAPTURE_PRIM = "/Capture"
#: Display-only spacing (metres, along X) between Neutral, Template and Frames in a viewer.
DISPLAY_SPACING = 0.3
_EXACT = "usdface:points"
_EXACT_OFFSETS = "usdface:offsets"
_ROLE_COLOR = {"train": (0.35, 0.55, 0.85), "test": (0.9, 0.55, 0.25)}


# ----------------------------------------------------------------------------------------------- writing
def _check_output(path: Path, force: bool, what: str = "capture file") -> None:
    """:func:`.layers.check_output_path` naming the file for what it is (it said 'output layer exists' of a
    capture)."""
    from .layers import check_output_path

    check_output_path(path, force, what=what)


def _save(stage, path: Path, force: bool = False) -> None:
    """Write the stage's root layer to ``path`` atomically (temp file in the same folder + rename)."""
    from .layers import atomic_save

    atomic_save(stage.GetRootLayer(), path, force)


def _topology(mesh, triangles) -> None:
    from pxr import UsdGeom, Vt

    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(triangles), 3, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(triangles.ravel(), np.int32)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)


def _set_points(mesh, points, time=None, exact=True) -> None:
    """Author float32 ``points`` and the exact float64 twin ``usdface:points`` (at ``time`` if given)."""
    from pxr import Sdf, Usd, Vt

    t = Usd.TimeCode.Default() if time is None else Usd.TimeCode(time)
    mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)), t)
    if not exact:
        return
    twin = mesh.GetPrim().CreateAttribute(_EXACT, Sdf.ValueTypeNames.Double3Array, custom=True)
    twin.Set(Vt.Vec3dArray.FromNumpy(np.ascontiguousarray(points, dtype=np.float64)), t)


def _valid_names(names) -> list[str]:
    """Prim names for shapes (Tf-valid identifiers, unique)."""
    from pxr import Tf

    out, seen = [], set()
    for n in names:
        base = Tf.MakeValidIdentifier(n)
        name, i = base, 1
        while name in seen:
            name, i = f"{base}_{i}", i + 1
        seen.add(name)
        out.append(name)
    return out


def _capture_stage(capture: Capture, time_codes_per_second: float, exact: bool):
    from pxr import Gf, Sdf, Usd, UsdGeom, Vt

    from .. import __version__, schemas

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    root = UsdGeom.Xform.Define(stage, CAPTURE_PRIM).GetPrim()
    stage.SetDefaultPrim(root)
    fr, names = capture.frames, list(capture.names)
    counts = {r: int(sum(x == r for x in fr.role)) for r in ROLES}
    schemas.apply_api(root, schemas.CAPTURE_API)
    meta = capture.metadata or {}
    for attr, type_, value in (
            ("usdface:capture:device", Sdf.ValueTypeNames.String, str(meta.get("device", ""))),
            ("usdface:capture:unitsNote", Sdf.ValueTypeNames.String, str(meta.get("units_note", "metres"))),
            ("usdface:capture:trainCount", Sdf.ValueTypeNames.Int, counts["train"]),
            ("usdface:capture:testCount", Sdf.ValueTypeNames.Int, counts["test"]),
            ("usdface:capture:shapeNames", Sdf.ValueTypeNames.TokenArray, Vt.TokenArray(names)),
            ("usdface:capture:sourceDigest", Sdf.ValueTypeNames.String, str(meta.get("source_digest", "")))):
        root.CreateAttribute(attr, type_).Set(value)
    layer_data = {"format": "capture", "formatVersion": 1, "version": __version__,
                  "source": str(capture.source or "")}
    if "take" in meta:  # made by 'capture select': keep the frame-selection record (JSON text)
        import json

        layer_data["takeSelection"] = json.dumps({**meta["take"], "take_frames": meta.get("take_frames", [])})
    stage.GetRootLayer().customLayerData = {"usdface": layer_data}

    neutral = UsdGeom.Mesh.Define(stage, f"{CAPTURE_PRIM}/Neutral")
    _topology(neutral, capture.triangles)
    _set_points(neutral, capture.neutral, exact=exact)
    # Template rig as UsdSkel, driven by the frames' weights so that scrubbing plays the generic rig.
    codes = np.arange(len(fr), dtype=np.float64)
    author_template(stage, f"{CAPTURE_PRIM}/Template", capture.template,
                    _columns(fr.weights, names, capture.template.names), codes, time_codes_per_second, exact)
    frames = author_frames(stage, f"{CAPTURE_PRIM}/Frames", capture.triangles, fr.points, fr.weights, names,
                           codes, exact)
    prim = frames.GetPrim()
    prim.CreateAttribute("usdface:frames:role", Sdf.ValueTypeNames.TokenArray, custom=True).Set(
        Vt.TokenArray(fr.role))
    prim.CreateAttribute("usdface:frames:label", Sdf.ValueTypeNames.StringArray, custom=True).Set(
        Vt.StringArray(fr.label))
    color = frames.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant)
    for f in range(len(fr)):
        color.Set(Vt.Vec3fArray([Gf.Vec3f(*_ROLE_COLOR.get(fr.role[f], (0.7, 0.7, 0.7)))]), f)
    if len(fr) == 0:
        stage.SetStartTimeCode(0)
        stage.SetEndTimeCode(0)
    return stage


def author_template(stage, prim_path: str, tpl: FaceRig, weights, time_codes, time_codes_per_second: float,
                    exact: bool = True):
    """Define the template rig at ``prim_path`` as UsdSkel: SkelRoot > Skeleton (one root joint) >
    SkelAnimation (``weights[F, K]`` in ``tpl.names`` order at ``time_codes[F]``) and Mesh + BlendShapes
    (dense offsets, float64 twins when ``exact``). Displayed ``DISPLAY_SPACING`` to the right. Returns the
    SkelRoot."""
    from pxr import Gf, Sdf, UsdGeom, UsdSkel, Vt

    from .usd_anim import author_skel_animation

    skel_root = UsdSkel.Root.Define(stage, prim_path)
    UsdGeom.Xformable(skel_root).AddTranslateOp().Set(Gf.Vec3d(DISPLAY_SPACING, 0, 0))
    skel = UsdSkel.Skeleton.Define(stage, f"{prim_path}/Skel")
    skel.CreateJointsAttr(Vt.TokenArray(["root"]))
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
    tcps = float(time_codes_per_second)
    anim = author_skel_animation(stage, f"{prim_path}/Skel/Anim", tpl.names, weights, tcps,
                                 times=np.array(time_codes, dtype=np.float64) / tcps)
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
    mesh = UsdGeom.Mesh.Define(stage, f"{prim_path}/Mesh")
    _topology(mesh, tpl.triangles)
    _set_points(mesh, tpl.neutral, exact=exact)
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    binding.CreateJointIndicesPrimvar(constant=True, elementSize=1).Set(Vt.IntArray([0]))
    binding.CreateJointWeightsPrimvar(constant=True, elementSize=1).Set(Vt.FloatArray([1.0]))
    binding.CreateGeomBindTransformAttr().Set(Gf.Matrix4d(1))
    targets = []
    for prim_name, delta in zip(_valid_names(tpl.names), tpl.deltas, strict=True):
        shape = UsdSkel.BlendShape.Define(stage, mesh.GetPath().AppendChild(prim_name))
        shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(delta.astype(np.float32)))
        if exact:
            shape.GetPrim().CreateAttribute(_EXACT_OFFSETS, Sdf.ValueTypeNames.Double3Array, custom=True).Set(
                Vt.Vec3dArray.FromNumpy(np.ascontiguousarray(delta)))
        targets.append(shape.GetPath())  # prim names may differ from names; the channel tokens are the names
    binding.CreateBlendShapesAttr(Vt.TokenArray(tpl.names))
    binding.CreateBlendShapeTargetsRel().SetTargets(targets)
    return skel_root


def author_frames(stage, prim_path: str, triangles, points, weights, names, time_codes, exact: bool = True):
    """Define a Mesh at ``prim_path`` whose ``points`` are time-sampled (``points[F, n, 3]`` at
    ``time_codes[F]``) with ``usdface:frames:weights`` (double[K], time-sampled) and ``usdface:frames:names``
    (token[K]). Displayed ``DISPLAY_SPACING`` to the left. Returns the UsdGeom.Mesh."""
    from pxr import Gf, Sdf, UsdGeom, Vt

    frames = UsdGeom.Mesh.Define(stage, prim_path)
    frames.AddTranslateOp().Set(Gf.Vec3d(-DISPLAY_SPACING, 0, 0))
    _topology(frames, triangles)
    prim = frames.GetPrim()
    prim.CreateAttribute("usdface:frames:names", Sdf.ValueTypeNames.TokenArray, custom=True).Set(
        Vt.TokenArray(list(names)))
    w_attr = prim.CreateAttribute("usdface:frames:weights", Sdf.ValueTypeNames.DoubleArray, custom=True)
    for f, code in enumerate(np.array(time_codes, dtype=np.float64).tolist()):
        _set_points(frames, points[f], code, exact)
        w_attr.Set(Vt.DoubleArray.FromNumpy(np.ascontiguousarray(weights[f], dtype=np.float64)), code)
    return frames


def _columns(weights, names, wanted) -> np.ndarray:
    index = {n: k for k, n in enumerate(names)}
    out = np.zeros((len(weights), len(wanted)))
    for j, n in enumerate(wanted):
        if n in index:
            out[:, j] = weights[:, index[n]]
    return out


def write_capture_usd(capture: Capture, path, force: bool = False, *,
                      time_codes_per_second: float = 24.0, exact: bool = True) -> Path:
    """Write ``capture`` as a capture USD file (``.usda`` text or ``.usdc`` binary, by extension).

    Atomic (temp file + rename); refuses an existing ``path`` unless ``force`` (OutputExistsError).
    ``read_capture_usd(write_capture_usd(c, p))`` equals ``c`` exactly (float64 twins, see the module doc);
    with ``exact=False`` (no twins, half the size) it equals ``c`` with geometry rounded to float32. Weights
    are always stored as double.
    """
    path = Path(path)
    if path.suffix.lower() not in (".usda", ".usdc", ".usd"):
        raise InputFileError("output must be a .usda, .usdc or .usd file", path=path,
                             fix="name the output capture.usda")
    refuse_whole_take(capture, path)
    _check_output(path, force)
    if capture.frames.points.shape[1:] != capture.neutral.shape:
        raise GeometryError("frames and neutral have different vertex counts", path=path,
                            fix="every frame must share the neutral's topology")
    stage = _capture_stage(capture, time_codes_per_second, exact)
    _save(stage, path, force)
    return path


# ----------------------------------------------------------------------------------------------- reading
def _points(prim, path, time=None) -> np.ndarray:
    """float64 points of a Mesh: the exact twin while it matches the float32 ``points``, else ``points``."""
    from pxr import Usd, UsdGeom

    t = Usd.TimeCode.Default() if time is None else Usd.TimeCode(time)
    value = UsdGeom.Mesh(prim).GetPointsAttr().Get(t)
    if value is None or len(value) == 0:
        raise GeometryError("mesh has no points", path=path, prim=prim.GetPath(),
                            fix="re-create the capture with 'usdface capture import'")
    p32 = np.array(value, dtype=np.float32)
    twin = prim.GetAttribute(_EXACT)
    exact = twin.Get(t) if twin else None
    if exact is not None and len(exact) == len(p32):
        p64 = np.array(exact, dtype=np.float64)
        if np.array_equal(p64.astype(np.float32), p32, equal_nan=True):     # NaN: refused below, not "edited"
            return _finite(p64, path, prim, t)
        warn(f"{path}: {prim.GetPath()} points were edited after import; using the edited float32 "
             f"points")
    return _finite(p32.astype(np.float64), path, prim, t)


def _finite(a, path, prim, time=None):
    if not np.isfinite(a).all():
        bad = int(np.flatnonzero(~np.isfinite(a).all(axis=-1))[0]) if a.ndim == 2 else None
        at = "" if time is None or time.IsDefault() else f" at time {time.GetValue():g}"
        where = f" (point {bad}{at})" if bad is not None else at
        raise GeometryError(f"NaN or infinite values{where}", path=path, prim=prim.GetPath(),
                            fix="repair the capture and import it again")
    return a


def _triangles(prim, path) -> np.ndarray:
    from pxr import UsdGeom

    mesh = UsdGeom.Mesh(prim)
    counts = np.array(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
    idx = np.array(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
    if counts.size == 0 or counts.min() < 3 or counts.sum() != idx.size:
        raise GeometryError("invalid or empty faces (faceVertexCounts/faceVertexIndices)", path=path,
                            prim=prim.GetPath(), fix="re-create the capture with 'usdface capture import'")
    return fan_triangulate(counts, idx)


def _child(stage, prim_path, path, kind):
    prim = stage.GetPrimAtPath(prim_path)
    if not prim or not prim.IsValid():
        raise CaptureError(f"no {kind} prim", path=path, prim=prim_path,
                           fix="write captures with 'usdface capture import' (see docs/capture-format.md)")
    return prim


def _template(stage, root, path, triangles, n) -> FaceRig:
    from pxr import UsdSkel

    mesh = _child(stage, root.AppendPath("Template/Mesh"), path, "template Mesh")
    neutral = _points(mesh, path)
    tris = _triangles(mesh, path)
    if len(neutral) != n or not np.array_equal(tris, triangles):
        raise GeometryError("template topology differs from the neutral's", path=path, prim=mesh.GetPath(),
                            fix="the template must share the neutral's vertices and faces")
    binding = UsdSkel.BindingAPI(mesh)
    names = [str(t) for t in (binding.GetBlendShapesAttr().Get() or [])]
    targets = binding.GetBlendShapeTargetsRel().GetTargets()
    if len(names) != len(targets):
        raise CaptureError(f"{len(names)} skel:blendShapes but {len(targets)} skel:blendShapeTargets",
                           path=path, prim=mesh.GetPath(), fix="author one target per blend shape name")
    if len(set(names)) != len(names):
        raise CaptureError("duplicate skel:blendShapes names", path=path, prim=mesh.GetPath(),
                           fix="give every blend shape a unique name")
    deltas = np.zeros((len(names), n, 3))
    for k, target in enumerate(targets):
        shape = stage.GetPrimAtPath(target)
        if not shape:
            raise CaptureError("blend shape target not found", path=path, prim=target,
                               fix="re-create the capture with 'usdface capture import'")
        bs = UsdSkel.BlendShape(shape)
        off32 = np.array(bs.GetOffsetsAttr().Get() or [], dtype=np.float32)
        twin = shape.GetAttribute(_EXACT_OFFSETS)
        exact = twin.Get() if twin else None
        off = off32.astype(np.float64)
        if exact is not None and len(exact) == len(off32):
            e = np.array(exact, dtype=np.float64)
            if np.array_equal(e.astype(np.float32), off32):
                off = e
        pi = bs.GetPointIndicesAttr().Get()
        idx = np.arange(n) if not pi else np.array(pi, dtype=np.int64)
        if len(idx) != len(off) or (len(idx) and (idx.min() < 0 or idx.max() >= n)):
            raise CaptureError("offsets/pointIndices do not match the mesh", path=path, prim=target,
                               fix="author one offset per point index, indices within the mesh")
        deltas[k, idx] = _finite(off, path, shape)
    return FaceRig(neutral, tris, names, deltas, name="template")


#: What :func:`read_capture_usd` says of a rig given where a capture goes, and its fix.
RIG_NOT_CAPTURE = ("this is a rig (meshes with blend shapes: an avatar, or a 'usdface fit' result), not a "
                   "capture: it holds no captured frames")
RIG_NOT_CAPTURE_FIX = ("pass the capture (folder or capture.usda) where a capture goes, e.g. personalize "
                       "AVATAR CAPTURE; a fitted rig is implanted with the API (personalize_avatar(..., "
                       "rig=...))")


def refuse_rig_as_capture(path) -> None:
    """:func:`read_capture_usd`'s refusal of a rig given as the capture (an avatar, a usdface layer or its
    flattened export, a ``usdface fit`` result: a manifest's avatar and capture columns swapped), told
    without reading a frame: by the root layer's usdface record, else by the composed stage (a SkelRoot with
    blend shapes, no capture or take layout). ``usdface batch`` asks it of every row before its first item
    (such a row failed only at its turn, after every row before it had run)."""
    from .file_kind import Kind, file_kind

    found = file_kind(path)
    if found.kind is Kind.USD and found.by == "nothing":
        found = file_kind(path, compose=True)
    rig = found.kind in (Kind.LAYER, Kind.FLATTENED, Kind.FIT) or (found.kind is Kind.AVATAR
                                                                    and found.blend_shapes)
    if rig:
        root = found.layer.defaultPrim if found.layer is not None else ""
        raise CaptureError(RIG_NOT_CAPTURE, path=path, prim=f"/{root}" if root else None,
                           fix=RIG_NOT_CAPTURE_FIX)


def read_capture_usd(path) -> Capture:
    """Read a capture USD file written by :func:`write_capture_usd` into a :class:`~usdface.model.Capture`.

    Stage units are honoured (points scaled by ``metersPerUnit``; ``upAxis`` Z rotated to Y). Raises
    InputFileError (missing/unreadable), CaptureError (layout: missing prims, inconsistent arrays) or
    GeometryError (NaN/inf, vertex counts), naming file and prim.
    """
    from pxr import UsdGeom

    from .usd_open import open_usd_stage

    path = Path(path)
    stage = open_usd_stage(path, "capture file", "pass a capture .usda written by 'usdface capture import'")
    root = stage.GetDefaultPrim() or stage.GetPrimAtPath(CAPTURE_PRIM)
    if not root or not root.GetChild("Frames"):
        from .file_kind import is_weights_take
        from .take import WEIGHTS_ONLY_FIX

        if is_weights_take(stage):
            from pxr import UsdSkel

            anim = root or next(p for p in stage.GetPseudoRoot().GetChildren() if p.IsA(UsdSkel.Animation))
            raise CaptureError("a take of weights only (a SkelAnimation, e.g. from 'usdface anim import'), "
                               "no meshes to fit", path=path, prim=anim.GetPath(), fix=WEIGHTS_ONLY_FIX)
        from pxr import Usd, UsdSkel

        if any(p.IsA(UsdSkel.BlendShape) for p in stage.Traverse(Usd.TraverseInstanceProxies())):
            raise CaptureError(RIG_NOT_CAPTURE, path=path, prim=root.GetPath() if root else None,
                               fix=RIG_NOT_CAPTURE_FIX)
        raise CaptureError("not a usdface capture (no Frames mesh of captured expressions under the default "
                           "prim or /Capture)", path=path, prim=root.GetPath() if root else None,
                           fix="make capture files with 'usdface capture import DIR -o capture.usda'")
    rp = root.GetPath()
    neutral_prim = _child(stage, rp.AppendChild("Neutral"), path, "Neutral mesh")
    neutral = _points(neutral_prim, path)
    triangles = _triangles(neutral_prim, path)
    if triangles.max() >= len(neutral):
        raise GeometryError("face index out of range", path=path, prim=neutral_prim.GetPath(),
                            fix="re-create the capture with 'usdface capture import'")
    template = _template(stage, rp, path, triangles, len(neutral))

    fprim = _child(stage, rp.AppendChild("Frames"), path, "Frames mesh")
    if not np.array_equal(_triangles(fprim, path), triangles):
        raise GeometryError("Frames topology differs from the neutral's", path=path, prim=fprim.GetPath(),
                            fix="every frame must share the neutral's topology")

    def get(name):
        attr = fprim.GetAttribute(f"usdface:frames:{name}")
        value = attr.Get() if attr else None
        if value is None:
            raise CaptureError(f"missing usdface:frames:{name}", path=path, prim=fprim.GetPath(),
                               fix="re-create the capture with 'usdface capture import'")
        return [str(v) for v in value]

    names, role, label = get("names"), get("role"), get("label")
    if len(role) != len(label):
        raise CaptureError(f"{len(role)} roles but {len(label)} labels", path=path, prim=fprim.GetPath(),
                           fix="author one role and one label per frame")
    bad_roles = sorted(set(role) - set(ROLES))
    if bad_roles:
        raise CaptureError(f"unknown frame roles {bad_roles}", path=path, prim=fprim.GetPath(),
                           fix="roles are 'train' or 'test'")
    if sorted(names) != sorted(template.names):
        raise CaptureError("usdface:frames:names differ from the template's blend shapes", path=path,
                           prim=fprim.GetPath(), fix="weights columns must name the template's shapes")
    w_attr = fprim.GetAttribute("usdface:frames:weights")
    points, weights = [], []
    for f in range(len(role)):
        points.append(_points(fprim, path, f))
        w = w_attr.Get(f) if w_attr else None
        if w is None or len(w) != len(names):
            raise CaptureError(f"frame {f}: weights missing or of the wrong length", path=path,
                               prim=fprim.GetPath(), fix="author usdface:frames:weights, one value per name")
        weights.append(_finite(np.array(w, dtype=np.float64), path, fprim))
    if any(p.shape != neutral.shape for p in points):
        raise GeometryError("a frame's vertex count differs from the neutral's", path=path,
                            prim=fprim.GetPath(), fix="every frame must share the neutral's topology")
    pts = np.stack(points) if points else np.zeros((0,) + neutral.shape)
    w = np.stack(weights) if weights else np.zeros((0, len(names)))
    refuse_weights_scale(w, names, path, fix_where="the capture's weights")
    if w.size and (w.min() < 0 or w.max() > 1):
        warn(f"{path}: weights outside [0, 1] clipped")
        w = np.clip(w, 0.0, 1.0)
    w = w[:, [names.index(n) for n in template.names]]

    # Units and axis -> internal metres, Y up (refused as for an avatar: a negative or zero unit mirrored
    # or collapsed the face without a word)
    from .usd_rig import read_stage_metadata

    mpu = read_stage_metadata(stage, path)["metersPerUnit"]
    rot = np.eye(3)
    if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z:
        rot = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # (x, y, z) Z-up -> (x, z, -y) Y-up
    if mpu != 1.0 or not np.array_equal(rot, np.eye(3)):
        m = mpu * rot
        neutral, pts = neutral @ m.T, pts @ m.T
        template = FaceRig(template.neutral @ m.T, template.triangles, template.names, template.deltas @ m.T,
                           name="template")
    from ..arkit import match_names

    match = match_names(template.names)
    root_attr = root.GetAttribute("usdface:capture:device")
    metadata = {"source": str(path), "units": "m",
                "name_report": {"inexact": match.inexact, "unknown": match.unknown, "missing": match.missing},
                "counts": {r: int(sum(x == r for x in role)) for r in ROLES},
                "device": str(root_attr.Get() or "") if root_attr else ""}
    metadata.update(_take_selection(stage))
    return Capture(neutral, triangles, template, Frames(pts, w, role, label), list(template.names),
                   source=str(path), metadata=metadata)


def _take_selection(stage) -> dict:
    """``{"take": ..., "take_frames": [...]}`` from the frame-selection record a capture made by ``usdface
    capture select`` keeps (``customLayerData["usdface"]["takeSelection"]``), so that rewriting the capture
    (``capture import capture.usdc -o capture.usda``, :func:`usdface.api.write_capture`) keeps it; it was
    dropped. ``{}`` without one (or an unreadable one: it is a record, not the capture's data)."""
    import json

    data = dict(stage.GetRootLayer().customLayerData).get("usdface")
    text = data.get("takeSelection") if hasattr(data, "get") else None
    try:
        record = json.loads(text) if isinstance(text, str) else None
    except ValueError:
        return {}
    if not isinstance(record, dict):
        return {}
    frames = record.pop("take_frames", [])
    return {"take": record, "take_frames": frames if isinstance(frames, list) else []}
