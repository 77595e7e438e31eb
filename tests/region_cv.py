"""Eq. (4)'s leave-one-region-out choice of ``mu``, computed the long way (explicit ridge solves per region,
row and ``mu`` of the grid): the reference the closed form in :mod:`usdface.transfer.retarget` is tested
against."""

from __future__ import annotations

import numpy as np

from usdface.transfer.retarget import MU_GRID, face_regions


def region_errors(basis, targets, prior, points, held=None) -> np.ndarray:
    """``[len(MU_GRID)]``: the error of predicting each region of ``points[n,3]`` (:func:`face_regions`) with
    the map solved on the other regions, summed over the regions and the rows, for each ``mu``.
    ``basis[K,n,3]``, ``targets[J,n,3]``, ``prior[J,K]`` (the ridge's centre), ``held[J,K]`` entries fixed at
    0 (None: none)."""
    label = face_regions(points)
    k = len(basis)
    A = np.moveaxis(basis, 0, -1).reshape(-1, k)                                      # [3n, K]
    lam_unit = np.trace(A.T @ A) / k
    held = np.zeros((len(targets), k), dtype=bool) if held is None else np.asarray(held, dtype=bool)
    errors = []
    for m in MU_GRID:
        e = 0.0
        for r in np.unique(label):
            out = np.repeat(label == r, 3)
            for j, target in enumerate(targets):
                f, t = ~held[j], np.asarray(target).ravel()
                a_in = A[~out][:, f]
                w = np.linalg.solve(a_in.T @ a_in + m * lam_unit * np.eye(f.sum()),
                                    a_in.T @ t[~out] + m * lam_unit * prior[j, f])
                e += np.sum((t[out] - A[out][:, f] @ w) ** 2)
        errors.append(e)
    return np.asarray(errors)


def parabola_mu(errors) -> tuple[int, float]:
    """(the grid index of the smallest error, the ``mu`` of the vertex of the parabola through it and its two
    neighbours in log ``mu``); the minimum must be inside the grid (so a test built on it can fail)."""
    best = int(np.argmin(errors))
    assert 0 < best < len(MU_GRID) - 1
    a, b, _ = np.polyfit(np.log(MU_GRID[best - 1:best + 2]), errors[best - 1:best + 2], 2)
    return best, float(np.exp(-b / (2 * a)))
