"""Triangulations the unit tests build their synthetic meshes on."""

from __future__ import annotations

import numpy as np


def grid_triangles(nx: int, ny: int) -> np.ndarray:
    """``[2 (nx-1)(ny-1), 3]`` triangles of a row-major ``nx`` x ``ny`` vertex grid: per cell (row by row)
    ``[a, b, d]`` then ``[a, d, c]`` with ``a`` its lower-left corner, ``b = a + 1``, ``c = a + nx``,
    ``d = a + nx + 1``."""
    j, i = np.meshgrid(np.arange(ny - 1), np.arange(nx - 1), indexing="ij")
    a = (j * nx + i).ravel()
    b, c, d = a + 1, a + nx, a + nx + 1
    return np.stack([np.stack([a, b, d], 1), np.stack([a, d, c], 1)], axis=1).reshape(-1, 3)


def identity_correspondence(points: np.ndarray, triangles: np.ndarray):
    """The correspondence of a mesh onto itself (every vertex in the face, each a corner of one of its
    triangles, the face triangles their own source): ``M`` is the identity."""
    from usdface.transfer.correspond import Correspondence

    n = len(points)
    tri = np.asarray(triangles)
    first = np.full(n, -1)
    first[tri.ravel()] = np.arange(tri.size) // 3                 # any triangle of the vertex will do
    bary = (tri[first] == np.arange(n)[:, None]).astype(float)
    return Correspondence(first, bary, np.zeros(n), np.ones(n, dtype=bool), np.arange(len(tri)))
