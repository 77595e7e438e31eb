"""A stand-in for ``usdface.cli.build_parser``: one command, ``wait NAME [-q]``, that runs a given function,
for the tests that run ``cli.main(argv)`` on a host's threads side by side."""

from __future__ import annotations

import argparse


def waiting_parser(run):
    """``build_parser`` replacement: ``usdface [--debug] wait NAME [-q]`` calls ``run(args)``."""

    def build_parser() -> argparse.ArgumentParser:
        parser = argparse.ArgumentParser(prog="usdface")
        parser.add_argument("--debug", action="store_true")
        sub = parser.add_subparsers(dest="command")
        cmd = sub.add_parser("wait")
        cmd.add_argument("name")
        cmd.add_argument("-q", "--quiet", action="store_true")
        cmd.set_defaults(func=run)
        return parser

    return build_parser
