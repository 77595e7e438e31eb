"""Cold start: the light commands must not import the heavy numerical stacks (issue 12).

Each case runs the CLI in a fresh interpreter and lists which heavy modules ended up in ``sys.modules``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_assets"
HEAVY = ("open3d", "ortools", "matplotlib", "scipy.spatial", "scipy.sparse", "scipy.optimize", "distributed",
         "dask", "rich")

_PROBE = """
import json, sys
from usdface.cli import main
argv = json.loads(sys.argv[1])
code = 0
if argv is not None:
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
sys.stdout.flush()
print("\\nMODULES " + json.dumps(sorted(m for m in json.loads(sys.argv[2]) if m in sys.modules)))
"""


def _heavy_modules(argv, modules=HEAVY) -> list[str]:
    """The ``modules`` imported after ``usdface.cli.main(argv)`` (``argv`` None: only the import)."""
    out = subprocess.run([sys.executable, "-c", _PROBE, json.dumps(argv), json.dumps(list(modules))],
                         capture_output=True, text=True, check=True, cwd=ROOT).stdout
    return json.loads(out.rsplit("MODULES ", 1)[1])


def test_import_cli_is_light():
    assert _heavy_modules(None) == []


def test_help_is_light():
    assert _heavy_modules(["--help"]) == []


@pytest.mark.parametrize("command", ["inspect", "check"])
def test_inspect_and_check_are_light(command):
    avatar = SAMPLE / "avatar.usda"
    if not avatar.exists():
        pytest.skip("no sample avatar")
    assert _heavy_modules([command, str(avatar)]) == []


def test_probe_detects_an_imported_module():
    """The probe sees what the CLI did import (json, argparse), so an empty list above means something."""
    assert _heavy_modules(["--help"], ("argparse", "json", "open3d")) == ["argparse", "json"]


#: What ``personalize`` never uses (landmark solver, plots, tables, batch schedulers, statistics/optimisers):
#: deferred to where they are used, so the product command does not pay for them (``scipy.stats`` alone cost a
#: cold run 1-2 s for one t quantile, now ``scipy.special.stdtrit``).
PERSONALIZE_UNUSED = ("ortools", "matplotlib", "rich", "dask", "distributed", "scipy.optimize", "scipy.stats")


def test_personalize_skips_the_stacks_it_does_not_use():
    avatar, capture = SAMPLE / "avatar.usda", SAMPLE / "capture.usda"
    if not (avatar.exists() and capture.exists()):
        pytest.skip("no sample avatar/capture")
    used = ("scipy.sparse", "scipy.spatial")     # what it does use: proves the probe saw a real run
    found = _heavy_modules(["personalize", str(avatar), str(capture), "--dry-run", "-q"],
                           PERSONALIZE_UNUSED + used)
    assert found == sorted(used)


def test_personalize_leaves_open3ds_visualization_unloaded(tmp_path):
    """Open3D's ``__init__`` imports ``open3d.visualization``, and with it Dash and Plotly (0.4 s of a cold
    run): usdface defers that subpackage to its first use, which still works."""
    avatar, capture = SAMPLE / "avatar.usda", SAMPLE / "capture.usda"
    if not (avatar.exists() and capture.exists()):
        pytest.skip("no sample avatar/capture")
    pytest.importorskip("open3d")
    found = _heavy_modules(["personalize", str(avatar), str(capture), "-o", str(tmp_path / "out.usda"), "-q"],
                           ("open3d", "dash", "plotly"))
    assert found == ["open3d"]
    assert (tmp_path / "out.usda").is_file()


def test_open3ds_deferred_visualization_loads_on_first_use():
    pytest.importorskip("open3d")
    probe = ("import sys\n"
             "from usdface.natives import open3d\n"
             "o3d = open3d()\n"
             "before = 'dash' in sys.modules\n"
             "draw = o3d.visualization.draw_geometries\n"
             "import open3d.visualization.rendering as rendering\n"
             "print(before, 'dash' in sys.modules, callable(draw), rendering.__name__)\n")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True,
                         cwd=ROOT).stdout.split()
    assert out == ["False", "True", "True", "open3d.pybind.visualization.rendering"]


_NUMPY_PROBE = """
import json, sys
sys.argv = ["usdface"] + json.loads(sys.argv[1])
from usdface.cli import main
try:
    main()
except SystemExit:
    pass
loaded = sorted(m for m in ("numpy.f2py.crackfortran", "unittest", "scipy.spatial.transform._rotation",
                            "scipy.sparse", "scipy.spatial") if m in sys.modules)
import numpy.testing
numpy.testing.assert_allclose(1.0, 1.0)
from scipy.spatial.transform import Rotation
print(json.dumps([loaded, "unittest" in sys.modules, Rotation.identity().as_quat().tolist()]))
"""


def test_the_program_loads_unused_submodules_on_first_use(tmp_path):
    """SciPy's array-API shim clones every numpy attribute, importing ``numpy.f2py`` and ``numpy.testing``
    (with ``unittest``), and ``scipy.spatial`` imports its rotations, none used by any step (0.1-0.2 s of a
    cold run): the ``usdface`` program defers them to their first use, which still works (docs/scale.md,
    Cold start)."""
    avatar, capture = SAMPLE / "avatar.usda", SAMPLE / "capture.usda"
    if not (avatar.exists() and capture.exists()):
        pytest.skip("no sample avatar/capture")
    argv = ["personalize", str(avatar), str(capture), "-o", str(tmp_path / "out.usda"), "-q"]
    out = subprocess.run([sys.executable, "-c", _NUMPY_PROBE, json.dumps(argv)], capture_output=True,
                         text=True, check=True, cwd=ROOT).stdout
    assert json.loads(out.strip().splitlines()[-1]) == [["scipy.sparse", "scipy.spatial"], True,
                                                        [0.0, 0.0, 0.0, 1.0]]
    assert (tmp_path / "out.usda").is_file()


_HUGEPAGE_PROBE = """
import os, sys
sys.argv = ["usdface", "--version"]
from usdface.cli import main
try:
    main()
except SystemExit:
    pass
import numpy
from numpy._core.multiarray import _set_madvise_hugepage
print(os.environ.get("NUMPY_MADVISE_HUGEPAGE"), _set_madvise_hugepage(True))
"""


@pytest.mark.parametrize(("preset", "expected"), [(None, "0 False"), ("1", "1 True")])
def test_the_program_asks_numpy_for_no_huge_pages_unless_the_user_chose(preset, expected):
    """The ``usdface`` program's own process turns numpy's huge-page ``madvise`` off before numpy is
    imported (direct-compaction stalls: a fresh 100 MB array 1.43 s instead of 0.09 s on this machine
    class, docs/scale.md); a user's own ``NUMPY_MADVISE_HUGEPAGE`` is kept, and a host application calling
    ``main(argv)`` is left alone."""
    import os

    pytest.importorskip("numpy._core.multiarray")
    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    if preset is not None:
        env["NUMPY_MADVISE_HUGEPAGE"] = preset
    out = subprocess.run([sys.executable, "-c", _HUGEPAGE_PROBE], capture_output=True, text=True, check=True,
                         cwd=ROOT, env=env).stdout
    assert out.strip().splitlines()[-1] == expected


def test_a_host_calling_main_keeps_its_numpy_settings(monkeypatch):
    import os

    from usdface.cli import main

    monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE", raising=False)
    with pytest.raises(SystemExit):
        main(["--version"])
    assert "NUMPY_MADVISE_HUGEPAGE" not in os.environ


_BLAS_PROBE = """
import json, os, sys
argv = json.loads(sys.argv[1])
from usdface.cli import main
if sys.argv[2] == "program":
    sys.argv = ["usdface"] + argv
    argv = None
try:
    main(argv)
except SystemExit:
    pass
loaded = "threadpoolctl" in sys.modules
from threadpoolctl import threadpool_info
print(json.dumps([os.environ.get("OPENBLAS_NUM_THREADS"), loaded,
                  sorted({i["num_threads"] for i in threadpool_info() if i["internal_api"] == "openblas"})]))
"""


@pytest.mark.parametrize(("preset", "how", "expected"), [
    (None, "program", ["1", False, [1]]),      # started at one thread: no workers, no limit to set
    ("2", "program", ["2", True, [2]]),        # the user's count kept: limited during the run, put back after
    (None, "host", [None, True, None]),        # a host calling main(argv): its own BLAS, limited in the run
])
def test_the_program_starts_blas_at_one_thread_for_personalize(tmp_path, preset, how, expected):
    """``usdface personalize`` runs its numerical work at one BLAS thread; the program's own process starts
    every OpenBLAS with one thread (``OPENBLAS_NUM_THREADS=1`` before numpy loads), so no idle worker spins
    beside the run and no ``threadpoolctl`` limit is needed (docs/scale.md, Cold start). A count the user set
    is kept, and a host calling ``main(argv)`` keeps its own BLAS."""
    import os

    pytest.importorskip("threadpoolctl")
    avatar, capture = SAMPLE / "avatar.usda", SAMPLE / "capture.usda"
    if not (avatar.exists() and capture.exists()):
        pytest.skip("no sample avatar/capture")
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                                                            "BLIS_NUM_THREADS")}
    if preset is not None:
        env["OPENBLAS_NUM_THREADS"] = preset
    argv = ["personalize", str(avatar), str(capture), "-o", str(tmp_path / "out.usda"), "-q"]
    out = subprocess.run([sys.executable, "-c", _BLAS_PROBE, json.dumps(argv), how], capture_output=True,
                         text=True, check=True, cwd=ROOT, env=env).stdout
    env_value, loaded, threads = json.loads(out.strip().splitlines()[-1])
    assert (tmp_path / "out.usda").is_file()
    assert [env_value, loaded] == expected[:2]
    if expected[2] is not None:
        assert threads == expected[2]


_GC_PROBE = """
import gc, sys
sys.argv = ["usdface", "--version"]
from usdface.cli import main
try:
    main()
except SystemExit:
    pass
print(gc.get_threshold()[0], gc.get_freeze_count() > 0)
"""


def test_the_program_collects_garbage_less_often_and_freezes_before_shutdown():
    """The ``usdface`` program's process runs the collector's young collections every 50,000 allocations
    and freezes what is alive when the command ends, so that neither the run nor the interpreter's shutdown
    walks the ~2,000 imported modules again and again (docs/scale.md, Cold start)."""
    out = subprocess.run([sys.executable, "-c", _GC_PROBE], capture_output=True, text=True, check=True,
                         cwd=ROOT).stdout
    assert out.strip().splitlines()[-1] == "50000 True"


def test_a_host_calling_main_keeps_its_garbage_collector():
    import gc

    from usdface.cli import main

    before, frozen = gc.get_threshold(), gc.get_freeze_count()
    with pytest.raises(SystemExit):
        main(["--version"])
    assert gc.get_threshold() == before and gc.get_freeze_count() == frozen


def _deferred_package(tmp_path, monkeypatch, name: str, body: str):
    """A package ``name`` (its ``__init__``: ``body``) imported as :mod:`usdface.natives` imports Open3D's
    deferred subpackage, and ``gate``, a module the package's code signals through."""
    import importlib

    from usdface import natives

    (tmp_path / name).mkdir()
    (tmp_path / name / "__init__.py").write_text(body)
    (tmp_path / f"{name}_gate.py").write_text("import threading\nstarted = threading.Event()\ntries = []\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(natives, "DEFERRED", (name,))
    for module in (name, f"{name}_gate"):
        monkeypatch.delitem(sys.modules, module, raising=False)
    finder = natives._Deferred()
    sys.meta_path.insert(0, finder)
    try:
        module = __import__(name)
    finally:
        sys.meta_path.remove(finder)
    return module, importlib.import_module(f"{name}_gate")


def test_a_deferred_subpackage_loads_once_for_threads_that_use_it_at_once(tmp_path, monkeypatch):
    """Python 3.11's ``LazyLoader`` marks the module loaded before it runs its code: a second thread using it
    meanwhile found half a module (``AttributeError``) instead of waiting."""
    import threading

    module, gate = _deferred_package(tmp_path, monkeypatch, "usdface_slow_pkg",
                                     "import time\nfrom usdface_slow_pkg_gate import started, tries\n"
                                     "tries.append(1)\nstarted.set()\ntime.sleep(0.5)\nvalue = 42\n")
    first = threading.Thread(target=lambda: module.value)
    first.start()
    assert gate.started.wait(10)
    try:
        assert module.value == 42                     # waits for the first thread's load
    finally:
        first.join()
    assert gate.tries == [1]


def test_a_deferred_subpackage_interrupted_in_its_load_loads_at_the_next_use(tmp_path, monkeypatch):
    """An interrupt (a host's cancel) inside the deferred load left the module half run for good (every
    later use: ``AttributeError``), where an interrupted eager import can be tried again."""
    module, gate = _deferred_package(tmp_path, monkeypatch, "usdface_cut_pkg",
                                     "from usdface_cut_pkg_gate import tries\ntries.append(1)\n"
                                     "if len(tries) == 1:\n    raise KeyboardInterrupt\nvalue = 42\n")
    with pytest.raises(KeyboardInterrupt):
        _ = module.value
    assert module.value == 42
    assert gate.tries == [1, 1]
