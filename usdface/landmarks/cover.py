"""Weighted set cover (Zell & McDonnell 2022, sec. 3.2, eq. 5), solved to a proven optimum with OR-tools.

    minimise   sum_n cost_n f_n
    subject to sum_n c_n^k f_n >= 1   for every coverable shape k      (eq. 5b)
               f_n in {0, 1}                                             (eq. 5c)

The problem is reduced before it reaches the solver (the paper's "vertices with identical candidate sets keep
only the best one", plus the two classic set-cover reductions: a column whose candidate set is a strict
subset of a no-more-expensive column's is dropped, and a shape whose candidate columns include all of another
shape's is implied by it and dropped). Every reduction keeps at least one optimal solution, so the reported
optimum and gap are those of the full problem.

Cost forms (``weighting``), with q_n^k from :func:`usdface.landmarks.candidates.landmark_quality`:

* ``"quality"`` (default): ``cost_n = m_n (1 + delta (1 - mean_k q_n^k))`` over the shapes vertex n is a
  candidate for, with ``delta = 1 / (2 K + 1)`` (``1 / (2 N K + 1)`` for an N-fold cover). Any layout with
  fewer landmarks is strictly cheaper than any layout with more (the whole quality term of a minimal cover
  stays below one landmark), so the count is minimised first and quality breaks the ties: the issue's
  "count still dominates".
* ``"count"``: ``cost_n = m_n`` (fewest landmarks, ties broken by the solver).
* ``"paper"``: the literal reading of the paper's eqs. 1 + 5a, ``cost_n = m_n sum_k c_n^k (2 - q_n^k)``; it
  charges a vertex per shape it covers, so merging shapes onto one landmark earns nothing and the count grows
  (measured in ``docs/landmarks.md``).

``m_n`` is the number of landmarks a column stands for (2 for a mirrored pair in symmetric mode, else 1).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..errors import LandmarkError

WEIGHTINGS = ("quality", "count", "paper")
BACKENDS = {"scip": "SCIP", "cbc": "CBC", "highs": "HIGHS", "cp-sat": "CP-SAT"}


@dataclass
class CoverSolution:
    """Outcome of one set-cover solve.

    ``selected[m]`` vertex (column) indices, sorted; ``uncovered[u]`` shape (row) indices with no candidate at
    all; ``status`` one of optimal / feasible / infeasible / timeLimit / notSolved; ``gap`` the relative gap
    between the solution and the solver's proven bound (0 = proven optimal); ``size`` / ``reduced`` the
    (shapes, vertices) of the full and the reduced problem.
    """

    selected: np.ndarray
    uncovered: np.ndarray
    status: str
    objective: float
    bound: float
    gap: float
    seconds: float
    backend: str
    size: tuple[int, int]
    reduced: tuple[int, int]


def set_cover_costs(c: np.ndarray, q: np.ndarray, weighting: str = "quality",
                    multiplicity: np.ndarray | None = None, cover_times: int = 1) -> np.ndarray:
    """Objective coefficients cost_n of Zell & McDonnell 2022, eq. 5a: ``c[K, n]`` bool, ``q[K, n]`` quality
    in [0, 1] -> ``cost[n]``.

    See the module docstring for the three forms. ``multiplicity[n]`` (default 1) is the number of landmarks
    column n stands for. ``cover_times = N``: the costs of an N-fold cover (the one-shot multi-cover), whose
    minimal layouts have up to N K columns, so the quality form's ``delta`` is ``1 / (2 N K + 1)`` and the
    count still dominates (with ``1 / (2 K + 1)`` an N-fold cover's quality term could outweigh a landmark
    from N = 3 on, N = 2 with mirrored pairs).
    """
    c = np.asarray(c, dtype=bool)
    q = np.asarray(q, dtype=np.float64)
    m = np.ones(c.shape[1]) if multiplicity is None else np.asarray(multiplicity, dtype=np.float64)
    if weighting == "count":
        return m.copy()
    count = c.sum(axis=0)
    if weighting == "paper":
        return m * np.where(c, 2.0 - q, 0.0).sum(axis=0)
    if weighting != "quality":
        raise LandmarkError(f"unknown weighting {weighting!r}", fix=f"use one of {', '.join(WEIGHTINGS)}")
    mean_q = np.where(c, q, 0.0).sum(axis=0) / np.maximum(count, 1)
    delta = 1.0 / (2.0 * max(int(cover_times), 1) * c.shape[0] + 1.0)
    return m * (1.0 + delta * (1.0 - mean_q))


def _subset_pairs(a: np.ndarray, chunk: int = 2048):
    """Yield (i, j) index arrays with set(a[j]) a subset of set(a[i]), i != j: ``a[m, K]`` bool rows."""
    f = a.astype(np.float32)
    size = f.sum(axis=1)
    for s in range(0, a.shape[0], chunk):
        inter = f @ f[s:s + chunk].T  # [m, chunk]: |S_i & S_j|
        i, j = np.nonzero(inter == size[None, s:s + chunk])
        j = j + s
        keep = i != j
        yield i[keep], j[keep]


def reduce_set_cover(c: np.ndarray, cost: np.ndarray, max_rounds: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Reduce a set-cover instance without losing an optimum: ``c[K, n]`` bool, ``cost[n]`` -> (rows, cols).

    Keeps rows (shapes) that have a candidate and are not implied by another row, and columns (vertices) that
    cover a kept row, are the cheapest (then lowest-index) of their identical candidate sets, and are not
    dominated by a no-more-expensive superset. Returns sorted index arrays into ``c``'s rows and columns.
    """
    c = np.asarray(c, dtype=bool)
    cost = np.asarray(cost, dtype=np.float64)
    rows = np.flatnonzero(c.any(axis=1))
    cols = np.flatnonzero(c[rows].any(axis=0))
    for _ in range(max_rounds):
        n_before = (rows.size, cols.size)
        sub = c[np.ix_(rows, cols)].T  # [m, K'] column candidate sets
        # identical candidate sets: keep the cheapest, then the lowest index
        packed = np.packbits(sub, axis=1)
        _, group = np.unique(packed, axis=0, return_inverse=True)
        order = np.lexsort((cols, cost[cols], group.ravel()))
        first = np.ones(order.size, dtype=bool)
        first[1:] = group.ravel()[order][1:] != group.ravel()[order][:-1]
        keep = np.sort(order[first])
        cols, sub = cols[keep], sub[keep]
        # dominated columns: S_j strict subset of S_i and cost_i <= cost_j
        drop = np.zeros(cols.size, dtype=bool)
        for i, j in _subset_pairs(sub):
            dominated = cost[cols[i]] <= cost[cols[j]]
            drop[j[dominated]] = True
        cols, sub = cols[~drop], sub[~drop]
        # implied rows: cols(j) subset of cols(i) -> covering j covers i; identical rows keep the lowest index
        rt = sub.T  # [K', m]
        implied = np.zeros(rows.size, dtype=bool)
        for i, j in _subset_pairs(rt):
            same = rt[i].sum(axis=1) == rt[j].sum(axis=1)
            implied[i[~same | (i > j)]] = True
        rows = rows[~implied]
        cols = cols[c[np.ix_(rows, cols)].any(axis=0)]
        if (rows.size, cols.size) == n_before:
            break
    return rows, cols


#: Backend options that silence a solver's own log (OR-tools' SuppressOutput does not reach HiGHS, which
#: printed "Running HiGHS 1.12.0 ..." on stdout at every solve: into a ``--json -`` document, a pipe, a log).
_QUIET = {"highs": "output_flag=false\nlog_to_console=false"}


def quiet_solver(solver, backend: str) -> None:
    """Keep an OR-tools ``pywraplp`` solver of ``backend`` from printing anything (numeric code never
    prints): ``SuppressOutput`` for all, and the backend's own log options where it has its own log."""
    solver.SuppressOutput()
    if backend in _QUIET:
        # applied when solving (the HiGHS interface returns False here, having only stored them)
        solver.SetSolverSpecificParametersAsString(_QUIET[backend])


def solve_set_cover(c: np.ndarray, cost: np.ndarray, backend: str = "scip", time_limit: float = 60.0,
                    reduce: bool = True, cover_times: int = 1) -> CoverSolution:
    """Solve the weighted set cover of Zell & McDonnell 2022, eqs. 5a-c, to a proven optimum.

    ``cover_times = N > 1`` asks each shape to be covered ``min(N, |C_k|)`` times (the one-shot multi-cover,
    :func:`usdface.landmarks.multicover.one_shot_multicover`); the dominance reduction, exact for a single
    cover only, is then skipped. ``c`` may then hold counts (ints >= 0) instead of bools: column n covers
    shape k ``c[k, n]`` times (a mirrored pair, two landmarks), and ``|C_k|`` is the row's sum.

    ``c[K, n]`` bool candidate sets (eq. 3), ``cost[n]`` > 0 (eq. 5a, :func:`set_cover_costs`). Shapes
    without any candidate are skipped and returned in ``uncovered``. ``backend`` is an OR-tools ``pywraplp``
    MIP solver (scip, cbc, highs, cp-sat); the relative MIP gap is set to 0 so "optimal" means proven
    optimal.
    """
    from ortools.linear_solver import pywraplp

    times = np.asarray(c)
    if times.dtype != bool and not (np.issubdtype(times.dtype, np.integer) and (times >= 0).all()):
        raise LandmarkError(f"set cover needs c[K, n] bool or counts >= 0; got {times.dtype}",
                            fix="pass the candidate sets (eq. 3), or how often each column covers each shape")
    c = times.astype(bool)
    cost = np.asarray(cost, dtype=np.float64)
    if c.ndim != 2 or cost.shape != (c.shape[1],):
        raise LandmarkError(f"set cover needs c[K, n] and cost[n]; got {c.shape} and {cost.shape}")
    if backend not in BACKENDS:
        raise LandmarkError(f"unknown solver backend {backend!r}", fix=f"use one of {', '.join(BACKENDS)}")
    t0 = time.perf_counter()
    uncovered = np.flatnonzero(~c.any(axis=1))
    if reduce and int(cover_times) == 1:
        rows, cols = reduce_set_cover(c, cost)
    else:
        rows = np.flatnonzero(c.any(axis=1))
        cols = np.flatnonzero(c[rows].any(axis=0))
    size = (int(c.shape[0]), int(c.shape[1]))
    if rows.size == 0:
        return CoverSolution(np.zeros(0, dtype=np.int64), uncovered, "optimal", 0.0, 0.0, 0.0,
                             time.perf_counter() - t0, backend, size, (0, 0))
    solver = pywraplp.Solver.CreateSolver(BACKENDS[backend])
    if solver is None:
        raise LandmarkError(f"OR-tools has no {backend} backend in this build", fix="use --backend scip")
    quiet_solver(solver, backend)
    solver.SetNumThreads(1)
    solver.SetTimeLimit(int(time_limit * 1000))
    f = [solver.BoolVar(f"f{n}") for n in cols]
    sub = times[np.ix_(rows, cols)].astype(np.int64)
    for k in range(rows.size):
        members = np.flatnonzero(sub[k])
        w = sub[k, members]
        terms = [f[j] for j in members] if (w == 1).all() else [int(x) * f[j] for x, j in zip(w, members,
                                                                                                strict=True)]
        solver.Add(solver.Sum(terms) >= min(int(cover_times), int(w.sum())))
    objective = solver.Objective()
    for j, n in enumerate(cols):
        objective.SetCoefficient(f[j], float(cost[n]))
    objective.SetMinimization()
    params = pywraplp.MPSolverParameters()
    params.SetDoubleParam(params.RELATIVE_MIP_GAP, 0.0)
    code = solver.Solve(params)
    seconds = time.perf_counter() - t0
    if code not in (pywraplp.Solver.OPTIMAL, pywraplp.Solver.FEASIBLE):
        status = {pywraplp.Solver.INFEASIBLE: "infeasible"}.get(code, "notSolved")
        return CoverSolution(np.zeros(0, dtype=np.int64), uncovered, status, float("nan"), float("nan"),
                             float("inf"), seconds, backend, size, (int(rows.size), int(cols.size)))
    chosen = np.array([v.solution_value() > 0.5 for v in f])
    value = float(objective.Value())
    bound = float(objective.BestBound())
    gap = max(0.0, (value - bound) / max(abs(value), 1e-12))
    if code == pywraplp.Solver.OPTIMAL:
        status, gap = "optimal", 0.0 if gap < 1e-9 else gap
    else:
        status = "timeLimit" if seconds >= time_limit else "feasible"
    return CoverSolution(np.sort(cols[chosen]), uncovered, status, value, bound, gap, seconds, backend, size,
                         (int(rows.size), int(cols.size)))
