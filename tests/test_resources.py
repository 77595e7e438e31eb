"""What the machine lets a process use (:mod:`usdface.resources`): the cores (affinity, a container's CPU
quota) and the memory available (``MemAvailable``, a container's memory limit), read from files laid out as
Linux's ``/proc/meminfo`` and cgroup v2 ``/sys/fs/cgroup``; and the batch's default pool built on them."""

from __future__ import annotations

import os

import pytest

from usdface import resources
from usdface.pipeline import batch
from usdface.resources import available_memory_mb, pool_size, usable_cores


def _cgroup(tmp_path, **files):
    d = tmp_path / "cgroup"
    d.mkdir()
    for name, text in files.items():
        (d / name.replace("_", ".")).write_text(text + "\n")
    return d


def _affinity():
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


@pytest.mark.parametrize("quota, cores", [("150000 100000", 2), ("100000 100000", 1), ("50000 100000", 1),
                                          ("max 100000", None), ("garbage", None)])
def test_a_containers_cpu_quota_lowers_the_cores(tmp_path, quota, cores):
    """A farm slot or container limited to 1.5 CPUs (cgroup v2 ``cpu.max`` ``150000 100000``) may use 2 cores
    at most, whatever the host has (``os.cpu_count()`` read the host's); no quota or an unreadable one leaves
    the affinity."""
    expected = _affinity() if cores is None else min(cores, _affinity())
    assert usable_cores(_cgroup(tmp_path, cpu_max=quota)) == expected
    assert usable_cores(tmp_path / "no cgroup") == _affinity()


def test_the_memory_available_is_the_lower_of_the_machines_and_the_containers(tmp_path):
    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemTotal:       25165824 kB\nMemFree:         1000000 kB\n"
                       "MemAvailable:   20971520 kB\n")
    assert available_memory_mb(meminfo, tmp_path / "none") == 20480
    limited = _cgroup(tmp_path, memory_max=str(4 << 30), memory_current=str(1 << 30))
    assert available_memory_mb(meminfo, limited) == 3072                      # 4 GB limit, 1 GB used
    unlimited = tmp_path / "unlimited"
    unlimited.mkdir()
    (unlimited / "memory.max").write_text("max\n")
    (unlimited / "memory.current").write_text(str(1 << 30))
    assert available_memory_mb(meminfo, unlimited) == 20480
    assert available_memory_mb(tmp_path / "no meminfo", tmp_path / "none") is None


def test_the_pool_is_the_cores_capped_by_the_memory_never_below_one():
    assert pool_size(16, 4 * 1024, 1024) == 4 and pool_size(2, 24 * 1024, 1024) == 2
    assert pool_size(8, 300, 1024) == 1 and pool_size(8, None, 1024) == 8


def test_the_batchs_default_pool_is_what_the_process_may_use(monkeypatch, tmp_path):
    """Stop 44: ``run_batch(jobs=None)`` and ``usdface batch`` without ``-j`` started ``os.cpu_count()``
    workers: 64 on a 64-core host whose slot allows 4 CPUs and 8 GB. The default is the usable cores, capped
    by the available memory at a personalize worker's ~1.2 GB."""
    monkeypatch.setattr(resources, "usable_cores", lambda cgroup=None: 64)
    monkeypatch.setattr(resources, "available_memory_mb", lambda *a, **k: 8 * 1024)
    assert batch.default_jobs() == 8 * 1024 // resources.PERSONALIZE_WORKER_MB == 6
    monkeypatch.setattr(resources, "available_memory_mb", lambda *a, **k: 500)
    assert batch.default_jobs() == 1
    # one worker: the batch runs in this process (no pool started) when the caller names no jobs
    out = tmp_path / "out"
    out.mkdir()
    items = [batch.BatchItem(index=i, avatar=str(tmp_path / f"{n}.usdc"), capture=str(tmp_path / n),
                             output=str(out / f"{n}.txt"), options={}) for i, n in enumerate("ab")]
    report = batch.run_batch(items, worker=_touch, progress=False)
    assert report.count(batch.DONE) == 2 and "in this process" in report.summary()


def _touch(item: dict) -> None:
    open(item["output"], "w").close()


def test_an_unreadable_cpu_quota_is_no_quota(tmp_path):
    """``cpu.max`` holding neither ``max`` nor a number (a damaged or unknown file) leaves the cores as
    they are, without an error."""
    assert usable_cores(_cgroup(tmp_path, cpu_max="abc 100000")) == _affinity()
