"""Cold start of ``usdface personalize`` (issues 10/12: dev1 end to end <= 3 s wall on a quiet 2-core
machine).

Runs the command ``--repeats`` times, each in a fresh interpreter with no correspondence cache, and prints one
table: median wall and CPU seconds (user + sys of the child, which includes its BLAS threads), the peak RSS,
and the in-process step timings (``--json`` ``report["timings"]``), beside the load average before and after,
since the machine is shared. A second table lists the slowest imports of one run (``python -X
importtime``)::

    python benchmarks/bench_cold_start.py [--case dev1] [--repeats 5] [--imports 12]

``--case sample`` uses the project's own ``sample_assets`` (no ../shared needed).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from shared_data import BENCH

ROOT = Path(__file__).resolve().parents[1]


def _inputs(case: str) -> tuple[Path, Path]:
    if case == "sample":
        return ROOT / "sample_assets" / "avatar.usda", ROOT / "sample_assets" / "capture.usda"
    return BENCH / case / "avatar.usdc", BENCH / case / "capture"


def runs(case: str, repeats: int) -> dict:
    """``{"wall": [...], "cpu": [...], "rss_mb": [...], "steps": {step: [...]}}`` over fresh processes."""
    avatar, capture = _inputs(case)
    out: dict = {"wall": [], "cpu": [], "rss_mb": [], "steps": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(repeats):
            args = [sys.executable, "-m", "usdface.cli", "personalize", str(avatar), str(capture),
                    "-o", str(Path(tmp) / f"out{r}.usda"), "--json"]
            r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            t = time.perf_counter()
            done = subprocess.run(args, check=True, capture_output=True, text=True, cwd=ROOT)
            out["wall"].append(time.perf_counter() - t)
            r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            out["cpu"].append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)
            out["rss_mb"].append(r1.ru_maxrss / 1024)     # the largest child so far (Linux: KiB)
            for k, v in json.loads(done.stdout)["timings"].items():
                out["steps"].setdefault(k, []).append(v)
    return out


def slowest_imports(case: str, count: int) -> list[tuple[str, float]]:
    """The ``count`` top-level imports of one run with the largest cumulative time (s), ``-X importtime``."""
    avatar, capture = _inputs(case)
    with tempfile.TemporaryDirectory() as tmp:
        err = subprocess.run([sys.executable, "-X", "importtime", "-m", "usdface.cli", "personalize",
                              str(avatar), str(capture), "-o", str(Path(tmp) / "out.usda"), "-q"],
                             check=True, capture_output=True, text=True, cwd=ROOT).stderr
    rows = []
    for line in err.splitlines():
        if not line.startswith("import time:") or "|" not in line:
            continue
        _, cum, name = line.split("|")
        if cum.strip().isdigit() and not name.startswith("  "):          # top level: no indentation
            rows.append((name.strip(), int(cum) / 1e6))
    return sorted(rows, key=lambda r: -r[1])[:count]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", default="dev1" if (BENCH / "dev1").is_dir() else "sample")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--imports", type=int, default=12,
                    help="how many of the slowest imports to list (0: none)")
    args = ap.parse_args(argv)
    if args.case != "sample" and not (BENCH / args.case).is_dir():
        print(f"no bench data at {BENCH / args.case}; try --case sample")
        return 0
    load0 = os.getloadavg()[0]
    r = runs(args.case, args.repeats)
    load1 = os.getloadavg()[0]
    med = statistics.median
    print(f"usdface personalize {args.case}, fresh process, no correspondence cache, median of "
          f"{args.repeats} (load average {load0:.1f} -> {load1:.1f} on {os.cpu_count()} cores)")
    print(f"{'figure':22} {'median':>8} {'min':>8} {'max':>8}")
    for label, key in (("wall s", "wall"), ("CPU s (user+sys)", "cpu"), ("peak RSS MB", "rss_mb")):
        v = r[key]
        print(f"{label:22} {med(v):8.2f} {min(v):8.2f} {max(v):8.2f}")
    for step, v in r["steps"].items():
        print(f"{'  step ' + step + ' s':22} {med(v):8.3f} {min(v):8.3f} {max(v):8.3f}")
    if os.environ.get("PYTHONDONTWRITEBYTECODE"):
        print("note: PYTHONDONTWRITEBYTECODE is set, so a source tree's usdface modules are compiled "
              "again in every run (~0.2 s of the figures above); unset it for an installed package's figure")
    if args.imports:
        print("\nslowest top-level imports of one run (-X importtime, cumulative s; the heavy ones are "
              "imported where first used)")
        for name, sec in slowest_imports(args.case, args.imports):
            print(f"  {name:40} {sec:6.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
