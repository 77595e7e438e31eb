"""Module-level locks that a forked child gets afresh.

A host may fork (``multiprocessing``'s default start on Linux) while one of its threads holds a lock usdface
keeps around process-wide state (stderr's redirect, the BLAS limit, the warnings filters, progress): that
thread does not exist in the child, the lock is never released there, and the child's first call waited
for good. :class:`ForkSafeLock` is replaced by a new lock in the child (``os.register_at_fork``).
:class:`SharedWhileInside` is that state itself: set by the first thread in, put back by the last one out.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from typing import Any

__all__ = ["ForkSafeLock", "SharedWhileInside"]


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


class SharedWhileInside:
    """Process-wide state held while any thread is inside ``with shared:``: ``install()`` runs when the first
    thread enters, ``restore(token)`` (``token``: what ``install`` returned) when the last one leaves, also
    when it leaves by an exception. Threads side by side share one install (each putting back what it
    found, the first out put back the host's and the last out the state the first had installed, for good);
    a thread may enter again while inside. The count's lock is a :class:`ForkSafeLock`. A child forked while
    other threads are inside has only the forking thread: it counts that thread's own entries, and if there
    are none, puts the state back at once (the threads that installed it will never leave there).

    Examples
    --------
    >>> log = []
    >>> shared = SharedWhileInside(lambda: log.append("set") or "before", log.append)
    >>> with shared:
    ...     with shared:
    ...         pass
    >>> log
    ['set', 'before']
    """

    def __init__(self, install: Callable[[], Any], restore: Callable[[Any], None]):
        self._install, self._restore = install, restore
        self._lock = ForkSafeLock()
        self._token = None
        self._entries: dict[int, int] = {}          # thread ident -> its entries now (none: not inside)
        if hasattr(os, "register_at_fork"):         # after the lock's own renewal (registered before)
            os.register_at_fork(after_in_child=self._after_fork)

    @property
    def inside(self) -> int:
        """Threads (entries) inside now."""
        return sum(self._entries.values())

    def __enter__(self) -> None:
        with self._lock:
            if not self._entries:
                self._token = self._install()       # an install that raises counts nobody in
            me = threading.get_ident()
            self._entries[me] = self._entries.get(me, 0) + 1

    def __exit__(self, *exc) -> None:
        with self._lock:
            me = threading.get_ident()
            if self._entries[me] > 1:
                self._entries[me] -= 1
            else:
                del self._entries[me]
            if not self._entries:
                token, self._token = self._token, None
                self._restore(token)

    def _after_fork(self) -> None:
        """In a forked child: only the forking thread's entries are inside; none left, the state goes back."""
        me = threading.get_ident()
        own = self._entries.get(me, 0)
        others = bool(self._entries) and not own
        self._entries = {me: own} if own else {}
        if others:
            token, self._token = self._token, None
            try:
                self._restore(token)
            except Exception:                        # a fork must go on; the child keeps the state then
                pass
