"""personalize on the project's own sample assets: accuracy vs the sample truth, regions, input untouched, and
Z-up cm / Y-up m / nested rotated variants written with the sample helper's avatar writer."""

from __future__ import annotations

import hashlib
import warnings
from pathlib import Path

import numpy as np
import pytest
from input_helpers import _capture

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


def _rmse(a, b):
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=-1))))


@pytest.fixture(scope="module")
def sample_fit(samples):
    from usdface.io import read_capture
    from usdface.personalize import fit_personalized_shapes

    capture = read_capture(samples / "capture.usda")
    return capture, fit_personalized_shapes(capture).rig


@pytest.fixture(scope="module")
def sample_result(samples, sample_fit, tmp_path_factory):
    from usdface.transfer import personalize_avatar

    avatar = samples / "avatar.usda"
    before = hashlib.sha256(avatar.read_bytes()).hexdigest()
    out = tmp_path_factory.mktemp("s") / "sample.usda"
    res = personalize_avatar(avatar, sample_fit[0], out)
    return res, before


def test_sample_accuracy_regions_input(samples, sample_result):
    """The sample: closer to the person than the generic avatar on the Head and the Mouth, the lips kept apart
    by the correspondence, the input untouched."""
    from usdface.io.usd_rig import read_avatar
    from usdface.transfer.scoring import score_mesh

    res, before = sample_result
    avatar = read_avatar(samples / "avatar.usda")
    npz = np.load(samples / "truth" / "avatar_truth.npz")
    for m in avatar.meshes:
        if not m.names:
            continue
        truth = np.array([npz[f"{m.name}/{n}"] for n in m.names]) @ m.source.to_internal[:3, :3].T
        s = score_mesh(m.names, m.deltas, res.offsets[m.source.prim], truth)
        assert s.whole_ratio <= (0.5 if m.name == "Head" else 0.9), (m.name, s.whole_ratio)
        # no Head shape worse than generic (the rigid Mouth's jawOpen is +0.09 mm, see docs/personalize.md)
        if m.name == "Head":
            assert s.per_shape_delta.max() <= 0.05, (m.name, s.worst_shape())
    # 15 lower-lip vertices landed on the upper lip with the neutral-only closest points
    assert res.report["correspondence"]["side_swaps_jawOpen"] == 0
    # the lips pass through each other only where the generic shapes do (the lip check of the report)
    lips = res.report["lips"]
    assert {"mouthClose", "mouthPressLeft", "mouthRollUpper"} <= set(lips)
    for shape, row in lips.items():
        if row["generic"][0] == 0:
            assert row["output"][0] == 0, (shape, row)
    assert hashlib.sha256((samples / "avatar.usda").read_bytes()).hexdigest() == before
    assert res.report["registration"]["fitness"] > 0.95


@pytest.fixture(scope="module")
def sample_result_without_eyelids(samples, sample_fit):
    """The reference for the variants, which carry no eye meshes (``write_rig_usd`` writes the rigs only)."""
    from usdface.transfer import personalize_avatar

    return personalize_avatar(samples / "avatar.usda", sample_fit[0], None, rig=sample_fit[1], eyelids=False)


@pytest.mark.parametrize("variant", [
    {"up_axis": "Z", "meters_per_unit": 0.01},
    {"up_axis": "Y", "meters_per_unit": 1.0},
    {"up_axis": "Z", "meters_per_unit": 0.01, "parents": ("World", "Character"), "parent_scale": 2.0,
     "parent_rotate_x_deg": 35.0},
], ids=["zup_cm", "yup_m", "zup_nested_scaled_rotated"])
def test_sample_variants_same_offsets(samples, sample_fit, sample_result_without_eyelids, tmp_path, variant):
    from usdface.io.avatar_writer import write_rig_usd
    from usdface.io.usd_rig import read_avatar
    from usdface.transfer import personalize_avatar
    from usdface.transfer.register import similarity_from_pairs

    original = read_avatar(samples / "avatar.usda")
    path = write_rig_usd(original.meshes, tmp_path / "variant.usda", **variant)
    res = personalize_avatar(path, sample_fit[0], None, rig=sample_fit[1], eyelids=False)
    ref = sample_result_without_eyelids
    var = read_avatar(path)
    for m in original.meshes:
        v = next(x for x in var.meshes if x.name == m.name)
        sim = similarity_from_pairs(m.neutral, v.neutral)  # where the variant put the avatar in the world
        back = np.einsum("ij,knj->kni", sim.rotation.T, res.offsets[v.source.prim]) / sim.scale
        back = back[[v.index(n) for n in m.names]]
        want = ref.offsets[m.source.prim]
        # float32 points in metres at ~1.6 m from the origin are quantised to ~1.2e-7 m; the non-rigid
        # registration amplifies that ~10x on this coarse head, hence 5e-4 rather than exact equality
        assert np.sqrt(np.mean((back - want) ** 2)) / np.sqrt(np.mean(want ** 2)) < 5e-4


def test_a_smaller_capture_gives_the_same_personalization(tmp_path):
    """Review: the field's smoothing (and the join of the offset modes) took the capture's mean edge as the
    correspondence measured it on the capture placed on the avatar, then multiplied it by the registration's
    scale again: a capture 10x smaller than its person (a wrong unit) smoothed over 9 rings instead of 2 and
    moved the offsets by 12 % of the personalization. The same capture at a tenth of its size (registration
    scale ~10) now gives the same offsets."""
    import dataclasses

    from usdface.api import read_avatar
    from usdface.model import Capture, FaceRig, Frames
    from usdface.transfer import personalize_avatar

    cap, avatar = _capture(), read_avatar(A)
    s = 0.1
    t, f = cap.template, cap.frames
    small = Capture(cap.neutral * s, cap.triangles,
                    FaceRig(t.neutral * s, t.triangles, list(t.names), t.deltas * s, name=t.name),
                    Frames(f.points * s, f.weights, f.role, f.label), cap.names)
    small = dataclasses.replace(small, metadata=dict(cap.metadata or {}))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = personalize_avatar(avatar, cap, None, method="dt")
        b = personalize_avatar(avatar, small, None, method="dt")
    key = avatar.mesh("Head").key
    change = np.abs(a.offsets[key] - avatar.mesh("Head").deltas).max()
    assert np.abs(a.offsets[key] - b.offsets[key]).max() < 1e-3 * change


def test_a_capture_turned_moved_and_in_centimetres_gives_the_same_personalization():
    """The capture's frame is the phone app's: turned, placed anywhere, in another unit. With the default
    method (the fit, its alignment and trust, the map, the field, the eyelids) the offsets are those of the
    capture as it was, to 1e-4 of the personalization (dev3 in a copy turned 35 degrees, moved 0.8 m or at
    100x: within 1.5e-4 mm).

    The capture is first sheared by 2 % (x += 0.02 y: a person's face is never exactly mirror-symmetric).
    The sample's capture and avatar face are, exactly, and the registration's optimum is then two-fold: two
    mirror images, +-5.4e-5 rad of yaw either side of the symmetric placement, which is a saddle - and where
    the shape-motion landmarks start, exactly, so the rounding of the capture's placement picked the side
    (stop 52: the turned copy went the other way on one machine, 2e-3 of the personalization apart)."""
    import dataclasses

    from scipy.spatial.transform import Rotation

    from usdface.api import read_avatar
    from usdface.model import Capture, FaceRig, Frames
    from usdface.transfer import personalize_avatar

    cap, avatar = _capture(), read_avatar(A)
    cap = _sheared(cap, 0.02)
    R = Rotation.from_rotvec(np.radians(35.0) * np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2]))
    s, shift = 100.0, np.array([40.0, -20.0, 70.0])

    def place(p):
        return s * R.apply(np.asarray(p).reshape(-1, 3)).reshape(np.shape(p)) + shift

    t, f = cap.template, cap.frames
    moved = Capture(place(cap.neutral), cap.triangles,
                    FaceRig(place(t.neutral), t.triangles, list(t.names),
                            s * R.apply(t.deltas.reshape(-1, 3)).reshape(t.deltas.shape), name=t.name),
                    Frames(place(f.points), f.weights, f.role, f.label), cap.names)
    moved = dataclasses.replace(moved, metadata=dict(cap.metadata or {}))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = personalize_avatar(avatar, cap, None)
        b = personalize_avatar(avatar, moved, None)
    for mesh in avatar.meshes:
        if mesh.key not in a.offsets:
            continue
        change = np.abs(a.offsets[mesh.key] - mesh.deltas).max()
        assert change > 1e-4, mesh.name                        # the sample's person moves each mesh
        assert np.abs(a.offsets[mesh.key] - b.offsets[mesh.key]).max() < 1e-4 * change, mesh.name


def _sheared(cap, amount):
    """``cap`` with every point and delta sheared, ``x += amount * y`` (the same linear map on all)."""
    import dataclasses

    from usdface.model import Capture, FaceRig, Frames

    shear = np.eye(3)
    shear[0, 1] = amount

    def move(p):
        return np.asarray(p) @ shear.T

    t, f = cap.template, cap.frames
    return dataclasses.replace(
        Capture(move(cap.neutral), cap.triangles,
                FaceRig(move(t.neutral), t.triangles, list(t.names), move(t.deltas), name=t.name),
                Frames(move(f.points), f.weights, f.role, f.label), cap.names),
        metadata=dict(cap.metadata or {}))


def _generic_on_capture(samples, monkeypatch, source):
    """The avatar's generic shapes the map puts on the capture of the sample folder ``samples`` (capture
    frame, m), with the map registered from the ``source`` face (``"template"``: forced; None: personalize's
    own choice), and the report's ``correspondence.source``."""
    from usdface.transfer import face_map, pipeline

    chosen = face_map.choose_source
    if source == "template":
        monkeypatch.setattr(face_map, "choose_source", lambda reg, person=None: ("template", reg))
    got = {}
    real = pipeline.avatar_shapes_on_capture

    def record(*args, **kwargs):
        got["g"] = real(*args, **kwargs)[0]
        return real(*args, **kwargs)

    monkeypatch.setattr(pipeline, "avatar_shapes_on_capture", record)
    res = pipeline.personalize_avatar(samples / "avatar.usda", samples / "capture.usda", None)
    monkeypatch.setattr(face_map, "choose_source", chosen)
    reg = res.report["registration"]
    rotation, scale = np.asarray(reg["rotation"]), reg["scale"]
    return np.einsum("ij,kni->knj", rotation, got["g"]) / scale, res.report["correspondence"]["source"]


def test_the_map_is_registered_from_the_face_closest_to_the_avatar(tmp_path, monkeypatch):
    """A generated sample's avatar is the person's (a digital double): the person's neutral scan lies closer
    to it than the template's neutral (another identity), so the map is registered from the scan, and it puts
    the avatar's generic shapes on the capture where they belong: with ``template="generic"`` the capture's
    template *is* the avatar's generic rig sampled at the true correspondence, so its deltas are the truth.
    Seed 2: from the person's scan 0.054 mm RMS from it, from the template's neutral 0.103 mm (the committed
    sample's two identities are alike: 0.051 mm both ways)."""
    from usdface.io import read_capture
    from usdface.sample import generate_samples

    folder = generate_samples(tmp_path / "generic2", seed=2, template="generic")
    truth = read_capture(folder / "capture.usda").template.deltas
    mine, source = _generic_on_capture(folder, monkeypatch, None)
    old, forced = _generic_on_capture(folder, monkeypatch, "template")
    assert (source, forced) == ("person", "template")
    err_mine, err_old = _rmse(mine, truth), _rmse(old, truth)
    assert err_mine < 0.75 * err_old, (err_mine, err_old)


def test_choose_source_ranks_as_the_registration_does():
    """Fitness first (two decimals), then the lower residual; the template without a person's neutral."""
    from usdface.transfer.face_map import choose_source
    from usdface.transfer.register import Registration, Similarity

    def reg(residual, fitness=1.0):
        return Registration(Similarity(1.0, np.eye(3), np.zeros(3)), residual, fitness, "test", 0.01)

    t = reg(1.2e-3)
    assert choose_source(t) == ("template", t)
    p = reg(0.4e-3)
    assert choose_source(t, (np.zeros((3, 3)), p)) == ("person", p)
    assert choose_source(t, (np.zeros((3, 3)), reg(1.5e-3)))[0] == "template"
    # a lower residual over fewer of the vertices is no closer face
    assert choose_source(t, (np.zeros((3, 3)), reg(0.4e-3, fitness=0.9)))[0] == "template"
    assert choose_source(t, (np.zeros((3, 3)), reg(0.4e-3, fitness=0.996)))[0] == "person"


def test_a_template_near_the_person_does_not_hide_the_person(samples):
    """The implant carries each shape's change from the fit's prior, so the prior is its reference. Before
    stop 47 the fit's cross-validation could take the capture's template as the prior, and a template that
    already holds part of the person then hid that part from the avatar: with the sample's template moved
    half way to the person's true shapes the face error went from 0.25 to ~0.6 of the generic's, the
    better the template the worse the avatar. The prior is now the avatar's own shapes: a template nearer
    the person changes the result by little either way."""
    import dataclasses

    from usdface.io import read_capture
    from usdface.io.usd_rig import read_avatar
    from usdface.transfer import personalize_avatar
    from usdface.transfer.scoring import score_mesh

    avatar = read_avatar(samples / "avatar.usda")
    capture = read_capture(samples / "capture.usda")
    ct = np.load(samples / "truth" / "capture_truth.npz")
    names = [str(n) for n in ct["names"]]
    person = ct["deltas"][[names.index(n) for n in capture.template.names]]
    npz = np.load(samples / "truth" / "avatar_truth.npz")
    head = avatar.mesh("Head")
    truth = np.array([npz[f"Head/{n}"] for n in head.names]) @ head.source.to_internal[:3, :3].T
    ratios = []
    own = capture.template.deltas
    for share in (0.0, 0.5):
        template = dataclasses.replace(capture.template, deltas=own + share * (person - own))
        res = personalize_avatar(avatar, dataclasses.replace(capture, template=template), None)
        assert set(res.report["fit"]["prior_choice"]) == {"avatar"}
        ratios.append(score_mesh(head.names, head.deltas, res.offsets[head.source.prim], truth).whole_ratio)
    assert ratios[0] < 0.35, ratios
    assert ratios[1] < ratios[0] + 0.05, ratios          # before: 0.27 -> 0.6


def test_a_run_builds_the_face_surfaces_scene_once_for_both_registrations(samples, sample_fit, monkeypatch):
    """The person's neutral and the template's are registered onto one closest-point scene of the avatar's
    face surface (``register.face_surface``, built once per run; the twice-subdivided head's has 450k
    triangles), not one each."""
    from usdface.transfer import face_map, personalize_avatar, pipeline, register

    built, used = [], []
    real_surface, real_register = register.face_surface, register.register_face

    def counted_surface(*args, **kwargs):
        built.append(real_surface(*args, **kwargs))
        return built[-1]

    def recorded_register(*args, surface=None, **kwargs):
        used.append(surface)
        return real_register(*args, surface=surface, **kwargs)

    for module in (pipeline, register):
        monkeypatch.setattr(module, "face_surface", counted_surface)
    for module in (pipeline, face_map):
        monkeypatch.setattr(module, "register_face", recorded_register)
    res = personalize_avatar(samples / "avatar.usda", sample_fit[0], None, rig=sample_fit[1], eyelids=False)
    assert "template_registration" in res.report["correspondence"]          # both registrations ran
    assert len(used) == 2 and len(built) == 1
    assert used[0] is built[0] and used[1] is built[0]
