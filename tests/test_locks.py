"""usdface.locks: the process-wide state the first thread in installs and the last one out puts back."""

from __future__ import annotations

import os
import threading

import pytest
from forking import child_finishes

from usdface.locks import SharedWhileInside


def _recording():
    """A SharedWhileInside whose install returns a new token each time, and the log of both calls."""
    log = []

    def install():
        log.append(("install", len(log)))
        return len(log) - 1

    return SharedWhileInside(install, lambda token: log.append(("restore", token))), log


def test_two_threads_side_by_side_share_one_install_put_back_after_the_last_leaves():
    shared, log = _recording()
    first_in, second_in, first_out = threading.Event(), threading.Event(), threading.Event()
    seen = {}

    def first():
        with shared:
            first_in.set()
            second_in.wait(5)
        first_out.set()

    def second():
        first_in.wait(5)
        with shared:
            second_in.set()
            first_out.wait(5)
            seen["after the first left"] = list(log)

    threads = [threading.Thread(target=first), threading.Thread(target=second)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert seen["after the first left"] == [("install", 0)]       # the first out put nothing back
    assert log == [("install", 0), ("restore", 0)]                # once each, the token install gave
    assert shared.inside == 0


def test_an_exception_inside_still_restores_and_the_next_entry_installs_again():
    shared, log = _recording()
    with pytest.raises(RuntimeError), shared:
        raise RuntimeError("item failed")
    assert log == [("install", 0), ("restore", 0)] and shared.inside == 0
    with shared:
        pass
    assert log[2:] == [("install", 2), ("restore", 2)]


def test_entering_again_on_the_same_thread_installs_once():
    shared, log = _recording()
    with shared:
        with shared:
            assert shared.inside == 2
        assert log == [("install", 0)]
    assert log == [("install", 0), ("restore", 0)]


def test_an_install_that_fails_counts_nobody_in():
    calls = []

    def install():
        calls.append(1)
        if len(calls) == 1:
            raise OSError("cannot set it")
        return "token"

    restored = []
    shared = SharedWhileInside(install, restored.append)
    with pytest.raises(OSError), shared:
        pass
    assert shared.inside == 0 and restored == []
    with shared:                                  # installed on the next entry, not taken as already there
        pass
    assert calls == [1, 1] and restored == ["token"]


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork")
def test_a_child_forked_while_another_thread_holds_the_count_lock_can_enter():
    """A host forking while one of its threads was counting itself in (an install takes milliseconds: a
    ThreadpoolController made again): the child's first entry must not wait for good on that lock."""
    shared, _ = _recording()

    def block():
        with shared:
            pass

    assert child_finishes(block, lambda: shared._lock)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork")
def test_a_child_forked_while_another_thread_is_inside_puts_the_state_back():
    """The thread that installed the state (the BLAS limit of one thread, a host's progress off) does not
    exist in a forked child, so it never leaves there: the child puts the state back at once, and its own
    next entry installs it again. The parent's count is untouched."""
    shared, log = _recording()
    read, write = os.pipe()

    def block():
        os.write(write, repr((list(log), shared.inside)).encode() + b"\n")
        with shared:
            os.write(write, repr((list(log), shared.inside)).encode() + b"\n")

    assert child_finishes(block, lambda: shared)
    os.close(write)
    with os.fdopen(read) as f:
        lines = f.read().splitlines()
    assert lines[0] == repr(([("install", 0), ("restore", 0)], 0))
    assert lines[1] == repr(([("install", 0), ("restore", 0), ("install", 2)], 1))
    assert log == [("install", 0), ("restore", 0)] and shared.inside == 0     # the parent's, after its thread


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork")
def test_a_child_forked_by_a_thread_inside_keeps_its_own_entry():
    """The forking thread itself inside: in the child it is still inside, and its leaving restores there."""
    shared, log = _recording()
    read, write = os.pipe()
    with shared:
        pid = os.fork()
        if pid == 0:
            try:
                os.write(write, repr((list(log), shared.inside)).encode() + b"\n")
            finally:
                os._exit(0)
        os.waitpid(pid, 0)
    os.close(write)
    with os.fdopen(read) as f:
        assert f.read().splitlines() == [repr(([("install", 0)], 1))]
    assert log == [("install", 0), ("restore", 0)]
