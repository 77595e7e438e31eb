"""Global visibility of landmark candidates (Zell & McDonnell 2022, sec. 3.1.2), with Open3D ray casting.

l_n = min over the neutral and every blendshape pose of the fraction of unoccluded rays on vertex n's
normal hemisphere (per-vertex ambient occlusion), so a vertex that is hidden in any expression scores low.
Each shape is posed at weight 1 on its own, except a shape authored to be used over another one
(:data:`POSE_BASES`: ARKit's ``mouthClose`` over ``jawOpen``), which is posed over it (:func:`pose_bases`).
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
from ..natives import open3d
from .candidates import displacement_magnitudes, moving_share, relative_displacement


def hemisphere_directions(count: int) -> np.ndarray:
    """``count`` deterministic, evenly spread unit directions on the +Z hemisphere (Fibonacci lattice) ->
    ``[count, 3]``; uniform in solid angle, so the unoccluded fraction is the ambient-occlusion visibility."""
    if count < 1:
        raise GeometryError(f"ray count must be >= 1, got {count}", fix="pass rays >= 1 (default 16)")
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
    o3d = open3d()

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)))
    return scene


#: Ray start offset along the normal (metres), as a share of the face size (:func:`face_size`): a physical
#: length, so a surface point gets the same rays at every mesh resolution (a share of the edge length would
#: shrink 4x per subdivision). 1e-4 of a 0.42 m head is 42 um: far above the float32 rounding of the scene's
#: coordinates (~0.1 um at 1.6 m), far below any gap between lips or lids.
RAY_OFFSET = 1e-4
#: A vertex belongs to the face when some shape moves it by at least this share of that shape's peak.
FACE_SHARE = 0.05


def face_size(neutral: np.ndarray, moving_share: np.ndarray | None = None) -> float:
    """Diagonal (metres) of the box around the face: the vertices whose ``moving_share[n]`` (max over shapes
    of |dv| / the shape's peak, eq. 2) is at least :data:`FACE_SHARE`; the whole mesh when none is given or
    nothing moves. ``neutral[n, 3]`` metres."""
    p = np.asarray(neutral, dtype=np.float64)
    if moving_share is not None and (np.asarray(moving_share) >= FACE_SHARE).any():
        p = p[np.asarray(moving_share) >= FACE_SHARE]
    return float(np.linalg.norm(p.max(axis=0) - p.min(axis=0))) if len(p) else 0.0


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


#: ARKit shapes authored to be used over others, by canonical name: eq. 4's pose of such a shape is the shape
#: at weight 1 over these at weight 1. The blendshape poses stand for the face's range of motion (Zell &
#: McDonnell 2022, sec. 3.1.2: "given the blendshape model, we have a proxy for the range of motion"); Apple
#: defines ``mouthClose`` as "closure of the lips independent of jaw position", whose values "can produce
#: unrealistic facial expressions unless other coefficients are also set" (its figure: neutral, ``jawOpen``,
#: ``jawOpen`` + ``mouthClose``). Alone it closes lips that are already closed: they pass through each other
#: and the rays from the upper lip start under the lower one. The phone never reports it alone (the four Live
#: Link Face takes, 11,780 frames: ``mouthClose`` exceeds ``jawOpen`` by at most 0.058). Only a shape whose
#: definition ties it to another belongs here, not shapes that merely move together.
POSE_BASES: dict[str, tuple[str, ...]] = {"mouthClose": ("jawOpen",)}


def pose_bases(names) -> list[tuple[int, ...]]:
    """Per shape of ``names[K]`` (any ARKit spelling, :func:`usdface.arkit.normalize_name`) the indices of the
    shapes its eq. 4 pose adds at weight 1 (:data:`POSE_BASES`); ``()`` for every other shape, and for one
    whose base the rig lacks (it is then posed alone, as the paper does)."""
    from ..arkit import normalize_name

    canon = [normalize_name(n) for n in names]
    where = {c: i for i, c in enumerate(canon) if c is not None}
    return [tuple(where[b] for b in POSE_BASES.get(c, ()) if b in where) if c is not None else ()
            for c in canon]


#: Offsets below this (metres) count as "not moving" when deciding which rays a pose can change.
STATIC_OFFSET = 1e-7

#: CPU microseconds per triangle of a scene build and per ray of an occlusion test (Open3D 0.19-0.20, measured
#: on the bench heads): the cost model choosing, per pose, between a scene of the whole posed mesh and the
#: never-moving triangles' scene + a scene of the rest (a body mesh around a face).
COST_US = {"build": 0.5, "cast": 0.3}


class PoseVisibility:
    """Global visibility l_n (Zell & McDonnell 2022, eq. 4) of any vertex subset, min over all poses.

    ``neutral[n, 3]`` metres, ``triangles[t, 3]``, ``deltas[K, n, 3]`` metres (``magnitudes[K, n]``: their
    norms, when the caller has them, :func:`usdface.landmarks.candidates.displacement_magnitudes`). The poses
    are the neutral and each shape at weight 1, over the shapes ``bases[k]`` (indices, each at weight 1) for
    a shape authored on top of others (:func:`pose_bases` of the shape names; default: every shape alone).
    ``self(vertices)`` casts ``rays`` hemisphere rays per vertex and pose (or, with ``camera[3]`` metres in
    the same frame, one ray to the camera) and returns ``l[v]`` in [0, 1]; results are cached per vertex.
    :meth:`upper_bound` is the neutral pose's visibility alone: an upper bound of l_n at 1/(K+1) of the cost,
    which callers use to skip vertices that cannot matter.

    Exact shortcut: a shape moves only part of the mesh. A ray from a vertex none of whose triangles move is
    the neutral's ray; if a triangle the shape leaves in place blocked it first in the neutral, it is still
    blocked, and it is not cast again. Every other ray (from a vertex next to moving triangles, or first hit
    by a moving triangle, or free in the neutral) is cast against the pose: either a scene of the whole
    posed mesh, or - when most of the mesh never moves (a body around a face) - a scene of the triangles no
    shape moves, built once, plus one of the others in the pose (a ray is blocked iff either blocks it);
    :data:`COST_US` picks the cheaper per pose. The work is pose-major: one scene per pose and call (kept
    across calls while the kept scenes stay under :attr:`cache_triangles`), the pose's points formed one pose
    at a time and vertex normals computed only at the vertices asked for, so memory is O(n + rays) plus the
    kept scenes.
    """

    def __init__(self, neutral: np.ndarray, triangles: np.ndarray, deltas: np.ndarray, rays: int = 16,
                 camera=None, magnitudes: np.ndarray | None = None, bases=None):
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
        # which vertices each shape moves (for the exact shortcut) and the face's extent (the moving share,
        # as the layout's face size, samples and exclusion radius take it: one rule)
        mag = displacement_magnitudes(deltas) if magnitudes is None else np.asarray(magnitudes)
        self._moving_v = mag > STATIC_OFFSET
        share = moving_share(relative_displacement(mag))
        self.bases = [()] * len(deltas) if bases is None else [tuple(int(j) for j in b) for b in bases]
        if len(self.bases) != len(deltas) or any(not 0 <= j < len(deltas) or j == k
                                                 for k, b in enumerate(self.bases) for j in b):
            raise GeometryError(f"pose bases {bases!r} do not index the {len(deltas)} shapes",
                                fix="pass per shape a tuple of other shapes' indices (visibility.pose_bases)")
        moving_own = self._moving_v.copy()
        for k, b in enumerate(self.bases):  # a pose over its bases moves what they move too
            for j in b:
                self._moving_v[k] |= moving_own[j]
        self.offset = max(RAY_OFFSET * face_size(neutral, share), 1e-9)
        self._neutral_scene = None
        self._neutral_normals = None
        self.values = np.full(len(neutral), np.nan)
        self.upper = np.full(len(neutral), np.nan)
        self.rays_cast = 0
        self.scenes_built = 0
        # pose scenes are kept across calls (lazy callers ask several times) while their triangles stay under
        # this budget (~77 bytes per triangle in Open3D/Embree: 4M triangles ~ 300 MB)
        self.cache_triangles = 4_000_000
        # "auto": per pose the cheaper exact way (a scene of the whole posed mesh, or one scene of the
        # triangles no shape moves, built once, + a scene of the others in the pose); "full"/"union" force one
        self.strategy = "auto"
        self._cache: dict = {}
        self._cached_triangles = 0

    @property
    def batch_hint(self) -> int:
        """Vertices worth evaluating per call: 0 when every pose's scene stays kept across calls, else about
        as many as make the rays of a call cost what rebuilding its scenes costs (a triangle's share of a
        scene build ~ a tenth of a vertex's rays, measured with Open3D 0.19-0.20)."""
        per_pose = len(self.triangles)
        if self.strategy != "full":
            per_pose = min(per_pose, int(self._union()[0].sum()))
        if (len(self.deltas) + 1) * per_pose <= self.cache_triangles:
            return 0
        return per_pose * 16 // (10 * self._per_vertex)

    @property
    def _per_vertex(self) -> int:
        return 1 if self.camera is not None else self.rays

    def _moving(self, k: int):
        """(any vertex moves, moving_t[t] bool, touched[n] bool: vertex of a moving triangle) of shape k."""
        key = ("moving", k)
        if key not in self._cache:
            moving_v = self._moving_v[k]
            moving_t = moving_v[self.triangles].any(axis=1)
            touched = np.zeros(len(self.neutral), dtype=bool)
            touched[self.triangles[moving_t].ravel()] = True
            self._cache[key] = (bool(moving_v.any()), moving_t, touched)
        return self._cache[key]

    def _normals_at(self, points: np.ndarray, vertices: np.ndarray) -> np.ndarray:
        """:func:`usdface.mesh.vertex_normals` of ``points`` at ``vertices`` only; bit-identical (the same
        area-weighted sums over the incident triangles, accumulated in the same order)."""
        near = np.zeros(len(self.neutral), dtype=bool)
        near[vertices] = True
        tri = self.triangles[near[self.triangles].any(axis=1)]
        used, local = np.unique(tri, return_inverse=True)  # a compact copy: O(ring) work, not O(n)
        normals = vertex_normals(points[used], local.reshape(-1, 3))
        out = np.zeros((len(vertices), 3))
        at = np.searchsorted(used, vertices)
        ok = (at < len(used)) & (used[np.minimum(at, len(used) - 1)] == vertices)
        out[ok] = normals[at[ok]]
        return out

    def _neutral(self):
        if self._neutral_scene is None:
            self._neutral_scene = _scene(self.neutral, self.triangles)
            self._neutral_normals = vertex_normals(self.neutral, self.triangles)
            self.scenes_built += 1
        return self._neutral_scene, self._neutral_normals

    def _pose_scene(self, k: int, pose: np.ndarray):
        key = ("scene", k)
        if key in self._cache:
            return self._cache[key]
        scene = _scene(pose, self.triangles)
        self.scenes_built += 1
        if self._cached_triangles + len(self.triangles) <= self.cache_triangles:
            self._cache[key] = scene
            self._cached_triangles += len(self.triangles)
        return scene

    def _make_rays(self, points: np.ndarray, normals: np.ndarray):
        if self.camera is None:
            return _hemisphere_rays(points, normals, self.offset, self.rays), None
        return _camera_rays(points, normals, self.offset, self.camera)

    def _cast(self, scene, rays: np.ndarray) -> np.ndarray:
        o3d = open3d()

        self.rays_cast += len(rays)
        if len(rays) == 0:
            return np.zeros(0, dtype=bool)
        tfar = 1.0 if self.camera is not None else np.inf
        return scene.test_occlusions(o3d.core.Tensor(rays), tfar=tfar).numpy().astype(bool)

    def _score(self, blocked: np.ndarray, facing, normals: np.ndarray) -> np.ndarray:
        valid = np.linalg.norm(normals, axis=1) > 0
        if self.camera is None:
            return np.where(valid, 1.0 - blocked.reshape(-1, self.rays).mean(axis=1), 0.0)
        return np.where(valid, (facing & ~blocked).astype(np.float64), 0.0)

    def _neutral_pass(self, todo: np.ndarray):
        """Neutral rays of ``todo``, their first hit (-1: none) and the neutral visibility ``[len(todo)]``."""
        o3d = open3d()

        scene, normals = self._neutral()
        n0 = normals[todo]
        rays0, facing0 = self._make_rays(self.neutral[todo], n0)
        first = np.full(len(rays0), -1, dtype=np.int64)
        if len(rays0):
            tfar = 1.0 if self.camera is not None else np.inf
            hit = scene.cast_rays(o3d.core.Tensor(rays0))
            t_hit = hit["t_hit"].numpy()
            self.rays_cast += len(rays0)
            ok = np.isfinite(t_hit) & (t_hit <= tfar)
            first[ok] = hit["primitive_ids"].numpy()[ok].astype(np.int64)
        vis = self._score(first >= 0, facing0, n0)
        self.upper[todo] = vis
        return n0, rays0, facing0, first, vis

    def _union(self):
        """(ever_t[t] bool: triangles some shape moves, scene of the others at their neutral positions)."""
        if "union" not in self._cache:
            ever = np.zeros(len(self.triangles), dtype=bool)
            for k in range(len(self.deltas)):
                ever |= self._moving(k)[1]
            static = self.triangles[~ever]
            scene = _scene(self.neutral, static) if len(static) else None
            self.scenes_built += scene is not None
            self._cache["union"] = (ever, scene)
        return self._cache["union"]

    def _union_scene(self, k: int, pose: np.ndarray, ever: np.ndarray):
        """Scene of the triangles some shape moves, at pose k's positions (compact vertex buffer), kept."""
        key = ("union scene", k)
        if key in self._cache:
            return self._cache[key]
        if "union buffer" not in self._cache:  # the same compact vertex buffer for every pose
            used, local = np.unique(self.triangles[ever], return_inverse=True)
            self._cache["union buffer"] = (used, local.reshape(-1, 3))
        used, tri = self._cache["union buffer"]
        scene = _scene(pose[used], tri)
        self.scenes_built += 1
        if self._cached_triangles + len(tri) <= self.cache_triangles:
            self._cache[key] = scene
            self._cached_triangles += len(tri)
        return scene

    def _use_union(self, k: int, rays: int) -> bool:
        """Cheaper of the two exact ways to cast pose k's ``rays`` (cost model of :data:`COST_US`): a scene of
        the whole posed mesh, or the never-moving triangles' scene (built once) + a scene of the others."""
        if self.strategy != "auto":
            return self.strategy == "union"
        build, cast = COST_US["build"], COST_US["cast"]
        ever_count = int(self._union()[0].sum())
        full = (0 if ("scene", k) in self._cache else build * len(self.triangles)) + cast * rays
        union = (0 if ("union scene", k) in self._cache else build * ever_count) + 2 * cast * rays
        return union < full

    def pose(self, k: int) -> np.ndarray:
        """Eq. 4's pose of shape ``k`` ``[n, 3]`` metres: the neutral + shape k + its :attr:`bases`, each at
        weight 1."""
        pose = self.neutral + self.deltas[k]
        for j in self.bases[k]:
            pose += self.deltas[j]
        return pose

    @property
    def order(self) -> np.ndarray:
        """Shape poses in evaluation order ``[K]``, most moving triangles first: big motions occlude most, so
        vertices reach l = 0 (after which no later pose can lower them, and none is cast) early."""
        if "order" not in self._cache:
            size = np.array([int(self._moving(k)[1].sum()) for k in range(len(self.deltas))], dtype=np.int64)
            self._cache["order"] = np.argsort(-size, kind="stable")
        return self._cache["order"]

    def _evaluate(self, todo: np.ndarray, on_pose=None) -> np.ndarray:
        per = self._per_vertex
        n0_all, rays0_all, facing0_all, first_all, out = self._neutral_pass(todo)
        out = out.copy()
        for done, k in enumerate(self.order, start=1):
            moves, moving_t, touched = self._moving(int(k))
            live = np.flatnonzero(out > 0.0)  # l = 0 is final: a minimum cannot fall further
            if not moves or live.size == 0:
                if on_pose is not None:
                    on_pose(done, len(self.deltas))
                continue
            ray_ids = (live[:, None] * per + np.arange(per)[None, :]).ravel()
            n0, rays0, first = n0_all[live], rays0_all[ray_ids], first_all[ray_ids]
            facing0 = None if facing0_all is None else facing0_all[live]
            affected = touched[todo[live]]  # origin or normal may change: recast from the pose
            same = ~np.repeat(affected, per)
            # a neutral ray first blocked by a triangle this shape leaves in place stays blocked
            blocked = same & (first >= 0) & ~moving_t[np.maximum(first, 0)]
            recast = same & ~blocked
            normals, facing = n0, facing0
            if recast.any() or affected.any():
                pose = self.pose(int(k))
                if self._use_union(k, int(recast.sum()) + int(affected.sum()) * per):
                    ever, static_scene = self._union()
                    scene = self._union_scene(k, pose, ever)

                    def cast_pose(rays, sc=scene, st=static_scene):
                        out = self._cast(sc, rays)
                        if st is not None:
                            out[~out] = self._cast(st, rays[~out])
                        return out
                else:
                    scene = self._pose_scene(k, pose)

                    def cast_pose(rays, sc=scene):
                        return self._cast(sc, rays)
                blocked[recast] = cast_pose(rays0[recast])
                if affected.any():
                    verts = todo[live[affected]]
                    nk = self._normals_at(pose, verts)
                    rays_k, facing_k = self._make_rays(pose[verts], nk)
                    blocked[~same] = cast_pose(rays_k)
                    normals = n0.copy()
                    normals[affected] = nk
                    if facing0 is not None:
                        facing = facing0.copy()
                        facing[affected] = facing_k
            out[live] = np.minimum(out[live], self._score(blocked, facing, normals))
            if on_pose is not None:
                on_pose(done, len(self.deltas))
        return out

    def upper_bound(self, vertices: np.ndarray | None = None) -> np.ndarray:
        """The neutral pose's visibility ``[v]``, an upper bound of l_n (l_n itself where it is known)."""
        idx = np.arange(len(self.neutral)) if vertices is None else np.asarray(vertices, dtype=np.int64)
        todo = np.unique(idx[np.isnan(self.upper[idx])])
        if todo.size:
            self._neutral_pass(todo)
        return np.where(np.isnan(self.values[idx]), self.upper[idx], self.values[idx])

    def __call__(self, vertices: np.ndarray | None = None, on_pose=None) -> np.ndarray:
        """l ``[v]`` of ``vertices`` (default all); ``on_pose(done, total)`` after each pose (progress)."""
        idx = np.arange(len(self.neutral)) if vertices is None else np.asarray(vertices, dtype=np.int64)
        todo = np.unique(idx[np.isnan(self.values[idx])])
        if todo.size:
            self.values[todo] = self._evaluate(todo, on_pose)
        return self.values[idx].copy()


def global_visibility(neutral: np.ndarray, triangles: np.ndarray, deltas: np.ndarray,
                      vertices: np.ndarray | None = None, rays: int = 16,
                      camera: np.ndarray | None = None, bases=None) -> np.ndarray:
    """Global visibility l_n (Zell & McDonnell 2022, eq. 4): minimum over the neutral and every shape pose.

    ``neutral[n, 3]`` metres, ``triangles[t, 3]``, ``deltas[K, n, 3]`` metres; ``vertices[v]`` restricts the
    work to the vertices that matter (e.g. landmark candidates; default all) -> ``l[v]`` in [0, 1].
    Hemisphere ambient occlusion with ``rays`` rays, or with ``camera[3]`` (metres, internal frame) the
    single-ray known-camera test; ``bases``: per shape the shapes its pose is over (:func:`pose_bases`).
    See :class:`PoseVisibility`.
    """
    return PoseVisibility(neutral, triangles, deltas, rays, camera, bases=bases)(vertices)
