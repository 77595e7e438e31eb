"""Issue 11 acceptance: a battery of malformed inputs and faults, each run through the CLI as a user would.

Every case must give exit status 2 and exactly one line on stderr that names the file (and the prim where
there is one) and the fix, with no traceback; leave no output and no temporary file; and leave every input
byte-identical. Inputs are copies of the sample assets (or files made from them) in a temporary folder, which
is also the working folder; anything new in it after the run is a leftover.
"""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import _no_traceback, _usdface

import usdface.io  # noqa: F401  (schemas registered before the fixtures open stages)
from usdface.cli import main

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"


def _export(out: Path, edit) -> None:
    from pxr import Sdf, Usd, UsdGeom

    copy = Sdf.Layer.CreateAnonymous(".usda")          # never the sample's own (cached, shared) layer
    copy.TransferContent(Sdf.Layer.FindOrOpen(str(SAMPLES / "avatar.usda")))
    stage = Usd.Stage.Open(copy)
    edit(stage, UsdGeom.Mesh(stage.GetPrimAtPath("/Avatar/Head")))
    stage.GetRootLayer().Export(str(out))


def _set_points(stage, head, fn):
    from pxr import Vt

    p = np.array(head.GetPointsAttr().Get(), dtype=np.float32)
    fn(p)
    head.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(p))


def _time_sampled(stage, head):
    attr = head.GetPointsAttr()
    value = attr.Get()
    attr.Clear()
    attr.Set(value, 1.0)
    attr.Set(value, 2.0)


RIG_EDITS = {
    "nan.usda": lambda s, h: _set_points(s, h, lambda p: p.__setitem__(5, np.nan)),
    "inf.usda": lambda s, h: _set_points(s, h, lambda p: p.__setitem__(7, np.inf)),
    "counts.usda": lambda s, h: h.GetFaceVertexCountsAttr().Set(
        [c + (i == 0) for i, c in enumerate(h.GetFaceVertexCountsAttr().Get())]),
    "indices.usda": lambda s, h: h.GetFaceVertexIndicesAttr().Set(
        [10 ** 6] + list(h.GetFaceVertexIndicesAttr().Get())[1:]),
    "nofaces.usda": lambda s, h: (h.GetFaceVertexCountsAttr().Set([]), h.GetFaceVertexIndicesAttr().Set([])),
    "mpu0.usda": lambda s, h: s.SetMetadata("metersPerUnit", 0.0),
    "mpuneg.usda": lambda s, h: s.SetMetadata("metersPerUnit", -0.01),
    "mpunan.usda": lambda s, h: s.SetMetadata("metersPerUnit", float("nan")),
    "upx.usda": lambda s, h: s.SetMetadata("upAxis", "X"),
    "timesampled.usda": _time_sampled,
}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    """The sample assets and the malformed files made from them, built once."""
    d = tmp_path_factory.mktemp("battery_inputs")
    shutil.copy(SAMPLES / "avatar.usda", d / "avatar.usda")
    shutil.copy(SAMPLES / "capture.usda", d / "capture.usda")
    for name, edit in RIG_EDITS.items():
        _export(d / name, edit)
    (d / "garbage.usda").write_bytes(b"\x00\x01 this is not usd at all \xff\xfe")
    (d / "empty.usdc").write_bytes(b"")
    (d / "truncated.usdc").write_bytes(b"PXR-USDC" + b"\x00" * 64)
    (d / "nosub.usda").write_text("#usda 1.0\n(\n    subLayers = [@missing_layer.usda@]\n)\n")
    (d / "cycle_a.usda").write_text("#usda 1.0\n(\n    subLayers = [@cycle_b.usda@]\n)\n")
    (d / "cycle_b.usda").write_text("#usda 1.0\n(\n    subLayers = [@cycle_a.usda@]\n)\n")
    (d / "dangling.usda").write_text('#usda 1.0\n(\n    defaultPrim = "Avatar"\n)\ndef SkelRoot "Avatar" '
                                      '(\n    references = @gone.usda@</Avatar>\n)\n{\n}\n')
    (d / "plain.usda").write_text('#usda 1.0\ndef Mesh "M"\n{\n    point3f[] points = [(0,0,0), (1,0,0), '
                                  '(0,1,0)]\n    int[] faceVertexCounts = [3]\n    int[] faceVertexIndices = '
                                  '[0, 1, 2]\n}\n')
    (d / "not_a_capture.usda").write_text('#usda 1.0\ndef Xform "Thing"\n{\n}\n')
    (d / "empty_capture").mkdir()
    (d / "notemplate").mkdir()
    shutil.copy(d / "plain.usda", d / "notemplate" / "readme.usda")
    (d / "neutral_only").mkdir()
    (d / "neutral_only" / "neutral.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (d / "nan_take.csv").write_text("Timecode,BlendShapeCount,EyeBlinkLeft,JawOpen\n"
                                    "00:00:00:00.000,2,0.1,nan\n00:00:00:01.000,2,0.2,0.3\n")
    (d / "garbage_take.csv").write_text("hello,world\n1,2\n")
    (d / "ragged_take.csv").write_text("Timecode,BlendShapeCount,EyeBlinkLeft,JawOpen\n"
                                       "00:00:00:00.000,2,0.1\n")
    (d / "dup_take.csv").write_text("Timecode,BlendShapeCount,EyeBlinkLeft,EyeBlinkLeft\n"
                                    "00:00:00:00.000,2,0.1,0.2\n")
    (d / "header_only.csv").write_text("Timecode,BlendShapeCount,EyeBlinkLeft\n")
    (d / "take_dir").mkdir()
    (d / "empty.npz").write_bytes(b"")
    (d / "text.npz").write_text("not an archive")
    (d / "exists.usda").write_text("#usda 1.0\n")
    (d / "exists.json").write_text("{}")
    (d / "exists.png").write_bytes(b"\x89PNG\r\n\x1a\nkeep")
    (d / "a_file").write_text("I am a file")
    (d / "out_dir.usda").mkdir()
    os.mkfifo(d / "pipe.usda")
    from usdface.io.layers import write_avatar_layer
    from usdface.io.usd_rig import read_avatar

    avatar = read_avatar(d / "avatar.usda")
    head = avatar.mesh("Head")            # a personalized layer (it carries the personalization variants)
    write_avatar_layer(avatar, d / "person.usda", {head.key: head.deltas * 1.01}, provenance={})
    return d


A, C = "avatar.usda", "capture.usda"
P = ["personalize"]
#: id -> (argv, strings the error line must contain). Paths are relative to the inputs folder (the cwd).
CASES = {
    # --- avatars: files that are not what they claim
    "avatar-missing": (P + ["nope.usda", C, "-o", "o.usda"], ["nope.usda", "not found"]),
    "avatar-folder": (P + ["empty_capture", C, "-o", "o.usda"], ["empty_capture", "folder"]),
    "avatar-pipe": (P + ["pipe.usda", C, "-o", "o.usda"], ["pipe.usda", "named pipe"]),
    "avatar-garbage": (P + ["garbage.usda", C, "-o", "o.usda"], ["garbage.usda", "USD cannot open"]),
    "avatar-empty-usdc": (P + ["empty.usdc", C, "-o", "o.usda"], ["empty.usdc"]),
    "avatar-truncated-usdc": (P + ["truncated.usdc", C, "-o", "o.usda"], ["truncated.usdc"]),
    "avatar-newline-path": (P + ["ava\ntar.usda", C, "-o", "o.usda"], ["line break"]),
    # --- composition
    "avatar-missing-sublayer": (P + ["nosub.usda", C, "-o", "o.usda"], ["nosub.usda", "missing_layer.usda"]),
    "avatar-sublayer-cycle": (P + ["cycle_a.usda", C, "-o", "o.usda"], ["cycle_a.usda", "cycle"]),
    "avatar-dangling-reference": (P + ["dangling.usda", C, "-o", "o.usda"], ["dangling.usda", "gone.usda"]),
    "check-sublayer-cycle": (["check", "cycle_a.usda"], ["cycle_a.usda", "cycle"]),
    "inspect-missing-sublayer": (["inspect", "nosub.usda"], ["nosub.usda", "missing_layer.usda"]),
    # --- rigs the reader refuses
    "avatar-nan-points": (P + ["nan.usda", C, "-o", "o.usda"], ["nan.usda", "/Avatar/Head", "NaN"]),
    "avatar-inf-points": (P + ["inf.usda", C, "-o", "o.usda"], ["inf.usda", "/Avatar/Head", "NaN/inf"]),
    "avatar-face-counts": (P + ["counts.usda", C, "-o", "o.usda"], ["counts.usda", "/Avatar/Head"]),
    "avatar-face-indices": (P + ["indices.usda", C, "-o", "o.usda"], ["indices.usda", "/Avatar/Head"]),
    "avatar-no-faces": (P + ["nofaces.usda", C, "-o", "o.usda"], ["nofaces.usda", "/Avatar/Head", "faces"]),
    "avatar-mpu-zero": (P + ["mpu0.usda", C, "-o", "o.usda"], ["mpu0.usda", "metersPerUnit"]),
    "avatar-mpu-negative": (P + ["mpuneg.usda", C, "-o", "o.usda"], ["mpuneg.usda", "metersPerUnit"]),
    "avatar-mpu-nan": (P + ["mpunan.usda", C, "-o", "o.usda"], ["mpunan.usda", "metersPerUnit"]),
    "avatar-up-x": (P + ["upx.usda", C, "-o", "o.usda"], ["upx.usda", "upAxis"]),
    "avatar-no-skelroot": (P + ["plain.usda", C, "-o", "o.usda"], ["plain.usda", "SkelRoot"]),
    "landmarks-nan-points": (["landmarks", "nan.usda"], ["nan.usda", "/Avatar/Head"]),
    "check-nan-points": (["check", "nan.usda", "--no-pixar"], None),  # exit 1: a report, not an error
    # --- the wrong kind of file
    "capture-as-avatar": (P + [C, C, "-o", "o.usda"], ["capture.usda", "/Capture", "not an avatar"]),
    "landmarks-on-capture": (["landmarks", C], ["capture.usda", "/Capture", "not an avatar"]),
    "usdface-output-as-avatar": (P + ["person.usda", C, "-o", "o.usda"], ["person.usda", "avatar.usda"]),
    "avatar-as-capture": (P + [A, A, "-o", "o.usda"], ["avatar.usda", "capture"]),
    # --- captures
    "capture-missing": (P + [A, "nocap", "-o", "o.usda"], ["nocap", "not found"]),
    "capture-garbage": (P + [A, "garbage.usda", "-o", "o.usda"], ["garbage.usda"]),
    "capture-not-a-capture": (P + [A, "not_a_capture.usda", "-o", "o.usda"], ["not_a_capture.usda"]),
    "capture-empty-folder": (["capture", "import", "empty_capture", "-o", "c.usda"], ["empty_capture"]),
    "capture-folder-no-template": (["capture", "import", "notemplate", "-o", "c.usda"], ["notemplate"]),
    "capture-neutral-only": (["capture", "import", "neutral_only", "-o", "c.usda"], ["neutral_only"]),
    "capture-missing-sublayer": (P + [A, "nosub.usda", "-o", "o.usda"], ["nosub.usda", "missing_layer.usda"]),
    # --- takes (validated before any work)
    "take-missing": (P + [A, C, "-o", "o.usda", "--take", "nope.csv"], ["nope.csv"]),
    "take-nan": (P + [A, C, "-o", "o.usda", "--take", "nan_take.csv"], ["nan_take.csv", "NaN"]),
    "take-garbage": (P + [A, C, "-o", "o.usda", "--take", "garbage_take.csv"], ["garbage_take.csv"]),
    "take-ragged": (P + [A, C, "-o", "o.usda", "--take", "ragged_take.csv"], ["ragged_take.csv", "line 2"]),
    "take-duplicate-column": (P + [A, C, "-o", "o.usda", "--take", "dup_take.csv"], ["dup_take.csv"]),
    "take-empty-folder": (P + [A, C, "-o", "o.usda", "--take", "take_dir"], ["take_dir"]),
    "anim-import-header-only": (["anim", "import", "header_only.csv", "-o", "t.usda"], ["header_only.csv"]),
    "anim-import-duplicate": (["anim", "import", "dup_take.csv", "-o", "t.usda"], ["dup_take.csv"]),
    "select-garbage": (["capture", "select", "garbage_take.csv"], ["garbage_take.csv"]),
    # --- caches
    "correspondence-empty": (P + [A, C, "-o", "o.usda", "--correspondence", "empty.npz"], ["empty.npz"]),
    "correspondence-text": (P + [A, C, "-o", "o.usda", "--correspondence", "text.npz"], ["text.npz"]),
    "correspondence-folder": (P + [A, C, "-o", "o.usda", "--correspondence", "take_dir"], ["take_dir"]),
    # --- outputs
    "output-exists": (P + [A, C, "-o", "exists.usda"], ["exists.usda", "--force"]),
    "output-is-folder": (P + [A, C, "-o", "out_dir.usda"], ["out_dir.usda", "folder"]),
    "output-parent-is-file": (P + [A, C, "-o", "a_file/o.usda"], ["a_file", "file"]),
    "output-wrong-extension": (P + [A, C, "-o", "o.txt"], ["o.txt", ".usda"]),
    "output-newline": (P + [A, C, "-o", "o\n.usda"], ["line break"]),
    "output-is-the-capture": (P + [A, C, "-o", C, "--force"], ["capture.usda", "input"]),
    "output-is-the-avatar": (P + [A, C, "-o", A, "--force"], ["avatar.usda", "input"]),
    "capture-import-obj": (["capture", "import", C, "-o", "c.obj"], ["c.obj", ".usda"]),
    "capture-import-onto-itself": (["capture", "import", C, "-o", C, "--force"], ["capture.usda", "input"]),
    "render-jpg": (["render", A, "-o", "x.jpg"], ["x.jpg", ".png"]),
    "render-exists": (["render", A, "-o", "exists.png"], ["exists.png", "--force"]),
    "landmarks-json-exists": (["landmarks", A, "--json", "exists.json"], ["exists.json", "--force"]),
    "landmarks-plot-jpg": (["landmarks", A, "--plot", "x.jpg"], ["x.jpg", ".png"]),
    "retarget-map-exists": (["retarget", A, C, "-o", "exists.json"], ["exists.json", "--force"]),
    "retarget-wrong-extension": (["retarget", A, C, "-o", "map.txt"], ["map.txt"]),
    "anim-import-exists": (["anim", "import", "nan_take.csv", "-o", "exists.usda"], ["exists.usda"]),
    "fit-output-exists": (["fit", C, "-o", "exists.usda"], ["exists.usda", "--force"]),
    # --- option values (argparse: one line naming the option)
    "mu-nan": (["retarget", A, C, "-o", "m.json", "--mu", "nan"], ["--mu", "'nan'"]),
    "mu-negative": (P + [A, C, "--mu", "-1"], ["--mu"]),
    "falloff-nan": (P + [A, C, "--falloff", "nan"], ["--falloff"]),
    "reg-inf": (["fit", C, "-o", "r.usda", "--reg", "inf"], ["--reg"]),
    "timecode-rate-zero": (["anim", "import", "nan_take.csv", "-o", "t.usda", "--timecode-rate", "0"],
                           ["--timecode-rate"]),
    "timecode-rate-nan": (["anim", "import", "nan_take.csv", "-o", "t.usda", "--timecode-rate", "nan"],
                          ["--timecode-rate"]),
    "camera-nan": (["landmarks", A, "--camera", "0,nan,1"], ["--camera"]),
    "threshold-nan": (["capture", "select", "nan_take.csv", "--threshold", "nan"], ["--threshold"]),
    "jobs-zero": (["batch", "m.csv", "-j", "0"], ["--jobs"]),
}


def _snapshot(folder: Path) -> dict:
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_fifo() or p.is_dir():
            out[str(p.relative_to(folder))] = "special"
        else:
            out[str(p.relative_to(folder))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _run(argv, cwd: Path, monkeypatch, capfd) -> tuple[int, str, str]:
    monkeypatch.chdir(cwd)
    capfd.readouterr()
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse
        code = exc.code
    out = capfd.readouterr()
    return code, out.out, out.err


def assert_clean_failure(code, err, needles, before, folder, code_expected=2):
    assert code == code_expected, f"exit {code}: {err}"
    assert "Traceback" not in err, err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, f"expected one line, got:\n{err}"
    line = lines[0]
    assert line.startswith("usdface"), line
    assert "(fix:" in line or "--help" in line, line
    for needle in needles:
        assert needle in line, f"{needle!r} not in {line!r}"
    after = _snapshot(folder)
    assert after == before, f"files changed or left behind: {set(after) ^ set(before) or 'contents'}"


@pytest.mark.parametrize("case", sorted(CASES))
def test_malformed_input(case, inputs, monkeypatch, capfd):
    argv, needles = CASES[case]
    before = _snapshot(inputs)
    code, out, err = _run(argv, inputs, monkeypatch, capfd)
    if needles is None:  # check: a report with errors, exit 1, nothing written
        assert code == 1 and "Traceback" not in err and "error" in out.lower()
        assert _snapshot(inputs) == before
        return
    assert_clean_failure(code, err, needles, before, inputs)


# ----------------------------------------------------------------------------------------------- faults
def _enospc(*_a, **_k):
    raise OSError(errno.ENOSPC, "No space left on device")


FAULTS = {
    # where the write fails -> what is patched
    "disk-full-capture-layer": (["capture", "import", C, "-o", "c2.usda"], "usdface.io.atomic.os.link"),
    "disk-full-take-layer": (["anim", "import", "ok_take.csv", "-o", "t.usda"], "usdface.io.atomic.os.link"),
    "disk-full-render": (["render", A, "-o", "r.png", "--shapes", "jawOpen"], "usdface.io.atomic.os.link"),
    "disk-full-capture-folder": (["capture", "import", C, "-o", "cap_folder"],
                                 "usdface.io.atomic.os.replace"),
}


@pytest.fixture
def work(inputs, tmp_path) -> Path:
    for name in (A, C):
        shutil.copy(inputs / name, tmp_path / name)
    (tmp_path / "ok_take.csv").write_text("Timecode,BlendShapeCount,EyeBlinkLeft,JawOpen\n"
                                          "00:00:00:00.000,2,0.1,0.2\n00:00:00:01.000,2,0.2,0.3\n")
    return tmp_path


@pytest.mark.parametrize("case", sorted(FAULTS))
def test_write_fault(case, work, monkeypatch, capfd):
    argv, target = FAULTS[case]
    before = _snapshot(work)
    monkeypatch.setattr(target, _enospc)
    code, _out, err = _run(argv, work, monkeypatch, capfd)
    assert_clean_failure(code, err, ["No space left", "free disk space"], before, work)


def _mount_tmpfs(where: Path, size: str, ro: bool = False) -> bool:
    where.mkdir()
    opts = f"size={size}" + (",ro" if ro else "")
    try:
        ok = subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(where)], capture_output=True,
                            timeout=20).returncode == 0
    except (OSError, subprocess.SubprocessError):
        ok = False
    return ok


@pytest.fixture
def tiny_fs(tmp_path):
    """A real 64 KiB file system (tmpfs; needs root and mount rights, else the test skips)."""
    mnt = tmp_path / "tiny"
    if not _mount_tmpfs(mnt, "64k"):
        pytest.skip("cannot mount a tmpfs here (needs root)")
    yield mnt
    subprocess.run(["umount", str(mnt)], capture_output=True, timeout=20)


@pytest.fixture
def ro_fs(tmp_path):
    mnt = tmp_path / "ro"
    if not _mount_tmpfs(mnt, "64k", ro=True):
        pytest.skip("cannot mount a read-only tmpfs here (needs root)")
    yield mnt
    subprocess.run(["umount", str(mnt)], capture_output=True, timeout=20)


def test_real_full_disk(work, tiny_fs, monkeypatch, capfd):
    before = _snapshot(work)
    code, _out, err = _run(["capture", "import", C, "-o", str(tiny_fs / "c.usda")], work, monkeypatch, capfd)
    assert_clean_failure(code, err, ["c.usda"], before, work)
    assert list(tiny_fs.iterdir()) == []


def test_real_read_only_file_system(work, ro_fs, monkeypatch, capfd):
    before = _snapshot(work)
    code, _out, err = _run(["capture", "import", C, "-o", str(ro_fs / "c.usda")], work, monkeypatch, capfd)
    assert_clean_failure(code, err, ["Read-only file system", "elsewhere"], before, work)


def test_read_only_folder(work, monkeypatch, capfd):
    if os.geteuid() == 0:
        pytest.skip("root ignores folder permissions")
    ro = work / "library"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        before = _snapshot(work)
        code, _out, err = _run(["capture", "import", C, "-o", "library/c.usda"], work, monkeypatch, capfd)
        assert_clean_failure(code, err, ["Permission denied"], before, work)
    finally:
        ro.chmod(0o755)


@pytest.mark.parametrize("command", ["personalize", "landmarks"])
def test_an_avatar_under_an_instanceable_prim_is_refused(samples, tmp_path, capsys, command):
    """USD composes no override under an instance: a layer over an instanced avatar would change nothing
    (it used to print "56 BlendShapes personalized" and pass ``check``). Refused, naming the prim, before
    any work; nothing written."""
    shutil.copy(samples / "avatar.usda", tmp_path / "avatar.usda")
    (tmp_path / "shot.usda").write_text(
        '#usda 1.0\n(\n    defaultPrim = "Hero"\n    metersPerUnit = 0.01\n    upAxis = "Y"\n)\n\n'
        'def "Hero" (\n    prepend references = @./avatar.usda@\n    instanceable = true\n)\n{\n}\n')
    out = tmp_path / "out.usda"
    args = ([str(tmp_path / "shot.usda"), str(samples / "capture.usda")] if command == "personalize"
            else [str(tmp_path / "shot.usda")])
    assert main([command, *args, "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "instanceable prim /Hero" in err and "instanceable = false" in err
    assert not out.exists()
    if command == "personalize":                    # a dry run reports what a real run would refuse
        assert main([command, *args, "-o", str(out), "--dry-run", "-q"]) == 1      # a preflight's answer
        said = capsys.readouterr()
        assert "a real run would refuse" in said.out + said.err


def test_time_sampled_only_points_are_read_at_their_first_sample(inputs, samples, tmp_path, capfd,
                                                                 monkeypatch):
    """A cache export whose Head points are only time-sampled (a user trial: refused with 'mesh has no
    points'): the first sample is the rest pose, said as a warning, and the answer is the sample's."""
    from usdface.io.usd_rig import read_avatar

    code, out, err = _run(P + ["timesampled.usda", C, "-o", str(tmp_path / "o.usda")], inputs, monkeypatch,
                          capfd)
    assert code == 0, err
    assert ("points have no default value, only 2 time sample(s): the sample at time 1 is read as the rest "
            "pose") in out
    code, _, err = _run(P + [A, C, "-o", str(tmp_path / "ref.usda")], inputs, monkeypatch, capfd)
    assert code == 0, err
    np.testing.assert_array_equal(read_avatar(tmp_path / "o.usda").mesh("Head").deltas,
                                  read_avatar(tmp_path / "ref.usda").mesh("Head").deltas)


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
