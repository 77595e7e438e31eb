"""Continuous takes (issue 6): Menzel 3.1 frame selection finds the true peaks, reports never-triggered
shapes, and the fit from selected frames equals the fit from hand-picked frames. Takes round-trip through USD
and OBJ sequence + Live Link CSV."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from input_helpers import _livelink_csv

from usdface.arkit import ARKIT_NAMES
from usdface.cli import main
from usdface.errors import CaptureError
from usdface.io import read_capture
from usdface.io.take import capture_from_take, read_take, write_take_folder, write_take_usd
from usdface.model import Capture, FaceRig, Frames
from usdface.sample.take import make_take
from usdface.take_select import format_coverage, select_frames

SKIP = ["jawLeft", "cheekPuff"]  # ARKit order

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


def grid_rigs(n=9, seed=0):
    """A curved grid 'face', all 52 ARKit shapes as smooth bumps -> (person's true rig, generic template)."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(-0.05, 0.05, n), np.linspace(-0.05, 0.05, n))
    neutral = np.stack([u.ravel(), v.ravel(), 0.05 - 8 * (u.ravel() ** 2 + v.ravel() ** 2)], axis=1)
    q = np.arange(n * n).reshape(n, n)[:-1, :-1].ravel()
    tris = np.concatenate([np.stack([q, q + 1, q + n], 1), np.stack([q + 1, q + n + 1, q + n], 1)])
    centres = rng.uniform(-0.04, 0.04, size=(52, 2))
    falloff = np.exp(-((neutral[None, :, :2] - centres[:, None]) ** 2).sum(-1) / (2 * 0.015 ** 2))
    direction = rng.normal(size=(52, 1, 3)) * 0.004
    template = FaceRig(neutral, tris, list(ARKIT_NAMES), falloff[..., None] * direction, name="template")
    person_deltas = template.deltas * rng.uniform(0.7, 1.4, size=(52, 1, 1)) + falloff[..., None] * 0.001
    person = FaceRig(neutral + 0.002 * np.sin(20 * neutral), tris, list(ARKIT_NAMES), person_deltas)
    return person, template


@pytest.fixture(scope="module")
def generated():
    person, template = grid_rigs()
    take, truth = make_take(person, template, skip=SKIP, seed=3)
    return take, truth, person


def test_rule_on_hand_made_weights():
    w = np.zeros((40, 3))
    w[2:9, 0] = [0.2, 0.6, 0.9, 0.9, 0.9, 0.4, 0.1]      # plateau: the middle frame (5)
    w[20:25, 0] = [0.3, 0.7, 0.8, 0.5, 0.1]              # a second, lower peak at 22
    w[30:35, 1] = [0.1, 0.3, 0.5, 0.3, 0.1]              # reaches exactly 0.5: not above the threshold
    w[35:40, 2] = [0.2, 0.4, 0.6, 0.8, 0.9]              # still rising when the take ends: no peak
    w[5, 1] = 0.3                                         # rival of shape 0 at its peak
    sel = select_frames(w, names=["a", "b", "c"], min_separation=5)
    assert sel.train.tolist() == [5] and sel.missing == ["b", "c"]
    a = sel.shapes[0]
    assert a.frames == [5] and a.peak == [0.9] and a.rival == ["b"] and a.dominance == [pytest.approx(0.6)]
    two = select_frames(w, names=["a", "b", "c"], per_shape=2, min_separation=5)
    assert two.shapes[0].frames == [5, 22] and two.train.tolist() == [5, 22]
    merged = select_frames(w, names=["a", "b", "c"], per_shape=2, min_separation=30)
    assert merged.shapes[0].frames == [5]  # peaks closer than min_separation count once
    low = select_frames(w, names=["a", "b", "c"], threshold=0.45, min_separation=5)
    assert low.shapes[1].frames == [32]
    text = format_coverage(sel)
    assert "never triggered (record again): b, c" in text and "max 0.50" in text


def test_test_split_stays_away_from_training_frames():
    w = np.zeros((200, 2))
    w[30:81, 0] = np.sin(np.linspace(0, np.pi, 51))           # expressions longer than the separation
    w[100:151, 1] = np.sin(np.linspace(0, np.pi, 51))
    sel = select_frames(w, names=["a", "b"], test_every=4, min_separation=15)
    assert sel.train.tolist() == [55, 125]
    assert len(sel.test) > 5 and np.abs(sel.test[:, None] - sel.train[None]).min() >= 15
    assert not set(sel.test.tolist()) & set(sel.train.tolist())


@pytest.mark.parametrize("kwargs", [{"weights": np.zeros(5)}, {"weights": np.full((5, 2), np.nan)},
                                    {"weights": np.zeros((5, 2)), "names": ["a"]},
                                    {"weights": np.zeros((5, 2)), "per_shape": 0}])
def test_bad_input(kwargs):
    with pytest.raises(CaptureError):
        select_frames(**kwargs)


def test_selected_frames_are_the_true_peaks(generated):
    take, truth, _ = generated
    sel = select_frames(take.weights, names=take.names, threshold=0.5, min_separation=int(0.5 * take.fps))
    chosen = {s.name: s.frames for s in sel.shapes if s.triggered}
    assert chosen == {name: [f] for name, f in truth.peak_frames.items()}
    assert sel.missing == SKIP == truth.skipped
    # cross-talk is real (mirror partners move 20-45%), yet every chosen frame is dominated by its shape
    assert truth.cross_talk.max() > 0.2 and min(s.dominance[0] for s in sel.shapes if s.triggered) > 0.2
    assert "never triggered (record again): jawLeft, cheekPuff" in format_coverage(sel, take.times)


def hand_picked_capture(take, truth, template) -> Capture:
    idx = [truth.peak_frames[n] for n in take.names if n in truth.peak_frames]
    labels = [f"{m:03d}_{n}" for m, n in enumerate(n for n in take.names if n in truth.peak_frames)]
    frames = Frames(take.points[idx], take.weights[idx], ["train"] * len(idx), labels)
    return Capture(take.neutral, take.triangles, template, frames, list(template.names))


def test_fit_from_selected_frames_matches_hand_picked(generated):
    from usdface.personalize import fit_personalized_shapes

    take, truth, person = generated
    sel = select_frames(take.weights, names=take.names, min_separation=15)
    selected = capture_from_take(take, sel)
    hand = hand_picked_capture(take, truth, take.template)
    assert selected.metadata["never_triggered"] == SKIP
    with pytest.warns(UserWarning):  # the two skipped shapes are never activated in training
        fit_sel = fit_personalized_shapes(selected, method="menzel", reg=0.01, eyelids=False)
    with pytest.warns(UserWarning):
        fit_hand = fit_personalized_shapes(hand, method="menzel", reg=0.01, eyelids=False)
    np.testing.assert_allclose(fit_sel.rig.deltas, fit_hand.rig.deltas, atol=1e-12)
    # and the fit is a real personalization: closer to the person's true shapes than the generic template
    swept = [take.names.index(n) for n in truth.swept]
    err = lambda d: np.sqrt(np.mean((d[swept] - person.deltas[swept]) ** 2))  # noqa: E731
    assert err(fit_sel.rig.deltas) < 0.5 * err(take.template.deltas)  # measured ~0.07 vs 0.30 mm


def test_usd_take_round_trip_and_cli_select(generated, tmp_path, capsys):
    take, truth, _ = generated
    path = write_take_usd(take, tmp_path / "take.usda")
    got = read_take(path)
    np.testing.assert_array_equal(got.points, take.points)
    np.testing.assert_array_equal(got.weights, take.weights)
    np.testing.assert_allclose(got.times, take.times, atol=1e-9)
    np.testing.assert_array_equal(got.neutral, take.neutral)
    assert got.names == take.names and got.template.names == take.template.names
    out = tmp_path / "capture.usda"
    # (takes.md's options: the generated sweeps last 1 s, so frames 0.5 s from their peaks are rests, never
    # held out since stop 52)
    assert main(["capture", "select", str(path), "-o", str(out), "--test-every", "10", "--min-separation",
                 "0.2"]) == 0
    printed = capsys.readouterr().out
    assert "jawLeft" in printed and "cheekPuff" in printed and "never triggered" in printed
    cap = read_capture(out)
    peak = [truth.peak_frames[n] for n in take.names if n in truth.peak_frames]
    np.testing.assert_array_equal(cap.train.points, take.points[peak])
    np.testing.assert_array_equal(cap.train.weights, take.weights[peak])
    assert cap.train.label[0] == "000_eyeBlinkLeft" and len(cap.test) > 10


def test_obj_sequence_with_livelink_csv(tmp_path):
    person, template = grid_rigs(n=5)
    names = ["eyeBlinkLeft", "eyeBlinkRight", "jawOpen", "mouthSmileLeft"]
    take, truth = make_take(person.subset(names), template.subset(names), seed=5, rest_seconds=0.2)
    folder = write_take_folder(take, tmp_path / "take")
    got = read_take(folder)
    np.testing.assert_array_equal(got.points, take.points)
    np.testing.assert_array_equal(got.weights, take.weights)  # CSV written with repr: exact
    np.testing.assert_allclose(got.times, take.times, atol=1e-9)
    (folder / "frames" / f"{len(take) - 1:05d}.obj").unlink()  # fewer OBJs than rows: matched by number
    assert len(read_take(folder)) == len(take) - 1
    out = tmp_path / "cap"
    assert main(["capture", "select", str(folder), "-o", str(out), "--min-separation", "0.3"]) == 0
    cap = read_capture(out)
    np.testing.assert_array_equal(cap.train.points, take.points[[truth.peak_frames[n] for n in names]])


def test_take_without_template_or_mesh(tmp_path, generated):
    take, _, _ = generated
    bare = type(take)(take.weights, take.names, take.times, take.points, take.triangles)
    sel = select_frames(take.weights, names=take.names)
    with pytest.raises(CaptureError, match="template"):
        capture_from_take(bare, sel)
    with pytest.warns(UserWarning, match="no neutral"):
        cap = capture_from_take(bare, sel, template=take.template)
    assert take.weights[cap.metadata["neutral_frame"]].max() < 0.05
    weights_only = type(take)(take.weights, take.names, take.times)
    with pytest.raises(CaptureError, match="weights only"):
        capture_from_take(weights_only, sel)


def test_generic_usd_take_with_skel_animation(tmp_path):
    """A take authored by another tool: any Mesh with time-sampled points + a SkelAnimation (raw ARKit names,
    centimetres, Z up)."""
    from pxr import Usd, UsdGeom, Vt

    from usdface.io.usd_anim import author_skel_animation

    person, _ = grid_rigs(n=4)
    rng = np.random.default_rng(2)
    w = rng.random((6, 2))
    pts = person.subset(["eyeBlinkLeft", "jawOpen"]).evaluate(w)
    path = tmp_path / "other.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    mesh = UsdGeom.Mesh.Define(stage, "/World/Face")
    stage.SetDefaultPrim(stage.GetPrimAtPath("/World"))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(person.triangles)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(person.triangles.ravel().tolist()))
    to_cm_zup = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]) * 100  # inverse of the reader's conversion
    codes = 10 + 2 * np.arange(6)
    for f in range(6):
        authored = (pts[f] @ to_cm_zup.T).astype(np.float32)
        mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(authored), float(codes[f]))
    author_skel_animation(stage, "/World/Anim", ["eyeBlink_L", "jawOpen"], w, 24, times=codes / 24)
    stage.SetFramesPerSecond(30)                 # played at 30: the time codes still count 24 per second
    stage.Save()
    take = read_take(path)
    assert take.names == ["eyeBlinkLeft", "jawOpen"] and take.metadata["weights_source"] == "/World/Anim"
    np.testing.assert_allclose(take.weights, w, atol=1e-7)
    np.testing.assert_allclose(take.points, pts, atol=1e-6)  # back to metres, Y up
    np.testing.assert_allclose(take.times, np.arange(6) * 2 / 24)
    assert take.template is None and take.neutral is None


def test_a_weights_only_usd_take_counts_its_times_from_its_first_sample(tmp_path):
    """A SkelAnimation alone (a take another tool wrote, or a shot's animation from frame 1001) is a take
    whose times start at 0 at its first sample and count the stage's timeCodesPerSecond, whatever rate the
    stage plays at."""
    from pxr import Usd

    from usdface.io.usd_anim import author_skel_animation

    w = np.random.default_rng(3).random((5, 2))
    path = tmp_path / "anim.usda"
    stage = Usd.Stage.CreateNew(str(path))
    author_skel_animation(stage, "/Anim", ["jawOpen", "eyeBlinkLeft"], w, 24, times=np.arange(5) * 2 / 24,
                          start_time_code=1001)
    stage.SetFramesPerSecond(30)
    stage.Save()
    take = read_take(path)
    np.testing.assert_allclose(take.weights, w, atol=1e-7)
    np.testing.assert_allclose(take.times, np.arange(5) * 2 / 24, rtol=0, atol=1e-12)


@pytest.mark.slow
def test_sample_assets_take_acceptance(samples):
    """Issue 6 acceptance on the project's own sample person: a take swept from the sample's TRUE blendshapes
    (template = the sample capture's generic rig): the selected frames are the true peaks, skipped shapes are
    reported by name, and the fit from the selected frames equals the fit from the hand-picked frames."""
    import warnings

    from usdface.io.usd_capture import read_capture_usd
    from usdface.personalize import fit_personalized_shapes

    truth = np.load(samples / "truth" / "capture_truth.npz")
    capture = read_capture_usd(samples / "capture.usda")
    names = [str(n) for n in truth["names"]]
    person = FaceRig(truth["neutral"], capture.triangles, names, truth["deltas"])
    take, tt = make_take(person, capture.template.subset(names), skip=["mouthRollUpper", "tongueOut"], fps=20,
                         seed=11)
    sel = select_frames(take.weights, names=take.names, min_separation=15)
    assert {s.name: s.frames[0] for s in sel.shapes if s.triggered} == tt.peak_frames
    assert sel.missing == ["mouthRollUpper", "tongueOut"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the skipped shapes are never activated in training
        fit_sel = fit_personalized_shapes(capture_from_take(take, sel), method="menzel", reg=0.002)
        fit_hand = fit_personalized_shapes(hand_picked_capture(take, tt, take.template), method="menzel",
                                           reg=0.002)
    np.testing.assert_array_equal(fit_sel.rig.deltas, fit_hand.rig.deltas)
    swept = [names.index(n) for n in tt.swept]
    err = lambda d: np.sqrt(np.mean((d[swept] - truth["deltas"][swept]) ** 2))  # noqa: E731
    assert err(fit_sel.rig.deltas) < 0.5 * err(take.template.deltas)  # measured 0.11 vs 0.56 mm



def test_test_frames_are_expressions_not_rests():
    """The default test-frame rule took every K-th frame away from the training frames, rests included: a
    take of expressions held between rests gave test frames with every weight ~0, on which every fitting
    method predicts the neutral (eq. 5 cannot tell them apart). The rule counts only frames that show an
    expression (a weight of at least ``REST_WEIGHT``): every test frame does, and every K-th of those is
    held out, spread over the take."""
    from usdface.take_select import REST_WEIGHT, select_frames

    t = np.arange(600)
    w = np.zeros((600, 3))
    for k, centre in enumerate((100, 300, 500)):               # three expressions held ~2 s among rests
        w[:, k] = 0.8 * np.exp(-0.5 * ((t - centre) / 25.0) ** 4)
    sel = select_frames(w, test_every=10, min_separation=15)
    assert sel.train.tolist() == [100, 300, 500]
    expressive = (w.max(axis=1) >= REST_WEIGHT) & (np.abs(t[:, None] - sel.train).min(axis=1) >= 15)
    assert len(sel.test) == int(np.ceil((expressive.sum() - 5) / 10))  # every 10th of them, from the 5th
    assert w[sel.test].max(axis=1).min() >= REST_WEIGHT, w[sel.test].max(axis=1)
    assert set(np.argmax(w[sel.test], axis=1).tolist()) == {0, 1, 2}   # around each expression


def test_held_out_rests_are_warned_about_with_evaluates_fix():
    """User trial: 'capture select --test-every 10' held out 71 frames, all rests (largest weight 0.02);
    'evaluate' then said the table cannot tell the methods apart and suggested other options. The selection
    says so itself, with the same fix; since stop 52 it holds out no rest, so there is no test frame."""
    import warnings

    from usdface.take_select import REST_FIX, select_frames

    t = np.arange(300)
    w = np.zeros((300, 2))
    w[:, 0] = np.exp(-0.5 * ((t - 80) / 4.0) ** 2)          # two short expressions in a take of rests
    w[:, 1] = np.exp(-0.5 * ((t - 220) / 4.0) ** 2)
    with pytest.warns(UserWarning, match="show no expression") as said:
        sel = select_frames(w, test_every=10, min_separation=15)
    assert REST_FIX in str(said[0].message) and len(sel.test) == 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")                       # test frames near the expressions: no warning
        sel = select_frames(w, test_every=2, min_separation=3)
    assert len(sel.test) and w[sel.test].max(axis=1).min() >= 0.15


def test_one_frame_usd_take_keeps_its_mesh_and_says_why_it_has_no_peak(generated, tmp_path, capsys):
    """A take of one frame written by ``write_take_usd`` was read as weights only ('a take of weights only
    (no meshes): nothing to fit' from fit, personalize and inspect), and ``capture select`` said 'no shape
    peaks above --threshold 0.5 (the highest peak: ... 0.81)' with the fix 'lower --threshold', which cannot
    help: a weight held at the take's end is no peak (a user trial)."""
    import dataclasses

    take, truth, _ = generated
    frame = truth.peak_frames["jawOpen"]
    one = dataclasses.replace(take, weights=take.weights[frame:frame + 1], times=take.times[frame:frame + 1],
                              points=take.points[frame:frame + 1])
    path = write_take_usd(one, tmp_path / "one.usda")
    got = read_take(path)
    assert got.points is not None and got.points.shape == (1, *take.points.shape[1:])
    np.testing.assert_array_equal(got.points[0], take.points[frame])
    assert main(["fit", str(path), "-o", str(tmp_path / "rig.usda"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "weights only" not in err and "distinct pose" in err
    assert main(["capture", "select", str(path), "-o", str(tmp_path / "c.usda")]) == 2
    err = capsys.readouterr().err
    assert "still rising or held at the take's end (1 frame(s))" in err and "lower --threshold" not in err
    assert not (tmp_path / "c.usda").exists() and not (tmp_path / "rig.usda").exists()


def test_select_names_the_arkit_shapes_a_take_has_no_weights_for(generated, tmp_path, capsys):
    """A take folder whose Live Link CSV lacks the ``JawOpen`` column: ``capture select`` printed a coverage
    table of 51 shapes and '50/51 shapes triggered', and jawOpen appeared nowhere (``anim import`` of the
    same CSV says 'missing shapes: jawOpen'); a user trial."""
    import csv

    take, _, _ = generated
    folder = write_take_folder(take, tmp_path / "take dir")
    table = folder / "take.csv"
    rows = list(csv.reader(table.open()))
    col = rows[0].index("JawOpen")
    with table.open("w", newline="") as f:
        csv.writer(f).writerows([r[:col] + r[col + 1:] for r in rows])
    assert main(["capture", "select", str(folder)]) == 0
    said = capsys.readouterr()
    assert "the take has no weights for 1 ARKit shape(s): jawOpen" in said.out + said.err
    assert main(["capture", "select", str(folder), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["not_in_take"] == ["jawOpen"] and any("jawOpen" in w for w in doc["warnings"])


def test_inspect_a_one_frame_take_gives_no_rate(generated, tmp_path, capsys):
    """``inspect`` of a one-frame take said 'a take of 1 frames at 30 fps' (30: the default of a take with
    no frame interval, not the take's rate; a user trial)."""
    import dataclasses

    take, _, _ = generated
    one = dataclasses.replace(take, weights=take.weights[:1], times=take.times[:1], points=take.points[:1])
    path = write_take_usd(one, tmp_path / "one.usda")
    assert main(["inspect", str(path)]) == 0
    out = capsys.readouterr().out
    assert "a take of 1 frame (no rate)" in out and "30 fps" not in out


def test_select_on_a_take_of_no_arkit_channel_says_so_in_one_line(tmp_path, capsys):
    """Blender's 'Key_1' take: the warning of ARKit shapes without weights listed all 52 names; a take none
    of whose channels is an ARKit shape is told as that, naming its own channels."""
    from usdface.io.usd_anim import write_animation_usd

    weights = np.array([[0.0, 0.0], [0.6, 0.1], [0.9, 0.2], [0.4, 0.7], [0.0, 0.9], [0.0, 0.1]])
    path = tmp_path / "keys.usda"
    write_animation_usd(path, ["Key_1", "Key_2"], weights, np.arange(6) / 30.0)
    assert main(["capture", "select", str(path)]) == 0
    said = capsys.readouterr()
    text = said.out + said.err
    assert "none of the take's 2 weight channel(s) ('Key_1', 'Key_2') is an ARKit shape" in text
    assert "eyeLookDownLeft" not in text


def test_select_with_output_on_a_weights_only_take_points_to_the_table(tmp_path, capsys):
    """``capture select recording.csv -o capture.usda``: the fix said only 'record the mesh with the
    weights'; it now says the coverage table alone is what such a take gives (leave out -o)."""
    from usdface.io.usd_anim import write_animation_usd

    path = tmp_path / "anim.usda"
    write_animation_usd(path, ["jawOpen", "eyeBlinkLeft"], np.array([[0.0, 0.0], [0.8, 0.1], [0.1, 0.0]]),
                        np.arange(3) / 30.0)
    assert main(["capture", "select", str(path), "-o", str(tmp_path / "c.usda")]) == 2
    err = capsys.readouterr().err
    assert "weights only" in err and "without -o" in err and not (tmp_path / "c.usda").exists()


def test_capture_select_refuses_a_capture_and_an_empty_selection(weights_take, tmp_path, capsys):
    """A capture given to ``capture select`` was re-selected (its test frames became training frames), and a
    threshold no shape reaches wrote a capture of 0 frames with exit 0: both refused, nothing written."""
    from usdface.cli import main

    assert main(["capture", "select", str(C), "-o", str(tmp_path / "cc.usda")]) == 2
    assert "this is a capture" in capsys.readouterr().err and not (tmp_path / "cc.usda").exists()
    assert main(["capture", "select", str(weights_take), "-o", str(tmp_path / "y.usda"),
                 "--threshold", "0.99"]) == 2
    err = capsys.readouterr().err
    assert "no shape peaks above --threshold 0.99" in err and "jawOpen 0.93" in err
    assert not (tmp_path / "y.usda").exists()


def test_select_capture_frames_takes_a_capture_as_template_and_checks_its_numbers(samples, tmp_path):
    """select_capture_frames(template=read_capture(...)) failed with TypeError 'expected str, bytes or
    os.PathLike object, not Capture'; threshold=1.5 gave a table of never-triggered shapes without a word
    (the command line refuses it)."""
    from test_take_select import grid_rigs

    from usdface import api
    from usdface.errors import CaptureError
    from usdface.io.take import write_take_usd
    from usdface.model import Capture, Frames
    from usdface.sample.take import make_take

    person, template = grid_rigs(n=4)
    take, _ = make_take(person, None, shapes=["jawOpen", "eyeBlinkLeft"], seed=1)
    src = write_take_usd(take, tmp_path / "take.usdc")
    empty = Frames(np.zeros((0, *template.neutral.shape)), np.zeros((0, template.n_shapes)), [], [])
    capture = Capture(template.neutral, template.triangles, template, empty, list(template.names))
    sel = api.select_capture_frames(src, tmp_path / "c.usda", template=capture)
    assert sel.out_path is not None and sel.capture.template.n_shapes == template.n_shapes
    for bad in ({"threshold": 1.5}, {"threshold": -0.1}, {"min_separation": -1}):
        with pytest.raises(CaptureError, match="threshold|min_separation"):
            api.select_capture_frames(src, **bad)


def test_capture_select_rest_warning_names_the_take_and_a_fix_not_yet_tried(tmp_path):
    """takes.md's advice for held-out frames that are all rests is '--test-every 5 --min-separation 0.2';
    given exactly that, 'capture select' warned '(fix: ... --test-every 5 --min-separation 0.2)' again, and
    without naming the take. It names the take and a --min-separation below the one given."""
    import re

    import numpy as np

    from usdface import api
    from usdface.arkit import ARKIT_NAMES

    frames = 600                                            # 20 s at 30 fps: short expressions among rests
    t = np.arange(frames)
    w = np.zeros((frames, len(ARKIT_NAMES)))
    for k, name in enumerate(("jawOpen", "eyeBlinkLeft", "mouthSmileLeft", "browInnerUp", "cheekPuff")):
        w[:, ARKIT_NAMES.index(name)] = 0.9 * np.exp(-0.5 * ((t - 60 - 110 * k) / 2.0) ** 2)
    take = tmp_path / "rests.csv"
    _livelink_csv(take, w, [f"10:00:{i // 30:02d}:{2 * (i % 30):02d}.000" for i in range(len(w))])
    with pytest.warns(UserWarning, match="show no expression") as said:
        api.select_capture_frames(take, test_every=5, min_separation=0.2)
    message = next(str(m.message) for m in said if "show no expression" in str(m.message))
    assert str(take) in message
    fix = message.split("(fix: ", 1)[1]
    suggested = float(re.search(r"--min-separation ([0-9.]+)\)", fix).group(1))
    assert suggested < 0.2, fix


def test_rewriting_a_selected_capture_keeps_its_frame_selection_record(tmp_path):
    """capture-format.md: a capture made by 'usdface capture select' keeps its frame-selection record
    (customLayerData takeSelection). 'usdface capture import capture.usdc -o capture.usda' (rewriting it, as
    the command offers) dropped it: the reader did not read it back."""
    import json

    import numpy as np
    from pxr import Sdf

    from usdface import api
    from usdface.io.take import Take, write_take_usd
    from usdface.sample import build_samples

    data = build_samples(0)
    capture = data["capture"]
    rig = capture.template
    frames = 40
    t = np.arange(frames)
    w = np.zeros((frames, len(rig.names)))
    for k in range(4):                                     # four shapes, one bump each
        w[:, k] = 0.9 * np.exp(-0.5 * ((t - 5 - 10 * k) / 1.5) ** 2)
    take = Take(weights=w, names=list(rig.names), times=t / 10.0,
                points=rig.neutral[None] + np.einsum("fk,knd->fnd", w, rig.deltas),
                triangles=rig.triangles, neutral=rig.neutral, template=rig)
    write_take_usd(take, tmp_path / "take.usdc")
    api.select_capture_frames(tmp_path / "take.usdc", tmp_path / "sel.usdc", threshold=0.5)
    first = Sdf.Layer.FindOrOpen(str(tmp_path / "sel.usdc")).customLayerData["usdface"]["takeSelection"]
    api.import_capture_folder(tmp_path / "sel.usdc", tmp_path / "again.usda")
    again = Sdf.Layer.FindOrOpen(str(tmp_path / "again.usda")).customLayerData["usdface"].get("takeSelection")
    assert again is not None and json.loads(again) == json.loads(first)


def test_a_pose_held_from_the_first_frame_is_a_peak_one_at_the_end_is_named():
    """find_peaks never returns an end sample: a take that starts on a held jawOpen lost it as 'never
    triggered' although it reached 0.95 and then relaxed (the paper's rule: it peaked). A weight still
    rising when the take ends has not peaked; the coverage now says so instead of 'never above 0.5'."""
    from usdface.take_select import format_coverage, select_frames

    w = np.zeros((60, 2))
    w[:10, 0] = 0.95
    w[10:20, 0] = np.linspace(0.9, 0.0, 10)             # held from frame 0, then relaxing
    w[50:, 1] = np.linspace(0.1, 1.0, 10)               # rising to the last frame
    sel = select_frames(w, names=["jawOpen", "eyeBlinkLeft"], min_separation=5)
    assert sel.shapes[0].frames == [4] and sel.missing == ["eyeBlinkLeft"]
    text = format_coverage(sel)
    assert "above 0.5 only at the take's end" in text and "max 1.00" in text


def test_capture_select_rest_warning_repeats_the_runs_output_and_template(generated, tmp_path):
    """The fix of the all-rests warning said "'usdface capture select TAKE -o capture.usda --test-every 5
    ...'" whatever the run was given: run as suggested after '-o sel/ --template CAPTURE' it wrote another
    file, without the template (a take without its own fails). It repeats the run's output (with --force,
    which the run wrote) and template now."""
    import dataclasses
    import re

    from usdface import api
    from usdface.io.take import write_take_usd

    take, _, _ = generated
    template = tmp_path / "template_capture.usda"
    api.write_capture(Capture(take.template.neutral, take.template.triangles, take.template,
                              Frames(np.zeros((0, *take.template.neutral.shape)),
                                     np.zeros((0, take.template.n_shapes)), [], []),
                              list(take.template.names)), template)
    src = write_take_usd(dataclasses.replace(take, template=None), tmp_path / "take.usdc")
    out = tmp_path / "sel"
    with pytest.warns(UserWarning, match="show no expression") as said:
        api.select_capture_frames(src, out, template=template, test_every=40)
    message = next(str(m.message) for m in said if "show no expression" in str(m.message))
    command = re.search(r"\(usdface capture select ([^()]*)\)", message).group(1)
    assert command.startswith(f"{src} -o {out} --template {template} --force --test-every 5"), message


def test_evaluate_rest_fix_halves_the_separation_the_capture_was_made_with(generated, tmp_path, monkeypatch):
    """takes.md: when every held-out frame is a rest, 'capture select' and 'evaluate' warn 'with that same
    fix'. capture select halves the --min-separation it was given; evaluate said "'usdface capture select
    TAKE -o capture.usda --test-every 5 --min-separation 0.2'" whatever the capture was made with (from 0.2,
    as the page suggests, it gave back the same capture; and another file than the one evaluated). The
    capture now records its take and test-frame options, and evaluate's fix names that take (from where
    evaluate runs), the capture evaluated (--force) and half the separation it was made with."""
    import re
    import shlex

    from usdface import api
    from usdface.io import read_capture
    from usdface.io.take import write_take_usd

    take, _, _ = generated
    monkeypatch.chdir(tmp_path)
    (tmp_path / "takes").mkdir()
    src = write_take_usd(take, tmp_path / "takes" / "take.usdc")
    with monkeypatch.context() as older:                  # a capture of rests, as selected before stop 52
        older.setattr("usdface.take_select.REST_WEIGHT", 0.0)
        api.select_capture_frames("takes/take.usdc", "capture.usda", test_every=40, min_separation=0.4)
    record = read_capture("capture.usda").metadata["take"]
    assert record["min_separation"] == 0.4 and record["test_every"] == 40
    assert (tmp_path / record["path"]).resolve() == src.resolve()        # relative to the capture
    monkeypatch.chdir(tmp_path / "takes")                                   # evaluate from elsewhere
    with pytest.warns(UserWarning, match="cannot tell the methods apart") as said:
        api.evaluate_methods("../capture.usda", ["dt"])
    message = next(str(m.message) for m in said if "cannot tell the methods apart" in str(m.message))
    argv = shlex.split(re.search(r"\(usdface capture select ([^()]*)\)", message).group(1))
    assert Path(argv[0]).resolve() == src.resolve(), message
    assert argv[argv.index("-o") + 1] == "../capture.usda" and "--force" in argv
    assert "made with" in message and "--min-separation 0.4 s" in message
    assert float(argv[argv.index("--min-separation") + 1]) == 0.2, message       # half, at most 0.2
    assert int(argv[argv.index("--test-every") + 1]) == 5


def test_cli_select_names_an_avatar_given_as_the_take(samples, tmp_path, capsys):
    """``capture select AVATAR`` was told only what the file lacks ("no mesh with time-sampled points ..."),
    where the other commands that read a take say what it is: an avatar, not a take. Refused before any
    output, with the kinds of take it reads."""
    out = tmp_path / "capture.usda"
    assert main(["capture", "select", str(samples / "avatar.usda"), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "this is an avatar, not a take" in err and "Live Link Face CSV" in err
    assert not out.exists()


def test_cli_select_names_a_template_of_another_mesh(generated, samples, tmp_path, capsys):
    """``capture select take_dir/ -o capture/ --template other_capture/`` (docs/takes.md) with a template
    capture of another mesh said ``take_dir: template has 1233 vertices, the take 81 (fix: the template
    must be on the take's topology)``: the take named, the template given (the file to change) not. Now
    the template's capture is named, with the fix (another template, or none: the take's own)."""
    take, _, _ = generated
    path = write_take_usd(take, tmp_path / "take.usda")
    other = samples / "capture.usda"
    out = tmp_path / "capture.usda"
    assert main(["capture", "select", str(path), "-o", str(out), "--template", str(other)]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    n = take.points.shape[1]
    assert f"the template given (capture {other}) has 1233 vertices, the take {n}" in err, err
    assert f"a capture recorded on the take's mesh ({n} vertices)" in err and "take's own template" in err
    assert not out.exists()
    from usdface import api
    from usdface.errors import GeometryError

    with pytest.raises(GeometryError, match=r"the template given \(capture .*capture.usda\) has 1233"):
        api.select_capture_frames(path, out, template=other)
    with pytest.raises(GeometryError, match=r"the template given has 1233"):   # a Capture read from elsewhere
        api.select_capture_frames(path, out, template=read_capture(other))


@pytest.mark.parametrize("kwargs, needle", [
    ({"min_separation": 0.5}, r"bad min_separation 0.5: select_frames' min_separation is a whole number >= 1 "
                              r"of frames"),
    ({"per_shape": 0}, r"bad per_shape 0: select_frames' per_shape is a whole number >= 1"),
    ({"test_every": -1}, r"bad test_every -1: select_frames' test_every is a whole number >= 0"),
    ({"test_every": 2.5}, r"bad test_every 2.5"),
    ({"threshold": 2}, r"threshold 2 is outside \[0, 1\]"),
    ({"threshold": "0.5"}, r"threshold '0.5' is outside \[0, 1\]"),
])
def test_select_frames_names_the_number_that_is_wrong(kwargs, needle):
    """docs/takes.md's script calls ``select_frames`` with ``min_separation`` in frames; given the CLI's
    seconds (0.5) it said "per_shape and min_separation must be >= 1, test_every >= 0 (fix: e.g.
    --per-shape 1 --test-every 40)", naming neither the one that was wrong nor the unit, and ``threshold=2``
    picked no frame without a word (a user trial). Each is named, with its fix."""
    w = np.zeros((9, 2))
    w[:, 0] = [0, .3, .8, .6, 0, 0, 0, 0, 0]
    with pytest.raises(CaptureError, match=needle) as err:
        select_frames(w, names=["jawOpen", "eyeBlinkLeft"], **kwargs)
    assert err.value.fix
    if "min_separation" in kwargs:
        assert "round(seconds * take.fps)" in err.value.fix
    sel = select_frames(w, names=["jawOpen", "eyeBlinkLeft"], min_separation=np.int64(2), per_shape=1.0)
    assert sel.train.tolist() == [2]       # whole numbers of any type pass


def test_read_take_refuses_a_capture(samples, sample_capture_folder):
    """A user trial (stop 42): ``usdface.io.take.read_take("capture.usda")`` (the function docs/takes.md
    imports) read the sample capture as a take of its 72 training and test frames without a word, where the
    CLI and the API refuse a capture given as a take. Now refused, file and folder alike, naming the path and
    read_capture."""
    from usdface.errors import CaptureError
    from usdface.io.take import read_take

    for capture in (samples / "capture.usda", sample_capture_folder):
        with pytest.raises(CaptureError, match="this is a capture .* not a take") as err:
            read_take(capture)
        assert str(capture) in str(err.value) and "read_capture" in err.value.fix
