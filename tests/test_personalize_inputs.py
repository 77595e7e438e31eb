"""Bad input to fit_personalized_shapes gets the right UsdFaceError (naming what and how to fix) or a
warning naming the shapes concerned."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from input_helpers import _capture

from usdface.cli import main
from usdface.errors import FitError, GeometryError
from usdface.model import Capture, FaceRig, Frames
from usdface.personalize import fit_personalized_shapes

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


def tiny_capture(F=6, K=3, n_frame=None, never=None, degenerate=False):
    rng = np.random.default_rng(0)
    nx, ny = 6, 5
    xs, ys = np.meshgrid(np.linspace(0, 0.1, nx), np.linspace(0, 0.08, ny))
    neutral = np.c_[xs.ravel(), ys.ravel(), 0.01 * np.sin(20 * xs.ravel())]
    tris = []
    for j in range(ny - 1):
        for i in range(nx - 1):
            a, b, c, d = j * nx + i, j * nx + i + 1, (j + 1) * nx + i, (j + 1) * nx + i + 1
            tris += [[a, b, d], [a, d, c]]
    tris = np.array(tris)
    n = len(neutral)
    deltas = rng.normal(size=(K, n, 3)) * 0.002
    tmpl_neutral = neutral.copy()
    if degenerate:
        tmpl_neutral[tris[0, 1]] = tmpl_neutral[tris[0, 0]]
    names = ["jawOpen", "mouthSmileLeft", "eyeBlinkLeft"][:K]
    W = rng.uniform(0, 1, size=(F, K))
    if never is not None:
        W[:, never] = 0.0
    pts = neutral + np.einsum("fk,knc->fnc", W, deltas)
    if n_frame is not None:
        pts = pts[:, :n_frame]
    frames = Frames(pts, W, ["train"] * F, [f"{i:03d}" for i in range(F)])
    template = FaceRig(tmpl_neutral, tris, names, deltas)
    return Capture(neutral, tris, template, frames, names, source="cap.usda")


def test_frames_with_a_different_vertex_count():
    with pytest.raises(GeometryError, match="vertex count") as exc:
        fit_personalized_shapes(tiny_capture(n_frame=20))
    assert "cap.usda" in str(exc.value) and "fix:" in str(exc.value)


def test_no_training_frames():
    cap = tiny_capture()
    cap.frames.role = ["test"] * len(cap.frames.role)
    with pytest.raises(FitError, match="no training frames"):
        fit_personalized_shapes(cap)


def test_degenerate_template_triangles():
    with pytest.raises(GeometryError, match="degenerate"):
        fit_personalized_shapes(tiny_capture(degenerate=True))


def test_unknown_method_and_bad_reg():
    with pytest.raises(FitError, match="unknown method"):
        fit_personalized_shapes(tiny_capture(), method="magic")
    with pytest.raises(FitError, match="reg"):
        fit_personalized_shapes(tiny_capture(), reg="lots")
    with pytest.raises(FitError, match="reg"):
        fit_personalized_shapes(tiny_capture(), reg=-1)


def test_underdetermined_and_never_activated_shapes_warn_by_name():
    with pytest.warns(UserWarning) as rec:
        res = fit_personalized_shapes(tiny_capture(F=2, never=1), align=False)
    text = " ".join(str(w.message) for w in rec)
    assert "underdetermined" in text and "mouthSmileLeft" in text
    assert any("mouthSmileLeft" in w for w in res.info["warnings"])
    # the never-activated shape stays at the generic (deformation-transferred) shape
    k = res.rig.names.index("mouthSmileLeft")
    cap = tiny_capture(F=2, never=1)
    assert np.allclose(res.rig.deltas[k], cap.template.deltas[k], atol=1e-6)


def test_unknown_method_options_are_named():
    with pytest.raises(FitError, match="bogus"):
        fit_personalized_shapes(tiny_capture(), method="laplacian", bogus=1)
    with pytest.raises(FitError, match="bogus"):
        fit_personalized_shapes(tiny_capture(), method="menzel", bogus=1)


def test_prior_auto_with_a_fixed_reg_names_the_reg():
    """'fit --reg paper --prior auto' said "bad prior 'auto'" with a fix listing 'auto' among the good ones:
    the prior is fine, the fixed reg turns the cross-validation that chooses it off."""
    for reg in ("paper", 0.01):
        with pytest.raises(FitError, match=r"prior='auto' is chosen by the cross-validation, which reg="):
            fit_personalized_shapes(tiny_capture(), prior="auto", reg=reg)


def test_options_a_method_cannot_use_are_refused():
    cap = tiny_capture()
    for method, kw in (("dt", {"reg": 0.1}), ("dt", {"align": True}), ("dt", {"prior": "dt"}),
                       ("ebfr", {"reg": "paper"}), ("ebfr", {"clamp": 10.0}), ("ebfr", {"reweight": True}),
                       ("ebfr", {"prior": "template"}), ("menzel", {"beta": 0.5}), ("dt", {"beta": 0.5}),
                       ("dt", {"align": False}), ("dt", {"reweight": False}), ("ebfr", {"reweight": False})):
        with pytest.raises(FitError, match="not used by method"):
            fit_personalized_shapes(cap, method=method, **kw)


def test_user_clamp_is_honoured_by_the_cross_validation_and_laplacian():
    """A user clamp changes eq. (3)'s weights and the vertices the CV treats as static."""
    from usdface.personalize.crossval import cv_vertices
    from usdface.personalize.fit import regularization_weights
    from usdface.personalize.laplacian import region_masks

    cap = tiny_capture(K=2)
    deltas = cap.template.deltas.copy()
    deltas[:, :5] = 0.0                                # 5 static vertices
    D = regularization_weights(deltas, clamp=50.0)
    static = np.flatnonzero(D.min(axis=0) >= 50.0)
    assert set(range(5)) <= set(static.tolist())
    assert set(cv_vertices(D, 50.0).tolist()) == set(range(len(D[0]))) - set(static.tolist())
    assert set(cv_vertices(D, 1e5).tolist()) == set(range(len(D[0])))    # the old hard-coded clamp
    cap.frames.points[:] += np.random.default_rng(1).normal(size=cap.frames.points.shape) * 1e-3
    kw = {"method": "laplacian", "reg": 1e-3, "mask_threshold": 0.5, "align": False, "reweight": False}
    a = fit_personalized_shapes(cap, clamp=50.0, **kw)
    b = fit_personalized_shapes(cap, **kw)
    outside = ~region_masks(cap.template.deltas, 0.5)              # where the mask clamps D_j
    assert np.abs(a.rig.deltas - b.rig.deltas)[outside].max() > 1e-6


def test_training_frames_repeated_exactly_warn_by_label():
    """A capture app that keeps one frame for several requested shapes (dev1/dev3: 51 labels, 28 distinct
    scans) is told: the repeated frames are named, grouped, and counted; a frame that differs in one weight or
    one coordinate is not a repeat."""
    from usdface.personalize.api import check_capture, duplicate_frames

    cap = tiny_capture(F=8, K=3)
    fr = cap.frames
    pts, w = fr.points.copy(), fr.weights.copy()
    pts[5], w[5] = pts[1], w[1]                        # 005 = 001
    pts[6], w[6] = pts[1], w[1]                        # 006 = 001
    pts[7], w[7] = pts[2], w[2].copy()                 # 007 = 002 but one weight off by 1e-12
    w[7, 0] += 1e-12
    pts[3], w[3] = pts[0] + 1e-12, w[0]                # 003 = 000 but every coordinate off by 1e-12
    assert duplicate_frames(pts, w) == [[1, 5, 6]]
    cap.frames = Frames(pts, w, fr.role, [f"{i:03d}_{n}" for i, n in enumerate("abcdefgh")])
    text = " ".join(check_capture(cap))
    assert "2 training frame(s) repeat another frame exactly" in text
    assert "001_b = 005_f = 006_g" in text and "6 distinct frames" in text
    assert "002_c" not in text and "003_d" not in text
    assert duplicate_frames(fr.points, fr.weights) == []      # tiny_capture's own frames are distinct
    # frames whose words sum alike but differ (two coordinates swapped): the fingerprint collides, and the
    # frames are then grouped by their bytes: the true repeat is found, the swapped frame kept apart
    swapped = pts.copy()
    swapped[4] = pts[1]
    swapped[4, 0, [0, 1]] = pts[1, 0, [1, 0]]
    assert swapped[4, 0, 0] != swapped[4, 0, 1]
    w4 = w.copy()
    w4[4] = w[1]
    assert duplicate_frames(swapped, w4) == [[1, 5, 6]]
    assert not any("repeat" in s for s in check_capture(tiny_capture(F=8, K=3)))


def test_dev1_capture_repeats_its_rest_frame(bench):
    """dev1's training frames as the phone app picked them: 23 of 51 repeat another (one frame stands for 12
    requested shapes the take never triggered)."""
    from usdface.io import read_capture
    from usdface.personalize.api import duplicate_frames

    train = read_capture(bench / "dev1" / "capture").train
    groups = duplicate_frames(train.points, train.weights)
    assert sum(len(g) - 1 for g in groups) == 23 and max(len(g) for g in groups) == 12
    assert [train.label[i] for i in groups[0]] == ["000_eyeBlinkLeft", "007_eyeBlinkRight"]


def test_inspect_of_a_capture_lists_its_repeated_frames(tmp_path):
    """``inspect`` of a capture says which training frames are copies (the fit warns about them too)."""
    from usdface.inspect import format_report, summarize_capture

    cap = tiny_capture(F=8, K=3)
    fr = cap.frames
    pts, w = fr.points.copy(), fr.weights.copy()
    pts[4], w[4] = pts[2], w[2]
    cap.frames = Frames(pts, w, fr.role, [f"{i:03d}_x" for i in range(8)])
    report = summarize_capture(cap)
    assert report["repeatedFrames"] == [["002_x", "004_x"]]
    assert "repeated exactly: 1 training frame(s)" in format_report(report)
    assert summarize_capture(tiny_capture(F=8, K=3))["repeatedFrames"] == []


def test_weights_that_activate_nothing_are_refused(tmp_path, capsys):
    """Every training weight 0 (weights lost on export) crashed with numpy's 'cannot reshape array of size
    0'; it is a FitError naming the capture and the fix, from the CLI before any output."""
    from usdface.api import write_capture
    from usdface.model import Capture, Frames

    cap = _capture()
    f = cap.frames
    zero = Capture(cap.neutral, cap.triangles, cap.template,
                   Frames(f.points, np.zeros_like(f.weights), f.role, f.label), cap.names)
    path = tmp_path / "zero.usda"
    write_capture(zero, path)
    for argv in (["fit", str(path), "-o", str(tmp_path / "o.usda")],
                 ["personalize", str(A), str(path), "-o", str(tmp_path / "p.usda")]):
        assert main([*argv, "-q"]) == 2
        err = capsys.readouterr().err
        assert "no training frame activates any shape" in err and "zero.usda" in err and "fix:" in err
    assert not any(tmp_path.glob("[op].usda"))


def test_one_frame_fits_and_zero_frame_weights_are_refused():
    """One training frame: the Laplacian fit's 3-fold CV trained on an empty fold (a reshape crash); ebfr
    with beta 0 hit a singular matrix; all-zero frame weights passed the check and crashed later."""
    from usdface.model import Capture, Frames
    from usdface.personalize import fit_personalized_shapes

    cap = _capture()
    f = cap.frames
    one = Capture(cap.neutral, cap.triangles, cap.template,
                  Frames(f.points[:1], f.weights[:1], ["train"], f.label[:1]), cap.names)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = fit_personalized_shapes(one, "laplacian")
        assert np.all(np.isfinite(res.rig.deltas))
        with pytest.raises(FitError, match="bad beta 0"):
            fit_personalized_shapes(one, "ebfr", beta=0.0, align=False)
        with pytest.raises(FitError, match="not all 0"):
            fit_personalized_shapes(cap, frame_weights=np.zeros(len(cap.train)))
