"""Baseline landmark layouts the paper compares against (Zell & McDonnell 2022, sec. 4).

* :func:`empirical_layout`: a fixed, hand-placed layout (e.g. the 68-point layout of ICT-FaceKit, given as
  vertex indices).
* :func:`pca_kmeans_layout`: Cohen et al. 2002 - PCA of the motion (here: the blendshape deltas), k-means on
  the vertices' rows of the PCA matrix, the vertex nearest each cluster centre.
* :func:`delta_cluster_layout`: Reverdy et al. 2015 - k-means on the rows of the delta-blendshape matrix
  (each vertex's displacements in all shapes), the vertex nearest each cluster centre.
* :func:`random_layout`: uniform random moving vertices.

As in the paper, vertices that barely move (max relative displacement < 0.01 over all shapes) are left out.
All seeded, so deterministic.
"""

from __future__ import annotations

import numpy as np
from scipy.cluster.vq import kmeans2
from scipy.spatial import cKDTree

from ..errors import LandmarkError
from .candidates import displacement_magnitudes, moving_share, relative_displacement

#: Vertices whose largest relative displacement is below this are not considered (paper, sec. 4.1).
MOVING = 0.01


def moving_vertices(deltas: np.ndarray, threshold: float = MOVING) -> np.ndarray:
    """Vertices with max_k r_n^k >= ``threshold``: ``deltas[K, n, 3]`` -> indices ``[v]``."""
    return np.flatnonzero(moving_share(relative_displacement(displacement_magnitudes(deltas))) >= threshold)


def empirical_layout(indices, n_vertices: int) -> np.ndarray:
    """A given vertex-index layout, validated against ``n_vertices`` -> sorted unique ``[m]``."""
    v = np.unique(np.asarray(indices, dtype=np.int64))
    if v.size == 0:               # it said 'out of range' of an empty list
        raise LandmarkError("empirical layout lists no vertex index",
                            fix="give the layout's vertex indices (a JSON list of ints, or ICT-FaceKit's "
                                "vertex_indices.json)")
    bad = v[(v < 0) | (v >= n_vertices)]
    if bad.size:
        shown = ", ".join(str(int(i)) for i in bad[:5]) + (f" (+{bad.size - 5})" if bad.size > 5 else "")
        raise LandmarkError(f"empirical layout indices out of range for a mesh of {n_vertices} vertices "
                            f"(0..{n_vertices - 1}): {shown}",
                            fix="use the layout of the mesh it was made for (e.g. ICT-FaceKit's on Head)")
    return v


def _nearest_to_centres(features: np.ndarray, count: int, seed: int) -> np.ndarray:
    count = min(int(count), len(features))
    centres, _ = kmeans2(features, count, minit="++", seed=np.random.default_rng(seed))
    _, nearest = cKDTree(features).query(centres)
    return np.unique(nearest)


def pca_features(deltas: np.ndarray, variance: float = 0.99) -> tuple[np.ndarray, np.ndarray]:
    """Cohen et al. 2002's features: ``(moving[v], loadings[v, 3P])``, each moving vertex's row of the scaled
    PCA matrix of the motion ``X[K, 3n]`` (its 3 coordinates x the P components explaining ``variance``)."""
    d = np.asarray(deltas, dtype=np.float64)
    moving = moving_vertices(d)
    x = d[:, moving].reshape(d.shape[0], -1)
    x = x - x.mean(axis=0, keepdims=True)
    _, s, vt = np.linalg.svd(x, full_matrices=False)
    keep = int(np.searchsorted(np.cumsum(s**2) / np.sum(s**2), variance) + 1)
    return moving, (vt[:keep].T * s[:keep]).reshape(len(moving), 3 * keep)


def pca_kmeans_layout(deltas: np.ndarray, count: int, variance: float = 0.99, seed: int = 0,
                      features: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Cohen et al. 2002: ``deltas[K, n, 3]`` -> ``count`` (or fewer, if clusters share a vertex) vertices.

    The motion matrix ``X[K, 3n]`` is decomposed by SVD; each vertex's row of the scaled PCA matrix
    (its 3 coordinates x the components explaining ``variance`` of the motion) is clustered by k-means.
    ``features``: :func:`pca_features` of the same deltas, when a sweep over counts computed them once.
    """
    moving, loadings = pca_features(deltas, variance) if features is None else features
    return moving[_nearest_to_centres(loadings, count, seed)]


def delta_cluster_layout(deltas: np.ndarray, count: int, seed: int = 0,
                         moving: np.ndarray | None = None) -> np.ndarray:
    """Reverdy et al. 2015: k-means on the delta-blendshape matrix rows ``[n, 3K]`` of the moving vertices
    (``moving``: :func:`moving_vertices` of the same deltas, when already known)."""
    d = np.asarray(deltas, dtype=np.float64)
    moving = moving_vertices(d) if moving is None else moving
    rows = d[:, moving].transpose(1, 0, 2).reshape(len(moving), -1)
    return moving[_nearest_to_centres(rows, count, seed)]


def random_layout(deltas: np.ndarray, count: int, seed: int = 0, moving: np.ndarray | None = None
                  ) -> np.ndarray:
    """``count`` distinct moving vertices drawn uniformly at random (``moving`` as in
    :func:`delta_cluster_layout`)."""
    moving = moving_vertices(deltas) if moving is None else moving
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(moving, size=min(int(count), len(moving)), replace=False))
