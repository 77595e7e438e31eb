"""The paper's diagnostics of a landmark layout (Zell & McDonnell 2022, Figs. 3 and 5), as per-vertex arrays.

* ``neutral_visibility[n]``: the ambient visibility of the neutral pose alone (Fig. 3, left: the ambient
  occlusion of the neutral expression);
* ``visibility[n]``: the global visibility l_n of eq. 4, the minimum over the neutral and every shape pose;
  ``neutral_visibility - visibility`` is what the expressions hide (Fig. 3, the difference);
* ``displacement[n]``: max over shapes of the relative displacement r_n^k (eq. 2);
* ``importance[n]``: the paper's importance weight w_n^k = c_n^k (2 - q_n^k) (eqs. 1, 3; small = a better
  landmark), the best (smallest) over the shapes vertex n is a candidate for; NaN where it is a candidate for
  none;
* :func:`landmark_importance`: Fig. 5, the importance weights of one landmark's shapes over the face,
  normalised to [0, 1] (nearby vertices of similar weight are nearly as good a place for that landmark).

Pure numpy on ``neutral[n, 3]`` metres, ``triangles[t, 3]``, ``deltas[K, n, 3]`` metres; values are NaN
outside the ``region`` evaluated (the vertices some shape moves by at least ``region_share`` of its peak),
so the ray casting is proportional to the moving face, not to the mesh.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import candidates as cand
from .visibility import FACE_SHARE, PoseVisibility, pose_bases

#: Default share of a shape's peak displacement above which a vertex belongs to the diagnosed region: the
#: face, as the ray offset's face size defines it.
REGION_SHARE = FACE_SHARE


@dataclass
class LandmarkDiagnostics:
    """Per-vertex diagnostics ``[n]`` (NaN outside ``region``), see the module docstring.

    ``region[v]`` the vertex indices evaluated; ``r[K, n]`` relative displacement (eq. 2), ``c[K, n]`` the
    candidate sets (eq. 3) at ``epsilon``; ``alpha`` the visibility weight of eq. 1; ``rays`` per vertex;
    ``camera[3]`` (metres) where visibility was seen from a known camera (``rays`` 1), else None.
    """

    region: np.ndarray
    neutral_visibility: np.ndarray
    visibility: np.ndarray
    displacement: np.ndarray
    importance: np.ndarray
    r: np.ndarray
    c: np.ndarray
    epsilon: float
    alpha: float
    rays: int
    camera: tuple | None = None

    @property
    def hidden(self) -> np.ndarray:
        """``neutral_visibility - visibility`` ``[n]``: how much the expressions occlude a vertex (>= 0)."""
        return self.neutral_visibility - self.visibility


def landmark_diagnostics(neutral: np.ndarray, triangles: np.ndarray, deltas: np.ndarray, epsilon: float = 0.5,
                         alpha: float = 0.5, rays: int = 16, camera=None, region_share: float = REGION_SHARE,
                         on_pose=None, names=None) -> LandmarkDiagnostics:
    """Diagnostics of Zell & McDonnell 2022 (Figs. 3, 5) on the moving region of a rig.

    ``neutral[n, 3]`` metres, ``triangles[t, 3]``, ``deltas[K, n, 3]`` metres; ``epsilon`` (eq. 3), ``alpha``
    (eq. 1), ``rays`` hemisphere rays per vertex or ``camera[3]`` (metres) as in
    :func:`usdface.landmarks.compute_landmarks`; ``region_share`` in (0, 1]: the region evaluated is the
    vertices some shape moves by at least this share of its own peak (relative, so the same surface region at
    every resolution). ``on_pose(done, total)`` is called after each pose's rays (progress). ``names[K]``:
    the shapes' names, so a shape authored over another is seen over it as the layout sees it
    (:func:`usdface.landmarks.visibility.pose_bases`; without names every shape is posed alone).
    """
    eps = cand.check_epsilon(epsilon)
    a = cand.check_alpha(alpha)
    rays = cand.check_rays(rays)
    share = cand.check_epsilon(region_share)
    mag = cand.displacement_magnitudes(deltas)
    r = cand.relative_displacement(mag)
    c = cand.candidate_sets(r, eps)
    peak_r = cand.moving_share(r)
    region = np.flatnonzero(peak_r >= share)
    n = len(neutral)
    vis_all = PoseVisibility(neutral, triangles, deltas, rays, camera, magnitudes=mag,
                             bases=None if names is None else pose_bases(names))
    neutral_vis = np.full(n, np.nan)
    vis = np.full(n, np.nan)
    neutral_vis[region] = vis_all.upper_bound(region)
    vis[region] = vis_all(region, on_pose=on_pose)
    q = cand.landmark_quality(r[:, region], vis[region], a)
    weight = np.where(c[:, region], 2.0 - q, np.inf).min(axis=0, initial=np.inf)
    importance = np.full(n, np.nan)
    importance[region] = np.where(np.isfinite(weight), weight, np.nan)
    displacement = np.full(n, np.nan)
    displacement[region] = peak_r[region]
    return LandmarkDiagnostics(region, neutral_vis, vis, displacement, importance, r, c, eps, a,
                               1 if camera is not None else int(rays),
                               None if camera is None else tuple(float(x) for x in np.ravel(camera)))


def landmark_importance(diagnostics: LandmarkDiagnostics, shapes) -> np.ndarray:
    """Fig. 5 of Zell & McDonnell 2022: the importance weights of one landmark's ``shapes`` (indices ``[s]``)
    at every vertex, the mean over those shapes of w_n^k = c_n^k (2 - q_n^k) with a non-candidate counted at
    the worst weight 2, normalised to [0, 1] over the region (0 = the best place) -> ``[n]``, NaN outside the
    region."""
    d = diagnostics
    ks = np.asarray(shapes, dtype=np.int64).ravel()
    out = np.full(len(d.visibility), np.nan)
    if ks.size == 0 or d.region.size == 0:
        return out
    reg = d.region
    q = cand.landmark_quality(d.r[ks][:, reg], d.visibility[reg], d.alpha)
    w = np.where(d.c[ks][:, reg], 2.0 - q, 2.0).mean(axis=0)
    lo, hi = float(w.min()), float(w.max())
    out[reg] = (w - lo) / (hi - lo) if hi > lo else 0.0
    return out


def diagnostic_panels(diagnostics: LandmarkDiagnostics, vertices, names) -> list[tuple]:
    """The pictures of ``usdface render --landmarks --diagnostics``: ``(title, values[n], colour map, vmin,
    vmax)`` per panel, for the layout ``vertices[m]`` and shape ``names[K]``: neutral and global visibility
    (eq. 4), what the expressions hide, the relative displacement (eq. 2), the best importance weight
    (eq. 1) and Fig. 5's normalised weights of the landmark that represents the most shapes (its panel has a
    sixth item: that landmark's vertex, ringed in the picture)."""
    d = diagnostics
    v = np.asarray(vertices, dtype=np.int64).ravel()
    panels = [
        ("neutral visibility\n" + ("(ambient: fraction of free rays)" if d.camera is None
                                    else "(from the camera: 1 seen, 0 hidden)"), d.neutral_visibility,
         "magma", 0.0, 1.0),
        ("global visibility l\n(eq. 4: min over all poses)", d.visibility, "magma", 0.0, 1.0),
        ("hidden by expressions\n(neutral - global)", d.hidden, "viridis", 0.0, None),
        ("relative displacement r\n(eq. 2, max over shapes)", d.displacement, "viridis", 0.0, 1.0),
        ("importance weight w = 2 - q\n(eq. 1, best over shapes; low = preferred)", d.importance,
         "magma_r", None, None),
    ]
    if v.size:
        counts = d.c[:, v].sum(axis=0)
        best = int(v[int(np.argmax(counts))])
        ks = np.flatnonzero(d.c[:, best])
        label = ", ".join(names[k] for k in ks[:2]) + (f" +{ks.size - 2}" if ks.size > 2 else "")
        # the landmark ringed on its panel (a sixth item): the title named a vertex index, and a TD could
        # not tell which of the dots it was
        panels.append((f"Fig. 5: weights of the ringed landmark ({best})\n({label}), normalised",
                       landmark_importance(d, ks), "magma_r", 0.0, 1.0, best))
    return panels
