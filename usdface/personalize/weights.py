"""Beyond the papers: re-estimate each training frame's blendshape weights from the current shapes.

The phone's weights are the main error source of a scan-regime capture. Given shapes ``B_j``, each frame's
weights are the MAP estimate under Gaussian geometry noise (per coordinate ``sigma_g``) and a Gaussian prior
around the phone's values (``sigma_w``), bounded to [0, 1]:

    w_i = argmin_{0 <= w <= 1} ||B0 + sum_j w_j B_j - S_i||^2 + (sigma_g / sigma_w)^2 ||w - w_i^phone||^2

All frames share the K x K normal matrix, so the bound-constrained problems are solved together by
accelerated projected gradient (FISTA) in a few hundred tiny matrix products.
"""

from __future__ import annotations

import numpy as np

__all__ = ["reestimate_weights"]


def reestimate_weights(neutral: np.ndarray, deltas: np.ndarray, points: np.ndarray, phone_weights: np.ndarray,
                       *, anchor, lower=0.0, upper=1.0, iterations: int = 150) -> np.ndarray:
    """Bounded, anchored weights ``[F,K]`` for ``points[F,n,3]`` given ``neutral[n,3]``, ``deltas[K,n,3]``
    (metres) and the phone's ``phone_weights[F,K]``; ``anchor`` = ``(sigma_g / sigma_w)^2`` (metres^2).

    ``anchor`` may also be a sequence of ``S`` values: then the ``S`` problems (one per prior width) are
    solved together, ``[S,F,K]`` - the same iterates as ``S`` separate calls, in one loop."""
    B = np.asarray(deltas, dtype=np.float64).reshape(len(deltas), -1)          # [K,3n]
    r = (np.asarray(points, dtype=np.float64) - np.asarray(neutral)[None]).reshape(len(points), -1)   # [F,3n]
    w0 = np.asarray(phone_weights, dtype=np.float64)
    a = np.asarray(anchor, dtype=np.float64)
    many = a.ndim > 0
    a = np.atleast_1d(a)[:, None, None]                                         # [S,1,1]
    G = B @ B.T                                                                 # [K,K]
    c = (r @ B.T)[None] + a * w0[None]                                          # [S,F,K]
    step = 1.0 / (np.linalg.eigvalsh(G)[-1] + a)                                # 1 / L_max per problem
    lo = np.broadcast_to(lower, w0.shape)
    hi = np.broadcast_to(upper, w0.shape)
    x = np.broadcast_to(np.clip(w0, lo, hi), c.shape).copy()
    y, tk = x.copy(), 1.0
    for _ in range(iterations):
        x_new = np.clip(y - step * (y @ G + a * y - c), lo, hi)
        t_new = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * tk * tk))
        y = x_new + ((tk - 1.0) / t_new) * (x_new - x)
        x, tk = x_new, t_new
    return x if many else x[0]
