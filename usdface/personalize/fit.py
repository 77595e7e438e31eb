"""Menzel, Botsch & Latoschik (VRST 2022), sec. 3.2: the position-based blendshape fit, eqs. (1)-(3).

Unknown personalized deltas ``B_j[n,3]`` minimise

    E_fit + lambda * E_reg = sum_i ||B0 + sum_j w_ij B_j - S_i||^2 + lambda * sum_j ||D_j (B_j - T_j)||^2

which separates per vertex: for vertex v, with ``W[F,K]`` the training weights, ``r_v[F,3]`` the observed
displacements ``S_i(v) - B0(v)`` and ``L_v = diag(D_jv^2)``,

    (W^T W + lambda L_v) b_v = W^T r_v + lambda L_v t_v          (a K x K system per vertex).

``lambda = 1`` is the paper's plain sum. :class:`PositionFit` diagonalises every vertex's system once
(``L^-1/2 W^T W L^-1/2 = U S U^T``), after which a solve and its exact leave-one-frame-out cross-validation
error cost O(n K^2) per ``lambda`` - that is what ``reg="auto"`` (:mod:`usdface.personalize.crossval`) uses.
"""

from __future__ import annotations

import numpy as np

__all__ = ["regularization_weights", "fit_blendshapes", "loo_residuals", "PositionFit", "blend", "project"]

#: Eq. (3)'s clamp for vertices the template shape does not move.
D_CLAMP = 1e5


def blend(weights: np.ndarray, deltas: np.ndarray) -> np.ndarray:
    """``sum_j w_fj B_j``: ``weights[F,K]``, ``deltas[K,n,3]`` -> ``[F,n,3]`` (one matrix product)."""
    d = np.asarray(deltas, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    return (w @ d.reshape(d.shape[0], -1)).reshape((w.shape[0],) + d.shape[1:])


def project(weights: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``W^T R`` per vertex: ``weights[F,K]``, ``values[F,n,c]`` -> ``[n,K,c]`` (one matrix product)."""
    v = np.asarray(values, dtype=np.float64)
    out = np.asarray(weights, dtype=np.float64).T @ v.reshape(v.shape[0], -1)       # [K, n*c]
    return out.reshape((out.shape[0],) + v.shape[1:]).transpose(1, 0, 2)


def regularization_weights(generic_deltas: np.ndarray, *, clamp: float = D_CLAMP) -> np.ndarray:
    """Menzel et al. (2022), eq. (3): per-vertex regularisation weights ``D[K,n]``.

    ``(D_j)_ii = max_k |t_kj - t_k0| / |t_ij - t_i0|`` from the generic (template) deltas
    ``generic_deltas[K,n,3]``
    (metres; the ratio is unit-free), clamped to ``clamp`` (1e5) where the displacement is (near) zero.
    A shape that moves no vertex at all gets ``clamp`` everywhere.
    """
    mag = np.linalg.norm(np.asarray(generic_deltas, dtype=np.float64), axis=-1)      # [K,n]
    peak = mag.max(axis=1, keepdims=True)
    D = np.divide(peak, mag, out=np.full_like(mag, clamp), where=mag > peak / clamp)
    return np.minimum(D, clamp)


def fit_blendshapes(neutral: np.ndarray, points: np.ndarray, weights: np.ndarray, generic_deltas: np.ndarray,
                    reg_weights: np.ndarray, reg: float = 1.0) -> np.ndarray:
    """Menzel et al. (2022), eqs. (1)+(2): personalized ``deltas[K,n,3]`` (metres) at a fixed balance ``reg``.

    ``neutral[n,3]`` = B0, ``points[F,n,3]`` = training meshes S_i, ``weights[F,K]`` = w_ij,
    ``generic_deltas[K,n,3]`` = T_j, ``reg_weights[K,n]`` = D_j diagonals (eq. 3). ``reg`` multiplies E_reg
    (1 = the paper). Solved as n batched K x K systems (one batched LAPACK call).
    """
    W = np.asarray(weights, dtype=np.float64)
    R = np.asarray(points, dtype=np.float64) - np.asarray(neutral, dtype=np.float64)[None]   # [F,n,3]
    T = np.asarray(generic_deltas, dtype=np.float64)
    L = reg * np.asarray(reg_weights, dtype=np.float64).T ** 2                               # [n,K]
    n, K = L.shape
    A = np.broadcast_to(W.T @ W, (n, K, K)).copy()
    idx = np.arange(K)
    A[:, idx, idx] += L
    rhs = project(W, R) + L[:, :, None] * T.transpose(1, 0, 2)             # [n,K,3]
    # partial-pivoting LU is accurate here without equilibration (the large entries are on the diagonal;
    # checked against an equilibrated solve: < 1e-11 m)
    B = np.linalg.solve(A, rhs)
    return B.transpose(1, 0, 2)


def loo_residuals(neutral: np.ndarray, points: np.ndarray, weights: np.ndarray, generic_deltas: np.ndarray,
                  reg_weights: np.ndarray, reg: float, predict_weights=None) -> np.ndarray:
    """Exact leave-one-frame-out residuals ``[F,n,3]`` (metres) of eqs. (1)+(2) at one ``reg``, by one batched
    solve per vertex (cheaper than :class:`PositionFit`'s eigen-decomposition when only one ``reg`` is
    needed). Arrays as in :func:`fit_blendshapes`; ``predict_weights[F,K]`` as in
    :meth:`PositionFit.loo_residuals`."""
    W = np.asarray(weights, dtype=np.float64)
    R = np.asarray(points, dtype=np.float64) - np.asarray(neutral, dtype=np.float64)[None]   # [F,n,3]
    T = np.asarray(generic_deltas, dtype=np.float64)
    L = reg * np.asarray(reg_weights, dtype=np.float64).T ** 2                               # [n,K]
    n, K = L.shape
    F = len(W)
    A = np.broadcast_to(W.T @ W, (n, K, K)).copy()
    idx = np.arange(K)
    A[:, idx, idx] += L
    rhs = np.concatenate([project(W, R) + L[:, :, None] * T.transpose(1, 0, 2),
                          np.broadcast_to(W.T, (n, K, F))], axis=2)                  # [n,K,3+F]
    X = np.linalg.solve(A, rhs)
    b, G = X[:, :, :3], X[:, :, 3:]                                                 # b_v, A^-1 W^T
    fitted = np.matmul(W[None], b).transpose(1, 0, 2)                               # [F,n,3]
    h = np.einsum("fk,nkf->fn", W, G)
    e = (R - fitted) / np.maximum(1.0 - h, 1e-9)[:, :, None]
    if predict_weights is None:
        return e
    Pw = np.asarray(predict_weights, dtype=np.float64)
    pred = np.matmul(Pw[None], b).transpose(1, 0, 2)
    cross = np.einsum("fk,nkf->fn", Pw, G)
    return R - pred + cross[:, :, None] * e


class PositionFit:
    """Menzel et al. (2022), eqs. (1)-(2) prepared for many regularisation strengths.

    ``neutral[n,3]``, ``points[F,n,3]``, ``weights[F,K]``, ``generic_deltas[K,n,3]``, ``reg_weights[K,n]``;
    optional ``alt_deltas[K,n,3]``, a second prior to blend with (:meth:`set_prior_mix`).
    After the one-off per-vertex eigen-decomposition, :meth:`solve` (deltas at a ``reg``) and
    :meth:`loo_error` (exact leave-one-frame-out residual, the closed form ``e_i / (1 - h_ii)`` of linear
    smoothers) are O(n K^2).
    """

    def __init__(self, neutral, points, weights, generic_deltas, reg_weights, alt_deltas=None):
        self.W = np.asarray(weights, dtype=np.float64)
        self.R = np.asarray(points, dtype=np.float64) - np.asarray(neutral, dtype=np.float64)[None]
        D = np.asarray(reg_weights, dtype=np.float64).T                      # [n,K]
        self.inv_sqrt_l = 1.0 / D                                            # L^-1/2 (L = D^2)
        W = self.W
        C = (W.T @ W)[None] * self.inv_sqrt_l[:, :, None] * self.inv_sqrt_l[:, None, :]   # [n,K,K]
        self.s, self.U = np.linalg.eigh(C)
        self.s = np.maximum(self.s, 0.0)
        M = self.inv_sqrt_l[:, :, None] * self.U                             # L^-1/2 U  [n,K,K]
        self.M = M
        self.neutral = np.asarray(neutral, dtype=np.float64)
        self.set_points(points)

        def prior_coef(T):                                                   # U^T L^1/2 t
            T = np.asarray(T, dtype=np.float64)
            return np.matmul(np.swapaxes(self.U, 1, 2), D[:, :, None] * T.transpose(1, 0, 2))

        self._prior_coef = prior_coef
        self.z_main = prior_coef(generic_deltas)
        self.z_alt = None if alt_deltas is None else prior_coef(alt_deltas)
        self.z = self.z_main
        self.q = np.matmul(W[None], M)                                       # [n,F,K]: w_i^T L^-1/2 U
        self.q2 = np.ascontiguousarray((self.q ** 2).transpose(1, 0, 2))     # [F,n,K]

    def set_points(self, points) -> None:
        """Replace the training frames ``points[F,n,3]`` (same weights): O(n F K), no new decomposition."""
        self.R = np.asarray(points, dtype=np.float64) - self.neutral[None]
        WtR = project(self.W, self.R)                                        # [n,K,3]
        self.y = np.matmul(np.swapaxes(self.M, 1, 2), WtR)                   # U^T L^-1/2 W^T r

    def set_prior_mix(self, alpha: float) -> None:
        """Use the prior ``alpha * generic_deltas + (1 - alpha) * alt_deltas`` (eq. 2's T_j) from now on."""
        self.z = self.z_main if self.z_alt is None else alpha * self.z_main + (1.0 - alpha) * self.z_alt

    def set_prior(self, prior_deltas) -> None:
        """Use the prior ``prior_deltas[K,n,3]`` (eq. 2's T_j, on this fit's vertices) from now on."""
        self.z = self._prior_coef(prior_deltas)

    def data_share(self, reg: float) -> np.ndarray:
        """Per vertex and shape, the share of the fitted shape determined by the frames rather than the prior:
        the diagonal of ``A_v^-1 W^T W`` (``A_v = W^T W + reg L_v``), ``[n,K]`` in [0, 1].

        Since ``b_v = A_v^-1 W^T r_v + A_v^-1 reg L_v t_v`` and the two matrices sum to the identity, entry
        ``(v, j)`` is how much of ``b_vj`` follows the data (1) rather than the prior (0): 0 for a shape with
        zero training weight, -> 1 for a shape isolated in a frame as ``reg`` -> 0. In the eigenbasis it is
        ``sum_k U_jk^2 s_k / (s_k + reg)`` (the per-shape effective degrees of freedom)."""
        return np.einsum("njk,nk->nj", self.U ** 2, self.s / (self.s + reg))

    def _coef(self, reg: float) -> np.ndarray:
        return (self.y + reg * self.z) / (self.s + reg)[:, :, None]          # [n,K,3]

    def solve(self, reg: float) -> np.ndarray:
        """Deltas ``[K,n,3]`` minimising E_fit + reg * E_reg."""
        return np.matmul(self.M, self._coef(reg)).transpose(1, 0, 2)

    def loo_residuals(self, reg: float, predict_weights: np.ndarray | None = None) -> np.ndarray:
        """Leave-one-frame-out residuals ``[F,n,3]`` (metres): frame i minus its prediction by the fit on the
        other frames, ``e_i / (1 - h_ii)``.

        ``predict_weights[F,K]``: predict frame i with these weights instead of the fitted ones (e.g. the
        phone's, when the fit used re-estimated weights): ``r_i - p_i^T b^(-i)`` with the exact downdate
        ``b^(-i) = b - A^-1 w_i e_i / (1 - h_ii)`` (Sherman-Morrison)."""
        # fitted frames W b_v = (W L^-1/2 U) coef_v = q_v coef_v: one batched product, b_v never formed
        coef = self._coef(reg)
        fitted = np.matmul(self.q, coef).transpose(1, 0, 2)                  # [F,n,3]
        inv = 1.0 / (self.s + reg)
        h = np.einsum("fnk,nk->fn", self.q2, inv)                            # [F,n]: w_i^T A^-1 w_i
        e = (self.R - fitted) / np.maximum(1.0 - h, 1e-9)[:, :, None]
        if predict_weights is None:
            return e
        qp = np.matmul(np.asarray(predict_weights, dtype=np.float64)[None], self.M)   # [n,F,K]
        pred = np.matmul(qp, coef).transpose(1, 0, 2)                        # p_i^T b
        cross = np.einsum("nfk,nfk,nk->fn", qp, self.q, inv)                 # p_i^T A^-1 w_i
        return self.R - pred + cross[:, :, None] * e

    def loo_error(self, reg: float, frame_weights: np.ndarray | None = None) -> float:
        """Exact leave-one-frame-out mean squared residual (per vertex coordinate, metres^2) at ``reg``."""
        e = self.loo_residuals(reg)
        per_frame = np.mean(e ** 2, axis=(1, 2))
        if frame_weights is not None:
            return float(np.average(per_frame, weights=frame_weights))
        return float(per_frame.mean())
