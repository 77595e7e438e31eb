"""File formats: the only package that knows USD, OBJ, JSON and CSV. Importing it registers usdface's USD
schemas (:func:`usdface.schemas.register`), which must happen before the first USD stage is created.

:func:`read_capture` reads a capture in either of its two forms: a capture folder (OBJ + JSON, see
``docs/capture-format.md``) or a ``capture.usda``/``.usdc``/``.usd`` written by ``usdface capture import``.
"""

from __future__ import annotations

import os
from pathlib import Path

from .. import schemas as _schemas

_schemas.register()

__all__ = ["read_capture", "check_capture_path", "USD_EXTENSIONS"]

#: File extensions read as USD.
USD_EXTENSIONS = (".usd", ".usda", ".usdc", ".usdz")


def check_capture_path(path) -> Path:
    """What :func:`read_capture` refuses about ``path`` without reading a frame (a batch checks every row's
    capture before its first item): a missing path, a Live Link Face CSV (weights only, no meshes), a file
    that is not USD or cannot be read, a folder that is neither a take nor a capture folder (no
    ``neutral.obj``). Raises :class:`usdface.errors.InputFileError` or ``CaptureError`` naming the path and
    the fix; returns it as a Path."""
    return _checked_capture(path).path


def _checked_capture(path):
    """:func:`check_capture_path`, returning what :func:`usdface.io.file_kind.file_kind` found."""
    from ..errors import CaptureError, InputFileError
    from .file_kind import Kind, file_kind

    path = Path(path)
    found = file_kind(path)
    if found.kind in (Kind.CAPTURE_FOLDER, Kind.TAKE_FOLDER, Kind.FOLDER):
        if found.kind is not Kind.TAKE_FOLDER and not (path / "neutral.obj").is_file():
            from .capture_folder import missing_layout, refuse_suffix_case

            refuse_suffix_case([path], (".obj",))       # NEUTRAL.OBJ: named for what it is
            raise missing_layout(path, "neutral.obj")
        return found
    if found.kind is Kind.LIVELINK_CSV and path.is_file():
        from .take import WEIGHTS_ONLY_FIX

        raise CaptureError("a Live Link Face CSV: a take of weights only, no meshes to fit", path=path,
                           fix=WEIGHTS_ONLY_FIX)
    if found.kind is Kind.MISSING:
        try:
            os.stat(path)
        except PermissionError:     # a folder on the way one may not enter: there, not "not found"
            raise InputFileError("cannot reach the capture (permission denied)", path=path,
                                 fix="ask for read and execute permission on its folders, or copy the "
                                     "capture somewhere you can read") from None
        except (OSError, ValueError):
            pass
        raise InputFileError("capture not found", path=path,
                             fix="pass a capture folder or a .usda written by 'usdface capture import'")
    if path.suffix.lower() not in USD_EXTENSIONS:
        raise InputFileError("not a capture folder or USD file", path=path,
                             fix="pass a capture folder (neutral.obj, template/, train/) or a capture .usda")
    from .usd_open import require_readable

    require_readable(path, "capture", fix="pass a capture folder or a capture .usda you can read")
    return found


def read_capture(path):
    """Read a capture folder or a capture USD file into a :class:`usdface.model.Capture`.

    Dispatches on what :func:`usdface.io.file_kind.file_kind` finds: a take (a USD take, an OBJ-sequence
    folder with a Live Link CSV) -> every frame as a training frame
    (:func:`usdface.io.take.capture_from_whole_take`, whole-take fitting); a folder ->
    :func:`usdface.io.capture_folder.read_capture_folder`; a ``.usd``, ``.usda``, ``.usdc`` file ->
    :func:`usdface.io.usd_capture.read_capture_usd`. Anything else raises
    :class:`usdface.errors.InputFileError` (:func:`check_capture_path`).
    """
    from .file_kind import Kind

    found = _checked_capture(path)      # held: the root layer is parsed once
    path = found.path
    if found.kind in (Kind.TAKE, Kind.TAKE_FOLDER):
        from .take import capture_from_whole_take, read_take

        return _absolute_source(capture_from_whole_take(read_take(path)))
    if found.kind in (Kind.CAPTURE_FOLDER, Kind.FOLDER):
        from .capture_folder import read_capture_folder

        return _absolute_source(read_capture_folder(path))
    from .usd_capture import read_capture_usd

    return _absolute_source(read_capture_usd(path))


def _absolute_source(capture):
    """``capture.source`` made absolute (symlinks kept, ``..`` by name), as ``Avatar.file`` is: a relative one
    named another file once the host changed folder (a DCC opening a scene), and a layer personalized from
    the ``Capture`` afterwards recorded that other path, without a digest, in its provenance."""
    import os

    if capture.source and not os.path.isabs(capture.source):
        capture.source = os.path.abspath(capture.source)
    return capture
