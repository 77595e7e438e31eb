"""Helpers for the workflow tests: run the installed ``usdface`` command as a user would (a subprocess, in a
temporary working folder), and check what a user relies on: the exit status, that the output opens in USD and
passes ``usdface check``, and that no input file changed by a single byte."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import usdface.io  # noqa: F401  (schemas first: a stage opened before them is the DCC case, tested on its own)

ROOT = Path(__file__).resolve().parents[2]
SHARED = Path(os.environ.get("USDFACE_SHARED", ROOT.parent / "shared"))
BENCH = SHARED / "data" / "bench"


def usdface_cmd() -> list[str]:
    """The ``usdface`` console script of this environment (the one a user runs), else ``python -m``."""
    script = Path(sys.executable).with_name("usdface")
    if script.exists():
        return [str(script)]
    return [sys.executable, "-c", "import sys; from usdface.cli import main; sys.exit(main())"]


def run(*args, cwd, ok=True, timeout=600) -> subprocess.CompletedProcess:
    """Run ``usdface ARGS`` in ``cwd``; with ``ok`` assert exit 0 and no traceback."""
    env = dict(os.environ, PYTHONWARNINGS="default", COLUMNS="100")
    proc = subprocess.run(usdface_cmd() + [str(a) for a in args], cwd=cwd, capture_output=True, text=True,
                          env=env, timeout=timeout)
    if ok:
        assert proc.returncode == 0, f"usdface {' '.join(map(str, args))} -> {proc.returncode}\n{proc.stderr}"
        assert "Traceback" not in proc.stderr, proc.stderr
    return proc


def digest(*paths) -> dict:
    """sha256 of every file under ``paths`` (files or folders), to prove inputs are unchanged."""
    out = {}
    for p in map(Path, paths):
        files = sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p]
        for f in files:
            out[str(f)] = hashlib.sha256(f.read_bytes()).hexdigest()
    return out


def assert_valid_usd(path, checked=True) -> None:
    """``path`` opens in USD with a default prim, and ``usdface check`` finds no error in it."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(path))
    assert stage and stage.GetDefaultPrim(), f"{path}: does not open or has no defaultPrim"
    if checked:
        errors = [i for i in usdface.check(path) if i.severity == "error"]
        assert not errors, f"{path}: {errors}"


def no_temp_left(folder) -> None:
    left = [p.name for p in Path(folder).rglob(".*") if ".tmp" in p.name]
    assert not left, f"temporary files left behind: {left}"
