"""Where the benchmarks find the product owner's material: ``$USDFACE_SHARED`` when set (as the tests read
it), else ``../shared`` beside the project. A worktree or clone elsewhere points at it with the variable."""

from __future__ import annotations

import os
from pathlib import Path

SHARED = Path(os.environ.get("USDFACE_SHARED") or Path(__file__).resolve().parents[2] / "shared")
BENCH = SHARED / "data" / "bench"
