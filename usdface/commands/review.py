"""``usdface review LAYER -o review.html``: one self-contained web page to review a personalize result."""

from __future__ import annotations

from pathlib import Path

from .options import add_quiet, nonnegative_int


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "review", help="a self-contained HTML viewer of a personalize result (generic | personalized)",
        description="Write ONE HTML file (the viewer and the mesh data inside; no server, no network) that "
                    "shows the avatar's face meshes lit and orbitable, generic and personalized side by side "
                    "with a shared camera: a slider per ARKit shape, presets, a heat map of the change (mm), "
                    "the landmarks when the layer has them, playback of the capture's test expressions and "
                    "of a Live Link Face take, and the fit's figures.")
    p.add_argument("layer", help="a layer written by 'usdface personalize' (.usda/.usdc)")
    p.add_argument("-o", "--output", type=Path, help="HTML file to write (default: <layer>.review.html)")
    p.add_argument("--capture", help="capture whose test expressions are played and scored (default: the one "
                                     "recorded in the layer's provenance, when it still exists)")
    p.add_argument("--take", help="a Live Link Face CSV (or USD take / take folder) to play (default: the "
                                  "take the layer was written with, 'personalize --take', when it still "
                                  "exists)")
    p.add_argument("--no-fit-errors", action="store_true",
                   help="skip scoring the fit on the capture's test expressions (eq. 5: the layer's recorded "
                        "figures; another --capture is refitted)")
    p.add_argument("--max-vertices", type=nonnegative_int, default=None, metavar="N",
                   help="show a mesh of more vertices decimated to about N of its own vertices (default "
                        "60000: a 225k-vertex head made a 124 MB page that updated a pose in seconds); 0 "
                        "shows every vertex")
    p.add_argument("--force", action="store_true", help="overwrite the HTML file")
    p.add_argument("--allow-moved-neutral", action="store_true",
                   help="review a layer whose avatar's neutral was re-sculpted after it was written (refused "
                        "by default: its offsets were fitted and checked on the old neutral)")
    p.add_argument("--json", action="store_true", help="print what was written as JSON (output, warnings)")
    add_quiet(p)
    p.set_defaults(func=run)


def default_output(layer) -> Path:
    """``<layer stem>.review.html`` next to the layer."""
    layer = Path(layer)
    return layer.with_name(layer.stem + ".review.html")


def run(args) -> int:
    from ..api import write_review

    out = args.output or default_output(args.layer)
    path = write_review(args.layer, out, capture=args.capture, take=args.take,
                        fit_errors=not args.no_fit_errors, force=args.force, max_vertices=args.max_vertices,
                        allow_moved_neutral=args.allow_moved_neutral)
    if args.json:
        import json

        from . import all_warnings, json_path

        print(json.dumps({"ok": True, "output": json_path(path), "bytes": path.stat().st_size,
                          "warnings": all_warnings([])}))
        return 0
    print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB)")
    return 0
