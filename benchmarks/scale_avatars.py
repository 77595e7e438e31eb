"""Production-size avatars built from a bench avatar (dev1), for ``bench_scale.py`` (issue 12).

    from scale_avatars import build_scale_avatars
    paths = build_scale_avatars(dev1_avatar, cache_dir)    # {"dev1": ..., "subdiv1": ..., ...}

Variants (each a valid UsdSkel avatar written with :func:`usdface.io.avatar_writer.write_rig_usd`, metres in,
the source's cm / Y-up on disk, eyes kept as static meshes):

* ``subdiv1`` / ``subdiv2``: the ``Head`` mesh subdivided once / twice by linear midpoint subdivision (every
  triangle into four, one new vertex per edge, no smoothing). The original vertices keep their indices and
  come first, so per-vertex results on them compare directly with the source's; the new vertices' points and
  offsets are the midpoints of their edge's (the shapes are the same piecewise-linear surfaces).
* ``body``: the source avatar plus a separate ~300k-vertex ``Body`` mesh (a closed tube under the head) with
  three sparse neck shapes (``jawOpen``, ``mouthClose``, ``jawForward``, a few mm over the top 4 cm).
* ``merged``: ``Head`` and that body as one mesh named ``Head`` (head vertices first, same indices), the
  body's vertices static except the three neck shapes: a full-body avatar whose face is 4 % of its mesh.

Builds are cached under ``cache_dir/<key>/`` (the key hashes the source file and :data:`BUILDER_VERSION`), so
re-running a benchmark reuses them. Nothing here is written into the repository.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

#: Bump when the construction changes, so cached avatars are rebuilt.
BUILDER_VERSION = 1
#: Vertices of the synthetic body mesh (rows x columns of the tube).
BODY_ROWS, BODY_COLUMNS = 500, 600
#: The body's neck shapes: offset (metres) at the top of the neck.
NECK_SHAPES = {"jawOpen": (0.0, -0.003, 0.002), "mouthClose": (0.0, 0.001, 0.0),
               "jawForward": (0.0, 0.0, 0.003)}
VARIANTS = ("subdiv1", "subdiv2", "body", "merged")


def midpoint_subdivide(points: np.ndarray, triangles: np.ndarray, deltas: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One step of linear midpoint subdivision: ``points[n,3]``, ``triangles[t,3]``, ``deltas[K,n,3]`` ->
    ``(points[n+e,3], triangles[4t,3], deltas[K,n+e,3])``; vertex ``i < n`` is the original vertex ``i``,
    vertex ``n + j`` the midpoint of unique edge ``j`` (points and offsets averaged)."""
    tri = np.asarray(triangles, dtype=np.int64)
    n = len(points)
    pairs = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    edges, inverse = np.unique(pairs, axis=0, return_inverse=True)
    mid = n + inverse.reshape(3, -1)  # [3, t]: edge 01, 12, 20 of each triangle
    a, b, c = tri.T
    m01, m12, m20 = mid
    new_tri = np.concatenate([np.stack([a, m01, m20], 1), np.stack([m01, b, m12], 1),
                              np.stack([m20, m12, c], 1), np.stack([m01, m12, m20], 1)])
    new_points = np.concatenate([points, 0.5 * (points[edges[:, 0]] + points[edges[:, 1]])])
    new_deltas = np.concatenate([deltas, 0.5 * (deltas[:, edges[:, 0]] + deltas[:, edges[:, 1]])], axis=1)
    return new_points, new_tri, new_deltas


def body_mesh(top: float, rows: int = BODY_ROWS, columns: int = BODY_COLUMNS
              ) -> tuple[np.ndarray, np.ndarray]:
    """A closed tube (neck, shoulders, torso) from y = top - 1.2 m up to ``top`` metres, elliptic sections:
    ``points[rows*columns + 2, 3]`` metres, ``triangles[t, 3]`` (outward, capped)."""
    y = np.linspace(top - 1.2, top, rows)
    s = (top - y) / 1.2  # 0 at the neck top, 1 at the bottom
    half_width = 0.055 + 0.13 / (1.0 + np.exp(-(s - 0.12) * 40.0)) - 0.03 * s
    half_depth = 0.05 + 0.06 / (1.0 + np.exp(-(s - 0.12) * 40.0))
    phi = np.linspace(0.0, 2.0 * np.pi, columns, endpoint=False)
    x = half_width[:, None] * np.sin(phi)[None]
    z = 0.01 + half_depth[:, None] * np.cos(phi)[None]
    pts = np.stack([x, np.broadcast_to(y[:, None], x.shape), z], axis=2).reshape(-1, 3)
    pts = np.concatenate([pts, [[0.0, y[0], 0.01], [0.0, y[-1], 0.01]]])
    r, c = np.meshgrid(np.arange(rows - 1), np.arange(columns), indexing="ij")
    v00 = r * columns + c
    v01 = r * columns + (c + 1) % columns
    v10, v11 = v00 + columns, v01 + columns
    quads = np.concatenate([np.stack([v00, v01, v11], -1).reshape(-1, 3),
                            np.stack([v00, v11, v10], -1).reshape(-1, 3)])
    ring0, ring1 = np.arange(columns), (rows - 1) * columns + np.arange(columns)
    bottom, cap = rows * columns, rows * columns + 1
    caps = np.concatenate([np.stack([np.full(columns, bottom), np.roll(ring0, -1), ring0], 1),
                           np.stack([np.full(columns, cap), ring1, np.roll(ring1, -1)], 1)])
    return pts, np.concatenate([quads, caps])


def neck_deltas(points: np.ndarray, top: float, names: list[str]) -> np.ndarray:
    """``[K, n, 3]`` metres: the :data:`NECK_SHAPES` offsets on body ``points`` within 4 cm of ``top``,
    fading smoothly to zero; zero for every other shape in ``names``."""
    fade = np.clip(1.0 - (top - points[:, 1]) / 0.04, 0.0, 1.0)
    fade = fade * fade * (3.0 - 2.0 * fade)
    out = np.zeros((len(names), len(points), 3))
    for name, offset in NECK_SHAPES.items():
        if name in names:
            out[names.index(name)] = fade[:, None] * np.asarray(offset)[None]
    return out


def _rig(neutral, triangles, names, deltas, name):
    from usdface.model import FaceRig

    return FaceRig(neutral, triangles, names, deltas, name=name)


def _static_rigs(avatar) -> list:
    rigs = []
    for prim, (points, triangles) in avatar.metadata.get("static_meshes", {}).items():
        rigs.append(_rig(points, triangles, [], np.zeros((0, len(points), 3)), prim.rsplit("/", 1)[-1]))
    return rigs


def variant_rigs(avatar, variant: str) -> list:
    """The meshes (:class:`usdface.model.FaceRig`, metres) of ``variant`` built from ``avatar`` (dev1)."""
    head = avatar.mesh("Head")
    others = [_rig(m.neutral, m.triangles, m.names, m.deltas, m.name) for m in avatar.meshes
              if m.name != "Head"] + _static_rigs(avatar)
    if variant == "dev1":
        return [_rig(head.neutral, head.triangles, head.names, head.deltas, "Head")] + others
    if variant in ("subdiv1", "subdiv2"):
        p, t, d = head.neutral, head.triangles, head.deltas
        for _ in range(1 if variant == "subdiv1" else 2):
            p, t, d = midpoint_subdivide(p, t, d)
        return [_rig(p, t, head.names, d, "Head")] + others
    top = float(head.neutral[:, 1].min()) - 0.002
    bp, bt = body_mesh(top)
    if variant == "body":
        names = [n for n in head.names if n in NECK_SHAPES]
        body = _rig(bp, bt, names, neck_deltas(bp, top, names), "Body")
        return [_rig(head.neutral, head.triangles, head.names, head.deltas, "Head")] + others + [body]
    if variant == "merged":
        n = head.n_vertices
        deltas = np.concatenate([head.deltas, neck_deltas(bp, top, head.names)], axis=1)
        merged = _rig(np.concatenate([head.neutral, bp]), np.concatenate([head.triangles, bt + n]),
                      head.names, deltas, "Head")
        return [merged] + others
    raise ValueError(f"unknown variant {variant!r}; use dev1 or one of {', '.join(VARIANTS)}")


def cache_key(source: Path) -> str:
    """Hash of the source avatar's bytes and :data:`BUILDER_VERSION`."""
    h = hashlib.sha256(f"scale-avatars-v{BUILDER_VERSION}".encode())
    h.update(Path(source).read_bytes())
    return h.hexdigest()[:16]


def build_scale_avatars(source: Path, cache_dir: Path, variants=VARIANTS, log=print) -> dict[str, Path]:
    """Write (or reuse) ``cache_dir/<key>/<variant>.usdc`` for each of ``variants``; returns {variant: path}.
    (``"dev1"`` rewrites ``source``'s own meshes through the same writer, for checking the writer.)"""
    from usdface.io.avatar_writer import write_rig_usd
    from usdface.io.usd_rig import read_avatar

    folder = Path(cache_dir) / cache_key(source)
    folder.mkdir(parents=True, exist_ok=True)
    out, avatar = {}, None
    for variant in variants:
        path = folder / f"{variant}.usdc"
        if not path.exists():
            if avatar is None:
                avatar = read_avatar(source)
            rigs = variant_rigs(avatar, variant)
            write_rig_usd(rigs, path, up_axis=avatar.up_axis, meters_per_unit=avatar.meters_per_unit)
            log(f"built {path} ({sum(r.n_vertices for r in rigs):,} vertices)")
        out[variant] = path
    return out
