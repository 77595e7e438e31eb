"""Defects found by a technical director's second trial (session 29): takes, landmarks, review, inspect."""

from __future__ import annotations

import numpy as np

from usdface.cli import main
from usdface.io.livelink import write_livelink_csv


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


