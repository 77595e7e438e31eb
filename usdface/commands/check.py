"""``usdface check FILE``: face-rig rules + OpenUSD's validators, one report; non-zero exit on errors."""

from __future__ import annotations

import json
import sys

from ..namelist import name_list
from . import add_name_map_option


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "check", help="validate a face rig or usdface layer (face-rig rules + OpenUSD validators)",
        description="Run usdface's ARKit face-rig rules and OpenUSD's own validators (UsdValidation) on a "
                    "USD file and print one merged report. Exit status: 0 clean, 1 errors found "
                    "(or warnings with --strict), 2 the file cannot be read.")
    p.add_argument("file", help="USD file (.usd, .usda, .usdc)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument("--no-pixar", action="store_true", help="run only usdface's face-rig rules")
    add_name_map_option(p)
    p.add_argument("--face-mesh", metavar="PRIM",
                   help="the face mesh personalize will be given (--face-mesh): a file holding several "
                        "characters' face rigs (a shot) is an error without it, as personalize refuses it")
    p.add_argument("--rules", help="comma-separated usdface rule ids to run (default: all)")
    p.add_argument("--strict", action="store_true", help="warnings also make the exit status non-zero")
    p.add_argument("--quiet", "-q", action="store_true", help="hide info-level findings in the text report")
    p.set_defaults(func=run)


def _refuse_folder(path) -> None:
    """``check`` validates USD files: a take or capture folder gets a fix that says what reads it."""
    from pathlib import Path

    from ..errors import InputFileError

    folder = Path(path)
    if not folder.is_dir():
        return
    from ..io.take import is_take

    kind = ("a take folder (OBJ frames + Live Link CSV)" if is_take(folder)
            else "a capture folder" if (folder / "neutral.obj").is_file() else "a folder")
    raise InputFileError(f"{kind}: check validates a USD file", path=folder,
                         fix="pass a .usd/.usda/.usdc file; 'usdface inspect' summarizes a take or capture "
                             "folder, 'usdface capture import' makes a capture folder a .usda")


def run(args) -> int:
    from ..api import check

    _refuse_folder(args.file)
    rules = None
    if args.rules is not None:         # ',' ran none of usdface's rules, and a broken rig passed them
        from ..pipeline.check import RULES

        rules = name_list(args.rules, "--rules", "rule",
                          fix=f"leave --rules out to run all, or name some: {', '.join(sorted(RULES))}")
    issues = check(args.file, pixar=not args.no_pixar, rules=rules, name_map=args.name_map,
                   face_mesh=args.face_mesh)
    counts = {s: sum(i.severity == s for i in issues) for s in ("error", "warning", "info")}
    failed = counts["error"] > 0 or (args.strict and counts["warning"] > 0)
    if args.json:
        json.dump({"ok": not failed, "output": None, "file": str(args.file), "counts": counts,
                   "issues": [i.to_dict() for i in issues]}, sys.stdout, indent=2)
        print()
    else:
        for issue in issues:
            if args.quiet and issue.severity == "info":
                continue
            print(issue)
        print(f"{args.file}: {counts['error']} error(s), {counts['warning']} warning(s), "
              f"{counts['info']} info")
    return 1 if failed else 0
