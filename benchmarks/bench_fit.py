"""Benchmark of the personalized-shape fit on the bench captures (../shared/data/bench/dev1-dev3) and the
project's sample capture (``sample``).

Prints (1) accuracy per method/option: test RMSE and mean max error (eq. 5, mm; a fit that read its shapes'
amplitudes on the test frames, the default, scores each frame with the readings of the others), error
against the true shapes (mm) and the issue-7 acceptance ratios; (2) timings, median of ``--repeat`` runs,
incl. the DT step.

    python benchmarks/bench_fit.py [--cases dev1,dev2,dev3,sample] [--repeat 7]

dev3 also runs the fit with an avatar prior: a stand-in for the avatar's generic shapes sampled on the
capture (dev1's template - the same avatar's rig on the same capture topology - rotated onto dev3's neutral;
needs dev1).

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
from shared_data import BENCH

from usdface.io import read_capture
from usdface.personalize import evaluate_rig, fit_personalized_shapes, truth_error
from usdface.personalize.api import left_out_scale

SAMPLE = Path(__file__).resolve().parents[1] / "sample_assets"

RUNS = {
    "dt": {"method": "dt"},
    "ebfr": {"method": "ebfr"},
    "ebfr tuned (beta auto)": {"method": "ebfr", "beta": "auto"},
    "menzel": {"method": "menzel"},
    "menzel --reg paper": {"method": "menzel", "reg": "paper", "align": False, "reweight": False},
    "menzel auto, no options": {"method": "menzel", "align": False, "reweight": False, "amplitude": False},
    "menzel auto, prior=dt, no options": {"method": "menzel", "prior": "dt", "align": False,
                                          "reweight": False, "amplitude": False},
    "menzel + align": {"method": "menzel", "reweight": False, "amplitude": False},
    "menzel + reweight": {"method": "menzel", "align": False, "amplitude": False},
    "menzel + amplitude": {"method": "menzel", "align": False, "reweight": False},
    "menzel, no amplitude": {"method": "menzel", "amplitude": False},
    "laplacian": {"method": "laplacian"},
}


def load(case: str):
    """(capture, truth npz) of a bench case or of the sample (``case="sample"``)."""
    if case == "sample":
        return read_capture(SAMPLE / "capture.usda"), np.load(SAMPLE / "truth" / "capture_truth.npz")
    return read_capture(BENCH / case / "capture"), np.load(BENCH / case / "truth" / "capture_truth.npz")


def avatar_prior_standin(cap):
    """dev1's template rotated onto ``cap``'s neutral (same avatar, same capture topology), or None."""
    from usdface.personalize.align import kabsch

    if not (BENCH / "dev1").is_dir():
        return None
    c1 = read_capture(BENCH / "dev1" / "capture")
    if c1.names != cap.names or c1.neutral.shape != cap.neutral.shape:
        return None
    R, _ = kabsch(c1.template.neutral[None], cap.neutral)
    return np.einsum("ij,knj->kni", R[0], c1.template.deltas)


def accuracy(case: str, console: Console) -> dict:
    cap, truth = load(case)
    true = truth["deltas"][[list(truth["names"]).index(n) for n in cap.names]]
    rows = {"template": {"truth": truth_error(cap.template.deltas, true)}}
    generic = type(cap.template)(cap.neutral, cap.triangles, cap.names, cap.template.deltas)
    tr = evaluate_rig(generic, cap.test)
    rows["template"].update(rmse=tr["mean_rmse_mm"], max=tr["mean_max_mm"])
    runs = dict(RUNS)
    if case == "dev3":
        prior = avatar_prior_standin(cap)
        if prior is not None:
            runs["menzel + avatar prior (stand-in)"] = {"method": "menzel", "avatar_prior": prior}
    for name, kw in runs.items():
        res = fit_personalized_shapes(cap, **kw)
        ev = evaluate_rig(res.rig, cap.test, left_out_scale(res, cap.test))     # cross-fitted (amplitude)
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
    et = rows["ebfr tuned (beta auto)"]
    console.print(f"{case}: tuned vs tuned - menzel / ebfr tuned RMSE {m['rmse'] / et['rmse']:.3f} "
                  f"(issue 13: <= 0.75), menzel paper / ebfr fixed {paper['rmse'] / eb['rmse']:.3f}, menzel "
                  f"paper / ebfr tuned {paper['rmse'] / et['rmse']:.3f}; default vs CV only (truth) "
                  f"{m['truth']:.4f} vs {rows['menzel auto, no options']['truth']:.4f}")
    cv_only = rows["menzel auto, no options"]["truth"]
    ok = "yes" if m["truth"] <= cv_only + 1e-9 else "NO"
    console.print(f"{case}: issue 13 acceptance - default truth {m['truth']:.4f} mm <= CV-only "
                  f"{cv_only:.4f} mm: {ok}; truth / template {m['truth'] / tm:.3f}")
    console.print(f"{case} ratios: menzel/dt RMSE {m['rmse'] / dt['rmse']:.3f}, menzel/ebfr RMSE "
                  f"{m['rmse'] / eb['rmse']:.3f}, menzel/dt max {m['max'] / dt['max']:.3f}, menzel/template "
                  f"truth {m['truth'] / tm:.3f}; paper: /dt {paper['rmse'] / dt['rmse']:.3f}, "
                  f"/ebfr {paper['rmse'] / eb['rmse']:.3f}, max/dt {paper['max'] / dt['max']:.3f}, "
                  f"truth/template {paper['truth'] / tm:.3f}")
    return rows


def timing(case: str, repeat: int, console: Console, laplacian: bool = True) -> None:
    cap = load(case)[0]
    runs = {
        "menzel fixed reg (incl. DT)": {"method": "menzel", "reg": 1e-3, "align": False, "reweight": False,
                                        "amplitude": False},
        "menzel fixed reg + align + reweight": {"method": "menzel", "reg": 1e-3},
        "menzel auto, no options": {"method": "menzel", "align": False, "reweight": False,
                                    "amplitude": False},
        "menzel default (auto + align + reweight)": {"method": "menzel"},
        # what ``personalize`` runs: the default plus the weights' sensitivity, noise and leak
        "menzel default + sensitivity (personalize)": {"method": "menzel", "sensitivity": True},
        "ebfr": {"method": "ebfr", "align": False},
        "dt": {"method": "dt"},
    }
    if laplacian:
        runs["laplacian fixed reg"] = {"method": "laplacian", "reg": 1e-3, "align": False, "reweight": False}
    med = {}
    table = Table(title=f"{case}: CPU seconds, median of {repeat} ({len(cap.neutral)} vertices, "
                        f"{len(cap.names)} shapes, {len(cap.train)} training frames)")
    for col in ("run", "median CPU s", "min CPU s", "DT s (median, wall)"):
        table.add_column(col)
    for name, kw in runs.items():
        ts, dts = [], []
        for _ in range(repeat):
            t0 = time.process_time()
            res = fit_personalized_shapes(cap, **kw)
            ts.append(time.process_time() - t0)
            dts.append(res.info["timings"]["dt"])
        med[name] = statistics.median(ts)
        table.add_row(name, f"{med[name]:.4f}", f"{min(ts):.4f}", f"{statistics.median(dts):.4f}")
    console.print(table)
    ratio = med["ebfr"] / med["menzel fixed reg (incl. DT)"]
    console.print(f"{case}: ebfr / menzel(fixed reg) = {ratio:.1f}x")
    default = med["menzel default (auto + align + reweight)"]
    fixed = med["menzel fixed reg (incl. DT)"]
    console.print(f"{case}: issue 12/13 acceptance - default fit {default:.3f} CPU-s (target <= 0.1): "
                  f"{'yes' if default <= 0.1 else 'NO'}; {default / fixed:.1f}x the fixed-reg fit, "
                  f"{default / med['dt']:.1f}x DT alone")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--cases", default="dev1,dev2,dev3,sample")
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--no-accuracy", action="store_true")
    ap.add_argument("--no-timing", action="store_true")
    ap.add_argument("--no-laplacian", action="store_true", help="skip the (slow) Laplacian timing")
    args = ap.parse_args()
    console = Console(width=150)
    for case in args.cases.split(","):
        if case != "sample" and not (BENCH / case).is_dir():
            console.print(f"no bench data at {BENCH / case}; skipped")
            continue
        if not args.no_accuracy:
            accuracy(case, console)
        if not args.no_timing:
            timing(case, args.repeat, console, laplacian=not args.no_laplacian)


if __name__ == "__main__":
    main()
