"""Sample-asset benchmark: time to build and write the sample assets (with and without the capture folder),
the size of the committed files, and how far the generic template and the personalization methods are from the
known truth on them.

Run from the project root:  python benchmarks/bench_sample.py [--repeat 3] [--fit]
Prints a table of median seconds and sizes; with --fit also the truth RMSE of each personalization method
(slow: tens of seconds per method on 2 cores).
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from bench_capture_io import median_time  # same folder: (median s, min s, last result) of ``repeat`` runs

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    from usdface.sample import build_samples, generate_samples

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--fit", action="store_true", help="also run the personalization methods")
    args = parser.parse_args(argv)
    rows = []
    med, best, _ = median_time(lambda: build_samples(0), args.repeat)
    rows.append(("build_samples (in memory)", med, best))
    with tempfile.TemporaryDirectory() as tmp:
        med, best, out = median_time(lambda: generate_samples(Path(tmp) / "s", force=True), args.repeat)
        rows.append(("generate_samples (committed files)", med, best))
        med, best, _ = median_time(lambda: generate_samples(Path(tmp) / "f", force=True, folder=True),
                                   args.repeat)
        rows.append(("generate_samples(folder=True)", med, best))
        sizes = {}
        for p in sorted(out.rglob("*")):
            if p.is_file():
                top = p.relative_to(out).parts[0]
                sizes[top] = sizes.get(top, 0) + p.stat().st_size
    print(f"{'step':34s} {'median s':>9s} {'min s':>8s}")
    for name, med, best in rows:
        print(f"{name:34s} {med:9.2f} {best:8.2f}")
    print(f"\n{'file':34s} {'MB':>9s}")
    for name, size in sizes.items():
        print(f"{name:34s} {size / 1e6:9.2f}")
    print(f"{'total':34s} {sum(sizes.values()) / 1e6:9.2f}")

    if args.fit:
        from usdface.io import read_capture
        from usdface.personalize import fit_personalized_shapes

        cap = read_capture(ROOT / "sample_assets" / "capture.usda")
        truth = np.load(ROOT / "sample_assets" / "truth" / "capture_truth.npz")
        names = list(truth["names"])

        def rmse_mm(deltas, order):
            d = deltas[[order.index(n) for n in names]]
            return 1000 * np.sqrt(((d - truth["deltas"]) ** 2).sum(-1).mean())

        print(f"\n{'shapes vs truth (capture mesh)':34s} {'RMSE mm':>9s} {'s':>8s}")
        print(f"{'generic template':34s} {rmse_mm(cap.template.deltas, cap.names):9.3f} {0.0:8.1f}")
        for method in ("dt", "ebfr", "laplacian", "menzel"):
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                rig = fit_personalized_shapes(cap, method=method).rig
            print(f"{method:34s} {rmse_mm(rig.deltas, rig.names):9.3f} {time.perf_counter() - t0:8.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
