"""Progress on stderr (issue 11, section 4): plain lines naming the running step when stderr is not a terminal
(logs, CI), a bar on a terminal, nothing with ``-q`` or ``--json`` (stdout stays one JSON document)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from usdface import progress
from usdface.arkit import ARKIT_NAMES
from usdface.cli import main

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
LINE = re.compile(r"^usdface: .+ \[\d+/\d+\] .+$")


@pytest.fixture(autouse=True)
def _plain(monkeypatch):
    """Every step announced at once (delay 0), progress on; the CLI sets it per call from -q/--json."""
    monkeypatch.setenv("USDFACE_PROGRESS_DELAY", "0")
    monkeypatch.delenv("USDFACE_PROGRESS", raising=False)
    progress.set_enabled(True)
    yield
    progress.set_enabled(True)


def progress_lines(err: str) -> list[str]:
    return [ln for ln in err.splitlines() if ln.startswith("usdface: ") and "error" not in ln]


def run_cli(capsys, *argv) -> tuple[str, str]:
    capsys.readouterr()
    assert main([str(a) for a in argv]) == 0
    cap = capsys.readouterr()
    return cap.out, cap.err


@pytest.fixture(scope="module")
def csv_take(tmp_path_factory) -> Path:
    """A weights-only Live Link Face CSV: 40 frames in which every shape peaks once."""
    from usdface.io.livelink import write_livelink_csv

    k = len(ARKIT_NAMES)
    frames = np.arange(40)[:, None]
    weights = np.clip(1.0 - np.abs(frames - (np.arange(k)[None, :] % 40)) / 3.0, 0.0, 1.0) * 0.9
    path = tmp_path_factory.mktemp("take") / "take.csv"
    write_livelink_csv(path, list(ARKIT_NAMES), weights, np.arange(40) / 30.0)
    return path


# ------------------------------------------------------------------------------------------- the module
def test_plain_lines_name_each_running_step_and_its_end(capsys):
    with progress.steps("job", 2) as p:
        p.start("first")
        assert progress_lines(capsys.readouterr().err) == ["usdface: job [1/2] first ... (t+0.0 s)"]
        p.start("second")
    err = progress_lines(capsys.readouterr().err)
    assert err[0].startswith("usdface: job [1/2] first done (")
    assert err[1].startswith("usdface: job [2/2] second ... (t+")
    assert err[2].startswith("usdface: job [2/2] second done (")
    assert err[3].startswith("usdface: job done in ")
    assert capsys.readouterr().out == ""


def test_a_host_application_gets_the_lines_in_its_own_log(capsys, caplog, monkeypatch):
    """A host application (a DCC, a farm job) wants progress in its log, not on its stderr (a user trial:
    no logging integration): :func:`usdface.progress.set_logger`; ``None`` goes back to stderr."""
    import logging

    monkeypatch.setenv("USDFACE_PROGRESS", "bar")          # the logger wins over a terminal's bar
    logger = logging.getLogger("studio.usdface")
    progress.set_logger(logger)
    try:
        with caplog.at_level(logging.INFO, logger="studio.usdface"), progress.steps("job", 2) as p:
            p.start("first")
            p.start("second")
    finally:
        progress.set_logger(None)
    lines = [r.getMessage() for r in caplog.records if r.name == "studio.usdface"]
    assert lines[0] == "job [1/2] first ... (t+0.0 s)" and lines[-1].startswith("job done in ")
    assert capsys.readouterr().err == ""
    monkeypatch.delenv("USDFACE_PROGRESS")
    with progress.steps("job", 1) as p:
        p.start("again")
    assert progress_lines(capsys.readouterr().err)[0] == "usdface: job [1/1] again ... (t+0.0 s)"


def test_quick_steps_print_nothing_and_a_slow_one_is_named_while_it_runs(capsys, monkeypatch):
    monkeypatch.setenv("USDFACE_PROGRESS_DELAY", "60")
    with progress.steps("job", 3) as p:
        p.start("quick")
        p.start("quick too")
        p("done-style")
    assert capsys.readouterr().err == ""
    monkeypatch.setenv("USDFACE_PROGRESS_DELAY", "0.05")
    with progress.steps("job", 1) as p:
        p.start("slow")
        deadline = time.monotonic() + 30
        while not p.announced and time.monotonic() < deadline:  # the timer thread names it after 0.05 s
            time.sleep(0.01)
        assert progress_lines(capsys.readouterr().err) == ["usdface: job [1/1] slow ... (t+0.0 s)"]
    assert progress_lines(capsys.readouterr().err)[0].startswith("usdface: job [1/1] slow done (")


def test_a_long_native_call_names_the_running_step_before_it_starts(capsys, monkeypatch):
    """Open3D's decimation of a large mesh holds Python's GIL for its seconds, so the timer thread could not
    print the running step's line: 'render''s draw and 'review''s read (10-19 s) showed it only when the
    call had ended, up to 8 s late. :func:`usdface.progress.announce` prints it before such a call, once,
    in every open block; a mesh under the display limit (no decimation) prints nothing."""
    from synthetic_meshes import grid_triangles

    from usdface import natives
    from usdface.mesh import display_subset

    monkeypatch.setenv("USDFACE_PROGRESS_DELAY", "60")           # no timer line within the test
    u, v = np.meshgrid(np.linspace(0, 1, 40), np.linspace(0, 1, 40))
    points, tris = np.c_[u.ravel(), v.ravel(), np.zeros(1600)], grid_triangles(40, 40)
    said = []
    real = natives.open3d

    def watched():                    # what stderr held when the native call was about to start
        said.extend(progress_lines(capsys.readouterr().err))
        return real()

    monkeypatch.setattr(natives, "open3d", watched)
    with progress.steps("render", 1) as p:
        p.start("draw")
        assert display_subset(points, tris, 2000) is None                 # under the limit: quiet
        assert capsys.readouterr().err == ""
        with progress.steps("inner", 1) as q:
            q.start("decimate")
            display_subset(points, tris, 400)
            progress.announce()                                            # once: already out
    assert said == ["usdface: render [1/1] draw ... (t+0.0 s)",
                    "usdface: render > inner [1/1] decimate ... (t+0.0 s)"]
    err = [ln.split(" (")[0].split(" in ")[0] for ln in progress_lines(capsys.readouterr().err)]
    assert err == ["usdface: render > inner [1/1] decimate done", "usdface: render > inner done",
                   "usdface: render [1/1] draw done", "usdface: render done"]       # each said once
    monkeypatch.setenv("USDFACE_PROGRESS", "off")
    with progress.steps("job", 1) as p:
        p.start("hidden")
        progress.announce()
    assert capsys.readouterr().err == ""


def test_nested_blocks_prefix_the_outer_title_and_off_prints_nothing(capsys):
    with progress.steps("outer", 1) as p:
        p.start("inner work")
        with progress.steps("inner", 1) as q:
            q.start("leaf")
    err = progress_lines(capsys.readouterr().err)
    assert "usdface: outer > inner [1/1] leaf ... (t+0.0 s)" in err
    progress.set_enabled(False)
    with progress.steps("job", 1) as p:
        p.start("hidden")
        p("old style")
    assert capsys.readouterr().err == ""


def test_env_override_and_bar_mode_nests_without_a_live_error(capsys, monkeypatch):
    monkeypatch.setenv("USDFACE_PROGRESS", "off")
    assert progress.mode() == "off"
    monkeypatch.setenv("USDFACE_PROGRESS", "bar")
    assert progress.mode() == "bar"
    with progress.steps("outer", 2) as p:  # rich allows one live display: the inner block is a second row
        p.start("a")
        with progress.steps("inner", 1) as q:
            q.start("b")
        p("a done")
    assert progress._LIVE is None and not progress._STACK
    assert capsys.readouterr().out == ""


@pytest.mark.skipif(sys.platform == "win32", reason="needs a pseudo-terminal")
def test_on_a_terminal_it_is_a_bar(tmp_path):
    """stderr a pseudo-terminal: rich draws the bar (control codes), labelled with the running step."""
    import pty

    master, slave = pty.openpty()
    env = {k: v for k, v in os.environ.items() if not k.startswith("USDFACE_PROGRESS")}
    proc = subprocess.Popen([sys.executable, "-m", "usdface.cli", "fit", str(SAMPLES / "capture.usda"), "-o",
                             "f.usda", "--method", "dt"], cwd=tmp_path, stdout=subprocess.PIPE, stderr=slave,
                            env=dict(env, COLUMNS="100"))
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 65536)
        except OSError:  # the child closed the terminal
            break
        if not data:
            break
        chunks.append(data)
    out = proc.stdout.read().decode()
    assert proc.wait() == 0
    os.close(master)
    err = b"".join(chunks).decode(errors="replace")
    assert "\x1b[" in err and "fit: " in err and "3/3" in err
    assert "usdface: fit [" not in err  # not the plain lines
    assert out.startswith(f"wrote {tmp_path / 'f.usda'}")       # the API's path: absolute


# ----------------------------------------------------------------------------------------- the commands
def test_subprocess_log_gets_plain_lines(tmp_path):
    """A log (stderr a pipe): one line per step naming it, no control codes."""
    env = dict(os.environ, USDFACE_PROGRESS_DELAY="0")
    env.pop("USDFACE_PROGRESS", None)
    proc = subprocess.run([sys.executable, "-m", "usdface.cli", "capture", "import",
                           str(SAMPLES / "capture.usda"), "-o", "c.usda"], cwd=tmp_path, capture_output=True,
                          text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    lines = progress_lines(proc.stderr)
    assert "usdface: capture import [1/2] read capture.usda ... (t+0.0 s)" in lines
    assert any(ln.startswith("usdface: capture import [2/2] write c.usda ...") for ln in lines)
    assert "\x1b" not in proc.stderr
    assert proc.stdout.startswith(f"wrote {tmp_path / 'c.usda'}")


def test_fit_names_its_steps_and_json_or_quiet_silence_them(capsys, tmp_path):
    out, err = run_cli(capsys, "fit", SAMPLES / "capture.usda", "-o", tmp_path / "a.usda", "--method", "dt")
    lines = progress_lines(err)
    assert "usdface: fit [1/3] read capture capture.usda ... (t+0.0 s)" in lines
    assert any(ln.startswith("usdface: fit [2/3] fit dt ...") for ln in lines)
    assert any(ln.startswith("usdface: fit [3/3] write a.usda ...") for ln in lines)
    out, err = run_cli(capsys, "fit", SAMPLES / "capture.usda", "-o", tmp_path / "b.usda", "--method", "dt",
                       "--json")
    assert json.loads(out)["ok"] is True and err == ""
    out, err = run_cli(capsys, "fit", SAMPLES / "capture.usda", "-o", tmp_path / "c.usda", "--method", "dt",
                       "-q")
    assert out.startswith("wrote") and err == ""


def test_evaluate_names_each_method(capsys):
    out, err = run_cli(capsys, "evaluate", SAMPLES / "capture.usda", "--methods", "dt")
    lines = progress_lines(err)
    assert any(ln.startswith("usdface: evaluate [2/2] fit and score the methods ...") for ln in lines)
    assert any(ln.startswith("usdface: evaluate > methods [1/1] fit and score dt ...") for ln in lines)
    assert run_cli(capsys, "evaluate", SAMPLES / "capture.usda", "--methods", "dt", "--quiet")[1] == ""


def test_anim_import_names_its_steps(capsys, tmp_path, csv_take):
    out, err = run_cli(capsys, "anim", "import", csv_take, "-o", tmp_path / "t.usda")
    lines = progress_lines(err)
    assert "usdface: anim import [1/2] read take.csv ... (t+0.0 s)" in lines
    assert any(ln.startswith("usdface: anim import [2/2] write t.usda (40 frames) ...") for ln in lines)
    out, err = run_cli(capsys, "anim", "import", csv_take, "-o", tmp_path / "u.usda", "--json")
    assert json.loads(out)["frames"] == 40 and err == ""
    assert run_cli(capsys, "anim", "import", csv_take, "-o", tmp_path / "v.usda", "-q")[1] == ""


def test_capture_select_names_its_steps(capsys, csv_take):
    out, err = run_cli(capsys, "capture", "select", csv_take)
    lines = progress_lines(err)
    assert "usdface: capture select [1/2] read take take.csv ... (t+0.0 s)" in lines
    assert any(ln.startswith("usdface: capture select [2/2] select frames (40 frames) ...") for ln in lines)
    out, err = run_cli(capsys, "capture", "select", csv_take, "--json")
    assert json.loads(out)["ok"] is True and err == ""
    assert run_cli(capsys, "capture", "select", csv_take, "-q")[1] == ""


def test_capture_import_quiet(capsys, tmp_path):
    out, err = run_cli(capsys, "capture", "import", SAMPLES / "capture.usda", "-o", tmp_path / "c.usda")
    assert any(ln.startswith("usdface: capture import [2/2] write c.usda ...") for ln in progress_lines(err))
    assert run_cli(capsys, "capture", "import", SAMPLES / "capture.usda", "-o", tmp_path / "d.usda",
                   "-q")[1] == ""


def test_sample_names_its_steps(capsys, tmp_path):
    out, err = run_cli(capsys, "sample", tmp_path / "s")
    lines = progress_lines(err)
    for n, label in enumerate(("build avatar and capture", "write avatar.usda", "write capture.usda",
                               "write truth"), 1):
        assert any(ln.startswith(f"usdface: sample [{n}/4] {label} ...") for ln in lines), (label, lines)
    out, err = run_cli(capsys, "sample", tmp_path / "t", "--json")
    assert json.loads(out)["ok"] is True and err == ""


def test_landmarks_and_personalize_use_it_too(capsys, tmp_path):
    out, err = run_cli(capsys, "landmarks", SAMPLES / "avatar.usda", "-o", tmp_path / "lm.usda")
    lines = progress_lines(err)
    assert any(ln.startswith("usdface: landmarks [1/2] layout of Head ...") for ln in lines), lines
    assert any(ln.startswith("usdface: landmarks [2/2] write lm.usda ...") for ln in lines), lines
    assert run_cli(capsys, "landmarks", SAMPLES / "avatar.usda", "-q")[1] == ""
    out, err = run_cli(capsys, "personalize", SAMPLES / "avatar.usda", SAMPLES / "capture.usda", "-o",
                       tmp_path / "q.usda")
    lines = progress_lines(err)
    for step in ("read", "register", "fit", "transfer", "write"):
        assert any(re.match(rf"usdface: personalize \[\d/8\] {step} done", ln) for ln in lines), (step, lines)
    assert all(LINE.match(ln) or " done in " in ln for ln in lines)


def test_landmarks_evaluate_names_each_layout(capsys):
    """``landmarks --evaluate`` (a reduced sweep of the same driver): a line per layout and baseline."""
    from usdface import api
    from usdface.landmarks.evaluate import evaluate_landmarks

    rig = api.pick_mesh(api.read_avatar(SAMPLES / "avatar.usda"), "Head")
    weights = np.random.default_rng(0).uniform(0, 1, (10, len(rig.names)))
    capsys.readouterr()
    evaluate_landmarks(rig, weights, epsilons=(0.5,), rounds=(1, 2), shares=(0.1,), counts=(8,),
                       random_seeds=1)
    lines = progress_lines(capsys.readouterr().err)
    assert lines[0].startswith("usdface: landmarks --evaluate [1/3] eps=0.5 multicover=1 share=0.1 done (")
    assert lines[1].startswith("usdface: landmarks --evaluate [2/3] eps=0.5 multicover=2 share=0.1 done (")
    assert lines[2].startswith("usdface: landmarks --evaluate [3/3] baselines at 8 done (")


def test_review_names_its_steps_for_what_they_do(capsys, tmp_path, personalized_sample):
    """User trial: ``usdface review`` printed "review [1/2] page done" for the reading and "review [2/2] step
    done" for building the page. Each step is named while it runs, the write included."""
    out, err = run_cli(capsys, "review", personalized_sample, "-o", tmp_path / "r.html")
    lines = progress_lines(err)
    for n, label in enumerate((f"read {personalized_sample.name} (meshes, shapes, fit figures)",
                               "build the page", "write r.html"), 1):
        assert any(ln.startswith(f"usdface: review [{n}/3] {label} ...") for ln in lines), (label, lines)
        assert any(ln.startswith(f"usdface: review [{n}/3] {label} done (") for ln in lines), (label, lines)
    assert not any(" step done" in ln or "] page done" in ln for ln in lines), lines
    assert all(LINE.match(ln) or " done in " in ln for ln in lines)
    assert (tmp_path / "r.html").stat().st_size > 0


def test_render_and_export_name_their_steps(capsys, tmp_path, personalized_sample):
    """Trial on a 225k-vertex head: ``render --compare`` (two avatars read, 9 panels drawn: ~50 s) and
    ``export --gltf`` (~30 CPU-s) said nothing until they were done. Each step is named while it runs."""
    layer = personalized_sample
    _out, err = run_cli(capsys, "render", layer, "-o", tmp_path / "c.png", "--compare", "--shapes", "jawOpen")
    lines = progress_lines(err)
    for n, label in enumerate((f"read {layer.name}", "read the generic avatar.usda", "draw c.png"), 1):
        assert any(ln.startswith(f"usdface: render [{n}/3] {label} ...") for ln in lines), (label, lines)
        assert any(ln.startswith(f"usdface: render [{n}/3] {label} done (") for ln in lines), (label, lines)
    _out, err = run_cli(capsys, "render", layer, "-o", tmp_path / "s.png")
    assert any(ln.startswith("usdface: render [2/2] draw s.png done (") for ln in progress_lines(err))
    _out, err = run_cli(capsys, "export", layer, "--gltf", tmp_path / "a.glb",
                        "--flatten", tmp_path / "f.usdc")
    lines = progress_lines(err)
    for n, label in enumerate((f"read the personalized variant of {layer.name}", "write a.glb",
                               "flatten the personalized variant into f.usdc"), 1):
        assert any(ln.startswith(f"usdface: export [{n}/3] {label} done (") for ln in lines), (label, lines)
    assert all(LINE.match(ln) or " done in " in ln for ln in lines)
    _out, err = run_cli(capsys, "render", layer, "-o", tmp_path / "d.png", "--landmarks", "--diagnostics",
                        "--rays", "4")
    lines = progress_lines(err)
    assert any(ln.startswith("usdface: render > diagnostics [1/") for ln in lines), lines
    assert not any("render > render" in ln for ln in lines), lines


def test_main_called_by_a_host_leaves_its_progress_setting_as_it_was(samples, capsys, monkeypatch):
    """``usdface.cli.main(argv)`` from a host application set progress for the whole process: ``-q`` turned
    the host's progress off for good, and a run without it turned it back on after the host had turned it
    off with ``usdface.progress.set_enabled(False)``."""
    monkeypatch.setattr(progress, "_ENABLED", progress._ENABLED)       # the test's own change undone
    avatar = str(samples / "avatar.usda")
    progress.set_enabled(False)
    assert main(["check", avatar, "--no-pixar"]) == 0 and progress._ENABLED is False
    progress.set_enabled(True)
    assert main(["check", avatar, "--no-pixar", "-q"]) == 0 and progress._ENABLED is True
    assert main(["inspect", str(samples / "missing.usda"), "--json"]) == 2 and progress._ENABLED is True


def test_main_called_on_two_host_threads_side_by_side_leaves_its_progress_setting(monkeypatch):
    """Each ``main(argv)`` put back the progress setting it found: a ``-q`` run and one without it on a
    host's threads side by side, the second found the first's 'off' and put it back last, and the host's
    progress stayed off for good."""
    import threading

    from cli_stubs import waiting_parser

    from usdface import cli

    gates = {name: (threading.Event(), threading.Event()) for name in ("a", "b")}

    def run(args):                               # a command that runs until the test lets it end
        gates[args.name][0].set()
        gates[args.name][1].wait(5)
        return 0

    monkeypatch.setattr(cli, "build_parser", waiting_parser(run))
    monkeypatch.setattr(progress, "_ENABLED", True)
    codes = []
    quiet = threading.Thread(target=lambda: codes.append(main(["wait", "a", "-q"])))
    quiet.start()
    assert gates["a"][0].wait(5)
    loud = threading.Thread(target=lambda: codes.append(main(["wait", "b"])))   # enters while -q runs
    loud.start()
    assert gates["b"][0].wait(5)
    gates["a"][1].set()                          # the -q run ends first ...
    quiet.join()
    gates["b"][1].set()                          # ... then the other
    loud.join()
    assert codes == [0, 0] and progress._ENABLED is True
