"""Cold start: the light commands must not import the heavy numerical stacks (issue 12).

Each case runs the CLI in a fresh interpreter and lists which heavy modules ended up in ``sys.modules``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_assets"
HEAVY = ("open3d", "ortools", "matplotlib", "scipy.spatial", "scipy.sparse", "scipy.optimize", "distributed",
         "dask", "rich")

_PROBE = """
import json, sys
from usdface.cli import main
argv = json.loads(sys.argv[1])
code = 0
if argv is not None:
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
sys.stdout.flush()
print("\\nMODULES " + json.dumps(sorted(m for m in json.loads(sys.argv[2]) if m in sys.modules)))
"""


def _heavy_modules(argv, modules=HEAVY) -> list[str]:
    """The ``modules`` imported after ``usdface.cli.main(argv)`` (``argv`` None: only the import)."""
    out = subprocess.run([sys.executable, "-c", _PROBE, json.dumps(argv), json.dumps(list(modules))],
                         capture_output=True, text=True, check=True, cwd=ROOT).stdout
    return json.loads(out.rsplit("MODULES ", 1)[1])


def test_import_cli_is_light():
    assert _heavy_modules(None) == []


def test_help_is_light():
    assert _heavy_modules(["--help"]) == []


@pytest.mark.parametrize("command", ["inspect", "check"])
def test_inspect_and_check_are_light(command):
    avatar = SAMPLE / "avatar.usda"
    if not avatar.exists():
        pytest.skip("no sample avatar")
    assert _heavy_modules([command, str(avatar)]) == []


def test_probe_detects_an_imported_module():
    """The probe sees what the CLI did import (json, argparse), so an empty list above means something."""
    assert _heavy_modules(["--help"], ("argparse", "json", "open3d")) == ["argparse", "json"]


#: What ``personalize`` never uses (landmark solver, plots, tables, batch schedulers, statistics/optimisers):
#: deferred to where they are used, so the product command does not pay for them (``scipy.stats`` alone cost a
#: cold run 1-2 s for one t quantile, now ``scipy.special.stdtrit``).
PERSONALIZE_UNUSED = ("ortools", "matplotlib", "rich", "dask", "distributed", "scipy.optimize", "scipy.stats")


def test_personalize_skips_the_stacks_it_does_not_use():
    avatar, capture = SAMPLE / "avatar.usda", SAMPLE / "capture.usda"
    if not (avatar.exists() and capture.exists()):
        pytest.skip("no sample avatar/capture")
    used = ("scipy.sparse", "scipy.spatial")     # what it does use: proves the probe saw a real run
    found = _heavy_modules(["personalize", str(avatar), str(capture), "--dry-run", "-q"],
                           PERSONALIZE_UNUSED + used)
    assert found == sorted(used)
