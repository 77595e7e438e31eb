"""The retarget map's gaze channels (stop 39): a gaze channel (``eyeLook*``, which an engine turns the eyes
with) driven by its namesake capture shape alone - eq. (4) with entries held at 0, solved as the reduced
system per row (:func:`usdface.transfer.retarget.retarget_weights` ``held``, :func:`gaze_held`) - and
``map_gaze="free"`` (``--map-gaze free``), eq. (4) as it was."""

from __future__ import annotations

import json

import numpy as np
import pytest
from region_cv import parabola_mu, region_errors

from usdface.arkit import GAZE_NAMES
from usdface.cli import main
from usdface.transfer.retarget import gaze_held, retarget_weights


def test_gaze_held_holds_a_gaze_column_but_its_namesake():
    """Held: a gaze channel's column except the row of its own name; a gaze row's other entries are free
    (the lid following the gaze) but for the other gaze columns; ``"free"`` holds nothing."""
    rows = ["eyeBlinkLeft", "eyeLookUpLeft", "jawOpen"]
    cols = ["eyeLookUpLeft", "eyeLookDownLeft", "eyeWideLeft", "jawOpen"]
    np.testing.assert_array_equal(gaze_held(rows, cols), [[1, 1, 0, 0], [0, 1, 0, 0], [1, 1, 0, 0]])
    assert gaze_held(rows, cols, "free") is None
    assert len(GAZE_NAMES) == 8 and all(n.startswith("eyeLook") for n in GAZE_NAMES)
    with pytest.raises(ValueError, match="namesake, free"):
        gaze_held(rows, cols, "pure")


def test_held_entries_solve_the_reduced_system_of_each_row():
    """Each row is eq. (4) minimised over its free entries (the held ones exactly 0): the stacked least
    squares on the free columns (face rows, the other meshes' rows targeting the prior, the ridge),
    unbounded and in [0, 1]; nothing held is the unconstrained solve."""
    from scipy.optimize import lsq_linear

    rng = np.random.default_rng(11)
    k, n = 6, 70
    basis = rng.normal(size=(k, n, 3))
    basis[1] = basis[0] + 0.1 * rng.normal(size=(n, 3))
    targets = np.einsum("jk,knc->jnc", rng.random((4, k)), basis) + 0.1 * rng.normal(size=(4, n, 3))
    prior = np.eye(k)[[0, 2, 3, 5]]
    other = rng.normal(size=(k, 30))
    gram = other @ other.T
    held = np.zeros((4, k), dtype=bool)
    held[0, [1, 4]] = held[1, 1] = held[3, [0, 1, 2]] = True             # row 2: nothing held
    A = basis.reshape(k, -1).T
    mu = 0.01
    lam = mu * np.trace(A.T @ A) / k
    for bounds in (None, (0.0, 1.0)):
        w = retarget_weights(basis, targets, mu=mu, prior=prior, elsewhere=gram, held=held, bounds=bounds)
        assert np.all(w[held] == 0.0)
        for j in range(4):
            f = ~held[j]
            stacked = np.vstack([A[:, f], other.T[:, f], np.sqrt(lam) * np.eye(k)[:, f]])
            rhs = np.concatenate([targets[j].ravel(), other.T @ prior[j], np.sqrt(lam) * prior[j]])
            ref = (np.linalg.lstsq(stacked, rhs, rcond=None)[0] if bounds is None
                   else lsq_linear(stacked, rhs, bounds=bounds).x)
            np.testing.assert_allclose(w[j, f], ref, atol=1e-6 if bounds else 1e-9)
    whole = retarget_weights(basis, targets, mu=mu, prior=prior, elsewhere=gram, bounds=(0.0, 1.0))
    nothing = retarget_weights(basis, targets, mu=mu, prior=prior, elsewhere=gram, bounds=(0.0, 1.0),
                               held=np.zeros((4, k), dtype=bool))
    np.testing.assert_allclose(nothing, whole, atol=1e-10)
    assert np.abs(whole[held]).max() > 0.05                      # what the held entries would have taken


def test_mu_by_regions_folds_solve_the_held_map():
    """``mu="auto"`` with ``held``: each region predicted by the map solved on the others with the same
    entries held (explicit reduced solves per region, row and ``mu`` of the grid), then the parabola's
    vertex - the closed form picks the same ``mu``, and another than without the constraint."""
    g = np.linspace(0.0, 1.0, 30)
    x, y = np.meshgrid(g, g)
    points = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    rng = np.random.default_rng(1)

    def bumps(count, width):
        centres, dirs = rng.random((count, 2)), rng.normal(size=(count, 3))
        return np.stack([np.exp(-np.sum((points[:, :2] - c) ** 2, axis=1) / width)[:, None] * d
                         for c, d in zip(centres, dirs, strict=True)])

    basis = bumps(5, 0.02)          # the avatar's shapes; the person's: two of them plus motion none has
    targets = basis[[0, 2]] + 0.6 * np.stack([bumps(3, 0.01).sum(axis=0) for _ in range(2)])
    prior = np.eye(5)[[0, 2]]
    held = np.zeros((2, 5), dtype=bool)
    held[0, 1] = held[1, [3, 4]] = True
    _, mu = retarget_weights(basis, targets, return_mu=True, positions=points, prior=prior, held=held)
    _, mu_free = retarget_weights(basis, targets, return_mu=True, positions=points, prior=prior)
    _, expected = parabola_mu(region_errors(basis, targets, prior, points, held=held))
    assert mu == pytest.approx(expected, rel=1e-6)
    assert mu != pytest.approx(mu_free, rel=1e-3)


@pytest.fixture(scope="module")
def sample_maps(samples, tmp_path_factory):
    """The sample's map by ``usdface retarget`` with the default gaze and with ``--map-gaze free`` (on the
    fit of ``--prior template``, the sample's fit before stop 47)."""
    out = tmp_path_factory.mktemp("gaze")
    base = ["retarget", str(samples / "avatar.usda"), str(samples / "capture.usda"), "-q"]
    assert main([*base, "-o", str(out / "map.json")]) == 0
    # the fit the old map was measured on: the template prior the cross-validation chose on the sample
    # before stop 47 (the default fit now takes the avatar's shapes; the map's rule is the same)
    assert main([*base, "-o", str(out / "free.json"), "--map-gaze", "free", "--prior", "template"]) == 0
    return {k: json.loads((out / f"{k}.json").read_text()) for k in ("map", "free")}


def _gaze_cross(doc):
    """The weights in a gaze channel's column from a capture shape of another name, ``{(row, col): w}``."""
    return {(s, t): w for s, row in doc["map"].items() for t, w in row.items() if t in GAZE_NAMES and t != s}


def test_the_sample_maps_gaze_channels_are_pure(sample_maps):
    """By default no capture shape but its namesake drives a gaze channel (the sample's blink took
    ``eyeLookDownLeft`` 0.30, its look down ``eyeLookOutLeft`` 1.0: an engine's eyes turned on every blink),
    each gaze channel keeps its namesake, and the JSON records the setting."""
    doc = sample_maps["map"]
    assert doc["meta"]["map_gaze"] == "namesake"
    assert _gaze_cross(doc) == {}
    for name in GAZE_NAMES:
        assert doc["map"][name][name] > 0.8
    assert doc["map"]["eyeBlinkLeft"]["eyeBlinkLeft"] > 0.9


def test_gaze_free_is_the_map_as_it_was(sample_maps):
    """``--map-gaze free`` is eq. (4) as before stop 39: the gaze channels take whatever capture shapes
    explain them, so the cross-terms the brief found are back (the sample's blink drives its look down, its
    look down drives its look out, its look up its eye-wide), where the default map has none. (Pinned to the
    JSON's six decimals until stop 49: the registration onto the face surface moved the sample's map - its
    cross-validated ``mu`` 0.0035 -> 0.0139, the blink's look-down 0.297 -> 0.093 - so the test keeps the
    property, not one fit's figures.)"""
    doc = sample_maps["free"]
    assert doc["meta"]["map_gaze"] == "free"
    assert 0.0 < doc["meta"]["mu"] < 1.0
    cross = _gaze_cross(doc)
    assert cross[("eyeBlinkLeft", "eyeLookDownLeft")] > 0.05
    assert cross[("eyeLookDownLeft", "eyeLookOutLeft")] > 0.3
    assert doc["map"]["eyeLookUpLeft"]["eyeWideLeft"] > 0.3
    assert len(cross) > len(_gaze_cross(sample_maps["map"])) == 0


def test_map_gaze_is_checked_before_any_work(samples, tmp_path, capsys, monkeypatch):
    """A bad ``--map-gaze`` is a usage error naming the choices; the API's ``map_gaze`` an ``OptionError``
    naming the fix, before the avatar is read."""
    from usdface import api
    from usdface.errors import OptionError
    from usdface.transfer import pipeline

    monkeypatch.setattr(pipeline, "crop_avatar", lambda *a, **k: pytest.fail("work started"))
    with pytest.raises(SystemExit) as done:
        main(["retarget", str(samples / "avatar.usda"), str(samples / "capture.usda"), "-o",
              str(tmp_path / "m.json"), "--map-gaze", "pure"])
    assert done.value.code == 2
    assert "'namesake', 'free'" in capsys.readouterr().err
    with pytest.raises(OptionError, match=r"unknown map gaze 'pure' \(map_gaze \(--map-gaze\)\)") as err:
        api.write_retarget_map(samples / "avatar.usda", samples / "capture.usda", tmp_path / "m.json",
                               map_gaze="pure")
    assert "namesake, free" in str(err.value)
    assert not (tmp_path / "m.json").exists()
