"""Fixtures of the workflow tests (helpers in ``wfutil.py``)."""

from __future__ import annotations

from pathlib import Path

import pytest
from wfutil import BENCH, run


@pytest.fixture(scope="session")
def sample_set(tmp_path_factory) -> Path:
    """``usdface sample DIR --folder`` once per session: avatar.usda, capture.usda, capture/, truth/."""
    out = tmp_path_factory.mktemp("wf") / "s"
    run("sample", out, "--folder", cwd=out.parent)
    return out


@pytest.fixture
def bench_case():
    if not (BENCH / "dev1" / "avatar.usdc").exists():
        pytest.skip("../shared data not present")
    return BENCH
