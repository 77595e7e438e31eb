"""The sub-commands of the ``usdface`` CLI (one module each, see :mod:`usdface.cli`)."""

from __future__ import annotations

_said: set[str] = set()


def say_warning(text) -> None:
    """Print ``warning: TEXT`` once per command run (a warning raised by the library and the same text in a
    result's ``warnings`` list are said once)."""
    text = str(text).strip()
    if text in _said:
        return
    _said.add(text)
    print(f"warning: {text}")


def reset_warnings() -> None:
    _said.clear()
