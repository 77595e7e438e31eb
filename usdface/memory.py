"""Handing freed memory back to the operating system between the large steps of a run.

A run frees many arrays of a few megabytes (the reader's per-shape offsets, USD's own buffers, the field's
chunks). glibc's allocator keeps such freed blocks in its heap for reuse (its mmap threshold rises to the
size of the blocks freed, up to 32 MB), so the process's resident memory stays at its high-water mark while
the next step maps fresh pages for its larger arrays. ``malloc_trim(0)`` returns the free heap pages; this is
the remedy Dask documents for "unmanaged memory" on Linux workers. It changes no value, only the resident
set size; elsewhere (macOS, Windows, musl) it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools


@functools.cache
def _malloc_trim():
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):        # not glibc
        return None
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return trim


def release_free_memory() -> bool:
    """Give the allocator's free heap pages back to the OS (glibc ``malloc_trim(0)``); True when it did."""
    trim = _malloc_trim()
    return bool(trim(0)) if trim is not None else False
