"""The stable API (usdface.api, re-exported lazily as usdface.<name>): names, type hints, behaviour on the
bench data, and that the CLI goes through it."""

from __future__ import annotations

import inspect as pyinspect
import subprocess
import sys

import numpy as np
import pytest

import usdface
from usdface import api
from usdface.cli import main
from usdface.errors import InputFileError, OutputExistsError


def test_public_names_are_lazy_and_typed():
    code = "import sys, usdface; print('usdface.api' in sys.modules, 'pxr' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]  # import usdface stays cheap
    assert set(api.__all__) == set(usdface._API)
    for name in api.__all__:
        fn = getattr(usdface, name)
        assert fn is getattr(api, name)
        sig = pyinspect.signature(fn)
        params = [p for p in sig.parameters.values() if p.kind != p.VAR_KEYWORD]
        assert all(p.annotation is not p.empty for p in params), name
        assert fn.__doc__ and len(fn.__doc__) > 40
    with pytest.raises(AttributeError):
        usdface.not_an_api_function  # noqa: B018


def test_documented_submodules_after_import_usdface_only():
    """pipeline.md's ``usdface.progress.set_enabled(False)`` after ``import usdface`` (api.md's
    ``usdface.errors.UsdFaceError``, README's numerical core ``usdface.personalize``...) raised
    ``AttributeError: progress``: the submodules were reachable only once something had imported them."""
    code = ("import sys, usdface; usdface.progress.set_enabled(False); "
            "print(usdface.errors.UsdFaceError.__name__, callable(usdface.mesh.triangle_normals), "
            "'progress' in dir(usdface))\n"
            "try:\n    usdface.nope\nexcept AttributeError as e:\n    print(e)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.splitlines() == ["UsdFaceError True True", "module 'usdface' has no attribute 'nope'"]


def test_cli_check_goes_through_the_api(monkeypatch, tmp_path, capsys):
    seen = []

    def fake_check(path, pixar=True, rules=None, name_map=None, face_mesh=None):
        seen.append((str(path), pixar, rules, name_map, face_mesh))
        return []

    monkeypatch.setattr(api, "check", fake_check)
    assert main(["check", str(tmp_path / "x.usda"), "--no-pixar", "--rules", "ArkitNames"]) == 0
    assert main(["check", str(tmp_path / "x.usda"), "--name-map", "m.csv"]) == 0
    assert main(["check", str(tmp_path / "x.usda"), "--face-mesh", "/Shot/Hero/Head"]) == 0
    assert seen == [(str(tmp_path / "x.usda"), False, ["ArkitNames"], None, None),
                    (str(tmp_path / "x.usda"), True, None, "m.csv", None),
                    (str(tmp_path / "x.usda"), True, None, None, "/Shot/Hero/Head")]


def test_check_accepts_a_stage():
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, "Y")
    issues = usdface.check(stage, pixar=False)
    assert {i.rule for i in issues} == {"StageMetadata"} and len(issues) == 2


def test_bad_paths_raise_input_errors(tmp_path):
    with pytest.raises(InputFileError) as err:
        usdface.check(tmp_path / "nope.usda")
    assert "nope.usda" in str(err.value) and err.value.fix
    with pytest.raises(InputFileError):
        usdface.read_capture(tmp_path / "nope.txt")


@pytest.mark.shared
def test_readers_and_import(bench, tmp_path):
    avatar = usdface.read_avatar(bench / "dev1" / "avatar.usdc")
    assert avatar.mesh("Head").n_vertices == 14062 and avatar.up_axis == "Y"
    capture = usdface.read_capture(bench / "dev1" / "capture")
    out = usdface.import_capture_folder(bench / "dev1" / "capture", tmp_path / "capture.usda")
    again = usdface.read_capture(out)
    np.testing.assert_allclose(again.neutral, capture.neutral, atol=1e-6)
    assert again.names == capture.names
    with pytest.raises(OutputExistsError):
        usdface.import_capture_folder(bench / "dev1" / "capture", out)
    info = usdface.inspect_file(bench / "dev1" / "avatar.usdc")
    assert isinstance(info, dict) and info


@pytest.mark.shared
def test_evaluate_generic_baseline(bench):
    """Eq. 5 of the generic baseline on dev1's test frames: errors are positive and in a plausible mm range,
    and the person's own truth shapes score better than the generic ones."""
    capture = usdface.read_capture(bench / "dev1" / "capture")
    generic = usdface.evaluate_capture(capture)
    assert 0.1 < generic["mean_rmse_mm"] < 20.0
    truth = np.load(bench / "dev1" / "truth" / "capture_truth.npz")
    from usdface.arkit import normalize_name
    from usdface.model import FaceRig

    names = [normalize_name(str(n)) or str(n) for n in truth["names"]]
    rig = FaceRig(truth["neutral"], capture.triangles, names, truth["deltas"]).subset(capture.names)
    assert usdface.evaluate_capture(capture, rig)["mean_rmse_mm"] < generic["mean_rmse_mm"]


@pytest.mark.shared
def test_fit_and_landmarks_wrappers(bench):
    capture = usdface.read_capture(bench / "dev1" / "capture")
    fit = usdface.fit_capture(capture, method="dt")
    assert fit.rig.n_vertices == capture.neutral.shape[0] and set(fit.rig.names) == set(capture.names)
    scores = usdface.evaluate_capture(capture, fit)  # a FitResult is accepted
    assert np.isfinite(scores["rmse_mm"]).all() and len(scores["rmse_mm"]) == len(capture.test)
    rig = fit.rig.subset(["jawOpen", "eyeBlinkLeft", "mouthSmileLeft"])
    layout = usdface.compute_landmarks(rig, epsilon=0.5, alpha=0.5, time_limit=10)
    vertices = np.asarray(layout.vertices)
    assert vertices.size > 0 and vertices.min() >= 0 and vertices.max() < rig.n_vertices


def test_math_page_names_real_functions():
    """Every `usdface.…` function the math page maps an equation to exists (the page cannot rot silently)."""
    import importlib
    import re
    from pathlib import Path

    page = Path(__file__).resolve().parents[1] / "docs" / "math.md"
    if not page.exists():
        pytest.skip("docs/math.md not present")
    names = sorted(set(re.findall(r"`(usdface(?:\.\w+)+)`", page.read_text())))
    assert len(names) > 20
    missing = []
    for dotted in names:
        parts = dotted.split(".")
        for cut in range(len(parts), 0, -1):  # longest importable module prefix, then attributes
            try:
                obj = importlib.import_module(".".join(parts[:cut]))
            except ImportError:
                continue
            try:
                for attr in parts[cut:]:
                    obj = getattr(obj, attr)
            except AttributeError:
                missing.append(dotted)
            break
        else:
            missing.append(dotted)
    assert missing == []


def test_a_misspelt_option_is_named_before_any_work(samples, tmp_path, monkeypatch):
    """``personalize_avatar(..., methd="dt")`` read both inputs and then raised a fit error listing the
    method's options (a user trial): the API refuses an option personalize does not take up front, as
    ``usdface batch`` does, and reads nothing."""
    from usdface.errors import OptionError
    from usdface.io import usd_rig

    monkeypatch.setattr(usd_rig, "read_avatar", lambda *a, **k: pytest.fail("read the avatar"))
    # an OptionError, as every API function's refusal of an option it does not take (was a bare UsdFaceError)
    with pytest.raises(OptionError, match=r"unknown personalize option\(s\): methd") as info:
        api.personalize_avatar(samples / "avatar.usda", samples / "capture.usda", tmp_path / "o.usda",
                               methd="dt")
    assert "method" in info.value.fix and not (tmp_path / "o.usda").exists()


def test_dir_of_the_package_lists_the_api():
    """api.md: 'every function is also available as usdface.<name>'; dir(usdface) (what IPython and a
    shell's completion offer) listed none of them: they are loaded lazily."""
    import sys

    import usdface
    from usdface import api

    names = dir(usdface)
    assert set(api.__all__) <= set(names) and "__version__" in names
    assert "personalize_avatar" in names and usdface.personalize_avatar is api.personalize_avatar
    assert "usdface.api" in sys.modules
