"""How far a personalized avatar is from the person: the figures ``benchmarks/bench_personalize.py`` prints
and the tests assert, for cases with a ground truth (the bench cases, the sample assets).

Pure numpy on one mesh at a time: ``generic[K,n,3]``, ``output[K,n,3]`` and ``truth[K,n,3]`` offsets in the
same units (metres internally; figures are returned in mm), ``region[n]`` bool masks, ``triangles[t,3]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..mesh import edges as mesh_edges

__all__ = ["rmse", "MeshScore", "score_mesh", "seam_jump", "border_band_edges"]


def rmse(a, b, region=None) -> float:
    """RMS over shapes and vertices (``region`` = vertex mask or indices) of ``|a - b|`` per vertex."""
    d = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    if region is not None:
        d = d[:, region]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=-1)))) if d.size else 0.0


def border_band_edges(triangles, covered, rings: int = 2) -> np.ndarray:
    """Edges ``[e,2]`` with both ends within ``rings`` edge rings of the border of ``covered[n]`` (the
    vertices the capture covers): the edges across which a seam would show."""
    edges = mesh_edges(triangles)
    covered = np.asarray(covered, dtype=bool)
    n = len(covered)
    near = np.zeros(n, dtype=bool)
    cross = covered[edges[:, 0]] != covered[edges[:, 1]]
    near[edges[cross].ravel()] = True
    for _ in range(rings - 1):
        grow = near[edges[:, 0]] | near[edges[:, 1]]
        near[edges[grow].ravel()] = True
    return edges[near[edges[:, 0]] & near[edges[:, 1]]]


def seam_jump(error, edges) -> float:
    """Largest jump of ``error[K,n,3]`` (output - truth) across ``edges[e,2]``, over shapes: mm if metres."""
    if len(edges) == 0:
        return 0.0
    e = np.asarray(error, dtype=np.float64)
    jump = np.linalg.norm(e[:, edges[:, 0]] - e[:, edges[:, 1]], axis=-1)
    return float(jump.max())


@dataclass
class MeshScore:
    """Figures of one mesh (mm): RMSE of the output and of the generic input vs the truth, over the face
    region and the whole mesh; per shape the difference output - generic RMSE over the face; the seam."""

    names: list
    face_out: float
    face_generic: float
    whole_out: float
    whole_generic: float
    per_shape_delta: np.ndarray = field(default_factory=lambda: np.zeros(0))
    seam_out: float = 0.0
    seam_generic: float = 0.0

    @property
    def face_ratio(self) -> float:
        return self.face_out / max(self.face_generic, 1e-300)

    @property
    def whole_ratio(self) -> float:
        return self.whole_out / max(self.whole_generic, 1e-300)

    def worst_shape(self) -> tuple[str, float]:
        if not len(self.per_shape_delta):
            return "", 0.0
        k = int(np.argmax(self.per_shape_delta))
        return self.names[k], float(self.per_shape_delta[k])


def score_mesh(names, generic, output, truth, *, face=None, covered=None, triangles=None,
               rings: int = 2) -> MeshScore:
    """Score one mesh. ``face[n]``: the region of the face figures (default: every vertex); ``covered[n]`` and
    ``triangles``: the seam across the border of what the capture covers (skipped without them). Inputs in
    metres, figures in mm."""
    g, o, t = (np.asarray(a, dtype=np.float64) for a in (generic, output, truth))
    region = slice(None) if face is None else np.asarray(face)
    per_out = np.sqrt(np.mean(np.sum((o - t)[:, region] ** 2, axis=-1), axis=1))
    per_gen = np.sqrt(np.mean(np.sum((g - t)[:, region] ** 2, axis=-1), axis=1))
    score = MeshScore(list(names), rmse(o, t, region) * 1e3, rmse(g, t, region) * 1e3, rmse(o, t) * 1e3,
                      rmse(g, t) * 1e3, (per_out - per_gen) * 1e3)
    if covered is not None and triangles is not None:
        edges = border_band_edges(triangles, covered, rings)
        score.seam_out = seam_jump(o - t, edges) * 1e3
        score.seam_generic = seam_jump(g - t, edges) * 1e3
    return score
