"""Benchmark the avatar USD I/O: read the dev avatars into the model, write a layer overriding every shape.

Usage::

    python benchmarks/bench_io.py [--repeat 7] [--bench ../shared/data/bench]

Prints a table of median / min wall-clock seconds over ``--repeat`` runs (the machine is shared, so look at
the median). Goal (issue 2): each row < 0.5 s on a 2-core machine. Needs ../shared (the dev1 bench case).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

from shared_data import BENCH

import usdface.io  # noqa: F401  (schemas registered before any stage)
from usdface.io.layers import write_avatar_layer
from usdface.io.usd_rig import read_avatar

ROOT = Path(__file__).resolve().parents[1]


def timed(fn, repeat: int) -> tuple[float, float]:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), min(times)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--bench", type=Path, default=BENCH)
    args = parser.parse_args(argv)
    dev1 = args.bench / "dev1"
    if not (dev1 / "avatar.usdc").exists():
        print(f"bench data not found under {args.bench}", file=sys.stderr)
        return 1
    avatar = read_avatar(dev1 / "avatar.usdc")
    blender = read_avatar(dev1 / "avatar_blender.usdc")
    head = avatar.mesh("Head")
    n_vertices = sum(m.n_vertices for m in avatar.meshes)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        rows.append(("read avatar.usdc (Head+Mouth, 21.5k verts, 101 shapes)",
                     *timed(lambda: read_avatar(dev1 / "avatar.usdc"), args.repeat)))
        rows.append(("read avatar_blender.usdc (Z up, nested, dense indices)",
                     *timed(lambda: read_avatar(dev1 / "avatar_blender.usdc"), args.repeat)))
        def scaled(av):
            return {m.source.prim: m.deltas * 1.1 for m in av.meshes}

        for label, av, offsets in (
            ("Head only (51 shapes)", avatar, {head.source.prim: head.deltas * 1.1}),
            ("Head+Mouth (101 shapes)", avatar, scaled(avatar)),
            ("Blender Head+Mouth (101 shapes)", blender, scaled(blender)),
        ):
            for ext in (".usdc", ".usda"):
                def write(av=av, out=tmp / f"out{ext}", offsets=offsets):
                    write_avatar_layer(av, out, offsets, provenance={"command": "bench"}, force=True)

                rows.append((f"write layer {label} {ext}", *timed(write, args.repeat)))
        out = tmp / "out.usdc"
        write_avatar_layer(avatar, out, {m.source.prim: m.deltas * 1.1 for m in avatar.meshes},
                           provenance={}, force=True)
        rows.append(("read back the layered avatar (.usdc)", *timed(lambda: read_avatar(out), args.repeat)))
    width = max(len(r[0]) for r in rows)
    print(f"usdface USD I/O benchmark: dev1 avatar ({n_vertices} vertices on meshes with blend shapes; "
          f"24,591 in the stage with the eyes), median of {args.repeat} runs")
    print(f"{'operation':<{width}}  {'median s':>9}  {'min s':>7}")
    for label, med, best in rows:
        print(f"{label:<{width}}  {med:9.3f}  {best:7.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
