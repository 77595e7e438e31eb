"""``usdface anim import take.csv -o take.usda``: a Live Link Face CSV as a UsdSkel SkelAnimation."""

from __future__ import annotations

import warnings
from pathlib import Path

from . import json_path, say_warning
from .options import add_quiet, positive_float


def register(subparsers) -> None:
    parser = subparsers.add_parser("anim", help="weight animations (Live Link Face CSV -> SkelAnimation)",
                                   description="Blend-shape weight animations.")
    sub = parser.add_subparsers(dest="anim_command", metavar="ACTION", required=True)
    imp = sub.add_parser(
        "import", help="Live Link Face CSV -> take.usda (SkelAnimation, time-sampled weights)",
        description="Read a Live Link Face CSV and write a USD file whose defaultPrim is a SkelAnimation "
                    "with the ARKit weights as time samples (head/eye angles as usdface:curves:* "
                    "attributes). Bind it to an avatar's Skeleton with skel:animationSource.")
    imp.add_argument("csv", help="Live Link Face .csv")
    imp.add_argument("-o", "--output", help="output .usda/.usdc (default: <CSV name>.usda in the current "
                                             "folder)")
    imp.add_argument("--timecode-rate", type=positive_float, default=None,
                     help="frames per second of the CSV's timecode FF field; also the stage's "
                          "timeCodesPerSecond (default 60, Live Link Face's, or the rate larger frame "
                          "fields imply, with a warning; a frame field at or above a rate given is refused, "
                          "a take whose frame fields stay below 30 is warned about)")
    imp.add_argument("--force", action="store_true", help="overwrite an existing output")
    imp.add_argument("--json", action="store_true", help="print the result as JSON")
    add_quiet(imp)
    imp.set_defaults(func=run_import)


def default_import_output(csv) -> Path:
    """``anim import``'s output without ``-o``: ``<CSV stem>.usda`` in the current folder (``take.csv`` ->
    ``take.usda``), as ``personalize`` names its layer after the avatar, never beside the recording; a stem
    that would make a hidden file (``.csv``) gives ``take.usda``. (A folder given is refused as no CSV.)"""
    return Path(f"{Path(csv).stem.lstrip('.') or 'take'}.usda")


def run_import(args) -> int:
    from .. import api

    if not args.output:
        args.output = str(default_import_output(args.csv))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out, take = api.import_livelink_take(args.csv, args.output, timecode_rate=args.timecode_rate,
                                             force=args.force)
    if args.json:
        import json

        print(json.dumps({"ok": True, "output": json_path(out), "frames": len(take.times),
                          "seconds": float(take.times[-1]), "fps": float(take.fps), "names": list(take.names),
                          "name_report": take.name_report, "warnings": [str(w.message) for w in caught]},
                         default=str))
        return 0
    for w in caught:
        say_warning(w.message)
    # frames per second over the whole take (the median step hides a wrong rate: bursts and gaps)
    span = take.times[-1] if len(take.times) > 1 else 0.0
    if span > 0:
        timing = f"{len(take.times)} frames over {span:.2f} s (~{(len(take.times) - 1) / span:.0f} Hz)"
    else:                   # one frame (or one time code): no span, no rate
        timing = f"{len(take.times)} frame{'s' if len(take.times) != 1 else ''} (no duration, no rate)"
    print(f"wrote {out}: {timing}, {len(take.names)} shapes")
    if take.name_report.get("missing"):
        print(f"missing shapes: {', '.join(take.name_report['missing'])}")
    return 0
