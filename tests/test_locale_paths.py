"""File names under a locale that is not UTF-8: USD takes paths as UTF-8, Python decodes file names in the
locale's encoding. A name with a non-ASCII character (in its folder too) is refused before any work, naming
the path and the way out (UTF-8 mode or a UTF-8 locale), instead of USD failing on other bytes."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from cli_helpers import _env

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"


def _usdface_ascii_locale(*args, cwd):
    """``usdface ARGS`` with file names decoded as ASCII (the C locale without Python's UTF-8 mode or locale
    coercion, as under ``LANG=en_US`` with ISO-8859-1 the bytes decode to other characters)."""
    env = {**_env(), "LC_ALL": "C", "LANG": "C", "PYTHONUTF8": "0", "PYTHONCOERCECLOCALE": "0"}
    return subprocess.run([sys.executable, "-c", "import sys; from usdface.cli import main; sys.exit(main())",
                           *map(str, args)], cwd=cwd, capture_output=True, text=True, env=env, timeout=600,
                          errors="replace")


@pytest.fixture
def zoe(tmp_path):
    if sys.platform == "win32":
        pytest.skip("file names are UTF-16 on Windows")
    folder = tmp_path / "zoë"
    folder.mkdir()
    shutil.copy(SAMPLES / "avatar.usda", folder / "avatar.usda")
    return folder


def test_an_input_under_a_non_ascii_folder_is_refused_naming_the_locale(zoe, tmp_path):
    """It was 'USD cannot open it: Failed to open layer' for a valid file (or a UnicodeEncodeError
    traceback)."""
    res = _usdface_ascii_locale("inspect", zoe / "avatar.usda", cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    assert "Traceback" not in res.stderr and "Failed to open layer" not in res.stderr
    assert "cannot be given to USD" in res.stderr and "PYTHONUTF8=1" in res.stderr, res.stderr


def test_an_output_in_a_non_ascii_folder_is_refused_before_any_work(zoe, tmp_path):
    """The output failed after the whole fit, naming a hidden temporary file ('No such file or
    directory'), or ended in a UnicodeEncodeError traceback."""
    res = _usdface_ascii_locale("personalize", SAMPLES / "avatar.usda", SAMPLES / "capture.usda", "-o",
                                "p.usda", cwd=zoe)
    assert res.returncode == 2, res.stderr
    assert "Traceback" not in res.stderr and ".tmp" not in res.stderr
    assert "output layer path cannot be given to USD" in res.stderr, res.stderr
    assert "fit" not in res.stderr                      # refused before the work (no step ran)
    assert sorted(p.name for p in zoe.iterdir()) == ["avatar.usda"]


def test_ascii_paths_work_under_the_same_locale(tmp_path):
    res = _usdface_ascii_locale("inspect", SAMPLES / "avatar.usda", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
