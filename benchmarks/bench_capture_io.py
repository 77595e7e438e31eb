"""Capture I/O benchmark: OBJ parsing, capture folder import, capture.usda write/read, Live Link CSV, and the
continuous-take frame selection on a take generated from a bench case's true blendshapes.

Run from the project root (needs ../shared):  python benchmarks/bench_capture_io.py [--repeat 5]
Prints a table of median seconds and the take-selection accuracy figures.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from shared_data import SHARED

ROOT = Path(__file__).resolve().parents[1]


def median_time(fn, repeat):
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), min(times), out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args(argv)
    bench = SHARED / "data" / "bench"
    if not bench.is_dir():
        print("../shared not present; nothing to measure")
        return 0
    from usdface.io.capture_folder import read_capture_folder
    from usdface.io.livelink import read_livelink_take
    from usdface.io.mesh_io import read_obj
    from usdface.io.take import capture_from_take, read_take, write_take_usd
    from usdface.io.usd_anim import write_animation_usd
    from usdface.io.usd_capture import read_capture_usd, write_capture_usd
    from usdface.model import FaceRig
    from usdface.sample.take import make_take
    from usdface.take_select import select_frames

    warnings.simplefilter("ignore")
    rows = []
    tmp = Path(tempfile.mkdtemp(prefix="usdface-bench-"))
    r = args.repeat
    rows.append(("read_obj dev1 neutral (1203 v)", *median_time(lambda: read_obj(
        bench / "dev1/capture/neutral.obj"), r * 4)[:2]))
    for case in ("dev1", "dev2"):
        n_obj = len(list((bench / case / "capture").rglob("*.obj")))
        med, best, cap = median_time(lambda c=case: read_capture_folder(bench / c / "capture"), r)
        rows.append((f"read_capture_folder {case} ({n_obj} OBJ + JSON)", med, best))
    for ext, exact in (("usda", True), ("usdc", True), ("usda", False)):
        out = tmp / f"capture.{ext}"
        med, best, _ = median_time(lambda o=out, e=exact: write_capture_usd(cap, o, force=True, exact=e), r)
        size = out.stat().st_size / 1e6
        rows.append((f"write_capture_usd .{ext} exact={exact} ({size:.1f} MB)", med, best))
        med, best, back = median_time(lambda o=out: read_capture_usd(o), r)
        same = np.array_equal(back.frames.points, cap.frames.points) and np.array_equal(
            back.template.deltas, cap.template.deltas)
        rows.append((f"read_capture_usd .{ext} exact={exact} (bit-exact: {same})", med, best))
    csv = SHARED / "data/livelinkface/alex_rom_3.csv"
    med, best, ll = median_time(lambda: read_livelink_take(csv), r)
    rows.append((f"read_livelink_take alex_rom_3 ({len(ll.times)} rows)", med, best))
    med, best, _ = median_time(lambda: write_animation_usd(tmp / "take.usdc", ll.names, ll.weights, ll.times,
                                                           60.0, curves=ll.angles, force=True), r)
    rows.append(("write_animation_usd (anim import body) .usdc", med, best))
    med, best, sel = median_time(lambda: select_frames(ll.weights, names=ll.names, min_separation=15,
                                                       test_every=100), r)
    rows.append((f"select_frames alex_rom_3 ({52 - len(sel.missing)}/52 triggered)", med, best))

    # Continuous take from dev1's TRUE blendshapes, template = dev1's generic template.
    truth = np.load(bench / "dev1/truth/capture_truth.npz")
    person = FaceRig(truth["neutral"], cap.triangles, [str(n) for n in truth["names"]], truth["deltas"])
    dev1 = read_capture_folder(bench / "dev1/capture")
    med, best, (take, tt) = median_time(
        lambda: make_take(person, dev1.template, skip=["cheekPuff"], seed=7), r)
    rows.append((f"make_take dev1 truth ({len(take)} frames, 50 swept)", med, best))
    take_path = tmp / "take.usdc"
    med, best, _ = median_time(lambda: write_take_usd(take, take_path, force=True), max(1, r // 2))
    rows.append((f"write_take_usd .usdc ({take_path.stat().st_size / 1e6:.0f} MB)", med, best))
    med, best, back = median_time(lambda: read_take(take_path), max(1, r // 2))
    rows.append(("read_take .usdc", med, best))
    med, best, sel = median_time(lambda: select_frames(back.weights, names=back.names, min_separation=15), r)
    rows.append(("select_frames on the dev1 take", med, best))

    print(f"{'step':<58}{'median s':>10}{'best s':>10}")
    for name, med, best in rows:
        print(f"{name:<58}{med:>10.4f}{best:>10.4f}")
    chosen = {s.name: s.frames[0] for s in sel.shapes if s.triggered}
    hits = sum(chosen.get(n) == f for n, f in tt.peak_frames.items())
    print(f"\ntake selection: {hits}/{len(tt.peak_frames)} selected frames == true peak frames; "
          f"never triggered: {', '.join(sel.missing)} (skipped: {', '.join(tt.skipped)})")
    from usdface.model import Capture, Frames
    from usdface.personalize import fit_personalized_shapes

    selected = capture_from_take(back, sel)
    idx = [tt.peak_frames[n] for n in take.names if n in tt.peak_frames]
    hand = Capture(take.neutral, take.triangles, dev1.template,
                   Frames(take.points[idx], take.weights[idx], ["train"] * len(idx), [str(i) for i in idx]),
                   list(dev1.template.names))
    fits = {}
    for label, capture in (("selected", selected), ("hand-picked", hand)):
        t0 = time.perf_counter()
        fits[label] = fit_personalized_shapes(capture, method="menzel", reg="auto").rig.deltas
        print(f"fit (menzel, reg=auto) from {label} frames: {time.perf_counter() - t0:.2f} s")
    swept = [take.names.index(n) for n in tt.swept]
    rms = lambda d: 1000 * np.sqrt(np.mean(np.sum((d[swept] - truth["deltas"][swept]) ** 2, -1)))  # noqa: E731
    gap = np.abs(fits["selected"] - fits["hand-picked"]).max()
    print(f"max |fit(selected) - fit(hand-picked)| = {gap:.3g} m; "
          f"RMSE vs true shapes: fit {rms(fits['selected']):.3f} mm, generic template "
          f"{rms(dev1.template.deltas):.3f} mm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
