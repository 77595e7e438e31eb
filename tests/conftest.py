"""Shared fixtures. Tests that need the product owner's data (../shared) skip cleanly without it."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# as the usdface program does for itself (usdface.cli._program_environment, docs/scale.md): numpy's
# transparent-huge-page madvise stalls in memory compaction on this machine class; read when numpy is imported
os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")
# a step's plain progress line appears once it has run 2 s (usdface.progress.delay): on a loaded machine (the
# suite on every core beside other work) a render's draw crossed that, and a test of a one-line error saw two
# lines; the tests of the progress itself set their own delay
os.environ.setdefault("USDFACE_PROGRESS_DELAY", "3600")

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("USDFACE_SHARED", ROOT.parent / "shared"))
SAMPLES = ROOT / "sample_assets"


@pytest.fixture(autouse=True)
def _progress_state_per_test():
    """Each test starts with usdface's process-wide progress state as a fresh process has it: a Dask item run
    on an in-process cluster turns progress off for good (``run_item_quiet``: process-wide by design, as on
    a real worker), and a later test of the progress lines in the same pytest worker then saw none
    (CI, stop 47: ``test_obj_dir_names_the_objs_as_it_writes_them`` after
    ``test_a_cancelled_dask_item_writes_nothing``)."""
    from usdface import progress

    saved = progress._ENABLED, progress._LOGGER
    progress._ENABLED, progress._LOGGER = True, None
    yield
    progress._ENABLED, progress._LOGGER = saved


@pytest.fixture(scope="session")
def shared() -> Path:
    """../shared (the product owner's data); skips the test when absent."""
    if not (SHARED / "data").is_dir():
        pytest.skip("../shared data not present")
    return SHARED


@pytest.fixture(scope="session")
def bench(shared) -> Path:
    """../shared/data/bench (dev1, dev2)."""
    return shared / "data" / "bench"


@pytest.fixture(scope="session")
def samples() -> Path:
    """The project's own generated sample assets."""
    if not (SAMPLES / "avatar.usda").exists():
        pytest.skip("sample_assets not generated yet")
    return SAMPLES


@pytest.fixture(scope="session")
def sample_capture_folder(samples, tmp_path_factory) -> Path:
    """The sample capture as a capture folder (OBJ + JSON), generated once per session into a temporary
    folder (``usdface sample OUTDIR --folder``; the committed ``sample_assets/`` holds only capture.usda).
    Returns the ``capture/`` folder; its parent holds the other generated files, equal to ``samples``."""
    from usdface.sample import generate_samples

    return generate_samples(tmp_path_factory.mktemp("samples") / "sample_assets", folder=True) / "capture"


@pytest.fixture(scope="session")
def personalized_sample(samples, tmp_path_factory) -> Path:
    """The sample avatar personalized with the sample capture once per session (a usdface layer over
    ``sample_assets/avatar.usda``), for tests that read a result (review page, export)."""
    from usdface import api

    out = tmp_path_factory.mktemp("personalized") / "person.usda"
    api.personalize_avatar(samples / "avatar.usda", samples / "capture.usda", out, force=True)
    return out


@pytest.fixture
def read_only_folder(monkeypatch):
    """``read_only_folder(path)``: the output probe (a temporary file made in the folder) sees ``path`` as on
    a read-only file system (EROFS), as a mount would show it (root ignores permission bits)."""
    import errno
    import tempfile

    real = tempfile.TemporaryFile
    folders = []

    def read_only(*args, dir=None, **kwargs):
        if dir is not None and any(Path(dir) == f for f in folders):
            raise OSError(errno.EROFS, "Read-only file system")
        return real(*args, dir=dir, **kwargs)

    monkeypatch.setattr(tempfile, "TemporaryFile", read_only)
    return lambda path: folders.append(Path(path))


@pytest.fixture
def pyblish_registered():
    """Pyblish's API with usdface's plugins registered (and only them) for one test; skipped without
    pyblish."""
    pyblish_api = pytest.importorskip("pyblish.api")
    from usdface.pipeline import pyblish_plugins

    pyblish_api.deregister_all_plugins()
    pyblish_plugins.register()
    yield pyblish_api
    pyblish_api.deregister_all_plugins()


@pytest.fixture(scope="module")
def weights_take(tmp_path_factory) -> Path:
    """A weights-only take as ``anim import`` writes it (the sample's test weights as a 30 fps recording)."""
    import numpy as np

    from usdface.io.usd_anim import write_animation_usd

    rng = np.random.default_rng(0)
    from usdface.arkit import ARKIT_NAMES

    w = rng.uniform(0.0, 0.45, size=(60, len(ARKIT_NAMES)))
    w[10, ARKIT_NAMES.index("jawOpen")] = 0.93
    out = tmp_path_factory.mktemp("take") / "take.usda"
    write_animation_usd(out, list(ARKIT_NAMES), w, np.arange(60) / 30.0)
    return out


@pytest.fixture(scope="module")
def livelink_csv(shared, tmp_path_factory) -> Path:
    """The first 30 frames of a real Live Link Face CSV."""
    lines = (shared / "data" / "livelinkface" / "facial.csv").read_text().splitlines()[:31]
    out = tmp_path_factory.mktemp("csv") / "facial.csv"
    out.write_text("\n".join(lines) + "\n")
    return out


@pytest.fixture(scope="module")
def sample_dir(tmp_path_factory) -> Path:
    """``usdface sample s2`` (avatar.usda, capture.usda, truth/{capture,avatar}_truth.npz)."""
    from usdface.sample import generate_samples

    return generate_samples(tmp_path_factory.mktemp("trial") / "s2")
