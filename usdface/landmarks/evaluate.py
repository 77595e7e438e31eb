"""Evaluation sweep: reconstruction error vs number of landmarks (Zell & McDonnell 2022, sec. 4).

Layouts of this method over a sweep of epsilon and multi-cover rounds are compared with the baselines of
:mod:`.baselines` (an empirical layout, PCA + k-means, delta-blendshape clustering, random) on test weights
(e.g. real Live Link Face takes): landmarks are tracked with Gaussian noise, the weights solved by bounded
least squares (:mod:`.reconstruct`) and the mesh RMSE measured over the moving vertices.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from ..model import FaceRig
from . import baselines
from .candidates import candidate_sets, displacement_magnitudes, relative_displacement
from .layout import compute_landmarks
from .reconstruct import layout_error
from .visibility import global_visibility, pose_bases


@dataclass
class EvaluationPoint:
    """One layout's result: ``method``, a ``label`` (parameters), landmark ``count``, ``rmse`` metres."""

    method: str
    label: str
    count: int
    rmse: float


@dataclass
class EvaluationReport:
    """All points, plus the summary the acceptance asks for (metres, counts)."""

    points: list[EvaluationPoint]
    frames: int
    noise: float
    summary: dict = field(default_factory=dict)
    #: the multi-cover's exclusion radius the layouts used (metres: ``radius`` given, or the default relative
    #: to the face, ``layout.problem["radius"]``); None when no layout had one
    radius: float | None = None

    def best(self, method: str, max_count: int) -> EvaluationPoint | None:
        """Lowest-error layout of ``method`` with at most ``max_count`` landmarks."""
        pts = [p for p in self.points if p.method == method and p.count <= max_count]
        return min(pts, key=lambda p: (p.rmse, p.count)) if pts else None

    def best_per_count(self, method: str = "ours") -> dict[int, float]:
        """{landmark count: lowest RMSE (metres) of ``method`` at that count}."""
        out: dict[int, float] = {}
        for p in self.points:
            if p.method == method:
                out[p.count] = min(out.get(p.count, np.inf), p.rmse)
        return dict(sorted(out.items()))

    def to_dict(self) -> dict:
        """The report as ``landmarks --evaluate --json`` writes it, with :data:`JSON_UNITS` as ``"units"``
        (the keys stay those of before: the unit is said in the JSON, not added to every key)."""
        return {"units": dict(JSON_UNITS), "frames": self.frames, "noise": self.noise, "radius": self.radius,
                "summary": self.summary, "points": [asdict(p) for p in self.points]}


#: The units of the evaluation JSON's lengths (``"units"`` in it): ``"rmse"`` covers every key with ``rmse``
#: in its name (``points[].rmse``, the summary's ``ours_best_rmse``, ``random_rmse_at_40``, ...), ``"noise"``
#: the tracking noise (std per coordinate), ``"radius"`` the multi-cover's exclusion radius. Metres, as every
#: array of the core; the printed summary is in mm.
#: It wrote metres under keys without a unit, beside a printed summary in mm (stop 43).
JSON_UNITS = {"rmse": "m", "noise": "m", "radius": "m"}


def _summary(report: EvaluationReport, empirical_count: int | None) -> dict:
    """The figures ``landmarks --evaluate`` prints: with an empirical layout, the smallest layout of this
    method that matches its error and this method's error at its count, beside the baselines'; without
    one, this method's most compact layout and its most accurate, each beside the baselines at (at most)
    that count (it was ``{}``: ``--json`` had no summary)."""
    ours = sorted((p for p in report.points if p.method == "ours"), key=lambda p: (p.count, p.rmse))
    out: dict = {}
    emp = [p for p in report.points if p.method == "empirical"]
    if ours and not emp:
        compact, accurate = ours[0], min(ours, key=lambda p: (p.rmse, p.count))
        out = {"ours_smallest_count": compact.count, "ours_rmse_at_smallest_count": compact.rmse,
               "ours_label_at_smallest_count": compact.label, "ours_best_rmse": accurate.rmse,
               "ours_count_at_best": accurate.count, "ours_label_at_best": accurate.label}
        for method in ("pca_kmeans", "delta_cluster", "random"):
            for count in sorted({compact.count, accurate.count}):
                b = [p for p in report.points if p.method == method and p.count <= count]
                if b:
                    top = max(b, key=lambda p: (p.count, -p.rmse))
                    out[f"{method}_rmse_at_{top.count}"] = top.rmse
        return out
    if emp and ours:
        e = emp[0]
        match = next((p for p in ours if p.rmse <= e.rmse), None)
        at = report.best("ours", e.count)
        out = {"empirical_count": e.count, "empirical_rmse": e.rmse,
               "match_count": match.count if match else None, "match_rmse": match.rmse if match else None,
               "match_label": match.label if match else None,
               "ours_at_empirical_count": at.count if at else None,
               "ours_rmse_at_empirical_count": at.rmse if at else None,
               "ours_label_at_empirical_count": at.label if at else None}
        for method in ("pca_kmeans", "delta_cluster", "random"):
            b = [p for p in report.points if p.method == method and p.count <= e.count]
            if b:
                top = max(b, key=lambda p: p.count)
                out[f"{method}_rmse_at_{top.count}"] = top.rmse
    return out


#: Landmark counts at which the clustering and random baselines are evaluated (plus the empirical count).
BASELINE_COUNTS = (8, 10, 12, 15, 20, 25, 30, 35, 40, 45, 50, 60, 68)


def evaluate_landmarks(rig: FaceRig, weights: np.ndarray, empirical: np.ndarray | None = None,
                       epsilons=(0.5, 0.6, 0.75, 0.9), rounds=(1, 2, 3, 4, 5, 6), radius: float | None = None,
                       shares=(0.1, 0.05, None), noise: float = 0.5e-3, tikhonov: float = 0.0,
                       alpha: float = 0.0, rays: int = 16, symmetric: bool = False, random_seeds: int = 3,
                       seed: int = 0, backend: str = "scip", counts=BASELINE_COUNTS) -> EvaluationReport:
    """Sweep this method's layouts and the baselines; ``weights[F, K]`` test weights in ``rig.names`` order.

    This method: every epsilon x multi-cover rounds x share (the adaptive heuristic's share; None =
    non-adaptive). ``alpha = 0`` (default; eq. 1 is ``q = (1 - alpha) r + alpha l``) follows the paper's
    evaluation protocol: layouts from displacement only (no ray casting); the synthetic tracking has no
    occlusion. ``radius``: the multi-cover radius (metres; None, the default: 2.4 % of the face size,
    :func:`.multicover.exclusion_radius`).
    ``empirical[m]``: vertex indices of an empirical layout (e.g. the 68 ICT points on ``Head``). Baselines at
    ``counts`` plus the empirical count. ``noise`` metres of tracking noise (std per coordinate), the same
    noise seed for every layout. RMSE over the vertices that move (:func:`baselines.moving_vertices`).
    """
    from ..personalize.api import one_blas_thread

    # thousands of small (3m x K) least-squares solves: a multi-threaded BLAS makes each one ~10x slower
    with one_blas_thread():
        return _evaluate(rig, weights, empirical, epsilons, rounds, radius, shares, noise, tikhonov, alpha,
                         rays, symmetric, random_seeds, seed, backend, counts)


def _sweep(epsilons, rounds, shares) -> list[tuple]:
    """The (epsilon, share, rounds) layouts of the sweep (the non-adaptive single cover equals the adaptive
    one at share 0.1 and is skipped)."""
    return [(eps, share, n) for eps in epsilons for share in shares for n in rounds
            if not (share is None and n == 1 and 0.1 in shares)]


def _evaluate(rig, weights, empirical, epsilons, rounds, radius, shares, noise, tikhonov, alpha, rays,
              symmetric, random_seeds, seed, backend, counts) -> EvaluationReport:
    from ..progress import steps

    w = np.asarray(weights, dtype=np.float64)
    region = baselines.moving_vertices(rig.deltas)
    if alpha > 0.0:
        r = relative_displacement(displacement_magnitudes(rig.deltas))
        need = np.flatnonzero(candidate_sets(r, min(epsilons)).any(axis=0))
        vis = np.zeros(rig.n_vertices)
        vis[need] = global_visibility(rig.neutral, rig.triangles, rig.deltas, need, rays,
                                      bases=pose_bases(rig.names))
    else:
        vis = np.ones(rig.n_vertices)

    def err(vertices) -> float:
        return layout_error(rig.neutral, rig.deltas, vertices, w, noise, tikhonov, seed, region)

    points: list[EvaluationPoint] = []
    seen: dict[tuple, float] = {}
    used = None
    sweep = _sweep(epsilons, rounds, shares)
    emp = None if empirical is None else baselines.empirical_layout(empirical, rig.n_vertices)
    counts = sorted({int(c) for c in counts} | ({int(emp.size)} if emp is not None else set()))
    with steps("landmarks --evaluate", len(sweep) + len(counts) + (emp is not None)) as advance:
        for eps, share, n in sweep:
            layout = compute_landmarks(rig, eps, alpha, symmetric=symmetric, multicover=n, radius=radius,
                                       visibility=vis, backend=backend, ignore_static=True,
                                       adaptive=share is not None, share=share or 0.1)
            used = layout.problem["radius"]     # the same for every layout of the sweep
            key = tuple(layout.vertices.tolist())
            if key not in seen:
                seen[key] = err(layout.vertices)
            mode = "non-adaptive" if share is None else f"share={share:g}"
            label = f"eps={eps:g} multicover={n} {mode}"
            points.append(EvaluationPoint("ours", label, layout.count, seen[key]))
            advance(label)
        if emp is not None:
            points.append(EvaluationPoint("empirical", f"{emp.size} points", int(emp.size), err(emp)))
            advance("empirical")
        pca = baselines.pca_features(rig.deltas)  # once for every count
        for m in counts:
            v = baselines.pca_kmeans_layout(rig.deltas, m, seed=seed, features=pca)
            points.append(EvaluationPoint("pca_kmeans", f"k={m}", int(v.size), err(v)))
            v = baselines.delta_cluster_layout(rig.deltas, m, seed=seed, moving=region)
            points.append(EvaluationPoint("delta_cluster", f"k={m}", int(v.size), err(v)))
            e = [err(baselines.random_layout(rig.deltas, m, seed=seed + s, moving=region))
                 for s in range(random_seeds)]
            points.append(EvaluationPoint("random", f"m={m} mean of {random_seeds}", m, float(np.mean(e))))
            advance(f"baselines at {m}")
    report = EvaluationReport(points, int(w.shape[0]), float(noise), radius=used)
    report.summary = _summary(report, None if empirical is None else len(empirical))
    return report
