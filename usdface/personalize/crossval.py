"""Beyond the papers: choose the fit/regularisation balance of eqs. (1)+(2) by cross-validation on the
training frames (``reg="auto"``).

The criterion is the exact leave-one-frame-out error of :class:`usdface.personalize.fit.PositionFit` (every
frame left out in turn, its residual predicted by the fit on the others), minimised over ``log10(reg)``: a
coarse grid, then a golden-section refinement around the best grid point. For speed the criterion is
evaluated on a deterministic subsample of vertices (it is a mean over vertices, so a few hundred estimate
it well); the final fit uses every vertex.
"""

from __future__ import annotations

import numpy as np

from .fit import PositionFit

__all__ = ["choose_regularization", "REG_GRID"]

#: log10 of the regularisation strengths tried (1 = the paper's plain sum of eqs. 1 and 2).
REG_GRID = np.arange(-7.0, 1.01, 1.0)


def choose_regularization(neutral, points, weights, generic_deltas, reg_weights, *, max_vertices: int = 400,
                          grid=REG_GRID, refine_steps: int = 8, seed: int = 0) -> tuple[float, dict]:
    """Regularisation strength minimising the leave-one-frame-out error of eqs. (1)+(2).

    Arrays as in :func:`usdface.personalize.fit.fit_blendshapes`. Returns ``(reg, info)`` with
    ``info = {"grid": [...], "loo_rmse_mm": [...], "reg": reg, "vertices": m}``.
    """
    neutral = np.asarray(neutral, dtype=np.float64)
    n = len(neutral)
    idx = np.arange(n)
    moving = np.asarray(reg_weights).min(axis=0) < 1e5          # vertices some template shape moves
    cand = idx[moving] if moving.any() else idx
    if len(cand) > max_vertices:
        cand = np.sort(np.random.default_rng(seed).choice(cand, max_vertices, replace=False))
    pts = np.asarray(points)[:, cand]
    pf = PositionFit(neutral[cand], pts, weights, np.asarray(generic_deltas)[:, cand],
                     np.asarray(reg_weights)[:, cand])
    grid = np.asarray(grid, dtype=np.float64)
    errs = np.array([pf.loo_error(10.0 ** g) for g in grid])
    k = int(np.argmin(errs))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    phi = (np.sqrt(5.0) - 1.0) / 2.0
    a, b = lo + (1 - phi) * (hi - lo), lo + phi * (hi - lo)
    fa, fb = pf.loo_error(10.0 ** a), pf.loo_error(10.0 ** b)
    for _ in range(refine_steps):
        if fa <= fb:
            hi, b, fb = b, a, fa
            a = lo + (1 - phi) * (hi - lo)
            fa = pf.loo_error(10.0 ** a)
        else:
            lo, a, fa = a, b, fb
            b = lo + phi * (hi - lo)
            fb = pf.loo_error(10.0 ** b)
    best = min([(errs[k], grid[k]), (fa, a), (fb, b)])
    reg = float(10.0 ** best[1])
    return reg, {"reg": reg, "grid": (10.0 ** grid).tolist(),
                 "loo_rmse_mm": (np.sqrt(errs) * 1000).tolist(), "vertices": int(len(cand))}
