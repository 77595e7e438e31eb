"""How many pytest-xdist workers this machine holds: one a core this process may use (its affinity and a
container's CPU quota; ``-n auto`` takes the machine's cores), but no more than the memory available holds
at :data:`WORKER_MB` each. ``-n auto`` alone started a worker per core whatever the memory: a many-core
runner with little memory per core (a CI container with a memory limit) would swap or have workers killed.
Prints the count (``.ci/run`` passes it as ``-n``). The machine's figures are :mod:`usdface.resources`'
(installed before this runs), as ``usdface batch`` reads them."""

from __future__ import annotations

from usdface.resources import available_memory_mb, pool_size, usable_cores

#: Peak memory of one worker, MB: a worker process and the CLI process one of its tests runs and waits on.
#: A personalize of a bench head peaks at ~370 MB RSS (docs/scale.md); the largest single process of
#: ``pytest tests/test_review.py tests/test_transfer_bench.py`` (the bench personalizations, in-process and
#: through the CLI) peaked at 563 MB (stop 43, ``/usr/bin/time -v``): the two together ~1.1 GB at most.
WORKER_MB = 1024


def workers() -> int:
    """The worker count for this machine (:func:`usdface.resources.pool_size` at :data:`WORKER_MB`)."""
    return pool_size(usable_cores(), available_memory_mb(), WORKER_MB)


if __name__ == "__main__":
    print(workers())
