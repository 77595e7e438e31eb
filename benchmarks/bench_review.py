"""Benchmark ``usdface review`` and ``usdface export``: page size, build time and the page's frame time in a
real browser (headless Chromium, software WebGL), glTF size and export time.

Usage::

    python benchmarks/bench_review.py [--repeat 3] [--frames 30] [--bench ../shared/data/bench]

Personalizes the sample (and dev1 when ../shared is present) once, then per case: the review page's size
and the median seconds to build it (without the eq. 5 refit), the median milliseconds per pose update in the
page over ``--frames`` updates (blend the sparse deltas + ``Plotly.restyle`` + draw; ``?bench=N``; real time,
software WebGL on a shared machine, so a desktop browser with a GPU is faster), and the glTF's size and
export time. The machine is shared: read the medians.
"""

from __future__ import annotations

import argparse
import re
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

from shared_data import BENCH

from usdface import api

ROOT = Path(__file__).resolve().parents[1]


def _frame_ms(page: Path, frames: int, query: str) -> tuple[float, float] | None:
    """Median ms per pose update (blend + ``Plotly.restyle``) and per frame (until the next animation frame,
    i.e. drawn), measured inside the page (``?bench=N``), driven by Python playwright with the system Chromium
    (``pip install playwright``; no browser download). None when either is missing."""
    exe = shutil.which("chromium") or shutil.which("google-chrome")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return None
    if not exe:
        return None
    logs: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=exe, args=["--no-sandbox", "--disable-gpu",
                                                               "--enable-unsafe-swiftshader"])
        tab = browser.new_page(viewport={"width": 1200, "height": 800})
        tab.on("console", lambda m: logs.append(m.text))
        tab.goto(f"{page.as_uri()}?{query}&bench={frames}")
        tab.wait_for_function("document.getElementById('usdface-status').textContent !== 'loading'",
                              timeout=300000)
        browser.close()
    found = next((re.search(r"usdface-bench: ([\d.]+) ms/update ([\d.]+) ms/frame", x) for x in logs
                  if "usdface-bench" in x), None)
    return (float(found.group(1)), float(found.group(2))) if found else None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--bench", type=Path, default=BENCH)
    args = ap.parse_args(argv)
    cases = [("sample", ROOT / "sample_assets" / "avatar.usda", ROOT / "sample_assets" / "capture.usda")]
    if (args.bench / "dev1" / "avatar.usdc").exists():
        cases.append(("dev1", args.bench / "dev1" / "avatar.usdc", args.bench / "dev1" / "capture"))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, avatar, capture in cases:
            layer = Path(tmp) / f"{name}.usda"
            api.personalize_avatar(avatar, capture, layer, force=True)
            page = Path(tmp) / f"{name}.html"
            build = []
            for _ in range(args.repeat):
                t = time.perf_counter()
                api.write_review(layer, page, fit_errors=False, force=True)
                build.append(time.perf_counter() - t)
            split = _frame_ms(page, args.frames, "variant=split")  # the median is taken inside the page
            single = _frame_ms(page, args.frames, "variant=personalized")
            glb = Path(tmp) / f"{name}.glb"
            export = []
            for _ in range(args.repeat):
                t = time.perf_counter()
                api.export_avatar(layer, gltf=glb, force=True)
                export.append(time.perf_counter() - t)
            nan = (float("nan"), float("nan"))
            rows.append((name, page.stat().st_size / 1e6, statistics.median(build), split or nan,
                         single or nan, glb.stat().st_size / 1e6, statistics.median(export)))
    print(f"{'case':8} {'page MB':>8} {'build s':>8} {'split update/frame ms':>22} "
          f"{'single update/frame ms':>23} {'glb MB':>7} {'export s':>9}")
    for r in rows:
        print(f"{r[0]:8} {r[1]:8.2f} {r[2]:8.2f} {r[3][0]:12.1f} /{r[3][1]:7.1f} {r[4][0]:13.1f} "
              f"/{r[4][1]:7.1f} {r[5]:7.2f} {r[6]:9.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
