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
from usdface.personalize.takefit import balanced_frame_weights, unique_excitation, weight_noise
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


def test_weight_noise_is_the_jitter_not_the_motion():
    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 20.0, 1500)[:, None]
    smooth = 0.5 + 0.4 * np.sin(t * np.linspace(0.5, 2.0, 8)[None])    # 8 shapes moving at 15-60 frames/cycle
    assert weight_noise(smooth) < 0.002                                 # smooth motion: ~no noise
    noisy = smooth + rng.normal(scale=0.02, size=smooth.shape)
    assert weight_noise(noisy) == pytest.approx(0.02, rel=0.1)
    assert np.isnan(weight_noise(noisy[:2]))


def test_unique_excitation_sees_coupled_and_never_performed_shapes():
    rng = np.random.default_rng(4)
    F = 1000
    w = np.zeros((F, 4))
    w[100:200, 0] = np.sin(np.linspace(0, np.pi, 100)) * 0.9           # shape 0 performed
    w[:, 1] = 0.3 * w[:, 0]                                             # shape 1 only as 0's fixed cross-talk
    w[500:600, 2] = np.sin(np.linspace(0, np.pi, 100)) * 0.8            # shape 2 performed on its own
    sigma = 0.02
    noisy = np.clip(w + rng.normal(scale=sigma, size=w.shape), 0.0, 1.0)  # shape 3: noise only
    e = unique_excitation(noisy, sigma)
    assert e[2] == pytest.approx(np.sqrt(np.sum(w[:, 2] ** 2) - F * sigma ** 2), rel=0.1)
    assert e[3] < 0.1 * e[2]                                            # never performed
    assert e[0] < 0.25 * e[2] and e[1] < 0.25 * e[2]                    # only their sum is measured
    exact = unique_excitation(w[:, :3], 0.0)                            # an exactly collinear pair: 0
    assert exact[0] < 1e-3 and exact[1] < 1e-3 and exact[2] == pytest.approx(np.linalg.norm(w[:, 2]))


@pytest.mark.slow
def test_whole_take_keeps_shapes_it_never_performs_generic():
    """A whole take in which the person never performs cheekPuff and jawLeft (seen only as cross-talk and
    the phone's noise, 0.02): both stay the avatar's generic shape instead of landing up to 0.7 mm worse
    (their trust was 1.0 from the total training energy of 1,000 frames of cross-talk), and the seam stays
    below the generic's."""
    import json
    from pathlib import Path

    from usdface.api import read_avatar, read_capture
    from usdface.io.take import capture_from_whole_take
    from usdface.model import FaceRig
    from usdface.sample import covered_vertices
    from usdface.transfer import personalize_avatar
    from usdface.transfer.scoring import score_mesh

    root = Path(__file__).resolve().parents[1] / "sample_assets"
    avatar, capture = read_avatar(root / "avatar.usda"), read_capture(root / "capture.usda")
    ct = np.load(root / "truth" / "capture_truth.npz")
    person = FaceRig(ct["neutral"], capture.triangles, [str(n) for n in ct["names"]], ct["deltas"])
    skip = ["cheekPuff", "jawLeft"]
    take, _ = make_take(person, capture.template.subset(person.names), skip=skip, point_noise=1e-4,
                        weight_noise=0.02, seed=2, fps=15)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = personalize_avatar(avatar, capture_from_whole_take(take), None)
    assert res.report["excitation"]["weight_noise"] == pytest.approx(0.0125, abs=0.003)  # 0.02, half clipped
    for name in skip:
        assert res.report["shape_confidence"][name] < 0.1
    head = avatar.mesh("Head")
    npz = np.load(root / "truth" / "avatar_truth.npz")
    truth = np.array([npz[f"Head/{n}"] for n in head.names]) @ head.source.to_internal[:3, :3].T
    meta = json.loads((root / "truth" / "meta.json").read_text())
    face = covered_vertices(head.neutral, meta, ct["neutral"], capture.triangles)
    sc = score_mesh(head.names, head.deltas, res.offsets[head.source.prim], truth, face=face,
                    triangles=head.triangles)
    for name in skip:
        assert sc.per_shape_delta[head.names.index(name)] <= 0.05            # mm, never worse than generic


def test_a_take_folder_with_fewer_frames_than_rows_says_how_it_pairs_them(tmp_path):
    """User trial: a take folder whose first frame OBJ was missing paired every later mesh with the previous
    frame's weights, silently (truth error 0.002 -> 3.78 mm). Frames and rows that do not match in number
    are now said, with the pairing used and the gaps."""
    from usdface.io.take import read_take, write_take_folder

    person, template = grid_rigs(seed=5)
    take, _ = make_take(person, template, sweep_seconds=0.2, rest_seconds=0.1, seed=1, fps=10)
    folder = write_take_folder(take, tmp_path / "take")
    frames = sorted((folder / "frames").glob("*.obj"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_take(folder)                                # complete: no warning
    frames[0].unlink()
    frames[5].unlink()
    with pytest.warns(UserWarning, match=r"OBJ frames for \d+ rows .*frame 1 read as row 0.*missing after 4"):
        read_take(folder)
    # a frame missing inside the take: every other mesh keeps its own row's weights *and time*
    whole = read_take(write_take_folder(take, tmp_path / "take2"))
    sorted((tmp_path / "take2" / "frames").glob("*.obj"))[5].unlink()
    with pytest.warns(UserWarning, match="missing after 4"):
        gap = read_take(tmp_path / "take2")
    np.testing.assert_array_equal(gap.times, np.delete(whole.times, 5))
    np.testing.assert_array_equal(gap.weights, np.delete(whole.weights, 5, axis=0))
    np.testing.assert_array_equal(gap.points, np.delete(whole.points, 5, axis=0))


@pytest.mark.parametrize("block", [4, 9], ids=["block-below-rank", "block-above-rank"])
def test_leave_block_out_residuals_are_refits_without_the_block(block):
    """:meth:`PositionFit._block_residuals` (the b x b system, or the r x r Woodbury form for a block longer
    than the weights' rank) is the fit on the other frames predicting the block, for every block and reg."""
    from usdface.personalize.fit import PositionFit, regularization_weights

    rng = np.random.default_rng(7)
    F, K, n = 31, 6, 5
    neutral = rng.normal(size=(n, 3))
    generic = rng.normal(size=(K, n, 3)) * 0.1
    weights = rng.random((F, K))
    points = neutral + np.einsum("fk,knc->fnc", weights, generic * 1.3) + rng.normal(size=(F, n, 3)) * 0.01
    D = regularization_weights(generic)
    regs = np.array([1e-3, 0.1, 3.0])
    pf = PositionFit(neutral, points, weights, generic, D, block=block)
    d, _ = pf._loo_parts(regs, pf.c, pf.e0n)
    got = pf._block_residuals(regs, d)                                            # [n,F,3,G]
    for lo in range(0, F, block):
        keep = np.r_[0:lo, min(lo + block, F):F]
        sub = PositionFit(neutral, points[keep], weights[keep], generic, D)
        for g, reg in enumerate(regs):
            b = sub.solve(reg)                                                    # [K,n,3]
            want = points[lo:lo + block] - neutral - np.einsum("fk,knc->fnc", weights[lo:lo + block], b)
            np.testing.assert_allclose(got[:, lo:lo + block, :, g], want.transpose(1, 0, 2), rtol=1e-6,
                                       atol=1e-10)


def test_correlation_frames_is_a_poses_duration():
    """Poses held for 12 frames (with a little noise): the weight curves decorrelate after about a pose;
    white noise decorrelates at once; the CV block is the half-correlation time, at most a fifth of the
    take."""
    from usdface.personalize.takefit import correlation_frames, cv_block

    rng = np.random.default_rng(3)
    poses = np.repeat(rng.random((40, 8)), 12, axis=0) + rng.normal(size=(480, 8)) * 0.01
    assert 8 <= correlation_frames(poses) <= 12
    assert correlation_frames(rng.normal(size=(480, 8))) == 1
    assert cv_block(rng.normal(size=(480, 8))) == 1
    assert cv_block(poses) == correlation_frames(poses, 0.5) < correlation_frames(poses)
    assert cv_block(poses[:40]) <= 8



def _short_sample_take(samples):
    """A short take (10 fps, quick sweeps) of the sample's person: ``(take, person rig, names)``."""
    from usdface.io import read_capture
    from usdface.model import FaceRig

    capture = read_capture(samples / "capture.usda")
    ct = np.load(samples / "truth" / "capture_truth.npz")
    names = [str(n) for n in ct["names"]]
    person = FaceRig(ct["neutral"], capture.triangles, names, ct["deltas"])
    take, _ = make_take(person, capture.template.subset(names), seed=1, fps=10, sweep_seconds=0.3,
                        rest_seconds=0.1)
    return take, person, names


def test_a_take_of_one_held_pose_is_refused_before_any_work(samples, tmp_path, capsys):
    """600 frames of one expression (jawOpen 0.7 + mouthSmileLeft 0.5, the phone's jitter on it): the fit
    gave that pose's motion to both shapes in full (trust 1.0) and the avatar came out 2.3x further from the
    person than the generic one, mouthSmileLeft 4.8 mm worse (a user trial). Refused on reading, naming the
    count of distinct poses; ``--every`` that leaves one frame is refused the same way."""
    import dataclasses

    from usdface.cli import main
    from usdface.io.take import write_take_usd
    from usdface.personalize.takefit import distinct_poses

    take, person, names = _short_sample_take(samples)
    rng = np.random.default_rng(0)
    pose = np.zeros(len(take.names))
    pose[take.names.index("jawOpen")], pose[take.names.index("mouthSmileLeft")] = 0.7, 0.5
    weights = np.clip(pose + rng.normal(0.0, 0.005, (120, len(pose))), 0.0, 1.0)
    order = [names.index(n) for n in take.names]
    points = person.neutral + np.einsum("fk,knc->fnc", np.tile(pose, (120, 1)), person.deltas[order])
    held = dataclasses.replace(take, weights=weights, points=points, times=np.arange(120) / 30.0)
    assert distinct_poses(held.weights) < 1.5 and distinct_poses(take.weights) > 10
    write_take_usd(held, tmp_path / "held.usdc")
    write_take_usd(take, tmp_path / "take.usdc")
    out = tmp_path / "o.usda"
    for argv in (["personalize", str(samples / "avatar.usda"), str(tmp_path / "held.usdc"), "-o", str(out)],
                 ["fit", str(tmp_path / "take.usdc"), "-o", str(out), "--every", "100000"]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "distinct pose(s)" in err and "too few to tell its shapes apart" in err, err
        assert not out.exists()
    assert "use a smaller --every: the whole take shows" in err                 # the last: --every


def test_a_nan_in_a_usd_takes_points_names_the_point_and_time(samples, tmp_path, capsys):
    """A NaN in one frame of a USD take: it was first called 'points edited after import' (NaN != NaN in the
    exact-twin comparison), then refused without saying where (a user trial)."""
    import dataclasses

    from usdface.cli import main
    from usdface.io.take import write_take_usd

    take, person, names = _short_sample_take(samples)
    points = take.points.copy()
    points[30, 7] = np.nan
    write_take_usd(dataclasses.replace(take, points=points), tmp_path / "nan.usdc")
    assert main(["fit", str(tmp_path / "nan.usdc"), "-o", str(tmp_path / "r.usda")]) == 2
    out = capsys.readouterr()
    assert "NaN or infinite values (point 7 at time 30)" in out.err, out.err
    assert "edited after import" not in out.out + out.err


def test_evaluate_says_when_its_test_frames_show_no_expression(samples):
    """``capture select --test-every 10`` on a take can hold out only rests: every method then scores the
    same (a user trial: six methods at 0.408 mm) and the table means nothing; evaluate says so."""
    import dataclasses

    from usdface import api
    from usdface.io import read_capture
    from usdface.model import Frames

    capture = read_capture(samples / "capture.usda")
    test = np.array([r == "test" for r in capture.frames.role])
    weights = capture.frames.weights.copy()
    weights[test] *= 0.05                                          # the held-out frames: rests
    points = capture.frames.points.copy()
    points[test] = capture.neutral
    rest = dataclasses.replace(capture, frames=Frames(points, weights, capture.frames.role,
                                                      capture.frames.label))
    with pytest.warns(UserWarning, match="test frames show no expression"):
        api.evaluate_methods(rest, ["dt"])
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        warnings.filterwarnings("ignore", message="(?!.*test frames show no expression)")
        api.evaluate_methods(capture, ["dt"])                      # the capture's own: expressions


def test_the_prior_choice_measures_a_takes_standard_error_by_batch_means():
    """Per-frame errors of a take are correlated over a pose's frames: ``std / sqrt(F)`` understates the
    standard error of their mean (2.3x on the sample's take, a review); batch means over the weights'
    correlation time give the right one, within its own sampling error, on a series of known error."""
    from usdface.personalize.api import _standard_error_of_mean

    rng = np.random.default_rng(5)
    poses, hold = 200, 12
    weights = np.repeat(rng.random((poses, 6)), hold, axis=0) + rng.normal(size=(poses * hold, 6)) * 0.01
    errors = []
    naive = []
    for _ in range(200):
        series = np.repeat(rng.normal(size=poses), hold)                # one error per pose, held
        errors.append(series.mean())
        naive.append(series.std(ddof=1) / np.sqrt(series.size))
        se = _standard_error_of_mean(series, weights)
    true_se = float(np.std(errors))                                        # 1 / sqrt(200) = 0.071
    assert abs(se - true_se) < 0.35 * true_se
    assert np.mean(naive) < 0.35 * true_se                                 # the plain formula: ~1/sqrt(12)


@pytest.mark.slow
def test_retarget_says_which_rows_follow_a_shape_the_take_never_shows(tmp_path):
    """The map of a take that never performs cheekPuff mapped it to mouthRollLower (0.61) over its namesake
    (0.17) without a word, where personalize keeps cheekPuff generic (a user trial). The map is unchanged;
    retarget now says which rows follow such a fit, with their strongest entry."""
    from pathlib import Path

    from usdface import api, read_avatar, read_capture
    from usdface.io.take import capture_from_whole_take
    from usdface.model import FaceRig

    root = Path(__file__).resolve().parents[1] / "sample_assets"
    avatar, capture = read_avatar(root / "avatar.usda"), read_capture(root / "capture.usda")
    ct = np.load(root / "truth" / "capture_truth.npz")
    person = FaceRig(ct["neutral"], capture.triangles, [str(n) for n in ct["names"]], ct["deltas"])
    take, _ = make_take(person, capture.template, skip=["jawLeft", "cheekPuff"], fps=15, weight_noise=0.02,
                        seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = api.write_retarget_map(avatar, capture_from_whole_take(take), tmp_path / "map.json")
    row = res.weights[res.names.index("cheekPuff")]
    assert res.avatar_names[int(np.argmax(row))] != "cheekPuff"      # the case: another shape dominates
    said = [w for w in res.report["warnings"] if w.startswith("map rows of shapes the capture barely shows")]
    assert said and "cheekPuff -> " in said[0] and "(cheekPuff 0.1" in said[0]


def test_a_pose_at_exactly_the_radius_is_a_neighbour():
    """``pose_counts`` counts the frames *within* ``radius`` (RMS over the weights), the radius itself
    included: three poses 0.25 apart (RMS; binary-exact values) at radius 0.25 are each the neighbours of the
    next, the ends 0.5 apart are not."""
    from usdface.personalize.takefit import pose_counts

    W = np.array([[0.0, 0.0], [0.25, 0.25], [0.5, 0.5]])
    np.testing.assert_array_equal(pose_counts(W, 0.25), [2, 3, 2])
    np.testing.assert_array_equal(pose_counts(W, 0.2), [1, 1, 1])


def test_a_takes_cv_block_keeps_at_least_min_folds_blocks():
    """``cv_block``: the weights' half-correlation time, but at most ``F // MIN_FOLDS`` frames (at least
    MIN_FOLDS blocks to hold out): one steady sweep over 12 frames stays correlated over 3 of them, so its
    blocks are 12 // 5 = 2 frames; over 30 frames (6) the cap is not reached."""
    from usdface.personalize.takefit import HALF_CORRELATION, MIN_FOLDS, correlation_frames, cv_block

    short, long = np.arange(12.0)[:, None], np.arange(30.0)[:, None]
    assert correlation_frames(short, HALF_CORRELATION) == 3
    assert cv_block(short) == 12 // MIN_FOLDS == 2
    assert correlation_frames(long, HALF_CORRELATION) == cv_block(long) == 6
