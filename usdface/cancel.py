"""Cooperative stop of running work: the host names a test, the work asks it at safe points.

Some hosts cannot interrupt the work they run: Dask cannot stop a running task (``Client.cancel`` only
forgets it, and the task runs on in its worker and writes its output after the batch that asked for it has
stopped), and a DCC's Cancel button cannot raise into a worker thread safely. Such a host runs the work
inside :func:`stop_when` with a test that says whether the work is still wanted; the work calls
:func:`checkpoint` at safe points - at each progress step (:mod:`usdface.progress`) and just before an
output is published (:func:`usdface.io.atomic.publish`) - and there :class:`Cancelled` unwinds it through
the atomic writers' clean-up, so that nothing is written after the stop. The test is per thread: items run
side by side on one process's threads stop each on its own.

From the Python API::

    from usdface import cancel

    with cancel.stop_when(lambda: cancel_button.pressed):
        usdface.api.personalize_avatar(avatar, capture, out)      # raises cancel.Cancelled once pressed

The batch's Dask items run under :func:`dask_task_cancelled` (the worker's own record of the task).
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator

_LOCAL = threading.local()          # .test: the running work's stop test on this thread, or None


class Cancelled(BaseException):
    """The work was stopped at a :func:`checkpoint` because its host's test said so. A ``BaseException``
    (as ``KeyboardInterrupt``): no ``except Exception`` on the way out may take it for the work's own
    error and carry on."""


@contextlib.contextmanager
def stop_when(test: Callable[[], bool] | None) -> Iterator[None]:
    """Run the ``with`` block's work on this thread so that it stops (:class:`Cancelled`) at its next
    :func:`checkpoint` once ``test()`` is true. ``None``: nothing to test. A block inside another one
    replaces the outer test until it ends."""
    previous = getattr(_LOCAL, "test", None)
    _LOCAL.test = test
    try:
        yield
    finally:
        _LOCAL.test = previous


def checkpoint() -> None:
    """Raise :class:`Cancelled` if this thread's work runs under :func:`stop_when` and its test is true
    now. A test that fails (its host is gone) does not stop the work: only a definite stop does."""
    test = getattr(_LOCAL, "test", None)
    if test is None:
        return
    try:
        stop = bool(test())
    except Exception:  # noqa: BLE001  (the host's test is broken or its host gone: not a stop)
        return
    if stop:
        raise Cancelled("stopped by its host (the batch or application that ran it no longer wants it)")


#: A Dask worker's task states meaning that no client wants the task any more (a cancelled future, a
#: client gone: the scheduler releases its keys, and a running task becomes ``cancelled``).
_DASK_UNWANTED = frozenset({"cancelled", "released", "forgotten"})


def dask_task_cancelled() -> Callable[[], bool] | None:
    """A :func:`stop_when` test for the Dask task running on this thread: true once the worker holds the task
    as no longer wanted (its future cancelled, or its client disconnected: a batch stopped with Ctrl-C,
    SIGTERM or killed). ``None`` outside a Dask task."""
    try:
        from distributed import get_worker

        worker = get_worker()
        key = worker.get_current_task()
        tasks = worker.state.tasks          # the worker's state machine (distributed 2022.8 and later)
    except (ImportError, ValueError, AttributeError):   # not on a Dask worker's task thread
        return None

    def cancelled() -> bool:
        ts = tasks.get(key)
        return ts is None or ts.state in _DASK_UNWANTED

    return cancelled
