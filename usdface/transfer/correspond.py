"""Correspondence map M between the avatar face and the capture mesh (Menzel et al. 2022, sec. 3.3).

1. :func:`nonrigid_register` - a face on the capture topology (the template's neutral or the person's,
   whichever lies closer to the avatar: :func:`usdface.transfer.face_map.choose_source`), already placed by
   the similarity of :mod:`usdface.transfer.register`, is deformed onto the avatar face surface: alternate
   closest points on the avatar (Open3D ``RaycastingScene``; pairs rejected by distance and normal tests) and
   a sparse least-squares solve that keeps the displacement smooth (Laplacian stiffness, relaxed over the
   iterations).
2. :func:`correspondence_map` - for every avatar face-mesh vertex, the closest point on the registered capture
   surface (triangle + barycentric coordinates). The face region is computed automatically: the vertex is
   within a distance tolerance of the capture surface, its normal agrees with the capture triangle's normal,
   and the closest point is not clamped onto the capture's open border or a hole (eyes, mouth).

The map is a function of the avatar's face mesh, the capture template and the person's neutral only, so it is
computed once per avatar and capture and cached (:func:`save_correspondence` / :func:`load_correspondence`,
keyed by a digest of them).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from ..errors import InputFileError
from ..mesh import spd_lu, vector_lengths
from .surface import (
    SurfaceQuery,
    boundary_vertices,
    cotangent_laplacian,
    mean_edge_length,
    triangle_normals,
    vertex_normals,
)

__all__ = ["Correspondence", "PosedSurface", "nonrigid_register", "correspondence_map", "geometry_digest",
           "save_correspondence", "load_correspondence", "ramp_down", "ramp_up", "border_reach"]

CACHE_VERSION = 6


@dataclass
class Correspondence:
    """Correspondence from capture vertices to avatar face-mesh vertices.

    ``triangle[m]`` (capture triangle of each avatar vertex), ``barycentric[m,3]``, ``distance[m]`` (m, from
    the avatar vertex to the registered capture surface), ``face[m]`` bool (the face region),
    ``source_triangle[t_avatar]`` the capture triangle under each avatar face triangle's centroid (-1 for
    triangles not entirely in the face; None when not computed: only the deformation-transfer modes read
    it), ``weight[m]`` in [0,1] the face membership (1 = fully face, the region's rim ramps down to 0;
    ``face = weight > 0``), ``key`` the digest it belongs to, ``info`` figures for the report,
    ``registered[n,3]`` the capture face deformed
    onto the avatar face (the inverse map's source).
    """

    triangle: np.ndarray
    barycentric: np.ndarray
    distance: np.ndarray
    face: np.ndarray
    source_triangle: np.ndarray | None
    weight: np.ndarray | None = None
    key: str = ""
    info: dict | None = None
    registered: np.ndarray | None = None

    def matrix(self, capture_triangles, n_capture: int, *, face_only: bool = True,
               rows=None) -> sp.csr_matrix:
        """M as a sparse ``[m, n_capture]`` interpolation matrix (rows outside the face are empty when
        ``face_only``); ``rows`` (indices or bool mask) keeps only those avatar vertices."""
        tri = np.asarray(capture_triangles)[self.triangle]
        w = self.barycentric * (self.face[:, None] if face_only else 1.0)
        if rows is not None:
            tri, w = tri[rows], w[rows]
        r = np.repeat(np.arange(len(tri)), 3)
        return sp.csr_matrix((w.ravel(), (r, tri.ravel())), shape=(len(tri), n_capture))

    def apply(self, capture_values, capture_triangles, rows=None, *, matrix=None) -> np.ndarray:
        """``M @ values``: interpolate per-capture-vertex values ``[..., n_capture, c]`` at the avatar
        vertices -> ``[..., m, c]`` (every vertex; use ``face`` to select the region). ``rows``: optional
        avatar vertex indices (or a bool mask): only those are interpolated -> ``[..., len(rows), c]``.
        ``matrix``: ``self.matrix(capture_triangles, n_capture, face_only=False, rows=rows)`` when the caller
        applies the map to several batches (built once)."""
        v = np.asarray(capture_values, dtype=np.float64)
        lead, (n, c) = v.shape[:-2], v.shape[-2:]
        flat = np.moveaxis(v.reshape(-1, n, c), 1, 0).reshape(n, -1)  # [n, F*c]
        if matrix is None:
            matrix = self.matrix(capture_triangles, n, face_only=False, rows=rows)
        out = matrix @ flat  # [m, F*c]
        return np.moveaxis(out.reshape(-1, int(np.prod(lead, dtype=int)), c), 1, 0).reshape(*lead, -1, c)


class PosedSurface:
    """Closest points on a triangle surface seen in several poses at once: the neutral ``points[n,3]`` and
    ``points + deltas_p`` for each ``deltas_p[n,3]`` of ``poses`` (one Open3D scene per pose, built once).

    :meth:`closest_points` takes queries with their own posed offsets and returns, among the closest points
    found in each pose separately, the one nearest in the stacked space of all poses,
    ``sum_p |q + dq_p - (s + ds_p)|^2``: a point on the right side of a mouth or an eye that is shut in the
    neutral. Without poses it is a plain closest-point query. The returned ``closest``/``distance`` are in
    the neutral pose.
    """

    def __init__(self, points, triangles, poses=()):
        self.points = np.asarray(points, dtype=np.float64)
        self.triangles = np.asarray(triangles)
        self.poses = [np.asarray(d, dtype=np.float64) for d in poses]
        self.queries = [SurfaceQuery(self.points, self.triangles)]
        self.queries += [SurfaceQuery(self.points + d, self.triangles) for d in self.poses]

    def serves(self, points, triangles, poses) -> bool:
        """True when this is the surface of ``points``/``triangles`` in the poses ``poses`` (``[p][m,3]``)
        exactly, so it can answer for them."""
        return (len(poses) == len(self.poses) and np.array_equal(self.points, points)
                and np.array_equal(self.triangles, triangles)
                and all(np.array_equal(a, b) for a, b in zip(self.poses, poses, strict=True)))

    def closest_points(self, queries, query_poses=(), *, within: float | None = None):
        """``(triangle[q], barycentric[q,3], closest[q,3], distance[q])``, closest in the neutral pose.

        ``within`` (m): queries farther than that from the surface in the neutral keep their neutral closest
        point (the poses are searched for the others only: no point of the stacked search is nearer in the
        neutral than the neutral's closest, so a query the caller rejects beyond ``within`` stays rejected).
        """
        q_all = np.asarray(queries, dtype=np.float64)
        tri, bary, closest, dist = self.queries[0].closest_points(q_all)
        if not self.poses:
            return tri, bary, closest, dist
        sel = np.flatnonzero(dist < within) if within is not None else np.arange(len(q_all))
        if sel.size == 0:
            return tri, bary, closest, dist
        out_tri, out_bary, out_closest, out_dist = tri, bary, closest, dist
        q, tri, bary = q_all[sel], tri[sel], bary[sel]
        qp = [q] + [q + np.asarray(d, dtype=np.float64)[sel] for d in query_poses]
        sp_ = [self.points] + [self.points + d for d in self.poses]

        def cost(t, b):
            corners = self.triangles[t]
            return sum(np.sum((qq - np.einsum("qk,qkc->qc", b, s.take(corners, axis=0))) ** 2, axis=1)
                       for qq, s in zip(qp, sp_, strict=True))

        best = cost(tri, bary)
        for k, query in enumerate(self.queries[1:]):
            t2, b2, _, _ = query.closest_points(qp[k + 1])
            c2 = cost(t2, b2)
            better = c2 < best
            tri, bary, best = np.where(better, t2, tri), np.where(better[:, None], b2, bary), \
                np.minimum(c2, best)
        out_tri[sel], out_bary[sel] = tri, bary
        corners = self.points.take(self.triangles.take(tri, axis=0), axis=0)      # (take: see SurfaceQuery)
        out_closest[sel] = np.einsum("qk,qkc->qc", bary, corners)
        out_dist[sel] = vector_lengths(out_closest[sel] - q)
        return out_tri, out_bary, out_closest, out_dist


def nonrigid_register(points, triangles, target_points, target_triangles, *,
                      stiffness=(30.0, 10.0, 3.0, 1.0), iterations_per_level: int = 2,
                      max_angle_deg: float = 60.0, poses=None, surface=None) -> tuple[np.ndarray, dict]:
    """Deform ``points[n,3]`` (already rigidly placed) onto the surface ``target_points/triangles``.

    Minimises ``alpha^2 ||L (x - x0)||^2 + sum_i w_i ||x_i - c_i||^2`` per iteration with ``c_i`` the closest
    target point of ``x_i`` (weight 0 if farther than 3 mean edge lengths or if the normals disagree by more
    than ``max_angle_deg``), ``L`` the cotangent Laplacian of the template, ``alpha`` relaxed through
    ``stiffness`` (relative to the Laplacian's scale). Returns ``(registered[n,3], info)``.

    ``poses``: semantic guidance, a list of ``(source_deltas[n,3], target_deltas[m,3])`` pairs, the same
    ARKit shape on both rigs (e.g. ``jawOpen`` and the blinks), in this frame. ``c_i`` is then the target
    surface point closest to ``x_i`` *in every pose at once* (:class:`PosedSurface`): where the lips or the
    lids touch in the neutral, the closest point can lie on the wrong lip; posed with the mouth open and the
    eyes shut, the two sides are centimetres apart.

    ``surface``: the target in those poses, :class:`PosedSurface` of ``target_points/triangles`` and the
    poses' target sides, when the caller has it (its ray-casting scenes are the cost on a production head).
    """
    x0 = np.asarray(points, dtype=np.float64)
    tri = np.asarray(triangles)
    n = len(x0)
    lap = cotangent_laplacian(x0, tri)
    ltl = (lap.T @ lap).tocsc()
    scale = float(np.abs(ltl.diagonal()).mean())
    edge = mean_edge_length(x0, tri)
    t_points, t_triangles = np.asarray(target_points, dtype=np.float64), np.asarray(target_triangles)
    cos_max = np.cos(np.deg2rad(max_angle_deg))
    x = x0.copy()
    used = 0.0
    target = surface if surface is not None else PosedSurface(
        target_points, target_triangles, [p[1] for p in poses or ()])     # one BVH per pose, every iteration
    src_poses = [np.asarray(p[0], dtype=np.float64) for p in poses or ()]
    for alpha in stiffness:
        for _ in range(iterations_per_level):
            t_id, _, c, d = target.closest_points(x, src_poses)
            nx = vertex_normals(x, tri)
            # soft rejection (ramps, not cuts) keeps the result continuous in the input geometry; the normals
            # of the matched triangles only (row by row: the same bits as forming a production head's 450k)
            tn = triangle_normals(t_points, t_triangles[t_id])
            w = ramp_down(d, 2.0 * edge, 4.0 * edge) * ramp_up(
                np.einsum("ij,ij->i", nx, tn), cos_max - 0.1, cos_max + 0.1)
            used = float((w > 0.5).mean())
            a = (alpha * alpha / scale) * ltl + sp.diags(w + 1e-8)
            rhs = (alpha * alpha / scale) * (ltl @ x0) + w[:, None] * c + 1e-8 * x
            x = _solve(a, rhs)
    t_id, _, c, d = target.closest_points(x, src_poses)
    return x, {"nonrigid_rms_m": float(np.sqrt(np.mean(d ** 2))), "nonrigid_matched": used, "n": n}


def _solve(a, rhs):
    return spd_lu(a).solve(np.asarray(rhs, dtype=np.float64))


def correspondence_map(registered, capture_triangles, avatar_points, avatar_triangles, *,
                       max_distance_ratio: float = 0.5, max_angle_deg: float = 60.0,
                       candidates=None, exclude_border: bool = True, poses=None,
                       source_triangles: bool = True) -> Correspondence:
    """Closest point on the registered capture surface for every avatar face-mesh vertex, and the face region.

    ``registered[n,3]`` the capture template after :func:`nonrigid_register`; ``avatar_points[m,3]``.
    Face region: distance below ``max_distance_ratio`` x the capture's mean edge length, normal angle below
    ``max_angle_deg``, closest point not on a border edge of the capture (open border, eye and mouth holes),
    and (optionally) ``candidates[m]`` true (e.g. vertices that move in some shape). Each test is a smooth
    ramp around its threshold; their product is ``weight`` and ``face = weight > 0``.

    ``poses``: ``(capture_deltas[n,3], avatar_deltas[m,3])`` pairs of the same shape on both rigs: the
    closest point is taken in all poses at once (:class:`PosedSurface`), so that no avatar vertex lands on
    the other lip or lid. ``source_triangles=False``: no ``source_triangle`` (None; the closest points of
    every face triangle's centroid, as many queries again as the vertices and more, for the deformation
    transfer only).
    """
    reg = np.asarray(registered, dtype=np.float64)
    ctri = np.asarray(capture_triangles)
    ap = np.asarray(avatar_points, dtype=np.float64)
    edge = mean_edge_length(reg, ctri)
    limit = max_distance_ratio * edge
    surface = PosedSurface(reg, ctri, [p[0] for p in poses or ()])
    # the poses are searched only for vertices the distance test can keep (weight 0 beyond 1.3 x limit)
    tri, bary, _, dist = surface.closest_points(ap, [np.asarray(p[1], dtype=np.float64) for p in poses or ()],
                                                within=1.3 * limit)
    # Every test is a ramp rather than a cut, so that the region (and the result) changes continuously with
    # the input: a float32 re-export of the avatar moves vertices by ~1e-7 m and must not flip any of them.
    w_dist = ramp_down(dist, 0.7 * limit, 1.3 * limit)
    w_normal = _facing(reg, ctri, tri, bary, vertex_normals(ap, avatar_triangles), max_angle_deg)
    weight = w_dist * w_normal
    if exclude_border:
        # Clamped onto the capture's border (open border, eye and mouth holes): the closest point is on a
        # border edge (opposite barycentric ~0) or a border vertex, and the avatar vertex is off the surface.
        near_border = _on_border(ctri, len(reg), tri, bary)
        weight = weight * (1.0 - near_border * ramp_up(dist, 0.02 * edge, 0.08 * edge))
    if candidates is not None:
        weight = weight * np.asarray(candidates, dtype=bool)
    face = weight > 0
    atri = np.asarray(avatar_triangles)
    src_tri = np.full(len(atri), -1, dtype=np.int64) if source_triangles else None
    in_face = np.flatnonzero(face[atri].all(axis=1)) if source_triangles else np.zeros(0, dtype=np.int64)
    if in_face.size:
        src_tri[in_face] = surface.closest_points(
            ap[atri[in_face]].mean(axis=1),
            [np.asarray(p[1], dtype=np.float64)[atri[in_face]].mean(axis=1) for p in poses or ()])[0]
    info = {"face_vertices": int(face.sum()), "capture_mean_edge_m": edge,
            "face_rms_distance_m": float(np.sqrt(np.mean(dist[face] ** 2))) if face.any() else None}
    return Correspondence(tri, bary, dist, face, src_tri, weight=weight, info=info)


def _facing(registered, capture_triangles, tri, bary, an, max_angle_deg: float) -> np.ndarray:
    """``[m]`` in [0,1]: the normal test of :func:`correspondence_map` - the avatar vertex normals ``an[m,3]``
    against the capture's at the closest points ``(tri[m], bary[m,3])`` on ``registered``, a smooth ramp 10
    degrees wide around ``max_angle_deg``."""
    ctri = np.asarray(capture_triangles)
    # capture normal at the closest point, interpolated from vertex normals: continuous across edges (a
    # triangle normal would jump when the closest point moves over a crease)
    cn = np.einsum("mk,mkc->mc", bary, vertex_normals(registered, ctri)[ctri[tri]])
    cn /= np.maximum(vector_lengths(cn)[:, None], 1e-300)
    cosang = np.einsum("ij,ij->i", an, cn)
    return ramp_up(cosang, np.cos(np.deg2rad(max_angle_deg + 5)), np.cos(np.deg2rad(max_angle_deg - 5)))


def _on_border(capture_triangles, n_capture: int, tri, bary) -> np.ndarray:
    """``[m]`` in [0,1]: the closest point ``(tri[m], bary[m,3])`` lies on a border edge of the capture
    (opposite barycentric ~0) or at a border vertex (open border, eye and mouth holes): smooth ramps."""
    ctri = np.asarray(capture_triangles)
    border = boundary_vertices(ctri, n_capture)
    corners = ctri[tri]
    near_border = np.zeros(len(tri))
    for k in range(3):
        a, b = corners[:, (k + 1) % 3], corners[:, (k + 2) % 3]
        on_border_edge = (border[a] & border[b]) * ramp_down(bary[:, k], 5e-4, 2e-3)
        near_border = np.maximum(near_border, on_border_edge)
    vtx = corners[np.arange(len(tri)), np.argmax(bary, axis=1)]
    return np.maximum(near_border, border[vtx] * ramp_up(bary.max(axis=1), 1 - 2e-3, 1 - 5e-4))


def border_reach(corr: Correspondence, capture_triangles, avatar_points, avatar_triangles, *,
                 max_angle_deg: float = 60.0) -> np.ndarray:
    """``[m]`` in [0,1): how well the capture's value at its border measures each avatar vertex just past
    it - the vertices :func:`correspondence_map` leaves out of the face because their closest point is
    clamped onto the capture's border, as far as its border test leaves them out (the same ramp, 0.02-0.08
    capture edge): ``1 - d / e`` (smooth, :func:`ramp_down`) for a vertex ``d`` metres from its closest
    point, ``e`` one registered capture edge (the resolution the capture measures at), times the normal
    test; 0 elsewhere (on the surface, or without ``corr.registered``). A value at the border stands for the
    skin around it over the capture's resolution: a raise that keeps growing past the border is measured
    there, not only at the last avatar vertex inside it (up to one avatar edge further in)."""
    reg = corr.registered
    ctri = np.asarray(capture_triangles)
    m = len(corr.triangle)
    if reg is None or not len(reg) or not m:
        return np.zeros(m)
    reg = np.asarray(reg, dtype=np.float64)
    edge = mean_edge_length(reg, ctri)
    tri, bary = np.asarray(corr.triangle), np.asarray(corr.barycentric, dtype=np.float64)
    near = _on_border(ctri, len(reg), tri, bary)
    dist = np.asarray(corr.distance, dtype=np.float64)
    # where the face's border test (:func:`correspondence_map`) takes the vertex out, and as far as it does
    out = near * ramp_up(dist, 0.02 * edge, 0.08 * edge) * ramp_down(dist, 0.0, edge)
    sel = np.flatnonzero(out > 0)
    if sel.size:
        an = vertex_normals(np.asarray(avatar_points, dtype=np.float64), avatar_triangles)[sel]
        out[sel] *= _facing(reg, ctri, tri[sel], bary[sel], an, max_angle_deg)
    return np.minimum(out, 1.0 - 1e-6)


def ramp_down(x, lo, hi, *, overwrite: bool = False):
    """1 below ``lo``, 0 above ``hi``, smooth (C1) in between: ``1 - t^2 (3 - 2 t)``, ``t = clip((x - lo) /
    (hi - lo), 0, 1)``. ``overwrite``: ``x`` is a float64 array the caller does not need, computed in it
    (the same operations in the same order, so the same bits; two temporaries instead of six)."""
    if not (overwrite and isinstance(x, np.ndarray) and x.dtype == np.float64):
        t = np.clip((np.asarray(x, dtype=np.float64) - lo) / (hi - lo), 0.0, 1.0)
        return 1.0 - t * t * (3.0 - 2.0 * t)
    t = x
    t -= lo
    t /= hi - lo
    np.clip(t, 0.0, 1.0, out=t)
    u = 2.0 * t
    np.subtract(3.0, u, out=u)
    t *= t
    t *= u
    return np.subtract(1.0, t, out=t)


def ramp_up(x, lo, hi):
    """0 below ``lo``, 1 above ``hi``, smooth (C1) in between."""
    return 1.0 - ramp_down(x, lo, hi)


def geometry_digest(*arrays) -> str:
    """SHA-256 over arrays' shapes and float64/int64 bytes (rounded to 1e-9 for floats): the cache key."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.asarray(a)
        a = np.round(a.astype(np.float64), 9) if a.dtype.kind == "f" else a.astype(np.int64)
        h.update(str(a.shape).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:32]


def correspondence_npz(corr: Correspondence) -> bytes:
    """The map as the ``.npz`` bytes :func:`save_correspondence` writes (taken when the map is made, written
    once the run that made it has succeeded)."""
    import io

    buffer = io.BytesIO()
    np.savez_compressed(buffer, triangle=corr.triangle, barycentric=corr.barycentric, distance=corr.distance,
                        face=corr.face,
                        source_triangle=(corr.source_triangle if corr.source_triangle is not None
                                         else np.zeros(0, dtype=np.int64)),
                        has_source_triangle=np.array(corr.source_triangle is not None),
                        weight=corr.weight if corr.weight is not None else corr.face.astype(float),
                        registered=(corr.registered if corr.registered is not None
                                    else np.zeros((0, 3))),
                        key=np.array(corr.key), version=np.array(CACHE_VERSION),
                        info=np.array(json.dumps(corr.info or {})))
    return buffer.getvalue()


def save_correspondence(corr: Correspondence | None, path, *, data: bytes | None = None) -> Path:
    """Write the map to ``path`` (``.npz``) atomically; ``data``: its bytes taken earlier
    (:func:`correspondence_npz`), written as they are."""
    from ..io.atomic import atomic_file

    path = Path(path)
    data = correspondence_npz(corr) if data is None else data
    with atomic_file(path, force=True) as tmp, open(tmp, "wb") as f:  # a file object: no ".npz" appended
        f.write(data)
    return path


def load_correspondence(path, key: str | None = None) -> Correspondence | None:
    """Read a cached map; None when the file is absent or belongs to another avatar/template (``key``)."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            if int(z["version"]) != CACHE_VERSION or (key is not None and str(z["key"]) != key):
                return None
            return Correspondence(z["triangle"], z["barycentric"], z["distance"], z["face"].astype(bool),
                                  z["source_triangle"] if bool(z["has_source_triangle"]) else None,
                                  z["weight"], str(z["key"]),
                                  json.loads(str(z["info"])),
                                  z["registered"] if len(z["registered"]) else None)
    except (OSError, KeyError, ValueError, EOFError) as exc:
        raise InputFileError(f"not a usdface correspondence cache ({exc})", path=path,
                             fix="delete it or pass another --correspondence file") from None
