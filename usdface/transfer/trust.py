"""How far the implant trusts each shape's personalization (issue 10: never worse than generic).

A shape's trust ``c_j`` in [0, 1] scales the person's change ``B_j - P_j`` the implant carries onto the
avatar (0: the avatar's generic shape stays, 1: the person's as fitted). It is the smaller of two
positive-part James-Stein factors, each the personalization against one of its estimate's errors: the
frames' noise (the shape's reliability, :func:`usdface.personalize.fit.james_stein`, taken as the scale
of the person's shape rather than of the fit's shrunk estimate: :func:`unshrunk`) and the weights' noise,
its expected leak into the shape as the capture shows the noise (:func:`leak_trust`) plus the change a
re-estimation of the weights makes (:func:`sensitivity_trust`), summed (:func:`weight_error_trust`); times a
ramp to 0 for shapes the frames show only weakly (:func:`weak_ramp`). Without the measured noise (a take
read whole, another method) the fit's share of the shape the frames set stands in for the last. Arrays in,
arrays out: ``fit`` is a :class:`usdface.personalize.FitResult`, ``capture`` a
:class:`usdface.model.Capture`."""

from __future__ import annotations

import numpy as np

from ..personalize.api import SIGNIFICANCE
from ..personalize.fit import james_stein
from ..personalize.weak import TAKE_NOISE_MIN, WEAK_SHAPE, weak_ramp
from .implant import shape_confidence

__all__ = ["WEAK_SHAPE", "TAKE_NOISE_MIN", "CONFIDENCE", "TEST_READING", "WITHHELD", "leak_trust",
           "raised_by_reading", "sensitivity_trust", "shape_trust", "test_frames_reading", "unshrunk",
           "weak_ramp", "weight_error_trust"]

#: :data:`WEAK_SHAPE`, :data:`TAKE_NOISE_MIN` and :func:`weak_ramp` live in :mod:`usdface.personalize.weak`
#: (the plain fit returns a weakly shown shape to its own prior by the same ramp); re-exported here.
#: The per-shape trust (see :func:`shape_trust`): "noise" (the estimate's errors, the weights' noise
#: measured on the capture), "fit" (capped by the fit's data share, as before stop 37) or "loo" (James-Stein
#: with the leave-one-frame-out error).
CONFIDENCE = "noise"
#: Raise a trust to the lower confidence bound of the capture's test frames' reading of the shape's
#: personalization scale where that bound is above it (:func:`raised_by_reading`; "noise" only).
TEST_READING = True
#: A shape is withheld where its trust keeps it closer to the avatar's generic shape than to the person's
#: (below one half, as the report's untrusted shapes): only there does the test frames' reading raise it
#: (:func:`raised_by_reading`).
WITHHELD = 0.5


def sensitivity_trust(deltas, prior, sensitivity, *, moving: float = 0.1) -> np.ndarray:
    """``[K]`` in [0, 1]: how far each shape's personalization ``D = deltas - prior`` (``[K,n,3]`` on the
    capture, metres) stands above the change the weights' noise makes in it (``sensitivity[K,n,3]``,
    :func:`usdface.personalize.api.weight_sensitivity`): the positive-part James-Stein factor ``max(0, 1 -
    s^2 / d^2)`` with ``s^2``, ``d^2`` the mean squared sensitivity and personalization over the vertices the
    personalization moves (more than ``moving`` of its peak). A shape the weights' errors decide stays near
    the prior, the avatar's own shape."""
    s = np.asarray(sensitivity, dtype=np.float64)
    return _moving_james_stein(deltas, prior, np.einsum("knc,knc->nk", s, s), moving)


def leak_trust(deltas, prior, leak, *, moving: float = 0.1) -> np.ndarray:
    """``[K]`` in [0, 1]: how far each shape's personalization ``D = deltas - prior`` (``[K,n,3]`` on the
    capture, metres) stands above the error the weights' noise leaks into it, ``leak[n,K]`` (m^2, the
    expected squared error at each vertex, ``FitResult.info["weight_leak"]``,
    :func:`usdface.personalize.fit.weight_leak_variance`): ``max(0, 1 - l^2 / d^2)`` over the vertices the
    personalization moves, as :func:`sensitivity_trust`. A shape the frames show once, beside a large shape
    whose weight errs in that frame by the noise the capture shows, stays near the prior; on a capture whose
    weights are exact (the phone mesh's own) nothing leaks and the shape keeps its personalization."""
    return _moving_james_stein(deltas, prior, leak, moving)


def weight_error_trust(deltas, prior, leak, sensitivity, *, moving: float = 0.1, direction=None,
                       along=None, level: float = SIGNIFICANCE) -> np.ndarray:
    """``[K]`` in [0, 1]: how far each shape's personalization ``D = deltas - prior`` (``[K,n,3]`` on the
    capture, metres) stands above the weights' error as both measures see it: the positive-part James-Stein
    factor ``max(0, 1 - (l^2 + s^2) / d^2)`` with ``l^2`` the expected leak (``leak[n,K]``, m^2,
    :func:`leak_trust`) and ``s^2`` the change a re-estimation of the weights makes (``sensitivity[K,n,3]``,
    :func:`sensitivity_trust`), mean squares over the vertices the personalization moves.

    The two are not one estimate twice. The leak is the error's expectation from the noise level the capture
    shows; the sensitivity is this capture's own draw as the geometry re-estimates it, from shapes that have
    already absorbed part of it. A single weight error of one frame (one degree of freedom) is often several
    times its expectation, and the re-estimation sees only part of it: each factor alone (the smaller of the
    two, before stop 39) left a generated capture's ``mouthShrugLower`` 0.108 mm and another's
    ``jawForward`` 0.086 mm worse than generic (factors 0.81 / 0.41: its fitted personalization was that
    frame's ``jawOpen`` error, orthogonal to the person's). Their sum is the error budget of the weights.

    With ``direction[K,n,3]`` (unit, capture metres) and ``along[K]`` (m^2), the leak's largest pattern and
    its variance summed over the vertices (:func:`usdface.personalize.fit.weight_leak_direction`), the
    personalization's projection on that pattern is one draw, not an average over the vertices. Where a draw
    at the ``1 - level`` quantile (chi-square with one degree of freedom: 3.84 ``along`` at 5 %), kept at the
    factor above, would cost more than the rest of the personalization gains (``c q along > (2 - c) R``, ``R``
    the rest's energy less the rest of the budget: the shape could end worse than the generic), the projection
    counts (James-Stein, its variance taken off) only if it stands out of that quantile - taken at ``level``
    over every shape whose leak has a pattern (``along > 0``; Bonferroni: the rule is for every shape of the
    capture) - and the rest against the rest of the budget, never above the factor above; elsewhere that
    factor stands. Without it a single weight error three times its expectation (``jawOpen`` in
    ``tongueOut``'s one frame, generated person 103) passed as the person: the expected leak was a fifth of
    the fitted change, the change was that error. The family is not the shapes at risk alone: a large draw
    leaves its shape's rest small and so puts it at risk, a family chosen by the draws it tests (with eq.
    3's ``D`` from the avatar prior, one-frame shapes of generated people passed a 2.5-2.9 sigma ``jawOpen``
    error as the person, each the one shape at risk and tested at 5 %: stop 54)."""
    s = np.asarray(sensitivity, dtype=np.float64)
    variance = np.asarray(leak, dtype=np.float64) + np.einsum("knc,knc->nk", s, s)
    if direction is None or along is None:
        return _moving_james_stein(deltas, prior, variance, moving)
    d, d2, mov = _moving(deltas, prior, moving)
    power = np.sum(d2 * mov, axis=1)                                                  # [K] m^2, summed
    budget = np.sum(variance.T * mov, axis=1)
    lam = np.minimum(np.asarray(along, dtype=np.float64), budget)
    proj2 = np.einsum("knc,knc->k", d, np.asarray(direction, dtype=np.float64) * mov[..., None]) ** 2
    proj2 = np.minimum(proj2, power)
    from scipy.special import gammaincinv

    quantile = 2.0 * gammaincinv(0.5, 1.0 - level)                                   # chi2_1, 3.84 at 5 %
    rest = np.maximum(power - proj2 - (budget - lam), 0.0)
    before = np.clip(1.0 - budget / np.maximum(power, 1e-300), 0.0, 1.0)
    # a draw that large along the pattern, taken at the old factor, outweighs what the rest gains
    risky = before * quantile * lam > (2.0 - before) * rest
    # one test per shape whose leak has a pattern, at risk or not: together no more than ``level`` of captures
    # has any of them pass a draw. Not the shapes at risk alone: a large draw puts its own shape at risk (it
    # leaves the rest small), so that family was chosen by the draw it tests, often one shape tested at 5 %
    quantile = 2.0 * gammaincinv(0.5, 1.0 - level / max(int(np.count_nonzero(lam > 0)), 1))
    stands_out = proj2 > quantile * lam
    kept = rest + np.where(stands_out, proj2 - lam, 0.0)
    # the test only lowers the factor: a projection that stands out is the person, not a reason to trust the
    # shape past its error budget (taken up to the test's own factor, a generated capture's `mouthShrugLower`
    # went +0.031 -> +0.077 mm and another's `mouthPressRight` +0.081 -> +0.133 over generic, stop 47)
    return np.where(risky, np.minimum(before, np.clip(kept / np.maximum(power, 1e-300), 0.0, 1.0)), before)


def raised_by_reading(trust, reading, variance, *, level: float = SIGNIFICANCE) -> np.ndarray:
    """``[K]``: each ``trust[K]`` below :data:`WITHHELD` raised to the lower confidence bound of the test
    frames' reading of the shape's personalization scale (``reading[K]``, ``variance[K]``,
    :func:`test_frames_reading`), where that bound is above it; elsewhere the trust as it is.

    The trust is read on the training frames; the capture's test frames are an independent reading of the
    same scale ``c`` (the fitted personalization's scale nearest the person's). Where the reading says with
    confidence that ``c >= L > trust``, the trust ``L`` is nearer ``c`` than the trust was: the shape's error
    on the capture, ``(trust - c)^2 |d|^2`` plus what no scale reaches, falls. ``L = a - z sd``, one-sided,
    ``z`` the normal ``1 - level / m`` quantile over the ``m`` shapes tested (those the test frames show whose
    trust withholds them, below :data:`WITHHELD`; Bonferroni: together no more than ``level`` of captures
    has any shape raised past its scale), capped at 1 (never past the fitted shape).

    Only where the reading is informative: where ``z sd < 1``, the bound a full personalization (``c = 1``)
    would read is above 0. A shape the test frames show weakly has a reading of large spread whose variance
    model is least sure (a generated capture's ``eyeLookOutRight`` read -43 +- 21); its bound is not used
    however far its reading lies. Trust is only raised: a reading below the trust says nothing the training
    frames' budget has not (the test frames show the shapes in the same mixtures, so they do not see the
    cross-talk that lowers a trust). Only withheld shapes: raised wherever the bound was above the trust,
    a generated capture's ``jawOpen`` went 0.821 -> 0.871 (its scale on the capture 1.008: right) and over
    the avatar's line, +0.043 -> +0.068 mm, a transfer floor no capture-side reading sees; and on strongly
    shown shapes the reading sits above the truth by more than its spread says (stop 54, h115)."""
    from scipy.special import ndtri

    t = np.asarray(trust, dtype=np.float64)
    a = np.asarray(reading, dtype=np.float64)
    sd = np.sqrt(np.asarray(variance, dtype=np.float64))
    tested = np.isfinite(sd) & (t < WITHHELD)
    z = float(ndtri(1.0 - level / max(int(tested.sum()), 1)))
    informative = tested & (z * sd < 1.0)
    bound = np.where(informative, np.clip(a - z * np.where(informative, sd, 0.0), 0.0, 1.0), 0.0)
    return np.maximum(t, bound)


def test_frames_reading(fit, capture, cap_idx) -> tuple[np.ndarray, np.ndarray] | None:
    """``(a[J], var[J])``: the capture's test frames' reading of the scale of the fitted personalization
    ``B - P`` of the shapes ``cap_idx`` (:func:`usdface.personalize.amplitude.personalization_reading`), with
    the reports' error variances at the phone's noise the fit's amplitude step measured
    (``FitResult.info["test_amplitude"]["weight_noise"]``), or None where the fit read no amplitude on test
    frames (no test frames, the step off, another method) or has no prior."""
    info = fit.info
    amplitude, prior = info.get("test_amplitude"), info.get("prior_deltas")
    test = getattr(capture, "test", None)             # a stand-in capture may carry no test frames
    if amplitude is None or prior is None or test is None or len(test) == 0:
        return None
    from ..personalize.amplitude import personalization_reading
    from ..personalize.weights import weight_error_variance

    deltas = np.asarray(fit.rig.deltas, dtype=np.float64)
    variance = weight_error_variance(capture.neutral, test.points, test.weights, deltas,
                                     np.ones(test.weights.shape, dtype=bool),
                                     noise=float(amplitude["weight_noise"]))
    a, var = personalization_reading(capture.neutral, test.points, test.weights, deltas, np.asarray(prior),
                                     variance)
    return a[cap_idx], var[cap_idx]


def unshrunk(factor, share) -> np.ndarray:
    """``[K]`` in [0, 1]: the James-Stein ``factor[K]`` of the fit's personalization against its frames'
    noise (``FitResult.info["shape_reliability"]``) as the scale of the *person's* personalization.

    The cross-validated ridge fit already shrinks each shape's personalization ``D`` towards its prior by
    about its data share ``h = share[K]`` (the hat matrix's diagonal, ``FitResult.info["data_share"]``): the
    estimate is ``h D + e``. The factor ``|hD|^2 / (|hD|^2 + var e)`` is the best scale of that estimate for
    ``hD``; for ``D`` it is ``<hD, D> / (|hD|^2 + var e) = factor / h``. Capped at 1: never past the fitted
    shape. 0 where ``h`` is 0 (the frames say nothing of the shape). Per shape on the capture, the scale
    nearest the truth averaged 0.85-1.41 on the bench cases where the factor averaged 0.42-0.87 (stop 38).

    Only the frames' noise is undone so: its energy is spread over every vertex and frame, so its expected
    size, which the factor reads, is what a capture has. The weights' leak (:func:`leak_trust`) and their
    sensitivity (:func:`sensitivity_trust`) are one weight error of one frame each, a single draw whose
    energy has one degree of freedom (one capture in twelve three times its expectation): their budget
    (:func:`weight_error_trust`), read from the expectation, stays a cap."""
    f = np.asarray(factor, dtype=np.float64)
    h = np.asarray(share, dtype=np.float64)
    return np.where(h > 0, np.minimum(1.0, f / np.maximum(h, 1e-300)), 0.0)


def _moving(deltas, prior, moving):
    """``(d[K,n,3], d2[K,n], mov[K,n])``: the personalization ``deltas - prior``, its squared lengths and the
    vertices where it moves more than ``moving`` of its peak (where the trust's factors are read)."""
    d = np.asarray(deltas, dtype=np.float64) - np.asarray(prior, dtype=np.float64)
    d2 = np.einsum("knc,knc->kn", d, d)
    return d, d2, d2 > moving ** 2 * np.maximum(d2.max(axis=1, keepdims=True), 1e-300)


def _moving_james_stein(deltas, prior, variance, moving) -> np.ndarray:
    """The James-Stein factor of ``deltas - prior`` against ``variance[n,K]`` over the vertices where the
    personalization moves more than ``moving`` of its peak (:func:`_moving`)."""
    d, _, mov = _moving(deltas, prior, moving)
    return james_stein(d, np.asarray(variance, dtype=np.float64), mov.T)


def shape_trust(fit, capture, rig, b_idx, person_deltas, prior_av, *,
                scale: float = 1.0) -> tuple[np.ndarray, dict, np.ndarray]:
    """Per-shape trust in the personalization, times a ramp to 0 for shapes the training frames show only
    weakly (:func:`weak_ramp`). ``CONFIDENCE = "noise"`` (default): the smaller of the shape's reliability
    (``FitResult.info["shape_reliability"]``, as the person's scale: :func:`unshrunk`) and
    :func:`weight_error_trust` (the weights' leak and sensitivity summed); where the
    fit did not measure the weights' noise (no ``weight_leak``: a take read whole, laplacian) or the frames'
    (no ``shape_reliability``: a fixed ``reg``), as ``"fit"``: the fit's own share of each shape set by the
    data rather than the prior (the hat matrix, ``FitResult.info["shape_confidence"]``, already no more than
    the reliability), capped by :func:`sensitivity_trust`; ``"loo"``: the
    positive-part James-Stein factor (:func:`usdface.transfer.implant.shape_confidence`) with the fit's
    leave-one-frame-out error as the noise (capture metres; ``person_deltas``, ``prior_av`` ``[J,n,3]`` are in
    the avatar frame, ``scale`` its metres per capture metre, the registration's similarity scale, so the
    noise is taken times ``scale``). 1 without training frames (a given rig). Returns ``(trust[J],
    report, weak[J])``, the report saying how the excitation was measured (``{}`` for a capture), ``weak``
    the shapes the frames show too weakly (ramp below one half), as against those shown but measured no
    better than their noise."""
    n_shapes = len(b_idx)
    if len(capture.train) == 0 or fit is None:
        return np.ones(n_shapes), {}, np.zeros(n_shapes, dtype=bool)
    w = np.asarray(fit.info.get("train_weights", capture.train.weights), dtype=np.float64)
    cap_idx = [list(capture.names).index(rig.names[i]) for i in b_idx]
    excitation = np.sum(w[:, cap_idx] ** 2, axis=0)
    ramp, info = weak_ramp(capture, excitation, cap_idx)
    share = fit.info.get("shape_confidence")
    if CONFIDENCE in ("noise", "fit") and share is not None:
        trust = np.clip(np.asarray(share, dtype=np.float64)[cap_idx], 0.0, 1.0)
        prior = fit.info.get("prior_deltas")
        leak = fit.info.get("weight_leak")
        sens = fit.info.get("weight_sensitivity")
        if prior is not None:
            fitted, prior = np.asarray(fit.rig.deltas)[cap_idx], np.asarray(prior)[cap_idx]
            if CONFIDENCE == "noise" and leak is not None and fit.info.get("shape_reliability") is not None:
                # the share stood in for the weights' noise; measured, the errors set the trust themselves
                reliability = np.clip(np.asarray(fit.info["shape_reliability"])[cap_idx], 0.0, 1.0)
                if fit.info.get("data_share") is not None:
                    reliability = unshrunk(reliability, np.asarray(fit.info["data_share"])[cap_idx])
                leak = np.asarray(leak)[:, cap_idx]
                if fit.info.get("contact_correction") is not None:
                    # the weights' budget is of the fit before the contact step; the correction's part the
                    # frames do not carry is the template's gap, no signal of theirs (noisy:115's
                    # mouthPressRight: 13 of 28.9 mm^2 where it moves, trusted 0.86 at a budget of 4.0)
                    fitted = fitted - np.asarray(fit.info["contact_correction"])[cap_idx]
                direction, along = fit.info.get("weight_leak_direction"), fit.info.get("weight_leak_along")
                if direction is not None and along is not None:
                    direction, along = np.asarray(direction)[cap_idx], np.asarray(along)[cap_idx]
                weights_error = (leak_trust(fitted, prior, leak) if sens is None else
                                 weight_error_trust(fitted, prior, leak, np.asarray(sens)[cap_idx],
                                                    direction=direction, along=along))
                trust = np.minimum(reliability, weights_error) * ramp
                # the test frames' own reading of the personalization's scale, where it is sure of more
                read = test_frames_reading(fit, capture, cap_idx) if TEST_READING else None
                if read is not None:
                    trust = raised_by_reading(trust, *read)
                return trust, info, ramp < 0.5
            if sens is not None:
                # and no more than the personalization stands above what the weights' noise makes of it
                trust = np.minimum(trust, sensitivity_trust(fitted, prior, np.asarray(sens)[cap_idx]))
            elif CONFIDENCE == "noise" and leak is not None:
                # a take read whole: no leave-one-frame-out reliability (a frame's neighbours predict it)
                # and no re-estimation, but the leak of the noise its weights show and the error its scans'
                # noise leaves (measured from the residual of its hundreds of frames): one error budget
                variance = np.asarray(leak)[:, cap_idx]
                if fit.info.get("frame_variance") is not None:
                    variance = variance + np.asarray(fit.info["frame_variance"])[:, cap_idx]
                trust = np.minimum(trust, leak_trust(fitted, prior, variance))
        return trust * ramp, info, ramp < 0.5
    loo = (fit.info.get("crossval") or {}).get("loo_rmse_best_mm")
    if loo is None:
        return ramp, info, ramp < 0.5
    diff = np.asarray(person_deltas) - np.asarray(prior_av)
    mag = np.maximum(np.linalg.norm(person_deltas, axis=-1), np.linalg.norm(prior_av, axis=-1))
    moving = mag > 0.1 * np.maximum(mag.max(axis=1, keepdims=True), 1e-300)
    # the fit reports the error per coordinate; the factor wants it per vertex (three coordinates), in the
    # frame of the personalization (the avatar's: the registration scales the capture by ``scale``)
    noise = np.sqrt(3.0) * float(loo) * 1e-3 * float(scale)
    return shape_confidence(diff, excitation, noise, moving=moving) * ramp, info, ramp < 0.5
