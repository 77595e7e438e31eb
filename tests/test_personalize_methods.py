"""The methods on the project's sample capture (known truth): the papers' ranking, and the bench acceptance
figures of issue 7 when ../shared is present."""

from __future__ import annotations

import numpy as np
import pytest

from usdface.io import read_capture
from usdface.personalize import evaluate_rig, fit_personalized_shapes, truth_error


def run_methods(capture_path, truth_path, methods=("dt", "ebfr", "menzel"), paper=False):
    capture = read_capture(capture_path)
    truth = np.load(truth_path)
    order = [list(truth["names"]).index(n) for n in capture.names]
    true = truth["deltas"][order]
    out = {"template": {"truth": truth_error(capture.template.deltas, true)}}
    runs = [(m, {}) for m in methods]
    if paper:
        runs.append(("paper", {"method": "menzel", "reg": "paper", "align": False, "reweight": False}))
    for name, kw in runs:
        res = fit_personalized_shapes(capture, **({"method": name} if not kw else kw))
        ev = evaluate_rig(res.rig, capture.test)
        out[name] = {"rmse": ev["mean_rmse_mm"], "max": ev["mean_max_mm"],
                     "truth": truth_error(res.rig.deltas, true), "info": res.info}
    return out


@pytest.fixture(scope="module")
def sample_results(samples):
    return run_methods(samples / "capture.usda", samples / "truth" / "capture_truth.npz", paper=True)


def test_sample_ranking_matches_the_papers(sample_results):
    r = sample_results
    # Menzel et al. 2022, Figs. 4-5: menzel < ebfr < dt in test RMSE and in max error
    assert r["menzel"]["rmse"] < r["ebfr"]["rmse"] < r["dt"]["rmse"]
    assert r["menzel"]["max"] < r["ebfr"]["max"] < r["dt"]["max"]
    assert r["menzel"]["rmse"] <= 0.5 * r["dt"]["rmse"]
    # and the recovered shapes are far closer to the truth than the generic template's
    assert r["menzel"]["truth"] <= 0.5 * r["template"]["truth"]
    assert r["menzel"]["truth"] < r["ebfr"]["truth"] < r["dt"]["truth"]


def test_sample_cross_validation_beats_the_paper_balance(sample_results):
    r = sample_results
    assert r["paper"]["info"]["reg"] == 1.0
    assert r["menzel"]["info"]["reg"] < 1.0                          # the paper's balance over-regularises
    assert r["menzel"]["rmse"] < r["paper"]["rmse"]
    assert r["menzel"]["truth"] < r["paper"]["truth"]


def test_sample_default_is_no_worse_than_cross_validation_only(samples, sample_results):
    """Issue 13: the beyond-paper steps decide for themselves; on the sample (clean frames, phone weights
    within 0.01) neither the alignment nor the re-estimation may raise the truth error of CV alone. Both
    fits read the shapes' sizes on the test frames (stop 51's default ``amplitude``); against CV without that
    reading the sample is 0.1203 vs 0.1192 mm (``bench_fit.py`` prints it: a statistical reading's draw)."""
    capture = read_capture(samples / "capture.usda")
    truth = np.load(samples / "truth" / "capture_truth.npz")
    true = truth["deltas"][[list(truth["names"]).index(n) for n in capture.names]]
    cv_only = fit_personalized_shapes(capture, align=False, reweight=False)
    default = sample_results["menzel"]
    assert default["info"]["reweight"]["applied"] is False and default["info"]["align"]["applied"] is False
    assert default["truth"] <= truth_error(cv_only.rig.deltas, true) + 1e-12


@pytest.mark.parametrize("case", ["dev1", "dev2"])
def test_bench_acceptance(bench, case):
    root = bench / case
    r = run_methods(root / "capture", root / "truth" / "capture_truth.npz", methods=("dt", "ebfr", "menzel"))
    m, dt, ebfr, tmpl = r["menzel"], r["dt"], r["ebfr"], r["template"]
    if case == "dev1":                                                # issue 7 acceptance, phone-mesh regime
        assert m["rmse"] <= 0.5 * dt["rmse"]
        assert m["rmse"] <= 0.65 * ebfr["rmse"]
        assert m["max"] <= 0.5 * dt["max"]
        assert m["truth"] <= 0.5 * tmpl["truth"]
    else:                                                             # scan regime: judge against truth
        assert m["truth"] <= 0.9 * tmpl["truth"]
        assert m["truth"] < dt["truth"] and m["truth"] < ebfr["truth"]


def scaled_capture(capture, s):
    from usdface.model import Capture, FaceRig, Frames

    t, f = capture.template, capture.frames
    return Capture(capture.neutral * s, capture.triangles,
                   FaceRig(t.neutral * s, t.triangles, t.names, t.deltas * s),
                   Frames(f.points * s, f.weights, f.role, f.label), capture.names)


@pytest.mark.parametrize("method", ["ebfr", "menzel", "dt"])
def test_methods_are_unit_invariant(samples, method):
    """Centimetre input gives the metre result x 100 (EBFR's constants are unit-free here)."""
    cap = read_capture(samples / "capture.usda")
    kw = {"method": method} if method != "menzel" else {"method": method, "reg": 0.01}
    a = fit_personalized_shapes(cap, **kw).rig.deltas
    b = fit_personalized_shapes(scaled_capture(cap, 100.0), **kw).rig.deltas
    assert np.abs(b / 100.0 - a).max() < 1e-6 * np.abs(a).max() + 1e-12


def test_transferred_blinks_close_with_virtual_eyelid_triangles(samples):
    """Menzel sec. 3.2: with the virtual eyelid triangles the transferred blink closes the eye opening as the
    template's blink does (closer to the template's closure ratio than without them)."""
    from usdface.mesh import boundary_loops
    from usdface.personalize.dt import _loop_area, eyelid_triangles

    cap = read_capture(samples / "capture.usda")
    t = cap.template
    lids = eyelid_triangles(t.neutral, t.deltas, cap.triangles, cap.names)
    assert len(lids) > 0
    k = cap.names.index("eyeBlinkLeft")
    eye = np.unique(lids)
    loops = [lp for lp in boundary_loops(cap.triangles, len(cap.neutral)) if np.isin(lp, eye).all()]
    assert len(loops) == 2                                            # both eyes, not the mouth

    def closure(neutral, delta):
        return min(_loop_area(neutral + delta, lp) / _loop_area(neutral, lp) for lp in loops)

    target = closure(t.neutral, t.deltas[k])
    blinks = [fit_personalized_shapes(cap, method="dt", eyelids=e).rig.deltas[k] for e in (False, True)]
    err = [abs(closure(cap.neutral, b) - target) for b in blinks]
    assert err[1] <= err[0]
