"""The CLI's stdout when it cannot take output: closed (not a failure) or on a full disk (said as stdout, not
as the output file)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from cli_helpers import _env


@pytest.mark.parametrize("closed", [(1,), (0, 1, 2)])
def test_a_closed_stdout_is_not_a_failure(samples, tmp_path, closed):
    """Started with stdout closed (``usdface ... >&-``, a launcher that closes it), Python's sys.stdout is
    None and the final flush raised AttributeError: a traceback and exit status 1 after the work was done.
    The program puts /dev/null in place of a closed standard stream."""
    def close():
        for fd in closed:
            os.close(fd)

    res = subprocess.run([sys.executable, "-m", "usdface", "inspect", str(samples / "avatar.usda")],
                         stdout=subprocess.DEVNULL if 1 not in closed else None,
                         stderr=subprocess.PIPE if 2 not in closed else None,
                         env=_env(), timeout=600, preexec_fn=close)
    assert res.returncode == 0, res.stderr
    assert not res.stderr or b"Traceback" not in res.stderr


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
@pytest.mark.parametrize("json_flag", [[], ["--json"]])
def test_stdout_on_a_full_disk_is_said_as_stdout(samples, tmp_path, json_flag):
    """``usdface personalize ... > /dev/full`` wrote the layer, then said 'No space left on device (fix:
    ... write the output elsewhere (-o))', pointing at the output; with --json it ended in a traceback (the
    error document failed on stdout too), exit 1. It says stdout, exit 2, and the layer stands."""
    out = tmp_path / "p.usda"
    with open("/dev/full", "w") as full:
        res = subprocess.run([sys.executable, "-m", "usdface", "personalize", str(samples / "avatar.usda"),
                              str(samples / "capture.usda"), "-o", str(out), "-q", *json_flag],
                             stdout=full, stderr=subprocess.PIPE, text=True, env=_env(), timeout=600)
    assert res.returncode == 2, res.stderr[-2000:]
    assert "Traceback" not in res.stderr
    assert "could not write to stdout" in res.stderr and "the outputs were written" in res.stderr
    assert out.exists()
