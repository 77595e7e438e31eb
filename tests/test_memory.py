"""usdface.memory: handing freed heap pages back to the OS changes no value."""

from __future__ import annotations

import numpy as np

from usdface import memory
from usdface.motion import peak_motion


def test_release_free_memory_keeps_every_value_and_reports_what_it_did(monkeypatch):
    kept = np.arange(1e6).reshape(-1, 4)
    before = kept.copy()
    for _ in range(8):                                   # freed blocks for the allocator to hand back
        np.ones((200_000, 3))
    assert isinstance(memory.release_free_memory(), bool)
    np.testing.assert_array_equal(kept, before)
    monkeypatch.setattr(memory, "_malloc_trim", lambda: None)        # not glibc: nothing to do
    assert memory.release_free_memory() is False



def test_a_small_free_heap_is_kept(monkeypatch):
    """Below ``TRIM_MIN_FREE`` free bytes the heap is not trimmed (its pages would be faulted back in by the
    next step); at or above it, or when the free heap cannot be told, it is."""
    calls = []
    monkeypatch.setattr(memory, "_malloc_trim", lambda: lambda pad: calls.append(pad) or 1)
    monkeypatch.setattr(memory, "free_heap", lambda: memory.TRIM_MIN_FREE - 1)
    assert memory.release_free_memory() is False and calls == []
    assert memory.release_free_memory(0) is True and calls == [0]
    monkeypatch.setattr(memory, "free_heap", lambda: memory.TRIM_MIN_FREE)
    assert memory.release_free_memory() is True
    monkeypatch.setattr(memory, "free_heap", lambda: None)
    assert memory.release_free_memory() is True and len(calls) == 3
    monkeypatch.undo()
    assert memory.free_heap() is None or memory.free_heap() >= 0

def test_float32_offsets_hold_the_readers_values_to_the_last_bit():
    """The reader's conversion (float32 authored offsets @ linear.T: cm to m, Z up to Y up) packed and
    expanded gives the same float64 values; values that are not float32 @ linear.T are refused (None)."""
    rng = np.random.default_rng(5)
    authored = rng.normal(scale=2.0, size=(4, 50, 3)).astype(np.float32)
    authored[1, :10] = 0.0
    linear = 0.01 * np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    deltas = np.stack([a.astype(np.float64) @ linear.T for a in authored])
    packed = memory.Float32Offsets.pack(deltas, linear)
    assert packed is not None and packed.shape == deltas.shape and packed.nbytes == deltas.nbytes // 2
    np.testing.assert_array_equal(packed.expand(), deltas)
    np.testing.assert_array_equal(packed[2], deltas[2])
    np.testing.assert_array_equal(packed[1:3], deltas[1:3])
    np.testing.assert_allclose(packed.peak_motion(), peak_motion(deltas), rtol=1e-15)
    assert np.allclose(memory.Float32Offsets(packed.authored, linear).peak_motion(), peak_motion(deltas))
    assert memory.Float32Offsets.pack(deltas + 1e-12, linear) is None           # not float32 values
    scaled = np.stack([a.astype(np.float64) * 0.01 for a in authored])          # cm to m, axes kept
    np.testing.assert_array_equal(memory.Float32Offsets.pack(scaled, 0.01 * np.eye(3)).expand(), scaled)
    turn = 0.01 * np.array([[0.8, -0.6, 0.0], [0.6, 0.8, 0.0], [0.0, 0.0, 1.0]])   # not an axis map
    turned = np.stack([a.astype(np.float64) @ turn.T for a in authored])
    packed = memory.Float32Offsets.pack(turned, turn)
    assert packed is not None
    np.testing.assert_array_equal(packed.expand(), turned)
    assert memory.Float32Offsets.pack(deltas, np.zeros((3, 3))) is None          # singular map
