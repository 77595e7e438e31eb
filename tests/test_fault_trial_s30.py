"""Fault-injection trial (stop 30): what a production pipeline does to usdface (signals, odd paths, broken
inputs, concurrent runs), each test failing without its fix."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env["USDFACE_PROGRESS"] = "off"
    return env


# A signal that lands while USD's C++ loader imports pxr's Python modules (the first ~0.3 s of every run).
# The meta-path hook sends it at that exact moment: no timing involved.
_SIGNAL_DURING_PXR_IMPORT = textwrap.dedent("""
    import os, signal, sys
    SIG = getattr(signal, sys.argv.pop(1))
    WHEN = sys.argv.pop(1)
    class Hook:
        fired = False
        def find_spec(self, name, path=None, target=None):
            if name == WHEN and not Hook.fired:
                Hook.fired = True
                os.kill(os.getpid(), SIG)
            return None
    sys.meta_path.insert(0, Hook())
    from usdface.cli import main
    sys.exit(main())
""")


def _interactive_signals() -> None:
    """In the child: SIGINT and SIGTERM at their defaults, as a terminal's foreground job has them. A run
    under a background job or nohup (as a CI runner may start the suite) inherits SIGINT ignored, and
    Python installs no KeyboardInterrupt handler then: Ctrl-C cannot reach such a program at all."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _signalled(tmp_path, sig: str, when: str, *args) -> subprocess.CompletedProcess:
    """Run ``usdface ARGS`` as the program, sending itself ``sig`` when module ``when`` is imported."""
    script = tmp_path / "run.py"
    script.write_text(_SIGNAL_DURING_PXR_IMPORT)
    return subprocess.run([sys.executable, str(script), sig, when, *map(str, args)],
                          capture_output=True, text=True, env=_env(), timeout=600,
                          preexec_fn=_interactive_signals)


@pytest.mark.parametrize(("sig", "status"), [("SIGTERM", 143), ("SIGINT", 130)])
def test_a_signal_during_the_usd_import_stops_the_run(samples, tmp_path, sig, status):
    """A SIGTERM or Ctrl-C in the first ~0.3 s was swallowed by USD's module loader (printed as 'Error
    loading lib gf's module'): the run went on, wrote its output and exited 0."""
    res = _signalled(tmp_path, sig, "pxr.Gf", "inspect", samples / "avatar.usda")
    assert res.returncode == status, res.stderr[-2000:]
    assert "Error loading lib" not in res.stderr


def test_sigterm_during_the_usd_import_writes_no_output(samples, tmp_path):
    out = tmp_path / "out" / "p.usda"
    out.parent.mkdir()
    res = _signalled(tmp_path, "SIGTERM", "pxr.Gf", "personalize", samples / "avatar.usda",
                     samples / "capture.usda", "-o", out)
    assert res.returncode == 143, res.stderr[-2000:]
    assert list(out.parent.iterdir()) == []


@pytest.mark.parametrize(("sig", "status"), [("SIGTERM", 143), ("SIGINT", 130)])
def test_a_signal_during_the_numpy_import_stops_the_run(samples, tmp_path, sig, status):
    """A Ctrl-C while numpy's C extension imported ``datetime`` (``inspect``'s first numpy import) became
    numpy's "Importing the numpy C-extensions failed ... a bad install" ImportError: a traceback telling the
    user to reinstall, exit status 1."""
    res = _signalled(tmp_path, sig, "datetime", "inspect", samples / "avatar.usda")
    assert res.returncode == status, res.stderr[-2000:]
    assert "Traceback" not in res.stderr and "numpy" not in res.stderr
    assert res.stderr.strip().splitlines()[-1] in ("usdface: interrupted", "usdface: terminated")


@pytest.mark.parametrize(("sig", "status"), [("SIGTERM", 143), ("SIGINT", 130)])
def test_a_signal_while_the_command_line_is_read_is_one_line(samples, tmp_path, sig, status):
    """Ctrl-C while the commands' modules were imported (building the parser) ended in a Python traceback
    and death by SIGINT; SIGTERM there was already 'usdface: terminated'."""
    res = _signalled(tmp_path, sig, "usdface.commands.personalize", "inspect", samples / "avatar.usda")
    assert res.returncode == status, res.stderr[-2000:]
    assert "Traceback" not in res.stderr
    assert res.stderr.strip().splitlines()[-1] in ("usdface: interrupted", "usdface: terminated")


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


@pytest.mark.parametrize(("sig", "kind", "status"),
                         [("SIGTERM", "Terminated", 143), ("SIGINT", "Interrupted", 130)])
def test_json_of_a_stopped_run_is_a_document(samples, tmp_path, sig, kind, status):
    """With --json, stdout holds one JSON document; a run stopped by Ctrl-C or SIGTERM printed nothing there
    (a pipeline reading it got an empty document)."""
    import json

    out = tmp_path / "out" / "p.usda"
    res = _signalled(tmp_path, sig, "pxr.Gf", "personalize", samples / "avatar.usda",
                     samples / "capture.usda", "-o", out, "--json")
    assert res.returncode == status, res.stderr[-2000:]
    doc = json.loads(res.stdout)
    assert doc["ok"] is False and doc["error"]["type"] == kind and doc["error"]["command"] == "personalize"
    assert not out.exists()


@pytest.mark.parametrize("closed", [(1,), (0, 1, 2)])
def test_a_closed_stdout_is_not_a_failure(samples, tmp_path, closed):
    """Started with stdout closed (``usdface ... >&-``, a launcher that closes it), Python's sys.stdout is
    None and the final flush raised AttributeError: a traceback and exit status 1 after the work was done.
    The program puts /dev/null in place of a closed standard stream."""
    def close():
        for fd in closed:
            os.close(fd)

    res = subprocess.run([sys.executable, "-m", "usdface", "inspect", str(samples / "avatar.usda")],
                         stdout=subprocess.DEVNULL if 1 not in closed else None,
                         stderr=subprocess.PIPE if 2 not in closed else None,
                         env=_env(), timeout=600, preexec_fn=close)
    assert res.returncode == 0, res.stderr
    assert not res.stderr or b"Traceback" not in res.stderr


def _publish(pyblish_api, **item):
    import pyblish.util

    context = pyblish_api.Context()
    context.data["usdfaceItems"] = [item]
    pyblish.util.publish(context)
    return {r["plugin"].__name__: r["error"] for r in context.data["results"] if r["error"] is not None}


def test_pyblish_refuses_an_existing_review_page_before_writing_the_layer(pyblish_registered, samples,
                                                                          tmp_path):
    """A publish with review=True whose review page was left by an earlier publish passed validation, wrote
    the layer, then failed in the review extractor: the failed publish left the layer behind, and its
    retry failed on it ('output layer exists')."""
    out = tmp_path / "person.usda"
    (tmp_path / "person.review.html").write_text("an earlier publish's page")
    errors = _publish(pyblish_registered, avatar=str(samples / "avatar.usda"),
                      capture=str(samples / "capture.usda"), output=str(out), review=True)
    assert "review page exists" in str(errors.get("ValidateUsdFaceOutputs"))
    assert "instance's data force=True" in str(errors.get("ValidateUsdFaceOutputs"))
    assert "ExtractUsdFacePersonalized" not in errors
    assert not out.exists()


@pytest.mark.parametrize("case", ["exists", "input"])
def test_pyblish_validates_the_layer_output(pyblish_registered, samples, tmp_path, case):
    """An output that exists (no force) or is an input failed only in the extractor, after validation
    passed."""
    out = tmp_path / "person.usda"
    if case == "exists":
        out.write_text("#usda 1.0\n")
    else:
        out = samples / "capture.usda"
    errors = _publish(pyblish_registered, avatar=str(samples / "avatar.usda"),
                      capture=str(samples / "capture.usda"), output=str(out), force=case == "input")
    assert "ValidateUsdFaceOutputs" in errors, errors
    assert "ExtractUsdFacePersonalized" not in errors
    if case == "exists":     # the fix in the publish's terms, not the command line's '--force'
        assert "instance's data force=True" in str(errors["ValidateUsdFaceOutputs"])
        assert "--force" not in str(errors["ValidateUsdFaceOutputs"])


@pytest.mark.parametrize(("option", "where"), [("gltf", "inside"), ("gltf", "same"), ("flatten", "inside")])
def test_export_refuses_a_file_output_in_its_obj_dir_before_writing(personalized_sample, tmp_path, option,
                                                                    where):
    """``export --obj-dir d --gltf d/x.glb`` wrote the glTF, then refused the folder it had just made not
    empty ('output folder exists and is not empty'): exit 2 with x.glb left behind; ``--gltf x.glb
    --obj-dir x.glb`` the same ('exists as a file')."""
    from usdface import api
    from usdface.errors import OptionError

    folder = tmp_path / "d"
    suffix = ".glb" if option == "gltf" else ".usdc"
    out = folder / f"x{suffix}" if where == "inside" else folder
    with pytest.raises(OptionError, match="--obj-dir folder"):
        api.export_avatar(personalized_sample, obj_dir=folder, **{option: out})
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


def test_a_batch_stopped_while_its_rows_are_checked_writes_this_runs_report(samples, tmp_path, monkeypatch):
    """Ctrl-C while the rows were checked (every avatar is opened: seconds on a large manifest) left the
    previous run's report standing, which the docs promise never happens."""
    import json

    from usdface import api
    from usdface.io import usd_rig

    manifest = tmp_path / "m.csv"
    manifest.write_text("avatar,capture,output\n"
                        f"{samples / 'avatar.usda'},{samples / 'capture.usda'},a.usda\n")
    report = tmp_path / "m.report.json"
    report.write_text(json.dumps({"from": "the last run", "items": []}))

    def stopped(*_a, **_k):
        raise KeyboardInterrupt

    monkeypatch.setattr(usd_rig, "refuse_usdface_output", stopped)
    with pytest.raises(KeyboardInterrupt):
        api.personalize_batch(manifest, jobs=1)
    doc = json.loads(report.read_text())
    assert "from" not in doc
    assert [(i["status"], i["error_type"]) for i in doc["items"]] == [("failed", "Interrupted")]
    assert not (tmp_path / "a.usda").exists()


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
@pytest.mark.parametrize("json_flag", [[], ["--json"]])
def test_stdout_on_a_full_disk_is_said_as_stdout(samples, tmp_path, json_flag):
    """``usdface personalize ... > /dev/full`` wrote the layer, then said 'No space left on device (fix:
    ... write the output elsewhere (-o))', pointing at the output; with --json it ended in a traceback (the
    error document failed on stdout too), exit 1. It says stdout, exit 2, and the layer stands."""
    out = tmp_path / "p.usda"
    with open("/dev/full", "w") as full:
        res = subprocess.run([sys.executable, "-m", "usdface", "personalize", str(samples / "avatar.usda"),
                              str(samples / "capture.usda"), "-o", str(out), "-q", *json_flag],
                             stdout=full, stderr=subprocess.PIPE, text=True, env=_env(), timeout=600)
    assert res.returncode == 2, res.stderr[-2000:]
    assert "Traceback" not in res.stderr
    assert "could not write to stdout" in res.stderr and "the outputs were written" in res.stderr
    assert out.exists()


# A signal that lands inside a native module's initialisation: pybind11 (open3d's module) turns the
# KeyboardInterrupt the handler raised into 'ImportError: initialization failed', chained from it.
_SIGNAL_DURING_NATIVE_INIT = textwrap.dedent("""
    import os, signal, sys, time
    SIG = getattr(signal, sys.argv.pop(1))
    class Hook:
        def find_spec(self, name, path=None, target=None):
            if name == "open3d":
                try:
                    os.kill(os.getpid(), SIG)
                    time.sleep(5)
                except KeyboardInterrupt as exc:
                    raise ImportError("initialization failed") from exc
            return None
    sys.meta_path.insert(0, Hook())
    from usdface.cli import main
    sys.exit(main())
""")


@pytest.mark.parametrize(("sig", "status", "line"), [("SIGTERM", 143, "usdface: terminated"),
                                                      ("SIGINT", 130, "usdface: interrupted")])
def test_a_signal_during_open3d_initialisation_stops_the_run(samples, tmp_path, sig, status, line):
    """A trial: SIGTERM 3 s into 'personalize' (open3d's first import, at the registration) ended in a
    traceback ending 'ImportError: initialization failed' and exit status 1."""
    script = tmp_path / "run.py"
    script.write_text(_SIGNAL_DURING_NATIVE_INIT)
    out = tmp_path / "out" / "p.usda"
    out.parent.mkdir()
    res = subprocess.run([sys.executable, str(script), sig, "personalize", str(samples / "avatar.usda"),
                          str(samples / "capture.usda"), "-o", str(out)], capture_output=True, text=True,
                         env=_env(), timeout=600, preexec_fn=_interactive_signals)
    assert res.returncode == status, res.stderr[-2000:]
    assert "Traceback" not in res.stderr and res.stderr.strip().splitlines()[-1] == line
    assert list(out.parent.iterdir()) == []


_SIGINT_DURING_OPEN3D_IMPORT = textwrap.dedent("""
    import os, signal, sys
    import numpy as np
    signal.signal(signal.SIGINT, signal.default_int_handler)    # a host's Python Ctrl-C handling
    class Hook:
        fired = False
        def find_spec(self, name, path=None, target=None):
            if name == "open3d.pybind" and not Hook.fired:     # inside Open3D's native initialisation
                Hook.fired = True
                os.kill(os.getpid(), signal.SIGINT)
            return None
    sys.meta_path.insert(0, Hook())
    from usdface.transfer.register import _even
    points = np.random.default_rng(0).random((200, 3))
    try:
        _even(points, 0.1)
        print("no interrupt")
    except KeyboardInterrupt:
        print("interrupted", "open3d" in sys.modules)
    print("again", len(_even(points, 0.1)) > 0)
""")


def test_an_interrupt_in_open3ds_import_is_a_keyboard_interrupt_after_it(tmp_path):
    """A host's cancel (Ctrl-C, ``_thread.interrupt_main()``) landing in Open3D's import, made at the first
    registration of a ``personalize_avatar`` call, came out as ``ImportError: initialization failed``, and
    every later call in that process failed with ``ImportError: generic_type: cannot initialize type
    "IntVector"``: one cancelled personalize broke the host's session. The import runs with the signal held
    back; the KeyboardInterrupt arrives once Open3D is loaded, and the next call works."""
    script = tmp_path / "run.py"
    script.write_text(_SIGINT_DURING_OPEN3D_IMPORT)
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=_env(),
                          timeout=600, preexec_fn=_interactive_signals)
    assert done.stdout.split("\n")[:2] == ["interrupted True", "again True"], (done.stdout,
                                                                               done.stderr[-2000:])
