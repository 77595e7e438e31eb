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


@pytest.fixture(scope="session")
def sample_take(sample_set):
    """A continuous take (:class:`usdface.model.Take`-like, from :func:`usdface.sample.take.make_take`) of the
    sample person, as a phone app would record it: 10 fps, seed 3."""
    import numpy as np

    from usdface.io.usd_capture import read_capture_usd
    from usdface.model import FaceRig
    from usdface.sample.take import make_take

    truth = np.load(sample_set / "truth" / "capture_truth.npz")
    capture = read_capture_usd(sample_set / "capture.usda")
    names = [str(n) for n in truth["names"]]
    person = FaceRig(truth["neutral"], capture.triangles, names, truth["deltas"])
    take, _ = make_take(person, capture.template.subset(names), fps=10, sweep_seconds=0.5, rest_seconds=0.2,
                        seed=3)
    return take
