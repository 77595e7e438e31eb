"""Atomic outputs: build in a temporary sibling, then swap it into place.

A single file is written through :func:`atomic_file` (or :func:`write_text_atomic` for text; USD
layers through :func:`usdface.io.layers.atomic_save`); a folder of many files (a capture folder, the
sample assets) is assembled with :func:`replace_dir_atomically`. A failure never leaves a half-written
output, and an existing output is only replaced once the new one is complete.
"""

from __future__ import annotations

import errno
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ..errors import InputFileError, OutputExistsError

__all__ = ["check_output_file", "check_output_dir", "replace_dir_atomically", "atomic_file",
           "write_text_atomic", "publish", "temp_sibling"]


#: errno values meaning "this file system cannot hard-link" (publish then falls back to check + rename).
_NO_LINKS = {errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK, errno.ENOSYS}


def publish(tmp, path, force: bool = False) -> Path:
    """Move the finished temporary file ``tmp`` to ``path`` (same folder, so atomic).

    With ``force`` an existing ``path`` is replaced (``os.replace``). Without it the target is created
    *exclusively*: ``os.link`` fails if ``path`` exists, so of two processes writing the same new output
    exactly one wins and the other gets :class:`~usdface.errors.OutputExistsError`; ``tmp`` is removed either
    way. On a file system without hard links the existence check and the rename are two steps."""
    tmp, path = Path(tmp), Path(path)
    if force:
        os.replace(tmp, path)
        return path
    try:
        os.link(tmp, path)
    except FileExistsError:
        tmp.unlink(missing_ok=True)
        raise OutputExistsError("output exists (written by another process meanwhile)", path=path,
                                fix="choose another output or pass --force (force=True)") from None
    except OSError as exc:
        if exc.errno not in _NO_LINKS:
            raise
        # no hard links here (FAT, some network shares): best effort
        if path.exists():
            tmp.unlink(missing_ok=True)
            raise OutputExistsError("output exists", path=path,
                                    fix="choose another output or pass --force (force=True)") from None
        os.replace(tmp, path)
        return path
    tmp.unlink()
    return path


def temp_sibling(path, create: bool = True) -> Path:
    """A new unique hidden file name next to ``path``: ``.NAME.XXXX.tmp<suffix>`` (created empty, or with
    ``create=False`` only reserved and removed again, for writers that insist on creating the file)."""
    path = Path(path)
    try:
        fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    except OSError as exc:  # name the output, not the hidden temp file nobody asked for
        raise OSError(exc.errno, exc.strerror, str(path)) from None
    try:
        os.close(fd)
    except BaseException:  # an interrupt right here leaves nothing behind
        os.unlink(name)
        raise
    if not create:
        os.unlink(name)
    return Path(name)


@contextmanager
def atomic_file(path, force: bool = False) -> Iterator[Path]:
    """Context manager: yield a temporary file path next to ``path``, ending in ``.tmp<suffix>`` so that
    writers going by the extension (``savefig``) still work. When the block completes, the file gets the
    permissions of a normally created file (0666 & ~umask) and is published at ``path`` (:func:`publish`:
    exclusively unless ``force``); on an exception (or Ctrl-C) it is removed and ``path`` is untouched."""
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = temp_sibling(path)
        yield tmp
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp, 0o666 & ~mask)
        publish(tmp, path, force)
    except OSError as exc:  # a failed write names the output, not the hidden temp file nobody asked for
        if tmp is None or exc.filename is None or Path(exc.filename) != tmp:
            raise
        raise OSError(exc.errno, exc.strerror, str(path)) from None
    finally:
        if tmp is not None and tmp.exists():
            tmp.unlink()


def write_text_atomic(path, text: str, force: bool = False) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (:func:`atomic_file`; an existing file is replaced only
    with ``force``); returns ``path`` as a Path."""
    with atomic_file(path, force=force) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def check_output_file(path, force: bool = False, *, suffixes=None, what: str = "output", inputs=()) -> Path:
    """Validate an output file path before any work; returns it as a Path.

    Refuses (InputFileError) a line break in the name, an extension not in ``suffixes`` (lower case, with
    the dot; None = any), a folder at ``path``, a parent that is a file, and ``path`` being one of the
    existing ``inputs`` (even with ``force``: inputs are never modified); an existing file needs ``force``
    (OutputExistsError)."""
    path = Path(path)
    if "\n" in str(path) or "\r" in str(path):
        raise InputFileError(f"{what} path contains a line break", path=repr(str(path)),
                             fix="choose a file name without line breaks")
    if suffixes is not None and path.suffix.lower() not in suffixes:
        raise InputFileError(f"{what} must end in {' or '.join(suffixes)}", path=path,
                             fix=f"name it e.g. {path.stem or 'out'}{suffixes[0]}")
    if path.is_dir():
        raise InputFileError(f"{what} path is a folder", path=path, fix="give a file name inside it")
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise InputFileError(f"{what}'s parent {parent} is a file, not a folder", path=path,
                             fix="choose another output path")
    if path.exists():
        for given in inputs:
            if given is not None and Path(given).exists() and path.samefile(given):
                raise InputFileError(f"{what} would overwrite an input", path=path,
                                     fix="choose a different output file; inputs are never modified")
        if not force:
            raise OutputExistsError(f"{what} exists", path=path,
                                    fix="pass --force (force=True) to replace it")
    return path


def check_output_dir(path, force: bool = False) -> Path:
    """Refuse an existing output folder that is not empty (or an existing file) unless ``force``.

    Raises :class:`~usdface.errors.OutputExistsError` naming ``path``; returns it as a Path. A missing or
    empty folder is always accepted.
    """
    dest = Path(path)
    if dest.exists() and (not dest.is_dir() or any(dest.iterdir())) and not force:
        what = "output folder exists and is not empty" if dest.is_dir() else "output exists (a file)"
        raise OutputExistsError(what, path=dest, fix="choose a new folder or pass --force (force=True)")
    return dest


@contextmanager
def replace_dir_atomically(path, force: bool = False) -> Iterator[Path]:
    """Context manager: yield a new, empty temporary folder next to ``path``; when the block completes, it
    becomes ``path``.

    ``path`` is checked first (:func:`check_output_dir`: an existing non-empty folder or a file needs
    ``force``). The temporary folder lives in ``path``'s parent (same file system, so the final rename is
    atomic) and gets mode 0755 like an ordinary folder. On success an existing ``path`` is moved aside, the
    new folder renamed into place, and the old one deleted (if the rename fails the old one is put back). If
    the block raises, the temporary folder is deleted and ``path`` is left untouched.

    Example::

        with replace_dir_atomically(out, force=force) as tmp:
            write_obj(tmp / "neutral.obj", points, triangles)
    """
    dest = check_output_dir(path, force)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = None
    try:
        try:
            tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", dir=dest.parent))
        except OSError as exc:  # name the output folder, not the hidden temporary one
            raise OSError(exc.errno, exc.strerror, str(dest)) from None
        os.chmod(tmp, 0o755)  # mkdtemp makes it private; the output is an ordinary folder
        yield tmp
        if dest.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{dest.name}.old.", dir=dest.parent))
            try:
                os.replace(dest, old / dest.name)
                try:
                    os.replace(tmp, dest)
                except BaseException:
                    os.replace(old / dest.name, dest)
                    raise
            finally:
                shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, dest)
    except BaseException:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
        raise
