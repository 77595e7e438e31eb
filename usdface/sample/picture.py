"""A picture of the sample avatar (neutral and a few expressions) for the README, drawn with matplotlib."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..model import FaceRig

#: Expressions shown next to the neutral: title -> {shape: weight}.
SHOWCASE = {
    "neutral": {},
    "jawOpen": {"jawOpen": 0.8},
    "smile": {"mouthSmileLeft": 1.0, "mouthSmileRight": 1.0, "cheekSquintLeft": 0.4, "cheekSquintRight": 0.4},
    "blink + browInnerUp": {"eyeBlinkLeft": 1.0, "eyeBlinkRight": 1.0, "browInnerUp": 1.0},
    "capture mask (person)": None,
}
_COLORS = {"Head": (0.86, 0.70, 0.60), "Mouth": (0.75, 0.38, 0.40)}
_LIGHT = np.array([0.35, 0.45, 1.0]) / np.linalg.norm([0.35, 0.45, 1.0])


def _draw(ax, meshes, edges=False):
    """One depth-sorted collection for all ``meshes`` [(points[n,3], triangles[t,3], rgb)], Lambert-shaded."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    tri = np.concatenate([p[t] for p, t, _ in meshes])
    rgb = np.concatenate([np.tile(c, (len(t), 1)) for _, t, c in meshes])
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
    shade = np.clip(n @ _LIGHT, 0.0, 1.0) * 0.7 + 0.3
    faces = rgb * shade[:, None]
    ax.add_collection3d(Poly3DCollection(tri[:, :, [0, 2, 1]], facecolors=faces,
                                         edgecolors=(0, 0, 0, 0.25) if edges else faces, linewidths=0.15))


def _frame(ax, center, half):
    ax.set_xlim(center[0] - half, center[0] + half)
    ax.set_ylim(center[2] - half, center[2] + half)
    ax.set_zlim(center[1] - half, center[1] + half)
    ax.set_box_aspect((1, 1, 1), zoom=1.35)   # the 3D axes' margins left the head a quarter of its panel
    ax.view_init(elev=8, azim=62)
    ax.set_axis_off()


def sample_title(meta: dict) -> str:
    """What a sample picture shows, from the build's ``meta`` (:func:`usdface.sample.build_samples`): the
    seed, the capture's template and the frames' noise, which tell one sample's picture from another's (a
    ``--seed 3 --template artist`` picture looked like the default sample's, stop 43)."""
    noise = meta.get("noise") or {}
    scan_mm, weights = 1e3 * float(noise.get("scan_m", 0.0)), float(noise.get("weights", 0.0))
    return (f"usdface sample, seed {meta.get('seed', 0)}: {meta.get('template', 'generic')} template, scan "
            f"noise {scan_mm:g} mm, weight noise {weights:g}\nthe avatar neutral and in expressions; the "
            "person's capture mask")


def render_sample_picture(rigs: list[FaceRig], capture_points, capture_triangles, path,
                          force: bool = True, title: str | None = None) -> Path:
    """Write a PNG: the avatar (Head, Mouth, eyes; cm) neutral and in :data:`SHOWCASE` expressions, and the
    capture mask (metres, scaled for display), under ``title`` (:func:`sample_title`) when given, in a band
    of its own above the panels. ``rigs`` as built by :func:`usdface.sample.build_samples`. Atomic (temp +
    rename); an existing file is replaced only with ``force``."""
    from matplotlib.figure import Figure  # its own canvas: the host's backend and figures left alone

    path = Path(path)
    head = next(r for r in rigs if r.name == "Head")
    center = head.neutral.mean(0) * 100 + np.array([0, 1.0, 0])
    band = 0.55 if title else 0.0           # inches for the title's two lines: the panels kept as they were
    fig = Figure(figsize=(3.2 * len(SHOWCASE), 3.8 + band), dpi=100)
    for i, (label, weights) in enumerate(SHOWCASE.items()):
        ax = fig.add_subplot(1, len(SHOWCASE), i + 1, projection="3d")
        if weights is None:
            pts = np.asarray(capture_points) * 100.0
            _draw(ax, [(pts, capture_triangles, (0.62, 0.72, 0.86))], edges=True)
            _frame(ax, pts.mean(0), 10.5)
        else:
            meshes = []
            for rig in rigs:
                w = np.array([weights.get(n, 0.0) for n in rig.names])
                pts = (rig.evaluate(w) if rig.n_shapes else rig.neutral) * 100.0
                meshes.append((pts, rig.triangles, _COLORS.get(rig.name, (0.95, 0.95, 0.93))))
            _draw(ax, meshes)
            _frame(ax, center, 10.5)
        ax.set_title(label, fontsize=11)
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.92 * 3.8 / (3.8 + band), wspace=0)
    if title:
        fig.suptitle(title, fontsize=11, y=1.0 - 0.08 / (3.8 + band), va="top")
    from ..io.atomic import atomic_file

    with atomic_file(path, force=force) as tmp:
        fig.savefig(tmp, metadata={"Software": None}, format="png")
    return path
