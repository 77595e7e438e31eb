"""``usdface personalize`` / ``usdface retarget`` command lines on the dev1 bench case."""

from __future__ import annotations

import pytest

from usdface.cli import main

pytestmark = pytest.mark.shared


def test_personalize_dry_run_writes_nothing(bench, tmp_path, capsys):
    out = tmp_path / "p.usda"
    code = main(["personalize", str(bench / "dev1" / "avatar.usdc"), str(bench / "dev1" / "capture"),
                 "-o", str(out), "--dry-run", "-q", "--correspondence", str(tmp_path / "c.npz")])
    text = capsys.readouterr().out
    assert code == 0
    assert not out.exists()
    assert "dry run:" in text and "/Avatar/Head/jawOpen: max" in text
    assert "registration: scale" in text
    assert (tmp_path / "c.npz").exists()


def test_retarget_writes_csv_and_refuses_to_overwrite(bench, tmp_path, capsys):
    out = tmp_path / "map.csv"
    args = ["retarget", str(bench / "dev1" / "avatar.usdc"), str(bench / "dev1" / "capture"), "-o", str(out),
            "-q"]
    assert main(args) == 0
    rows = out.read_text().splitlines()
    assert rows[0].startswith("source,") and len(rows) == 52  # header + 51 capture shapes
    assert main(args) == 2  # exists, no --force
    assert "--force" in capsys.readouterr().err


def test_personalize_bad_input_exit_2(tmp_path, capsys):
    code = main(["personalize", str(tmp_path / "missing.usdc"), str(tmp_path / "nocapture"), "-o",
                 str(tmp_path / "o.usda"), "-q"])
    assert code == 2
    assert "missing.usdc" in capsys.readouterr().err
