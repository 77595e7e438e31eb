"""The ``usdface`` command line: parse, call the API, print. Each sub-command lives in
``usdface/commands/<name>.py`` and exposes ``register(subparsers)`` which adds its parser and sets
``func=run(args) -> int``.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from . import __version__
from .errors import UsdFaceError

#: Sub-command modules, in the order ``usdface --help`` lists them.
COMMAND_MODULES = (
    "personalize", "fit", "evaluate", "retarget", "landmarks", "inspect", "check", "capture", "anim",
    "sample", "render", "batch",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="usdface",
        description="Personalized ARKit facial blendshapes from a phone capture, written as a USD layer.")
    parser.add_argument("--version", action="version", version=f"usdface {__version__}")
    parser.add_argument("--debug", action="store_true", help="show full tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            mod = importlib.import_module(f"usdface.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"usdface.commands.{name}":
                continue  # command not built yet
            raise
        mod.register(sub)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    try:
        return int(args.func(args) or 0)
    except UsdFaceError as exc:
        if args.debug:
            raise
        print(f"usdface {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("usdface: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
