"""Shapes the training frames show too weakly to be measured: returned towards their prior.

A shape seen at an effective weight ``w`` (the root of its training energy ``sum_f w_fj^2``) is known only
as well as ``w`` stands above the phone's weight noise ``sigma``: what a frame's residual leaves where the
shape moves is taken up by it at ~``1 / w``, and an error ``sigma`` in its one weight is an error
``sigma / w`` in its size. Below ``4 sigma`` no frame measures it (``jawLeft`` shown at 0.07 in one frame of
dev3 was fitted 1.81 mm from the person where its prior is 1.18), above ``10 sigma`` the frames do. The
smooth ramp between (:func:`weak_ramp`) is the implant's (``usdface.transfer.trust``): there it returns a
shape to the avatar's generic one, here, in the plain fit, to the fit's own prior ``T_j`` of eq. (2)
(:func:`toward_prior`). Arrays in, arrays out."""

from __future__ import annotations

import numpy as np

__all__ = ["WEIGHT_NOISE", "WEAK_SHAPE", "TAKE_NOISE_MIN", "toward_prior", "weak_ramp"]

#: The phone's weights are uncertain by about this much (ARKit reports, per frame and shape): the prior width
#: of the re-estimation that measures each shape's sensitivity to them
#: (:func:`usdface.personalize.api.weight_sensitivity`) and the scale of a weakly shown shape
#: (:data:`WEAK_SHAPE`).
WEIGHT_NOISE = 0.04
#: Effective training weight (sqrt of the shape's training energy) below which a shape stays at its prior
#: (the avatar's generic shape in the implant, eq. 2's ``T_j`` in the plain fit), and above which the
#: capture's version is trusted in full: where the weights' uncertainty is more than a quarter (4 sigma)
#: resp. less than a tenth (10 sigma) of the weight the shape is seen at.
WEAK_SHAPE = (4 * WEIGHT_NOISE, 10 * WEIGHT_NOISE)
#: The least weight noise assumed of a take (its measured jitter can be ~0 for computed weights).
TAKE_NOISE_MIN = 1e-3


def weak_ramp(capture, excitation, cap_idx) -> tuple[np.ndarray, dict]:
    """``[J]`` smooth ramp from 0 (the shape stays at its prior) to 1 over the effective weight a shape is
    shown at, between 4 and 10 times the weights' noise (:data:`WEAK_SHAPE`): a shape seen at a small
    effective weight is known only to a fraction of its amplitude, whatever the residuals say (the fit can
    explain other shapes' non-linear motion with it).

    A capture (one frame per requested shape): the effective weight is the root of the shape's training
    energy ``excitation[J]`` (``sum_f w_fj^2`` over the shapes ``cap_idx[J]`` of ``capture.names``), the
    noise the phone's nominal :data:`WEIGHT_NOISE`. A take read whole (hundreds of frames): that energy grows
    with every frame of cross-talk and noise (a shape the take never performs reached trust 0.98 and landed
    0.1-2 mm worse than generic), so the effective weight is the part of the shape's weights the other
    shapes' do not explain, above the noise's own share
    (:func:`usdface.personalize.takefit.unique_excitation`), and the noise is the take's own, measured from
    its frame-to-frame jitter (:func:`usdface.personalize.takefit.weight_noise`). Returns ``(ramp[J],
    info)``, ``info`` saying how a take's excitation was measured (``{}`` for a capture)."""
    lo, hi = WEAK_SHAPE
    effective = np.sqrt(np.asarray(excitation, dtype=np.float64))
    info = {}
    if capture.whole_take and len(capture.train) >= 3:
        from .takefit import unique_excitation, weight_noise

        reported = np.asarray(capture.train.weights, dtype=np.float64)       # time order, as the phone said
        noise = max(weight_noise(reported), TAKE_NOISE_MIN)
        effective = unique_excitation(reported, noise)[cap_idx]
        lo, hi = noise * lo / WEIGHT_NOISE, noise * hi / WEIGHT_NOISE
        info = {"statistic": "unique weight above the take's noise", "weight_noise": round(noise, 5)}
    t = np.clip((effective - lo) / (hi - lo), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t), info


def toward_prior(deltas, prior, factor) -> np.ndarray:
    """``[K,n,3]``: each shape's personalization ``deltas - prior`` (``[K,n,3]``, metres) scaled by
    ``factor[K]`` in [0, 1]: ``prior + c_j (deltas_j - prior_j)`` (0: the prior, 1: the fitted shape as it
    is, bit for bit). A vertex where ``deltas`` equals ``prior`` (an artist's pin held at the template,
    passed as its prior) is unchanged whatever the factor."""
    out = np.array(deltas, dtype=np.float64)
    c = np.asarray(factor, dtype=np.float64)
    k = np.flatnonzero(c < 1.0)
    p = np.asarray(prior, dtype=np.float64)[k]
    out[k] = p + c[k, None, None] * (out[k] - p)
    return out
