"""The avatar prior of the fit (``avatar_prior``), the per-shape prior report and the shape confidence."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from synthetic_meshes import grid_triangles

from usdface.errors import FitError
from usdface.model import Capture, FaceRig, Frames
from usdface.personalize import fit_personalized_shapes, truth_error

NAMES = ["jawOpen", "mouthSmileLeft", "eyeBlinkLeft", "browInnerUp", "cheekPuff", "noseSneerLeft"]
NEVER = [4, 5]          # shapes with weight 0 in every training frame


def grid_mesh(nx=9, ny=8):
    xs, ys = np.meshgrid(np.linspace(0, 0.1, nx), np.linspace(0, 0.08, ny))
    neutral = np.c_[xs.ravel(), ys.ravel(), 0.01 * np.sin(20 * xs.ravel()) + 0.005 * np.cos(30 * ys.ravel())]
    return neutral, grid_triangles(nx, ny)


def prior_capture(seed=0):
    """Clean synthetic capture: the person's shapes = the avatar's generic shapes + a small personal offset
    (excited shapes) or exactly the avatar's (never-excited shapes); the template is another rig, 1.5 mm off.
    Shape 0 is isolated at weight 1 in frame 0 (and nowhere else)."""
    rng = np.random.default_rng(seed)
    neutral, tris = grid_mesh()
    K, n = len(NAMES), len(neutral)
    avatar = rng.normal(size=(K, n, 3)) * 0.002
    true = avatar + rng.normal(size=(K, n, 3)) * 0.0002
    true[NEVER] = avatar[NEVER]
    template = avatar + rng.normal(size=(K, n, 3)) * 0.0015
    tmpl_neutral = neutral + rng.normal(size=neutral.shape) * 0.0005
    F = 8
    W = rng.uniform(0, 1, size=(F, K)) * (rng.uniform(size=(F, K)) < 0.6)
    W[:, 0] = 0.0
    W[0] = 0.0
    W[0, 0] = 1.0
    W[:, NEVER] = 0.0
    pts = neutral + np.einsum("fk,knc->fnc", W, true)
    frames = Frames(pts, W, ["train"] * F, [f"{i:03d}" for i in range(F)])
    cap = Capture(neutral, tris, FaceRig(tmpl_neutral, tris, list(NAMES), template), frames, list(NAMES),
                  source="cap.usda")
    return cap, true, avatar


def fit(cap, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")           # "never activated" is expected here
        return fit_personalized_shapes(cap, **kw)


def test_never_excited_shapes_are_exactly_the_avatar_prior():
    cap, true, avatar = prior_capture()
    res = fit(cap, avatar_prior=avatar)
    assert [res.info["prior_choice"][k] for k in NEVER] == ["avatar", "avatar"]
    assert np.abs(res.rig.deltas[NEVER] - true[NEVER]).max() < 1e-9
    assert truth_error(res.rig.deltas, true) < 0.5 * truth_error(fit(cap).rig.deltas, true)


def test_without_avatar_prior_never_excited_shapes_are_the_chosen_generic_prior():
    from usdface.personalize.dt import deformation_transfer

    cap, true, avatar = prior_capture()
    res = fit(cap)
    dt = deformation_transfer(cap.template.neutral, cap.template.deltas, cap.neutral, cap.triangles,
                              names=cap.names)
    a = res.info["prior_alpha"]
    expect = a * dt + (1 - a) * cap.template.deltas
    assert res.info["prior_choice"] == [{1.0: "dt", 0.0: "template"}.get(a, "blend")] * len(NAMES)
    assert np.abs(res.rig.deltas[NEVER] - expect[NEVER]).max() < 1e-9
    # prior="template" really gives the template there
    res_t = fit(cap, prior="template", reg=1e-3)
    assert res_t.info["prior_choice"] == ["template"] * len(NAMES)
    assert np.abs(res_t.rig.deltas[NEVER] - cap.template.deltas[NEVER]).max() < 1e-9


def test_shape_the_avatar_lacks_falls_back_to_the_generic_prior():
    cap, true, avatar = prior_capture()
    av = avatar.copy()
    av[5] = np.nan
    res = fit(cap, avatar_prior=av)
    assert res.info["prior_choice"][4] == "avatar" and res.info["prior_choice"][5] != "avatar"
    assert np.abs(res.rig.deltas[4] - true[4]).max() < 1e-9
    assert np.all(np.isfinite(res.rig.deltas))


def test_with_the_avatar_prior_the_template_does_not_set_the_fitted_shapes():
    """Eq. (3)'s ``D_j`` is the prior's: with the avatar's shapes as the prior, a template by another artist
    (other shapes, one that leaves part of a shape still) gives the same fit; with the template's ``D`` the
    person's motion where that template is still was clamped to the prior."""
    import dataclasses

    cap, true, avatar = prior_capture()
    other = cap.template.deltas + np.random.default_rng(7).normal(size=cap.template.deltas.shape) * 0.0015
    other[1, :30] = 0.0                                     # this artist's mouthSmileLeft leaves them still
    cap2 = dataclasses.replace(cap, template=dataclasses.replace(cap.template, deltas=other))
    a, b = fit(cap, avatar_prior=avatar, prior="avatar"), fit(cap2, avatar_prior=avatar, prior="avatar")
    assert np.abs(a.rig.deltas - b.rig.deltas).max() < 1e-12
    assert truth_error(b.rig.deltas, true) < 1e-5


def test_shape_confidence_is_zero_without_data_and_one_when_isolated():
    cap, true, avatar = prior_capture()
    for kw in ({}, {"avatar_prior": avatar}, {"reg": 1e-4}, {"reg": 1e-4, "align": False, "reweight": False}):
        conf = fit(cap, **kw).info["shape_confidence"]
        assert conf.shape == (len(NAMES),) and np.all((conf >= 0) & (conf <= 1))
        assert np.all(conf[NEVER] < 1e-9)
        # isolated at weight 1, clean data; with a cross-validated reg the reliability's noise is the
        # leave-one-frame-out error, which holds shape 0's own personalization (frame 0, its only view, left
        # out): 0.87-0.89 here, 1 - 3 x diag x that error^2 / |B_0 - T_0|^2
        assert conf[0] > (0.9 if "reg" in kw else 0.85)


def test_bad_avatar_prior_is_refused():
    cap, true, avatar = prior_capture()
    with pytest.raises(FitError, match="shape"):
        fit(cap, avatar_prior=avatar[:3])
    part = avatar.copy()
    part[2, :5] = np.nan
    with pytest.raises(FitError, match="eyeBlinkLeft"):
        fit(cap, avatar_prior=part)
    for kw in ({"method": "dt"}, {"method": "ebfr"}, {"prior": "dt"}):
        with pytest.raises(FitError, match="avatar_prior"):
            fit(cap, avatar_prior=avatar, **kw)
    with pytest.raises(FitError, match="avatar_prior"):
        fit(cap, prior="avatar")


def test_dev3_avatar_prior_beats_the_other_artists_template(bench):
    """dev3's template is another artist's rig (~1.4 mm off the person). A stand-in for the avatar's generic
    shapes on the capture: dev1's template (the same ICT avatar's rig sampled on the same capture topology),
    rotated rigidly onto dev3's neutral. With it the CV picks the avatar prior and the truth error drops
    below the issue's 0.40 mm (0.53 mm without)."""
    from usdface.io import read_capture
    from usdface.personalize.align import kabsch

    if not (bench / "dev3").is_dir():
        pytest.skip("dev3 not present")
    c1, c3 = read_capture(bench / "dev1" / "capture"), read_capture(bench / "dev3" / "capture")
    truth = np.load(bench / "dev3" / "truth" / "capture_truth.npz")
    assert c1.names == c3.names == list(truth["names"])
    R, _ = kabsch(c1.template.neutral[None], c3.neutral)
    prior = np.einsum("ij,knj->kni", R[0], c1.template.deltas)
    res = fit(c3, avatar_prior=prior)
    assert set(res.info["prior_choice"]) == {"avatar"}
    err = truth_error(res.rig.deltas, truth["deltas"])
    assert err < 0.40
    assert err < 0.8 * truth_error(fit(c3).rig.deltas, truth["deltas"])


def person_and_template(seed):
    """``(rng, neutral[n,3], triangles, true[K,n,3], template[K,n,3], W[F,K])`` of a generated capture on a
    14 x 12 grid: the person's shapes (2 mm), a template 0.5 mm off them, one frame per shape at weight 1
    and ten mixtures; ``rng`` the generator, drawn on further by the caller."""
    rng = np.random.default_rng(seed)
    neutral, tris = grid_mesh(14, 12)
    K, n = len(NAMES), len(neutral)
    true = rng.normal(size=(K, n, 3)) * 0.002
    template = true + rng.normal(size=(K, n, 3)) * 0.0005
    W = np.vstack([np.eye(K), rng.uniform(0, 0.6, size=(10, K))])
    return rng, neutral, tris, true, template, W


def noisy_capture(misalign_deg=0.0, seed=3, weight_noise=0.0):
    """A larger clean capture (one frame per shape plus mixtures) whose frames are optionally rotated and
    whose reported weights optionally carry Gaussian noise (clipped to [0, 1])."""
    from scipy.spatial.transform import Rotation

    rng, neutral, tris, true, template, W = person_and_template(seed)
    n = len(neutral)
    pts = neutral + np.einsum("fk,knc->fnc", W, true) + rng.normal(size=(len(W), n, 3)) * 2e-5
    if misalign_deg:
        c = neutral.mean(axis=0)
        for f in range(len(W)):
            R = Rotation.from_rotvec(rng.normal(size=3) * np.radians(misalign_deg)).as_matrix()
            pts[f] = (pts[f] - c) @ R.T + c + rng.normal(size=3) * 5e-4
    if weight_noise:
        W = np.clip(W + rng.normal(size=W.shape) * weight_noise, 0.0, 1.0)
    frames = Frames(pts, W, ["train"] * len(W), [f"{i:03d}" for i in range(len(W))])
    rig = FaceRig(neutral.copy(), tris, list(NAMES), template)
    return Capture(neutral, tris, rig, frames, list(NAMES)), true


def test_alignment_and_reweighting_are_no_ops_on_clean_data():
    cap, true = noisy_capture()
    res = fit(cap)
    assert res.info["align"]["applied"] is False and res.info["reweight"]["applied"] is False
    plain = fit(cap, align=False, reweight=False)
    assert np.array_equal(res.rig.deltas, plain.rig.deltas)


def test_alignment_is_applied_where_frames_are_misaligned():
    cap, true = noisy_capture(misalign_deg=1.0)
    res = fit(cap, reweight=False)
    assert res.info["align"]["applied"] is True
    plain = fit(cap, align=False, reweight=False)
    assert truth_error(res.rig.deltas, true) < 0.6 * truth_error(plain.rig.deltas, true)


def test_reweighting_is_applied_where_the_phone_weights_are_noisy():
    cap, true = noisy_capture(weight_noise=0.05)
    res = fit(cap, align=False)
    assert res.info["reweight"]["applied"] is True
    assert res.info["reweight"]["held_out_rmse_mm"]["phone"] > min(
        v for k, v in res.info["reweight"]["held_out_rmse_mm"].items() if k != "phone")
    plain = fit(cap, align=False, reweight=False)
    # one round (the default since stop 50): 0.245 against 0.294 mm; two rounds, which this capture's mixtures
    # keep from drifting, 0.225
    assert truth_error(res.rig.deltas, true) < 0.85 * truth_error(plain.rig.deltas, true)


def test_significance_test_refuses_a_gain_within_the_noise():
    from usdface.personalize.api import significantly_better

    rng = np.random.default_rng(0)
    old = rng.uniform(1.0, 2.0, size=50)
    noise = rng.normal(size=50) * 0.2
    assert not significantly_better(old + noise - noise.mean() - 1e-3, old)    # mean gain 1e-3, sd 0.2
    assert significantly_better(old * 0.9, old)                                # 10 % on every frame
    assert not significantly_better(old * 1.1, old)


def test_evaluate_reports_tuned_and_fixed_variants():
    from usdface.personalize.report import evaluate_methods

    cap, true = noisy_capture()
    test = Frames(cap.frames.points[-4:], cap.frames.weights[-4:], ["test"] * 4, ["t0", "t1", "t2", "t3"])
    both = Frames(np.concatenate([cap.frames.points, test.points]),
                  np.concatenate([cap.frames.weights, test.weights]), cap.frames.role + test.role,
                  cap.frames.label + test.label)
    cap = Capture(cap.neutral, cap.triangles, cap.template, both, cap.names)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rep = evaluate_methods(cap, ["ebfr", "menzel"], reg="auto", prior=None, align=None, reweight=None)
    assert list(rep["methods"]) == ["ebfr", "ebfr tuned", "menzel", "menzel paper"]
    assert rep["methods"]["ebfr"]["info"]["beta"] == 0.5
    assert rep["methods"]["ebfr tuned"]["info"]["beta"] != 0.5
    assert rep["methods"]["menzel paper"]["info"]["reg"] == 1.0


def test_pinned_vertices_are_the_artists_version():
    cap, true = noisy_capture()
    n = len(cap.neutral)
    region = np.arange(n) < n // 3
    res = fit(cap, pins={"jawOpen": region, "eyeBlinkLeft": [0, 1, 2]})
    k, b = cap.names.index("jawOpen"), cap.names.index("eyeBlinkLeft")
    assert np.abs(res.rig.deltas[k, region] - cap.template.deltas[k, region]).max() < 1e-9
    assert np.abs(res.rig.deltas[b, :3] - cap.template.deltas[b, :3]).max() < 1e-9
    free = fit(cap)
    # elsewhere the shape is still fitted (closer to the truth than the template)
    err = np.abs(res.rig.deltas[k, ~region] - true[k, ~region]).mean()
    assert err < np.abs(cap.template.deltas[k, ~region] - true[k, ~region]).mean()
    assert not np.allclose(free.rig.deltas[k, region], res.rig.deltas[k, region])
    with pytest.raises(FitError, match="lacks"):
        fit(cap, pins={"nope": [0]})
    with pytest.raises(FitError, match="pins"):
        fit(cap, method="dt", pins={"jawOpen": [0]})


def test_reweighting_holds_each_shape_weight_in_its_peak_frame():
    """A shape's amplitude and its weight in the frame that isolates it are not separately identifiable:
    re-estimation keeps that weight at the phone's value (and so cannot rescale the shape) and re-estimates
    the others."""
    from usdface.personalize.weights import held_weights, peak_frames

    cap, true = noisy_capture(weight_noise=0.05)
    W = cap.train.weights
    res = fit(cap, align=False)
    assert res.info["reweight"]["applied"] is True
    new = res.info["train_weights"]
    peak = peak_frames(W)
    K = W.shape[1]
    assert np.array_equal(new[peak, np.arange(K)], W[peak, np.arange(K)])
    assert np.abs(new - W)[~held_weights(W)].max() > 1e-3            # the other weights do move
    W2 = np.array([[0.9, 0.0, 0.01], [0.2, 0.7, 0.0], [0.3, 0.8, 0.02]])
    assert peak_frames(W2).tolist() == [0, 2, 2]
    assert held_weights(W2, 0.05).tolist() == [[True, False, True], [False, False, True], [False, True, True]]


def test_reweighting_runs_the_one_round_its_gate_validates():
    """The gate tests one re-estimation (from the phone-weight shapes); the default runs that one round and
    says so. A second round, asked for, re-estimates from the refitted shapes: other weights, other shapes."""
    cap, true = noisy_capture(weight_noise=0.05)
    one = fit(cap, align=False)
    assert one.info["reweight"]["applied"] is True and one.info["reweight"]["rounds"] == 1
    two = fit(cap, align=False, rounds=2)
    assert two.info["reweight"]["rounds"] == 2
    assert np.abs(two.info["train_weights"] - one.info["train_weights"]).max() > 1e-3
    assert np.abs(two.rig.deltas - one.rig.deltas).max() > 1e-6


def test_a_second_reestimation_round_drifts_on_a_scan_regime_capture(bench):
    """dev2 (scan regime, one picked frame per shape): shapes refitted with the first round's weights take
    those weights' errors in, and a second re-estimation drifts with them: one round ends nearer the
    person's true shapes than two (0.3305 against 0.3458 mm; the raw template 0.3992), the shapes' sizes as
    the training frames set them (``amplitude=False``: the test frames' second reading narrows the gap,
    0.2996 against 0.3064)."""
    from usdface.io import read_capture

    cap = read_capture(bench / "dev2" / "capture")
    truth = np.load(bench / "dev2" / "truth" / "capture_truth.npz")
    true = truth["deltas"][[list(truth["names"]).index(n) for n in cap.names]]
    one = fit(cap, amplitude=False)
    assert one.info["reweight"]["applied"] is True and one.info["reweight"]["rounds"] == 1
    two = fit(cap, rounds=2, amplitude=False)
    assert truth_error(one.rig.deltas, true) < truth_error(two.rig.deltas, true) - 0.01
    assert truth_error(one.rig.deltas, true) < 0.84 * truth_error(cap.template.deltas, true)


def test_dev2s_shape_sizes_read_on_the_test_frames_bring_the_fit_within_issue_13s_ratio(bench):
    """Issue 13's dev2 figure: a shape's size is fixed by its one weight in its peak frame (dev2: 51 frames
    for 51 shapes, no second reading of it in the training frames; the phone's weights +-0.045 about the
    truth's), so the fit read it again on the test frames (default ``amplitude``): the truth error at most
    0.80 of the raw template's (0.750; without the reading 0.828), below the CV-only fit's, and the
    held-out eq. 5 score cross-fitted (each test frame scored with the scales read on the others: no frame
    scores a number it helped set), within 2 % of the fit without the reading (the phone's noisy test weights
    score the scaled and the unscaled shapes alike)."""
    from usdface.io import read_capture
    from usdface.personalize import evaluate_rig
    from usdface.personalize.api import left_out_scale

    cap = read_capture(bench / "dev2" / "capture")
    truth = np.load(bench / "dev2" / "truth" / "capture_truth.npz")
    true = truth["deltas"][[list(truth["names"]).index(n) for n in cap.names]]
    template = truth_error(cap.template.deltas, true)
    read = fit(cap)
    unread = fit(cap, amplitude=False)
    cv_only = fit(cap, align=False, reweight=False, amplitude=False)
    assert truth_error(read.rig.deltas, true) <= 0.80 * template
    assert truth_error(unread.rig.deltas, true) > 0.80 * template
    assert truth_error(read.rig.deltas, true) < truth_error(cv_only.rig.deltas, true)
    scale = left_out_scale(read, cap.test)
    assert scale is not None and scale.shape == cap.test.weights.shape and np.any(scale != 1.0)
    crossed = evaluate_rig(read.rig, cap.test, scale)["mean_rmse_mm"]
    assert crossed != evaluate_rig(read.rig, cap.test)["mean_rmse_mm"]
    assert abs(crossed / evaluate_rig(unread.rig, cap.test)["mean_rmse_mm"] - 1.0) < 0.02


def test_a_whole_take_keeps_the_avatar_prior_even_where_the_template_scores_better():
    """On a take read whole (``frame_weights``) personalize measures the person's change from the fit's
    prior, so another artist's template there lands its mismatch with the avatar on the avatar; the old rule
    took it once its held-out score was better by one standard error, which generated takes cross by chance
    (stop 45: face 1.95x generic). Here the template is the person exactly, so its held-out score is better
    by far more than that (the old rule took it); the prior stays the avatar's, the scores are reported,
    and the shapes the frames show are the person's whichever prior (the frames decide them)."""
    rng = np.random.default_rng(3)
    neutral, tris = grid_mesh()
    K, n, F = len(NAMES), len(neutral), 240
    avatar = rng.normal(size=(K, n, 3)) * 0.002
    true = avatar + rng.normal(size=(K, n, 3)) * 0.0003
    W = rng.uniform(0, 1, size=(F, K)) * (rng.uniform(size=(F, K)) < 0.5)
    W[:, 3] *= 0.05                                           # one shape barely shown: the prior matters
    pts = neutral + np.einsum("fk,knc->fnc", W, true) + rng.normal(size=(F, n, 3)) * 5e-5
    cap = Capture(neutral, tris, FaceRig(neutral, tris, list(NAMES), true.copy()),
                  Frames(pts, W, ["train"] * F, [f"f{i:05d}" for i in range(F)]), list(NAMES), source="take")
    res = fit(cap, avatar_prior=avatar, frame_weights=np.ones(F))
    search = res.info["prior_search"]
    assert search["mean_difference_mm2"] > 2 * search["standard_error_mm2"] > 0   # the template scores better
    assert set(res.info["prior_choice"]) == {"avatar"}
    np.testing.assert_allclose(res.info["prior_deltas"], avatar)
    shown = [0, 1, 2, 4, 5]
    assert truth_error(res.rig.deltas[shown], true[shown]) < 0.1 * truth_error(avatar[shown], true[shown])
