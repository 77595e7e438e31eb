"""Global visibility of landmark candidates (Zell & McDonnell 2022, sec. 3.1.2), with Open3D ray casting.

l_n = min over the neutral and every blendshape pose of the fraction of unoccluded rays on vertex n's
normal hemisphere (per-vertex ambient occlusion), so a vertex that is hidden in any expression scores low.
With a known camera (head-mounted rig) one ray per vertex towards the camera replaces the hemisphere: l_n is 1
when the vertex faces the camera and nothing is in between, in every pose, else 0.

:class:`PoseVisibility` builds the ray-casting scenes of all poses once and answers for any vertex subset, so
callers can evaluate visibility lazily, only where it can change the result (see
:mod:`usdface.landmarks.layout`).
"""

from __future__ import annotations

import numpy as np

from ..errors import GeometryError
from ..mesh import vertex_normals


def hemisphere_directions(count: int) -> np.ndarray:
    """``count`` deterministic, evenly spread unit directions on the +Z hemisphere (Fibonacci lattice) ->
    ``[count, 3]``; uniform in solid angle, so the unoccluded fraction is the ambient-occlusion visibility."""
    if count < 1:
        raise GeometryError(f"ray count must be >= 1, got {count}", fix="pass rays >= 1 (default 64)")
    i = np.arange(count) + 0.5
    z = 1.0 - i / count  # uniform in z on (0, 1] <=> uniform in solid angle on the hemisphere
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    s = np.sqrt(1.0 - z * z)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)


def _tangent_frames(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents ``[n, 3]`` completing each normal to a right-handed orthonormal frame."""
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t = np.cross(helper, normals)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-300)
    return t, np.cross(normals, t)


def _scene(points: np.ndarray, triangles: np.ndarray):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)))
    return scene


def _offset(points: np.ndarray, triangles: np.ndarray) -> float:
    """Ray start offset (metres) along the normal: 1% of the mean edge length, to avoid self-hits."""
    e = points[triangles[:, 1]] - points[triangles[:, 0]]
    return 0.01 * float(np.mean(np.linalg.norm(e, axis=1))) if len(e) else 1e-6


def _hemisphere_rays(p: np.ndarray, n: np.ndarray, offset: float, rays: int) -> np.ndarray:
    """Rays ``[v * rays, 6]`` float32 (origin, direction) over each vertex's normal hemisphere."""
    t, b = _tangent_frames(n)
    d = hemisphere_directions(rays)
    dirs = d[None, :, 0:1] * t[:, None] + d[None, :, 1:2] * b[:, None] + d[None, :, 2:3] * n[:, None]
    origins = np.broadcast_to((p + offset * n)[:, None], dirs.shape)
    return np.concatenate([origins, dirs], axis=2).reshape(-1, 6).astype(np.float32)


def _camera_rays(p: np.ndarray, n: np.ndarray, offset: float, camera: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Rays ``[v, 6]`` towards the camera, unnormalised so t = 1 at the camera, and ``facing[v]`` bool."""
    origins = p + offset * n
    to_cam = np.asarray(camera, dtype=np.float64)[None, :] - origins
    facing = np.einsum("ij,ij->i", to_cam, n) > 0.0
    return np.concatenate([origins, to_cam], axis=1).astype(np.float32), facing


def ambient_visibility(points: np.ndarray, triangles: np.ndarray, vertices: np.ndarray | None = None,
                       rays: int = 16) -> np.ndarray:
    """Fraction of unoccluded normal-hemisphere rays per vertex, for one pose (ambient occlusion).

    ``points[n, 3]`` metres, ``triangles[t, 3]``; ``vertices[v]`` the vertices to evaluate (default all) ->
    ``[v]`` in [0, 1]. One batched Open3D ``RaycastingScene.test_occlusions`` call over v x rays rays.
    """
    return PoseVisibility(points, triangles, np.zeros((0,) + np.shape(points)), rays=rays)(vertices)


def camera_visibility(points: np.ndarray, triangles: np.ndarray, camera: np.ndarray,
                      vertices: np.ndarray | None = None) -> np.ndarray:
    """1.0 where a vertex faces ``camera[3]`` (metres, same frame as points) with a clear line of sight, else
    0.0: one ray per vertex, for one pose. ``points[n, 3]``, ``triangles[t, 3]`` -> ``[v]``."""
    return PoseVisibility(points, triangles, np.zeros((0,) + np.shape(points)), camera=camera)(vertices)


#: Offsets below this (metres) count as "not moving" when deciding which rays a pose can change.
STATIC_OFFSET = 1e-7


class PoseVisibility:
    """Global visibility l_n (Zell & McDonnell 2022, eq. 4) of any vertex subset, min over all poses.

    ``neutral[n, 3]`` metres, ``triangles[t, 3]``, ``deltas[K, n, 3]`` metres. The poses are the neutral and
    each shape at weight 1. ``self(vertices)`` casts ``rays`` hemisphere rays per vertex and pose (or, with
    ``camera[3]`` metres in the same frame, one ray to the camera) and returns ``l[v]`` in [0, 1]; results are
    cached per vertex.

    Exact shortcut for the hemisphere: a shape moves only part of the mesh. A ray from a vertex none of whose
    triangles move is the same ray as in the neutral; if a static triangle blocked it there, it is still
    blocked, and if nothing blocked it, only the shape's moving triangles can. So per shape only the rays of
    vertices next to moving triangles (and rays first hit by a moving triangle) are cast against the full
    pose; the neutral's free rays are cast against the moving triangles alone, a much cheaper scene.
    """

    def __init__(self, neutral: np.ndarray, triangles: np.ndarray, deltas: np.ndarray, rays: int = 16,
                 camera=None):
        neutral = np.asarray(neutral, dtype=np.float64)
        deltas = np.asarray(deltas, dtype=np.float64)
        if not np.isfinite(neutral).all() or not np.isfinite(deltas).all():
            raise GeometryError("neutral or shape offsets contain NaN/inf",
                                fix="repair the mesh or its shapes")
        if rays < 1:
            raise GeometryError(f"ray count must be >= 1, got {rays}", fix="pass rays >= 1 (default 16)")
        self.triangles = np.asarray(triangles, dtype=np.int64)
        self.neutral, self.deltas = neutral, deltas
        self.rays = int(rays)
        self.camera = None if camera is None else np.asarray(camera, dtype=np.float64).reshape(3)
        self.offset = _offset(neutral, self.triangles)
        self._neutral_scene = None
        self._neutral_normals = None
        self.values = np.full(len(neutral), np.nan)
        self.rays_cast = 0
        # per-pose scenes, normals and moving-triangle masks are kept across calls (lazy callers ask several
        # times) while their triangles stay under this budget
        self.cache_triangles = 6_000_000
        self._cache: dict = {}
        self._cached_triangles = 0

    def _cached(self, key, make, triangles: int = 0):
        if key in self._cache:
            return self._cache[key]
        value = make()
        if self._cached_triangles + triangles <= self.cache_triangles:
            self._cache[key] = value
            self._cached_triangles += triangles
        return value

    def _pose(self, k: int):
        pose = self.neutral if k < 0 else self.neutral + self.deltas[k]
        return pose, self._cached(("normals", k), lambda: vertex_normals(pose, self.triangles))

    def _moving(self, k: int):
        def make():
            moving_v = np.linalg.norm(self.deltas[k], axis=1) > STATIC_OFFSET
            moving_t = moving_v[self.triangles].any(axis=1)
            touched = np.zeros(len(self.neutral), dtype=bool)
            touched[self.triangles[moving_t].ravel()] = True
            return moving_v.any(), moving_t, touched
        return self._cached(("moving", k), make)

    def _cast(self, scene, rays: np.ndarray, tfar: float = np.inf) -> np.ndarray:
        import open3d as o3d

        self.rays_cast += len(rays)
        if len(rays) == 0:
            return np.zeros(0, dtype=bool)
        return scene.test_occlusions(o3d.core.Tensor(rays), tfar=tfar).numpy().astype(bool)

    def _camera(self, todo: np.ndarray) -> np.ndarray:
        out = np.ones(todo.size)
        for k in range(-1, len(self.deltas)):
            pose, normals = self._pose(k)
            batch, facing = _camera_rays(pose[todo], normals[todo], self.offset, self.camera)
            hit = self._cast(_scene(pose, self.triangles), batch, tfar=1.0)
            v = np.where(np.linalg.norm(normals[todo], axis=1) > 0, (facing & ~hit).astype(np.float64), 0.0)
            np.minimum(out, v, out=out)
        return out

    def _hemisphere(self, todo: np.ndarray) -> np.ndarray:
        import open3d as o3d

        if self._neutral_scene is None:
            self._neutral_scene = _scene(self.neutral, self.triangles)
            self._neutral_normals = vertex_normals(self.neutral, self.triangles)
        n0 = self._neutral_normals[todo]
        rays0 = _hemisphere_rays(self.neutral[todo], n0, self.offset, self.rays)
        first = self._neutral_scene.cast_rays(o3d.core.Tensor(rays0))
        self.rays_cast += len(rays0)
        hit0 = np.isfinite(first["t_hit"].numpy())
        prim0 = np.where(hit0, first["primitive_ids"].numpy().astype(np.int64), 0)
        valid = np.linalg.norm(n0, axis=1) > 0
        out = np.where(valid, 1.0 - hit0.reshape(todo.size, self.rays).mean(axis=1), 0.0)
        for k in range(len(self.deltas)):
            moves, moving_t, touched = self._moving(k)
            if not moves:
                continue
            affected = np.repeat(touched[todo], self.rays)  # origin or normal may change
            full = affected | (hit0 & moving_t[prim0])
            free = ~hit0 & ~affected
            blocked = hit0.copy()
            if full.any():
                pose, normals = self._pose(k)
                sel = np.flatnonzero(full)
                local = np.unique(sel // self.rays)  # positions in todo of the vertices involved
                verts = todo[local]
                dirs = _hemisphere_rays(pose[verts], normals[verts], self.offset, self.rays)
                row = np.searchsorted(local, sel // self.rays) * self.rays + sel % self.rays
                scene = self._cached(("full", k), lambda p=pose: _scene(p, self.triangles),
                                     len(self.triangles))
                blocked[sel] = self._cast(scene, dirs[row])
                nk = normals[todo]
            else:
                pose, nk = self.neutral + self.deltas[k], n0
            if free.any():
                sub_tri = self.triangles[moving_t]
                scene = self._cached(("moving", k, 1), lambda p=pose, t=sub_tri: _scene(p, t), len(sub_tri))
                blocked[free] = self._cast(scene, rays0[free])
            v = 1.0 - blocked.reshape(todo.size, self.rays).mean(axis=1)
            np.minimum(out, np.where(np.linalg.norm(nk, axis=1) > 0, v, 0.0), out=out)
        return out

    def __call__(self, vertices: np.ndarray | None = None) -> np.ndarray:
        idx = np.arange(len(self.neutral)) if vertices is None else np.asarray(vertices, dtype=np.int64)
        todo = np.unique(idx[np.isnan(self.values[idx])])
        if todo.size:
            self.values[todo] = self._hemisphere(todo) if self.camera is None else self._camera(todo)
        return self.values[idx].copy()


def global_visibility(neutral: np.ndarray, triangles: np.ndarray, deltas: np.ndarray,
                      vertices: np.ndarray | None = None, rays: int = 16,
                      camera: np.ndarray | None = None) -> np.ndarray:
    """Global visibility l_n (Zell & McDonnell 2022, eq. 4): minimum over the neutral and every shape pose.

    ``neutral[n, 3]`` metres, ``triangles[t, 3]``, ``deltas[K, n, 3]`` metres; ``vertices[v]`` restricts the
    work to the vertices that matter (e.g. landmark candidates; default all) -> ``l[v]`` in [0, 1].
    Hemisphere ambient occlusion with ``rays`` rays, or with ``camera[3]`` (metres, internal frame) the
    single-ray known-camera test. See :class:`PoseVisibility`.
    """
    return PoseVisibility(neutral, triangles, deltas, rays, camera)(vertices)
