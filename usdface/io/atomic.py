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
import stat
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ..cancel import checkpoint
from ..errors import InputFileError, OutputExistsError, OutputNotWritableError, UsdFaceError, warn, write_fix

__all__ = ["check_output_file", "check_output_dir", "check_not_input", "check_writable",
           "replace_dir_atomically", "atomic_file", "write_text_atomic", "publish", "temp_sibling",
           "outputs_all_or_nothing"]


#: errno values meaning "this file system cannot hard-link" (publish then falls back to check + rename).
_NO_LINKS = {errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK, errno.ENOSYS}


def current_umask() -> int:
    """The process's umask, read without changing it (Linux: ``/proc/self/status``): setting it to 0 and back,
    the only portable way, leaves a moment in which a host's other threads create world-writable files.
    Elsewhere that way, as before."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0)
    os.umask(mask)
    return mask


def publish(tmp, path, force: bool = False) -> Path:
    """Move the finished temporary file ``tmp`` to ``path`` (same folder, so atomic).

    With ``force`` an existing ``path`` is replaced (``os.replace``), the new file taking the replaced one's
    permission bits (a symbolic link at ``path`` is replaced by the file, its target left as it was).
    Without it the target is created *exclusively*: ``os.link`` fails if ``path`` exists, so of two
    processes writing the same new output exactly one wins and the other gets
    :class:`~usdface.errors.OutputExistsError`; ``tmp`` is removed either way. On a file system without
    hard links the existence check and the rename are two steps.

    Work whose host has stopped it (:func:`usdface.cancel.stop_when`: a Dask batch stopped) raises
    :class:`~usdface.cancel.Cancelled` here, before the output appears; the caller's clean-up removes
    ``tmp``."""
    checkpoint()
    tmp, path = Path(tmp), Path(path)
    if force:
        try:
            replaced = os.stat(path)
        except OSError:
            replaced = None
        if replaced is not None and stat.S_ISREG(replaced.st_mode):
            # the file replaced keeps its permissions (a group-writable publish stayed group-writable only
            # until the first --force, which gave it the umask's 0644: a pipeline user's note)
            os.chmod(tmp, stat.S_IMODE(replaced.st_mode))
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


def _naming_output(exc: OSError, hidden: Path, shown: Path) -> OSError:
    """``exc`` as raised, or - where it names ``hidden`` (a temporary file or folder nobody asked for) or a
    file inside it - the same error naming ``shown`` (the output) or the file at the same place in it. An
    error naming no file (a write or close that fails on a full disk: ``No space left on device``) names
    ``shown``, the output being written, so that its line says which output failed."""
    if exc.filename is None:
        return OSError(exc.errno, exc.strerror or str(exc), str(shown))
    try:
        rel = Path(os.path.abspath(exc.filename)).relative_to(os.path.abspath(hidden))
    except ValueError:
        return exc
    return OSError(exc.errno, exc.strerror, str(Path(shown) / rel if rel.parts else shown))


def hidden_prefix(name: str, folder, room: int) -> str:
    """``.NAME.``, the start of a temporary file's or folder's name next to the output ``name`` in ``folder``,
    with NAME cut short where needed so that the whole temporary name - ``room`` more bytes (the random part
    and the suffix) and 16 to spare (USD's own temporary name while it saves a layer there) - stays within
    the file system's limit on a name (255 bytes): an output with a long but legal name is written, where
    ``.NAME.XXXXXXXX.tmp.usda`` failed with 'File name too long' after all the work."""
    try:
        limit = os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):
        limit = 255
    keep = max(limit - room - 16 - 2, 1)
    raw = os.fsencode(name)
    if len(raw) > keep:
        name = raw[:keep].decode("utf-8", "ignore") or "output"   # never half a character
    return f".{name}."


def temp_sibling(path, create: bool = True) -> Path:
    """A new unique hidden file name next to ``path``: ``.NAME.XXXX.tmp<suffix>`` (created empty, or with
    ``create=False`` only reserved and removed again, for writers that insist on creating the file)."""
    path = Path(path)
    try:
        suffix = f".tmp{path.suffix}"
        prefix = hidden_prefix(path.name, path.parent, 8 + len(os.fsencode(suffix)))
        fd, name = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=path.parent)
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


def missing_parents(path) -> list[Path]:
    """The folders above ``path`` that do not exist, deepest first (what :func:`make_parents` would make)."""
    missing = []
    folder = Path(path).parent
    while not os.path.lexists(folder) and folder != folder.parent:
        missing.append(folder)
        folder = folder.parent
    return missing


def make_parents(path) -> list[Path]:
    """Create the missing folders above ``path``; returns those made, deepest first, for
    :func:`remove_made` to take away again when the write fails (a failure leaves nothing behind)."""
    missing = missing_parents(path)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    return missing


def remove_made(folders: list[Path]) -> None:
    """Remove the folders :func:`make_parents` made, deepest first, as long as they are empty (another
    process may have put something there meanwhile)."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            return


@contextmanager
def atomic_file(path, force: bool = False) -> Iterator[Path]:
    """Context manager: yield a temporary file path next to ``path``, ending in ``.tmp<suffix>`` so that
    writers going by the extension (``savefig``) still work. When the block completes, the file gets the
    permissions of a normally created file (0666 & ~umask) and is published at ``path`` (:func:`publish`:
    exclusively unless ``force``); on an exception (or Ctrl-C) it is removed and ``path`` is untouched."""
    path = Path(path)
    tmp = None
    made: list[Path] = []
    done = False
    try:
        made = make_parents(path)
        tmp = temp_sibling(path)
        yield tmp
        os.chmod(tmp, 0o666 & ~current_umask())
        publish(tmp, path, force)
        done = True
    except OSError as exc:  # a failed write names the output, not the hidden temp file nobody asked for
        named = exc if tmp is None else _naming_output(exc, tmp, path)
        if named is exc:
            raise
        raise named from None
    finally:
        if tmp is not None and tmp.exists():
            tmp.unlink()
        if not done:
            remove_made(made)


def write_text_atomic(path, text: str, force: bool = False) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (:func:`atomic_file`; an existing file is replaced only
    with ``force``); returns ``path`` as a Path."""
    with atomic_file(path, force=force) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


#: What a layer an input composes can be called.
_USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")


def usd_dependencies(path: Path) -> list[Path]:
    """The files a USD input composes besides itself (sublayers, references, payloads, recursively:
    ``UsdUtils.ComputeAllDependencies``); [] when USD cannot read it (the reader reports that later)."""
    if path.suffix.lower() not in _USD_SUFFIXES or not path.is_file():
        return []
    try:
        from pxr import UsdUtils

        from .usd_open import quiet_stderr

        with quiet_stderr():  # a missing sublayer: the reader names it in one line later
            layers, _assets, _unresolved = UsdUtils.ComputeAllDependencies(str(path))
    except Exception:  # noqa: BLE001  (a broken file: its reader says why later, not this check)
        return []
    return [Path(layer.realPath) for layer in layers if layer.realPath]


def _shown(path: Path) -> str:
    """``path`` relative to the current folder when it lies inside it (USD gives absolute real paths)."""
    try:
        return str(path.relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def _given_inputs(inputs, composed: bool = True) -> list[tuple[Path, str]]:
    """(path, how to name it) of the existing ``inputs`` (paths; None and non-path objects skipped) and, with
    ``composed``, of the files the USD ones compose."""
    found: list[tuple[Path, str]] = []
    for given in inputs:
        if not isinstance(given, str | os.PathLike) or not os.path.exists(given):  # its reader says so
            continue
        given = Path(given)
        # '.' or '..' named by its own name too: 'inside the input folder .' left the user to guess which
        alias = f" ({given.resolve().name})" if given.name in ("", ".", "..") and given.resolve().name else ""
        found.append((given, f"{'input folder' if given.is_dir() else 'input'} {given}{alias}"))
        if composed:
            real = given.resolve()
            found.extend((d, f"input {_shown(d)} (a layer the input {given} composes)")
                         for d in usd_dependencies(given) if d.exists() and d.resolve() != real)
    return found


def _output_tree(folder: Path) -> tuple[set, list[Path]]:
    """(dev, inode) of every entry under the existing ``folder`` (symlinks not followed), and the resolved
    targets of the symlinks found there."""
    ids, links = set(), []
    for root, dirs, files in os.walk(folder):
        for name in dirs + files:
            entry = Path(root) / name
            st = entry.lstat()
            if entry.is_symlink():
                links.append(entry.resolve())
            else:
                ids.add((st.st_dev, st.st_ino))
    return ids, links


def check_not_input(path, inputs, *, what: str = "output", folder: bool = False) -> None:
    """THE check that an output never touches an input, used by every command before any work.

    Raises :class:`~usdface.errors.InputFileError` naming the input and the fix, whatever ``force`` says,
    when writing ``path`` could modify one of the existing ``inputs`` (paths; for a USD file also every file
    it composes: sublayers, references, payloads):

    * ``path`` is an input: the same file, also through a symlink or a hard link;
    * ``path`` is an input folder or lies inside one (a new file there changes the input folder); the fix
      names the same name beside the folder as the path alone, also held as the error's ``beside`` (the
      command line names ``-o`` with it where ``-o`` gives the output,
      :func:`usdface.cli.name_output_option`);
    * ``folder=True`` (``path`` is an output folder): ``path`` contains an input, or an entry under ``path``
      is a hard link of an input or a symlink to an input (or to a folder holding one).
    """
    path = Path(path)
    # only an existing USD file (or a folder) can be a layer an input composes: skip opening them otherwise
    composed = os.path.lexists(path) and (folder or path.suffix.lower() in _USD_SUFFIXES)
    given = _given_inputs(inputs, composed=composed)
    if not given:
        return
    target = path.resolve()
    tree = _output_tree(path) if folder and path.is_dir() else (set(), [])
    for inp, named in given:
        real, st = inp.resolve(), inp.stat()
        if path.exists() and os.path.samestat(path.stat(), st):
            raise InputFileError(f"{what} would overwrite an input: it is the {named}", path=path,
                                 fix=f"choose a different {what}; inputs are never modified, even with "
                                     "--force")
        if inp.is_dir() and target.is_relative_to(real):
            beside = _beside_inputs(path, [g for g, _ in given])
            # the path alone (the API, a Pyblish instance's output): the command line names the option
            # that gives this output, where one does (usdface.cli.name_output_option)
            where = f" ({beside}, beside it)" if beside else ""
            error = InputFileError(f"{what} is inside the {named} (writing it would change that input)",
                                   path=path, fix=f"write the {what} outside {inp}{where}; inputs are never "
                                                  "modified, even with --force")
            error.beside = beside
            raise error
        if folder and (real.is_relative_to(target) or (st.st_dev, st.st_ino) in tree[0]
                       or any(real == link or real.is_relative_to(link) for link in tree[1])):
            raise InputFileError(f"{what} holds the {named} (writing into it could overwrite or delete "
                                 "that input)", path=path,
                                 fix="choose a new or empty folder that holds none of the inputs; inputs are "
                                     "never modified, even with --force")


def _beside_inputs(path: Path, inputs: list[Path]) -> str | None:
    """Where an output found inside an input folder can go instead: the same name beside the outermost
    input folder holding it (``capture import .`` run inside ``capture/`` -> ``../capture.usda``), named from
    the current folder as every fix names a path (:func:`usdface.io.usd_rig._from_cwd`: shell-quoted, to
    paste); None when that place is itself an input or inside one (the output named as the input folder,
    ``-o capture`` for ``capture/``)."""
    from .usd_rig import _from_cwd

    target, folders = path.resolve(), [p.resolve() for p in inputs if p.is_dir()]
    holders = [f for f in folders if target.is_relative_to(f)]
    if not holders:
        return None
    outer = min(holders, key=lambda f: len(f.parts))
    if outer.parent == outer:                                 # the file system's root holds it
        return None
    candidate = outer.parent / path.name
    if any(candidate.is_relative_to(f) for f in folders) or any(candidate == p.resolve() for p in inputs):
        return None
    return _from_cwd(candidate)


def existing_ancestor(path) -> Path:
    """``path`` itself when it exists, else its nearest existing ancestor (where a write would create the
    missing folders); the file system's root at worst."""
    path = Path(path)
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def check_output_file(path, force: bool = False, *, suffixes=None, what: str = "output", inputs=(),
                      fix: str | None = None, example: str | None = None) -> Path:
    """Validate an output file path before any work; returns it as a Path.

    Refuses (InputFileError) a line break in the name, an extension not in ``suffixes`` (lower case, with
    the dot; None = any), a folder at ``path`` or a name ending in a separator (``newdir/``: a folder, whose
    fix names a file inside it, ``example`` or ``out<suffix>``), and ``path`` touching one of the existing
    ``inputs``
    (:func:`check_not_input`, even with ``force``: inputs are never modified); an existing file needs
    ``force`` (OutputExistsError). A place that cannot be written (:func:`check_writable`: a parent that is a
    file, a read-only folder or file system, a missing permission, an immutable file) raises
    OutputNotWritableError with ``fix`` (default: by the errno, :func:`usdface.errors.write_fix`)."""
    raw = os.fspath(path) if isinstance(path, str | os.PathLike) else str(path)
    path = Path(path)
    if "\n" in str(path) or "\r" in str(path):
        raise InputFileError(f"{what} path contains a line break", path=repr(str(path)),
                             fix="choose a file name without line breaks")
    if str(path) == "-":        # the Unix 'standard output': 'landmarks --json -' was told to name it -.json
        raise InputFileError(f"{what} is written to a file, not to standard output ('-')", path=path,
                             fix=f"name a file, e.g. out{suffixes[0] if suffixes else ''}")
    # a folder (sub/), or a name given as one (newdir/, Path drops the '/'): a file inside it, not a sibling
    # named like it ('name it e.g. newdir.usda' answered a user who meant the folder)
    slash = raw.endswith(("/", os.sep)) and not path.is_dir()
    if path.is_dir() or slash:
        import shlex

        # as given, shell-quoted as every path in a fix: 'new dir/...' pastes
        inside = shlex.quote(str(path / (example or f"out{suffixes[0] if suffixes else ''}")))
        raise InputFileError(f"{what} path {'names' if slash else 'is'} a folder"
                             + (f" (it ends in '{raw[-1]}'), not a file" if slash else ""), path=raw,
                             fix=f"give a file name inside it, e.g. {inside}"
                                 + ("; the missing folder is made" if slash else ""))
    if suffixes is not None and path.suffix.lower() not in suffixes:
        # '.json' alone is a name without an extension (a hidden file): its stem is the whole name
        stem = path.stem if path.stem.lower() not in suffixes else ""
        raise InputFileError(f"{what} must end in {' or '.join(suffixes)}", path=path,
                             fix=f"name it e.g. {stem or 'out'}{suffixes[0]}"
                                 + (f" ({path.name} is a hidden file's name, with no extension)"
                                    if not stem and path.name.lower() in suffixes else ""))
    if path.suffix.lower() in (".usd", ".usda", ".usdc", ".usdz"):    # written by USD: a name it can take
        from .usd_open import require_usd_path

        require_usd_path(path, what)
    _refuse_unexpanded_home(path, what)
    _check_parent(path, what, fix)
    check_not_input(path, inputs, what=what)
    refuse_existing(path, force, what)
    return check_writable(path, what=what, fix=fix)


def refuse_existing(path, force: bool = False, what: str = "output") -> None:
    """An existing output file ``path`` without ``force``: OutputExistsError, the one rule of
    :func:`check_output_file` and the writers that check alone (``usdface.render``'s pictures,
    :func:`usdface.io.gltf.write_gltf`). A symbolic link to nothing is an existing name (``exists()``
    follows the link and said no; the exclusive write then refused it at its end, 'written by another
    process meanwhile', after the work: stop 54); with ``force`` the file replaces the link, its target is
    left as it is."""
    if not os.path.lexists(path) or force:
        return
    if not os.path.exists(path):     # a link to nothing
        raise OutputExistsError(f"{what} exists as a symbolic link to {os.readlink(path)}, which does not "
                                "exist", path=path, fix="pass --force (force=True) to replace the link with "
                                "the file (its target is left as it is), or choose another output")
    raise OutputExistsError(f"{what} exists", path=path, fix="pass --force (force=True) to replace it")


def _refuse_unexpanded_home(path: Path, what: str, folder: bool = False) -> None:
    """Refuse (InputFileError) an output whose write would create a folder named like a home folder, ``~``
    or ``~name``: a ``~`` the shell did not expand (quoted, ``-o "~/renders/p.usda"``, or given by a job
    template or a batch manifest that runs no shell). usdface does not expand it either, and the write made
    a folder literally named ``~`` in the current folder (or beside the manifest), one a later ``rm -rf ~``
    meant for it would take the home folder with it. A ``~`` folder that exists already is the user's."""
    path = Path(path)
    new_folders = []
    for part in ([path] if folder else []) + list(path.parents):
        if part.exists() or part == part.parent:
            break
        new_folders.append(part)
    tilde = next((p for p in reversed(new_folders) if p.name.startswith("~")), None)
    if tilde is not None:
        raise InputFileError(f"{what} path would create a folder named {tilde.name!r} in "
                             f"{tilde.parent.absolute()}: a '~' is not expanded to the home folder here "
                             "(only an unquoted ~ is, by the shell)",
                             path=path, fix="write the home folder out (e.g. $HOME/... unquoted, or the full "
                                            "path), or leave the ~ unquoted for the shell to expand")


def _check_parent(path: Path, what: str, fix: str | None) -> Path:
    """The nearest existing ancestor of ``path``'s folder; OutputNotWritableError when it is a file."""
    parent = existing_ancestor(Path(path).parent)
    if not parent.is_dir():
        raise OutputNotWritableError(f"{what}'s parent {parent} is a file, not a folder", path=path,
                                     fix=fix or write_fix(errno.ENOTDIR))
    return parent


#: ``FS_IOC_GETFLAGS`` (the Linux ioctl of ``lsattr``) and the inode flags that forbid replacing a file.
_FS_IOC_GETFLAGS = 0x80086601
_FS_IMMUTABLE_FL, _FS_APPEND_FL = 0x10, 0x20


def _locked_flag(path: Path) -> str:
    """"immutable" or "append-only" when ``path`` (a file or folder; a link is not followed) carries that
    inode flag (``chattr +i`` / ``+a``: nobody, root included, may replace or delete it), else "". Linux
    only; "" wherever the flags cannot be read."""
    try:
        import fcntl
        import struct
    except ImportError:                                     # not a POSIX system
        return ""
    import stat

    try:
        if not stat.S_ISREG(os.lstat(path).st_mode) and not stat.S_ISDIR(os.lstat(path).st_mode):
            return ""                                       # a link, pipe or device: not opened
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOFOLLOW", 0))
    except OSError:
        return ""
    try:
        flags = struct.unpack("i", fcntl.ioctl(fd, _FS_IOC_GETFLAGS, b"\0" * 4))[0]
    except OSError:                                         # a file system without inode flags
        return ""
    finally:
        os.close(fd)
    return "immutable" if flags & _FS_IMMUTABLE_FL else "append-only" if flags & _FS_APPEND_FL else ""


def _probe_folder(folder: Path) -> OSError | None:
    """The error creating a file in ``folder`` raises, None if it can: permission bits tell neither a
    read-only mount nor an immutable folder nor root's rights, so a temporary file is made and removed
    (never visible where the system has O_TMPFILE)."""
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        return exc
    return None


def check_writable(path, *, what: str = "output", fix: str | None = None, folder: bool = False) -> Path:
    """Refuse, before any work, an output that cannot be written: OutputNotWritableError naming ``path``,
    what refuses it and ``fix`` (default: by the errno, :func:`usdface.errors.write_fix`). Returns ``path``.

    * the output's folder - or its nearest existing ancestor, where the write would create the missing
      ones - must be a folder in which a file can be created (not a read-only folder or file system, an
      immutable folder, one without write permission);
    * the output's folder must not be append-only (``chattr +a``: it takes new files but refuses the write's
      final rename, new output or not);
    * an existing file the write would replace must not be immutable or append-only (``chattr +i``/``+a``),
      nor be another user's in a sticky folder (``/tmp``);
    * with ``folder`` (``path`` is an output folder, written into with ``--force``): an existing ``path``
      must accept new files and not be immutable or append-only itself.
    """
    path = Path(path)
    real = path.resolve() if folder and path.is_symlink() else path   # a linked folder: where it points
    parent = _check_parent(real, what, fix)
    places = [parent] + ([real] if folder and real.is_dir() else [])
    for place in places:
        exc = _probe_folder(place)
        if exc is not None:
            flag = _locked_flag(place)
            why = f"{exc.strerror or exc}" + (f", the folder is {flag} (chattr +{flag[0]})" if flag else "")
            raise OutputNotWritableError(f"{what} cannot be written in {place}: {why}", path=path,
                                         fix=fix or (f"lift the flag (chattr -{flag[0]} {place}, as root) or "
                                                     "write the output elsewhere" if flag
                                                     else write_fix(exc.errno))) from None
    # the write ends with a rename in the output's folder: an append-only folder takes new files (the probe
    # passes) but no rename, so a new output fails after all the work as surely as a replaced one
    if parent.absolute() == real.absolute().parent and _locked_flag(parent) == "append-only":
        raise OutputNotWritableError(f"{what} cannot be written in the append-only folder {parent} "
                                     "(chattr +a): the atomic write's final rename is refused there",
                                     path=path,
                                     fix=fix or f"lift the flag (chattr -a {parent}, as root) or write the "
                                                "output elsewhere")
    if not os.path.lexists(real) or real.is_dir() and not folder:
        return path
    flag = _locked_flag(real)
    if flag:
        raise OutputNotWritableError(f"{what} is {flag} (chattr +{flag[0]}): it cannot be replaced",
                                     path=path, fix=fix or f"lift the flag (chattr -{flag[0]} {path}, as "
                                                           "root) or write the output elsewhere")
    if not folder and hasattr(os, "geteuid") and os.geteuid() != 0:
        st, dst = real.lstat(), parent.stat()
        if dst.st_mode & 0o1000 and os.geteuid() not in (st.st_uid, dst.st_uid):
            raise OutputNotWritableError(f"{what} belongs to another user in the sticky folder {parent}: it "
                                         "cannot be replaced", path=path,
                                         fix=fix or "write the output elsewhere, or ask its owner to "
                                                    "remove it")
    return path


#: Extensions of the files usdface reads and writes: a new output folder named so would later be read (or
#: mistaken) as such a file.
_FILE_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz", ".glb", ".gltf", ".png", ".html", ".htm", ".json",
                  ".csv", ".obj", ".npz")


def check_output_dir(path, force: bool = False, *, inputs=(), what: str = "output folder",
                     fix: str | None = None) -> Path:
    """Validate an output folder before any work; returns it as a Path.

    Refuses (InputFileError) a new folder named like a file usdface reads (``x.usda``, ``x.png``: a later
    command would take it for one), and a folder that touches one of the existing ``inputs``
    (:func:`check_not_input` with ``folder=True``: it is, holds or lies inside an input), even with ``force``.
    An existing file at ``path`` is refused (OutputExistsError), even with ``force``: usdface does not
    delete a file it did not write. An existing folder that is not empty needs ``force``
    (OutputExistsError); with ``force`` :func:`replace_dir_atomically` replaces only the files it writes.
    A missing or empty folder is accepted where it can be written (:func:`check_writable` with
    ``folder=True``: else OutputNotWritableError, with ``fix``, default by the errno).
    """
    dest = Path(path)
    if dest.suffix.lower() in _FILE_SUFFIXES and not dest.is_dir():   # 'sample x.usda': a folder x.usda
        raise InputFileError(f"{what} is named like a {dest.suffix} file, but it is written as a folder",
                             path=dest, fix=f"name the folder without the extension ({dest.with_suffix('')})")
    _refuse_unexpanded_home(dest, what, folder=True)
    _check_parent(dest, what, fix)
    check_not_input(dest, inputs, what=what, folder=True)
    if dest.exists() and not dest.is_dir():
        raise OutputExistsError(f"{what} exists as a file", path=dest,
                                fix="choose a new folder (--force never replaces a file by a folder)")
    if dest.is_dir() and any(dest.iterdir()) and not force:
        raise OutputExistsError(f"{what} exists and is not empty", path=dest,
                                fix="choose a new folder, or pass --force (force=True) to replace the files "
                                    "usdface writes there (other files are kept)")
    return check_writable(dest, what=what, fix=fix, folder=True)


@contextmanager
def replace_dir_atomically(path, force: bool = False) -> Iterator[Path]:
    """Context manager: yield a new, empty temporary folder next to ``path``; when the block completes, its
    files are published at ``path``.

    ``path`` is checked first (:func:`check_output_dir`; callers check it against their inputs before any
    work). The temporary folder lives beside ``path`` (same file system) and gets mode 0755 like an ordinary
    folder. A missing or empty ``path`` is replaced by the new folder in one rename (atomic). An existing
    non-empty folder (only with ``force``) is *merged into*: each file written replaces the file of the same
    name (atomically, the old one staying in place until then), every other file is kept (a warning says how
    many), and if any move fails the files already moved are put back. A file this run does not write, in a
    sub-folder and of a kind the run writes in its sub-folders (a capture's stale ``train/*.obj`` or
    ``test/*.json`` frame), would be read as part of the output: refused, changing nothing. A file where the
    new folder has a sub-folder (or the reverse) is refused, changing nothing. If the block raises, the
    temporary folder is deleted and ``path`` is left untouched.

    Example::

        with replace_dir_atomically(out, force=force) as tmp:
            write_obj(tmp / "neutral.obj", points, triangles)
    """
    dest = check_output_dir(path, force)
    if dest.is_symlink():  # write into the folder the link names, on its file system
        dest = dest.resolve()
    dest = Path(os.path.abspath(dest))  # "." named: its own name for the temporary folder and messages
    made = make_parents(dest)
    tmp = None
    done = False
    try:
        try:
            tmp = Path(tempfile.mkdtemp(prefix=hidden_prefix(dest.name, dest.parent, 8), dir=dest.parent))
        except OSError as exc:  # name the output folder, not the hidden temporary one
            raise OSError(exc.errno, exc.strerror, str(dest)) from None
        os.chmod(tmp, 0o755)  # mkdtemp makes it private; the output is an ordinary folder
        try:
            yield tmp
        except OSError as exc:  # a failed write names the file in the output folder, not in the hidden one
            named = _naming_output(exc, tmp, dest)
            if named is exc:
                raise
            raise named from None
        except UsdFaceError as exc:  # so does usdface's own error (USD could not write a layer there)
            if exc.path is not None:
                exc.path = _naming_output(OSError(0, "", exc.path), tmp, dest).filename
            raise
        checkpoint()      # work its host stopped meanwhile publishes nothing (the folder is removed below)
        if dest.is_dir() and dest.resolve() == Path.cwd().resolve():
            # the current folder: a rename would swap it for a new folder under the caller (and the user's
            # shell), whose relative paths would then point into the old, deleted one - filled file by file
            _merge_into(tmp, dest)
            done = True
            return
        try:
            os.rename(tmp, dest)  # a missing or empty dest: the whole folder appears at once
            tmp = None
        except OSError as exc:
            if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST) or not dest.is_dir():
                raise
            if not force:  # a file appeared meanwhile
                raise OutputExistsError("output folder is not empty (written by another process meanwhile)",
                                        path=dest, fix="choose a new folder or pass --force (force=True)"
                                        ) from None
            _merge_into(tmp, dest)
        done = True
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
        if not done:
            remove_made(made)


def _merge_into(tmp: Path, dest: Path) -> None:
    """Move every file under ``tmp`` to the same place under ``dest``, replacing only those files; all or
    nothing (see :func:`replace_dir_atomically`)."""

    files = sorted(p.relative_to(tmp) for p in tmp.rglob("*") if not p.is_dir())
    written = {rel.as_posix() for rel in files}
    for rel in files:
        for up in reversed(rel.parents[:-1]):
            if os.path.lexists(dest / up) and not (dest / up).is_dir():
                raise OutputExistsError(f"{dest / up} is a file where usdface writes a folder", path=dest,
                                        fix="move that file away or choose a new folder")
        if (dest / rel).is_dir():
            raise OutputExistsError(f"{dest / rel} is a folder where usdface writes a file", path=dest,
                                    fix="move that folder away or choose a new folder")
    # below the top of the folder (a capture's train/ and test/, an export's Head/) a file of a kind this run
    # writes there, left from another run, would be read as part of this one (a stale frame - also in a
    # test/ this run leaves empty - or a shape that is not there)
    others = [rel for rel in (p.relative_to(dest) for p in dest.rglob("*") if not p.is_dir())
              if rel.as_posix() not in written]                 # the folder's files this run does not write
    kinds = {rel.suffix.lower() for rel in files if rel.parent != Path(".")}
    stale = sorted(rel.as_posix() for rel in others
                   if rel.parent != Path(".") and rel.suffix.lower() in kinds)
    if stale:
        raise OutputExistsError(f"{len(stale)} file(s) in sub-folders of {dest.name}, of kinds this run "
                                "writes there, would stay from another run and could be read as part of this "
                                f"output (e.g. {dest / stale[0]})", path=dest,
                                fix="delete them (or the sub-folder), or choose a new folder")
    backup = Path(tempfile.mkdtemp(prefix=hidden_prefix(dest.name, dest.parent, 8 + 4) + "old.",
                                   dir=dest.parent))
    done: list[tuple[Path, bool]] = []
    made: list[Path] = []
    try:
        for rel in files:
            target = dest / rel
            for up in reversed(rel.parents[:-1]):
                if not (dest / up).exists():
                    (dest / up).mkdir()
                    made.append(dest / up)
            had = os.path.lexists(target)
            if had:  # keep the old file until the new one replaces it (put back on failure)
                (backup / rel).parent.mkdir(parents=True, exist_ok=True)
                try:
                    os.link(target, backup / rel, follow_symlinks=False)
                except OSError:
                    shutil.copy2(target, backup / rel, follow_symlinks=False)
            os.replace(tmp / rel, target)
            done.append((rel, had))
    except BaseException:
        for rel, had in reversed(done):
            if had:
                os.replace(backup / rel, dest / rel)
            else:
                (dest / rel).unlink(missing_ok=True)
        for folder in reversed(made):
            try:
                folder.rmdir()
            except OSError:
                pass
        raise
    finally:
        shutil.rmtree(backup, ignore_errors=True)
    if others:
        warn(f"{dest}: kept {len(others)} file(s) this run did not write (e.g. "
             f"{others[0].as_posix()}); --force only replaces the files usdface writes: delete "
             "stale ones yourself")


@contextmanager
def outputs_all_or_nothing(done: dict, **outputs):
    """Several outputs, all or nothing: ``outputs`` {key: path or None} are the ones the block may write,
    ``done`` {key: Path} the ones it has finished. When the block fails (a full disk, Ctrl-C) the finished
    ones that did not exist before it are removed (the finished part of a failed
    :func:`usdface.api.export_avatar`, :func:`~usdface.api.evaluate_methods`, ``landmarks`` or
    ``sample``); one that replaced an existing file (``force``) is left. The folders the block made for them
    are removed too, once empty again (an interrupted ``-o new/out.usda --review`` left ``new/``)."""
    new = {key: not os.path.lexists(out) for key, out in outputs.items() if out}
    missing = set()
    for out in outputs.values():
        folder = Path(out).parent if out else None
        while folder is not None and not os.path.lexists(folder) and folder != folder.parent:
            missing.add(folder)
            folder = folder.parent
    try:
        yield
    except BaseException:
        for key, path in done.items():
            if not new.get(key):
                continue
            try:
                if path.is_dir() and not path.is_symlink():
                    shutil.rmtree(path)
                else:
                    path.unlink()
            except OSError:
                pass
        for folder in sorted(missing, key=lambda f: len(f.parts), reverse=True):  # deepest first
            try:
                folder.rmdir()          # only when empty: another process may have put something there
            except OSError:
                pass
        raise
