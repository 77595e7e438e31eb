"""The procedural sample assets: deterministic, consistent, symmetric, readable, with a known truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import _no_traceback, _usdface
from scipy.spatial import cKDTree

import usdface.io  # noqa: F401  (registers the schemas before a test opens a stage)
from usdface.arkit import ARKIT_NAMES, mirror_name
from usdface.cli import main
from usdface.errors import OutputExistsError
from usdface.io.capture_folder import read_capture_folder
from usdface.io.usd_capture import read_capture_usd
from usdface.io.usd_rig import read_avatar
from usdface.sample import build_samples, generate_samples

MIRROR = np.array([-1.0, 1.0, 1.0])
PAIRS = [(n, mirror_name(n)) for n in ARKIT_NAMES if n.endswith("Left")]
CENTRE = [n for n in ARKIT_NAMES if mirror_name(n) == n]


@pytest.fixture(scope="module")
def capture(samples):
    return read_capture_usd(samples / "capture.usda")


@pytest.fixture(scope="module")
def capture_truth(samples):
    return dict(np.load(samples / "truth" / "capture_truth.npz"))


@pytest.fixture(scope="module")
def avatar(samples):
    return read_avatar(samples / "avatar.usda")


def _files(root):
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())


def f32(a):
    """``a`` rounded to float32, as capture.usda stores geometry (exact=False)."""
    return np.asarray(a).astype(np.float32).astype(np.float64)


def test_regeneration_is_byte_identical_to_the_committed_assets(samples, tmp_path, capsys):
    out = tmp_path / "again"
    assert main(["sample", str(out)]) == 0
    assert "capture 1" in capsys.readouterr().out
    assert _files(out) == _files(samples)
    assert "capture/neutral.obj" not in _files(out)            # the capture folder only with --folder
    differ = [f for f in _files(samples) if (out / f).read_bytes() != (samples / f).read_bytes()]
    assert differ == [], f"regenerated files differ from sample_assets/: {differ[:10]}"
    # an existing folder is refused without --force (exit 2, nothing touched), replaced with it
    stamp = (out / "avatar.usda").stat().st_mtime_ns
    assert main(["sample", str(out)]) == 2
    assert "--force" in capsys.readouterr().err
    assert (out / "avatar.usda").stat().st_mtime_ns == stamp
    assert main(["sample", str(out), "--force"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again"]  # no temp folders left behind


def test_generate_refuses_non_empty_folder(tmp_path):
    (tmp_path / "keep.txt").write_text("mine")
    with pytest.raises(OutputExistsError, match="force"):
        generate_samples(tmp_path)
    assert _files(tmp_path) == ["keep.txt"]


def test_other_seed_gives_another_person():
    a, b = build_samples(0), build_samples(1)
    assert a["capture"].neutral.shape == b["capture"].neutral.shape
    assert np.abs(a["capture_truth"]["deltas"] - b["capture_truth"]["deltas"]).max() > 5e-4
    assert np.abs(a["capture"].neutral - b["capture"].neutral).max() > 1e-3


def test_artist_template_is_another_rig_for_the_same_person():
    """``--template artist`` (the dev3 regime): the same person, frames and avatar; only the capture's
    template changes, and it is further from the person's true shapes than the avatar's own generic template
    is."""
    g, a = build_samples(2), build_samples(2, "artist")
    for key in ("neutral", "deltas", "test_weights"):
        np.testing.assert_array_equal(g["capture_truth"][key], a["capture_truth"][key])
    np.testing.assert_array_equal(g["capture"].frames.points, a["capture"].frames.points)

    def rmse(t):
        return np.sqrt(np.mean(np.sum((t["template_deltas"] - t["deltas"]) ** 2, axis=-1)))

    assert rmse(a["capture_truth"]) > 1.3 * rmse(g["capture_truth"])
    assert a["meta"]["template"] == "artist" and "template" not in g["meta"]
    with pytest.raises(ValueError, match="artist"):
        build_samples(0, "other")


def test_noise_options_change_only_the_frames_and_the_reported_weights():
    """``--scan-noise`` / ``--weight-noise``: the same person, truth and template; the frames and the phone's
    weights deviate from the noise-free ones by the asked amounts; meta.json records them."""
    base, noisy = build_samples(3), build_samples(3, scan_noise_m=1.5e-4, weight_noise=0.03)
    for key in ("neutral", "deltas", "template_deltas", "test_weights"):
        np.testing.assert_array_equal(base["capture_truth"][key], noisy["capture_truth"][key])
    clean = build_samples(3, scan_noise_m=0.0, weight_noise=0.0)
    scan = noisy["capture"].frames.points - clean["capture"].frames.points
    assert 1.3e-4 < np.std(scan) < 1.7e-4
    reported = noisy["capture"].frames.weights - clean["capture"].frames.weights
    assert 0.005 < np.std(reported) < 0.04            # clipped to [0, 1]: less than 0.03 where a weight is 0
    assert noisy["meta"]["noise"] == {"scan_m": 1.5e-4, "weights": 0.03}
    with pytest.raises(ValueError, match=">= 0"):
        build_samples(0, scan_noise_m=-1.0)


def test_negative_seed_is_refused_before_any_work(tmp_path, capsys):
    """A user trial: ``usdface sample out --seed -1`` ended in a numpy traceback (``ValueError: expected
    non-negative integer``, exit status 1); now the option is refused in one line (status 2), and the API
    says which argument is wrong, before the folder is made."""
    from usdface.cli import main

    with pytest.raises(SystemExit) as exit_:
        main(["sample", str(tmp_path / "neg"), "--seed", "-1"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "--seed" in err and ">= 0" in err and "Traceback" not in err
    for seed in (-1, 1.5, True):
        with pytest.raises(ValueError, match="seed must be a whole number >= 0"):
            generate_samples(tmp_path / "api", seed=seed)
        with pytest.raises(ValueError, match="seed must be a whole number >= 0"):
            build_samples(seed)
    assert not (tmp_path / "neg").exists() and not (tmp_path / "api").exists()


def test_capture_topology_like_arkit(capture):
    n, t = len(capture.neutral), len(capture.triangles)
    assert 1100 <= n <= 1300 and 2000 <= t <= 2500
    # a face mask: one outer border plus holes for two eyes and the mouth = 4 boundary loops
    edges = np.sort(np.concatenate([capture.triangles[:, [0, 1]], capture.triangles[:, [1, 2]],
                                    capture.triangles[:, [2, 0]]]), axis=1)
    uniq, count = np.unique(edges, axis=0, return_counts=True)
    assert count.max() == 2  # manifold
    border = uniq[count == 1]
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components
    g = sp.coo_matrix((np.ones(len(border)), (border[:, 0], border[:, 1])), shape=(n, n))
    labels = connected_components(g, directed=False)[1]
    assert len(np.unique(labels[np.unique(border)])) == 4
    # metres, centred near the origin like ARKit's face anchor; the face looks down +z
    extent = capture.neutral.max(0) - capture.neutral.min(0)
    assert 0.1 < extent[0] < 0.18 and 0.12 < extent[1] < 0.2
    assert np.abs(capture.neutral.mean(0)).max() < 0.06
    assert len(capture.train) == 52 and len(capture.test) == 20
    assert capture.names == list(ARKIT_NAMES)


def test_frames_are_neutral_plus_true_shapes_within_scan_noise(capture, capture_truth):
    T = capture_truth["deltas"]
    assert list(capture_truth["names"]) == capture.names
    np.testing.assert_array_equal(capture.neutral, f32(capture_truth["neutral"]))
    for frames, w_true in ((capture.train, capture_truth["train_weights"]),
                           (capture.test, capture_truth["test_weights"])):
        residual = frames.points - capture.neutral - np.einsum("fk,knc->fnc", w_true, T)
        assert 0.85e-4 < residual.std() < 1.15e-4          # 0.1 mm scan noise, nothing else
        assert np.abs(residual.mean()) < 2e-6
        # the phone's weights are slightly wrong: noise ~0.01, clipped to [0, 1]
        err = frames.weights - w_true
        assert 0.004 < np.abs(err).mean() < 0.02 and np.abs(err).max() < 0.06
        assert frames.weights.min() >= 0 and frames.weights.max() <= 1
    # training frame j asks for shape j; cross-talk is real (e.g. a blink also closes the other eye a bit)
    w = capture_truth["train_weights"]
    assert (np.diag(w) >= 0.85).all()
    k = ARKIT_NAMES.index
    assert 0.1 <= w[k("eyeBlinkLeft"), k("eyeBlinkRight")] <= 0.35
    assert w[k("mouthClose"), k("jawOpen")] >= 0.3
    assert w[k("eyeLookInLeft"), k("eyeLookOutRight")] >= 0.7


def test_template_is_the_generic_rig_and_truth_differs_by_millimetres(capture, capture_truth):
    np.testing.assert_allclose(capture.template.deltas, capture_truth["template_deltas"], rtol=0, atol=1e-7)
    T, G = capture_truth["deltas"], capture_truth["template_deltas"]
    per_shape = np.linalg.norm(T - G, axis=-1).max(axis=1) * 1000  # mm
    assert (per_shape > 0.5).all() and (per_shape < 10).all()
    assert np.median(per_shape) > 1.5
    size = np.linalg.norm(T, axis=-1).max(axis=1) * 1000
    assert size[ARKIT_NAMES.index("jawOpen")] > 20 and size[ARKIT_NAMES.index("eyeBlinkLeft")] > 5
    # the template has another identity than the person (a few mm) but the same topology
    np.testing.assert_array_equal(capture.template.triangles, capture.triangles)
    d = np.linalg.norm(capture.template.neutral - capture.neutral, axis=1) * 1000
    assert 2 < d.mean() < 10
    # the accuracy story: with the true shapes the test frames are explained down to the noise, with the
    # generic template clearly not (eq. 5 RMSE with the phone's weights)
    te = capture.test
    def rmse(D):
        return np.sqrt(((capture.neutral + np.einsum("fk,knc->fnc", te.weights, D) - te.points) ** 2)
                       .sum(-1).mean())
    assert rmse(T) < 0.5 * rmse(G)


def _mirror_map(points, atol):
    dist, idx = cKDTree(points).query(points * MIRROR)
    assert dist.max() < atol
    return idx


def test_shapes_are_left_right_mirror_symmetric(capture_truth, avatar):
    names = list(capture_truth["names"])
    for key, pts in (("deltas", capture_truth["neutral"]), ("template_deltas", capture_truth["neutral"])):
        D = capture_truth[key]
        m = _mirror_map(pts, 2e-6)
        for left, right in PAIRS:
            np.testing.assert_allclose(D[names.index(right)][m] * MIRROR, D[names.index(left)], atol=2e-6)
        for c in CENTRE:
            np.testing.assert_allclose(D[names.index(c)][m] * MIRROR, D[names.index(c)], atol=2e-6)
    head = avatar.mesh("Head")
    m = _mirror_map(head.neutral, 2e-6)
    for left, right in PAIRS:
        np.testing.assert_allclose(head.deltas[head.index(right)][m] * MIRROR, head.deltas[head.index(left)],
                                   atol=2e-6)
    assert np.abs(head.deltas[head.index("eyeBlinkLeft")][head.neutral[:, 0] < -0.01]).max() == 0.0


def test_avatar_reads_with_52_shapes_in_cm_y_up(avatar, samples):
    assert avatar.meters_per_unit == 0.01 and avatar.up_axis == "Y"
    assert avatar.default_prim.strip("/") == "Avatar"
    by_name = {m.name: m for m in avatar.meshes}
    assert set(by_name) == {"Head", "Mouth"}          # eyes carry no shapes
    head = by_name["Head"]
    assert 2000 <= head.n_vertices <= 8000 and head.names == list(ARKIT_NAMES)
    assert set(by_name["Mouth"].names) == {"jawForward", "jawLeft", "jawRight", "jawOpen", "tongueOut"}
    # internal metres: the head sits around (0, 1.60, 0.02) m, about 15 x 21 cm
    centre = 0.5 * (head.neutral.min(0) + head.neutral.max(0))
    np.testing.assert_allclose(centre, [0.0, 1.60, 0.02], atol=0.02)
    assert 0.13 < np.ptp(head.neutral[:, 0]) < 0.17
    # sparse where a shape moves < 70% of the mesh
    sparse = [p is not None for p in head.source.point_indices]
    assert sum(sparse) >= 45
    moved = (np.linalg.norm(head.deltas, axis=-1) > 0).mean(axis=1)
    assert (moved < 0.7).tolist() == sparse
    from pxr import Usd, UsdGeom, UsdSkel
    stage = Usd.Stage.Open(str(samples / "avatar.usda"))
    for eye in ("EyeLeft", "EyeRight"):
        prim = stage.GetPrimAtPath(f"/Avatar/{eye}")
        assert prim.IsA(UsdGeom.Mesh) and UsdSkel.BindingAPI(prim).GetSkeletonRel().GetTargets()
    eyes = np.array(UsdGeom.Mesh(stage.GetPrimAtPath("/Avatar/EyeLeft")).GetPointsAttr().Get())
    assert eyes.mean(0)[0] > 2.0  # the subject's left is +x, as in ARKit


def test_avatar_truth_matches_capture_truth_on_the_shared_face(samples, avatar, capture_truth):
    """The truth exists on both meshes: mapped into the capture frame (meta.json), nearby avatar and capture
    vertices carry nearly the same true offsets (the fields are smooth away from the lip slit)."""
    meta = json.loads((samples / "truth" / "meta.json").read_text())
    at = np.load(samples / "truth" / "avatar_truth.npz")
    tr = meta["avatar_to_capture"]
    R = np.array(tr["R"])
    head = avatar.mesh("Head")
    head_cap = (head.neutral * 100 - tr["head_center_cm"] - tr["origin_cm"]) @ R.T / 100
    dist, idx = cKDTree(head_cap).query(capture_truth["neutral"])
    assert np.median(dist) < 3e-3            # the capture mask lies on the avatar's face (5 mm avatar grid)
    near = dist < 1.5e-3
    assert near.sum() > 300
    errors, sizes = [], []
    for k, name in enumerate(capture_truth["names"]):
        a = at[f"Head/{name}"].astype(np.float64)[idx[near]] @ R.T / 100   # cm avatar -> m capture frame
        c = capture_truth["deltas"][k][near]
        errors.append(np.sqrt(((a - c) ** 2).sum(-1).mean()))
        sizes.append(np.sqrt((c ** 2).sum(-1).mean()))
    errors, sizes = np.array(errors), np.array(sizes)
    assert np.median(errors) < 1e-4 and (errors < 0.2 * sizes + 1e-5).all()
    # units: cm, like the bench truth files (jawOpen moves the chin by centimetres)
    assert 1.0 < np.linalg.norm(at["Head/jawOpen"], axis=1).max() < 5.0
    assert sorted(k for k in at.files if k.startswith("Mouth/")) == sorted(
        f"Mouth/{n}" for n in avatar.mesh("Mouth").names)


def test_folder_variant_adds_the_capture_folder_and_changes_nothing_else(samples, sample_capture_folder):
    """``usdface sample OUTDIR --folder`` writes the committed files byte for byte plus capture/, and that
    folder is the capture of capture.usda: the usda equals the folder's capture rounded to float32."""
    root = sample_capture_folder.parent
    folder_files = _files(sample_capture_folder)
    assert _files(root) == sorted(_files(samples) + [f"capture/{f}" for f in folder_files])
    differ = [f for f in _files(samples) if (root / f).read_bytes() != (samples / f).read_bytes()]
    assert differ == []
    assert len([f for f in folder_files if f.startswith("train/") and f.endswith(".obj")]) == 52
    folder = read_capture_folder(sample_capture_folder)
    usd = read_capture_usd(samples / "capture.usda")
    assert usd.names == folder.names == list(ARKIT_NAMES)
    assert usd.frames.role == folder.frames.role and usd.frames.label == folder.frames.label
    np.testing.assert_array_equal(usd.triangles, folder.triangles)
    np.testing.assert_array_equal(usd.neutral, f32(folder.neutral))
    np.testing.assert_array_equal(usd.frames.points, f32(folder.frames.points))
    np.testing.assert_array_equal(usd.frames.weights, folder.frames.weights)
    np.testing.assert_array_equal(usd.template.neutral, f32(folder.template.neutral))
    np.testing.assert_allclose(usd.template.deltas, folder.template.deltas, rtol=0, atol=1e-7)
    # and the folder holds the generator's exact (micrometre-rounded) values
    truth = np.load(samples / "truth" / "capture_truth.npz")
    np.testing.assert_array_equal(folder.neutral, truth["neutral"])
    np.testing.assert_allclose(folder.template.deltas, truth["template_deltas"], rtol=0, atol=1e-12)


def test_avatar_passes_pixar_validators(samples):
    from pxr import Usd, UsdValidation

    validators = [v for v in UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
                  if not v.GetMetadata().name.startswith("usdface")]
    assert len(validators) > 20
    stage = Usd.Stage.Open(str(samples / "avatar.usda"))
    errors = UsdValidation.ValidationContext(validators).Validate(stage)
    assert [f"{e.GetName()}: {e.GetMessage()}" for e in errors] == []


def test_sample_assets_size(samples):
    """The committed sample_assets/ stays under the spec's 10 MB (README, avatar, capture.usda, truth)."""
    size = sum(p.stat().st_size for p in samples.rglob("*") if p.is_file())
    assert size < 10e6
    assert not (samples / "capture").exists()


def test_a_failed_picture_takes_the_new_sample_folder_with_it(tmp_path, monkeypatch, capsys):
    """A user trial: ``usdface sample out --picture out.png`` whose picture failed (a full disk, Ctrl-C) left
    the new sample folder behind as if the run had finished. The folder this run created goes with the
    failure, as export's outputs do; a folder written into with --force stays."""
    import errno

    from usdface.cli import main
    from usdface.sample import picture

    def full_disk(*_a, **_k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(picture, "render_sample_picture", full_disk)
    assert main(["sample", str(tmp_path / "s"), "--picture", str(tmp_path / "s.png"), "-q"]) == 2
    assert "No space left on device" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "kept").mkdir()
    (tmp_path / "kept" / "mine.txt").write_text("mine")
    kept = ["sample", str(tmp_path / "kept"), "--force", "--picture", str(tmp_path / "k.png"), "-q"]
    assert main(kept) == 2
    assert (tmp_path / "kept" / "mine.txt").read_text() == "mine"


def test_sample_picture_extension_checked_before_the_samples_are_written(tmp_path):
    res = _usdface("sample", "s4", "--picture", "x.pgn", cwd=tmp_path)
    _no_traceback(res)
    assert "x.pgn" in res.stderr and "x.png" in res.stderr
    assert list(tmp_path.iterdir()) == []


def test_sample_json_still_draws_the_picture(tmp_path):
    """``sample --json --picture`` returned before drawing the picture; it is drawn and named in the JSON."""
    res = _usdface("sample", "s5", "--json", "--picture", "s5.png", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc["ok"] and Path(doc["picture"]).name == "s5.png"
    assert (tmp_path / "s5.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_sample_picture_heads_fill_their_panels(tmp_path):
    """A trial (stop 42): ``sample out --picture p.png`` drew each head in about a quarter of its panel (the
    3D axes' margins: the head half the picture's height); it is two thirds of it now, nothing cut off."""
    import matplotlib.image

    assert main(["sample", str(tmp_path / "s"), "--picture", str(tmp_path / "p.png"), "-q"]) == 0
    image = matplotlib.image.imread(tmp_path / "p.png")[:, :, :3]
    height, width = image.shape[:2]
    panel = (image[:, : width // 5] < 0.9).any(axis=2)          # the neutral's panel, ink where not white
    panel[:60] = False                                          # its title
    rows, cols = np.flatnonzero(panel.any(axis=1)), np.flatnonzero(panel.any(axis=0))
    assert rows.max() - rows.min() >= 0.6 * height, (rows.min(), rows.max(), height)
    assert rows.max() < height - 5 and cols.min() > 5 and cols.max() < width // 5 - 5   # not cut off


def test_sample_picture_says_which_sample_it_shows(tmp_path, monkeypatch):
    """Stop 43: ``sample out --seed 3 --template artist --picture p.png`` drew a picture with no title, which
    looked like the default sample's. It is titled with the seed, the template and the noise, over what the
    panels show (as the render pictures name their file and mesh)."""
    from usdface.sample import picture

    titles = []
    real = picture.render_sample_picture
    monkeypatch.setattr(picture, "render_sample_picture",
                        lambda *a, **kw: (titles.append(kw.get("title")), real(*a, **kw))[1])
    argv = ["sample", str(tmp_path / "s"), "--seed", "3", "--template", "artist", "--weight-noise", "0.03",
            "--picture", str(tmp_path / "p.png"), "-q"]
    assert main(argv) == 0
    assert titles == ["usdface sample, seed 3: artist template, scan noise 0.1 mm, weight noise 0.03\n"
                      "the avatar neutral and in expressions; the person's capture mask"]
    assert (tmp_path / "p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
