"""Small inputs several test modules build: the sample capture read, a Live Link Face CSV written."""

from __future__ import annotations

from pathlib import Path

SAMPLES = Path(__file__).resolve().parents[1] / "sample_assets"
C = SAMPLES / "capture.usda"


def _livelink_csv(path: Path, w, timecodes) -> Path:
    """``w[F, 52]`` (ARKit order) written as Live Link Face writes a take: its column names, the timecodes,
    the head and eye angles at 0."""
    import csv

    from usdface.arkit import ARKIT_NAMES, livelink_name
    from usdface.io.livelink import ANGLE_COLUMNS

    with open(path, "w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(["Timecode", "BlendShapeCount"] + [livelink_name(n) for n in ARKIT_NAMES]
                     + list(ANGLE_COLUMNS))
        for code, row in zip(timecodes, w, strict=True):
            out.writerow([code, 61] + [f"{x:.6f}" for x in row] + ["0"] * len(ANGLE_COLUMNS))
    return path


def _capture():
    from usdface.api import read_capture

    return read_capture(C)
