"""The commands a warning or an error suggests paste into a shell and run as written, also for files in
folders whose names have spaces (a shoot's ``shoot day/``, ``Anna Smith/``): each path in them is one
shell word.
Before stop 40 they were joined unquoted (``usdface capture select shoot day/take.usdc -o ...``), and the
pasted fix failed with ``unrecognized arguments``."""

from __future__ import annotations

import re
import shlex
import shutil

from wfutil import run

from usdface.io.take import write_take_usd
from usdface.io.usd_capture import read_capture_usd
from usdface.sample.take import make_take


def _fix_command(text: str, command: str) -> list[str]:
    """The ``(usdface COMMAND ...)`` a message suggests, split as a shell splits it: a command is set in
    parentheses, never in quotes of its own (stop 43: ``'usdface personalize 'a b.usda' ...'``)."""
    found = re.search(rf"\((usdface {command} (?:'[^']*'|[^'()])*)\)", text)
    assert found, text
    return shlex.split(found.group(1))


def test_capture_select_rest_fix_runs_as_written_from_a_folder_with_spaces(sample_set, tmp_path):
    """A take with rests longer than --min-separation: the held-out test frames are rests, and the warning's
    fix repeats the run with other test-frame options; pasted, it runs (exit 0) on the same take."""
    import numpy as np

    from usdface.model import FaceRig

    truth = np.load(sample_set / "truth" / "capture_truth.npz")
    capture = read_capture_usd(sample_set / "capture.usda")
    names = [str(n) for n in truth["names"]]
    person = FaceRig(truth["neutral"], capture.triangles, names, truth["deltas"])
    # 30 fps, 0.4 s rests between the sweeps: test frames every 40 frames 0.5 s from the peaks are rests
    take, _ = make_take(person, capture.template.subset(names), shapes=names[:12], seed=2)
    (tmp_path / "shoot day").mkdir()
    write_take_usd(take, tmp_path / "shoot day" / "my take.usdc")
    proc = run("capture", "select", "shoot day/my take.usdc", "-o", "out dir/c.usda", "--test-every", "40",
               cwd=tmp_path)
    said = proc.stdout + proc.stderr
    assert "show no expression" in said, said
    argv = _fix_command(said, "capture select")
    assert argv[3] == "shoot day/my take.usdc" and argv[argv.index("-o") + 1] == "out dir/c.usda", argv
    again = run(*argv[1:], cwd=tmp_path)          # the pasted fix: one argument per path, --force included
    assert "wrote" in again.stdout, again.stdout


def test_review_of_a_plain_avatar_suggests_personalize_on_that_path(sample_set, tmp_path):
    (tmp_path / "hero assets").mkdir()
    shutil.copy(sample_set / "avatar.usda", tmp_path / "hero assets" / "hero v2.usda")
    proc = run("review", "hero assets/hero v2.usda", cwd=tmp_path, ok=False)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    argv = _fix_command(proc.stderr, "personalize")
    assert argv[2] == "hero assets/hero v2.usda", argv


def _layout_commands(text: str) -> tuple[list[str], list[str]]:
    """The ``usdface landmarks ...`` and ``usdface render ... --landmarks`` a render refusal tells, split."""
    return _fix_command(text, "landmarks"), _fix_command(text, "render")


def test_render_landmarks_without_a_layout_tells_commands_that_run_as_written(sample_set, tmp_path):
    """No layout in the file: both commands told, pasted whole, draw one (the render command lacked its
    -o, which render requires)."""
    (tmp_path / "hero assets").mkdir()
    shutil.copy(sample_set / "avatar.usda", tmp_path / "hero assets" / "hero v2.usda")
    proc = run("render", "hero assets/hero v2.usda", "-o", "lm.png", "--landmarks", cwd=tmp_path, ok=False)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    write, draw = _layout_commands(proc.stderr)
    assert write[2] == "hero assets/hero v2.usda", write
    assert draw[2] == write[write.index("-o") + 1], (write, draw)
    run(*write[1:], cwd=tmp_path)
    run(*draw[1:], cwd=tmp_path)
    assert (tmp_path / "lm.png").stat().st_size > 0


def test_render_landmarks_of_another_mesh_tells_commands_that_run_as_written(sample_set, tmp_path):
    """A layout of the Mouth drawn with --mesh Head: the fix told 'usdface landmarks --mesh Head' (no file,
    no output), which pasted stops at its missing argument. Now the two commands, pasted, draw a Head
    layout."""
    run("landmarks", sample_set / "avatar.usda", "--mesh", "Mouth", "-o", "lm mouth.usda", cwd=tmp_path)
    proc = run("render", "lm mouth.usda", "-o", "head.png", "--landmarks", "--mesh", "Head", cwd=tmp_path,
               ok=False)
    assert proc.returncode == 2 and "the file has one for /Avatar/Mouth" in proc.stderr, proc.stderr
    write, draw = _layout_commands(proc.stderr)
    assert write[2] == "lm mouth.usda" and write[write.index("--mesh") + 1] == "Head", write
    run(*write[1:], cwd=tmp_path)
    run(*draw[1:], cwd=tmp_path)
    assert (tmp_path / "head.png").stat().st_size > 0


def test_export_of_a_capture_tells_its_own_fix_which_runs_as_written(sample_set, tmp_path):
    """``export CAPTURE`` (a capture where the personalized layer goes) was told the avatar reader's shared
    fix, "personalize: AVATAR, then CAPTURE", which says nothing of export; ``--flatten`` wrote the capture
    flattened as "a plain avatar". Now export says what the file is, that it takes the layer personalize
    writes, and the two commands to run: pasted (AVATAR filled in), they write the outputs asked for."""
    (tmp_path / "shoot day").mkdir()
    shutil.copy(sample_set / "capture.usda", tmp_path / "shoot day" / "anna cap.usda")
    shutil.copy(sample_set / "avatar.usda", tmp_path / "hero.usda")
    for given in ("shoot day/anna cap.usda", sample_set / "capture"):      # a capture file, a capture folder
        proc = run("export", given, "--gltf", "out dir/anna.glb", "--flatten", "anna flat.usdc", cwd=tmp_path,
                   ok=False)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
        assert "not a layer written by 'usdface personalize'" in proc.stderr, proc.stderr
        assert "personalize: AVATAR, then CAPTURE" not in proc.stderr, proc.stderr
        assert not (tmp_path / "out dir").exists() and not (tmp_path / "anna flat.usdc").exists()
    personalize, export = _fix_command(proc.stderr, "personalize"), _fix_command(proc.stderr, "export")
    assert personalize[2:4] == ["AVATAR", str(sample_set / "capture")], personalize
    personalize[2] = "hero.usda"
    run(*personalize[1:], "-q", "--method", "dt", cwd=tmp_path)
    assert export[1:] == ["export", "person.usda", "--gltf", "out dir/anna.glb", "--flatten",
                          "anna flat.usdc"], export
    run(*export[1:], cwd=tmp_path)
    assert (tmp_path / "out dir" / "anna.glb").is_file() and (tmp_path / "anna flat.usdc").is_file()
