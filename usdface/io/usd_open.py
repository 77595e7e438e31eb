"""Opening an input file the one way every reader does: the path is checked first (missing, a folder, a named
pipe or device, a newline in the name), USD's own warnings while composing are kept off the terminal, and a
composition problem (missing or cyclic sublayer, dangling reference, unreadable crate) is raised once as an
:class:`~usdface.errors.InputFileError` naming the file and the layer at fault."""

from __future__ import annotations

import os
import re
import stat
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

from ..errors import InputFileError
from ..locks import ForkSafeLock

__all__ = ["require_file", "require_readable", "open_usd_stage", "quiet_stderr", "tf_error_text",
           "diagnostic_notes", "require_usd_path"]


def require_usd_path(path, what: str = "file") -> Path:
    """``path`` as a Path if USD can be given it: USD takes a path as UTF-8 text, and Python hands it the
    UTF-8 encoding of the name as Python decoded it from the file system, in the locale's encoding. Under a
    locale that is not UTF-8 (``LANG=en_US`` as ISO-8859-1 on an older farm node; ``LC_ALL=C`` with
    ``PYTHONUTF8=0``) a name with a non-ASCII character anywhere in its absolute path (``/proj/Zoë/a.usda``;
    the current folder for a relative one) reached USD as other bytes: an input was "USD cannot open it:
    Failed to open layer" (a valid file), an output failed after all the work, naming a hidden temporary
    file ("No such file or directory"), or the run ended in a UnicodeEncodeError traceback. Refused
    (InputFileError) before any work instead, naming the path and the way out."""
    path = Path(path)
    text = os.fspath(path.absolute())
    try:
        same = os.fsencode(text) == text.encode("utf-8")
    except UnicodeEncodeError:           # bytes the locale's encoding could not decode (surrogates)
        same = False
    if not same:
        raise InputFileError(
            f"{what} path cannot be given to USD: its full path ({text}) has non-ASCII characters and Python "
            f"reads file names as {sys.getfilesystemencoding()} here (the locale), while USD takes them as "
            "UTF-8", path=path,
            fix="run in Python's UTF-8 mode (PYTHONUTF8=1, or python -X utf8) or under a UTF-8 locale "
                "(LC_ALL=C.UTF-8), or use a path of ASCII characters only")
    return path


def require_file(path, what: str = "file", fix: str = "check the path") -> Path:
    """``path`` as a Path if it is an existing regular file; else InputFileError saying what it is instead."""
    path = Path(path)
    if "\n" in str(path) or "\r" in str(path):
        raise InputFileError(f"{what} path contains a line break", path=repr(str(path)),
                             fix="rename the file without line breaks")
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise InputFileError(f"{what} not found", path=path, fix=fix) from None
    except OSError as exc:
        raise InputFileError(f"{what} cannot be read ({exc.strerror})", path=path, fix=fix) from None
    if stat.S_ISDIR(mode):
        if what == "avatar" and ((path / "train").is_dir() or (path / "neutral.obj").is_file()
                                 or (path / "frames").is_dir()):
            # the fix names the two-argument commands: 'arguments swapped?' alone misled 'landmarks FOLDER'
            raise InputFileError("avatar is a capture (or take) folder, not an avatar", path=path,
                                 fix="pass the avatar's .usd/.usda/.usdc file here (personalize, retarget: "
                                     "arguments swapped? the avatar's .usd file first, then the capture "
                                     "folder)")
        if what == "avatar":
            # a person's folder (avatar.usdc + capture/) given as the avatar: name its USD files (stop 47)
            try:
                held = sorted(p.name for p in path.iterdir() if p.suffix.lower() in (".usd", ".usda", ".usdc")
                              and not p.name.startswith(".") and p.is_file())
            except OSError:
                held = []
            if held:
                shown = ", ".join(held[:4]) + (f" (+{len(held) - 4})" if len(held) > 4 else "")
                raise InputFileError(f"{what} is a folder, not a file (it holds {shown})", path=path,
                                     fix=f"pass the avatar's file itself, e.g. {path / held[0]}")
        raise InputFileError(f"{what} is a folder, not a file", path=path, fix=fix)
    if not stat.S_ISREG(mode):
        kind = "a named pipe" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode) else "a device"
        raise InputFileError(f"{what} is {kind}, not a regular file", path=path, fix=fix)
    return path


def require_readable(path, what: str = "file", fix: str = "check the path") -> Path:
    """:func:`require_file`, and the file opened for reading (a missing read permission, an unreadable
    network file), before any work."""
    path = require_file(path, what, fix)
    try:
        with open(path, "rb"):
            pass
    except OSError as exc:
        raise InputFileError(f"{what} cannot be read ({exc.strerror or exc})", path=path, fix=fix) from None
    return path


#: One thread at a time redirects file descriptor 2 (it is the process's): two blocks on threads side by side
#: (a Dask worker's, a host's pool) each put back what they found, and the second found the first's temporary
#: file, so the process's stderr went on into an unlinked file after both had ended.
_STDERR_LOCK = ForkSafeLock(reentrant=True)   # (a host forking while a thread opens a stage: the child's own)


@contextmanager
def quiet_stderr():
    """Collect what C++ code (USD's diagnostics) writes to file descriptor 2 while the block runs; yields a
    list that receives the text afterwards. Falls back to doing nothing when fd 2 cannot be redirected.

    File descriptor 2 is the whole process's: what the host's other threads wrote meanwhile (its log lines,
    a progress timer's) went into the buffer too and was lost. Lines that are not USD's diagnostics
    (:func:`_others_lines`) are written to the real stderr once the block ends."""
    out: list[str] = []
    with _STDERR_LOCK:
        try:
            sys.stderr.flush()
            buf = _capture_file()
        except (OSError, ValueError, AttributeError):
            buf = None
        if buf is None:
            yield out
            return
        try:
            saved = os.dup(2)
        except OSError:
            buf.close()
            yield out
            return
        with buf:
            os.dup2(buf.fileno(), 2)
            try:
                yield out
            finally:
                os.dup2(saved, 2)
                os.close(saved)
                buf.seek(0)
                text = buf.read().decode("utf-8", "replace")
                out.append(text)
                others = _others_lines(text)
                if others:
                    try:
                        os.write(2, others.encode("utf-8", "replace"))
                    except OSError:
                        pass


def _capture_file():
    """A file for :func:`quiet_stderr` to collect into: a temporary file in the temporary folder, else (no
    usable one: ``/tmp`` read-only or full, ``TMPDIR`` naming nothing writable) an anonymous in-memory file
    (``memfd_create``, Linux), else None (USD's warnings are then shown, not collected). It was
    ``tempfile.TemporaryFile()`` alone, and without a temporary folder every command that opens a stage
    failed: ``usdface inspect: error: No usable temporary directory found in ['/tmp', '/var/tmp', ...] (fix:
    check the path)``, although the inputs and the output's folder were fine."""
    try:
        return tempfile.TemporaryFile()
    except OSError:
        pass
    if hasattr(os, "memfd_create"):
        try:
            return os.fdopen(os.memfd_create("usdface-stderr"), "w+b")
        except OSError:
            pass
    return None


#: The first line of a diagnostic USD's default handler prints ("Warning: in FUNCTION at line N of FILE --
#: ...", "Coding Error: ...", "Runtime Error: ...").
_TF_LINE = re.compile(r"^(?:Warning|Error|Coding Error|Runtime Error|Fatal Error|Status)(?: in |: )")


def _others_lines(text: str) -> str:
    """The lines of ``text`` that are not USD's diagnostics (a diagnostic's first line, :data:`_TF_LINE`,
    and the indented or empty lines that continue it): what other threads wrote meanwhile."""
    kept, in_usd = [], False
    for line in text.splitlines(keepends=True):
        if _TF_LINE.match(line):
            in_usd = True
        elif not (in_usd and (not line.strip() or line[:1].isspace())):
            in_usd = False
            kept.append(line)
    return "".join(kept)


#: One diagnostic USD printed on stderr: "Warning: in FUNCTION at line N of SOURCE -- MESSAGE".
_TF_DIAGNOSTIC = re.compile(r"^\s*(?:Warning|Error|Coding Error|Runtime Error)[^\n]*? -- (.+)$", re.M)


def diagnostic_notes(said: list[str], prefix: str = "USD") -> list[str]:
    """What :func:`quiet_stderr` collected, as notes for a report: each diagnostic's message once
    (``"USD: jointIndices element size (3) != jointWeights element size (4)."``), other non-empty lines as
    they are; [] when nothing was printed."""
    text = "".join(said)
    found = [m.strip() for m in _TF_DIAGNOSTIC.findall(text)]
    if not found:
        found = [line.strip() for line in text.splitlines() if line.strip()]
    return [f"{prefix}: {m[:300]}" for m in dict.fromkeys(found)]


#: One error of a ``Tf.ErrorException``'s text: "Error in 'FUNCTION' at line N in file SOURCE : 'COMMENTARY'".
_TF_ERROR = re.compile(r"Error in '[^']*' at line \d+ in file \S+ : '(.*?)'\s*(?=(?:Error in '|$))", re.S)


def tf_error_text(exc, path=None, limit: int = 300) -> str:
    """What USD said in a ``Tf.ErrorException``, without its C++ source locations: the commentary of each
    error (the parser's message with the file's line and column first), USD's generic "Failed to open layer"
    dropped when there is more, namespaces stripped; ``FILE:LINE:COL:`` of ``path`` becomes "line L, column
    C:"."""
    text = str(exc)
    found = [m.strip() for m in _TF_ERROR.findall(text) if m.strip()]
    if not found:
        lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
        found = lines[-1:] or ["unreadable"]
    specific = [m for m in found if not m.startswith("Failed to open layer")]
    parts = []
    for msg in specific or found:
        msg = re.sub(r"pxrInternal_v\d+_\d+(?:_\d+)?__pxrReserved__::", "", msg)
        msg = re.sub(r"^<?(/[^:>]*?)>? is not", lambda m: f"{Path(m.group(1)).name} is not", msg)
        loc = re.match(r"^(.*?):(\d+):(\d+): ", msg)
        if loc and (path is None or Path(loc.group(1)).name == Path(path).name):
            msg = f"line {loc.group(2)}, column {loc.group(3)}: {msg[loc.end():]}"
        parts.append(" ".join(msg.split()))
    joined = "; ".join(dict.fromkeys(parts))
    return joined if len(joined) <= limit else joined[:limit - 3] + "..."


def _fix_for(error_type: str) -> str:
    return {
        "ErrorInvalidSublayerPath": "restore the missing sublayer at the path the layer names (relative to "
                                    "the layer: a layer copied elsewhere needs its sublayers at the same "
                                    "relative place, e.g. the avatar copied beside it); for one "
                                    "self-contained file to move, flatten it where it was written, before "
                                    "moving it ('usdface export LAYER --flatten OUT.usdc')",
        "ErrorSublayerCycle": "remove the sublayer that points back to a layer above it",
        "ErrorUnresolvedPrimPath": "fix the reference/payload prim path or restore the referenced prim",
        "ErrorInvalidAssetPath": "restore the referenced file or fix the asset path",
        "ErrorInvalidExternalTargetPath": "fix the relationship/connection target",
    }.get(error_type, "repair the layer (usdcat FILE shows what USD reads)")


def open_usd_stage(path, what: str = "file", fix: str = "pass an existing .usd/.usda/.usdc file",
                   composition_errors: bool = True):
    """Open ``path`` as a ``Usd.Stage`` (LoadAll) after :func:`require_file`; USD's own warnings are kept
    quiet. Raises InputFileError naming the file for an unreadable layer and, with ``composition_errors``,
    for the first composition error (missing/cyclic sublayer, dangling reference)."""
    from pxr import Usd

    path = require_usd_path(require_file(path, what, fix), what)
    if path.suffix.lower() == ".csv":  # USD would say only 'Cannot determine file format'
        usd_what = what if what.startswith("USD") else f"USD {what}"        # not 'a USD USD file'
        raise InputFileError(f"a CSV file (a Live Link Face take?) where a {usd_what} is expected", path=path,
                             fix="pass the USD file here; a Live Link take plays on the avatar with "
                                 "'personalize AVATAR CAPTURE --take FILE', becomes USD with 'usdface anim "
                                 "import FILE -o take.usda', and 'capture select FILE' shows its coverage")
    try:
        with quiet_stderr() as said:
            stage = Usd.Stage.Open(str(path), Usd.Stage.LoadAll)
    except Exception as exc:  # pxr.Tf.ErrorException with USD's text
        if type(exc).__name__ != "ErrorException":
            raise
        if path.suffix.lower() not in (".usd", ".usda", ".usdc", ".usdz"):   # a .json map, an .obj scan
            kind = f"a {path.suffix} file" if path.suffix else "a file without a USD extension"
            usd_what = what if what.startswith("USD") else f"USD {what}"
            raise InputFileError(f"{kind} where a {usd_what} is expected", path=path,
                                 fix="pass the USD file here (.usd, .usda, .usdc)") from None
        raise InputFileError(f"USD cannot open it: {tf_error_text(exc, path)}", path=path,
                             fix="check that it is a valid USD layer (usdcat FILE)") from None
    if stage is None:
        text = " ".join((said[0] if said else "").split())[:200]
        raise InputFileError(f"USD cannot open it{f' ({text})' if text else ''}", path=path,
                             fix="check that it is a valid USD layer (usdcat FILE)")
    if composition_errors:
        errors = stage.GetCompositionErrors()
        if errors:
            first = errors[0]
            more = f" (+{len(errors) - 1} more)" if len(errors) > 1 else ""
            raise InputFileError(f"composition error: {str(first).strip()}{more}", path=path,
                                 fix=_fix_for(type(first).__name__))
    return stage
