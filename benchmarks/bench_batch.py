"""Benchmark ``usdface batch``: throughput (avatars/minute) of the real personalize on the bench cases, run
in-process, on the local process pool, and on a Dask LocalCluster.

Usage::

    python benchmarks/bench_batch.py [--case sample|bench] [--items 4] [--repeat 3] [--jobs 2]
                                     [--bench ../shared/data/bench]

Each run personalizes ``--items`` avatars from scratch into separate outputs: with ``--case bench`` (default
when ../shared is there) dev1, dev2, dev1, ...; with ``--case sample`` the project's own
``sample_assets/avatar.usda`` + ``capture.usda`` every time. Prints a table of the median / min wall-clock
seconds over ``--repeat`` runs and the median throughput (the pool's and the cluster's start-up included: it
is what a batch costs). The machine is shared, so read the median. The Dask row needs ``distributed``. A rate
marked ``*`` is of a batch shorter than ``usdface.pipeline.batch.MIN_RATE_SECONDS``, which ``usdface batch``
states no rate for: give more ``--items`` for issue 12's avatars/minute figure.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
from pathlib import Path

from shared_data import BENCH

from usdface.pipeline.batch import MIN_RATE_SECONDS, read_manifest, run_batch

ROOT = Path(__file__).resolve().parents[1]


def _cases(case: str, bench: Path) -> list[tuple[Path, Path]]:
    if case == "sample":
        return [(ROOT / "sample_assets" / "avatar.usda", ROOT / "sample_assets" / "capture.usda")]
    return [(bench / c / "avatar.usdc", bench / c / "capture") for c in ("dev1", "dev2")
            if (bench / c / "avatar.usdc").exists()]


def _manifest(folder: Path, cases: list[tuple[Path, Path]], items: int) -> Path:
    rows = [{"avatar": str(cases[i % len(cases)][0]), "capture": str(cases[i % len(cases)][1]),
             "output": f"out_{i:02d}.usda"} for i in range(items)]
    path = folder / "manifest.json"
    path.write_text(json.dumps(rows))
    return path


def _run(where: str, cases, items: int, jobs: int) -> tuple[float, int, float]:
    with tempfile.TemporaryDirectory() as tmp:
        manifest = _manifest(Path(tmp), cases, items)
        if where == "dask":
            from distributed import LocalCluster

            with LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True,
                              dashboard_address=None) as cluster:
                report = run_batch(read_manifest(manifest), scheduler=cluster.scheduler_address,
                                   progress=False)
        else:
            report = run_batch(read_manifest(manifest), jobs=1 if where == "in-process" else jobs,
                               progress=False)
        if report.failed:
            print(f"{where}: {len(report.failed)} failed: {report.failed[0].error}", file=sys.stderr)
        cpu = [r.cpu_seconds for r in report.results if r.status == "done"]
        return report.seconds, report.count("done"), statistics.median(cpu) if cpu else 0.0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--items", type=int, default=4)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--bench", type=Path, default=BENCH)
    parser.add_argument("--case", choices=("bench", "sample"))
    parser.add_argument("--only", choices=("in-process", "pool", "dask"), action="append")
    args = parser.parse_args(argv)
    case = args.case or ("bench" if (args.bench / "dev1" / "avatar.usdc").exists() else "sample")
    cases = _cases(case, args.bench)
    if not cases:
        print(f"(bench data not found under {args.bench}: use --case sample)")
        return 0
    rows = []
    for where in args.only or ("in-process", "pool", "dask"):
        runs = [_run(where, cases, args.items, args.jobs) for _ in range(args.repeat)]
        seconds = [s for s, _, _ in runs]
        done = min(d for _, d, _ in runs)
        cpu = statistics.median(c for _, _, c in runs)
        med = statistics.median(seconds)
        rows.append((where, done, med, min(seconds), 60.0 * done / med if med else 0.0, cpu))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"{'where':<12} {'items':>5} {'median s':>9} {'min s':>8} {'avatars/min':>12} {'CPU s/item':>11}   "
          f"({case}, jobs={args.jobs}, repeat={args.repeat}, load {load:.1f} on {os.cpu_count()} CPUs)")
    for where, done, med, low, rate, cpu in rows:
        short = "*" if med < MIN_RATE_SECONDS else " "     # what usdface batch would state no rate for
        print(f"{where:<12} {done:>5} {med:>9.1f} {low:>8.1f} {rate:>11.2f}{short} {cpu:>11.1f}")
    if any(med < MIN_RATE_SECONDS for _, _, med, _, _, _ in rows):
        print(f"* a batch under {MIN_RATE_SECONDS:g} s: its rate is mostly start-up (usdface batch states "
              "none); raise --items")
    return 0


if __name__ == "__main__":
    sys.exit(main())
