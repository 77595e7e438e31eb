"""The fit's per-shape reliability: the sampling variance of the ridge estimate of eqs. (1)+(2)
(:func:`usdface.personalize.fit.estimate_variance`) and the James-Stein factor it gives each shape's
personalization (:func:`usdface.personalize.fit.james_stein`), the cap on the implant's trust in a shape."""

from __future__ import annotations

import warnings

import numpy as np

from usdface.personalize.fit import estimate_variance, fit_blendshapes, james_stein


def _problem(seed=0, n=40, K=4, collinear=True):
    """A small fit: K shapes on n vertices, one frame per shape at weight ~1 plus combination frames; with
    ``collinear`` shapes 0 and 1 are shown only together, at weights that differ by the phone's noise
    (+-0.02: as dev1's mouthPress pair)."""
    rng = np.random.default_rng(seed)
    neutral = rng.normal(size=(n, 3)) * 0.05
    T = rng.normal(size=(K, n, 3)) * 2e-3                         # generic shapes (the prior), metres
    W = np.vstack([np.eye(K), 0.5 * np.eye(K)[[0, 2]] + 0.5 * np.eye(K)[[2, 3]]])
    if collinear:
        W[:, 1] = W[:, 0] + (W[:, 0] > 0) * rng.normal(size=len(W)) * 0.02
    return neutral, T, W


def test_variance_matches_the_monte_carlo_spread_of_the_fit():
    """Gaussian noise of variance s^2 per vertex on the frames: the empirical variance of the fitted shapes
    over 400 noise draws equals ``estimate_variance * s^2`` within sampling error (10 %), for every shape,
    the collinear pair included."""
    neutral, T, W = _problem()
    person = T + np.random.default_rng(1).normal(size=T.shape) * 3e-4
    clean = neutral[None] + np.einsum("fk,knc->fnc", W, person)
    D = np.ones(T.shape[:2])
    reg = 0.05
    sigma = 1e-4                                              # per coordinate: s^2 = 3 sigma^2 per vertex
    rng = np.random.default_rng(2)
    fits = np.array([fit_blendshapes(neutral, clean + rng.normal(size=clean.shape) * sigma, W, T, D, reg)
                     for _ in range(400)])                    # [draws,K,n,3]
    empirical = np.mean(np.sum((fits - fits.mean(axis=0)) ** 2, axis=-1), axis=(0, 2))     # [K] per vertex
    predicted = np.mean(estimate_variance(W, D, reg), axis=0) * 3 * sigma ** 2
    np.testing.assert_allclose(empirical, predicted, rtol=0.1)


def test_a_pair_shown_only_together_is_far_less_certain_than_a_shape_shown_alone():
    """Shapes 0 and 1 always together, at weights equal but for the phone's noise: the data fix their sum
    well and their difference only through that noise, so each one's variance is many times that of a shape
    shown alone at the same weight, although the hat share calls each mostly set by the data;
    apart (shape 1 in its own frame) they are as certain as the others."""
    from usdface.personalize.fit import data_share

    neutral, T, W = _problem()
    D = np.ones(T.shape[:2])
    reg = 1e-3
    var = estimate_variance(W, D, reg).mean(axis=0)
    assert min(var[0], var[1]) > 20 * max(var[2], var[3])
    assert data_share(W, D, reg).mean(axis=0)[:2].min() > 0.5
    _, _, W_apart = _problem(collinear=False)
    var_apart = estimate_variance(W_apart, D, reg).mean(axis=0)
    assert var_apart.max() < 2 * var_apart.min()


def test_james_stein_is_the_positive_part_james_stein_factor():
    D = np.zeros((3, 20, 3))
    D[:, :, 0] = 1e-3                                        # |D|^2 = 1e-6 m^2 on every vertex
    var = np.array([0.0, 0.25e-6, 2e-6])[None].repeat(20, axis=0)                   # [m,K]
    w = np.ones((20, 3))
    np.testing.assert_allclose(james_stein(D, var, w), [1.0, 0.75, 0.0], atol=1e-12)
    w[10:, 1] = 0.0                                          # weights pick the vertices that count
    var[10:, 1] = 1.0
    np.testing.assert_allclose(james_stein(D, var, w)[1], 0.75, atol=1e-12)
    assert james_stein(np.zeros_like(D), var + 1e-12, np.ones((20, 3))).tolist() == [0.0, 0.0, 0.0]


def test_the_fit_caps_its_shape_confidence_by_the_reliability(tmp_path):
    """A generated capture (artist template, the phone's weights +-0.03): the fit reports each shape's
    reliability, and its confidence (what the implant trusts) is never above it nor above the data share."""
    from usdface.io import read_capture
    from usdface.personalize import fit_personalized_shapes
    from usdface.sample import generate_samples

    d = generate_samples(tmp_path / "n4", seed=4, template="artist", scan_noise_m=1.5e-4, weight_noise=0.03)
    cap = read_capture(d / "capture.usda")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = fit_personalized_shapes(cap)
    rel = np.asarray(fit.info["shape_reliability"])
    conf = np.asarray(fit.info["shape_confidence"])
    assert rel.shape == conf.shape == (len(cap.names),)
    assert np.all(conf <= rel + 1e-12)
    assert 0.0 <= rel.min() and rel.max() <= 1.0 and np.median(rel) > 0.5
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fixed = fit_personalized_shapes(cap, reg=0.1)         # no cross-validated noise: no reliability
    assert "shape_reliability" not in fixed.info


def test_the_decomposed_fit_gives_the_same_variance():
    """:meth:`PositionFit.estimate_variance` (from the cross-validation's eigen-decomposition, what the fit
    uses) equals the direct batched solve at every ``reg`` of a grid."""
    from usdface.personalize.fit import PositionFit

    neutral, T, W = _problem(K=5)
    rng = np.random.default_rng(3)
    D = 0.5 + rng.random(T.shape[:2])
    points = neutral[None] + np.einsum("fk,knc->fnc", W, T)
    pf = PositionFit(neutral, points, W, T, D)
    for reg in (1e-4, 1e-2, 1.0):
        np.testing.assert_allclose(pf.estimate_variance(reg), estimate_variance(W, D, reg), rtol=1e-8)


def test_a_personalization_that_is_only_noise_gets_no_trust():
    """The person is the prior, the frames carry Gaussian noise of ``sigma`` per coordinate (what
    ``loo_rmse_best_mm`` measures, :meth:`PositionFit.loo_error`): the fitted personalization ``B_j - T_j``
    is the estimate's noise alone, so its reliability must be ~0. The variance is that of a vertex's three
    coordinates together, as ``|B_j - T_j|^2`` is (with one coordinate's, the James-Stein factor of pure
    noise was ~2/3)."""
    from usdface.personalize.api import _shape_confidence
    from usdface.personalize.fit import PositionFit

    neutral, T, W = _problem(n=60, collinear=False)
    rng = np.random.default_rng(5)
    D = 0.5 + rng.random(T.shape[:2])
    reg, sigma = 0.05, 2e-4
    clean = neutral[None] + np.einsum("fk,knc->fnc", W, T)
    cand = np.arange(len(neutral))
    rel = []
    for _ in range(20):
        points = clean + rng.normal(size=clean.shape) * sigma
        pf = PositionFit(neutral, points, W, T, D)
        info = {"crossval": {"fit": pf, "vertices": cand, "loo_rmse_best_mm": sigma * 1e3}}
        _, reliable = _shape_confidence(None, points, W, T, D, T, reg, info)
        rel.append(reliable(pf.solve(reg)))
    assert np.mean(rel) < 0.2, np.mean(rel, axis=0)        # ~0.05 (clipped fluctuations about 0)


def _dense_variance(W, D, reg):
    """``diag(A_v^-1 W^T W A_v^-1)`` per vertex by dense K x K inverses (pseudo-free: ``A_v`` is definite)."""
    G = W.T @ W
    out = np.empty(D.T.shape)
    for v in range(D.shape[1]):
        Ai = np.linalg.inv(G + reg * np.diag(D[:, v] ** 2))
        out[v] = np.diag(Ai @ G @ Ai)
    return out


def test_variance_is_the_dense_sandwich_at_every_reg_rank_deficient_weights_included():
    """The reduced-basis forms (the batched solve and the cross-validation's eigen-decomposition) equal the
    dense sandwich for non-uniform ``D``, at ``reg`` from the grid's ends, with weights of full rank, of rank
    2 < K (a shape never shown, two always at the same weight), and all zero (variance 0)."""
    from usdface.personalize.fit import PositionFit

    neutral, T, W = _problem(K=5, collinear=False)
    rng = np.random.default_rng(7)
    D = 10.0 ** rng.uniform(-1.0, 1.0, size=T.shape[:2])
    low = np.zeros((6, 5))
    low[:, 0] = low[:, 1] = rng.random(6)
    low[:, 3] = rng.random(6)
    for weights in (W, low, np.zeros_like(low)):
        points = neutral[None] + np.einsum("fk,knc->fnc", weights, T)
        pf = PositionFit(neutral, points, weights, T, D)
        for reg in (1e-5, 1e-2, 1.0, 1e2):
            dense = _dense_variance(weights, D, reg)
            np.testing.assert_allclose(estimate_variance(weights, D, reg), dense, rtol=1e-7, atol=1e-12)
            np.testing.assert_allclose(pf.estimate_variance(reg), dense, rtol=1e-7, atol=1e-12)



def _loo_case():
    """A one-shape, one-frame fit whose leave-one-frame-out error is 0.1 mm per coordinate and whose
    personalization ``d`` has 6 x its square per vertex (three coordinates): ``(fit, capture, rig, prior,
    d)`` for :func:`usdface.transfer.trust.shape_trust` with ``CONFIDENCE = "loo"``."""
    import types

    loo_m = 1e-4
    d = np.full((1, 10, 3), np.sqrt(2.0) * loo_m)                  # |D|^2 = 6 loo^2 per vertex

    class Frames:                                                  # one training frame, jawOpen at 1
        weights = np.ones((1, 1))

        def __len__(self):
            return 1

    capture = types.SimpleNamespace(train=Frames(), names=["jawOpen"], whole_take=None)
    fit = types.SimpleNamespace(info={"crossval": {"loo_rmse_best_mm": loo_m * 1e3}})
    rig = types.SimpleNamespace(names=["jawOpen"])
    prior = np.zeros((1, 10, 3))
    prior[0, :, 1] = 1e-2                                          # moves everywhere: every vertex counts
    return fit, capture, rig, prior, d

def test_the_loo_trust_variant_reads_the_fits_error_per_vertex(monkeypatch):
    """``CONFIDENCE = "loo"``: the fit reports its leave-one-frame-out error per coordinate; the James-Stein
    factor of :func:`usdface.transfer.implant.shape_confidence` takes it per vertex (three coordinates), so a
    personalization whose mean square per vertex is 3 x 2 x that error's square keeps 1 - 1/2 of it."""

    from usdface.transfer import trust

    monkeypatch.setattr(trust, "CONFIDENCE", "loo")
    fit, capture, rig, prior, d = _loo_case()
    trust_, _, _ = trust.shape_trust(fit, capture, rig, [0], prior + d, prior)
    np.testing.assert_allclose(trust_, [0.5], atol=1e-9)           # 1 - 3 loo^2 / 6 loo^2 (excitation 1)


def test_the_trust_undoes_the_ridges_own_shrink():
    """The ridge fit returns about ``h D + e`` for a personalization ``D`` (``h`` the data share); the
    James-Stein factor is the best scale of that for ``hD``, and :func:`usdface.transfer.trust.unshrunk`
    (factor / h, at most 1) the best for ``D``: over noise draws, the unshrunk scale brings the fitted
    personalization nearer the person's than the factor does, and it never exceeds 1 (0 without data)."""
    from usdface.personalize.fit import data_share
    from usdface.transfer.trust import unshrunk

    neutral, T, W = _problem(collinear=False)
    rng = np.random.default_rng(5)
    change = rng.normal(size=T.shape) * 4e-4                      # the person's personalization D, metres
    clean = neutral[None] + np.einsum("fk,knc->fnc", W, T + change)
    D = np.ones(T.shape[:2])
    reg, sigma = 0.5, 1e-4                                         # a ridge that shrinks (h ~ 0.7)
    h = data_share(W, D, reg).mean(axis=0)                         # [K]
    assert 0.5 < h.min() and h.max() < 0.9
    variance = estimate_variance(W, D, reg) * 3 * sigma ** 2       # [n,K] m^2 per vertex
    errors = {"factor": 0.0, "unshrunk": 0.0}
    for _ in range(50):
        fitted = fit_blendshapes(neutral, clean + rng.normal(size=clean.shape) * sigma, W, T, D, reg)
        factor = james_stein(fitted - T, variance, np.ones(variance.shape))
        for name, scale in (("factor", factor), ("unshrunk", unshrunk(factor, h))):
            errors[name] += float(np.sum((scale[:, None, None] * (fitted - T) - change) ** 2))
        assert np.all(unshrunk(factor, h) <= 1.0)
    assert errors["unshrunk"] < 0.9 * errors["factor"], errors          # measured 0.85
    np.testing.assert_array_equal(unshrunk([0.3, 0.8, 0.2], [0.0, 0.5, 0.4]), [0.0, 1.0, 0.5])


def test_the_loo_trust_reads_the_fits_error_in_the_avatar_frame(monkeypatch):
    """The personalization reaches :func:`usdface.transfer.trust.shape_trust` in the avatar frame (the
    registration's similarity, scale ``s``), the fit's leave-one-frame-out error in capture metres: the trust
    must not depend on ``s`` (it compared ``s D`` with the unscaled noise: at ``s = 2`` the factor 1 - 1/2
    read 1 - 1/8)."""

    from usdface.transfer import trust

    monkeypatch.setattr(trust, "CONFIDENCE", "loo")
    fit, capture, rig, prior, d = _loo_case()                      # (in the capture's metres)
    for s in (0.5, 1.0, 2.0):
        got, _, _ = trust.shape_trust(fit, capture, rig, [0], s * (prior + d), s * prior, scale=s)
        np.testing.assert_allclose(got, [0.5], atol=1e-9)


def test_the_weak_shape_ramp_reads_the_effective_weight_against_the_phones_noise():
    """A capture's shape is trusted from 0 at an effective weight (the root of its training energy) of 4
    weight-noise units to 1 at 10, smoothly (WEAK_SHAPE): 7 units is the ramp's middle. Shown at 0.1 in one
    frame and at 0.2 in another, the effective weight is sqrt(0.01 + 0.04) = 5.6 units."""
    from types import SimpleNamespace

    from usdface.personalize.api import WEIGHT_NOISE
    from usdface.transfer.trust import weak_ramp

    capture = SimpleNamespace(whole_take=False, train=[])
    units = np.array([2.0, 4.0, 7.0, 10.0, 15.0])
    ramp, info = weak_ramp(capture, (units * WEIGHT_NOISE) ** 2, list(range(5)))
    np.testing.assert_allclose(ramp, [0.0, 0.0, 0.5, 1.0, 1.0], atol=1e-12)
    assert info == {}
    two, _ = weak_ramp(capture, np.array([0.1 ** 2 + 0.2 ** 2]), [0])
    t = (np.sqrt(0.05) / WEIGHT_NOISE - 4.0) / 6.0
    np.testing.assert_allclose(two, [t * t * (3 - 2 * t)], rtol=1e-12)


def test_a_whole_takes_weak_shape_ramp_reads_the_unique_weight_against_the_takes_own_noise():
    """A take read whole (3 frames or more): the effective weight is the shape's weight beyond what the
    other shapes' explain and the noise's share (``unique_excitation`` at the take's measured noise), the
    ramp's ends 4 and 10 times *that* noise, and the noise no less than TAKE_NOISE_MIN (a take of computed
    weights, without jitter: a ramp over 0 would divide by 0). The given excitation is not read."""
    from usdface.personalize.takefit import unique_excitation, weight_noise
    from usdface.transfer.trust import TAKE_NOISE_MIN, weak_ramp

    class Train(list):
        weights = None

    def take(weights):
        train = Train(range(len(weights)))
        train.weights = np.asarray(weights, dtype=np.float64)
        return type("Capture", (), {"whole_take": True, "train": train})()

    def smoothstep(x, lo, hi):
        t = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
        return t * t * (3 - 2 * t)

    rng = np.random.default_rng(3)
    f = np.arange(60)
    W = np.c_[0.5 + 0.5 * np.sin(f / 5.0), 0.3 + 0.3 * np.cos(f / 7.0), 0.07 * np.sin(f / 2.3)]
    W = W + 0.04 * rng.standard_normal(W.shape)                 # jitter: 0.04, the phone's 0.01 x 4
    noise = weight_noise(W)
    assert 0.03 < noise < 0.05                                  # measured 0.044
    ramp, info = weak_ramp(take(W), np.full(3, 1e6), [2, 0])
    expected = smoothstep(unique_excitation(W, noise)[[2, 0]], 4 * noise, 10 * noise)
    np.testing.assert_allclose(ramp, expected, rtol=1e-12)
    assert 0.0 < ramp[0] < 1.0 and ramp[1] == 1.0              # 0.07 under 0.04 noise: partly shown
    assert info["weight_noise"] == round(noise, 5)
    smooth = np.c_[np.linspace(0, 1, 3), np.full(3, 0.002)]      # three frames, no jitter
    ramp, info = weak_ramp(take(smooth), np.zeros(2), [0, 1])
    assert info["weight_noise"] == TAKE_NOISE_MIN
    expected = smoothstep(unique_excitation(smooth, TAKE_NOISE_MIN), 4e-3, 1e-2)
    np.testing.assert_allclose(ramp, expected, rtol=1e-12)
    assert ramp[0] == 1.0


def _trust_of(info, *, whole_take=False, weights=None):
    """``shape_trust`` of two shapes fitted as 1 mm on each of 4 vertices (prior 0), each shown at weight 1
    (the weak-shape ramp 1) unless ``weights[F,2]``, with the fit's ``info`` (arrays over the capture's two
    shapes) added."""
    from types import SimpleNamespace

    from usdface.transfer.trust import shape_trust

    names = ["jawOpen", "tongueOut"]
    weights = np.eye(2) if weights is None else np.asarray(weights, dtype=np.float64)
    deltas = np.full((2, 4, 3), 1e-3 / np.sqrt(3))               # |D| = 1 mm at each vertex
    capture = SimpleNamespace(names=names, whole_take=whole_take,
                              train=type("Train", (list,), {"weights": weights})(range(len(weights))))
    fit = SimpleNamespace(rig=SimpleNamespace(deltas=deltas),
                          info={"train_weights": weights, "prior_deltas": np.zeros_like(deltas), **info})
    # the avatar's rig names them in the other order: its shapes [1, 0] are the capture's [0, 1]
    trust, report, weak = shape_trust(fit, capture, SimpleNamespace(names=names[::-1]), [1, 0], None, None)
    assert report == {}
    return trust, weak


def test_the_trust_of_each_path_is_the_smaller_of_its_factors():
    """``shape_trust`` per path, on constructed factors (the personalization's power 1 mm^2 a vertex):
    measured frames' and weights' noise: the reliability as the person's scale (factor / data share: 0.3 /
    0.5), capped by the weights' budget (here none); no reliability, a re-estimation: the data share capped
    by the sensitivity's James-Stein factor (1 - 0.75); a take read whole: the share capped by the factor of
    the leak and the scans' error together (1 - (0.25 + 0.25))."""
    z = np.zeros((4, 2))
    noise, _ = _trust_of({"shape_confidence": [0.2, 0.2], "shape_reliability": [0.3, 0.9],
                       "data_share": [0.5, 0.6], "weight_leak": z, "weight_sensitivity": np.zeros((2, 4, 3))})
    np.testing.assert_allclose(noise, [0.6, 1.0], rtol=1e-12)
    sens = np.zeros((2, 4, 3))
    sens[0, :, 0] = np.sqrt(0.75) * 1e-3
    fit, _ = _trust_of({"shape_confidence": [0.5, 0.5], "weight_sensitivity": sens})
    np.testing.assert_allclose(fit, [0.25, 0.5], rtol=1e-12)
    quarter = np.c_[np.full(4, 0.25e-6), np.zeros(4)]
    take, weak = _trust_of({"shape_confidence": [0.9, 0.9], "weight_leak": quarter,
                            "frame_variance": quarter})
    np.testing.assert_allclose(take, [0.5, 0.9], rtol=1e-12)
    assert not weak.any()


def test_a_captures_weak_shape_ramp_reads_the_root_of_the_training_energy():
    """A shape shown at 0.12 and 0.16 in two frames: effective weight sqrt(0.0144 + 0.0256) = 0.2, 5 noise
    units (the ramp at 1/6 of its way, weak); its weights' sum, 0.28 (7 units), would be the middle."""
    from usdface.personalize.api import WEIGHT_NOISE

    trust, weak = _trust_of({"shape_confidence": [1.0, 1.0]}, weights=[[0.12, 1.0], [0.16, 0.0]])
    t = (0.2 / WEIGHT_NOISE - 4.0) / 6.0
    np.testing.assert_allclose(trust, [t * t * (3 - 2 * t), 1.0], rtol=1e-9)
    assert weak.tolist() == [True, False]


def test_a_given_rig_is_trusted_whole():
    """No training frames (a rig given as it is) or no fit: every shape's trust is 1, none weak."""
    from types import SimpleNamespace

    from usdface.transfer.trust import shape_trust

    rig = SimpleNamespace(names=["jawOpen", "tongueOut"])
    fit = SimpleNamespace(info={}, rig=None)
    for capture, f in ((SimpleNamespace(train=[], names=rig.names), fit),
                       (SimpleNamespace(train=[0], names=rig.names), None)):
        trust, report, weak = shape_trust(f, capture, rig, [0, 1], None, None)
        np.testing.assert_array_equal(trust, [1.0, 1.0])
        assert report == {} and not weak.any()
