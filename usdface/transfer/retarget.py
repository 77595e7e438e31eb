"""Automatic facial retargeting (Menzel et al. 2022, eq. 4): each personalized capture shape, mapped onto the
avatar face, approximated by a ridge-regularised combination of the avatar's own generic shapes.

The result is a weight map ``W[J,K]`` (row j: the avatar-shape weights that best reproduce capture shape j)
and the approximations ``A_j = sum_i W[j,i] B~_i`` on every avatar mesh. The map is also what a game engine
can use in place of a hand-made retargeting table (``usdface retarget ... -o map.json|csv``).
"""

from __future__ import annotations

import csv
import io
import json

import numpy as np

__all__ = ["retarget_weights", "namesake_prior", "approximate", "weight_map_rows", "weight_map_json",
           "weight_map_csv"]


#: Vertices per block of :func:`retarget_weights`' products over ``rows``.
ROW_BLOCK = 16384


def choose_mu(gram_eigenvalues, projected, residual_ss, n_rows: int, k: int,
              grid=None) -> float:
    """Generalized cross-validation (Golub, Heath & Wahba 1979) of the eq. (4) ridge weight, pooled over the
    targets: ``GCV(mu) = N ||r_mu||^2 / (N - tr H_mu)^2`` with ``N = n_rows`` observations per target, from
    the Gram matrix's eigenvalues ``[K]``, the targets projected on its eigenvectors ``projected[K,J]`` and
    the residual outside the shapes' span ``residual_ss``. ``mu`` is relative (see :func:`retarget_weights`).
    """
    ev = np.maximum(np.asarray(gram_eigenvalues, dtype=np.float64), 0.0)
    scale = float(ev.sum()) / max(k, 1)
    grid = np.logspace(-6, 0, 25) if grid is None else np.asarray(grid)
    best, best_mu = np.inf, float(grid[0])
    proj2 = np.sum(np.asarray(projected) ** 2, axis=1)                     # [K] summed over targets
    for m in grid:
        lam = m * scale
        shrink = lam / (ev + lam)
        rss = float(np.sum(np.where(ev > 0, shrink ** 2 * proj2 / np.maximum(ev, 1e-300), 0.0))) + residual_ss
        dof = float(np.sum(ev / (ev + lam)))
        score = rss / max(n_rows - dof, 1e-9) ** 2
        if score < best:
            best, best_mu = score, float(m)
    return best_mu


def retarget_weights(avatar_deltas, targets, mu="auto", *, return_mu: bool = False, rows=None, bounds=None,
                     prior=None):
    """Menzel et al. 2022, eq. (4): ``argmin_w ||sum_i w_i B~_i - M B_j||^2 + mu' sum_i (w_i - p_ji)^2`` for
    every j, with ``p = 0`` as the paper.

    Parameters
    ----------
    avatar_deltas : ``[K,m,3]`` the avatar's generic shapes B~_i restricted to the face region (metres).
    targets : ``[J,m,3]`` the personalized capture shapes mapped onto the same vertices, ``M B_j`` (metres).
    mu : ridge weight relative to the shapes' mean squared norm, ``mu' = mu * trace(B~^T B~) / K``, so it is
        unit- and resolution-free; ``"auto"`` (default) chooses it by generalized cross-validation over the
        face rows (:func:`choose_mu`), which bounds the weights where shapes are nearly collinear.
    return_mu : also return the relative ``mu`` used.
    prior : ``[J,K]`` weights the ridge shrinks towards (None: 0, the paper). With the identity of the shared
        ARKit names (``p_ji = 1`` where avatar shape i is capture shape j) a shape maps to its namesake
        unless the geometry says otherwise, as a hand-made retargeting table does.
    bounds : None (the paper: any real weights) or ``(lo, hi)``: the same objective minimised over
        ``lo <= w <= hi`` (e.g. ``(0, 1)``, the range an ARKit rig's channels are authored for, so an engine
        can drive the avatar with the map as it is), by the exact bounded least squares of
        :func:`usdface.bounded_lsq.box_least_squares` on the regularised normal matrix, all rows at once.
    rows : optional vertex indices (or a bool mask) of ``avatar_deltas[K,n,3]`` that ``targets[J,m,3]`` are
        on: the products are summed over blocks of those rows, never forming ``avatar_deltas[:, rows]`` (a
        production head's face region: 180 MB); the same weights up to rounding.

    Returns
    -------
    weights : ``[J,K]`` with ``A_j = sum_i weights[j,i] B~_i``. One Cholesky-free dense solve of the K x K
    normal equations shared by every j.
    """
    d = np.asarray(avatar_deltas, dtype=np.float64)
    k = d.shape[0]
    # BLAS products: personalize_avatar caps BLAS at one thread (a multi-threaded BLAS on a busy 2-core
    # machine took 1.9 s for this 51 x 20k Gram matrix at load 10; single-threaded it is ~2 ms)
    if rows is None:
        a = d.reshape(k, -1)  # [K, 3m]
        t = np.asarray(targets, dtype=np.float64).reshape(-1, a.shape[1])  # [J, 3m]
        gram = a @ a.T
        rhs = a @ t.T  # [K, J]
        n_t, n_rows = t.shape
        tt = float(np.einsum("jv,jv->", t, t))
    else:
        idx = np.asarray(rows)
        idx = np.flatnonzero(idx) if idx.dtype == bool else idx.astype(np.int64)
        t3 = np.asarray(targets, dtype=np.float64)
        n_t = len(t3)
        # the targets as the correspondence gives them, vertex-major ([m, J, 3] in memory): read per block
        # in that order (a [J, 3m] copy of a 180k-vertex face region is a strided 150 MB transpose, 0.7 s)
        tv = np.moveaxis(t3, 1, 0)                                                            # [m, J, 3]
        gram, rhs, tt = np.zeros((k, k)), np.zeros((k, n_t)), 0.0
        for lo in range(0, idx.size, ROW_BLOCK):
            a = np.take(d, idx[lo:lo + ROW_BLOCK], axis=1).reshape(k, -1)   # C order: no copy to reshape
            b = tv[lo:lo + ROW_BLOCK].transpose(0, 2, 1)
            b = b.reshape(3 * len(b), n_t)                                                    # [3b, J]
            gram += a @ a.T
            rhs += a @ b
            tt += float(np.einsum("vj,vj->", b, b))
        n_rows = 3 * idx.size
    p = np.zeros((n_t, k)) if prior is None else np.asarray(prior, dtype=np.float64)      # [J,K]
    # the ridge around p is the plain ridge of the targets' residual from p: t - B~ p
    rhs_p = rhs - gram @ p.T                                                  # [K,J]
    if isinstance(mu, str):
        if mu != "auto":
            raise ValueError(f"mu must be a number or 'auto', not {mu!r}")
        ev, vec = np.linalg.eigh(gram)
        proj = vec.T @ rhs_p                                                 # [K,J]: U^T A t  (= s_i u_i^T t)
        # the part of the targets outside the span of the shapes, from ||t||^2 - ||P t||^2
        inside = float(np.sum(proj ** 2 / np.maximum(ev, 1e-300)[:, None] * (ev > 1e-12 * ev.max())[:, None]))
        tt = tt - 2.0 * float(np.sum(p.T * rhs))                           # ||t - B~ p||^2, no [J, 3m]
        residual = max(tt + float(np.sum(p.T * (gram @ p.T))) - inside, 0.0)      # temporary
        mu = choose_mu(ev, proj, residual, n_rows, k)
    lam = float(mu) * float(np.trace(gram)) / max(k, 1)
    w = p + np.linalg.solve(gram + lam * np.eye(k), rhs_p).T
    if bounds is not None:
        w = _bounded(gram + lam * np.eye(k), rhs + lam * p.T, w, bounds)
    return (w, float(mu)) if return_mu else w


def namesake_prior(target_names, avatar_names) -> np.ndarray:
    """``[J,K]``: 1 where avatar shape i has capture shape j's (canonical ARKit) name, else 0 - the
    identity of the shared names, the prior of the product's retarget map (:func:`retarget_weights`)."""
    index = {n: i for i, n in enumerate(avatar_names)}
    p = np.zeros((len(target_names), len(avatar_names)))
    for j, n in enumerate(target_names):
        if n in index:
            p[j, index[n]] = 1.0
    return p


def _bounded(normal, rhs, start, bounds) -> np.ndarray:
    """``argmin_{lo <= w <= hi} w^T N w - 2 w^T rhs_j`` for every column j of ``rhs[K,J]`` (``N[K,K]``
    symmetric positive definite), all rows at once by the exact active-set method of
    :func:`usdface.bounded_lsq.box_least_squares`; ``start[J,K]``: the unbounded solutions (kept where they
    are inside the bounds). Returns ``[J,K]``."""
    from ..bounded_lsq import box_least_squares

    lo, hi = (float(b) for b in bounds)
    if not lo < hi:
        raise ValueError(f"weight bounds must have lo < hi, not {bounds!r}")
    out = np.array(start, dtype=np.float64, copy=True)
    outside = np.flatnonzero(((out < lo) | (out > hi)).any(axis=1))
    if outside.size:
        out[outside], _ = box_least_squares(normal, np.asarray(rhs, dtype=np.float64)[:, outside].T, lo, hi,
                                            out[outside])
    return out


def approximate(weights, deltas) -> np.ndarray:
    """Menzel et al. 2022, sec. 3.3: the approximations ``A[J,n,3] = weights[J,K] @ deltas[K,n,3]`` of the
    personalized shapes by the avatar's own ``deltas`` on one mesh, with the eq. (4) ``weights``."""
    d = np.asarray(deltas, dtype=np.float64)
    flat = np.asarray(weights, dtype=np.float64) @ d.reshape(d.shape[0], -1)
    return flat.reshape(-1, *d.shape[1:])


def weight_map_rows(weights, target_names, avatar_names, *, threshold: float = 0.0) -> dict:
    """The map as ``{capture_shape: {avatar_shape: weight}}``, dropping ``|weight| <= threshold``."""
    w = np.asarray(weights)
    return {t: {a: float(w[j, i]) for i, a in enumerate(avatar_names) if abs(w[j, i]) > threshold}
            for j, t in enumerate(target_names)}


def weight_map_json(weights, target_names, avatar_names, *, meta: dict | None = None) -> str:
    """JSON text: ``{"format": "usdface.retarget/1", "source": [...], "target": [...], "weights": [[...]],
    "map": {...}}`` (rows = capture/ARKit input shapes, columns = avatar shapes)."""
    doc = {"format": "usdface.retarget/1", "equation": "Menzel et al. 2022, eq. 4",
           "source": list(target_names), "target": list(avatar_names),
           "weights": np.asarray(weights).round(6).tolist(),
           "map": weight_map_rows(np.asarray(weights).round(6), target_names, avatar_names, threshold=1e-6)}
    if meta:
        doc["meta"] = meta
    return json.dumps(doc, indent=1)


def weight_map_csv(weights, target_names, avatar_names) -> str:
    """CSV text: header ``source,<avatar shapes...>``, one row per capture/ARKit input shape."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["source", *avatar_names])
    for j, name in enumerate(target_names):
        w.writerow([name, *(f"{v:.6g}" for v in np.asarray(weights)[j])])
    return buf.getvalue()
