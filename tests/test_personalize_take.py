"""Whole-take fitting: every frame of a scan-regime take (usdface.sample.take), balanced frame weights."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from test_take_select import grid_rigs

from usdface.errors import FitError
from usdface.io.take import capture_from_take
from usdface.model import Capture, Frames
from usdface.personalize import fit_personalized_shapes, truth_error
from usdface.personalize.takefit import balanced_frame_weights
from usdface.sample.take import make_take
from usdface.take_select import select_frames


@pytest.fixture(scope="module")
def scan_take():
    person, template = grid_rigs(seed=4)
    take, truth = make_take(person, template, point_noise=3e-4, weight_noise=0.02, sweep_seconds=0.3,
                            rest_seconds=0.2, seed=2)
    return take, person, template


def fit(cap, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fit_personalized_shapes(cap, **kw)


def test_whole_take_fit_beats_the_peak_frames_and_improves_with_frames(scan_take):
    take, person, template = scan_take
    peak = capture_from_take(take, select_frames(take.weights, names=take.names, min_separation=8))
    e_peak = truth_error(fit(peak).rig.deltas, person.deltas)
    errs = []
    for step in (4, 2, 1):
        idx = np.arange(0, len(take.weights), step)
        frames = Frames(take.points[idx], take.weights[idx], ["train"] * len(idx), [str(i) for i in idx])
        cap = Capture(take.neutral, take.triangles, template, frames, list(template.names))
        errs.append(truth_error(fit(cap, frame_weights="balanced").rig.deltas, person.deltas))
    assert errs[-1] <= 0.75 * e_peak                    # issue 13: at least 25 % below the peak-frame fit
    assert errs[0] > errs[1] > errs[2]                  # and falling as frames are added


def test_balanced_weights_count_each_pose_once():
    held = np.tile([[0.9, 0.0]], (30, 1)) + np.random.default_rng(0).normal(size=(30, 2)) * 0.005
    once = np.array([[0.0, 0.8]])
    omega = balanced_frame_weights(np.vstack([held, once]))
    assert np.isclose(omega[:30].sum(), omega[30])      # 30 repeats of a pose weigh as much as one pose
    assert np.isclose(omega.mean(), 1.0)


def test_frame_weights_are_checked(scan_take):
    take, person, template = scan_take
    cap = Capture(take.neutral, take.triangles, template,
                  Frames(take.points[:60], take.weights[:60], ["train"] * 60, [str(i) for i in range(60)]),
                  list(template.names))
    with pytest.raises(FitError, match="frame_weights"):
        fit(cap, frame_weights=np.ones(3))
    with pytest.raises(FitError, match="frame_weights"):
        fit(cap, method="ebfr", frame_weights="balanced")
    with pytest.raises(FitError, match="align"):
        fit(cap, frame_weights="balanced", align=True)
    # uniform weights are the unweighted fit
    a = fit(cap, frame_weights=np.ones(60), reg=1e-3).rig.deltas
    b = fit(cap, reg=1e-3, align=False, reweight=False).rig.deltas
    assert np.allclose(a, b, atol=1e-12)
