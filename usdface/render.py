"""Pictures of face rigs without a display (matplotlib, Agg backend): neutral and selected shapes, generic vs
personalized side by side, per-vertex heat maps, landmarks.

Arrays in, PNG out; no USD here (``usdface render`` reads the files and calls these). Meshes are drawn as an
orthographic view of flat-shaded triangles, back faces culled and the rest painted far-to-near (painter's
algorithm), which is exact for the convex-ish, single-sheet face meshes usdface handles.

Conventions: ``points[n, 3]`` metres, internal frame (Y up, the face looking down +Z, as the readers produce);
``triangles[t, 3]``; ``values[n]`` per-vertex scalars (e.g. error in metres, drawn in millimetres).

Example::

    from usdface.render import render_shapes
    render_shapes(rig, ["jawOpen", "eyeBlinkLeft"], "shapes.png")
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import UsdFaceError, warn

#: View name -> rotation applied to points before dropping z (camera looks down -z of the rotated frame).
VIEWS = {
    "front": np.eye(3),
    "left": np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]),   # camera on the person's left
    "right": np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
}
_LIGHT = np.array([0.35, 0.45, 1.0]) / np.linalg.norm([0.35, 0.45, 1.0])
_SKIN = np.array([0.86, 0.74, 0.66])


def _figure(n_panels: int, ncols: int | None = None, size: float = 3.2):
    # a Figure of its own, saved by its own canvas: no matplotlib.use, which switched the host's backend
    # (and, with pyplot imported, closed the host's figures)
    from matplotlib.figure import Figure

    ncols = ncols or min(n_panels, 4)
    nrows = int(np.ceil(n_panels / ncols))
    # "compressed": equal-aspect panels packed without the blank bands their grid cells left between the
    # rows and under the figure's title (a trial's note on render --compare and --diagnostics)
    fig = Figure(figsize=(size * ncols, size * 1.15 * nrows), dpi=100, layout="compressed")
    axes = [fig.add_subplot(nrows, ncols, i + 1) for i in range(n_panels)]
    for ax in axes:
        ax.set_aspect("equal")
        ax.set_axis_off()
    return fig, axes


def display_mesh(points, triangles, max_vertices: int | None = None, *, view: str = "front", frame=None):
    """``(keep, triangles)`` of the decimated copy a mesh of more than ``max_vertices`` vertices (default
    :data:`usdface.mesh.DISPLAY_MAX_VERTICES`; 0: no limit) is drawn on (:func:`usdface.mesh.display_subset`:
    a subset of its own vertices), for ``draw_mesh(..., display=...)``; ``None`` for a smaller mesh. Made
    once from the neutral and used for every pose of the mesh. ``frame``: ``(lo[2], hi[2])`` in ``view``'s
    plane the picture is cut to (a face on a head-and-body mesh, :func:`moving_region`): such a mesh drops
    the triangles beyond it first and is decimated only if the rest is still over the limit (the face drawn
    with every vertex; the body's decimation cost most of the picture)."""
    from .mesh import DISPLAY_MAX_VERTICES, display_subset, triangles_in_box

    limit = DISPLAY_MAX_VERTICES if max_vertices is None else int(max_vertices)
    visible = None
    if frame is not None and 0 < limit < len(points):
        xy = (np.asarray(points, dtype=np.float64) @ VIEWS[view].T)[:, :2]
        visible = triangles_in_box(xy, triangles, *frame)
    return display_subset(points, triangles, limit, visible=visible)


def crop_frame(points, crop, view: str = "front", pad: float = 0.04):
    """The frame ``(lo[2], hi[2])`` :func:`draw_mesh` gives the ``crop`` vertices of ``points`` in ``view``'s
    plane (their box with a margin of ``pad`` times its extent); ``None`` without a crop (the whole mesh)."""
    if crop is None or not len(crop):
        return None
    xy = (np.asarray(points, dtype=np.float64)[np.asarray(crop, dtype=np.int64)] @ VIEWS[view].T)[:, :2]
    return _with_margin(xy.min(axis=0), xy.max(axis=0), pad)


def moving_region(deltas, tolerance: float = 1e-6) -> np.ndarray | None:
    """The vertices that shapes ``deltas[K, n, 3]`` move by more than ``tolerance`` (metres), to frame the
    view on when they are less than half of the mesh (a face on a head-and-body mesh: the face was a few
    per cent of a picture of the whole body, and the panels' titles ran into each other); ``None`` when
    they are most of it, or nothing moves."""
    deltas = np.asarray(deltas)
    if deltas.ndim != 3 or not deltas.shape[0] or not deltas.shape[1]:
        return None
    moved = np.zeros(deltas.shape[1], dtype=bool)
    for d in deltas:                                         # shape by shape: no [K, n, 3] temporaries
        moved |= np.abs(d).max(axis=1) > tolerance
        if moved.sum() >= 0.5 * deltas.shape[1]:             # most of the mesh already: the answer is None
            return None                                      # (a head: after a shape or two, not 51)
    count = int(moved.sum())
    return np.flatnonzero(moved) if 0 < count < 0.5 * deltas.shape[1] else None


def draw_mesh(ax, points, triangles, *, values=None, cmap="magma", vmin=None, vmax=None, view="front",
              color=_SKIN, display=None, crop=None, pad: float = 0.04, frame=None):
    """Draw ``points[n,3]``/``triangles[t,3]`` on a matplotlib axis, flat shaded (``values[n]`` -> colour
    map with shading; faces with a NaN value drawn as plain skin). ``display``: ``(keep, triangles)`` of
    :func:`display_mesh`, drawn instead of the full mesh (``points[keep]``, ``values[keep]``). ``crop``:
    vertex indices of ``points`` the view is framed on (:func:`moving_region`; default the whole mesh), with
    a margin of ``pad`` times its extent; ``frame``: ``(lo[2], hi[2])`` in the view's plane, the limits of a
    picture whose panels share one (:func:`shared_frame`), instead. Returns the ``PolyCollection`` (a
    colour-bar mappable when ``values`` is given)."""
    from matplotlib.collections import PolyCollection

    from .mesh import index_set

    framed = None
    if crop is not None and len(crop):
        framed = np.asarray(points, dtype=np.float64)[np.asarray(crop, dtype=np.int64)]
        framed = (framed @ VIEWS[view].T)[:, :2]
    if display is not None:
        keep, triangles = display
        points = np.asarray(points)[keep]
        values = None if values is None else np.asarray(values).ravel()[keep]
    rot = VIEWS[view]
    p = np.asarray(points, dtype=np.float64) @ rot.T
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    corners = p[tri]                                            # [t, 3, 3]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    length = np.linalg.norm(normals, axis=1)
    ok = length > 0
    normals[ok] /= length[ok, None]
    front = ok & (normals[:, 2] > 0.0)
    if len(tri) and not front.any():
        # every face edge-on or turned away (Pixar's Z-up test plane, lying flat once Y is up): the panel
        # came out blank and nothing said why

        warn(f"no face of the mesh faces the camera in the {view} view (it is seen edge-on or "
             "from behind: the face is expected to look down +Z with Y up, after the file's up "
             "axis); its panel is empty (check the file's upAxis; --view left or right shows a face "
             "turned sideways)")
    order = np.argsort(corners[front][:, :, 2].mean(axis=1))    # far to near
    faces = np.flatnonzero(front)[order]
    shade = 0.35 + 0.65 * np.clip(normals[faces] @ _LIGHT, 0.0, 1.0)
    if values is not None:
        import matplotlib

        vals = np.asarray(values, dtype=np.float64)[tri[faces]].mean(axis=1)
        known = np.isfinite(vals)  # NaN (not evaluated): plain shaded skin
        lo = (np.min(vals[known]) if known.any() else 0.0) if vmin is None else vmin
        hi = (np.max(vals[known]) if known.any() else 1.0) if vmax is None else vmax
        norm = matplotlib.colors.Normalize(lo, hi if hi > lo else lo + 1e-12)
        rgb = matplotlib.colormaps[cmap](norm(np.where(known, vals, lo)))[:, :3]
        rgb = rgb * (0.55 + 0.45 * shade[:, None])
        rgb[~known] = 0.8 * np.asarray(color)[None, :] * shade[~known, None]
    else:
        rgb = np.asarray(color)[None, :] * shade[:, None]
    coll = PolyCollection(corners[faces][:, :, :2], facecolors=np.clip(rgb, 0, 1), edgecolors="none",
                          antialiased=False)
    if values is not None:
        coll.set_cmap(cmap)
        coll.set_norm(norm)
        coll.set_array(None)
    ax.add_collection(coll)
    if frame is None:
        xy = framed if framed is not None else p[index_set(tri, len(p))][:, :2] if len(tri) else p[:, :2]
        frame = _with_margin(xy.min(axis=0), xy.max(axis=0), pad)
    (x0, y0), (x1, y1) = frame
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    return coll


def _with_margin(lo, hi, pad: float):
    margin = pad * float(np.max(hi - lo) or 1.0)
    return lo - margin, hi + margin


def shared_frame(poses, triangles, view: str = "front", crop=None, pad: float = 0.04):
    """The view limits ``(lo[2], hi[2])`` (metres, in the view's plane) that hold every pose of ``poses``
    (an iterable of ``points[n, 3]`` of one mesh, ``triangles[t, 3]``): its vertices in a triangle, or the
    ``crop`` vertices (:func:`moving_region`), with a margin of ``pad`` times the extent. The panels of one
    picture drawn in it share one length scale: each was framed on its own pose, so a shape that moves a lot
    (the bench Mouth's jawOpen, 42 mm) was drawn smaller than the neutral beside it."""
    from .mesh import index_set

    rot = VIEWS[view]
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    for points in poses:
        points = np.asarray(points, dtype=np.float64)
        keep = (np.asarray(crop, dtype=np.int64) if crop is not None and len(crop)
                else index_set(tri, len(points)) if len(tri) else slice(None))
        xy = (points[keep] @ rot.T)[:, :2]
        lo, hi = np.minimum(lo, xy.min(axis=0)), np.maximum(hi, xy.max(axis=0))
    return _with_margin(lo, hi, pad)


def save_figure(fig, out, force: bool = False) -> Path:
    """Save a figure as PNG atomically (temp file + rename); refuses an existing file (or a link to nothing)
    unless ``force`` (:func:`usdface.io.atomic.refuse_existing`)."""
    from .io.atomic import atomic_file, refuse_existing

    out = Path(out)
    refuse_existing(out, force, "picture")

    with atomic_file(out, force=force) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
    return out


def resolve_shape(rig, name: str) -> str | None:
    """The rig's name for a shape asked as ``name``: itself, the canonical ARKit name of the channel the
    mesh authors as ``name`` (a studio's own channel name read through a name map), or the ARKit name
    ``name`` spells another way (``eyeBlink_L``, ``JawOpen``: the spellings every reader accepts); None if
    none of these."""
    from .arkit import normalize_name

    if name in rig.names:
        return name
    tokens = list(rig.source.channel_tokens) if rig.source is not None else []
    if name in tokens and len(tokens) == len(rig.names):
        return rig.names[tokens.index(name)]
    canonical = normalize_name(name)
    return canonical if canonical in rig.names else None


def check_shapes(rig, names, path=None) -> None:
    """Refuse (RigError naming ``path`` -- else the rig's file --, the mesh prim and the shapes it has) a
    shape name ``rig`` lacks (by its name or the channel name the mesh authors, :func:`resolve_shape`), before
    anything is drawn. An ARKit name asked of a rig whose shapes are not ARKit-named (a studio's own names)
    points at ``--name-map``."""
    from .arkit import ARKIT_SET
    from .errors import RigError

    for name in names or ():
        if resolve_shape(rig, name) is not None:
            continue
        import difflib

        more = " ..." if rig.n_shapes > 8 else ""
        close = difflib.get_close_matches(name, list(rig.names), n=1, cutoff=0.75)   # a typo: jawOpn
        fix = ((f"did you mean {close[0]}? " if close else "")
               + f"choose from {', '.join(rig.names[:8])}{more}")
        if name in ARKIT_SET and not ARKIT_SET & set(rig.names):
            fix += ("; the mesh's shapes have the studio's own names: name them as ARKit shapes with "
                    "--name-map FILE (docs/names.md) or pass the studio names")
        source = rig.source
        raise RigError(f"mesh {rig.name or ''} has no shape {name!r}",
                       path=path if path is not None else (source.file if source else None),
                       prim=source.prim if source else None, fix=fix)


def _shape_index(rig, name: str) -> int:
    check_shapes(rig, [name])
    return rig.index(resolve_shape(rig, name))


def default_shapes(rig, count: int = 5) -> list[str]:
    """The ``count`` shapes that move the mesh most (largest max vertex offset), in rig order."""
    if rig.n_shapes == 0:
        return []
    size = np.linalg.norm(rig.deltas, axis=2).max(axis=1)
    keep = np.sort(np.argsort(-size)[:count])
    return [rig.names[k] for k in keep]


def render_shapes(rig, shapes=None, out=None, *, weight: float = 1.0, view: str = "front",
                  force: bool = False, title: str | None = None, max_vertices: int | None = None,
                  crop="moving"):
    """Neutral plus each shape of ``shapes`` (default: :func:`default_shapes`) at ``weight``; the heat of
    each panel is the vertex displacement in mm over the full mesh (the panel's largest in its title). The
    panels share one length scale (:func:`shared_frame`) and one colour scale, from 0 to the largest
    displacement of them all, with one colour bar, so they compare (stop 43: each was framed on its own pose
    and coloured to its own maximum). A mesh of more than ``max_vertices`` is drawn decimated
    (:func:`display_mesh`). ``crop``: the vertices the panels are framed on, by default
    :func:`moving_region` of the rig's shapes (``None``: the whole mesh). Returns the figure; saved to
    ``out`` when given."""
    shapes = list(shapes) if shapes is not None else default_shapes(rig)
    fig, axes = _figure(1 + len(shapes))
    crop = moving_region(rig.deltas) if isinstance(crop, str) else crop
    poses = []
    for name in shapes:
        w = np.zeros(rig.n_shapes)
        w[_shape_index(rig, name)] = weight
        poses.append(rig.evaluate(w))
    frame = shared_frame([rig.neutral, *poses], rig.triangles, view, crop)
    display = display_mesh(rig.neutral, rig.triangles, max_vertices, view=view,
                           frame=frame if crop is not None else None)
    draw_mesh(axes[0], rig.neutral, rig.triangles, view=view, display=display, frame=frame)
    axes[0].set_title("neutral")
    moved_mm = [1000.0 * np.linalg.norm(moved - rig.neutral, axis=1) for moved in poses]
    # from 0 (a trial's note: the colours ran from the smallest to the largest visible triangle's mean,
    # without a bar; Pixar's targetC, 138.9 mm, drawn with no colour reaching the top) to the largest panel's
    top = max((float(d.max()) for d in moved_mm), default=0.0)
    coll = None
    for ax, name, moved, disp_mm in zip(axes[1:], shapes, poses, moved_mm, strict=True):
        coll = draw_mesh(ax, moved, rig.triangles, values=disp_mm, cmap="viridis", vmin=0.0, vmax=top,
                         view=view, display=display, frame=frame)
        # the weight when it is not 1: a panel at 0.5 read as the full shape's motion (a trial's note)
        at = "" if weight == 1.0 else f" at {weight:g}"
        ax.set_title(f"{name}{at}\n(max {disp_mm.max():.1f} mm)")
    if coll is not None:
        fig.colorbar(coll, ax=axes, shrink=0.7, label="mm moved")
    if title:
        fig.suptitle(title)
    if out is not None:
        save_figure(fig, out, force)
    return fig


def render_comparison(generic, personalized, shapes=None, out=None, *, view: str = "front",
                      force: bool = False, title: str | None = None, max_vertices: int | None = None,
                      crop="moving"):
    """Generic vs personalized, side by side, one row per shape: generic, personalized, and the per-vertex
    distance between the two deformed meshes (mm). Both rigs must share the mesh (same vertex count). Every
    panel shares one length scale (:func:`shared_frame`) and the difference panels one colour scale, from 0 to
    the largest difference of them all, with one colour bar (stop 43: each was framed and coloured on its
    own). ``crop``: as :func:`render_shapes`' (default: what the personalized shapes move)."""
    if generic.n_vertices != personalized.n_vertices:
        def where(rig):
            src = rig.source
            return f"{rig.name or 'mesh'} ({src.file}, {src.prim})" if src is not None else rig.name or "mesh"

        raise UsdFaceError(f"cannot compare {where(generic)}, {generic.n_vertices} vertices, with "
                           f"{where(personalized)}, {personalized.n_vertices} vertices",
                           fix="compare the same mesh of the generic and personalized avatars (--compare the "
                               "avatar the layer was made over, --mesh the same mesh)")
    shapes = list(shapes) if shapes is not None else default_shapes(personalized, 3)
    fig, axes = _figure(3 * len(shapes), ncols=3)
    crop = moving_region(personalized.deltas) if isinstance(crop, str) else crop
    pairs = [(generic.evaluate(_one_hot(generic, name)), personalized.evaluate(_one_hot(personalized, name)))
             for name in shapes]
    frame = shared_frame([p for pair in pairs for p in pair], personalized.triangles, view, crop)
    display = display_mesh(personalized.neutral, personalized.triangles, max_vertices, view=view,
                           frame=frame if crop is not None else None)
    diffs_mm = [1000.0 * np.linalg.norm(b - a, axis=1) for a, b in pairs]
    # from 0 (the bar ended at the largest visible triangle's mean: 2.65 under a title of 2.89 mm on the
    # sample's eyeBlinkLeft) to the largest difference of the picture's rows
    top = max((float(d.max()) for d in diffs_mm), default=0.0)
    coll = None
    for row, (name, (a, b), diff_mm) in enumerate(zip(shapes, pairs, diffs_mm, strict=True)):
        draw_mesh(axes[3 * row], a, generic.triangles, view=view, display=display, frame=frame)
        # the shape's name on a line of its own: "browDownRight: generic" ran into "browDownRight:
        # personalized" beside it on a head (dev3's --compare)
        axes[3 * row].set_title(f"{name}\ngeneric")
        draw_mesh(axes[3 * row + 1], b, personalized.triangles, view=view, display=display, frame=frame)
        axes[3 * row + 1].set_title(f"{name}\npersonalized")
        coll = draw_mesh(axes[3 * row + 2], b, personalized.triangles, values=diff_mm, cmap="magma",
                         vmin=0.0, vmax=top, view=view, display=display, frame=frame)
        # two lines: on one, a wide mesh's title ran into the colour bar beside the panel (the Mouth)
        axes[3 * row + 2].set_title(f"difference\n(max {diff_mm.max():.2f} mm)")
    if coll is not None:
        fig.colorbar(coll, ax=axes, shrink=0.7, label="mm")
    if title:
        fig.suptitle(title)
    if out is not None:
        save_figure(fig, out, force)
    return fig


def heat_colors(values, vmax: float | None = None, cmap: str = "magma") -> np.ndarray:
    """Per-vertex RGB ``colors[n, 3]`` in [0, 1] for ``values[n]`` on a colour map, 0 -> dark, ``vmax``
    (default: the 99th percentile, robust to a few outliers) -> bright."""
    import matplotlib

    values = np.nan_to_num(np.asarray(values, dtype=np.float64).ravel())
    top = float(np.percentile(values, 99)) if vmax is None and values.size else float(vmax or 0.0)
    norm = matplotlib.colors.Normalize(0.0, top if top > 0 else 1.0)
    return matplotlib.colormaps[cmap](norm(values))[:, :3]


def _one_hot(rig, name: str) -> np.ndarray:
    w = np.zeros(rig.n_shapes)
    w[_shape_index(rig, name)] = 1.0
    return w


def render_heatmap(points, triangles, values, out=None, *, label: str = "error (mm)", scale: float = 1000.0,
                   view: str = "front", vmax: float | None = None, force: bool = False,
                   title: str | None = None, max_vertices: int | None = None, crop=None):
    """A per-vertex heat map: ``values[n]`` (metres by default, drawn as ``values * scale``) on the mesh
    (``crop``: vertex indices to frame the view on, as :func:`draw_mesh`)."""
    values = np.asarray(values, dtype=np.float64).ravel()
    if values.shape[0] != np.asarray(points).shape[0]:
        raise UsdFaceError(f"{values.shape[0]} heat-map values for {np.asarray(points).shape[0]} vertices",
                           fix="give one value per vertex")
    fig, axes = _figure(1, size=5.0)
    if vmax is None and np.isfinite(values).any():   # the bar's top is the largest vertex's value, as the
        vmax = float(np.nanmax(values * scale))        # default title says (not the largest triangle mean)
    frame = crop_frame(points, crop, view)
    coll = draw_mesh(axes[0], points, triangles, values=values * scale, cmap="magma", vmin=0.0,
                     vmax=vmax, view=view, display=display_mesh(points, triangles, max_vertices, view=view,
                                                                frame=frame), frame=frame)
    fig.colorbar(coll, ax=axes[0], shrink=0.8, label=label)
    axes[0].set_title(title or f"max {np.nanmax(values * scale):.2f}, mean {np.nanmean(values * scale):.2f}")
    if out is not None:
        save_figure(fig, out, force)
    return fig


def render_landmarks(points, triangles, indices, out=None, *, labels=None, view: str = "front",
                     force: bool = False, title: str | None = None, max_vertices: int | None = None):
    """Landmark vertices ``indices[m]`` as dots on the mesh (optionally numbered with ``labels[m]``)."""
    indices = _check_landmarks(points, indices)
    fig, axes = _figure(1, size=5.0)
    draw_mesh(axes[0], points, triangles, view=view, display=display_mesh(points, triangles, max_vertices))
    hidden = _landmark_dots(axes[0], points, triangles, indices, view, labels, colour="#1f77b4",
                            edge="white")
    far = f" ({hidden} on the far side)" if hidden else ""
    # the far-side note with a title given too: 'render --landmarks --view left' titled 'Head: 10 landmarks'
    # over the 6 dots a side view shows, and nothing said where the others were (stop 42)
    axes[0].set_title((title or f"{indices.size} landmarks") + far)
    if out is not None:
        save_figure(fig, out, force)
    return fig


def _check_landmarks(points, indices) -> np.ndarray:
    """``indices`` as int64 ``[m]``, or :class:`UsdFaceError` when one is not a vertex of ``points``."""
    indices = np.asarray(indices, dtype=np.int64).ravel()
    if indices.size and (indices.min() < 0 or indices.max() >= len(points)):
        raise UsdFaceError(f"landmark index out of range [0, {len(points)})",
                           fix="use vertex indices of this mesh")
    return indices


def _landmark_dots(ax, points, triangles, indices, view: str, labels=None, colour: str = "#00c8ff",
                   edge: str = "black") -> int:
    """Landmarks ``indices[m]`` as dots on ``ax``, those on the far side of the view hidden; returns how many
    are hidden.

    A landmark is on the near side when it is a corner of a face the picture draws (one facing the camera,
    :func:`draw_mesh`'s test): a landmark on the silhouette belongs to the side it is seen from, so one on
    the face's mid-line (upper lip, chin) is shown in both profiles, on the outline, and one in the middle
    of a face turned away in neither. It was hidden where its vertex normal did not face the camera: a
    mid-line normal is edge-on in a profile, so a side view counted the upper lip and chin as on the far
    side of both (stop 43)."""
    from .mesh import triangle_normals

    rotated = np.asarray(points, dtype=np.float64) @ VIEWS[view].T
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    near = np.zeros(len(rotated), dtype=bool)
    near[tri[triangle_normals(rotated, tri)[:, 2] > 0.0].ravel()] = True
    visible = near[indices]
    xy = rotated[indices][:, :2]
    ax.scatter(xy[visible, 0], xy[visible, 1], s=16, c=colour, edgecolors=edge, linewidths=0.7, zorder=3)
    if labels is not None:
        for (x, y), text, shown in zip(xy, labels, visible, strict=True):
            if shown:
                ax.annotate(str(text), (x, y), fontsize=6, xytext=(2, 2), textcoords="offset points")
    return int((~visible).sum())


def render_landmark_diagnostics(points, triangles, panels, indices, out=None, *, view: str = "front",
                                force: bool = False, title: str | None = None, crop=None,
                                max_vertices: int | None = None):
    """Heat maps of per-vertex diagnostics with the landmarks ``indices[m]`` dotted on each (Zell & McDonnell
    2022, Figs. 3 and 5). ``panels``: a list of ``(title, values[n], colour map, vmin, vmax)``, optionally
    with a sixth item, a landmark vertex to ring on that panel (Fig. 5's); NaN values
    (not evaluated) are drawn as plain skin. ``crop[v]``: vertex indices the view is framed on (default all).
    Returns the figure; saved to ``out`` when given."""
    points = np.asarray(points, dtype=np.float64)
    indices = _check_landmarks(points, indices)
    fig, axes = _figure(len(panels), ncols=min(len(panels), 3), size=4.0)
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    frame = crop_frame(points, crop, view, pad=0.06)
    display = display_mesh(points, tri, max_vertices, view=view, frame=frame)
    for ax, (name, values, cmap, vmin, vmax, *ringed) in zip(axes, panels, strict=True):
        values = np.asarray(values, dtype=np.float64).ravel()
        if values.shape[0] != len(points):
            raise UsdFaceError(f"{values.shape[0]} values for {len(points)} vertices in panel {name!r}",
                               fix="give one value per vertex")
        coll = draw_mesh(ax, points, tri, values=values, cmap=cmap, vmin=vmin, vmax=vmax, view=view,
                         display=display, frame=frame)
        fig.colorbar(coll, ax=ax, shrink=0.7)
        _landmark_dots(ax, points, tri, indices, view)
        if ringed:
            ring = (points[_check_landmarks(points, ringed[:1])] @ VIEWS[view].T)[:, :2]
            ax.scatter(ring[:, 0], ring[:, 1], s=160, facecolors="none", edgecolors="#00c8ff", linewidths=2.0,
                       zorder=4)
        ax.set_title(name, fontsize=9)
    if title:
        fig.suptitle(title)
    if out is not None:
        save_figure(fig, out, force)
    return fig
