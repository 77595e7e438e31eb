"""Menzel, Botsch & Latoschik (VRST 2022), sec. 3.2: the position-based blendshape fit, eqs. (1)-(3).

Unknown personalized deltas ``B_j[n,3]`` minimise

    E_fit + lambda * E_reg = sum_i ||B0 + sum_j w_ij B_j - S_i||^2 + lambda * sum_j ||D_j (B_j - T_j)||^2

which separates per vertex: for vertex v, with ``W[F,K]`` the training weights, ``r_v[F,3]`` the observed
displacements ``S_i(v) - B0(v)`` and ``L_v = diag(D_jv^2)``,

    (W^T W + lambda L_v) b_v = W^T r_v + lambda L_v t_v          (a K x K system per vertex).

``lambda = 1`` is the paper's plain sum. Every vertex shares ``W``: with its thin SVD ``W = P S Q^T`` (rank
``r``, computed once) and ``B = Q S``, the push-through identity turns each K x K system into an r x r one,

    b_v = t_v + lambda^-1 L_v^-1 B x_v,   (I_r + lambda^-1 H_v) x_v = P^T (r_v - W t_v),
    H_v = B^T L_v^-1 B                                           (:func:`reduced_normal_matrix`),

exact (no approximation) and cheaper when the frames excite fewer than K directions (dev1: r = 28 of 51).
:class:`PositionFit` diagonalises every vertex's ``H_v = V_v diag(mu_v) V_v^T`` once, after which a solve,
its hat matrix ``P V diag(mu / (mu + lambda)) V^T P^T`` and the exact leave-one-frame-out cross-validation
error cost O(n F r) per ``lambda`` - that is what ``reg="auto"`` (:mod:`usdface.personalize.crossval`) uses.
"""

from __future__ import annotations

import numpy as np

from ..mesh import squared_lengths, vector_lengths
from .align import distinct_frames

__all__ = ["regularization_weights", "fit_blendshapes", "FitSystem", "loo_residuals", "PositionFit", "blend",
           "project", "weight_basis", "reduced_normal_matrix", "data_share", "estimate_variance",
           "james_stein"]

#: How many of the weights' errors (frame, shape) span the leak's largest pattern in a shape
#: (:func:`weight_leak_direction`): the few that carry it (1.4-5 effective draws on the generated captures).
LEAK_PARTS = 8
#: Eq. (3)'s clamp for vertices the template shape does not move.
D_CLAMP = 1e5
#: The bytes a per-vertex block of the weights' leak may take at a time (:func:`weight_leak_direction`'s
#: gain rows ``B_j^T M_v^-1``, :func:`frame_error_variance`'s K x K blocks): a 50k-vertex capture's
#: ``[n,K,r]`` gain took ~0.8 GB at once.
BLOCK_BYTES = 64e6
#: Single-``reg`` solves use the rank-r basis while ``r <= REDUCED_MAX_RANK * K`` (its cost grows ~r^2.5; at
#: full rank the direct K x K solve is 2x cheaper, at dev1's r = 28 of 51 the reduced one is 1.8x cheaper).
REDUCED_MAX_RANK = 0.75


def _left(A: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``A @ X_v`` for every ``v``: ``A[a,b]``, ``X[n,b,c]`` -> ``[n,a,c]`` as one matrix product (not ``n``
    small ones)."""
    return _lefts(X, A)[0]


def _lefts(X: np.ndarray, *matrices: np.ndarray) -> list[np.ndarray]:
    """:func:`_left` of ``X[n,b,c]`` by each of ``matrices`` (``A[a,b]`` each), ``X``'s vertex-major copy
    ``[b,n*c]`` made once for all of them (the same numbers as one :func:`_left` each)."""
    n, b, c = X.shape
    Xr = X.transpose(1, 0, 2).reshape(b, n * c)
    return [(A @ Xr).reshape(A.shape[0], n, c).transpose(1, 0, 2) for A in matrices]


def _take1(x: np.ndarray, idx) -> np.ndarray:
    """``x[:, idx]``: for indices a gather by :func:`numpy.take` (the same copy, 2-3x cheaper than fancy
    indexing along a middle axis); for a slice the view."""
    return x[:, idx] if isinstance(idx, slice) else np.take(x, idx, axis=1)


def _sum_axis2(x: np.ndarray) -> np.ndarray:
    """``x.sum(axis=2)`` of ``x[a,b,k,c]`` with small ``k`` by ``k - 1`` whole-array additions (numpy's
    reduction over a middle axis is several times slower)."""
    out = x[:, :, 0].copy()
    for j in range(1, x.shape[2]):
        out += x[:, :, j]
    return out


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
    mag = vector_lengths(generic_deltas)                                             # [K,n]
    peak = mag.max(axis=1, keepdims=True)
    D = np.divide(peak, mag, out=np.full_like(mag, clamp), where=mag > peak / clamp)
    return np.minimum(D, clamp)


def weight_basis(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Thin SVD ``W = P diag(s) Q^T`` of ``weights[F,K]`` truncated to its numerical rank ``r`` (singular
    values above ``s_max max(F, K) eps``): ``P[F,r]``, ``s[r]``, ``Q[K,r]``. Dropped directions carry no
    data (the fit holds them at the prior)."""
    W = np.asarray(weights, dtype=np.float64)
    P, s, Qt = np.linalg.svd(W, full_matrices=False)
    keep = s > (s[0] if s.size else 0.0) * max(W.shape) * np.finfo(np.float64).eps
    return P[:, keep], s[keep], Qt[keep].T


def reduced_normal_matrix(inv_l: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """``H_v = B^T diag(inv_l_v) B`` for every vertex: ``inv_l[n,K]`` (the inverse regularisation weights
    ``1 / (lambda D_jv^2)``), ``basis[K,r]`` (``B = Q S``) -> ``[n,r,r]`` symmetric, by one matrix product of
    the upper triangle, spread to both triangles by one gather (two fancy-index scatters took 5x as long)."""
    K, r = basis.shape
    iu, ju = np.triu_indices(r)
    upper = np.asarray(inv_l, dtype=np.float64) @ (basis[:, iu] * basis[:, ju])       # [n, r(r+1)/2]
    pos = np.empty((r, r), dtype=np.intp)                                           # entry (i, j) -> column
    pos[iu, ju] = pos[ju, iu] = np.arange(len(iu))
    return np.take(upper, pos.ravel(), axis=1).reshape(len(upper), r, r)


def _reduced_matrices(s, Q, D, reg):
    """``(B[K,r], inv_l[n,K], M[n,r,r])`` of eqs. (1)+(2) at ``reg`` in the weights' rank-r basis (``s``,
    ``Q`` of :func:`weight_basis`): ``B = Q S`` (``W^T W = B B^T``), ``inv_l = 1 / (reg D^2)`` and ``M_v = I +
    B^T diag(inv_l_v) B``."""
    B = Q * s
    inv_l = 1.0 / (reg * np.asarray(D, dtype=np.float64).T ** 2)                      # [n,K]
    r = len(s)
    M = reduced_normal_matrix(inv_l, B)
    M.reshape(len(M), -1)[:, ::r + 1] += 1.0                                          # the diagonals
    return B, inv_l, M


def _square_block_vertices(r: int) -> int:
    """Vertices per block of the steps that hold three ``[v,r,r]`` float64 arrays at a time (the gain's
    ``M^-1`` formed, :func:`frame_error_variance`'s sandwich): within :data:`BLOCK_BYTES`, at least one."""
    return max(1, int(BLOCK_BYTES // (8 * 3 * max(r, 1) ** 2)))


def _reduced_inverse_blocks(s, Q, D, reg):
    """``(B[K,r], inv_l[n,K], M^-1[n,r,r])``: :func:`_reduced_matrices`' ``B`` and ``inv_l`` and the inverse
    of its ``M``, formed and inverted a block of vertices at a time (:data:`BLOCK_BYTES`), so that ``M``
    itself is never whole (per vertex the same arithmetic as inverting :func:`_reduced_matrices`' ``M``)."""
    B = Q * s
    inv_l = 1.0 / (reg * np.asarray(D, dtype=np.float64).T ** 2)                      # [n,K]
    n, r = len(inv_l), len(s)
    inverse = np.empty((n, r, r))
    step = _square_block_vertices(r)
    for lo in range(0, n, step):
        v = slice(lo, min(lo + step, n))
        M = reduced_normal_matrix(inv_l[v], B)
        M.reshape(len(M), -1)[:, ::r + 1] += 1.0                                      # the diagonals
        inverse[v] = np.linalg.inv(M)
    return B, inv_l, inverse


def _direct_matrices(W, D, reg):
    """``(A[n,K,K], L[n,K])``: the K x K systems ``A_v = W^T W + L_v`` of eqs. (1)+(2), ``L = reg D^2``."""
    L = reg * np.asarray(D, dtype=np.float64).T ** 2                                 # [n,K]
    n, K = L.shape
    A = np.broadcast_to(W.T @ W, (n, K, K)).copy()
    A.reshape(n, -1)[:, ::K + 1] += L                                                # the diagonals
    return A, L


def _reduced_solve(W, R, T, system, extra_rhs: bool):
    """The r x r systems ``(I + H_v / reg) x_v = P^T e0_v`` (and, with ``extra_rhs``, ``= P^T``) of eqs.
    (1)+(2), ``e0 = R - W T``, in the weights' basis of ``system`` (a :class:`FitSystem` with ``basis``).
    With the system's ``gain`` the batched inverse ``M^-1`` is kept in it and applied (the weights' leak
    reuses it), else one batched LU solve. Returns ``(P, B, inv_l, e0, X)`` with ``X[n,r,c(+F)]``."""
    P, s, _ = system.basis
    B, inv_l, M = system.B, system.inv_l, system.M
    e0 = R - blend(W, T)                                                             # [F,n,c]
    F, n, c = e0.shape
    r = len(s)
    rhs = (P.T @ e0.reshape(F, -1)).reshape(r, n, c).transpose(1, 0, 2)              # [n,r,c]
    if extra_rhs:
        rhs = np.concatenate([rhs, np.broadcast_to(P.T, (n, r, F))], axis=2)
    if not r:
        X = rhs
    elif system.gain:
        X = np.matmul(system.inverse, rhs)              # M^-1, formed with the system (FitSystem)
    else:
        X = np.linalg.solve(M, rhs)
    return P, B, inv_l, e0, X


def _direct_system(W, R, T, system, extra):
    """The K x K systems ``A_v = W^T W + reg L_v`` of eqs. (1)+(2) (those of ``system``, a
    :class:`FitSystem` without ``basis``) with right-hand sides ``W^T r_v + reg L_v t_v`` (and ``W^T`` with
    ``extra``), solved in one batched LAPACK call: ``[n,K,c(+F)]``."""
    A, L = system.A, system.L
    n, K = L.shape
    rhs = project(W, R) + L[:, :, None] * T.transpose(1, 0, 2)                      # [n,K,c]
    if extra:
        rhs = np.concatenate([rhs, np.broadcast_to(W.T, (n, K, len(W)))], axis=2)
    return np.linalg.solve(A, rhs)


def _reduced_basis(W: np.ndarray):
    """:func:`weight_basis` of ``W`` when the r x r path pays (``r <= REDUCED_MAX_RANK K``; its rank is
    ``np.linalg.matrix_rank``'s, by the same threshold: one SVD for the test and the solve), else None."""
    basis = weight_basis(W)
    return basis if len(basis[1]) <= REDUCED_MAX_RANK * W.shape[1] else None


_UNSET = object()


def fit_block_vertices(weights: np.ndarray, basis) -> int:
    """Vertices per block of a fit without a caller's system (:func:`fit_blendshapes`): its per-vertex
    systems (``M[v,r,r]`` and the solve's copy and the product that forms it, or ``A[v,K,K]``), right-hand
    sides and residuals within :data:`BLOCK_BYTES` (at least one). A 74.5k-vertex capture's ``[n,r,r]``
    systems took ~1.4 GB at once. dev1's and dev3's captures (rank 28) are one block; the sample's (1,233)
    and dev2's (1,203), whose weights' rank takes the K x K systems, two (943 and 980 vertices a block at
    K = 51-52). Each vertex's solve is its own, but the batched LAPACK/BLAS calls' last bits can depend on
    the block's size (h106 measured 245-, 61- and 15-vertex blocks differing from 980-vertex ones in the last
    digits), so the fit's bits are those of this split; the answer is the same to rounding."""
    F, K = np.shape(weights)
    size = len(basis[1]) if basis is not None else K
    return max(1, int(BLOCK_BYTES // (8 * (3 * size * size + 3 * (F + size) + K))))


class FitSystem:
    """Eqs. (1)+(2)'s per-vertex systems at one ``weights[F,K]``, ``reg_weights[K,n]`` (D of eq. 3) and
    ``reg``, built once for the fit (:func:`fit_blendshapes`) and the extras that need the same matrices
    (:func:`weight_leak_variance`): in the weights' rank-r basis when it pays (:func:`_reduced_basis`:
    ``basis = (P, s, Q)``, ``B = Q S``, ``inv_l[n,K] = 1 / (reg D^2)``, ``M[n,r,r] = I + B^T diag(inv_l_v)
    B``), else the K x K systems (``basis`` None, ``A[n,K,K] = W^T W + reg diag(D_v^2)``, ``L[n,K]``).

    ``gain=True`` keeps the ridge's gain ``A_v^-1 W^T`` from the fit's own factorization, for the weights'
    leak: ``inverse = M^-1`` ``[n,r,r]`` (the fit applies it, one batched inverse instead of an LU solve
    and then the inverse; the same products up to rounding) or ``G = A^-1 W^T`` ``[n,K,F]`` (extra
    right-hand sides of the fit's one LU solve). ``G`` is None until the fit ran (or without ``gain``);
    with ``gain`` in the basis ``inverse`` is formed here, a block of vertices at a time, and ``M`` is None
    (at 74.5k capture vertices each is 0.47 GB: ``M`` whole beside its inverse took twice that)."""

    def __init__(self, weights, reg_weights, reg: float, *, gain: bool = False, basis=_UNSET):
        self.weights = np.asarray(weights, dtype=np.float64)
        self.reg_weights = reg_weights
        self.reg = float(reg)
        self.gain = bool(gain)
        self.inverse = self.G = None
        # ``basis``: :func:`_reduced_basis` of these weights when the caller has it (a blocked fit's blocks)
        self.basis = _reduced_basis(self.weights) if basis is _UNSET else basis
        if self.basis is None:
            self.A, self.L = _direct_matrices(self.weights, reg_weights, reg)
        else:
            _, s, Q = self.basis
            if self.gain and len(s):
                # the gain's M^-1 formed block by block, M never whole (_reduced_solve applies it)
                self.B, self.inv_l, self.inverse = _reduced_inverse_blocks(s, Q, reg_weights, reg)
                self.M = None
            else:
                self.B, self.inv_l, self.M = _reduced_matrices(s, Q, reg_weights, reg)

    def holds(self, weights, reg_weights, reg: float) -> bool:
        """Whether these are this system's ``weights``, ``reg_weights`` and ``reg`` (to the bit)."""
        return (float(reg) == self.reg
                and (reg_weights is self.reg_weights or np.array_equal(reg_weights, self.reg_weights))
                and np.array_equal(np.asarray(weights, dtype=np.float64), self.weights))


def fit_blendshapes(neutral: np.ndarray, points: np.ndarray, weights: np.ndarray, generic_deltas: np.ndarray,
                    reg_weights: np.ndarray, reg: float = 1.0, *,
                    system: FitSystem | None = None) -> np.ndarray:
    """Menzel et al. (2022), eqs. (1)+(2): personalized ``deltas[K,n,3]`` (metres) at a fixed balance ``reg``.

    ``neutral[n,3]`` = B0, ``points[F,n,3]`` = training meshes S_i, ``weights[F,K]`` = w_ij,
    ``generic_deltas[K,n,3]`` = T_j, ``reg_weights[K,n]`` = D_j diagonals (eq. 3, > 0). ``reg`` multiplies
    E_reg (1 = the paper). Solved exactly, n batched systems in one LAPACK call: r x r in the weights' rank-r
    basis (module docstring) when ``r <= REDUCED_MAX_RANK K``, else the K x K systems themselves.
    ``system``: the :class:`FitSystem` of these ``weights``, ``reg_weights`` and ``reg`` if the caller
    built it (with ``gain``, it keeps the gain for :func:`weight_leak_variance`).
    """
    W = np.asarray(weights, dtype=np.float64)
    if system is None:
        # every vertex's system is its own: solved a block of vertices at a time (fit_block_vertices), each
        # block's the same arithmetic as one call over every vertex
        basis = _reduced_basis(W)
        neutral = np.asarray(neutral, dtype=np.float64)
        step = fit_block_vertices(W, basis)
        if step < len(neutral):
            points, generic_deltas = np.asarray(points), np.asarray(generic_deltas)
            D = np.asarray(reg_weights)
            out = np.empty(generic_deltas.shape, dtype=np.float64)
            for lo in range(0, len(neutral), step):
                v = slice(lo, lo + step)
                out[:, v] = fit_blendshapes(neutral[v], points[:, v], W, generic_deltas[:, v], D[:, v], reg,
                                            system=FitSystem(W, D[:, v], reg, basis=basis))
            return out
        system = FitSystem(W, reg_weights, reg, basis=basis)
    R = np.asarray(points, dtype=np.float64) - np.asarray(neutral, dtype=np.float64)[None]   # [F,n,3]
    T = np.asarray(generic_deltas, dtype=np.float64)
    if system.basis is None:
        # partial-pivoting LU is accurate here without equilibration (the large entries are on the diagonal);
        # with the gain, A^-1 W^T as extra right-hand sides of the same solve
        c = R.shape[2]
        X = _direct_system(W, R, T, system, system.gain)
        if system.gain:
            system.G = X[:, :, c:]                                                         # A^-1 W^T
        return X[:, :, :c].transpose(1, 0, 2)
    _, B, inv_l, _, X = _reduced_solve(W, R, T, system, False)
    return T + (inv_l[:, :, None] * _left(B, X)).transpose(1, 0, 2)


def _reduced_inverse(weights, reg_weights, reg):
    """``(B[K,r], inv_l[n,K], X[n,r,K])`` of eqs. (1)+(2) at one ``reg`` in the weights' rank-r basis
    (``W^T W = B B^T``, ``B = Q S``; ``inv_l = 1 / (reg D^2)``): ``X_v = M_v^-1 B^T`` with ``M_v = I + B^T
    diag(inv_l_v) B``, by one batched r x r solve; ``X`` is None when the weights are all zero."""
    _, s, Q = weight_basis(weights)
    B, inv_l, M = _reduced_matrices(s, Q, reg_weights, reg)
    r = len(s)
    if r == 0:
        return B, inv_l, None
    return B, inv_l, np.linalg.solve(M, np.broadcast_to(B.T, (len(M), r, len(B))))


def data_share(weights: np.ndarray, reg_weights: np.ndarray, reg: float) -> np.ndarray:
    """:meth:`PositionFit.data_share` at one ``reg`` without the eigen-decomposition: the diagonal of
    ``A_v^-1 W^T W = reg^-1 L_v^-1 B (I + H_v / reg)^-1 B^T`` per vertex, ``[n,K]`` in [0, 1], by one batched
    r x r solve (``weights[F,K]``, ``reg_weights[K,n]``)."""
    B, inv_l, X = _reduced_inverse(weights, reg_weights, reg)
    return np.zeros_like(inv_l) if X is None else inv_l * np.einsum("kr,nrk->nk", B, X)


def estimate_variance(weights: np.ndarray, reg_weights: np.ndarray, reg: float) -> np.ndarray:
    """``[n,K]``: the sampling variance of each fitted shape at each vertex of eqs. (1)+(2) per unit of the
    frames' noise variance, the diagonal of the ridge estimator's sandwich ``A_v^-1 W^T W A_v^-1`` with ``A_v
    = W^T W + reg diag(D_v^2)`` (``weights[F,K]``, ``reg_weights[K,n]``, ``reg`` as in
    :func:`fit_blendshapes`). Times the frames' noise variance per coordinate (m^2), it is the variance of
    each coordinate of a shape's data-driven part; times the noise's variance per vertex (the coordinates'
    sum, 3x that of one), the expected squared length of its error, what :func:`james_stein` compares with.
    Unlike the hat share (:func:`data_share`, how much of the estimate the data sets) it grows where the data
    set a shape imprecisely: two shapes always shown together, at weights equal but for the phone's noise
    (dev1's ``mouthPressLeft`` and ``mouthPressRight``), are each "set by the data" when ``reg`` is small, but
    their difference only through that noise, and each one's variance is large. (Shown at exactly equal
    weights, their difference is the prior's and the variance small: the hat share is then one half.) Since
    ``A_v^-1 B = L_v^-1 B M_v^-1`` (:func:`_reduced_inverse`), the diagonal is ``inv_l^2 sum_r (M_v^-1
    B^T)_rk^2``."""
    _, inv_l, X = _reduced_inverse(weights, reg_weights, reg)
    return np.zeros_like(inv_l) if X is None else inv_l * inv_l * np.einsum("nrk,nrk->nk", X, X)


def weight_leak_variance(weights: np.ndarray, reg_weights: np.ndarray, reg: float, deltas: np.ndarray,
                         free: np.ndarray, *, system: FitSystem | None = None) -> np.ndarray:
    """``[n,K]`` (m^2 per unit of the weights' noise variance): the expected squared error each fitted shape
    of eqs. (1)+(2) takes at each vertex from independent errors of unit variance in the weights the frames
    report (``weights[F,K]``, the entries ``free[F,K]`` may err; ``reg_weights[K,n]``, ``reg`` as in
    :func:`fit_blendshapes`; ``deltas[K,n,3]`` the fitted shapes, metres). ``free`` may instead hold each
    entry's error variance (weight units squared, e.g. :func:`.weights.weight_error_variance`): the result is
    then in m^2. To first order a weight error
    ``e_fk`` is the frame error ``-e_fk B_k`` (the frame explained with the wrong weight), so frame ``f``'s
    noise variance at vertex ``v`` is ``E_fv = sum_k free_fk |B_kv|^2`` and each shape's error variance is
    ``sum_f (A_v^-1 W^T)_jf^2 E_fv`` (:func:`frame_error_variance`). A shape seen in one frame, beside a
    large shape whose weight errs there, takes that error whole: the leak that makes it worse than the prior.

    ``system``: the fit's :class:`FitSystem` (of these ``weights``, ``reg_weights`` and ``reg``; built with
    ``gain`` and used by the fit, it holds the gain already): its matrices and factorization are reused
    instead of being built again."""
    D = np.asarray(deltas, dtype=np.float64)
    energy = np.asarray(free, dtype=np.float64) @ np.einsum("knc,knc->kn", D, D)        # [F,n]
    return frame_error_variance(weights, reg_weights, reg, energy, system=system)


def weight_leak_direction(weights: np.ndarray, reg_weights: np.ndarray, reg: float, deltas: np.ndarray,
                          free: np.ndarray, vertex_weights: np.ndarray, *, system: FitSystem | None = None,
                          parts: int = LEAK_PARTS) -> tuple[np.ndarray, np.ndarray]:
    """The one pattern along which the weights' leak into each fitted shape is largest, and its variance:
    ``(direction[K,n,3], energy[K])``, ``direction_j`` of unit length (zero off ``vertex_weights[n,K] > 0``,
    the vertices the shape's personalization moves) and ``energy_j`` (m^2 per unit of the weights' noise
    variance; m^2 when ``free`` holds each entry's error variance) the expected squared projection of the leak
    on it, every part's. Arrays as in :func:`weight_leak_variance`.

    A weight error ``e_fk`` moves every vertex of shape ``j`` along one pattern, ``u_fk(v) = (A_v^-1
    W^T)_jf B_k(v)``, so the leak is a Gaussian field whose covariance ``sum_fk free_fk u_fk u_fk^T`` has the
    per-vertex trace :func:`weight_leak_variance` and a few large eigenvalues: a shape shown in one frame
    beside ``jawOpen`` at an inside weight takes that weight's error along the jaw's own pattern, one draw
    (one number) whatever the number of vertices. The ``parts`` largest ``(f, k)`` (by their energy on the
    vertices) span the direction: the top eigenvector of their Gram matrix."""
    W = np.asarray(weights, dtype=np.float64)
    D = np.asarray(deltas, dtype=np.float64)
    var = np.asarray(free, dtype=np.float64)                                          # [F,K]
    wv = np.asarray(vertex_weights, dtype=np.float64) > 0                              # [n,K]
    K = D.shape[0]
    direction, energy = np.zeros_like(D), np.zeros(K)
    if system is None or not system.holds(W, reg_weights, reg):
        system = FitSystem(W, reg_weights, reg)
    if len(W) == 0 or not var.any():
        return direction, energy
    if system.basis is None:
        inv_a = None if system.G is not None else np.linalg.inv(system.A)

        def gain(j, m):
            """``(A_v^-1 W^T)_j`` for every vertex ``m`` (bool ``[n]``) and frame, ``[v,F]``."""
            return system.G[m, j, :] if inv_a is None else inv_a[m, j, :] @ W.T
    else:
        P, _, _ = system.basis
        if P.shape[1] == 0:
            return direction, energy
        inv_m = np.linalg.inv(system.M) if system.inverse is None else system.inverse
        # B_j^T M_v^-1 for every vertex, a block of g shapes at a time ([n,g,r] of at most BLOCK_BYTES; every
        # shape in one block up to BLOCK_BYTES / (8 K r) vertices, dev1's 1,203 at K = 51, r = 28 included):
        # one stacked matrix product per block (not K unbuffered einsums; 3x faster than one flat product
        # over a transposed copy of M^-1, and without that copy)
        n, r = len(inv_m), P.shape[1]
        group = int(min(K, max(1, BLOCK_BYTES // (8 * n * r))))
        block = {"first": -1, "rows": None}

        def gain(j, m):
            first = j - j % group
            if block["first"] != first:
                block["rows"] = None                    # the last block's memory before the next one's
                block["first"], block["rows"] = first, np.matmul(system.B[first:first + group], inv_m)
            return system.inv_l[m, j, None] * (block["rows"][m, j - first] @ P.T)
    B2 = squared_lengths(D)                                                          # [K,n]
    D_v = np.ascontiguousarray(D.transpose(1, 0, 2))                                 # [n,K,3]: rows gathered
    for j in range(K):
        m = wv[:, j]
        if not m.any():
            continue
        G = gain(j, m)                                                               # [v,F]
        # each part's energy on the shape's vertices (the gain and the shape's size each averaged there)
        e = np.sum(G * G, axis=0)[:, None] * var * B2[:, m].mean(axis=1)[None]        # [F,K]
        top = np.argsort(e, axis=None)[::-1][:parts]
        top = top[e.ravel()[top] > 0]
        if not len(top):
            continue
        fs, ks = np.unravel_index(top, e.shape)
        u = np.sqrt(var[fs, ks])[:, None, None] * G.T[fs][:, :, None] * D[ks][:, m]     # [i,v,3]
        gram = np.einsum("inc,lnc->il", u, u)
        vals, vecs = np.linalg.eigh(gram)
        if vals[-1] <= 0:
            continue
        e_j = np.einsum("i,inc->nc", vecs[:, -1], u) / np.sqrt(vals[-1])
        direction[j, m] = e_j
        # the variance along it of every part, not only of those that span it: sum_fk var_fk <u_fk, e>^2
        energy[j] = np.sum(var * (G.T @ np.einsum("vc,vkc->vk", e_j, D_v[m])) ** 2)
    return direction, energy


def frame_error_variance(weights: np.ndarray, reg_weights: np.ndarray, reg: float, energy: np.ndarray, *,
                         system: FitSystem | None = None) -> np.ndarray:
    """``[n,K]`` (m^2): the variance each fitted shape of eqs. (1)+(2) takes at each vertex from independent
    errors in the frames, frame ``f``'s at vertex ``v`` of variance ``energy[F,n]`` (m^2, summed over the
    vertex's coordinates): ``sum_f (A_v^-1 W^T)_jf^2 E_fv``, the ridge's sandwich with per-frame noise
    (``weights[F,K]``, ``reg_weights[K,n]``, ``reg`` as in :func:`fit_blendshapes`). The weights' leak
    (:func:`weight_leak_variance`) and a take's scan noise (:func:`take_frame_noise`) are two such energies.
    ``system`` as in :func:`weight_leak_variance`."""
    W = np.asarray(weights, dtype=np.float64)
    energy = np.asarray(energy, dtype=np.float64)
    if system is None or not system.holds(W, reg_weights, reg):
        system = FitSystem(W, reg_weights, reg)
    if system.basis is None:
        G = system.G                                                                 # [n,K,F]
        if G is not None:
            return np.einsum("nkf,nkf,fn->nk", G, G, energy)
        # without the fit's gain (a take of thousands of frames: [n,K,F] would be gigabytes) the same sum per
        # vertex as diag(A_v^-1 (W^T diag(E_v) W) A_v^-1), over blocks of vertices of at most ~64 MB
        n, K = system.L.shape
        out = np.empty((n, K))
        step = max(1, int(BLOCK_BYTES // (8 * max(len(W), 1) * max(K, 1))))
        for lo in range(0, n, step):
            v = slice(lo, min(lo + step, n))
            C = (W.T[None] * energy[:, v].T[:, None, :]) @ W                            # [c,K,K]
            inv = np.linalg.inv(system.A[v])
            out[v] = np.einsum("cjk,ckl,cjl->cj", inv, C, inv)
        return out
    P, s, _ = system.basis
    B, inv_l, M = system.B, system.inv_l, system.M
    n, r = len(inv_l), len(s)
    if r == 0:
        return np.zeros_like(inv_l)
    # A_v^-1 W^T = diag(inv_l_v) B M_v^-1 P^T (W^T = B P^T, A_v^-1 B = L_v^-1 B M_v^-1), so the sum over the
    # frames is inv_l_vj^2 (B C_v B^T)_jj with C_v = M_v^-1 (P^T diag(E_v) P) M_v^-1: r x r per vertex, no
    # [n,K,F] array
    pp = (P[:, :, None] * P[:, None, :]).reshape(len(P), r * r)                       # [F, r^2]
    bb = (B[:, :, None] * B[:, None, :]).reshape(len(B), r * r)                       # [K, r^2]
    # one batched inverse (the fit's, if it kept it), then two stacked products, a block of vertices at a
    # time (three [v,r,r] arrays within BLOCK_BYTES: 1.4 GB at once on a 74.5k-vertex capture)
    out = np.empty_like(inv_l)
    step = _square_block_vertices(r)
    for lo in range(0, n, step):
        v = slice(lo, min(lo + step, n))
        inv_m = np.linalg.inv(M[v]) if system.inverse is None else system.inverse[v]
        C = inv_m @ (energy[:, v].T @ pp).reshape(-1, r, r) @ inv_m
        out[v] = inv_l[v] ** 2 * (C.reshape(-1, r * r) @ bb.T)
    return out


def take_frame_noise(offsets: np.ndarray, weights: np.ndarray, omega: np.ndarray) -> float:
    """The scan noise of a take read whole, m^2 per coordinate, from its frames' ``offsets[F,n,3]`` (metres,
    frame minus neutral) and ``weights[F,K]``, both scaled by ``sqrt(omega[F])`` as the frame-weighted fit
    has them (:func:`usdface.personalize.takefit.weighted_frames`): the least-squares residual of the
    offsets on the weights (no prior, no regularization: the ridge's shrink towards the prior would count as
    noise, by 50 % on a take thinned to 281 frames), ``|R|^2 - |U^T R|^2`` with ``U`` the weights' left
    singular vectors, over its expectation ``3 n sum_f omega_f (1 - h_f)`` per unit variance (``h_f =
    |U_f|^2`` the leverage; the residual of a projection, so exact). A take has hundreds of frames for ~50
    shapes, so this measures what the shapes do not explain: the scans' noise, and what the weights' noise and
    the model's misfit add (the first counted again beside :func:`weight_leak_variance`: on the cautious
    side). NaN without a degree of freedom left."""
    F = len(weights)
    R = np.asarray(offsets, dtype=np.float64).reshape(F, -1)
    if not F or not R.shape[1]:
        return float("nan")
    rss, dof = _unexplained(R, weights, omega)
    return rss / (R.shape[1] * dof) if dof > 0 else float("nan")


def _unexplained(rows: np.ndarray, weights: np.ndarray, omega: np.ndarray) -> tuple[float, float]:
    """``(rss, dof)`` of ``rows[F,m]`` regressed on ``weights[F,K]`` by least squares (both scaled by
    ``sqrt(omega[F])``): the residual's energy ``|R|^2 - |U^T R|^2`` (``U`` the weights' left singular
    vectors, :func:`weight_basis`) and its expectation per column and unit noise variance, ``sum_f omega_f
    (1 - h_f)`` (``h_f = |U_f|^2`` the leverage). The common part of :func:`take_frame_noise` and
    :func:`take_white_noise`."""
    U = weight_basis(weights)[0]
    explained = U.T @ rows                                                                # [r, m]
    rss = float(np.einsum("fi,fi->", rows, rows) - np.einsum("ri,ri->", explained, explained))
    om = np.asarray(omega, dtype=np.float64)
    dof = float(np.sum(om * np.clip(1.0 - np.einsum("fr,fr->f", U, U), 0.0, 1.0)))
    return max(rss, 0.0), dof


def take_white_noise(offsets: np.ndarray, weights: np.ndarray, omega: np.ndarray, triangles) -> float:
    """The part of :func:`take_frame_noise` that is independent from vertex to vertex (the scans' own), m^2
    per coordinate: the same least-squares residual ``R`` (``offsets[F,n,3]``, ``weights[F,K]`` scaled by
    ``sqrt(omega)``), read through the mesh's umbrella Laplacian ``L``
    (:func:`usdface.mesh.uniform_laplacian`), ``|R L^T|^2`` over its expectation for white noise
    ``3 sum_f omega_f (1 - h_f) tr(L L^T)``. What the
    weights' noise and the model's misfit leave in the residual moves neighbouring vertices alike (a shape's
    motion times a weight's error) and the Laplacian cancels it; on a phone-noise take (0.1 mm scans, weights
    +-0.02) it was most of :func:`take_frame_noise`. The smoothing of
    :func:`usdface.transfer.denoise.denoise_personalization` is set by this part alone. NaN without a degree
    of freedom left."""
    from ..mesh import uniform_laplacian

    F = len(weights)
    off = np.asarray(offsets, dtype=np.float64)
    if not F or not off.size:
        return float("nan")
    n = off.shape[1]
    lap = uniform_laplacian(np.asarray(triangles), n)
    # L acts on the vertices, the projection on the frames: they commute, so the residual of the rough part
    rough = (lap @ off.transpose(1, 0, 2).reshape(n, -1)).reshape(n, F, 3).transpose(1, 0, 2).reshape(F, -1)
    rss, dof = _unexplained(rough, weights, omega)
    trace = float(lap.multiply(lap).sum())
    if dof <= 0 or trace <= 0:
        return float("nan")
    return rss / (3.0 * trace * dof)


def james_stein(personalization: np.ndarray, variance: np.ndarray, vertex_weights: np.ndarray) -> np.ndarray:
    """``[K]`` in [0, 1]: the positive-part James-Stein factor ``max(0, 1 - var_j / |D_j|^2)`` (Efron &
    Morris 1973) of each shape's personalization ``personalization[K,m,3]`` (``D_j = B_j - T_j``, metres)
    given its estimate's variance ``variance[m,K]`` (m^2, :func:`estimate_variance` times the noise),
    both averaged over the vertices with ``vertex_weights[m,K]`` (>= 0). A shape whose personalization is
    no larger than its estimate's noise gets 0 (stays the prior); one far above it keeps it (~1)."""
    D = np.asarray(personalization, dtype=np.float64)
    w = np.asarray(vertex_weights, dtype=np.float64)
    total = np.maximum(w.sum(axis=0), 1e-300)                                          # [K]
    power = np.einsum("mk,kmc,kmc->k", w, D, D) / total
    var = np.sum(w * np.asarray(variance, dtype=np.float64), axis=0) / total
    return np.clip(1.0 - var / np.maximum(power, 1e-300), 0.0, 1.0)


def loo_residuals(neutral: np.ndarray, points: np.ndarray, weights: np.ndarray, generic_deltas: np.ndarray,
                  reg_weights: np.ndarray, reg: float, predict_weights=None) -> np.ndarray:
    """Exact leave-one-frame-out residuals ``[F,n,3]`` (metres) of eqs. (1)+(2) at one ``reg``, by one batched
    r x r solve per vertex (cheaper than :class:`PositionFit`'s eigen-decomposition when only one ``reg`` is
    needed). Arrays as in :func:`fit_blendshapes`; ``predict_weights[F,K]`` as in
    :meth:`PositionFit.loo_residuals`.

    With ``G_v = (I + H_v / reg)^-1 P^T``: the fitted frames are ``W t + P (P^T e0 - x)``, the hat diagonal
    ``h_i = |P_i|^2 - P_i . G_v[:, i]`` and ``A_v^-1 W^T = reg^-1 L_v^-1 B G_v``."""
    W = np.asarray(weights, dtype=np.float64)
    R = np.asarray(points, dtype=np.float64) - np.asarray(neutral, dtype=np.float64)[None]   # [F,n,3]
    T = np.asarray(generic_deltas, dtype=np.float64)
    c = R.shape[2]
    Pw = None if predict_weights is None else np.asarray(predict_weights, dtype=np.float64)
    system = FitSystem(W, reg_weights, reg)
    if system.basis is None:                                 # the K x K systems: b_v and G_v = A_v^-1 W^T
        X = _direct_system(W, R, T, system, True)
        b, G = X[:, :, :c], X[:, :, c:]
        e = (R - _left(W, b).transpose(1, 0, 2)) / np.maximum(1.0 - np.einsum("fk,nkf->fn", W, G),
                                                              1e-9)[:, :, None]
        if Pw is None:
            return e
        cross = np.einsum("fk,nkf->fn", Pw, G)
        return R - _left(Pw, b).transpose(1, 0, 2) + cross[:, :, None] * e
    P, B, inv_l, e0, X = _reduced_solve(W, R, T, system, True)
    x, G = X[:, :, :c], X[:, :, c:]                                                  # [n,r,c], [n,r,F]
    Pte0 = _left(P.T, e0.transpose(1, 0, 2))                                         # [n,r,c]
    resid = e0 - _left(P, Pte0 - x).transpose(1, 0, 2)                               # [F,n,c]
    h = np.sum(P ** 2, axis=1)[:, None] - np.einsum("fr,nrf->fn", P, G)
    e = resid / np.maximum(1.0 - h, 1e-9)[:, :, None]
    if Pw is None:
        return e
    XB = _left(Pw, inv_l[:, :, None] * B)                                            # [n,F,r]: p^T L^-1 B
    pred = blend(Pw, T) + np.matmul(XB, x).transpose(1, 0, 2)                        # p_i^T b
    cross = np.einsum("nfr,nrf->fn", XB, G)                                          # p_i^T A^-1 w_i
    return R - pred + cross[:, :, None] * e


class PositionFit:
    """Menzel et al. (2022), eqs. (1)-(2) prepared for many regularisation strengths.

    ``neutral[n,3]``, ``points[F,n,c]``, ``weights[F,K]``, ``generic_deltas[K,n,c]``, ``reg_weights[K,n]``
    (> 0); optional ``alt_deltas[K,n,c]``, a second prior to blend with (:meth:`set_prior_mix`).
    One SVD of the weights and one per-vertex eigen-decomposition of the r x r ``H_v = B^T L_v^-1 B``
    (module docstring); then :meth:`solve` (deltas at a ``reg``), :meth:`loo_error` (exact
    leave-one-frame-out residual, the closed form ``e_i / (1 - h_ii)`` of linear smoothers, for many ``reg``
    at once: :meth:`loo_errors`) and :meth:`data_share` cost O(n F r) per ``reg``; new points
    (:meth:`set_points`) or priors (:meth:`set_prior`) need no new decomposition.
    """

    def __init__(self, neutral, points, weights, generic_deltas, reg_weights, alt_deltas=None, *,
                 block: int = 1):
        #: frames held out together by the cross-validation criteria (1: leave-one-frame-out, the default;
        #: see :meth:`_block_residuals` and :func:`usdface.personalize.takefit.cv_block`)
        self.block = max(int(block), 1)
        self.W = np.asarray(weights, dtype=np.float64)
        self.neutral = np.asarray(neutral, dtype=np.float64)
        self.P, s, Q = weight_basis(self.W)
        self.B = Q * s                                                       # [K,r]
        self.inv_l = 1.0 / np.asarray(reg_weights, dtype=np.float64).T ** 2  # L^-1  [n,K]
        H = reduced_normal_matrix(self.inv_l, self.B)
        if self.B.shape[1]:
            self.mu, self.V = np.linalg.eigh(H)                              # [n,r], [n,r,r]
        else:
            self.mu, self.V = np.zeros(H.shape[:2]), H
        self.mu = np.maximum(self.mu, 0.0)
        # P V [n,F,r] and B V [n,K,r]: V's vertex-major copy made once for both products
        self.Z, self.BV = _lefts(self.V, self.P, self.B)
        # Z^2 (the hat diagonals' weights), once for every reg and step; per vertex block for a long take
        self._Z2 = self.Z ** 2 if self.Z.nbytes <= (64 << 20) else None
        self.T_main = np.asarray(generic_deltas, dtype=np.float64)
        self.T_alt = None if alt_deltas is None else np.asarray(alt_deltas, dtype=np.float64)
        self.has_alt = self.T_alt is not None
        self._prior_parts = {}
        self._loo_cache = (None, None)          # ((prior/points state, reg), LOO residuals) of the last call
        self._state = 0
        self.set_points(points)

    def _coeffs(self, T):
        """``(V^T B^T t_v [n,r,c], W t [F,n,c])`` of a prior ``T[K,n,c]``."""
        Bt = _left(self.B.T, T.transpose(1, 0, 2))                          # [n,r,c]
        return np.matmul(np.swapaxes(self.V, 1, 2), Bt), blend(self.W, T)

    def set_points(self, points) -> None:
        """Replace the training frames ``points[F,n,c]`` (same weights): O(n F r), no new decomposition
        (the priors' coefficients do not depend on the frames: computed once). The frames it already holds:
        a no-op."""
        points = np.asarray(points, dtype=np.float64)
        if hasattr(self, "_points") and self._points.shape == points.shape and np.array_equal(self._points,
                                                                                              points):
            return
        self._points = points.copy()                    # a copy: the caller may change its array in place
        self.R = points - self.neutral[None]
        self._set_frame_groups()
        PtR = _left(self.P.T, self.R.transpose(1, 0, 2))                     # [n,r,c]
        self.cR = np.matmul(np.swapaxes(self.V, 1, 2), PtR)                 # V^T P^T r
        if not hasattr(self, "_main"):
            self._main = self._coeffs(self.T_main)
            self._alt = None if self.T_alt is None else self._coeffs(self.T_alt)
            self._custom_T, self._custom = None, None
            self._mix = 1.0
        self._apply_prior()

    def _set_frame_groups(self) -> None:
        """Training frames that are one frame (the same weights and points to the bit: a capture app that
        kept one scan for several shapes) have the same rows of ``Z``, ``e0`` and hence the same
        leave-one-frame-out residual: the criteria compute it once per distinct frame
        (``_first[U]``, ``_inverse[F]``; None when every frame is distinct, for block hold-outs, and when
        ``Z`` is too large to keep a copy of its distinct rows: a long take's). ``Z``'s distinct rows are
        gathered again only when the groups change (new frames usually keep them: an aligned copy of a
        repeated frame is the same copy)."""
        previous = getattr(self, "_first", None)
        self._first = self._inverse = None
        F = len(self._points)
        if self.block > 1 or F < 2 or self._Z2 is None:
            return
        groups = self.frame_groups()                                    # (each group's first frame, group)
        if groups is None:
            return
        self._first, self._inverse = groups
        first = self._first
        if previous is not None and np.array_equal(previous, first):
            return                                                      # Z's rows of the same frames
        # [n,U,r] C-ordered, gathered frame-major from Z's own [F,n,r] layout (np.take on the [n,F,r] view
        # first copied all of Z)
        self._Zu = np.ascontiguousarray(np.take(self.Z.transpose(1, 0, 2), first, axis=0).transpose(1, 0, 2))
        self._Z2u = None if self._Z2 is None else self._Zu ** 2          # = Z^2's rows, squared once

    def frame_groups(self):
        """``(first[U], inverse[F])``: the training frames that are one frame, the same weights and points to
        the bit (:func:`.align.distinct_frames`; None when every frame is distinct), found once per set of
        frames - for a caller that works frame by frame on them (the alignment's rigid transforms)."""
        if getattr(self, "_groups_of", None) is not self._points:
            self._groups = distinct_frames(self.W, self._points) if len(self._points) > 1 else None
            self._groups_of = self._points
        return self._groups

    def _apply_prior(self) -> None:
        self._state += 1                                # new frames or prior: cached residuals are stale
        if self._custom is not None:
            self.T, (cT, WT) = self._custom_T, self._custom
        elif self._alt is None or self._mix == 1.0:
            self.T, (cT, WT) = self.T_main, self._main
        else:
            a = self._mix
            self.T = a * self.T_main + (1.0 - a) * self.T_alt
            cT = a * self._main[0] + (1.0 - a) * self._alt[0]
            WT = a * self._main[1] + (1.0 - a) * self._alt[1]
        self.c = self.cR - cT                                                # V^T P^T (r - W t)  [n,r,c]
        self.e0 = self.R - WT                                                # r - W t  [F,n,c]
        self.e0n = np.ascontiguousarray(self.e0.transpose(1, 0, 2))          # the same, [n,F,c]
        self._e0nu = None                                                    # its distinct frames' rows

    def _e0n_distinct(self) -> np.ndarray:
        """``e0n`` on the distinct frames only (:meth:`_set_frame_groups`), ``[n,U,c]``: gathered once per
        prior and frames (every criterion of the searches asked for it again)."""
        if self._e0nu is None:
            self._e0nu = _take1(self.e0n, self._first)
        return self._e0nu

    def set_prior_mix(self, alpha: float) -> None:
        """Use the prior ``alpha * generic_deltas + (1 - alpha) * alt_deltas`` (eq. 2's T_j) from now on."""
        if self._custom is None and self._mix == float(alpha):
            return                                                        # the blend it already uses
        self._custom_T, self._custom = None, None
        self._mix = float(alpha)
        self._apply_prior()

    def set_prior(self, prior_deltas) -> None:
        """Use the prior ``prior_deltas[K,n,c]`` (eq. 2's T_j, on this fit's vertices) from now on."""
        prior = np.asarray(prior_deltas, dtype=np.float64)
        if self.T.shape == prior.shape and np.array_equal(self.T, prior):
            return              # the prior it holds, as given or as a blend (the alignment passes re-set it)
        self._custom_T = prior
        self._custom = self._coeffs(self._custom_T)
        self._apply_prior()

    def data_share(self, reg: float) -> np.ndarray:
        """Per vertex and shape, the share of the fitted shape determined by the frames rather than the prior:
        the diagonal of ``A_v^-1 W^T W`` (``A_v = W^T W + reg L_v``), ``[n,K]`` in [0, 1].

        Since ``b_v = A_v^-1 W^T r_v + A_v^-1 reg L_v t_v`` and the two matrices sum to the identity, entry
        ``(v, j)`` is how much of ``b_vj`` follows the data (1) rather than the prior (0): 0 for a shape with
        zero training weight, -> 1 for a shape isolated in a frame as ``reg`` -> 0. In the reduced basis it
        is ``L_jj^-1 sum_k (B V)_jk^2 / (mu_k + reg)`` (the per-shape effective degrees of freedom)."""
        return self.inv_l * np.matmul(self.BV ** 2, (1.0 / (self.mu + reg))[:, :, None])[:, :, 0]

    def estimate_variance(self, reg: float) -> np.ndarray:
        """:func:`estimate_variance` from this fit's decomposition, ``[n,K]``: with ``A_v^-1 B = L_v^-1 B V
        diag(mu + reg)^-1 V^T`` the diagonal of ``A_v^-1 W^T W A_v^-1`` is ``L_jj^-2 sum_k (B V)_jk^2 /
        (mu_k + reg)^2`` (one product, as :meth:`data_share`)."""
        return self.inv_l ** 2 * np.matmul(self.BV ** 2, (1.0 / (self.mu + reg) ** 2)[:, :, None])[:, :, 0]

    def solve(self, reg: float) -> np.ndarray:
        """Deltas ``[K,n,c]`` minimising E_fit + reg * E_reg."""
        coef = self.c / (self.mu + reg)[:, :, None]
        return self.T + (self.inv_l[:, :, None] * np.matmul(self.BV, coef)).transpose(1, 0, 2)

    def _z2(self, v, distinct=False):
        """``Z^2`` on the vertices ``v`` (a slice or indices; ``distinct``: the distinct frames' rows): the
        kept copy, or squared for the block (for a take's thousands of frames no ``[n,F,r]`` copy is kept)."""
        if distinct:
            return self._Zu[v] ** 2 if self._Z2u is None else self._Z2u[v]
        return self.Z[v] ** 2 if self._Z2 is None else self._Z2[v]

    def _loo_parts(self, regs, c, e0n, v=slice(None), distinct=False):
        """For ``regs[G]``: the leave-in residuals ``d[n,F,k,G]`` of the prior's ``c[n,r,k]``, ``e0n[n,F,k]``
        and the squared LOO factors ``q = (1 - h)^-2`` ``[n,F,G]`` (LOO residual = ``d sqrt(q)``): two batched
        products for the whole grid. The grid is the last (contiguous) axis: the broadcasts run over it.
        ``v``: only these vertices (a block of :meth:`_loo_blocks`); ``distinct``: on the distinct frames
        only (:meth:`_set_frame_groups`; ``e0n`` given on them, ``F`` = their number)."""
        regs = np.asarray(regs, dtype=np.float64)
        Z, mu, c, e0n = (self._Zu if distinct else self.Z)[v], self.mu[v], c[v], e0n[v]
        n, F, r = Z.shape
        # [n,r,G], computed as [G,n,r] (each reg a scalar against whole planes: 2x cheaper than the broadcast
        # over a 9-long last axis), the same numbers
        g = np.ascontiguousarray((mu[None] / (mu[None] + regs[:, None, None])).transpose(1, 2, 0))
        gc = (c[:, :, :, None] * g[:, :, None, :]).reshape(n, r, -1)                 # [n,r,k*G]
        d = np.matmul(Z, gc).reshape(n, F, c.shape[2], len(regs))
        np.subtract(e0n[:, :, :, None], d, out=d)
        q = np.maximum(1.0 - np.matmul(self._z2(v, distinct), g), 1e-9)
        return d, np.reciprocal(q * q, out=q)                                         # [n,F,G]

    def _block_residuals(self, regs, d, v=slice(None)) -> np.ndarray:
        """Leave-block-out residuals ``[n,F,k,G]`` from the leave-in residuals ``d[n,F,k,G]``
        (:meth:`_loo_parts`) of the vertices ``v``: the training frames in consecutive blocks of
        :attr:`block` (the last one shorter), each block's residual predicted by the fit on the other
        blocks, ``(I - H_BB)^-1 e_B`` with the hat matrix ``H = Z diag(g) Z^T``, ``g = mu / (mu + reg)`` (the
        block form of ``e_i / (1 - h_ii)``; ``I - H_BB`` is positive definite, its eigenvalues at least
        ``reg / (mu_max + reg)``, since ``Z`` has orthonormal columns). Not the default for takes (see
        docs/takes.md: a block long enough to stop the neighbours' help holds out whole expressions and
        over-regularizes); exact against refits. A block of ``b <= r`` frames solves its ``b x b`` system; a
        longer one the ``r x r`` system of the Woodbury identity
        ``(I - Z_B G Z_B^T)^-1 = I + Z_B G^1/2 (I - G^1/2 Z_B^T Z_B G^1/2)^-1 G^1/2 Z_B^T``."""
        regs = np.asarray(regs, dtype=np.float64)
        Z, mu = self.Z[v], self.mu[v]
        n, F, r = Z.shape
        k = d.shape[2]
        b = min(self.block, F)
        m = F // b
        parts = [(0, m * b, m, b)] + ([(m * b, F, 1, F - m * b)] if F % b else [])
        out = np.empty_like(d)
        for gi, reg in enumerate(regs):
            g = mu / (mu + reg)                                                      # [n,r]
            for lo, hi, nb, bb in parts:
                zb = Z[:, lo:hi].reshape(n, nb, bb, r)
                db = np.ascontiguousarray(d[:, lo:hi, :, gi]).reshape(n, nb, bb, k)
                if bb <= r:                                                         # I - Z_B G Z_B^T
                    a = -np.matmul(zb * g[:, None, None, :], np.swapaxes(zb, 2, 3))
                    a[..., np.arange(bb), np.arange(bb)] += 1.0
                    sol = np.linalg.solve(a, db)
                else:
                    zs = zb * np.sqrt(g)[:, None, None, :]                          # Z_B G^1/2
                    a = -np.matmul(np.swapaxes(zs, 2, 3), zs)
                    a[..., np.arange(r), np.arange(r)] += 1.0
                    sol = db + np.matmul(zs, np.linalg.solve(a, np.matmul(np.swapaxes(zs, 2, 3), db)))
                out[:, lo:hi, :, gi] = sol.reshape(n, hi - lo, k)
        return out

    def _loo_blocks(self, regs, k: int):
        """Vertex blocks (slices) for :meth:`_loo_parts` whose ``d[n,F,k,G]`` stays within ~64 MB: one block
        (all vertices, the same arithmetic as unblocked) for a capture of a few dozen frames, several for the
        thousands of frames of a whole take, whose grids would otherwise need gigabytes."""
        n, F, _ = self.Z.shape
        per_vertex = F * k * max(len(np.atleast_1d(regs)), 1) * 8
        step = max(1, (64 << 20) // per_vertex)
        return [slice(s, s + step) for s in range(0, n, step)] if step < n else [slice(None)]

    def loo_errors_mix(self, regs, alphas) -> np.ndarray:
        """:meth:`loo_error` ``[A,G]`` for every prior blend ``alpha`` in ``alphas`` (:meth:`set_prior_mix`)
        and ``reg`` in ``regs``: the LOO residual is affine in ``alpha``, so two grids give them all."""
        alphas = np.asarray(alphas, dtype=np.float64)
        if self._alt is None:
            return np.broadcast_to(self.loo_errors(regs), (len(alphas), len(regs))).copy()
        if len(alphas) == 1:
            self.set_prior_mix(float(alphas[0]))
            return self.loo_errors(regs)[None]
        k = self.c.shape[2]
        c = np.concatenate([self.cR - self._main[0], self.cR - self._alt[0]], axis=2)
        distinct = self._first is not None
        R, WT1, WT0 = self.R, self._main[1], self._alt[1]
        if distinct:                                     # each distinct frame once, counted by its copies
            R, WT1, WT0 = R[self._first], WT1[self._first], WT0[self._first]
            count = np.bincount(self._inverse).astype(np.float64)[None, :, None]
        e0n = np.ascontiguousarray(np.concatenate([R - WT1, R - WT0], axis=2).transpose(1, 0, 2))
        s11 = s00 = s01 = 0.0
        for v in self._loo_blocks(regs, 2 * k):
            d, q = self._loo_parts(regs, c, e0n, v, distinct)
            if distinct:
                q *= count
            if self.block > 1:                    # the block residuals are linear in the prior's too
                d = self._block_residuals(regs, d, v)
                d1, d0 = d[:, :, :k], d[:, :, k:]
                b11, b00, b01 = (np.einsum("nfkg,nfkg->g", x, y) for x, y in ((d1, d1), (d0, d0), (d1, d0)))
            else:
                d1, d0 = d[:, :, :k], d[:, :, k:]
                b11, b00, b01 = (np.einsum("nfg,nfg->g", _sum_axis2(x * y), q)
                                 for x, y in ((d1, d1), (d0, d0), (d1, d0)))
            s11, s00, s01 = s11 + b11, s00 + b00, s01 + b01
        a = alphas[:, None]
        n, F = self.Z.shape[:2]
        return (a ** 2 * s11 + (1 - a) ** 2 * s00 + 2 * a * (1 - a) * s01) / (n * F * k)

    def loo_residuals(self, reg: float, predict_weights: np.ndarray | None = None,
                      vertices: np.ndarray | None = None, loo: np.ndarray | None = None) -> np.ndarray:
        """Leave-one-frame-out residuals ``[F,n,c]`` (metres): frame i minus its prediction by the fit on the
        other frames, ``e_i / (1 - h_ii)``.

        ``predict_weights[F,K]``: predict frame i with these weights instead of the fitted ones (e.g. the
        phone's, when the fit used re-estimated weights): ``r_i - p_i^T b^(-i)`` with the exact downdate
        ``b^(-i) = b - A^-1 w_i e_i / (1 - h_ii)`` (Sherman-Morrison); ``predict_weights[S,F,K]``: ``S`` such
        sets at once, ``[S,F,n,c]`` (one product for all). ``vertices``: only these (indices into this fit's
        vertices; the result is ``[F,len(vertices),c]``). ``loo``: the plain residuals ``e`` at ``reg`` on
        these vertices if already computed (they do not depend on ``predict_weights``). The plain residuals on
        every vertex are kept (read-only) for the next call with the same ``reg``, frames and prior."""
        v = slice(None) if vertices is None else np.asarray(vertices)
        mu, c = self.mu[v], self.c[v]
        key = (self._state, float(reg))
        if loo is None and vertices is None and self._loo_cache[0] == key:
            e = self._loo_cache[1]          # the same frames, prior and reg (the alignment test, then pass)
        elif loo is None:
            distinct = self._first is not None                    # once per distinct frame, then copied
            g = mu / (mu + reg)
            fitted = np.matmul((self._Zu if distinct else self.Z)[v], g[:, :, None] * c)     # [n,F,c]
            h = np.matmul(self._z2(v, distinct), g[:, :, None])[:, :, 0]             # [n,F]
            e0n = (self._e0n_distinct() if distinct else self.e0n)[v]
            e = (e0n - fitted) / np.maximum(1.0 - h, 1e-9)[:, :, None]
            e = (_take1(e, self._inverse) if distinct else e).transpose(1, 0, 2)
            if vertices is None:
                e.flags.writeable = False                                             # kept: read-only
                self._loo_cache = (key, e)
        else:
            e = loo
        if predict_weights is None:
            return e
        Pw = np.asarray(predict_weights, dtype=np.float64)
        F, K = Pw.shape[-2:]
        P2 = Pw.reshape(-1, K)                                                        # [S*F,K]
        S = len(P2) // F
        inv = 1.0 / (mu + reg)                                                        # [n,r]
        LBV = self.inv_l[v][:, :, None] * self.BV[v]                                  # L^-1 B V  [n,K,r]
        b = _take1(self.T, v) + np.matmul(LBV, c * inv[:, :, None]).transpose(1, 0, 2)    # the fit, [K,n,c]
        pred = blend(P2, b)                                                           # p_i^T b  [SF,n,c]
        # A^-1 w_i: once per distinct frame (the same rows of Z, :meth:`_set_frame_groups`), then copied;
        # frame-major and contiguous ([F,K,n], the frames' copies whole blocks), so that the per-frame
        # products p_i^T A^-1 w_i are plain BLAS calls (the strided [n,K,F] view took 4x as long; the same
        # numbers)
        distinct = self._first is not None
        Aw = np.matmul(LBV * inv[:, None, :], np.swapaxes((self._Zu if distinct else self.Z)[v], 1, 2))
        Aw = np.ascontiguousarray(Aw.transpose(2, 1, 0))                                  # [U or F,K,n]
        if distinct:
            Aw = np.take(Aw, self._inverse, axis=0)
        cross = np.matmul(np.ascontiguousarray(P2.reshape(S, F, K).transpose(1, 0, 2)), Aw)   # [F,S,n]
        out = _take1(self.R, v) - pred.reshape((S, F) + pred.shape[1:])
        out += cross.transpose(1, 0, 2)[..., None] * e
        return out if Pw.ndim == 3 else out[0]

    def _loo_per_frame(self, regs) -> np.ndarray:
        """``[G,F]``: per ``reg`` and training frame, its leave-one-frame-out mean squared residual (computed
        once per distinct frame, :meth:`_set_frame_groups`)."""
        k = self.c.shape[2]
        per_frame = 0.0
        distinct = self._first is not None
        e0n = self._e0n_distinct() if distinct else self.e0n
        for v in self._loo_blocks(regs, k):
            d, q = self._loo_parts(regs, self.c, e0n, v, distinct)
            if self.block > 1:
                d = self._block_residuals(regs, d, v)
                per_frame = per_frame + np.einsum("nfkg,nfkg->gf", d, d)
                continue
            d *= d
            sq = _sum_axis2(d)                                                             # [n,F,G]
            per_frame = per_frame + np.einsum("nfg,nfg->gf", sq, q)                        # [G,F]
        per_frame = per_frame / (self.Z.shape[0] * k)
        return per_frame[:, self._inverse] if distinct else per_frame

    def loo_frame_errors(self, reg: float) -> np.ndarray:
        """``[F]``: each training frame's leave-one-frame-out mean squared residual (per vertex coordinate,
        metres^2) at ``reg`` with the current prior - what :meth:`loo_error` averages, kept per frame for a
        paired comparison of two priors on the same frames."""
        return self._loo_per_frame([reg])[0]

    def loo_errors(self, regs, frame_weights: np.ndarray | None = None) -> np.ndarray:
        """:meth:`loo_error` for every ``reg`` in ``regs`` at once, ``[G]``."""
        per_frame = self._loo_per_frame(regs)
        if frame_weights is not None:
            return np.average(per_frame, axis=1, weights=frame_weights)
        return per_frame.mean(axis=1)

    def loo_error(self, reg: float, frame_weights: np.ndarray | None = None) -> float:
        """Exact leave-one-frame-out mean squared residual (per vertex coordinate, metres^2) at ``reg``."""
        return float(self.loo_errors([reg], frame_weights)[0])
