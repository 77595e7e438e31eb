"""Bounded linear least squares ``min_w 1/2 w^T G w - c^T w``, ``lo <= w <= hi``, for many right-hand sides
at once (pure numpy): the landmark reconstruction's weights (:mod:`usdface.landmarks.reconstruct`) and the
retarget map's (:func:`usdface.transfer.retarget.retarget_weights`). Exact (an active-set method that stops at
the KKT point), without :mod:`scipy.optimize` on the paths that only need this.
"""

from __future__ import annotations

import numpy as np

__all__ = ["admm_box_start", "box_least_squares", "ADMM_ITERATIONS"]

#: ADMM iterations of :func:`admm_box_start` (each one K x K matrix product for all frames).
ADMM_ITERATIONS = 100


def admm_box_start(gram: np.ndarray, c: np.ndarray, lo: float, hi: float, start: np.ndarray,
                   iterations: int = ADMM_ITERATIONS) -> np.ndarray:
    """Near-optimal feasible starting weights ``[F, K]`` for :func:`box_least_squares`, all frames at once.

    ADMM (Boyd et al. 2011, sec. 5.2) on min 1/2 w^T G w - c^T w s.t. lo <= w <= hi: one eigendecomposition of
    ``gram[K, K]`` per layout gives (G + rho I)^-1 with rho = sqrt(lambda_min lambda_max) (the usual
    conditioning choice), then every iteration is one [F, K] x [K, K] product and a clip. It only picks the
    active set: the active-set method that follows proves (or reaches) the exact optimum, in one or two
    batched solves where the set is already right instead of one per bound change. ``c[F, K]`` = A^T b_f,
    ``start[F, K]`` the unconstrained solutions.
    """
    lam, vec = np.linalg.eigh(np.asarray(gram, dtype=np.float64))
    top = max(float(lam.max(initial=0.0)), 1e-300)
    rho = np.sqrt(top * max(float(lam.min(initial=0.0)), 1e-6 * top))
    inverse = (vec / (lam + rho)) @ vec.T
    z = np.clip(np.asarray(start, dtype=np.float64), lo, hi)
    u = np.zeros_like(z)
    c = np.asarray(c, dtype=np.float64)
    for _ in range(iterations):
        w = (c + rho * (z - u)) @ inverse
        z = np.clip(w + u, lo, hi)
        u += w - z
    return z


def box_least_squares(gram: np.ndarray, c: np.ndarray, lo: float, hi: float, start: np.ndarray,
                      max_iter: int | None = None, hold=None) -> tuple[np.ndarray, np.ndarray]:
    """min_w 1/2 w^T G w - c^T w subject to lo <= w <= hi, for every row of ``c[F, K]`` at once.

    ``gram[K, K]`` = A^T A positive definite (A of full column rank), ``c[F, K]`` = A^T b_f, ``start[F, K]``
    (e.g. the unconstrained solutions). A primal active-set method (Lawson & Hanson's, with two bounds, as in
    BVLS) vectorized over frames: per iteration one batched K x K solve with the bound variables held, a step
    to the first bound crossed or, when the step is feasible, the release of the most violating bound
    variable; it stops at the KKT point, the unique optimum. Returns ``(w[F, K], converged[F])``; frames not
    converged within ``max_iter`` (default 10 K) iterations keep their last feasible iterate. ``hold[F, K]``
    (bool, optional): entries held at their ``start`` value, never solved for nor released (the reduced
    problem on the other entries; the retarget map's gaze constraint holds entries at 0).
    """
    gram = np.asarray(gram, dtype=np.float64)
    c = np.asarray(c, dtype=np.float64)
    f_count, k = c.shape
    w = np.clip(np.asarray(start, dtype=np.float64), lo, hi)
    fixed = (w <= lo) | (w >= hi)
    w[fixed] = np.where(w[fixed] <= lo, lo, hi)
    if hold is not None:
        hold = np.asarray(hold, dtype=bool)
        fixed |= hold
        w[hold] = np.asarray(start, dtype=np.float64)[hold]
    running = np.ones(f_count, dtype=bool)
    eye = np.eye(k)
    tol = 1e-12 * max(float(np.abs(c).max(initial=0.0)), float(np.abs(gram).max(initial=0.0)), 1e-300)
    for _ in range(max_iter or 10 * k):
        idx = np.flatnonzero(running)
        if idx.size == 0:
            break
        free = ~fixed[idx]
        cur = w[idx]
        system = np.where(free[:, :, None], gram[None], eye[None])
        z = np.linalg.solve(system, np.where(free, c[idx], cur)[..., None])[..., 0]
        z = np.where(free, z, cur)
        bad = free & ((z < lo) | (z > hi))
        crossing = bad.any(axis=1)
        ok = idx[~crossing]
        if ok.size:  # feasible: accept, then release the bound variable whose gradient points inside
            zk = z[~crossing]
            w[ok] = zk
            g = zk @ gram - c[ok]
            wrong = fixed[ok] & (((zk <= lo) & (g < -tol)) | ((zk >= hi) & (g > tol)))
            if hold is not None:
                wrong &= ~hold[ok]
            score = np.where(wrong, np.abs(g), -1.0)
            release = score.max(axis=1) > 0
            fixed[ok[release], score[release].argmax(axis=1)] = False
            running[ok[~release]] = False
        cr = idx[crossing]
        if cr.size:  # infeasible: move towards z up to the first bound crossed, which becomes bound
            zc, wc, bc = z[crossing], cur[crossing], bad[crossing]
            d = zc - wc
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.where(zc < lo, (lo - wc) / d, (hi - wc) / d)
            t = np.where(bc, t, np.inf)
            step = np.clip(t.min(axis=1), 0.0, 1.0)
            new = wc + step[:, None] * d
            hit = bc & (t <= step[:, None])
            hit |= ~fixed[cr] & ((new <= lo) | (new >= hi))
            new = np.where(hit, np.where(zc < lo, lo, hi), np.clip(new, lo, hi))
            if hold is not None:                      # a held value outside [lo, hi] stays as it is
                new = np.where(hold[cr], wc, new)
            w[cr] = new
            fixed[cr] |= hit
    return w, ~running
