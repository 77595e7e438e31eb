"""``usdface render FILE -o out.png``: pictures without a display (shapes, generic vs personalized, heat maps,
landmarks)."""

from __future__ import annotations

import shlex
from pathlib import Path

from ..errors import warn
from ..namelist import name_list
from . import add_name_map_option
from .options import add_quiet, finite_float, nonnegative_int, positive_int, refuse_camera_with_rays, vector3


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "render", help="draw an avatar, a capture or a personalize result to PNG (no display needed)",
        description="Draw the neutral and selected shapes of a mesh (default), generic vs personalized side "
                    "by side (--compare), a per-vertex heat map of what personalization moved "
                    "(--heatmap), or the landmark layout stored in the file (--landmarks).")
    p.add_argument("file", help="avatar / personalize result (.usd*) or capture (folder or capture .usda)")
    p.add_argument("-o", "--output", required=True, type=Path, help="PNG to write")
    p.add_argument("--mesh", help="mesh to draw (prim name or path; default: the one with the most shapes)")
    p.add_argument("--shapes", help="comma-separated shape names (default: the shapes that move most)")
    p.add_argument("--weight", type=finite_float, default=None,
                   help="weight of each drawn shape (default 1; the shape pictures only: --compare draws "
                        "each shape at 1)")
    p.add_argument("--view", choices=("front", "left", "right"), default="front")
    add_name_map_option(p)
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--compare", nargs="?", const="", metavar="GENERIC",
                      help="side by side with the generic avatar (default: the file a usdface layer is over)")
    mode.add_argument("--heatmap", nargs="?", const="", metavar="GENERIC",
                      help="RMS over shapes of |personalized - generic| per vertex (mm)")
    mode.add_argument("--landmarks", action="store_true", help="the landmark layout authored in FILE")
    p.add_argument("--diagnostics", action="store_true",
                   help="with --landmarks: the paper's diagnostics as heat maps with the landmarks (neutral "
                        "and global visibility, what expressions hide, relative displacement, importance "
                        "weights); FILE without a layout gets one computed with the landmarks defaults")
    p.add_argument("--rays", type=positive_int, default=None,
                   help="hemisphere rays per vertex for --diagnostics, also over a camera layout's camera "
                        "(default: those the authored layout was computed with, else 16, as 'usdface "
                        "landmarks'); not with --camera")
    p.add_argument("--camera", type=vector3, metavar="X,Y,Z",
                   help="with --diagnostics: visibility from this camera position (metres, usdface's "
                        "internal frame, as 'usdface landmarks --camera'; default: the camera the authored "
                        "layout was computed with, else the hemisphere)")
    p.add_argument("--capture", action="store_true",
                   help="FILE is a capture (.usda); folders, files written by 'capture import/select' and "
                        "takes always are")
    p.add_argument("--max-vertices", type=nonnegative_int, default=None, metavar="N",
                   help="draw a mesh of more vertices decimated to about N of its own vertices (default "
                        "60000: a panel shows no more; the figures in the titles are the full mesh's); 0 "
                        "draws every triangle")
    p.add_argument("--force", action="store_true", help="overwrite the PNG")
    p.add_argument("--allow-moved-neutral", action="store_true",
                   help="--compare/--heatmap of a layer whose avatar's neutral was re-sculpted after it was "
                        "written (refused by default: its offsets were fitted and checked on the old "
                        "neutral)")
    add_quiet(p)
    p.set_defaults(func=run)


def _generic(args, path: Path) -> Path:
    from ..errors import InputFileError
    from ..io.usd_rig import generic_input

    given = args.compare if args.compare is not None else args.heatmap
    generic = Path(given) if given else generic_input(path) or _flattened_original(path)
    if generic is None:
        from ..io.usd_rig import dcc_export_marks

        marks = dcc_export_marks(path)
        if marks:       # Blender's export of a personalized layer: its shapes are personalized, not generic
            raise InputFileError("a DCC export (Blender, ...) of a usdface output layer (it has "
                                 f"{marks[0]}): the personalized shapes with no sublayer or variant to "
                                 "compare with",
                                 path=path, prim=marks[0],
                                 fix="pass the original avatar explicitly: --compare AVATAR.usdc, or draw "
                                     "the usdface layer it was exported from")
        raise InputFileError("not a usdface layer (no sublayer to compare with)", path=path,
                             fix="pass the generic avatar explicitly: --compare GENERIC.usdc")
    return generic


def _flattened_original(path: Path) -> Path | None:
    """The avatar a flattened export of a personalized layer (``usdface export --flatten``) was personalized
    from, as its provenance records it (relative to the flattened file): the generic to compare with, as a
    layer's first sublayer is. A recorded avatar that is no longer there is refused naming it (before, any
    flattened export was 'not a usdface layer (no sublayer to compare with)', which it is, flattened)."""
    from ..errors import InputFileError
    from ..io.file_kind import file_kind
    from ..io.usd_rig import _from_cwd, flattened_source

    found = file_kind(path)             # the root layer, read once
    flat = found.flattened
    if flat is None or flat["variant"] != "personalized":
        return None
    inputs = (found.provenance or {}).get("inputs") or []
    if not inputs:
        return None
    from ..io.layers import recorded_path

    original = recorded_path(Path(path).parent, inputs[0])       # by name, as USD anchors the file's paths
    if not original.is_file():
        layer = flattened_source(path, flat) or "?"
        raise InputFileError(f"a flattened export of the personalized layer {layer}: the "
                             f"avatar it was personalized from, {_from_cwd(original)}, is not there to "
                             "compare with", path=path,
                             fix="pass the generic avatar explicitly: --compare GENERIC.usdc")
    return original


def _matching_generic(generic, rig, generic_path: Path, path: Path):
    """``generic``'s shapes in ``rig``'s order, once it is the same mesh (vertex count) and has every shape
    ``rig`` has; else a RigError naming both files (another avatar given as GENERIC ended in a traceback:
    a ValueError for a missing shape, a broadcast error for another vertex count)."""
    from ..errors import RigError

    fix = (f"pass the avatar {path.name} was personalized from as GENERIC, or leave GENERIC out to compare "
           "with the file a usdface layer is over")
    if generic.n_vertices != rig.n_vertices:
        raise RigError(f"generic mesh {rig.name!r} has {generic.n_vertices} vertices, {path.name}'s "
                       f"{rig.n_vertices}: not the same mesh", path=generic_path,
                       prim=generic.source.prim if generic.source else None, fix=fix)
    missing = [n for n in rig.names if n not in generic.names]
    if missing:
        shown = ", ".join(missing[:6]) + (f" (+{len(missing) - 6})" if len(missing) > 6 else "")
        raise RigError(f"generic mesh {rig.name!r} has no shape {shown} that {path.name}'s has",
                       path=generic_path, prim=generic.source.prim if generic.source else None, fix=fix)
    return generic.subset(rig.names)


def _mesh_with_layout(avatar, rig, path: Path):
    """The mesh ``--landmarks`` draws without ``--mesh``: the default one, or, when the file's landmark layout
    is on another mesh (``usdface landmarks --mesh Mouth -o lm.usda``), that mesh (the one with the most
    shapes among those with a layout). Before, the default mesh was taken: 'no landmark layout for mesh
    Head' of a file that has one, and ``--diagnostics`` computed a new layout for the Head instead."""
    from ..io.usd_inspection import read_landmarks

    layouts = read_landmarks(path)
    if not layouts or (rig.source is not None and rig.source.prim in layouts):
        return rig
    with_layout = [m for m in avatar.meshes if m.source is not None and m.source.prim in layouts]
    return max(with_layout, key=lambda m: (m.n_shapes, m.n_vertices)) if with_layout else rig


def _capture_file(path: Path) -> tuple[bool, object]:
    """Whether ``path`` is a capture or take (:func:`usdface.io.file_kind.file_kind`: marked by 'capture
    import/select' or write_take_usd, a take another tool wrote, a take folder), drawn like a capture folder
    without ``--capture``; and the root layer opened to tell (None for folders and other files)."""
    from ..io.file_kind import Kind, file_kind

    found = file_kind(path)
    return found.kind in (Kind.CAPTURE, Kind.TAKE, Kind.TAKE_FOLDER), found.layer


def run(args) -> int:

    from .. import api, render
    from ..io.atomic import check_output_file

    path = Path(args.file)
    if args.diagnostics and not args.landmarks:
        from ..errors import LandmarkError

        raise LandmarkError("--diagnostics draws a landmark layout", fix="pass --landmarks --diagnostics")
    given = [flag for flag, value in (("--camera", args.camera), ("--rays", args.rays)) if value is not None]
    if given and not args.diagnostics:
        from ..errors import OptionError

        named = " and ".join(given)
        raise OptionError(f"{named} set where --diagnostics sees from; without it nothing would use them",
                          fix=f"add --landmarks --diagnostics, or drop {named}")
    ignored = [flag for flag, value, used in (
        ("--weight", args.weight, args.compare is None and args.heatmap is None and not args.landmarks),
        ("--shapes", args.shapes, not args.landmarks)) if value is not None and not used]
    if ignored:                        # the layout and the heat map draw no shape at a weight
        from ..errors import OptionError

        named = " and ".join(ignored)
        mode = "--landmarks" if args.landmarks else "--compare" if args.compare is not None else "--heatmap"
        raise OptionError(f"{named} not used by {mode} (it would be ignored)",
                          fix=f"drop {named}, or leave out {mode} to draw the shapes")
    weight = 1.0 if args.weight is None else args.weight
    refuse_camera_with_rays(args.camera, args.rays)
    check_output_file(args.output, args.force, suffixes=(".png",), what="picture",
                      inputs=[path, args.compare or None, args.heatmap or None, args.name_map])
    # ',' drew the neutral alone and '' the default shapes
    shapes = name_list(args.shapes, "--shapes", "shape",
                       fix="name shapes (--shapes jawOpen,eyeBlinkLeft), or leave --shapes out for the "
                           "shapes that move most")
    is_capture, _layer = _capture_file(path)  # _layer held: the file is parsed once
    if path.is_dir() or args.capture or is_capture:
        unused = [flag for flag, value in (("--compare", args.compare), ("--heatmap", args.heatmap),
                                           ("--landmarks", args.landmarks or None), ("--mesh", args.mesh),
                                           ("--name-map", args.name_map)) if value is not None]
        if unused:                     # a capture draws its template shapes: these were silently ignored
            from ..errors import OptionError

            named = ", ".join(unused)
            raise OptionError(f"{named} not used for a capture (it is drawn as its template shapes on the "
                              "person's neutral)", path=path,
                              fix=f"drop {named}, or render an avatar or a personalize result")
        capture = api.read_capture(path)
        rig = capture.template
        rig = type(rig)(capture.neutral, rig.triangles, rig.names, rig.deltas, rig.inbetweens, rig.source,
                        "capture")
        render.check_shapes(rig, shapes, path)
        render.render_shapes(rig, shapes, args.output, weight=weight, view=args.view, force=args.force,
                             max_vertices=args.max_vertices,
                             title=f"{path.name}: template shapes on the person's neutral")
        print(f"wrote {args.output}")
        return 0
    from ..progress import steps

    comparing = args.compare is not None or args.heatmap is not None
    # each step named on stderr while it runs: a 225k-vertex head's --compare read two avatars and drew
    # for ~50 s without a word
    with steps("render", 1 + comparing + (not args.diagnostics)) as p:
        p.start(f"read {path.name}")
        return _render_avatar(args, path, shapes, weight, p)


def _render_avatar(args, path: Path, shapes, weight: float, p) -> int:
    """``run`` for an avatar or a usdface layer (``p``: the command's progress steps)."""

    from .. import api, render

    if args.landmarks and not args.diagnostics:
        from ..io.usd_rig import read_avatar

        # the layout's picture is the neutral: no shape's offsets read (a 225k-vertex head's 51 dense shapes
        # were most of the command's memory)
        avatar = read_avatar(path, name_map=args.name_map, shapes=False)
    else:
        avatar = api.read_avatar(path, args.name_map)
    rig = api.pick_mesh(avatar, args.mesh)
    if args.landmarks and args.mesh is None:
        rig = _mesh_with_layout(avatar, rig, path)
    render.check_shapes(rig, shapes, path)
    if shapes:            # the mesh's own channel names as the names the rig reads them under
        shapes = [render.resolve_shape(rig, s) for s in shapes]
    # what the shapes move, once: the pictures of a face on a still body are framed (and cut) on it
    crop = None if args.landmarks else render.moving_region(rig.deltas)
    if args.diagnostics:
        p()                                    # read: its own steps follow
        _diagnostics(args, path, rig)
    elif args.landmarks:
        from ..errors import LandmarkError
        from ..io.usd_inspection import read_landmarks

        layouts = read_landmarks(path)
        key = next((k for k in layouts if rig.source and k == rig.source.prim), None)
        if key is None:
            others = ", ".join(layouts)
            lm = path.with_name(f"{path.stem}.landmarks.usda")
            # the layout 'usdface landmarks' writes goes into a new file: that file is the one to draw
            src, out = shlex.quote(str(path)), shlex.quote(str(lm))     # one word each, pasted in a shell
            # both commands whole (the mesh asked for, render's -o): 'usdface landmarks --mesh Head' and
            # 'usdface render LM --landmarks' were told, which pasted stop at their missing arguments
            mesh = f" --mesh {shlex.quote(args.mesh)}" if args.mesh is not None else ""
            # each command in parentheses, never in quotes of its own (a quoted path inside one read
            # 'usdface landmarks 'a b.usda' ...')
            write = (f"layout into a file (usdface landmarks {src}{mesh} -o {out}), then draw that file "
                     f"(usdface render {out} -o {shlex.quote(str(args.output))} --landmarks{mesh})")
            write_one = (f"write a {write} (or personalize with --landmarks); or add --diagnostics to "
                         "compute one with the defaults")
            raise LandmarkError(f"no landmark layout for mesh {rig.name!r}"
                                + (f" (the file has one for {others})" if others else ""), path=path,
                                fix=(f"pass --mesh {next(iter(layouts))}, or write a {rig.name} {write}")
                                if others else write_one)
        p.start(f"draw {args.output.name}")
        render.render_landmarks(rig.neutral, rig.triangles, layouts[key], args.output, view=args.view,
                                force=args.force,
                                # the file's name, as the shapes picture's 'avatar.usdc: Head' (stop 42)
                                title=f"{path.name}\n{rig.name}: {len(layouts[key])} landmarks")
    elif args.compare is not None or args.heatmap is not None:

        from ..io.layers import refuse_avatar_mismatch, stale_inputs

        refuse_avatar_mismatch(path, "a comparison",        # its 'personalized' is not the layer's answer
                               allow_moved_neutral=args.allow_moved_neutral)
        generic_path = _generic(args, path)
        # as export and review do: a layer whose avatar changed since is compared with the avatar as it is
        # now, and the picture shows the edit as personalization (it said nothing)
        for text in stale_inputs(path):
            warn(text)
        # the avatar under the layer with the layer's channel names: the map given, else the one it records
        name_map = args.name_map or (avatar.metadata or {}).get("name_map")
        p.start(f"read the generic {Path(generic_path).name}")
        generic = _matching_generic(api.pick_mesh(api.read_avatar(generic_path, name_map), rig.name), rig,
                                    generic_path, path)
        p.start(f"draw {args.output.name}")
        if args.compare is not None:
            render.render_comparison(generic, rig, shapes, args.output, view=args.view, crop=crop,
                                     force=args.force, max_vertices=args.max_vertices,
                                     title=f"{rig.name}: generic vs personalized")
        else:
            from ..motion import shape_changes

            # the RMS over the shapes asked for (it was over all of them); shape by shape
            ks = [rig.names.index(s) for s in shapes] if shapes else list(range(rig.n_shapes))
            rms = shape_changes([rig.deltas[k] for k in ks], [generic.deltas[k] for k in ks])[0]
            render.render_heatmap(rig.neutral, rig.triangles, rms, args.output, view=args.view,
                                  max_vertices=args.max_vertices, crop=crop,
                                  label=(f"change in {shapes[0]} (mm)" if shapes and len(shapes) == 1 else
                                         f"RMS change over {len(shapes) if shapes else 'all'} shapes (mm)"),
                                  force=args.force,
                                  title=f"{rig.name}: personalized vs generic "
                                        f"(max {1000 * rms.max():.2f} mm)")
    else:
        p.start(f"draw {args.output.name}")
        render.render_shapes(rig, shapes, args.output, weight=weight, view=args.view, force=args.force,
                             max_vertices=args.max_vertices, crop=crop,
                             title=f"{path.name}: {rig.name}")
    _decimated_note(rig, args.max_vertices, crop is not None)
    print(f"wrote {args.output}")
    return 0


def _decimated_note(rig, max_vertices, framed: bool = False) -> None:
    """Say when the picture shows the mesh decimated (``--max-vertices``), or, ``framed`` on the part that
    moves of a larger still mesh (a face on a body), cut to the picture's frame."""
    import sys

    from ..mesh import DISPLAY_MAX_VERTICES

    limit = DISPLAY_MAX_VERTICES if max_vertices is None else max_vertices
    if limit and rig.n_vertices > limit:
        how = (f"drawn on its part in the picture's frame (decimated only where that part has more than "
               f"{limit:,} vertices)" if framed else f"drawn decimated to about {limit:,} of its vertices")
        print(f"note: {rig.name} ({rig.n_vertices:,} vertices) {how} (the titles' figures are the full "
              "mesh's; --max-vertices 0 draws every triangle)", file=sys.stderr)


def _layout_setup(path: Path) -> dict:
    """The visibility set-up (``camera``, ``rays``) recorded by ``usdface landmarks -o`` in ``path``'s
    provenance (its root layer's ``customLayerData``), for the layouts it authored; {} for any other file."""
    from ..io.usd_rig import usdface_layer_data

    data = usdface_layer_data(path)
    if data.get("method") != "landmarks":
        return {}
    params = data.get("parameters")
    if not hasattr(params, "get"):
        return {}
    setup = {}
    camera = params.get("camera")
    if camera is not None and not isinstance(camera, str) and len(camera) == 3:
        setup["camera"] = [float(x) for x in camera]
    if isinstance(params.get("rays"), int) and params["rays"] > 0:
        setup["rays"] = int(params["rays"])
    return setup


def _diagnostics(args, path: Path, rig) -> None:
    """``--landmarks --diagnostics``: the layout authored in FILE (or one computed with the defaults) over
    the paper's per-vertex diagnostics, with the visibility it was computed with (a ``--camera`` layout from
    its camera; ``--camera``/``--rays`` given here win)."""
    import numpy as np

    from .. import api, render
    from ..io.usd_inspection import read_landmark_settings, read_landmarks
    from ..landmarks.diagnostics import diagnostic_panels
    from ..progress import steps

    prim = rig.source.prim if rig.source else None
    layouts = read_landmarks(path)
    settings = read_landmark_settings(path).get(prim, {})
    recorded = _layout_setup(path) if prim in layouts else {}
    # given here wins: --rays asks for the hemisphere, also over a camera layout's recorded camera
    camera = (args.camera if args.camera is not None
              else None if args.rays is not None else recorded.get("camera"))
    rays = args.rays if args.rays is not None else recorded.get("rays", 16)
    with steps("diagnostics", 2 + (prim not in layouts)) as p:       # inside render's own block
        if prim in layouts:
            vertices = layouts[prim]
            epsilon, alpha = settings.get("epsilon", 0.5), settings.get("alpha", 0.5)
            source = "authored"
        else:
            p.start(f"layout of {rig.name} (none authored: landmarks defaults)")
            layout = api.compute_landmarks(rig, rays=rays, camera=camera, ignore_static=True)
            vertices, epsilon, alpha, source = layout.vertices, layout.epsilon, layout.alpha, "computed"
        seen_from = ("camera at " + ", ".join(f"{x:g}" for x in camera) + " m" if camera is not None
                     else f"{rays} hemisphere rays")
        p.start(f"visibility of {rig.name} ({rig.n_shapes + 1} poses, {seen_from})")
        diag = api.landmark_diagnostics(rig, epsilon=epsilon, alpha=alpha, rays=rays, camera=camera)
        p.start(f"draw {args.output.name}")
        panels = diagnostic_panels(diag, vertices, rig.names)
        summary = (f"{rig.name}: {len(vertices)} landmarks ({source}), epsilon {epsilon:g}, alpha {alpha:g}, "
                   f"visibility: {seen_from}")
        render.render_landmark_diagnostics(rig.neutral, rig.triangles, panels, vertices, args.output,
                                           view=args.view, force=args.force,
                                           max_vertices=args.max_vertices,
                                           crop=np.flatnonzero(diag.c.any(axis=0)), title=summary)
    print(summary)
