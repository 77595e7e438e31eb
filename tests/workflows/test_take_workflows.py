"""A recorded take given where a capture goes: ``usdface fit TAKE`` and ``usdface personalize AVATAR TAKE``
fit every frame (balanced frame weights), as docs/takes.md shows, against the peak-frame capture
``usdface capture select`` makes of the same take. The take is the sample person recorded in the scan regime
(0.3 mm scan noise, phone weights +- 0.02), so the truth is known."""

from __future__ import annotations

import json
import re

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
    assert re.search(rf"whole take: {len(take)} frames, \d+ distinct poses weighted balanced", text), text


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
    assert "take take.usdc (every frame fitted)" in (tmp_path / "take.review.html").read_text()
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
    # arcs and sublayers elsewhere do not change the answer (the review found a looks reference, a
    # sublayer and a template in a file of its own turned real takes into "captures")
    looks = tmp_path / "looks.usda"
    looks.write_text('#usda 1.0\ndef Scope "Looks"\n{\n}\n')
    text = (tmp_path / "plain.usda").read_text()
    (tmp_path / "withlooks.usda").write_text(
        text + '\ndef Scope "Looks" (\n    references = @./looks.usda@\n)\n{\n}\n')
    (tmp_path / "withsub.usda").write_text(text.replace("#usda 1.0\n(", "#usda 1.0\n(\n    subLayers = "
                                                        "[@./looks.usda@]", 1))
    assert "subLayers" in (tmp_path / "withsub.usda").read_text()
    assert probe_take(tmp_path / "withlooks.usda")[0] and probe_take(tmp_path / "withsub.usda")[0]
    # a shot file that animates a mesh of a referenced avatar (an over) is not a take
    (tmp_path / "shot.usda").write_text(
        '#usda 1.0\ndef "Hero" (\n    references = @' + (sample_set / "avatar.usda").as_posix() + '@\n)\n{\n'
        '    over "Head"\n    {\n        point3f[] points.timeSamples = {\n            1: [(0, 0, 0)],\n'
        '            2: [(0, 0, 1)],\n        }\n    }\n}\n')
    assert not probe_take(tmp_path / "shot.usda")[0]
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


def test_takes_that_cannot_be_fitted_say_why_and_how(scan_take, sample_set, tmp_path):
    """A take without its template, a Live Link CSV and an 'anim import' take given where a capture goes:
    each refusal names the file (and prim) and a fix the command has (fit/personalize have no --template)."""
    from dataclasses import replace

    d, take, _ = scan_take
    short = replace(take, weights=take.weights[:12], times=take.times[:12], points=take.points[:12],
                    template=None)
    write_take_usd(short, tmp_path / "bare.usdc")
    write_take_folder(short, tmp_path / "bare_dir")
    avatar = sample_set / "avatar.usda"
    for args, said in ((("fit", "bare.usdc", "-o", "a.usda"), ["bare.usdc, prim /Take/Template"]),
                       (("personalize", avatar, "bare_dir", "-o", "b.usda"), ["bare_dir/template"])):
        proc = run(*args, cwd=tmp_path, ok=False)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
        assert "no template rig" in proc.stderr and "capture select" in proc.stderr, proc.stderr
        assert "pass --template" not in proc.stderr, proc.stderr
        for s in said:
            assert s in proc.stderr, proc.stderr
    (tmp_path / "take.csv").write_text((tmp_path / "bare_dir" / "take.csv").read_text())
    run("anim", "import", "take.csv", "-o", "anim.usda", "-q", cwd=tmp_path)
    for args in (("fit", "take.csv", "-o", "c.usda"), ("personalize", avatar, "anim.usda", "-o", "d.usda")):
        proc = run(*args, cwd=tmp_path, ok=False)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
        assert "weights only" in proc.stderr and "--take" in proc.stderr, proc.stderr
    assert "prim /" in proc.stderr  # the SkelAnimation
    assert not list(tmp_path.glob("[abcd].usda"))


def test_render_draws_capture_and_take_files_like_capture_folders(scan_take, sample_set, tmp_path):
    """docs/pipeline.md: 'usdface render capture/' draws the template shapes on the person's neutral; a
    capture.usda or a take file is the same thing and is drawn without --capture (not refused as 'not an
    avatar')."""
    d, _, _ = scan_take
    for i, src in enumerate((sample_set / "capture.usda", d / "take.usdc", sample_set / "capture")):
        proc = run("render", src, "-o", f"{i}.png", "--shapes", "jawOpen", cwd=tmp_path)
        assert (tmp_path / f"{i}.png").read_bytes()[:4] == b"\x89PNG", proc.stderr
    run("render", sample_set / "avatar.usda", "-o", "avatar.png", cwd=tmp_path)  # an avatar still an avatar


def test_a_take_where_an_avatar_goes_points_to_the_take_commands(scan_take, tmp_path):
    """The refusal's fix names what a take is for since whole-take fitting: personalize AVATAR TAKE, fit."""
    d, _, _ = scan_take
    proc = run("landmarks", d / "take.usdc", cwd=tmp_path, ok=False)
    assert proc.returncode == 2 and "prim /Take" in proc.stderr, proc.stderr
    assert "'personalize AVATAR TAKE'" in proc.stderr and "'fit TAKE'" in proc.stderr, proc.stderr


def test_personalize_take_inspect_plays_the_take(scan_take, sample_set, tmp_path):
    """personalize AVATAR TAKE --inspect: a take read whole has no test expressions, so the inspection
    SkelAnimation plays the take itself (one sample per frame), and the summary says so."""
    from pxr import Usd, UsdSkel

    d, take, _ = scan_take
    text = run("personalize", sample_set / "avatar.usda", d / "take.usdc", "-o", "person.usda", "--inspect",
               "-q", cwd=tmp_path).stdout
    assert "SkelAnimation of the take" in text and "test-expression" not in text, text
    stage = Usd.Stage.Open(str(tmp_path / "person.usda"))
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Avatar/Skel/usdfaceInspection"))
    assert anim and anim.GetBlendShapeWeightsAttr().GetNumTimeSamples() == len(take)
    assert_valid_usd(tmp_path / "person.usda")
    # a method that weights no frames (dt) plays the take too, and the summary says so as well
    text = run("personalize", sample_set / "avatar.usda", d / "take.usdc", "-o", "dt.usda", "--inspect",
               "--method", "dt", "-q", cwd=tmp_path).stdout
    assert "SkelAnimation of the take" in text and "test-expression" not in text, text


def test_personalize_take_with_a_capture_of_no_test_frames_says_it_plays_the_take(scan_take, sample_set,
                                                                                 tmp_path):
    """personalize AVATAR CAPTURE --take TAKE where the capture holds out no test frames ('capture select'
    without --test-every): the summary says the SkelAnimation plays the take (it said 'test-expression
    SkelAnimation + take'), and the layer's animation is the take's frames alone."""
    from pxr import Usd, UsdSkel

    from usdface.io import read_capture

    d, take, _ = scan_take
    assert len(read_capture(d / "peaks.usda").test) == 0
    text = run("personalize", sample_set / "avatar.usda", d / "peaks.usda", "--take", d / "take.usdc",
               "-o", "person.usda", "-q", cwd=tmp_path).stdout
    assert "SkelAnimation of the take" in text and "no test expressions" in text, text
    assert "test-expression" not in text, text
    stage = Usd.Stage.Open(str(tmp_path / "person.usda"))
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Avatar/Skel/usdfaceInspection"))
    assert anim.GetBlendShapeWeightsAttr().GetNumTimeSamples() == len(take)


def test_review_of_a_take_layer_plays_the_take(scan_take, sample_set, tmp_path):
    """usdface review of a layer personalized from a take: the recorded capture is that take, read whole,
    so the page plays it (there are no test expressions) and says why nothing is scored."""
    d, _, _ = scan_take
    run("personalize", sample_set / "avatar.usda", d / "take.usdc", "-o", "person.usda", "-q", cwd=tmp_path)
    run("review", "person.usda", "-o", "review.html", cwd=tmp_path)
    page = (tmp_path / "review.html").read_text()
    assert "take take.usdc" in page and "fitted whole" in page


def test_batch_item_with_a_frame_weighting_that_is_not_one(scan_take, sample_set, tmp_path):
    """A manifest's frame_weights other than 'balanced' or numbers fails its item with a FitError that names
    the accepted values (not 'ValueError: could not convert string to float')."""
    d, _, _ = scan_take
    manifest = tmp_path / "m.json"
    manifest.write_text(json.dumps({"items": [{"avatar": str(sample_set / "avatar.usda"),
                                               "capture": str(d / "take.usdc"), "output": "out/a.usda",
                                               "frame_weights": "uniform"}]}))
    proc = run("batch", manifest, "-j", "1", cwd=tmp_path, ok=False)
    assert proc.returncode == 1, proc.stderr
    item = json.loads((tmp_path / "m.report.json").read_text())["items"][0]
    assert item["status"] == "failed", item
    assert item["error_type"] == "FitError" and "'balanced'" in item["error"], item


def test_capture_select_test_every_that_holds_out_nothing_says_so(scan_take, tmp_path):
    """capture select --test-every on a take without rests: no frame is --min-separation from every training
    frame, so no test frame is held out; select warns at once and evaluate's refusal names the select route
    (not a test/ folder, which a capture.usda has no place for)."""
    d, _, _ = scan_take
    proc = run("capture", "select", d / "take.usdc", "-o", "c.usda", "--test-every", "40", cwd=tmp_path)
    assert "0 test frames" in proc.stdout
    said = proc.stdout + proc.stderr
    assert "warning:" in said and "held out no test frame" in said and "--min-separation" in said, said
    proc = run("evaluate", "c.usda", cwd=tmp_path, ok=False)
    assert proc.returncode == 2 and "capture select" in proc.stderr, proc.stderr
    # (0.1 s: the frames next to the peaks; those 0.2 s away end the 0.5 s sweeps, rests never held out)
    proc = run("capture", "select", d / "take.usdc", "-o", "ok.usda", "--test-every", "3", "--min-separation",
               "0.1", cwd=tmp_path)
    assert "held out no test frame" not in proc.stdout + proc.stderr and " 0 test frames" not in proc.stdout


def test_a_take_packaged_as_usdz_is_a_take(scan_take, tmp_path):
    """A USD take delivered as a .usdz package (as captures already may be): capture select reads it and fit
    fits every frame, instead of 'not a take' / 'missing usdface:frames:role'."""
    from pxr import Sdf, UsdUtils

    d, take, _ = scan_take
    assert UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(d / "take.usdc")), str(tmp_path / "take.usdz"))
    assert probe_take(tmp_path / "take.usdz")[0]
    proc = run("capture", "select", "take.usdz", "--min-separation", "0.2", cwd=tmp_path)
    assert "52/52 shapes triggered" in proc.stdout, proc.stdout
    proc = run("fit", "take.usdz", "-o", "rig.usda", "-q", cwd=tmp_path)
    assert f"whole take: {len(take)} frames" in proc.stdout, proc.stdout


def test_a_dcc_take_without_template_names_where_the_template_goes(scan_take, tmp_path):
    """An unmarked take another tool wrote, its mesh deep in the hierarchy (/Root/Geo/Face): the refusal
    names <defaultPrim>/Template, where the reader looks, not a sibling of the mesh."""
    from pxr import Usd, UsdGeom, Vt

    from usdface.io.usd_anim import author_skel_animation

    _, take, _ = scan_take
    stage = Usd.Stage.CreateNew(str(tmp_path / "dcc.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/Root").GetPrim())
    mesh = UsdGeom.Mesh.Define(stage, "/Root/Geo/Face")
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(take.triangles)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(take.triangles.ravel().tolist()))
    for f in range(12):
        mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(take.points[f].astype(np.float32)), float(f))
    author_skel_animation(stage, "/Root/Anim", list(take.names), take.weights[:12], 10.0,
                          times=take.times[:12])
    stage.Save()
    proc = run("fit", "dcc.usda", "-o", "rig.usda", cwd=tmp_path, ok=False)
    assert proc.returncode == 2 and "dcc.usda, prim /Root/Template:" in proc.stderr, proc.stderr


def test_inspect_reads_a_take_file_as_it_reads_a_take_folder(scan_take, tmp_path):
    """inspect take_dir/ summarized the take (read whole) while inspect take.usdc refused it as 'not an
    avatar': both now show the frames, and say it is a take read whole."""
    d, take, _ = scan_take
    short = type(take)(take.weights[:12], take.names, take.times[:12], take.points[:12], take.triangles,
                       take.neutral, take.template)
    write_take_folder(short, tmp_path / "take_dir")
    for src in (d / "take.usdc", tmp_path / "take_dir"):
        text = run("inspect", src, cwd=tmp_path).stdout
        assert "read whole: every frame trains" in text and "frames:" in text, text
        assert text.splitlines()[0].endswith(": take with meshes"), text     # not ': capture' (trial 24)
    doc = json.loads(run("inspect", d / "take.usdc", "--json", cwd=tmp_path).stdout)
    assert doc["take"]["frames"] == len(take) and doc["roles"]["train"]["count"] == len(take)


def test_a_live_link_csv_where_a_usd_file_goes_is_named(tmp_path):
    """A Live Link CSV given to a command that reads USD (check, the avatar of personalize): the refusal says
    it is a CSV take and how takes are used, not USD's 'Cannot determine file format'. (inspect summarises
    it as the weights-only take it is.)"""
    from usdface.io.livelink import write_livelink_csv

    write_livelink_csv(tmp_path / "take.csv", ["jawOpen", "eyeBlinkLeft"], np.zeros((4, 2)),
                       np.arange(4) / 30.0)
    assert "take.csv: take" in run("inspect", "take.csv", cwd=tmp_path).stdout
    for args in (("check", "take.csv"), ("personalize", "take.csv", "take.csv", "-o", "out.usda")):
        proc = run(*args, cwd=tmp_path, ok=False)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
        assert "take.csv: a CSV file (a Live Link Face take?)" in proc.stderr and "--take" in proc.stderr
        assert "Cannot determine file format" not in proc.stderr


def test_every_thins_a_take_and_is_refused_on_a_capture(scan_take, sample_set, tmp_path):
    """``--every N`` fits every N-th frame of a take (a long take's cost is its frames); on a capture of
    picked frames it is refused before any output, naming the option and the fix."""
    d, take, person = scan_take
    proc = run("fit", d / "take.usdc", "-o", "every2.usda", "--every", "2", "--json", "-q", cwd=tmp_path)
    doc = json.loads(proc.stdout)
    assert doc["frame_weights"]["frames"] == (len(take) + 1) // 2
    every2 = truth_error(_rig_deltas(tmp_path / "every2.usda", person.names), person.deltas)
    assert every2 < 0.345                          # still below the peak-frame fit of the same take
    for cmd in (("fit", sample_set / "capture.usda", "-o", "x.usda", "--every", "2"),
                ("personalize", sample_set / "avatar.usda", sample_set / "capture.usda", "-o", "y.usda",
                 "--every", "3")):
        proc = run(*cmd, cwd=tmp_path, ok=False)
        assert proc.returncode == 2, proc.stderr
        assert "thins a take read whole" in proc.stderr and "leave out --every" in proc.stderr, proc.stderr
    assert not (tmp_path / "x.usda").exists() and not (tmp_path / "y.usda").exists()
    proc = run("fit", d / "take.usdc", "-o", "z.usda", "--every", "0", cwd=tmp_path, ok=False)
    assert proc.returncode == 2 and "--every" in proc.stderr


def test_fit_take_with_ebfr_says_its_frames_count_equally(scan_take, tmp_path):
    """EBFR takes no frame weights: a take fitted whole with it says so instead of nothing."""
    d, take, _ = scan_take
    text = run("fit", d / "take.usdc", "-o", "ebfr.usda", "--method", "ebfr", "-q", cwd=tmp_path).stdout
    assert re.search(rf"whole take: {len(take)} frames, \d+ distinct poses weighted equally \(ebfr takes no "
                     r"frame weights\)", text), text


def test_check_of_a_take_folder_says_what_reads_it(scan_take, tmp_path):
    """``check`` validates USD files; a take folder got 'file is a folder, not a file'."""
    from dataclasses import replace

    _, take, _ = scan_take
    write_take_folder(replace(take, weights=take.weights[:6], times=take.times[:6], points=take.points[:6]),
                      tmp_path / "take_dir")
    proc = run("check", "take_dir", cwd=tmp_path, ok=False)
    assert proc.returncode == 2 and "a take folder" in proc.stderr and "usdface inspect" in proc.stderr


def _inspection_weights(layer):
    """(blendShapes, weights[F, K], time codes[F]) of a layer's inspection SkelAnimation."""
    from pxr import Usd, UsdSkel

    stage = Usd.Stage.Open(str(layer))
    prim = next(p for p in stage.Traverse() if p.GetName() == "usdfaceInspection")
    attr = UsdSkel.Animation(prim).GetBlendShapeWeightsAttr()
    codes = attr.GetTimeSamples()
    return (list(UsdSkel.Animation(prim).GetBlendShapesAttr().Get()),
            np.array([np.asarray(attr.Get(t)) for t in codes]), np.asarray(codes))


def test_a_usd_take_played_reads_no_points(scan_take, tmp_path, monkeypatch):
    """A played USD take (``personalize --take take.usdc``, ``review --take``) read every frame's points to
    play its weights, as a take folder parsed every OBJ (stop 50). ``read_take(meshes=False)`` reads the
    weights at the frames' time samples and no points: the same weights, names and times as the whole
    read, with a points reader that fails."""
    import usdface.io.usd_capture as usd_capture
    from usdface.io.take import read_take

    _, take, _ = scan_take
    short = type(take)(take.weights[:30], take.names, take.times[:30], take.points[:30], take.triangles,
                       take.neutral, take.template)
    write_take_usd(short, tmp_path / "take.usdc")
    whole = read_take(tmp_path / "take.usdc")
    assert whole.points is not None and whole.points.shape[0] == 30

    def no_points(*args, **kwargs):
        raise AssertionError("a played take's points were read")

    monkeypatch.setattr(usd_capture, "_points", no_points)
    played = read_take(tmp_path / "take.usdc", meshes=False)
    assert played.points is None and played.neutral is None and played.template is None
    assert played.names == whole.names
    np.testing.assert_array_equal(played.weights, whole.weights)
    np.testing.assert_array_equal(played.times, whole.times)
    with pytest.raises(AssertionError, match="points were read"):
        read_take(tmp_path / "take.usdc")


def test_personalize_take_folder_plays_its_weights_without_reading_its_meshes(scan_take, sample_set,
                                                                               tmp_path):
    """A user trial: 'personalize AVATAR CAPTURE --take take_dir/' parsed every OBJ frame of the folder to
    play its weights (1,458 frames: read 7.45 s, against 0.94 s for the same take as .usdc). The playback
    reads the CSV and the frame names only: frames no OBJ reader could parse play the same animation as
    the same take given as a USD file."""
    _, take, _ = scan_take
    short = type(take)(take.weights[:40], take.names, take.times[:40], take.points[:40], take.triangles,
                       take.neutral, take.template)
    write_take_usd(short, tmp_path / "take.usdc")
    write_take_folder(short, tmp_path / "take_dir")
    frames = sorted((tmp_path / "take_dir" / "frames").glob("*.obj"))
    assert len(frames) == 40
    for f in frames:                      # no mesh in any frame: only the names pair them with the CSV rows
        f.write_text("not an OBJ mesh\n")
    avatar, capture = sample_set / "avatar.usda", sample_set / "capture.usda"
    run("personalize", avatar, capture, "--take", "take.usdc", "-o", "from_usd.usda", "-q", cwd=tmp_path)
    run("personalize", avatar, capture, "--take", "take_dir", "-o", "from_dir.usda", "-q", cwd=tmp_path)
    names_usd, w_usd, t_usd = _inspection_weights(tmp_path / "from_usd.usda")
    names_dir, w_dir, t_dir = _inspection_weights(tmp_path / "from_dir.usda")
    assert names_dir == names_usd and len(t_dir) > 40
    np.testing.assert_allclose(t_dir, t_usd)
    np.testing.assert_allclose(w_dir, w_usd, atol=1e-6)  # the CSV's 6 decimals
    assert np.ptp(w_dir[-40:]) > 0.1                       # the take's frames play, not a still face


def test_sample_take_lets_a_new_user_follow_takes_md(tmp_path):
    """``usdface sample OUT --take`` writes ``take.usdc``, a continuous take of the sample person with
    meshes (docs/takes.md's commands need one; before stop 52 a fresh clone had only weights-only Live Link
    CSVs, and a take with meshes took Python): it is the person's truth on the capture mesh, every ARKit
    shape swept once, and ``capture select`` takes it as written in docs/takes.md."""
    from usdface.io.take import read_take

    out = tmp_path / "s"
    run("sample", out, "--take", "-q", cwd=tmp_path)
    take = read_take(out / "take.usdc")
    truth = np.load(out / "truth" / "capture_truth.npz")
    capture = read_capture_usd(out / "capture.usda")
    assert take.points.shape[1:] == truth["neutral"].shape and len(take) > 52 * 10
    assert take.fps == pytest.approx(30.0)
    # the take's neutral is the person's (the capture's), its template the capture's template
    assert np.abs(take.neutral - truth["neutral"]).max() < 1e-6
    order = [capture.template.names.index(n) for n in take.template.names]
    assert np.abs(take.template.deltas - capture.template.deltas[order]).max() < 1e-6
    # every swept shape peaks alone once above capture select's threshold (0.5)
    sel = run("capture", "select", out / "take.usdc", "-o", "c.usda", "--test-every", "10",
              "--min-separation", "0.2", cwd=tmp_path)
    assert "52/52 shapes triggered" in sel.stdout
    # a frame is the person's true rig at the reported weights, up to the scan and weight noise
    names = [str(n) for n in truth["names"]]
    w = take.weights[:, [take.names.index(n) for n in names]]
    model = truth["neutral"] + np.einsum("fk,knc->fnc", w, truth["deltas"])
    assert np.sqrt(np.mean((take.points - model) ** 2)) < 5e-4
    # the same seed gives the same bytes; without --take no take is written
    again = tmp_path / "again"
    run("sample", again, "--take", "-q", cwd=tmp_path)
    assert list(digest(out / "take.usdc").values()) == list(digest(again / "take.usdc").values())
    run("sample", tmp_path / "plain", "-q", cwd=tmp_path)
    assert not (tmp_path / "plain" / "take.usdc").exists()
