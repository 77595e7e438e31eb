"""A recorded take given where a capture goes: ``usdface fit TAKE`` and ``usdface personalize AVATAR TAKE``
fit every frame (balanced frame weights), as docs/takes.md shows, against the peak-frame capture
``usdface capture select`` makes of the same take. The take is the sample person recorded in the scan regime
(0.3 mm scan noise, phone weights +- 0.02), so the truth is known."""

from __future__ import annotations

import json

import numpy as np
import pytest
from wfutil import assert_valid_usd, digest, run

from usdface.io.take import probe_take, write_take_folder, write_take_usd
from usdface.io.usd_capture import read_capture_usd
from usdface.io.usd_rig import read_avatar
from usdface.model import FaceRig
from usdface.personalize import truth_error
from usdface.sample.take import make_take


def record_take(case, point_noise):
    """(take, the person's true rig, the case's capture truth): the person of a ``usdface sample`` folder
    recorded with the capture's template at 10 fps, 0.5 s sweeps (366 frames), phone weights +- 0.02."""
    truth = np.load(case / "truth" / "capture_truth.npz")
    capture = read_capture_usd(case / "capture.usda")
    names = [str(n) for n in truth["names"]]
    person = FaceRig(truth["neutral"], capture.triangles, names, truth["deltas"])
    take, _ = make_take(person, capture.template.subset(names), fps=10, sweep_seconds=0.5, rest_seconds=0.2,
                        point_noise=point_noise, weight_noise=0.02, seed=5)
    return take, person, truth, capture


@pytest.fixture(scope="module")
def scan_take(sample_set, tmp_path_factory):
    """(folder with take.usdc, the take, the person's true rig): the scan regime (0.3 mm)."""
    take, person, _, _ = record_take(sample_set, 3e-4)
    d = tmp_path_factory.mktemp("scan_take")
    write_take_usd(take, d / "take.usdc")
    run("capture", "select", "take.usdc", "-o", "peaks.usda", "--min-separation", "0.2", cwd=d)
    return d, take, person


def _rig_deltas(path, names):
    rig = read_avatar(path).meshes[0]
    order = [rig.names.index(n) for n in names]
    return rig.deltas[order]


def test_fit_take_fits_every_frame_and_beats_its_peak_frames(scan_take, tmp_path):
    d, take, person = scan_take
    before = digest(d / "take.usdc")
    run("fit", d / "peaks.usda", "-o", "peaks_rig.usda", "-q", cwd=tmp_path)
    proc = run("fit", d / "take.usdc", "-o", "take_rig.usda", "--json", "-q", cwd=tmp_path)
    doc = json.loads(proc.stdout)
    assert doc["frame_weights"]["mode"] == "balanced" and doc["frame_weights"]["frames"] == len(take)
    assert 30 < doc["frame_weights"]["effective_frames"] < len(take)  # held poses count about once
    peak = truth_error(_rig_deltas(tmp_path / "peaks_rig.usda", person.names), person.deltas)
    whole = truth_error(_rig_deltas(tmp_path / "take_rig.usda", person.names), person.deltas)
    # issue 13: the whole-take fit at least 25 % below the peak-frame fit of the same take
    # (measured 0.247 against 0.345 mm, 0.71x)
    assert whole <= 0.75 * peak, (whole, peak)
    assert digest(d / "take.usdc") == before
    text = run("fit", d / "take.usdc", "-o", "again.usda", "-q", cwd=tmp_path).stdout
    assert f"whole take: {len(take)} frames weighted balanced" in text


def test_personalize_take_beats_its_peak_frames_on_the_avatar(scan_take, sample_set, tmp_path):
    d, take, _ = scan_take
    avatar = sample_set / "avatar.usda"
    run("personalize", avatar, d / "peaks.usda", "-o", "peaks.usda", "-q", cwd=tmp_path)
    text = run("personalize", avatar, d / "take.usdc", "-o", "take.usda", "-q", "--inspect", "--review",
               cwd=tmp_path).stdout
    assert f"fit: whole take: {len(take)} frames" in text
    assert_valid_usd(tmp_path / "take.usda")
    # inspection and review play the take itself (it has no test expressions)
    from pxr import Usd, UsdSkel

    stage = Usd.Stage.Open(str(tmp_path / "take.usda"))
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Avatar/Skel/usdfaceInspection"))
    assert anim.GetBlendShapeWeightsAttr().GetNumTimeSamples() == len(take)
    assert "the take (every frame fitted)" in (tmp_path / "take.review.html").read_text()
    truth = np.load(sample_set / "truth" / "avatar_truth.npz")
    generic = read_avatar(avatar).mesh("Head")
    true = np.stack([truth[f"Head/{n}"] for n in generic.names]) @ generic.source.to_internal[:3, :3].T
    errors = {}
    for name in ("peaks", "take"):
        head = read_avatar(tmp_path / f"{name}.usda").mesh("Head")
        errors[name] = truth_error(head.deltas, true)
    errors["generic"] = truth_error(generic.deltas, true)
    # more frames, less of the scan noise on the avatar (measured 0.152 against 0.270 mm, generic 0.343)
    assert errors["take"] < 0.8 * errors["peaks"] < errors["generic"], errors


def test_takes_are_told_from_captures(scan_take, sample_set, tmp_path):
    d, take, _ = scan_take
    assert probe_take(d / "take.usdc")[0]
    assert not probe_take(sample_set / "capture.usda")[0]
    assert not probe_take(sample_set / "capture")[0]             # capture folder (train/, test/)
    assert not probe_take(d / "peaks.usda")[0]                    # a capture made from a take
    short = type(take)(take.weights[:12], take.names, take.times[:12], take.points[:12], take.triangles,
                       take.neutral, take.template)
    write_take_folder(short, tmp_path / "take_dir")               # OBJ sequence + Live Link CSV
    assert probe_take(tmp_path / "take_dir")[0]
    # a take another tool wrote: no usdface marker, a mesh with time-sampled points
    from pxr import Sdf

    write_take_usd(short, tmp_path / "plain.usda")
    layer = Sdf.Layer.FindOrOpen(str(tmp_path / "plain.usda"))
    layer.customLayerData = {}
    layer.Save()
    del layer
    assert probe_take(tmp_path / "plain.usda")[0]
    proc = run("evaluate", d / "take.usdc", cwd=tmp_path, ok=False)
    assert proc.returncode == 2 and "capture select" in proc.stderr and "Traceback" not in proc.stderr


def test_personalize_a_take_with_another_artists_template_stays_better_than_generic(tmp_path):
    """A take whose template is another artist's rig (``usdface sample --template artist``, dev3's regime),
    recorded clean (0.1 mm): with hundreds of frames every shape is decided by the frames, so the avatar
    prior and the template tie in the fit's cross-validation - but the prior is what the implant measures
    the person's change from, and a coin flip for the template put its mismatch with the avatar on the
    avatar (face 1.004x generic, eyeBlinkLeft +0.86 mm). Ties go to the avatar's own shapes (measured
    0.322x, every shape at or below generic)."""
    from usdface.sample import covered_vertices
    from usdface.transfer.scoring import score_mesh

    d = tmp_path / "artist"
    run("sample", d, "--template", "artist", "--seed", "24", cwd=tmp_path)
    take, _, truth, capture = record_take(d, 1e-4)
    write_take_usd(take, tmp_path / "take.usdc")
    run("personalize", d / "avatar.usda", "take.usdc", "-o", "out.usda", "-q", cwd=tmp_path)
    generic = read_avatar(d / "avatar.usda").mesh("Head")
    head = read_avatar(tmp_path / "out.usda").mesh("Head")
    npz = np.load(d / "truth" / "avatar_truth.npz")
    true = np.stack([npz[f"Head/{n}"] for n in generic.names]) @ generic.source.to_internal[:3, :3].T
    meta = json.loads((d / "truth" / "meta.json").read_text())
    covered = covered_vertices(generic.neutral, meta, truth["neutral"], capture.triangles)
    score = score_mesh(generic.names, generic.deltas, head.deltas, true, face=covered)
    assert score.face_ratio < 0.6, score.face_ratio
    assert score.worst_shape()[1] <= 0.05, score.worst_shape()      # issue 10's per-shape rule
