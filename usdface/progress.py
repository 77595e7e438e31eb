"""Progress reporting for long steps, on stderr: a rich bar on a terminal, plain lines in logs and CI.

The mode is chosen per ``steps()`` block: ``bar`` when stderr is a terminal, ``plain`` when it is not (a log,
CI, a pipe): no control codes, one flushed line when a step has run :func:`delay` seconds (2 by default,
``USDFACE_PROGRESS_DELAY``) naming it, and one when it ends; ``off`` after :func:`set_enabled(False)
<set_enabled>` (``--quiet``, ``--json``). ``USDFACE_PROGRESS=bar|plain|off`` overrides the choice;
:func:`set_logger` sends the plain lines to a :mod:`logging` logger instead (a host application's log).

Two ways to mark steps, both on the callable a ``steps()`` block yields::

    with steps("fit", 3) as p:
        p.start("read capture")      # names the step that runs now
        ...
        p.start("fit menzel")        # ends the previous one, starts the next
        ...
    with steps("personalize", 8) as advance:
        ...
        advance("read")              # the step "read" is done

A ``steps()`` block inside another one (an API call inside a command's block) shares the same bar (a
second row) or prefixes its lines with the outer title.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import time

from .cancel import checkpoint

_ENABLED = True
_STACK: list[_Steps] = []  # open steps() blocks, outermost first
_LIVE = None  # the rich Progress shared by nested blocks in bar mode
_LOGGER = None  # a host application's logging.Logger for the plain lines (set_logger), else stderr


def set_enabled(flag: bool) -> None:
    """Turn progress on or off for the whole process (``--quiet``, ``--json``)."""
    global _ENABLED
    _ENABLED = bool(flag)


def set_logger(logger) -> None:
    """Send the progress lines to ``logger`` (a :class:`logging.Logger`, level INFO; the plain lines, no bar)
    instead of stderr: a host application's own log (a DCC's, a farm job's). ``None``: back to stderr.
    Warnings are Python warnings (``logging.captureWarnings(True)`` routes them to the same log)."""
    global _LOGGER
    _LOGGER = logger


def mode() -> str:
    """``off``, ``bar`` or ``plain``: what a ``steps()`` block opened now shows."""
    if not _ENABLED:
        return "off"
    env = os.environ.get("USDFACE_PROGRESS", "").strip().lower()
    if env in ("off", "0", "none", "quiet"):
        return "off"
    if _LOGGER is not None:
        return "plain"
    if env in ("bar", "plain"):
        return env
    try:
        tty = sys.stderr.isatty()
    except (AttributeError, ValueError):  # stderr closed or replaced by an object without isatty
        tty = False
    return "bar" if tty else "plain"


def delay() -> float:
    """Seconds a step runs before its plain line is printed (``USDFACE_PROGRESS_DELAY``, default 2): a log
    names every step that takes longer, and a quick command (or a quick error) prints no progress at all."""
    try:
        value = float(os.environ.get("USDFACE_PROGRESS_DELAY", "2"))
    except ValueError:
        return 2.0
    return value if value >= 0 else 2.0  # NaN and negatives: the default


class _Steps:
    """The callable a ``steps()`` block yields: ``advance(label)`` (a step is done) and ``start(label)``
    (a step begins; the one started before is done)."""

    def __init__(self, title: str, total: int, how: str, every: bool = False):
        self.title, self.total, self.how = title, max(int(total), 0), how
        self.every = every      # a plain line for every step, however quick (a batch's items)
        self.done = 0
        self.running: str | None = None
        self.t0 = self.t_step = time.perf_counter()
        self.task = None
        self.delay = delay()
        self.timer: threading.Timer | None = None
        self.announced = False  # the running step's line is printed
        self.printed = False    # any line of this block is printed
        self.t_line = self.t0   # when this block last printed (many short steps: a line every ``delay`` s)
        self.lock = threading.Lock()
        self.waiting_for = None  # waiting(): what runs elsewhere, a callable giving its label
        self.wait_timer: threading.Timer | None = None
        outer = [s.title for s in _STACK if s.how == "plain"]
        self.prefix = " > ".join([*outer, title])

    # plain lines -----------------------------------------------------------------------------------------
    def _line(self, text: str) -> None:
        self.printed = True
        self.t_line = time.perf_counter()
        if _LOGGER is not None:
            _LOGGER.info("%s %s", self.prefix, text)
        else:
            print(f"usdface: {self.prefix} {text}", file=sys.stderr, flush=True)

    def _counter(self, n: int) -> str:
        return f"[{min(n, self.total)}/{self.total}]" if self.total else f"[{n}]"

    def _announce(self, label: str) -> None:
        """The running step's line (from the timer thread once it has run ``delay`` seconds)."""
        with self.lock:
            if self.running == label and not self.announced:
                self.announced = True
                self._line(f"{self._counter(self.done + 1)} {label} ... "
                           f"(t+{self.t_step - self.t0:.1f} s)")

    def _end_running(self) -> None:
        """The started step is done: stop its timer; if its line was printed, say how long it took."""
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None
        with self.lock:
            label, self.running = self.running, None
            self.done += 1
            if self.how == "plain" and self.announced:
                self._line(f"{self._counter(self.done)} {label} done "
                           f"({time.perf_counter() - self.t_step:.1f} s)")
            self.announced = False
        if self.how == "bar":
            _LIVE.update(self.task, advance=1)

    def _waited(self, since: float) -> None:
        """The waiting line (timer thread): the steps running elsewhere, unless a line came since."""
        with self.lock:
            if self.waiting_for is None or self.t_line > since or self.done >= self.total:
                return
            label = self.waiting_for()
            if label:
                since_start = time.perf_counter() - self.t0
                self._line(f"{self._counter(self.done + 1)} {label} ... (t+{since_start:.1f} s)")

    def _arm_wait(self) -> None:
        if self.wait_timer is not None:
            self.wait_timer.cancel()
            self.wait_timer = None
        if self.how != "plain" or self.waiting_for is None or self.done >= self.total:
            return
        self.wait_timer = threading.Timer(self.delay, self._waited, args=(time.perf_counter(),))
        self.wait_timer.daemon = True
        self.wait_timer.start()

    def waiting(self, label) -> None:
        """Steps that run elsewhere (a batch's items on pool workers or a Dask cluster, which print nothing
        here): once ``delay`` seconds pass with no line of this block, one line ``[i/n] <label()> ...``
        naming what runs (``label``: a callable, asked then), and again after each step that ends, so a log
        says what is running as it does for a step run here. Plain mode only (a bar shows its own clock)."""
        self.waiting_for = label
        self._arm_wait()

    # the two calls ---------------------------------------------------------------------------------------
    def __call__(self, label: str | None = None, outcome: str = "done", seconds: float | None = None) -> None:
        """The step ``label`` (or the one started last) is over; ``outcome`` says how (``done``, or e.g.
        ``failed`` for a batch item whose error is reported at the end). ``seconds``: how long the step ran,
        when it did not run since the step before ended (a batch item on a pool: by default the time since
        then).

        Each step is a safe point for work its host has stopped (:func:`usdface.cancel.checkpoint`)."""
        checkpoint()
        if self.how == "off":
            return
        if self.running is not None:
            self._end_running()
            self.t_step = time.perf_counter()
            return
        self.done += 1
        now = time.perf_counter()
        if self.how == "plain":
            if (self.every or now - self.t_step >= self.delay or now - self.t_line >= self.delay
                    or outcome != "done"):  # a failure is always said
                took = now - self.t_step if seconds is None else seconds
                self._line(f"{self._counter(self.done)} {label or 'step'} {outcome} ({took:.1f} s)")
        else:
            text = f"{label} {outcome}" if label and outcome != "done" else label
            _LIVE.update(self.task, advance=1, description=f"{self.title}: {text}" if text else self.title)
        self.t_step = now
        if self.waiting_for is not None:
            self._arm_wait()

    def start(self, label: str) -> None:
        """The step ``label`` begins (ending the one started before, if any); a safe point to stop, as the
        end of a step is."""
        checkpoint()
        if self.how == "off":
            return
        if self.running is not None:
            self._end_running()
        self.running = label
        self.t_step = time.perf_counter()
        if self.how == "bar":
            _LIVE.update(self.task, description=f"{self.title}: {label}")
        elif self.delay <= 0 or self.t_step - self.t_line >= self.delay:
            self._announce(label)
        else:
            self.timer = threading.Timer(self.delay, self._announce, args=(label,))
            self.timer.daemon = True
            self.timer.start()

    def _close(self, ok: bool) -> None:
        if self.how == "off":
            return
        self.waiting_for = None
        if self.wait_timer is not None:
            self.wait_timer.cancel()
        if self.running is not None:
            if ok:
                self._end_running()
            elif self.timer is not None:
                self.timer.cancel()
                self.running = None
        if self.how == "plain" and ok and self.printed:
            self._line(f"done in {time.perf_counter() - self.t0:.1f} s")


def announce() -> None:
    """Print the running step's plain line now, in every open ``steps()`` block that has not printed it yet:
    called before a native call that holds Python's GIL for seconds (Open3D's quadric decimation of a large
    mesh), during which the timer thread that prints it after :func:`delay` seconds cannot run (its line
    came when the call had ended, 8 s late, in a 19 s step). A step that is not running, or whose line is
    out, prints nothing; bar mode and ``off`` print nothing."""
    for s in _STACK:
        if s.how == "plain" and s.running is not None:
            s._announce(s.running)


@contextlib.contextmanager
def steps(title: str, total: int, *, every: bool = False):
    """A progress block over ``total`` named steps (see the module docstring). ``every``: in plain mode a
    line for each step however quick (a batch's items, which a farm log must list one by one)."""
    global _LIVE
    how = mode()
    s = _Steps(title, total, how, every)
    own_live = False
    if how == "bar":
        if _LIVE is None:
            from rich.console import Console
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

            columns = (TextColumn("[bold]{task.description}"), BarColumn(),
                       TextColumn("{task.completed}/{task.total}"), TimeElapsedColumn())
            _LIVE = Progress(*columns, transient=False, console=Console(stderr=True))
            _LIVE.start()
            own_live = True
        s.task = _LIVE.add_task(title, total=s.total or None)
    _STACK.append(s)
    ok = False
    try:
        yield s
        ok = True
    finally:
        _STACK.pop()
        s._close(ok)
        if how == "bar":
            if own_live:
                _LIVE.stop()
                _LIVE = None
            else:
                _LIVE.remove_task(s.task)
