"""Blendshape weights from tracked landmarks, and the reconstruction error of a layout.

Given tracked landmark positions ``targets[F, m, 3]`` the weights solve, per frame, the bounded, optionally
Tikhonov-regularised least squares

    min_w  sum_i |neutral_i + sum_k w_k dv_i^k - target_i|^2 + lambda |w|^2,   0 <= w_k <= 1,

(all frames at once: one ``lstsq``, then for the frames outside the bounds an ADMM start and a batched
active-set method, :mod:`usdface.bounded_lsq`, with scipy's BVLS ``lsq_linear`` as a per-frame safety net;
the minimum-norm optimum when the landmarks leave several), the mesh is rebuilt as ``neutral + w @ deltas``
and compared with the truth.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import lsq_linear

from ..bounded_lsq import admm_box_start, box_least_squares
from ..errors import LandmarkError


def solve_weights(landmark_deltas: np.ndarray, offsets: np.ndarray, tikhonov: float = 0.0,
                  bounds: tuple[float, float] = (0.0, 1.0)) -> np.ndarray:
    """Bounded least-squares blendshape weights from landmark offsets (Zell & McDonnell 2022, sec. 4).

    ``landmark_deltas[K, m, 3]`` metres (the rig's deltas at the landmarks), ``offsets[F, m, 3]`` metres
    (tracked positions minus the neutral landmarks), ``tikhonov`` lambda >= 0 (metres^2 per unit weight^2)
    -> ``weights[F, K]`` within ``bounds``.
    """
    d = np.asarray(landmark_deltas, dtype=np.float64)
    b = np.asarray(offsets, dtype=np.float64)
    if b.ndim == 2:
        b = b[None]
    k, m = d.shape[0], d.shape[1]
    if b.shape[1:] != (m, 3):
        raise LandmarkError(f"offsets {b.shape} do not match {m} landmarks")
    a = d.reshape(k, 3 * m).T  # [3m, K]
    rhs = b.reshape(len(b), 3 * m)
    if tikhonov > 0.0:
        a = np.vstack([a, np.sqrt(tikhonov) * np.eye(k)])
        rhs = np.hstack([rhs, np.zeros((len(b), k))])
    lo, hi = bounds
    # frames whose unconstrained least-squares solution (the minimum-norm one) is already inside the bounds
    # are solved (convexity); the rest are solved together (batched active set, :func:`box_least_squares`)
    out = np.linalg.lstsq(a, rhs.T, rcond=None)[0].T
    outside = np.flatnonzero(((out < lo) | (out > hi)).any(axis=1))
    if outside.size == 0:
        return out
    gram = a.T @ a
    if np.linalg.matrix_rank(a) < k:
        # fewer independent landmark coordinates than shapes: a whole set of weights is optimal; take the
        # (near) minimum-norm one, as lstsq does for the frames above, via a vanishing ridge
        ridge = RANK_DEFICIENT_RIDGE * max(float(np.trace(gram)) / k, 1e-300)
        gram = gram + ridge * np.eye(k)
        a = np.vstack([a, np.sqrt(ridge) * np.eye(k)])
        rhs = np.hstack([rhs, np.zeros((len(rhs), k))])
    c = rhs[outside] @ a
    start = admm_box_start(gram, c, lo, hi, out[outside])
    out[outside], converged = box_least_squares(gram, c, lo, hi, start)
    for f in outside[~converged]:  # safety net: scipy's BVLS, one frame at a time
        out[f] = lsq_linear(a, rhs[f], bounds=(lo, hi), method="bvls").x
    return out


#: Relative ridge (of the mean diagonal of A^T A) that picks the minimum-norm optimum of a rank-deficient
#: bounded least squares: it changes the objective by a relative ~1e-9, far below the tracking noise.
RANK_DEFICIENT_RIDGE = 1e-9


def tracked_landmarks(neutral: np.ndarray, deltas: np.ndarray, vertices: np.ndarray, weights: np.ndarray,
                      noise: float = 0.0, seed: int = 0) -> np.ndarray:
    """Simulated tracking: landmark positions of the linear rig at ``weights[F, K]`` plus isotropic Gaussian
    noise of standard deviation ``noise`` metres per coordinate -> ``[F, m, 3]`` metres."""
    v = np.asarray(vertices, dtype=np.int64)
    w = np.asarray(weights, dtype=np.float64)
    pos = neutral[v][None] + np.einsum("fk,kmc->fmc", w, deltas[:, v])
    if noise > 0.0:
        pos = pos + np.random.default_rng(seed).normal(0.0, noise, pos.shape)
    return pos


def reconstruction_rmse(deltas: np.ndarray, weights_true: np.ndarray, weights_est: np.ndarray,
                        vertices: np.ndarray | None = None) -> float:
    """RMSE (metres) over frames and vertices between ``neutral + w_true @ deltas`` and
    ``neutral + w_est @ deltas``; ``deltas[K, n, 3]``, ``weights[F, K]``; ``vertices`` restricts the average
    (e.g. to the moving face region). Exact for a linear rig, via the K x K Gram matrix (no mesh rebuilt)."""
    d = np.asarray(deltas, dtype=np.float64)
    if vertices is not None:
        d = d[:, np.asarray(vertices)]
    flat = d.reshape(d.shape[0], -1)
    gram = flat @ flat.T
    dw = np.asarray(weights_est, dtype=np.float64) - np.asarray(weights_true, dtype=np.float64)
    sq = np.einsum("fk,kl,fl->f", dw, gram, dw)
    return float(np.sqrt(max(sq.mean(), 0.0) / d.shape[1]))


def layout_error(neutral: np.ndarray, deltas: np.ndarray, vertices: np.ndarray, weights: np.ndarray,
                 noise: float = 0.5e-3, tikhonov: float = 0.0, seed: int = 0,
                 region: np.ndarray | None = None) -> float:
    """Reconstruction RMSE (metres) of a landmark layout (Zell & McDonnell 2022, sec. 4): track ``vertices``
    through ``weights[F, K]`` with ``noise`` metres of tracking noise, solve the weights
    (:func:`solve_weights`), rebuild, compare over ``region`` vertices (default all)."""
    v = np.asarray(vertices, dtype=np.int64)
    if v.size == 0:
        raise LandmarkError("empty landmark layout", fix="pass at least one landmark vertex")
    pos = tracked_landmarks(neutral, deltas, v, weights, noise, seed)
    est = solve_weights(deltas[:, v], pos - neutral[v][None], tikhonov)
    return reconstruction_rmse(deltas, weights, est, region)
