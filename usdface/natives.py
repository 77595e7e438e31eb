"""Native modules imported lazily, with a host's interrupt held back while they initialise.

Open3D is imported at the first registration or ray cast, inside an API call. A ``KeyboardInterrupt`` (a
host's cancel: Ctrl-C, ``_thread.interrupt_main()``) that lands in its pybind11 initialisation came out as
``ImportError: initialization failed``, and left the process unable to import Open3D again (every later
call: ``ImportError: generic_type: cannot initialize type "IntVector": an object with that name is already
defined``), so one cancelled personalize broke every later one in the host's session. The ``usdface``
program holds the signals around its own native imports (:func:`usdface.cli.main`); this does the same for
Open3D wherever it is imported.
"""

from __future__ import annotations

import contextlib
import importlib.abc
import importlib.machinery
import importlib.util
import os
import sys
import threading
import types

#: Open3D's subpackages its ``__init__`` imports that usdface never uses, loaded on first use instead
#: (:class:`_Deferred`): ``open3d.visualization`` imports Dash and Plotly unconditionally, 0.40 of the 0.75 s
#: the first ``import open3d`` takes (``python -X importtime``), a tenth of a cold ``personalize`` of a bench
#: head.
DEFERRED = ("open3d.visualization",)

#: Subpackages usdface never uses that its libraries import: numpy's ``f2py`` (its ``crackfortran``
#: compiles 58 regular expressions) and ``testing`` (with ``unittest``), which SciPy's array-API shim
#: (``scipy._lib.array_api_compat.numpy``, imported with ``scipy.sparse``) imports by cloning every attribute
#: of numpy (``from numpy import *``), 0.08-0.17 s of a cold ``personalize`` (``python -X importtime``); and
#: ``scipy.spatial.transform`` (rotations, 0.02-0.05 s), which ``scipy.spatial``'s ``__init__`` imports with
#: the k-d tree usdface does use. The ``usdface`` program's own process loads them on first use instead
#: (:func:`defer_unused_submodules`). (``numpy.ma``, which the shim imports too, is used by Open3D's import;
#: ``scipy.spatial.distance`` by ``scipy.spatial``'s own ``__init__``: deferring either saves nothing.)
UNUSED_DEFERRED = ("numpy.f2py", "numpy.testing", "scipy.spatial.transform")


#: The BLAS thread-count variables (OpenBLAS, MKL, BLIS) :func:`start_blas_single_threaded` sets to 1.
BLAS_THREAD_ENV = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")
#: True once :func:`start_blas_single_threaded` saw every BLAS of the process start with one thread.
_BLAS_SINGLE = [False]


def start_blas_single_threaded() -> bool:
    """Before numpy is imported, ask every BLAS the process will load to start with one thread (each of
    :data:`BLAS_THREAD_ENV` set to 1 unless the user set it); returns :func:`blas_started_single_threaded`.
    For the ``usdface`` program's own process, whose command runs its numerical work at one BLAS thread anyway
    (:func:`usdface.personalize.api.single_threaded_blas`); nothing once numpy is loaded (a host's).

    Each OpenBLAS loaded (numpy's, SciPy's) otherwise starts a worker thread per further core at its load,
    which such a run never uses but which spins waiting for work after its start (~0.03 CPU-s each of a cold
    dev1 ``personalize`` on a 2-core machine), and the run's ``threadpoolctl`` limit costs its import and
    the listing of the loaded libraries (10-15 ms). The same single-threaded BLAS code runs either way: the
    same results to the bit. Open3D's own worker threads (TBB) are not BLAS and keep every core."""
    if "numpy" in sys.modules:
        return _BLAS_SINGLE[0]
    for name in BLAS_THREAD_ENV:
        os.environ.setdefault(name, "1")
    _BLAS_SINGLE[0] = all(os.environ[name] == "1" for name in BLAS_THREAD_ENV)
    return _BLAS_SINGLE[0]


def blas_started_single_threaded() -> bool:
    """True when :func:`start_blas_single_threaded` ran before numpy's import with every BLAS thread count 1:
    each BLAS of the process runs on one thread already, and nothing in usdface raises the count."""
    return _BLAS_SINGLE[0]


@contextlib.contextmanager
def signals_held():
    """Hold SIGINT, SIGTERM, SIGHUP and SIGXCPU back inside the block (only those whose handlers Python
    manages: one set outside Python, or ignored, is left alone), then let each held signal through to the
    handler that was there before, a termination first: a ``KeyboardInterrupt`` from the first let through
    dropped the others. For native imports a signal landing inside breaks (:func:`open3d`,
    :func:`usdface.cli._import_natives_with_signals_held`). The main thread only (where Python delivers
    signals and may set handlers)."""
    import signal

    held: list[int] = []
    previous = {}
    names = ("SIGINT", "SIGTERM", "SIGHUP", "SIGXCPU")      # the usdface program stops on each
    for signum in [getattr(signal, name) for name in names if hasattr(signal, name)]:
        handler = signal.getsignal(signum)
        if handler is None or handler == signal.SIG_IGN:   # set outside Python, or ignored: left alone
            continue
        previous[signum] = signal.signal(signum, lambda got, _frame: held.append(got))
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        raised = None
        # now the host's handlers run, outside the block: each held signal, a termination first
        for signum in sorted(set(held), key=lambda s: s == signal.SIGINT):
            try:
                signal.raise_signal(signum)
            except BaseException as exc:
                raised = raised or exc
        if raised is not None:
            raise raised


class _LazyModule(types.ModuleType):
    """A :data:`DEFERRED` module not run yet: its first attribute access runs it, as the standard library's
    ``importlib.util._LazyModule`` does, but (Python 3.11's does neither) under a lock, so another thread
    using it meanwhile waits for the whole module instead of finding half of it, and, should its code raise
    (a host's ``KeyboardInterrupt``), left as it was before, to run at the next access, as an eager import
    that failed can be tried again."""

    def __getattribute__(self, attr):
        spec = object.__getattribute__(self, "__spec__")
        state = spec.loader_state
        with state["lock"]:
            if object.__getattribute__(self, "__class__") is _LazyModule:
                if state["loading"]:                      # from inside the load, in its own thread
                    return types.ModuleType.__getattribute__(self, attr)
                state["loading"] = True
                attrs = object.__getattribute__(self, "__dict__")
                before = dict(attrs)
                then = state["__dict__"]
                # what was set on it meanwhile (a submodule imported) stays, as after an eager import
                updated = {k: v for k, v in attrs.items() if k not in then or then[k] is not v}
                try:
                    spec.loader.exec_module(self)
                except BaseException:
                    attrs.clear()
                    attrs.update(before)
                    raise
                finally:
                    state["loading"] = False
                attrs.update(updated)
                object.__setattr__(self, "__class__", types.ModuleType)
        return getattr(self, attr)

    def __delattr__(self, attr):
        self.__getattribute__(attr)                       # loaded first, as the standard library's
        delattr(self, attr)


class _LazyLoader(importlib.util.LazyLoader):
    """``importlib.util.LazyLoader`` with :class:`_LazyModule`."""

    def exec_module(self, module):
        super().exec_module(module)
        object.__getattribute__(module, "__spec__").loader_state.update(lock=threading.RLock(), loading=False)
        object.__setattr__(module, "__class__", _LazyModule)


class _Deferred(importlib.abc.MetaPathFinder):
    """Finds the ``names`` (default :data:`DEFERRED`) as the import system would, with a lazy loader
    (:class:`_LazyLoader`): the module is in ``sys.modules`` at once and runs its code at its first
    attribute access (``open3d.visualization.draw_geometries`` works as before, a moment later)."""

    def __init__(self, names=None):
        # DEFERRED read when the finder is made, not when this module was (a host or test may set it)
        self.names = tuple(DEFERRED if names is None else names)

    def find_spec(self, name, path, target=None):
        if name not in self.names:
            return None
        spec = importlib.machinery.PathFinder.find_spec(name, path, target)
        if spec is not None and spec.loader is not None:
            spec.loader = _LazyLoader(spec.loader)
        return spec


def defer_unused_submodules() -> bool:
    """For the ``usdface`` program's own process (:func:`usdface.cli.main` run as the program): the
    :data:`UNUSED_DEFERRED` subpackages of numpy and SciPy, when not imported yet, load at their first
    attribute access instead of at their import (the same lazy module as Open3D's :data:`DEFERRED`:
    ``numpy.testing.assert_allclose`` works as before, a moment later). Returns True when the finder was
    installed (once a process)."""
    if any(isinstance(f, _Deferred) and f.names == UNUSED_DEFERRED for f in sys.meta_path):
        return False
    sys.meta_path.insert(0, _Deferred(UNUSED_DEFERRED))
    return True


def _import_open3d():
    """``import open3d`` with its :data:`DEFERRED` subpackages loaded on first use."""
    finder = _Deferred()
    sys.meta_path.insert(0, finder)
    try:
        import open3d as o3d
    finally:
        sys.meta_path.remove(finder)
    return o3d


def open3d():
    """The ``open3d`` module; its first import runs with SIGINT and SIGTERM held back (:func:`signals_held`,
    in the main thread), so an interrupt arrives once the import is done, as ``KeyboardInterrupt``, and a
    later call imports nothing again. usdface imports it here only, with ``open3d.visualization`` (Dash,
    Plotly) deferred to its first use (:data:`DEFERRED`)."""
    if "open3d" in sys.modules:
        import open3d as o3d  # loaded (or being loaded by another thread: the import lock waits)

        return o3d
    if threading.current_thread() is not threading.main_thread():
        return _import_open3d()
    with signals_held():
        return _import_open3d()
