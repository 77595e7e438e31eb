"""How many pytest-xdist workers this machine holds: one a core (what ``-n auto`` takes), but no more than the
memory available holds at :data:`WORKER_MB` each. ``-n auto`` alone started a worker per core whatever the
memory: a many-core runner with little memory per core (a CI container with a memory limit) would swap or
have workers killed. Prints the count (``.ci/run`` passes it as ``-n``)."""

from __future__ import annotations

import os

#: Peak memory of one worker, MB: a worker process and the CLI process one of its tests runs and waits on.
#: A personalize of a bench head peaks at ~370 MB RSS (docs/scale.md); the largest single process of
#: ``pytest tests/test_review.py tests/test_transfer_bench.py`` (the bench personalizations, in-process and
#: through the CLI) peaked at 563 MB (stop 43, ``/usr/bin/time -v``): the two together ~1.1 GB at most.
WORKER_MB = 1024


def cores() -> int:
    """The cores this process may run on (its affinity; else the machine's)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def available_mb() -> int | None:
    """Memory available for new work, MB: Linux's ``MemAvailable``, lowered to a cgroup v2 limit (a
    container's ``memory.max``) less what the cgroup already uses; None when neither can be read."""
    found = []
    try:
        with open("/proc/meminfo") as fh:
            found += [int(line.split()[1]) // 1024 for line in fh if line.startswith("MemAvailable:")]
    except OSError:
        pass
    try:
        with open("/sys/fs/cgroup/memory.max") as fh:
            limit = fh.read().strip()
        with open("/sys/fs/cgroup/memory.current") as fh:
            used = int(fh.read().strip())
        if limit.isdigit():
            found.append(max(int(limit) - used, 0) // (1 << 20))
    except (OSError, ValueError):
        pass
    return min(found) if found else None


def workers(n_cores: int, memory_mb: int | None, worker_mb: int = WORKER_MB) -> int:
    """``min(n_cores, memory_mb // worker_mb)``, at least 1; ``n_cores`` when the memory is unknown."""
    fit = n_cores if memory_mb is None else memory_mb // worker_mb
    return max(1, min(n_cores, fit))


if __name__ == "__main__":
    print(workers(cores(), available_mb()))
