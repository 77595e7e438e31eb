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

__all__ = ["retarget_weights", "face_regions", "choose_mu_by_regions", "driven_gram", "namesake_prior",
           "gaze_held", "GAZE_CHOICES", "approximate", "weight_map_rows", "weight_map_json", "weight_map_csv"]


#: Vertices per block of :func:`retarget_weights`' products over ``rows``.
ROW_BLOCK = 16384
#: The face rows are split into FACE_GRID x FACE_GRID regions of their extent for the leave-one-region-out
#: choice of eq. (4)'s ``mu`` (:func:`face_regions`): the face's thirds from brow to chin times its left,
#: centre and right - regions the size of a feature (an eye and its brow, the nose, the mouth, a cheek).
FACE_GRID = 3
#: The relative ``mu`` values either choice of it searches (:func:`choose_mu`, :func:`choose_mu_by_regions`).
MU_GRID = np.logspace(-6, 0, 25)
#: How the map treats the gaze channels (:func:`gaze_held`): ``"namesake"`` (default) a gaze channel is
#: driven by its namesake capture shape alone; ``"free"`` eq. (4) as it is, any shape may drive any channel.
GAZE_CHOICES = ("namesake", "free")


def gaze_held(target_names, avatar_names, gaze: str = "namesake"):
    """``[J,K]`` bool, True where the map's weight ``W[j,k]`` is held at 0 (:func:`retarget_weights`'
    ``held``), or None (nothing held, ``gaze="free"``). With ``"namesake"`` a gaze channel k
    (:data:`usdface.arkit.GAZE_NAMES`, the canonical ``eyeLook*`` names) is driven only by the capture shape
    of its own name: every other row's entry in its column is held at 0. In an engine the gaze channels turn
    the eyes (eye bones, eyeball meshes), which the face rows eq. (4) is fitted on do not see: a blink that
    took ``eyeLookDownLeft`` 0.30 to match the lid skin turned the avatar's eyes down on every blink.

    A gaze capture shape may still drive the lid channels (``eyeLookUpLeft`` -> ``eyeWideLeft``): that is the
    person's lid following the gaze, skin the face rows do see, and it turns no eye. Only its entries in the
    other gaze channels are held (they are gaze columns)."""
    if gaze not in GAZE_CHOICES:
        raise ValueError(f"gaze must be one of {', '.join(GAZE_CHOICES)}, not {gaze!r}")
    if gaze == "free":
        return None
    from ..arkit import GAZE_NAMES

    rows = np.asarray(list(target_names), dtype=object)
    cols = np.asarray(list(avatar_names), dtype=object)
    gaze_col = np.array([n in GAZE_NAMES for n in cols], dtype=bool)
    return gaze_col[None, :] & (rows[:, None] != cols[None, :])


def _free_groups(held, k: int, n_t: int) -> list:
    """The rows ``[J]`` of the map grouped by which of their ``k`` entries are solved for (``~held[J,K]``):
    ``[(rows, free columns)]``, one group of all rows and columns when ``held`` is None. Each group's rows
    share one reduced system (the held entries' rows and columns removed)."""
    if held is None:
        return [(np.arange(n_t), np.arange(k))]
    patterns, group = np.unique(~np.asarray(held, dtype=bool), axis=0, return_inverse=True)
    group = np.asarray(group).reshape(-1)
    return [(np.flatnonzero(group == g), np.flatnonzero(patterns[g])) for g in range(len(patterns))]


def choose_mu(gram_eigenvalues, projected, residual_ss, n_rows: int, k: int,
              grid=None) -> float:
    """Generalized cross-validation (Golub, Heath & Wahba 1979) of the eq. (4) ridge weight, pooled over the
    targets: ``GCV(mu) = N ||r_mu||^2 / (N - tr H_mu)^2`` with ``N = n_rows`` observations per target, from
    the Gram matrix's eigenvalues ``[K]``, the targets projected on its eigenvectors ``projected[K,J]`` and
    the residual outside the shapes' span ``residual_ss``. ``mu`` is relative (see :func:`retarget_weights`).
    """
    ev = np.maximum(np.asarray(gram_eigenvalues, dtype=np.float64), 0.0)
    scale = float(ev.sum()) / max(k, 1)
    grid = MU_GRID if grid is None else np.asarray(grid)
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


def face_regions(points, grid: int = FACE_GRID) -> np.ndarray:
    """``[m]`` int: the region of each face row ``points[m,3]`` (the avatar frame: x across the face, y up),
    the ``grid`` x ``grid`` split of the rows' extent in x and y (:data:`FACE_GRID`: the face's thirds from
    brow to chin times left, centre and right). It depends on where the rows are, not on how many there are
    (a subdivided head's face rows fall into the same regions) nor on the units."""
    xy = np.asarray(points, dtype=np.float64)[:, :2]
    if not len(xy):
        return np.zeros(0, dtype=np.int64)
    lo, span = xy.min(axis=0), np.ptp(xy, axis=0)
    cell = np.floor((xy - lo) / np.where(span > 0, span, 1.0) * grid).astype(np.int64)
    cell = np.clip(cell, 0, grid - 1)
    return cell[:, 0] * grid + cell[:, 1]


def choose_mu_by_regions(grams, rhs, tt, prior=None, grid=None, elsewhere=None, held=None) -> float:
    """Leave-one-region-out cross-validation of the eq. (4) ridge weight ``mu`` (relative, see
    :func:`retarget_weights`): for each region ``r`` of the face rows (:func:`face_regions`) the map solved on
    the other regions predicts the targets on ``r``; ``mu`` minimises that prediction error summed over the
    regions and the targets (on the grid, refined by the parabola through its best point and neighbours,
    :func:`_parabola_vertex`). This is what the map is for - the approximations ``A_j`` stand in for the
    person's shapes where the capture does not see them - and, unlike GCV over the rows as independent
    observations (neighbouring vertices are not: with thousands of rows per target GCV takes the smallest
    ``mu`` of its grid), it penalises combinations of shapes that match one region by moving another.

    ``grams[R,K,K]``, ``rhs[R,K,J]``, ``tt[R]``: each region's ``B~_r^T B~_r``, ``B~_r^T t_r`` and
    ``||t_r||^2`` (summed over targets); ``prior[J,K]``: the ridge's centre (None: 0); ``elsewhere[K,K]``:
    the Gram matrix of the rows the map drives outside the face (:func:`retarget_weights`), held in by every
    fold (it is no data of the person's); ``held[J,K]``: entries of the map held at 0 (:func:`gaze_held`),
    so that every fold solves the map as :func:`retarget_weights` does (the rows that share which entries
    are free share one reduced system; ``prior`` is 0 at the held entries). Closed form per region: one
    eigendecomposition of the held-in K x K Gram matrix (per group of rows, its free rows and columns)
    serves every ``mu`` of the grid."""
    grams = np.asarray(grams, dtype=np.float64)
    rhs = np.asarray(rhs, dtype=np.float64)
    n_r, k, n_t = rhs.shape
    grid = MU_GRID if grid is None else np.asarray(grid, dtype=np.float64)
    gram, total = grams.sum(axis=0), rhs.sum(axis=0)
    lam = grid * float(np.trace(gram)) / max(k, 1)                                    # [M]
    pt = np.zeros((k, n_t)) if prior is None else np.asarray(prior, dtype=np.float64).T  # [K,J]
    if held is not None:
        pt = np.where(np.asarray(held, dtype=bool).T, 0.0, pt)
    err = np.zeros(len(grid))
    extra = 0.0 if elsewhere is None else np.asarray(elsewhere, dtype=np.float64)
    groups = [(slice(None), slice(None))] if held is None else _free_groups(held, k, n_t)
    for r in range(n_r):
        g_in = gram - grams[r]
        h_in = g_in + extra
        shifted = total - rhs[r] - g_in @ pt                                             # [K,J]
        for i, (rows, cols) in enumerate(groups):
            whole = held is None
            ev, vec = np.linalg.eigh(h_in if whole else h_in[np.ix_(cols, cols)])
            q = vec.T @ (shifted if whole else shifted[np.ix_(cols, rows)])             # [F,J_g]
            step = np.einsum("kl,mlj->mkj", vec, q / (np.maximum(ev, 0.0)[None, :, None]
                                                      + lam[:, None, None]))
            if whole:
                w = pt + step
            else:                                  # the held entries stay at 0 (= the prior there)
                w = np.repeat(pt[None, :, rows], len(grid), axis=0)
                w[:, cols, :] += step
            rhs_r = rhs[r] if whole else rhs[r][:, rows]
            # ||t_r - B~_r w||^2 = ||t_r||^2 - 2 w . B~_r^T t_r + w^T B~_r^T B~_r w, per mu, summed over
            # targets (the quadratic term by one batched product: a three-operand einsum looped in C over
            # M K^2 J terms, 0.1 s of dev1's run); ||t_r||^2 once per region
            err += ((float(tt[r]) if i == 0 else 0.0) - 2.0 * np.einsum("mkj,kj->m", w, rhs_r)
                    + np.einsum("mkj,mkj->m", np.matmul(grams[r], w), w))
    return _parabola_vertex(np.log(grid), err)


def _parabola_vertex(x, y) -> float:
    """``exp`` of the minimum of the parabola through the grid's best point ``x[i]`` (log ``mu``) and its two
    neighbours, kept between them (the grid's end point when the best is there): the choice moves
    continuously with the data instead of jumping a grid step (1.8x) when the curve, flat at its minimum,
    tips the other way - a subdivided head's face rows and the original's then give nearly the same ``mu``."""
    i = int(np.argmin(y))
    if i == 0 or i == len(y) - 1:
        return float(np.exp(x[i]))
    (x0, x1, x2), (y0, y1, y2) = x[i - 1:i + 2], y[i - 1:i + 2]
    curve = y2 - 2.0 * y1 + y0                                          # an even grid in log mu
    if not curve > 0:
        return float(np.exp(x1))
    vertex = x1 - 0.5 * (x1 - x0) * (y2 - y0) / curve
    return float(np.exp(np.clip(vertex, x0, x2)))


def retarget_weights(avatar_deltas, targets, mu="auto", *, return_mu: bool = False, rows=None, bounds=None,
                     prior=None, positions=None, elsewhere=None, held=None):
    """Menzel et al. 2022, eq. (4): ``argmin_w ||sum_i w_i B~_i - M B_j||^2 + mu' sum_i (w_i - p_ji)^2`` for
    every j, with ``p = 0`` as the paper.

    Parameters
    ----------
    avatar_deltas : ``[K,m,3]`` the avatar's generic shapes B~_i restricted to the face region (metres).
    targets : ``[J,m,3]`` the personalized capture shapes mapped onto the same vertices, ``M B_j`` (metres).
    mu : ridge weight relative to the shapes' mean squared norm, ``mu' = mu * trace(B~^T B~) / K``, so it is
        unit- and resolution-free; ``"auto"`` (default) chooses it by leaving out one region of the face at a
        time (:func:`choose_mu_by_regions`, with ``positions``), else by generalized cross-validation over
        the rows (:func:`choose_mu`, which takes the smallest ``mu`` when the rows are many).
    positions : ``[n,3]`` the points of the mesh ``avatar_deltas`` is on (avatar frame, y up): the regions of
        the face rows for ``mu="auto"`` (:func:`face_regions`).
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
    elsewhere : optional ``[K,K]`` Gram matrix of the avatar's shapes on the rows the map also drives but
        the face rows do not see (the teeth, tongue and eyeball meshes: :func:`driven_gram`). The objective
        then adds ``||sum_i (w_i - p_ji) B^else_i||^2``: there the map reproduces the ridge's centre (the
        namesake's own motion), since the capture says nothing about the person's tongue or eyeballs. An
        engine drives every mesh with the map: the sample's ``jawForward`` row took ``tongueOut`` at 0.82
        (a tongue out on every jaw slide), matching a few face rows by moving what the face rows do not
        hold; on a rig whose eyeballs carry the ``eyeLook*`` shapes a lid could turn an eyeball so.
    held : optional ``[J,K]`` bool: entries of the map held at 0, the rest solved for (:func:`gaze_held`: a
        gaze channel driven by its namesake alone). Each row is the same objective minimised over its free
        entries - the reduced system of the normal equations, all rows at once (a batched solve with the held
        rows and columns replaced by the identity; the bounded solve holds them too) - and ``mu="auto"``'s
        folds solve the same reduced systems (:func:`choose_mu_by_regions`; GCV, without ``positions``,
        chooses it without them). ``prior`` is taken as 0 at the held entries.

    Returns
    -------
    weights : ``[J,K]`` with ``A_j = sum_i weights[j,i] B~_i``. One Cholesky-free dense solve of the K x K
    normal equations shared by every j.
    """
    d = np.asarray(avatar_deltas, dtype=np.float64)
    k = d.shape[0]
    if rows is None:
        idx = np.arange(d.shape[1])
    else:
        idx = np.asarray(rows)
        idx = np.flatnonzero(idx) if idx.dtype == bool else idx.astype(np.int64)
    t3 = np.asarray(targets, dtype=np.float64)
    n_t = len(t3)
    # the targets as the correspondence gives them, vertex-major ([m, J, 3] in memory): read per block in that
    # order (a [J, 3m] copy of a 180k-vertex face region is a strided 150 MB transpose, 0.7 s)
    tv = np.moveaxis(t3, 1, 0)                                                                # [m, J, 3]
    # the products per region of the face (one region without positions), summed over blocks of its rows,
    # never forming avatar_deltas[:, rows] (a production head's face region: 180 MB). BLAS products:
    # personalize_avatar caps BLAS at one thread (a multi-threaded BLAS on a busy 2-core machine took 1.9 s
    # for this 51 x 20k Gram matrix at load 10; single-threaded it is ~2 ms)
    label = (face_regions(np.asarray(positions)[idx]) if positions is not None
             else np.zeros(idx.size, dtype=np.int64))
    order = np.argsort(label, kind="stable")
    starts = np.searchsorted(label[order], np.unique(label))
    ends = np.append(starts[1:], idx.size)
    grams, rhss, tts = np.zeros((len(starts), k, k)), np.zeros((len(starts), k, n_t)), np.zeros(len(starts))
    for r, (a0, a1) in enumerate(zip(starts, ends, strict=True)):
        for lo in range(a0, a1, ROW_BLOCK):
            at = order[lo:min(lo + ROW_BLOCK, a1)]
            a = np.take(d, idx[at], axis=1).reshape(k, -1)          # C order: no copy to reshape
            b = tv[at].transpose(0, 2, 1).reshape(3 * len(at), n_t)                             # [3b, J]
            grams[r] += a @ a.T
            rhss[r] += a @ b
            tts[r] += float(np.einsum("vj,vj->", b, b))
    gram, rhs, tt = grams.sum(axis=0), rhss.sum(axis=0), float(tts.sum())
    n_rows = 3 * idx.size
    p = np.zeros((n_t, k)) if prior is None else np.asarray(prior, dtype=np.float64)      # [J,K]
    if held is not None:
        held = np.asarray(held, dtype=bool)
        if held.shape != (n_t, k):
            raise ValueError(f"held must be [J,K] = {(n_t, k)}, not {held.shape}")
        p = np.where(held, 0.0, p)
    # the ridge around p is the plain ridge of the targets' residual from p: t - B~ p
    rhs_p = rhs - gram @ p.T                                                  # [K,J]
    if isinstance(mu, str):
        if mu != "auto":
            raise ValueError(f"mu must be a number or 'auto', not {mu!r}")
        if len(starts) > 1:
            mu = choose_mu_by_regions(grams, rhss, tts, p, elsewhere=elsewhere, held=held)
        else:
            ev, vec = np.linalg.eigh(gram)
            proj = vec.T @ rhs_p                                             # [K,J]: U^T A t  (= s_i u_i^T t)
            # the part of the targets outside the span of the shapes, from ||t||^2 - ||P t||^2
            inside = float(np.sum(proj ** 2 / np.maximum(ev, 1e-300)[:, None]
                                  * (ev > 1e-12 * ev.max())[:, None]))
            tt = tt - 2.0 * float(np.sum(p.T * rhs))                       # ||t - B~ p||^2, no [J, 3m]
            residual = max(tt + float(np.sum(p.T * (gram @ p.T))) - inside, 0.0)      # temporary
            mu = choose_mu(ev, proj, residual, n_rows, k)
    lam = float(mu) * float(np.trace(gram)) / max(k, 1)
    normal = gram + lam * np.eye(k)
    centre = lam * p.T                                         # the ridge's pull: lam (w - p), [K,J]
    if elsewhere is not None:                                  # and the rows elsewhere: G_else (w - p)
        g_else = np.asarray(elsewhere, dtype=np.float64)
        normal = normal + g_else
        centre = centre + g_else @ p.T
    if held is None:
        w = p + np.linalg.solve(normal, rhs_p).T
    else:                    # per row, the reduced system on its free entries: held rows/columns -> identity
        free = ~held
        system = np.where(free[:, :, None] & free[:, None, :], normal[None], np.eye(k)[None])   # [J,K,K]
        w = np.linalg.solve(system, np.where(free, (rhs + centre).T, 0.0)[..., None])[..., 0]
    if bounds is not None:
        w = _bounded(normal, rhs + centre, w, bounds, held)
    return (w, float(mu)) if return_mu else w


def driven_gram(meshes, names) -> np.ndarray:
    """``[K,K]``: ``sum_v B_i(v) . B_k(v)`` of the shapes ``names[K]`` over the vertices of other ``meshes``
    (an iterable of ``(mesh shape names, deltas)``, ``deltas[s]`` one shape's ``[n,3]`` offsets, metres),
    matched by name: the rows an engine drives with the map besides the face rows, for
    :func:`retarget_weights`' ``elsewhere``. Only the vertices some shape moves are gathered (a body mesh's
    neck, not its 300k vertices), one shape at a time."""
    index = {n: i for i, n in enumerate(names)}
    gram = np.zeros((len(names), len(names)))
    for mesh_names, deltas in meshes:
        shared = [(index[n], s) for s, n in enumerate(mesh_names) if n in index]
        if not shared:
            continue
        moving = None
        for _, s in shared:
            d = np.asarray(deltas[s], dtype=np.float64)
            hit = np.any(d != 0.0, axis=1)
            moving = hit if moving is None else moving | hit
        rows = np.flatnonzero(moving)
        if not rows.size:
            continue
        a = np.stack([np.asarray(deltas[s], dtype=np.float64)[rows].ravel() for _, s in shared])    # [S,3u]
        at = [i for i, _ in shared]
        gram[np.ix_(at, at)] += a @ a.T
    return gram


def namesake_prior(target_names, avatar_names) -> np.ndarray:
    """``[J,K]``: 1 where avatar shape i has capture shape j's (canonical ARKit) name, else 0 - the
    identity of the shared names, the prior of the product's retarget map (:func:`retarget_weights`)."""
    index = {n: i for i, n in enumerate(avatar_names)}
    p = np.zeros((len(target_names), len(avatar_names)))
    for j, n in enumerate(target_names):
        if n in index:
            p[j, index[n]] = 1.0
    return p


def _bounded(normal, rhs, start, bounds, held=None) -> np.ndarray:
    """``argmin_{lo <= w <= hi} w^T N w - 2 w^T rhs_j`` for every column j of ``rhs[K,J]`` (``N[K,K]``
    symmetric positive definite), all rows at once by the exact active-set method of
    :func:`usdface.bounded_lsq.box_least_squares`; ``start[J,K]``: the unbounded solutions (kept where they
    are inside the bounds); ``held[J,K]``: entries held at their ``start`` value (0). Returns ``[J,K]``."""
    from ..bounded_lsq import box_least_squares

    lo, hi = (float(b) for b in bounds)
    if not lo < hi:
        raise ValueError(f"weight bounds must have lo < hi, not {bounds!r}")
    out = np.array(start, dtype=np.float64, copy=True)
    bad = (out < lo) | (out > hi)
    if held is not None:
        bad &= ~held
    outside = np.flatnonzero(bad.any(axis=1))
    if outside.size:
        out[outside], _ = box_least_squares(normal, np.asarray(rhs, dtype=np.float64)[:, outside].T, lo, hi,
                                            out[outside], hold=None if held is None else held[outside])
    return out


def approximate(weights, deltas) -> np.ndarray:
    """Menzel et al. 2022, sec. 3.3: the approximations ``A[J,n,3] = weights[J,K] @ deltas[K,n,3]`` of the
    personalized shapes by the avatar's own ``deltas`` on one mesh, with the eq. (4) ``weights``."""
    d = np.asarray(deltas, dtype=np.float64)
    flat = np.asarray(weights, dtype=np.float64) @ d.reshape(d.shape[0], -1)
    return flat.reshape(-1, *d.shape[1:])


def weight_map_rows(weights, target_names, avatar_names, *, threshold: float = 0.0) -> dict:
    """The map as ``{capture_shape: {avatar_shape: weight}}``, dropping ``|weight| <= threshold`` (the zeros).

    The map file and the layer's provenance give the weights rounded to six decimals and these rows of
    them without the zeros: a weight is the share of an avatar shape per unit of a phone channel (in [0,
    1]), moving the avatar by at most its size times that shape's peak, so its resolution is absolute - a
    millionth of the shape, 10 nm of a 1 cm shape, below float32's resolution of a head's positions - not
    relative to its row (a cut at a share of the row's largest weight would drop a real 0.01 cross term
    beside an unbounded map's namesake of 20). Before stop 52 the rows also dropped ``|w| = 1e-6`` after
    the rounding: entries the ``weights`` matrix held."""
    w = np.asarray(weights)
    return {t: {a: float(w[j, i]) for i, a in enumerate(avatar_names) if abs(w[j, i]) > threshold}
            for j, t in enumerate(target_names)}


def weight_map_json(weights, target_names, avatar_names, *, meta: dict | None = None,
                    channels=None, mesh_channels: dict | None = None) -> str:
    """JSON text: ``{"format": "usdface.retarget/1", "source": [...], "target": [...], "target_channels":
    [...], "mesh_channels": {...}, "weights": [[...]], "map": {...}}`` (rows = capture/ARKit input shapes,
    columns = avatar shapes; ``target_channels``: the face mesh's own channel name of each ``target`` shape,
    ``channels`` or the ARKit names; ``mesh_channels``: ``{mesh prim: [channel or None per target]}`` of the
    other meshes the columns drive, when given)."""
    doc = {"format": "usdface.retarget/1", "equation": "Menzel et al. 2022, eq. 4",
           "source": list(target_names), "target": list(avatar_names),
           "target_channels": list(avatar_names if channels is None else channels),
           **({"mesh_channels": mesh_channels} if mesh_channels else {}),
           "weights": np.asarray(weights).round(6).tolist(),
           "map": weight_map_rows(np.asarray(weights).round(6), target_names, avatar_names)}
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
