"""Errors raised by usdface.

Every user-facing failure is a :class:`UsdFaceError` subclass whose message names the file, the prim
(when there is one) and the fix, so the CLI can print one clear line and exit non-zero.
"""

from __future__ import annotations


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


class InputFileError(UsdFaceError):
    """A file is missing, unreadable or not of the expected format."""


class TimecodeError(InputFileError):
    """A Live Link Face take's timecodes do not fit the rate they are read at (a frame field at or above the
    rate, a negative field): reading on would place the frames at wrong times."""


class RigError(UsdFaceError):
    """An avatar's UsdSkel face rig is malformed (no SkelRoot, no blend shapes, inconsistent arrays...)."""


class AlreadyPersonalizedError(RigError):
    """An avatar given to ``personalize``/``retarget`` is already personalized: a usdface output layer, or a
    flattened export of its personalized variant (``usdface export --flatten``); personalizing it again would
    stack the personalization on the personalized shapes."""


class CaptureError(UsdFaceError):
    """A capture (folder, capture.usda, take) is malformed."""


class GeometryError(UsdFaceError):
    """Geometry is unusable: NaN/inf, empty, degenerate, mismatched vertex counts."""


class OutputExistsError(UsdFaceError):
    """The output file exists and --force was not given."""


class RegistrationError(UsdFaceError):
    """Capture and avatar could not be registered (no overlap, too large a residual)."""


class FitError(UsdFaceError):
    """The personalized-shape fit cannot be set up (no training frames, unknown method...)."""


class LandmarkError(UsdFaceError):
    """A landmark layout cannot be computed (no shapes, bad epsilon...)."""
