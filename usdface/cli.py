"""The ``usdface`` command line: parse, call the API, print. Each sub-command lives in
``usdface/commands/<name>.py`` and exposes ``register(subparsers)`` which adds its parser and sets
``func=run(args) -> int``.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from . import __version__
from .errors import UsdFaceError

#: Sub-command modules, in the order ``usdface --help`` lists them.
COMMAND_MODULES = (
    "personalize", "fit", "evaluate", "retarget", "landmarks", "inspect", "check", "capture", "anim",
    "sample", "render", "batch", "review", "export",
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


def _silence_stdout() -> None:
    """Point stdout at /dev/null after the reader closed the pipe, so Python's final flush stays quiet."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # stdout is not a real file (captured in tests)
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, fd)
    os.close(devnull)


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    try:
        code = int(args.func(args) or 0)
        sys.stdout.flush()  # a closed pipe (`usdface inspect x | head`) fails here, not at interpreter exit
        return code
    except BrokenPipeError:
        _silence_stdout()
        return 141  # 128 + SIGPIPE, what a shell tool killed by the closed pipe returns
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
