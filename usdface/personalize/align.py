"""Beyond the papers: rigid pre-alignment of every captured frame to the neutral scan, on the vertices that
no template shape moves (scans are never perfectly aligned; a misaligned frame otherwise leaks a rigid motion
into the fitted shapes).

Weighted Kabsch (Umeyama without scale) batched over frames, made robust by iteratively re-weighted least
squares with Geman-McClure weights (scale from the median absolute residual), so the few "static" vertices
that do move in a given frame (or are noisy) do not bias the alignment.
"""

from __future__ import annotations

import numpy as np

__all__ = ["static_vertices", "kabsch", "rigid_align", "rigid_transforms"]


def static_vertices(generic_deltas: np.ndarray, *, rel: float = 0.05, min_count: int = 12) -> np.ndarray:
    """Indices of vertices that no template shape moves by more than ``rel`` x the largest template
    displacement (``generic_deltas[K,n,3]``, metres). Falls back to the least-moving quarter of the mesh when
    fewer than ``min_count`` qualify."""
    mag = np.linalg.norm(np.asarray(generic_deltas, dtype=np.float64), axis=-1).max(axis=0)   # [n]
    idx = np.flatnonzero(mag <= rel * mag.max()) if mag.max() > 0 else np.arange(len(mag))
    if len(idx) < min_count:
        idx = np.sort(np.argsort(mag)[: max(min_count, len(mag) // 4)])
    return idx


def _det3(M: np.ndarray) -> np.ndarray:
    """Determinants of ``M[F,3,3]`` (closed form, no LAPACK call per matrix)."""
    return (M[:, 0, 0] * (M[:, 1, 1] * M[:, 2, 2] - M[:, 1, 2] * M[:, 2, 1])
            - M[:, 0, 1] * (M[:, 1, 0] * M[:, 2, 2] - M[:, 1, 2] * M[:, 2, 0])
            + M[:, 0, 2] * (M[:, 1, 0] * M[:, 2, 1] - M[:, 1, 1] * M[:, 2, 0]))


def _kabsch_prepared(src, srcT, dst, w):
    """:func:`kabsch` with ``srcT = src^T`` per frame given (contiguous), ``dst[F,m,3]``: no centred copies,
    ``H = src^T diag(w~) dst - c_s c_d^T`` with ``w~`` the normalised weights."""
    ws = (w / np.maximum(w.sum(axis=1, keepdims=True), 1e-300))[:, None, :]          # [F,1,m]
    cs = np.matmul(ws, src)                                                          # [F,1,3]
    cd = np.matmul(ws, dst)
    # the weights multiply src^T along its contiguous axis (2x cheaper than weighting dst[F,m,3])
    H = np.matmul(srcT * ws, dst) - np.swapaxes(cs, 1, 2) * cd                       # [F,3,3]
    U, _, Vt = np.linalg.svd(H)
    V, Ut = np.swapaxes(Vt, 1, 2), np.swapaxes(U, 1, 2)
    V[:, :, 2] *= np.sign(_det3(np.matmul(V, Ut)))[:, None]                          # no reflection
    R = np.matmul(V, Ut)
    t = cd[:, 0] - np.matmul(cs, np.swapaxes(R, 1, 2))[:, 0]
    return R, t


def kabsch(src: np.ndarray, dst: np.ndarray, w: np.ndarray | None = None):
    """Rigid transforms minimising ``sum_v w_v |R src_v + t - dst_v|^2``, batched:
    ``src[F,m,3]``, ``dst[m,3]`` or ``[F,m,3]``, ``w[F,m]`` -> ``R[F,3,3]``, ``t[F,3]`` (proper rotations)."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.broadcast_to(np.asarray(dst, dtype=np.float64), src.shape)
    w = np.ones(src.shape[:2]) if w is None else np.asarray(w, dtype=np.float64)
    return _kabsch_prepared(src, np.ascontiguousarray(np.swapaxes(src, 1, 2)), dst, w)


def rigid_align(points: np.ndarray, reference: np.ndarray, vertices: np.ndarray, *, robust: bool = True,
                iterations: int = 10) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Align every frame ``points[F,n,3]`` rigidly to ``reference[n,3]`` (or one reference per frame,
    ``[F,n,3]``) on ``vertices`` (indices).

    Returns ``(aligned[F,n,3], R[F,3,3], t[F,3])`` with ``aligned = points @ R^T + t``. With ``robust`` the
    fit is re-weighted ``iterations`` times (Geman-McClure, scale 1.4826 x median residual).
    """
    P = np.asarray(points, dtype=np.float64)
    R, t = rigid_transforms(P, reference, vertices, robust=robust, iterations=iterations)
    return np.matmul(P, np.swapaxes(R, 1, 2)) + t[:, None], R, t


def rigid_transforms(points: np.ndarray, reference: np.ndarray, vertices: np.ndarray, *, robust: bool = True,
                     iterations: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """:func:`rigid_align`'s transforms ``(R[F,3,3], t[F,3])`` only (no aligned copy of the points)."""
    P = np.asarray(points, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    src = P[:, vertices]
    dst = np.ascontiguousarray(np.broadcast_to(ref[..., vertices, :], src.shape))
    srcT = np.ascontiguousarray(np.swapaxes(src, 1, 2))
    w = np.ones(src.shape[:2])
    R, t = _kabsch_prepared(src, srcT, dst, w)
    m = src.shape[1]
    dstT = np.swapaxes(dst, 1, 2)                                    # [F,3,m] views: coordinate planes
    d = np.empty((3,) + src.shape[:2])
    for _ in range(iterations if robust else 0):
        # residual R src + t - dst, one coordinate plane [F,m] at a time (a batched 3 x 3 matmul is 2x slower)
        for j in range(3):
            np.multiply(srcT[:, 0], R[:, j, 0, None], out=d[j])
            d[j] += srcT[:, 1] * R[:, j, 1, None]
            d[j] += srcT[:, 2] * R[:, j, 2, None]
            d[j] += t[:, j, None]
            d[j] -= dstT[:, j]
        r = np.sqrt(np.einsum("cfm,cfm->fm", d, d))
        # the median (np.median's value): one partition at m // 2; for even m the lower middle is the
        # largest value below it
        part = np.partition(r, m // 2, axis=1)
        lower = part[:, m // 2] if m % 2 else part[:, :m // 2].max(axis=1)
        med = (0.5 * (lower + part[:, m // 2]))[:, None]
        s = 1.4826 * med + 1e-12
        w = 1.0 / (1.0 + (r / (2.0 * s)) ** 2) ** 2
        R, t = _kabsch_prepared(src, srcT, dst, w)
    return R, t
