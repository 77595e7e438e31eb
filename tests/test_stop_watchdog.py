"""The ``usdface`` program's stop bound (``usdface.cli._Stop``, ``_on_sigint``, ``_on_sigterm``) in this
process: the watchdog's delay from ``USDFACE_STOP_SECONDS``, its exit status and line, one watchdog per
stop, a second Ctrl-C. ``os._exit`` is replaced by a recorder (the process must not end); every watchdog a
test starts fires before the test ends, while the recorder is in place. The end-to-end runs (a stopped batch
stuck at exit) are in ``test_batch.py``."""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from usdface import cli


class _Exits:
    """``os._exit`` recorded: ``(status, seconds since the recorder was made)`` per call."""

    def __init__(self):
        self.calls: list[tuple[int, float]] = []
        self.event = threading.Event()
        self.start = time.monotonic()

    def __call__(self, status):
        self.calls.append((int(status), time.monotonic() - self.start))
        self.event.set()

    def wait(self, timeout=10.0):
        assert self.event.wait(timeout), "the watchdog did not end the process"
        return self.calls[0]


@pytest.fixture
def exits(monkeypatch):
    rec = _Exits()
    monkeypatch.setattr(os, "_exit", rec)
    monkeypatch.delenv("USDFACE_STOP_SECONDS", raising=False)
    yield rec
    _settle()              # pass or fail, no watchdog outlives the recorder (it would end pytest)


def _watchdogs():
    return [t for t in threading.enumerate() if t.name == "usdface stop watchdog"]


def _settle():
    """Until no watchdog of this test runs any more (each fires within its short bound)."""
    deadline = time.monotonic() + 10
    while _watchdogs() and time.monotonic() < deadline:
        time.sleep(0.02)


def test_a_stop_exits_with_its_signals_status_after_the_bound_the_environment_sets(exits, monkeypatch, capfd):
    monkeypatch.setenv("USDFACE_STOP_SECONDS", "0.3")
    stop = cli._Stop()
    stop.begin(signal.SIGTERM)
    assert stop.status == 128 + signal.SIGTERM
    dogs = _watchdogs()
    assert dogs and all(t.daemon for t in dogs)        # the interpreter's exit does not wait for it
    status, when = exits.wait()
    _settle()
    assert status == 143
    assert 0.3 <= when < 8.0
    assert "usdface: terminated: still stopping after 0.3 s" in capfd.readouterr().err


@pytest.mark.parametrize("value, seconds", [("soon", 0.4), ("-5", 0.0)])
def test_a_bound_that_is_no_number_is_the_default_and_a_negative_one_is_none(exits, monkeypatch, capfd,
                                                                           value, seconds):
    """``USDFACE_STOP_SECONDS=soon``: the default bound (here 0.4 s), not none at all; a negative one: the
    program exits at once (a watchdog that slept a negative time raised in its thread and never exited)."""
    monkeypatch.setattr(cli, "STOP_SECONDS", 0.4)
    monkeypatch.setenv("USDFACE_STOP_SECONDS", value)
    cli._Stop().begin(signal.SIGINT)
    status, when = exits.wait()
    _settle()
    assert status == 130
    assert seconds <= when < seconds + 8.0
    assert f"usdface: interrupted: still stopping after {seconds:g} s" in capfd.readouterr().err


def test_a_second_signal_does_not_restart_the_stop(exits, monkeypatch):
    """The first stop signal sets the status and starts the one watchdog: a SIGTERM after a Ctrl-C neither
    changes the status (130) nor starts a second watchdog (two exits)."""
    monkeypatch.setenv("USDFACE_STOP_SECONDS", "0.2")
    stop = cli._Stop()
    stop.begin(signal.SIGINT)
    stop.begin(signal.SIGTERM)
    assert (stop.status, stop.signum) == (130, signal.SIGINT)
    exits.wait()
    _settle()
    time.sleep(0.1)
    assert [status for status, _ in exits.calls] == [130]


def test_exiting_without_a_stop_under_way_is_an_interrupt(exits, capfd):
    cli._Stop().exit_now("why")
    assert [status for status, _ in exits.calls] == [130]
    assert capfd.readouterr().err == "usdface: interrupted: why\n"


def test_a_second_ctrl_c_exits_at_once_and_a_first_one_starts_the_stop(exits, monkeypatch, capfd):
    monkeypatch.setenv("USDFACE_STOP_SECONDS", "2")
    monkeypatch.setattr(cli, "_STOP", cli._Stop())
    with pytest.raises(KeyboardInterrupt):
        cli._on_sigint(signal.SIGINT, None)
    assert exits.calls == []                           # the first Ctrl-C: the stop's clean-up runs
    assert cli._STOP.status == 130
    with pytest.raises(KeyboardInterrupt):             # the recorder returns: the handler goes on
        cli._on_sigint(signal.SIGINT, None)
    assert len(exits.calls) == 1 and exits.calls[0][0] == 130
    assert exits.calls[0][1] < 1.5                      # at once, not at the bound
    assert "usdface: interrupted: interrupted again" in capfd.readouterr().err
    _settle()


def test_sigterm_starts_the_stop_and_a_ctrl_c_after_it_does_not_end_it_at_once(exits, monkeypatch):
    monkeypatch.setenv("USDFACE_STOP_SECONDS", "0.5")
    monkeypatch.setattr(cli, "_STOP", cli._Stop())
    with pytest.raises(cli.Terminated) as caught:
        cli._on_sigterm(signal.SIGTERM, None)
    assert caught.value.signum == signal.SIGTERM
    assert (cli._STOP.status, cli._STOP.signum) == (143, signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt):
        cli._on_sigint(signal.SIGINT, None)
    assert exits.calls == []
    status, when = exits.wait()                        # the watchdog of the SIGTERM's stop
    _settle()
    assert status == 143 and when >= 0.5
