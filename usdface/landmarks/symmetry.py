"""Symmetric landmark layouts (Zell & McDonnell 2022, sec. 3.3.1).

Mirror vertex pairs are found geometrically (the neutral reflected across the mid-plane - its axis detected
from the neutral - matched by nearest neighbour, kept only when the match is mutual and close). Per shape the
stronger side's displacement is given to the *primary* side (below the mid-plane) and the other side set to
0; the cover is solved on primary and mid-line vertices, and the result mirrored, so the layout is exactly
symmetric.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def _reflect(p: np.ndarray, tree: cKDTree, axis: int) -> tuple[np.ndarray, float]:
    """``p`` reflected across the plane ``x[axis] = centre`` (the median coordinate, refined once by the
    median offset of the reflected points' nearest neighbours), and that centre."""
    mirrored = p.copy()
    centre = float(np.median(p[:, axis]))
    mirrored[:, axis] = 2.0 * centre - p[:, axis]
    _, j = tree.query(mirrored)
    centre += 0.5 * float(np.median(p[j, axis] - mirrored[:, axis]))
    mirrored[:, axis] = 2.0 * centre - p[:, axis]
    return mirrored, centre


def mirror_axis(neutral: np.ndarray) -> int:
    """The coordinate axis (0, 1, 2) across which the mesh ``neutral[n, 3]`` is mirror-symmetric: the one
    whose reflection lands closest to the mesh (least median distance of reflected vertices to their nearest
    vertex). A face's left-right axis, whatever the rig's up axis and facing."""
    p = np.asarray(neutral, dtype=np.float64)
    tree = cKDTree(p)
    return int(np.argmin([np.median(tree.query(_reflect(p, tree, a)[0])[0]) for a in range(3)]))


def mirror_pairs(neutral: np.ndarray, axis: int | None = None, tolerance: float | None = None,
                 centre: float | None = None) -> np.ndarray:
    """Mirror partner of every vertex (Zell & McDonnell 2022, sec. 3.3.1): ``neutral[n, 3]`` metres ->
    ``partner[n]`` int (-1 = none, itself on the mid-line).

    The mirror plane is ``x[axis] = centre`` (``axis`` default: detected, :func:`mirror_axis`; ``centre``
    default: the median coordinate, refined once by the median offset of the reflected points' nearest
    neighbours, robust to scanned, slightly asymmetric meshes). A pair
    (i, j) is kept when
    j is the nearest vertex to i's reflection, i the nearest to j's, and the distance is below ``tolerance``
    (default: half the median nearest-neighbour spacing).
    """
    p = np.asarray(neutral, dtype=np.float64)
    axis = mirror_axis(p) if axis is None else int(axis)
    tree = cKDTree(p)
    if centre is None:
        mirrored, centre = _reflect(p, tree, axis)
    else:
        mirrored = p.copy()
        mirrored[:, axis] = 2.0 * centre - p[:, axis]
    if tolerance is None:
        spacing, _ = tree.query(p, k=2)
        tolerance = 0.5 * float(np.median(spacing[:, 1]))
    dist, j = tree.query(mirrored)
    mutual = j[j] == np.arange(len(p))
    return np.where((dist <= tolerance) & mutual, j, -1).astype(np.int64)


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


def mirror_selection(selected: np.ndarray, partner: np.ndarray) -> np.ndarray:
    """Selected primary vertices plus their mirror partners, sorted and unique -> ``[m]`` (Zell & McDonnell
    2022, sec. 3.3.1: symmetric layouts)."""
    s = np.asarray(selected, dtype=np.int64)
    return np.unique(np.concatenate([s, partner[s]]))
