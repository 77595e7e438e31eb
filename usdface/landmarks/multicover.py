"""Adaptive multi-cover (Zell & McDonnell 2022, sec. 3.3.2, Algorithm 1).

Single covers are solved repeatedly; after each round the chosen vertices and every vertex within ``radius``
of them leave the candidate sets, and a shape stays in the problem only while it has a candidate left, fewer
than ``max_per_shape`` landmarks, and (adaptive) its landmarks serve too many shapes: the paper's heuristic
that "one landmark should not be assigned to more than 10% of blendshapes". Here a shape k is satisfied once
``|L_k| >= |union of C_l for l in L_k| / (share K)``, i.e. its landmarks serve at most ``share`` of all shapes
each on average.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from .candidates import moving_share
from .cover import CoverSolution
from .visibility import face_size


def shapes_needing_landmarks(c: np.ndarray, chosen: np.ndarray, max_per_shape: int, share: float | None = 0.1
                             ) -> np.ndarray:
    """Algorithm 1, lines 14-18: ``c[K, n]`` bool candidates (original), ``chosen[m]`` vertex indices ->
    ``[K]`` bool, True where shape k should get another landmark (before checking candidates remain)."""
    c = np.asarray(c, dtype=bool)
    chosen = np.asarray(chosen, dtype=np.int64)
    cl = c[:, chosen]  # [K, m]: landmark l is a candidate for shape k
    count = cl.sum(axis=1)
    need = count < max_per_shape
    if share is None or chosen.size == 0:
        return need
    # shapes served by the landmarks of shape k: union over l in L_k of C_l
    served = (cl.astype(np.int32) @ cl.T.astype(np.int32)) > 0  # [K, K]
    limit = max(share * c.shape[0], 1.0)
    return need & (count < np.ceil(served.sum(axis=1) / limit))


#: Default exclusion radius of the multi-cover's later rounds, as a share of the face size
#: (:func:`usdface.landmarks.visibility.face_size`: the diagonal of the box around the vertices some shape
#: moves by at least 5 % of its peak, the face size that also sets the rays' offset and the skin samples'
#: spacing): 1 cm on the dev avatars' human head (0.417 m), the radius the layouts and the evaluation sweep
#: were measured with at an absolute 0.01 m; relative, so a rig of another size (or read in other units)
#: gets the same layout, and the same at every epsilon and in symmetric mode (it was 5 % of the box around
#: the epsilon's candidates: 12.8 mm on dev1 at epsilon 0.5, 10.0 at 0.9, 11.2 symmetric - and nothing but
#: the API took it).
RADIUS_SHARE = 0.024


def exclusion_radius(neutral: np.ndarray, r: np.ndarray) -> float:
    """The default multi-cover exclusion radius (Algorithm 1, line 10: "vertices close to F"), in
    ``neutral``'s units: :data:`RADIUS_SHARE` x the face size of ``neutral[n, 3]``, the face being the
    vertices whose relative displacement ``r[K, n]`` (eq. 2) reaches 5 % for some shape. Independent of
    epsilon and of the symmetric preprocessing (both change the candidates, not the face)."""
    return RADIUS_SHARE * face_size(neutral, moving_share(r))


def adaptive_multicover(c: np.ndarray, cost, neutral: np.ndarray, max_per_shape: int,
                        solve: Callable[[np.ndarray, np.ndarray], CoverSolution], radius: float,
                        share: float | None = 0.1, partner: np.ndarray | None = None,
                        coverage: np.ndarray | None = None
                        ) -> tuple[np.ndarray, np.ndarray, list[CoverSolution]]:
    """Zell & McDonnell 2022, Algorithm 1 (sec. 3.3.2): ``c[K, n]`` bool candidates (eq. 3), ``cost[n]``
    (eq. 5a) or a callable ``cost(sub[K, n]) -> [n]`` evaluated per round, ``neutral[n, 3]`` metres.

    ``solve(c, cost)`` solves one cover (eq. 5). ``partner[n]`` (symmetric mode) adds mirror partners to the
    excluded neighbourhood; ``coverage[K, n]`` is the candidate matrix used to count landmarks per shape
    (default ``c``). ``radius`` in ``neutral``'s units (:func:`exclusion_radius` gives the default of
    :func:`usdface.landmarks.compute_landmarks`, relative to the face).
    Returns (selected vertex indices [m], round of each [m], the per-round solutions).
    """
    c = np.asarray(c, dtype=bool)
    coverage = c if coverage is None else np.asarray(coverage, dtype=bool)
    tree = cKDTree(neutral)
    chosen: list[int] = []
    rounds: list[int] = []
    solutions: list[CoverSolution] = []
    available = np.ones(c.shape[1], dtype=bool)
    active = c.any(axis=1)
    for i in range(max(1, int(max_per_shape))):
        if i > 0:
            sel = _expand(np.asarray(chosen, dtype=np.int64), partner)
            near = np.concatenate([np.asarray(n, dtype=np.int64)
                                   for n in tree.query_ball_point(neutral[sel], radius)] + [sel])
            available[near] = False
            active = shapes_needing_landmarks(coverage, sel, max_per_shape, share)
        sub = c & available[None, :] & active[:, None]
        if not sub.any():
            break
        sol = solve(sub, cost(sub) if callable(cost) else cost)
        solutions.append(sol)
        new = [int(v) for v in sol.selected if v not in chosen]
        if not new:
            break
        chosen += new
        rounds += [i + 1] * len(new)
    order = np.argsort(chosen, kind="stable")
    return np.asarray(chosen, dtype=np.int64)[order], np.asarray(rounds, dtype=np.int64)[order], solutions


def _expand(selected: np.ndarray, partner: np.ndarray | None) -> np.ndarray:
    if partner is None:
        return selected
    return np.unique(np.concatenate([selected, partner[selected][partner[selected] >= 0]]))


def one_shot_multicover(c: np.ndarray, cost: np.ndarray, n_per_shape: int, *, backend: str = "scip",
                        time_limit: float = 60.0) -> CoverSolution:
    """Zell & McDonnell 2022, sec. 3.3.2, the one-shot multi-cover beside :func:`adaptive_multicover`: one ILP
    that covers every shape ``N = n_per_shape`` times, ``min sum_n cost_n f_n`` s.t. ``sum_n c_kn f_n >=
    min(N, |C_k|)`` for every shape k, ``f_n`` binary (eq. 5 with the right-hand side N). ``c[K, n]`` bool
    candidates (eq. 3), or counts: how many of the landmarks column n stands for serve shape k (symmetric
    mode, :func:`.symmetry.pair_candidate_counts`); ``cost[n] > 0`` (eq. 5a). Unlike the adaptive rounds it
    sees all the landmarks at once (a proven optimum of the whole layout) but has no spatial exclusion radius
    and no 10 % heuristic. Shapes without a candidate are returned in ``uncovered``. Solved to a proven
    optimum with OR-tools (relative gap 0) like :func:`usdface.landmarks.cover.solve_set_cover`.
    """
    from ..errors import LandmarkError
    from .cover import solve_set_cover

    c = np.asarray(c)
    cost = np.asarray(cost, dtype=np.float64)
    if c.ndim != 2 or cost.shape != (c.shape[1],):
        raise LandmarkError(f"multi-cover needs c[K, n] and cost[n]; got {c.shape} and {cost.shape}")
    if int(n_per_shape) < 1:
        raise LandmarkError(f"n_per_shape must be >= 1, got {n_per_shape}", fix="use 1 or more")
    return solve_set_cover(c, cost, backend, time_limit, reduce=False, cover_times=int(n_per_shape))
