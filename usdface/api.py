"""usdface's small, stable Python API (also re-exported as ``usdface.<name>``).

Thin wrappers over the modules that do the work, imported lazily so ``import usdface`` stays cheap. The CLI
calls these functions, so the command line and a pipeline script behave identically. Every failure on bad
input raises a :class:`usdface.errors.UsdFaceError` subclass that names the file, the prim and the fix.

Example::

    import usdface
    issues = usdface.check("avatar.usdc")                  # list[Issue], errors first
    avatar = usdface.read_avatar("avatar.usdc")            # Avatar (metres, Y up)
    capture = usdface.read_capture("capture/")             # Capture
    out = usdface.personalize_avatar("avatar.usdc", "capture/", "avatar_person.usda")
"""

from __future__ import annotations

import json
import os
import shlex
from collections.abc import Iterable, Sequence
from numbers import Integral
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

from .errors import expect_kind, warn
from .namelist import name_list

if TYPE_CHECKING:  # pragma: no cover
    from collections.abc import Callable

    from .io.livelink import LiveLinkTake
    from .io.take import Take
    from .landmarks import LandmarkLayout
    from .landmarks.evaluate import EvaluationReport
    from .model import Avatar, Capture, FaceRig
    from .personalize import FitResult
    from .pipeline.batch import BatchReport, ItemResult
    from .pipeline.check import Issue
    from .take_select import Selection
    from .transfer import PersonalizeResult

PathLike = str | Path


def _written(path: PathLike) -> Path:
    """A written output as every function here returns it: an absolute ``Path`` (symlinks kept, ``..`` left
    as given, as the layer writers return theirs). Some returned the path as given (``out/x.usda``), others
    absolute, one function both (``evaluate_methods``' JSON and plot as given, its USD absolute)."""
    return Path(path).absolute()

_expect = expect_kind        # (usdface.errors: the io writers refuse their arguments alike)


def _flags(what: str, **named) -> tuple[bool, ...]:
    """The values of the API function ``what``'s boolean arguments ``name=value``, in the order given, as
    :func:`usdface.errors.expect_flag` takes them: ``None`` is the argument's default (its signature's; an
    option given in ``**options``, such as ``personalize_avatar``'s ``force``, defaults to ``False``), any
    value but a boolean an :class:`usdface.errors.OptionError` naming the function, the argument and the fix,
    before any work (``force="no"`` counted as true and replaced an existing output, ``skin="no"`` exported
    the skin, ``pixar="no"`` ran Pixar's validators: a user trial)."""
    import inspect

    from .errors import expect_flag

    params = inspect.signature(globals()[what]).parameters
    whose = what + ("'" if what.endswith("s") else "'s")     # select_capture_frames' force
    return tuple(expect_flag(value, name, whose, params[name].default if name in params else False)
                 for name, value in named.items())


_PATH = (str, os.PathLike)


def _paths(**named) -> None:
    """Each ``name=(value, none_ok)`` a path (a str or Path), else :class:`usdface.errors.OptionError` naming
    the argument (``inspect_file(None)``, ``export_avatar(None, ...)`` died with Python's TypeError)."""
    for name, (value, none_ok) in named.items():
        _expect(value, _PATH, name, "a path (a str or Path)" + (" or None" if none_ok else ""),
                f"pass {name} as a file or folder path", none_ok=none_ok)
        if isinstance(value, str) and not value:    # Path("") is the current folder: written into it
            from .errors import OptionError

            raise OptionError(f"{name} is an empty string",
                              fix=f"pass {name} as a file or folder path (an unset variable?); for the "
                                  "current folder say '.'")


def _model(name: str):
    from . import model

    return getattr(model, name)


__all__ = [
    "personalize_avatar", "fit_capture", "write_fit_rig", "evaluate_capture", "evaluate_methods",
    "compute_landmarks", "landmark_diagnostics", "read_avatar", "pick_mesh", "read_capture", "write_capture",
    "import_capture_folder", "select_capture_frames", "import_livelink_take", "write_landmarks",
    "evaluate_landmarks",
    "write_retarget_map", "personalize_batch", "check", "inspect_file",
]

#: The personalization methods of :func:`fit_capture` / :func:`evaluate_methods`.
METHODS = ("dt", "ebfr", "menzel", "laplacian")


def read_avatar(path: PathLike, name_map: dict | PathLike | None = None) -> Avatar:
    """Read a UsdSkel avatar: every skinned mesh with blend shapes, converted to metres / Y up, ARKit names
    canonicalised (see :func:`usdface.io.usd_rig.read_avatar`). ``name_map``: the studio's
    ``{"studio_channel": "arkitName"}`` dict or a JSON / CSV file of them, for channels usdface does not
    recognise (:mod:`usdface.io.name_map`)."""
    from .io.usd_rig import read_avatar as _read

    _expect(path, _PATH, "read_avatar's path", "the avatar's file (a str or Path)",
            "pass the avatar's .usd/.usda/.usdc file")
    return _read(path, name_map=name_map)


def read_capture(path: PathLike) -> Capture:
    """Read a capture folder (OBJ + JSON) or a capture ``.usda`` (see :func:`usdface.io.read_capture`)."""
    from .io import read_capture as _read

    _expect(path, _PATH, "read_capture's path", "a capture folder or file (a str or Path)",
            "pass the capture folder or its capture.usda")
    return _read(path)


def pick_mesh(avatar: Avatar, name: str | None = None) -> FaceRig:
    """The mesh of ``avatar`` to work on: the one whose prim name or path is ``name``, or by default the one
    with the most shapes (then the most vertices). Raises :class:`~usdface.errors.RigError` naming the
    avatar file and its meshes when there is no such mesh (or no mesh with blend shapes at all), and, without
    ``name``, when the avatar holds several characters' face rigs (a shot: the first character was taken
    until stop 45), by personalize's test (:func:`usdface.motion.refuse_several_characters`)."""
    from .errors import RigError

    _expect(avatar, (_model("Avatar"),), "pick_mesh's avatar", "an Avatar",
            "pass usdface.read_avatar(PATH), not the path")
    _expect(name, (str,), "pick_mesh's name", "a prim name or path (a str)",
            "pass the mesh's prim name ('Head') or path ('/Avatar/Head')", none_ok=True)
    if name:
        from .io.layers import avatar_mesh

        return avatar_mesh(avatar, name)
    if not avatar.meshes:
        raise RigError("no mesh with blend shapes", path=avatar.file, fix="pass an avatar with a face rig")
    from .motion import refuse_several_characters

    # the default order (a stable sort: the first in the file on a tie, as max took); the meshes' bounds
    # tell the characters apart, so it holds for an avatar read without its offsets (render --landmarks)
    ordered = sorted(avatar.meshes, key=lambda m: (m.n_shapes, m.n_vertices), reverse=True)
    refuse_several_characters(avatar, [(m, None) for m in ordered], option="--mesh (pick_mesh's name=)",
                              also="")
    return ordered[0]


def check_capture_output(out_path: PathLike, force: bool = False, inputs=()) -> Path:
    """Validate a capture output before any work: ``.usda``/``.usdc``/``.usd`` (a file) or a name without
    extension (a folder); never touching one of the ``inputs`` (:func:`usdface.io.atomic.check_not_input`:
    not an input, not inside an input folder, a folder holding none of them), even with ``force``; an
    existing output needs ``force``."""
    from .errors import InputFileError

    out = Path(out_path)
    usd = out.suffix.lower() in (".usda", ".usdc", ".usd")
    if out.suffix and not usd:
        raise InputFileError("a capture is written as .usda/.usdc/.usd or as a folder (a name without "
                             "extension)", path=out, fix=f"name it e.g. {out.stem}.usda or {out.stem}/")
    if usd:
        from .io.layers import check_output_path

        return check_output_path(out, force, inputs=inputs, what="capture file")
    from .io.atomic import check_output_dir

    return check_output_dir(out, force, inputs=inputs, what="capture folder")


def write_capture(capture: Capture, out_path: PathLike, force: bool = False, *, exact: bool = True,
                  source: PathLike | None = None, inputs: Sequence[PathLike | None] = ()) -> Path:
    """Write ``capture`` as a capture ``.usda``/``.usdc``/``.usd`` file, or as a capture folder (OBJ + JSON)
    for any other path; returns the path written (atomically). Refuses an existing output unless ``force``.
    ``exact=False`` stores USD geometry as float32 only (half the size, not bit-exact). ``source``: the file
    or folder the capture was read from; its sha256 digest is recorded as ``metadata["source_digest"]``.
    ``source`` and ``inputs`` (other files the capture was made from) are never overwritten, even with
    ``force`` (:func:`check_capture_output`); one path alone is one input."""
    if isinstance(inputs, str | os.PathLike):     # its characters were taken as paths: '.' and '/', so
        inputs = [inputs]                         # every output was 'inside the input folder /'
    _expect(capture, (_model("Capture"),), "write_capture's capture", "a Capture",
            "pass usdface.read_capture(PATH) (a capture is copied as a file with import_capture_folder)")
    force, exact = _flags("write_capture", force=force, exact=exact)
    out = check_capture_output(out_path, force, inputs=[source, *inputs])
    if source is not None:
        from .io.layers import file_digest

        capture.metadata.setdefault("source_digest", file_digest(source))
    if out.suffix.lower() in (".usda", ".usdc", ".usd"):
        from .io.usd_capture import write_capture_usd

        return _written(write_capture_usd(capture, out, force=force, exact=exact))
    from .io.capture_folder import write_capture_folder

    return _written(write_capture_folder(capture, out, force=force))


def import_capture_folder(folder: PathLike, out_path: PathLike, force: bool = False, *,
                          exact: bool = True) -> Path:
    """Convert a capture folder (or rewrite a capture ``.usda``) into one ``capture.usda``
    (``usdface capture import``); returns the path written. Refuses to overwrite an existing file unless
    ``force``; the source's digest is recorded (see :func:`write_capture`). A take is refused (its frames are
    picked with :func:`select_capture_frames`, or it is fitted whole)."""
    _paths(folder=(folder, False), out_path=(out_path, False))
    force, exact = _flags("import_capture_folder", force=force, exact=exact)
    from .io.capture_folder import refuse_whole_take

    check_capture_output(out_path, force, inputs=[folder])
    capture = read_capture(folder)
    refuse_whole_take(capture, folder)            # naming the take given, before the write would
    return write_capture(capture, out_path, force=force, exact=exact, source=folder)


class CaptureSelection(NamedTuple):
    """Result of :func:`select_capture_frames`: the ``take`` read, the frame ``selection``
    (:class:`usdface.take_select.Selection`), its plain-text ``coverage`` table, and the ``capture`` built
    from it with the path it was written to (both None when no output was asked for)."""

    take: Take
    selection: Selection
    coverage: str
    capture: Capture | None
    out_path: Path | None


def select_capture_frames(take: PathLike, out_path: PathLike | None = None, *,
                          template: PathLike | FaceRig | None = None, threshold: float = 0.5,
                          per_shape: int = 1, test_every: int = 0, min_separation: float = 0.5,
                          force: bool = False) -> CaptureSelection:
    """Pick training (and held-out test) frames from a continuous take (Menzel et al. 2022, section 3.1;
    ``usdface capture select``): for each shape up to ``per_shape`` frames where its weight peaks above
    ``threshold``, peaks of one shape at least ``min_separation`` seconds apart; every ``test_every``-th take
    frame that shows an expression (a weight of at least :data:`usdface.take_select.REST_WEIGHT`: never a
    rest) at least ``min_separation`` seconds from every training frame held out as a test frame (0: none).
    With ``out_path``, a selection without training frames (no peak above ``threshold``) and a capture given
    as the take are refused (:class:`usdface.errors.CaptureError`) before anything is written.

    ``take``: a USD take, an OBJ-sequence folder with a Live Link Face CSV, or a weights-only CSV. With
    ``out_path`` the selected frames are written as a capture (:func:`write_capture`: ``.usd*`` file or
    folder) using ``template`` (a capture path, a Capture or a FaceRig; default the take's own template)."""
    _paths(take=(take, False), out_path=(out_path, True))
    (force,) = _flags("select_capture_frames", force=force)
    import numpy as np

    from .errors import CaptureError
    from .io.take import capture_from_take, read_take
    from .model import Capture
    from .personalize.api import check_number
    from .progress import steps
    from .take_select import format_coverage, select_frames

    _expect(template, (Capture, _model("FaceRig"), *_PATH), "select_capture_frames' template",
            "a capture path, a Capture or a FaceRig (or None: the take's own)",
            "pass the capture whose template rig to use (its folder or capture.usda), or leave it out",
            none_ok=True)   # an Avatar or a number died with Python's TypeError from Path()
    if isinstance(template, Capture):   # a capture read already: its template rig, as --template CAPTURE
        template = template.template
    # as the command line's options refuse them (a string or a fraction died in numpy with a TypeError)
    threshold = check_number("threshold", threshold, low=0.0, inclusive=True, error=CaptureError,
                             fix="pass a weight in [0, 1] (0.5)")
    if threshold > 1.0:
        raise CaptureError(f"threshold {threshold:g} is outside [0, 1]", fix="pass a weight in [0, 1] (0.5)")
    min_separation = check_number("min_separation", min_separation, low=0.0, inclusive=True,
                                  error=CaptureError, fix="pass seconds >= 0 (0.5)")
    for name, value, low in (("per_shape", per_shape, 1), ("test_every", test_every, 0)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
            hint = " (0: no test frames)" if low == 0 else ""
            raise CaptureError(f"bad {name} {value!r}: expected a whole number >= {low}",
                               fix=f"pass {name}={max(low, 1)}{hint}")
    if out_path is not None:
        check_capture_output(out_path, force, inputs=[take, template])
    _check_select_take(take)
    with steps("capture select", 2 if out_path is None else 4) as p:
        p.start(f"read take {Path(take).name}")
        data = read_take(take)
        p.start(f"select frames ({len(data.times)} frames)")
        import warnings

        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            selection = select_frames(data.weights, names=data.names, threshold=threshold,
                                      per_shape=per_shape, test_every=test_every,
                                      min_separation=max(1, round(min_separation * data.fps)))
        rests = False
        for w in caught:
            message = str(w.message)
            if "show no expression" in message:     # its fix named the take nowhere, and the options given
                rests = True
                suggest = (f"--test-every {min(test_every, 5)} "     # (it told '--test-every 5
                           f"--min-separation {min(0.2, min_separation / 2):g}")   # --min-separation 0.2')
                message = (f"{take}: " + message.split(" (fix: ")[0] + " (fix: hold out frames nearer the "
                           f"expressions than --min-separation {min_separation:g} s (usdface capture select "
                           f"{_select_again(take, out_path, template, threshold, per_shape)} {suggest}))")
            warn(message, w.category)
        if test_every > 0 and len(selection.test) == 0 and not rests:     # (the rests' warning says why)
            warn(f"{take}: --test-every {test_every} held out no test frame: every candidate is "
                 f"within --min-separation {min_separation:g} s of a training frame (evaluate will "
                 "refuse this capture); lower --min-separation or --test-every")
        coverage = format_coverage(selection, data.times)
        if out_path is None:
            return CaptureSelection(data, selection, coverage, None, None)
        if len(selection.train) == 0:
            peak = data.weights.max(axis=0) if data.weights.size else None
            best = "" if peak is None else (f" (the highest peak: {data.names[int(peak.argmax())]} "
                                            f"{float(peak.max()):.2f})")
            if peak is not None and float(peak.max()) > threshold:
                # above the threshold but never decreasing after it: lowering the threshold does not help
                raise CaptureError(f"no shape peaks in the take: {data.names[int(peak.argmax())]} reaches "
                                   f"{float(peak.max()):.2f} (above --threshold {threshold:g}) but is still "
                                   f"rising or held at the take's end ({len(data.weights)} frame(s)), and a "
                                   "shape's frame is kept once its weight starts decreasing: the capture "
                                   "would have no training frames", path=take,
                                   fix="record each expression through its peak and back (a take of a few "
                                       "frames, or one that ends on the expression, has no peaks)")
            raise CaptureError(f"no shape peaks above --threshold {threshold:g} in the take{best}: the "
                               "capture would have no training frames", path=take,
                               fix="lower --threshold (0.5 is the paper's), or record the shapes again")
        p.start("build capture")
        capture = capture_from_take(data, selection, template=template)
        # the test-frame options and the take (relative to the capture), in the capture's selection record:
        # evaluate's fix for rest-only test frames names them (it repeated the options this run was given)
        capture.metadata["take"].update(
            min_separation=float(min_separation), test_every=int(test_every),
            path=os.path.relpath(Path(take).absolute(), Path(out_path).absolute().parent))
        p.start(f"write {Path(out_path).name}")
        written = write_capture(capture, out_path, force=force, inputs=[take, template])
    return CaptureSelection(data, selection, coverage, capture, written)


def _rest_fix(capture, source) -> str | None:
    """For a capture ``capture select`` made (its selection record keeps the take and the test-frame
    options), the ``capture select`` run that holds out frames nearer the expressions: half the
    ``--min-separation`` it was made with. The generic fix told ``--min-separation 0.2`` to a capture made
    with 0.2, which gave the same capture again. None for other captures."""
    record = (capture.metadata or {}).get("take") if isinstance(capture.metadata, dict) else None
    if source is None or not isinstance(record, dict) or "min_separation" not in record:
        return None
    try:
        separation, every = float(record["min_separation"]), int(record.get("test_every") or 5)
        threshold, per_shape = float(record.get("threshold", 0.5)), int(record.get("per_shape", 1))
    except (TypeError, ValueError):
        return None                                   # a record, not the capture's data: the generic fix
    take = record.get("path")
    found = Path(source).absolute().parent / take if isinstance(take, str) else None
    # a capture rewritten elsewhere ('capture import sel.usdc -o elsewhere/sel.usda') keeps the record
    take = os.path.relpath(found) if found is not None and found.exists() else "TAKE"
    again = _select_again(take, source, None, threshold, per_shape)
    return (f"hold out frames nearer the expressions than the --min-separation {separation:g} s it was made "
            f"with (usdface capture select {again} --test-every {min(every, 5)} "
            f"--min-separation {min(0.2, separation / 2):g})")


def _select_again(take, out_path, template, threshold, per_shape) -> str:
    """The arguments of ``capture select`` that repeat this selection (the take, its output, the template and
    the options given), for a fix that suggests other test-frame options: it said ``-o capture.usda`` and
    dropped ``--template`` (a take without its own template then failed) whatever the run was given.
    Shell-quoted: a path with a space (``shoot day/take.usdc``) is one word of the pasted command."""
    parts = [str(take), "-o", str(out_path) if out_path is not None else "capture.usda"]
    if template is not None:
        parts += ["--template", str(template) if isinstance(template, str | os.PathLike) else "CAPTURE"]
    if threshold != 0.5:
        parts += ["--threshold", f"{threshold:g}"]
    if per_shape != 1:
        parts += ["--per-shape", str(per_shape)]
    if out_path is not None:
        parts.append("--force")                      # this run writes it
    return shlex.join(parts)         # a path with a space stays one word of the pasted command


def _check_select_take(path: PathLike) -> None:
    """What ``capture select`` reads must be a take (:func:`usdface.io.take.check_take_path`, one look at
    the file): a capture (a folder with ``train/``, a USD capture) holds frames already picked - read as a
    take its test frames would become training frames - and is refused naming what it is and what reads it;
    an avatar or a fitted rig is named as one (it was told only what it lacks)."""
    from .io.take import check_take_path

    check_take_path(path, capture_fix="use it as it is (usdface fit / personalize AVATAR CAPTURE); capture "
                                      "select reads a take: a USD take ('anim import', a time-sampled mesh) "
                                      "or an OBJ-sequence folder with its Live Link CSV")


def import_livelink_take(csv: PathLike, out_path: PathLike, *, timecode_rate: float | None = None,
                         force: bool = False) -> tuple[Path, LiveLinkTake]:
    """Convert a Live Link Face CSV into a USD file whose defaultPrim is a ``SkelAnimation`` with the ARKit
    weights as time samples and the head/eye angles (and other numeric columns) as ``usdface:curves:*``
    attributes (``usdface anim import``). ``timecode_rate``: frames per second of the CSV's timecode FF
    field, also the stage's timeCodesPerSecond (None: 60, the app's, or the rate larger frame fields imply,
    with a warning; a frame field at or above a rate given raises :class:`usdface.errors.TimecodeError`; see
    :func:`usdface.io.livelink.parse_timecodes`). Returns the path
    written (atomically; an existing file needs ``force``) and the
    :class:`usdface.io.livelink.LiveLinkTake` read."""
    _paths(csv=(csv, False), out_path=(out_path, False))
    (force,) = _flags("import_livelink_take", force=force)
    from . import __version__
    from .io.layers import check_output_path
    from .io.livelink import DEFAULT_TIMECODE_RATE, read_livelink_take, require_livelink_file
    from .io.usd_anim import write_animation_usd
    from .progress import steps

    # the CSV's own problems (missing, a folder) before the output's: 'anim import .' was told that '.usda'
    # is a hidden file's name, 'anim import takes/' that 'takes.usda' exists
    require_livelink_file(csv)
    check_output_path(out_path, force, inputs=[csv], what="take file")
    with steps("anim import", 2) as p:
        p.start(f"read {Path(csv).name}")
        data = read_livelink_take(csv, timecode_rate)
        p.start(f"write {Path(out_path).name} ({len(data.times)} frames)")
        rate = DEFAULT_TIMECODE_RATE if timecode_rate is None else timecode_rate
        out = write_animation_usd(out_path, data.names, data.weights, data.times, rate,
                                  curves={**data.angles, **data.extra}, force=force,
                                  layer_data={"source": str(csv), "startTimecode": data.timecodes[0],
                                              "version": __version__})
    return _written(out), data


def _as_capture(capture) -> Capture:
    _expect(capture, (_model("Capture"), *_PATH), "the capture", "a Capture or a capture path",
            "pass the capture folder, its capture.usda or usdface.read_capture(PATH)")
    return read_capture(capture) if isinstance(capture, _PATH) else capture


def fit_capture(capture: Capture | PathLike, method: str = "menzel", *, out_path: PathLike | None = None,
                force: bool = False, command: str | None = None, **options: Any) -> FitResult:
    """Fit personalized blendshapes on the capture mesh (``usdface fit``); returns a ``FitResult`` whose
    ``.rig`` is a :class:`usdface.model.FaceRig` (neutral = the person's neutral, deltas = personalized
    shapes).
    ``method`` is one of ``dt``, ``ebfr``, ``menzel``, ``laplacian``; ``options`` go to
    :func:`usdface.personalize.fit_personalized_shapes` (``pins`` may also be a file: JSON or USD primvars,
    :func:`usdface.io.pins.read_pins`). With ``out_path`` an existing output is refused
    before fitting (unless ``force``) and the rig is then written with :func:`write_fit_rig`; the path
    written is ``result.info["out_path"]``, whose provenance records ``command`` (the CLI's command line),
    the method and options, and the capture file read (:func:`write_fit_rig`)."""
    _paths(out_path=(out_path, True))
    (force,) = _flags("fit_capture", force=force)
    from .personalize import fit_personalized_shapes
    from .progress import steps

    refuse_missing_inputs(capture_path=capture)          # before the output's problems
    if out_path is not None:
        from .io.layers import check_output_path

        check_output_path(out_path, force, inputs=[capture, options.get("pins")], what="fit rig file")
    reading = isinstance(capture, _PATH)            # any os.PathLike, as _as_capture reads it
    source = capture if reading else None
    parameters = {k: (str(v) if isinstance(v, Path) else v) for k, v in options.items()
                  if k != "pins" or isinstance(v, str | Path)}           # a pins file by its path
    with steps("fit", 1 + reading + (out_path is not None)) as p:
        if reading:
            p.start(f"read capture {Path(capture).name}")
        capture = _as_capture(capture)
        _read_pins_option(options, capture)
        p.start(f"fit {method}")
        result = fit_personalized_shapes(capture, method=method, **options)
        if result.info.get("train_rmse_mm") is None and len(capture.frames.select("train")):
            # dt/ebfr do not score themselves: eq. 5 on the training frames, as the other methods report
            result.info["train_rmse_mm"] = float(evaluate_capture(capture, result,
                                                                  role="train")["mean_rmse_mm"])
        if out_path is not None:
            p.start(f"write {Path(out_path).name}")
            result.info["out_path"] = _write_fit_rig(
                result, out_path, force, source,
                command or "usdface.api.fit_capture (Python API)",   # what ran, not its writer
                {"method": method, **parameters})
    return result


def _read_pins_file(options: dict, capture: Capture | PathLike) -> Capture | PathLike:
    """A pins file among ``options`` read against the capture (:func:`_read_pins_option`, which needs its
    names and vertex count): returns the capture, read for it, or ``capture`` as given when no file is."""
    if not isinstance(options.get("pins"), str | Path):
        return capture
    capture = _as_capture(capture)
    _read_pins_option(options, capture)
    return capture


def _read_pins_option(options: dict, capture: Capture) -> None:
    """``options["pins"]`` given as a file (JSON or USD primvars, :func:`usdface.io.pins.read_pins`) ->
    the ``{shape: vertex indices}`` mapping the fit takes (in place)."""
    pins = options.get("pins")
    if isinstance(pins, str | Path):
        from .io.pins import read_pins

        options["pins"] = read_pins(pins, capture.names, len(capture.neutral))


def write_fit_rig(fit: FitResult | FaceRig, out_path: PathLike, *, force: bool = False,
                  capture: PathLike | None = None, command: str | None = None,
                  parameters: dict | None = None) -> Path:
    """Write a fitted rig (a ``FitResult`` or its ``FaceRig``) as a UsdSkel rig on the capture mesh, in its
    vertex order (metres, Y up, root ``/Capture``); returns the path written (atomically; an existing file
    needs ``force``).

    The root layer's ``customLayerData["usdface"]`` records what made it, as a personalized layer does: the
    method, ``command`` (the CLI passes its command line; the API is named otherwise), the fit's
    ``parameters``, its chosen ``reg`` and training RMSE, ``createdAt`` (UTC; ``SOURCE_DATE_EPOCH`` when set)
    and, when the capture was read from ``capture`` (a file or folder), its path relative to the rig and its
    sha256 (``capture``, ``captureDigest``): which capture a rig came from stays answerable after files
    move. A ``capture`` the rig was not fitted on (another vertex count, or another neutral: the person's
    scan a fitted rig keeps) is refused with :class:`usdface.errors.FitError` before the output is checked
    (:func:`usdface.personalize.api.refuse_rig_of_another_capture`); it was recorded as the rig's source.
    A pins file among ``parameters`` (``pins``) is recorded the same way (relative to the rig, its sha256 as
    ``pinsDigest``)."""
    _paths(out_path=(out_path, False))
    (force,) = _flags("write_fit_rig", force=force)
    from .model import FaceRig

    if not isinstance(getattr(fit, "rig", fit), FaceRig):
        _expect(fit, (), "write_fit_rig's fit", "a FitResult or a FaceRig",
                "pass what fit_capture / fit_personalized_shapes returned")
    # the capture recorded as the rig's source: a path (a Capture died in the path arithmetic), and one that
    # is there (it said 'cannot digest: not found (fix: check the path)', a user trial); before the output
    _paths(capture=(capture, True))
    if capture is not None and not Path(capture).exists():
        from .errors import InputFileError

        raise InputFileError("capture not found (the file the rig records as fitted on)", path=capture,
                             fix="pass the capture file or folder the rig was fitted on, or leave capture "
                                 "out")
    if capture is not None:     # recorded as the rig's source: the capture it was fitted on, or refused
        from .personalize.api import refuse_rig_of_another_capture

        refuse_rig_of_another_capture(
            getattr(fit, "rig", fit), _as_capture(capture), path=capture, same_neutral=True,
            fix="pass the capture file or folder the rig was fitted on, or leave capture out")
    return _write_fit_rig(fit, out_path, force, capture, command, parameters)


def _write_fit_rig(fit, out_path, force: bool, capture, command, parameters) -> Path:
    """:func:`write_fit_rig` once its arguments are checked (``fit_capture`` writes the rig of the capture it
    has just read and fitted: not read again)."""
    from . import __version__
    from .io.avatar_writer import write_rig_usd
    from .io.layers import _created_at, _relative_to_layer, check_output_path, file_digest, json_default

    out = check_output_path(out_path, force, what="fit rig file")
    info = getattr(fit, "info", None) or {}
    data = {"format": "fit", "formatVersion": 1, "version": __version__,
            "method": str(info.get("method", "")),
            "command": command or "usdface.api.write_fit_rig (Python API)", "createdAt": _created_at()}
    if parameters:
        # plain values (a pins file's path, not its mapping; numbers, strings, booleans)
        data["parameters"] = json.loads(json.dumps({k: v for k, v in parameters.items() if v is not None},
                                                   default=json_default))
        pins = parameters.get("pins")
        if isinstance(pins, str | Path) and Path(pins).is_file():
            # a pins file as the capture is recorded: relative to the rig, with its sha256 (it was the path as
            # typed, relative to the folder the command ran in: from the rig's folder another file)
            data["parameters"]["pins"] = _relative_to_layer(pins, out)
            data["pinsDigest"] = file_digest(pins)
    for key, name in (("reg", "reg"), ("train_rmse_mm", "trainRmseMm")):
        if isinstance(info.get(key), int | float):
            data[name] = float(info[key])
    if capture is not None:
        data["capture"] = _relative_to_layer(capture, out)
        data["captureDigest"] = file_digest(capture)
    return _written(write_rig_usd(getattr(fit, "rig", fit), out, meters_per_unit=1.0, root="/Capture",
                                  force=force, layer_data={"usdface": data}))




def evaluate_capture(capture: Capture | PathLike, rig: FaceRig | None = None, role: str = "test") -> dict:
    """Paper eq. 5 on the capture's held-out ``test`` (or ``train``) expressions: per-frame RMSE and max
    vertex error in mm of ``rig`` with the frames' weights (``usdface evaluate``); see
    :func:`usdface.personalize.evaluate_rig`. ``rig`` defaults to the generic baseline: the template's deltas
    on the person's neutral. ``rig`` may also be a ``FitResult`` (its ``.rig`` is used; a fit that read its
    amplitudes on the test frames scores each frame without its own reading, cross-fitted). A capture without
    test frames raises :class:`~usdface.errors.FitError` for ``role="test"``, as :func:`evaluate_methods`."""
    from .personalize.evaluate import score_capture_rig, template_rig

    if role not in ("test", "train"):
        from .errors import OptionError

        raise OptionError(f"bad role {role!r}: not a frame role evaluate_capture scores ('test' or 'train')",
                          fix="use role='test' (the held-out frames, eq. 5) or role='train'")
    from .model import FaceRig
    from .personalize import FitResult

    _expect(rig, (FaceRig, FitResult), "evaluate_capture's rig", "a FaceRig or a FitResult (or None)",
            "pass usdface.fit_capture(capture) or its .rig; None scores the generic baseline", none_ok=True)
    source = capture if isinstance(capture, str | Path) else None
    capture = _as_capture(capture)
    if role == "test":      # the mean of no frames was NaN, without a word
        _refuse_without_test_frames(capture, source)
    fit = rig
    rig = template_rig(capture) if rig is None else getattr(rig, "rig", rig)
    _refuse_rig_of_another_capture(rig, capture, source)
    # a fit that read its shapes' amplitudes on the test frames: each scored without its own reading
    scale = None
    if role == "test" and isinstance(fit, FitResult) and list(rig.names) == list(capture.names):
        from .personalize.api import left_out_scale

        scale = left_out_scale(fit, capture.test)
    return score_capture_rig(rig, capture, role, scale)


def _refuse_rig_of_another_capture(rig: FaceRig, capture: Capture, source) -> None:
    """A rig fitted on another capture (another person's mesh, or without some of this capture's shapes) is
    refused naming the capture, what differs and the fix: it was Python's ``ValueError: 'tongueOut' is not in
    list`` from the shape lookup, or a GeometryError naming no file (a user trial)."""
    from .errors import FitError
    from .personalize.api import refuse_rig_of_another_capture

    where = source if source is not None else (capture.source or None)
    fix = ("score the rig fitted on this capture: evaluate_capture(capture, fit_capture(capture)), or None "
           "for the generic baseline")
    refuse_rig_of_another_capture(rig, capture, fix=fix, path=where)
    missing = [name for name in capture.names if name not in set(rig.names)]
    if missing:
        shown = ", ".join(missing[:5]) + (f" (+{len(missing) - 5} more)" if len(missing) > 5 else "")
        raise FitError(f"the rig lacks {len(missing)} of the capture's shapes: {shown}", path=where, fix=fix)


def _refuse_without_test_frames(capture: Capture, source=None) -> None:
    """Eq. 5 scores held-out test frames: a capture without them is refused (a FitError with the fix)."""
    if len(capture.test) == 0:
        from .errors import FitError

        whole_take = capture.whole_take
        raise FitError("the capture has no test frames" + (" (a take read whole: every frame trains)"
                                                           if whole_take else ""),
                       path=source or capture.source or None,
                       fix=("hold frames out with 'usdface capture select TAKE -o capture.usda "
                            "--test-every 10' and evaluate that capture" if whole_take
                            else "add held-out frames to evaluate on: a test/ folder in a capture "
                                 "folder, or for a capture picked from a take 'usdface capture select "
                                 "TAKE -o capture.usda --test-every 10' (lower --min-separation when it "
                                 "holds out none)"))


def evaluate_methods(capture: Capture | PathLike, methods: Sequence[str] = METHODS, *,
                     truth: PathLike | dict | None = None, json_path: PathLike | None = None,
                     plot_path: PathLike | None = None, usd_path: PathLike | None = None, force: bool = False,
                     **options: Any) -> dict:
    """Fit each of ``methods`` on the capture's training frames and score it on the held-out test frames
    (Menzel et al. 2022, eq. 5; ``usdface evaluate``); see :func:`usdface.personalize.report.evaluate_methods`
    for the report (``report["methods"][m]``: ``rmse_mm[F]``, ``max_mm[F]``, ``mean_rmse_mm``,
    ``mean_max_mm``, ``seconds``, with ``truth`` also ``truth_rmse_mm`` and a ``template`` row).

    ``truth``: a ``capture_truth.npz`` path (or its dict: ``names``, ``deltas``). Optional outputs, all
    refused before fitting if they exist (unless ``force``): ``json_path`` (the report), ``plot_path`` (per
    test frame bar charts, paper Figs. 4-5), ``usd_path`` (colour-coded error maps, Fig. 6); the paths
    written are ``report["_outputs"]``; when a later output fails, the ones this call created are removed.
    ``options`` go to the fit (``reg``, ``prior``, ...). Raises :class:`~usdface.errors.FitError` if the
    capture has no test frames."""
    from .io.atomic import check_output_file, outputs_all_or_nothing
    from .personalize.report import METHODS, check_method_options
    from .personalize.report import evaluate_methods as _evaluate

    methods = name_list(methods, "methods", "method", fix=f"name some of {', '.join(METHODS)}")
    check_method_options(list(methods), options)          # an option no chosen method takes: before any work
    (force,) = _flags("evaluate_methods", force=force)
    _check_evaluate_suffixes(json_path, plot_path)       # a plot format matplotlib writes, a .json report
    inputs = [capture, truth]
    for out, what in ((json_path, "JSON report"), (plot_path, "plot")):
        if out:
            check_output_file(out, force, what=what, inputs=inputs)
    if usd_path:
        from .io.layers import check_output_path

        check_output_path(usd_path, force, inputs=inputs, what="error-map file")
    truth_path = truth if isinstance(truth, str | Path) else None
    if truth_path is not None:
        truth = _read_truth(truth_path)
    source = capture if isinstance(capture, str | Path) else None
    from .progress import steps

    with steps("evaluate", 1 + (source is not None) + bool(json_path or plot_path or usd_path)) as p:
        if source is not None:
            p.start(f"read capture {Path(source).name}")
        capture = _as_capture(capture)
        _check_truth_matches(truth, capture, truth_path)
        _refuse_without_test_frames(capture, source)
        tw = capture.test.weights
        test_peak = float(abs(tw).max()) if tw.size else 0.0
        from .take_select import REST_FIX, REST_WEIGHT

        if test_peak < REST_WEIGHT:                         # every method predicts them as the neutral
            warn(f"{source or capture.source or 'the capture'}: its {len(capture.test)} test frames "
                 f"show no expression (largest weight {test_peak:.2f}): every method predicts them "
                 f"as the neutral, so the table cannot tell the methods apart "
                 f"({_rest_fix(capture, source) or REST_FIX})")
        p.start("fit and score the methods")
        report = _evaluate(capture, list(methods), truth=truth, **options)
        outputs = {}
        if json_path or plot_path or usd_path:
            p.start("write outputs")
        # all or nothing: a later output that fails takes the new earlier ones
        with outputs_all_or_nothing(outputs, json=json_path, plot=plot_path, usd=usd_path):
            if json_path:
                from .personalize.report import write_report_json

                outputs["json"] = _written(write_report_json(report, json_path, force=force))
            if plot_path:
                from .personalize.report import plot_errors

                outputs["plot"] = _written(plot_errors(
                    report, plot_path, force=force,
                    title=f"{source or capture.source or 'capture'}: test-frame errors (eq. 5)"))  # as given
            if usd_path:
                from .io.usd_error_maps import write_error_maps_usd

                outputs["usd"] = _written(write_error_maps_usd(usd_path, capture.triangles, report["_maps"],
                                                               force=force))
    report["_outputs"] = outputs
    return report


def _check_evaluate_suffixes(json_path, plot_path) -> None:
    """Refuse, before any fitting, a ``--json`` report not ending in .json and a ``--plot`` whose extension
    matplotlib cannot write (``errors.pgn``), so a typo fails at once and leaves no output behind."""
    from .errors import InputFileError

    if json_path and str(json_path) == "-":      # as every output file (io.atomic.check_output_file)
        raise InputFileError("JSON report is written to a file, not to standard output ('-')", path=json_path,
                             fix="name a file, e.g. report.json")
    if json_path and Path(json_path).suffix.lower() != ".json":
        raise InputFileError("JSON report must end in .json", path=json_path,
                             fix=f"name it e.g. {Path(json_path).stem or 'report'}.json")
    if plot_path:
        from matplotlib.backend_bases import FigureCanvasBase

        kinds = sorted(FigureCanvasBase.get_supported_filetypes())
        suffix = Path(plot_path).suffix.lower().lstrip(".")
        if suffix not in kinds:
            kind = repr(suffix) if suffix else "(no extension)"
            raise InputFileError(f"plot format {kind} is not supported "
                                 f"(supported: {', '.join(kinds)})", path=plot_path,
                                 fix=f"name it e.g. {Path(plot_path).stem or 'errors'}.png")


#: RMS distance (m) between a truth file's neutral and the capture's neutral scan above which the truth is
#: another person's (a scan's noise is ~0.1-0.15 mm; two people differ by millimetres).
TRUTH_NEUTRAL_RMS_M = 1e-3


def _check_truth_matches(truth, capture, path) -> None:
    """Refuse a truth file made for another capture: its ``neutral`` (when it has one) on another vertex
    count, or more than :data:`TRUTH_NEUTRAL_RMS_M` RMS from the capture's neutral scan ('vs truth 0.677'
    was printed against another person's truth)."""
    import numpy as np

    from .errors import InputFileError

    if truth is None or not isinstance(truth, dict) or "neutral" not in truth:
        return
    neutral = np.asarray(truth["neutral"], dtype=np.float64)
    fix = "pass the truth file written with this capture (truth/capture_truth.npz beside it)"
    if neutral.shape != np.asarray(capture.neutral).shape:
        raise InputFileError(f"the truth's neutral has {len(neutral)} vertices, the capture "
                             f"{len(capture.neutral)}", path=path, fix=fix)
    rms = float(np.sqrt(np.mean(np.sum((neutral - capture.neutral) ** 2, axis=1))))
    if rms > TRUTH_NEUTRAL_RMS_M:
        raise InputFileError(f"the truth's neutral is {rms * 1e3:.2f} mm RMS from the capture's neutral scan "
                             "(another capture's truth?)", path=path, fix=fix)


def _read_truth(path) -> dict:
    """Read a ``capture_truth.npz`` (``usdface sample`` writes it in ``truth/`` next to the capture) and
    check it holds ``names[K]`` and ``deltas[K, n, 3]``; InputFileError naming the file expected otherwise
    (e.g. for ``avatar_truth.npz``, which holds the avatar's true shapes, not the capture's)."""
    import zipfile

    import numpy as np

    from .errors import InputFileError

    fix = "pass the capture's capture_truth.npz (usdface sample writes it to truth/capture_truth.npz)"
    from .io.usd_open import require_file

    require_file(path, "truth file", fix)
    if not zipfile.is_zipfile(path):
        raise InputFileError("not a capture truth file (not an .npz archive)", path=path, fix=fix)
    try:
        with np.load(path) as npz:
            keys = set(npz.files)
            missing = [k for k in ("names", "deltas") if k not in keys]
            if missing:
                raise InputFileError(f"not a capture truth file: no {' or '.join(repr(k) for k in missing)} "
                                     f"array (it has {', '.join(sorted(keys)[:4]) or 'nothing'}"
                                     f"{', ...' if len(keys) > 4 else ''})", path=path, fix=fix)
            truth = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, EOFError) as exc:
        raise InputFileError(f"cannot read truth file ({exc})", path=path, fix=fix) from None
    names, deltas = np.asarray(truth["names"]), np.asarray(truth["deltas"])
    if names.ndim != 1 or deltas.ndim != 3 or deltas.shape[0] != len(names) or deltas.shape[2] != 3:
        raise InputFileError(f"truth file's names {names.shape} and deltas {deltas.shape} do not match "
                             "(expected names[K] and deltas[K, n, 3])", path=path, fix=fix)
    return truth


def _check_correspondence_cache(path, inputs=(), outputs=(), *, option: str = "--correspondence",
                                output_option: str = "-o") -> None:
    """Refuse, before any work, a ``--correspondence`` file the run could not use or write: one of the run's
    ``outputs`` (``-o``: the layer would overwrite the cache, or the cache the layer), a place an output may
    not be written (a read-only or immutable folder, inside an input folder: :func:`check_output_file`, the
    cache is written when missing or stale), an existing file that cannot be a cache (not a file, empty, not
    an npz zip). One of the run's ``inputs`` (the avatar, the capture, ...: a swapped or mistyped option) is
    named as such, never suggested for deletion. ``option`` and ``output_option`` are how the caller's user
    names the cache and the layer (``usdface batch``: the manifest's columns, which its user edits)."""
    if path is None:
        return
    import zipfile

    from .errors import InputFileError
    from .io.atomic import check_output_file
    from .io.usd_open import require_file

    for out in outputs:
        if out is not None and Path(os.path.abspath(out)) == Path(os.path.abspath(path)):
            raise InputFileError(f"{option} and {output_option} name the same file: the layer and the cache "
                                 "would overwrite each other", path=path,
                                 fix="give the cache its own name (e.g. avatar.corr.npz)")
    if not Path(path).exists():
        check_output_file(path, True, what=f"correspondence cache ({option})",
                          inputs=[p for p in inputs if isinstance(p, str | Path)])
        return

    for given in inputs:
        if given is None or not isinstance(given, str | Path) or not Path(given).exists():
            continue
        try:
            same = Path(given).resolve() == Path(path).resolve() or Path(given).samefile(path)
        except OSError:
            same = False
        if same:
            raise InputFileError(f"{option} names one of this run's inputs, not a cache", path=path,
                                 fix="pass a new file name for the cache (e.g. avatar.corr.npz); the input "
                                     "is never written")
    require_file(path, "correspondence cache", "pass a .npz cache written by usdface, or a new file name")
    if not zipfile.is_zipfile(path):
        raise InputFileError("not a usdface correspondence cache (empty or not an .npz archive)", path=path,
                             fix=f"give {option} another file (a new name is written), or remove "
                                 "this one if it is a stale cache of yours")


def personalize_inputs(avatar_path, capture_path, *, take=None, **options: Any) -> list:
    """Every file ``personalize``/``retarget`` read (avatar, capture, take, pins, name map; the
    correspondence cache is read *and* written, by design): no output may be one of them."""
    return [avatar_path, capture_path, take, options.get("pins"), options.get("name_map")]


def refuse_missing_inputs(avatar_path=None, capture_path=None, take=None) -> None:
    """A missing avatar, capture or take (given as paths; None: not read) named as their readers name it,
    before the output is checked: 'personalize MISSING.usda CAPTURE' in a folder one cannot write to was
    told that the layer could not be written there (a user trial). What an existing input is, its reader
    says, as before."""
    if isinstance(avatar_path, str | os.PathLike) and not Path(avatar_path).exists():
        from .io.usd_open import require_file

        require_file(avatar_path, "avatar", "pass the avatar's .usd/.usda/.usdc file")
    if isinstance(capture_path, str | os.PathLike) and not Path(capture_path).exists():
        from .io import check_capture_path

        check_capture_path(capture_path)
    if isinstance(take, str | os.PathLike) and not Path(take).exists():
        from .io.take import check_take_path

        check_take_path(take)


def _refuse_wrong_personalize_kinds(avatar_path, capture_path, out_path, *, take=None, face_mesh=None,
                                    rig=None, **_options) -> None:
    """The arguments of :func:`personalize_avatar` / :func:`write_retarget_map` of the kind they take."""
    from .model import FaceRig
    from .personalize import FitResult

    _expect(avatar_path, (_model("Avatar"), *_PATH), "the avatar", "the avatar's file or an Avatar",
            "pass the avatar's .usd/.usda/.usdc file (or usdface.read_avatar(PATH))")
    _expect(capture_path, (_model("Capture"), *_PATH), "the capture", "a capture path or a Capture",
            "pass the capture folder, its capture.usda or a take (or usdface.read_capture(PATH))")
    _expect(out_path, _PATH, "the output", "a file path", "pass the layer's path, e.g. 'person.usda' (None: "
            "no layer, personalize_avatar only)", none_ok=True)
    _expect(take, _PATH, "take", "a take's file (a Live Link CSV or a USD take)",
            "pass the take's path", none_ok=True)
    _expect(face_mesh, (str,), "face_mesh", "a mesh's prim name or path (a str)",
            "pass e.g. 'Head' or '/Avatar/Head'", none_ok=True)
    _expect(rig, (FaceRig,), "rig", "a FaceRig (a FitResult's .rig)",
            "pass usdface.fit_capture(capture).rig" if isinstance(rig, FitResult)
            else "pass the capture-mesh rig to implant, usdface.fit_capture(capture).rig", none_ok=True)


def personalized_name(avatar: PathLike | Avatar) -> str:
    """``<avatar stem>.personalized.usda``: ``usdface personalize``'s default output name (in the current
    folder), and the file an output given as a folder (``-o newdir/``) is told to name inside it."""
    file = avatar if isinstance(avatar, str | os.PathLike) else getattr(avatar, "file", None)
    return f"{Path(file).stem if file else 'avatar'}.personalized.usda"


def personalize_avatar(avatar_path: PathLike | Avatar, capture_path: PathLike | Capture,
                       out_path: PathLike | None, *, inspect: bool = False, take: PathLike | None = None,
                       landmarks: bool = False, **options: Any) -> PersonalizeResult:
    """Personalize an avatar from a capture and write the result as a USD layer over the untouched avatar
    (``usdface personalize``); returns the ``PersonalizeResult`` (``.out_path`` = the layer written).

    ``options`` go to :func:`usdface.transfer.personalize_avatar` (``method``, ``force``, ``mu``, ...). With
    ``inspect=True`` the layer also gets inspection data for usdview (:mod:`usdface.io.usd_inspection`): a
    ``displayColor`` heat map of how much each vertex changed (RMS over shapes) and a ``SkelAnimation`` that
    plays the capture's test expressions on the personalized avatar, followed by ``take`` (a Live Link Face
    CSV or a take imported with ``usdface anim import``) when given, and with ``landmarks=True`` the landmark
    layout of the personalized face mesh as ``Points`` (about 1.5 s more on the bench avatars)."""
    from .io.layers import source_date_epoch
    from .io.usd_rig import refuse_usdface_output

    source_date_epoch()                  # a bad SOURCE_DATE_EPOCH: before any work, not at the write
    _paths(out_path=(out_path, True))
    inspect, landmarks, force, dry_run = _flags("personalize_avatar", inspect=inspect, landmarks=landmarks,
                                                force=options.get("force"), dry_run=options.get("dry_run"))
    options.update({k: v for k, v in (("force", force), ("dry_run", dry_run)) if k in options})
    from .transfer import personalize_avatar as _personalize

    _refuse_wrong_personalize_kinds(avatar_path, capture_path, out_path, take=take, **options)
    # the layer's provenance names what wrote it, as write_fit_rig and write_landmarks do ('usdface
    # personalize' from a script claimed a command line that had never run; the CLI passes its own)
    options["command"] = options.get("command") or "usdface.api.personalize_avatar (Python API)"
    refuse_usdface_output(avatar_path)
    # an option personalize does not take (a typo) is named as such before any work, as batch does (it was
    # a fit error listing the method's options, after reading the inputs; a user trial); the pipeline's
    # own keyword arguments (a given rig, the provenance's command) are not the user's options. The values
    # are checked where they always were (a given rig skips the fit's checks; numpy booleans pass)
    _refuse_unknown_options([k for k in options if k not in ("command", "rig", "layer_edit", "fit_options")])
    from .transfer.options import check_mode_options

    check_mode_options(options.get("face_transfer", "person"), options)   # one the mode would ignore
    _check_correspondence_cache(options.get("correspondence"),
                                personalize_inputs(avatar_path, capture_path, take=take, **options),
                                outputs=[out_path])
    refuse_missing_inputs(avatar_path, capture_path, take)   # said before any output problem
    if out_path is not None and not options.get("dry_run"):
        from .io.layers import check_output_path

        check_output_path(out_path, options.get("force", False), inputs=personalize_inputs(
            avatar_path, capture_path, take=take, **options), example=personalized_name(avatar_path))
    if take is not None or landmarks:    # as --take and --landmarks imply --inspect (landmarks=True alone
        inspect = True                   # wrote no landmarks, without a word)
    capture_path = _read_pins_file(options, capture_path)
    if not inspect:
        return _personalize(avatar_path, capture_path, out_path, **options)
    import time

    from .io.take import check_take_path, read_take

    start = time.perf_counter()
    if take is not None:                 # of the wrong kind (a capture, an avatar, a fit rig): named as such
        check_take_path(take)
    # a bad take fails before any work; played, not fitted: a take folder's weights alone (its 1,458 OBJ
    # frames were parsed to play them: 7.45 s against 0.94 s for the same take as .usdc)
    take_data = read_take(take, meshes=False) if take is not None else None
    avatar = (avatar_path if not isinstance(avatar_path, _PATH)       # any os.PathLike, as the check takes
              else read_avatar(avatar_path, options.get("name_map")))
    capture = _as_capture(capture_path)
    read_s = time.perf_counter() - start
    t_inspect = [0.0]
    frames_played = [0, 0]              # what the inspection animation plays (0: no SkelAnimation written),
    #                                     of it the capture's test expressions

    def inspection(offsets, face_prim):
        """The inspection data, authored in the same atomic write as the layer (no second save)."""
        import numpy as np

        from .io.usd_inspection import change_heat, inspection_animation, inspection_edit

        t = time.perf_counter()
        animation = inspection_animation(capture, take_data)
        frames_played[0] = 0 if animation is None else len(animation[1])
        frames_played[1] = len(capture.test) if capture is not None else 0
        layouts = None
        if landmarks:
            from .model import FaceRig as _FaceRig

            face = avatar.mesh(face_prim)
            personalized = _FaceRig(face.neutral, face.triangles, face.names, np.asarray(offsets[face_prim]),
                                    face.inbetweens, face.source, face.name)
            layouts = {face_prim: compute_landmarks(personalized)}
        edit = inspection_edit(avatar, heat=change_heat(avatar, offsets), landmarks=layouts,
                               animation=animation)
        t_inspect[0] = time.perf_counter() - t
        return edit

    result = _personalize(avatar, capture, out_path, layer_edit=inspection,
                          extra_inputs={"take": take} if take is not None else {}, **options)
    if take_data is not None and isinstance(getattr(result, "report", None), dict):
        from .arkit import ARKIT_NAMES
        from .io.take import missing_arkit_weights

        # a take without some shapes' weights (a CSV without the JawOpen column) played them as still,
        # without a word (a user trial)
        wanted = [n for n in ARKIT_NAMES if any(n in m.names for m in avatar.meshes)]
        _, text = missing_arkit_weights(take, take_data.names, wanted, of="of the avatar's ",
                                        effect="they stay still in the inspection animation",
                                        effect_none=": the inspection animation plays nothing",
                                        fix="export the take with every ARKit weight")
        if text:
            result.report.setdefault("warnings", []).append(text)
    timings = result.report.get("timings") if isinstance(getattr(result, "report", None), dict) else None
    if timings is not None and getattr(result, "out_path", None):
        timings["inspect"] = t_inspect[0]
        result.report["inspection"] = {"animation_frames": frames_played[0], "test_frames": frames_played[1]}
    if timings is not None:  # the reading done here, and the whole call, belong in the report
        timings["read"] = float(timings.get("read", 0.0)) + read_s
        timings.pop("total", None)
        timings["total"] = time.perf_counter() - start
    return result


def _as_rig(rig) -> FaceRig:
    """A :class:`FaceRig`: as given, the face mesh of an :class:`Avatar` (:func:`pick_mesh`), or of the avatar
    file a path names (:func:`read_avatar`); anything else is refused naming what is expected."""
    from .model import Avatar, FaceRig

    if isinstance(rig, FaceRig):
        return rig
    if isinstance(rig, Avatar):
        return pick_mesh(rig)
    if isinstance(rig, _PATH):
        return pick_mesh(read_avatar(rig))
    _expect(rig, (), "the rig", "a FaceRig, an Avatar or an avatar file",
            "pass usdface.pick_mesh(usdface.read_avatar(PATH)), the avatar or its path")


def _refuse_unknown_keywords(func, options: dict, what: str, given: tuple = ()) -> None:
    """An option ``func`` (the core function ``options`` go to) does not take, refused before any work as
    the other API functions refuse theirs (:class:`usdface.errors.OptionError` naming it and what it takes):
    ``compute_landmarks(avatar, epsilom=0.4)`` died with Python's TypeError from the core function, after the
    avatar was read. ``given``: the core's parameters the API function fills itself. A boolean option given
    as anything else (``symmetric="yes"``, which counted as true, and ``"no"`` too) is refused as well, and
    one given as ``None`` is set to the core's default in ``options`` (:func:`usdface.errors.expect_flag`)."""
    import inspect

    from .errors import OptionError

    signature = inspect.signature(func).parameters
    params = [n for n, p in signature.items() if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)]
    unknown = [k for k in options if k not in params or k in given]
    if unknown:
        raise OptionError(f"{what} does not take {', '.join(map(str, unknown))}",
                          fix=f"drop it, or use one of: {', '.join(n for n in params if n not in given)}")
    from .errors import expect_flag

    for name, value in options.items():     # symmetric="yes" was taken as true, and "no" too; None: default
        if signature[name].annotation in ("bool", bool):
            options[name] = expect_flag(value, name, f"{what}'s", signature[name].default)


def compute_landmarks(rig: FaceRig | Avatar | PathLike, epsilon: float = 0.5, alpha: float = 0.5,
                      **options: Any):
    """A landmark layout for ``rig`` (``usdface landmarks``): a :class:`FaceRig`, or an avatar (object or
    file: its face mesh, :func:`pick_mesh`); see :func:`usdface.landmarks.compute_landmarks`."""
    from .landmarks import compute_landmarks as _landmarks

    _refuse_unknown_keywords(_landmarks, options, "compute_landmarks", given=("rig", "epsilon", "alpha"))
    return _landmarks(_as_rig(rig), epsilon=epsilon, alpha=alpha, **options)


def landmark_diagnostics(rig: FaceRig | Avatar | PathLike, epsilon: float = 0.5, alpha: float = 0.5,
                         **options: Any):
    """The paper's per-vertex diagnostics of ``rig`` (as :func:`compute_landmarks` takes it: visibility,
    relative displacement, importance weights; ``usdface render --landmarks --diagnostics``); see
    :func:`usdface.landmarks.diagnostics.landmark_diagnostics`."""
    from .landmarks.diagnostics import landmark_diagnostics as _diagnostics
    from .landmarks.layout import naming

    _refuse_unknown_keywords(_diagnostics, options, "landmark_diagnostics",
                             given=("neutral", "triangles", "deltas", "epsilon", "alpha", "names"))
    rig = _as_rig(rig)
    with naming(rig):                # the options are checked before any work: name the rig's file and prim
        return _diagnostics(rig.neutral, rig.triangles, rig.deltas, epsilon=epsilon, alpha=alpha,
                            names=rig.names, **options)


def write_landmarks(avatar: Avatar, rig: FaceRig, layout: LandmarkLayout, out_path: PathLike, *,
                    force: bool = False, provenance: dict | None = None) -> Path:
    """Write a landmark ``layout`` computed on ``rig`` (a mesh of ``avatar``) as a new USD layer over the
    untouched ``avatar.file``: a ``Points`` prim and mesh primvars, with the ``UsdFaceLandmarksAPI`` schema
    (``usdface landmarks -o``); see :func:`usdface.io.usd_landmarks.write_landmark_layer`. Returns the path
    written (atomically; an existing file needs ``force``)."""
    from .io.usd_landmarks import write_landmark_layer
    from .landmarks import LandmarkLayout

    _expect(avatar, (_model("Avatar"),), "write_landmarks' avatar", "an Avatar",
            "pass usdface.read_avatar(PATH)")
    _expect(rig, (_model("FaceRig"),), "write_landmarks' rig", "a FaceRig (a mesh of the avatar)",
            "pass usdface.pick_mesh(avatar) (the mesh the layout was computed on)")
    _expect(layout, (LandmarkLayout,), "write_landmarks' layout", "a LandmarkLayout",
            "pass usdface.compute_landmarks(rig)")
    _paths(out_path=(out_path, False))
    (force,) = _flags("write_landmarks", force=force)
    return _written(write_landmark_layer(avatar, rig, layout, out_path, force=force, provenance=provenance))


def evaluate_landmarks(rig: FaceRig | Avatar | PathLike, takes: PathLike | Sequence[PathLike], *,
                       empirical: PathLike | Sequence[int] | None = None, frames: int = 400,
                       noise_mm: float = 0.5, **options: Any) -> EvaluationReport:
    """Sweep landmark layouts (epsilon x multi-cover) against baselines on test weights read from Live Link
    Face CSV ``takes`` (``usdface landmarks --evaluate``): reconstruction RMSE vs landmark count (Zell &
    McDonnell 2022, Sec. 5), with ``noise_mm`` of tracking noise, ``frames`` test frames evenly sampled.
    ``rig`` as :func:`compute_landmarks` takes it (a :class:`FaceRig`, or an avatar object or file);
    ``takes`` one path or a sequence of them.
    ``empirical``: the vertex indices of a layout scored as an extra one, as a sequence of ints or a JSON
    file of them (or ICT-FaceKit's ``vertex_indices.json``). ``options`` go to
    :func:`usdface.landmarks.evaluate.evaluate_landmarks` (``rays``, ``symmetric``, ``backend``, ...)."""
    import numpy as np

    from .errors import LandmarkError, OptionError
    from .io.livelink import livelink_weights
    from .landmarks.evaluate import evaluate_landmarks as _evaluate
    from .personalize.api import check_number

    _refuse_unknown_keywords(_evaluate, options, "evaluate_landmarks",
                             given=("rig", "weights", "empirical", "noise"))
    if isinstance(frames, bool) or not isinstance(frames, int | np.integer) or frames < 1:
        # 0 read every frame of the takes, a float died in numpy after reading them
        raise OptionError(f"bad frames {frames!r}: evaluate_landmarks' frames is a whole number >= 1",
                          fix="pass frames=400 (the default; --frames), the test frames taken from the takes")
    noise_mm = check_number("noise_mm", noise_mm, low=0.0, inclusive=True, error=OptionError,
                            fix="the tracking noise in mm >= 0, e.g. noise_mm=0.5 (the default, --noise)")
    if isinstance(takes, _PATH):            # one take, not its characters
        takes = [takes]
    elif isinstance(takes, Iterable) and not isinstance(takes, str | bytes):
        takes = list(takes)
    # named as this function's argument (it said "pass --takes", the command line's flag, to a script)
    _expect(takes, (list, tuple), "evaluate_landmarks' takes", "a take's path or a list of them",
            "pass takes='take.csv' or takes=['take1.csv', 'take2.csv'] (Live Link Face CSVs or USD takes)")
    for take in takes:
        _expect(take, _PATH, "each of evaluate_landmarks' takes", "a path (a str or Path)",
                "pass the takes as file paths (Live Link Face CSVs or USD takes)")
    if not takes:
        raise LandmarkError("evaluate_landmarks' takes is empty: the sweep needs test weights",
                            fix="pass takes=['take1.csv', ...] (usdface landmarks --evaluate --takes ...)")
    rig = _as_rig(rig)
    indices = _read_vertex_list(empirical) if empirical is not None else None
    if indices is not None:            # checked before the takes are read, naming the file
        from .landmarks.baselines import empirical_layout

        try:
            empirical_layout(indices, rig.n_vertices)
        except LandmarkError as exc:
            raise LandmarkError(exc.message, path=empirical if isinstance(empirical, str | Path) else None,
                                prim=getattr(rig.source, "prim", None),
                                fix=exc.fix) from None
    weights = livelink_weights(takes, rig.names, frames)
    if not weights.any():        # every test frame the neutral: the sweep would score tracking noise alone
        shown = ", ".join(rig.names[:8]) + (f" ... (+{len(rig.names) - 8})" if len(rig.names) > 8 else "")
        names = ", ".join(Path(t).name for t in takes)
        raise LandmarkError(f"the takes ({names}) move none of the mesh's {len(rig.names)} shapes ({shown}): "
                            "every test frame is the neutral", prim=getattr(rig.source, "prim", None),
                            fix="pass takes with these channels, or map the avatar's channel names to ARKit "
                                "with --name-map (docs/names.md)")
    return _evaluate(rig, weights, indices, noise=noise_mm * 1e-3, **options)


def _read_vertex_list(path: PathLike | Sequence[int]) -> list[int]:
    """An empirical layout: vertex indices given as they are (a sequence of whole numbers), or a JSON file
    of a list of them or of a dict with ``idx_to_landmark_verts`` (ICT-FaceKit) or ``vertices``."""
    import json

    import numpy as np

    from .errors import InputFileError, LandmarkError

    if not isinstance(path, str | Path):            # the indices themselves (a list, a numpy array)
        values = np.asarray(path)
        if values.ndim != 1 or not values.size or values.dtype.kind not in "iu":
            raise LandmarkError(f"empirical layout {str(path)[:40]!r} is no list of vertex indices",
                                fix="pass whole vertex indices (e.g. [12, 480, 3301]) or a JSON file of them")
        return [int(v) for v in values]

    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise InputFileError(f"cannot read the empirical layout: {exc}", path=path,
                             fix="pass a JSON list of vertex indices or ICT-FaceKit's vertex_indices.json"
                             ) from None
    if isinstance(data, dict):
        data = data.get("idx_to_landmark_verts", data.get("vertices"))
    if not isinstance(data, list) or not all(isinstance(v, int) for v in data):
        raise InputFileError("no vertex index list in the empirical layout", path=path,
                             fix="use a JSON list of ints or a dict with 'idx_to_landmark_verts'")
    return data


def write_retarget_map(avatar_path: PathLike | Avatar, capture_path: PathLike | Capture, out_path: PathLike,
                       *, force: bool = False, **options: Any) -> PersonalizeResult:
    """The automatic retargeting map of Menzel et al. 2022 eq. (4) (``usdface retarget``): each personalized
    ARKit shape of the capture as a ridge-regularised combination of the avatar's own shapes, written as a
    ``.json`` or ``.csv`` K x K weight map (atomically; an existing file needs ``force``, checked before any
    work). ``options`` go to :func:`usdface.transfer.personalize_avatar` (``mu``, ...; it stops after eq. 4:
    no implant, no layer, empty ``offsets``);
    the implant's (``face_transfer``, ``falloff``, ...: :data:`usdface.transfer.options.IMPLANT_OPTIONS`)
    do not change the map and are refused (:class:`usdface.errors.OptionError`). Returns the
    ``PersonalizeResult`` (``.weights[K_capture, K_avatar]``, ``.names``, ``.avatar_names``; ``.out_path`` the
    map file). A ``correspondence`` cache is written after the map (as personalize writes it after the
    layer), and a cache that cannot be written takes a new map with it: a run that fails leaves neither."""
    _paths(out_path=(out_path, False))
    (force,) = _flags("write_retarget_map", force=force)
    from .io.atomic import check_output_file, outputs_all_or_nothing, write_text_atomic
    from .io.usd_rig import refuse_usdface_output
    from .transfer import personalize_avatar as _personalize
    from .transfer.correspond import save_correspondence
    from .transfer.retarget import weight_map_csv, weight_map_json

    _refuse_implant_options(options)
    _refuse_wrong_personalize_kinds(avatar_path, capture_path, out_path, **options)
    refuse_usdface_output(avatar_path)
    out = check_output_file(out_path, force, suffixes=(".json", ".csv"), what="retarget map",
                            inputs=personalize_inputs(avatar_path, capture_path, **options))
    _check_correspondence_cache(options.get("correspondence"),
                                personalize_inputs(avatar_path, capture_path, **options), outputs=[out])
    given_capture, pins_file = capture_path, options.get("pins")
    capture_path = _read_pins_file(options, capture_path)     # as personalize_avatar reads it
    pending: list = []             # the correspondence cache: written once the map is, as personalize's
    result = _personalize(avatar_path, capture_path, None, map_only=True, pending_cache=pending, **options)
    if out.suffix.lower() == ".json":
        eq4 = result.report["retarget"]
        meta = {"avatar": _map_input(getattr(avatar_path, "file", avatar_path), out),
                "capture": _map_input(getattr(given_capture, "source", given_capture), out),
                "mu": eq4["mu"], "mu_choice": eq4["mu_choice"], "weight_bounds": eq4["bounds"],
                "map_prior": eq4["prior"], "map_gaze": eq4["gaze"]}
        if isinstance(pins_file, str | os.PathLike):
            meta["pins"] = _map_input(pins_file, out)
        text = weight_map_json(result.weights, result.names, result.avatar_names, meta=meta,
                               channels=eq4["channels"], mesh_channels=eq4.get("mesh_channels"))
    else:
        text = weight_map_csv(result.weights, result.names, result.avatar_names)
    done: dict = {}
    with outputs_all_or_nothing(done, map=out):   # a cache that cannot be written takes a new map with it
        done["map"] = write_text_atomic(out, text, force=force)
        for cache, data in pending:
            save_correspondence(None, cache, data=data)
    result.out_path = _written(out)       # the map written (a layer's path for personalize_avatar)
    return result


def _map_input(path, out: Path) -> str | None:
    """An input of a retarget map as its ``meta`` records it: relative to the map's folder, as a layer records
    its inputs (the avatar was recorded as typed, relative to the folder the command ran in, and the capture
    absolute once a pins file had made it be read first), or None for an object not read from a file."""
    from .io.layers import _relative_to_layer

    if path is None or str(path) == "":
        return None
    return _relative_to_layer(path, out)


def _refuse_implant_options(options) -> None:
    """Refuse (:class:`usdface.errors.OptionError`) an implant option among ``options`` given to
    :func:`write_retarget_map`: the map is eq. (4) of the fit's shapes on the avatar's, whatever the face
    transfer (``usdface retarget`` does not offer them)."""
    from .errors import OptionError
    from .transfer.options import IMPLANT_OPTIONS, option_name

    given = [k for k in IMPLANT_OPTIONS if k in options]
    if given:
        raise OptionError(f"{', '.join(option_name(k) for k in given)}: not used by the retarget map "
                          "(eq. 4 of the fitted shapes; no implant is written)",
                          fix="drop them, or use personalize (usdface personalize): it implants the "
                              "shapes")


#: Options :func:`personalize_avatar` itself takes (the rest go to :func:`usdface.transfer.personalize_avatar`
#: and the fit).
_API_OPTIONS = ("inspect", "take", "landmarks")


def _fit_option_names() -> set[str]:
    """The options :func:`personalize_avatar` passes to the fit: the fit's keywords and every method's own."""
    import inspect as _inspect

    from .personalize.api import METHOD_OPTIONS, fit_personalized_shapes

    return (set(_inspect.signature(fit_personalized_shapes).parameters)
            - {"capture", "method", "reg", "prior", "options", "avatar_prior"}
            | {k for ks in METHOD_OPTIONS.values() for k in ks})


#: What a name that is no personalize option is instead: a Pyblish manifest's ``review`` column (instance data
#: there) given to ``usdface batch`` was refused with the 40 options alone (a user trial, stop 50).
_NOT_AN_OPTION = {
    "review": "review: the review page is no option of the layer: write it from the layer with 'usdface "
              "review OUTPUT' (usdface.write_review), or give a batch manifest a review column (usdface "
              "batch, and a Pyblish publish of the manifest, write the page beside each layer)",
}


def _refuse_unknown_options(options, unlisted: Iterable[str] = (), columns: Iterable[str] = ()) -> None:
    """Refuse (:class:`usdface.errors.OptionError`, as every API function refuses an option it does not take)
    a name among ``options`` that :func:`personalize_avatar` does not take (a typo, a CLI flag such as
    ``review``), listing the ones it takes, less ``unlisted`` (ones the caller refuses with its own message,
    such as ``dry_run`` for a batch item: a list offering them sent the user from one refusal to the next),
    plus ``columns`` (names the caller takes itself, a batch row's ``review``: accepted, and offered for a
    misspelt one)."""
    import inspect as _inspect

    from .errors import OptionError
    from .transfer import pipeline as _pipeline

    transfer = set(_inspect.signature(_pipeline.personalize_avatar).parameters) - {
        "avatar", "capture", "out_path", "fit_options", "rig", "layer_edit", "command", "map_only",
        "extra_inputs", "pending_cache"}
    known = transfer | _fit_option_names() | set(_API_OPTIONS) | set(columns)
    unknown = sorted(set(options) - known)
    if unknown:
        import difflib

        offered = sorted(known - set(unlisted))
        # a batch row's 'metod' column: name the option meant, as the command line's flags do (stop 47)
        meant = {u: difflib.get_close_matches(u, offered, n=1, cutoff=0.75) for u in unknown}
        hints = "; ".join([f"{u}: did you mean {m[0]}?" for u, m in meant.items() if m]
                          + [_NOT_AN_OPTION[u] for u in unknown if u in _NOT_AN_OPTION])
        raise OptionError(f"unknown personalize option(s): {', '.join(unknown)}",
                          fix=(f"{hints}; " if hints else "")
                          + "drop them, or use one of: " + ", ".join(offered))


def check_personalize_options(**options: Any) -> None:
    """Refuse, before any work, what :func:`personalize_avatar` would refuse or ignore among ``options``: an
    option it does not take (a CLI flag such as ``review``, a typo), a bad mode, number or fit option
    (:class:`usdface.errors.OptionError` naming it and the fix). ``usdface batch`` runs it on every manifest
    row before the first item starts."""
    check_item_options(options, unlisted=())


#: The personalize options that are booleans (a batch row's and a Pyblish instance's are checked as such).
BOOLEAN_OPTIONS = ("inspect", "landmarks", "dry_run", "force")


def _item_flags(options, whose: str, fix) -> None:
    """The :data:`BOOLEAN_OPTIONS` among the personalize ``options`` (a dict, a batch row's, a Pyblish
    instance's or ``personalize_batch(options=)``) checked by :func:`usdface.errors.expect_flag`,
    ``fix(name)`` saying how to give one there; ``None`` is the default (False), as
    :func:`personalize_avatar` takes it."""
    from .errors import expect_flag

    for name in BOOLEAN_OPTIONS:
        expect_flag(options.get(name), name, whose, False, fix(name))


def check_item_options(options: dict, unlisted: Iterable[str] = ("dry_run",),
                       columns: Iterable[str] = ()) -> None:
    """:func:`check_personalize_options` on the dict ``options`` of a batch row or a Pyblish instance; an
    unknown name's refusal lists the options taken less ``unlisted`` (``dry_run``, which both refuse with a
    message of its own: a list offering it sent the user from one refusal to the next) plus ``columns``
    (names the caller takes and checks itself: a batch row's ``review``)."""
    from .transfer import options as _implant

    _refuse_unknown_options(options, unlisted, columns)
    _item_flags(options, "personalize's", lambda name: f"{name}=true or false, or leave it out (the default)")
    get = options.get
    _implant.check_mode_options(get("face_transfer", "person"), options)
    _implant.check_modes(get("face_transfer", "person"), get("approximation"),
                         get("prior", "avatar"), get("weight_bounds", (0.0, 1.0)),
                         get("map_prior", "namesake"), get("map_gaze", "namesake"))
    _implant.check_numbers(mu=get("mu", "auto"), extension_length=get("extension_length", 1.0),
                           falloff=get("falloff", 0.15), support=get("support", (0.01, 0.03)))
    from .personalize.api import check_fit_options

    method, reg = get("method", "menzel"), get("reg", "auto")
    fit = _fit_option_names()
    fit_opts = {k: v for k, v in options.items() if k in fit}
    check_fit_options(method, reg, **_implant.fit_prior_options(get("prior", "avatar"), method),
                      **fit_opts)


def _unique_mesh_names(keyed):
    """The rigs of ``keyed`` ``[(prim path, rig)]``, renamed where two meshes share a name (two SkelRoots
    with a ``Head`` each): those take their prim path (``/A/Head`` -> ``A_Head``), so glTF nodes and OBJ
    folders stay one per mesh."""
    import collections
    import dataclasses

    counts = collections.Counter(rig.name for _, rig in keyed)
    out = []
    for prim, rig in keyed:
        if counts[rig.name] > 1:
            rig = dataclasses.replace(rig, name=str(prim).strip("/").replace("/", "_"))
        out.append(rig)
    return out


def personalize_batch(manifest: PathLike, *, jobs: int | None = None, scheduler: str | None = None,
                      worker: str | None = None, options: dict | None = None, force: bool = False,
                      report_path: PathLike | None = None,
                      on_item: Callable[[ItemResult], None] | None = None) -> BatchReport:
    """Personalize every (avatar, capture, output) row of a CSV/JSON manifest (``usdface batch``) on ``jobs``
    local processes (default: one a CPU this process may use, as many as the memory holds,
    :func:`usdface.pipeline.batch.default_jobs`; 1 = in this process) or a Dask ``scheduler`` address.
    Items whose output exists are skipped (resume) unless ``force``; a failing item is recorded and the
    batch goes on.
    ``options`` apply to every item (manifest columns win); ``worker`` (``"module:function"``) replaces
    :func:`personalize_avatar` with a studio's own step. The JSON report is written (atomically) to
    ``report_path``, default ``<manifest stem>.report.json`` next to the manifest; returns the
    :class:`usdface.pipeline.batch.BatchReport` (``.report_path`` = where it was written).
    ``on_item(result)``, if given, is called with each item's :class:`usdface.pipeline.batch.ItemResult` as
    the item ends (in this process; its ``warnings`` are the item's), e.g. to log them as they come; an
    exception it raises stops the batch (no later item starts) and propagates with ``batch_report``."""
    _paths(manifest=(manifest, False), report_path=(report_path, True))
    if on_item is not None and not callable(on_item):
        from .errors import OptionError

        raise OptionError(f"personalize_batch's on_item must be a function of one item result, not "
                          f"{type(on_item).__name__}", fix="pass on_item=lambda result: ..., or leave it out")
    (force,) = _flags("personalize_batch", force=force)
    from .errors import OptionError
    from .io.atomic import check_output_file
    from .pipeline.batch import read_manifest, run_batch

    # as --jobs takes it: jobs=0 ran a process per CPU, a negative count in-process, "2" a ValueError
    if jobs is not None and (isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1):
        raise OptionError(f"jobs must be a whole number >= 1 (or None: one process per usable CPU), not "
                          f"{jobs!r}",
                          fix="pass jobs=1 to run in this process, jobs=N for N worker processes, or leave "
                              "it out")
    # options=["inspect"] died with Python's ValueError (dict update sequence), scheduler=8786 was taken
    from collections.abc import Mapping

    _expect(options, (Mapping,), "personalize_batch's options", "a {option: value} dict (or None)",
            'pass e.g. options={"inspect": True}, as --set inspect=true', none_ok=True)
    _expect(scheduler, (str,), "personalize_batch's scheduler", "a Dask scheduler's address (or None)",
            "pass scheduler='tcp://host:8786', or None for the local process pool", none_ok=True)
    _expect(worker, (str,), "personalize_batch's worker", "a 'module:function' string (or None)",
            "pass worker='studio.usdface_steps:run', or None for personalize", none_ok=True)
    # told as the options= given, not as the manifest's first row
    _item_flags(options or {}, "personalize_batch's options'",
                lambda name: f'pass options={{"{name}": True}} (or False), as --set {name}=true')
    from .pipeline.batch import review_flag

    review_flag(options or {}, "personalize_batch's options'",
                'pass options={"review": True} (or False), as --set review=true')
    items = read_manifest(manifest)
    _apply_batch_options(items, dict(options or {}), manifest)
    manifest = Path(manifest)
    path = Path(report_path) if report_path else manifest.with_name(manifest.stem + ".report.json")
    # the report is rewritten on every run (resume), but never over the manifest or an item's input; it is
    # written after the last item, so a place that refuses it (a read-only folder, an immutable report) stops
    # the batch before the first
    check_output_file(path, True, suffixes=(".json",), what="batch report",
                      inputs=[manifest, *(p for item in items for p in (item.avatar, item.capture))],
                      fix="pass --report PATH in a folder you can write to")
    try:
        run = _batch_preflight(items, worker, manifest, force)
    except KeyboardInterrupt as exc:   # stopped before the first item: this run's report, not the last run's
        from .pipeline.batch import FAILED, BatchReport, ItemResult

        why = "the batch was stopped before it started (while its rows were checked); run it again"
        exc.batch_report = BatchReport([ItemResult(index=i.index, avatar=str(i.avatar),
                                                   capture=str(i.capture), output=str(i.output),
                                                   status=FAILED, error=why, error_type="Interrupted")
                                        for i in items], 0.0, "not started")
        exc.batch_report.write(path)
        exc.report_path = _written(path)  # the command line names it (it printed only 'interrupted')
        raise
    try:
        report = run_batch(items, worker=run, jobs=jobs, scheduler=scheduler, force=force, on_item=on_item)
    except BaseException as exc:      # stopped: the report of this run (what finished), not the last run's
        partial = getattr(exc, "batch_report", None)
        if partial is not None:
            partial.write(path)
            exc.report_path = _written(path)
        raise
    report.report_path = _written(report.write(path))
    return report


def _row_error(item, exc, manifest, fix: str):
    """A row's path refused (``exc``) as the manifest's error: the row, the file, what is wrong, the fix."""
    from .errors import InputFileError

    where = [w for w in (exc.path, exc.prim and f"prim {exc.prim}") if w]     # as UsdFaceError names them
    named = f"{', '.join(where)}: " if where else ""
    return InputFileError(f"{item.label}: {named}{exc.message}", path=manifest, fix=exc.fix or fix)


def _batch_preflight(items, worker, manifest, force: bool = False):
    """Every row checked before any item runs (the default worker): its output (a layer's extension, not a
    folder, a place it can be written, no input), its options, and for a row that will run (``force`` or no
    output yet: resume skips the others without reading their inputs) its inputs (:func:`usdface.pipeline.
    batch.check_item_inputs`: present, readable, of the kind read) and an avatar not already personalized; a
    bad last row failed only at its turn, after the rows before it had run. Returns the worker function."""
    from .pipeline.batch import load_worker, personalize_worker

    run = load_worker(worker) if worker else personalize_worker
    if worker is None:                 # every row's options and output's place checked before any item runs
        from .errors import InputFileError, UsdFaceError
        from .io.atomic import refuse_existing
        from .io.layers import check_output_path
        from .io.usd_rig import refuse_usdface_output
        from .pipeline.batch import REVIEW, check_item_inputs, check_review_page, redoes, review_flag
        from .pipeline.batch import review_page as page_of

        for item in items:
            # the row's boolean cells, checked on every row as the options are: the review page beside the
            # layer (the manifest column the Pyblish collector reads too; it was refused as an unknown
            # option), then whether the row is redone (the batch's --force, or the row's force column)
            try:
                review = review_flag(item.options)
                redo = redoes(item, force)
            except UsdFaceError as exc:
                raise InputFileError(f"{item.label}: {exc.message}", path=manifest,
                                     fix=exc.fix) from None
            options = {k: v for k, v in item.options.items() if k != REVIEW}
            # an existing output is resume's (skipped, or redone with force); one skipped is not written, so
            # it cannot overwrite an input (listing the layers a USD input composes: ~16 ms a row)
            written = redo or not os.path.lexists(item.output)
            inputs = personalize_inputs(item.avatar, item.capture, **options) if written else ()
            try:
                check_output_path(item.output, True, inputs=inputs)
                # a link to nothing is not a finished row (resume runs it: run_batch) but an existing name
                # the worker refuses without force: refused here, as personalize -o refuses it (stop 54)
                if not redo and not os.path.exists(item.output):
                    refuse_existing(item.output, False, "output layer")
            except UsdFaceError as exc:
                raise _row_error(item, exc, manifest, "fix the manifest's output column") from None
            # the correspondence cache, an output too (in an input folder, where it cannot be written), as
            # a Pyblish publish validates it: it failed only at its row's turn, after the rows before it
            if written:
                try:
                    _check_correspondence_cache(options.get("correspondence"), inputs, outputs=[item.output],
                                                option="the manifest's correspondence column",
                                                output_option="its output column")
                except UsdFaceError as exc:
                    raise _row_error(item, exc, manifest, "fix the manifest's correspondence column") \
                        from None
            # the page as the layer: a place that takes it, not there without force; a finished layer's
            # missing page (resume writes it alone) too
            if review and (written or not os.path.lexists(page_of(item.output))):
                try:
                    check_review_page(item.output, redo, inputs=[item.output, *inputs])
                except UsdFaceError as exc:
                    raise _row_error(item, exc, manifest, "fix the manifest's output or review column") \
                        from None
            try:
                check_item_options(item.options, columns=(REVIEW,))   # dry_run not offered: refused below
            except UsdFaceError as exc:
                raise InputFileError(f"{item.label}: {exc.message}", path=manifest,
                                     fix=exc.fix or "fix the manifest's option columns") from None
            except (TypeError, ValueError) as exc:      # a value of the wrong shape for its option
                raise InputFileError(f"{item.label}: bad option value ({exc})", path=manifest,
                                     fix="fix the manifest's option columns (docs/personalize.md, Options)") \
                    from None
            # run_batch's own test: resume skips the row (or reports its output stale), reading nothing (a
            # done row's capture since moved away did not stop the resume)
            if not redo and Path(item.output).exists():
                continue
            try:                       # what the item's readers would refuse, after the rows before it ran
                check_item_inputs(item)
            except UsdFaceError as exc:
                raise _row_error(item, exc, manifest, "fix the manifest's path columns") from None
            try:              # a row whose avatar is already personalized (a usdface layer, its export)
                refuse_usdface_output(item.avatar)
            except UsdFaceError as exc:
                raise InputFileError(f"{item.label}: {item.avatar}: {exc.message}", path=manifest,
                                     fix=f"{exc.fix} in the manifest's avatar column" if exc.fix
                                     else "fix the manifest's avatar column") from None
            if item.options.get("dry_run"):              # nothing written, yet the item counted as done
                raise InputFileError(f"{item.label}: dry_run writes no output, and the batch would "
                                     "count the item done without it", path=manifest,
                                     fix="drop dry_run; preview one item with 'usdface personalize AVATAR "
                                         "CAPTURE -o OUT --dry-run'")
            every = item.options.get("every", 1)
            if not isinstance(every, bool) and isinstance(every, int) and every > 1 \
                    and Path(item.capture).exists():
                from .io.take import is_take

                if not is_take(item.capture):    # as the item itself would refuse it, but before any work
                    raise InputFileError(f"{item.label}: every={every} thins a take read whole; "
                                         f"{item.capture} holds frames picked one per shape", path=manifest,
                                         fix="leave 'every' out for that row, or give the take itself as its "
                                             "capture")
    return run


def _apply_batch_options(items, shared: dict, manifest) -> None:
    """Give every item the batch-wide ``shared`` options (``--set``) under its own (manifest columns win).
    A join option a face-transfer mode does not use (``falloff``, ``extension_length``, ``support``:
    :data:`usdface.transfer.options.MODE_OPTIONS`) goes only to the rows whose mode uses it, so one
    ``--set falloff=0`` serves a manifest of ``offset`` and ``person`` rows; one that no row's mode uses is
    refused (it would change nothing). A row's own columns are checked as given. A path-valued one
    (``take``, ``name_map``, ``pins``, ``correspondence``) given relative is made absolute against the current
    folder, where it was given: the items' own paths are absolute, and a relative one reached the workers as
    it was, so a Dask worker (or a studio worker that changes folder) looked for it in its own folder."""
    from .errors import InputFileError
    from .pipeline.batch import PATH_OPTIONS
    from .transfer.options import MODE_ONLY_OPTIONS, MODE_OPTIONS, modes_using, option_name

    shared = {k: os.path.abspath(v) if k in PATH_OPTIONS and isinstance(v, str | os.PathLike) and str(v)
              else v for k, v in shared.items()}
    restricted = MODE_ONLY_OPTIONS & set(shared)
    used, taken = set(), set()
    for item in items:
        mode = item.options.get("face_transfer", shared.get("face_transfer", "person"))
        keep = set(MODE_OPTIONS.get(mode, restricted))
        used |= restricted & keep
        given = {k: v for k, v in shared.items() if k not in restricted or k in keep}
        taken |= set(given) - set(item.options)
        item.options = {**given, **item.options}
    unused = sorted(restricted - used)
    if unused and items:
        names = ", ".join(option_name(k) for k in unused)
        raise InputFileError(f"{names} set for the whole batch, but no row's face_transfer uses "
                             f"{'them' if len(unused) > 1 else 'it'}", path=manifest,
                             fix="drop it, or give it to rows whose face_transfer uses it: "
                                 + "; ".join(f"{option_name(k)}: {', '.join(modes_using(k))}"
                                             for k in unused))
    overridden = sorted(set(shared) - taken)     # every row that would take it sets its own: changes nothing
    if overridden and items:
        names = ", ".join(f"{k}={shared[k]}" for k in overridden)
        raise InputFileError(f"--set {names} reaches no row: every row it would apply to sets its own "
                             f"{', '.join(overridden)} (manifest columns win)", path=manifest,
                             fix="drop the --set, or empty that column's cells in the rows it should reach")


def check(file_or_stage: PathLike | Any, pixar: bool = True,
          rules: Iterable[str] | None = None, name_map: dict | PathLike | None = None,
          face_mesh: str | None = None) -> list[Issue]:
    """Validate a face-rig USD file (or an open ``Usd.Stage``): usdface's face-rig rules plus, with ``pixar``,
    OpenUSD's own validators, merged and sorted errors first (``usdface check``). ``name_map``: as for
    :func:`read_avatar`; ``face_mesh``: as for :func:`personalize` (a stage holding several characters' face
    rigs, a shot, is an error without it, as personalize refuses it). An ``Sdf.Layer`` is checked as the
    stage it opens; anything else is refused (``UsdFaceError``; it was an ``AttributeError`` from deep in the
    rules). Never modifies the file."""
    from .io.name_map import read_name_map
    from .pipeline.validators import validate_file, validate_stage

    (pixar,) = _flags("check", pixar=pixar)
    name_map = read_name_map(name_map)
    if isinstance(file_or_stage, str | os.PathLike):
        return validate_file(file_or_stage, pixar=pixar, rules=rules, name_map=name_map, face_mesh=face_mesh)
    from pxr import Sdf, Usd

    if isinstance(file_or_stage, Sdf.Layer):
        file_or_stage = Usd.Stage.Open(file_or_stage, Usd.Stage.LoadAll)
    if not isinstance(file_or_stage, Usd.Stage):
        from .errors import UsdFaceError

        raise UsdFaceError(f"check takes a USD file's path, a Usd.Stage or an Sdf.Layer, not "
                           f"{type(file_or_stage).__name__}", fix="pass the file's path or the open stage")
    return validate_stage(file_or_stage, pixar=pixar, rules=rules, name_map=name_map, face_mesh=face_mesh)


def inspect_file(path: PathLike, name_map: dict | PathLike | None = None) -> dict:
    """A summary of a USD avatar, capture or usdface layer (``usdface inspect``): meshes, shapes, units,
    how each channel maps to ARKit (``name_map`` as for :func:`read_avatar`), provenance."""
    _paths(path=(path, False))
    from .inspect import inspect_file as _inspect

    return _inspect(path, name_map=name_map)


# ---------------------------------------------------------------------------------------------------------
# review and delivery (usdface review / usdface export)
# ---------------------------------------------------------------------------------------------------------
__all__ += ["write_review", "export_avatar"]


def write_review(layer_path: PathLike, out_path: PathLike, *, capture: PathLike | Capture | None = None,
                 take: PathLike | None = None, fit_errors: bool = True, force: bool = False,
                 max_vertices: int | None = None, allow_moved_neutral: bool = False) -> Path:
    """Write the review page of a usdface layer (``usdface review``): ONE self-contained HTML file (plotly.js
    and the mesh data inside, no network needed to view it) with generic | personalized side by side, a
    slider per shape, presets, a change heat map (mm), the landmarks when the layer has them, playback of
    the capture's test expressions and of ``take`` (Live Link Face CSV or USD take), and the fit's figures.

    ``capture`` defaults to the capture recorded in the layer's provenance (when it still exists); with
    ``fit_errors`` the generic template and the personalized shapes are scored on its test
    expressions (eq. 5: the layer's recorded figures of its own fit, or a refit for another capture).
    A mesh of more than ``max_vertices`` vertices (default 60,000; 0: no limit) is shown decimated to about
    that many of its own vertices (the page says so; its tables are the full mesh's figures).
    Returns the path written (atomically; an existing file needs ``force``, checked before any work).
    A layer its avatar no longer fits is refused (:func:`usdface.io.layers.refuse_avatar_mismatch`), one
    whose avatar's neutral was re-sculpted too unless ``allow_moved_neutral`` (then warned about)."""
    _paths(layer_path=(layer_path, False), out_path=(out_path, False))
    fit_errors, force = _flags("write_review", fit_errors=fit_errors, force=force)
    if max_vertices is not None and (isinstance(max_vertices, bool) or not isinstance(max_vertices, Integral)
                                     or max_vertices < 0):   # -1 and "1000" were taken (the CLI refuses them)
        from .errors import OptionError

        raise OptionError(f"bad max_vertices {max_vertices!r:.60}: write_review's max_vertices is a whole "
                          "number >= 0 or None",
                          fix="pass max_vertices=60000 (the default, None; --max-vertices) or 0 (no limit)")
    from .errors import InputFileError
    from .io.atomic import check_output_file, write_text_atomic
    from .io.usd_open import require_file
    from .review.collect import collect_review
    from .review.page import build_review_html

    # a missing input first, then the output ('review MISSING.usda' in a folder one cannot write to was
    # told that the page could not be written there); what an existing input is, its readers say
    if not Path(layer_path).exists():
        require_file(layer_path, "USD file", "check the path (a .usd/.usda/.usdc file)")
    if take is not None and not Path(take).exists():
        raise InputFileError("take not found", path=take, fix="pass a Live Link Face CSV, USD take or folder")
    if isinstance(capture, str | Path) and not Path(capture).exists():
        raise InputFileError("capture not found", path=capture, fix="pass a capture folder or capture .usda")
    out = check_output_file(out_path, force, suffixes=(".html", ".htm"), what="review page",
                            inputs=[layer_path, capture, take])
    from . import progress
    from .io.layers import refuse_avatar_mismatch, stale_inputs
    from .io.usd_rig import usdface_output_provenance
    from .review.collect import _fitted

    (allow_moved_neutral,) = _flags("write_review", allow_moved_neutral=allow_moved_neutral)
    refuse_avatar_mismatch(layer_path, "a review page",    # a sign-off of a layer that no longer fits
                           allow_moved_neutral=allow_moved_neutral)

    provenance = usdface_output_provenance(layer_path)       # the root layer's header: no stage composed
    record = provenance or {}
    # a --capture is compared with the capture a personalize layer records (a landmarks layer records none)
    given = [capture] if isinstance(capture, str | Path) and _fitted(record) else []
    what = [w for w, given in (("fit figures", fit_errors), ("take", take is not None)) if given]
    with progress.steps("review", 3) as p:          # each step named for what it does while it runs
        p.start(f"read {Path(layer_path).name} (meshes, shapes" + "".join(f", {w}" for w in what) + ")")
        data = collect_review(layer_path, capture=capture, take=take, fit_errors=fit_errors,
                              max_vertices=max_vertices)
        # the page is a sign-off: said before it is built, once its inputs are known to be usable (a take
        # given as --capture was warned about as 'not among the inputs', then refused)
        for text in stale_inputs(layer_path, given, record=provenance) if provenance else []:
            warn(text)
        p.start("build the page")
        page = build_review_html(data)
        p.start(f"write {out.name}")
        written = write_text_atomic(out, page, force=force)
    return _written(written)


def export_avatar(layer_path: PathLike, *, gltf: PathLike | None = None, obj_dir: PathLike | None = None,
                  flatten: PathLike | None = None, variant: str | None = None, skin: bool = True,
                  morph_normals: bool = True, force: bool = False,
                  allow_moved_neutral: bool = False) -> dict[str, Path]:
    """Deliver one variant (``personalized`` or ``generic``) of a usdface layer (``usdface export``):

    * ``gltf``: glTF 2.0 (``.glb`` or ``.gltf``), one morph target per shape, names in
      ``mesh.extras.targetNames``, metres, Y up, with the skin and skeleton when ``skin`` and the avatar has
      joints (see :mod:`usdface.io.gltf`), each target with its ``NORMAL`` deltas unless
      ``morph_normals=False`` (``POSITION`` only: about half the file, for engines that recompute normals);
    * ``obj_dir``: a folder with one sub-folder per mesh: ``neutral.obj`` and one full target mesh
      ``<shape>.obj`` per shape (metres, Y up, like a capture folder's ``template/``), with ``vt`` texture
      coordinates when the mesh has them;
    * ``flatten``: one flattened USD file with the variant baked in (``.usdz``: packaged by USD)
      (:func:`usdface.io.flatten.flatten_variant`).

    Every output is checked before any work (an existing one needs ``force``) and written atomically, and
    the set is all or nothing for new outputs: when a later one fails (a full disk, Ctrl-C), the ones this
    call created are removed (one it replaced with ``force`` stays replaced). The inputs are never modified.
    Returns {"gltf"|"obj_dir"|"flatten": path written, absolute}. ``variant`` None (the default): the
    personalized variant of a layer; a plain avatar (not a usdface layer) exports as authored (the glTF's
    ``extras.usdface.variant`` is then ``"authored"``; for a flattened export of a layer, the variant baked
    into it, see :func:`usdface.io.flatten.exported_variant`). An explicit ``"personalized"`` (or
    ``"generic"``) of a file that has no such variant (a plain avatar; the generic variant flattened) is
    refused, naming the file (:class:`usdface.errors.InputFileError`): a plain avatar exported as asked
    was labelled 'as authored' in passing, while ``--variant generic`` of it was refused."""
    _paths(layer_path=(layer_path, False))
    skin, morph_normals, force, allow_moved_neutral = _flags(
        "export_avatar", skin=skin, morph_normals=morph_normals, force=force,
        allow_moved_neutral=allow_moved_neutral)
    from .errors import OptionError
    from .io.atomic import check_output_dir, check_output_file, outputs_all_or_nothing
    from .io.flatten import VARIANTS
    from .io.gltf import GLTF_EXTENSIONS
    from .io.layers import check_output_path

    asked = variant is not None           # an explicit variant must be in the file; the default need not
    variant = "personalized" if variant is None else variant
    if variant not in VARIANTS:
        raise OptionError(f"unknown variant {variant!r}", fix=f"choose one of {', '.join(VARIANTS)}")
    if not (gltf or obj_dir or flatten):
        raise OptionError("nothing to export: no gltf, obj_dir or flatten output given",
                          fix="pass --gltf OUT.glb, --obj-dir DIR and/or --flatten OUT.usdc")
    if obj_dir:   # a file output in the folder output: written first, it made the folder "not empty"
        folder = Path(obj_dir).resolve()
        for what, option, out in (("glTF output", "--gltf", gltf),
                                  ("flattened USD file", "--flatten", flatten)):
            place = Path(out).resolve() if out else None
            if place is not None and (place == folder or folder in place.parents):
                raise OptionError(f"{what} {out} is {'the' if place == folder else 'inside the'} --obj-dir "
                                  f"folder {obj_dir}: one output would be written into (or over) the other",
                                  path=out, fix=f"give {option} a path outside the --obj-dir folder")
    if not Path(layer_path).exists():                   # a missing layer before the outputs' problems
        from .io.usd_open import require_file

        require_file(layer_path, "layer", "check the path (a .usd/.usda/.usdc file)")
    _refuse_export_input(layer_path, gltf=gltf, obj_dir=obj_dir, flatten=flatten, variant=variant)
    if asked and variant == "personalized":
        _refuse_absent_personalized(layer_path, gltf=gltf, obj_dir=obj_dir, flatten=flatten)
    if gltf:
        check_output_file(gltf, force, suffixes=GLTF_EXTENSIONS, what="glTF output", inputs=[layer_path],
                          example=f"{Path(layer_path).stem}.glb")            # newdir/: a file inside it
    if obj_dir:
        check_output_dir(obj_dir, force, inputs=[layer_path])
    if flatten:
        check_output_path(flatten, force, inputs=[layer_path], what="flattened USD file",
                          example=f"{Path(layer_path).stem}.usdc", usdz=True)
    from .io.layers import refuse_avatar_mismatch, stale_inputs

    # a layer its revised avatar no longer fits (overrides on nothing, offsets on shifted vertices) is
    # refused: exported, it was a generic or broken face labelled [personalized]; over a re-sculpted
    # neutral, offsets fitted and checked on the old one, unless the caller accepts them (allow_moved_neutral)
    refuse_avatar_mismatch(layer_path, "an export", allow_moved_neutral=allow_moved_neutral)
    for text in stale_inputs(layer_path):          # a stale layer is exported as it is, but not silently
        warn(text)
    done: dict[str, Path] = {}
    with outputs_all_or_nothing(done, gltf=gltf, obj_dir=obj_dir, flatten=flatten):
        _export_outputs(layer_path, done, gltf, obj_dir, flatten, variant, skin, morph_normals, force)
    return done


def _refuse_export_input(layer_path, **outputs) -> None:
    """A personalize input given to ``export`` where its layer goes (a capture file or folder, a take, a
    weights take, an error-map file): say what it is, that export takes a layer written by ``usdface
    personalize`` (or an avatar), and the two commands to run (personalize with it, then this export of the
    layer), each path one shell word. The avatar reader's own refusal told export's user the fix of
    personalize's ('personalize: AVATAR, then CAPTURE'), and ``--flatten`` of a capture wrote the capture
    flattened, as 'a plain avatar'."""
    import shlex

    from .errors import RigError
    from .io.file_kind import Kind, file_kind
    from .io.usd_rig import non_avatar_input

    path = Path(layer_path)
    if path.is_dir():
        folder = file_kind(path)                    # one look at the folder
        kind = folder.kind
        if kind is not Kind.CAPTURE_FOLDER and not (kind is Kind.TAKE_FOLDER and folder.meshes):
            return                                  # another folder: the reader says it is one
        found = (Kind.CAPTURE if kind is Kind.CAPTURE_FOLDER else Kind.TAKE,
                 f"a {kind} ('usdface personalize' reads it with the avatar), not an avatar", None)
    else:
        found = non_avatar_input(path)
    if found is None:
        return
    kind, what, prim = found
    word = shlex.quote(str(path))
    personalize = {
        Kind.CAPTURE: f"usdface personalize AVATAR {word} -o person.usda",
        Kind.TAKE: f"usdface personalize AVATAR {word} -o person.usda",
        Kind.WEIGHTS_TAKE: f"usdface personalize AVATAR CAPTURE --take {word} -o person.usda",
    }.get(kind)
    options = [f"--{name.replace('_', '-')} {shlex.quote(str(out))}" for name, out in outputs.items()
               if out and name != "variant"]
    if outputs.get("variant") == "generic":
        options.append("--variant generic")
    export = " ".join(["usdface export person.usda", *options])
    what = what.removesuffix("not an avatar") + "not a layer written by 'usdface personalize' (nor an avatar)"
    fix = (f"export takes the layer personalize writes: personalize first ({personalize}), then export "
           f"({export})" if personalize else
           f"open it in usdview to look at the errors; export takes a layer written by 'usdface personalize' "
           f"(or an avatar) ({export})")
    raise RigError(f"this is {what}", path=path, prim=prim, fix=fix)


def _refuse_absent_personalized(layer_path, **outputs) -> None:
    """An explicit ``variant="personalized"`` (``export --variant personalized``) of a file with no
    personalized variant: a plain avatar (no ``usdfacePersonalization`` variant set, not a flattened export,
    a DCC export or a ``usdface fit`` rig, which hold the person's shapes) or a flattened export of the
    *generic* variant. Raises :class:`usdface.errors.InputFileError` naming the file and the two fixes
    (personalize it first; or export it as authored, without ``--variant``). It was written as authored,
    said only in the label, while ``--variant generic`` of the same file was refused."""
    import shlex

    from .errors import InputFileError
    from .io.file_kind import Kind, file_kind
    from .io.flatten import AS_AUTHORED, exported_variant
    from .io.usd_rig import dcc_export_marks

    given = exported_variant(layer_path, "personalized")
    if given == "personalized":
        return
    if given == AS_AUTHORED and (dcc_export_marks(layer_path) or file_kind(layer_path).kind is Kind.FIT):
        return                     # the person's shapes as authored: the label says which
    word = shlex.quote(str(layer_path))
    options = " ".join(f"--{name.replace('_', '-')} {shlex.quote(str(out))}" for name, out in outputs.items()
                       if out)
    if given == "generic":
        raise InputFileError("a flattened export of the generic variant ('usdface export --flatten "
                             "--variant generic'): the personalized variant is not in it", path=layer_path,
                             fix="export the personalized variant of the layer it was flattened from, or "
                                 f"export this file as authored (usdface export {word} {options})")
    raise InputFileError("no usdfacePersonalization variant set: a plain avatar, not personalized, so "
                         "'--variant personalized' has nothing to export", path=layer_path,
                         fix=f"personalize it first (usdface personalize {word} CAPTURE -o person.usda), "
                             f"then export the layer (usdface export person.usda {options}); or export the "
                             f"avatar as authored, without --variant (usdface export {word} {options})")


def _export_outputs(layer_path, done: dict, gltf, obj_dir, flatten, variant: str, skin: bool,
                    morph_normals: bool, force: bool) -> None:
    """:func:`export_avatar`'s writes, each output recorded in ``done`` once it is complete; each step named
    on stderr while it runs (a 225k-vertex head's glTF export ran 30 CPU-s without a word)."""
    from .progress import steps

    count = 2 * bool(gltf or obj_dir) + bool(gltf and obj_dir) + bool(flatten)
    with steps("export", count) as p:
        _export_steps(p, layer_path, done, gltf, obj_dir, flatten, variant, skin, morph_normals, force)


def _export_steps(p, layer_path, done: dict, gltf, obj_dir, flatten, variant: str, skin: bool,
                  morph_normals: bool, force: bool) -> None:
    from .io.atomic import replace_dir_atomically
    from .io.flatten import exported_variant, flatten_variant, read_avatar_variant
    from .io.gltf import write_gltf
    from .io.mesh_io import ObjWriter
    from .io.usd_rig import VARIANT_PROPERTY
    from .model import FaceRig as _FaceRig
    from .progress import steps

    if gltf or obj_dir:
        p.start(f"read the {variant} variant of {Path(layer_path).name}")
        avatar = read_avatar_variant(layer_path, variant)
        keyed = [(m.key, m) for m in avatar.meshes] + [
            (prim, _FaceRig(points, tris, [], [], name=prim.rsplit("/", 1)[-1]))
            for prim, (points, tris) in sorted(avatar.metadata.get("static_meshes", {}).items())]
        rigs = _unique_mesh_names(keyed)
        with_inbetweens = [f"{rig.name}:{n}" for rig in rigs for n in rig.inbetweens]
        if with_inbetweens:           # glTF morph targets and full target OBJs are the primary shapes only
            more = " ..." if len(with_inbetweens) > 4 else ""
            warn(f"{len(with_inbetweens)} shape(s) have inbetweens, which glTF and OBJ targets do "
                 f"not carry ({', '.join(with_inbetweens[:4])}{more}): they play linearly between 0 "
                 "and 1 there")
        from .io.usd_texcoords import read_texcoords

        uvs = read_texcoords(layer_path, [(prim, rig.name, rig.triangles)
                                          for (prim, _), rig in zip(keyed, rigs, strict=True)])
        if gltf:
            from .io.usd_skeleton import read_gltf_skins

            p.start(f"write {Path(gltf).name}")
            # one skin per skeleton (a shot with two avatars: each mesh skinned by its own), keyed by the
            # meshes' names in the glTF (A_Head, B_Head when two share a name)
            names = {str(prim): rig.name for (prim, _), rig in zip(keyed, rigs, strict=True)}
            skeleton = read_gltf_skins(layer_path, avatar, names=names) if skin else None
            root = (avatar.default_prim or "/Avatar").rsplit("/", 1)[-1]
            given = exported_variant(layer_path, variant)
            extras = {"usdface": {"source": Path(layer_path).name, "variant": given}}
            # on the nodes too: what a DCC keeps (Blender: custom properties, exported as userProperties),
            # so a DCC's USD export of the personalized glTF is refused as personalized (dcc_export_marks)
            marks = {VARIANT_PROPERTY: given} if given in ("personalized", "generic") else None
            from .io.usd_texcoords import normal_offsets, read_normals

            # the meshes' authored normals (hard edges, a DCC's custom normals) and the shapes' normalOffsets
            placed = {m.key: m.source.to_internal for m in avatar.meshes if m.source}
            placed.update(avatar.metadata.get("static_to_internal", {}))
            normals = read_normals(layer_path, [(prim, rig.name, rig.triangles, placed[prim])
                                                for (prim, _), rig in zip(keyed, rigs, strict=True)
                                                if prim in placed])
            offsets = {rig.name: found for rig in rigs if (found := normal_offsets(rig)) is not None}
            write_gltf(gltf, rigs, skin=skeleton, root_name=root, extras=extras, node_extras=marks,
                       texcoords=uvs, normals=normals, target_normals=offsets, morph_normals=morph_normals,
                       force=force)
            done["gltf"] = _written(gltf)
        if obj_dir:
            count = sum(len(r.names) + 1 for r in rigs)
            p.start(f"write {count} OBJs to {Path(obj_dir).name}")
            # one line every few seconds naming the OBJ written (a 225k-vertex head: ~12 MB and ~0.3 s each)
            with replace_dir_atomically(obj_dir, force=force) as tmp, steps("OBJ", count) as wrote:
                for rig in rigs:
                    folder = tmp / rig.name
                    folder.mkdir()
                    # vt: the same texture coordinates as the glTF; faces, vt and unmoved rows formatted once
                    objs = ObjWriter(rig.neutral, rig.triangles, uv=uvs.get(rig.name),
                                     path=folder / "neutral.obj")
                    objs.write(folder / "neutral.obj", rig.neutral)
                    wrote(f"{rig.name}/neutral.obj")
                    for name, delta in zip(rig.names, rig.deltas, strict=True):
                        objs.write(folder / f"{name}.obj", rig.neutral + delta)
                        wrote(f"{rig.name}/{name}.obj")
            done["obj_dir"] = _written(obj_dir)
    if flatten:
        p.start(f"flatten the {variant} variant into {Path(flatten).name}")
        flatten_variant(layer_path, flatten, variant, force=force)
        done["flatten"] = _written(flatten)
