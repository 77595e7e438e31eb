"""Eyelid-eyeball repair (Menzel et al. 2022, sec. 3.3, last paragraph): the capture mask has no eyeballs,
so a personalized eyelid shape can push eyelid vertices into the eye; those vertices are moved back onto the
eyeball surface.

Eyeballs are found by name (``eye``/``eyeball`` in the mesh name, not lashes/brows/lids) or by geometry (a
closed, nearly spherical mesh of eyeball size), and modelled by their least-squares sphere.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

__all__ = ["Eyeball", "fit_sphere", "find_eyeballs", "repair_eyelids"]

_EYE_NAME = re.compile(r"eye", re.IGNORECASE)
_NOT_EYE = re.compile(r"lash|brow|lid|socket|shadow|occlusion|tear", re.IGNORECASE)


@dataclass
class Eyeball:
    """A sphere ``center[3]``, ``radius`` (metres) fitted to mesh ``name``; ``rms`` the fit residual (m)."""

    name: str
    center: np.ndarray
    radius: float
    rms: float


def fit_sphere(points) -> tuple[np.ndarray, float, float]:
    """Linear least-squares sphere through ``points[n,3]``: ``(center[3], radius, rms_residual)``."""
    p = np.asarray(points, dtype=np.float64)
    a = np.column_stack([2.0 * p, np.ones(len(p))])
    b = np.einsum("ij,ij->i", p, p)
    sol = np.linalg.lstsq(a, b, rcond=None)[0]
    c = sol[:3]
    r = float(np.sqrt(max(sol[3] + c @ c, 0.0)))
    rms = float(np.sqrt(np.mean((np.linalg.norm(p - c, axis=1) - r) ** 2)))
    return c, r, rms


def find_eyeballs(meshes: dict, *, min_radius: float = 0.007, max_radius: float = 0.02,
                  max_rel_rms: float = 0.12) -> list[Eyeball]:
    """Eyeballs among ``meshes`` = ``{name: points[n,3]}`` (internal metres).

    A mesh qualifies by name (contains "eye" but not lash/brow/lid/...) with a sphere fit of plausible radius,
    or, unnamed, by geometry alone (sphere fit residual below ``max_rel_rms`` x radius, radius in
    [``min_radius``, ``max_radius``]). At most the two best-fitting spheres are returned.
    """
    found = []
    for name, pts in meshes.items():
        pts = np.asarray(pts, dtype=np.float64)
        if len(pts) < 20:
            continue
        c, r, rms = fit_sphere(pts)
        if not (min_radius <= r <= max_radius):
            continue
        leaf = str(name).rsplit("/", 1)[-1]
        named = bool(_EYE_NAME.search(leaf)) and not _NOT_EYE.search(leaf)
        if named and rms < 2 * max_rel_rms * r or rms < max_rel_rms * r:
            found.append(Eyeball(str(name), c, r, rms))
    found.sort(key=lambda e: e.rms / e.radius)
    return found[:2]


def _signed_distance(points, triangles, queries):
    """Signed distance (m, negative inside) and closest points from ``queries[q,3]`` to a closed mesh."""
    import open3d as o3d

    p = np.asarray(points, dtype=np.float64)
    origin = p.mean(axis=0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((p - origin).astype(np.float32)),
                        o3d.core.Tensor(np.asarray(triangles, dtype=np.uint32)))
    q = o3d.core.Tensor((np.asarray(queries, dtype=np.float64) - origin).astype(np.float32))
    d = scene.compute_signed_distance(q).numpy().astype(np.float64)
    c = scene.compute_closest_points(q)["points"].numpy().astype(np.float64) + origin
    return d, c


def repair_eyelids(neutral, shapes, eyeballs, *, reference=None, tolerance: float = 5e-5):
    """Move eyelid vertices that a shape pushes into an eyeball back onto its surface.

    Parameters
    ----------
    neutral : ``[n,3]`` face-mesh neutral (metres).
    shapes : ``[J,n,3]`` personalized offsets.
    eyeballs : list of ``(Eyeball, points[m,3], triangles[t,3])``, closed eye meshes.
    reference : ``[J,n,3]`` the avatar's generic offsets (optional). A vertex may sit as deep inside the
        eyeball as it does in the neutral or in the artist's generic shape (eye sockets and lids that tuck
        behind the eyeball are modelled that way on purpose); only deeper penetration, by more than
        ``tolerance`` m, is an artifact of the personalization.

    A penetrating vertex moves to the closest point on the eyeball surface, pushed back to the allowed depth.
    Returns ``(repaired shapes[J,n,3], number of repaired vertex-shape pairs)``.
    """
    x0 = np.asarray(neutral, dtype=np.float64)
    out = np.array(shapes, dtype=np.float64, copy=True)
    n_shapes = out.shape[0]
    count = 0
    for eye, pts, tris in eyeballs:
        r0 = np.linalg.norm(x0 - eye.center, axis=1)
        near = np.flatnonzero(r0 < 1.5 * eye.radius)
        if near.size == 0:
            continue
        d0, _ = _signed_distance(pts, tris, x0[near])
        allowed = np.broadcast_to(np.minimum(d0, 0.0), (n_shapes, near.size)).copy()
        if reference is not None:
            ref = x0[near][None] + np.asarray(reference)[:, near]
            dref, _ = _signed_distance(pts, tris, ref.reshape(-1, 3))
            allowed = np.minimum(allowed, dref.reshape(n_shapes, -1))
        pos = x0[near][None] + out[:, near]
        d, closest = _signed_distance(pts, tris, pos.reshape(-1, 3))
        d = d.reshape(n_shapes, -1)
        closest = closest.reshape(n_shapes, -1, 3)
        bad = d < allowed - tolerance
        count += int(bad.sum())
        if not bad.any():
            continue
        # closest surface point, then back inside by the allowed depth along the inward direction
        inward = (pos - closest) / np.maximum(-d, 1e-300)[..., None]
        target = closest + inward * (-allowed)[..., None]
        out[:, near] = np.where(bad[..., None], target - x0[near][None], out[:, near])
    return out, count
