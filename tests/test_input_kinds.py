"""A file given where another kind of file goes (a take or a capture as the avatar, JSON or OBJ where USD
goes, a folder of takes, a missing file) is named for what it is and for what the command reads, with exit
status 2."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cli_helpers import _no_traceback, _usdface

import usdface.io  # noqa: F401  (registers the schemas before a test opens a stage)
from usdface.cli import main
from usdface.io.livelink import write_livelink_csv

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


def test_errors_name_what_the_file_is(tmp_path, capsys):
    """--correspondence naming the avatar said 'delete it'; a capture folder given as the avatar said only
    'is a folder'; a fitted rig given as the capture said 'not a usdface capture (no /Capture with ...)'."""
    from usdface.cli import main

    avatar = tmp_path / "avatar.usda"
    avatar.write_bytes(A.read_bytes())
    assert main(["personalize", str(avatar), str(C), "-o", str(tmp_path / "p.usda"),
                 "--correspondence", str(avatar)]) == 2
    err = capsys.readouterr().err
    assert "names one of this run's inputs" in err and "delete" not in err
    assert avatar.read_bytes() == A.read_bytes()
    cap = tmp_path / "cap"
    (cap / "train").mkdir(parents=True)
    assert main(["personalize", str(cap), str(A), "-o", str(tmp_path / "q.usda")]) == 2
    assert "arguments swapped?" in capsys.readouterr().err
    assert main(["personalize", str(A), str(A), "-o", str(tmp_path / "r.usda")]) == 2
    assert "this is a rig" in capsys.readouterr().err


def test_an_avatar_given_as_the_take_is_named_an_avatar(tmp_path, capsys):
    """'personalize AVATAR CAPTURE --take AVATAR' said only 'no mesh with time-sampled points and no
    SkelAnimation ...': the take's kind is judged as batch and Pyblish judge it (io.take.check_take_path),
    naming an avatar as such, before any work."""
    assert main(["personalize", str(A), str(C), "--take", str(A), "-o", str(tmp_path / "p.usda")]) == 2
    err = capsys.readouterr().err
    assert "this is an avatar, not a take" in err and "give a take" in err
    assert list(tmp_path.iterdir()) == []


def test_an_output_folder_asks_for_a_file_inside_it(tmp_path, capsys):
    """'fit CAP -o sub/' (an existing folder) said 'must end in .usda ... (fix: name it e.g. sub.usda)', a
    sibling of the folder; it says the path is a folder and names a file inside it."""
    (tmp_path / "sub").mkdir()
    assert main(["fit", str(C), "-o", str(tmp_path / "sub"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "fit rig file path is a folder" in err and f"e.g. {tmp_path / 'sub' / 'out.usda'}" in err
    assert list((tmp_path / "sub").iterdir()) == []


def test_a_non_usd_file_where_usd_is_expected_is_named_as_such(tmp_path, capsys):
    """The retarget map (``map.json``) given to ``render --heatmap``, ``inspect`` or ``check``, or an exported
    OBJ to ``export``, said USD's "Cannot determine file format for @map.json@ (fix: check that it is a
    valid USD layer (usdcat FILE))": the message names the file's type and asks for the USD file."""
    from usdface.cli import main

    bad = tmp_path / "map.json"
    bad.write_text('{"format": "usdface.retarget/1"}')
    obj = tmp_path / "neutral.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    for args in (["inspect", str(bad)], ["check", str(bad)], ["export", str(obj), "--gltf",
                                                                 str(tmp_path / "o.glb")]):
        assert main(args) == 2
        err = capsys.readouterr().err
        assert "Cannot determine file format" not in err and "where a USD" in err and "USD USD" not in err
        assert "pass the USD file here" in err
    assert not (tmp_path / "o.glb").exists()


def test_a_folder_of_live_link_csvs_is_not_one_take(tmp_path, capsys):
    """'usdface inspect livelinkface/' (four CSVs, no meshes) said 'expected one Live Link .csv in the take
    folder, found 4 (fix: put exactly one Live Link Face CSV next to the OBJ frames)': there are no frames."""
    for name in ("a.csv", "b.csv"):
        write_livelink_csv(tmp_path / name, ["jawOpen"], np.full((4, 1), 0.5), np.arange(4) / 60)
    for args in (["inspect", str(tmp_path)], ["capture", "select", str(tmp_path)]):
        assert main(args) == 2
        err = capsys.readouterr().err
        assert "a folder of 2 Live Link CSVs (a.csv, b.csv) and no OBJ frames" in err, err
        assert f"pass the CSV files themselves, e.g. {tmp_path / 'a.csv'}" in err


def test_capture_import_refuses_a_take(tmp_path, capsys):
    """'capture import take_dir/ -o c.usda' wrote every frame of the take as a capture's training frame: the
    file then fitted as picked frames (no frame weighting; reg 0.0009 against the take's 0.045) and 'fit
    c.usda --every 2' said it 'holds frames picked one per shape'."""
    from test_take_select import grid_rigs

    from usdface import api
    from usdface.errors import CaptureError
    from usdface.io.take import write_take_folder, write_take_usd
    from usdface.sample.take import make_take

    person, template = grid_rigs(n=4)
    take, _ = make_take(person, template, shapes=["jawOpen", "eyeBlinkLeft"], seed=1)
    for src in (write_take_usd(take, tmp_path / "take.usdc"), write_take_folder(take, tmp_path / "take_dir")):
        out = tmp_path / "c.usda"
        assert main(["capture", "import", str(src), "-o", str(out), "-q"]) == 2
        err = capsys.readouterr().err
        assert "a take, not a capture" in err and "usdface capture select TAKE" in err, err
        assert not out.exists()
        with pytest.raises(CaptureError, match="a take, not a capture"):
            api.import_capture_folder(src, out)
        assert not out.exists()


def test_capture_passed_as_avatar_is_named(capfd):
    for argv in (["personalize", str(SAMPLES / "capture.usda"), str(SAMPLES / "capture.usda"), "--dry-run"],
                 ["landmarks", str(SAMPLES / "capture.usda")]):
        assert main(argv) == 2
        err = capfd.readouterr().err
        assert "usdface capture" in err and "not an avatar" in err and "/Capture" in err


@pytest.mark.parametrize("command", ["personalize", "render"])
def test_anim_import_take_passed_as_avatar_is_named_a_take(livelink_csv, sample_dir, tmp_path, command):
    take = tmp_path / "take.usdc"
    assert _usdface("anim", "import", livelink_csv, "-o", take, "-q", cwd=tmp_path).returncode == 0
    args = {"personalize": [take, sample_dir / "capture.usda", "--dry-run"],
            "render": [take, "-o", "x.png"]}[command]     # inspect summarises it (test_inspect)
    res = _usdface(command, *args, cwd=tmp_path)
    _no_traceback(res)
    assert "this is a take" in res.stderr and "not an avatar" in res.stderr, res.stderr
    assert "SkelRoot" not in res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["take.usdc"]


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


@pytest.mark.parametrize("argv, needle", [
    (["review", "MISSING.usda"], "MISSING.usda: USD file not found"),
    (["review", "MISSING.usda", "-o", "r.html"], "MISSING.usda: USD file not found"),
    (["review", str(A), "--take", "nope.csv"], "nope.csv: take not found"),
    (["personalize", "MISSING.usda", str(C)], "MISSING.usda: avatar not found"),
    (["personalize", "MISSING.usda", str(C), "--review"], "MISSING.usda: avatar not found"),
    (["personalize", str(A), "MISSING", "--dry-run"], "MISSING: capture not found"),
    (["personalize", str(A), str(C), "--take", "nope.csv", "-o", "p.usda"], "nope.csv: take not found"),
    (["landmarks", "MISSING.usda", "-o", "l.usda"], "MISSING.usda: avatar not found"),
    (["export", "MISSING.usda", "--gltf", "a.glb"], "MISSING.usda: layer not found"),
    (["fit", "MISSING", "-o", "f.usda"], "MISSING: capture not found"),
    (["capture", "import", "MISSING", "-o", "c.usda"], "MISSING: capture not found"),
])
def test_a_missing_input_is_said_before_an_output_that_cannot_be_written(tmp_path, monkeypatch, capsys,
                                                                           read_only_folder, argv, needle):
    """A user trial: 'review MISSING.usda' in a folder one cannot write to said that the page could not be
    written there, of a page that could never be made; the missing input is the first thing said (review,
    personalize with its layer and --review page, and the other commands that read one)."""
    monkeypatch.chdir(tmp_path)
    read_only_folder(tmp_path)
    read_only_folder(".")                          # as the outputs named relative to it are probed
    assert main([*argv, "-q"]) == 2
    err = capsys.readouterr().err
    assert needle in err and "cannot be written" not in err, err
    assert list(tmp_path.iterdir()) == []
    assert main(["personalize", str(A), str(C), "-q"]) == 2    # the folder is one that cannot be written
    assert "cannot be written in " in capsys.readouterr().err
