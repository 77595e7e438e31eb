"""Option: the position fit with J. Hable's Laplacian term and per-shape region masks ("Solving face scans
for ARKit", Filmic Worlds, 2021).

Energy over all shapes at once (coupled across vertices by the Laplacian, so not per-vertex separable):

    E = sum_i ||B0 + sum_j w_ij B_j - S_i||^2                       (blendshape term = Menzel eq. 1)
      + reg * sum_j ||D_j (B_j - T_j)||^2                           (source term = Menzel eq. 2, D_j of eq. 3)
      + mu  * sum_j ||L (B_j - T_j)||^2                              (Laplacian term: match T_j's Laplacian)

with ``L`` the umbrella Laplacian (offset of a vertex from its neighbours' average) and the region mask of
shape j (vertices the template moves by at least ``mask_threshold`` x its peak) enforced by clamping D_j
outside it (off by default: on realistic captures the true shapes move vertices the template barely
moves - a 0.1 % mask already costs accuracy - and eq. (3)'s weights are a soft mask anyway).
Solved by conjugate gradients on the normal equations, preconditioned by the exact per-vertex
K x K blocks (i.e. by the Menzel solve itself), warm-started from the Menzel solution: one sparse Laplacian
product per iteration (none at mu = 0), every right-hand side (x, y, z) at once, vertex-major [n,3,K]
(no transposes) - to the minimiser (tested against a direct sparse solve of the same energy), not to a
residual relative to a right-hand side that the 1e10-weighted clamped rows dominate.
"""

from __future__ import annotations

import numpy as np

from ..mesh import uniform_laplacian
from .fit import D_CLAMP, blend, project

__all__ = ["LaplacianFit", "region_masks", "LAPLACIAN_GRID"]

#: Laplacian weights mu tried by ``laplacian_weight="auto"`` (:meth:`LaplacianFit.choose_weight`).
LAPLACIAN_GRID = (0.0, 0.03, 0.3)


def region_masks(generic_deltas: np.ndarray, threshold: float = 0.02) -> np.ndarray:
    """Hable's per-shape regions of influence ``mask[K,n]`` (bool): vertices the generic shape moves by at
    least ``threshold`` x its largest displacement."""
    mag = np.linalg.norm(np.asarray(generic_deltas, dtype=np.float64), axis=-1)
    return mag >= threshold * np.maximum(mag.max(axis=1, keepdims=True), 1e-300)


class LaplacianFit:
    """Prepared Laplacian-regularised fit on one mesh.

    ``neutral[n,3]`` B0, ``triangles[t,3]``, ``generic_deltas[K,n,3]`` T_j, ``reg_weights[K,n]`` D_j (eq. 3),
    ``laplacian_weight`` mu (relative to the fit term, unit-free since L is), ``mask_threshold``.
    """

    def __init__(self, neutral, triangles, generic_deltas, reg_weights, *, laplacian_weight: float = 0.03,
                 mask_threshold: float = 0.0, tol: float = 1e-10, max_iter: int = 2000,
                 clamp: float = D_CLAMP):
        self.neutral = np.asarray(neutral, dtype=np.float64)
        self.T = np.asarray(generic_deltas, dtype=np.float64)
        n = len(self.neutral)
        D = np.asarray(reg_weights, dtype=np.float64).copy()
        D[~region_masks(self.T, mask_threshold)] = clamp
        self.D2 = D ** 2                                                     # [K,n]
        L = uniform_laplacian(triangles, n)
        self.LtL = (L.T @ L).tocsr()
        self.mu = float(laplacian_weight)
        self.tol, self.max_iter = tol, max_iter
        self._TV = np.ascontiguousarray(self.T.transpose(1, 2, 0))          # T_j vertex-major [n,3,K]
        self._LtLTV = (self.LtL @ self._TV.reshape(n, -1)).reshape(self._TV.shape)   # L^T L T_j [n,3,K]
        self.info: dict = {}
        self.warm = None                                                     # start of the next solve

    def choose_weight(self, points, weights, reg: float, grid=None, folds: int = 3,
                      progress=None) -> dict:
        """Choose ``mu`` (sets it) by ``folds``-fold cross-validation over the training frames of this energy
        itself: for every ``mu`` in ``grid`` the fit on the other folds (warm-started from the fit on all
        frames) predicts each held-out frame with its weights; the mean squared residual over every vertex is
        minimised. Frames are dealt to folds in turn (frame i to fold i mod folds). Returns ``{"mu", "grid",
        "cv_rmse_mm"}``. ``progress``: called with a label as each ``mu``'s fits begin (1 + ``folds``
        solves each, nearly all of the method's time: ~10 CPU-s a value on the bench captures). ``grid``
        None: :data:`LAPLACIAN_GRID` as it is at the call."""
        grid = LAPLACIAN_GRID if grid is None else grid
        P = np.asarray(points, dtype=np.float64)
        W = np.asarray(weights, dtype=np.float64)
        folds = min(int(folds), len(W))
        if folds < 2:                              # one frame: nothing to hold out, mu stays as given
            return {"mu": float(self.mu), "grid": [float(g) for g in grid], "cv_rmse_mm": [],
                    "note": f"{len(W)} training frame(s): no cross-validation, mu kept"}
        fold = np.arange(len(W)) % folds
        errs, fulls = [], []
        tol = self.tol
        self.tol = max(tol, 1e-6)                  # a CV score needs no 1e-10 solve
        try:
            for mu in grid:
                if progress is not None:
                    progress(f"mu {float(mu):g}: all frames + {folds} folds")
                self.mu = float(mu)
                self.tol = max(tol, 1e-6)
                full = self.solve(P, W, reg, x0=fulls[-1] if fulls else None)
                fulls.append(full)
                sse = 0.0
                self.tol = max(tol, 1e-3)          # folds start at the all-frame fit: a small correction
                for k in range(folds):
                    tr, te = fold != k, fold == k
                    X = self.solve(P[tr], W[tr], reg, x0=full)
                    sse += float(np.sum((P[te] - self.neutral[None] - blend(W[te], X)) ** 2))
                errs.append(sse / P.size)
        finally:
            self.tol = tol
        best = int(np.argmin(errs))
        self.mu = float(grid[best])
        self.warm = fulls[best]                    # the next solve starts here
        return {"mu": self.mu, "grid": [float(g) for g in grid],
                "cv_rmse_mm": [float(np.sqrt(e) * 1000) for e in errs]}

    def solve(self, points, weights, reg: float, x0=None) -> np.ndarray:
        """Deltas ``[K,n,3]`` (metres) minimising the energy for training ``points[F,n,3]``, ``weights[F,K]``
        at balance ``reg`` (``x0``: optional start). Preconditioned CG run to the minimiser: until the
        preconditioned residual has fallen by ``tol`` (1e-10) and the last step moved no coordinate by more
        than ``tol`` x the solution's largest."""
        W = np.asarray(weights, dtype=np.float64)
        R = np.asarray(points, dtype=np.float64) - self.neutral[None]
        WtW = W.T @ W
        lam = reg * self.D2                                                  # [K,n]
        n, K = lam.shape[1], lam.shape[0]
        lamv = np.ascontiguousarray(lam.T)[:, None, :]                       # [n,1,K]
        mu, LtL = self.mu, self.LtL
        # every array vertex-major [n,3,K]: the fit term is one [3n,K] x [K,K] product, the Laplacian one
        # sparse product on [n,3K], the preconditioner one batched [3,K] x [K,K] product per vertex

        def apply(V):                                                        # normal-equation operator
            out = (V.reshape(3 * n, K) @ WtW).reshape(n, 3, K)
            out += lamv * V
            if mu != 0.0:
                out += mu * (LtL @ V.reshape(n, 3 * K)).reshape(n, 3, K)
            return out

        b = project(W, R).transpose(0, 2, 1) + lamv * self._TV
        if mu != 0.0:
            b += mu * self._LtLTV
        # block-Jacobi preconditioner: per-vertex K x K blocks (fit + source + Laplacian diagonal)
        blocks = np.broadcast_to(WtW, (n, K, K)).copy()
        idx = np.arange(K)
        blocks[:, idx, idx] += lam.T + mu * self.LtL.diagonal()[:, None]
        s = 1.0 / np.sqrt(blocks[:, idx, idx])
        inv = np.linalg.inv(blocks * s[:, :, None] * s[:, None, :]) * s[:, :, None] * s[:, None, :]
        invT = np.ascontiguousarray(inv.transpose(0, 2, 1))                  # precond(V)[v] = V[v] inv[v]^T

        def precond(V):
            return np.matmul(V, invT)

        if x0 is None and self.warm is not None and self.warm.shape == (K, n, 3):
            x0 = self.warm
        if x0 is None:
            X = precond(b)
        else:                                                                # a copy: the caller's start kept
            X = np.array(np.asarray(x0, dtype=np.float64).transpose(1, 2, 0), order="C")
        r = b - apply(X)
        z = precond(r)
        p = z.copy()
        rz = np.sum(r * z)
        rz0 = max(rz, 1e-300)
        it = 0
        # stop on the preconditioned residual r^T M^-1 r (~ the error in the energy norm, free of the
        # 1e10-weighted rows that dominate |b|) relative to its start, and on the step vs the solution
        scale = max(np.abs(X).max(), 1e-300)
        while it < self.max_iter and rz > 0:
            it += 1
            Ap = apply(p)
            alpha = rz / np.sum(p * Ap)
            step = alpha * p
            X += step
            r -= alpha * Ap
            z = precond(r)
            rz_new = np.sum(r * z)
            if rz_new <= self.tol ** 2 * rz0 and np.abs(step).max() <= self.tol * scale:
                rz = rz_new
                break
            p = z + (rz_new / rz) * p
            rz = rz_new
        self.info = {"cg_iterations": it,
                     "relative_preconditioned_residual": float(np.sqrt(max(rz, 0) / rz0))}
        return np.ascontiguousarray(X.transpose(2, 0, 1))
