"""``usdface landmarks AVATAR``: compact landmark layout by weighted set cover (Zell & McDonnell 2022)."""

from __future__ import annotations

import json
from pathlib import Path

from . import add_name_map_option, command_line, say_warning
from .options import (
    add_quiet,
    nonnegative_float,
    positive_float,
    positive_int,
    refuse_camera_with_rays,
    unit_float,
    vector3,
)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "landmarks", help="compute a compact facial landmark layout (weighted set cover, OR-tools)",
        description="Choose the fewest mesh vertices to track so that every blend shape has a "
                    "representative landmark (Zell & McDonnell, Eurographics 2022), solved to a proven "
                    "optimum, and write it as a USD layer over the avatar (a Points prim + mesh primvars).")
    p.add_argument("avatar", help="avatar USD file (UsdSkel, blend shapes)")
    p.add_argument("--mesh", help="mesh prim name or path (default: most shapes, then most vertices)")
    add_name_map_option(p)
    p.add_argument("--epsilon", type=positive_float, default=None,
                   help="relative-displacement threshold, (0,1] (0.5)")
    p.add_argument("--alpha", type=unit_float, default=None,
                   help="displacement vs visibility weight, [0,1] (0.5)")
    p.add_argument("--symmetric", action="store_true", help="left/right symmetric layout")
    p.add_argument("--multicover", type=positive_int, default=None, metavar="N",
                   help="multi-cover: up to N landmarks per shape in adaptive rounds (with --one-shot: "
                        "N each, one ILP) (1)")
    p.add_argument("--radius", type=nonnegative_float, default=None,
                   help="metres; multi-cover excludes vertices this close to chosen landmarks (default: "
                        "2.4%% of the face size, 1 cm on a human head)")
    p.add_argument("--one-shot", action="store_true",
                   help="with --multicover N: one ILP covering every shape N times (the paper's other "
                        "multi-cover), instead of the adaptive rounds; no --radius, no 10%% heuristic")
    p.add_argument("--no-adaptive", action="store_true",
                   help="multi-cover every shape N times (drop the paper's 10%%-of-shapes heuristic)")
    p.add_argument("--camera", type=vector3, metavar="X,Y,Z",
                   help="known camera position, metres in usdface's internal frame (Y up, as read): "
                        "one visibility ray per vertex instead of the hemisphere")
    p.add_argument("--rays", type=positive_int, default=None,
                   help="hemisphere rays per vertex (16); not with --camera, which casts one ray per vertex, "
                        "nor with --evaluate, which casts none")
    p.add_argument("--spacing", type=nonnegative_float, default=None,
                   help="metres between the skin points whose visibility is ray cast (default: 2%% of the "
                        "face size as a power of two mm, 8 mm on a human head); 0: every vertex, against "
                        "the full mesh")
    p.add_argument("--sampled-candidates", action="store_true",
                   help="candidates only at those skin points too: the same layout at every mesh resolution, "
                        "fewer places to choose from")
    p.add_argument("--backend", default="scip", choices=["scip", "cbc", "highs", "cp-sat"],
                   help="OR-tools MIP backend (scip)")
    p.add_argument("--weighting", default=None, choices=["quality", "count", "paper"],
                   help="cost of eq. 5a: quality (count first, quality breaks ties; default), count, paper")
    p.add_argument("--skip-static", action="store_true", help="leave out shapes that move no vertex")
    p.add_argument("-o", "--output", help="output layer (.usda/.usdc/.usd); not with --evaluate")
    p.add_argument("--force", action="store_true", help="replace an existing output")
    p.add_argument("--json", dest="json_out", help="write the layout (or evaluation) as JSON")
    p.add_argument("--plot", help="PNG: the layout (front view), or with --evaluate the error curve")
    p.add_argument("--evaluate", action="store_true",
                   help="sweep epsilon x multi-cover vs baselines; reconstruction error vs landmark count")
    p.add_argument("--takes", nargs="+", default=[],
                   help="takes (test weights) for --evaluate: Live Link Face CSVs, USD takes ('anim "
                        "import') or take folders")
    p.add_argument("--empirical",
                   help="JSON with an empirical layout (list of vertex indices, or ICT-FaceKit's "
                        "vertex_indices.json: idx_to_landmark_verts) for --evaluate")
    p.add_argument("--frames", type=positive_int, default=None,
                   help="test frames used by --evaluate (evenly sampled; 400)")
    p.add_argument("--noise", type=nonnegative_float, default=None,
                   help="tracking noise for --evaluate, mm (0.5)")
    add_quiet(p)
    p.set_defaults(func=run)


#: Options only the layout reads (attribute, spelling, default): ``--evaluate`` sweeps epsilon x multi-cover
#: at the paper's protocol (alpha 0, every vertex a candidate, no camera), so given with it they would be
#: ignored. ``--radius``, ``--symmetric`` and ``--backend`` are read by both.
LAYOUT_ONLY = (("epsilon", "--epsilon", 0.5), ("alpha", "--alpha", 0.5), ("multicover", "--multicover", 1),
               ("weighting", "--weighting", "quality"), ("no_adaptive", "--no-adaptive", False),
               ("skip_static", "--skip-static", False), ("camera", "--camera", None),
               ("spacing", "--spacing", None), ("sampled_candidates", "--sampled-candidates", False),
               ("rays", "--rays", None),     # the sweep casts no rays (alpha 0): it was ignored
               ("one_shot", "--one-shot", False))

#: Options only ``--evaluate`` reads (attribute, spelling): given without it they would be ignored.
EVALUATE_ONLY = (("takes", "--takes"), ("empirical", "--empirical"), ("frames", "--frames"),
                 ("noise", "--noise"))


def refuse_other_mode(args) -> None:
    """Refuse, before any work, an option of the other mode: ``--takes/--empirical/--frames/--noise``
    without ``--evaluate`` (the layout ignores them), ``-o`` or a layout-only option (:data:`LAYOUT_ONLY`)
    with it (the sweep writes no layer and sets those itself); then fill in the layout's defaults."""
    from ..errors import LandmarkError

    if args.evaluate and args.output:
        raise LandmarkError("-o/--output writes a landmark layout layer, which --evaluate does not compute",
                            fix="leave out -o to evaluate (the results go to --json/--plot), or leave out "
                                "--evaluate to write the layout layer")
    if args.evaluate and not args.takes:     # before the avatar is read, in the command line's terms
        raise LandmarkError("--evaluate needs test weights", fix="pass --takes take1.csv [take2.csv ...]")
    given = [flag for name, flag in EVALUATE_ONLY if getattr(args, name) not in (None, [])]
    if given and not args.evaluate:
        raise LandmarkError(f"{'/'.join(given)} applies only to --evaluate (the layout would ignore it)",
                            fix=f"add --evaluate to evaluate layouts on the takes, or leave out "
                                f"{'/'.join(given)}")
    layout_only = [flag for name, flag, _ in LAYOUT_ONLY           # 'is': --spacing 0 is given, not False
                   if getattr(args, name) is not None and getattr(args, name) is not False]
    if layout_only and args.evaluate:
        raise LandmarkError(f"{'/'.join(layout_only)} applies only to the layout: --evaluate sweeps epsilon "
                            "x multi-cover at the paper's protocol (alpha 0, no camera, every vertex a "
                            "candidate) and would ignore it",
                            fix=f"leave out {'/'.join(layout_only)} to evaluate, or --evaluate to compute "
                                "the layout")
    later = [flag for flag, given in (("--radius", args.radius is not None),
                                      ("--no-adaptive", args.no_adaptive)) if given]
    if later and not args.evaluate and (args.multicover or 1) == 1:   # one round: they were ignored
        raise LandmarkError(f"{'/'.join(later)} act(s) only on the multi-cover's later rounds, and "
                            "--multicover is 1 (a single cover, one round): the layout would ignore it",
                            fix=f"add --multicover N (N >= 2: up to N landmarks per shape), or leave out "
                                f"{'/'.join(later)}")
    if not args.evaluate:          # what --one-shot would ignore: the library's one rule, before any work
        from ..landmarks.layout import check_one_shot

        check_one_shot(args.one_shot, args.multicover or 1, not args.no_adaptive, args.radius)
    if args.weighting == "count" and args.alpha is not None:   # the cost is the count alone: it was ignored
        raise LandmarkError("--alpha weighs visibility against displacement in the quality of eq. 1, which "
                            "--weighting count does not use (every landmark costs 1)",
                            fix="leave out --alpha, or use --weighting quality (default) or paper")
    refuse_camera_with_rays(args.camera, args.rays, LandmarkError)      # --rays was ignored
    if args.rays is None:
        args.rays = 16
    for name, _, default in LAYOUT_ONLY:   # the layout's defaults (None above: 'not given')
        if getattr(args, name) is None:
            setattr(args, name, default)


def run(args) -> int:
    import time

    from .. import api
    from ..io.atomic import check_output_file, outputs_all_or_nothing, write_text_atomic
    from ..progress import steps

    refuse_other_mode(args)
    t0 = time.perf_counter()
    inputs = [args.avatar, args.name_map, args.empirical, *args.takes]
    api.refuse_missing_inputs(avatar_path=args.avatar)         # a missing avatar before the outputs
    if args.output:
        from ..io.layers import check_output_path

        check_output_path(args.output, args.force, inputs=inputs,    # newdir/: a file inside it
                          example=f"{Path(args.avatar).stem}.landmarks.usda")
    for out, suffix in ((args.json_out, ".json"), (args.plot, ".png")):
        if out:
            check_output_file(out, args.force, suffixes=(suffix,), inputs=inputs)
    avatar = api.read_avatar(args.avatar, args.name_map)
    rig = api.pick_mesh(avatar, args.mesh)
    if args.output and not args.evaluate:     # its primvars would change nothing under an instance
        from ..io.usd_rig import refuse_instanced

        refuse_instanced(avatar, [rig.key], "the landmarks layer")
    if args.evaluate:
        from ..landmarks.plots import plot_evaluation

        asked = 400 if args.frames is None else args.frames
        report = api.evaluate_landmarks(rig, args.takes, empirical=args.empirical, frames=asked,
                                        noise_mm=0.5 if args.noise is None else args.noise, rays=args.rays,
                                        symmetric=args.symmetric, backend=args.backend,
                                        radius=args.radius)
        done: dict = {}
        # all or nothing, as export and evaluate: a plot written, then the JSON failing (a full disk,
        # Ctrl-C), left the plot as if the sweep had finished
        with outputs_all_or_nothing(done, plot=args.plot, json=args.json_out):
            if args.plot:
                plot_evaluation(report, args.plot, title=f"{Path(args.avatar).name} {rig.name}",
                                force=args.force)
                done["plot"] = Path(args.plot)
            if args.json_out:
                write_text_atomic(args.json_out, json.dumps(report.to_dict(), indent=2), force=args.force)
                done["json"] = Path(args.json_out)
        if report.frames < asked:           # only the plot's title said so
            say_warning(f"the takes hold {report.frames} frame(s): {report.frames} test frame(s) evaluated, "
                        f"not {asked} (--frames); give longer or more takes for a steadier figure")
        for key, value in report.summary.items():
            mm = "rmse" in key and isinstance(value, float)
            print(f"{key}: {value * 1e3:.4f} mm" if mm else f"{key}: {value}")
        for method in ("ours", "pca_kmeans", "delta_cluster", "random"):
            best = report.best_per_count(method)
            print(f"{method} RMSE (mm) by landmark count: "
                  + ", ".join(f"{m}: {v * 1e3:.3f}" for m, v in best.items()))
        for out in (args.json_out, args.plot):     # as 'evaluate' says each file it wrote
            if out:
                print(f"wrote {out}")
        return 0
    done: dict = {}
    # the layer, the JSON and the picture all or nothing, as export and evaluate: a picture that failed
    # (a full disk, Ctrl-C) left the layer and the JSON behind as if the run had finished
    with outputs_all_or_nothing(done, layer=args.output, json=args.json_out, plot=args.plot):
        with steps("landmarks", 1 + bool(args.output)) as p:
            p.start(f"layout of {rig.name}")
            layout = api.compute_landmarks(rig, args.epsilon, args.alpha, symmetric=args.symmetric,
                                           multicover=args.multicover,
                                           radius=args.radius,
                                           camera=args.camera, rays=args.rays, backend=args.backend,
                                           weighting=args.weighting, adaptive=not args.no_adaptive,
                                           ignore_static=args.skip_static,
                                           spacing="auto" if args.spacing is None else (args.spacing or None),
                                           thin_candidates=args.sampled_candidates,
                                           one_shot=args.one_shot)
            if args.output:
                p.start(f"write {Path(args.output).name}")
                params = {k: v for k, v in vars(args).items() if k not in ("func",)}
                # the values the layout was computed with, not 'not given' (recorded as ''): the default
                # radius (2.4 % of the face size) and the skin sampling's spacing (2 % of the face, rounded;
                # 0 = every vertex)
                params["radius"] = "" if layout.problem["radius"] is None else float(layout.problem["radius"])
                params["spacing"] = float(layout.problem.get("spacing") or 0.0)
                api.write_landmarks(avatar, rig, layout, args.output, force=args.force,
                                    provenance={"command": command_line(),
                                                "parameters": params, "timings": layout.timings,
                                                "elapsedSeconds": time.perf_counter() - t0})
                done["layer"] = Path(args.output)
        mesh = rig.key
        if args.json_out:
            write_text_atomic(args.json_out, json.dumps({"avatar": str(args.avatar), "mesh": mesh,
                                                         **layout.to_dict()}, indent=2), force=args.force)
            done["json"] = Path(args.json_out)
        if args.plot:
            from ..landmarks.plots import plot_layout

            plot_layout(rig.neutral, layout, args.plot, title=f"{Path(args.avatar).name} {rig.name}",
                        force=args.force, triangles=rig.triangles)
            done["plot"] = Path(args.plot)
    print(f"{mesh}: {layout.count} landmarks for {len(rig.names)} shapes (epsilon {layout.epsilon:g}, "
          f"alpha {layout.alpha:g}, {layout.weighting}); solver {layout.backend} {layout.status}, "
          f"gap {layout.gap:.2g}; {time.perf_counter() - t0:.2f} s")
    print("vertices: " + " ".join(str(int(v)) for v in layout.vertices))
    for w in layout.warnings:
        say_warning(w)
    if layout.uncoverable:
        print(f"uncoverable at epsilon {layout.epsilon:g}: {', '.join(layout.uncoverable)}")
    for out in (args.output, args.json_out, args.plot):   # the JSON and the picture were written unsaid
        if out:
            print(f"wrote {out}")
    return 0
