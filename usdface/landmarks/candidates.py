"""Landmark candidates: relative displacement, candidate sets and quality (Zell & McDonnell 2022, sec. 3.1).

All functions are pure numpy: ``deltas[K, n, 3]`` metres in, ``[K, n]`` arrays out (shape-major, like
``deltas``).
"""

from __future__ import annotations

import numpy as np

from ..errors import LandmarkError

#: A shape whose largest vertex displacement is below this (metres) "moves no vertex".
STATIC_TOLERANCE = 1e-9


def check_epsilon(epsilon: float) -> float:
    """``epsilon`` as a float, or :class:`LandmarkError` when it is outside (0, 1]."""
    try:
        eps = float(epsilon)
    except (TypeError, ValueError):
        eps = float("nan")
    if not (0.0 < eps <= 1.0):
        raise LandmarkError(f"epsilon {epsilon!r} is outside (0, 1]",
                            fix="pass a relative-displacement threshold in (0, 1]; the paper uses 0.3-0.8")
    return eps


def check_alpha(alpha: float) -> float:
    """``alpha`` as a float, or :class:`LandmarkError` when it is outside [0, 1]."""
    try:                                   # "x" died in a ValueError
        a = float(alpha)
    except (TypeError, ValueError):
        a = float("nan")
    if not (0.0 <= a <= 1.0):
        raise LandmarkError(f"alpha {alpha!r} is outside [0, 1]",
                            fix="pass the weight of relative displacement vs visibility, in [0, 1]")
    return a


def check_rays(rays) -> int:
    """``rays`` (hemisphere rays per vertex and pose, eq. 4) as an int, or :class:`LandmarkError` when it is
    no whole number >= 1 (2.5 was taken as 2, "16" died in a TypeError and 0 in the ray casting, after the
    candidates and skin samples were computed; the callers name the rig, :func:`.layout.naming`)."""
    if isinstance(rays, bool) or not isinstance(rays, int | np.integer) or rays < 1:
        raise LandmarkError(f"rays {rays!r:.40} is not a whole number >= 1",
                            fix="pass the hemisphere rays per vertex and pose, e.g. rays=16 (the default; "
                                "--rays)")
    return int(rays)


def displacement_magnitudes(deltas: np.ndarray) -> np.ndarray:
    """|dv_n^k|: ``deltas[K, n, 3]`` metres -> ``[K, n]`` metres (the same sums as ``np.linalg.norm``, in the
    same order, without its ``[K, n, 3]`` temporary)."""
    d = np.asarray(deltas, dtype=np.float64)
    return np.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2])


def static_shapes(magnitudes: np.ndarray, tolerance: float = STATIC_TOLERANCE) -> np.ndarray:
    """Shapes moving no vertex (max |dv| <= ``tolerance`` metres): ``magnitudes[K, n]`` -> indices ``[s]``."""
    return np.flatnonzero(np.asarray(magnitudes).max(axis=1, initial=0.0) <= tolerance)


def relative_displacement(magnitudes: np.ndarray) -> np.ndarray:
    """Relative displacement r_n^k = |dv_n^k| / max_m |dv_m^k| (Zell & McDonnell 2022, eq. 2).

    ``magnitudes[K, n]`` (metres, from :func:`displacement_magnitudes`) -> ``r[K, n]`` in [0, 1]. Shapes that
    move no vertex get r = 0 everywhere (callers reject them first, see :func:`static_shapes`).
    """
    m = np.asarray(magnitudes, dtype=np.float64)
    peak = m.max(axis=1, keepdims=True, initial=0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(peak > 0.0, m / np.where(peak > 0.0, peak, 1.0), 0.0)
    return r


def moving_share(r: np.ndarray) -> np.ndarray:
    """Each vertex's moving share max_k r_n^k: the most any shape moves it, as a share of that shape's peak
    (eq. 2's relative displacement ``r[K, n]`` in [0, 1] -> ``[n]`` in [0, 1]; 0 everywhere without shapes).
    The one rule behind the face (:data:`.visibility.FACE_SHARE`: its size, the skin samples, the exclusion
    radius, the rays' offset) and the baselines' moving vertices."""
    return np.asarray(r, dtype=np.float64).max(axis=0, initial=0.0)


def candidate_sets(r: np.ndarray, epsilon: float) -> np.ndarray:
    """Candidates c_n^k = 1 if r_n^k >= epsilon else 0 (Zell & McDonnell 2022, eq. 3).

    ``r[K, n]`` in [0, 1] -> ``c[K, n]`` bool. The paper's eq. 3 uses ``>=`` (so ``epsilon = 1`` still keeps
    the most-displaced vertex of every shape); epsilon must lie in (0, 1].
    """
    return np.asarray(r) >= check_epsilon(epsilon)


def landmark_quality(r: np.ndarray, visibility: np.ndarray, alpha: float) -> np.ndarray:
    """Quality q_n^k = (1 - alpha) r_n^k + alpha l_n (Zell & McDonnell 2022, eq. 1, as a quality in [0, 1]).

    ``r[K, n]`` relative displacement, ``visibility[n]`` global visibility l_n in [0, 1] -> ``q[K, n]``.
    ``alpha`` weighs the visibility, as in the paper (``alpha = 0``: displacement only; 1: visibility only).
    The paper's importance weight is the negated form ``2 - q`` (small = good); see
    :mod:`usdface.landmarks.cover`.
    """
    a = check_alpha(alpha)
    return (1.0 - a) * np.asarray(r, dtype=np.float64) + a * np.asarray(visibility, dtype=np.float64)[None, :]
