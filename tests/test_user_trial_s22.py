"""User trial, session 22: the fixes a trial user's findings asked for, each pinned by a test that failed
before the fix."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from usdface.cli import main

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"


# ------------------------------------------------------------------------- 1. flattened personalized export
@pytest.fixture(scope="module")
def person_layer(tmp_path_factory) -> Path:
    """A usdface layer over the sample avatar (personalized offsets on the Head: the layer carries the
    personalization variant set and the provenance)."""
    from usdface.io.layers import write_avatar_layer
    from usdface.io.usd_rig import read_avatar

    avatar = read_avatar(SAMPLES / "avatar.usda")
    head = avatar.mesh("Head")
    return write_avatar_layer(avatar, tmp_path_factory.mktemp("person") / "person.usda",
                              {head.key: head.deltas * 1.01}, provenance={})


def test_flattened_personalized_export_is_not_personalized_again(person_layer, tmp_path, capsys):
    """A `usdface export --flatten` of the personalized variant lost the variant set the refusal looked for:
    personalize stacked the personalization a second time. Now it is refused (AlreadyPersonalizedError) naming
    the file, the layer it came from and the fix (the generic variant, or the original avatar)."""
    from usdface.io.flatten import flatten_variant

    flat = flatten_variant(person_layer, tmp_path / "flat.usdc", "personalized")
    for command, out in (("personalize", tmp_path / "p2.usda"), ("retarget", tmp_path / "m.json")):
        argv = [command, str(flat), str(SAMPLES / "capture.usda"), "-o", str(out)]
        assert main(argv + (["--json"] if command == "personalize" else [])) == 2
        captured = capsys.readouterr()
        assert "flattened export" in captured.err and str(flat) in captured.err
        assert "--variant generic" in captured.err and "avatar.usda" in captured.err
        if command == "personalize":
            error = json.loads(captured.out)["error"]
            assert error["type"] == "AlreadyPersonalizedError" and error["file"] == str(flat)
            assert "person.usda --flatten flat.generic.usdc --variant generic" in error["fix"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["flat.usdc"]


def test_flattened_generic_export_and_plain_avatar_are_accepted(person_layer, tmp_path):
    """A flattened *generic* export is the avatar's own shapes: accepted. A flattened plain avatar records
    'authored' (it used to record 'personalized', the variant asked for, which it does not have)."""
    from pxr import Sdf

    from usdface.errors import AlreadyPersonalizedError
    from usdface.io.flatten import flatten_variant
    from usdface.io.usd_rig import flattened_from, refuse_usdface_output

    generic = flatten_variant(person_layer, tmp_path / "generic.usdc", "generic")
    flat = flattened_from(generic)            # the source relative to the flattened file (stop 23)
    assert flat["variant"] == "generic"
    assert (generic.parent / flat["source"]).resolve() == person_layer.resolve()
    refuse_usdface_output(generic)                       # no error
    plain = flatten_variant(SAMPLES / "avatar.usda", tmp_path / "plain.usdc", "personalized")
    assert dict(Sdf.Layer.FindOrOpen(str(plain)).customLayerData)["usdfaceFlatten"]["variant"] == "authored"
    refuse_usdface_output(plain)
    with pytest.raises(AlreadyPersonalizedError):        # the layer itself: refused as before
        refuse_usdface_output(person_layer)


# ----------------------------------------------------------------------------- 2. --json and system errors
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


# ------------------------------------------------------------------ 3. landmarks: the other mode's options
@pytest.mark.parametrize("extra, named", [
    (["--takes", "take.csv"], "--takes"),
    (["--frames", "100", "--noise", "1"], "--frames/--noise"),
    (["--empirical", "layout.json"], "--empirical"),
    (["--evaluate", "--takes", "take.csv", "-o", "layout.usda"], "-o/--output"),
    (["--evaluate", "--takes", "take.csv", "--epsilon", "0.6", "--alpha", "0.2"], "--epsilon/--alpha"),
    (["--evaluate", "--takes", "take.csv", "--spacing", "0"], "--spacing"),
    (["--evaluate", "--takes", "take.csv", "--multicover", "2", "--no-adaptive"],
     "--multicover/--no-adaptive"),
])
def test_landmarks_refuses_an_option_of_the_other_mode(tmp_path, monkeypatch, capsys, extra, named):
    """--takes/--frames/--noise/--empirical without --evaluate used to be ignored (a layout was computed and
    written as if they were not there); -o with --evaluate was ignored too. Now refused before any work
    (the avatar is not even read: the missing take files are not reached), naming the option and the fix."""
    from usdface import api

    monkeypatch.setattr(api, "read_avatar", lambda *_a, **_k: pytest.fail("work started"))
    monkeypatch.chdir(tmp_path)
    assert main(["landmarks", str(SAMPLES / "avatar.usda"), *extra]) == 2
    err = capsys.readouterr().err
    assert "LandmarkError" not in err and named in err and "(fix: " in err
    if "--evaluate" not in extra:
        assert "add --evaluate" in err
    else:
        assert f"leave out {named}" in err or "leave out -o" in err
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------ 4. docs/pipeline.md plugin table
def test_pipeline_doc_lists_every_pyblish_plugin_in_publish_order():
    """docs/pipeline.md's plugin table missed ExtractUsdFaceReview; it lists exactly PLUGINS, in order."""
    import re

    pytest.importorskip("pyblish")
    from usdface.pipeline.pyblish_plugins import PLUGINS

    text = (ROOT / "docs" / "pipeline.md").read_text()
    table = text[text.index("| plugin | order | does |"):]
    rows = re.findall(r"^\| `(\w+)` \|", table[:table.index("\n\n")], flags=re.M)
    assert rows == [plugin.__name__ for plugin in PLUGINS]


# ------------------------------------------------------------------------------- 5. batch report's name
def test_batch_report_is_named_as_documented(tmp_path, capsys):
    """The docs said `MANIFEST.report.json` (read: people.csv.report.json) where batch writes
    `<manifest stem>.report.json` beside the manifest; docs, --help and the file written now agree."""
    out = tmp_path / "out" / "anna.usda"
    out.parent.mkdir()
    out.write_text("#usda 1.0\n")                        # finished before: skipped, so the batch is instant
    manifest = tmp_path / "people.csv"
    manifest.write_text(f"avatar,capture,output\n{SAMPLES / 'avatar.usda'},{SAMPLES / 'capture.usda'},"
                        "out/anna.usda\n")
    assert main(["batch", str(manifest), "-j", "1"]) == 0
    report = tmp_path / "people.report.json"
    assert f"report: {report}" in capsys.readouterr().out
    assert json.loads(report.read_text())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "people.csv", "people.report.json"]
    pipeline = (ROOT / "docs" / "pipeline.md").read_text()
    assert "`<manifest stem>.report.json` next to the manifest (`people.csv` -> `people.report.json`" \
        in pipeline
    for doc in [ROOT / "README.md", *(ROOT / "docs").glob("*.md"), ROOT / "usdface" / "commands" / "batch.py",
                ROOT / "usdface" / "api.py"]:
        assert "MANIFEST.report.json" not in doc.read_text(), doc


def test_python_dash_m_usdface_runs_the_cli():
    """``python -m usdface`` (a venv without the console script on PATH) is the ``usdface`` command."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "usdface", "--version"], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0 and proc.stdout.startswith("usdface "), proc.stderr
