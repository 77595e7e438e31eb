"""Example-based facial rigging (Li, Weise & Pauly, SIGGRAPH 2010), blendshape optimisation step only (the
weights are known from the phone), as the baseline of Menzel et al. (2022), sec. 4.1.

Per triangle f, the unknown blendshape deformation gradients ``M_j = I + R_j`` fit the captured frames'
gradients ``M_i^S`` (relative to the neutral B0) through the linear model ``M_i^S - I = sum_j w_ij R_j``,
regularised towards the template's gradients ``R*_j = G_j - I`` (template shape j relative to the template
neutral):

    E_f = sum_i ||M_i^S - I - sum_j w_ij R_j||_F^2 + beta sum_j omega_jf ||R_j - R*_j||_F^2,
    omega_jf = ((1 + ||R*_jf||_F) / (kappa + ||R*_jf||_F))^theta

(Li et al. 2010, eqs. 5-7; kappa = 0.1, theta = 2). The K x K normal equations of every triangle are solved in
one batched call; the vertex positions of each shape are then reconstructed by one sparse factorisation
(:class:`usdface.personalize.dt.PoissonSolver`).

Unit invariance: deformation gradients are ratios of lengths, so the energy and its constants are unit-free;
the only length the reconstruction leaves free - each shape's global translation - is pinned to the
deformation-transferred template's (mass-weighted mean displacement), then refined by ridge least squares
on the frames' mean residuals (unit-free ridge: a fraction of the mean activation energy; without it the
refinement is ill-conditioned with noisy weights). No constant in centimetres anywhere.
"""

from __future__ import annotations

import numpy as np

from ..mesh import deformation_gradients
from .dt import PoissonSolver, eyelid_triangles
from .fit import blend, project

__all__ = ["ebfr_gradients", "ebfr_blendshapes"]


def ebfr_gradients(frame_gradients: np.ndarray, weights: np.ndarray, prior_gradients: np.ndarray, *,
                   beta: float | str = 0.5, kappa: float = 0.1, theta: float = 2.0,
                   info: dict | None = None) -> np.ndarray:
    """Li et al. (2010), eqs. (5)-(7): blendshape gradients ``M_j[K,t,3,3]`` from frame gradients
    ``frame_gradients[F,t,3,3]`` (relative to the neutral), ``weights[F,K]`` and template gradients
    ``prior_gradients[K,t,3,3]``. Batched over triangles (no Python loop).

    ``beta="auto"`` picks the regularisation weight by the same leave-one-frame-out cross-validation as the
    position fit (:func:`usdface.personalize.crossval.choose_regularization`, here on per-triangle gradients),
    so both methods are tuned by one principle; a number uses it as is (Li et al. use 0.5 as a start value).
    """
    W = np.asarray(weights, dtype=np.float64)
    F, K = W.shape
    I = np.eye(3)
    Y = (np.asarray(frame_gradients) - I).reshape(F, -1, 9)               # [F,t,9]
    Rs = (np.asarray(prior_gradients) - I).reshape(K, -1, 9)             # [K,t,9]
    nrm = np.linalg.norm(Rs, axis=-1)                                     # [K,t]
    shape_w = ((1.0 + nrm) / (kappa + nrm)) ** theta                      # [K,t]
    if isinstance(beta, str):
        from .crossval import choose_regularization
        beta, cv = choose_regularization(np.zeros(Y.shape[1:]), Y, W, Rs, np.sqrt(shape_w))
        if info is not None:
            info["crossval"] = cv
    if info is not None:
        info["beta"] = float(beta)
    omega = beta * shape_w                                                # [K,t]
    t = Y.shape[1]
    A = np.broadcast_to(W.T @ W, (t, K, K)).copy()
    idx = np.arange(K)
    A[:, idx, idx] += omega.T
    rhs = project(W, Y) + omega.T[:, :, None] * Rs.transpose(1, 0, 2)                   # [t,K,9]
    R = np.linalg.solve(A, rhs)                                           # [t,K,9]
    return R.transpose(1, 0, 2).reshape(K, t, 3, 3) + I


def ebfr_blendshapes(neutral: np.ndarray, triangles: np.ndarray, points: np.ndarray, weights: np.ndarray,
                     template_neutral: np.ndarray, template_deltas: np.ndarray, generic_deltas: np.ndarray,
                     *, beta: float | str = 0.5, kappa: float = 0.1, theta: float = 2.0, names=None,
                     eyelids: bool = True, info: dict | None = None,
                     translation_ridge: float = 0.1) -> np.ndarray:
    """Li, Weise & Pauly (2010), eqs. (5)-(7) then vertex reconstruction (Sumner & Popović 2004, eq. 5):
    EBFR personalized ``deltas[K,n,3]`` (metres).

    ``neutral[n,3]`` = B0, ``points[F,n,3]`` training frames, ``weights[F,K]``, the template rig
    (``template_neutral[n,3]``, ``template_deltas[K,n,3]``, same topology) for the prior gradients,
    ``generic_deltas[K,n,3]`` (its DT onto B0) as the translation reference. Virtual eyelid triangles
    (:func:`usdface.personalize.dt.eyelid_triangles`) join the gradient fit when ``eyelids``.
    """
    B0 = np.asarray(neutral, dtype=np.float64)
    tris = np.asarray(triangles, dtype=np.int64)
    if eyelids:
        extra = eyelid_triangles(template_neutral, template_deltas, tris, names)
        tris = np.concatenate([tris, extra]) if len(extra) else tris
    P = np.asarray(points, dtype=np.float64)
    W = np.asarray(weights, dtype=np.float64)
    T0 = np.asarray(template_neutral, dtype=np.float64)
    frame_grads = deformation_gradients(B0, P, tris)
    prior = deformation_gradients(T0, T0[None] + np.asarray(template_deltas), tris)
    M = ebfr_gradients(frame_grads, W, prior, beta=beta, kappa=kappa, theta=theta, info=info)
    solver = PoissonSolver(B0, tris)
    X = solver.solve(M, reference=B0[None] + np.asarray(generic_deltas))
    deltas = X - B0[None]
    # refine each shape's translation c_j by ridge least squares on the frames' mean residuals m_i:
    # min sum_i |sum_j w_ij c_j - m_i|^2 + ridge sum_j |c_j|^2 (ridge: fraction of mean activation)
    m = np.mean(P - B0[None] - blend(W, deltas), axis=1)        # [F,3]
    K = W.shape[1]
    WtW = W.T @ W
    ridge = translation_ridge * max(np.trace(WtW) / K, 1e-12)
    c = np.linalg.solve(WtW + ridge * np.eye(K), W.T @ m)                          # [K,3]
    return deltas + c[:, None, :]
