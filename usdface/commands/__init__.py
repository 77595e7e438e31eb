"""The sub-commands of the ``usdface`` CLI (one module each, see :mod:`usdface.cli`): thin, parse arguments,
call the API, print."""

from __future__ import annotations

NAME_MAP_HELP = ('JSON object {"studio_channel": "arkitName"} or two-column CSV mapping the avatar\'s '
                 "channel names to ARKit names, for names usdface does not recognise (see docs/names.md)")


def command_line() -> str:
    """The command being run as a shell line that runs it again (a layer's provenance ``command``): the
    arguments ``usdface.cli.main`` parsed (not the host process's ``sys.argv`` when it was given a list),
    each quoted as a shell needs (a path with a space stays one argument)."""
    import shlex

    from ..cli import parsed_argv

    return shlex.join(["usdface", *parsed_argv()])


def add_name_map_option(p) -> None:
    """``--name-map FILE`` for every command that reads an avatar."""
    p.add_argument("--name-map", metavar="FILE", help=NAME_MAP_HELP)


_said: dict[str, None] = {}          # the texts said this run, in the order said
#: Where ``warning:`` lines go: stdout with the command's text, stderr when stdout carries a ``--json``
#: document (a warning line there would make it unparseable); set per run by :func:`reset_warnings`.
_to_stderr = [False]


def say_warning(text) -> None:
    """Print ``warning: TEXT`` once per command run (a warning raised by the library and the same text in a
    result's ``warnings`` list are said once)."""
    import sys

    text = str(text).strip()
    if text in _said:
        return
    _said[text] = None
    print(f"warning: {text}", file=sys.stderr if _to_stderr[0] else sys.stdout)


def reset_warnings(json_on_stdout: bool = False) -> None:
    _said.clear()
    _to_stderr[0] = bool(json_on_stdout)


def all_warnings(own) -> list[str]:
    """A ``--json`` document's ``warnings``: the result's ``own`` list, then every other warning the run
    said (a reader's: a template name that is not ARKit, weights the template lacks), each once - a pipeline
    reading the document sees what a person reading the terminal sees."""
    out = [str(w).strip() for w in own or []]
    return out + [w for w in _said if w not in out]


def json_path(path) -> str | None:
    """A written file as ``--json`` reports it (``"output"``): absolute, whatever the command was given, so
    every command's document names its output the same way (None when nothing was written)."""
    import os

    return None if path is None else os.path.abspath(str(path))
