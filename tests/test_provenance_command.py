"""The ``command`` a usdface output records (its provenance) is the command that wrote it, as a shell line
that runs it again: the arguments ``main`` was given (not the host process's ``sys.argv``), quoted."""

from __future__ import annotations

import shlex
from pathlib import Path

from pxr import Sdf

from usdface.cli import main

SAMPLES = Path(__file__).resolve().parents[1] / "sample_assets"


def test_fit_records_its_own_arguments_quoted(tmp_path):
    out = tmp_path / "my rig.usda"
    argv = ["fit", str(SAMPLES / "capture.usda"), "-o", str(out), "--method", "dt", "-q"]
    assert main(argv) == 0
    command = Sdf.Layer.FindOrOpen(str(out)).customLayerData["usdface"]["command"]
    assert shlex.split(command) == ["usdface", *argv]
