"""A forked child and a lock another thread holds: the tests of the locks usdface takes around process-wide
state (stderr, the BLAS limit, the warnings filters) fork while a thread is inside one."""

from __future__ import annotations

import os
import signal
import threading
import time


def child_finishes(block, hold) -> bool:
    """Fork while another thread is inside ``hold`` (a context manager); True if the child runs ``block``
    and exits within 3 s (False: it waited for good on a lock held by a thread the child does not have)."""
    inside, leave = threading.Event(), threading.Event()

    def holder():
        with hold():
            inside.set()
            leave.wait(10)

    thread = threading.Thread(target=holder)
    thread.start()
    try:
        assert inside.wait(5)
        pid = os.fork()
        if pid == 0:                                  # the child: nothing of pytest's may run here
            try:
                block()
            finally:
                os._exit(0)
        deadline = time.monotonic() + 3
        while time.monotonic() < deadline:
            if os.waitpid(pid, os.WNOHANG)[0]:
                return True
            time.sleep(0.02)
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        return False
    finally:
        leave.set()
        thread.join()
