"""The result objects a TD prints in a DCC console or a notebook read as one short line (stop 47, h52).

The dataclass reprs printed every array: ``repr(read_avatar(sample))`` was ~127 kB, a ``PersonalizeResult``
~55 kB, over many lines, the figures a TD wanted (file, meshes, shapes, frames) lost in them.
"""
from __future__ import annotations

import numpy as np

from usdface.arkit import ARKIT_NAMES as ARKIT_52
from usdface.landmarks.layout import LandmarkLayout
from usdface.model import Avatar, Capture, FaceRig, Frames, MeshSource
from usdface.personalize.api import FitResult
from usdface.transfer.pipeline import PersonalizeResult

N, K = 2000, len(ARKIT_52)


def _rig(name="Head") -> FaceRig:
    rng = np.random.default_rng(0)
    tri = np.stack([np.arange(N - 2), np.arange(1, N - 1), np.arange(2, N)], axis=1)
    return FaceRig(rng.normal(size=(N, 3)), tri, list(ARKIT_52), rng.normal(size=(K, N, 3)) * 1e-3,
                   source=MeshSource(file="a.usda", prim=f"/Avatar/{name}"), name=name)


def _one_line(obj, *facts: str) -> str:
    text = repr(obj)
    assert "\n" not in text and len(text) < 400, text[:300]
    for fact in facts:
        assert fact in text, (fact, text)
    return text


def test_rig_and_avatar_repr_are_one_line_with_their_figures():
    rig = _rig()
    _one_line(rig, "/Avatar/Head", f"{N} vertices", f"{N - 2} triangles", f"{K} shapes", "eyeBlinkLeft")
    avatar = Avatar([rig, _rig("Mouth")], file="a.usda", meters_per_unit=0.01)
    _one_line(avatar, "a.usda", "/Avatar/Head", "/Avatar/Mouth", "metersPerUnit 0.01", "upAxis Y")


def test_capture_fit_and_personalize_results_repr_are_one_line():
    rig = _rig()
    frames = Frames(np.zeros((3, N, 3)), np.zeros((3, K)), ["train", "train", "test"], ["a", "b", "c"])
    capture = Capture(rig.neutral, rig.triangles, rig, frames, list(ARKIT_52), source="capture.usda")
    _one_line(capture, "capture.usda", f"{N} vertices", "2 train + 1 test frames")
    fit = FitResult(rig, {"method": "menzel", "reg": 0.5, "loo_rmse_mm": np.ones(K)})
    _one_line(fit, "menzel", "reg 0.5")
    result = PersonalizeResult({"/Avatar/Head": rig.deltas}, list(ARKIT_52), list(ARKIT_52), np.eye(K), {},
                               "/Avatar/Head", np.ones(N, bool), np.ones((K, N), bool), out_path=None)
    _one_line(result, f"{K} shapes implanted", "/Avatar/Head", "not written")


def test_landmark_layout_repr_names_its_vertices():
    layout = LandmarkLayout(np.array([3, 7]), np.zeros((2, 3)), np.ones((2, K), bool), np.zeros(2, int),
                            np.ones(2), list(ARKIT_52), 0.5, 0.5, False, 1, "optimal", 0.0, 2.0, "quality",
                            "scip")
    _one_line(layout, "2 landmarks", f"{K} shapes", "optimal", "[3, 7]")


def test_a_retarget_map_result_says_it_is_a_map(samples, tmp_path):
    """User trial (stop 48): ``print(usdface.write_retarget_map(avatar, capture, "map.json"))`` said
    ``<PersonalizeResult map.json: 52 shapes implanted, 0 mesh(es) (), ...>``: nothing is implanted by
    ``usdface retarget``, the map is the product. It says what was made now."""
    from usdface import api

    result = api.write_retarget_map(samples / "avatar.usda", samples / "capture.usda", tmp_path / "m.json",
                                    method="dt")
    text = _one_line(result, "m.json", "retarget map of 52 shapes onto 52 avatar shapes of /Avatar/Head")
    assert "implanted" not in text and "0 mesh(es)" not in text
