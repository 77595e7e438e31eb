"""Errors raised by usdface.

Every user-facing failure is a :class:`UsdFaceError` subclass whose message names the file, the prim
(when there is one) and the fix, so the CLI can print one clear line and exit non-zero.
"""

from __future__ import annotations

import errno
import os
import sys
import warnings


class UsdFaceError(Exception):
    """Base class of every error usdface raises on bad input or a failed step.

    Parameters
    ----------
    message : what went wrong.
    path : the file concerned (str or Path), if any.
    prim : the USD prim path concerned, if any.
    fix : one sentence telling the user what to do about it.
    """

    def __init__(self, message: str, *, path=None, prim=None, fix: str | None = None):
        self.message = message
        self.path = None if path is None else str(path)
        self.prim = None if prim is None else str(prim)
        self.fix = fix
        super().__init__(self.__str__())

    def __str__(self) -> str:
        where = []
        if self.path:
            where.append(self.path)
        if self.prim:
            where.append(f"prim {self.prim}")
        text = (": ".join([", ".join(where), self.message]) if where else self.message)
        if self.fix:
            text += f" (fix: {self.fix})"
        return text


def add_to_message(exc: BaseException, note: str) -> None:
    """Add ``note`` (what a failed step removed or left on disk, and why) to ``exc``'s message: a
    :class:`UsdFaceError`'s text before its fix, any other exception's as a note (``__notes__``, which
    ``usdface batch``'s report joins to the error). The Pyblish extractors and the batch's review page say
    what they left with it."""
    if isinstance(exc, UsdFaceError):
        exc.message = f"{exc.message} ({note})"
        exc.args = (str(exc),)
    else:
        exc.add_note(note)


class InputFileError(UsdFaceError):
    """A file is missing, unreadable or not of the expected format."""


class TimecodeError(InputFileError):
    """A Live Link Face take's timecodes do not fit the rate they are read at (a frame field at or above the
    rate, a negative field): reading on would place the frames at wrong times."""


class RigError(UsdFaceError):
    """An avatar's UsdSkel face rig is malformed (no SkelRoot, no blend shapes, inconsistent arrays...)."""


class AlreadyPersonalizedError(RigError):
    """An avatar given to ``personalize``/``retarget`` is already personalized: a usdface output layer, or a
    flattened export of its personalized variant (``usdface export --flatten``), or a DCC's export of such a
    layer (Blender's, recognised by the ``usdfaceShapes`` scopes it keeps); personalizing it again would
    stack the personalization on the personalized shapes."""


class CaptureError(UsdFaceError):
    """A capture (folder, capture.usda, take) is malformed."""


class GeometryError(UsdFaceError):
    """Geometry is unusable: NaN/inf, empty, degenerate, mismatched vertex counts."""


class OptionError(UsdFaceError):
    """An option cannot be used as given: one the chosen mode or command does not use (``falloff`` with
    ``face_transfer='person'``, a face-transfer option for ``retarget``), or a value out of its range. Named
    in both spellings (``falloff (--falloff)``), refused before any work."""


class OutputExistsError(UsdFaceError):
    """The output file exists and --force was not given."""


class OutputNotWritableError(InputFileError):
    """An output cannot be written where it was asked for: a read-only folder or file system, a missing
    permission, an immutable (``chattr +i``) or append-only file or folder, a parent that is a file. Raised
    by the output checks (:func:`usdface.io.atomic.check_output_file`,
    :func:`usdface.io.atomic.check_output_dir`) before any work, naming the output, the folder that refuses
    it and the fix (:func:`write_fix`)."""


#: errno -> what to do about a write that fails with it; ``{o}`` is " (-o)" where the command has that option.
_WRITE_FIXES = {
    errno.EACCES: "choose a folder you can write to{o} or fix its permissions",
    errno.EPERM: "choose a folder you can write to{o} or fix its permissions",
    errno.EROFS: "the file system is read-only: write the output elsewhere{o}",
    errno.ENOSPC: "free disk space or write the output elsewhere{o}",
    errno.EDQUOT: "free disk space (quota) or write the output elsewhere{o}",
    errno.EISDIR: "the path is a folder: give a file name",
    errno.ENOTDIR: "a parent of the path is a file, not a folder: choose another path",
    errno.EEXIST: "a file is in the way of a folder the output needs: choose another path{o} or move it",
    errno.ENOENT: "check the path",
    errno.ENAMETOOLONG: "use a shorter path",
}


def _shown(value) -> str:
    """``value`` as a refusal shows it: its repr on one line (a Capture's spans several: its arrays), at most
    60 characters."""
    return " ".join(repr(value).split())[:60]


def expect_kind(value, kinds: tuple, what: str, expected: str, fix: str, *, none_ok: bool = False) -> None:
    """Refuse an argument of the wrong kind with :class:`OptionError` naming the argument (``what``), what it
    takes and the fix, before any work: ``personalize_avatar(None, ...)``, a ``face_mesh`` given as a
    number, a path for a ``Capture`` died with Python's ``TypeError`` / ``AttributeError`` from deep inside
    (``'str' object has no attribute 'names'``)."""
    if (value is None and none_ok) or (value is not None and isinstance(value, kinds)):
        return
    raise OptionError(f"{what} must be {expected}, not {type(value).__name__} ({_shown(value)})", fix=fix)


def expect_flag(value, name: str, whose: str, default: bool, fix: str | None = None) -> bool:
    """The value of the boolean option ``name``: ``True``/``False`` (numpy's too) as a Python ``bool``,
    ``None`` as ``default`` (the option left out: a JSON manifest's ``null``, a script's ``force=None``),
    anything else refused with :class:`OptionError` before any work (``force="no"`` counted as true and
    replaced an existing output). ``whose``: the owner as the message names it (``"write_capture's"``,
    ``"personalize's"``); ``fix``: how to give it where it was given (default: as a Python argument).

    The one check of a boolean option: the API's arguments, a batch row's or a Pyblish instance's
    personalize options and ``personalize_batch(options=)`` differed on ``None`` (refused, refused,
    accepted and then refused by the row check) and in their messages."""
    if value is None:
        return default
    if isinstance(value, bool):
        return value
    import numpy as np

    if isinstance(value, np.bool_):
        return bool(value)
    raise OptionError(f"bad {name} {_shown(value)}: {whose} {name} is a boolean (True or False; None: the "
                      f"default, {default})", fix=fix or f"pass {name}=True or {name}=False")


def write_fix(err: int | None, output_option: bool = False) -> str:
    """What to do about a write that failed with errno ``err`` (one sentence, the ``fix`` of an error);
    ``output_option``: name ``-o`` (the command has that option). Shared by the output checks and the CLI's
    one-line report of an OSError, so both say the same."""
    fix = _WRITE_FIXES.get(err, "check the path, its permissions and the free disk space")
    return fix.format(o=" (-o)" if output_option else "")


class RegistrationError(UsdFaceError):
    """Capture and avatar could not be registered (no overlap, too large a residual)."""


class FitError(UsdFaceError):
    """The personalized-shape fit cannot be set up (no training frames, unknown method...)."""


class LandmarkError(UsdFaceError):
    """A landmark layout cannot be computed (no shapes, bad epsilon...)."""


class UsdFaceWarning(UserWarning):
    """Category of the warnings usdface issues (a :class:`UserWarning`): ``warnings.filterwarnings("ignore",
    category=UsdFaceWarning)`` silences them, ``"error"`` makes them raise. They name the line of the
    caller's code (a script's call of the API), not usdface's own (:func:`warn`), so a filter by
    ``module=`` matches the caller's module."""


#: usdface's own folder: frames whose file is in it are not the caller's (:func:`warn`).
_PACKAGE = os.path.dirname(os.path.abspath(__file__)) + os.sep


def _importlib_frame(frame) -> bool:
    """A frame of the import machinery, which :func:`warnings.warn` does not count in ``stacklevel``."""
    name = frame.f_code.co_filename
    return "importlib" in name and "_bootstrap" in name


def warn(message, category: type[Warning] = UsdFaceWarning) -> None:
    """Issue a warning at the caller's line: the first frame outside the usdface package (a script's call of
    :func:`usdface.api.personalize_avatar`, not the reader several calls down that noticed), whatever the
    depth of the call inside usdface. (``skip_file_prefixes`` of Python 3.12 does this; 3.11 is supported.)"""
    level, frame = 1, sys._getframe(0)                 # stacklevel 1 is this function
    while True:
        back = frame.f_back
        while back is not None and _importlib_frame(back):
            back = back.f_back
        if back is None:
            break
        frame, level = back, level + 1
        if not os.path.abspath(frame.f_code.co_filename).startswith(_PACKAGE):
            break
    warnings.warn(message, category, stacklevel=level)
