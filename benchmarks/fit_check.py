"""Regression check for the fit's speed work: the default fit's shapes (and decisions) on the bench cases and
the sample must not change.

    python benchmarks/fit_check.py save DIR      # before: fitted deltas[K,n,3] and decisions per case
    python benchmarks/fit_check.py compare DIR   # after: largest |difference| per case (target <= 1e-10 m)

Also prints the truth error (mm, vs ``truth/capture_truth.npz``) and the CPU seconds of one default fit.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from bench_fit import BENCH, load

from usdface.personalize import fit_personalized_shapes, truth_error

TOLERANCE_M = 1e-10


def decisions(info: dict) -> dict:
    return {"reg": info["reg"], "prior_alpha": info["prior_alpha"],
            "align": info.get("align", {}).get("applied"),
            "reweight": info.get("reweight", {}).get("applied"),
            "weight_sigma": info.get("reweight", {}).get("weight_sigma")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("mode", choices=("save", "compare"))
    ap.add_argument("directory", type=Path)
    ap.add_argument("--cases", default="sample,dev1,dev2,dev3")
    args = ap.parse_args()
    args.directory.mkdir(parents=True, exist_ok=True)
    worst = 0.0
    for case in args.cases.split(","):
        if case != "sample" and not (BENCH / case).is_dir():
            print(f"{case}: no bench data, skipped")
            continue
        cap, truth = load(case)
        true = truth["deltas"][[list(truth["names"]).index(n) for n in cap.names]]
        t0 = time.process_time()
        res = fit_personalized_shapes(cap)
        cpu = time.process_time() - t0
        dec = decisions(res.info)
        line = (f"{case}: truth {truth_error(res.rig.deltas, true):.5f} mm, {cpu:.3f} CPU s, "
                f"reg {dec['reg']:.6g}, align {dec['align']}, reweight {dec['reweight']}")
        npy, js = args.directory / f"{case}.npy", args.directory / f"{case}.json"
        if args.mode == "save":
            np.save(npy, res.rig.deltas)
            js.write_text(json.dumps(dec))
        else:
            diff = float(np.abs(np.load(npy) - res.rig.deltas).max())
            worst = max(worst, diff)
            old = json.loads(js.read_text())
            same = all(old[k] == dec[k] for k in ("align", "reweight", "weight_sigma", "prior_alpha"))
            line += (f"; max |change| {diff:.2e} m, decisions {'same' if same else 'CHANGED'}, "
                     f"reg rel. change {abs(old['reg'] - dec['reg']) / old['reg']:.1e}")
        print(line, flush=True)
    if args.mode == "compare":
        print(f"largest change {worst:.2e} m: {'ok' if worst <= TOLERANCE_M else 'TOO LARGE'} "
              f"(tolerance {TOLERANCE_M:g} m)")


if __name__ == "__main__":
    main()
