"""A procedural head: an analytic surface sampled on two topologies (avatar head, ARKit-like capture mask).

Everything here is in the head's *reference frame*: centimetres, origin at the head centre, Y up, the face
looking down +Z, the subject's left at +X. The surface is a deformed ellipsoid

    base(u, v) = (A(v) sin u cos v,  B sin v,  C cos u cos v)       u = azimuth (0 = front), v = elevation

plus facial features added as smooth Gaussian heights along +Z on the front of the face (so the front's
``x, y`` are exactly the base's ``x, y``: landmarks and the eye openings are simple 2-D shapes there): eye
sockets, brow ridge, nose, cheekbones, lips with a mouth crease, chin. The mouth is a slit along the
elevation row ``v = V_MOUTH`` whose two sides (``side=+1`` upper lip, ``-1`` lower lip) open by a small gap;
the eye openings are holes bounded by an ellipse. Both meshes sample the *same* function of
``(u, v, side)``, so a point of the capture mask and of the avatar head with the same parameters are the
same surface point.

An identity (:func:`identity_warp`) is a smooth, left/right-symmetric displacement field of the reference
points (a few mm: nose, jaw width, cheeks, brows, eye spacing, lips, a global scale), so the template and the
person are different faces on the same parametrisation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Head centre of the avatar in its world (cm, Y up), like the bench avatars.
AVATAR_CENTER = np.array([0.0, 160.0, 2.0])
A0, B0, C0 = 7.4, 11.0, 9.8            # ellipsoid half-axes (cm): width, height, depth
Y_MOUTH = -3.0                           # mouth line (cm)
V_MOUTH = float(np.arcsin(Y_MOUTH / B0))
MOUTH_HALF_WIDTH = 2.4                   # lip corners at x = +-2.4 cm
MOUTH_GAP = 0.16                         # lips parted by 1.6 mm at the centre in the neutral
EYE_CENTER = np.array([3.2, 3.5])        # left eye opening centre (x, y); the right eye is its mirror
EYE_RADII = np.array([1.35, 0.5])        # eye opening half-width, half-height
EYEBALL_RADIUS = 1.2
MIRROR = np.array([-1.0, 1.0, 1.0])

# Facial features: (height cm, centre x, centre y, sigma x, sigma y, mirrored pair)
_FEATURES = (
    (-0.9, 3.2, 3.5, 1.7, 1.2, True),     # eye sockets
    (0.55, 3.0, 5.3, 2.2, 0.75, True),    # brow ridge
    (1.3, 0.0, 1.2, 0.7, 1.9, False),     # nose dorsum
    (1.3, 0.0, -0.6, 0.9, 0.9, False),    # nose tip
    (0.5, 1.2, -1.0, 0.55, 0.55, True),   # alae
    (0.6, 4.0, 1.2, 1.6, 1.3, True),      # cheekbones
    (0.45, 0.0, -2.4, 1.7, 0.55, False),  # upper lip
    (0.45, 0.0, -3.6, 1.5, 0.5, False),   # lower lip
    (-0.25, 0.0, -3.0, 2.2, 0.2, False),  # mouth crease
    (-0.25, 0.0, -4.6, 1.8, 0.4, False),  # mentolabial groove
    (0.7, 0.0, -6.3, 1.7, 1.2, False),    # chin
)


def _width(v):
    """A(v): the lower face is narrower than the cranium."""
    return A0 * (1.0 - 0.14 / (1.0 + np.exp((v + 0.35) / 0.1)))


def _front_weight(z_base):
    """1 on the face, 0 on the sides and back (features live on the front)."""
    t = np.clip((z_base / C0 - 0.15) / 0.45, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def feature_height(x, y):
    """Height (cm, along +Z) of the facial features at base coordinates ``x[n], y[n]``."""
    h = np.zeros_like(x)
    for amp, cx, cy, sx, sy, pair in _FEATURES:
        for sign in ((1.0, -1.0) if pair else (1.0,)):
            h += amp * np.exp(-0.5 * (((x - sign * cx) / sx) ** 2 + ((y - cy) / sy) ** 2))
    return h


def mouth_gap(x):
    """Lip separation (cm) at ``x``: MOUTH_GAP at the centre, 0 at and beyond the corners."""
    return MOUTH_GAP * np.clip(1.0 - (x / MOUTH_HALF_WIDTH) ** 2, 0.0, None)


def surface(u, v, side=None) -> np.ndarray:
    """Reference surface points ``[n,3]`` (cm) at parameters ``u[n], v[n]``; ``side[n]`` in {-1,0,1} picks
    the lower/upper lip on the mouth row (0 elsewhere: the side is then the sign of ``y - Y_MOUTH``)."""
    u, v = np.asarray(u, float), np.asarray(v, float)
    x = _width(v) * np.sin(u) * np.cos(v)
    y = B0 * np.sin(v)
    z = C0 * np.cos(u) * np.cos(v)
    front = _front_weight(z)
    z = z + front * feature_height(x, y)
    s = np.sign(y - Y_MOUTH) if side is None else np.where(np.asarray(side) != 0, side, np.sign(y - Y_MOUTH))
    y = y + s * 0.5 * mouth_gap(x) * np.exp(-(((y - Y_MOUTH) / 0.5) ** 2)) * front
    return np.stack([x, y, z], axis=-1)


def base_to_param(x, y):
    """Front-of-face inverse of the base map: (x, y) -> (u, v)."""
    v = np.arcsin(np.clip(y / B0, -1.0, 1.0))
    u = np.arcsin(np.clip(x / (_width(v) * np.cos(v)), -1.0, 1.0))
    return u, v


def front_point(x, y, side=0) -> np.ndarray:
    """The reference surface point in front of base coordinates (x, y)."""
    u, v = base_to_param(np.atleast_1d(np.asarray(x, float)), np.atleast_1d(np.asarray(y, float)))
    return surface(u, v, np.full(u.shape, side))


def eye_ellipse_radius(x, y, sign=1.0):
    """Normalised radius of (x, y) w.r.t. the eye opening of the eye on side ``sign`` (<1 inside)."""
    return np.hypot((x - sign * EYE_CENTER[0]) / EYE_RADII[0], (y - EYE_CENTER[1]) / EYE_RADII[1])


# ---------------------------------------------------------------------------------------------- meshes
@dataclass
class SampledMesh:
    """A triangulated sampling of the reference surface: ``u, v, side`` per vertex, ``triangles[t,3]`` and
    ``mirror[n]`` (index of the left/right mirror vertex)."""

    u: np.ndarray
    v: np.ndarray
    side: np.ndarray
    triangles: np.ndarray
    mirror: np.ndarray

    def points(self) -> np.ndarray:
        return surface(self.u, self.v, self.side)


def _base_xyz(u, v):
    """Base-ellipsoid coordinates (no features) at parameters (u, v)."""
    return np.stack([_width(v) * np.sin(u) * np.cos(v), B0 * np.sin(v), C0 * np.cos(u) * np.cos(v)], -1)


def _bad_triangles(points, tris, min_quality: float = 0.05) -> np.ndarray:
    """Triangles facing inwards (w.r.t. the ellipsoid normal) or of poor shape (quality < ``min_quality``)."""
    tri = points[tris]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    outward = np.einsum("ij,ij->i", n, tri.mean(1) / np.array([A0, B0, C0]) ** 2) > 0
    edges2 = (np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2) ** 2).sum(1)
    quality = 2.0 * np.sqrt(3.0) * np.linalg.norm(n, axis=1) / np.maximum(edges2, 1e-30)
    return ~outward | (quality < min_quality)


def _grid_mesh(U, V, wrap: bool, keep_cell, pole: bool) -> SampledMesh:
    """Triangulate a (rows x cols) grid of surface parameters ``U[nr, nc], V[nr, nc]``.

    Rows go up (increasing v), columns towards +x; the grid must be mirror-symmetric (column j <-> nc-1-j, or
    (nc-j) % nc when ``wrap``). Cells whose centre (base coordinates) fails ``keep_cell(x, y, z)`` are
    removed; the eye-opening boundaries are snapped onto their ellipses; the mouth row (``V == V_MOUTH``) is
    split into upper/lower lip vertices between the corners. The two diagonals of a quad are chosen
    mirror-symmetrically, so the topology is symmetric.
    """
    nr, nc = U.shape
    u, v = U.ravel().copy(), V.ravel().copy()
    side = np.zeros(nr * nc, dtype=np.int64)
    vid = np.arange(nr * nc).reshape(nr, nc)
    base = _base_xyz(u, v)

    i0, j0 = np.meshgrid(np.arange(nr - 1), np.arange(nc if wrap else nc - 1), indexing="ij")
    i0, j0 = i0.ravel(), j0.ravel()
    j1 = (j0 + 1) % nc
    a, b = vid[i0, j0], vid[i0, j1]
    c, d = vid[i0 + 1, j1], vid[i0 + 1, j0]
    centre = 0.25 * (base[a] + base[b] + base[c] + base[d])
    keep = keep_cell(centre[:, 0], centre[:, 1], centre[:, 2])
    a, b, c, d, i0, centre = a[keep], b[keep], c[keep], d[keep], i0[keep], centre[keep]

    # mouth slit: duplicate the mouth-row vertices between the corners for the lower lip
    rows = np.flatnonzero(np.all(np.abs(V - V_MOUTH) < 1e-12, axis=1))
    assert len(rows) == 1, "the grid must contain the mouth row"
    i_m = int(rows[0])
    row_base = base[vid[i_m]]
    slit_cols = np.flatnonzero((np.abs(row_base[:, 0]) < MOUTH_HALF_WIDTH) & (row_base[:, 2] > 0))
    upper_ids = vid[i_m, slit_cols]
    lower_ids = np.arange(nr * nc, nr * nc + len(slit_cols))
    u = np.concatenate([u, u[upper_ids]])
    v = np.concatenate([v, v[upper_ids]])
    side[upper_ids] = 1
    side = np.concatenate([side, -np.ones(len(slit_cols), np.int64)])
    remap = np.arange(len(u))
    remap[upper_ids] = lower_ids
    below = i0 + 1 == i_m            # cells whose top edge is the mouth row use the lower-lip copies
    c = np.where(below, remap[c], c)
    d = np.where(below, remap[d], d)

    right = centre[:, 0] >= 0
    tris = np.concatenate([
        np.stack([a, b, c], 1)[right], np.stack([a, c, d], 1)[right],
        np.stack([a, b, d], 1)[~right], np.stack([b, c, d], 1)[~right]])
    if pole:
        top = vid[nr - 1]
        pole_id = len(u)
        u = np.append(u, 0.0)
        v = np.append(v, np.pi / 2)
        side = np.append(side, 0)
        tris = np.concatenate([tris, np.stack([top, np.roll(top, -1), np.full(nc, pole_id)], 1)])

    # drop unreferenced vertices (inside holes), keep the order
    used = np.zeros(len(u), bool)
    used[tris.ravel()] = True
    new_index = np.cumsum(used) - 1
    tris = new_index[tris]
    u, v, side = u[used], v[used], side[used]

    # snap the eye-opening boundary onto its ellipse (front vertices on the hole's border)
    edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    uniq, count = np.unique(edges, axis=0, return_counts=True)
    border = np.unique(uniq[count == 1].ravel())
    p = surface(u[border], v[border], side[border])
    u0, v0 = u.copy(), v.copy()
    for sign in (1.0, -1.0):
        r = eye_ellipse_radius(p[:, 0], p[:, 1], sign)
        near = (r < 1.6) & (p[:, 2] > 0)
        ex = sign * EYE_CENTER[0] + (p[near, 0] - sign * EYE_CENTER[0]) / r[near]
        ey = EYE_CENTER[1] + (p[near, 1] - EYE_CENTER[1]) / r[near]
        u[border[near]], v[border[near]] = base_to_param(ex, ey)
    for _ in range(3):  # undo the snap of vertices whose triangles it folds or squashes (near eye corners)
        bad = tris[_bad_triangles(surface(u, v, side), tris)].ravel()
        moved = bad[(u[bad] != u0[bad]) | (v[bad] != v0[bad])]
        if not len(moved):
            break
        u[moved], v[moved] = u0[moved], v0[moved]

    # mirror map: the vertex with parameters (-u, v, side)
    from scipy.spatial import cKDTree

    uw = np.angle(np.exp(1j * u))
    on_seam = np.isclose(np.abs(uw), np.pi)
    key = np.stack([np.where(on_seam, np.pi, uw), v, side], 1)
    mirrored = key * np.array([-1.0, 1.0, 1.0])
    mirrored[on_seam, 0] = np.pi
    dist, mirror = cKDTree(key).query(mirrored)
    assert dist.max() < 1e-9, "mesh is not mirror-symmetric"
    return SampledMesh(u, v, side, tris.astype(np.int64), mirror)


def _symmetric_columns(n: int, warp: float) -> np.ndarray:
    """n (even) azimuths around the head, denser at the front: u = s - warp sin s, s uniform."""
    s = 2 * np.pi * np.arange(n) / n
    s = np.where(s > np.pi, s - 2 * np.pi, s)
    s[n // 2] = np.pi
    return s - warp * np.sin(s)


def _rows(lo: float, hi: float, step: float) -> np.ndarray:
    """Elevation rows from ``lo`` to ``hi`` with the mouth row exactly on the grid."""
    k_lo = int(np.ceil((lo - V_MOUTH) / step))
    k_hi = int(np.floor((hi - V_MOUTH) / step))
    return V_MOUTH + step * np.arange(k_lo, k_hi + 1)


def _outside_eyes(x, y, z):
    return (z <= 0) | ((eye_ellipse_radius(x, y, 1.0) > 1.0) & (eye_ellipse_radius(x, y, -1.0) > 1.0))


def avatar_head_mesh(columns: int = 80, row_step: float = 0.058) -> SampledMesh:
    """The avatar's Head: the whole head from the neck up (open at the neck), eye holes, mouth slit."""
    rows = _rows(-1.2, np.pi / 2 - 0.04, row_step)
    V, U = np.meshgrid(rows, _symmetric_columns(columns, 0.55), indexing="ij")
    return _grid_mesh(U, V, True, _outside_eyes, pole=True)


#: Outline of the capture mask: azimuth half-range ``u0 * (1 - |(y - yc) / b|^p)^(1/p)`` per row (y in cm).
MASK_OUTLINE = {"u0": 1.12, "b": 8.3, "yc": -0.7, "p": 2.6}


def capture_mask_mesh(half_columns: int = 20, row_step: float = 0.54) -> SampledMesh:
    """An ARKit-like face mask: front of the face only, forehead to chin, holes for the eyes and mouth.

    Rows are uniform in y (one on the mouth line); in each row the columns spread evenly in azimuth between
    the two sides of the outline, so the border is smooth.
    """
    o = MASK_OUTLINE
    k = np.arange(int(np.ceil((o["yc"] - 0.96 * o["b"] - Y_MOUTH) / row_step)),
                  int(np.floor((o["yc"] + 0.96 * o["b"] - Y_MOUTH) / row_step)) + 1)
    y = Y_MOUTH + row_step * k
    half = o["u0"] * (1.0 - np.abs((y - o["yc"]) / o["b"]) ** o["p"]) ** (1.0 / o["p"])
    s = np.linspace(-1.0, 1.0, 2 * half_columns + 1)
    U = half[:, None] * s[None, :]
    V = np.repeat(np.arcsin(y / B0)[:, None], len(s), axis=1)
    return _grid_mesh(U, V, False, _outside_eyes, pole=False)


def uv_sphere(center, radius, n_u: int = 16, n_v: int = 10, axis_scale=(1.0, 1.0, 1.0)):
    """A closed UV sphere (poles on the Z axis, front pole at +Z): points[n,3], triangles[t,3]."""
    th = np.linspace(0, np.pi, n_v + 1)[1:-1]
    ph = 2 * np.pi * np.arange(n_u) / n_u
    tt, pp = np.meshgrid(th, ph, indexing="ij")
    ring = np.stack([np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], -1).reshape(-1, 3)
    pts = np.concatenate([[[0, 0, 1.0]], ring, [[0, 0, -1.0]]]) * np.asarray(axis_scale) * radius
    pts = pts + np.asarray(center, float)
    nr = n_v - 1
    idx = 1 + np.arange(nr * n_u).reshape(nr, n_u)
    tris = [np.stack([np.zeros(n_u, int), idx[0, (np.arange(n_u) + 1) % n_u], idx[0]], 1)]
    for i in range(nr - 1):
        a, b = idx[i], idx[i, (np.arange(n_u) + 1) % n_u]
        c, d = idx[i + 1, (np.arange(n_u) + 1) % n_u], idx[i + 1]
        tris += [np.stack([a, b, c], 1), np.stack([a, c, d], 1)]
    last = len(pts) - 1
    tris.append(np.stack([idx[-1], idx[-1, (np.arange(n_u) + 1) % n_u], np.full(n_u, last)], 1))
    tris = np.concatenate(tris)
    # orient outwards
    cen = pts[tris].mean(1) - np.asarray(center, float)
    nrm = np.cross(pts[tris[:, 1]] - pts[tris[:, 0]], pts[tris[:, 2]] - pts[tris[:, 0]])
    flip = np.einsum("ij,ij->i", cen, nrm) < 0
    tris[flip] = tris[flip][:, ::-1]
    return pts, tris


def eyeball_center(sign: float = 1.0) -> np.ndarray:
    """Reference centre of the eyeball on side ``sign`` (+1 left): behind the opening, front flush with it."""
    p = front_point(sign * EYE_CENTER[0], EYE_CENTER[1])[0]
    return p - np.array([0.0, 0.0, EYEBALL_RADIUS - 0.3])


def mouth_block(n_u: int = 18, n_v: int = 10):
    """The teeth/tongue block behind the lips (reference cm): points[n,3], triangles[t,3]."""
    lips = front_point(0.0, Y_MOUTH)[0]
    center = np.array([0.0, Y_MOUTH - 0.3, lips[2] - 2.7])
    return uv_sphere(center, 1.0, n_u, n_v, axis_scale=(2.2, 1.15, 1.8))


# ---------------------------------------------------------------------------------------------- identity
#: Identity modes: (displacement direction, centre xyz, sigma xyz, mirrored pair, std (cm)).
_IDENTITY_MODES = (
    ((0, 0, 1), (0, -0.5, 11.5), (1.2, 2.0, 2.0), False, 0.25),     # nose length
    ((1, 0, 0), (1.2, -1.0, 10.5), (0.7, 0.8, 1.5), True, 0.12),    # nose width
    ((0, -1, 0.4), (0, -6.6, 8.0), (1.8, 1.4, 2.0), False, 0.3),    # chin
    ((1, 0, 0), (5.5, -4.5, 4.0), (2.0, 2.2, 3.0), True, 0.3),      # jaw width
    ((0.6, 0, 0.8), (4.2, 0.5, 7.0), (1.6, 1.6, 2.0), True, 0.2),   # cheek fullness
    ((0, 0, 1), (3.0, 5.3, 8.5), (2.0, 0.9, 2.0), True, 0.2),       # brow prominence
    ((1, 0, 0), (3.2, 3.5, 7.5), (1.6, 1.1, 2.0), True, 0.12),      # eye spacing
    ((0, 1, 0), (3.2, 3.5, 7.5), (1.6, 1.1, 2.0), True, 0.1),       # eye height
    ((0, 0, 1), (0, -3.0, 9.5), (1.8, 0.8, 1.5), False, 0.15),      # lip fullness
    ((0, 0, 1), (0, 7.5, 7.0), (4.0, 2.0, 3.0), False, 0.3),        # forehead slope
    ((1, 0, 0), (6.5, 2.0, 0.0), (2.5, 4.0, 4.0), True, 0.25),      # head width
)


def identity_params(rng: np.random.Generator, scale_std: float = 0.02) -> dict:
    """Random identity: a global scale and one amplitude per identity mode."""
    return {"scale": float(1.0 + scale_std * rng.standard_normal()),
            "amplitudes": [float(std * rng.standard_normal()) for *_, std in _IDENTITY_MODES]}


def identity_warp(points: np.ndarray, params: dict) -> np.ndarray:
    """Apply an identity to reference points ``[n,3]`` (cm): a global scale plus symmetric smooth modes."""
    out = points * params["scale"]
    for (direction, c, s, pair, _), amp in zip(_IDENTITY_MODES, params["amplitudes"], strict=True):
        d = np.asarray(direction, float)
        d = d / np.linalg.norm(d)
        for sign in ((1.0, -1.0) if pair else (1.0,)):
            m = np.array([sign, 1.0, 1.0])
            g = np.exp(-0.5 * np.sum(((points - np.asarray(c) * m) / np.asarray(s)) ** 2, axis=1))
            out = out + amp * g[:, None] * (d * m)
    return out
