"""What this machine lets the process use: the cores it may run on and the memory available for new work,
and how many worker processes of a given size that holds.

``os.cpu_count()`` is the machine's cores, not the process's: a render-farm slot or a container limited to 4
CPUs of a 64-core host (a cgroup v2 ``cpu.max`` quota, or a CPU affinity set by the scheduler) reads 64, and
a pool of 64 personalize workers (~0.4-1.2 GB each, docs/scale.md) then runs out of memory or thrashes.
:func:`usable_cores` and :func:`available_memory_mb` read what the process may actually use (Linux; other
systems fall back to the machine's figures), :func:`pool_size` turns them into a worker count.
Standard library only: ``usdface batch`` and ``.ci/xdist_workers.py`` read it before any heavy import.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

__all__ = ["PERSONALIZE_WORKER_MB", "CGROUP", "usable_cores", "available_memory_mb", "pool_size"]

#: Peak memory of one ``personalize`` worker process, MB: the largest rig docs/scale.md measures (a
#: 225k-vertex face, issue 12's bound 1.2 GB; a 24.6k bench head peaks at ~0.4 GB). The default pool holds
#: no more workers than the available memory holds at this size.
PERSONALIZE_WORKER_MB = 1200

#: Where Linux mounts the cgroup v2 hierarchy of this process (a container sees its own cgroup there).
CGROUP = Path("/sys/fs/cgroup")


def _read(path: Path) -> str | None:
    try:
        return path.read_text().strip()
    except (OSError, UnicodeDecodeError):
        return None


def usable_cores(cgroup: Path = CGROUP) -> int:
    """The cores this process may use: its CPU affinity (else the machine's count), lowered to a cgroup v2
    CPU quota (``cpu.max`` = ``QUOTA PERIOD``: QUOTA/PERIOD CPUs' worth of time, rounded up; ``max`` = none).
    At least 1."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    quota = (_read(Path(cgroup) / "cpu.max") or "").split()
    if len(quota) == 2 and quota[0].isdigit() and quota[1].isdigit() and int(quota[1]) > 0:
        cores = min(cores, math.ceil(int(quota[0]) / int(quota[1])))
    return max(1, cores)


def available_memory_mb(meminfo: Path = Path("/proc/meminfo"), cgroup: Path = CGROUP) -> int | None:
    """Memory available for new work, MB: Linux's ``MemAvailable``, lowered to a cgroup v2 limit (a
    container's ``memory.max``) less what the cgroup already uses (``memory.current``); None when neither
    can be read (not Linux)."""
    found = []
    for line in (_read(Path(meminfo)) or "").splitlines():
        field = line.split()
        if len(field) >= 2 and field[0] == "MemAvailable:" and field[1].isdigit():
            found.append(int(field[1]) // 1024)
    limit, used = _read(Path(cgroup) / "memory.max"), _read(Path(cgroup) / "memory.current")
    if limit is not None and limit.isdigit() and used is not None and used.isdigit():
        found.append(max(int(limit) - int(used), 0) // (1 << 20))
    return min(found) if found else None


def pool_size(cores: int, memory_mb: int | None, worker_mb: int) -> int:
    """``min(cores, memory_mb // worker_mb)`` worker processes, at least 1; ``cores`` when the memory is
    unknown (None)."""
    fit = cores if memory_mb is None else memory_mb // worker_mb
    return max(1, min(int(cores), int(fit)))
