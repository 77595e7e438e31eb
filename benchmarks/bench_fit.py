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

A case is any name ``benchmarks/bench_personalize.py`` takes (``artist:201``, ``noisy:103/scan0.3``,
``dev1/minus3``, ``dev3/template1``, ...; the truth is the base case's ``truth/capture_truth.npz``), and
``--per-shape`` prints, per shape, the default fit's error against the truth beside its prior's and the
template's, its share of the squared error, and how the training frames excite it (:func:`per_shape`):

    python benchmarks/bench_fit.py --cases dev3 --per-shape --no-timing

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
    "menzel + weak prior": {"method": "menzel", "align": False, "reweight": False, "amplitude": False,
                            "weak_prior": True},
    "menzel, no amplitude": {"method": "menzel", "amplitude": False},
    "menzel default + weak prior": {"method": "menzel", "weak_prior": True},
    "laplacian": {"method": "laplacian"},
}


def load(case: str):
    """(capture, truth npz) of a bench case, of the sample (``case="sample"``) or of any case name
    ``bench_personalize.py`` takes (a generated case, a bench case with frames missing, its weights scaled or
    another template: the truth of the case it derives from, :func:`truth_path`)."""
    if case == "sample":
        return read_capture(SAMPLE / "capture.usda"), np.load(SAMPLE / "truth" / "capture_truth.npz")
    if (BENCH / case).is_dir():
        return read_capture(BENCH / case / "capture"), np.load(BENCH / case / "truth" / "capture_truth.npz")
    import bench_personalize

    return bench_personalize._case(case)[1], np.load(truth_path(case))


def truth_path(case: str) -> Path:
    """``truth/capture_truth.npz`` of a ``bench_personalize.py`` case name: a derived case's (``/weightsS``,
    ``/templateSRCxS``, ``/minusK``: the person and the truth are the base case's) is its base case's."""
    import bench_personalize as bp

    for derived in (bp._weights, bp._template, bp._minus):
        base = derived(case)
        if base is not None:
            return truth_path(base[0])
    if case == "sample":
        return SAMPLE / "truth" / "capture_truth.npz"
    if bp._generated(case):
        return bp._folder(case) / "truth" / "capture_truth.npz"
    return BENCH / case / "truth" / "capture_truth.npz"


def known(case: str) -> bool:
    """Can :func:`load` read ``case``?"""
    if case == "sample" or (BENCH / case).is_dir():
        return True
    import bench_personalize

    return bench_personalize._known(case)


def per_shape(capture, true, result) -> list[dict]:
    """Per shape of ``capture.names``: the fit ``result``'s (a :class:`FitResult`) RMSE against the true
    ``true[K,n,3]`` (mm, ``fit``), its prior's (``prior``: eq. 2's T_j as the fit used it) and the raw
    template's (``template``), ``share`` its part of the fit's summed squared error (the RMS over shapes of
    ``fit`` is :func:`truth_error`), how the training frames excite it - its largest weight (``peak``), the
    sum of its squared weights (``energy``), its weight in the training frame labelled with its name
    (``own``, nan without one) and whether that is the frame's largest (``isolated``: the frame recorded for
    it shows it at least as strongly as any other shape; ties count) - and the fit's own ``data_share`` and
    ``reliability`` of it (nan where the fit reports none)."""
    from usdface.arkit import normalize_name

    def rms(d):
        return np.sqrt(np.mean(np.sum(np.asarray(d, dtype=np.float64) ** 2, axis=-1), axis=-1)) * 1000.0

    info = result.info
    fit = rms(result.rig.deltas - true)
    prior = rms(np.asarray(info.get("prior_deltas", capture.template.deltas)) - true)
    template = rms(capture.template.deltas - true)
    W = capture.train.weights
    K = len(capture.names)
    canonical = [normalize_name(n) or n for n in capture.names]
    own, isolated = np.full(K, np.nan), np.zeros(K, dtype=bool)
    for f, label in enumerate(capture.train.label or []):
        name = normalize_name(str(label).split("_", 1)[-1])
        if name in canonical:
            k = canonical.index(name)
            own[k], isolated[k] = W[f, k], W[f, k] >= W[f].max()
    share = np.asarray(info.get("data_share", np.full(K, np.nan)), dtype=np.float64)
    reliable = np.asarray(info.get("shape_reliability", np.full(K, np.nan)), dtype=np.float64)
    total = max(float(np.sum(fit ** 2)), 1e-300)
    return [{"shape": name, "fit": float(fit[k]), "prior": float(prior[k]), "template": float(template[k]),
             "share": float(fit[k] ** 2 / total), "peak": float(W[:, k].max(initial=0.0)),
             "energy": float(np.sum(W[:, k] ** 2)), "own": float(own[k]), "isolated": bool(isolated[k]),
             "data_share": float(share[k]),
             "reliability": float(reliable[k])} for k, name in enumerate(capture.names)]


def per_shape_table(case: str, console: Console) -> list[dict]:
    """:func:`per_shape` of the default fit of ``case``, printed largest error first, with the part of the
    squared error the shapes their own training frame does not isolate carry."""
    cap, truth = load(case)
    true = truth["deltas"][[list(truth["names"]).index(n) for n in cap.names]]
    res = fit_personalized_shapes(cap)
    rows = per_shape(cap, true, res)
    table = Table(title=f"{case}: per shape, the default fit against the truth (mm) and the training frames' "
                        "excitation")
    for col in ("shape", "fit", "prior", "template", "% of error", "peak w", "sum w^2", "own frame w",
                "isolated", "data share", "reliability"):
        table.add_column(col)
    for r in sorted(rows, key=lambda r: -r["fit"]):
        table.add_row(r["shape"], f"{r['fit']:.3f}", f"{r['prior']:.3f}", f"{r['template']:.3f}",
                      f"{100 * r['share']:.1f}", f"{r['peak']:.2f}", f"{r['energy']:.3f}", f"{r['own']:.2f}",
                      "yes" if r["isolated"] else "no", f"{r['data_share']:.2f}", f"{r['reliability']:.2f}")
    console.print(table)
    behind = [r for r in rows if not r["isolated"]]
    worse = [r["shape"] for r in rows if r["fit"] > r["prior"]]
    part = 100 * sum(r["share"] for r in behind)
    console.print(f"{case}: truth {truth_error(res.rig.deltas, true):.4f} mm; the {len(behind)} shapes their "
                  f"own frame does not isolate carry {part:.1f} % of the squared error; fitted further from "
                  f"the truth than their prior: {', '.join(worse) or 'none'}")
    return rows


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
    ap.add_argument("--per-shape", action="store_true",
                    help="also print each shape's truth error beside its prior's and its excitation")
    args = ap.parse_args()
    console = Console(width=150)
    for case in args.cases.split(","):
        if not known(case):
            console.print(f"no bench data at {BENCH / case} and not a generated case's name; skipped")
            continue
        if not args.no_accuracy:
            accuracy(case, console)
        if args.per_shape:
            per_shape_table(case, console)
        if not args.no_timing:
            timing(case, args.repeat, console, laplacian=not args.no_laplacian)


if __name__ == "__main__":
    main()
