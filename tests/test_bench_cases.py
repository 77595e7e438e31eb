"""The benchmark's case names (benchmarks/bench_personalize.py): a bench case whose capture misses frames."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_personalize  # noqa: E402


def test_minus_names_a_bench_case_and_a_step():
    assert bench_personalize._minus("dev1/minus3") == ("dev1", 3)
    assert bench_personalize._minus("dev2/minus2") == ("dev2", 2)
    for other in ("dev1", "sample", "artist:3", "dev1/minus1", "dev1/minus", "dev1/minusx"):
        assert bench_personalize._minus(other) is None


def test_capture_minus_drops_every_kth_requested_frame_and_keeps_the_rest(tmp_path, monkeypatch):
    capture = tmp_path / "bench" / "devX" / "capture"
    (capture / "train").mkdir(parents=True)
    (capture / "template").mkdir()
    (capture / "test").mkdir()
    (capture / "neutral.obj").write_text("v 0 0 0\n")
    for i, name in enumerate(["eyeBlinkLeft", "jawOpen", "mouthClose", "mouthFunnel", "mouthPucker",
                              "browInnerUp", "cheekPuff"]):
        for ext in ("obj", "json"):
            (capture / "train" / f"{i:03d}_{name}.{ext}").write_text(f"{i}\n")
    monkeypatch.setattr(bench_personalize, "BENCH", tmp_path / "bench")
    out = bench_personalize._capture_minus("devX", 3)
    kept = sorted(p.name for p in (out / "train").iterdir())
    numbers = sorted({int(name.split("_")[0]) for name in kept})
    assert numbers == [0, 2, 3, 5, 6]                       # 1 and 4 (1 modulo 3) are gone
    assert len(kept) == 2 * len(numbers)                    # each frame's scan and its weights
    assert sorted(p.name for p in out.iterdir()) == ["neutral.obj", "template", "test", "train"]
    assert (out / "train" / "002_mouthClose.obj").read_text() == "2\n"     # the case's own files
    assert (out / "neutral.obj").resolve() == (capture / "neutral.obj").resolve()
