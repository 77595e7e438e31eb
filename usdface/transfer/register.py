"""Rigid registration with scaling of the capture face onto the avatar face (Menzel et al. 2022, sec. 3.3).

Two stages, both on arrays in internal metres / Y-up (the avatar reader has already applied the
stage's ``metersPerUnit``, ``upAxis`` and every ancestor transform, so stage metadata is accounted for there):

1. :func:`motion_initialiser` - a global initialiser that needs no manual points: every ARKit shape that both
   rigs carry moves a recognisable part of the face (an eyelid, a mouth corner, a brow), so the
   motion-weighted centroid of each shape is a landmark that exists on both meshes, whatever their
   topology, units, orientation and placement in a full-body scene. A weighted similarity (Umeyama) between
   the two landmark sets gives scale, rotation and translation.
2. :func:`register_icp` - point-to-point ICP with scaling (Umeyama's similarity of each iteration's pairs)
   from the capture neutral to the avatar's moving face, coarse to fine: onto the exact closest points of
   the face's *surface* when its triangles are given (:func:`register_icp_surface`; the same surface gives
   the same placement at every resolution of the mesh), else Open3D ``registration_icp`` onto its points.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import RegistrationError
from ..motion import moving_vertices, peak_motion
from ..natives import open3d
from .surface import SurfaceQuery

__all__ = ["Similarity", "Registration", "motion_landmarks", "similarity_from_pairs", "motion_initialiser",
           "register_icp", "register_icp_surface", "face_surface", "register_face"]


@dataclass
class Similarity:
    """``x -> scale * rotation @ x + translation`` (rotation[3,3] proper, translation[3] metres)."""

    scale: float = 1.0
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def apply(self, points) -> np.ndarray:
        """Transform points ``[...,3]``."""
        return self.scale * np.asarray(points) @ self.rotation.T + self.translation

    def apply_vectors(self, vectors) -> np.ndarray:
        """Transform offsets/deltas ``[...,3]`` (linear part only)."""
        return self.scale * np.asarray(vectors) @ self.rotation.T

    def inverse_vectors(self, vectors) -> np.ndarray:
        """The inverse of :meth:`apply_vectors`: offsets ``[...,3]`` back into the source frame."""
        return np.asarray(vectors) @ self.rotation / self.scale

    def matrix(self) -> np.ndarray:
        """Homogeneous ``[4,4]`` (column vectors)."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    @classmethod
    def from_matrix(cls, m) -> Similarity:
        m = np.asarray(m, dtype=np.float64)
        s = float(np.cbrt(np.linalg.det(m[:3, :3])))
        return cls(s, m[:3, :3] / s, m[:3, 3].copy())

    def as_dict(self) -> dict:
        return {"scale": self.scale, "rotation": self.rotation.tolist(),
                "translation_m": self.translation.tolist()}


@dataclass
class Registration:
    """Result of :func:`register_face`: the similarity, the inlier RMS residual (m), the fraction of capture
    vertices with an avatar point within the final correspondence distance (``fitness``), and which
    initialiser won."""

    transform: Similarity
    residual: float
    fitness: float
    initialiser: str
    max_distance: float
    target: np.ndarray | None = None

    def rank(self) -> tuple[float, float]:
        """The order of two registrations of a face, higher is better: more of it within the final distance
        (fitness to two decimals), then the lower ICP residual."""
        return round(self.fitness, 2), -self.residual

    def as_dict(self) -> dict:
        return {**self.transform.as_dict(), "residual_m": self.residual, "fitness": self.fitness,
                "initialiser": self.initialiser, "max_distance_m": self.max_distance}


def motion_landmarks(neutral, deltas, *, power: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """One landmark per shape: the centroid of ``neutral[n,3]`` weighted by ``|deltas[k]|^power``.

    Returns ``(landmarks[K,3], strength[K])`` where strength is the shape's largest vertex motion (m); shapes
    that do not move get strength 0.
    """
    d = np.asarray(deltas, dtype=np.float64)
    # one [K,n] array, its norms and their powers in place (at 225k vertices x 51 shapes each copy is 92 MB;
    # the squares themselves are not the norms squared to the last bit, and the registration follows them)
    w = np.einsum("knc,knc->kn", d, d)
    np.sqrt(w, out=w)
    top = w.max(axis=1)
    w = np.square(w, out=w) if power == 2.0 else w ** power     # (``** 2`` is numpy's square)
    tot = w.sum(axis=1)
    lm = (w @ np.asarray(neutral)) / np.maximum(tot, 1e-300)[:, None]
    return lm, np.where(tot > 0, top, 0.0)


def similarity_from_pairs(src, dst, weights=None) -> Similarity:
    """Weighted least-squares similarity ``dst ~ s R src + t`` (Umeyama 1991); ``src, dst[m,3]``."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    mu_s, mu_d = w @ src, w @ dst
    a, b = src - mu_s, dst - mu_d
    cov = (b * w[:, None]).T @ a
    u, sig, vt = np.linalg.svd(cov)
    d = np.ones(3)
    d[2] = np.sign(np.linalg.det(u @ vt)) or 1.0
    rot = u @ np.diag(d) @ vt
    var_s = float(w @ np.einsum("ij,ij->i", a, a))
    s = float((sig * d).sum() / max(var_s, 1e-300))
    return Similarity(s, rot, mu_d - s * rot @ mu_s)


def motion_initialiser(capture_neutral, capture_deltas, avatar_points, avatar_deltas, *,
                       avatar_landmarks=None) -> Similarity:
    """Global initial similarity from capture space to avatar space, from shape-motion landmarks.

    ``capture_deltas[K,n,3]`` and ``avatar_deltas[K,m,3]`` must list the same K shapes in the same order
    (the generic template shapes on the capture mesh and the avatar's own generic shapes);
    ``avatar_landmarks``: :func:`motion_landmarks` of the avatar side when the caller has them. Raises
    :class:`RegistrationError` with fewer than 4 shapes that move on both.
    """
    lc, sc = motion_landmarks(capture_neutral, capture_deltas)
    la, sa = (motion_landmarks(avatar_points, avatar_deltas) if avatar_landmarks is None
              else avatar_landmarks)
    ok = (sc > 0) & (sa > 0)
    if ok.sum() < 4:
        raise RegistrationError(f"only {int(ok.sum())} shapes move on both the capture and the avatar face; "
                                "need at least 4 to place the capture",
                                fix="give the avatar ARKit-named blend shapes that move the face")
    return similarity_from_pairs(lc[ok], la[ok])


def register_icp(source, target, init: Similarity, *, scales=(0.08, 0.03, 0.012), iterations: int = 40,
                 with_scaling: bool = True, surface=None) -> tuple[Similarity, float, float, float]:
    """Open3D point-to-point ICP with scaling, coarse to fine.

    ``source[n,3]`` (capture neutral), ``target[m,3]`` (avatar face points); correspondence distances are
    ``scales`` times the diagonal of the initially placed source. Returns ``(similarity, inlier_rmse_m,
    fitness, final_max_distance_m)``. ``surface``: ``(points[m,3], triangles[t,3])``, the avatar face's
    surface, or a :class:`usdface.transfer.surface.SurfaceQuery` of it (built once by a caller that registers
    from several starts): the pairs are its exact closest points instead (:func:`register_icp_surface`;
    ``target`` unused).
    """
    if surface is not None:
        query = surface if isinstance(surface, SurfaceQuery) else SurfaceQuery(*surface)
        return register_icp_surface(source, query.points, query.triangles, init, scales=scales,
                                    iterations=iterations, with_scaling=with_scaling, query=query)
    o3d = open3d()

    reg = o3d.pipelines.registration
    src = np.asarray(source, dtype=np.float64)
    tgt = np.asarray(target, dtype=np.float64)
    origin = tgt.mean(axis=0)
    pcs = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
    pct = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt - origin))
    placed = init.apply(src)
    diag = float(np.linalg.norm(placed.max(axis=0) - placed.min(axis=0)))
    shift = np.eye(4)
    shift[:3, 3] = -origin
    current = shift @ init.matrix()
    est = reg.TransformationEstimationPointToPoint(with_scaling=with_scaling)
    res = None
    dist = diag
    for f in scales:
        dist = f * diag
        res = reg.registration_icp(pcs, pct, dist, current, est,
                                   reg.ICPConvergenceCriteria(relative_fitness=1e-9, relative_rmse=1e-9,
                                                              max_iteration=iterations))
        if res.fitness > 0:
            current = np.asarray(res.transformation)
    unshift = np.eye(4)
    unshift[:3, 3] = origin
    sim = Similarity.from_matrix(unshift @ current)
    # Open3D sums the residual over threads in a varying order: its last bits differ run to run (the
    # transformation does not); 12 significant digits make the recorded figure - and a layer written with
    # SOURCE_DATE_EPOCH - the same every run
    return sim, float(f"{res.inlier_rmse:.12g}"), float(res.fitness), dist


def register_icp_surface(source, points, triangles, init: Similarity, *, scales=(0.08, 0.03, 0.012),
                         iterations: int = 40, with_scaling: bool = True, query: SurfaceQuery | None = None
                         ) -> tuple[Similarity, float, float, float]:
    """Point-to-point ICP with scaling onto a triangle surface, coarse to fine: each iteration pairs every
    ``source[n,3]`` point (capture neutral, as placed) with its exact closest point on the surface
    ``points[m,3]``/``triangles[t,3]`` (:class:`usdface.transfer.surface.SurfaceQuery`), keeps the pairs
    within the correspondence distance (``scales`` times the diagonal of the initially placed source) and
    moves the source by their least-squares similarity (Open3D's ``TransformationEstimationPointToPoint``,
    the step of its ``registration_icp``, on these pairs; a rigid motion without ``with_scaling``), until
    the fitness and inlier RMS residual change by less than 1e-9 (as Open3D's ``registration_icp``) or
    ``iterations`` pass. Returns ``(similarity, inlier_rmse_m, fitness,
    final_max_distance_m)``, as :func:`register_icp`.

    The target is the surface, not points sampled on it: a sampled target's nearest points sit up to half
    its spacing from the surface's closest points, in a pattern that follows the mesh's triangles, and the
    placement followed it (dev1's head and the same head subdivided twice - the same surface - were placed
    0.13 % apart in scale and 0.08 degrees in rotation, which the avatar prior carries into the fit: issue
    12's same answer 1.3 -> 2.6 % at stop 47). On the surface the two are placed alike to 1e-6.

    ``query``: the surface's :class:`SurfaceQuery` when the caller has it (its closest-point scene, built
    once for every start: the twice-subdivided head's face has 450k triangles)."""
    o3d = open3d()
    est = o3d.pipelines.registration.TransformationEstimationPointToPoint(with_scaling=with_scaling)

    def corres(n):
        return o3d.utility.Vector2iVector(np.repeat(np.arange(n, dtype=np.int32)[:, None], 2, axis=1))

    src = np.asarray(source, dtype=np.float64)
    query = SurfaceQuery(points, triangles) if query is None else query
    placed = init.apply(src)
    diag = float(np.linalg.norm(placed.max(axis=0) - placed.min(axis=0)))
    current, rmse, fitness, dist = init, 0.0, 0.0, diag
    for f in scales:
        dist = f * diag
        previous = None
        for _ in range(iterations + 1):         # the last pass measures the last move's result
            x = current.apply(src)
            _, _, closest, d = query.closest_points(x)
            pairs = d <= dist
            fitness = float(pairs.mean())
            rmse = float(np.sqrt(np.mean(np.square(d[pairs])))) if pairs.any() else 0.0
            if previous is not None and abs(previous[0] - fitness) < 1e-9 and abs(previous[1] - rmse) < 1e-9:
                break
            previous = (fitness, rmse)
            if pairs.sum() < 3:
                break
            # the step: Open3D's own estimator of registration_icp on the pairs (Umeyama; rigid without
            # with_scaling), about the pairs' target centroid for conditioning
            origin = closest[pairs].mean(axis=0)
            pcs = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(x[pairs] - origin))
            pct = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(closest[pairs] - origin))
            m = np.asarray(est.compute_transformation(pcs, pct, corres(int(pairs.sum()))))
            shift = np.eye(4)
            shift[:3, 3] = origin
            step = shift @ m
            step[:3, 3] -= step[:3, :3] @ origin
            current = Similarity.from_matrix(step @ current.matrix())
    return current, float(f"{rmse:.12g}"), fitness, dist


def face_surface(avatar_points, avatar_triangles, avatar_peak) -> SurfaceQuery | None:
    """The avatar face *surface* :func:`register_face` registers onto, as a closest-point scene
    (:class:`usdface.transfer.surface.SurfaceQuery`): the triangles of ``avatar_triangles[t,3]`` with a
    moving corner (:func:`usdface.motion.moving_vertices` of ``avatar_peak[n]``, the shapes' peak motion, on
    ``avatar_points[n,3]``; every triangle when fewer than 10 vertices move). As a surface, the union is the
    same at every resolution of the mesh, where "every corner" grows with each subdivision. None when there
    is no such triangle. Built once by a caller that registers several capture faces on one avatar face
    (the person's neutral and the template's: the twice-subdivided head's face has 450k triangles)."""
    ap = np.asarray(avatar_points, dtype=np.float64)
    tri = np.asarray(avatar_triangles)
    moving = moving_vertices(avatar_peak, ap)
    face_tri = tri[moving[tri].any(axis=1)] if moving.sum() >= 10 else tri
    return SurfaceQuery(ap, face_tri) if len(face_tri) else None


def register_face(capture_neutral, capture_deltas, avatar_points, avatar_deltas, *, avatar_triangles=None,
                  capture_triangles=None, min_fitness: float = 0.6, max_residual_ratio: float = 0.05,
                  path=None, initial: Similarity | None = None, target=None,
                  avatar_peak=None, avatar_landmarks=None, avatar_mesh: str | None = None,
                  surface: SurfaceQuery | None = None) -> Registration:
    """Place the capture on the avatar face: motion initialiser, then ICP with scaling onto the avatar's face
    vertices (those that move in any shape). Unless that converges (95 % of the capture within the final
    distance, residual below 2 % of the face size), also tries the identity-rotation centroid initialiser and
    keeps the better result (more fitness, then lower residual).

    With ``avatar_triangles`` the ICP target is the avatar face *surface* (the triangles with a moving
    corner), its exact closest points (:func:`register_icp_surface`): a coarse avatar does not bias scale
    and residual by its vertex spacing, and a finer mesh of the same surface is placed the same
    (``capture_triangles`` is accepted and unused since stop 49: it set the density of the points sampled on
    the surface before). ``target`` (points) is then only the fallback placement's extent and centroid.

    Raises :class:`RegistrationError` (with the residual and fitness) when the capture does not overlap the
    avatar face after registration: fitness below ``min_fitness`` or residual above ``max_residual_ratio``
    times the face's size.

    ``avatar_peak[n]``: :func:`usdface.motion.peak_motion` of ``avatar_deltas`` when the caller has it (the
    pipeline registers the person and the template on the same face: computed once), ``avatar_landmarks``
    its :func:`motion_landmarks` (the same: a ``[K,n]`` pass over a production face). ``avatar_mesh``: the
    mesh's name for the error (e.g. ``"/Avatar/Head of avatar.usdc"``: a ``--face-mesh`` choice shows).
    ``surface``: :func:`face_surface` of ``avatar_points``, ``avatar_triangles`` and the peak motion when the
    caller has it (the same: its closest-point scene built once for both registrations).
    """
    cn = np.asarray(capture_neutral, dtype=np.float64)
    ap = np.asarray(avatar_points, dtype=np.float64)
    peak = peak_motion(avatar_deltas) if avatar_peak is None else avatar_peak
    moving = moving_vertices(peak, ap)   # float noise of an export: no motion
    try:   # the global initialiser
        landmarks, no_landmarks = motion_initialiser(cn, capture_deltas, ap, avatar_deltas,
                                                     avatar_landmarks=avatar_landmarks), None
    except RegistrationError as exc:
        landmarks, no_landmarks = None, exc
    given = target is not None
    target = np.asarray(target, dtype=np.float64) if given else (ap[moving] if moving.sum() >= 10 else ap)
    if surface is None and avatar_triangles is not None:
        # the face surface: the triangles the shapes move; one closest-point scene for every start below
        surface = face_surface(ap, avatar_triangles, peak)
    if surface is not None and not given:
        # the ICP pairs the capture with the surface's exact closest points; ``target`` (its vertices) gives
        # the fallback placement's extent and centroid
        from ..mesh import index_set

        target = ap[index_set(surface.triangles, len(ap))]
    # ``initial``: a placement known to be close (the person's neutral, in the same capture frame as the
    # template); tried first, refined by the same ICP
    candidates = [("person's registration", initial)] if initial is not None else []
    if landmarks is not None:
        candidates.append(("shape-motion landmarks", landmarks))
    elif not candidates and moving.sum() < 10:
        raise no_landmarks
    ext_c = np.linalg.norm(cn.max(axis=0) - cn.min(axis=0))
    ext_a = np.linalg.norm(target.max(axis=0) - target.min(axis=0))
    s0 = ext_a / max(ext_c, 1e-300)
    shift = target.mean(axis=0) - s0 * cn.mean(axis=0)
    candidates.append(("centroid + extent", Similarity(s0, np.eye(3), shift)))
    best = None
    size0 = float(np.linalg.norm(np.ptp(cn, axis=0)))
    for name, init in candidates:
        sim, rmse, fit, dist = register_icp(cn, target, init, surface=surface)
        reg = Registration(sim, rmse, fit, name, dist, target)
        if best is None or reg.rank() > best.rank():
            best = reg
        if fit >= 0.95 and rmse < 0.02 * size0 * sim.scale:
            break  # the landmark initialiser converged: no need for the fallback
    result = best
    size = float(np.linalg.norm(np.ptp(result.transform.apply(cn), axis=0)))
    # a capture shrunk to a point is no placement whatever its residual: collapsed onto one target point it
    # has fitness 1 and residual exactly 0 (Pixar's 10 cm test plane under dev1's capture: scale 1e-28,
    # accepted, and the template's registration from it then crashed in Open3D). Below a thousandth of the
    # target's size only: a capture shrunk to a few mm on a mouth mesh (dev1 --face-mesh Mouth, 3.6 mm on
    # 99 mm) goes on to the error that names the skin meshes to pick
    collapsed = size < 1e-3 * ext_a
    if collapsed or result.fitness < min_fitness or result.residual > max_residual_ratio * size:
        text = _no_overlap_text(result, size, size0, ext_a, min_fitness, max_residual_ratio)
        if avatar_mesh:        # which avatar mesh it was registered against (a --face-mesh choice, say)
            text = text.replace("the avatar face mesh", f"the avatar mesh {avatar_mesh}", 1).replace(
                "the avatar face after", f"the avatar mesh {avatar_mesh} after", 1)
        raise RegistrationError(
            text, path=path,
            fix="check that the avatar mesh registered against is the face's skin (pick it with "
                "--face-mesh, not the mouth, teeth or eyes), that the capture and the avatar show the same "
                "kind of face and that the avatar's blend shapes are ARKit-named")
    return result


def _no_overlap_text(result: Registration, size: float, size0: float, target_size: float, min_fitness: float,
                     max_residual_ratio: float) -> str:
    """What failed in :func:`register_face`'s final check, in words: the capture shrunk to a point (ICP with
    scaling onto a mesh much smaller than the face, e.g. the mouth interior: a tiny residual and every vertex
    "within" the distance, which is no overlap at all), too few capture vertices near the face, or too large
    a residual."""
    mm = 1000.0
    if size < 0.2 * target_size:
        return (f"registration shrank the capture to a point ({size * mm:.2f} mm across, scale "
                f"{result.transform.scale:.3g}; it is {size0 * mm:.0f} mm across) instead of placing it on "
                f"the avatar face mesh ({target_size * mm:.0f} mm across): the capture and that mesh do not "
                f"show the same face")
    if result.fitness < min_fitness:
        return (f"the capture does not overlap the avatar face after registration: only "
                f"{result.fitness * 100:.0f}% of capture vertices lie within "
                f"{result.max_distance * mm:.1f} mm of it (need {min_fitness * 100:.0f}%)")
    return (f"the capture does not fit the avatar face after registration: residual "
            f"{result.residual * mm:.2f} mm is more than {max_residual_ratio * 100:.0f}% of the placed "
            f"capture's size ({size * mm:.0f} mm)")
