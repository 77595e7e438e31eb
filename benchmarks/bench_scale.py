"""Benchmark ``usdface personalize`` and ``usdface landmarks`` at production sizes (issue 12).

    python benchmarks/bench_scale.py [--only subdiv2 merged] [--skip landmarks] [--repeat 1]
                                     [--cache DIR] [--bench ../shared/data/bench]

Builds, from ``dev1/avatar.usdc`` itself (:mod:`scale_avatars`; cached in ``--cache``, default
``$XDG_CACHE_HOME/usdface/bench_scale``, never in the repository), the avatars of the issue's table: the
``Head`` subdivided once and twice (original vertices first, same indices), dev1 plus a separate ~300k-vertex
body mesh, and head + body merged into one mesh. Each must pass ``usdface check``. Then runs, each in a fresh
process, ``usdface personalize AVATAR dev1/capture -o ...`` and ``usdface landmarks AVATAR -o ... --json``
and prints:

* CPU seconds (user + sys of the child, from ``os.wait4`` in a small launcher, as ``/usr/bin/time -v``
  reports them), the ratio to dev1 measured in the same run, peak RSS (``ru_maxrss``) and wall seconds;
* "same answer": the personalized offsets on the original ``Head`` vertices against dev1's own result, RMS as
  a percentage of dev1's personalization change (output minus generic offsets, RMS over all shapes and
  ``Head`` vertices) and the largest absolute difference in mm; and whether the landmark layout is dev1's.

Skips cleanly (exit 0) without ../shared. The machine is shared: CPU seconds are steadier than wall time.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from scale_avatars import VARIANTS, build_scale_avatars  # noqa: E402
from shared_data import BENCH  # noqa: E402

ROOT = HERE.parent
LABELS = {"dev1": "dev1", "subdiv1": "Head subdivided once", "subdiv2": "Head subdivided twice",
          "merged": "head + body as one mesh", "body": "separate 300k body mesh"}


def default_cache() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "usdface" / "bench_scale"


#: Runs ``argv[2:]`` in a grandchild and writes its rusage to ``argv[1]``. Linux keeps, in the peak RSS
#: ``wait4`` reports, the size of the process image a child replaced at ``exec``: a child forked straight
#: from this script (hundreds of MB once it holds the results it compares) reported this script's size, not
#: its own (a 477 MB run read 796 MB). The grandchild is forked from this small launcher, as
#: ``/usr/bin/time`` forks its command.
LAUNCHER = """import json, os, sys
pid = os.fork()
if pid == 0:
    os.execv(sys.argv[2], sys.argv[2:])
_, status, ru = os.wait4(pid, 0)
with open(sys.argv[1], "w") as f:
    json.dump({"cpu": ru.ru_utime + ru.ru_stime, "maxrss_kb": ru.ru_maxrss}, f)
sys.exit(os.waitstatus_to_exitcode(status))
"""


def run_measured(cmd: list[str]) -> dict:
    """Run ``cmd`` in a grandchild (:data:`LAUNCHER`); {"cpu": user+sys s, "rss_mb": peak RSS MB, "wall":
    s, "rc", "out"}."""
    t = time.perf_counter()
    with tempfile.TemporaryFile() as out, tempfile.TemporaryDirectory() as tmp:
        usage_file = Path(tmp) / "rusage.json"
        rc = subprocess.run([sys.executable, "-S", "-c", LAUNCHER, str(usage_file), *cmd], stdout=out,
                            stderr=subprocess.STDOUT, cwd=ROOT).returncode
        wall = time.perf_counter() - t
        usage = json.loads(usage_file.read_text())
        out.seek(0)
        text = out.read().decode(errors="replace")
    return {"cpu": usage["cpu"], "rss_mb": usage["maxrss_kb"] / 1024.0, "wall": wall, "rc": rc, "out": text}


def usdface(*args) -> list[str]:
    return [sys.executable, "-m", "usdface.cli", *map(str, args)]


def measure(cmd: list[str], repeat: int, label: str) -> dict:
    runs = []
    for _ in range(repeat):
        r = run_measured(cmd)
        if r["rc"] != 0:
            print(f"{label} failed (exit {r['rc']}):\n{r['out'][-2000:]}", file=sys.stderr)
            return {"cpu": float("nan"), "rss_mb": float("nan"), "wall": float("nan"), "ok": False}
        runs.append(r)
    return {"cpu": statistics.median(r["cpu"] for r in runs),
            "rss_mb": statistics.median(r["rss_mb"] for r in runs),
            "wall": statistics.median(r["wall"] for r in runs), "ok": True}


def head_offsets(path: Path, n: int | None = None) -> tuple[list[str], np.ndarray]:
    """Shape names and ``Head`` offsets ``[K, n, 3]`` metres of a (composed) avatar or output layer."""
    from usdface.io.usd_rig import read_avatar

    head = read_avatar(path).mesh("Head")
    return head.names, head.deltas if n is None else head.deltas[:, :n]


def same_answer(out: Path, ref_out: Path, ref_generic: Path) -> dict:
    """Offsets on the original Head vertices of ``out`` vs dev1's personalized ``ref_out``: RMS as % of
    dev1's personalization change (``ref_out`` - ``ref_generic``) and max abs difference, mm."""
    names, ref = head_offsets(ref_out)
    gnames, generic = head_offsets(ref_generic)
    onames, got = head_offsets(out, ref.shape[1])
    order = [onames.index(s) for s in names]
    generic = generic[[gnames.index(s) for s in names]]
    diff = got[order] - ref
    change = np.sqrt(np.mean((ref - generic) ** 2))
    rms = np.sqrt(np.mean(diff ** 2))
    worst = np.abs(diff).max(axis=(1, 2))
    return {"rms_pct": 100.0 * rms / change, "max_mm": 1e3 * float(worst.max()),
            "worst_shape": names[int(np.argmax(worst))]}


def vertex_counts(path: Path) -> tuple[int, int]:
    from usdface.io.usd_rig import read_avatar

    avatar = read_avatar(path)
    total = sum(m.n_vertices for m in avatar.meshes)
    total += sum(len(p) for p, _ in avatar.metadata.get("static_meshes", {}).values())
    return total, avatar.mesh("Head").n_vertices


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bench", type=Path, default=BENCH)
    parser.add_argument("--cache", type=Path, default=default_cache())
    parser.add_argument("--only", nargs="+", choices=VARIANTS, help="variants to run (dev1 always runs)")
    parser.add_argument("--skip", nargs="*", default=[], choices=["personalize", "landmarks", "check"])
    parser.add_argument("--repeat", type=int, default=1, help="runs per command (median)")
    parser.add_argument("--keep", type=Path, help="keep the outputs in this folder (default: a temp folder)")
    parser.add_argument("--json", type=Path, help="also write the figures as JSON")
    parser.add_argument("--layer-format", choices=["usdc", "usda"], default="usdc",
                        help="format of the personalized layers written (default usdc, as a pipeline "
                        "writes a 100 MB+ layer; usda: USD's text serialisation, ~5 CPU-s of the "
                        "twice-subdivided head's run)")
    args = parser.parse_args(argv)
    case = args.bench / "dev1"
    if not (case / "avatar.usdc").is_file():
        print(f"(no {case / 'avatar.usdc'}: scale benchmark skipped)")
        return 0
    variants = [v for v in VARIANTS if args.only is None or v in args.only]
    t = time.perf_counter()
    paths = {"dev1": case / "avatar.usdc", **build_scale_avatars(case / "avatar.usdc", args.cache, variants)}
    print(f"avatars ready in {time.perf_counter() - t:.1f} s under {args.cache}")
    tmp = tempfile.TemporaryDirectory() if args.keep is None else None
    outdir = Path(tmp.name) if tmp else args.keep
    outdir.mkdir(parents=True, exist_ok=True)
    rows: dict[str, dict] = {}
    for name, avatar in paths.items():
        row = rows[name] = {"label": LABELS[name]}
        row["vertices"], row["head"] = vertex_counts(avatar)
        if "check" not in args.skip:
            r = run_measured(usdface("check", "-q", avatar))
            row["check"] = r["rc"] == 0
            if r["rc"] != 0:
                print(f"{name}: usdface check failed:\n{r['out'][-2000:]}", file=sys.stderr)
        if "personalize" not in args.skip:
            out = outdir / f"{name}.personalized.{args.layer_format}"
            cmd = usdface("personalize", avatar, case / "capture", "-o", out, "--force", "-q")
            row["personalize"] = measure(cmd, args.repeat, f"{name} personalize")
            row["personalize"]["output"] = out
        if "landmarks" not in args.skip:
            out, js = outdir / f"{name}.landmarks.usda", outdir / f"{name}.landmarks.json"
            row["landmarks"] = measure(usdface("landmarks", avatar, "--mesh", "Head", "-o", out, "--force",
                                               "--json", js), args.repeat, f"{name} landmarks")
            if row["landmarks"]["ok"]:
                row["landmarks"]["vertices"] = json.loads(js.read_text())["vertices"]
        print(f"{name}: done ({json.dumps({k: v for k, v in row.items() if k in ('vertices', 'check')})})",
              flush=True)
    base = rows["dev1"]
    for name, row in rows.items():
        p = row.get("personalize")
        if p and p["ok"] and base.get("personalize", {}).get("ok") and name != "dev1":
            row["same"] = same_answer(p["output"], base["personalize"]["output"], paths["dev1"])
    print_tables(rows, args.repeat)
    if args.json:
        def plain(o):
            return str(o) if isinstance(o, Path) else o
        args.json.write_text(json.dumps(rows, indent=2, default=plain))
    if tmp:
        tmp.cleanup()
    return 0


def _ratio(row, base, key):
    a, b = row.get(key, {}), base.get(key, {})
    return a["cpu"] / b["cpu"] if a.get("ok") and b.get("ok") else float("nan")


def print_tables(rows: dict, repeat: int) -> None:
    base = rows["dev1"]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"\n## scale (CPU s = user+sys of the child, median of {repeat}; load {load:.1f} on "
          f"{os.cpu_count()} CPUs)\n")
    print("| avatar | vertices (Head) | check | personalize CPU s | x dev1 | RSS MB | wall s "
          "| landmarks CPU s | x dev1 | RSS MB | wall s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for row in rows.values():
        p, lm = row.get("personalize", {}), row.get("landmarks", {})
        cells = [row["label"], f"{row['vertices'] / 1e3:.1f}k ({row['head'] / 1e3:.1f}k)",
                 {True: "ok", False: "FAIL"}.get(row.get("check"), "-")]
        for m, key in ((p, "personalize"), (lm, "landmarks")):
            if m:
                cells += [f"{m['cpu']:.1f}", f"{_ratio(row, base, key):.2f}", f"{m['rss_mb']:,.0f}",
                          f"{m['wall']:.1f}"]
            else:
                cells += ["-"] * 4
        print("| " + " | ".join(cells) + " |")
    print("\n## same answer (Head offsets on the original vertices vs dev1's own result)\n")
    print("| avatar | RMS, % of dev1's change | max abs mm | worst shape | landmarks = dev1's |")
    print("|---|---|---|---|---|")
    ref_lm = base.get("landmarks", {}).get("vertices")
    for name, row in rows.items():
        if name == "dev1":
            continue
        s = row.get("same")
        lm = row.get("landmarks", {}).get("vertices")
        if lm is None or ref_lm is None:
            same_lm = "-"
        else:
            shared = len(set(lm) & set(ref_lm))
            same_lm = "yes" if lm == ref_lm else f"no ({len(lm)} vs {len(ref_lm)}, {shared} shared)"
        if s:
            print(f"| {row['label']} | {s['rms_pct']:.2f} | {s['max_mm']:.3f} | {s['worst_shape']} "
                  f"| {same_lm} |")
        else:
            print(f"| {row['label']} | - | - | - | {same_lm} |")


if __name__ == "__main__":
    sys.exit(main())
