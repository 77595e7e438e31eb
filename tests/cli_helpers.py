"""Running the ``usdface`` command as a user runs it, in a subprocess: the command, its environment, and the
check that a refusal is one line (exit status 2) with no traceback."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env["USDFACE_PROGRESS"] = "off"
    return env


def _usdface(*args, cwd):
    exe = Path(sys.executable).with_name("usdface")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-c", "import sys; from usdface.cli import main; "
                                                                  "sys.exit(main())"]
    return subprocess.run(cmd + [str(a) for a in args], cwd=cwd, capture_output=True, text=True, timeout=600)


def _no_traceback(res) -> None:
    assert "Traceback" not in res.stderr, res.stderr
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
