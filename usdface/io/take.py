"""Continuous takes (a time-sampled face mesh plus per-frame weights) <-> :class:`Take`, and the capture made
from a take by frame selection (:func:`capture_from_take`, rule in :mod:`usdface.take_select`).

A take comes in three forms (:func:`read_take` dispatches):

* **USD take** (``.usda``/``.usdc``/``.usd``, or packaged as ``.usdz``): a Mesh whose ``points`` are
  time-sampled (usdface's own layout, :func:`write_take_usd`: ``/Take/Frames``; otherwise the mesh with the
  most time samples), with per-frame weights either on that mesh (``usdface:frames:weights`` +
  ``usdface:frames:names``) or in a ``SkelAnimation`` (``blendShapes`` + time-sampled
  ``blendShapeWeights``, read at each mesh time code); optional ``Neutral`` mesh and ``Template`` SkelRoot
  as in capture.usda.
* **OBJ sequence + Live Link Face CSV** (a folder): ``frames/*.obj`` (or ``*.obj``; frame number = the
  trailing integer of the file name) and one ``*.csv``; optional ``neutral.obj`` and ``template/`` as in a
  capture folder. OBJ k is matched to CSV row k when the counts agree, else OBJ number ``n`` to row
  ``n - first number``.
* **Live Link CSV alone** (weights only; no mesh, so it cannot become a capture).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..arkit import ARKIT_NAMES, match_names
from ..errors import CaptureError, GeometryError, InputFileError, warn
from ..model import Capture, FaceRig, Frames
from .capture_folder import refuse_weights_scale
from .mesh_io import read_obj

__all__ = ["Take", "read_take", "read_take_usd", "read_take_folder", "write_take_usd", "write_take_folder",
           "capture_from_take", "capture_from_whole_take", "is_take", "probe_take", "check_take_path",
           "whole_take_playback", "missing_arkit_weights", "TAKE_PRIM"]

TAKE_PRIM = "/Take"


@dataclass
class Take:
    """A continuous take: ``weights[F, K]`` for ``names[K]`` at ``times[F]`` seconds; ``points[F, n, 3]``
    metres and ``triangles[t, 3]`` (None for weights-only takes); optional person ``neutral[n, 3]`` and
    generic ``template`` rig on the same topology."""

    weights: np.ndarray
    names: list[str]
    times: np.ndarray
    points: np.ndarray | None = None
    triangles: np.ndarray | None = None
    neutral: np.ndarray | None = None
    template: FaceRig | None = None
    source: str = ""
    metadata: dict = field(default_factory=dict)

    def __post_init__(self):
        self.weights = np.array(self.weights, dtype=np.float64)
        self.times = np.array(self.times, dtype=np.float64)
        self.names = [str(n) for n in self.names]

    @property
    def fps(self) -> float:
        """Median frame rate (frames per second), :func:`usdface.io.livelink.median_fps`."""
        from .livelink import median_fps

        return median_fps(self.times)

    def __len__(self) -> int:
        return int(self.weights.shape[0])


# ----------------------------------------------------------------------------------------------- reading
def missing_arkit_weights(take, names, wanted=ARKIT_NAMES, *, of: str = "", effect: str,
                          effect_none: str = "", fix: str) -> tuple[list[str], str | None]:
    """The ARKit shapes among ``wanted`` a take (``names``: its weight channels) has no weights for at all
    (a Live Link CSV without the ``JawOpen`` column), and the warning naming them: ``(absent, text)``,
    ``([], None)`` when none is missing. ``of`` qualifies the shapes counted (``"of the avatar's "``),
    ``effect`` says what becomes of them and ``fix`` how to mend it; a take with no ARKit channel at all (a
    studio's ``Key_1``) is named by its own channels instead, with ``effect_none`` (a user trial: all 52 ARKit
    names listed said less)."""
    shown = set(names)
    absent = [n for n in wanted if n not in shown]
    if not absent:
        return [], None
    if not shown & set(ARKIT_NAMES):          # not a face take at all: its own channels say more
        own = list(names)
        preview = ", ".join(map(repr, own[:4])) + (", ..." if len(own) > 4 else "")
        return absent, (f"{take}: none of the take's {len(own)} weight channel(s) ({preview}) is an ARKit "
                        f"shape{effect_none} (fix: a face take names its weights as ARKit does: "
                        "eyeBlinkLeft, jawOpen, ...)")
    return absent, (f"{take}: the take has no weights for {len(absent)} {of}ARKit shape(s): "
                    f"{', '.join(absent)}; {effect} (fix: {fix})")


#: The fix when a capture is given to ``--take`` (personalize, review), which plays a take.
TAKE_NOT_CAPTURE_FIX = ("pass the capture as CAPTURE (its test expressions already play in the inspection "
                        "animation and the review page); --take plays a take: a Live Link Face CSV, a USD "
                        "take ('anim import', a time-sampled mesh) or an OBJ-sequence folder with its CSV")


def refuse_capture_as_take(path, fix: str) -> None:
    """A capture (a folder with ``train/``, a USD file marked ``format = "capture"``:
    :func:`usdface.io.file_kind.file_kind`) where a take is read: CaptureError naming what it is, with ``fix``
    (what the caller reads instead); a capture read as a take would play or pick its frames as if recorded
    in that order."""
    from .file_kind import file_kind

    _refuse_capture(file_kind(path), fix)


def _refuse_capture(found, fix: str) -> None:
    """:func:`refuse_capture_as_take` for what :func:`usdface.io.file_kind.file_kind` found."""
    from .file_kind import Kind

    if found.kind is Kind.CAPTURE or (found.kind is Kind.CAPTURE_FOLDER and found.by == "train/"):
        raise CaptureError("this is a capture (its training and test frames are already picked), not a "
                           "take", path=found.path, fix=fix)


#: The fix when :func:`read_take` is given a capture.
READ_CAPTURE_FIX = ("read a capture with usdface.read_capture(PATH); read_take reads a take: a Live Link "
                    "Face CSV, a USD take ('usdface anim import') or an OBJ-sequence folder with its CSV")


def read_take(path, *, meshes: bool = True) -> Take:
    """Read a take: a folder (OBJ sequence + Live Link CSV), a USD take, or a Live Link CSV (weights only).
    A capture (file or folder) is refused (:class:`CaptureError`): its picked frames read as a take's.
    ``meshes=False`` (what a playback needs: ``personalize --take``, ``review --take``): a take folder's
    weights alone, its OBJ frames not parsed (:func:`read_take_folder`), nor a USD take's points
    (:func:`read_take_usd`)."""
    from .file_kind import file_kind

    path = Path(path)
    suffix = path.suffix.lower()
    usd = suffix in (".usd", ".usda", ".usdc", ".usdz")
    if path.is_dir() or (usd and path.is_file()):
        # a capture.usda read as a take of its 72 training and test frames, without a word (a user trial)
        found = file_kind(path)                  # held while the take is read: its layer is parsed once
        _refuse_capture(found, READ_CAPTURE_FIX)
    if path.is_dir():
        return read_take_folder(path, meshes=meshes)
    if usd:
        return read_take_usd(path, meshes=meshes)
    if suffix == ".csv":
        from .livelink import read_livelink_take

        ll = read_livelink_take(path)
        return Take(ll.weights, ll.names, ll.times, source=str(path),
                    metadata={"name_report": ll.name_report, "angles": ll.angles})
    if not path.exists():
        raise InputFileError("take not found", path=path, fix="check the path")
    raise InputFileError("not a take (expected a folder, a .usd/.usda/.usdc/.usdz or a Live Link .csv)",
                         path=path, fix="pass a USD take, or a folder of OBJ frames with a Live Link Face "
                                        "CSV")


def _canonical(names, path, prim=None) -> list[str]:
    match = match_names(names)
    if match.duplicates:
        raise CaptureError(f"the same shape under several names: {', '.join(match.duplicates)}", path=path,
                           prim=prim, fix="keep one channel per shape")
    return match.canonical


def _frame_number(p: Path) -> int | None:
    m = re.search(r"(\d+)$", p.stem)
    return int(m.group(1)) if m else None


def _take_folder_rows(root: Path):
    """The CSV of an OBJ-sequence take folder and its OBJ frames paired with the CSV's rows, from the file
    names alone (no OBJ is parsed): ``(ll, csv, objs[F], rows[F])`` (``ll``: the LiveLinkTake read from
    ``csv``, ``objs`` the frame files in frame order, ``rows`` the CSV row of each). Refuses what
    :func:`read_take_folder` refuses about the folder's layout (no or several CSVs, no frames, a frame
    name without a number, a frame past the CSV's end)."""
    from .capture_folder import refuse_suffix_case
    from .file_kind import folder_files
    from .livelink import read_livelink_take

    frame_dir = root / "frames" if (root / "frames").is_dir() else root
    refuse_suffix_case([root, frame_dir, root / "template"], (".obj", ".csv"))
    csvs = folder_files(root, "*.csv")
    if len(csvs) > 1 and not any(p.name != "neutral.obj" for p in folder_files(frame_dir, "*.obj")):
        names = ", ".join(p.name for p in csvs[:4]) + (" ..." if len(csvs) > 4 else "")
        raise CaptureError(f"a folder of {len(csvs)} Live Link CSVs ({names}) and no OBJ frames, not one "
                           "take", path=root, fix=f"pass the CSV files themselves, e.g. {csvs[0]}")
    if len(csvs) != 1:
        raise CaptureError(f"expected one Live Link .csv in the take folder, found {len(csvs)}", path=root,
                           fix="put exactly one Live Link Face CSV next to the OBJ frames")
    ll = read_livelink_take(csvs[0])
    objs = [p for p in folder_files(frame_dir, "*.obj") if p.name != "neutral.obj"]
    if not objs:
        raise CaptureError("no OBJ frames", path=frame_dir, fix="put the take's meshes in frames/NNNN.obj")
    numbers = [_frame_number(p) for p in objs]
    if None in numbers:
        bad = objs[numbers.index(None)]
        raise CaptureError("OBJ frame name has no frame number", path=bad,
                           fix="name frames with a trailing number, e.g. frames/0042.obj")
    order = np.argsort(numbers, kind="stable")
    objs = [objs[i] for i in order]
    numbers = np.array(numbers)[order]
    rows = np.arange(len(objs)) if len(objs) == len(ll.times) else numbers - numbers[0]
    if len(objs) != len(ll.times):
        # row = frame number - the first file's: right for a take trimmed at its start or its end, wrong by
        # one row for every later mesh when the first file is the one missing; said, not guessed silently
        gaps = np.flatnonzero(np.diff(numbers) > 1)
        after = ", ".join(str(int(numbers[i])) for i in gaps[:5])
        warn(f"{root}: {len(objs)} OBJ frames for {len(ll.times)} rows of {csvs[0].name}: frame "
             f"{int(numbers[0])} read as row 0, frame n as row n - {int(numbers[0])}"
             + (f"; frames missing after {after}" if after else "")
             + " (if a frame file is missing at the start, every later mesh is paired with the "
               "wrong weights: restore it, or trim the CSV to the frames)")
    if rows.max() >= len(ll.times):
        late = objs[int(rows.argmax())]
        raise CaptureError(f"OBJ frame {late.relative_to(root) if late.is_relative_to(root) else late} has "
                           f"no CSV row ({len(ll.times)} rows for {len(objs)} frames)", path=csvs[0],
                           fix="the CSV must cover every OBJ frame (row k = frame k): export the whole "
                               "take's weights, or remove the frames past its end")
    return ll, csvs[0], objs, rows


def read_take_folder(path, *, meshes: bool = True) -> Take:
    """Read an OBJ-sequence take folder with its Live Link Face CSV (see the module doc). ``meshes=False``:
    the weights alone (``points`` None, no neutral or template): the OBJ frames are not parsed, only their
    names pair them with the CSV's rows (a playback needs no more: a 1,458-frame folder read every mesh to
    play its weights, 7.45 s against 0.94 s for the same take as .usdc)."""
    root = Path(path)
    ll, csv, objs, rows = _take_folder_rows(root)
    meta = {"name_report": ll.name_report, "frame_files": [p.name for p in objs], "csv": str(csv)}
    if not meshes:
        return Take(ll.weights[rows], ll.names, ll.times[rows], source=str(root), metadata=meta)
    from .capture_folder import _template

    faces: dict = {}                  # the first frame's face block: the others' are the same bytes
    first, triangles = read_obj(objs[0], faces=faces)
    points = np.empty((len(objs),) + first.shape)
    points[0] = first
    for i, p in enumerate(objs[1:], start=1):
        pts, tris = read_obj(p, faces=faces)
        if pts.shape != first.shape or not np.array_equal(tris, triangles):
            raise GeometryError(f"topology differs from {objs[0].name}", path=p,
                                fix="every frame of a take must share vertices and faces")
        points[i] = pts
    neutral = template = None
    if (root / "neutral.obj").is_file():
        neutral, ntris = read_obj(root / "neutral.obj", faces=faces)
        if neutral.shape != first.shape or not np.array_equal(ntris, triangles):
            raise GeometryError("neutral.obj topology differs from the frames'", path=root / "neutral.obj",
                                fix="the neutral must share the frames' vertices and faces")
    if (root / "template").is_dir():
        template = _template(root, first if neutral is None else neutral, triangles, {}, faces)
    return Take(ll.weights[rows], ll.names, ll.times[rows], points, triangles, neutral, template, str(root),
                meta)


def read_take_usd(path, *, meshes: bool = True) -> Take:
    """Read a USD take (see the module doc). Raises InputFileError / CaptureError / GeometryError naming the
    file and prim. ``meshes=False``: the weights alone (``points`` None, no neutral or template), at the
    frames' time samples; the points of no frame are read (the weights and their refusals are the same)."""
    from pxr import Usd, UsdGeom, UsdSkel

    from .usd_anim import read_skel_animation
    from .usd_capture import _points, _template, _triangles
    from .usd_open import open_usd_stage

    path = Path(path)
    stage = open_usd_stage(path, "take", "pass a USD take (e.g. written by 'usdface anim import')")
    root = stage.GetDefaultPrim() or stage.GetPseudoRoot()
    frames = root.GetChild("Frames") if root.GetChild("Frames") else None
    if frames is None or not UsdGeom.Mesh(frames):
        meshes = [p for p in Usd.PrimRange(root) if p.IsA(UsdGeom.Mesh)]
        frames = max(meshes, key=lambda p: UsdGeom.Mesh(p).GetPointsAttr().GetNumTimeSamples(), default=None)
    codes = UsdGeom.Mesh(frames).GetPointsAttr().GetTimeSamples() if frames else []
    # one time sample is a take of one frame when it is the take's own Frames mesh ('write_take_usd'):
    # read as weights only, it was refused as 'a take of weights only (no meshes)' (a user trial)
    own_frames = bool(frames) and frames.GetPath() == root.GetPath().AppendChild("Frames")
    if len(codes) < (1 if own_frames else 2):
        weights_only = _weights_only_take(stage, path)
        if weights_only is not None:
            return weights_only
        raise CaptureError("no mesh with time-sampled points and no SkelAnimation with time-sampled "
                           "blendShapeWeights", path=path, prim=root.GetPath(),
                           fix="a take needs a Mesh whose points are time-sampled (one sample per frame), or "
                               "the weights as written by 'usdface anim import'")
    codes = np.array(codes, dtype=np.float64)
    triangles = _triangles(frames, path) if meshes else None
    points = np.stack([_points(frames, path, c) for c in codes.tolist()]) if meshes else None
    if meshes and triangles.max() >= points.shape[1]:
        raise GeometryError("face index out of range", path=path, prim=frames.GetPath(),
                            fix="repair the take's mesh")
    w_attr = frames.GetAttribute("usdface:frames:weights")
    meta: dict = {"frames_prim": str(frames.GetPath()),
                  "template_prim": str(root.GetPath().AppendChild("Template"))}
    if w_attr and w_attr.GetNumTimeSamples():
        names = [str(n) for n in frames.GetAttribute("usdface:frames:names").Get() or []]
        weights = np.stack([np.array(w_attr.Get(c), dtype=np.float64) for c in codes.tolist()])
        meta["weights_source"] = str(w_attr.GetPath())
    else:
        anims = [p for p in Usd.PrimRange(stage.GetPseudoRoot()) if p.IsA(UsdSkel.Animation)
                 and UsdSkel.Animation(p).GetBlendShapeWeightsAttr().GetNumTimeSamples()]
        if not anims:
            # a point cache without weights is as often baked skinning or a simulation (Pixar's
            # lbs.baked.usda) as a take missing its weights: say both, so neither reader is misled
            raise CaptureError("time-sampled points but no per-frame weights (no usdface:frames:weights, "
                               "no SkelAnimation with time-sampled blendShapeWeights): a mesh cache (baked "
                               "skinning?), not a take usdface can read",
                               path=path, prim=frames.GetPath(),
                               fix="for a take, author the phone's weights as a SkelAnimation in it; for an "
                                   "avatar, pass the file whose meshes carry the blend shapes, not a bake")
        names, _, anim_codes = read_skel_animation(anims[0])
        attr = UsdSkel.Animation(anims[0]).GetBlendShapeWeightsAttr()
        weights = np.stack([np.array(attr.Get(c), dtype=np.float64) for c in codes.tolist()])
        if not np.isin(codes, anim_codes).all():
            warn(f"{path}: weights time samples differ from the mesh's; USD interpolated them")
            meta["weights_interpolated"] = True
        meta["weights_source"] = str(anims[0].GetPath())
    if weights.shape[1] != len(names):
        raise CaptureError(f"{weights.shape[1]} weights per frame for {len(names)} names", path=path,
                           prim=frames.GetPath(), fix="author one weight per shape name")
    if not np.isfinite(weights).all():
        raise CaptureError("weights contain NaN or infinite values", path=path, prim=frames.GetPath(),
                           fix="repair the take's weights")
    names = _canonical(names, path, frames.GetPath())
    refuse_weights_scale(weights, names, path, prim=frames.GetPath(), fix_where="the take's weights")
    if weights.min() < 0 or weights.max() > 1:
        warn(f"{path}: weights outside [0, 1] clipped")
        weights = np.clip(weights, 0.0, 1.0)
    times = (codes - codes[0]) / stage.GetTimeCodesPerSecond()
    if not meshes:
        return Take(weights, names, times, source=str(path), metadata=meta)
    neutral = template = None
    rp = root.GetPath()
    if stage.GetPrimAtPath(rp.AppendChild("Neutral")):
        neutral = _points(stage.GetPrimAtPath(rp.AppendChild("Neutral")), path)
        if neutral.shape != points.shape[1:]:
            raise GeometryError("Neutral and frames have different vertex counts", path=path,
                                prim=rp.AppendChild("Neutral"), fix="the neutral must share the frames' mesh")
    if stage.GetPrimAtPath(rp.AppendPath("Template/Mesh")):
        template = _template(stage, rp, path, triangles, points.shape[1])
    # Units and axis -> internal metres, Y up (a bad unit refused as for an avatar or a capture)
    from .usd_rig import read_stage_metadata

    m = read_stage_metadata(stage, path)["metersPerUnit"] * np.eye(3)
    if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z:
        m = m @ np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
    if not np.array_equal(m, np.eye(3)):
        points = points @ m.T
        neutral = None if neutral is None else neutral @ m.T
        if template is not None:
            template = FaceRig(template.neutral @ m.T, template.triangles, template.names,
                               template.deltas @ m.T, name="template")
    return Take(weights, names, times, points, triangles, neutral, template, str(path), meta)


def _weights_only_take(stage, path) -> Take | None:
    """The weights of the first SkelAnimation with time-sampled ``blendShapeWeights`` as a weights-only Take
    (what ``usdface anim import`` writes), or None when the stage has none."""
    from pxr import Usd, UsdSkel

    from .usd_anim import read_skel_animation

    anims = [p for p in Usd.PrimRange(stage.GetPseudoRoot()) if p.IsA(UsdSkel.Animation)
             and UsdSkel.Animation(p).GetBlendShapeWeightsAttr().GetNumTimeSamples()]
    if not anims:
        return None
    names, weights, codes = read_skel_animation(anims[0])
    prim = anims[0].GetPath()
    if not len(names) or weights.shape[1] != len(names):
        raise CaptureError("the SkelAnimation has no blendShapes names for its weights", path=path, prim=prim,
                           fix="author one blendShapes token per weight")
    if not np.isfinite(weights).all():
        raise CaptureError("weights contain NaN or infinite values", path=path, prim=prim,
                           fix="repair the take's weights")
    tcps = stage.GetTimeCodesPerSecond()
    if not (np.isfinite(tcps) and tcps > 0):
        raise CaptureError(f"invalid timeCodesPerSecond {tcps!r}", path=path,
                           fix="set a positive timeCodesPerSecond (e.g. 60)")
    names = _canonical(names, path, prim)
    refuse_weights_scale(weights, names, path, frame=lambda f: f"time {codes[f]:g}", prim=prim,
                         fix_where="the take's weights")
    if weights.min() < 0 or weights.max() > 1:
        weights = np.clip(weights, 0.0, 1.0)
    times = (codes - codes[0]) / tcps
    return Take(weights, names, times, source=str(path), metadata={"weights_source": str(prim)})


# ----------------------------------------------------------------------------------------------- writing
def write_take_usd(take: Take, path, force: bool = False, exact: bool = True) -> Path:
    """Write a take as USD: ``/Take`` (defaultPrim) with ``Neutral`` (if any), ``Template`` (UsdSkel rig
    driven by the take's weights, if any) or else ``Anim`` (SkelAnimation), and ``Frames`` (time-sampled
    points and ``usdface:frames:weights``). Frame f is at time code ``times[f] * fps`` with the stage's
    timeCodesPerSecond = the take's fps. Atomic; refuses an existing file unless ``force``."""
    from pxr import Usd, UsdGeom

    from . import usd_capture as uc
    from .usd_anim import author_skel_animation

    path = Path(path)
    uc._check_output(path, force, what="take file")
    if take.points is None:
        raise CaptureError("the take has no meshes", path=path,
                           fix="use 'usdface anim import' for weights only")
    fps = round(take.fps, 6)
    codes = np.round(take.times * fps, 6)
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    root = UsdGeom.Xform.Define(stage, TAKE_PRIM).GetPrim()
    stage.SetDefaultPrim(root)
    if take.neutral is not None:
        neutral = UsdGeom.Mesh.Define(stage, f"{TAKE_PRIM}/Neutral")
        uc._topology(neutral, take.triangles)
        uc._set_points(neutral, take.neutral, exact=exact)
    if take.template is not None:
        uc.author_template(stage, f"{TAKE_PRIM}/Template", take.template,
                           uc._columns(take.weights, take.names, take.template.names), codes, fps, exact)
    else:
        author_skel_animation(stage, f"{TAKE_PRIM}/Anim", take.names, take.weights, fps, times=take.times)
    uc.author_frames(stage, f"{TAKE_PRIM}/Frames", take.triangles, take.points, take.weights, take.names,
                     codes, exact)
    stage.SetTimeCodesPerSecond(fps)
    stage.SetFramesPerSecond(fps)
    stage.SetStartTimeCode(float(np.floor(codes[0] + 1e-6)))    # whole frames around the samples (as
    stage.SetEndTimeCode(float(np.ceil(codes[-1] - 1e-6)))      # usd_anim.author_skel_animation)
    stage.GetRootLayer().customLayerData = {"usdface": {"format": "take", "formatVersion": 1,
                                                        "source": str(take.source or "")}}
    uc._save(stage, path, force)
    return path


def write_take_folder(take: Take, path, force: bool = False) -> Path:
    """Write a take as ``frames/NNNNN.obj`` + ``take.csv`` (Live Link Face layout) [+ ``neutral.obj``,
    ``template/``]: the OBJ-sequence form :func:`read_take_folder` reads. Built in a temporary folder and
    swapped in (:func:`usdface.io.atomic.replace_dir_atomically`); an existing non-empty folder needs
    ``force``."""
    from .atomic import check_output_dir, replace_dir_atomically
    from .livelink import write_livelink_csv
    from .mesh_io import write_obj

    dest = check_output_dir(path, force)
    if take.points is None:
        raise CaptureError("the take has no meshes", path=dest, fix="a take folder needs one OBJ per frame")
    with replace_dir_atomically(dest, force=force) as tmp:
        for f in range(len(take)):
            write_obj(tmp / "frames" / f"{f:05d}.obj", take.points[f], take.triangles)
        write_livelink_csv(tmp / "take.csv", take.names, take.weights, take.times)
        if take.neutral is not None:
            write_obj(tmp / "neutral.obj", take.neutral, take.triangles)
        if take.template is not None:
            tpl = take.template
            write_obj(tmp / "template" / "neutral.obj", tpl.neutral, tpl.triangles)
            for k, name in enumerate(tpl.names):
                write_obj(tmp / "template" / f"{name}.obj", tpl.neutral + tpl.deltas[k], tpl.triangles)
    return dest


# ---------------------------------------------------------------------------------------- take -> capture
def is_take(path) -> bool:
    """True when ``path`` is a take rather than a capture (:func:`usdface.io.file_kind.file_kind`: a
    :attr:`~usdface.io.file_kind.Kind.TAKE_FOLDER` or a :attr:`~usdface.io.file_kind.Kind.TAKE`): a folder
    with ``frames/`` or a Live Link CSV and no ``train/``; a USD file marked ``format = "take"`` by
    :func:`write_take_usd`, or, unmarked, one whose root layer *defines* a mesh with time-sampled ``points``
    and has no capture ``usdface:frames:role`` and no blend shapes outside the take's own ``Template`` rig (an
    avatar with an animated cache mesh is an avatar, and so is a shot file whose cache is an ``over`` of a
    referenced avatar); arcs and sublayers elsewhere (a take's looks, its template in a file of its own) do
    not change the answer. A capture (or anything else) is False, so its reader reports what is wrong with
    it."""
    return probe_take(path)[0]


def probe_take(path) -> tuple[bool, object]:
    """:func:`is_take` and the USD root layer it opened (None for folders and files that are not USD): hold
    it while the file is read so that USD parses it once (the stage reader finds the open layer in USD's
    registry)."""
    from .file_kind import Kind, file_kind

    found = file_kind(path)
    return found.kind in (Kind.TAKE, Kind.TAKE_FOLDER), found.layer


#: The fix when a file that is no take is given where a take is read (``--take``, a manifest's ``take``).
TAKE_FIX = ("give a take: a Live Link Face CSV, a USD take ('usdface anim import', a time-sampled mesh with "
            "its weights) or an OBJ-sequence folder with its CSV")


def check_take_path(path, fix: str = TAKE_FIX, *, capture_fix: str = TAKE_NOT_CAPTURE_FIX) -> Path:
    """What :func:`read_take` refuses about the kind of ``path`` without reading its frames (``usdface batch``
    and the Pyblish validators check a take before the first item / extractor; an avatar given as the take
    failed only at the item): a missing path, a capture (:func:`refuse_capture_as_take`), a folder with no
    OBJ frames and no CSV, a CSV without a Live Link ``Timecode`` header or frames, a file neither CSV nor
    USD, and a USD file with no time-sampled mesh and no per-frame weights (an avatar, a fitted rig: named
    as such). Raises :class:`usdface.errors.InputFileError` / ``CaptureError`` naming the path and ``fix``
    (``capture_fix`` for a capture: what the caller reads instead); returns it as a Path."""
    from .file_kind import Kind, file_kind

    p = Path(path)
    found = file_kind(p)                       # held: the stage below parses the file once
    if found.kind is Kind.MISSING:
        raise InputFileError("take not found", path=p, fix=fix)
    _refuse_capture(found, capture_fix)
    if found.kind in (Kind.CAPTURE_FOLDER, Kind.FOLDER):
        raise InputFileError("not a take: a folder with no frames/ folder and no Live Link CSV", path=p,
                             fix=fix)
    if found.kind is Kind.TAKE_FOLDER:
        return p
    if found.kind is Kind.LIVELINK_CSV:        # the header and the first frame only, as the reader sees them
        try:
            with open(p, encoding="utf-8-sig", newline="") as f:
                lines = [line for line in (f.readline() for _ in range(64)) if line.strip()][:2]
        except (OSError, UnicodeDecodeError) as exc:
            raise InputFileError(f"cannot read the take as a Live Link Face CSV ({exc})", path=p,
                                 fix=fix) from None
        import csv

        from .livelink import livelink_header

        # judged as the reader judges it ('timecode' in any letter case, a spreadsheet's separator named)
        livelink_header(next(csv.reader([lines[0]]), []) if lines else [], lines[0] if lines else "", p, fix)
        if len(lines) < 2:
            raise InputFileError("the take's CSV has a header but no frames", path=p,
                                 fix="record a take first")
        return p
    if found.kind is Kind.OTHER:
        raise InputFileError("not a take (expected a folder, a .usd/.usda/.usdc/.usdz or a Live Link .csv)",
                             path=p, fix=fix)
    if found.kind is Kind.TAKE:
        return p
    from .usd_open import open_usd_stage

    stage = open_usd_stage(p, "take", fix)
    if has_frame_weights(stage):               # a weights-only take (a SkelAnimation, 'anim import')
        return p
    found = file_kind(p, stage=stage, compose=True)
    if found.kind is Kind.FIT:
        what = "a 'usdface fit' rig (the person's shapes on the capture mesh)"
    elif found.kind is Kind.ERROR_MAPS and found.by == "format":      # one that says so
        what = "an error-map file written by 'usdface evaluate --usd'"
    elif found.skel_root:
        what = ("a usdface output layer (a personalized avatar)" if found.usdface.get("inputs")
                else "an avatar")
    else:
        what = "a USD file"
    raise CaptureError(f"this is {what}, not a take: no mesh with time-sampled points and no SkelAnimation "
                       "with time-sampled blendShapeWeights", path=p,
                       prim=stage.GetDefaultPrim().GetPath() if stage.GetDefaultPrim() else None, fix=fix)


def has_frame_weights(stage) -> bool:
    """Whether a stage holds per-frame weights a take is read with: a time-sampled
    ``usdface:frames:weights`` or a SkelAnimation with time-sampled ``blendShapeWeights``
    (:func:`read_take_usd`'s two sources). A point cache without them (baked skinning) is no take."""
    from pxr import Usd, UsdSkel

    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        attr = prim.GetAttribute("usdface:frames:weights")
        if attr and attr.GetNumTimeSamples():
            return True
        if prim.IsA(UsdSkel.Animation) and \
                UsdSkel.Animation(prim).GetBlendShapeWeightsAttr().GetNumTimeSamples():
            return True
    return False


def capture_from_whole_take(take: Take, template=None) -> Capture:
    """Every frame of ``take`` as a training frame (labels ``fNNNNN``; no test frames): the capture of
    whole-take fitting (``usdface fit TAKE``, ``usdface personalize AVATAR TAKE``). ``metadata["whole_take"]``
    marks it, so the fit weights its frames (``frame_weights="balanced"``, a held pose counts once,
    :mod:`usdface.personalize.takefit`) unless told otherwise. ``template`` and the neutral as in
    :func:`capture_from_take`."""
    if take.points is None:
        raise CaptureError("a take of weights only (no meshes): nothing to fit", path=take.source or None,
                           fix=WEIGHTS_ONLY_FIX)
    if template is None and take.template is None:
        _refuse_without_template(take)
    frames_idx = np.arange(len(take), dtype=np.int64)
    capture = _capture(take, frames_idx, ["train"] * len(take), [f"f{f:05d}" for f in frames_idx], template,
                       {"source": take.source, "units": "m"})
    capture.metadata["whole_take"] = {"frames": len(take), "fps": take.fps,
                                      "times": (take.times - take.times[0]).tolist()}
    capture.metadata["counts"] = {"train": len(take), "test": 0}
    return capture


def whole_take_playback(capture) -> tuple | None:
    """``(names[K], weights[F,K], times[F] s)`` of a capture read from a whole take (its training frames, at
    their times in the take: what inspection and review play when no other take is given), else None."""
    whole = capture.whole_take
    if not whole or not len(capture.train):
        return None
    return list(capture.names), capture.train.weights, np.asarray(whole["times"], dtype=np.float64)


#: What to do with a weights-only take (a Live Link CSV, an ``anim import`` SkelAnimation) given as a capture.
WEIGHTS_ONLY_FIX = ("fit on the take's meshes: a folder of its OBJ frames (frames/NNNN.obj) with the "
                    "Live Link CSV, or a USD take with time-sampled points; a weights-only take plays on "
                    "the avatar with 'personalize AVATAR CAPTURE --take FILE' and 'capture select FILE' "
                    "shows its coverage")


def _refuse_without_template(take: Take) -> None:
    """A take read whole (``fit TAKE``, ``personalize AVATAR TAKE``) without its template rig: where the
    template belongs in the take, and the capture-select route that takes one from elsewhere."""
    source = Path(take.source) if take.source else None
    route = ("or pick frames with 'usdface capture select TAKE -o capture.usda --template CAPTURE' "
             "(a capture on the take's topology) and use that capture")
    if source is not None and source.is_dir():
        raise CaptureError("the take has no template rig (no template/ folder)", path=source / "template",
                           fix="add template/ (neutral.obj + one OBJ per ARKit shape, as in a capture "
                               f"folder) on the frames' topology, {route}")
    prim = take.metadata.get("template_prim") or "/Take/Template"  # where read_take_usd looks
    raise CaptureError("the take has no template rig", path=source, prim=prim,
                       fix="author the template SkelRoot there as in capture.usda (write_take_usd with "
                           f"take.template set), {route}")


def capture_from_take(take: Take, selection, template=None) -> Capture:
    """The capture a phone app would have recorded: the selected training frames (``selection.train``,
    labels ``NNN_<shape>``) and held-out test frames (``selection.test``) of ``take``, with their whole weight
    vectors and meshes, the person's neutral and the template rig.

    ``template``: a FaceRig, or a capture folder / capture.usda path whose template to use; default the
    take's own. The neutral is the take's ``Neutral`` when present, else the take frame with the smallest
    largest weight (recorded in ``metadata["neutral_frame"]``, with a warning). Weight columns follow the
    template's shape order; take channels the template lacks are reported in ``metadata``.
    """
    metadata: dict = {"source": take.source, "units": "m", "take": {
        "threshold": selection.threshold, "per_shape": selection.per_shape,
        "coverage": [{"name": s.name, "frames": s.frames, "times": [float(take.times[f]) for f in s.frames],
                      "peak": s.peak, "dominance": s.dominance, "max_weight": s.max_weight}
                     for s in selection.shapes],
        "missing": selection.missing}}
    frames_idx = np.concatenate([selection.train, selection.test]).astype(np.int64)
    roles = ["train"] * len(selection.train) + ["test"] * len(selection.test)
    capture = _capture(take, frames_idx, roles, selection.labels + selection.test_labels, template, metadata)
    capture.metadata["counts"] = {"train": len(selection.train), "test": len(selection.test)}
    capture.metadata["never_triggered"] = list(selection.missing)
    return capture


def _capture(take: Take, frames_idx, roles, labels, template, metadata: dict) -> Capture:
    """The capture of ``take``'s frames ``frames_idx`` with these roles and labels (see
    :func:`capture_from_take`)."""
    if take.points is None:
        raise CaptureError("the take has weights only, no meshes", path=take.source or None,
                           fix="record the mesh with the weights (USD take or OBJ sequence + CSV); a take of "
                               "weights only gives its coverage table alone ('usdface capture select TAKE' "
                               "without -o)")
    given = None                          # where a template given for the take's own came from
    if template is None:
        template = take.template
    elif not isinstance(template, FaceRig):
        from . import read_capture

        if isinstance(template, Capture):
            given, template = f"capture {template.source}" if template.source else "", template.template
        else:
            given, template = f"capture {template}", read_capture(template).template
    else:
        given = f"rig {template.source.file}" if template.source is not None and template.source.file else ""
    if template is None:
        raise CaptureError("the take has no template rig", path=take.source or None,
                           fix="pass --template with a capture folder or capture.usda on the same topology")
    n = take.points.shape[1]
    if template.n_vertices != n:          # the template given was a path the message did not name
        if given is None:
            raise GeometryError(f"template has {template.n_vertices} vertices, the take {n}",
                                path=take.source or None, fix="the template must be on the take's topology")
        raise GeometryError(f"the template given{' (' + given + ')' if given else ''} has "
                            f"{template.n_vertices} vertices, the take {n}: a template of another mesh",
                            path=take.source or None,
                            fix=f"pass --template (template=) a capture recorded on the take's mesh ({n} "
                                "vertices), or leave it out to use the take's own template")
    if take.neutral is not None:
        neutral = take.neutral
    else:
        f0 = int(np.argmin(take.weights.max(axis=1)))
        neutral = take.points[f0]
        metadata["neutral_frame"] = f0
        warn(f"{take.source}: the take has no neutral mesh; using frame {f0} (weights all "
             f"<= {take.weights[f0].max():.2f}) as the neutral")
    index = {nm: k for k, nm in enumerate(take.names)}
    cols = np.array([index.get(nm, -1) for nm in template.names])
    extra = [nm for nm in take.names if nm not in set(template.names)]
    if extra:
        metadata["extra_channels"] = extra
    w = np.where(cols[None, :] >= 0, take.weights[frames_idx][:, np.maximum(cols, 0)], 0.0)
    metadata["take_frames"] = frames_idx.tolist()
    frames = Frames(take.points[frames_idx], w, roles, labels)
    return Capture(neutral, take.triangles, template, frames, list(template.names), source=take.source,
                   metadata=metadata)
