"""Benchmark of the personalized-shape fit on the bench captures (../shared/data/bench/dev1, dev2).

Prints (1) accuracy per method/option: test RMSE and mean max error (eq. 5, mm), error against the true shapes
(mm) and the issue-7 acceptance ratios; (2) timings, median of ``--repeat`` runs, incl. the DT step.

    python benchmarks/bench_fit.py [--cases dev1,dev2] [--repeat 7]

Timings are noisy on a shared machine: run it when the machine is quiet. ``fit_personalized_shapes`` limits
BLAS to one thread itself (threadpoolctl), which avoids oversubscription for the many tiny (K x K) problems.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from usdface.io import read_capture
from usdface.personalize import evaluate_rig, fit_personalized_shapes, truth_error

BENCH = Path(__file__).resolve().parents[2] / "shared" / "data" / "bench"

RUNS = {
    "dt": {"method": "dt"},
    "ebfr": {"method": "ebfr"},
    "menzel": {"method": "menzel"},
    "menzel --reg paper": {"method": "menzel", "reg": "paper", "align": False, "reweight": False},
    "menzel auto, no options": {"method": "menzel", "align": False, "reweight": False},
    "menzel auto, prior=dt, no options": {"method": "menzel", "prior": "dt", "align": False,
                                          "reweight": False},
    "menzel + align": {"method": "menzel", "reweight": False},
    "menzel + reweight": {"method": "menzel", "align": False},
    "laplacian": {"method": "laplacian"},
}


def accuracy(case: str, console: Console) -> dict:
    cap = read_capture(BENCH / case / "capture")
    truth = np.load(BENCH / case / "truth" / "capture_truth.npz")
    true = truth["deltas"][[list(truth["names"]).index(n) for n in cap.names]]
    rows = {"template": {"truth": truth_error(cap.template.deltas, true)}}
    generic = type(cap.template)(cap.neutral, cap.triangles, cap.names, cap.template.deltas)
    tr = evaluate_rig(generic, cap.test)
    rows["template"].update(rmse=tr["mean_rmse_mm"], max=tr["mean_max_mm"])
    for name, kw in RUNS.items():
        res = fit_personalized_shapes(cap, **kw)
        ev = evaluate_rig(res.rig, cap.test)
        rows[name] = {"rmse": ev["mean_rmse_mm"], "max": ev["mean_max_mm"],
                      "truth": truth_error(res.rig.deltas, true), "reg": res.info.get("reg"),
                      "alpha": res.info.get("prior_alpha")}
    table = Table(title=f"{case}: accuracy (test frames: eq. 5; truth: RMSE vs true shapes)")
    for col in ("run", "test RMSE mm", "mean max mm", "vs truth mm", "truth / template", "reg",
                "prior DT share"):
        table.add_column(col)
    for name, r in rows.items():
        table.add_row(name, f"{r['rmse']:.4f}", f"{r['max']:.4f}", f"{r['truth']:.4f}",
                      f"{r['truth'] / rows['template']['truth']:.3f}",
                      "" if r.get("reg") is None else f"{r['reg']:.3g}",
                      "" if r.get("alpha") is None else f"{r['alpha']:.2f}")
    console.print(table)
    m, dt, eb, paper = rows["menzel"], rows["dt"], rows["ebfr"], rows["menzel --reg paper"]
    tm = rows["template"]["truth"]
    console.print(f"{case} ratios: menzel/dt RMSE {m['rmse'] / dt['rmse']:.3f}, menzel/ebfr RMSE "
                  f"{m['rmse'] / eb['rmse']:.3f}, menzel/dt max {m['max'] / dt['max']:.3f}, menzel/template "
                  f"truth {m['truth'] / tm:.3f}; paper: /dt {paper['rmse'] / dt['rmse']:.3f}, "
                  f"/ebfr {paper['rmse'] / eb['rmse']:.3f}, max/dt {paper['max'] / dt['max']:.3f}, "
                  f"truth/template {paper['truth'] / tm:.3f}")
    return rows


def timing(case: str, repeat: int, console: Console) -> None:
    cap = read_capture(BENCH / case / "capture")
    runs = {
        "menzel fixed reg (incl. DT)": {"method": "menzel", "reg": 1e-3, "align": False, "reweight": False},
        "menzel fixed reg + align + reweight": {"method": "menzel", "reg": 1e-3},
        "menzel auto, no options": {"method": "menzel", "align": False, "reweight": False},
        "menzel default (auto + align + reweight)": {"method": "menzel"},
        "ebfr": {"method": "ebfr", "align": False},
        "dt": {"method": "dt"},
        "laplacian fixed reg": {"method": "laplacian", "reg": 1e-3, "align": False, "reweight": False},
    }
    med = {}
    table = Table(title=f"{case}: seconds, median of {repeat} ({len(cap.neutral)} vertices, {len(cap.names)} "
                        f"shapes, {len(cap.train)} training frames)")
    for col in ("run", "median s", "min s", "DT s (median)"):
        table.add_column(col)
    for name, kw in runs.items():
        ts, dts = [], []
        for _ in range(repeat):
            t0 = time.perf_counter()
            res = fit_personalized_shapes(cap, **kw)
            ts.append(time.perf_counter() - t0)
            dts.append(res.info["timings"]["dt"])
        med[name] = statistics.median(ts)
        table.add_row(name, f"{med[name]:.4f}", f"{min(ts):.4f}", f"{statistics.median(dts):.4f}")
    console.print(table)
    ratio = med["ebfr"] / med["menzel fixed reg (incl. DT)"]
    console.print(f"{case}: ebfr / menzel(fixed reg) = {ratio:.1f}x")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--cases", default="dev1,dev2")
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--no-accuracy", action="store_true")
    ap.add_argument("--no-timing", action="store_true")
    args = ap.parse_args()
    console = Console(width=150)
    if not BENCH.is_dir():
        console.print(f"no bench data at {BENCH}; nothing to do")
        return
    for case in args.cases.split(","):
        if not args.no_accuracy:
            accuracy(case, console)
        if not args.no_timing:
            timing(case, args.repeat, console)


if __name__ == "__main__":
    main()
