"""Benchmark ``usdface personalize`` on the bench cases (../shared): accuracy vs truth and wall time.

Run:  python benchmarks/bench_personalize.py [--cases dev1,dev2] [--repeats 3] [--variants]

Prints two tables:
1. accuracy: RMSE over the avatar ``Head`` vertices of the output offsets vs ``truth/avatar_truth.npz``, as a
   ratio of the generic input offsets' RMSE, with the eq. (4) approximation alone for comparison (and, with
   ``--variants``, the other transfer options);
2. time: end-to-end wall time of the ``usdface personalize`` command (fresh process each run), cold
   (no correspondence cache) and warm (cache reused), median of ``--repeats`` runs, plus the in-process step
   breakdown of one run, and the import-only time of a fresh process (with and without Open3D).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT.parent / "shared" / "data" / "bench"


def _rmse(a, b):
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=-1))))


def accuracy(case: str, variants: bool) -> list[tuple]:
    from usdface.io import read_capture
    from usdface.io.usd_rig import read_avatar
    from usdface.personalize import fit_personalized_shapes
    from usdface.transfer import personalize_avatar

    avatar = read_avatar(BENCH / case / "avatar.usdc")
    capture = read_capture(BENCH / case / "capture")
    fit = fit_personalized_shapes(capture)
    head = avatar.mesh("Head")
    npz = np.load(BENCH / case / "truth" / "avatar_truth.npz")
    truth = np.array([npz["Head/" + n] for n in head.names]) @ head.source.to_internal[:3, :3].T
    generic = _rmse(head.deltas, truth)
    settings = [("default (offset, generic, falloff 0.15)", {})]
    if variants:
        settings += [("face_transfer=dt (paper DT)", {"face_transfer": "dt"}),
                     ("face_transfer=dt-offset", {"face_transfer": "dt-offset"}),
                     ("approximation=retarget (paper A_j)", {"approximation": "retarget"}),
                     ("falloff=0 (harmonic, paper)", {"falloff": 0}),
                     ("paper: dt + retarget + harmonic", {"face_transfer": "dt", "approximation": "retarget",
                                                          "falloff": 0})]
    rows = []
    for label, opts in settings:
        res = personalize_avatar(avatar, capture, None, rig=fit.rig, **opts)
        out = res.offsets[head.source.prim]
        eq4 = head.deltas.copy()
        for j, n in enumerate(res.names):
            eq4[head.index(n)] = res.approximation[head.source.prim][j]
        rows.append((case, label, generic * 1000, _rmse(out, truth) / generic, _rmse(eq4, truth) / generic,
                     int(res.face.sum())))
    return rows


def wall_times(case: str, repeats: int) -> dict:
    """Median wall and CPU seconds (user + sys of the child: about the wall time on an idle machine)."""
    import resource

    exe = [sys.executable, "-m", "usdface.cli"]
    out = {"cold": [], "warm": [], "cold_cpu": [], "warm_cpu": []}
    with tempfile.TemporaryDirectory() as tmp:
        cache = Path(tmp) / "corr.npz"
        for r in range(repeats):
            for kind in ("cold", "warm"):
                if kind == "cold" and cache.exists():
                    cache.unlink()
                args = exe + ["personalize", str(BENCH / case / "avatar.usdc"), str(BENCH / case / "capture"),
                              "-o", str(Path(tmp) / f"o{r}{kind}.usda"), "-q", "--correspondence", str(cache)]
                r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
                t = time.perf_counter()
                subprocess.run(args, check=True, capture_output=True)
                out[kind].append(time.perf_counter() - t)
                r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
                out[kind + "_cpu"].append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)
    return {k: statistics.median(v) for k, v in out.items()}


def import_times(repeats: int) -> dict:
    """Median wall seconds of fresh processes that only import what ``usdface personalize`` imports: the
    interpreter with numpy/scipy/pxr/usdface, and the same plus Open3D (its marginal cost)."""
    base = ("import usdface.cli, usdface.commands.personalize, usdface.api, usdface.transfer, "
            "usdface.personalize, usdface.io.usd_rig, usdface.io.layers, scipy.spatial")
    out = {}
    for label, code in (("python + numpy/scipy/pxr/usdface", base), ("... + open3d", base + ", open3d")):
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            subprocess.run([sys.executable, "-c", code], check=True, capture_output=True)
            ts.append(time.perf_counter() - t)
        out[label] = statistics.median(ts)
    return out


def step_times(case: str) -> dict:
    from usdface.transfer import personalize_avatar

    res = personalize_avatar(BENCH / case / "avatar.usdc", BENCH / case / "capture", None)
    return res.report["timings"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default="dev1,dev2")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--variants", action="store_true", help="also score the paper's transfer options")
    ap.add_argument("--no-time", action="store_true")
    args = ap.parse_args(argv)
    if not BENCH.is_dir():
        print(f"{BENCH} not found: nothing to benchmark")
        return 0
    cases = args.cases.split(",")
    print(f"{'case':5} {'setting':42} {'generic mm':>10} {'out/generic':>11} {'eq4/generic':>11} "
          f"{'face v':>7}")
    for case in cases:
        for row in accuracy(case, args.variants):
            print(f"{row[0]:5} {row[1]:42} {row[2]:10.4f} {row[3]:11.3f} {row[4]:11.3f} {row[5]:7d}")
    if args.no_time:
        return 0
    print(f"\n{'case':5} {'cold s':>8} {'warm s':>8} {'cold cpu':>9} {'warm cpu':>9}   (usdface personalize, "
          f"fresh process, median of {args.repeats}; cpu = user+sys)")
    for case in cases:
        t = wall_times(case, args.repeats)
        print(f"{case:5} {t['cold']:8.2f} {t['warm']:8.2f} {t['cold_cpu']:9.2f} {t['warm_cpu']:9.2f}")
    for case in cases:
        t = step_times(case)
        print(f"{case} steps: " + ", ".join(f"{k} {v:.2f}s" for k, v in t.items()))
    for label, sec in import_times(args.repeats).items():
        print(f"imports only ({label}): {sec:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
