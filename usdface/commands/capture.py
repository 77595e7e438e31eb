"""``usdface capture import DIR -o capture.usda`` and ``usdface capture select TAKE -o capture.usda``."""

from __future__ import annotations

import warnings
from pathlib import Path

from . import json_path, say_warning
from .options import add_quiet, nonnegative_float, nonnegative_int, positive_int, unit_float


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "capture", help="import a capture folder or select frames from a take",
        description="Capture tools: import a capture folder as capture.usda, or pick training frames from a "
                    "continuous take (Menzel et al. 3.1).")
    sub = parser.add_subparsers(dest="capture_command", metavar="ACTION", required=True)

    imp = sub.add_parser(
        "import", help="capture folder (OBJ + JSON) -> capture.usda",
        description="Read a capture folder (neutral.obj, template/, train/, test/) and write it as a USD "
                    "capture one can open and scrub (see docs/capture-format.md).")
    imp.add_argument("source", help="capture folder (or a capture .usda to rewrite)")
    imp.add_argument("-o", "--output",
                     help="output .usda/.usdc/.usd, or a name without extension: a capture folder (default: "
                          "<folder name>.usda in the current folder)")
    imp.add_argument("--force", action="store_true", help="overwrite an existing output")
    imp.add_argument("--no-exact", dest="exact", action="store_false",
                     help="store geometry as float32 only (half the size; not bit-exact)")
    add_quiet(imp)
    imp.set_defaults(func=run_import)

    sel = sub.add_parser("select", help="continuous take -> capture.usda (frame selection, Menzel 3.1)",
                         description="Pick training frames from a continuous take: for each shape the frame "
                                     "where its weight exceeds the threshold and peaks over time; hold out a "
                                     "test split; print a coverage table (see docs/takes.md).")
    sel.add_argument("take", help="take: a USD take (time-sampled mesh + weights) or an OBJ-sequence folder "
                                  "with a Live Link Face CSV")
    sel.add_argument("-o", "--output",
                     help="output capture .usda/.usdc (or a folder); without it only the coverage table is "
                          "printed (e.g. for a weights-only Live Link CSV)")
    sel.add_argument("--template", help="capture folder or capture.usda whose template rig to use "
                                        "(default: the take's own template)")
    sel.add_argument("--threshold", type=unit_float, default=0.5, help="minimum peak weight (default 0.5)")
    sel.add_argument("--per-shape", type=positive_int, default=1,
                     help="distinct peaks kept per shape (default 1)")
    sel.add_argument("--test-every", type=nonnegative_int, default=0,
                     help="hold out every K-th take frame that shows an expression (a weight >= 0.15; "
                          "never a rest) at least --min-separation from every training frame as a test "
                          "frame (default 0: none)")
    sel.add_argument("--min-separation", type=nonnegative_float, default=0.5,
                     help="seconds between two peaks of the same shape, and between a test frame and every "
                          "training frame (default 0.5)")
    sel.add_argument("--force", action="store_true", help="overwrite an existing output")
    sel.add_argument("--json", action="store_true", help="print the coverage table and result as JSON")
    add_quiet(sel)
    sel.set_defaults(func=run_select)


def default_import_output(source) -> Path:
    """``capture import``'s output without ``-o``: ``<folder name>.usda`` (a capture file given: its stem) in
    the current folder, never beside the source (a capture app's export, often read-only), as
    ``personalize`` names its layer after the avatar (``capture/`` -> ``capture.usda``)."""
    src = Path(source)
    if src.name in ("", ".", ".."):
        src = src.resolve()
    usd = src.suffix.lower() in (".usda", ".usdc", ".usd", ".usdz")
    return Path(f"{src.stem if usd else src.name}.usda")


def run_import(args) -> int:
    from .. import api
    from ..io.capture_folder import refuse_whole_take
    from ..progress import steps

    if not args.output:
        args.output = str(default_import_output(args.source))
    api.refuse_missing_inputs(capture_path=args.source)     # a missing source before the output's problems
    api.check_capture_output(args.output, args.force, inputs=[args.source])
    with steps("capture import", 2) as p:
        p.start(f"read {Path(args.source).name}")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            capture = api.read_capture(args.source)
        refuse_whole_take(capture, args.source)
        for w in caught:
            say_warning(w.message)
        p.start(f"write {Path(args.output).name}")
        out = api.write_capture(capture, args.output, force=args.force, exact=args.exact, source=args.source)
    report = capture.metadata.get("name_report", {})
    counts = capture.metadata.get("counts", {})
    print(f"wrote {out}: {capture.neutral.shape[0]} vertices, {len(capture.names)} shapes, "
          f"{counts.get('train', 0)} train + {counts.get('test', 0)} test frames")
    if report.get("missing"):
        print(f"missing shapes: {', '.join(report['missing'])}")
    if report.get("inexact"):
        print(f"renamed: {len(report['inexact'])} shape names mapped to canonical ARKit names "
              f"(e.g. {report['inexact'][0][0]} -> {report['inexact'][0][1]})")
    return 0


def run_select(args) -> int:
    from .. import api

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = api.select_capture_frames(args.take, args.output, template=args.template,
                                           threshold=args.threshold, per_shape=args.per_shape,
                                           test_every=args.test_every, min_separation=args.min_separation,
                                           force=args.force)
    from ..io.take import missing_arkit_weights

    # ARKit shapes the take has no weights for at all (a CSV without the column): the coverage table,
    # of the take's own shapes, left them out without a word (a user trial)
    taken = getattr(result.take, "names", None)     # None from a studio's stand-in for the API
    absent, absent_text = ([], None) if taken is None else missing_arkit_weights(
        args.take, taken, effect="they cannot be selected (the capture gives them weight 0)",
        fix="export the take with every ARKit weight, or record them in another take")
    if args.json:
        import json

        sel = result.selection
        shapes = [{"name": s.name, "triggered": bool(s.frames), "frames": [int(f) for f in s.frames],
                   "times_s": [float(result.take.times[f]) for f in s.frames],
                   "peak": [float(v) for v in s.peak], "dominance": [float(v) for v in s.dominance],
                   "strongest_other": list(s.rival), "max_weight": float(s.max_weight)} for s in sel.shapes]
        print(json.dumps({"ok": True, "output": json_path(result.out_path),
                          "threshold": float(sel.threshold), "per_shape": int(sel.per_shape),
                          "train_frames": [int(f) for f in sel.train],
                          "test_frames": [int(f) for f in sel.test], "shapes": shapes,
                          "never_triggered": [s["name"] for s in shapes if not s["triggered"]],
                          "not_in_take": absent,
                          "warnings": [str(w.message) for w in caught] + ([absent_text] if absent else [])}))
        return 0
    print(result.coverage)
    for w in caught:
        say_warning(w.message)
    if absent:
        say_warning(absent_text)
    if result.capture is None:
        return 0
    counts = result.capture.metadata.get("counts", {})
    print(f"wrote {result.out_path}: {counts.get('train', 0)} train + {counts.get('test', 0)} test frames")
    return 0
