"""Beyond the papers: re-estimate each training frame's blendshape weights from the current shapes.

The phone's weights are the main error source of a scan-regime capture. Given shapes ``B_j``, each frame's
weights are the MAP estimate under Gaussian geometry noise (per coordinate ``sigma_g``) and a Gaussian prior
around the phone's values (``sigma_w``), bounded to [0, 1]:

    w_i = argmin_{0 <= w <= 1} ||B0 + sum_j w_j B_j - S_i||^2 + (sigma_g / sigma_w)^2 ||w - w_i^phone||^2

All frames share the K x K normal matrix, so the bound-constrained problems are solved together by
accelerated projected gradient (FISTA) in a few hundred tiny matrix products.

Each shape's weight in its *peak frame* (:func:`peak_frames`, the frame Menzel keeps for the shape) is held
at the phone's value (:func:`held_weights`): a shape's amplitude and its weight in the frame that isolates it
are not separately identifiable (``w B_j = (c w)(B_j / c)``), so re-estimating that weight only trades against
the shape's own scale. The other shapes' weights in that frame, and the shape's weights in every other frame,
are re-estimated; the peak frame fixes the scale they are measured in.
"""

from __future__ import annotations

import math

import numpy as np

from .align import distinct_frames
from .fit import weight_basis

__all__ = ["held_weights", "peak_frames", "reestimate_weights", "reestimate_weights_batched", "shape_basis",
           "weight_error_variance", "weight_noise", "weight_residuals"]


def peak_frames(weights: np.ndarray) -> np.ndarray:
    """``[K]`` int: for each shape the training frame where the phone reports its largest weight
    (``weights[F,K]``; the first on ties) - the frame that isolates the shape, as :mod:`usdface.take_select`
    picks it from a take. Defined by the weights, not by the frames' labels (a frame recorded for
    ``eyeBlinkLeft`` often blinks both eyes; then it is the peak frame of both blinks).

    >>> peak_frames(np.array([[0.9, 0.1], [0.2, 0.7], [0.3, 0.8]]))
    array([0, 2])
    """
    return np.argmax(np.asarray(weights), axis=0)


def held_weights(weights: np.ndarray, activation_min: float = 0.0) -> np.ndarray:
    """``bool[F,K]``: the entries of ``weights[F,K]`` that re-estimation keeps at the phone's value - each
    shape's weight in its peak frame (:func:`peak_frames`; fixes the shape's scale) and every weight of a
    shape whose largest weight is below ``activation_min`` (never activated)."""
    w = np.asarray(weights)
    held = np.zeros(w.shape, dtype=bool)
    held[:, w.max(axis=0) < activation_min] = True
    held[peak_frames(w), np.arange(w.shape[1])] = True
    return held


def reestimate_weights(neutral: np.ndarray, deltas: np.ndarray, points: np.ndarray, phone_weights: np.ndarray,
                       *, anchor, lower=0.0, upper=1.0, iterations: int = 150) -> np.ndarray:
    """Bounded, anchored weights ``[F,K]`` for ``points[F,n,3]`` given ``neutral[n,3]``, ``deltas[K,n,3]``
    (metres) and the phone's ``phone_weights[F,K]``; ``anchor`` = ``(sigma_g / sigma_w)^2`` (metres^2).

    ``anchor`` may also be a sequence of ``S`` values: then the ``S`` problems (one per prior width) are
    solved together, ``[S,F,K]`` - the same iterates as ``S`` separate calls, in one loop."""
    a = np.asarray(anchor, dtype=np.float64)
    x = reestimate_weights_batched([(neutral, deltas, points)], phone_weights, np.atleast_1d(a)[None],
                                   lower=lower, upper=upper, iterations=iterations)[0]
    return x if a.ndim > 0 else x[0]


def reestimate_weights_batched(problems, phone_weights: np.ndarray, anchors: np.ndarray, *, lower=0.0,
                               upper=1.0, iterations: int = 150) -> np.ndarray:
    """:func:`reestimate_weights` for ``H`` vertex sets at once: ``problems`` = ``[(neutral[n_h,3],
    deltas[K,n_h,3], points[F,n_h,3]), ...]``, ``anchors[H,S]`` -> weights ``[H,S,F,K]`` (the same iterates as
    ``H x S`` separate calls, one loop; frames posing the same problem solved once,
    :func:`.align.distinct_frames`)."""
    w0 = np.asarray(phone_weights, dtype=np.float64)
    a = np.asarray(anchors, dtype=np.float64)[:, :, None, None]                   # [H,S,1,1]
    Gs, cs = [], []
    for neutral, deltas, points in problems:
        B = np.asarray(deltas, dtype=np.float64).reshape(len(deltas), -1)        # [K,3n]
        r = (np.asarray(points, dtype=np.float64) - np.asarray(neutral)[None]).reshape(len(points), -1)
        Gs.append(B @ B.T)
        cs.append(r @ B.T)
    G = np.stack(Gs)[:, None]                                                   # [H,1,K,K]
    c = np.stack(cs)[:, None] + a * w0                                          # [H,S,F,K]
    step = 1.0 / (np.linalg.eigvalsh(G[:, 0])[:, -1][:, None, None, None] + a)  # 1 / L_max per problem
    # the bounds as whole [H,S,F,K] arrays: the projection's maximum/minimum run 2x faster than broadcast
    lo = np.ascontiguousarray(np.broadcast_to(lower, c.shape), dtype=np.float64)
    hi = np.ascontiguousarray(np.broadcast_to(upper, c.shape), dtype=np.float64)
    x0 = np.broadcast_to(w0, c.shape)
    # frames that pose the same problem (a capture app's repeated frame: the same points, phone weights and
    # bounds) have the same iterates (every step works row by row): solved once, then copied
    groups = distinct_frames(*(np.moveaxis(arr, 2, 0) for arr in (c, lo, hi, x0)))
    if groups is not None:
        first, inverse = groups
        c, lo, hi, x0 = (np.ascontiguousarray(arr[:, :, first]) for arr in (c, lo, hi, x0))
    x = np.clip(x0, lo, hi)
    y, tk = x.copy(), 1.0
    # the gradient step y - step (y (G + a I) - c) as one affine map y M + step c (M symmetric)
    eye = np.eye(G.shape[-1])
    M = eye - step * (G + a * eye)                                              # [H,S,K,K]
    c *= step
    x_new = np.empty_like(x)
    for _ in range(iterations):
        np.matmul(y, M, out=x_new)
        x_new += c
        np.maximum(x_new, lo, out=x_new)                                        # = np.clip, cheaper
        np.minimum(x_new, hi, out=x_new)
        t_new = 0.5 * (1.0 + math.sqrt(1.0 + 4.0 * tk * tk))               # a Python float
        np.subtract(x_new, x, out=y)                                            # y = x_new + m (x_new - x)
        y *= (tk - 1.0) / t_new
        y += x_new
        x, x_new, tk = x_new, x, t_new
    return x if groups is None else x[:, :, inverse]


def shape_basis(deltas: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The thin SVD of the shapes as columns, ``A^T = U diag(s) V^T`` with ``A[K,3n]`` the rows
    ``deltas[K,n,3]`` flattened (metres), truncated to its numerical rank (:func:`.fit.weight_basis` of
    ``A^T``): ``U[3n,r]``, ``s[r]``, ``V[K,r]``. What :func:`weight_residuals` reads the frames' weights on;
    one decomposition for every set of frames read on the same shapes (the fit's training frames, as
    aligned and as scanned)."""
    D = np.asarray(deltas, dtype=np.float64)
    return weight_basis(D.reshape(len(D), -1).T)


def weight_residuals(neutral: np.ndarray, points: np.ndarray, weights: np.ndarray,
                     deltas: np.ndarray, *, basis=None) -> tuple[np.ndarray, np.ndarray]:
    """What :func:`weight_noise` reads, for any set of entries: ``(difference[F,K], own[K])``, each training
    frame's weights re-estimated by least squares on the fitted shapes minus the weights the shapes were
    fitted with (weight units), and each shape's estimate's own variance from the frames' scan noise,
    ``s^2 [(A A^T)^+]_kk`` (weight units squared; ``s`` the residual's std per coordinate, ``A`` the shapes
    as rows). ``neutral[n,3]``, ``points[F,n,3]`` metres, ``weights[F,K]``, ``deltas[K,n,3]`` the fitted
    shapes. Computed once when the noise is read over several sets (:func:`weight_error_variance`).
    ``basis``: :func:`shape_basis` of these ``deltas`` when the caller has it (the same numbers)."""
    W = np.asarray(weights, dtype=np.float64)
    Y = np.asarray(points, dtype=np.float64) - np.asarray(neutral, dtype=np.float64)[None]
    Y = Y.reshape(len(W), -1)                                                        # [F, 3n]
    # one thin SVD A^T = U S V^T to its numerical rank for the estimate (pseudo-inverse), the rank and
    # (A A^T)^+'s diagonal
    U, sv, V = shape_basis(deltas) if basis is None else basis
    Vt = V.T
    coef = (Y @ U) / sv                                                              # [F, rank]
    estimate = coef @ Vt                                                             # [F,K]
    dof = max(len(U) - len(sv), 1)
    scan = max(float(np.sum(Y * Y) - np.sum(coef * coef * sv * sv)), 0.0) / (len(W) * dof)   # m^2 a coord.
    own = scan * np.sum((Vt / sv[:, None]) ** 2, axis=0)                              # [K]
    return estimate - W, own


def weight_noise(neutral: np.ndarray, points: np.ndarray, weights: np.ndarray, deltas: np.ndarray,
                 free: np.ndarray, *, residuals: tuple[np.ndarray, np.ndarray] | None = None) -> float:
    """The weights' noise as the capture itself shows it (a std, in weight units): each training frame's
    weights re-estimated by least squares on the fitted shapes, minus the weights the shapes were fitted
    with, over the entries that may err (``free[F,K]``, e.g. not :func:`held_weights`); the robust variance
    of those differences (1.4826 x their median absolute deviation, squared) less the part the frames' scan
    noise explains (the least-squares estimate's own variance, ``s^2 [(A A^T)^-1]_kk`` with ``s`` the
    residual's std per coordinate and ``A`` the shapes as rows; its median over the entries).

    ``neutral[n,3]``, ``points[F,n,3]`` metres, ``weights[F,K]``, ``deltas[K,n,3]`` the fitted shapes. Had
    the phone reported each frame's weights exactly, the fitted shapes would explain every frame with them
    and the differences would be the scan noise's share and the non-linear motion's (dev1 and dev3, whose
    weights are the phone mesh's own: 0.001 and 0.0005); weights reported with noise leave the frames
    inconsistent with one another, and the shapes fitted to all of them explain no frame with its reported
    weights (generated captures with scan noise 0.1 mm and the phone's weights +-0.01: 0.011-0.016, +-0.03
    at 0.15 mm: 0.036-0.041; the scan noise alone would read 0.011-0.027). The median keeps a few frames of
    large non-linear motion from setting it. ``residuals``: :func:`weight_residuals` of these arrays, when
    the caller reads the noise over several sets of entries."""
    W = np.asarray(weights, dtype=np.float64)
    mask = np.asarray(free, dtype=bool)
    if not mask.any():
        return 0.0
    difference, own = weight_residuals(neutral, points, W, deltas) if residuals is None else residuals
    diff = difference[mask]
    spread = (1.4826 * np.median(np.abs(diff - np.median(diff)))) ** 2
    return float(np.sqrt(max(0.0, spread - np.median(np.broadcast_to(own, W.shape)[mask]))))


def weight_error_variance(neutral, points, weights, deltas, free, *, residuals=None,
                          noise: float | None = None) -> np.ndarray:
    """``[F,K]`` (weight units squared): the expected squared error of each weight the phone reported, for
    the leak (:func:`.fit.weight_leak_variance`, :func:`.fit.weight_leak_direction`), 0 where ``free[F,K]``
    is False (the entries the fit holds). ``neutral[n,3]``, ``points[F,n,3]`` metres, ``weights[F,K]`` the
    reports, ``deltas[K,n,3]`` the fitted shapes.

    The phone reports ``r = clip(w + e, 0, 1)``, ``e ~ N(0, s^2)``. An entry inside ``(0, 1)`` errs by the
    whole ``e``, and so does one past a bound (a report not clipped: the readers clip, an in-memory
    :class:`usdface.model.Capture` need not): ``s`` is :func:`weight_noise` over these entries alone (the
    "inside" ones below). An entry at a bound
    ``b`` errs by ``b - w`` (the clip took ``e``'s part beyond ``b``), ``|b - w| <= |e|``, and its truth is
    one of two kinds: ``w = b`` exactly (at 0 every shape a frame does not perform: no error at all), or a
    value spread near ``b`` with some density ``g`` (the performed ones). Of the latter, a truth at distance
    ``x`` from ``b`` is reported at ``b`` with probability ``Phi(-x/s)``, so their count at the bound is
    ``g int_0^inf Phi(-x/s) dx = g s / sqrt(2 pi)`` and their mean squared error
    ``int x^2 Phi(-x/s) dx / int Phi(-x/s) dx = (2/3) s^2`` (the censored normal's, mean included). The
    entry's expected squared error is then ``(2/3) s^2 q``, ``q`` the share of the bound's entries of the
    spread kind: ``g`` is read from the reports between ``3 s`` and ``6 s`` from the bound (past the reach
    of the exact ones' noise, ``g = count / (3 s)``), ``q = min(1, g s / sqrt(2 pi) / count at b)``; each
    bound on its own. On generated captures (noisy:115, noisy:140, noisy:143, generic:149, artist:163) the
    inside entries read 0.0351, 0.0314, 0.0303, 0.0124, 0.0106 against the truth's 0.0297, 0.0292, 0.0294,
    0.0097, 0.0099; the entries at 0 0.0018, 0.0019, 0.0016, 0.0009, 0.0010 against 0.0054, 0.0048, 0.0044,
    0.0011, 0.0014 (the performed weights' density rises towards 0, so the band reads it low; either is
    below a fifth of the inside noise, a few per cent of an inside entry's variance). Pooled with the inside
    entries, the entries at 0 (about half of a capture's) pulled the one noise below the inside entries' and
    the leak of a frame's reported ``jawOpen`` 0.067 (true 0, an inside entry at 2.2 sigma of dev2's regime)
    was read at 0.025 instead of 0.030 and passed as the person; read apart by re-estimation, the entries at
    0 scatter with the other entries' errors, not their own, 4x the truth's (docs/history.md, stop 48).
    ``residuals``: :func:`weight_residuals` of these arrays when the caller has them.

    ``noise``: the inside level ``s`` measured elsewhere (the training frames' for the test frames, whose
    residual on the fitted shapes also holds those shapes' own errors: 0.060 against a true 0.029 on a
    generated capture where the training frames read 0.041), instead of measuring it on these frames."""
    w = np.asarray(weights, dtype=np.float64)
    free = np.asarray(free, dtype=bool)
    inside = free & (w != 0.0) & (w != 1.0)                 # not clipped: past a bound errs by all of e too
    variance = np.zeros(w.shape)
    if not inside.any():
        return variance
    s = (weight_noise(neutral, points, w, deltas, inside, residuals=residuals) if noise is None
         else float(noise))
    variance[inside] = s * s
    if s <= 0.0:
        return variance
    for bound in (0.0, 1.0):
        at = free & (w == bound)
        distance = np.abs(w - bound)
        band = int(np.count_nonzero(free & (distance > 3.0 * s) & (distance <= 6.0 * s)))
        if at.any():
            spread = band / 3.0 / np.sqrt(2.0 * np.pi)       # g s / sqrt(2 pi), g = band / (3 s)
            variance[at] = 2.0 / 3.0 * s * s * min(1.0, spread / np.count_nonzero(at))
    return variance
