"""Compact landmark layouts for a blendshape rig (Zell & McDonnell 2022): the whole method in one call.

    layout = compute_landmarks(rig, epsilon=0.5, alpha=0.5)
    layout.vertices      # [m] vertex indices on rig.neutral
    layout.coverage      # [m, K] bool: landmark i is a candidate for shape k

Steps: relative displacement and candidates (eqs. 2-3, :mod:`.candidates`), global visibility (eq. 4,
:mod:`.visibility`), quality-weighted set cover solved to a proven optimum (eqs. 1, 5, :mod:`.cover`),
optional symmetry (:mod:`.symmetry`) and adaptive multi-cover (Algorithm 1, :mod:`.multicover`).
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field

import numpy as np

from ..errors import LandmarkError
from ..model import FaceRig
from . import candidates as cand
from . import sampling
from .cover import BACKENDS, WEIGHTINGS, CoverSolution, set_cover_costs, solve_set_cover
from .multicover import adaptive_multicover, exclusion_radius, one_shot_multicover
from .symmetry import mirror_pairs, pair_candidate_counts, primary_side, symmetric_magnitudes
from .visibility import FACE_SHARE, PoseVisibility, face_size, pose_bases


@dataclass
class LandmarkLayout:
    """A landmark layout on one rig.

    ``vertices[m]`` sorted vertex indices, ``positions[m, 3]`` neutral positions (metres, internal frame),
    ``coverage[m, K]`` bool (landmark i is a candidate for shape k at ``epsilon``), ``rounds[m]`` multi-cover
    round that added each landmark, ``visibility[m]`` global visibility l_n, ``shape_names[K]``.
    ``status`` is the worst solver status over the rounds (optimal / feasible / timeLimit / infeasible),
    ``gap`` the largest proven relative gap; ``uncoverable`` names shapes no landmark represents;
    ``warnings`` says what was changed (e.g. the symmetric fallback).
    """

    vertices: np.ndarray
    positions: np.ndarray
    coverage: np.ndarray
    rounds: np.ndarray
    visibility: np.ndarray
    shape_names: list[str]
    epsilon: float
    alpha: float
    symmetric: bool
    multicover: int
    status: str
    gap: float
    objective: float
    weighting: str
    backend: str
    camera: list[float] | None = None
    uncoverable: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    timings: dict = field(default_factory=dict)
    problem: dict = field(default_factory=dict)

    def __repr__(self) -> str:
        return (f"<LandmarkLayout: {self.count} landmarks for {len(self.shape_names)} shapes (epsilon "
                f"{self.epsilon:g}, alpha {self.alpha:g}, {self.status}); vertices {self.vertices.tolist()}>")

    @property
    def count(self) -> int:
        return int(self.vertices.size)

    def landmarks_per_shape(self) -> dict[str, int]:
        """Number of landmarks that are candidates for each shape."""
        return {n: int(v) for n, v in zip(self.shape_names, self.coverage.sum(axis=0), strict=True)}

    def to_dict(self) -> dict:
        """A JSON-ready summary (lists, floats)."""
        d = asdict(self)
        for key in ("vertices", "positions", "rounds", "visibility"):
            d[key] = np.asarray(d[key]).tolist()
        d["coverage"] = [[self.shape_names[k] for k in np.flatnonzero(row)] for row in self.coverage]
        d["count"] = self.count
        d["landmarks_per_shape"] = self.landmarks_per_shape()
        return d


_STATUS_RANK = {"optimal": 0, "feasible": 1, "timeLimit": 2, "notSolved": 3, "infeasible": 4}


def _where(rig: FaceRig) -> dict:
    """The file and prim of ``rig`` for an error's message (None when it was not read from a file)."""
    return {"path": rig.source.file if rig.source else None, "prim": rig.source.prim if rig.source else None}


@contextmanager
def naming(rig: FaceRig):
    """Re-raise a :class:`LandmarkError` raised inside the block without a file as one naming ``rig``'s file
    and prim (the options' checks of :func:`compute_landmarks` and of ``usdface.landmark_diagnostics``)."""
    try:
        yield
    except LandmarkError as exc:
        if exc.path is None and rig.source is not None:
            raise LandmarkError(exc.message, **_where(rig), fix=exc.fix) from None
        raise


def check_one_shot(one_shot: bool, multicover: int, adaptive: bool = True, radius=None) -> None:
    """Refuse what the one-shot multi-cover (``one_shot``, the CLI's ``--one-shot``: one ILP covering every
    shape ``multicover`` times, Zell & McDonnell 2022 sec. 3.3.2) would ignore: ``multicover`` 1 (the layout
    would be the single cover; the Python API took it), and the adaptive rounds' ``radius`` or
    ``adaptive=False`` (no exclusion radius, no 10 % heuristic in the one ILP). One rule for
    :func:`compute_landmarks` and ``usdface landmarks``, in both spellings; :class:`LandmarkError` without a
    file (:func:`naming` adds the rig's)."""
    if not one_shot:
        return
    if multicover == 1:
        raise LandmarkError("one_shot (--one-shot) is a multi-cover (every shape covered N times in one "
                            "ILP), and multicover is 1 (--multicover 1): the layout would be the single "
                            "cover",
                            fix="pass multicover=N with N >= 2 (--multicover N), or leave out one_shot "
                                "(--one-shot)")
    ignored = [(said, name, flag) for said, name, flag, given in (
        (f"radius {radius!r:.30}", "radius", "--radius", radius is not None),
        ("adaptive=False", "adaptive=False", "--no-adaptive", not adaptive)) if given]
    if ignored:
        said, names, flags = (list(t) for t in zip(*ignored, strict=True))
        raise LandmarkError(f"one_shot takes no {' or '.join(said)} ({'/'.join(flags)}): the one-shot "
                            "multi-cover (--one-shot) replaces the adaptive rounds by one ILP (no exclusion "
                            "radius, no 10 % heuristic), which would ignore it",
                            fix=f"leave out {' and '.join(names)} ({'/'.join(flags)}), or leave out one_shot "
                                "(--one-shot) for the adaptive rounds")


def _number_in(value, low: float, high: float) -> bool:
    """Whether ``value`` is a finite real number (not a bool or a string) with ``low < value <= high``
    (an infinite time limit died in the solver's set-up, ``int(inf)``)."""
    if isinstance(value, bool | str) or not isinstance(value, int | float | np.integer | np.floating):
        return False
    return bool(low < float(value) <= high) and bool(np.isfinite(float(value)))


def _validate(rig: FaceRig, ignore_static: bool) -> tuple[np.ndarray, list[str]]:
    where = _where(rig)
    if rig.n_shapes == 0:
        raise LandmarkError(f"mesh {rig.name or '?'} has no blend shapes", **where,
                            fix="pick a mesh with blend shapes (--mesh) or add shapes to this one")
    if not np.isfinite(rig.deltas).all() or not np.isfinite(rig.neutral).all():
        raise LandmarkError("neutral or shape offsets contain NaN/inf", **where,
                            fix="repair the rig's geometry")
    mag = cand.displacement_magnitudes(rig.deltas)
    static = [rig.names[k] for k in cand.static_shapes(mag)]
    if static and not ignore_static:
        raise LandmarkError(f"shape(s) moving no vertex: {', '.join(static)}", **where,
                            fix="remove or fix these shapes, or pass --skip-static to leave them out")
    if len(static) == rig.n_shapes:  # --skip-static left nothing to cover (an IndexError deep in sampling)
        raise LandmarkError(f"every shape of mesh {rig.name or '?'} moves no vertex ({', '.join(static)}): "
                            "no landmark can represent any (normal offsets alone, or all-zero offsets?)",
                            **where, fix="pick a mesh whose shapes move its points (--mesh), or fix the "
                                         "shapes' offsets")
    return mag, static


def face_samples(rig: FaceRig, spacing: float | str = "auto", r: np.ndarray | None = None
                 ) -> tuple[float, np.ndarray]:
    """(spacing in metres, sample vertices ``[m]``): the vertices nearest the skin of the face sampled at
    ``spacing`` (:func:`sampling.sample_vertices` over the vertices some shape moves by at least
    :data:`visibility.FACE_SHARE` of its peak); "auto": :func:`sampling.sample_spacing` of the face size.
    ``r[K, n]``: eq. 2's relative displacement when the caller has it. The same for every epsilon, so a sweep
    computes them once (``compute_landmarks(samples=)``)."""
    if r is None:
        r = cand.relative_displacement(cand.displacement_magnitudes(rig.deltas))
    share = cand.moving_share(r)
    if isinstance(spacing, str):
        if spacing != "auto":
            raise LandmarkError(f"unknown spacing {spacing!r}", fix="pass metres, 'auto' or None")
        spacing = sampling.sample_spacing(face_size(rig.neutral, share))
    near = np.flatnonzero(share >= FACE_SHARE)
    samples = sampling.sample_vertices(rig.neutral, rig.triangles, spacing, near=near)
    if not len(samples):  # no skin point found (a few large faces lying on the grid's planes): the face's
        samples = near    # own vertices stand for themselves
    return float(spacing), samples


def nearest_sample(rig: FaceRig, samples: np.ndarray) -> np.ndarray:
    """Each vertex's nearest sample along the mesh's edges ``[n]`` (vertex indices; multi-source Dijkstra,
    so the two lips or lids are never each other's; vertices no edge path joins to a sample take the
    nearest one in space)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import dijkstra
    from scipy.spatial import cKDTree

    from ..mesh import edges

    e = edges(rig.triangles)
    length = np.linalg.norm(rig.neutral[e[:, 0]] - rig.neutral[e[:, 1]], axis=1)
    graph = sp.coo_matrix((np.maximum(length, 1e-12), (e[:, 0], e[:, 1])),
                          shape=(rig.n_vertices, rig.n_vertices)).tocsr()
    _, _, source = dijkstra(graph, directed=False, indices=np.asarray(samples), min_only=True,
                            return_predecessors=True)
    source = np.asarray(source, dtype=np.int64)
    lost = source < 0
    if lost.any():
        _, j = cKDTree(rig.neutral[samples]).query(rig.neutral[lost])
        source[lost] = np.asarray(samples)[j]
    return source


def _thin_candidates(rig: FaceRig, r: np.ndarray, c: np.ndarray, samples: np.ndarray, partner):
    """Restrict the candidates ``c[K, n]`` (in place) to the ``samples`` (:func:`face_samples`); each shape
    keeps at least its peak vertex (eq. 3 at epsilon = 1), and with ``partner[n]`` a mirror pair stays when
    either side is a sample. Returns the ``allowed[n]`` mask."""
    allowed = np.zeros(rig.n_vertices, dtype=bool)
    allowed[np.asarray(samples, dtype=np.int64)] = True
    allowed[np.argmax(r, axis=1)] = True  # every shape keeps a candidate (its peak)
    if partner is not None:
        allowed[partner[allowed & (partner >= 0)]] = True
    c &= allowed[None, :]
    return allowed


def _occluder(rig: FaceRig, origins: np.ndarray, spacing: float) -> np.ndarray:
    """The occluder triangles: the mesh clustered at ``spacing`` x :data:`sampling.OCCLUDER_SHARE`, with every
    ray origin and its first ring of triangles kept exact (the origins' normals are the mesh's, and nothing
    of the clustering lies between an origin and its first ring)."""
    ring = np.zeros(rig.n_vertices, dtype=bool)
    ring[origins] = True
    ring[rig.triangles[ring[rig.triangles].any(axis=1)].ravel()] = True
    cluster, reps = sampling.cluster_vertices(rig.neutral, rig.triangles, spacing * sampling.OCCLUDER_SHARE)
    return sampling.occluder_triangles(rig.triangles, cluster, reps, keep=np.flatnonzero(ring))


def lazy_costs(sub: np.ndarray, r: np.ndarray, alpha: float, weighting: str, multiplicity, lookup, evaluate,
               batch: int = 16, upper=None, min_batch: int = 0, cover_times: int = 1) -> np.ndarray:
    """Costs of eq. 5a for the cover sub-problem ``sub[K, n]``, evaluating visibility only where it matters.

    Every cost form is a non-increasing linear function of the vertex's visibility l_n, and
    :func:`usdface.landmarks.cover.reduce_set_cover` keeps only the cheapest vertex of each group of identical
    candidate sets. So per group, vertices are evaluated best-first (by their optimistic cost, l = 1) until no
    unevaluated vertex can be as cheap as the best evaluated one; the others keep a pessimistic cost (l = 0),
    provably no lower than the winner's, so the reduced problem - hence the optimum - equals the fully
    evaluated one. ``lookup() -> l[n]`` (NaN = not evaluated yet), ``evaluate(vertices)``; ``upper(vertices)
    -> [v]`` an optional cheap upper bound of l (e.g. the neutral pose's visibility, l being a minimum over
    poses): the optimistic cost is taken at it instead of l = 1, so far fewer vertices need evaluating.
    ``min_batch``: evaluate at least this many vertices per call (the best-ranked of every group first), for
    evaluators whose calls have a fixed cost (scenes rebuilt per call); it changes the work, not the result.
    ``cover_times``: the costs of an N-fold cover (:func:`set_cover_costs`); its callers evaluate every
    candidate first (a multi-cover may take several vertices of one candidate set).
    """
    if weighting == "count":
        return set_cover_costs(sub, r, "count", multiplicity)
    n = sub.shape[1]

    def cost_at_zero():
        return set_cover_costs(sub, np.zeros((1, n)), weighting, multiplicity, cover_times)

    cols = np.flatnonzero(sub.any(axis=0))
    if cols.size == 0:
        return cost_at_zero()
    # costs are per column: work on the candidate columns only (a body mesh has ~20x more vertices)
    sub_c, r_c = sub[:, cols], r[:, cols]
    mult_c = None if multiplicity is None else np.asarray(multiplicity)[cols]

    def cost_cols(vis_c):
        q = cand.landmark_quality(r_c, vis_c, alpha)
        return set_cover_costs(sub_c, q, weighting, mult_c, cover_times)

    bound = np.ones(cols.size)
    if upper is not None:
        bound = np.clip(upper(cols), 0.0, 1.0)
    optimistic = cost_cols(bound)
    _, group = np.unique(np.packbits(sub_c.T, axis=1), axis=0, return_inverse=True)
    group = group.ravel()
    while True:
        vis = lookup()
        known = ~np.isnan(vis[cols])
        exact = cost_cols(np.nan_to_num(vis[cols], nan=0.0))
        best = np.full(group.max() + 1, np.inf)
        np.minimum.at(best, group[known], exact[known])
        need = np.flatnonzero(~known & (optimistic <= best[group] + 1e-12))
        if need.size == 0:  # non-candidate columns cost what they cost at any visibility
            out = cost_at_zero()
            out[cols] = exact
            return out
        order = need[np.lexsort((cols[need], optimistic[need], group[need]))]
        g = group[order]
        start = np.r_[0, np.flatnonzero(g[1:] != g[:-1]) + 1]
        rank = np.arange(order.size) - np.repeat(start, np.diff(np.r_[start, order.size]))
        take = max(int(np.count_nonzero(rank < batch)), min(int(min_batch), order.size))
        evaluate(cols[order[np.argsort(rank, kind="stable")[:take]]])
        batch *= 4


def compute_landmarks(rig: FaceRig, epsilon: float = 0.5, alpha: float = 0.5, symmetric: bool = False,
                      multicover: int = 1, radius: float | None = None, camera=None, rays: int = 16,
                      backend: str = "scip", weighting: str = "quality", adaptive: bool = True,
                      share: float = 0.1, time_limit: float = 60.0, ignore_static: bool = False,
                      visibility: np.ndarray | None = None, spacing: float | str | None = "auto",
                      samples: np.ndarray | None = None, thin_candidates: bool = False,
                      one_shot: bool = False) -> LandmarkLayout:
    """Compute a compact landmark layout for ``rig`` (Zell & McDonnell 2022, secs. 3.1-3.3).

    Parameters
    ----------
    rig : FaceRig with ``neutral[n, 3]`` and ``deltas[K, n, 3]`` in metres.
    epsilon : relative-displacement threshold of the candidates (eq. 3), in (0, 1].
    alpha : weight of the visibility against the relative displacement in the quality, eq. (1)
        ``q = (1 - alpha) r + alpha l``, in [0, 1].
    symmetric : mirror-symmetric layout (falls back to asymmetric, with a warning, when infeasible).
    multicover : maximum landmarks per shape of the adaptive multi-cover (Algorithm 1); 1 = single cover.
    radius : metres; vertices this close to a chosen landmark leave the candidates of later rounds. None
        (default): :func:`.multicover.exclusion_radius`, 2.4 % of the face size (1 cm on a human head), the
        same at every epsilon and in symmetric mode; the value used is ``layout.problem["radius"]``.
    camera : optional [3] camera position (metres, internal Y-up frame) for the known-camera visibility;
        vertices the camera cannot see in some pose are then not candidates.
    rays : hemisphere rays per vertex for the ambient-occlusion visibility.
    backend : OR-tools MIP backend: scip (default, measured fastest to a proof), cbc, highs, cp-sat.
    weighting : cost form of eq. 5a: quality (count first, quality breaks ties), count, paper.
    adaptive, share : the paper's 10%-of-shapes heuristic in the multi-cover (off: cover every shape
        ``multicover`` times where candidates remain).
    one_shot : the paper's other multi-cover (sec. 3.3.2): one ILP covering every shape ``min(multicover,
        |C_k|)`` times (:func:`.multicover.one_shot_multicover`), the cheapest such layout, instead of the
        rounds of Algorithm 1; no exclusion radius (refused with a ``radius``) and no 10 % heuristic, so, as
        the paper warns, it may take neighbouring vertices ("Distance Off", Fig. 4). Visibility is then
        ray cast at every candidate (a multi-cover may take several of one candidate set).
    ignore_static : leave shapes that move no vertex out (reported in ``uncoverable``) instead of raising.
    visibility : precomputed l_n ``[n]`` (skips the ray casting; used by the evaluation sweep).
    spacing : metres between points on the skin sampled for the visibility (:mod:`.sampling`): every
        vertex takes the global visibility of its nearest sample (along the mesh), ray cast against the mesh
        clustered at a quarter of the spacing, so the ray casting does not grow with the mesh resolution.
        "auto" (default): :func:`sampling.sample_spacing` of the face size (8 mm on a human head); None:
        every vertex ray cast against the full mesh (the exact eq. 4 at the mesh's own resolution).
    thin_candidates : also restrict the set cover's candidates to the samples (each shape keeps its peak
        vertex): the same candidate points at every resolution, hence resolution-independent layouts, but
        fewer places to choose from (measured: worse reconstruction at 10-11 landmarks; off by default).
    samples : precomputed sample vertices at ``spacing`` (:func:`face_samples`; a sweep computes them once).

    Returns a :class:`LandmarkLayout`. Raises :class:`LandmarkError` on a rig without shapes, epsilon outside
    (0, 1], a radius that is no length >= 0, or a shape that moves no vertex (unless ``ignore_static``).
    """
    if not isinstance(rig, FaceRig):      # an avatar's path (as usdface.compute_landmarks takes it) died with
        raise LandmarkError(             # AttributeError: 'str' object has no attribute 'source'
            f"usdface.landmarks.compute_landmarks takes a FaceRig, not {type(rig).__name__} ({rig!r:.60})",
            fix="pass read_avatar(PATH).mesh('Head') (docs/landmarks.md), or call usdface.compute_landmarks, "
                "which also takes an avatar or its file")
    with naming(rig):   # every refusal names the rig's file and prim, before any work
        eps = cand.check_epsilon(epsilon)
        a = cand.check_alpha(alpha)
        rays = cand.check_rays(rays)
        if weighting not in WEIGHTINGS:
            raise LandmarkError(f"unknown weighting {weighting!r}",
                                fix=f"use one of {', '.join(WEIGHTINGS)}")
        if backend not in BACKENDS:
            raise LandmarkError(f"unknown solver backend {backend!r}",
                                fix=f"use one of {', '.join(BACKENDS)}")
        if isinstance(multicover, bool) or not isinstance(multicover, int | np.integer) or multicover < 1:
            # 2.5 was taken as 2 and True as 1; "x" died in int()
            raise LandmarkError(f"multicover {multicover!r:.30} is not a whole number >= 1",
                                fix="pass the maximum landmarks per shape, e.g. multicover=3 (--multicover; "
                                    "1 = a single cover)")
        if not _number_in(share, 0.0, 1.0):       # -1 and 0 were taken, "x" died after the ray casting
            raise LandmarkError(f"share {share!r:.30} is not in (0, 1]",
                                fix="pass the adaptive multi-cover's share of the shapes one landmark may "
                                    "serve, e.g. share=0.1 (the paper's 10 %)")
        if not _number_in(time_limit, 0.0, np.inf):   # a negative one: SCIP printed errors, no layout
            raise LandmarkError(f"time_limit {time_limit!r:.30} is not a number of seconds > 0",
                                fix="pass the solver's time limit in seconds, e.g. time_limit=60 (the "
                                    "default)")
        check_one_shot(one_shot, multicover, adaptive, radius)
        if radius is not None:                 # -1 and 'x' were taken without a word (the CLI refuses -1)
            try:
                ok = (not isinstance(radius, str | bool) and bool(np.isfinite(float(radius)))
                      and float(radius) >= 0.0)
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise LandmarkError(f"multi-cover radius {radius!r:.60} is not a length >= 0 in metres",
                                    fix="pass metres >= 0 (--radius), or None (the default: 2.4 % of the "
                                        "face size, 1 cm on a human head)")
        if not (spacing is None or (isinstance(spacing, str) and spacing == "auto")
                or _number_in(spacing, 0.0, np.inf)):     # a list died in float()
            raise LandmarkError(f"candidate spacing {spacing!r} is not a positive length in metres",
                                fix="pass metres > 0, 'auto' (2 % of the face size) or None (every vertex)")
        if camera is not None:                 # a string ('0,1.6,0.35', the CLI's form) died in float()
            try:
                camera = np.asarray(camera, dtype=np.float64).reshape(3)
                ok = bool(np.isfinite(camera).all())
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise LandmarkError(f"camera {camera!r} is not a position", fix="pass three finite numbers "
                                    "(x, y, z) in metres, usdface's Y-up frame, e.g. camera=(0, 1.6, 0.35)")
    mag, static = _validate(rig, ignore_static)
    timings: dict[str, float] = {}
    warnings: list[str] = []
    t0 = time.perf_counter()
    r = cand.relative_displacement(mag)
    c = cand.candidate_sets(r, eps)
    if not one_shot:
        radius = exclusion_radius(rig.neutral, r) if radius is None else float(radius)
    partner = primary = None
    if symmetric:
        partner = mirror_pairs(rig.neutral)
        primary = primary_side(rig.neutral, partner)
    sample_spacing, allowed = None, None
    if spacing is not None and (thin_candidates or visibility is None):
        if samples is None:
            sample_spacing, samples = face_samples(rig, spacing, r)
        elif isinstance(spacing, str):
            sample_spacing = sampling.sample_spacing(face_size(rig.neutral, cand.moving_share(r)))
        else:
            sample_spacing = float(spacing)
        if thin_candidates:
            allowed = _thin_candidates(rig, r, c, samples, partner)
    need = np.flatnonzero(c.any(axis=0))
    if partner is not None:
        need = np.unique(np.concatenate([need, partner[need][partner[need] >= 0]]))
    occluder, owner, origins = rig.triangles, None, None
    if samples is not None and visibility is None:  # ray casting ahead: against the clustered mesh
        if thin_candidates or camera is not None:  # each candidate its own ray origin (the camera test is
            occluder = _occluder(rig, need, sample_spacing)  # binary: a neighbour's answer would be a guess)
        else:
            owner = nearest_sample(rig, samples)
            origins = np.unique(owner[need])  # the samples that stand for the candidates
            occluder = _occluder(rig, origins, sample_spacing)
    timings["candidates"] = time.perf_counter() - t0
    pose_vis = None
    if visibility is not None:
        known = np.asarray(visibility, dtype=np.float64).copy()

        def lookup_plain():
            return known

        def evaluate_plain(vertices):
            return None

        def upper_plain(vertices):
            return np.nan_to_num(known[vertices], nan=1.0)
    else:
        pose_vis = PoseVisibility(rig.neutral, occluder, rig.deltas, rays, camera, magnitudes=mag,
                                  bases=pose_bases(rig.names))
        at = np.arange(rig.n_vertices) if owner is None else owner  # a vertex sees what its sample sees

        def lookup_plain():
            return pose_vis.values[at]

        def evaluate_plain(vertices):
            t = time.perf_counter()
            pose_vis(np.unique(at[vertices]))
            timings["visibility"] = timings.get("visibility", 0.0) + time.perf_counter() - t

        def upper_plain(vertices):
            t = time.perf_counter()
            out = pose_vis.upper_bound(at[vertices])
            timings["visibility"] = timings.get("visibility", 0.0) + time.perf_counter() - t
            return out
    min_batch = 0 if pose_vis is None else pose_vis.batch_hint
    if owner is not None and weighting != "count":
        # a few hundred samples stand for every candidate: casting them all in one pass (one scene per pose)
        # is cheaper than the lazy passes, and gives the same values
        evaluate_plain(need)
    if camera is not None:  # a vertex the camera cannot see in some pose is no candidate
        evaluate_plain(need)
        c &= np.nan_to_num(lookup_plain(), nan=0.0)[None, :] > 0.0
        face = rig.neutral[need] if len(need) else rig.neutral
        centre, size = face.mean(axis=0), float(np.linalg.norm(np.ptp(face, axis=0)))
        far = float(np.linalg.norm(np.asarray(camera, dtype=np.float64) - centre))
        if not c.any() or far > 20 * size:   # behind the head, or not in metres of the internal frame
            warnings.append(f"the camera at {', '.join(f'{x:g}' for x in camera)} m sees "
                            f"{'no candidate of any shape' if not c.any() else 'the face from afar'}: "
                            f"{far:.3g} m from the face's centre "
                            f"({', '.join(f'{x:.3f}' for x in centre + 0.0)} m, "
                            f"the face {size:.3g} m across); --camera is metres in usdface's Y-up frame")

    def solve(cc, cost):
        return solve_set_cover(cc, cost, backend=backend, time_limit=time_limit)

    times = int(multicover) if one_shot else 1   # the costs' cover count (eq. 5a's quality term's scale)
    if one_shot and weighting != "count":
        # the lazy evaluation relies on the single cover keeping one vertex per candidate set: cast them all
        evaluate_plain(need)

    def cover(cc, costs, part=None, coverage=None):
        """Algorithm 1's rounds, or the one-shot ILP: (selected [m], round of each [m], solutions); both
        count a shape's landmarks on ``coverage`` (the mesh's candidates; a mirrored pair may be two)."""
        if one_shot:
            counts = cc if part is None else pair_candidate_counts(coverage, part, cc)
            sol = one_shot_multicover(counts, costs(cc), multicover, backend=backend, time_limit=time_limit)
            return sol.selected, np.ones(sol.selected.size, dtype=np.int64), [sol]
        return adaptive_multicover(cc, costs, rig.neutral, multicover, solve, radius,
                                   share if adaptive else None, part, coverage=coverage)

    t0 = time.perf_counter()
    vis_before = timings.get("visibility", 0.0)
    result, fell_back = None, False
    if symmetric:
        # relative to each shape's own peak (a peak on an unpaired vertex must not be renormalised away)
        peak = np.maximum(mag.max(axis=1, keepdims=True), 1e-300)
        sym_r = symmetric_magnitudes(mag, partner, primary) / peak
        sym_c = cand.candidate_sets(sym_r, eps)
        if allowed is not None:
            sym_c &= allowed[None, :]
        safe = np.where(partner >= 0, partner, np.arange(rig.n_vertices))

        def lookup_sym():
            v = lookup_plain()
            return np.where(primary, np.minimum(v, v[safe]), 0.0)  # NaN propagates: not evaluated

        def evaluate_sym(vertices):
            evaluate_plain(np.concatenate([vertices, safe[vertices]]))

        def upper_sym(vertices):
            bound = np.minimum(upper_plain(vertices), upper_plain(safe[vertices]))
            return np.where(primary[vertices], bound, 0.0)

        if camera is not None:
            sym_c &= np.nan_to_num(lookup_sym(), nan=0.0)[None, :] > 0.0
        lost = [rig.names[k] for k in np.flatnonzero(c.any(axis=1) & ~sym_c.any(axis=1))]
        fell_back = bool(lost)
        if lost:
            warnings.append("symmetric layout infeasible (no mirrored candidate for "
                            f"{', '.join(lost)}); fell back to an asymmetric layout")
        else:
            mult = np.where(partner == np.arange(rig.n_vertices), 1.0, 2.0)

            def sym_costs(sub):
                return lazy_costs(sub, sym_r, a, weighting, mult, lookup_sym, evaluate_sym, upper=upper_sym,
                                  min_batch=min_batch // 2, cover_times=times)

            sel, rounds, sols = cover(sym_c, sym_costs, partner, coverage=c)
            vertices = np.concatenate([sel, partner[sel]])  # mirror, keeping each pair's round
            vertices, first = np.unique(vertices, return_index=True)
            result = (vertices, np.concatenate([rounds, rounds])[first], sols)
    if result is None:
        def plain_costs(sub):
            return lazy_costs(sub, r, a, weighting, None, lookup_plain, evaluate_plain, upper=upper_plain,
                              min_batch=min_batch, cover_times=times)

        result = cover(c, plain_costs)
    vertices, rounds, sols = result
    evaluate_plain(vertices)
    vis = np.nan_to_num(lookup_plain(), nan=0.0)
    timings["cover"] = time.perf_counter() - t0 - (timings.get("visibility", 0.0) - vis_before)
    coverage = c[:, vertices].T
    covered = coverage.any(axis=0)
    uncoverable = [n for k, n in enumerate(rig.names) if not covered[k]]
    worst = max(sols, key=lambda s: (_STATUS_RANK.get(s.status, 3), s.gap)) if sols else None
    head: CoverSolution | None = sols[0] if sols else None
    return LandmarkLayout(
        vertices=vertices, positions=rig.neutral[vertices], coverage=coverage, rounds=rounds,
        visibility=vis[vertices], shape_names=list(rig.names), epsilon=eps, alpha=a,
        symmetric=bool(symmetric and not fell_back), multicover=int(multicover),
        status=worst.status if worst else "optimal", gap=max((s.gap for s in sols), default=0.0),
        objective=float(sum(s.objective for s in sols)), weighting=weighting, backend=backend,
        camera=None if camera is None else [float(x) for x in camera], uncoverable=uncoverable,
        warnings=warnings + ([f"static shapes left out: {', '.join(static)}"] if static else []),
        timings=timings,
        problem={"shapes": int(rig.n_shapes), "vertices": int(rig.n_vertices), "candidates": int(need.size),
                 "visibility_evaluated": int(np.count_nonzero(~np.isnan(  # ray-cast vertices (samples)
                     lookup_plain() if pose_vis is None else pose_vis.values))),
                 "reduced": list(head.reduced) if head else [0, 0], "rounds": len(sols),
                 "spacing": sample_spacing, "radius": radius, "one_shot": bool(one_shot),
                 "samples": (int(allowed.sum()) if allowed is not None
                             else None if origins is None else int(origins.size)),
                 "occluder_triangles": int(len(occluder)),
                 "solve_seconds": [round(s.seconds, 4) for s in sols]})
