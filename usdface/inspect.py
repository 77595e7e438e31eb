"""``usdface inspect``: what an avatar, a usdface layer or a capture contains, as a dict and as text.

For an avatar (or a usdface output layer over one): every skinned mesh with blend shapes, its vertex /
triangle counts, units and up axis of the stage, and its shapes compared with the ARKit 52: present, missing,
extra (not ARKit), misspelt (close to an ARKit name: a likely typo), renamed (mapped inexactly, e.g. Blender's
``eyeBlinkLeft2`` or the raw spelling ``eyeBlink_L``), sparse / dense storage and inbetweens. For a usdface
layer also the provenance and the variant selections; for a capture (folder or ``capture.usda``) the frames
by role, the shape names and the mesh sizes.

Pure Python over the model: the file reading is done by :mod:`usdface.io`.

Example::

    from usdface.inspect import inspect_file, format_report
    report = inspect_file("avatar_blender.usdc")
    print(format_report(report))
"""

from __future__ import annotations

import difflib
import os
from pathlib import Path

import numpy as np

from . import arkit
from .model import Avatar, Capture, FaceRig

MISSPELLING_CUTOFF = arkit.MISSPELLING_CUTOFF


def _misspellings(unknown) -> dict[str, str]:
    """{unknown name -> closest ARKit name} for names that look like typos (difflib ratio >= cutoff)."""
    out = {}
    candidates = {n.lower(): n for n in arkit.ARKIT_NAMES}
    for name in unknown:
        hit = difflib.get_close_matches(name.lower(), list(candidates), n=1, cutoff=MISSPELLING_CUTOFF)
        if hit:
            out[name] = candidates[hit[0]]
    return out


def shape_storage(rig: FaceRig) -> dict:
    """How the rig's shapes are stored: counts of dense (no pointIndices), dense-indexed (pointIndices listing
    every point) and sparse shapes, the mean fraction of points listed, and inbetweens by shape."""
    src = rig.source
    kinds = {"dense": 0, "denseIndexed": 0, "sparse": 0}
    fractions = []
    for idx in (src.point_indices if src else [None] * rig.n_shapes):
        if idx is None:
            kinds["dense"] += 1
            fractions.append(1.0)
        elif len(idx) == rig.n_vertices:
            kinds["denseIndexed"] += 1
            fractions.append(1.0)
        else:
            kinds["sparse"] += 1
            fractions.append(len(idx) / max(rig.n_vertices, 1))
    normals = sum(n is not None for n in (src.normal_offsets if src else []))
    # shape by shape: np.linalg.norm over the whole [K, n, 3] formed a squared copy and a [K, n] of norms
    # (370 MB beside the 275 MB rig on a 225k-vertex head: inspect peaked at 1.2 GB)
    still = [not d.any() for d in rig.deltas]
    return {**kinds, "meanListedFraction": float(np.mean(fractions)) if fractions else 0.0,
            "normalOffsets": int(normals),
            "inbetweens": {name: [{"name": b.name, "weight": float(b.weight)} for b in ibs]
                           for name, ibs in rig.inbetweens.items()},
            "zeroShapes": [name for name, zero in zip(rig.names, still, strict=True) if zero]}


def names_vs_arkit(names, report: dict | None = None) -> dict:
    """Shape names against the ARKit 52: present, missing, extra, misspelt, renamed (inexact mappings)."""
    report = report or {}
    present = [n for n in arkit.ARKIT_NAMES if n in names]
    extra = [n for n in names if n not in arkit.ARKIT_SET]
    lost = {given for given, _c, _k in report.get("conflicts", [])}  # mean a shape another channel has
    missing = [n for n in arkit.ARKIT_NAMES if n not in names]
    return {"present": len(present), "missing": missing,
            "missingRequired": [n for n in missing if n not in arkit.OPTIONAL_NAMES],
            "extra": extra, "misspelt": _misspellings([n for n in extra if n not in lost]),
            "renamed": [{"given": g, "canonical": c, "how": h} for g, c, h in report.get("inexact", [])]}


def channel_mapping(rig: FaceRig, report: dict) -> list[dict]:
    """How each channel of ``rig`` was mapped to ARKit: ``[{"channel", "arkit" (or None), "how", "label"}]``
    in channel order, ``how`` one of :data:`usdface.arkit.HOW_LABELS` (``label`` its words); a channel that
    lost to a better one for the same shape also names ``"kept"`` (the channel that has it)."""
    rows = report.get("channels")
    if rows is None:  # a rig not read by usd_rig (or an older report): the names are what they are
        tokens = rig.source.channel_tokens if rig.source and rig.source.channel_tokens else rig.names
        rows = [(t, n if n in arkit.ARKIT_SET else None, "exact" if t == n and n in arkit.ARKIT_SET
                 else ("unknown" if n not in arkit.ARKIT_SET else "spelling"))
                for t, n in zip(tokens, rig.names, strict=True)]
    kept = {given: k for given, _c, k in report.get("conflicts", [])}
    out = []
    for given, canonical, how in rows:
        row = {"channel": given, "arkit": canonical, "how": how, "label": arkit.HOW_LABELS.get(how, how)}
        if given in kept:
            row["kept"] = kept[given]
        out.append(row)
    return out


def _mesh_summary(rig: FaceRig, report: dict) -> dict:
    src = rig.source
    lo, hi = rig.neutral.min(axis=0), rig.neutral.max(axis=0)
    counts = src.face_vertex_counts if src is not None and src.face_vertex_counts is not None else None
    return {
        "prim": src.prim if src else rig.name, "name": rig.name, "vertices": rig.n_vertices,
        "faces": int(len(counts)) if counts is not None else int(len(rig.triangles)),
        "triangles": int(len(rig.triangles)),
        "polygons": {str(int(k)): int(v) for k, v in zip(*np.unique(counts, return_counts=True), strict=True)}
        if counts is not None else {"3": int(len(rig.triangles))},
        "shapes": rig.n_shapes, "skelRoot": src.skel_root if src else None,
        "skeleton": src.skeleton if src else None, "animation": src.animation if src else None,
        "boundsMetres": [lo.round(4).tolist(), hi.round(4).tolist()],
        "arkit": names_vs_arkit(rig.names, report), "storage": shape_storage(rig),
        "channelTokens": list(src.channel_tokens) if src else list(rig.names),
        "channels": channel_mapping(rig, report),
    }


def summarize_avatar(avatar: Avatar, layer_info: dict | None = None) -> dict:
    """Report dict for an avatar (see module doc); ``layer_info`` (from
    :func:`usdface.io.usd_rig.read_layer_info`) adds provenance, sublayers and variant selections."""
    layer_info = layer_info or {}
    written = layer_info.get("usdface") or {}
    flattened = layer_info.get("flattened") or {}
    baked = flattened.get("variant") in ("personalized", "generic") and not layer_info.get("variants")
    kind = ("usdface-fit" if isinstance(written, dict) and written.get("format") == "fit"
            else "usdface-flattened" if baked             # one file, a variant baked in: no layer over one
            else "usdface-layer" if written else "avatar")          # a fit's rig is no layer over an avatar
    out = {
        "file": avatar.file, "kind": kind,
        "upAxis": avatar.up_axis, "metersPerUnit": avatar.meters_per_unit, "defaultPrim": avatar.default_prim,
        "stageMetadata": dict(avatar.metadata.get("stage", {})),
        "notes": list(avatar.metadata.get("notes", [])),
        "meshes": [_mesh_summary(m, avatar.name_report.get(m.key, {}))
                   for m in avatar.meshes],
    }
    if layer_info:
        # the avatar revised or an input changed since the layer was written: its meshes are not its result
        out["notes"] += [*layer_info.get("avatarRevised", []), *layer_info.get("neutralNudged", []),
                         *layer_info.get("staleInputs", [])]
        # a recorded input gone (a take moved away) was listed as if it were there
        missing = layer_info.get("missingInputs", [])
        if missing:
            from .io.layers import recorded_path

            out["missingInputs"] = list(missing)
            folder = Path(str(layer_info.get("file", avatar.file or "."))).parent
            out["notes"] += [f"the recorded input {p} is missing (not at {recorded_path(folder, p)}): moved "
                             "or deleted since the layer was written; whether it changed cannot be told"
                             for p in missing]
        out["subLayers"] = layer_info.get("subLayers", [])
        out["provenance"] = layer_info.get("usdface", {})
        out["variants"] = layer_info.get("variants", {})
        out["schemas"] = {p: v["schemas"] for p, v in layer_info.get("schemas", {}).items()}
        if baked:
            out["flattened"] = dict(flattened)
        layouts = {}        # the landmark layouts authored (usdface landmarks -o, personalize --landmarks)
        for prim, v in layer_info.get("schemas", {}).items():
            if "UsdFaceLandmarksAPI" in v.get("schemas", []):
                values = v.get("values", {})
                layouts[prim] = {key: values.get(f"usdface:landmarks:{key}") for key in
                                 ("count", "epsilon", "alpha", "multicover", "symmetric", "solverStatus")}
        if layouts:
            out["landmarks"] = layouts
        played = _inspection_animation(avatar)
        if played:
            out["inspectionAnimation"] = played
    if kind == "avatar" and avatar.file:      # a DCC's export of a usdface layer reads as a plain avatar
        from .io.usd_rig import dcc_export_marks

        marks = dcc_export_marks(avatar.file)
        if marks:
            out["dccExport"] = {"usdfaceShapes": marks}
    return out


def _inspection_animation(avatar: Avatar) -> dict | None:
    """The inspection animation a ``personalize --inspect/--take`` layer plays (a SkelAnimation
    ``usdfaceInspection`` bound to the avatar's Skeleton): its prim, frames and seconds; None without one."""
    from .io.usd_inspection import ANIMATION_NAME

    paths = {m.source.animation for m in avatar.meshes if m.source is not None and m.source.animation}
    path = next((p for p in sorted(paths) if str(p).rsplit("/", 1)[-1] == ANIMATION_NAME), None)
    if path is None or not avatar.file:
        return None
    from pxr import UsdSkel

    from .io.usd_open import open_usd_stage

    stage = open_usd_stage(avatar.file, "layer", "check the path")
    anim = UsdSkel.Animation(stage.GetPrimAtPath(str(path)))
    if not anim:
        return None
    times = anim.GetBlendShapeWeightsAttr().GetTimeSamples()
    rate = stage.GetTimeCodesPerSecond() or 24.0
    return {"prim": str(path), "frames": len(times),
            "seconds": round((times[-1] - times[0]) / rate, 3) if len(times) > 1 else 0.0}


#: ``report["kind"]`` of a take with meshes, read whole as a capture (``fit TAKE``, ``personalize AVATAR
#: TAKE``).
TAKE_WITH_MESHES = "take with meshes"


def summarize_capture(capture: Capture, layer_info: dict | None = None) -> dict:
    """Report dict for a capture: frames per role with labels, shape names vs ARKit, mesh sizes."""
    frames = capture.frames
    roles = {}
    for role in sorted(set(frames.role)):
        sel = [i for i, r in enumerate(frames.role) if r == role]
        roles[role] = {"count": len(sel), "labels": [frames.label[i] for i in sel]}
    report = capture.metadata.get("name_report", {}) if isinstance(capture.metadata, dict) else {}
    out = {"file": capture.source, "kind": "capture", "vertices": int(len(capture.neutral)),
           "triangles": int(len(capture.triangles)), "frames": len(frames), "roles": roles,
           "shapes": len(capture.names), "arkit": names_vs_arkit(capture.names, report),
           "templateShapes": capture.template.n_shapes}
    whole = capture.whole_take
    if whole:            # what the text report says: --json said "capture" for a take read whole
        out["kind"] = TAKE_WITH_MESHES
        out["take"] = {"frames": int(whole["frames"]), "fps": float(whole["fps"])}
        out["neverAbove"] = _never_above(capture.names, capture.train.weights)
    else:                 # frames stored more than once (one scan for several requested shapes)
        from .personalize.api import duplicate_frames

        train = capture.train
        out["repeatedFrames"] = [[train.label[i] for i in g]
                                 for g in duplicate_frames(train.points, train.weights)]
    if layer_info:
        out["stageMetadata"] = layer_info.get("stage", {})
        out["schemas"] = {p: v for p, v in layer_info.get("schemas", {}).items()}
    return out


def inspect_file(path, name_map=None) -> dict:
    """Inspect an avatar / usdface layer (.usd, .usda, .usdc) or a capture (folder or capture.usda), or a
    take (read whole, as a capture: ``report["take"]``; a weights-only take, USD or a Live Link Face CSV:
    :func:`summarize_take`).

    ``name_map``: the studio's {channel: ARKit name} dict or JSON / CSV file, used to read an avatar
    (:func:`usdface.io.usd_rig.read_avatar`); validated first, also for a capture.

    Raises the readers' :class:`usdface.errors.UsdFaceError` subclasses on unreadable input.
    """
    import usdface.io as io

    from .io.file_kind import Kind, file_kind
    from .io.name_map import read_name_map

    name_map = read_name_map(name_map)
    path = Path(path)
    found = file_kind(path)  # held: the root layer is parsed once
    if found.kind is Kind.TAKE_FOLDER:
        return _summarize_whole_take(path)
    if found.kind in (Kind.CAPTURE_FOLDER, Kind.FOLDER):
        return summarize_capture(io.read_capture(path))
    if found.kind is Kind.LIVELINK_CSV or (found.kind is Kind.MISSING and path.suffix.lower() == ".csv"):
        from .io.take import read_take  # a Live Link Face recording (a missing one named by its reader)

        return summarize_take(read_take(path))
    from .io.usd_rig import read_avatar, read_layer_info

    info = read_layer_info(path, revisions=True)
    if found.kind is Kind.TAKE:  # read as every command that takes a capture reads it: whole
        return _summarize_whole_take(path, info)
    if found.kind is Kind.USD:      # the root layer leaves it open: ask the composed stage
        found = file_kind(path, compose=True)
    if found.kind is Kind.CAPTURE and found.by in ("format", "schema") and hasattr(io, "read_capture"):
        # (one told only by its layout is left to the avatar reader, which refuses it as a capture)
        return summarize_capture(io.read_capture(path), info)
    if found.kind is Kind.WEIGHTS_TAKE:
        from .io.take import read_take

        return summarize_take(read_take(path), info)
    if found.kind is Kind.ERROR_MAPS:
        return summarize_error_maps(path, info)
    from .errors import RigError

    try:
        avatar = read_avatar(path, name_map=name_map)
    except RigError as exc:         # meshes and no blend shape: said what the file is, not refused
        described = summarize_meshes_without_shapes(path, exc, info)
        if described is None:
            raise
        return described
    return summarize_avatar(avatar, info)


#: ``inspect``'s kind of a USD file with meshes but no blend shape (:func:`summarize_meshes_without_shapes`).
NO_BLEND_SHAPES = "meshes without blend shapes"


def summarize_meshes_without_shapes(path, refusal, layer_info: dict | None = None) -> dict | None:
    """Report dict for a USD file whose meshes carry no blend shape (a skinning test, a prop, a static
    scan): what it holds - units, per mesh its vertices, faces, SkelRoot and skeleton, each skeleton's joints
    - and, as a note, why it is no face rig (``refusal``, the avatar reader's RigError, with its fix). None
    when the file has a mesh with blend shapes or no mesh at all (the reader's refusal stands: it is what is
    wrong with the file)."""
    from pxr import Usd, UsdGeom, UsdSkel

    from .io.usd_open import open_usd_stage
    from .io.usd_rig import _has_blend_shapes, read_stage_metadata

    stage = open_usd_stage(path)
    prims = list(stage.Traverse(Usd.TraverseInstanceProxies()))
    meshes = [p for p in prims if p.IsA(UsdGeom.Mesh)]
    if not meshes or any(_has_blend_shapes(p) for p in prims):
        return None
    meta = read_stage_metadata(stage, path)
    mpu = meta["metersPerUnit"]
    cache = UsdGeom.BBoxCache(Usd.TimeCode.Default(), [UsdGeom.Tokens.default_, UsdGeom.Tokens.render])
    rows = []
    for prim in meshes:
        mesh = UsdGeom.Mesh(prim)
        points = mesh.GetPointsAttr().Get()
        counts = mesh.GetFaceVertexCountsAttr().Get()
        root = next((a for a in prim.GetPath().GetAncestorsRange()
                     if stage.GetPrimAtPath(a).IsA(UsdSkel.Root)), None)
        skeleton = UsdSkel.BindingAPI(prim).GetInheritedSkeleton()
        box = cache.ComputeWorldBound(prim).ComputeAlignedRange()
        rows.append({"prim": str(prim.GetPath()), "vertices": len(points) if points is not None else 0,
                     "faces": len(counts) if counts is not None else 0,
                     "skelRoot": None if root is None else str(root),
                     "skeleton": str(skeleton.GetPath()) if skeleton else None,
                     "boundsMetres": None if box.IsEmpty() else
                     [[round(float(v) * mpu, 4) + 0.0 for v in box.GetMin()],
                      [round(float(v) * mpu, 4) + 0.0 for v in box.GetMax()]]})
    skeletons = {str(p.GetPath()): len(UsdSkel.Skeleton(p).GetJointsAttr().Get() or [])
                 for p in prims if p.IsA(UsdSkel.Skeleton)}
    fix = f" (fix: {refusal.fix})" if refusal.fix else ""
    out = {"file": str(Path(path).absolute()), "kind": NO_BLEND_SHAPES, "upAxis": meta["upAxis"],
           "metersPerUnit": mpu, "defaultPrim": stage.GetRootLayer().defaultPrim or None,
           "stageMetadata": dict(meta["authored"]), "meshes": rows, "skeletons": skeletons,
           "notes": [f"no BlendShape: not a face rig usdface can personalize ({refusal.message}){fix}"]}
    if layer_info:
        out["subLayers"] = layer_info.get("subLayers", [])
    return out


def summarize_error_maps(path, layer_info: dict | None = None) -> dict:
    """Report dict for an error-map file (``usdface evaluate --usd``): per method the test frames, the mean
    of their per-vertex RMS error and the largest vertex error, mm (inspect refused the file as 'not an
    avatar')."""
    from .io.usd_error_maps import read_error_maps

    methods = {}
    for method, frames in read_error_maps(path).items():
        errs = list(frames.values())
        methods[method] = {"frames": len(errs),
                           "meanRmseMm": float(np.mean([np.sqrt(np.mean(e ** 2)) for e in errs])),
                           "maxMm": float(max(e.max() for e in errs))}
    out = {"file": str(Path(path).absolute()), "kind": "errorMaps", "methods": methods}
    if layer_info:
        out["stageMetadata"] = layer_info.get("stage", {})
    return out


#: A shape whose weight never exceeds this in a take is one ``capture select`` cannot pick (its default
#: threshold): listed by ``inspect`` so the recording can be repeated.
TAKE_PEAK = 0.5


def _never_above(names, weights) -> dict[str, float]:
    """``{shape: its largest weight}`` for the shapes a take's ``weights[F,K]`` never show above
    :data:`TAKE_PEAK`."""
    peak = weights.max(axis=0) if len(weights) else np.zeros(len(names))
    return {n: round(float(w), 3) for n, w in zip(names, peak, strict=True) if w < TAKE_PEAK}


def _never_above_line(report: dict) -> list[str]:
    never = report.get("neverAbove") or {}
    return [_names_line(f"never above {TAKE_PEAK}", [f"{n} {w:.2f}" for n, w in never.items()], 8)] if never \
        else []


def _summarize_whole_take(path: Path, layer_info: dict | None = None) -> dict:
    """A take with meshes as ``fit`` / ``personalize`` read it (whole, as a capture); one without its template
    rig, which they refuse, as a take (``capture select --template`` still picks its frames)."""
    from .io.take import capture_from_whole_take, read_take

    take = read_take(path)
    if take.points is not None and take.template is None:
        return summarize_take(take, layer_info)
    return summarize_capture(capture_from_whole_take(take), layer_info)


def summarize_take(take, layer_info: dict | None = None) -> dict:
    """Report dict for a take of weights only (``usdface anim import``): frames, rate, duration, shapes vs
    ARKit, and the shapes never above :data:`TAKE_PEAK` (what ``capture select`` could not pick)."""
    source = str(Path(take.source).absolute()) if take.source else take.source   # as an avatar's: absolute
    out = {"file": source, "kind": "take", "frames": len(take.weights), "fps": float(take.fps),
           "seconds": float(take.times[-1] - take.times[0]) if len(take.times) else 0.0,
           "shapes": len(take.names), "meshes": take.points is not None,
           "neverAbove": _never_above(take.names, take.weights),
           "arkit": names_vs_arkit(take.names, take.metadata.get("name_report", {}))}
    if layer_info:
        out["stageMetadata"] = layer_info.get("stage", {})
    return out


def _names_line(label: str, items, limit: int = 12) -> str:
    items = list(items)
    more = f" ... (+{len(items) - limit})" if len(items) > limit else ""
    return f"    {label} ({len(items)}): {', '.join(map(str, items[:limit]))}{more}"


def _frames_at(frames: int, fps: float) -> str:
    """'1056 frames at 15 fps'; one frame has no rate ('1 frame at 30 fps' was the default's, not the
    take's: a user trial)."""
    return f"{frames} frames at {fps:.3g} fps" if frames > 1 else f"{frames} frame (no rate)"


def format_report(report: dict) -> str:
    """Human-readable text for :func:`inspect_file`'s dict."""
    kind = report.get("kind")
    lines = [f"{report.get('file')}: {kind}"]
    if report.get("kind") == "take":
        head = f"  {_frames_at(report['frames'], report['fps'])} ({report['seconds']:.1f} s), " \
               f"{report['shapes']} shapes, "
        if report.get("meshes"):      # no template rig: read whole by fit / personalize, it is refused
            lines.append(head + "meshes but no template rig: 'fit' and 'personalize' need one (template/ or "
                         "the Template prim); 'capture select TAKE -o capture.usda --template CAPTURE' picks "
                         "its frames with another capture's")
        else:
            lines.append(head + "weights only: it plays on an avatar ('personalize AVATAR CAPTURE --take "
                         "TAKE'); 'capture select TAKE' shows which frames a capture would keep")
        lines += _never_above_line(report)
        lines += _arkit_lines(report["arkit"])
        return "\n".join(lines)
    if kind == NO_BLEND_SHAPES:
        lines.append(_units_line(report))
        for note in report.get("notes", []):
            lines.append(f"  note: {note}")
        for mesh in report["meshes"]:
            bound = ("" if mesh["skeleton"] is None else f", skinned by {mesh['skeleton']}") + (
                "" if mesh["skelRoot"] is None else f" under SkelRoot {mesh['skelRoot']}")
            lines.append(f"  mesh {mesh['prim']}: {mesh['vertices']} vertices, {mesh['faces']} faces, "
                         f"no blend shapes{bound}")
        for skel, joints in report.get("skeletons", {}).items():
            lines.append(f"  skeleton {skel}: {joints} joints")
        return "\n".join(lines)
    if kind == "errorMaps":
        lines[0] = (f"{report.get('file')}: error maps ('usdface evaluate --usd'; displayColor 0 mm blue, "
                    ">= 5 mm red)")
        for method, m in report["methods"].items():
            lines.append(f"  {method}: {m['frames']} test frame(s), mean RMSE {m['meanRmseMm']:.3f} mm, "
                         f"largest vertex error {m['maxMm']:.3f} mm")
        return "\n".join(lines)
    if kind in ("capture", TAKE_WITH_MESHES):
        if report.get("take"):
            lines.append(f"  a take of {_frames_at(report['take']['frames'], report['take']['fps'])}, "
                         "read whole: every frame trains ('fit TAKE', 'personalize AVATAR TAKE')")
            lines += _never_above_line(report)
        lines.append(f"  mesh: {report['vertices']} vertices, {report['triangles']} triangles")
        lines.append(f"  frames: {report['frames']} ("
                     + ", ".join(f"{r}: {v['count']}" for r, v in report["roles"].items()) + ")")
        for role, v in report["roles"].items():
            lines.append(_names_line(role, v["labels"], 8))
        groups = report.get("repeatedFrames") or []
        if groups:
            lines.append(f"  repeated exactly: {sum(len(g) - 1 for g in groups)} training frame(s) are "
                         f"copies of another ({len(groups)} group(s): one scan for several requested shapes)")
            for g in sorted(groups, key=len, reverse=True)[:3]:
                lines.append(_names_line("same frame", g, 6))
        lines.append(f"  shapes: {report['shapes']} (template {report['templateShapes']})")
        lines += _arkit_lines(report["arkit"])
        return "\n".join(lines)
    lines.append(_units_line(report))
    flat = report.get("flattened")
    if flat:      # it read as a usdface layer, and nothing said its shapes were the personalized ones
        what = ("the person's shapes baked in: personalize refuses it as the avatar"
                if flat["variant"] == "personalized" else
                "the avatar's own shapes: it personalizes as the avatar")
        source = os.path.normpath(Path(str(report.get("file"))).parent / str(flat.get("source")))
        lines.append(f"  flattened export (usdface export --flatten) of the {flat['variant']} variant of "
                     f"{source}: {what}")
    dcc = report.get("dccExport")
    if dcc:       # read as a plain avatar, its shapes are the personalized ones (Blender's re-export)
        lines.append(f"  DCC export of a usdface output layer (it has {dcc['usdfaceShapes'][0]}): the "
                     "variant the DCC composed baked in (personalized unless switched), no variant set or "
                     "provenance: personalize refuses it as the avatar")
    for note in report.get("notes", []):
        lines.append(f"  note: {note}")
    for mesh in report["meshes"]:
        st = mesh["storage"]
        lines.append(f"  mesh {mesh['prim']}: {mesh['vertices']} vertices, {mesh['faces']} faces "
                     f"({mesh['triangles']} triangles), {mesh['shapes']} shapes; skeleton {mesh['skeleton']}")
        lines.append(f"    storage: {st['sparse']} sparse, {st['dense']} dense, {st['denseIndexed']} dense "
                     f"pointIndices (listing every point); {st['meanListedFraction']:.0%} of points "
                     f"listed on average; {st['normalOffsets']} with normalOffsets")
        if st["inbetweens"]:
            lines.append("    inbetweens: " + ", ".join(
                f"{k} @ " + "/".join(f"{b['weight']:g}" for b in v) for k, v in st["inbetweens"].items()))
        if st["zeroShapes"]:
            lines.append(_names_line("zero shapes", st["zeroShapes"]))
        elsewhere = {n: other["prim"] for other in reversed(report["meshes"]) if other is not mesh
                     for n in set(arkit.ARKIT_NAMES) - set(other["arkit"]["missing"])}
        lines += _arkit_lines(mesh["arkit"], renamed=not mesh.get("channels"), elsewhere=elsewhere)
        lines += _channel_lines(mesh.get("channels", []))
    if report.get("provenance"):
        prov = report["provenance"]
        # what the file records (a fit rig from before 0.1's provenance has its method only)
        parts = [f"{label} {prov[key]!r}" if key == "command" else f"{label} {prov[key]}"
                 for key, label in (("version", "version"), ("method", "method"), ("command", "command"),
                                    ("createdAt", "created")) if prov.get(key) is not None]
        lines.append("  usdface layer: " + ", ".join(parts))
        if prov.get("workingDirectory"):      # where the command ran (its relative paths start there)
            lines.append(f"    command run in {prov['workingDirectory']}")
        gone = set(report.get("missingInputs", []))      # said as such, not listed as if there
        for src, digest in zip(prov.get("inputs", []), prov.get("inputDigests", []), strict=False):
            lines.append(f"    input {src} sha256 {str(digest)[:16]}..."
                         + (" (missing)" if src in gone else ""))
        if prov.get("capture"):              # a fit rig: the capture it was fitted on
            lines.append(f"    capture {prov['capture']} sha256 {str(prov.get('captureDigest', ''))[:16]}..."
                         + (" (missing)" if prov["capture"] in gone else ""))
        if prov.get("pinsDigest"):           # ... and the pins file it kept
            pins = (prov.get("parameters") or {}).get("pins")
            lines.append(f"    pins {pins} sha256 {str(prov['pinsDigest'])[:16]}...")
    if report.get("inspectionAnimation"):
        played = report["inspectionAnimation"]
        prov = report.get("provenance") or {}
        gone = " (missing now; the layer holds its frames)" if prov.get("take") in report.get(
            "missingInputs", []) else ""
        parts = (["the capture's test expressions"] if prov.get("fitTestExpressions") else []) + (
            [f"the take {prov['take']}{gone}"] if prov.get("take") else [])
        what = ", then ".join(parts) or "recorded frames"
        lines.append(f"  inspection animation {played['prim']}: {played['frames']} frames, "
                     f"{played['seconds']:g} s ({what}; usdview plays it on the personalized avatar)")
    for prim, lay in report.get("landmarks", {}).items():
        extra = "".join(f", {key} {lay[key]:g}" for key in ("epsilon", "alpha")
                        if isinstance(lay.get(key), int | float))
        if (lay.get("multicover") or 1) > 1:
            extra += f", multi-cover {lay['multicover']}"
        if lay.get("symmetric"):
            extra += ", symmetric"
        lines.append(f"  landmark layout {prim}: {lay.get('count')} landmarks{extra}; solver "
                     f"{lay.get('solverStatus')} ('usdface render FILE -o OUT.png --landmarks' draws it)")
    for prim, sets in report.get("variants", {}).items():
        for name, v in sets.items():
            lines.append(f"  variant set {prim}:{name} = {v['selection']} (of {', '.join(v['variants'])})")
    return "\n".join(lines)


def _arkit_lines(a: dict, renamed: bool = True, elsewhere: dict | None = None) -> list[str]:
    """The ARKit lines of one mesh (or rig). ``elsewhere``: ``{shape: the first other mesh of the file that
    carries it}``; this mesh's missing shapes found there are named as carried by it, not listed as missing
    (a teeth mesh's 5 jaw shapes read 'missing (47): eyeBlinkLeft, ...' beside the Head's 52/52: a TD's
    trial, stop 53)."""
    elsewhere = elsewhere or {}
    carried = [n for n in a["missing"] if n in elsewhere]
    missing = [n for n in a["missing"] if n not in elsewhere]
    owners = list(dict.fromkeys(elsewhere[n] for n in carried))
    lines = [f"    ARKit: {a['present']}/52 present" + (
        f" (the other {len(carried)} on {', '.join(owners)})" if carried and not missing else "")]
    if missing:
        lines.append(_names_line("missing", missing))
        if carried:
            lines.append(_names_line(f"on {', '.join(owners)}", carried))
    if a["extra"]:
        lines.append(_names_line("extra (not ARKit)", a["extra"]))
    if a["misspelt"]:
        lines.append(_names_line("misspelt?", [f"{k} -> {v}" for k, v in a["misspelt"].items()]))
    if a["renamed"] and renamed:
        # Live Link Face's CSV columns are the ARKit names capitalised (EyeBlinkLeft): its convention, one
        # line, not 52 "renamed (spelling)" entries; any other inexact mapping is listed
        livelink = [r for r in a["renamed"] if r["given"] == arkit.livelink_name(r["canonical"])]
        others = [r for r in a["renamed"] if r not in livelink]
        if livelink:
            r = livelink[0]
            lines.append(f"    capitalised ARKit names (Live Link Face's columns): {len(livelink)} "
                         f"({r['given']} is {r['canonical']})")
        if others:
            lines.append(_names_line("renamed", [f"{r['given']} -> {r['canonical']} ({r['how']})"
                                                 for r in others], 6))
    return lines


def _channel_lines(channels: list[dict]) -> list[str]:
    """How the channels were mapped: the exact ones counted, every other one listed with how."""
    if not channels:
        return []
    exact = sum(c["how"] == "exact" for c in channels)
    lines = [f"    channel names: {exact} of {len(channels)} exact ARKit names"]
    for c in channels:
        if c["how"] == "exact":
            continue
        if c["arkit"]:
            lines.append(f"      {c['channel']} -> {c['arkit']} ({c['label']})")
        elif c.get("kept"):
            lines.append(f"      {c['channel']}: unmapped, same shape as {c['kept']!r} (kept)")
        else:
            lines.append(f"      {c['channel']}: unmapped (not an ARKit shape; map it with --name-map)")
    return lines


def _units_line(report: dict) -> str:
    """The ``units:`` line of an avatar and of a file without blend shapes alike: the latter printed
    ``metersPerUnit 1.0, ... defaultPrim root`` where an avatar prints ``metersPerUnit 1.0 (m), ...
    defaultPrim /root`` (a trial's note, stop 42)."""
    mpu = report["metersPerUnit"]
    unit = {0.01: "cm", 1.0: "m", 0.001: "mm"}.get(mpu, f"{mpu} m")
    prim = report.get("defaultPrim")
    if isinstance(prim, str) and prim and not prim.startswith("/"):
        prim = "/" + prim                                   # the root layer's defaultPrim is a name
    return f"  units: metersPerUnit {mpu} ({unit}), upAxis {report['upAxis']}, defaultPrim {prim}"
