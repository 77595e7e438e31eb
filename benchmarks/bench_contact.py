"""Benchmark of lip and eyelid contact in the fit (``contact=off|auto|on``) on the bench captures
(../shared/data/bench/dev1-dev3) and the project's sample capture (``sample``).

Prints (1) per case and contact shape: the pairs the template brings into contact, the template's own gap
there, and the largest gap vs the template's (mm) of the true shapes and of the fit without contact (before),
with ``auto`` and with ``on`` (after); (2) per case the truth error (RMSE vs ``truth/capture_truth.npz``, mm)
over all shapes and over the contact shapes, the training RMSE, and the contact step's seconds (median of
``--repeat`` fits); (3) for the implant (issue 10 item 4): lower-lip vertices of the avatar's Head that pass
through the upper lip (:func:`usdface.personalize.contact.lip_crossings`, lips found by their motion under
jawOpen), count and deepest (mm), in the generic shapes and in the true personalized ones
(``truth/avatar_truth.npz``); mouthClose is posed on jawOpen.

    python benchmarks/bench_contact.py [--cases dev1,dev2,dev3,sample] [--repeat 3]
"""

from __future__ import annotations

import argparse
import statistics
import warnings
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table
from shared_data import BENCH

from usdface.io import read_capture
from usdface.personalize import fit_personalized_shapes, truth_error
from usdface.personalize.contact import apply_contact, find_contact_pairs, find_openings, lip_crossings

SAMPLE = Path(__file__).resolve().parents[1] / "sample_assets"
MODES = ("off", "auto", "on")
LIP_SHAPES = ("mouthClose", "mouthPressLeft", "mouthPressRight", "mouthRollLower", "mouthRollUpper",
              "mouthPucker", "mouthFunnel", "mouthShrugLower")


def load(case: str):
    if case == "sample":
        return read_capture(SAMPLE / "capture.usda"), np.load(SAMPLE / "truth" / "capture_truth.npz")
    return read_capture(BENCH / case / "capture"), np.load(BENCH / case / "truth" / "capture_truth.npz")


def run_case(case: str, repeat: int):
    cap, truth = load(case)
    true = truth["deltas"][[list(truth["names"]).index(n) for n in cap.names]]
    fits, secs = {}, {m: [] for m in MODES}
    for mode in MODES:
        for _ in range(max(repeat, 1)):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                fits[mode] = fit_personalized_shapes(cap, contact=mode)
            secs[mode].append(fits[mode].info["timings"]["contact"])
    tmpl = cap.template
    ops = find_openings(tmpl.neutral, cap.triangles)
    pairs = find_contact_pairs(tmpl.neutral, tmpl.deltas, cap.triangles, cap.names, openings=ops)
    _, truth_rep = apply_contact(cap.neutral, cap.triangles, true, pairs, ops, mode="off")
    shapes = [cap.names.index(p.name) if p.name in cap.names else p.shape for p in pairs]
    per_shape = {}
    for pr in pairs:
        per_shape[pr.name] = {"pairs": len(pr.upper),
                              "target": (pr.target.min() * 1000, pr.target.max() * 1000),
                              "truth": truth_rep[pr.name]["gap_before_mm"],
                              **{m: fits[m].info["contact"]["shapes"][pr.name] for m in MODES}}
    summary = {m: {"truth": truth_error(fits[m].rig.deltas, true),
                   "truth_contact": (truth_error(fits[m].rig.deltas[shapes], true[shapes]) if shapes
                                     else float("nan")),
                   "train": fits[m].info["train_rmse_mm"], "sec": statistics.median(secs[m])} for m in MODES}
    return per_shape, summary


def avatar_lips(case: str) -> list[tuple]:
    """(shape, generic count, generic depth mm, truth count, truth depth mm) on the avatar's Head."""
    from pxr import Usd, UsdGeom

    from usdface.io.usd_rig import read_avatar

    path = BENCH / case / "avatar.usdc"
    truth_path = BENCH / case / "truth" / "avatar_truth.npz"
    if not path.is_file() or not truth_path.is_file():
        return []
    head = next(m for m in read_avatar(path).meshes if m.name == "Head")
    unit = UsdGeom.GetStageMetersPerUnit(Usd.Stage.Open(str(path)))        # truth offsets: avatar units
    truth = np.load(truth_path)
    jaw = head.deltas[head.names.index("jawOpen")]
    true_jaw = truth["Head/jawOpen"] * unit
    rows = []
    for s in LIP_SHAPES:
        if s not in head.names or f"Head/{s}" not in truth:
            continue
        gen = head.deltas[head.names.index(s)] + (jaw if s == "mouthClose" else 0.0)
        tru = truth[f"Head/{s}"] * unit + (true_jaw if s == "mouthClose" else 0.0)
        g = lip_crossings(head.neutral, head.triangles, gen, opening_delta=jaw)
        t = lip_crossings(head.neutral, head.triangles, tru, opening_delta=jaw)
        rows.append((s, g.count, g.max_depth * 1000, t.count, t.max_depth * 1000))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="dev1,dev2,dev3,sample")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    console = Console(width=150)
    cases = [c for c in args.cases.split(",") if c == "sample" or (BENCH / c).is_dir()]
    if not cases:
        console.print("no bench cases (../shared/data/bench) and no sample requested: nothing to do")
        return 0
    gaps = Table(title="Contact gaps: largest |gap - template's gap| over the pairs, mm")
    for col in ("case", "shape", "pairs", "template gap mm", "truth", "before (off)", "auto", "on"):
        gaps.add_column(col, justify="left" if col in ("case", "shape") else "right")
    errs = Table(title="Truth error (RMSE vs the true shapes, mm), training RMSE, contact step seconds")
    for col in ("case", "mode", "truth, all shapes", "truth, contact shapes", "train RMSE", "contact s"):
        errs.add_column(col, justify="left" if col in ("case", "mode") else "right")
    for case in cases:
        per_shape, summary = run_case(case, args.repeat)
        if not per_shape:
            gaps.add_row(case, "(no pairs)", "0", "", "", "", "", "")
        for name, r in per_shape.items():
            auto = r["auto"]
            auto_txt = f"{auto['gap_after_mm']:.3f}" + ("" if auto["applied"] else " (frames disagree)")
            gaps.add_row(case, name, str(r["pairs"]), f"{r['target'][0]:.2f} .. {r['target'][1]:.2f}",
                         f"{r['truth']:.3f}", f"{r['off']['gap_before_mm']:.3f}", auto_txt,
                         f"{r['on']['gap_after_mm']:.3f}")
        for m in MODES:
            s = summary[m]
            errs.add_row(case, m, f"{s['truth']:.4f}", f"{s['truth_contact']:.4f}", f"{s['train']:.4f}",
                         f"{s['sec']:.3f}")
    console.print(gaps)
    console.print(errs)
    lips = Table(title="Avatar Head: lower-lip vertices past the upper lip (count, deepest mm)")
    for col in ("case", "shape", "generic", "generic mm", "true shapes", "true mm"):
        lips.add_column(col, justify="left" if col in ("case", "shape") else "right")
    for case in cases:
        if case == "sample":
            continue
        for s, gc, gd, tc, td in avatar_lips(case):
            lips.add_row(case, s + (" + jawOpen" if s == "mouthClose" else ""), str(gc), f"{gd:.2f}", str(tc),
                         f"{td:.2f}")
    console.print(lips)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
