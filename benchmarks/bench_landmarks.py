"""Benchmark `usdface landmarks` (Zell & McDonnell 2022) - timings and the evaluation curve.

    python benchmarks/bench_landmarks.py [--repeat 5] [--evaluate] [--out /tmp/landmarks_bench]

1. ILP backends on the dev avatar's Head (eq. 5 after reduction; visibility computed once): median seconds
   to a proven optimum per OR-tools backend, with and without the problem reduction.
2. The whole command (`usdface landmarks dev1/avatar.usdc -o ...`, a fresh process) wall time, and
   ``compute_landmarks`` in-process: CPU seconds, rays cast, scenes built, vertices ray cast.
3. A synthetic 237-shape, 20k-vertex model: reduction + ILP seconds, and compute_landmarks end to end.
4. (--evaluate) reconstruction error vs landmark count on the dev avatar, Live Link Face takes as test
   weights, 0.5 mm tracking noise: this method's sweep vs the 68-point empirical layout and the baselines;
   writes landmarks_eval.png / .json into --out.

Timings are medians of --repeat runs on whatever machine this runs on (noisy when shared).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from shared_data import SHARED as SHARED_ROOT

ROOT = Path(__file__).resolve().parents[1]
SHARED = SHARED_ROOT / "data"


def median_time(fn, repeat: int):
    times, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def synthetic_rig(n_shapes: int = 237, side: int = 142, seed: int = 0):
    """A curved sheet of side x side vertices (~20k) with n_shapes random Gaussian bumps (metres)."""
    from usdface.model import FaceRig

    xs = np.linspace(-0.08, 0.08, side)
    x, y = np.meshgrid(xs, np.linspace(0.0, 0.2, side))
    pts = np.stack([x.ravel(), y.ravel(), 0.03 * np.exp(-(x.ravel() ** 2) / 0.003)], axis=1)
    i, j = np.meshgrid(np.arange(side - 1), np.arange(side - 1))
    a = (j * side + i).ravel()
    tri = np.concatenate([np.stack([a, a + 1, a + side + 1], 1), np.stack([a, a + side + 1, a + side], 1)])
    rng = np.random.default_rng(seed)
    deltas = np.zeros((n_shapes, len(pts), 3))
    for k in range(n_shapes):
        c = np.array([rng.uniform(-0.07, 0.07), rng.uniform(0.01, 0.19)])
        s = rng.uniform(0.004, 0.03)
        d2 = ((pts[:, :2] - c) ** 2).sum(axis=1)
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        deltas[k] = rng.uniform(0.001, 0.012) * np.exp(-d2 / (2 * s * s))[:, None] * direction
    return FaceRig(pts, tri, [f"shape{k:03d}" for k in range(n_shapes)], deltas, name="Synthetic")


def bench_backends(rig, repeat: int):
    from usdface.landmarks.candidates import (
        candidate_sets,
        displacement_magnitudes,
        landmark_quality,
        relative_displacement,
    )
    from usdface.landmarks.cover import set_cover_costs, solve_set_cover
    from usdface.landmarks.visibility import global_visibility, pose_bases

    r = relative_displacement(displacement_magnitudes(rig.deltas))
    c = candidate_sets(r, 0.5)
    need = np.flatnonzero(c.any(axis=0))
    vis = np.zeros(rig.n_vertices)
    vis[need] = global_visibility(rig.neutral, rig.triangles, rig.deltas, need, 16,
                                  bases=pose_bases(rig.names))
    rows = []
    for weighting in ("quality", "count"):
        cost = set_cover_costs(c, landmark_quality(r, vis, 0.5), weighting)
        for backend in ("scip", "cbc", "highs", "cp-sat"):
            for reduce in (True, False):
                t, sol = median_time(lambda b=backend, rd=reduce, co=cost: solve_set_cover(
                    c, co, backend=b, time_limit=10.0, reduce=rd), repeat)
                rows.append((weighting, backend, reduce, sol.reduced, len(sol.selected), sol.status,
                             sol.gap, t))
    print(f"\n## ILP backends, dev1 Head ({rig.n_vertices} vertices, {rig.n_shapes} shapes, eps 0.5, "
          f"{need.size} candidates), median of {repeat}")
    print(f"{'cost':8} {'backend':7} {'reduce':6} {'reduced (K, n)':15} {'#lm':>4} {'status':10} {'gap':>8} "
          f"{'seconds':>8}")
    for w, b, rd, red, m, st, gap, t in rows:
        print(f"{w:8} {b:7} {str(rd):6} {str(red):15} {m:4d} {st:10} {gap:8.2g} {t:8.3f}")


def bench_command(avatar: Path, repeat: int):
    times = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(repeat):
            out = Path(tmp) / f"lm{i}.usda"
            t = time.perf_counter()
            subprocess.run([sys.executable, "-m", "usdface.cli", "landmarks", str(avatar), "-o", str(out)],
                           check=True, capture_output=True)
            times.append(time.perf_counter() - t)
    print(f"\n## whole command `usdface landmarks {avatar.name} -o out.usda` (fresh process): median "
          f"{statistics.median(times):.2f} s, runs {', '.join(f'{t:.2f}' for t in times)}")


def bench_synthetic(repeat: int):
    from usdface.landmarks import compute_landmarks
    from usdface.landmarks.candidates import candidate_sets, displacement_magnitudes, relative_displacement
    from usdface.landmarks.cover import set_cover_costs, solve_set_cover

    rig = synthetic_rig()
    r = relative_displacement(displacement_magnitudes(rig.deltas))
    c = candidate_sets(r, 0.5)
    cost = set_cover_costs(c, 0.5 * r + 0.5, "quality")
    t, sol = median_time(lambda: solve_set_cover(c, cost), repeat)
    print(f"\n## synthetic model: {rig.n_shapes} shapes, {rig.n_vertices} vertices, eps 0.5 "
          f"({int(c.any(axis=0).sum())} candidates)")
    print(f"reduction + ILP (SCIP): median {t:.3f} s, {len(sol.selected)} landmarks, {sol.status}, gap "
          f"{sol.gap:.2g}, reduced to {sol.reduced}")
    t2, layout = median_time(lambda: compute_landmarks(rig, 0.5, rays=16), max(1, repeat // 2))
    print(f"compute_landmarks incl. visibility (16 rays): median {t2:.2f} s, {layout.count} landmarks, "
          f"{layout.status}; timings {({k: round(v, 3) for k, v in layout.timings.items()})}; "
          f"visibility evaluated on {layout.problem['visibility_evaluated']} of "
          f"{layout.problem['candidates']}")


def bench_visibility(rig, repeat: int):
    """compute_landmarks on the rig in-process: CPU seconds (median), rays cast, scenes built, vertices
    evaluated (the work of eq. 4's lazy visibility)."""
    from usdface.landmarks import compute_landmarks, visibility

    made = []
    original = visibility.PoseVisibility.__init__

    def init(self, *a, **k):
        original(self, *a, **k)
        made.append(self)

    visibility.PoseVisibility.__init__ = init
    try:
        cpu = []
        for _ in range(repeat):
            made.clear()
            t = time.process_time()
            layout = compute_landmarks(rig)
            cpu.append(time.process_time() - t)
    finally:
        visibility.PoseVisibility.__init__ = original
    pv, prob = made[0], layout.problem
    print(f"\n## compute_landmarks, {rig.name} ({rig.n_vertices} vertices, {rig.n_shapes} shapes), median of "
          f"{repeat}: {statistics.median(cpu):.2f} CPU-s; {layout.count} landmarks; rays cast "
          f"{pv.rays_cast:,}, scenes built {pv.scenes_built}, visibility evaluated on "
          f"{prob['visibility_evaluated']:,} of {prob['candidates']:,} candidates; ray offset "
          f"{pv.offset * 1e6:.1f} um")


def bench_evaluate(rig, out: Path, frames: int):
    from usdface.io.livelink import livelink_weights
    from usdface.landmarks.evaluate import evaluate_landmarks
    from usdface.landmarks.plots import plot_evaluation

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        w = livelink_weights(sorted((SHARED / "livelinkface").glob("*.csv")), rig.names, frames)
    indices = json.loads((SHARED / "ict-facekit" / "vertex_indices.json").read_text())
    empirical = indices["idx_to_landmark_verts"]
    t, cpu = time.perf_counter(), time.process_time()
    report = evaluate_landmarks(rig, w, empirical)
    cpu = time.process_time() - cpu
    out.mkdir(parents=True, exist_ok=True)
    plot_evaluation(report, out / "landmarks_eval.png", title="dev1 Head")
    (out / "landmarks_eval.json").write_text(json.dumps(report.to_dict(), indent=2))
    print(f"\n## evaluation, dev1 Head, {len(w)} Live Link frames, 0.5 mm noise "
          f"({time.perf_counter() - t:.0f} s wall, {cpu:.0f} CPU-s); plot {out / 'landmarks_eval.png'}")
    for key, value in report.summary.items():
        print(f"{key}: {value * 1e3:.4f} mm" if "rmse" in key and value is not None else f"{key}: {value}")
    best = {}
    for p in report.points:
        if p.method == "ours":
            best[p.count] = min(best.get(p.count, np.inf), p.rmse)
    print("ours, best RMSE (mm) per count: "
          + ", ".join(f"{m}: {v * 1e3:.3f}" for m, v in sorted(best.items())))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--evaluate", action="store_true")
    parser.add_argument("--frames", type=int, default=400)
    parser.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "landmarks_bench")
    parser.add_argument("--skip", nargs="*", default=[],
                        choices=["backends", "command", "visibility", "synthetic"])
    args = parser.parse_args(argv)
    avatar = SHARED / "bench" / "dev1" / "avatar.usdc"
    rig = None
    if avatar.is_file():
        from usdface.io.usd_rig import read_avatar

        rig = read_avatar(avatar).mesh("Head")
        if "backends" not in args.skip:
            bench_backends(rig, args.repeat)
        if "command" not in args.skip:
            bench_command(avatar, max(1, args.repeat // 2 + 1))
        if "visibility" not in args.skip:
            bench_visibility(rig, max(1, args.repeat // 2 + 1))
    else:
        print(f"(no {avatar}: dev-avatar benchmarks skipped)")
    if "synthetic" not in args.skip:
        bench_synthetic(args.repeat)
    if args.evaluate and rig is not None:
        bench_evaluate(rig, args.out, args.frames)
    return 0


if __name__ == "__main__":
    sys.exit(main())
