"""The public entry point: :func:`fit_personalized_shapes` (method dispatch, input checks, options)."""

from __future__ import annotations

import functools
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..errors import FitError, GeometryError
from ..mesh import check_triangles
from ..model import Capture, FaceRig
from .align import rigid_align
from .crossval import choose_regularization
from .dt import deformation_transfer
from .fit import D_CLAMP, PositionFit, blend, fit_blendshapes, regularization_weights
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


def single_threaded_blas(func):
    """Run ``func`` with BLAS limited to one thread (``threadpoolctl``): thousands of tiny (K x K) LAPACK
    calls and the mid-sized products of the fit and the transfer run 2-3x slower (seconds at high load) with a
    multi-threaded BLAS on a busy 2-core machine."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        from threadpoolctl import threadpool_limits

        with threadpool_limits(limits=1, user_api="blas"):
            return func(*args, **kwargs)

    return wrapper


_single_threaded_blas = single_threaded_blas


@_single_threaded_blas
def fit_personalized_shapes(capture: Capture, method: str = "menzel", reg="auto", *, prior: str | None = None,
                            align: bool | None = None, reweight: bool | None = None, eyelids: bool = True,
                            clamp: float = D_CLAMP, weight_sigma: float = 0.05, rounds: int = 2,
                            **options) -> FitResult:
    """Personalized blendshapes on the capture mesh.

    Parameters
    ----------
    capture : the capture (neutral B0 [n,3] m, template rig on the same topology, train frames S_i [F,n,3]
        with weights [F,K]).
    method : "menzel" (eqs. 1-3, default), "dt", "ebfr" or "laplacian".
    reg : balance of E_reg against E_fit for menzel/laplacian: "auto" (leave-one-frame-out cross-validation,
        :func:`usdface.personalize.crossval.choose_regularization`), "paper" (1.0, the paper's plain sum) or a
        number.
    prior : the generic shapes T_j of eq. (2): "dt" (the paper: template transferred to B0), "template" (the
        template's deltas as they are, same topology) or "auto" (a blend of both chosen by the same
        cross-validation; needs ``reg="auto"``). Default: "auto" with ``reg="auto"``, else "dt". The weights
        D_j of eq. (3) always come from the DT shapes.
    align : robust rigid pre-alignment of every training frame (menzel/laplacian/ebfr): each frame is aligned
        to its leave-one-out prediction (the fit on the other frames), twice, on the moving vertices
        (:mod:`.align`). Where frames are already aligned this is a no-op. Default: on, except with
        ``reg="paper"`` (the paper's method as published).
    reweight : alternate the shape fit with re-estimating each training frame's weights (bounded to [0,1],
        anchored to the phone's with prior std ``weight_sigma``), ``rounds`` times (:mod:`.weights`).
        Default: on, except with ``reg="paper"``.
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
    auto = isinstance(reg, str) and reg == "auto"
    paper = isinstance(reg, str) and reg == "paper"
    align = (not paper) if align is None else bool(align)
    reweight = (not paper) if reweight is None else bool(reweight)
    prior = prior or ("auto" if auto else "dt")
    if prior not in ("auto", "dt", "template") or (prior == "auto" and not auto):
        raise FitError(f"bad prior {prior!r}", fix="use 'dt', 'template', or 'auto' (with reg='auto')")
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
    tmpl = capture.template
    if method == "dt":
        deltas = generic
    elif method == "ebfr":
        from .ebfr import ebfr_blendshapes
        if align:
            points = _align_frames(capture.neutral, points, weights, generic, info, timings)
        t1 = time.perf_counter()
        deltas = ebfr_blendshapes(capture.neutral, capture.triangles, points, weights, tmpl.neutral,
                                  tmpl.deltas, generic, names=capture.names, eyelids=eyelids,
                                  info=info, **options)
        timings["ebfr"] = time.perf_counter() - t1
    else:
        D = regularization_weights(generic, clamp=clamp)
        alt = tmpl.deltas if prior == "auto" else None
        lam, alpha = _balance(reg, capture.neutral, points, weights, generic, D, alt, prior, info, timings)
        if align:
            for _ in range(2):
                points = _align_frames(capture.neutral, points, weights, generic, info, timings,
                                       cv=info.get("crossval"), reg=lam, alpha=alpha, D=D, alt=tmpl.deltas)
                if auto:
                    cv = info["crossval"]
                    cv["fit"].set_points(points[:, cv["vertices"]])
                    # re-tune around the previous choice only (same blend, +-1 decade)
                    lam, alpha = _balance(reg, capture.neutral, points, weights, generic, D, alt, prior, info,
                                          timings, fit=cv["fit"], vertices=cv["vertices"],
                                          grid=np.log10(lam) + np.array([-1.0, 0.0, 1.0]), alphas=(alpha,))
        prior_deltas = alpha * generic + (1.0 - alpha) * tmpl.deltas if alpha < 1.0 else generic
        solve = _make_solver(method, capture, D, prior_deltas, options)
        t1 = time.perf_counter()
        deltas = solve(points, weights, lam)
        timings["fit"] = time.perf_counter() - t1
        w_cur = weights
        if reweight:
            t1 = time.perf_counter()
            for _ in range(rounds):
                res = points - capture.neutral[None] - blend(w_cur, deltas)
                w_cur = reestimate_weights(capture.neutral, deltas, points, weights,
                                           anchor=float(np.mean(res ** 2)) / weight_sigma ** 2)
                deltas = solve(points, w_cur, lam)
            info["reweight"] = {"rounds": rounds, "weight_sigma": weight_sigma,
                                "mean_abs_change": float(np.abs(w_cur - weights).mean()),
                                "max_abs_change": float(np.abs(w_cur - weights).max())}
            info["train_weights"] = w_cur
            timings["reweight"] = time.perf_counter() - t1
        res = points - capture.neutral[None] - blend(w_cur, deltas)
        info["train_rmse_mm"] = float(np.sqrt(np.mean(np.sum(res ** 2, axis=-1))) * 1000)
    info.pop("crossval_fit", None)
    if "crossval" in info:
        info["crossval"] = {k: v for k, v in info["crossval"].items() if k not in ("fit", "vertices")}
    timings["total"] = time.perf_counter() - t0
    rig = FaceRig(capture.neutral, capture.triangles, list(capture.names), deltas, name="FaceMask")
    return FitResult(rig, info)


def _balance(reg, neutral, points, weights, generic, D, alt, prior, info, timings, fit=None, vertices=None,
             **search):
    """(reg, alpha): the E_reg weight and the prior blend (alpha * DT + (1 - alpha) * template)."""
    t1 = time.perf_counter()
    alpha = {"dt": 1.0, "template": 0.0}.get(prior, 1.0)
    if isinstance(reg, str) and reg == "auto":
        gen = generic if prior != "template" else alt
        lam, cv = choose_regularization(neutral, points, weights, gen, D,
                                        alt_deltas=alt if prior == "auto" else None, fit=fit,
                                        vertices=vertices, **search)
        if prior == "auto":
            alpha = cv["alpha"]
        info["crossval"] = cv
    elif isinstance(reg, str) and reg == "paper":
        lam = 1.0
    else:
        try:
            lam = float(reg)
        except (TypeError, ValueError):
            raise FitError(f"bad reg {reg!r}", fix="use 'auto', 'paper' or a positive number") from None
        if not lam > 0:
            raise FitError(f"bad reg {reg!r}", fix="use 'auto', 'paper' or a positive number")
    timings["reg"] = timings.get("reg", 0.0) + time.perf_counter() - t1
    info["reg"] = lam
    info["prior_alpha"] = alpha
    return lam, alpha


def _align_frames(neutral, points, weights, generic, info, timings, *, cv=None, reg=None, alpha=1.0, D=None,
                  alt=None):
    """Rigidly align every frame to its leave-one-out prediction on (a subsample of) the moving vertices."""
    t1 = time.perf_counter()
    if D is None:
        D = regularization_weights(generic)
    if cv is None or "fit" not in cv:
        if reg is None:
            reg, cv = choose_regularization(neutral, points, weights, generic, D)
        else:
            _, cv = choose_regularization(neutral, points, weights, generic, D, alt_deltas=alt,
                                          grid=np.array([np.log10(reg)]), refine_steps=0)
            info["crossval"] = cv
    pf, cand = cv["fit"], cv["vertices"]
    pf.set_points(points[:, cand])
    pf.set_prior_mix(alpha)
    target = points[:, cand] - pf.loo_residuals(reg)
    _, R, tr = rigid_align(points[:, cand], target, np.arange(len(cand)))
    aligned = np.matmul(points, np.swapaxes(R, 1, 2)) + tr[:, None]
    ang = np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    prev = info.get("align", {"max_rotation_deg": 0.0, "max_translation_mm": 0.0, "passes": 0})
    info["align"] = {"vertices": int(len(cand)), "passes": prev["passes"] + 1,
                     "max_rotation_deg": prev["max_rotation_deg"] + float(ang.max()),
                     "max_translation_mm": prev["max_translation_mm"] + float(np.linalg.norm(tr, axis=1).max()
                                                                             * 1000)}
    timings["align"] = timings.get("align", 0.0) + time.perf_counter() - t1
    return aligned


def _make_solver(method, capture, D, generic, options):
    """A function ``(points, weights, reg) -> deltas`` for the position-based methods."""
    if method == "laplacian":
        from .laplacian import LaplacianFit
        unknown = set(options) - {"laplacian_weight", "mask_threshold", "tol", "max_iter"}
        if unknown:
            raise FitError(f"unknown option(s) for laplacian: {', '.join(sorted(unknown))}",
                           fix="use laplacian_weight, mask_threshold, tol or max_iter")
        lf = LaplacianFit(capture.neutral, capture.triangles, generic, D, **options)
        return lambda P, W, lam: lf.solve(P, W, lam)
    if options:
        raise FitError(f"unknown option(s) for {method}: {', '.join(options)}", fix="see usdface fit --help")
    return lambda P, W, lam: fit_blendshapes(capture.neutral, P, W, generic, D, lam)


# keep PositionFit importable from here for callers that want the prepared solver
_ = PositionFit
