"""Issue 20: what a new user's trial of the CLI hit (``usdface sample``, ``personalize``, ``anim import``,
``evaluate``, ``render``, ``export``...), each pinned by a test that runs the CLI as the user did and failed
before the fix."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

import usdface.io  # noqa: F401  (registers the schemas before a test opens a stage)

ROOT = Path(__file__).resolve().parents[1]


def _usdface(*args, cwd):
    exe = Path(sys.executable).with_name("usdface")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-c", "import sys; from usdface.cli import main; "
                                                                  "sys.exit(main())"]
    return subprocess.run(cmd + [str(a) for a in args], cwd=cwd, capture_output=True, text=True, timeout=600)


def _no_traceback(res) -> None:
    assert "Traceback" not in res.stderr, res.stderr
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)


@pytest.fixture(scope="module")
def livelink_csv(shared, tmp_path_factory) -> Path:
    """The first 30 frames of a real Live Link Face CSV."""
    lines = (shared / "data" / "livelinkface" / "facial.csv").read_text().splitlines()[:31]
    out = tmp_path_factory.mktemp("csv") / "facial.csv"
    out.write_text("\n".join(lines) + "\n")
    return out


@pytest.fixture(scope="module")
def sample_dir(tmp_path_factory) -> Path:
    """``usdface sample s2`` (avatar.usda, capture.usda, truth/{capture,avatar}_truth.npz)."""
    from usdface.sample import generate_samples

    return generate_samples(tmp_path_factory.mktemp("trial") / "s2")


# ------------------------------------------------------------------------------- 1. anim import --force
@pytest.mark.parametrize("suffix", [".usda", ".usdc"])
def test_anim_import_force_overwrites(livelink_csv, tmp_path, suffix):
    out = tmp_path / f"t{suffix}"
    first = _usdface("anim", "import", livelink_csv, "-o", out, "-q", cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    out.write_bytes(b"stale")  # so the second write is seen to replace it
    again = _usdface("anim", "import", livelink_csv, "-o", out, "--force", "-q", cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    from pxr import Usd

    assert Usd.Stage.Open(str(out)).GetDefaultPrim().GetTypeName() == "SkelAnimation"
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name]
    refused = _usdface("anim", "import", livelink_csv, "-o", out, "-q", cwd=tmp_path)
    assert refused.returncode == 2 and "exists" in refused.stderr


def test_write_take_usd_force_overwrites(tmp_path):
    """The other take writer had the same missing ``force``."""
    from usdface.io.take import read_take_usd, write_take_usd

    take_file = tmp_path / "take.usda"
    take = _sample_take(tmp_path)
    write_take_usd(take, take_file)
    write_take_usd(take, take_file, force=True)
    assert len(read_take_usd(take_file).times) == len(take.times)


def _sample_take(tmp_path):
    import numpy as np

    from usdface.io.take import Take

    tri = np.array([[0, 1, 2]])
    pts = np.zeros((3, 3, 3))
    pts[:, 1, 0] = pts[:, 2, 1] = 0.01
    return Take(points=pts, triangles=tri, times=np.arange(3) / 30.0, weights=np.zeros((3, 1)),
                names=["jawOpen"])


# ------------------------------------------------------------------------------------------ 2. evaluate
def test_evaluate_bad_plot_format_fails_before_work(sample_dir, tmp_path):
    res = _usdface("evaluate", sample_dir / "capture.usda", "--plot", "errors.pgn", "--json", "rep.json",
                   cwd=tmp_path)
    _no_traceback(res)
    assert "errors.pgn" in res.stderr and "'pgn'" in res.stderr and "errors.png" in res.stderr
    assert list(tmp_path.iterdir()) == []  # rep.json not written


def test_evaluate_json_report_must_end_in_json(sample_dir, tmp_path):
    res = _usdface("evaluate", sample_dir / "capture.usda", "--json", "rep.txt", cwd=tmp_path)
    _no_traceback(res)
    assert "rep.txt" in res.stderr and ".json" in res.stderr
    assert list(tmp_path.iterdir()) == []


def test_evaluate_wrong_truth_file_names_the_right_one(sample_dir, tmp_path):
    capture = sample_dir / "capture.usda"
    res = _usdface("evaluate", capture, "--truth", sample_dir / "truth" / "avatar_truth.npz",
                   "--plot", "e.png", cwd=tmp_path)
    _no_traceback(res)
    assert "avatar_truth.npz" in res.stderr and "capture_truth.npz" in res.stderr
    assert list(tmp_path.iterdir()) == []
    res = _usdface("evaluate", capture, "--truth", capture, cwd=tmp_path)
    _no_traceback(res)
    assert "not an .npz" in res.stderr


def test_sample_picture_extension_checked_before_the_samples_are_written(tmp_path):
    res = _usdface("sample", "s4", "--picture", "x.pgn", cwd=tmp_path)
    _no_traceback(res)
    assert "x.pgn" in res.stderr and "x.png" in res.stderr
    assert list(tmp_path.iterdir()) == []



def test_sample_json_still_draws_the_picture(tmp_path):
    """``sample --json --picture`` returned before drawing the picture; it is drawn and named in the JSON."""
    res = _usdface("sample", "s5", "--json", "--picture", "s5.png", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc["ok"] and Path(doc["picture"]).name == "s5.png"
    assert (tmp_path / "s5.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

# ------------------------------------------------------------------------------------- 3. error messages
def test_face_mesh_mouth_says_the_capture_collapsed_not_a_perfect_residual(sample_dir, tmp_path):
    res = _usdface("personalize", sample_dir / "avatar.usda", sample_dir / "capture.usda",
                   "--face-mesh", "Mouth", "--dry-run", cwd=tmp_path)
    _no_traceback(res)
    assert "shrank the capture to a point" in res.stderr and "--face-mesh" in res.stderr
    assert "residual 0.00 mm" not in res.stderr and "100% of capture vertices" not in res.stderr


def test_face_mesh_mouth_on_a_production_avatar_names_the_skin_meshes(shared, tmp_path, capfd):
    """User trial: ``--face-mesh Mouth`` on dev1 (the capture registers, but covers none of the mouth
    socket) said "no avatar vertex lies on the registered capture surface (empty face region) (fix: check that
    the capture and the avatar are faces)": they were. The message says the chosen mesh has no vertex the
    capture covers and names the skin mesh to pick."""
    from usdface.cli import main

    bench = shared / "data" / "bench" / "dev1"
    code = main(["personalize", str(bench / "avatar.usdc"), str(bench / "capture"), "--face-mesh", "Mouth",
                 "--dry-run", "-q"])
    err = capfd.readouterr().err
    assert code == 2 and "prim /Avatar/Mouth" in err, err
    assert "empty face region" not in err and "are faces" not in err
    assert "--face-mesh has no vertex the capture covers" in err
    assert "pick the skin mesh with --face-mesh (candidates: /Avatar/Head (" in err
    assert "without --face-mesh usdface picks /Avatar/Head" in err


def test_empty_face_region_error_lists_the_meshes_the_shapes_move(samples):
    from usdface.errors import RigError
    from usdface.io.usd_rig import read_avatar
    from usdface.transfer.pipeline import empty_face_region

    avatar = read_avatar(samples / "avatar.usda")
    names = ["jawOpen", "eyeBlinkLeft", "mouthSmileLeft"]
    chosen = empty_face_region(avatar.file, avatar.meshes, "/Avatar/Mouth", names, chosen=True)
    assert isinstance(chosen, RigError) and chosen.prim == "/Avatar/Mouth"
    assert "no vertex the capture covers" in chosen.message
    assert chosen.fix.startswith("pick the skin mesh with --face-mesh (candidates: /Avatar/Head (")
    assert "/Avatar/Mouth (" not in chosen.fix                          # not the mesh that failed
    auto = empty_face_region(avatar.file, avatar.meshes, "/Avatar/Head", names, chosen=False)
    assert "same face" in auto.fix and "--face-mesh" in auto.fix and "/Avatar/Head (" not in auto.fix


@pytest.mark.parametrize("command", ["personalize", "render"])
def test_anim_import_take_passed_as_avatar_is_named_a_take(livelink_csv, sample_dir, tmp_path, command):
    take = tmp_path / "take.usdc"
    assert _usdface("anim", "import", livelink_csv, "-o", take, "-q", cwd=tmp_path).returncode == 0
    args = {"personalize": [take, sample_dir / "capture.usda", "--dry-run"],
            "render": [take, "-o", "x.png"]}[command]     # inspect summarises it (test_user_trial_s23)
    res = _usdface(command, *args, cwd=tmp_path)
    _no_traceback(res)
    assert "this is a take" in res.stderr and "not an avatar" in res.stderr, res.stderr
    assert "SkelRoot" not in res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["take.usdc"]


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


@pytest.mark.parametrize("content,expected", [
    ('#usda 1.0\ndef Xform "A" {\n  float x = \n}\n', "line 3, column 3: Expected }"),
    ("garbage\n", "bad.usda is not a valid usda layer"),
    ("", "bad.usda is not a valid usda layer"),
])
def test_usd_syntax_error_shows_the_parsers_message_with_the_line(sample_dir, tmp_path, content, expected):
    bad = tmp_path / "bad.usda"
    bad.write_text(content)
    for args in (["inspect", bad], ["personalize", bad, sample_dir / "capture.usda", "--dry-run"],
                 ["personalize", sample_dir / "avatar.usda", sample_dir / "capture.usda", "--pins", bad,
                  "--dry-run"]):
        res = _usdface(*args, cwd=tmp_path)
        _no_traceback(res)
        assert expected in res.stderr, res.stderr
        assert "pxrInternal" not in res.stderr and ".cpp" not in res.stderr and "Error in '" not in res.stderr


def test_truncated_usdc_says_so(sample_dir, tmp_path):
    from pxr import Sdf

    whole = tmp_path / "whole.usdc"
    Sdf.Layer.FindOrOpen(str(sample_dir / "avatar.usda")).Export(str(whole))
    cut = tmp_path / "cut.usdc"
    cut.write_bytes(whole.read_bytes()[:whole.stat().st_size // 2])
    res = _usdface("inspect", cut, cwd=tmp_path)
    _no_traceback(res)
    assert "possibly truncated" in res.stderr and "crateFile.cpp" not in res.stderr, res.stderr


def _studio_named(avatar: Path, out: Path) -> Path:
    """``avatar`` with every ARKit shape name replaced by a studio's own (``ch17_ctrl``), everywhere."""
    import re

    from usdface.arkit import ARKIT_NAMES

    idx = {n: i for i, n in enumerate(ARKIT_NAMES)}
    words = re.compile(r"\b(" + "|".join(sorted(ARKIT_NAMES, key=len, reverse=True)) + r")\b")
    out.write_text(words.sub(lambda m: f"ch{idx[m.group(1)]:02d}_ctrl", avatar.read_text()))
    return out


def test_render_unknown_shape_names_the_file_and_the_name_map(sample_dir, tmp_path):
    studio = _studio_named(sample_dir / "avatar.usda", tmp_path / "studio.usda")
    res = _usdface("render", studio, "--shapes", "jawOpen", "-o", "x.png", cwd=tmp_path)
    _no_traceback(res)
    assert "studio.usda, prim /Avatar/Head: mesh Head has no shape 'jawOpen'" in res.stderr, res.stderr
    assert "--name-map" in res.stderr and "ch00_ctrl" in res.stderr
    assert not (tmp_path / "x.png").exists()


def test_render_compare_unknown_shape_names_the_layer(personalized_sample, tmp_path):
    res = _usdface("render", personalized_sample, "--compare", "--shapes", "jawOpen,nope", "-o", "x.png",
                   cwd=tmp_path)
    _no_traceback(res)
    assert f"{personalized_sample}, prim /Avatar/Head: mesh Head has no shape 'nope'" in res.stderr
    assert "--name-map" not in res.stderr  # its shapes are ARKit-named
    assert "did you mean" not in res.stderr  # nothing close to 'nope'
    assert not (tmp_path / "x.png").exists()


def test_render_a_shape_name_typo_gets_the_close_name(samples, tmp_path, capsys):
    """User trial: ``--shapes jawOpn`` listed the first eight shapes only; the close name is offered."""
    from usdface.cli import main

    assert main(["render", str(samples / "avatar.usda"), "--shapes", "jawOpn", "-o", str(tmp_path / "x.png"),
                 "-q"]) == 2
    assert "has no shape 'jawOpn' (fix: did you mean jawOpen?" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------- 4. --json
def test_every_json_success_says_ok_and_output(sample_dir, livelink_csv, tmp_path):
    avatar, capture = sample_dir / "avatar.usda", sample_dir / "capture.usda"
    runs = {
        "personalize": ["personalize", avatar, capture, "-o", "p.usda", "--json"],
        "personalize --dry-run": ["personalize", avatar, capture, "--dry-run", "--json"],
        "inspect": ["inspect", avatar, "--json"],
        "check": ["check", avatar, "--json"],
        "sample": ["sample", "s3", "--json"],
        "anim import": ["anim", "import", livelink_csv, "-o", "t.usda", "--json"],
        "fit": ["fit", capture, "-o", "rig.usda", "--json"],
    }
    for what, args in runs.items():
        res = _usdface(*args, cwd=tmp_path)
        assert res.returncode == 0, (what, res.stderr)
        doc = json.loads(res.stdout)
        assert doc["ok"] is True and "output" in doc, (what, list(doc)[:5])
    assert json.loads(_usdface(*runs["personalize"], "--force", cwd=tmp_path).stdout)["output"].endswith(
        "p.usda")


def test_json_failures_are_ok_false_also_for_usage_errors(sample_dir, tmp_path):
    for args in (["inspect", tmp_path / "nope.usda", "--json"],                   # input error
                 ["inspect", sample_dir / "avatar.usda", "--json", "--bogus"],    # usage errors
                 ["personalize", sample_dir / "avatar.usda", sample_dir / "capture.usda", "--mu", "-1",
                  "--json"]):
        res = _usdface(*args, cwd=tmp_path)
        assert res.returncode == 2 and "Traceback" not in res.stderr
        doc = json.loads(res.stdout)
        assert doc["ok"] is False and doc["error"]["message"] and doc["error"]["command"] == args[0], doc


# -------------------------------------------------------------------------------------------- 5. minor
def test_export_of_a_plain_avatar_says_as_authored(sample_dir, personalized_sample, tmp_path):
    import pygltflib

    res = _usdface("export", sample_dir / "avatar.usda", "--gltf", "a.glb", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "[personalized]" not in res.stdout and "as authored" in res.stdout, res.stdout
    extras = pygltflib.GLTF2().load(str(tmp_path / "a.glb")).scenes[0].extras
    assert extras["usdface"]["variant"] == "authored"
    res = _usdface("export", personalized_sample, "--gltf", "p.glb", cwd=tmp_path)
    assert res.returncode == 0 and "[personalized]" in res.stdout, res.stderr
    extras = pygltflib.GLTF2().load(str(tmp_path / "p.glb")).scenes[0].extras
    assert extras["usdface"]["variant"] == "personalized"


def test_batch_progress_says_failed_for_a_failed_item(sample_dir, tmp_path):
    import os

    # captures that pass the batch's check of every row (present, readable, USD) and fail in the reader: a
    # missing file no longer runs at all (the batch refuses the manifest before its first item)
    (tmp_path / "broken.usda").write_text("not USD\n")
    (tmp_path / "m.csv").write_text("avatar,capture,output\n"
                                    f"{sample_dir / 'avatar.usda'},{tmp_path / 'broken.usda'},bad.usda\n"
                                    f"{sample_dir / 'avatar.usda'},{sample_dir / 'avatar.usda'},bad2.usda\n")
    env = dict(os.environ, USDFACE_PROGRESS="plain", USDFACE_PROGRESS_DELAY="0")
    exe = Path(sys.executable).with_name("usdface")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-c", "import sys; from usdface.cli import main; "
                                                                  "sys.exit(main())"]
    res = subprocess.run(cmd + ["batch", "m.csv", "-j", "1"], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=600)
    assert res.returncode == 1
    assert "[1/2] bad.usda failed" in res.stderr and "[2/2] bad2.usda failed" in res.stderr, res.stderr
    assert "bad.usda done" not in res.stderr


def test_a_failed_write_names_the_output_not_the_temp_file(tmp_path):
    import errno

    from usdface.io.atomic import atomic_file

    out = tmp_path / "report.json"
    with pytest.raises(OSError) as info, atomic_file(out) as tmp:
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp))
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(out)
    assert list(tmp_path.iterdir()) == []


def test_debug_after_the_command_shows_the_traceback(tmp_path, capsys):
    """User trial: ``usdface personalize ... --debug`` (added to the failed command line) said
    'unrecognized arguments: --debug'; it worked only as ``usdface --debug personalize``. Both work now,
    in sub-commands too; without it the one-line error stays."""
    from usdface.cli import main
    from usdface.errors import InputFileError

    line = ["personalize", str(tmp_path / "nothere.usda"), str(tmp_path / "c.usda"),
            "-o", str(tmp_path / "o.usda")]
    assert main(line) == 2 and "avatar not found" in capsys.readouterr().err
    for argv in ([*line, "--debug"], ["--debug", *line]):
        with pytest.raises(InputFileError, match="avatar not found"):
            main(argv)
    with pytest.raises(InputFileError, match="capture not found"):
        main(["capture", "import", str(tmp_path / "none"), "-o", str(tmp_path / "c.usda"), "--debug"])


def test_a_missing_file_is_named_for_what_the_command_reads(tmp_path, capsys):
    """User trial: review, export and inspect of a missing file said 'avatar not found' (the avatar
    reader's noun); they read a layer or any USD file."""
    from usdface.cli import main

    missing = str(tmp_path / "nothere.usda")
    for argv, said in ((["review", missing, "-o", str(tmp_path / "r.html")], "USD file not found"),
                       (["inspect", missing], "USD file not found"),
                       (["export", missing, "--gltf", str(tmp_path / "x.glb")], "layer not found"),
                       (["render", missing, "-o", str(tmp_path / "x.png")], "avatar not found")):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert f"nothere.usda: {said}" in err, err


def test_usdface_alone_prints_its_usage_on_stderr_and_exits_2(tmp_path, capsys):
    """``usdface`` without a command printed the help on stdout and exited 0, so a script's ``usdface $CMD``
    with ``$CMD`` unset passed; now a usage error (exit 2, as ``usdface capture`` alone); ``--help``: 0."""
    from usdface.cli import main

    with pytest.raises(SystemExit) as code:
        main([])
    out, err = capsys.readouterr()
    assert code.value.code == 2 and out == ""
    assert err.startswith("usage: usdface ") and "required: COMMAND (see 'usdface --help')" in err
    res = _usdface(cwd=tmp_path)
    assert (res.returncode, res.stdout) == (2, "") and "usage: usdface " in res.stderr, res.stderr
    assert "Traceback" not in res.stderr
    res = _usdface("--help", cwd=tmp_path)
    assert res.returncode == 0 and "personalize" in res.stdout and res.stderr == ""
