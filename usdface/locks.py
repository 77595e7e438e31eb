"""Module-level locks that a forked child gets afresh.

A host may fork (``multiprocessing``'s default start on Linux) while one of its threads holds a lock usdface
keeps around process-wide state (stderr's redirect, the BLAS limit, the warnings filters, progress): that
thread does not exist in the child, the lock is never released there, and the child's first call waited
for good. :class:`ForkSafeLock` is replaced by a new lock in the child (``os.register_at_fork``).
"""

from __future__ import annotations

import os
import threading

__all__ = ["ForkSafeLock"]


class ForkSafeLock:
    """A ``threading.Lock`` (``reentrant=True``: an ``RLock``) used as ``with lock:``, replaced by a new,
    unheld one in a forked child."""

    def __init__(self, reentrant: bool = False):
        self._factory = threading.RLock if reentrant else threading.Lock
        self._lock = self._factory()
        if hasattr(os, "register_at_fork"):
            os.register_at_fork(after_in_child=self._renew)

    def _renew(self) -> None:
        self._lock = self._factory()

    def __enter__(self):
        return self._lock.__enter__()

    def __exit__(self, *exc):
        return self._lock.__exit__(*exc)
