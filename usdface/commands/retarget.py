"""``usdface retarget AVATAR CAPTURE -o map.json|.csv``: the automatic retargeting map of eq. (4)."""

from __future__ import annotations

from .fit import add_pins_option
from .personalize import add_transfer_options, transfer_kwargs


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "retarget", help="automatic facial retargeting map (capture ARKit shapes -> avatar shapes), eq. (4)",
        description="Compute the K x K weight map of Menzel et al. 2022 eq. (4): each personalized ARKit "
                    "shape approximated by a ridge-regularised combination of the avatar's own shapes. "
                    "Engines "
                    "(Live Link, Unity) can drive the avatar with it instead of a hand-made map.")
    add_transfer_options(p)
    add_pins_option(p)
    p.add_argument("--face-mesh", metavar="PRIM",
                   help="prim name or path of the face mesh whose shapes the map targets (default: the mesh "
                        "the capture's shapes move most)")
    p.add_argument("-o", "--output", required=True, help="map file: .json or .csv")
    p.add_argument("--force", action="store_true", help="overwrite the output")
    p.add_argument("--json", action="store_true",
                   help="print the result as JSON (the map file, its size, the settings it was solved with, "
                        "the shapes it has no row for, the warnings)")
    p.set_defaults(func=run)


def run(args) -> int:
    from .. import api, progress

    if args.quiet:
        progress.set_enabled(False)
    result = api.write_retarget_map(args.avatar, args.capture, args.output, force=args.force,
                                    face_mesh=args.face_mesh, **transfer_kwargs(args),
                                    **({"pins": args.pins} if args.pins else {}))
    from . import say_warning

    rep = result.report
    for text in rep.get("warnings") or []:
        say_warning(text)
    lacking = rep.get("capture_shapes_missing_from_avatar") or []
    if lacking:      # a row the map lacks is a phone weight that drives nothing on the avatar
        say_warning(f"the map has no row for {', '.join(lacking)}: the phone's weights for them drive "
                    "nothing on the avatar (fix: if the avatar has these shapes under its own channel names, "
                    "map them with --name-map FILE, docs/names.md)")
    w = result.weights
    if args.json:
        import json

        from . import all_warnings, json_path

        eq4 = rep.get("retarget") or {}
        print(json.dumps({"ok": True, "output": json_path(args.output), "sources": list(result.names),
                          "targets": list(result.avatar_names), "mu": eq4.get("mu"),
                          "mu_choice": eq4.get("mu_choice"), "weight_bounds": eq4.get("bounds"),
                          "map_prior": eq4.get("prior"), "map_gaze": eq4.get("gaze"),
                          "weight_min": float(w.min()) if w.size else 0.0,
                          "weight_max": float(w.max()) if w.size else 0.0,
                          "above_0_05": int((abs(w) > 0.05).sum()), "no_row": list(lacking),
                          "warnings": all_warnings(rep.get("warnings"))}))
        return 0
    print(f"{w.shape[0]} x {w.shape[1]} retarget map -> {args.output} (weights in [{w.min():.2f}, "
          f"{w.max():.2f}], {int((abs(w) > 0.05).sum())} above 0.05)")
    return 0
