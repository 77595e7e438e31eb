"""Capture folders (OBJ meshes + JSON weights) <-> :class:`usdface.model.Capture`.

Folder layout (see ``docs/capture-format.md``)::

    capture/
      neutral.obj                  the person's neutral scan (capture topology, metres)
      template/neutral.obj         the generic template rig on the same topology: its neutral ...
      template/<shape>.obj         ... and one full target mesh per ARKit shape (not deltas)
      train/<NNN>_<shape>.obj      training expressions: the person performing <shape> ...
      train/<NNN>_<shape>.json     ... and the weights the phone reported: {"blendShapes": {name: w, ...}}
      test/<NNN>.obj + .json       held-out test expressions, for evaluation only

Shape names (template file stems and JSON keys) may use any of the three ARKit spellings and are mapped to the
canonical name (:mod:`usdface.arkit`). ``Capture.names`` is the template's shape order: ARKit order for ARKit
shapes, then unknown names (kept, with a warning) sorted. Missing shapes are allowed and listed in
``capture.metadata["name_report"]["missing"]``.
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path

import numpy as np

from ..arkit import ARKIT_NAMES, match_names
from ..errors import CaptureError, GeometryError, InputFileError, warn
from ..model import Capture, FaceRig, Frames
from .atomic import check_output_dir, replace_dir_atomically
from .file_kind import folder_files
from .mesh_io import read_obj, write_obj

__all__ = ["read_capture_folder", "write_capture_folder", "read_weights_json", "order_names",
           "ROLES"]

#: Frame roles, in the order frames are stored.
ROLES = ("train", "test")
_ARKIT_INDEX = {n: i for i, n in enumerate(ARKIT_NAMES)}


def order_names(names) -> list[str]:
    """Canonical shape order: ARKit documentation order for ARKit names, then other names sorted."""
    return sorted(names, key=lambda n: (0, _ARKIT_INDEX[n], "") if n in _ARKIT_INDEX else (1, 0, n))


#: the largest weight read as an ARKit weight that overshoots (clipped to 1, with a warning): ARKit and Live
#: Link Face report 0..1 and overshoot by a few per cent (1.059 in the bench takes); a weight twice the full
#: shape is another scale (percent, 0..100), which clipping turned into every shape at 1
WEIGHT_SCALE_LIMIT = 2.0


def refuse_weights_scale(weights, names, path, *, frame=lambda f: f"frame {f}", prim=None,
                         fix_where: str = "the weights") -> None:
    """Refuse weights ``weights[F, K]`` (columns ``names``) on another scale than ARKit's 0..1 (see
    :data:`WEIGHT_SCALE_LIMIT`), naming the largest weight, its frame (``frame(f)``: the row's label;
    ``None``: the file is the frame) and shape: until stop 45 a capture written in percent was clipped to 1
    with a warning and fitted (train RMSE 2.0 mm against the same capture's 0.2)."""
    weights = np.asarray(weights)
    if not (weights.size and weights.max() > WEIGHT_SCALE_LIMIT):
        return
    f, k = np.unravel_index(int(np.argmax(weights)), weights.shape)
    largest = float(weights[f, k])
    where = names[k] if frame is None else f"{frame(int(f))}, {names[k]}"
    percent = largest <= 100 * WEIGHT_SCALE_LIMIT
    raise CaptureError(f"weight {largest:.4g} ({where}): ARKit weights run from 0 to 1 (a phone overshoots "
                       f"by a few per cent), so these are on another scale"
                       + (" (percent, 0..100?)" if percent else ""), path=path, prim=prim,
                       fix=(f"divide {fix_where} by 100" if percent else f"rescale {fix_where} to 0..1")
                       + " before reading them")


@functools.lru_cache(maxsize=16)
def _weight_names(names: tuple[str, ...]):
    """:func:`usdface.arkit.match_names` of one frame's weight names, kept for the next frames: a capture's
    frames list the same names (dev1: 81 files, 0.02-0.03 s of mapping the same 52 names again). Read only
    (its ``names``, ``canonical`` and ``duplicates``)."""
    return match_names(list(names))


def _weights_found(data) -> str:
    """What a weights JSON without a ``blendShapes`` object holds instead, for its refusal (a user trial, stop
    50: a key spelt ``BlendShapes``, a list of ``{"name", "value"}`` and the weights at the top level were all
    told 'no "blendShapes" object', the first two beside the key the message said was missing)."""
    def kind(value) -> str:
        return {list: "array", str: "string", bool: "boolean", type(None): "null"}.get(type(value), "number")

    if not isinstance(data, dict):
        return f" (it holds a JSON {kind(data)}, not an object)"
    if "blendShapes" in data:
        return f" (its \"blendShapes\" is a JSON {kind(data['blendShapes'])}, not an object of name: weight)"
    other = next((k for k in data if isinstance(k, str) and k.lower() == "blendshapes"), None)
    if other is not None:
        return f" (it has {other!r}: the key is spelt \"blendShapes\")"
    if data and all(isinstance(v, int | float) and not isinstance(v, bool) for v in data.values()):
        return f" (its {len(data)} weights are at the top level, not inside \"blendShapes\")"
    return ""


def read_weights_json(path) -> dict[str, float]:
    """Read one frame's weights ``{"blendShapes": {name: weight}}`` -> {canonical name: weight}.

    Any of the three ARKit spellings is accepted; unknown names are kept as they are. Raises InputFileError
    (missing file, invalid JSON) or CaptureError (no ``blendShapes`` object, non-numeric or NaN/inf weights,
    the same shape under two spellings), naming the file.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_bytes())
    except FileNotFoundError:
        raise InputFileError("weights file not found", path=path,
                             fix="every frame .obj needs a .json of the same name with its weights") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(f"cannot read weights file ({exc})", path=path, fix="check the file") from None
    except json.JSONDecodeError as exc:
        raise InputFileError(f"invalid JSON ({exc.msg} at line {exc.lineno})", path=path,
                             fix="write the weights as {\"blendShapes\": {\"jawOpen\": 0.8, ...}}") from None
    shapes = data.get("blendShapes") if isinstance(data, dict) else None
    if not isinstance(shapes, dict):
        raise CaptureError(f"no \"blendShapes\" object in the weights JSON{_weights_found(data)}", path=path,
                           fix="write the weights as {\"blendShapes\": {\"jawOpen\": 0.8, ...}}")
    match = _weight_names(tuple(shapes))
    if match.duplicates:
        spellings = [n for n, c in zip(match.names, match.canonical, strict=True) if c in match.duplicates]
        raise CaptureError(f"the same shape appears under several names: {', '.join(spellings)}", path=path,
                           fix="keep one spelling per shape")
    out = {}
    for given, canonical in zip(match.names, match.canonical, strict=True):
        w = shapes[given]
        try:
            value = float(w) if isinstance(w, int | float) and not isinstance(w, bool) else np.nan
        except OverflowError:  # a huge JSON integer
            value = np.inf
        if not math.isfinite(value):   # a Python float (np.isfinite per scalar: 20 ms of dev1's 81 frames)
            raise CaptureError(f"weight of {given!r} is not a finite number: {str(w)[:20]!r}", path=path,
                               fix="weights must be numbers in [0, 1]")
        out[canonical] = value
    return out


def _check_topology(points, triangles, ref_points, ref_triangles, path, what, ref_path=None):
    """Refuse a capture mesh whose topology is not ``what``'s (the reference at ``ref_path``); when either
    file ends in the middle of a line, the one cut off is named (a neutral.obj cut inside its last face read,
    and the first mesh compared with it was blamed)."""
    from .mesh_io import cut_off_error, ends_mid_line

    error = None
    if points.shape != ref_points.shape:
        error = GeometryError(f"{len(points)} vertices, but {what} has {len(ref_points)}", path=path,
                              fix="capture meshes must share the neutral's topology (vertices, order)")
    elif len(triangles) < len(ref_triangles) and np.array_equal(triangles, ref_triangles[:len(triangles)]):
        # the reference's first faces and no more: cut at a line end, which ends_mid_line cannot see (stop 52:
        # 'faces differ from neutral.obj's')
        error = GeometryError(f"only the first {len(triangles)} of {what}'s {len(ref_triangles)} triangles: "
                              "the file was probably cut off (an interrupted copy or write, a full disk)",
                              path=path, fix="copy or export the file again")
    elif not np.array_equal(triangles, ref_triangles):
        error = GeometryError(f"faces differ from {what}'s", path=path,
                              fix="every capture mesh must share the neutral's topology (same faces)")
    if error is not None:          # a file cut off inside its faces parses, with faces missing or wrong
        if ref_path is not None and ends_mid_line(ref_path) and not ends_mid_line(path):
            other = Path(path).relative_to(Path(ref_path).parent) if Path(path).is_relative_to(
                Path(ref_path).parent) else Path(path).name
            raise cut_off_error(GeometryError(f"its faces differ from {other}'s", path=ref_path), ref_path)
        raise cut_off_error(error, path) if ends_mid_line(path) else error


def _read_mesh(path: Path, faces, ref_points, what: str):
    """``read_obj(path)`` of a capture mesh compared with ``what`` (``ref_points[n, 3]``): a file with no face
    line and fewer vertices than the reference is told as cut off (at a line end: :func:`ends_mid_line` cannot
    see it), not as a mesh exported without faces (stop 52)."""
    try:
        return read_obj(path, faces=faces)
    except GeometryError as exc:
        if exc.message != "mesh has no faces":
            raise
        try:
            kept = sum(line[:2] in (b"v ", b"v\t") for line in Path(path).read_bytes().splitlines())
        except OSError:
            raise exc from None
        if kept >= len(ref_points):
            raise
        raise GeometryError(f"only {kept} of {what}'s {len(ref_points)} vertices and no faces: the file was "
                            "probably cut off (an interrupted copy or write, a full disk)", path=path,
                            fix="copy or export the file again") from None


def missing_layout(root: Path, what: str, fix: str | None = None) -> CaptureError:
    """The refusal of a capture folder without ``what`` (``neutral.obj``, ``template/neutral.obj``); when the
    folder is a capture's own ``train/``, ``test/`` or ``template/`` (tab completion stops there: 'usdface fit
    capture/train' said only 'missing neutral.obj'), it names the capture to pass instead."""
    folder = Path(root).absolute()
    parent = folder.parent
    if (folder.name in ("train", "test", "template") and (parent / "neutral.obj").is_file()
            and (parent / "template").is_dir()):
        return CaptureError(f"missing {what}: this is the {folder.name}/ folder of the capture {parent}",
                            path=root, fix=f"pass the capture folder itself: {parent}")
    inner = _captures_inside(folder) if what == "neutral.obj" else []
    if inner:
        # a person's folder (avatar.usdc + capture/, or the sample's sample_assets/) given for its capture
        # said only 'missing neutral.obj' (stop 47, h52): name the capture folder inside it
        more = f" (+{len(inner) - 3})" if len(inner) > 3 else ""
        listed = ", ".join(f"{c.name}/" for c in inner[:3]) + more
        return CaptureError(f"missing {what}: the capture is in its subfolder {listed}", path=root,
                            fix=f"pass the capture folder itself: {Path(root) / inner[0].name}")
    return CaptureError(f"missing {what}", path=root,
                        fix=fix or "see docs/capture-format.md: neutral.obj, template/, train/, test/")


def _captures_inside(folder: Path) -> list[Path]:
    """The capture folders (``neutral.obj`` + ``template/``) directly inside ``folder``, sorted; [] when it
    cannot be listed."""
    try:
        children = sorted(c for c in folder.iterdir() if not c.name.startswith(".") and c.is_dir())
    except OSError:
        return []
    return [c for c in children if (c / "neutral.obj").is_file() and (c / "template").is_dir()]


def refuse_suffix_case(folders, suffixes: tuple[str, ...]) -> None:
    """Refuse (CaptureError) files in ``folders`` whose extension is one of ``suffixes`` in another case
    (``jawOpen.OBJ``, ``000.JSON``, as some Windows tools write them): the folder is read by lower-case
    extension, so a template target so named was left out without a word (the capture lost ``jawOpen``,
    its frames' weights set aside as a shape the template lacks), a frame's scan was reported missing
    beside its ``.json``, and a ``NEUTRAL.OBJ`` folder was told it has no ``neutral.obj``."""
    for folder in folders:
        if not Path(folder).is_dir():
            continue
        odd = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in suffixes
                     and p.suffix not in suffixes and not p.name.startswith("."))
        if odd:
            more = f" (and {len(odd) - 1} more)" if len(odd) > 1 else ""
            raise CaptureError(f"{odd[0].name}{more}: a {odd[0].suffix} extension is read only in lower case "
                               f"({odd[0].suffix.lower()})", path=folder,
                               fix=f"rename the files to lower-case extensions (e.g. "
                                   f"{odd[0].with_suffix(odd[0].suffix.lower()).name})")


def _template(root: Path, neutral, triangles, report: dict, faces: dict | None = None) -> FaceRig:
    tdir = root / "template"
    tneutral_path = tdir / "neutral.obj"
    if not tneutral_path.is_file():
        raise missing_layout(root, "template/neutral.obj",
                             fix="add the template rig: template/neutral.obj + template/<shape>.obj")
    tneutral, ttris = _read_mesh(tneutral_path, faces, neutral, "neutral.obj")
    _check_topology(tneutral, ttris, neutral, triangles, tneutral_path, "neutral.obj", root / "neutral.obj")
    files = [p for p in folder_files(tdir, "*.obj") if p.stem != "neutral"]
    if not files:
        raise CaptureError("template has no shapes", path=tdir,
                           fix="add one template/<shape>.obj per ARKit shape")
    match = match_names([p.stem for p in files])
    if match.duplicates:
        spellings = [p.name for p, c in zip(files, match.canonical, strict=True) if c in match.duplicates]
        raise CaptureError(f"the same shape has several template files: {', '.join(spellings)}", path=tdir,
                           fix="keep one file per shape")
    if match.unknown:
        warn(f"{tdir}: template shapes that are not ARKit names (kept as they are): "
             f"{', '.join(match.unknown)}")
    report.update(inexact=match.inexact, unknown=match.unknown, missing=match.missing)
    by_name = dict(zip(match.canonical, files, strict=True))
    names = order_names(by_name)
    targets = np.empty((len(names),) + tneutral.shape)
    for k, name in enumerate(names):
        pts, tris = _read_mesh(by_name[name], faces, tneutral, "template/neutral.obj")
        _check_topology(pts, tris, tneutral, ttris, by_name[name], "template/neutral.obj", tneutral_path)
        targets[k] = pts
    return FaceRig(tneutral, ttris, names, targets - tneutral, name="template")


def _frames(root: Path, neutral, triangles, names: list[str], metadata: dict,
            faces: dict | None = None) -> Frames:
    points, weights, roles, labels, extra = [], [], [], [], {}
    clipped, absent = [], set()
    index = {n: k for k, n in enumerate(names)}
    for role in ROLES:
        folder = root / role
        if not folder.is_dir():
            continue
        orphans = [j for j in folder_files(folder, "*.json") if not j.with_suffix(".obj").is_file()]
        if orphans:                     # a frame's weights without its scan (as its scan without weights)
            raise CaptureError(f"{role}/{orphans[0].name} has no scan {orphans[0].with_suffix('.obj').name} "
                               f"({len(orphans)} such weight file(s))", path=root,
                               fix="restore the frame's OBJ, or remove its .json too")
        for obj in folder_files(folder, "*.obj"):
            pts, tris = _read_mesh(obj, faces, neutral, "neutral.obj")
            _check_topology(pts, tris, neutral, triangles, obj, "neutral.obj", root / "neutral.obj")
            w = read_weights_json(obj.with_suffix(".json"))
            _refuse_misspelt_weight(root, f"{role}/{obj.with_suffix('.json').name}", w, index)
            row = np.zeros(len(names))
            for name, value in w.items():
                if name in index:
                    row[index[name]] = value
                else:
                    extra.setdefault(name, {})[len(points)] = value
            absent.update(n for n in names if n not in w)
            refuse_weights_scale(row[None], names, obj.with_suffix(".json"), frame=None,
                                 fix_where="every frame's weights")
            if row.min() < 0.0 or row.max() > 1.0:
                clipped.append(obj.with_suffix(".json").name)
                row = np.clip(row, 0.0, 1.0)
            points.append(pts)
            weights.append(row)
            roles.append(role)
            labels.append(obj.stem)
    if not points:
        raise CaptureError("no frames: train/ and test/ hold no .obj files", path=root,
                           fix="add train/<NNN>_<shape>.obj + .json frames")
    if clipped:
        warn(f"{root}: weights outside [0, 1] clipped in {len(clipped)} frame(s): "
             f"{', '.join(clipped[:5])}{' ...' if len(clipped) > 5 else ''}")
    if extra:
        warn(f"{root}: frame weights for shapes the template lacks (kept in "
             f"metadata['extra_weights'], "
             f"not fitted): {', '.join(sorted(extra))}")
        metadata["extra_weights"] = {n: np.array([v.get(f, 0.0) for f in range(len(points))])
                                     for n, v in sorted(extra.items())}
    metadata["weights_absent"] = sorted(absent, key=names.index)  # template shapes some JSON did not list (0)
    metadata["weights_clipped"] = clipped
    return Frames(np.stack(points), np.stack(weights), roles, labels)


def read_capture_folder(path) -> Capture:
    """Read a capture folder into a :class:`~usdface.model.Capture` (points in the files' units: metres).

    ``capture.names`` = template shape order (canonical names), which is also the column order of
    ``capture.frames.weights[F, K]``; frames are train then test, each sorted by file name, labelled by file
    stem. ``capture.metadata`` holds ``name_report`` (inexact / unknown / missing names), ``counts`` and
    ``source``.

    Raises InputFileError (missing/unreadable files), CaptureError (layout, JSON, names) or GeometryError
    (NaN/inf, empty, vertex count or faces differing from ``neutral.obj``), naming the offending file.
    Weights outside [0, 1] are clipped with a warning.
    """
    root = Path(path)
    if not root.is_dir():
        raise InputFileError("capture folder not found" if not root.exists() else "not a folder", path=root,
                             fix="pass the capture folder (neutral.obj, template/, train/, test/)")
    refuse_suffix_case([root, root / "template", *(root / role for role in ROLES)], (".obj", ".json"))
    neutral_path = root / "neutral.obj"
    if not neutral_path.is_file():
        raise missing_layout(root, "neutral.obj")
    faces: dict = {}                   # the neutral's face block: the other meshes' faces are the same bytes
    neutral, triangles = read_obj(neutral_path, faces=faces)
    report: dict = {}
    template = _template(root, neutral, triangles, report, faces)
    metadata: dict = {"source": str(root), "name_report": report, "units": "m"}
    frames = _frames(root, neutral, triangles, template.names, metadata, faces)
    _refuse_misspelt_template(root, report.get("unknown") or [], metadata.get("extra_weights") or {})
    metadata["counts"] = {role: int(sum(r == role for r in frames.role)) for role in ROLES}
    return Capture(neutral, triangles, template, frames, list(template.names), source=str(root),
                   metadata=metadata)


def _refuse_misspelt_weight(root: Path, where: str, weights: dict, index: dict) -> None:
    """A frame's weight whose name is a misspelling of a template shape the frame does not give
    (:func:`usdface.arkit.lookalike`: ``jawOpn``, ``STU_jawOpen``): the shape's weight in the frame would be
    read as 0 and its value set aside, so the fit would learn the scan's motion from the other shapes.
    Refused, naming the file and the rename. Not a misspelling: a side or combined form of it (``mouthSmile``
    for the two ``mouthSmile*``, ``cheekPuffLeft`` beside ``cheekPuff``, a sparse frame that lists neither):
    those stay extra weights, with the reader's warning (a review)."""
    from ..arkit import lookalike, spelling_key

    def core(n: str) -> str:
        return spelling_key(n).replace("left", "").replace("right", "")

    for name in weights:
        if name in index:
            continue
        meant = lookalike(name)
        if meant is None or meant not in index or meant in weights or core(name) == core(meant):
            continue
        raise CaptureError(f"{where}: weight {name!r} is not a template shape, and the frame gives no "
                           f"{meant!r}, which the template has: misspelt?", path=root,
                           fix=f"rename the weight {name!r} to {meant!r} in {where} (and in any other "
                           "frame that spells it so)")


def _refuse_misspelt_template(root: Path, unknown, extra_weights) -> None:
    """A template file whose name is a near-miss of an ARKit name that the frames' weights use while the
    template lacks it (``template/jawOpn.obj``, weights ``jawOpen``): every jawOpen weight would be dropped
    and jawOpn never fitted. Refused, with the rename."""
    import difflib

    from ..arkit import MISSPELLING_CUTOFF

    for name in unknown:
        hit = difflib.get_close_matches(name, list(extra_weights), n=1, cutoff=MISSPELLING_CUTOFF)
        if hit:
            raise CaptureError(f"template/{name}.obj is not an ARKit name, and the frames' weights name "
                               f"{hit[0]!r}, which the template lacks: misspelt?", path=root,
                               fix=f"rename template/{name}.obj to template/{hit[0]}.obj")


def _weights_json(names, row) -> str:
    shapes = {n: float(w) for n, w in zip(names, row, strict=True)}
    return json.dumps({"blendShapes": shapes}, indent=1) + "\n"


def refuse_whole_take(capture: Capture, path) -> None:
    """A take read whole (``capture.whole_take``: every frame trains, weighted as a take) is not written or
    imported as a capture (``path``: the output, or the take being imported): read back, its every frame would
    pass for a frame picked one per shape, fitted equally weighted without the take's noise model - another
    fit than ``fit TAKE`` gives. :class:`CaptureError` with the fix."""
    if capture.whole_take:
        raise CaptureError(f"a take, not a capture: a take read whole ({len(capture.train)} frames, every "
                           "frame trains); as a capture its every frame would pass for a frame picked one "
                           "per shape and lose the take's whole-take fit (frame weighting, --every)",
                           path=path,
                           fix="pick its frames with 'usdface capture select TAKE -o capture.usda', pass "
                               "the take itself to fit / personalize, or write it as a take "
                               "(usdface.io.take.write_take_usd / write_take_folder)")


def write_capture_folder(capture: Capture, path, force: bool = False) -> Path:
    """Write ``capture`` as a capture folder (the layout :func:`read_capture_folder` reads).

    Template shapes are written as full targets (``template.neutral + deltas``) named by ``capture.names``;
    frames as ``<role>/<label>.obj`` + ``.json``. The folder is assembled next to the destination and renamed
    into place (:func:`usdface.io.atomic.replace_dir_atomically`), so a failure never leaves a half-written
    capture. Refuses an existing, non-empty destination unless ``force`` (OutputExistsError). Points and
    weights round-trip exactly; template deltas to float rounding of ``(neutral + delta) - neutral``.
    """
    refuse_whole_take(capture, path)
    dest = check_output_dir(path, force)
    labels = [f"{r}/{lab}" for r, lab in zip(capture.frames.role, capture.frames.label, strict=True)]
    if len(set(labels)) != len(labels):
        raise CaptureError("two frames share a role and label (they would overwrite each other)", path=dest,
                           fix="give every frame a unique label")
    with replace_dir_atomically(dest, force=force) as tmp:
        tris = capture.triangles
        write_obj(tmp / "neutral.obj", capture.neutral, tris)
        tpl = capture.template
        write_obj(tmp / "template" / "neutral.obj", tpl.neutral, tpl.triangles)
        for k, name in enumerate(tpl.names):
            write_obj(tmp / "template" / f"{name}.obj", tpl.neutral + tpl.deltas[k], tpl.triangles)
        fr = capture.frames
        for f in range(len(fr)):
            base = tmp / fr.role[f] / fr.label[f]
            write_obj(base.with_suffix(".obj"), fr.points[f], tris)
            base.with_suffix(".json").write_text(_weights_json(capture.names, fr.weights[f]))
    return dest
