"""Cooperative stop (usdface.cancel): work run under a host's test stops at its next safe point and
publishes nothing; other threads' work runs on."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from usdface import cancel
from usdface.io.atomic import atomic_file, replace_dir_atomically, write_text_atomic

SAMPLE = Path(__file__).resolve().parents[1] / "sample_assets"


def test_a_stopped_write_publishes_nothing_and_leaves_no_temporary_file(tmp_path):
    with cancel.stop_when(lambda: True), pytest.raises(cancel.Cancelled):
        write_text_atomic(tmp_path / "a.txt", "x")
    with cancel.stop_when(lambda: True), pytest.raises(cancel.Cancelled):
        with replace_dir_atomically(tmp_path / "folder") as tmp:
            (tmp / "b.txt").write_text("y")
    assert list(tmp_path.iterdir()) == []


def test_work_not_stopped_writes_as_before(tmp_path):
    with cancel.stop_when(lambda: False):
        write_text_atomic(tmp_path / "a.txt", "x")
    with cancel.stop_when(None):
        write_text_atomic(tmp_path / "b.txt", "y")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt"]


def test_a_broken_test_does_not_stop_the_work(tmp_path):
    """The host's test raising (its client gone) is not a stop: only a definite answer stops the work."""
    def broken():
        raise RuntimeError("no scheduler")

    with cancel.stop_when(broken):
        write_text_atomic(tmp_path / "a.txt", "x")
    assert (tmp_path / "a.txt").read_text() == "x"


def test_the_test_is_per_thread_and_nested_blocks_restore_the_outer_one(tmp_path):
    """Items run side by side on one process's threads (a Dask worker): one stopped, the other finishes."""
    results = {}

    def item(name, stop):
        try:
            with cancel.stop_when(lambda: stop):
                with atomic_file(tmp_path / f"{name}.txt") as tmp:
                    tmp.write_text(name)
            results[name] = "written"
        except cancel.Cancelled:
            results[name] = "stopped"

    threads = [threading.Thread(target=item, args=(n, s)) for n, s in (("a", True), ("b", False))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert results == {"a": "stopped", "b": "written"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.txt"]
    with cancel.stop_when(lambda: True):
        with cancel.stop_when(lambda: False):
            cancel.checkpoint()                  # the inner test rules inside its block
        with pytest.raises(cancel.Cancelled):
            cancel.checkpoint()                  # the outer one again after it
    cancel.checkpoint()                          # nothing outside


def test_personalize_stopped_at_a_step_writes_nothing(tmp_path):
    """The API's personalize under a test that turns true after its first steps stops at the next step and
    writes nothing: no layer, no temporary file, no folder it made."""
    from usdface import api

    calls = []

    def stop_after_three():
        calls.append(1)
        return len(calls) > 3

    out = tmp_path / "new" / "person.usda"
    with cancel.stop_when(stop_after_three), pytest.raises(cancel.Cancelled):
        api.personalize_avatar(SAMPLE / "avatar.usda", SAMPLE / "capture.usda", out)
    assert len(calls) == 4                       # stopped at the first checkpoint after the test turned
    assert list(tmp_path.iterdir()) == []


def test_outside_a_dask_task_there_is_nothing_to_watch():
    assert cancel.dask_task_cancelled() is None


def test_a_dask_task_is_unwanted_once_its_worker_cancels_releases_or_forgets_it(monkeypatch):
    """The test :func:`cancel.dask_task_cancelled` gives a Dask task reads the worker's record of the task
    each time it is asked (the state changes while the task runs): a task executing is wanted; cancelled (its
    future cancelled), released (its client gone) or forgotten, or no longer in the worker's record at all,
    it is not. A stand-in worker (no cluster: the end-to-end runs are in ``test_batch.py``)."""
    from types import SimpleNamespace

    distributed = pytest.importorskip("distributed")
    task = SimpleNamespace(state="executing")
    tasks = {"usdface-item-1": task}
    worker = SimpleNamespace(get_current_task=lambda: "usdface-item-1", state=SimpleNamespace(tasks=tasks))
    monkeypatch.setattr(distributed, "get_worker", lambda: worker)
    test = cancel.dask_task_cancelled()
    assert test is not None and test() is False
    for state in ("cancelled", "released", "forgotten"):
        task.state = state
        assert test() is True, state
    task.state = "executing"
    assert test() is False
    tasks["usdface-item-1"] = SimpleNamespace(state="released")     # the record replaced: read anew
    assert test() is True
    del tasks["usdface-item-1"]
    assert test() is True
