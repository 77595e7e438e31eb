"""usdface.memory: handing freed heap pages back to the OS changes no value."""

from __future__ import annotations

import numpy as np

from usdface import memory


def test_release_free_memory_keeps_every_value_and_reports_what_it_did(monkeypatch):
    kept = np.arange(1e6).reshape(-1, 4)
    before = kept.copy()
    for _ in range(8):                                   # freed blocks for the allocator to hand back
        np.ones((200_000, 3))
    assert isinstance(memory.release_free_memory(), bool)
    np.testing.assert_array_equal(kept, before)
    monkeypatch.setattr(memory, "_malloc_trim", lambda: None)        # not glibc: nothing to do
    assert memory.release_free_memory() is False
