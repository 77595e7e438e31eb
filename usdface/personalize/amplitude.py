"""Beyond the papers: each fitted shape's amplitude read a second time, on the capture's test frames.

A shape's scale is fixed by its weight in its peak frame (:func:`.weights.held_weights`: there the
weight and the amplitude are not separately identifiable, ``w B = (c w)(B / c)``), so the phone's error
in that one weight is the shape's amplitude error, ``sigma_w / w_peak`` of the shape: a 1-sigma draw of
0.03 at a peak of 0.94 is 3 % of a 13 mm ``jawOpen``, 0.4 mm, the size by which a person's jaw differs
from the avatar's. No other training frame sees it, and the trust's leak and sensitivity hold that
weight. The capture's test frames (mixed expressions the fit does not use, each with the phone's own
weights) are independent draws: each shows the shape at its reported weight beside the others, and
together they measure how far the fitted shape must be scaled to explain them. The two readings of one
amplitude, each with its own variance, are combined by inverse variance (the Gaussian posterior of the
scale given both): where the test frames show the shape strongly the peak weight's draw is corrected,
where they show it weakly the fit stands.

Arrays in, arrays out; shapes ``[K,n,3]`` metres, weights ``[F,K]``.
"""

from __future__ import annotations

import numpy as np

from .weights import peak_frames

__all__ = ["amplitude_terms", "combined_amplitude", "each_frame_left_out", "held_out_amplitude",
           "peak_amplitude_variance", "personalization_reading"]


def peak_amplitude_variance(weights, variance) -> np.ndarray:
    """``[K]``: the relative variance of each fitted shape's amplitude from its peak frame's weight,
    ``var_peak / w_peak^2`` (``weights[F,K]`` the phone's training reports, ``variance[F,K]`` their error
    variances, :func:`.weights.weight_error_variance` with every entry free; the peak frame
    :func:`.weights.peak_frames`). The shape is fitted as ``w_peak B``'s motion: a reported ``w_peak (1 + x)``
    makes it ``B / (1 + x)``, a relative error ``-x`` of sd ``sigma_peak / w_peak``."""
    w = np.asarray(weights, dtype=np.float64)
    peak = peak_frames(w)
    cols = np.arange(w.shape[1])
    return np.asarray(variance, dtype=np.float64)[peak, cols] / np.maximum(w[peak, cols], 1e-3) ** 2


def held_out_amplitude(neutral, points, weights, deltas, variance, *,
                       terms=None) -> tuple[np.ndarray, np.ndarray]:
    """``(a[K], var[K])``: each fitted shape's amplitude as the test frames read it, relative to the fitted
    shape (1: the fit's own), and its variance from the test weights' errors. ``neutral[n,3]``,
    ``points[T,n,3]`` metres, ``weights[T,K]`` the phone's reports, ``deltas[K,n,3]`` the fitted shapes,
    ``variance[T,K]`` each report's error variance (:func:`.weights.weight_error_variance`).

    Frame ``t``'s residual at the reported weights, ``R_t = P_t - N - sum_m r_tm B_m``, holds
    ``(a_k - 1) w_tk B_k`` of a shape whose true amplitude is ``a_k`` times the fitted one. Projected on
    ``B_k`` and weighted by the frame's report: ``a_k - 1 = sum_t r_tk <R_t, B_k> / den_k``, ``den_k =
    |B_k|^2 sum_t (r_tk^2 - v_tk)``, the least-squares scale of each shape on its own (a joint fit over
    all shapes reads the other shapes' errors of shape as amplitudes: a generated person's 44 readings
    scattered 1.8 sd above their truth, these 0.3). The reports err by ``e_tk`` (``E e^2 = v_tk``) in the
    regressor too, so ``sum r^2`` exceeds ``sum w^2`` by ``V = sum_t v_tk``, taken off the denominator.
    The numerator keeps the reports' own ``-e_tk B_k`` in the residual: on the model alone the reading is
    ``V / W`` low (``W = sum_t (r_tk^2 - v_tk)``; tests/test_amplitude.py). It is kept so because on fitted
    shapes it is what reads the truth: on six generated people (scan 0.05-0.15 mm, weights +-0.01-0.08)
    the 42 readings the combination weighs at least 0.3 scatter about the truth's scale (its optimum,
    ``<T_k, B_k> / |B_k|^2``) at a mean z-score of 0.03, with ``V / W`` added back at 0.47.

    The variance: each report's error moves ``R_t`` by ``-e_tm B_m``, so ``sum_t r_tk^2 sum_m v_tm <B_k,
    B_m>^2 / den_k^2``; and the residual holds what no weight explains (the other fitted shapes' errors of
    shape, the scans' noise, motion no blend of the shapes makes): its part along ``B_k``, ``c_k``, read in
    the frames that do not report the shape (there ``<R_t, B_k>`` holds no amplitude of it) as the mean of
    ``<R_t, B_k>^2 - sum_m v_tm <B_k, B_m>^2`` over them (over every frame if each reports it), at least 0,
    adds ``sum_t r_tk^2 c_k / den_k^2``. Without it a capture whose weights are the phone mesh's own (the
    weights' noise 0.0005) reads the fitted shapes' errors at that noise's tiny variance. A shape the test
    frames do not show (``den <= 0``; every shape when ``T = 0``) reads 1 at infinite variance. ``terms``:
    :func:`amplitude_terms` of these arrays if the caller has them (:func:`each_frame_left_out` sums the
    same; :func:`personalization_reading` passes them read along another pattern)."""
    terms = amplitude_terms(neutral, points, weights, deltas, variance) if terms is None else terms
    if terms is None:                                # no test frames: every shape unseen
        K = np.asarray(weights).shape[1]
        return np.ones(K), np.full(K, np.inf)
    return _reading(terms, None)


def personalization_reading(neutral, points, weights, deltas, prior,
                            variance) -> tuple[np.ndarray, np.ndarray]:
    """``(a[K], var[K])``: the scale of each fitted shape's personalization ``d_k = B_k - P_k`` (``deltas``,
    ``prior`` ``[K,n,3]`` metres, the fitted shapes and the prior the fit shrank them towards) as the test
    frames read it, and its variance; same ``neutral``, ``points``, ``weights``, ``variance`` as
    :func:`held_out_amplitude`, whose reading this is with the residual projected on ``d_k`` instead of
    ``B_k``: ``a_k = 1 + sum_t r_tk <R_t, d_k> / (|d_k|^2 sum_t (r_tk^2 - v_tk))``.

    If the person's shape is ``T_k = P_k + c_k d_k + o_k`` (``o_k`` orthogonal to ``d_k``: ``c_k`` the scale
    of the fitted personalization nearest the person's, the trust's target), frame ``t``'s residual holds
    ``(c_k - 1) w_tk d_k`` along ``d_k``, so ``a_k`` reads ``c_k``, with the variance model of
    :func:`held_out_amplitude` (the reports' errors and what no weight explains, read in the frames that do
    not report the shape). A shape the test frames do not show, or whose fit is its prior (``d_k = 0``),
    reads 1 at infinite variance."""
    along = np.asarray(deltas, dtype=np.float64) - np.asarray(prior, dtype=np.float64)
    return held_out_amplitude(neutral, points, weights, deltas, variance,
                              terms=amplitude_terms(neutral, points, weights, deltas, variance, along=along))


def each_frame_left_out(neutral, points, weights, deltas, variance, *,
                        terms=None) -> tuple[np.ndarray, np.ndarray]:
    """``(a[T,K], var[T,K])``: :func:`held_out_amplitude` read once per test frame ``t`` on the other
    ``T - 1`` frames (same arguments): the reading with which frame ``t`` is scored when the fit reads its
    amplitudes on the test frames (eq. 5 cross-fitted: no frame scores a reading it took part in). Each sum
    of the reading (numerator, denominator, variance, the unexplained part's mean over the frames that do
    not report the shape) less frame ``t``'s own term, so row ``t`` equals :func:`held_out_amplitude` of the
    frames without ``t`` exactly. ``[0,K]`` with no test frames. ``terms``: :func:`amplitude_terms` of these
    arrays if the caller has them."""
    terms = amplitude_terms(neutral, points, weights, deltas, variance) if terms is None else terms
    if terms is None:
        K = np.asarray(weights).shape[1]
        return np.ones((0, K)), np.full((0, K), np.inf)
    return _reading(terms, np.eye(len(terms["rr"]), dtype=bool))


def amplitude_terms(neutral, points, weights, deltas, variance, *, along=None) -> dict | None:
    """Per test frame and shape, the terms :func:`held_out_amplitude` and :func:`each_frame_left_out` sum
    over frames (``[T,K]`` each; the shapes' squared norms ``[K]``), or None with no test frames: formed once
    when a caller reads both (the shapes' Gram matrix and every frame's projection on them). ``along[K,n,3]``
    (metres): read each shape's residual along this pattern instead of the shape itself (the scale of a part
    of the shape, :func:`personalization_reading`); the shapes ``deltas`` still explain the frames."""
    r = np.asarray(weights, dtype=np.float64)
    v = np.asarray(variance, dtype=np.float64)
    if len(r) == 0:
        return None
    A = np.asarray(deltas, dtype=np.float64).reshape(r.shape[1], -1)                    # [K, 3n]
    D = A if along is None else np.asarray(along, dtype=np.float64).reshape(r.shape[1], -1)
    Y = np.asarray(points, dtype=np.float64) - np.asarray(neutral, dtype=np.float64)[None]
    Y = Y.reshape(len(r), -1)                                                          # [T, 3n]
    cross = D @ A.T                                                                    # [K,K] <D_k, B_m> m^2
    proj = (Y - r @ A) @ D.T                                                           # [T,K] <R_t, D_k>
    by_weights = v @ (cross * cross).T                                                 # [T,K] m^4
    norm2 = np.einsum("ki,ki->k", D, D)
    return {"num": r * proj, "rr": r * r - v, "norm2": norm2, "r2": r * r,
            "r2b": r * r * by_weights, "excess": proj ** 2 - by_weights, "off": r == 0.0}


def _reading(terms, left_out) -> tuple[np.ndarray, np.ndarray]:
    """The reading and its variance from :func:`_amplitude_terms`: over every frame (``left_out`` None:
    ``[K]``), or once per row of ``left_out[L,T]`` (bool) over the frames it does not mark (``[L,K]``)."""
    def total(x):
        """``x[T,K]`` summed over the frames kept: ``[K]``, or ``[L,K]`` per row of ``left_out``."""
        return x.sum(axis=0) if left_out is None else x.sum(axis=0)[None] - left_out.astype(np.float64) @ x

    off = terms["off"].astype(np.float64)
    den = total(terms["rr"]) * terms["norm2"]
    shown = den > 0
    den = np.where(shown, den, 1.0)
    a = np.where(shown, 1.0 + total(terms["num"]) / den, 1.0)
    count = total(off)
    every = total(np.ones_like(off))
    other = np.where(count > 0, total(off * terms["excess"]) / np.maximum(count, 1),
                     total(terms["excess"]) / np.maximum(every, 1))
    var = (total(terms["r2b"]) + total(terms["r2"]) * np.maximum(other, 0.0)) / den ** 2
    return a, np.where(shown, var, np.inf)


def combined_amplitude(reading, reading_variance, fit_variance) -> np.ndarray:
    """``[K]``: the scale of each fitted shape given the fit's amplitude (1, relative variance
    ``fit_variance[K]``, :func:`peak_amplitude_variance`) and the test frames' ``reading[K]`` (variance
    ``reading_variance[K]``, :func:`held_out_amplitude`), by inverse variance: ``1 + f / (f + v) (a - 1)``. 1
    where the test frames do not show the shape (``v`` infinite) or the fit's amplitude has no error
    (``f = 0``)."""
    f = np.asarray(fit_variance, dtype=np.float64)
    v = np.asarray(reading_variance, dtype=np.float64)
    total = f + v
    gain = np.where(np.isfinite(v) & (total > 0), f / np.where(total > 0, total, 1.0), 0.0)
    return 1.0 + gain * (np.asarray(reading, dtype=np.float64) - 1.0)
