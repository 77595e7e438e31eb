"""The public entry point: :func:`fit_personalized_shapes` (method dispatch, input checks, options)."""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..errors import FitError, GeometryError
from ..mesh import check_triangles
from ..model import Capture, FaceRig
from .align import rigid_align, static_vertices
from .crossval import choose_regularization
from .dt import deformation_transfer
from .fit import D_CLAMP, PositionFit, fit_blendshapes, regularization_weights
from .weights import reestimate_weights

__all__ = ["METHODS", "FitResult", "fit_personalized_shapes", "check_capture"]

#: Methods of :func:`fit_personalized_shapes`.
METHODS = ("dt", "ebfr", "menzel", "laplacian")

#: A shape whose largest training weight is below this is "never activated".
ACTIVATION_MIN = 0.05


@dataclass
class FitResult:
    """Result of :func:`fit_personalized_shapes`.

    ``rig``: FaceRig on the capture mesh (neutral = B0 [n,3] m, deltas = personalized B_j [K,n,3] m,
    names = capture.names). ``info``: method, chosen ``reg``, ``timings`` (s), ``warnings`` (list of str),
    per-option figures (e.g. ``loo_rmse_mm`` of the regularisation search, ``train_rmse_mm``).
    """

    rig: FaceRig
    info: dict = field(default_factory=dict)


def check_capture(capture: Capture) -> list[str]:
    """Validate a capture for fitting; raise on unusable input, return warnings for degraded input.

    Raises :class:`GeometryError` (vertex-count mismatch, degenerate template triangles, non-finite points)
    or :class:`FitError` (no training frames, no shapes). Warns (returned strings) about fewer training
    frames than shapes and shapes never activated in training (by name).
    """
    src = capture.source or None
    n = len(capture.neutral)
    tmpl = capture.template
    if len(capture.names) == 0:
        raise FitError("the capture has no blendshapes", path=src, fix="add template shapes to the capture")
    if tmpl.n_vertices != n:
        raise GeometryError(f"template has {tmpl.n_vertices} vertices, the neutral scan {n}", path=src,
                            fix="the template must be on the capture's topology")
    pts = capture.frames.points
    if pts.ndim != 3 or pts.shape[1:] != (n, 3):
        bad = [lab for lab, p in zip(capture.frames.label, pts, strict=False) if p.shape != (n, 3)]
        raise GeometryError(f"frames have a different vertex count than the neutral ({n}): "
                            f"{', '.join(bad[:5]) or pts.shape}", path=src,
                            fix="every frame must be on the capture topology, in the same vertex order")
    check_triangles(tmpl.neutral, capture.triangles, what="template neutral", path=src)
    check_triangles(capture.neutral, capture.triangles, what="neutral scan", path=src)
    train = capture.train
    if len(train) == 0:
        raise FitError("no training frames", path=src, fix="add frames with role 'train' (train/ folder)")
    if not np.all(np.isfinite(train.points)) or not np.all(np.isfinite(train.weights)):
        raise GeometryError("non-finite training points or weights", path=src, fix="repair the frames")
    warn = []
    K = len(capture.names)
    if len(train) < K:
        warn.append(f"{len(train)} training frames for {K} shapes: the fit is underdetermined; shapes the "
                    f"frames do not determine are held to the template")
    never = [nm for nm, w in zip(capture.names, train.weights.max(axis=0), strict=True) if w < ACTIVATION_MIN]
    if never:
        warn.append(f"shape(s) never activated in training (max weight < {ACTIVATION_MIN}): "
                    f"{', '.join(never)}; they stay at the template's deformation transfer")
    return warn


def _generic_shapes(capture: Capture, eyelids: bool) -> np.ndarray:
    t = capture.template
    return deformation_transfer(t.neutral, t.deltas, capture.neutral, capture.triangles, names=capture.names,
                                eyelids=eyelids)


def fit_personalized_shapes(capture: Capture, method: str = "menzel", reg="auto", *, align: bool = False,
                            reweight: bool | None = None, eyelids: bool = True, clamp: float = D_CLAMP,
                            weight_sigma: float = 0.05, rounds: int = 3, **options) -> FitResult:
    """Personalized blendshapes on the capture mesh.

    Parameters
    ----------
    capture : the capture (neutral B0 [n,3] m, template rig on the same topology, train frames S_i [F,n,3]
        with weights [F,K]).
    method : "menzel" (eqs. 1-3, default), "dt", "ebfr" or "laplacian".
    reg : balance of E_reg against E_fit for menzel/laplacian: "auto" (leave-one-frame-out cross-validation,
        :func:`usdface.personalize.crossval.choose_regularization`), "paper" (1.0, the paper's plain sum) or a
        number.
    align : robust rigid pre-alignment of the training frames to B0 on the vertices no template shape moves
        (:mod:`.align`); applies to every method that uses the frames.
    reweight : alternate the shape fit with re-estimating each training frame's weights (bounded to [0,1],
        anchored to the phone's with prior std ``weight_sigma``), ``rounds`` times (:mod:`.weights`).
        ``None`` = on for menzel/laplacian.
    eyelids : virtual eyelid triangles in the deformation transfer.
    clamp : eq. (3) clamp (1e5).
    options : method-specific (ebfr: ``beta``, ``kappa``, ``theta``; laplacian: ``laplacian_weight``,
        ``mask_threshold``).

    Returns a :class:`FitResult`. Raises FitError / GeometryError on unusable input (see
    :func:`check_capture`); warnings are in ``result.info["warnings"]`` and issued as ``UserWarning``.
    """
    if method not in METHODS:
        raise FitError(f"unknown method {method!r}", path=capture.source or None,
                       fix=f"use one of {', '.join(METHODS)}")
    timings = {}
    t0 = time.perf_counter()
    warn = check_capture(capture)
    for w in warn:
        warnings.warn(w, stacklevel=2)
    info: dict = {"method": method, "warnings": warn, "timings": timings}
    t1 = time.perf_counter()
    generic = _generic_shapes(capture, eyelids)
    timings["dt"] = time.perf_counter() - t1
    train = capture.train
    points, weights = train.points, train.weights
    if method != "dt" and align:
        t1 = time.perf_counter()
        static = static_vertices(generic)
        points, R, tr = rigid_align(points, capture.neutral, static)
        ang = np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1)))
        info["align"] = {"static_vertices": int(len(static)), "max_rotation_deg": float(ang.max()),
                         "max_translation_mm": float(np.linalg.norm(tr, axis=1).max() * 1000)}
        timings["align"] = time.perf_counter() - t1
    if method == "dt":
        deltas = generic
    elif method == "ebfr":
        from .ebfr import ebfr_blendshapes
        t1 = time.perf_counter()
        tmpl = capture.template
        deltas = ebfr_blendshapes(capture.neutral, capture.triangles, points, weights, tmpl.neutral,
                                  tmpl.deltas, generic, **options)
        timings["ebfr"] = time.perf_counter() - t1
    else:
        D = regularization_weights(generic, clamp=clamp)
        if reweight is None:
            reweight = False
        solve = _make_solver(method, capture, D, generic, options)
        deltas, lam = _fit_with_reg(solve, capture.neutral, points, weights, generic, D, reg, info, timings)
        if reweight:
            t1 = time.perf_counter()
            w_cur = weights
            for _ in range(rounds):
                res = points - capture.neutral[None] - np.einsum("fk,knc->fnc", w_cur, deltas)
                sigma_g2 = float(np.mean(res ** 2))
                w_cur = reestimate_weights(capture.neutral, deltas, points, weights,
                                           anchor=sigma_g2 / weight_sigma ** 2)
                deltas = solve(points, w_cur, lam)
            info["reweight"] = {"rounds": rounds, "weight_sigma": weight_sigma,
                                "mean_abs_change": float(np.abs(w_cur - weights).mean()),
                                "max_abs_change": float(np.abs(w_cur - weights).max())}
            info["train_weights"] = w_cur
            timings["reweight"] = time.perf_counter() - t1
        weights_used = info.get("train_weights", weights)
        res = points - capture.neutral[None] - np.einsum("fk,knc->fnc", weights_used, deltas)
        info["train_rmse_mm"] = float(np.sqrt(np.mean(np.sum(res ** 2, axis=-1))) * 1000)
    timings["total"] = time.perf_counter() - t0
    rig = FaceRig(capture.neutral, capture.triangles, list(capture.names), deltas,
                  name=f"personalized ({method})")
    return FitResult(rig, info)


def _make_solver(method, capture, D, generic, options):
    """A function ``(points, weights, reg) -> deltas`` for the position-based methods."""
    if method == "laplacian":
        from .laplacian import LaplacianFit
        lf = LaplacianFit(capture.neutral, capture.triangles, generic, D, **options)
        return lambda P, W, lam: lf.solve(P, W, lam)
    if options:
        raise FitError(f"unknown option(s) for {method}: {', '.join(options)}", fix="see usdface fit --help")
    return lambda P, W, lam: fit_blendshapes(capture.neutral, P, W, generic, D, lam)


def _fit_with_reg(solve, neutral, points, weights, generic, D, reg, info, timings):
    t1 = time.perf_counter()
    if isinstance(reg, str) and reg == "auto":
        lam, cv = choose_regularization(neutral, points, weights, generic, D)
        info["crossval"] = cv
    elif isinstance(reg, str) and reg == "paper":
        lam = 1.0
    else:
        try:
            lam = float(reg)
        except (TypeError, ValueError):
            raise FitError(f"bad --reg {reg!r}", fix="use 'auto', 'paper' or a positive number") from None
        if not lam > 0:
            raise FitError(f"bad --reg {reg!r}", fix="use 'auto', 'paper' or a positive number")
    timings["reg"] = time.perf_counter() - t1
    info["reg"] = lam
    t1 = time.perf_counter()
    deltas = solve(points, weights, lam)
    timings["fit"] = time.perf_counter() - t1
    return deltas, lam


# keep PositionFit importable from here for callers that want the prepared solver
_ = PositionFit
