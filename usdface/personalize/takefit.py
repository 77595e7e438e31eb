"""Beyond Menzel et al. (2022): fitting on every frame of a recorded take, not one peak frame per shape.

A take has hundreds of frames: long runs of near-identical poses (rest, the plateau of a sweep) and a few
frames in between. Fitting eq. (1) on all of them with equal weight lets the most repeated poses dominate;
weighting each frame by the inverse of the number of frames with (nearly) the same weights makes every
distinct pose count about once, while the repeats still average out the scan noise of that pose.
:func:`balanced_frame_weights` computes those weights; ``fit_personalized_shapes(capture,
frame_weights=...)`` uses them in E_fit (``sum_i omega_i ||B0 + sum_j w_ij B_j - S_i||^2``) and in the
leave-one-frame-out criterion.
"""

from __future__ import annotations

import numpy as np

__all__ = ["balanced_frame_weights", "distinct_poses", "pose_counts", "unique_excitation", "weight_noise",
           "weighted_frames", "cv_block",
           "correlation_frames", "CORRELATION_LEVEL", "MIN_FOLDS", "HALF_CORRELATION"]

#: The weight curves are taken as decorrelated from a lag at which their mean autocorrelation is this low.
CORRELATION_LEVEL = 0.1
#: The cross-validation of a take keeps at least this many blocks.
MIN_FOLDS = 5
#: A take's cross-validation holds out the frames whose weights correlate with the left-out one's above this.
HALF_CORRELATION = 0.5


def balanced_frame_weights(weights: np.ndarray, radius: float = 0.05) -> np.ndarray:
    """``omega[F]`` for the frames' blendshape weights ``weights[F,K]``: 1 / (number of frames whose weight
    vector lies within ``radius`` of this frame's - RMS over the K weights, so the radius means "every weight
    within about ``radius``", independent of K; itself included), normalised to mean 1. A pose held for 30
    frames then weighs as much as a pose passed through once; the default (0.05) is above the phone's weight
    noise (~0.01-0.03), so noisy repeats of one pose count as that pose."""
    W = np.asarray(weights, dtype=np.float64)
    if len(W) == 0:
        return np.zeros(0)
    omega = 1.0 / pose_counts(W, radius)
    return omega * (len(W) / omega.sum())


def distinct_poses(weights: np.ndarray, radius: float = 0.05) -> float:
    """How many distinct poses the frames' weights ``weights[F,K]`` show: ``sum_i 1 / count_i`` with
    ``count_i`` the frames within ``radius`` of frame i (:func:`balanced_frame_weights`' neighbourhoods): a
    pose held for 600 frames counts 1, 600 different poses count 600."""
    W = np.asarray(weights, dtype=np.float64)
    return float(np.sum(1.0 / pose_counts(W, radius))) if len(W) else 0.0


def pose_counts(weights: np.ndarray, radius: float = 0.05) -> np.ndarray:
    """``[F]``: the number of frames whose weight vector lies within ``radius`` (RMS over the K weights) of
    each frame's, itself included."""
    W = np.asarray(weights, dtype=np.float64)
    r2 = radius ** 2 * W.shape[1]
    # Counting neighbours in K ~ 52 dimensions: a k-d tree degrades to brute force there (0.9 s for 2,248
    # frames); the pairwise distances by blocks of rows through one matrix product are ~20x faster, with
    # memory bounded by the block (about 4M distances).
    sq = np.einsum("ij,ij->i", W, W)
    counts = np.empty(len(W))
    step = max(1, (1 << 22) // len(W))
    for s in range(0, len(W), step):
        d2 = sq[s:s + step, None] + sq[None, :] - 2.0 * (W[s:s + step] @ W.T)
        counts[s:s + step] = np.count_nonzero(d2 <= r2, axis=1)
    return np.maximum(counts, 1.0)  # itself, whatever the rounding


def weighted_frames(neutral: np.ndarray, points: np.ndarray, weights: np.ndarray, omega: np.ndarray):
    """Frames and weights scaled by ``sqrt(omega)`` about the neutral, so that the unweighted eqs. (1)+(2)
    on them are the frame-weighted fit: ``(neutral + sqrt(omega_i) (S_i - B0), sqrt(omega_i) w_i)``."""
    s = np.sqrt(np.asarray(omega, dtype=np.float64))
    B0 = np.asarray(neutral, dtype=np.float64)
    P = B0[None] + s[:, None, None] * (np.asarray(points, dtype=np.float64) - B0[None])
    return P, s[:, None] * np.asarray(weights, dtype=np.float64)


def weight_noise(weights: np.ndarray) -> float:
    """The phone's weight noise, measured on a take: ``weights[F,K]`` in time order. A face moves smoothly
    from frame to frame, the solver's jitter does not: the second difference ``w_f - (w_{f-1} + w_{f+1}) / 2``
    of white noise of standard deviation ``sigma`` has variance ``1.5 sigma^2``, of smooth motion about 0.
    Returns ``sigma`` (weight units), the RMS over the frames and shapes; ``nan`` with fewer than 3 frames.
    The motion's own curvature (a subsampled take, fast moves) makes it larger, never smaller: a
    conservative figure."""
    W = np.asarray(weights, dtype=np.float64)
    if W.ndim != 2 or len(W) < 3 or W.shape[1] == 0:
        return float("nan")
    d = W[1:-1] - 0.5 * (W[:-2] + W[2:])
    return float(np.sqrt(np.mean(d * d) / 1.5))


def unique_excitation(weights: np.ndarray, noise: float) -> np.ndarray:
    """``[K]``: how strongly a take shows each shape *on its own*, beyond what its weight noise alone would
    show (weight units). ``weights[F,K]``, ``noise`` the weights' standard deviation (:func:`weight_noise`).

    The part of shape j's weight column that the other shapes' columns do not explain has energy
    ``1 / [(W^T W)^+]_jj`` (the precision of j's least-squares coefficient); a column of pure noise has
    ``F noise^2`` of it. Returns ``sqrt(max(0, 1 / [(W^T W)^+]_jj - F noise^2))``: 0 for a shape the take
    shows only in a fixed ratio to another (a mirror partner's cross-talk: their sum is measured, not each)
    or only at the noise's level (a shape never performed). The total energy ``sum_f w_fj^2`` grows with
    every frame of cross-talk and noise, so on a take of hundreds of frames it calls such a shape well
    shown."""
    W = np.asarray(weights, dtype=np.float64)
    F, K = W.shape
    if F == 0 or K == 0:
        return np.zeros(K)
    G = W.T @ W
    # a vanishing ridge keeps an exactly collinear pair at ~0 (a pseudo-inverse would call each of two
    # equal columns a quarter of their energy unique)
    eps = 1e-10 * max(float(np.max(np.diag(G))), 1e-300)
    inv_diag = np.diag(np.linalg.inv(G + eps * np.eye(K)))
    unique = 1.0 / np.maximum(inv_diag, 1e-300)
    return np.sqrt(np.maximum(0.0, unique - F * float(noise) ** 2))


def correlation_frames(weights: np.ndarray, level: float = CORRELATION_LEVEL) -> int:
    """The frames over which a take's weight curves ``weights[F,K]`` (time order) stay correlated: the first
    lag at which the mean autocorrelation of the centred curves (those that vary) falls to ``level`` or
    below; 1 for fewer than 3 frames or curves that never vary, ``F // 2`` if they never decorrelate. On
    the sample generator's takes (15 fps) 8 frames; on the real Live Link Face recordings in ../shared
    (30 fps) 41-116 frames, 1.4-3.9 s: an expression's duration."""
    W = np.asarray(weights, dtype=np.float64)
    F = len(W)
    if W.ndim != 2 or F < 3:
        return 1
    X = W - W.mean(axis=0)
    var = np.einsum("fk,fk->k", X, X)
    X = X[:, var > 1e-12 * max(float(var.max()), 1e-300)]
    if X.shape[1] == 0:
        return 1
    var = np.einsum("fk,fk->k", X, X)
    # all lags at once: the autocovariance by FFT (zero-padded, no circular wrap)
    n = 1 << int(np.ceil(np.log2(2 * F)))
    spec = np.fft.rfft(X, n=n, axis=0)
    acov = np.fft.irfft(spec * np.conj(spec), n=n, axis=0)[:F // 2 + 1]
    mean = (acov / var).mean(axis=1)
    below = np.flatnonzero(mean[1:] <= level)
    return int(below[0] + 1) if below.size else F // 2


def cv_block(weights: np.ndarray) -> int:
    """A block length for leave-block-out cross-validation of a take (h-block cross-validation, Burman,
    Chow & Nolan 1994; :meth:`usdface.personalize.fit.PositionFit._block_residuals`,
    ``choose_regularization(block=...)``): the weights' half-correlation time, the first lag at which their
    mean autocorrelation falls to 0.5 (:func:`correlation_frames`): the neighbours that show nearly the same
    pose leave with the frame, but never a whole expression; at most ``F // MIN_FOLDS`` frames, 1 when the
    weights decorrelate at once. Not the default (measured in docs/takes.md: the fit gains or ties, but the
    avatar lost 31 % on a noisy 30 fps take through the data share the implant trusts)."""
    F = len(np.asarray(weights))
    lag = correlation_frames(weights, HALF_CORRELATION)
    return 1 if lag <= 1 else int(max(1, min(lag, F // MIN_FOLDS)))
