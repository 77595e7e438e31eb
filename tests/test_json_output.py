"""``--json``: every command's success document (ok, output) and its error document (type, file, fix), usage
errors and system errors included."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from cli_helpers import _usdface

import usdface.io  # noqa: F401  (registers the schemas before a test opens a stage)
from usdface.cli import main

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"


def test_json_error_for_a_full_disk_carries_the_fix(tmp_path, monkeypatch, capsys):
    """With --json a system OSError (here a full disk) used to give `"fix": null` while the stderr line and a
    UsdFaceError document carry one; now the document has the same fix as the line."""
    import errno

    from usdface.io import atomic

    def full(*_a, **_k):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "capture2.usda"))

    monkeypatch.setattr(atomic.os, "link", full)
    monkeypatch.chdir(tmp_path)
    code = main(["fit", str(SAMPLES / "capture.usda"), "-o", "capture2.usda", "--json"])
    captured = capsys.readouterr()
    error = json.loads(captured.out)["error"]
    assert code == 2 and error["type"] == "OSError" and error["file"] == str(tmp_path / "capture2.usda")
    assert error["fix"] == "free disk space or write the output elsewhere (-o)"
    assert f"(fix: {error['fix']})" in captured.err


def test_json_error_for_a_file_in_the_way_carries_the_fix(tmp_path, capsys):
    """A real system error, no mock: `sample` into a folder under a plain file."""
    (tmp_path / "afile").write_text("")
    assert main(["sample", str(tmp_path / "afile" / "sub"), "--json"]) == 2
    captured = capsys.readouterr()
    error = json.loads(captured.out)["error"]
    assert error["fix"] and f"(fix: {error['fix']})" in captured.err and "(-o)" not in error["fix"]
    # what it means here, not a generic fix (refused before any work now: the ENOTDIR fix of the preflight)
    assert "a parent of the path is a file, not a folder" in error["fix"]


def test_json_output_and_json_errors(tmp_path, monkeypatch, capfd):
    """Section 4: fit, anim import, capture select and sample speak JSON with --json, errors included."""
    from usdface.io.livelink import write_livelink_csv

    monkeypatch.chdir(tmp_path)
    w = np.clip(np.sin(np.linspace(0, 3, 40))[:, None] * [0.9, 0.2], 0, 1)
    write_livelink_csv("t.csv", ["jawOpen", "eyeBlinkLeft"], w, np.arange(40) / 30)
    assert main(["anim", "import", "t.csv", "-o", "t.usda", "--json"]) == 0
    doc = json.loads(capfd.readouterr().out)
    assert doc["ok"] and doc["frames"] == 40 and set(doc["names"]) == {"jawOpen", "eyeBlinkLeft"}
    assert main(["capture", "select", "t.csv", "--json"]) == 0
    doc = json.loads(capfd.readouterr().out)
    by_name = {s["name"]: s for s in doc["shapes"]}
    assert by_name["jawOpen"]["triggered"] and by_name["jawOpen"]["frames"] == [int(np.argmax(w[:, 0]))]
    assert "eyeBlinkLeft" in doc["never_triggered"]
    assert main(["fit", str(SAMPLES / "capture.usda"), "-o", "rig.usda", "--method", "dt", "--json"]) == 0
    doc = json.loads(capfd.readouterr().out)
    assert doc["ok"] and doc["method"] == "dt" and doc["train_rmse_mm"] > 0 and len(doc["shapes"]) == 52
    assert main(["fit", "missing.usda", "-o", "rig2.usda", "--json"]) == 2
    out = capfd.readouterr()
    err = json.loads(out.out)["error"]
    assert err["file"] == "missing.usda" and err["fix"] and err["type"] == "InputFileError"
    assert not Path("rig2.usda").exists()


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
        "retarget": ["retarget", avatar, capture, "-o", "map.json", "--json"],
    }
    for what, args in runs.items():
        res = _usdface(*args, cwd=tmp_path)
        assert res.returncode == 0, (what, res.stderr)
        doc = json.loads(res.stdout)
        assert doc["ok"] is True and "output" in doc, (what, list(doc)[:5])
    assert json.loads(_usdface(*runs["personalize"], "--force", cwd=tmp_path).stdout)["output"].endswith(
        "p.usda")
    # retarget had no --json (a trial): the map's size and settings, and an existing map refused as JSON
    res = _usdface(*runs["retarget"], "--force", cwd=tmp_path)
    doc = json.loads(res.stdout)
    assert len(doc["sources"]) == len(json.loads((tmp_path / "map.json").read_text())["source"])
    assert doc["weight_bounds"] == [0.0, 1.0] and doc["mu_choice"] == "leave one face region out"
    assert "usdface: retarget" not in res.stderr                     # no progress beside the document
    fail = _usdface(*runs["retarget"], cwd=tmp_path)
    assert fail.returncode == 2 and json.loads(fail.stdout)["error"]["type"] == "OutputExistsError"


def test_json_failures_are_ok_false_also_for_usage_errors(sample_dir, tmp_path):
    for args in (["inspect", tmp_path / "nope.usda", "--json"],                   # input error
                 ["inspect", sample_dir / "avatar.usda", "--json", "--bogus"],    # usage errors
                 ["personalize", sample_dir / "avatar.usda", sample_dir / "capture.usda", "--mu", "-1",
                  "--json"]):
        res = _usdface(*args, cwd=tmp_path)
        assert res.returncode == 2 and "Traceback" not in res.stderr
        doc = json.loads(res.stdout)
        assert doc["ok"] is False and doc["error"]["message"] and doc["error"]["command"] == args[0], doc


def test_a_json_error_names_the_command_with_its_action(tmp_path, capsys):
    """'capture select' and 'anim import' errors said "command": "capture" / "anim" in their JSON (the line on
    stderr says 'usdface capture select: error'), so a pipeline could not tell capture import from select."""
    csv = tmp_path / "angles.csv"
    csv.write_text("Timecode,BlendShapeCount,HeadYaw\n10:00:00:00.0,1,0.1\n10:00:00:02.0,1,0.2\n")
    anim = ["anim", "import", str(csv), "-o", str(tmp_path / "t.usda"), "--json"]
    select = ["capture", "select", str(csv), "--json"]
    for argv, command in ((select, "capture select"), (anim, "anim import"),
                          (["anim", "import", "--json"], "anim import")):              # a usage error
        try:
            status = main(argv)
        except SystemExit as exc:          # argparse's usage error
            status = exc.code
        out, err = capsys.readouterr()
        assert status == 2 and json.loads(out)["error"]["command"] == command, (argv, out)
        assert f"usdface {command}: error" in err
