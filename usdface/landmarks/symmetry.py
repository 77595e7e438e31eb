"""Symmetric landmark layouts (Zell & McDonnell 2022, sec. 3.3.1).

Mirror vertex pairs are found geometrically: the mesh's own symmetry is fitted (an improper rigid motion by
ICP of the mesh onto its mirror image, its axis detected from the neutral, plus a smooth asymmetry field), so
a scanned, slightly asymmetric head pairs as well as an authored one; each vertex is paired with the vertex
its mirror image lands on (mutual nearest, then a one-to-one matching within one vertex spacing). Per shape
the stronger side's displacement is given to the *primary* side (below the mid-plane) and the other side
set to 0; the cover is solved on primary and mid-line vertices, and the result mirrored, so the layout is
exactly symmetric.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import maximum_bipartite_matching
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ..personalize.align import kabsch

#: The nodes of the asymmetry field are the mesh sampled every ``FIELD_SHARE`` of its bounding-box diagonal
#: (~9 mm on a head), the field a Gaussian of ``FIELD_SIGMA`` node spacings (~2 cm): a scanned head's
#: asymmetry is smooth at that scale (dev3's, read against its topological pairs: 1.3 mm median, up to 13 mm,
#: of which a 16 mm Gaussian leaves 0.16 mm median).
FIELD_SHARE = 0.02
FIELD_SIGMA = 2.0
#: Iterations of the rigid (improper) ICP and of the smooth field.
RIGID_ITERATIONS = 30
FIELD_ITERATIONS = 10


def _reflect(p: np.ndarray, tree: cKDTree, axis: int) -> tuple[np.ndarray, float]:
    """``p`` reflected across the plane ``x[axis] = centre`` (the median coordinate, refined once by the
    median offset of the reflected points' nearest neighbours in ``tree``, the mesh), and that centre."""
    mirrored = p.copy()
    centre = float(np.median(p[:, axis]))
    mirrored[:, axis] = 2.0 * centre - p[:, axis]
    _, j = tree.query(mirrored)
    centre += 0.5 * float(np.median(tree.data[j, axis] - mirrored[:, axis]))
    mirrored[:, axis] = 2.0 * centre - p[:, axis]
    return mirrored, centre


def mirror_axis(neutral: np.ndarray) -> int:
    """The coordinate axis (0, 1, 2) across which the mesh ``neutral[n, 3]`` is mirror-symmetric: the one
    whose reflection lands closest to the mesh (least median distance of the reflected nodes,
    :func:`symmetry_nodes`, to their nearest vertex). A face's left-right axis, whatever the rig's up axis and
    facing. On the nodes, not every vertex: the same statistic at every resolution, and a 314k-vertex head +
    body mesh took 12.6 CPU-s (nearest-vertex queries of points reflected far off the mesh), 0.8 now."""
    p = np.asarray(neutral, dtype=np.float64)
    tree = cKDTree(p)
    x = p[symmetry_nodes(p)]
    return int(np.argmin([np.median(tree.query(_reflect(x, tree, a)[0])[0]) for a in range(3)]))


def symmetry_nodes(neutral: np.ndarray, share: float | None = None) -> np.ndarray:
    """``[m]`` vertex indices: per cube of side ``share`` (default ``FIELD_SHARE``) of the bounding-box
    diagonal of ``neutral[n, 3]`` (a grid anchored at the origin) the vertex nearest the cube's centre: the
    mesh sampled at a physical spacing (~9 mm on a head), the same points at every resolution."""
    p = np.asarray(neutral, dtype=np.float64)
    size = float(np.linalg.norm(np.ptp(p, axis=0)))
    h = (FIELD_SHARE if share is None else float(share)) * size if size > 0 else 1.0
    cell = np.floor(p / h).astype(np.int64)
    off = np.linalg.norm(p - (cell + 0.5) * h, axis=1)
    _, inv = np.unique(cell, axis=0, return_inverse=True)
    inv = inv.ravel()
    order = np.lexsort((off, inv))
    return order[np.r_[True, inv[order][1:] != inv[order][:-1]]]


def _point_to_plane(sx: np.ndarray, x: np.ndarray, normal: np.ndarray, rot: np.ndarray, t: np.ndarray,
                    size: float) -> tuple[np.ndarray, np.ndarray]:
    """Trimmed point-to-plane ICP (Chen & Medioni 1992), linearised per step, of ``sx[m, 3]`` onto the
    planes through ``x[m, 3]`` with unit ``normal[m, 3]``, from ``(rot, t)``: the fitted ``(rot, t)``."""
    node_tree = cKDTree(x)
    for _ in range(RIGID_ITERATIONS):
        y = sx @ rot.T + t
        dist, j = node_tree.query(y)
        keep = dist <= 2.5 * np.median(dist)
        nrm, yk = normal[j[keep]], y[keep]
        mid = yk.mean(axis=0)                   # rotate about the matched points' centre (conditioning)
        jac = np.hstack([np.cross(yk - mid, nrm), nrm])
        step = np.linalg.lstsq(jac, -np.einsum("mi,mi->m", yk - x[j[keep]], nrm), rcond=None)[0]
        angle = float(np.linalg.norm(step[:3]))
        turn = Rotation.from_rotvec(step[:3]).as_matrix()
        rot, t = turn @ rot, turn @ (t - mid) + mid + step[3:]
        if angle < 1e-10 and np.linalg.norm(step[3:]) < 1e-10 * max(size, 1.0):
            break
    return rot, t


def _point_to_point(sx: np.ndarray, p: np.ndarray, tree: cKDTree, rot: np.ndarray, t: np.ndarray,
                    size: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Trimmed point-to-point ICP (Besl & McKay 1992) of ``sx[m, 3]`` onto the vertices ``p[n, 3]`` from
    ``(rot, t)``: the fitted ``(rot, t)`` and the median distance of ``sx @ rot.T + t`` to the mesh."""
    for _ in range(RIGID_ITERATIONS):
        dist, j = tree.query(sx @ rot.T + t)
        keep = dist <= 2.5 * np.median(dist)
        new_rot, new_t = (m[0] for m in kabsch(sx[keep][None], p[j[keep]]))
        done = np.abs(new_rot - rot).max() < 1e-12 and np.abs(new_t - t).max() < 1e-12 * max(size, 1.0)
        rot, t = new_rot, new_t
        if done:
            break
    return rot, t, float(np.median(tree.query(sx @ rot.T + t)[0]))


def _gaussian_weights(nodes: np.ndarray, at: np.ndarray, sigma: float, k: int) -> sp.csr_matrix:
    """``[len(at), len(nodes)]`` Gaussian weights (width ``sigma`` metres) to the ``k`` nearest nodes."""
    k = min(int(k), len(nodes))
    d, j = cKDTree(nodes).query(at, k=k)
    d, j = d.reshape(len(at), k), j.reshape(len(at), k)
    w = np.exp(-0.5 * (d / sigma) ** 2)
    return sp.csr_matrix((w.ravel(), j.ravel(), np.arange(0, w.size + 1, k)), shape=(len(at), len(nodes)))


def mirror_map(neutral: np.ndarray, axis: int | None = None) -> np.ndarray:
    """Where each vertex's mirror image lies on the mesh: ``neutral[n, 3]`` metres -> ``[n, 3]`` metres.

    A scanned head is not symmetric about a coordinate plane, nor exactly about any plane. Its symmetry is
    fitted, coarse to fine, on nodes (the vertex nearest the centre of each cube of side ``FIELD_SHARE`` of
    the bounding-box diagonal, the same points at every resolution):

    1. the best improper rigid motion ``M(x) = R S x + t`` (``S`` the reflection of ``axis``, detected by
       :func:`mirror_axis`), so a tilted or shifted symmetry plane is found, not assumed: ICP of the nodes'
       reflections onto the mesh (trimmed: matches beyond 2.5x the median distance left out),
       point-to-plane (the nodes' tangent planes, from their 12 nearest vertices) from the plain reflection
       to reach a tilt of several degrees, then point-to-point onto the vertices from both that fit and the
       plain reflection, keeping the one closer to the mesh (a skull is nearly a surface of revolution, along
       which point-to-plane can slide: on dev3 it turned 6.6 degrees where the mesh's own pairs say 1.6);
    2. a smooth displacement field ``u`` on the nodes (Gaussian of ``FIELD_SIGMA`` node spacings), the
       trimmed nearest-vertex residuals of ``M(x) + u`` smoothed and added, ``FIELD_ITERATIONS`` times: the
       head's smooth asymmetry (a jaw or nose a few mm to one side);

    then the field is interpolated to every vertex (its 8 nearest nodes, the same Gaussian).
    """
    p = np.asarray(neutral, dtype=np.float64)
    axis = mirror_axis(p) if axis is None else int(axis)
    tree = cKDTree(p)
    size = float(np.linalg.norm(np.ptp(p, axis=0)))
    h = FIELD_SHARE * size if size > 0 else 1.0
    nodes = symmetry_nodes(p)
    reflect = np.ones(3)
    reflect[axis] = -1.0
    sx = p[nodes] * reflect
    x = p[nodes]
    _, near = tree.query(x, k=min(12, len(p)))
    near = near.reshape(len(x), -1)
    nbh = p[near] - p[near].mean(axis=1, keepdims=True)
    normal = np.linalg.eigh(np.einsum("mki,mkj->mij", nbh, nbh))[1][:, :, 0]   # the nodes' tangent planes
    plain = np.eye(3), np.zeros(3)
    plain[1][axis] = 2.0 * float(np.median(p[:, axis]))
    fit = _point_to_plane(sx, x, normal, *plain, size)
    # point-to-point from both starts (the plain reflection, the point-to-plane fit): a head's skull is
    # nearly a surface of revolution, along which point-to-plane may slide; keep the closer fit
    rot, t, _ = min((_point_to_point(sx, p, tree, r0, t0, size) for r0, t0 in (plain, fit)),
                    key=lambda fit: fit[2])
    y0 = sx @ rot.T + t
    sigma = FIELD_SIGMA * h
    w = _gaussian_weights(p[nodes], p[nodes], sigma, 16)
    u = np.zeros_like(y0)
    for _ in range(FIELD_ITERATIONS):
        y = y0 + u
        dist, j = tree.query(y)
        keep = (dist <= 2.5 * np.median(dist)).astype(np.float64)
        u += (w @ ((p[j] - y) * keep[:, None])) / np.maximum(w @ keep, 1e-300)[:, None]
    wv = _gaussian_weights(p[nodes], p, sigma, 8)
    field = (wv @ u) / np.maximum(np.asarray(wv.sum(axis=1)), 1e-300)
    return (p * reflect) @ rot.T + t + field


def mirror_pairs(neutral: np.ndarray, axis: int | None = None, tolerance: float | None = None,
                 centre: float | None = None) -> np.ndarray:
    """Mirror partner of every vertex (Zell & McDonnell 2022, sec. 3.3.1): ``neutral[n, 3]`` metres ->
    ``partner[n]`` int (-1 = none, itself on the mid-line); ``partner[partner[i]] == i`` for every pair.

    Each vertex's mirror image is :func:`mirror_map` (the fitted symmetry of the mesh, a scanned head's
    tilted plane and smooth asymmetry included); with ``centre`` given, the plain reflection across
    ``x[axis] = centre``. Pairs are formed in two steps, each within ``tolerance`` (default: relative to the
    local vertex spacing ``s_i``, the distance to a vertex's nearest neighbour, the larger of the two):

    1. mutual nearest: j the vertex nearest i's image and i the one nearest j's, within ``max(s_i, s_j) / 2``;
    2. the vertices left, on either side of the symmetry, by a maximum bipartite matching (Hopcroft-Karp,
       ``scipy.sparse.csgraph.maximum_bipartite_matching``) between each one's image and the 8 nearest
       unpaired vertices of the other side within ``max(s_i, s_j)``: where the asymmetry slides the surface
       along itself (which no nearest-point fit can see) the image lands between vertices, and each still
       gets a partner within one vertex spacing of it, one to one.
    """
    p = np.asarray(neutral, dtype=np.float64)
    axis = mirror_axis(p) if axis is None else int(axis)
    n = len(p)
    tree = cKDTree(p)
    if centre is None:
        image = mirror_map(p, axis)
    else:
        image = p.copy()
        image[:, axis] = 2.0 * centre - p[:, axis]
    near, _ = tree.query(p, k=2)
    local = near[:, 1]
    dist, j = tree.query(image)
    idx = np.arange(n)
    limit = local if tolerance is None else np.full(n, float(tolerance))
    mutual = (j[j] == idx) & (dist <= (0.5 * np.maximum(limit, limit[j]) if tolerance is None else limit))
    partner = np.where(mutual & mutual[j], j, -1).astype(np.int64)
    lower = p[:, axis] < image[:, axis]
    left, right = np.flatnonzero((partner < 0) & lower), np.flatnonzero((partner < 0) & ~lower)
    if left.size and right.size:
        k = min(8, right.size)
        d, col = cKDTree(p[right]).query(image[left], k=k)
        d, col = d.reshape(left.size, k), col.reshape(left.size, k)
        ok = (d <= np.maximum(limit[left][:, None], limit[right][col])).ravel()
        rows = np.repeat(np.arange(left.size), k)[ok]
        graph = sp.csr_matrix((np.ones(rows.size), (rows, col.ravel()[ok])), shape=(left.size, right.size))
        match = maximum_bipartite_matching(graph, perm_type="column")
        hit = match >= 0
        partner[left[hit]] = right[match[hit]]
        partner[right[match[hit]]] = left[hit]
    return partner


def primary_side(neutral: np.ndarray, partner: np.ndarray, axis: int | None = None) -> np.ndarray:
    """``[n]`` bool: vertices the symmetric problem is solved on (the lower-``axis`` member of each pair, and
    mid-line vertices); unpaired vertices are excluded. ``axis`` default: :func:`mirror_axis`."""
    p = np.asarray(neutral, dtype=np.float64)
    axis = mirror_axis(p) if axis is None else int(axis)
    idx = np.arange(len(p))
    paired = partner >= 0
    safe = np.where(paired, partner, idx)
    lower = (p[:, axis] < p[safe, axis]) | ((p[:, axis] == p[safe, axis]) & (idx <= safe))
    return paired & lower


def symmetric_magnitudes(magnitudes: np.ndarray, partner: np.ndarray, primary: np.ndarray) -> np.ndarray:
    """Displacement magnitudes of the symmetric problem: ``magnitudes[K, n]`` -> ``[K, n]`` with
    max(|dv_i|, |dv_partner(i)|) on primary vertices and 0 elsewhere (so each shape keeps its peak)."""
    m = np.asarray(magnitudes, dtype=np.float64)
    safe = np.where(partner >= 0, partner, np.arange(m.shape[1]))
    return np.where(primary[None, :], np.maximum(m, m[:, safe]), 0.0)


def pair_candidate_counts(c: np.ndarray, partner: np.ndarray, sym_c: np.ndarray) -> np.ndarray:
    """``[K, n]`` int: how many of the landmarks a column of the symmetric problem stands for are candidates
    of shape k - ``c[K, n]`` (eq. 3 on the mesh) at the vertex and at its mirror partner (``partner[n]``, -1
    or itself: the vertex alone), on the columns ``sym_c[K, n]`` allows, 0 elsewhere. The one-shot
    multi-cover's coefficients in symmetric mode: a mirrored pair both of whose vertices serve a shape is two
    of its landmarks (counted, as the adaptive rounds count them, on the mesh's candidates)."""
    c = np.asarray(c, dtype=bool)
    partner = np.asarray(partner)
    other = (partner >= 0) & (partner != np.arange(partner.size))
    mirror = c[:, np.where(other, partner, 0)] & other[None, :]
    return np.where(np.asarray(sym_c, dtype=bool), c.astype(np.int64) + mirror, 0)


def mirror_selection(selected: np.ndarray, partner: np.ndarray) -> np.ndarray:
    """Selected primary vertices plus their mirror partners, sorted and unique -> ``[m]`` (Zell & McDonnell
    2022, sec. 3.3.1: symmetric layouts)."""
    s = np.asarray(selected, dtype=np.int64)
    return np.unique(np.concatenate([s, partner[s]]))
