"""In-memory model: face rigs, avatars and captures as dataclasses of numpy arrays (no USD types).

Conventions everywhere in usdface's numerical core:

* points are float64, **metres, Y up** (readers convert on the way in, writers convert back);
* ``neutral[n, 3]``, ``deltas[K, n, 3]`` (dense, every vertex), ``weights[F, K]`` in [0, 1];
* ``triangles[t, 3]`` int64 vertex indices (polygons are fan-triangulated by the readers);
* shape names are canonical ARKit names where the input's name maps to one (see :mod:`usdface.arkit`),
  otherwise the input's own name, kept.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import GeometryError


def _names_brief(names, shown: int = 3) -> str:
    """``a, b, c ... (+N)``: the first ``shown`` of ``names`` for a one-line ``repr``."""
    names = [str(n) for n in names]
    more = f" ... (+{len(names) - shown})" if len(names) > shown else ""
    return ", ".join(names[:shown]) + more


@dataclass
class Inbetween:
    """One in-between target of a shape: ``offsets[n, 3]`` (dense, metres) reached at ``weight``."""

    name: str
    weight: float
    offsets: np.ndarray
    normal_offsets: np.ndarray | None = None


@dataclass
class MeshSource:
    """Where a rig came from, so that a writer can author overrides at the same place in the same form.

    ``to_internal[4, 4]`` maps the mesh's authored local points (column vectors, homogeneous) to internal
    metres / Y-up world space: ``p_internal = to_internal[:3, :3] @ p_local + to_internal[:3, 3]``. Offsets
    map by the linear part only.

    ``region``: when the rig holds only part of the mesh (``read_avatar(..., moving_only=True)``,
    :func:`usdface.submesh.crop_rig`), the :class:`usdface.submesh.SubMesh` it is (full-mesh vertex indices,
    the full vertex count and rest points); ``residue[k]``: for such a rig, shape ``k``'s authored points
    outside the region as ``(indices[r], offsets[r,3] internal metres, [inbetween offsets[r,3], ...])``
    (float noise below the moving tolerance, kept so that a writer leaves it as it was). None: the whole
    mesh.
    """

    file: str
    prim: str
    shape_prims: list[str] = field(default_factory=list)
    channel_tokens: list[str] = field(default_factory=list)
    point_indices: list[np.ndarray | None] = field(default_factory=list)
    normal_offsets: list[np.ndarray | None] = field(default_factory=list)
    to_internal: np.ndarray = field(default_factory=lambda: np.eye(4))
    face_vertex_counts: np.ndarray | None = None
    face_vertex_indices: np.ndarray | None = None
    skel_root: str | None = None
    skeleton: str | None = None
    animation: str | None = None
    region: object | None = None
    residue: list | None = None


@dataclass
class FaceRig:
    """A blendshape rig on one mesh.

    neutral[n, 3] metres, triangles[t, 3], names[K], deltas[K, n, 3] metres, inbetweens by shape name.
    """

    neutral: np.ndarray
    triangles: np.ndarray
    names: list[str]
    deltas: np.ndarray
    inbetweens: dict[str, list[Inbetween]] = field(default_factory=dict)
    source: MeshSource | None = None
    name: str = ""

    def __post_init__(self):
        self.neutral = np.asarray(self.neutral, dtype=np.float64)
        self.triangles = np.asarray(self.triangles, dtype=np.int64).reshape(-1, 3)
        self.names = [str(n) for n in self.names]
        self.deltas = np.asarray(self.deltas, dtype=np.float64)
        # a rig may have no shapes (e.g. eyes bound to the skeleton only): deltas [0, n, 3]
        self.deltas = (self.deltas.reshape(len(self.names), -1, 3) if self.names
                       else np.zeros((0, len(self.neutral), 3)))
        if self.neutral.ndim != 2 or self.neutral.shape[1] != 3:
            raise GeometryError(f"rig {self.name!r}: neutral must be [n,3], got {self.neutral.shape}")
        if self.deltas.shape[1] != self.neutral.shape[0]:
            raise GeometryError(
                f"rig {self.name!r}: deltas have {self.deltas.shape[1]} vertices, "
                f"neutral {self.neutral.shape[0]}")

    def __repr__(self) -> str:
        # one line: the dataclass repr printed every array (~70 kB for the sample's head in a DCC console)
        ib = f", {len(self.inbetweens)} with inbetweens" if self.inbetweens else ""
        return (f"<FaceRig {self.key or '(unnamed)'}: {self.n_vertices} vertices, "
                f"{len(self.triangles)} triangles, {self.n_shapes} shapes ({_names_brief(self.names)}){ib}>")

    def peak_motion(self) -> np.ndarray:
        """``[n]`` the largest offset of each vertex over the shapes (metres;
        :func:`usdface.motion.peak_motion` of ``deltas``, inbetweens not counted), computed once per offsets
        array and kept while ``deltas`` is that array (a production head's 225k vertices x 51 shapes: ~0.1 s
        a pass, which the face mesh's choice, the crop, the registration and the packing each took).
        Read-only; the rig's offsets are not written in place anywhere (a step that changes them assigns a
        new array, which is measured anew)."""
        from .motion import peak_motion

        peak = self.kept_peak()
        if peak is None:
            peak = peak_motion(self.deltas)
            self.keep_peak(peak)
        return peak

    def kept_peak(self) -> np.ndarray | None:
        """:meth:`peak_motion` if it is kept for the current ``deltas``, else None (nothing computed)."""
        kept = self.__dict__.get("_peak")
        return kept[1] if kept is not None and kept[0]() is self.deltas else None

    def keep_peak(self, peak) -> None:
        """Keep ``peak[n]`` as :meth:`peak_motion` of the current ``deltas`` (a weak reference to them: the
        offsets are not kept alive for it)."""
        import weakref

        peak = np.asarray(peak, dtype=np.float64)
        peak.flags.writeable = False
        self.__dict__["_peak"] = (weakref.ref(self.deltas), peak)

    @property
    def n_vertices(self) -> int:
        return int(self.neutral.shape[0])

    @property
    def key(self) -> str:
        """The mesh's prim path when read from USD, else its name: how meshes are keyed (offsets, regions)."""
        return self.source.prim if self.source else self.name

    @property
    def n_shapes(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        return self.names.index(name)

    def evaluate(self, weights) -> np.ndarray:
        """Deformed points for ``weights[K]`` -> ``[n,3]`` or ``weights[F,K]`` -> ``[F,n,3]``.

        Implements UsdSkel blend-shape semantics, inbetweens included: for a shape with inbetweens at weights
        w_1 < ... < w_m, the offset at weight w interpolates linearly between the neighbouring sub-shapes of
        the sorted list (0 -> zero offset, w_i -> inbetween i, 1 -> primary offset) and extrapolates the end
        segments.
        """
        w = np.asarray(weights, dtype=np.float64)
        single = w.ndim == 1
        w = np.atleast_2d(w)
        out = np.broadcast_to(self.neutral, (w.shape[0],) + self.neutral.shape).copy()
        plain = [k for k, n in enumerate(self.names) if n not in self.inbetweens]
        if plain:
            d = np.asarray(self.deltas)[plain]                  # one matrix product (einsum: 2.5x slower)
            out += (w[:, plain] @ d.reshape(len(plain), -1)).reshape(out.shape)
        for name, ibs in self.inbetweens.items():
            k = self.index(name)
            subs = sorted([(0.0, np.zeros_like(self.neutral))] + [(b.weight, b.offsets) for b in ibs]
                          + [(1.0, self.deltas[k])], key=lambda s: s[0])
            ws = np.array([s[0] for s in subs])
            for f, wf in enumerate(w[:, k]):
                i = int(np.clip(np.searchsorted(ws, wf, side="right") - 1, 0, len(ws) - 2))
                t = (wf - ws[i]) / (ws[i + 1] - ws[i])
                out[f] += (1.0 - t) * subs[i][1] + t * subs[i + 1][1]
        return out[0] if single else out

    def subset(self, names) -> FaceRig:
        """A rig with only the given shapes, in the given order."""
        idx = [self.index(n) for n in names]
        return FaceRig(self.neutral, self.triangles, [self.names[i] for i in idx], self.deltas[idx],
                       {n: v for n, v in self.inbetweens.items() if n in names}, self.source, self.name)


@dataclass
class Avatar:
    """An avatar: every skinned mesh with blend shapes under the SkelRoot(s), plus the stage's metadata."""

    meshes: list[FaceRig]
    file: str = ""
    up_axis: str = "Y"
    meters_per_unit: float = 1.0
    default_prim: str | None = None
    metadata: dict = field(default_factory=dict)
    name_report: dict = field(default_factory=dict)

    def __repr__(self) -> str:
        meshes = ", ".join(f"{m.key} ({m.n_shapes} shapes)" for m in self.meshes)
        return (f"<Avatar {self.file or '(no file)'}: {len(self.meshes)} mesh(es) [{meshes}], "
                f"metersPerUnit {self.meters_per_unit:g}, upAxis {self.up_axis}>")

    def mesh(self, name: str) -> FaceRig:
        """The mesh whose prim name or path is ``name`` (e.g. ``Head`` or ``/Avatar/Head``)."""
        for m in self.meshes:
            if m.name == name or (m.source and (m.source.prim == name or m.source.prim.endswith("/" + name))):
                return m
        raise KeyError(name)


@dataclass
class Frames:
    """Captured expressions: points[F, n, 3] metres, weights[F, K] (columns follow Capture.names),
    role[F] in {'train', 'test'}, label[F] (e.g. '000_eyeBlinkLeft')."""

    points: np.ndarray
    weights: np.ndarray
    role: list[str]
    label: list[str]

    def __post_init__(self):
        self.points = np.asarray(self.points, dtype=np.float64)
        self.weights = np.asarray(self.weights, dtype=np.float64)
        self.role = [str(r) for r in self.role]
        self.label = [str(s) for s in self.label]

    def select(self, role: str) -> Frames:
        idx = [i for i, r in enumerate(self.role) if r == role]
        return Frames(self.points[idx], self.weights[idx], [self.role[i] for i in idx],
                      [self.label[i] for i in idx])

    def __len__(self) -> int:
        return int(self.points.shape[0])


@dataclass
class Capture:
    """A capture session: the person's neutral[n,3], the generic template rig on the same topology, frames.

    ``names`` is the shape order of ``frames.weights`` columns and of ``template.names``.
    """

    neutral: np.ndarray
    triangles: np.ndarray
    template: FaceRig
    frames: Frames
    names: list[str]
    source: str = ""
    metadata: dict = field(default_factory=dict)

    def __post_init__(self):
        self.neutral = np.asarray(self.neutral, dtype=np.float64)
        self.triangles = np.asarray(self.triangles, dtype=np.int64).reshape(-1, 3)

    def __repr__(self) -> str:
        roles = list(self.frames.role)
        return (f"<Capture {self.source or '(no file)'}: {len(self.neutral)} vertices, "
                f"{len(self.names)} shapes ({_names_brief(self.names)}), "
                f"{roles.count('train')} train + {roles.count('test')} test frames>")

    @property
    def train(self) -> Frames:
        return self.frames.select("train")

    @property
    def whole_take(self) -> dict | None:
        """``{"frames", "fps", "times"}`` when this capture is a take read whole (every frame a training
        frame, :func:`usdface.io.take.capture_from_whole_take`), else None."""
        return (self.metadata or {}).get("whole_take") if isinstance(self.metadata, dict) else None

    @property
    def test(self) -> Frames:
        return self.frames.select("test")
