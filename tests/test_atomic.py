"""Atomic output folders (usdface.io.atomic): complete or untouched, never half-written, no leftovers."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
from pathlib import Path

import pytest
from cli_helpers import _env
from forking import child_finishes

import usdface.io  # noqa: F401  (registers the schemas before a test opens a stage)
from usdface.cli import main
from usdface.errors import InputFileError, OutputExistsError
from usdface.io import atomic
from usdface.io.atomic import check_output_dir, replace_dir_atomically

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"


def _tree(root):
    return {p.relative_to(root).as_posix(): p.read_text() for p in root.rglob("*") if p.is_file()}


@pytest.fixture
def existing(tmp_path):
    dest = tmp_path / "out"
    (dest / "sub").mkdir(parents=True)
    (dest / "old.txt").write_text("old")
    (dest / "sub" / "keep.txt").write_text("keep")
    return dest


def test_new_folder_appears_complete_with_normal_permissions(tmp_path):
    dest = tmp_path / "a" / "out"
    with replace_dir_atomically(dest) as tmp:
        assert tmp.parent == dest.parent and tmp != dest and not dest.exists()
        (tmp / "x.txt").write_text("x")
    assert _tree(dest) == {"x.txt": "x"}
    assert os.stat(dest).st_mode & 0o777 == 0o755
    assert [p.name for p in dest.parent.iterdir()] == ["out"]


def test_existing_folder_needs_force(existing):
    before = _tree(existing)
    with pytest.raises(OutputExistsError, match="force") as info:
        with replace_dir_atomically(existing):
            raise AssertionError("the block must not run")
    assert str(existing) in str(info.value)
    assert _tree(existing) == before and [p.name for p in existing.parent.iterdir()] == ["out"]
    check_output_dir(existing.parent / "missing")           # missing and empty folders are fine
    (existing.parent / "empty").mkdir()
    check_output_dir(existing.parent / "empty")
    (existing.parent / "file").write_text("f")
    with pytest.raises(OutputExistsError, match="a file"):
        check_output_dir(existing.parent / "file")


def test_force_replaces_only_the_files_written(existing):
    with pytest.warns(UserWarning, match="kept 1 file"):
        with replace_dir_atomically(existing, force=True) as tmp:
            (tmp / "new.txt").write_text("new")
            (tmp / "old.txt").write_text("replaced")
    assert _tree(existing) == {"new.txt": "new", "old.txt": "replaced", "sub/keep.txt": "keep"}
    assert sorted(p.name for p in existing.parent.iterdir()) == ["out"]


def test_force_refuses_a_stale_file_of_a_kind_written_in_its_folder(tmp_path):
    """A capture folder written with ``--force`` over another run's: a frame that run had and this one has
    not would be read as one of this capture's frames - refused, changing nothing; a file of another kind in
    that folder is kept."""
    dest = tmp_path / "cap"
    (dest / "train").mkdir(parents=True)
    (dest / "train" / "001_old.obj").write_text("old frame")
    (dest / "train" / "notes.txt").write_text("mine")
    before = _tree(dest)
    with pytest.raises(OutputExistsError, match="001_old.obj"):
        with replace_dir_atomically(dest, force=True) as tmp:
            (tmp / "train").mkdir()
            (tmp / "train" / "001_new.obj").write_text("new frame")
    assert _tree(dest) == before
    (dest / "train" / "001_old.obj").unlink()
    with pytest.warns(UserWarning, match="kept 1 file"):
        with replace_dir_atomically(dest, force=True) as tmp:
            (tmp / "train").mkdir()
            (tmp / "train" / "001_new.obj").write_text("new frame")
    assert _tree(dest) == {"train/001_new.obj": "new frame", "train/notes.txt": "mine"}
    (dest / "test").mkdir()                         # an earlier run's test frame; this run writes none
    (dest / "test" / "007.obj").write_text("old test frame")
    with pytest.raises(OutputExistsError, match="007.obj"):
        with replace_dir_atomically(dest, force=True) as tmp:
            (tmp / "train").mkdir()
            (tmp / "train" / "001_new.obj").write_text("newer frame")
    assert (dest / "train" / "001_new.obj").read_text() == "new frame"


def test_force_never_replaces_a_file_by_a_folder(existing):
    (existing.parent / "file").write_text("f")
    with pytest.raises(OutputExistsError, match="a file"):
        check_output_dir(existing.parent / "file", force=True)
    before = _tree(existing)
    with pytest.raises(OutputExistsError, match="is a file where usdface writes a folder"):
        with replace_dir_atomically(existing, force=True) as tmp:
            (tmp / "old.txt").mkdir()
            (tmp / "old.txt" / "x.txt").write_text("x")
    assert _tree(existing) == before and sorted(p.name for p in existing.parent.iterdir()) == ["file", "out"]


def test_failure_in_the_block_leaves_the_old_folder(existing):
    before = _tree(existing)
    with pytest.raises(RuntimeError, match="disk full"):
        with replace_dir_atomically(existing, force=True) as tmp:
            (tmp / "half.txt").write_text("half")
            raise RuntimeError("disk full")
    assert _tree(existing) == before
    assert [p.name for p in existing.parent.iterdir()] == ["out"]


def test_failed_merge_puts_the_old_files_back(existing, monkeypatch):
    before = _tree(existing)
    real = os.replace
    calls = []

    def flaky(src, dst):
        calls.append((src, dst))
        if len(calls) == 3:                              # moving the third new file into place fails
            raise OSError("rename failed")
        return real(src, dst)

    monkeypatch.setattr(atomic.os, "replace", flaky)
    with pytest.raises(OSError, match="rename failed"):
        with replace_dir_atomically(existing, force=True) as tmp:
            for name in ("a.txt", "old.txt", "sub/keep.txt", "z/new.txt"):
                (tmp / name).parent.mkdir(parents=True, exist_ok=True)
                (tmp / name).write_text("new")
    assert _tree(existing) == before
    assert [p.name for p in existing.parent.iterdir()] == ["out"]


def test_empty_folder_is_replaced_in_one_rename(tmp_path):
    dest = tmp_path / "out"
    dest.mkdir()
    with replace_dir_atomically(dest) as tmp:
        (tmp / "x.txt").write_text("x")
    assert _tree(dest) == {"x.txt": "x"} and [p.name for p in tmp_path.iterdir()] == ["out"]


def test_writing_into_the_current_folder_keeps_it_the_current_folder(tmp_path, monkeypatch):
    """``usdface sample .`` in an empty folder: the files are moved into it (a rename would swap the folder
    for a new one under the process and the user's shell, whose relative paths then pointed into the old,
    deleted one: the command failed reading its own truth/meta.json; before that it failed with EBUSY)."""
    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)
    with replace_dir_atomically(".") as tmp:
        (tmp / "sub").mkdir()
        (tmp / "sub" / "a.txt").write_text("a")
    assert Path("sub/a.txt").read_text() == "a" and Path.cwd().samefile(here)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["here"]                      # no temp folder left


def test_a_failed_write_inside_the_temporary_folder_names_the_output_file(tmp_path):
    """A write that fails in the hidden temporary folder (disk full, a read-only sub-folder) is reported at
    the place the user asked for: ``out/train/x.obj``, not ``.out.XXXX/train/x.obj``; nothing is left."""
    import errno

    dest = tmp_path / "out"
    with pytest.raises(OSError) as info:
        with replace_dir_atomically(dest) as tmp:
            raise OSError(errno.ENOSPC, "No space left on device", str(tmp / "train" / "x.obj"))
    assert info.value.errno == errno.ENOSPC
    assert info.value.filename == str(dest / "train" / "x.obj")
    assert list(tmp_path.iterdir()) == []


def test_an_unrelated_os_error_in_the_block_is_raised_as_it_was(tmp_path):
    elsewhere = tmp_path / "input.obj"
    with pytest.raises(FileNotFoundError) as info:
        with replace_dir_atomically(tmp_path / "out"):
            elsewhere.read_text()
    assert info.value.filename == str(elsewhere)


def test_a_failed_file_write_names_the_output_not_the_temporary_file(tmp_path):
    import errno

    out = tmp_path / "layer.usda"
    with pytest.raises(OSError) as info:
        with atomic.atomic_file(out) as tmp:
            raise OSError(errno.EDQUOT, "Disk quota exceeded", str(tmp))
    assert info.value.filename == str(out)
    assert list(tmp_path.iterdir()) == []


def test_a_failed_usd_save_publishes_nothing_and_keeps_the_existing_output(samples, tmp_path, monkeypatch,
                                                                             capsys):
    """A full disk: USD's save fails after writing part of the .usda. It was published as the output with
    exit 0 (`--force` replaced a good layer by a file USD cannot parse; a user trial, 300 KB tmpfs): the
    failure is an error now, the old output stays, no temporary file is left."""
    from pathlib import Path

    from usdface.cli import main
    from usdface.io import layers

    real = layers._usd_call

    def full_disk(fn, *args, **kwargs):
        if getattr(fn, "__name__", "") == "Save":
            Path(fn.__self__.realPath).write_text("#usda 1.0\n(\n    customLayerData = {\n")   # cut off
            return False
        return real(fn, *args, **kwargs)

    out = tmp_path / "out" / "avatar.usda"
    args = ["personalize", str(samples / "avatar.usda"), str(samples / "capture.usda"), "-o", str(out), "-q"]
    assert main(args) == 0
    good = out.read_bytes()
    monkeypatch.setattr(layers, "_usd_call", full_disk)
    assert main(args + ["--force"]) == 2
    assert "could not write the layer" in capsys.readouterr().err
    assert out.read_bytes() == good
    assert sorted(p.name for p in out.parent.iterdir()) == ["avatar.usda"]
    assert main(args[:3] + ["-o", str(tmp_path / "new.usda"), "-q"]) == 2
    assert not (tmp_path / "new.usda").exists()


# ------------------------------------------------------------------------- outputs that cannot be written
@pytest.fixture
def chattr(tmp_path):
    """``chattr(path, "+i")``: set an inode flag (root may not write an immutable file or folder either, so
    this is what a read-only place is for tests run as root); every flag set is lifted at the end. Skips
    where the file system or the user cannot set flags."""
    import shutil
    import subprocess

    if shutil.which("chattr") is None:
        pytest.skip("no chattr here")
    done = []

    def set_flag(path, flag):
        res = subprocess.run(["chattr", flag, str(path)], capture_output=True, text=True)
        if res.returncode != 0:
            pytest.skip(f"chattr {flag} refused here: {res.stderr.strip()}")
        done.append((path, flag.replace("+", "-")))

    yield set_flag
    for path, flag in reversed(done):
        subprocess.run(["chattr", flag, str(path)], capture_output=True)


def test_an_immutable_output_file_is_refused_before_any_work_even_with_force(tmp_path, chattr):
    """User trial: ``-o`` an immutable file with ``--force`` ran the whole personalization, then failed to
    publish (EPERM). The check names the file, the flag and the fix."""
    from usdface.errors import InputFileError, OutputNotWritableError

    out = tmp_path / "out.usda"
    out.write_text("#usda 1.0\n")
    atomic.check_output_file(out, force=True)                 # a plain existing file: fine with force
    chattr(out, "+i")
    with pytest.raises(OutputNotWritableError) as info:
        atomic.check_output_file(out, force=True, what="output layer")
    text = str(info.value)
    assert str(out) in text and "immutable" in text and f"chattr -i {out}" in info.value.fix
    assert isinstance(info.value, InputFileError)             # the input/output error family
    with pytest.raises(OutputExistsError):                    # without force: that it exists comes first
        atomic.check_output_file(out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.usda"]


def test_an_immutable_folder_refuses_outputs_in_it_before_any_work(tmp_path, chattr):
    from usdface.errors import OutputNotWritableError

    locked = tmp_path / "locked"
    (locked / "old").mkdir(parents=True)
    chattr(locked, "+i")
    for check in (lambda: atomic.check_output_file(locked / "a.usda"),
                  lambda: atomic.check_output_file(locked / "new" / "deeper" / "a.usda"),
                  lambda: check_output_dir(locked / "capture"),
                  lambda: check_output_dir(locked, force=True)):
        with pytest.raises(OutputNotWritableError) as info:
            check()
        assert f"cannot be written in {locked}" in str(info.value) and "immutable" in str(info.value)
        assert "chattr -i" in info.value.fix
    assert [p.name for p in locked.iterdir()] == ["old"]         # nothing left behind
    with pytest.raises(OutputNotWritableError):                  # an empty immutable output folder too
        check_output_dir(locked / "old")


def test_an_append_only_folder_refuses_new_outputs_before_any_work(tmp_path, chattr, samples):
    """Review: ``chattr +a`` folder: a new file can be made there (the probe passed), but the atomic write's
    final rename cannot: personalize ran all its work, then failed naming its temp file, and left it behind.
    Refused up front now, new output or not; a missing subfolder of it is fine (made, then renamed in)."""
    from usdface.cli import main
    from usdface.errors import OutputNotWritableError

    folder = tmp_path / "appendonly"
    folder.mkdir()
    chattr(folder, "+a")
    for check in (lambda: atomic.check_output_file(folder / "new.usda"),
                  lambda: check_output_dir(folder / "capture")):
        with pytest.raises(OutputNotWritableError, match="append-only") as info:
            check()
        assert "chattr -a" in info.value.fix
    atomic.check_output_file(folder / "sub" / "new.usda")        # the rename happens in the new subfolder
    assert main(["render", str(samples / "avatar.usda"), "-o", str(folder / "r.png"), "-q"]) == 2
    assert list(folder.iterdir()) == []                          # refused before any work: nothing left


def test_an_output_under_a_regular_file_is_refused_with_the_enotdir_fix(tmp_path):
    """``-o notes.txt/capture``: the folder could never be made (ENOTDIR), found only after the work."""
    import errno

    from usdface.errors import OutputNotWritableError, write_fix

    (tmp_path / "notes.txt").write_text("x")
    for check in (lambda: check_output_dir(tmp_path / "notes.txt" / "capture"),
                  lambda: atomic.check_output_file(tmp_path / "notes.txt" / "sub" / "a.usda")):
        with pytest.raises(OutputNotWritableError, match="notes.txt is a file, not a folder") as info:
            check()
        assert info.value.fix == write_fix(errno.ENOTDIR)


def test_a_read_only_place_is_named_with_the_fix_for_its_errno(tmp_path, read_only_folder):
    """A read-only file system (EROFS): the fix of the shared errno table (errors.write_fix), the same the
    CLI gives when a write fails later; the table lives in errors.py, the CLI uses it."""
    import errno

    from usdface import cli
    from usdface.errors import OutputNotWritableError, write_fix

    read_only_folder(tmp_path)
    with pytest.raises(OutputNotWritableError, match="Read-only file system") as info:
        check_output_dir(tmp_path / "out")
    assert info.value.fix == write_fix(errno.EROFS) and "read-only" in info.value.fix
    assert not (tmp_path / "out").exists()
    exc = OSError(errno.EROFS, "Read-only file system", "x")
    assert cli.os_error_fix(exc) == write_fix(errno.EROFS, True) and "(-o)" in cli.os_error_fix(exc)
    assert not hasattr(cli, "_OS_FIXES")


def test_personalize_into_an_immutable_folder_fails_at_once_writing_nothing(samples, tmp_path, chattr, capfd):
    from usdface.cli import main

    locked = tmp_path / "locked"
    locked.mkdir()
    chattr(locked, "+i")
    code = main(["personalize", str(samples / "avatar.usda"), str(samples / "capture.usda"), "-o",
                 str(locked / "person.usda")])
    err = capfd.readouterr().err
    assert code == 2 and f"{locked / 'person.usda'}: output layer cannot be written in {locked}" in err, err
    assert "fix: lift the flag" in err and "[1/" not in err         # refused before the first step
    assert list(locked.iterdir()) == []


def test_quiet_stderr_on_threads_side_by_side_gives_the_process_its_stderr_back():
    """``quiet_stderr`` (every stage usdface opens) redirects file descriptor 2, which is the process's: two
    blocks on threads side by side each put back what they found, and the second had found the first's
    temporary file, so the process's stderr went into an unlinked file for good (a Dask worker's threads)."""
    import os
    import threading

    from usdface.io.usd_open import quiet_stderr

    before = os.fstat(2)
    first_in, second_in, go, go_second = (threading.Event() for _ in range(4))

    def first():
        with quiet_stderr():
            first_in.set()
            go.wait(5)

    def second():
        with quiet_stderr():
            second_in.set()
            go_second.wait(5)

    one = threading.Thread(target=first)
    one.start()
    first_in.wait(5)
    two = threading.Thread(target=second)      # tries to enter while the first redirects
    two.start()
    second_in.wait(0.2)
    go.set()                                   # the first leaves first ...
    one.join()
    go_second.set()                            # ... then the second
    two.join()
    after = os.fstat(2)
    assert (after.st_dev, after.st_ino) == (before.st_dev, before.st_ino)


def test_what_other_threads_write_to_stderr_during_quiet_stderr_is_not_lost(capfd):
    """``quiet_stderr`` (every stage usdface opens or saves) redirects file descriptor 2, the process's: a
    host's log lines written by its other threads meanwhile went into the buffer with USD's warnings and
    were lost (6 of 341 lines of a thread logging every 2 ms while the API read a bench avatar three times).
    USD's diagnostics stay quiet; the other lines reach stderr when the block ends."""
    import threading

    from usdface.io.usd_open import quiet_stderr

    with quiet_stderr() as said:
        os.write(2, b"Warning: in _ReportErrors at line 3196 of stage.cpp -- In </A>: a USD warning\n")
        other = threading.Thread(target=lambda: os.write(2, b"host: a log line\n"))
        other.start()
        other.join()
        os.write(2, b"Coding Error: in Foo at line 1 of bar.cpp -- a second one\n    its second line\n")
    err = capfd.readouterr().err
    assert "host: a log line" in err, err
    assert "USD warning" not in err and "second" not in err, err
    assert "a USD warning" in said[0] and "host: a log line" in said[0]


def test_without_a_temporary_folder_stages_still_open(monkeypatch, capfd):
    """With no usable temporary folder (``/tmp`` read-only or full, ``TMPDIR`` naming nothing writable) every
    command that opens a stage failed, ``inspect: error: No usable temporary directory found in ['/tmp',
    ...] (fix: check the path)``: the capture of USD's stderr needed a temporary file. It falls back to an
    in-memory file (Linux), else shows USD's warnings instead of collecting them."""
    import tempfile

    from usdface.io import usd_open

    def no_temporary_folder(*a, **k):
        raise FileNotFoundError(2, "No usable temporary directory found in ['/tmp', '/var/tmp']")

    monkeypatch.setattr(tempfile, "TemporaryFile", no_temporary_folder)
    with usd_open.quiet_stderr() as said:
        os.write(2, b"Warning: in F at line 1 of x.cpp -- a USD warning\n")
    err = capfd.readouterr().err
    if hasattr(os, "memfd_create"):
        assert "a USD warning" in said[0] and "a USD warning" not in err
    assert main(["inspect", str(SAMPLES / "avatar.usda")]) == 0
    assert "temporary" not in capfd.readouterr().err
    monkeypatch.delattr(os, "memfd_create", raising=False)      # nowhere to collect: shown, not an error
    with usd_open.quiet_stderr() as said:
        os.write(2, b"Warning: in F at line 1 of x.cpp -- shown\n")
    assert said == [] and "shown" in capfd.readouterr().err


def test_a_new_output_folder_named_like_a_file_is_refused(tmp_path, capsys):
    """A user trial: 'usdface sample x.usda' wrote a folder x.usda, which every later command then took for
    a USD file ('USD cannot open it'); capture import already refused 'c.obj'."""
    from usdface.cli import main
    from usdface.io.atomic import check_output_dir

    assert main(["sample", str(tmp_path / "x.usda")]) == 2
    err = capsys.readouterr().err
    assert "named like a .usda file" in err and "x.usda" in err and not (tmp_path / "x.usda").exists()
    with pytest.raises(InputFileError, match="named like a .PNG file"):
        check_output_dir(tmp_path / "pics.PNG")
    (tmp_path / "v1.2").mkdir()
    assert check_output_dir(tmp_path / "v1.2") == tmp_path / "v1.2"      # a dotted folder name is fine
    (tmp_path / "old.usda").mkdir()                     # and an existing folder is the user's choice
    assert check_output_dir(tmp_path / "old.usda") == tmp_path / "old.usda"


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork")
def test_quiet_stderr_in_a_child_forked_while_another_thread_is_inside():
    """A host forking (``multiprocessing``'s default on Linux) while one of its threads opened a stage: the
    child's first ``quiet_stderr`` waited for good on the lock that thread held."""
    from usdface.io.usd_open import quiet_stderr

    def block():
        with quiet_stderr():
            pass

    assert child_finishes(block, quiet_stderr)


def _long_name(stem_bytes: int, suffix: str) -> str:
    """A legal file name of ``stem_bytes`` + len(suffix) bytes (255 at most on Linux file systems)."""
    return "a" * stem_bytes + suffix


@pytest.mark.parametrize("total", [240, 250, 255])
def test_a_long_legal_output_name_is_written(tmp_path, total):
    """An output whose name is long but legal (up to 255 bytes) failed with 'File name too long (fix: use a
    shorter path)' after all the work: the hidden temporary name ``.NAME.XXXXXXXX.tmp.usda`` beside it did
    not fit. The temporary name is cut short; the output keeps its name."""
    from pxr import Sdf

    from usdface.io.atomic import replace_dir_atomically, temp_sibling, write_text_atomic
    from usdface.io.layers import atomic_save

    text = tmp_path / _long_name(total - 5, ".json")
    write_text_atomic(text, "{}")
    assert text.read_text() == "{}"
    write_text_atomic(text, "[]", force=True)
    assert text.read_text() == "[]"

    layer = Sdf.Layer.CreateAnonymous(".usda")
    Sdf.CreatePrimInLayer(layer, "/A")
    for suffix in (".usda", ".usdc"):
        out = tmp_path / _long_name(total - len(suffix), suffix)
        atomic_save(layer, out)
        atomic_save(layer, out, force=True)
        assert Sdf.Layer.FindOrOpen(str(out)).GetPrimAtPath("/A")

    folder = tmp_path / ("f" * total)
    for force in (False, True):
        with replace_dir_atomically(folder, force=force) as tmp:
            (tmp / "x.obj").write_text("v 0 0 0\n")
    assert (folder / "x.obj").exists()
    assert len(os.fsencode(temp_sibling(tmp_path / ("ö" * 127 + ".usda"), create=False).name)) <= 255
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


def test_a_long_legal_output_name_through_the_cli(samples, tmp_path):
    out = tmp_path / _long_name(245, ".usda")
    res = subprocess.run([sys.executable, "-m", "usdface", "personalize", str(samples / "avatar.usda"),
                          str(samples / "capture.usda"), "-o", str(out), "-q", "--inspect"],
                         capture_output=True, text=True, env=_env(), timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    assert [p.name for p in tmp_path.iterdir()] == [out.name]


def test_a_full_disk_names_the_output(tmp_path):
    """A write that fails on a full disk raises an OSError naming no file (a write or close, ENOSPC): the
    line said only 'error: No space left on device' (review, render, export --obj-dir, capture import to
    a folder), not which output failed."""
    import errno

    from usdface.io.atomic import atomic_file, replace_dir_atomically

    full = OSError(errno.ENOSPC, "No space left on device")
    out = tmp_path / "page.html"
    with pytest.raises(OSError) as err, atomic_file(out):
        raise full
    assert err.value.filename == str(out) and err.value.errno == errno.ENOSPC

    folder = tmp_path / "objs"
    with pytest.raises(OSError) as err, replace_dir_atomically(folder):
        raise full
    assert err.value.filename == str(folder)
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_a_usd_layer_that_cannot_be_saved_into_an_output_folder_names_it_not_the_hidden_folder(tmp_path):
    """'usdface sample OUTDIR' on a full disk said 'OUTDIR/../.s.9q28_9rp/avatar.usda: USD could not write
    the layer': the hidden temporary folder nobody asked for."""
    from usdface.errors import InputFileError
    from usdface.io.atomic import replace_dir_atomically

    folder = tmp_path / "s"
    with pytest.raises(InputFileError) as err, replace_dir_atomically(folder) as tmp:
        raise InputFileError("USD could not write the layer", path=tmp / "avatar.usda", fix="free disk space")
    assert err.value.path == str(folder / "avatar.usda")
    assert str(err.value).startswith(f"{folder / 'avatar.usda'}: USD could not write")
    assert list(tmp_path.iterdir()) == []


def test_a_failed_write_removes_the_folders_it_made(tmp_path, monkeypatch):
    """-o new/sub/p.usda on a full disk failed, but left new/sub behind (empty folders the write made);
    the same for a review page, a picture or an export folder. A folder that was there stays."""
    import errno

    from pxr import Sdf

    from usdface.errors import InputFileError
    from usdface.io import layers
    from usdface.io.atomic import atomic_file, replace_dir_atomically

    (tmp_path / "kept").mkdir()
    full = OSError(errno.ENOSPC, "No space left on device")
    with pytest.raises(OSError), atomic_file(tmp_path / "kept" / "new" / "sub" / "r.html"):
        raise full
    with pytest.raises(OSError), replace_dir_atomically(tmp_path / "new" / "sub" / "objs"):
        raise full
    monkeypatch.setattr(layers, "_usd_call", lambda *a, **k: False)   # USD's save fails (a full disk)
    layer = Sdf.Layer.CreateAnonymous(".usda")
    with pytest.raises(InputFileError, match="could not write"):
        layers.atomic_save(layer, tmp_path / "new" / "sub" / "p.usda")
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")) == ["kept"]


def test_a_failed_personalize_write_removes_the_folders_it_made(samples, tmp_path, monkeypatch):
    from usdface import api
    from usdface.errors import InputFileError
    from usdface.io import layers

    monkeypatch.setattr(layers, "_usd_call", lambda *a, **k: False)
    with pytest.raises(InputFileError, match="could not write"):
        api.personalize_avatar(samples / "avatar.usda", samples / "capture.usda",
                               tmp_path / "a" / "b" / "p.usda")
    assert list(tmp_path.iterdir()) == []


def test_two_writers_of_one_new_output_exactly_one_wins(tmp_path):
    """The second writer used to replace the first one's file; now the target is created exclusively."""
    from pxr import Sdf

    from usdface.io.layers import atomic_save

    first, second = Sdf.Layer.CreateAnonymous(".usda"), Sdf.Layer.CreateAnonymous(".usda")
    first.documentation, second.documentation = "first", "second"
    out = tmp_path / "out.usda"
    atomic_save(first, out)  # both passed the "does it exist" check; the first one publishes...
    with pytest.raises(OutputExistsError):
        atomic_save(second, out)  # ...and the second one is refused, not silently replacing it
    assert Sdf.Layer.OpenAsAnonymous(str(out)).documentation == "first"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.usda"]
    atomic_save(second, out, force=True)
    assert Sdf.Layer.OpenAsAnonymous(str(out)).documentation == "second"


def test_write_text_atomic_is_exclusive_without_force(tmp_path):
    from usdface.io.atomic import write_text_atomic

    write_text_atomic(tmp_path / "a.json", "1")
    with pytest.raises(OutputExistsError):
        write_text_atomic(tmp_path / "a.json", "2")
    assert (tmp_path / "a.json").read_text() == "1" and len(list(tmp_path.iterdir())) == 1


def test_interrupt_while_creating_the_temp_file_leaves_nothing(tmp_path, monkeypatch):
    """A Ctrl-C just after the temp file was created used to leave a hidden ``.NAME.*.tmp.EXT``."""
    from usdface.io import atomic

    real_close = os.close
    calls = []

    def interrupted_close(fd):
        real_close(fd)
        if not calls:
            calls.append(fd)
            raise KeyboardInterrupt

    monkeypatch.setattr(atomic.os, "close", interrupted_close)
    with pytest.raises(KeyboardInterrupt), atomic.atomic_file(tmp_path / "x.json") as tmp:
        tmp.write_text("never")
    assert list(tmp_path.iterdir()) == []


def test_oserror_on_write_is_one_line_exit_2(tmp_path, monkeypatch, capfd):
    """A full disk used to end in a traceback (exit 1) with the temp file left behind."""
    from usdface.io import atomic

    def full(*_a, **_k):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "capture.usda"))

    monkeypatch.setattr(atomic.os, "link", full)
    monkeypatch.chdir(tmp_path)
    code = main(["capture", "import", str(SAMPLES / "capture.usda"), "-o", "capture2.usda"])
    err = capfd.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "No space left" in err and "free disk space" in err
    assert list(tmp_path.iterdir()) == []


def _read_only_folder(monkeypatch, folder: Path) -> None:
    """Make creating files or folders in ``folder`` fail as in a read-only folder (the tests run as root, who
    may write anywhere): ``tempfile`` raises PermissionError naming the temporary path it tried, as it
    does."""
    import errno
    import os
    import tempfile

    real_mkstemp, real_mkdtemp = tempfile.mkstemp, tempfile.mkdtemp

    def denied(real, tail):
        def make(suffix=None, prefix=None, dir=None, *a, **k):
            if dir is not None and Path(dir).resolve() == folder.resolve():
                name = os.path.join(dir, f"{prefix or ''}cmx9kqh4{tail(suffix)}")
                raise PermissionError(errno.EACCES, "Permission denied", name)
            return real(suffix, prefix, dir, *a, **k)

        return make

    monkeypatch.setattr(tempfile, "mkstemp", denied(real_mkstemp, lambda s: s or ""))
    monkeypatch.setattr(tempfile, "mkdtemp", denied(real_mkdtemp, lambda s: ""))


def test_read_only_output_folder_names_the_output_not_the_temp_file(sample_dir, tmp_path, monkeypatch,
                                                                    capsys):
    from usdface.cli import main

    ro = tmp_path / "ro"
    ro.mkdir()
    _read_only_folder(monkeypatch, ro)
    out = ro / "avatar.personalized.usda"
    assert main(["personalize", str(sample_dir / "avatar.usda"), str(sample_dir / "capture.usda"),
                 "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert f"{out}: Permission denied" in err and ".tmp" not in err and "cmx9kqh4" not in err, err
    assert "(-o)" in err

    assert main(["sample", str(ro / "s"), "-q"]) == 2
    err = capsys.readouterr().err
    assert f"{ro / 's'}: Permission denied" in err and "cmx9kqh4" not in err, err
    assert "(-o" not in err  # sample has no -o option
    assert list(ro.iterdir()) == []


def test_a_failed_write_names_the_output_not_the_temp_file(tmp_path):
    import errno

    from usdface.io.atomic import atomic_file

    out = tmp_path / "report.json"
    with pytest.raises(OSError) as info, atomic_file(out) as tmp:
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp))
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(out)
    assert list(tmp_path.iterdir()) == []


def test_an_unexpanded_tilde_would_not_become_a_folder(tmp_path, monkeypatch):
    """``-o "~/renders/p.usda"`` (quoted, or from a job template or a manifest: no shell expands it) made a
    folder literally named ``~`` in the current folder. Refused before any work; a ``~`` folder that exists
    is the user's, and a file named ``~x.usda`` makes no folder."""
    from usdface.io.atomic import check_output_file

    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputFileError, match="folder named '~'.*not expanded"):
        check_output_file("~/renders/p.usda", suffixes=(".usda",))
    with pytest.raises(InputFileError, match="folder named '~'"):
        check_output_dir("~/caps/c1")
    with pytest.raises(InputFileError, match="folder named '~me'"):
        check_output_file(tmp_path / "out" / "~me" / "p.usda", suffixes=(".usda",))
    assert list(tmp_path.iterdir()) == []
    check_output_file("~x.usda", suffixes=(".usda",))
    (tmp_path / "~").mkdir()
    check_output_file("~/renders/p.usda", suffixes=(".usda",))
    check_output_dir("~/caps/c1")


def test_a_forced_replacement_keeps_the_replaced_files_permissions(tmp_path, samples):
    """A pipeline user's note: a group-writable publish (0664) became 0644 at the first --force (the new
    file got the umask's mode). The replacement keeps the replaced file's bits, for a plain file and a USD
    layer; a new file still gets the umask's; a symbolic link is replaced, its target untouched."""
    import os
    import stat

    from usdface.cli import main
    from usdface.io.atomic import write_text_atomic

    old = os.umask(0o022)
    try:
        text = tmp_path / "notes.txt"
        text.write_text("old")
        os.chmod(text, 0o664)
        write_text_atomic(text, "new", force=True)
        assert text.read_text() == "new" and stat.S_IMODE(text.stat().st_mode) == 0o664
        fresh = write_text_atomic(tmp_path / "fresh.txt", "x")
        assert stat.S_IMODE(fresh.stat().st_mode) == 0o644
        layer = tmp_path / "person.usda"
        args = ["personalize", str(samples / "avatar.usda"), str(samples / "capture.usda"), "-o", str(layer),
                "-q"]
        assert main(args) == 0
        os.chmod(layer, 0o660)
        assert main([*args, "--force"]) == 0
        assert stat.S_IMODE(layer.stat().st_mode) == 0o660
        target = tmp_path / "v001.txt"
        target.write_text("v1")
        link = tmp_path / "latest.txt"
        link.symlink_to(target)
        write_text_atomic(link, "v2", force=True)
        assert not link.is_symlink() and link.read_text() == "v2" and target.read_text() == "v1"
    finally:
        os.umask(old)


def test_the_umask_is_read_without_being_changed(monkeypatch):
    """Setting the umask to 0 and back to learn it opened a window in which a host's other threads made
    world-writable files; it is read from /proc where there is one."""
    import os

    from usdface.io.atomic import current_umask

    old = os.umask(0o027)
    try:
        calls = []
        real = os.umask
        monkeypatch.setattr(os, "umask", lambda m: calls.append(m) or real(m))
        assert current_umask() == 0o027
        if os.path.exists("/proc/self/status"):
            assert calls == []
    finally:
        monkeypatch.undo()
        os.umask(old)
