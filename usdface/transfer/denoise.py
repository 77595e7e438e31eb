"""A take's scan noise smoothed out of each shape's personalization (stop 46).

A shape a take read whole shows only at small weights is fitted from the scans' noise over that weight: its
change from the prior is right on average and rough from vertex to vertex, which the implant carries into the
avatar as a seam. :func:`denoise_personalization` smooths each shape's change over the capture mesh by the
strength that minimizes Stein's unbiased risk estimate of its error on the avatar's face. Arrays in, arrays
out."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph

__all__ = ["SMOOTHING_GRID", "DENOISE_MAX_VERTICES", "denoise_personalization"]

#: the smoothing strengths tried by :func:`denoise_personalization`, times the mesh Laplacian (0 = none)
SMOOTHING_GRID = np.concatenate([[0.0], np.logspace(-2.0, 3.0, 26)])
#: capture vertices above which :func:`denoise_personalization` is skipped: its dense eigendecomposition is
#: O(n^3) (a phone's 1,220-vertex mask ~0.3 s; 3,000 vertices ~4 s and 72 MB per n x n array)
DENOISE_MAX_VERTICES = 3000


def denoise_personalization(diff, triangles, variance,
                            metric=None) -> tuple[np.ndarray, np.ndarray]:
    """``diff[J,n,3]`` (the person's change of each shape on the capture, ``B_j - P_j``) smoothed over the
    capture mesh by ``S_j = (I + lam_j L)^-1`` (``L`` the graph Laplacian), each shape's ``lam_j`` the one of
    :data:`SMOOTHING_GRID` (0 included: no smoothing) that minimizes Stein's unbiased estimate of its error
    against the true change where it is used, ``|M (d - S d)|^2 + 2 tr(M S V M^T) - tr(M V M^T)``:
    ``metric`` ``M[m,n]`` the interpolation onto the avatar's face (sparse; None: the capture itself),
    ``V = diag(variance[:,j])`` with ``variance[n,J]`` (m^2, summed over the coordinates) the error the fit
    takes at each vertex from noise independent from vertex to vertex (a take's scans:
    :func:`usdface.personalize.fit.frame_error_variance`). A shape a take shows only at small weights is
    fitted from the scan noise over its weight: its change is right on average and rough from vertex to
    vertex (a seam in the avatar); a shape measured well keeps ``lam`` near 0. The interpolation averages
    some of that noise away itself, so the smoothing is chosen for the avatar, not the capture (chosen on
    the capture it over-smoothed: clean generated takes lost 1-2 % on the avatar's face). Returns
    ``(smoothed[J,n,3], lam[J])``; unchanged above :data:`DENOISE_MAX_VERTICES` (a dense eigensolve)."""
    from ..mesh import vertex_adjacency

    d = np.asarray(diff, dtype=np.float64)
    var = np.clip(np.asarray(variance, dtype=np.float64), 0.0, None)
    n_shapes, n = d.shape[:2]
    lam = np.zeros(n_shapes)
    if n_shapes == 0 or n > DENOISE_MAX_VERTICES or not np.any(var > 0):
        return d, lam
    lap = csgraph.laplacian(vertex_adjacency(np.asarray(triangles), n).astype(np.float64)).toarray()
    ev, u = np.linalg.eigh(lap)
    ev = np.clip(ev, 0.0, None)
    c = u.T @ d.transpose(1, 0, 2).reshape(n, -1)                            # [n, J*3] spectral coefficients
    h = 1.0 / (1.0 + SMOOTHING_GRID[:, None] * ev[None])                     # [G, n] the filter
    if metric is None:
        c2 = np.sum(c.reshape(n, n_shapes, 3) ** 2, axis=-1)                  # [n, J]
        residual = ((1.0 - h) ** 2) @ c2                                     # [G, J]
        q = (u * u).T @ var                                                  # [n, J] u_i^T V u_i
    else:
        gram = sp.csr_matrix(metric.T @ metric) if sp.issparse(metric) else np.asarray(metric.T @ metric)
        qu = np.asarray(gram @ u)                                            # [n, n] M^T M U (never M U)
        p_mat = u.T @ qu                                                     # U^T M^T M U
        q = (u * qu).T @ var                                                 # [n, J] u_i^T V M^T M u_i
        residual = np.empty((len(SMOOTHING_GRID), n_shapes))
        for g, hg in enumerate(h):                                           # a few dozen strengths
            x = (1.0 - hg)[:, None] * c
            residual[g] = np.sum((x * (p_mat @ x)).reshape(n, n_shapes, 3), axis=(0, 2))
    sure = residual + 2.0 * h @ q                                            # [G, J] (+ a constant per shape)
    best = np.argmin(sure, axis=0)
    lam = SMOOTHING_GRID[best]
    filt = h[best].T                                                         # [n, J]
    out = (u @ (c.reshape(n, n_shapes, 3) * filt[..., None]).reshape(n, -1)).reshape(n, n_shapes, 3)
    return out.transpose(1, 0, 2), lam
