"""Beyond the papers: rigid pre-alignment of every captured frame to the neutral scan, on the vertices that
no template shape moves (scans are never perfectly aligned; a misaligned frame otherwise leaks a rigid motion
into the fitted shapes).

Weighted Kabsch (Umeyama without scale) batched over frames, made robust by iteratively re-weighted least
squares with Geman-McClure weights (scale from the median absolute residual), so the few "static" vertices
that do move in a given frame (or are noisy) do not bias the alignment.
"""

from __future__ import annotations

import numpy as np

from ..mesh import vector_lengths

__all__ = ["static_vertices", "kabsch", "rigid_align", "rigid_transforms", "rigid_transforms_sets",
           "distinct_frames", "expression_weights"]


def static_vertices(generic_deltas: np.ndarray, *, rel: float = 0.05, min_count: int = 12) -> np.ndarray:
    """Indices of vertices that no template shape moves by more than ``rel`` x the largest template
    displacement (``generic_deltas[K,n,3]``, metres). Falls back to the least-moving quarter of the mesh when
    fewer than ``min_count`` qualify."""
    mag = vector_lengths(generic_deltas).max(axis=0)                                 # [n]
    idx = np.flatnonzero(mag <= rel * mag.max()) if mag.max() > 0 else np.arange(len(mag))
    if len(idx) < min_count:
        idx = np.sort(np.argsort(mag)[: max(min_count, len(mag) // 4)])
    return idx


def _det3(M: np.ndarray) -> np.ndarray:
    """Determinants of ``M[F,3,3]`` (closed form, no LAPACK call per matrix)."""
    return (M[:, 0, 0] * (M[:, 1, 1] * M[:, 2, 2] - M[:, 1, 2] * M[:, 2, 1])
            - M[:, 0, 1] * (M[:, 1, 0] * M[:, 2, 2] - M[:, 1, 2] * M[:, 2, 0])
            + M[:, 0, 2] * (M[:, 1, 0] * M[:, 2, 1] - M[:, 1, 1] * M[:, 2, 0]))


def _kabsch_prepared(srcA, dstA, w):
    """:func:`kabsch` on homogeneous copies ``srcA[F,4,m]``, ``dstA[F,4,m]`` (``src^T``, ``dst^T`` with a row
    of ones; :func:`_homogeneous`), made once per point set: one batched product gives the weighted moments
    ``[[sum w s d^T, sum w s], [sum w d^T, sum w]]``, hence ``H = src^T diag(w~) dst - c_s c_d^T`` (``w~`` the
    normalised weights) without centred copies."""
    return _kabsch_moments(_moments(srcA, dstA, w))


def _moments(srcA, dstA, w):
    """The weighted moments ``[F,4,4]`` of :func:`_kabsch_prepared` (one batched product)."""
    return np.matmul(srcA * w[:, None, :], np.swapaxes(dstA, 1, 2))


def _kabsch_moments(M):
    """``(R[F,3,3], t[F,3])`` of :func:`_kabsch_prepared` from its moments ``M[F,4,4]`` (:func:`_moments`),
    frame by frame: the moments of several point sets stacked go through one batched SVD, each frame's
    transform the one it gets alone."""
    sw = np.maximum(M[:, 3, 3], 1e-300)[:, None]
    cs, cd = M[:, :3, 3] / sw, M[:, 3, :3] / sw                                      # [F,3]
    H = M[:, :3, :3] / sw[:, :, None] - cs[:, :, None] * cd[:, None, :]              # [F,3,3]
    U, _, Vt = np.linalg.svd(H)
    V, Ut = np.swapaxes(Vt, 1, 2), np.swapaxes(U, 1, 2)
    R = np.matmul(V, Ut)
    mirrored = _det3(R) < 0                                  # no reflection: V's last column turned, again
    if mirrored.any():
        V[mirrored, :, 2] *= -1.0
        R[mirrored] = np.matmul(V[mirrored], Ut[mirrored])
    t = cd - np.matmul(R, cs[:, :, None])[:, :, 0]
    return R, t


def _homogeneous(src, dst):
    """``(srcA[F,4,m], dstA[F,4,m])`` of :func:`_kabsch_prepared` for ``src[F,m,3]``, ``dst[F,m,3]``: the
    coordinate planes and a plane of ones (copied plane-wise: filling a ``[F,m,4]`` array's first three
    columns is a strided copy 30x slower)."""
    F, m, _ = src.shape
    out = []
    for x in (src, dst):
        a = np.ones((F, 4, m))
        a[:, :3] = np.swapaxes(x, 1, 2)
        out.append(a)
    return tuple(out)


def kabsch(src: np.ndarray, dst: np.ndarray, w: np.ndarray | None = None):
    """Rigid transforms minimising ``sum_v w_v |R src_v + t - dst_v|^2``, batched:
    ``src[F,m,3]``, ``dst[m,3]`` or ``[F,m,3]``, ``w[F,m]`` -> ``R[F,3,3]``, ``t[F,3]`` (proper rotations)."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.broadcast_to(np.asarray(dst, dtype=np.float64), src.shape)
    w = np.ones(src.shape[:2]) if w is None else np.asarray(w, dtype=np.float64)
    return _kabsch_prepared(*_homogeneous(src, dst), w)


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


def distinct_frames(*arrays) -> tuple[np.ndarray, np.ndarray] | None:
    """The frames (first axis) equal to the bit in every one of ``arrays`` (each ``[F, ...]``, float64):
    ``(first[U], inverse[F])``, each distinct frame's first index (ascending) and each frame's distinct
    index; None when every frame is distinct. One pass: a fingerprint per frame (the wrapped sums of its
    64-bit words, equal for equal frames) groups the frames, and each repeat is confirmed bit for bit against
    its group's first frame; a fingerprint shared by different frames (never seen) falls back to grouping
    the frames by their bytes, frame by frame (:func:`_distinct_by_bytes`): no frame is taken for another."""
    F = len(arrays[0])
    if F < 2:
        return None
    words = [np.ascontiguousarray(a, dtype=np.float64).reshape(F, -1).view(np.uint64) for a in arrays]
    key = words[0].sum(axis=1)
    for w in words[1:]:
        key = key * np.uint64(0x9E3779B97F4A7C15) + w.sum(axis=1)
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    if len(first) == F:
        return None
    inverse = inverse.ravel()
    repeat = np.flatnonzero(first[inverse] != np.arange(F))
    if not all(np.array_equal(w[repeat], w[first[inverse[repeat]]]) for w in words):
        return _distinct_by_bytes(words)
    order = np.argsort(first)                                  # the groups in order of their first frame
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return first[order], rank[inverse]


def _distinct_by_bytes(words) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`distinct_frames` exactly, one frame's bytes at a time (``words``: each array's ``[F, w]``
    uint64 view): the groups numbered in order of their first frame."""
    seen: dict[bytes, int] = {}
    inverse = np.array([seen.setdefault(b"".join(w[f].tobytes() for w in words), len(seen))
                        for f in range(len(words[0]))], dtype=np.intp)
    if len(seen) == len(inverse):
        return None
    return np.unique(inverse, return_index=True)[1], inverse


def rigid_transforms(points: np.ndarray, reference: np.ndarray, vertices: np.ndarray, *, robust: bool = True,
                     iterations: int = 10, groups=None, weights=None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`rigid_align`'s transforms ``(R[F,3,3], t[F,3])`` only (no aligned copy of the points).

    Frames that are one frame (the same points on ``vertices``, and the same reference there: a capture app
    that kept one scan for several shapes) are aligned once and the transform copied (every step works frame
    by frame, so the copies are the transforms they would get; :func:`distinct_frames`). ``groups``: such
    frames if the caller knows them (``(first[U], inverse[F])`` of frames equal in both, or False: every
    frame distinct), else None (found here). ``weights[F,m]``: each frame's prior weight of each of
    ``vertices`` (the inverse of its expected non-rigid residual's variance, :func:`expression_weights`),
    multiplied into the robust weights; None: all 1 (frames found equal here are equal in them too; a
    caller's ``groups`` must be)."""
    P, ref, base = _frames(points, reference, weights, groups)
    _, src, dst = _on_vertices(P, ref, vertices)
    if groups is None:
        extra = () if base is None else (base,)
        groups = distinct_frames(src, *extra) if ref.ndim == 2 else distinct_frames(src, dst, *extra)
        if groups is not None:
            src, dst = src[groups[0]], dst[groups[0]]
            base = None if base is None else base[groups[0]]
    groups = groups or None
    R, t = _robust_kabsch(src, dst, robust, iterations, base)
    return (R, t) if groups is None else (R[groups[1]], t[groups[1]])


def rigid_transforms_sets(points: np.ndarray, reference: np.ndarray, vertex_sets, *, groups,
                          iterations: int = 10, weights=None) -> list[tuple[np.ndarray, np.ndarray]]:
    """:func:`rigid_transforms` (robust) of the same frames on each of several vertex sets: ``[(R[F,3,3],
    t[F,3]), ...]``, one per set of ``vertex_sets``, each the transforms that set gets alone (to the bit).
    The sets' re-weighting loops run side by side and their 3x3 Kabsch SVDs go through LAPACK in one batched
    call an iteration (the alignment test's four half-faces: four calls of 28 small SVDs became one of 112).
    ``groups``: the frames' :func:`distinct_frames` (``(first, inverse)``, or False: every frame distinct),
    as :func:`rigid_transforms` takes it from a caller; ``weights[F,n_ref]``: per-frame prior weights of every
    vertex the sets index (each set takes its own columns). No sets: ``[]``."""
    if groups is None:
        raise ValueError("rigid_transforms_sets needs the frames' groups (or False)")
    P, ref, base = _frames(points, reference, weights, groups)
    sets = []
    for vertices in vertex_sets:
        vertices, src, dst = _on_vertices(P, ref, vertices)
        sets.append((src, dst, None if base is None else base[:, vertices]))
    out = _robust_kabsch_sets(sets, True, iterations) if sets else []
    return out if not groups else [(R[groups[1]], t[groups[1]]) for R, t in out]


def _frames(points, reference, weights, groups):
    """``(P[U,N,3], ref, base)`` of :func:`rigid_transforms`' arguments as float arrays, gathered to the
    distinct frames ``groups[0]`` when ``groups`` is given (the same numbers): the one front of it and of
    :func:`rigid_transforms_sets`."""
    P = np.asarray(points, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    base = None if weights is None else np.asarray(weights, dtype=np.float64)
    if groups:                            # the distinct frames known: gather only theirs (the same numbers)
        ref = ref[groups[0]] if ref.ndim == 3 and len(ref) == len(P) else ref
        base = None if base is None else base[groups[0]]
        P = P[groups[0]]
    return P, ref, base


def _on_vertices(P, ref, vertices):
    """``(indices, src[F,m,3], dst[F,m,3])``: the frames ``P`` and the reference ``ref`` (``[N,3]`` or
    ``[F,N,3]``) on ``vertices`` (indices or a mask)."""
    vertices = np.asarray(vertices)
    if vertices.dtype == bool:
        vertices = np.flatnonzero(vertices)
    src = np.take(P, vertices, axis=1)                              # take: 2x cheaper than fancy indexing
    return vertices, src, np.broadcast_to(np.take(ref, vertices, axis=-2), src.shape)


def _robust_kabsch(src, dst, robust, iterations, base=None):
    """:func:`rigid_transforms` on the points ``src[F,m,3]`` and ``dst[F,m,3]`` (m), re-weighted
    ``iterations`` times with ``robust``: ``(R[F,3,3], t[F,3])``; ``base[F,m]`` multiplies every weight."""
    return _robust_kabsch_sets([(src, dst, base)], robust, iterations)[0]


def _robust_kabsch_sets(sets, robust, iterations):
    """:func:`_robust_kabsch` of every ``(src[F,m_s,3], dst[F,m_s,3], base[F,m_s] or None)`` of ``sets`` (the
    same frames ``F``, each set its own points), the loops side by side: each set's residuals, median and
    weights on its own points, the moments of every set through one :func:`_kabsch_moments` (stacked).
    ``[(R, t), ...]``, each set's transforms as it gets them alone."""
    prepared = []
    for src, dst, base in sets:
        srcA, dstA = _homogeneous(src, dst)
        prepared.append((srcA, dstA, np.ones(src.shape[:2]) if base is None else base))
    F = len(prepared[0][0])

    def transforms(ws):
        M = [_moments(srcA, dstA, w) for (srcA, dstA, _), w in zip(prepared, ws, strict=True)]
        R, t = _kabsch_moments(M[0] if len(M) == 1 else np.concatenate(M))
        return [(R[i * F:(i + 1) * F], t[i * F:(i + 1) * F]) for i in range(len(M))]

    Rt = transforms([base for _, _, base in prepared])
    for _ in range(iterations if robust else 0):
        ws = []
        for (srcA, dstA, base), (R, t) in zip(prepared, Rt, strict=True):
            m = srcA.shape[2]
            srcT, dstT = srcA[:, :3], dstA[:, :3]                        # coordinate planes [F,3,m]
            d = np.matmul(R, srcT)                                       # residual R src + t - dst  [F,3,m]
            d += t[:, :, None]
            d -= dstT
            r = np.sqrt(np.einsum("fcm,fcm->fm", d, d))
            # the median (np.median's value): one partition at m // 2; for even m the lower middle is the
            # largest value below it
            part = np.partition(r, m // 2, axis=1)
            lower = part[:, m // 2] if m % 2 else part[:, :m // 2].max(axis=1)
            med = (0.5 * (lower + part[:, m // 2]))[:, None]
            s = 1.4826 * med + 1e-12
            ws.append(base / (1.0 + (r / (2.0 * s)) ** 2) ** 2)
        Rt = transforms(ws)
    return Rt


def expression_weights(weights, prior, residuals) -> np.ndarray:
    """Each frame's weight of each vertex in its rigid alignment: the inverse of the variance its non-rigid
    residual is expected to have, ``1 / (a + b q_fv)`` with ``q_fv = sum_k W_fk^2 |T_k(v)|^2`` (``weights
    W[F,K]``, ``prior T[K,m,3]`` metres): the person's shapes differ from the prior by a share of their own
    motion, so a frame's residual from its prediction holds, besides the scan's noise (``a``), that share of
    the motion the frame shows (``b q``). ``a`` and ``b`` are the least-squares fit of the squared
    ``residuals[F,m,3]`` on ``[1, q]`` over every frame and vertex (each >= a thousandth of the mean squared
    residual). Returns ``[F,m]``, mean 1.

    A rigid head motion moves every vertex, an expression only those it shows: weighted so, a frame that is
    the only one to show a shape (whose personal part the leave-one-out prediction cannot know) is aligned on
    the vertices its expression leaves still, not moved to absorb that part (generic:143's ``jawForward``
    frame was moved 1.3 mm towards the prior's ``jawForward``)."""
    W = np.asarray(weights, dtype=np.float64)
    T2 = np.einsum("kmc,kmc->km", prior, prior)                                    # [K,m]
    q = (W ** 2) @ T2                                                              # [F,m]
    r2 = np.einsum("fmc,fmc->fm", residuals, residuals)                            # [F,m]
    A = np.stack([np.ones(q.size), q.ravel()], axis=1)
    a, b = np.linalg.lstsq(A, r2.ravel(), rcond=None)[0]
    floor = 1e-3 * float(r2.mean()) + 1e-300
    a = max(float(a), floor)
    b = max(float(b), 0.0)
    w = 1.0 / (a + b * q)
    return w / w.mean()
