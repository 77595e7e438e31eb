"""Pictures of landmark layouts and of the evaluation curve (matplotlib, Agg backend; no USD)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .evaluate import EvaluationReport


def _subplots(figsize):
    """A figure of its own and its axis, saved by its own canvas: pyplot with ``matplotlib.use("Agg")``
    switched the host's backend (a notebook's, a DCC's) and closed its figures."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize)
    return fig, fig.subplots()


def plot_layout(neutral: np.ndarray, layout, path, title: str = "Landmark layout",
                force: bool = False, triangles: np.ndarray | None = None) -> None:
    """Front view (X right, Y up) of ``neutral[n, 3]`` with the layout's landmarks coloured by multi-cover
    round and labelled with the number of shapes each represents -> PNG at ``path``. With the mesh's
    ``triangles[t, 3]`` the points drawn are those whose normal faces the viewer (+Z); without, the front
    60 % in Z (all of a thin mesh)."""
    p = np.asarray(neutral)
    v = np.asarray(layout.vertices, dtype=np.int64)
    front = p[:, 2] > np.percentile(p[:, 2], 40)        # a head: its face half, not the back of it
    facing = None
    if triangles is not None and len(triangles):
        from ..mesh import vertex_normals

        # a capture mask (no back to hide) lost 40 % of its points, its cheeks drawn half empty
        facing = vertex_normals(p, np.asarray(triangles, dtype=np.int64).reshape(-1, 3))[:, 2] > 0.0
    if facing is not None and facing.mean() >= 0.1:     # not a mesh wound the other way round
        front = facing
    elif np.ptp(p[:, 2]) < 0.25 * max(float(np.ptp(p[:, 0])), float(np.ptp(p[:, 1]))):
        # a thin mesh (a mask, Pixar's blend-shape test plane) has no back: every point (the 40 % cut drew
        # a flat plane's landmark off the points drawn, or no point at all)
        front = np.ones(len(p), dtype=bool)
    fig, ax = _subplots((5, 6))
    ax.scatter(p[front, 0], p[front, 1], s=0.3, color="0.75")
    sc = ax.scatter(p[v, 0], p[v, 1], c=np.asarray(layout.rounds), cmap="autumn", s=40, edgecolors="k",
                    zorder=3)
    for i, n in zip(v, np.asarray(layout.coverage).sum(axis=1), strict=True):
        ax.annotate(str(int(n)), p[i, :2], fontsize=6, xytext=(3, 3), textcoords="offset points")
    rounds = int(np.asarray(layout.rounds).max(initial=1))
    if rounds > 1:
        # whole rounds only: the bar's default ticks read 1.25, 1.75, 2.25 ... (a trial's note)
        fig.colorbar(sc, ax=ax, label="multi-cover round", ticks=np.arange(1, rounds + 1))
    # what the figure beside each dot is: a trial's TD could not tell (a vertex index? a rank?)
    ax.set_xlabel("number beside a landmark: the shapes it represents"
                  + ("; symmetric layout" if getattr(layout, "symmetric", False) else ""), fontsize=8)
    if v.size:  # frame the face around the landmarks
        lo, hi = p[v, :2].min(axis=0), p[v, :2].max(axis=0)
        if float((hi - lo).max()) <= 1e-9:
            # one landmark (or all on one point): the frame was 0.4 mm around it, a dot on a blank panel
            lo, hi = p[front, :2].min(axis=0), p[front, :2].max(axis=0)
        pad = 0.4 * max(float((hi - lo).max()), 1e-3)
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.set_title(f"{title}: {layout.count} landmarks, eps {layout.epsilon:g}")
    ax.set_xticks([])
    ax.set_yticks([])
    fig.tight_layout()
    _save(fig, path, force)


def plot_evaluation(report: EvaluationReport, path, title: str = "Landmark layouts",
                    force: bool = False) -> None:
    """Reconstruction RMSE (mm) vs number of landmarks, one curve per method (matplotlib, Agg) -> ``path``."""
    fig, ax = _subplots((7, 4.5))
    styles = {"ours": ("tab:red", "o", "this method (best with at most N)"),
              "pca_kmeans": ("tab:blue", "s", "PCA + k-means (Cohen 2002)"),
              "delta_cluster": ("tab:green", "^", "delta clustering (Reverdy 2015)"),
              "random": ("tab:gray", ".", "random")}
    for method, (color, marker, label) in styles.items():
        pts = [p for p in report.points if p.method == method]
        if not pts:
            continue
        if method == "ours":
            ax.scatter([p.count for p in pts], [p.rmse * 1e3 for p in pts], color=color, alpha=0.25, s=12)
            counts = sorted({p.count for p in pts})
            best = [min(q.rmse for q in pts if q.count <= c) for c in counts]
            ax.plot(counts, np.array(best) * 1e3, color=color, marker=marker, label=label)
        else:
            pts = sorted(pts, key=lambda p: p.count)
            ax.plot([p.count for p in pts], [p.rmse * 1e3 for p in pts], color=color, marker=marker,
                    label=label, alpha=0.8)
    for p in (q for q in report.points if q.method == "empirical"):
        ax.scatter([p.count], [p.rmse * 1e3], color="black", marker="*", s=120, zorder=5,
                   label=f"empirical {p.count} points")
        ax.axhline(p.rmse * 1e3, color="black", lw=0.6, ls="--")
    ax.set_xlabel("number of landmarks")
    ax.set_ylabel(f"reconstruction RMSE (mm), {report.noise * 1e3:g} mm tracking noise")
    ax.set_yscale("log")
    from matplotlib.ticker import FuncFormatter

    # the errors span about one decade, so most labels are minor ticks: plain numbers (0.3, 2, at 1, 2, 3
    # and 5 of each decade), not matplotlib's default 3x10^-1 and 2x10^0
    def plain(v, _pos, marks=(1, 2, 3, 5)):
        return f"{v:g}" if v > 0 and round(v / 10 ** np.floor(np.log10(v)), 6) in marks else ""

    ax.yaxis.set_major_formatter(FuncFormatter(plain))
    ax.yaxis.set_minor_formatter(FuncFormatter(plain))
    ax.set_title(f"{title} ({report.frames} frames)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    _save(fig, path, force)


def _save(fig, path, force: bool) -> None:
    """Save ``fig`` as PNG atomically (never over an existing file unless ``force``)."""
    from ..io.atomic import atomic_file

    with atomic_file(path, force=force) as tmp:
        fig.savefig(str(tmp), dpi=120, format="png")
