"""personalize on the bench cases (../shared): accuracy vs truth, regions, input untouched, variants."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

pytestmark = pytest.mark.shared


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def dev1(bench):
    from usdface.io import read_capture
    from usdface.personalize import fit_personalized_shapes

    capture = read_capture(bench / "dev1" / "capture")
    return capture, fit_personalized_shapes(capture).rig


@pytest.fixture(scope="module")
def dev1_result(bench, dev1, tmp_path_factory):
    from usdface.transfer import personalize_avatar

    avatar = bench / "dev1" / "avatar.usdc"
    before = _sha(avatar)
    out = tmp_path_factory.mktemp("p") / "dev1.usda"
    result = personalize_avatar(avatar, dev1[0], out)
    return result, before


def _scores(bench, case, result):
    """Head (face region 0-9408, seam across the capture border 0-6705) and Mouth scores vs the truth."""
    from usdface.io.usd_rig import read_avatar
    from usdface.transfer.scoring import score_mesh

    avatar = read_avatar(bench / case / "avatar.usdc")
    truth_npz = np.load(bench / case / "truth" / "avatar_truth.npz")
    scores = {}
    for m in avatar.meshes:
        truth = np.array([truth_npz[f"{m.name}/{n}"] for n in m.names]) @ m.source.to_internal[:3, :3].T
        idx = np.arange(m.n_vertices)
        extra = {"face": idx <= 9408, "covered": idx <= 6705, "triangles": m.triangles} if m.name == "Head" \
            else {}
        scores[m.name] = score_mesh(m.names, m.deltas, result.offsets[m.source.prim], truth, **extra)
    return scores, avatar.mesh("Head")


def test_dev1_accuracy_and_input_untouched(bench, dev1_result):
    result, before = dev1_result
    scores, head = _scores(bench, "dev1", result)
    s = scores["Head"]
    assert s.face_ratio <= 0.45, s.face_ratio            # issue 10 acceptance (0.39 before)
    assert s.whole_ratio < 1.0
    assert s.seam_out <= s.seam_generic + 0.2, (s.seam_out, s.seam_generic)
    # issue 10's per-shape rule: mouthPressLeft was +0.078 mm until the fit capped its trust by the shape's
    # estimate variance (the pair is always shown together: only its sum is known); now every shape +0.000
    worst = int(np.argmax(s.per_shape_delta))
    assert s.per_shape_delta[worst] <= 0.05, (head.names[worst], s.per_shape_delta[worst])
    # and the report says why the pair stays near generic: shown, but its difference within the fit's noise
    assert {"mouthPressLeft", "mouthPressRight"} <= set(result.report["within_noise"])
    barely = [w for w in result.report["warnings"] if w.startswith("the capture barely shows")]
    assert len(barely) == 1 and "jawLeft" in barely[0] and "mouthPressRight" not in barely[0]
    assert not set(result.report["within_noise"]) & {"jawLeft", "jawRight"}
    assert _sha(bench / "dev1" / "avatar.usdc") == before
    assert result.out_path.exists()
    reg = result.report["registration"]
    assert 0.95 < reg["scale"] < 1.05 and reg["residual_m"] < 0.003
    # the correspondence keeps the lips apart
    assert result.report["correspondence"]["side_swaps_jawOpen"] == 0


def test_dev3_other_artists_template_is_not_worse_than_generic(bench):
    """dev3: the capture's template is another artist's rig; the output must beat the generic avatar on the
    face, the whole head and the Mouth mesh (issue 10 acceptance: 0.70 / 0.80 / 0.90; 1.71 / 1.55 / 1.00
    before)."""
    from usdface.transfer import personalize_avatar

    result = personalize_avatar(bench / "dev3" / "avatar.usdc", bench / "dev3" / "capture", None)
    scores, _ = _scores(bench, "dev3", result)
    head, mouth = scores["Head"], scores["Mouth"]
    assert head.face_ratio <= 0.70, head.face_ratio
    assert head.whole_ratio <= 0.80, head.whole_ratio
    assert mouth.whole_ratio <= 0.90, mouth.whole_ratio
    # the shapes the range-of-motion take barely shows stay (nearly) generic
    assert result.report["shape_confidence"]["jawLeft"] < 0.1
    names = head.names
    assert head.per_shape_delta[names.index("jawLeft")] <= 0.05
    # the map is registered from the person's scan, closer to this avatar of the person than the template's
    # neutral (residual 0.45 mm against 1.68): no lip or lid on the wrong side and no shape worse than generic
    # (from the template's neutral: 9 lid swaps, browDownRight +0.054 mm and the blinks kept within 0.1 mm of
    # generic only by dropping 448 mis-mapped capture vertices, now 0)
    corr = result.report["correspondence"]
    assert corr["source"] == "person", corr["source"]
    assert (corr["side_swaps"], corr["mapping_outliers"]) == (0, 0)
    worst = int(np.argmax(head.per_shape_delta))
    assert head.per_shape_delta[worst] <= 0.05, (names[worst], head.per_shape_delta[worst])
    assert head.seam_out <= head.seam_generic + 0.2, (head.seam_out, head.seam_generic)


def test_dev1_layer_round_trip(dev1_result):
    from usdface.io.usd_rig import read_avatar

    result, _ = dev1_result
    back = read_avatar(result.out_path)
    for m in back.meshes:
        np.testing.assert_allclose(m.deltas, result.offsets[m.source.prim], atol=1e-6)


def test_dev2_accuracy(bench, dev1_result):
    from usdface.transfer import personalize_avatar

    result = personalize_avatar(bench / "dev2" / "avatar.usdc", bench / "dev2" / "capture", None)
    scores, _ = _scores(bench, "dev2", result)
    assert scores["Head"].face_ratio <= 0.95, scores["Head"].face_ratio


def _variant(src, dst, *, up_axis, mpu, xform):
    from pxr import Gf, Usd, UsdGeom

    layer = Usd.Stage.Open(str(src)).Flatten()
    layer.Export(str(dst))
    stage = Usd.Stage.Open(str(dst))
    UsdGeom.SetStageUpAxis(stage, up_axis)
    UsdGeom.SetStageMetersPerUnit(stage, mpu)
    root = UsdGeom.Xformable(stage.GetDefaultPrim())
    root.ClearXformOpOrder()
    root.AddTransformOp().Set(Gf.Matrix4d(*np.asarray(xform).T.ravel()))
    stage.Save()
    return dst


@pytest.mark.parametrize("kind", ["zup_cm", "yup_m", "blender"])
def test_units_axis_and_dcc_variants_give_the_same_offsets(bench, dev1, dev1_result, tmp_path, kind):
    from usdface.io.usd_rig import read_avatar
    from usdface.transfer import personalize_avatar

    src = bench / "dev1" / "avatar.usdc"
    if kind == "blender":
        path = bench / "dev1" / "avatar_blender.usdc"
    elif kind == "zup_cm":  # Z up, cm, placed elsewhere and turned: rotate +90 about X, move
        rot = np.eye(4)
        rot[1:3, 1:3] = [[0, -1], [1, 0]]
        rot[:3, 3] = [250.0, -40.0, 3.0]
        path = _variant(src, tmp_path / "zup.usda", up_axis="Z", mpu=0.01, xform=rot)
    else:  # Y up, metres, the 0.01 scale on the root transform
        path = _variant(src, tmp_path / "m.usda", up_axis="Y", mpu=1.0, xform=np.diag([0.01, 0.01, 0.01, 1]))
    res = personalize_avatar(path, dev1[0], None)
    ref, _ = dev1_result
    ref_avatar, var_avatar = read_avatar(src), read_avatar(path)
    for m in ref_avatar.meshes:
        v = next(x for x in var_avatar.meshes if x.name == m.name)
        a = np.einsum("ij,knj->kni", np.linalg.inv(v.source.to_internal[:3, :3]), res.offsets[v.source.prim])
        b = np.einsum("ij,knj->kni", np.linalg.inv(m.source.to_internal[:3, :3]), ref.offsets[m.source.prim])
        a = a[[v.index(n) for n in m.names]]
        rel = np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(b ** 2))
        assert rel < 1e-4, (kind, m.name, rel)
    if kind == "blender":
        assert "/root/Avatar/Head/Head" in res.offsets and "/root/Avatar/Mouth/Mouth" in res.offsets


def test_missing_shapes_are_reported(bench, dev1):
    from usdface.transfer import personalize_avatar

    capture, rig = dev1
    partial = rig.subset([n for n in rig.names if n != "jawOpen"])
    res = personalize_avatar(bench / "dev1" / "avatar.usdc", capture, None, rig=partial)
    assert "jawOpen" in res.report["avatar_shapes_missing_from_capture"]
    assert "tongueOut" not in res.names
    head = next(m for m in res.offsets if m.endswith("Head"))
    assert "jawOpen" not in res.names and head


def test_eyelid_repair_on_dev1_eyes(bench, dev1, dev1_result):
    from usdface.io.usd_rig import read_avatar
    from usdface.transfer import personalize_avatar
    from usdface.transfer.eyelids import _signed_distance, eye_surfaces, find_eyeballs

    avatar = bench / "dev1" / "avatar.usdc"
    eyes = read_avatar(avatar).metadata["static_meshes"]  # the eyes carry no blend shapes
    res, _ = dev1_result  # default settings: eyes found in the avatar, repair on
    assert sorted(res.report["eyelids"]["eyeballs"]) == ["/Avatar/EyeLeft", "/Avatar/EyeRight"]
    assert res.report["eyelids"]["repaired_vertex_shapes"] > 0
    ref = personalize_avatar(avatar, dev1[0], None, eyelids=False)
    key = next(k for k in res.offsets if k.endswith("Head"))
    head = read_avatar(avatar).mesh("Head")
    idx = [head.index(n) for n in res.names]
    eyes = {k: v for k, v in eyes.items() if "Eye" in k}
    for eye in find_eyeballs({k: v[0] for k, v in eyes.items()}):
        # each surface of the eye on its own: the bench eyes are an eyeball inside a closed shell 2 mm out
        # (the avatar's own lids sit between the two), no inside by ray parity as one mesh (eye_surfaces); the
        # eyeball, repaired last, holds its bound; the shell's is undone by at most 0.31 mm in a few pairs by
        # the eyeball's repair (against the whole mesh: 0.84 mm, 121 pairs)
        surfaces = eye_surfaces(*eyes[eye.name])
        assert len(surfaces) == 2
        for (pts, tris), slack, share in zip(surfaces, (4e-4, 6e-5), (0.01, 0.0), strict=True):
            near = np.flatnonzero(np.linalg.norm(head.neutral - eye.center, axis=1) < 1.5 * eye.radius)
            d0 = _signed_distance(pts, tris, head.neutral[near])[0]
            for out in (res.offsets[key][idx],):
                d = _signed_distance(pts, tris, (head.neutral[near][None] + out[:, near]).reshape(-1, 3))[0]
                gen = _signed_distance(pts, tris, (head.neutral[near][None] + head.deltas[idx][:, near])
                                       .reshape(-1, 3))[0]
                deep = np.minimum(np.minimum(d0, 0.0)[None].repeat(len(idx), 0).ravel(), gen)
                # issue 10: a lid the generic shape keeps off the eyeball keeps min(its clearance, 0.3 mm);
                # one it tucks in goes no deeper than the generic shape / the neutral
                required = np.where(gen > 0, np.minimum(gen, 3e-4), deep)
                moved = (np.linalg.norm(out[:, near] - head.deltas[idx][:, near], axis=-1) > 1e-9).ravel()
                short = (required - d)[moved]
                assert short.max() <= slack and np.mean(short > 6e-5) <= share
    # the repair is local: only vertices near the eyes change
    changed = np.linalg.norm(res.offsets[key] - ref.offsets[key], axis=-1) > 1e-12
    assert changed.sum() > 0
    centers = [e.center for e in find_eyeballs({k: v[0] for k, v in eyes.items()})]
    dist = np.min([np.linalg.norm(head.neutral - c, axis=1) for c in centers], axis=0)
    assert dist[np.nonzero(changed)[1]].max() < 0.03


def test_eq4_maps_the_generic_template_onto_itself(bench, dev1):
    """Issue 10: implanting dev1's template (the avatar's generic shapes sampled on the capture) through the
    semantic correspondence, eq. (4) with the GCV ridge finds each shape in itself: jawOpen ~1 (it was
    mouthPress 4.7, mouthUpperUp 2.7, mouthFunnel -1.8 with the lips swapped), bounded weights."""
    from usdface.model import FaceRig
    from usdface.transfer import personalize_avatar

    capture = dev1[0]
    t = capture.template
    rig = FaceRig(capture.neutral, capture.triangles, list(t.names), t.deltas, name="template")
    res = personalize_avatar(bench / "dev1" / "avatar.usdc", capture, None, rig=rig, eyelids=False)
    w = res.weights
    diag = np.array([w[res.names.index(n), res.avatar_names.index(n)] for n in res.names])
    assert 0.9 < w[res.names.index("jawOpen"), res.avatar_names.index("jawOpen")] < 1.1
    assert np.median(diag) > 0.9 and diag.min() > 0.7
    assert -0.5 < w.min() and w.max() < 1.5
