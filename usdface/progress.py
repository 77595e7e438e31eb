"""Progress reporting for long steps (rich), silent when not attached to a terminal or when disabled."""

from __future__ import annotations

import contextlib
import sys

_ENABLED = True


def set_enabled(flag: bool) -> None:
    """Turn progress bars on or off for the whole process (``--quiet``)."""
    global _ENABLED
    _ENABLED = bool(flag)


@contextlib.contextmanager
def steps(title: str, total: int):
    """A progress bar over ``total`` named steps.

    ``with steps("personalize", 6) as advance: advance("ICP")``
    """
    if not _ENABLED or not sys.stderr.isatty():
        yield lambda label=None: None
        return
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    columns = (TextColumn("[bold]{task.description}"), BarColumn(),
               TextColumn("{task.completed}/{task.total}"), TimeElapsedColumn())
    with Progress(*columns, transient=False) as prog:
        task = prog.add_task(title, total=total)

        def advance(label: str | None = None):
            prog.update(task, advance=1, description=f"{title}: {label}" if label else title)

        yield advance
