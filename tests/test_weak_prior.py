"""With ``weak_prior`` (off by default) the plain fit returns a shape its training frames show too weakly to
measure towards its prior (:mod:`usdface.personalize.weak`): what the one frame that shows it leaves
unexplained would otherwise go into it at ~1/weight."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from test_personalize_prior import NAMES, person_and_template

from usdface.errors import FitError
from usdface.model import Capture, FaceRig, Frames
from usdface.personalize import fit_personalized_shapes
from usdface.personalize.weak import WEAK_SHAPE, toward_prior, weak_ramp

WEAK = 1            # shown at 0.07, in one frame only (dev3's jawLeft)
MID = 2             # shown at 0.25 in one frame: within the ramp (4-10 times the weights' noise)


def weak_capture(seed=5, weak_weight=0.07, unexplained=3e-4):
    """A generated capture (the person's shapes, a template 0.5 mm off them): one frame per shape at weight 1
    and ten mixtures, except shape ``WEAK``, shown only in the ``jawOpen`` frame at ``weak_weight``, and
    ``MID`` only in its own frame at 0.25. The ``jawOpen`` frame also holds motion no shape explains (a
    non-linear bulge of ``unexplained`` m where ``WEAK`` moves, as a real jaw frame has)."""
    rng, neutral, tris, true, template, W = person_and_template(seed)
    n = len(neutral)
    W[:, WEAK] = 0.0
    W[0, WEAK] = weak_weight
    W[:, MID] = 0.0
    W[MID, MID] = 0.25
    pts = neutral + np.einsum("fk,knc->fnc", W, true) + rng.normal(size=(len(W), n, 3)) * 2e-5
    pts[0] += unexplained * np.sign(true[WEAK]) * (np.abs(true[WEAK]) > 0.001)
    frames = Frames(pts, W, ["train"] * len(W), [f"{i:03d}" for i in range(len(W))])
    return Capture(neutral, tris, FaceRig(neutral.copy(), tris, list(NAMES), template), frames,
                   list(NAMES)), true


def fit(cap, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fit_personalized_shapes(cap, **kw)


def rms_mm(a, b):
    return float(np.sqrt(np.mean(np.sum((np.asarray(a) - np.asarray(b)) ** 2, axis=-1))) * 1e3)


def test_a_weakly_shown_shape_ends_no_further_from_the_truth_than_its_prior():
    cap, true = weak_capture()
    res = fit(cap, weak_prior=True)
    prior = res.info["prior_deltas"]
    kept = fit(cap)
    # without it the frame's unexplained motion, amplified ~1/0.07, puts the shape further off than its prior
    assert rms_mm(kept.rig.deltas[WEAK], true[WEAK]) > 1.5 * rms_mm(prior[WEAK], true[WEAK])
    # with it the shape is its prior (ramp 0 below 4 sigma): no further from the truth (tolerance 1e-6 mm)
    assert rms_mm(res.rig.deltas[WEAK], true[WEAK]) <= rms_mm(prior[WEAK], true[WEAK]) + 1e-6
    assert res.info["weak"][NAMES[WEAK]] == 0.0


def test_a_shape_within_the_ramp_is_taken_part_way_and_the_shown_shapes_are_untouched():
    cap, true = weak_capture()
    res, kept = fit(cap, weak_prior=True), fit(cap)
    prior = res.info["prior_deltas"]
    lo, hi = WEAK_SHAPE
    t = (0.25 - lo) / (hi - lo)
    factor = t * t * (3 - 2 * t)
    assert res.info["weak"][NAMES[MID]] == pytest.approx(factor, abs=1e-3)
    np.testing.assert_allclose(res.rig.deltas[MID], prior[MID] + factor * (kept.rig.deltas[MID] - prior[MID]),
                               atol=1e-12)
    shown = [k for k in range(len(NAMES)) if k not in (WEAK, MID)]
    assert set(res.info["weak"]) == {NAMES[WEAK], NAMES[MID]}
    np.testing.assert_array_equal(res.rig.deltas[shown], kept.rig.deltas[shown])


def test_off_by_default_and_then_the_fit_as_before():
    cap, _ = weak_capture()
    for kw in ({}, {"reg": "paper"}, {"sensitivity": True}):
        res, off = fit(cap, **kw), fit(cap, weak_prior=False, **kw)
        assert "weak" not in res.info
        np.testing.assert_array_equal(res.rig.deltas, off.rig.deltas)
    on = fit(cap, reg="paper", weak_prior=True)
    assert on.info["weak"][NAMES[WEAK]] == 0.0


def test_weak_prior_is_refused_where_no_prior_is_fitted():
    cap, _ = weak_capture()
    for method in ("dt", "ebfr"):
        with pytest.raises(FitError, match="--weak-prior"):
            fit(cap, method=method, weak_prior=True)
        assert "weak" not in fit(cap, method=method, weak_prior=False).info
    with pytest.raises(FitError, match="not a boolean"):
        fit(cap, weak_prior="no")


def test_toward_prior_keeps_a_vertex_where_the_fit_is_the_prior():
    rng = np.random.default_rng(0)
    prior = rng.normal(size=(3, 5, 3))
    deltas = prior + rng.normal(size=(3, 5, 3))
    deltas[1, 2] = prior[1, 2]                      # a pinned vertex: the template in both
    out = toward_prior(deltas, prior, np.array([0.0, 0.5, 1.0]))
    np.testing.assert_array_equal(out[0], prior[0])
    np.testing.assert_array_equal(out[2], deltas[2])
    np.testing.assert_array_equal(out[1, 2], prior[1, 2])
    np.testing.assert_allclose(out[1], 0.5 * (prior[1] + deltas[1]))


def test_weak_ramp_ends_at_four_and_ten_times_the_weights_noise():
    cap, _ = weak_capture()
    lo, hi = WEAK_SHAPE
    ramp, info = weak_ramp(cap, np.array([0.0, lo ** 2, hi ** 2, 1.0]), [0, 1, 2, 3])
    assert info == {}
    np.testing.assert_allclose(ramp, [0.0, 0.0, 1.0, 1.0])


def test_fit_prints_each_weak_shape_with_its_factor():
    from usdface.commands.fit import weak_line

    assert weak_line(None) is None and weak_line({}) is None
    line = weak_line({"jawLeft": 0.0, "cheekSquintLeft": 0.528})
    assert "jawLeft 0.00" in line and "cheekSquintLeft 0.53" in line
