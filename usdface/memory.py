"""Handing freed memory back to the operating system between the large steps of a run.

A run frees many arrays of a few megabytes (the reader's per-shape offsets, USD's own buffers, the field's
chunks). glibc's allocator keeps such freed blocks in its heap for reuse (its mmap threshold rises to the
size of the blocks freed, up to 32 MB), so the process's resident memory stays at its high-water mark while
the next step maps fresh pages for its larger arrays. ``malloc_trim(0)`` returns the free heap pages; this is
the remedy Dask documents for "unmanaged memory" on Linux workers. It changes no value, only the resident
set size; elsewhere (macOS, Windows, musl) it does nothing.
A heap holding less than :data:`TRIM_MIN_FREE` free bytes is left as it is (the next step would fault
the pages back in).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools

import numpy as np


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


#: Free heap below this is kept, not handed back: the next step allocates it again, and faulting the pages
#: back in costs more than the resident memory saved (dev1's run trims 10-54 MB at each of its five
#: calls: 40,000 more page faults, 0.15-0.2 s of system time, for 25 MB less peak RSS); a production head
#: frees hundreds of megabytes between its steps and is trimmed as before.
TRIM_MIN_FREE = 64 << 20


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks",
        "keepcost")]


@functools.cache
def _mallinfo2():
    """glibc's ``mallinfo2`` (2.33+), or None."""
    name = ctypes.util.find_library("c")
    try:
        info = ctypes.CDLL(name or "libc.so.6").mallinfo2
    except (OSError, AttributeError):
        return None
    info.argtypes, info.restype = [], _MallInfo2
    return info


def free_heap() -> int | None:
    """Bytes of free blocks the allocator holds in its heap (glibc ``mallinfo2().fordblks``), or None when
    it cannot be told."""
    info = _mallinfo2()
    return int(info().fordblks) if info is not None else None


def release_free_memory(min_free: int = TRIM_MIN_FREE) -> bool:
    """Give the allocator's free heap pages back to the OS (glibc ``malloc_trim(0)``) when it holds at least
    ``min_free`` bytes of them (:data:`TRIM_MIN_FREE`; unknown: always); True when it did."""
    trim = _malloc_trim()
    if trim is None:
        return False
    free = free_heap() if min_free > 0 else None
    if free is not None and free < min_free:
        return False
    return bool(trim(0))


class Float32Offsets:
    """Offsets ``[K,n,3]`` float64 held as float32 ``authored[K,n,3]`` and one linear map ``linear[3,3]``,
    expanded shape by shape as ``authored[k] @ linear.T``: the reader's own conversion of a USD file's float32
    offsets to internal metres (a cm-to-m scale, an up-axis rotation), so half the memory of the float64
    array and the same values to the last bit (:meth:`pack` checks every shape; when it cannot hold them
    exactly it returns None). ``self[k]``, ``self[lo:hi]`` and :meth:`expand` give float64 arrays.

    Examples
    --------
    >>> d = np.float32([[[1.5, -2.0, 0.25]]]).astype(np.float64) @ (0.01 * np.eye(3)).T
    >>> packed = Float32Offsets.pack(d, 0.01 * np.eye(3))
    >>> bool(np.array_equal(packed.expand(), d)), packed.shape
    (True, (1, 1, 3))
    """

    def __init__(self, authored, linear):
        self.authored = authored
        self.linear = np.asarray(linear, dtype=np.float64)
        self.peak = None                             # [n] the largest offset of each vertex (from pack)
        # a scaled axis permutation (a snapped cm/up-axis map): one product per coordinate, no matrix
        # product (the same values: the other terms are exact zeros; :meth:`pack` checks them anyway)
        nonzero = self.linear != 0.0
        self._axes = (np.argmax(nonzero, axis=1) if (nonzero.sum(axis=1) == 1).all()
                      and (nonzero.sum(axis=0) == 1).all() else None)

    @classmethod
    def pack(cls, deltas, linear, peak=None) -> Float32Offsets | None:
        """``deltas[K,n,3]`` (float64) as float32 authored values, or None where one shape's values are not
        exactly ``float32 @ linear.T`` (offsets not read from float32, a singular map). ``peak[n]``:
        :func:`usdface.motion.peak_motion` of ``deltas`` when the caller has it (else computed here)."""
        d = np.asarray(deltas)
        lin = np.asarray(linear, dtype=np.float64)
        if d.dtype != np.float64 or d.ndim != 3 or d.shape[-1] != 3 or abs(np.linalg.det(lin)) < 1e-300:
            return None
        inverse = np.linalg.inv(lin).T
        out = cls(np.empty(d.shape, dtype=np.float32), lin)
        square = np.zeros(d.shape[1]) if peak is None else None
        for k in range(len(d)):
            out.authored[k] = d[k] @ inverse
            if not np.array_equal(out[k], d[k]):
                return None
            if square is not None:
                np.maximum(square, np.einsum("nc,nc->n", d[k], d[k]), out=square)
        out.peak = np.sqrt(square) if peak is None else peak
        return out

    def peak_motion(self) -> np.ndarray:
        """``[n]`` the largest offset of each vertex over the shapes (:func:`usdface.motion.peak_motion`)."""
        if self.peak is None:
            square = np.zeros(self.shape[1])
            for k in range(len(self)):
                d = self[k]
                np.maximum(square, np.einsum("nc,nc->n", d, d), out=square)
            self.peak = np.sqrt(square)
        return self.peak

    @property
    def shape(self) -> tuple:
        return self.authored.shape

    @property
    def dtype(self):
        return np.dtype(np.float64)

    @property
    def nbytes(self) -> int:
        return int(self.authored.nbytes)

    def __len__(self) -> int:
        return len(self.authored)

    def __getitem__(self, shapes) -> np.ndarray:
        """Float64 offsets of one shape ``[n,3]`` or of a slice of shapes ``[k,n,3]``."""
        a = self.authored[shapes]
        if a.ndim == 2:
            return self._expand(a)
        out = np.empty(a.shape)
        for k in range(len(a)):                      # shape by shape: no copy of them all
            self._expand(a[k], out=out[k])
        return out

    def take(self, shapes, vertices) -> np.ndarray:
        """Float64 offsets ``[k,s,3]`` of a slice of shapes at the vertices ``vertices[s]`` only: the same
        values as ``self[shapes][:, vertices]`` without expanding the others."""
        a = self.authored[shapes]
        out = np.empty((len(a), len(vertices), 3))
        for k in range(len(a)):
            self._expand(a[k][vertices], out=out[k])
        return out

    def _expand(self, a, out=None) -> np.ndarray:
        """One shape's float64 offsets ``[n,3]`` from its float32 ``a[n,3]``, written into ``out`` (float64
        ``[n,3]``) when given (no temporary)."""
        if self._axes is not None:
            scale = self.linear[np.arange(3), self._axes]
            return np.multiply(a if (self._axes == np.arange(3)).all() else a[:, self._axes], scale, out=out)
        if out is None:
            return a.astype(np.float64) @ self.linear.T
        out[...] = a.astype(np.float64) @ self.linear.T
        return out

    def expand(self) -> np.ndarray:
        """The float64 ``[K,n,3]`` array."""
        return self[:]
