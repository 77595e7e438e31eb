"""Inspection data authored into a personalize result, so usdview shows what usdface did.

:func:`inspection_edit` builds the ``edit(stage)`` callback that :func:`usdface.io.layers.write_avatar_layer`
runs on the new layer before saving. It authors, as local opinions of the new layer only:

* **heat maps**: for each mesh given, ``primvars:displayColor`` (vertex interpolation, a colour map of the
  per-vertex values) and the raw values as ``primvars:usdface:heat`` (float, metres). usdview draws
  displayColor when the mesh has no bound material (or with "Enable Scene Materials" off);
* **landmarks**: for each :class:`usdface.landmarks.LandmarkLayout` given, the landmark writer's
  ``Points`` prim ``<mesh>_landmarks`` with ``UsdFaceLandmarksAPI`` (one implementation:
  :mod:`usdface.io.usd_landmarks`);
* **animation**: a ``SkelAnimation`` ``<Skeleton>/usdfaceInspection`` playing weights (the capture's test
  expressions, a Live Link take...) through :func:`usdface.io.usd_anim.author_skel_animation`, with the
  Skeleton's ``skel:animationSource`` pointed at it (the original binding target is kept in the relationship's
  ``customData["usdface:originalAnimationSource"]``); the stage's time range covers the animation.

:func:`read_landmarks` reads back what ``usdface render`` needs (the generic avatar under a layer:
:func:`usdface.io.usd_rig.generic_input`).

Example::

    edit = inspection_edit(avatar, heat={"Head": err[n]}, landmarks={"Head": layout},
                           animation=(capture.names, capture.test.weights))
    write_avatar_layer(avatar, "out.usda", offsets, edit=edit)
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import RigError
from ..model import Avatar
from ..motion import shape_changes

#: Name of the inspection SkelAnimation under the Skeleton.
ANIMATION_NAME = "usdfaceInspection"
#: Primvar holding the raw heat-map values (metres).
HEAT_PRIMVAR = "usdface:heat"


def _rig(avatar: Avatar, key: str):
    from .layers import avatar_mesh

    rig = avatar_mesh(avatar, key)
    if rig.source is None:
        raise RigError(f"mesh {key!r} has no USD source", path=avatar.file,
                       fix="read the avatar with read_avatar")
    return rig


def _author_heat(stage, avatar: Avatar, heat: dict, vmax: float | None):
    from pxr import Sdf, UsdGeom, Vt

    from ..render import heat_colors

    for key, values in heat.items():
        rig = _rig(avatar, key)
        values = np.array(values, dtype=np.float64).ravel()
        if values.shape[0] != rig.n_vertices:
            raise RigError(f"heat map for {key!r} has {values.shape[0]} values, the mesh {rig.n_vertices}",
                           path=avatar.file, prim=rig.source.prim, fix="give one value per mesh point")
        api = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath(rig.source.prim))
        colors = heat_colors(values, vmax=vmax).astype(np.float32)
        api.CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray, UsdGeom.Tokens.vertex).Set(
            Vt.Vec3fArray.FromNumpy(colors))
        api.CreatePrimvar(HEAT_PRIMVAR, Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).Set(
            Vt.FloatArray.FromNumpy(values.astype(np.float32)))


def _author_landmarks(stage, avatar: Avatar, landmarks: dict):
    """Landmark Points through the landmark writer's own authoring (one implementation of the Points prim)."""
    from .usd_landmarks import _author

    for key, layout in landmarks.items():
        rig = _rig(avatar, key)
        if not hasattr(layout, "vertices") or not hasattr(layout, "coverage"):
            raise RigError(f"landmarks for {key!r} must be a LandmarkLayout (usdface.compute_landmarks)",
                           path=avatar.file, prim=rig.source.prim, fix="pass the layout object, not indices")
        vertices = np.array(layout.vertices, dtype=np.int64)
        if vertices.size and (vertices.min() < 0 or vertices.max() >= rig.n_vertices):
            raise RigError(f"landmark index out of range [0, {rig.n_vertices}) for {key!r}", path=avatar.file,
                           prim=rig.source.prim, fix="use a layout computed on this mesh")
        _author(stage, rig, layout, avatar.meters_per_unit)


def _author_animation(stage, avatar: Avatar, names, weights, fps: float | None, times=None):
    from pxr import Sdf, UsdSkel

    from .usd_anim import author_skel_animation

    weights = np.array(weights, dtype=np.float64)
    names = [str(n) for n in names]
    column = {n: i for i, n in enumerate(names)}
    by_skeleton: dict[str, list[str]] = {}
    for rig in avatar.meshes:
        if rig.source is None or not rig.source.skeleton:
            continue
        tokens = rig.source.channel_tokens or rig.names
        channels = by_skeleton.setdefault(rig.source.skeleton, [])
        for canonical, token in zip(rig.names, tokens, strict=True):
            if token not in channels:
                channels.append(token)
                column.setdefault(token, column.get(canonical, -1))
    if not by_skeleton:
        raise RigError("no Skeleton bound to the avatar's meshes; cannot add an animation", path=avatar.file,
                       fix="bind the meshes to a Skeleton (rel skel:skeleton)")
    # the avatar's own timeline: its rate and first frame (a 30 fps shot from frame 1001 stays one; the root
    # layer repeats the avatar's metadata, so the stage reads them), unless a rate is given
    rate = float(fps) if fps else stage.GetTimeCodesPerSecond()
    origin = stage.GetStartTimeCode() if stage.GetRootLayer().HasStartTimeCode() else 0.0
    for skeleton, tokens in by_skeleton.items():
        cols = np.array([column.get(t, -1) for t in tokens])
        w = np.zeros((weights.shape[0], len(tokens)))
        w[:, cols >= 0] = weights[:, cols[cols >= 0]]
        anim_path = Sdf.Path(skeleton).AppendChild(ANIMATION_NAME)
        author_skel_animation(stage, anim_path, tokens, w, rate, times=times, start_time_code=origin)
        binding = UsdSkel.BindingAPI.Apply(stage.GetPrimAtPath(skeleton))
        rel = binding.CreateAnimationSourceRel()
        old = rel.GetTargets()
        if old and old[0] != anim_path:
            rel.SetCustomDataByKey("usdface:originalAnimationSource", str(old[0]))
        rel.SetTargets([anim_path])


def inspection_edit(avatar: Avatar, *, heat: dict | None = None, heat_vmax: float | None = None,
                    landmarks: dict | None = None, animation: tuple | None = None,
                    fps: float | None = None) -> Callable:
    """The ``edit(stage)`` callback for :func:`usdface.io.layers.write_avatar_layer` that authors inspection
    data.

    Parameters
    ----------
    avatar : the avatar the layer is written over (``read_avatar``); meshes are named by prim name or path.
    heat : {mesh -> values[n]} per-vertex values in metres (e.g. |personalized - generic| or an error).
    heat_vmax : value mapped to the brightest colour (default: each map's 99th percentile).
    landmarks : {mesh -> LandmarkLayout} layouts computed on those meshes (:func:`usdface.compute_landmarks`).
    animation : (names[K], weights[F, K]) or (names, weights, times[F] seconds): weights per frame (frame f at
        time code f when no times); names in any ARKit spelling, mapped onto the avatar's channel tokens (a
        channel with no column stays at 0).
    fps : time codes per second of the animation (None: the avatar's ``timeCodesPerSecond``, which the layer
        repeats; USD's 24 when the avatar authors none). The animation starts at the avatar's
        ``startTimeCode`` when it authors one (a shot's frame 1001), else at 0.
    """

    def edit(stage) -> None:
        if heat:
            _author_heat(stage, avatar, heat, heat_vmax)
        if landmarks:
            _author_landmarks(stage, avatar, landmarks)
        if animation is not None:
            names, weights, *times = animation
            _author_animation(stage, avatar, _canonical(names), weights, fps, times[0] if times else None)

    return edit


def _canonical(names) -> list[str]:
    from ..arkit import normalize_name

    return [normalize_name(str(n)) or str(n) for n in names]


def _landmark_prims(stage_or_path):
    """(mesh prim path, Points prim) of every prim with ``usdface:landmarks:vertexIndices`` authored."""
    from pxr import Usd

    stage = stage_or_path
    if isinstance(stage_or_path, str | Path):
        from ..pipeline.validators import open_stage

        stage = open_stage(stage_or_path)
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        attr = prim.GetAttribute("usdface:landmarks:vertexIndices")
        if not attr or not attr.HasAuthoredValue():
            continue
        rel = prim.GetRelationship("usdface:landmarks:mesh")
        targets = rel.GetTargets() if rel else []
        yield (str(targets[0]) if targets else str(prim.GetPath())), prim


def read_landmarks(stage_or_path) -> dict[str, np.ndarray]:
    """{mesh prim path -> vertex indices} of every prim with ``usdface:landmarks:vertexIndices`` authored."""
    return {key: np.array(prim.GetAttribute("usdface:landmarks:vertexIndices").Get(), dtype=np.int64)
            for key, prim in _landmark_prims(stage_or_path)}


def read_landmark_settings(stage_or_path) -> dict[str, dict[str, float]]:
    """{mesh prim path -> {"epsilon": .., "alpha": ..}} of every authored landmark layout (the values the
    layout was computed with; keys as in :func:`read_landmarks`, entries only for authored values)."""
    found = {}
    for key, prim in _landmark_prims(stage_or_path):
        values = {}
        for name in ("epsilon", "alpha"):
            attr = prim.GetAttribute(f"usdface:landmarks:{name}")
            if attr and attr.HasAuthoredValue():
                values[name] = float(attr.Get())
        found[key] = values
    return found


def layer_inspection(layer) -> dict[str, bool]:
    """What inspection data a layer (an ``Sdf.Layer``, or a path to one) holds as its own opinions:
    ``{"heat": a heat map's primvars:usdface:heat, "landmarks": a landmark layout's
    usdface:landmarks:vertexIndices, "animation": the usdfaceInspection SkelAnimation}``, read from the
    layer's specs alone (not composed: the avatar beneath has none of them). What a batch's resume compares
    with a row's ``inspect``, ``landmarks`` and ``take`` (:func:`usdface.pipeline.batch.stale_output`): a
    layer records no such option, but holds what it wrote."""
    from pxr import Sdf

    if not isinstance(layer, Sdf.Layer):
        layer = Sdf.Layer.FindOrOpen(str(layer))
    found = {"heat": False, "landmarks": False, "animation": False}

    def visit(path):
        if path.IsPropertyPath():
            name = path.name
            found["heat"] |= name == f"primvars:{HEAT_PRIMVAR}"
            found["landmarks"] |= name == "usdface:landmarks:vertexIndices"
        elif path.IsPrimPath():
            found["animation"] |= path.name == ANIMATION_NAME

    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    return found


def change_heat(avatar: Avatar, offsets: dict) -> dict[str, np.ndarray]:
    """{mesh prim path -> values[n]}: per-vertex RMS over shapes of |new - generic| offsets, metres.

    ``offsets`` is {mesh prim path (or name) -> deltas[K_mesh, n, 3]} in ``rig.names`` order, as given to
    :func:`usdface.io.layers.write_avatar_layer`."""
    heat = {}
    for key, deltas in offsets.items():
        rig = _rig(avatar, key)
        # shape by shape (:func:`usdface.motion.shape_changes`): the whole [K, n, 3] difference, its squares
        # and norms were ~670 MB of temporaries on a 225k-vertex head ('personalize --inspect' peaked at
        # 1.78 GB against 1.11 GB without)
        heat[rig.source.prim] = (shape_changes(deltas, rig.deltas)[0] if len(deltas)
                                 else np.zeros(rig.n_vertices))
    return heat


def inspection_animation(capture=None, take=None, hold: float = 0.5, gap: float = 1.0) -> tuple | None:
    """One timeline for usdview: the capture's test expressions (one every ``hold`` seconds, interpolated in
    between), then, ``gap`` seconds later, a take (a ``usdface.io.take.Take``: Live Link CSV or USD take);
    without a take, a capture read from a whole take plays its frames at their times.
    Returns ``(names[K], weights[F, K], times[F] seconds)`` for :func:`inspection_edit`, or None."""
    parts = []
    if capture is not None and len(capture.test):
        w = capture.test.weights
        parts.append((list(capture.names), w, np.arange(len(w)) * hold))
    if take is None and capture is not None:  # a take read whole as the capture: play it
        from .take import whole_take_playback

        take = whole_take_playback(capture)
        if take is not None:
            parts.append(take)
            take = None
    if take is not None and len(take):
        start = (parts[0][2][-1] + gap) if parts else 0.0
        parts.append((list(take.names), take.weights, start + take.times - take.times[0]))
    if not parts:
        return None
    names = list(dict.fromkeys(n for p in parts for n in _canonical(p[0])))
    rows, times = [], []
    for part_names, w, t in parts:
        cols = [names.index(n) for n in _canonical(part_names)]
        block = np.zeros((len(w), len(names)))
        block[:, cols] = w
        rows.append(block)
        times.append(t)
    return names, np.vstack(rows), np.concatenate(times)


def add_inspection(layer_path, edit: Callable) -> Path:
    """Run an inspection ``edit(stage)`` on an already written usdface layer and save it again atomically
    (temporary file in the same folder + ``os.replace``). Only the layer itself is changed, never its inputs.
    """
    import os

    from pxr import Sdf, Usd

    from ..errors import InputFileError

    path = Path(layer_path).absolute()
    layer = Sdf.Layer.FindOrOpen(str(path))
    if layer is None:
        raise InputFileError("USD cannot open the layer", path=path, fix="pass a layer written by usdface")
    layer.Reload(force=True)
    stage = Usd.Stage.Open(layer, Usd.Stage.LoadAll)
    stage.SetEditTarget(stage.GetRootLayer())
    edit(stage)
    from .atomic import temp_sibling

    tmp = str(temp_sibling(path, create=False))
    try:
        if not layer.Export(tmp):
            raise InputFileError("USD could not write the layer", path=path, fix="check permissions")
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    layer.Reload(force=True)
    return path
