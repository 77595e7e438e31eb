"""Menzel et al. (2022), eq. (5): reconstruction error of a blendshape rig on held-out test frames, and the
error against known true blendshapes (benchmarks, sample assets)."""

from __future__ import annotations

import numpy as np

from ..errors import GeometryError
from ..model import FaceRig, Frames

__all__ = ["evaluate_rig", "reconstruction_errors", "score_capture_rig", "template_rig",
           "test_expression_errors", "truth_error", "error_colors"]


def reconstruction_errors(neutral: np.ndarray, deltas: np.ndarray, weights: np.ndarray,
                          points: np.ndarray) -> np.ndarray:
    """Per-vertex reconstruction errors ``[F,n]`` (metres): ``|B0 + sum_j w_fj B_j - T_f|`` for
    ``neutral[n,3]``, ``deltas[K,n,3]``, ``weights[F,K]``, test meshes ``points[F,n,3]``."""
    from .fit import blend

    model = np.asarray(neutral)[None] + blend(weights, deltas)
    return np.linalg.norm(model - np.asarray(points, dtype=np.float64), axis=-1)


def evaluate_rig(rig: FaceRig, frames: Frames, scale=None) -> dict:
    """Menzel et al. (2022), eq. (5): per-frame RMSE ``sqrt(1/n ||B0 + sum_j w_j B_j - T||^2)`` and max vertex
    error, both in **millimetres**, of ``rig`` (neutral[n,3] m, deltas[K,n,3] m) on ``frames``
    (points[F,n,3] m, weights[F,K] in the rig's shape order).

    ``scale[F,K]`` (optional): frame ``f`` scored with each shape ``k`` scaled by ``scale[f,k]`` - a fit that
    read its shapes' amplitudes on these frames, cross-fitted (``info["test_scale_left_out"]`` of
    :func:`usdface.personalize.fit_personalized_shapes`: frame ``f`` sees the scales read without it, so no
    frame scores a number it helped set). Applied to the weights, ``w_fk scale_fk``: the same for a rig
    without inbetweens (a fit's).

    Returns ``{"rmse_mm": [F], "max_mm": [F], "vertex_mm": [F,n], "labels": [F], "mean_rmse_mm": float,
    "mean_max_mm": float}``. The rig is evaluated with its UsdSkel semantics (:meth:`FaceRig.evaluate`).
    """
    pts = np.asarray(frames.points, dtype=np.float64)
    if pts.ndim != 3 or pts.shape[1] != rig.n_vertices:
        raise GeometryError(f"test frames have {pts.shape[1] if pts.ndim == 3 else '?'} vertices, the rig "
                            f"{rig.n_vertices}", fix="evaluate a rig on the capture mesh it was fitted to")
    if len(frames) == 0:
        z = np.zeros(0)
        return {"rmse_mm": z, "max_mm": z, "vertex_mm": np.zeros((0, rig.n_vertices)), "labels": [],
                "mean_rmse_mm": float("nan"), "mean_max_mm": float("nan")}
    weights = np.asarray(frames.weights, dtype=np.float64)
    if scale is not None:
        scale = np.asarray(scale, dtype=np.float64)
        if scale.shape != weights.shape:
            raise GeometryError(f"scale is {scale.shape}, the frames' weights {weights.shape}",
                                fix="pass the fit's test_scale_left_out for these frames")
        weights = weights * scale
    err = np.linalg.norm(rig.evaluate(weights) - pts, axis=-1) * 1000.0
    rmse = np.sqrt(np.mean(err ** 2, axis=1))
    mx = err.max(axis=1)
    return {"rmse_mm": rmse, "max_mm": mx, "vertex_mm": err, "labels": list(frames.label),
            "mean_rmse_mm": float(rmse.mean()), "mean_max_mm": float(mx.mean())}


def template_rig(capture) -> FaceRig:
    """The capture's generic template shapes on its neutral (``neutral[n,3]`` m, ``deltas[K,n,3]`` m): the
    rig eq. (5) scores as "generic" beside a fitted one."""
    t = capture.template
    return FaceRig(capture.neutral, capture.triangles, t.names, t.deltas, t.inbetweens, t.source, "generic")


def score_capture_rig(rig: FaceRig, capture, role: str = "test", scale=None) -> dict:
    """Eq. (5) (:func:`evaluate_rig`) of ``rig`` on the capture's ``role`` frames (``"test"``, held out, or
    ``"train"``), its shapes taken in the capture's order; ``scale[F,K]`` (capture order) as
    :func:`evaluate_rig`'s."""
    rig = rig.subset(capture.names) if list(rig.names) != list(capture.names) else rig
    return evaluate_rig(rig, capture.frames.select(role), scale)


def test_expression_errors(capture, rig: FaceRig, scale=None) -> dict | None:
    """Eq. (5) on the capture's held-out test expressions, the capture's generic template beside the fitted
    ``rig`` (the person's shapes on the capture mesh): ``{"labels": [F], "generic_rmse_mm": [F],
    "personalized_rmse_mm": [F], "generic_max_mm": [F], "personalized_max_mm": [F]}`` (plain lists, mm), or
    None when the capture has no test expressions. ``capture``: a :class:`usdface.model.Capture`
    (``neutral[n,3]`` m, ``template``, ``test`` frames with weights ``[F,K]`` in ``capture.names`` order);
    ``scale[F,K]``: the fitted rig's per-frame scale (:func:`evaluate_rig`: a fit that read its amplitudes on
    these frames, cross-fitted)."""
    if len(capture.test) == 0:
        return None
    out = {"labels": [str(s) for s in capture.test.label]}
    for label, r, s in (("generic", template_rig(capture), None), ("personalized", rig, scale)):
        res = score_capture_rig(r, capture, scale=s)
        out[f"{label}_rmse_mm"] = [float(v) for v in res["rmse_mm"]]
        out[f"{label}_max_mm"] = [float(v) for v in res["max_mm"]]
    return out


def truth_error(deltas: np.ndarray, true_deltas: np.ndarray) -> float:
    """RMSE in **millimetres** between fitted ``deltas[K,n,3]`` and the true ``true_deltas[K,n,3]`` (metres),
    over every shape and vertex: ``sqrt(mean_{j,i} |B_ij - B*_ij|^2)``."""
    d = np.asarray(deltas, dtype=np.float64) - np.asarray(true_deltas, dtype=np.float64)
    return float(np.sqrt(np.mean(np.sum(d ** 2, axis=-1))) * 1000.0)


def error_colors(error_mm: np.ndarray, vmax_mm: float = 5.0) -> np.ndarray:
    """Menzel et al. (2022), Fig. 6 colour code: ``error_mm[...]`` -> RGB ``[..., 3]`` in [0, 1], blue at 0 mm
    through green to red at ``vmax_mm`` (5 mm) and above."""
    t = np.clip(np.asarray(error_mm, dtype=np.float64) / vmax_mm, 0.0, 1.0)[..., None]
    blue, green, red = np.array([0.1, 0.2, 1.0]), np.array([0.1, 0.9, 0.2]), np.array([1.0, 0.1, 0.1])
    low = blue + (green - blue) * np.clip(2 * t, 0, 1)
    return np.where(t < 0.5, low, green + (red - green) * np.clip(2 * t - 1, 0, 1))
