"""Beyond the papers: choose the fit/regularisation balance of eqs. (1)+(2) - and, optionally, the generic
prior T_j as a blend of the deformation-transferred and the raw template shapes - by cross-validation on the
training frames (``reg="auto"``).

The criterion is the exact leave-one-frame-out error of :class:`usdface.personalize.fit.PositionFit` (every
frame left out in turn, its residual predicted by the fit on the others), minimised over ``log10(reg)``: a
coarse grid, then a grid of 4 points per decade around the best grid point (each grid one batched
evaluation of :meth:`~usdface.personalize.fit.PositionFit.loo_errors`) and the vertex of the parabola
through the best fine point and its neighbours; with an alternative prior, for each blend ``alpha`` in
:data:`PRIOR_MIX` (:meth:`~usdface.personalize.fit.PositionFit.loo_errors_mix`). For speed the criterion is
evaluated on a deterministic subsample of the moving vertices (it is a mean over vertices, so a few
hundred estimate it well); the final fit uses every vertex.
"""

from __future__ import annotations

import numpy as np

from .fit import D_CLAMP, PositionFit, _take1

__all__ = ["choose_regularization", "REG_GRID", "PRIOR_MIX"]

#: log10 of the regularisation strengths tried (1 = the paper's plain sum of eqs. 1 and 2).
REG_GRID = np.arange(-7.0, 1.01, 1.0)
#: Blends alpha of the prior alpha * DT + (1 - alpha) * template tried when an alternative prior is given.
PRIOR_MIX = (0.0, 0.5, 1.0)


def _minimise_log(errors, grid, refine, errs=None):
    """Minimise ``errors(log10 regs[G]) -> [G]`` over the coarse ``grid``, then over ``refine`` points per
    decade in the two grid intervals around the best point (one batched evaluation each), then at the vertex
    of the parabola through the best fine point and its neighbours."""
    union = _union_grid(grid, refine) if errs is None else None
    if union is not None:
        # every fine grid this search can need lies on one grid through the coarse points (a short coarse
        # grid, e.g. the +-1 decade re-tune): one batched evaluation serves the coarse and the fine step
        ue = errors(union)
        step = (len(union) - 1) // (len(grid) - 1)
        errs = ue[::step]
    else:
        errs = errors(grid) if errs is None else np.asarray(errs)
    k = int(np.argmin(errs))
    best, best_err = float(grid[k]), float(errs[k])
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    if refine and hi > lo:
        if union is not None:
            fine = union[max(k - 1, 0) * step:min(k + 1, len(grid) - 1) * step + 1]
            fe = ue[max(k - 1, 0) * step:min(k + 1, len(grid) - 1) * step + 1]
        else:
            fine = np.linspace(lo, hi, int(round((hi - lo) * refine)) + 1)
            fe = errors(fine)
        j = int(np.argmin(fe))
        if fe[j] < best_err:
            best, best_err = float(fine[j]), float(fe[j])
        if 0 < j < len(fine) - 1:                    # the parabola through the best fine point's neighbours
            x, y = fine[j - 1:j + 2], fe[j - 1:j + 2]
            den = (x[1] - x[0]) * (y[1] - y[2]) - (x[1] - x[2]) * (y[1] - y[0])
            if den != 0:
                num = (x[1] - x[0]) ** 2 * (y[1] - y[2]) - (x[1] - x[2]) ** 2 * (y[1] - y[0])
                xv = x[1] - 0.5 * num / den
                if x[0] < xv < x[2]:
                    ev = float(errors(np.array([xv]))[0])
                    if ev < best_err:
                        best, best_err = float(xv), ev
    return best, best_err, errs


def _union_grid(grid, refine):
    """The grid of ``refine`` points per decade through a uniform coarse ``grid``, if evaluating it at once
    costs no more than the coarse grid plus one fine step (short coarse grids); else None."""
    grid = np.asarray(grid, dtype=np.float64)
    if not refine or len(grid) < 2:
        return None
    h = np.diff(grid)
    step = int(round(h[0] * refine))
    if step < 1 or not np.allclose(h, h[0], rtol=0, atol=1e-12) or abs(h[0] * refine - step) > 1e-9:
        return None
    m = (len(grid) - 1) * step + 1
    if m > len(grid) + 2 * step + 1:
        return None
    return np.linspace(grid[0], grid[-1], m)


def cv_vertices(reg_weights, clamp: float = D_CLAMP, max_vertices: int = 300, seed: int = 0) -> np.ndarray:
    """The vertices the cross-validation (and what reuses its decomposition: the alignment, the trust)
    evaluates: those some template shape moves (eq. 3's ``reg_weights[K,n]`` below ``clamp`` in some shape;
    every vertex when none is), at most ``max_vertices`` of them drawn at random (``seed``: the same draw
    every run), sorted.

    A draw by vertex, as the fit's energy counts vertices: the criterion's estimate is unbiased, denser where
    the mesh is (the lips, the lids). It depends on the capture mesh's vertex order (a phone's mesh has one
    fixed order); farthest-point sampling by position, which does not, was measured at stop 45 and not kept
    (it under-samples the dense, moving regions: the dev2-regime cases noisy:1/noisy:2 0.705/0.431 ->
    0.747/0.463 face ratio; the history's stop 45 entry)."""
    idx = np.arange(np.shape(reg_weights)[1])
    moving = np.asarray(reg_weights).min(axis=0) < clamp        # vertices some template shape moves
    cand = idx[moving] if moving.any() else idx
    if len(cand) > max_vertices:
        cand = np.sort(np.random.default_rng(seed).choice(cand, max_vertices, replace=False))
    return cand


def choose_regularization(neutral, points, weights, generic_deltas, reg_weights, *, alt_deltas=None,
                          max_vertices: int = 300, grid=REG_GRID, refine: int = 4,
                          seed: int = 0, fit: PositionFit | None = None, vertices=None,
                          alphas=None, keep_prior: bool = False,
                          clamp: float = D_CLAMP, block: int = 1) -> tuple[float, dict]:
    """Regularisation strength (and prior blend) minimising the leave-one-frame-out error of eqs. (1)+(2).

    Arrays as in :func:`usdface.personalize.fit.fit_blendshapes`; ``alt_deltas[K,n,3]`` an optional second
    prior (the raw template deltas). Returns ``(reg, info)`` with ``info = {"reg", "alpha" (blend weight of
    ``generic_deltas``, 1 without alternative), "grid", "loo_rmse_mm" (at the chosen alpha),
    "loo_rmse_best_mm", "vertices" (indices used), "fit" (the prepared PositionFit on them)}``.
    Pass ``fit`` and ``vertices`` from a previous call (after :meth:`PositionFit.set_points`) to skip the
    decomposition; ``alphas`` restricts the prior blends tried; ``keep_prior`` searches ``reg`` only, with the
    prior ``fit`` holds (e.g. the avatar prior, :meth:`PositionFit.set_prior`). ``clamp``: eq. (3)'s clamp
    used for ``reg_weights`` (vertices at the clamp in every shape are static and left out). ``block``:
    frames held out together (a take's consecutive frames, :func:`usdface.personalize.takefit.cv_block`;
    1: leave-one-frame-out).
    """
    neutral = np.asarray(neutral, dtype=np.float64)
    if fit is None:
        cand = cv_vertices(reg_weights, clamp, max_vertices, seed)
        # the frames gathered contiguous (np.take; a fancy index on the middle axis returns a
        # vertex-major copy that every later reshape and take copies again): the same numbers
        fit = PositionFit(neutral[cand], _take1(np.asarray(points), cand), weights,
                          np.asarray(generic_deltas)[:, cand], np.asarray(reg_weights)[:, cand],
                          None if alt_deltas is None else np.asarray(alt_deltas)[:, cand], block=block)
        vertices = cand
    pf, cand = fit, vertices
    grid = np.asarray(grid, dtype=np.float64)
    # coarse grid for every prior blend (one batched evaluation), then a finer grid of reg for the best blend
    mixes = None if keep_prior else (tuple(alphas or PRIOR_MIX) if pf.has_alt else (1.0,))
    if mixes is None or len(mixes) == 1:
        # one prior: the coarse grid is evaluated by the search itself (with the fine grid, if short)
        alpha, best_errs = float("nan"), None
        if mixes is not None:
            alpha = mixes[0]
            if pf.has_alt:
                pf.set_prior_mix(alpha)
    else:
        coarse = pf.loo_errors_mix(10.0 ** grid, mixes)                          # [A,G]
        a = int(np.argmin(coarse.min(axis=1)))
        alpha, best_errs = mixes[a], coarse[a]
        pf.set_prior_mix(alpha)
    g, err, errs = _minimise_log(lambda x: pf.loo_errors(10.0 ** np.asarray(x)), grid, refine, best_errs)
    reg = float(10.0 ** g)
    return reg, {"reg": reg, "alpha": float(alpha), "grid": (10.0 ** grid).tolist(),
                 "loo_rmse_mm": (np.sqrt(errs) * 1000).tolist(),
                 "loo_rmse_best_mm": float(np.sqrt(err) * 1000),
                 "vertices": cand, "fit": pf}

