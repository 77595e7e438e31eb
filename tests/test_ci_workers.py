"""CI's pytest-xdist worker count (``.ci/xdist_workers.py``): one a core, capped by the memory available."""

from __future__ import annotations

import runpy
from pathlib import Path

from usdface.resources import available_memory_mb, pool_size, usable_cores

ROOT = Path(__file__).resolve().parents[1]


def test_ci_runs_no_more_workers_than_the_memory_holds():
    """Stop 43: ``.ci/run`` ran the suite with ``-n auto``, a worker per core whatever the memory (a 16-core
    runner limited to 4 GB would start 16 workers of ~1 GB). The count is the cores, capped at the memory
    available over a worker's ~1 GB, never below one (tests/test_resources.py: ``pool_size``); ``.ci/run``
    passes it."""
    script = ROOT / ".ci" / "xdist_workers.py"
    ns = runpy.run_path(str(script))
    assert ns["WORKER_MB"] == 1024
    cores, memory = usable_cores(), available_memory_mb()
    assert ns["workers"]() == pool_size(cores, memory, 1024)
    assert 1 <= ns["workers"]() <= cores
    run = [line for line in (ROOT / ".ci" / "run").read_text().splitlines() if "pytest" in line
           and not line.startswith("#")]
    assert len(run) == 1 and "-n auto" not in run[0]
    assert '-n "$(.venv/bin/python .ci/xdist_workers.py)"' in run[0]
