"""The ``command`` a usdface output records (its provenance) is the command that wrote it, as a shell line
that runs it again: the arguments ``main`` was given (not the host process's ``sys.argv``), quoted."""

from __future__ import annotations

import shlex
from pathlib import Path

from pxr import Sdf

from usdface.cli import main

SAMPLES = Path(__file__).resolve().parents[1] / "sample_assets"

A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


def test_fit_records_its_own_arguments_quoted(tmp_path):
    out = tmp_path / "my rig.usda"
    argv = ["fit", str(SAMPLES / "capture.usda"), "-o", str(out), "--method", "dt", "-q"]
    assert main(argv) == 0
    command = Sdf.Layer.FindOrOpen(str(out)).customLayerData["usdface"]["command"]
    assert shlex.split(command) == ["usdface", *argv]


def test_main_on_two_host_threads_side_by_side_records_each_its_own_command(monkeypatch):
    """The arguments main() parsed were one module-wide list: a host running main(argv) on threads side by
    side, a run's layer recorded the command another thread had started since (landmarks reads it after
    the sweep, minutes later)."""
    import threading

    from cli_stubs import waiting_parser

    from usdface import cli
    from usdface.commands import command_line

    gates = {name: (threading.Event(), threading.Event()) for name in ("a b", "c")}
    recorded = {}

    def run(args):                               # a command that records its line once the test lets it
        gates[args.name][0].set()
        gates[args.name][1].wait(5)
        recorded[args.name] = command_line()
        return 0

    monkeypatch.setattr(cli, "build_parser", waiting_parser(run))
    first = threading.Thread(target=cli.main, args=(["wait", "a b"],))
    first.start()
    assert gates["a b"][0].wait(5)
    second = threading.Thread(target=cli.main, args=(["wait", "c"],))      # parsed while the first runs
    second.start()
    assert gates["c"][0].wait(5)
    gates["a b"][1].set()
    first.join()
    gates["c"][1].set()
    second.join()
    assert recorded == {"a b": "usdface wait 'a b'", "c": "usdface wait c"}


def test_api_layers_pass_check_without_a_command(tmp_path):
    """``write_landmarks`` / ``write_avatar_layer`` with the documented default ``provenance=None`` wrote an
    empty ``usdface:provenance:command``, which ``check`` calls an error: the API names itself."""
    from usdface import api
    from usdface.api import check as check_file

    av = api.read_avatar(A)
    rig = api.pick_mesh(av)
    out = api.write_landmarks(av, rig, api.compute_landmarks(A), tmp_path / "lm.usda")
    assert not [i for i in check_file(out) if i.severity == "error"]
    from pxr import Usd

    stage = Usd.Stage.Open(str(out))
    command = stage.GetPrimAtPath("/Avatar").GetAttribute("usdface:provenance:command").Get()
    assert "write_landmarks" in command


def test_fit_rig_records_command_parameters_and_capture(tmp_path, monkeypatch):
    """A rig written by ``usdface fit`` says what made it, as a personalized layer does: the command line,
    the options, the capture read (path relative to the rig and its sha256) and when (it recorded only the
    method: which capture and settings a rig came from was lost)."""
    import shutil

    from usdface.cli import main
    from usdface.io.layers import file_digest
    from usdface.io.usd_rig import usdface_layer_data

    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    cap = tmp_path / "cap.usda"
    shutil.copy(SAMPLES / "capture.usda", cap)
    out = tmp_path / "rigs" / "rig.usda"
    monkeypatch.setattr("sys.argv", ["usdface", "fit", str(cap), "-o", str(out), "--reg", "0.05", "-q"])
    assert main(["fit", str(cap), "-o", str(out), "--reg", "0.05", "-q"]) == 0
    data = usdface_layer_data(out)
    assert data["format"] == "fit" and data["method"] == "menzel"
    assert data["command"].startswith("usdface fit ") and "--reg 0.05" in data["command"]
    assert data["parameters"]["reg"] == 0.05 and data["parameters"]["method"] == "menzel"
    assert data["capture"] == "../cap.usda" and data["captureDigest"] == file_digest(cap)
    assert data["createdAt"] == "2023-11-14T22:13:20Z"
    assert data["trainRmseMm"] > 0 and data["reg"] == 0.05


def test_a_layer_written_from_python_or_a_batch_names_what_wrote_it(tmp_path):
    """personalize_avatar from a script recorded 'usdface personalize' (a command line that never ran, and
    runs nothing again), where write_fit_rig and write_landmarks name the API function; a batch item the
    same. The layer names the API function, a batch item its batch and row, the CLI its command line."""
    import usdface
    from usdface.pipeline.batch import personalize_worker

    def command(path):
        return Sdf.Layer.FindOrOpen(str(path)).customLayerData["usdface"]["command"]

    args = (SAMPLES / "avatar.usda", SAMPLES / "capture.usda")
    usdface.personalize_avatar(*args, tmp_path / "api.usda")
    assert command(tmp_path / "api.usda") == "usdface.api.personalize_avatar (Python API)"
    personalize_worker({"avatar": str(args[0]), "capture": str(args[1]), "output": str(tmp_path / "b.usda"),
                        "options": {}, "index": 2})
    assert command(tmp_path / "b.usda").startswith("usdface batch, item 3")
    argv = ["personalize", str(args[0]), str(args[1]), "-o", str(tmp_path / "cli.usda"), "-q"]
    assert main(argv) == 0 and shlex.split(command(tmp_path / "cli.usda")) == ["usdface", *argv]
    # a rig written by fit_capture names fit_capture, the function that ran (it named its writer)
    usdface.fit_capture(args[1], out_path=tmp_path / "rig.usda", reg=0.05)
    assert command(tmp_path / "rig.usda") == "usdface.api.fit_capture (Python API)"


def test_personalize_records_where_its_command_ran(tmp_path, monkeypatch, capsys):
    """The layer recorded the command as typed (relative paths: 'usdface personalize lib/avatar.usda ...
    -o pub/v001/p.usda') but not the folder it ran in, so the record could not be run again from anywhere
    else (the inputs are recorded relative to the layer, the command line is not). It records the working
    folder now, and inspect shows it; from there the recorded line runs again."""
    import os
    import shutil

    (tmp_path / "lib").mkdir()
    shutil.copy(A, tmp_path / "lib" / "avatar.usda")
    monkeypatch.chdir(tmp_path)
    argv = ["personalize", "lib/avatar.usda", str(C), "-o", "pub/v001/p.usda", "-q"]
    assert main(argv) == 0
    record = Sdf.Layer.FindOrOpen(str(tmp_path / "pub" / "v001" / "p.usda")).customLayerData["usdface"]
    assert shlex.split(record["command"]) == ["usdface", *argv]
    assert os.path.samefile(record["workingDirectory"], tmp_path)
    capsys.readouterr()
    assert main(["inspect", "pub/v001/p.usda"]) == 0
    assert f"command run in {record['workingDirectory']}" in capsys.readouterr().out


def test_a_reproducible_layer_records_no_working_directory(tmp_path, monkeypatch):
    """With SOURCE_DATE_EPOCH the same command gives the same bytes wherever it ran: no workingDirectory."""
    from usdface.io.layers import write_avatar_layer
    from usdface.io.usd_rig import read_avatar

    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    avatar = read_avatar(A)
    head = avatar.mesh("Head")
    out = write_avatar_layer(avatar, tmp_path / "p.usda", {head.key: head.deltas},
                             provenance={"command": "usdface personalize a.usda c.usda -o p.usda"})
    assert "workingDirectory" not in Sdf.Layer.FindOrOpen(str(out)).customLayerData["usdface"]
