"""Blend-shape weight animation as UsdSkel: a SkelAnimation with ``blendShapes`` tokens and time-sampled
``blendShapeWeights``; and the reverse, reading such an animation back into arrays.

Used by ``usdface anim import`` (Live Link Face CSV -> take.usda), by capture.usda (the template rig driven by
the frames' weights) and by anyone who needs to drive an avatar with weights.
"""

from __future__ import annotations

import numpy as np

from ..errors import CaptureError

__all__ = ["author_skel_animation", "read_skel_animation"]


def author_skel_animation(stage, prim_path, names, weights, time_codes_per_second: float = 24.0, *,
                          times=None, set_stage_range: bool = True, start_time_code: float = 0.0):
    """Define a ``SkelAnimation`` at ``prim_path`` holding ``weights[F, K]`` for the channels ``names[K]``.

    Frame ``f`` is authored at time code ``start_time_code + f`` (or ``start_time_code + times[f] *
    time_codes_per_second`` when ``times[F]`` in seconds is given). With ``set_stage_range`` the stage's
    ``timeCodesPerSecond`` and start/end time codes are set to cover the animation, and its
    ``framesPerSecond`` to the same rate unless the root layer already authors one for that
    ``timeCodesPerSecond`` (a layer over an avatar keeps the avatar's playback rate). Weights are authored
    as float[] (the UsdSkel type). Returns the ``UsdSkel.Animation``.
    """
    from pxr import Sdf, UsdSkel, Vt

    weights = np.array(weights, dtype=np.float64)
    names = [str(n) for n in names]
    if weights.ndim != 2 or weights.shape[1] != len(names):
        raise CaptureError(f"weights must be [frames, {len(names)}], got {weights.shape}", prim=prim_path,
                           fix="pass one weight column per channel name")
    if not np.isfinite(weights).all():
        raise CaptureError("weights contain NaN or infinite values", prim=prim_path,
                           fix="repair the weights before authoring the animation")
    codes = float(start_time_code) + (
        np.arange(len(weights), dtype=np.float64) if times is None
        else np.round(np.array(times, dtype=np.float64) * float(time_codes_per_second), 9))
    anim = UsdSkel.Animation.Define(stage, Sdf.Path(str(prim_path)))
    anim.CreateBlendShapesAttr(Vt.TokenArray(names))
    attr = anim.CreateBlendShapeWeightsAttr()
    w32 = weights.astype(np.float32)
    for code, row in zip(codes.tolist(), w32, strict=True):
        attr.Set(Vt.FloatArray.FromNumpy(row), code)
    if set_stage_range and len(codes):
        rate = float(time_codes_per_second)
        keep_fps = stage.GetRootLayer().HasFramesPerSecond() and stage.GetTimeCodesPerSecond() == rate
        stage.SetTimeCodesPerSecond(rate)
        if not keep_fps:
            stage.SetFramesPerSecond(rate)
        # whole frames around the samples: a take's times fall between frames (its last sample at
        # 1994.978), and a viewer's frame slider, which steps by whole frames, stopped short of it
        stage.SetStartTimeCode(float(np.floor(codes.min() + 1e-6)))
        stage.SetEndTimeCode(float(np.ceil(codes.max() - 1e-6)))
    return anim


def read_skel_animation(prim) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Read a SkelAnimation prim -> (names[K], weights[F, K] float64, time_codes[F]) over its time samples."""
    from pxr import UsdSkel

    anim = UsdSkel.Animation(prim)
    names = [str(n) for n in (anim.GetBlendShapesAttr().Get() or [])]
    attr = anim.GetBlendShapeWeightsAttr()
    codes = np.array(attr.GetTimeSamples(), dtype=np.float64)
    if len(codes) == 0:
        value = attr.Get()
        rows = [np.array(value, dtype=np.float64)] if value is not None else []
        codes = np.zeros(len(rows))
    else:
        rows = [np.array(attr.Get(c), dtype=np.float64) for c in codes.tolist()]
    bad = [i for i, r in enumerate(rows) if r.shape != (len(names),)]
    if bad:
        raise CaptureError(f"blendShapeWeights at time code {codes[bad[0]]} has {rows[bad[0]].size} values "
                           f"for {len(names)} blendShapes", path=prim.GetStage().GetRootLayer().identifier,
                           prim=prim.GetPath(), fix="author one weight per blendShapes token at every time")
    weights = np.stack(rows) if rows else np.zeros((0, len(names)))
    return names, weights, codes


def write_animation_usd(path, names, weights, times=None, time_codes_per_second: float = 60.0, *,
                        curves: dict | None = None, prim_name: str = "Take", force: bool = False,
                        layer_data: dict | None = None):
    """Write a weights-only take as a USD file whose defaultPrim is a SkelAnimation (``/<prim_name>``).

    ``weights[F, K]`` for channels ``names[K]``; frame ``f`` at time code ``times[f] * time_codes_per_second``
    (``times[F]`` in seconds; default: frame index). ``curves`` {name: values[F]} are authored as time-sampled
    ``double usdface:curves:<name>`` attributes (e.g. Live Link head/eye angles in radians). The file can be
    bound to an avatar with ``skel:animationSource``. Atomic; refuses an existing file unless ``force``.
    Returns the path.
    """
    from pathlib import Path

    from pxr import Sdf, Tf, Usd, UsdGeom

    from .usd_capture import _check_output, _save

    path = Path(path)
    _check_output(path, force, what="animation file")
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    anim = author_skel_animation(stage, f"/{Tf.MakeValidIdentifier(prim_name)}", names, weights,
                                 time_codes_per_second, times=times)
    stage.SetDefaultPrim(anim.GetPrim())
    codes = (np.arange(len(weights), dtype=np.float64) if times is None
             else np.round(np.array(times, dtype=np.float64) * float(time_codes_per_second), 9))
    for name, values in (curves or {}).items():
        attr = anim.GetPrim().CreateAttribute(f"usdface:curves:{Tf.MakeValidIdentifier(name)}",
                                              Sdf.ValueTypeNames.Double, custom=True)
        for code, v in zip(codes.tolist(), np.array(values, dtype=np.float64).tolist(), strict=True):
            attr.Set(v, code)
    if layer_data:
        stage.GetRootLayer().customLayerData = {"usdface": dict(layer_data)}
    _save(stage, path, force)
    return path
