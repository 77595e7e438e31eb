"""``usdface inspect FILE [--json]``: meshes, units, shapes vs ARKit 52, storage, provenance."""

from __future__ import annotations

import json
import sys

from . import add_name_map_option
from .options import add_quiet


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "inspect", help="summarize an avatar, a usdface layer or a capture",
        description="Print what a USD avatar (or usdface output layer) or a capture contains: meshes, vertex "
                    "counts, units and up axis, shapes against the ARKit 52 (missing / extra / misspelt / "
                    "renamed such as Blender's eyeBlinkLeft2), how each channel name was mapped (exact, "
                    "spelling variant, DCC suffix, name map, unmapped), sparse or dense storage, inbetweens, "
                    "and for "
                    "usdface layers the provenance; for captures the frames by role.")
    p.add_argument("file", help="avatar or layer (.usd/.usda/.usdc), capture.usda, or a capture folder")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    add_name_map_option(p)
    add_quiet(p)          # (inspect shows no progress: taken so a wrapper can pass -q to every command)
    p.set_defaults(func=run)


def run(args) -> int:
    from ..inspect import format_report, inspect_file

    report = inspect_file(args.file, name_map=args.name_map)
    if args.json:
        json.dump({"ok": True, "output": None, **report}, sys.stdout, indent=2, default=str)
        print()
    else:
        print(format_report(report))
    return 0
