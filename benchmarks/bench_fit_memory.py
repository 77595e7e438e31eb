"""Peak memory of the fit ``personalize`` runs (the default plus the weights' sensitivity, noise and leak) on
a large capture: a bench capture (dev1 by default) midpoint-subdivided ``--levels`` times (3: 74,542
vertices from dev1's 1,203), its frames and template shapes carried along (issue 12's memory item).

Prints the resident set size at the fit's start and its peak (sampled every 20 ms on a thread), the step of
``fit_personalized_shapes`` the peak fell in, and the fit's CPU seconds::

    python benchmarks/bench_fit_memory.py [--case dev1] [--levels 3]

One process per figure (the peak is the process's); compare a change with its base in the same minutes.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
import warnings
from dataclasses import replace

import numpy as np
from scale_avatars import midpoint_subdivide
from shared_data import BENCH

from usdface.io import read_capture
from usdface.model import Capture, Frames
from usdface.personalize import fit_personalized_shapes


def subdivided_capture(case: str, levels: int) -> Capture:
    """The bench ``case``'s capture with its mesh, frames and template shapes midpoint-subdivided ``levels``
    times (:func:`scale_avatars.midpoint_subdivide`)."""
    cap = read_capture(BENCH / case / "capture")
    points, triangles = cap.neutral, cap.triangles
    F = len(cap.frames)
    stack = np.concatenate([cap.frames.points - points[None], cap.template.deltas])
    for _ in range(levels):
        points, triangles, stack = midpoint_subdivide(points, triangles, stack)
    frames = Frames(points[None] + stack[:F], cap.frames.weights, cap.frames.role, cap.frames.label)
    template = replace(cap.template, neutral=points, triangles=triangles, deltas=stack[F:].copy(),
                       source=None)
    return Capture(points, triangles, template, frames, cap.names, source=cap.source, metadata=cap.metadata)


def _rss_mb() -> float:
    """The process's resident set (MB) now: /proc's resident pages times the system's page size."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def traced_fit(capture: Capture) -> dict:
    """``{"start_mb", "peak_mb", "at", "cpu_s"}`` of one ``fit_personalized_shapes(capture, method="menzel",
    sensitivity=True)``; ``at`` the line of ``fit_personalized_shapes`` running at the peak."""
    main = threading.get_ident()
    peak = {"mb": 0.0, "at": ""}
    done = threading.Event()

    def sample():
        while not done.is_set():
            rss = _rss_mb()
            if rss > peak["mb"]:
                frame, at = sys._current_frames().get(main), ""
                while frame is not None and frame.f_code.co_name != "fit_personalized_shapes":
                    at = f"{frame.f_code.co_name}:{frame.f_lineno}" if not at else at
                    frame = frame.f_back
                where = f"fit_personalized_shapes:{frame.f_lineno}" if frame is not None else "-"
                peak.update(mb=rss, at=f"{where} ({at})")
            time.sleep(0.02)

    start = _rss_mb()
    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    t0 = time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit_personalized_shapes(capture, method="menzel", sensitivity=True)
    cpu = time.process_time() - t0
    done.set()
    thread.join()
    return {"start_mb": start, "peak_mb": peak["mb"], "at": peak["at"], "cpu_s": cpu}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", default="dev1")
    ap.add_argument("--levels", type=int, default=3)
    args = ap.parse_args(argv)
    capture = subdivided_capture(args.case, args.levels)
    out = traced_fit(capture)
    print(f"{args.case} capture subdivided {args.levels}x ({len(capture.neutral):,} vertices, "
          f"{len(capture.names)} shapes, {len(capture.frames)} frames): fit with sensitivity "
          f"{out['cpu_s']:.2f} CPU-s, RSS {out['start_mb']:,.0f} MB at its start, peak "
          f"{out['peak_mb']:,.0f} MB (+{out['peak_mb'] - out['start_mb']:,.0f}) in {out['at']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
