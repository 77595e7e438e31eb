"""Face-rig validation rules: ``check(stage) -> list[Issue]``.

The rules a pipeline TD expects of an ARKit face rig in UsdSkel, and of a layer written by usdface. Each rule
is one function ``stage -> Iterable[Issue]`` registered in :data:`RULES` under a stable id; :func:`check` runs
them all (or a chosen subset). The same rules are exposed to OpenUSD's validation framework by
:mod:`usdface.pipeline.validators`, to Pyblish by :mod:`usdface.pipeline.pyblish_plugins`, and to the command
line by ``usdface check``.

Rules (id: what it checks; severity of a violation):

* ``StageMetadata``: ``upAxis``, ``metersPerUnit`` authored, ``defaultPrim`` set to an existing prim (error).
* ``SkelBinding``: a mesh with blend shapes has ``SkelBindingAPI`` applied (error), lies under a ``SkelRoot``
  (error) and inherits a ``skel:skeleton`` binding (error: without one nothing drives its weights).
* ``BlendShapeArrays``: ``skel:blendShapes`` and ``skel:blendShapeTargets`` the same length, every target a
  ``BlendShape`` prim (error).
* ``BlendShapeOffsets``: ``offsets`` (and ``normalOffsets``, inbetween offsets) have one entry per
  ``pointIndices`` entry, or one per mesh point when ``pointIndices`` is not authored; offsets finite (error).
* ``PointIndices``: ``pointIndices`` in ``[0, n_points)`` and unique (error).
* ``Inbetweens``: inbetween weights strictly inside (0, 1) (warning: UsdSkel accepts others, ARKit rigs and
  most DCC exporters do not).
* ``ArkitNames``: every channel is an ARKit name in its canonical spelling (warning for a DCC suffix such as
  ``eyeBlinkLeft2`` or a near-miss typo; info for the raw/Live Link spellings and non-ARKit extras); no two
  channels of a mesh mean the same shape (error); together the meshes bound to a skeleton cover all 52 ARKit
  shapes, ``tongueOut`` optional (error).
* ``AnimationNames``: the bound ``SkelAnimation``'s ``blendShapes`` name every mesh channel exactly (UsdSkel
  matches by token; a channel it does not name never animates: warning) and ``blendShapeWeights`` has one
  weight per name (error).
* ``Provenance``: a usdface layer's ``usdface:provenance:*`` attributes are present and consistent (version,
  command, one sha256 digest per input: error) and every input that is still reachable has the recorded digest
  (warning: the input changed after the layer was written).
* ``Readable`` (runs last): the avatar reader every command uses accepts the rig and finds one face mesh in
  it (error): a stage holding several characters' face rigs (a shot) is refused as personalize refuses it,
  unless ``face_mesh=`` names one.
* ``AvatarMatch``: a usdface layer still fits the avatar it sublayers: the prims it overrides exist, each
  personalized mesh's blend shapes are those its ``skel:blendShapeTargets`` list, its point count and faces
  are those recorded at writing, the avatar's units and up axis are those the layer repeats (error: the
  avatar was revised after the layer was written; re-run personalize).

Example::

    from pxr import Usd
    from usdface.pipeline.check import check
    for issue in check(Usd.Stage.Open("avatar.usdc")):
        print(issue)
"""

from __future__ import annotations

import difflib
import hashlib
import re
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..arkit import (
    ARKIT_NAMES,
    ARKIT_SET,
    HOW_LABELS,
    OPTIONAL_NAMES,
    match_name,
    match_names,
    unused_map_entries,
)
from ..namelist import name_list

ERROR, WARNING, INFO = "error", "warning", "info"
SEVERITIES = (ERROR, WARNING, INFO)
_RANK = {ERROR: 0, WARNING: 1, INFO: 2}


@dataclass(frozen=True)
class Issue:
    """One finding: ``severity`` (error / warning / info), the ``rule`` id, the ``prim`` path ("/" for the
    stage), a ``message``, a suggested ``fix``, and its ``source`` ("usdface" or "pixar" for OpenUSD's own
    validators)."""

    severity: str
    rule: str
    prim: str
    message: str
    fix: str = ""
    source: str = "usdface"

    def to_dict(self) -> dict:
        return asdict(self)

    def __str__(self) -> str:
        text = f"{self.severity.upper():7s} [{self.rule}] {self.prim}: {self.message}"
        return text + (f" (fix: {self.fix})" if self.fix else "")


def has_errors(issues: Iterable[Issue]) -> bool:
    """True when any issue is an error."""
    return any(i.severity == ERROR for i in issues)


def sort_issues(issues: Iterable[Issue]) -> list[Issue]:
    """Errors first, then warnings, then infos; by prim path within a severity."""
    return sorted(issues, key=lambda i: (_RANK.get(i.severity, 3), i.prim, i.rule, i.message))


#: rule id -> (function stage -> Iterable[Issue], one-line description). Filled by :func:`_rule`.
RULES: dict[str, tuple[Callable, str]] = {}


def _rule(rule_id: str, doc: str):
    def deco(fn):
        RULES[rule_id] = (fn, doc)
        return fn

    return deco


#: Rules that take the studio's channel-name map (``name_map=`` {channel: ARKit name}).
_NAME_MAP_RULES = {"ArkitNames", "Readable"}
#: Rules whose errors the avatar reader would only repeat (a broken binding or blend-shape array): after one
#: of them, Readable is not run. After any other rule's error (no metersPerUnit, a stale provenance, a
#: non-canonical name) it still runs, so that what the reader refuses is told at once, not after the first
#: error is fixed.
READER_RULES = {"SkelBinding", "BlendShapeArrays", "BlendShapeOffsets", "PointIndices", "Inbetweens"}


def _split_fix(text: str) -> tuple[str, str]:
    """``(message, fix)`` of a reader's warning that ends in its own ``(fix: ...)``; else ``(text, "")``
    (the issue's fix was printed after the message's own: '(fix: author ...) (fix: author what the reader
    assumed ...)')."""
    head, sep, tail = text.rpartition(" (fix: ")
    if sep and tail.endswith(")"):
        return head, tail[:-1]
    return text, ""


def _prim_in(text: str) -> str:
    """The prim a reader's message names (``file, prim /A/B: ...``), else ``/``."""
    import re

    hit = re.search(r"prim (/[^\s:,]*)", text)
    return hit.group(1) if hit else "/"


def check(stage, rules: Iterable[str] | None = None, name_map: dict | None = None,
          face_mesh: str | None = None) -> list[Issue]:
    """Run the face-rig rules on an open ``Usd.Stage``; returns the issues sorted errors first.

    ``rules`` selects rule ids from :data:`RULES` (default: all; a string is one name or comma-separated
    names); ``name_map`` ({studio channel: ARKit name}, :func:`usdface.io.name_map.read_name_map`; default:
    the one a usdface layer records, :func:`usdface.io.usd_rig.recorded_name_map`) is used by the name
    rules; ``face_mesh`` (personalize's ``--face-mesh``: a prim name or path) is the face mesh ``Readable``
    checks a stage with several characters' face rigs by (without it such a stage is an error, as personalize
    refuses it). Never modifies the stage.
    """
    if name_map is None:
        from ..io.usd_rig import recorded_name_map

        name_map = recorded_name_map(stage)
    chosen = name_list(rules, "rules", "rule",
                       fix=f"leave rules out (None) to run all, or name some: {', '.join(sorted(RULES))}")
    if chosen is None:
        chosen = list(RULES)
    unknown = [r for r in chosen if r not in RULES]
    if unknown:
        from ..errors import OptionError

        # a rule misspelt (ArkitName, pointindices) is named with the one meant, as a shape name is
        meant = {u: hit for u in unknown if (hit := _closest(u, RULES, 0.8))}
        said = ", ".join(f"{u!r} (did you mean {meant[u]}?)" if u in meant else repr(u) for u in unknown)
        raise OptionError(f"unknown check rule(s) {said}", fix=f"choose from {sorted(RULES)}")
    issues: list[Issue] = []
    for rule_id in chosen:
        if rule_id == "Readable" and any(i.severity == ERROR and i.rule in READER_RULES for i in issues):
            continue  # the reader would only repeat a finding already made
        fn = RULES[rule_id][0]
        if rule_id == "Readable" and face_mesh:
            issues.extend(fn(stage, name_map=name_map, face_mesh=face_mesh))
        else:
            issues.extend(fn(stage, name_map=name_map) if rule_id in _NAME_MAP_RULES and name_map
                          else fn(stage))
    return sort_issues(issues)


# ----------------------------------------------------------------------------------------------- helpers
def _skel():
    from pxr import UsdSkel

    return UsdSkel


def _brings_personalization(stage, rig) -> bool:
    """Whether ``rig``'s SkelRoot composes a usdface layer with its ``personalized`` variant selected (an
    instance of the published layer, which personalize refuses as already personalized, not an avatar a
    layer would be written over)."""
    from ..io.layers import PERSONALIZATION_VARIANT_SET

    root = stage.GetPrimAtPath(rig.source.skel_root) if rig.source and rig.source.skel_root else None
    sets = root.GetVariantSets() if root else None
    return bool(sets) and sets.HasVariantSet(PERSONALIZATION_VARIANT_SET) and \
        sets.GetVariantSelection(PERSONALIZATION_VARIANT_SET) == "personalized"


def _blend_shape_meshes(stage):
    """Every Mesh with blend-shape bindings, as the reader finds them
    (:func:`usdface.io.usd_rig._has_blend_shapes`): UsdSkel ignores ``skel:blendShapes`` on other prims (a
    Scope that passes it down, Pixar's "ignored" token), and a blocked ``skel:blendShapes`` / an empty
    ``skel:blendShapeTargets`` binds nothing."""
    from pxr import Usd

    from ..io.usd_rig import _has_blend_shapes

    return [p for p in stage.Traverse(Usd.TraverseInstanceProxies()) if _has_blend_shapes(p)]


def _channels(prim) -> tuple[list[str], list]:
    attr = prim.GetAttribute("skel:blendShapes")
    rel = prim.GetRelationship("skel:blendShapeTargets")
    names = [str(n) for n in (attr.Get() if attr else None) or []]
    targets = list(rel.GetTargets()) if rel else []
    return names, targets


def _n_points(prim) -> int | None:
    attr = prim.GetAttribute("points")
    pts = attr.Get() if attr else None
    return None if pts is None else len(pts)


def _path(prim) -> str:
    return str(prim.GetPath())


# ----------------------------------------------------------------------------------------------- rules
@_rule("StageMetadata", "upAxis and metersPerUnit authored, defaultPrim set to an existing prim")
def _stage_metadata(stage) -> Iterable[Issue]:
    layer = stage.GetRootLayer().identifier
    if not stage.HasAuthoredMetadata("upAxis"):
        yield Issue(ERROR, "StageMetadata", "/", f"stage {layer} does not author upAxis",
                    "author upAxis (Y or Z) in the root layer; a sublayer's metadata does not compose")
    if not stage.HasAuthoredMetadata("metersPerUnit"):
        yield Issue(ERROR, "StageMetadata", "/", f"stage {layer} does not author metersPerUnit",
                    "author metersPerUnit in the root layer (0.01 for centimetres, 1 for metres)")
    if not stage.HasDefaultPrim():
        yield Issue(ERROR, "StageMetadata", "/", f"stage {layer} has no defaultPrim",
                    "set defaultPrim to the avatar's root prim so references need no prim path")
    elif not stage.GetDefaultPrim():
        yield Issue(ERROR, "StageMetadata", "/",
                    f"defaultPrim {stage.GetRootLayer().defaultPrim!r} does not name an existing prim",
                    "set defaultPrim to the avatar's root prim")


@_rule("SkelBinding", "blend-shape meshes: SkelBindingAPI applied, under a SkelRoot, bound to a Skeleton")
def _skel_binding(stage) -> Iterable[Issue]:
    UsdSkel = _skel()
    for prim in _blend_shape_meshes(stage):
        path = _path(prim)
        if not prim.HasAPI(UsdSkel.BindingAPI):
            yield Issue(ERROR, "SkelBinding", path,
                        "authors skel:blendShapes but SkelBindingAPI is not applied",
                        "apply the API: prepend apiSchemas = [\"SkelBindingAPI\"] (UsdSkel.BindingAPI.Apply)")
        if not UsdSkel.Root.Find(prim):
            from ..io.usd_rig import _overridden_skel_root

            hidden = _overridden_skel_root([prim])       # a shot layer's def Xform over the asset's SkelRoot
            if hidden is not None:
                root, typed, strong = hidden
                yield Issue(ERROR, "SkelBinding", path,
                            f"blend-shape mesh is not under a SkelRoot: {root} is a SkelRoot in {typed} but "
                            f"{strong}, a stronger layer, gives it another type",
                            f"author {root} in {strong} without a type ('over', or 'def' with no type name), "
                            "or as 'def SkelRoot'")
            else:
                yield Issue(ERROR, "SkelBinding", path, "blend-shape mesh is not under a SkelRoot",
                            "put the mesh and its Skeleton under a SkelRoot prim")
        if not UsdSkel.BindingAPI(prim).GetInheritedSkeleton():
            yield Issue(ERROR, "SkelBinding", path,
                        "no Skeleton bound (skel:skeleton on the mesh or an ancestor): "
                        "nothing drives its weights",
                        "bind a Skeleton with rel skel:skeleton on the mesh or its SkelRoot")


def _sampled_issue(rule: str, path: str, what: str) -> Issue:
    """The error of a blend-shape attribute authored only as time samples (a cache export,
    :func:`usdface.io.usd_rig.time_sampled_only`): UsdSkel reads it at the default time, where it is
    missing. Worded as the reader's refusal (``usd_rig._default_only``)."""
    from ..io.usd_rig import time_sampled_fix

    return Issue(ERROR, rule, path, f"{what} are time-sampled only, with no default value: UsdSkel reads the "
                 "default (they are uniform)", time_sampled_fix(what))


@_rule("BlendShapeArrays", "skel:blendShapes and skel:blendShapeTargets same length; targets are BlendShapes")
def _blend_shape_arrays(stage) -> Iterable[Issue]:
    from ..io.usd_rig import time_sampled_only

    UsdSkel = _skel()
    for prim in _blend_shape_meshes(stage):
        names, targets = _channels(prim)
        path = _path(prim)
        if time_sampled_only(prim.GetAttribute("skel:blendShapes")):
            yield _sampled_issue("BlendShapeArrays", path, "skel:blendShapes")
        elif len(names) != len(targets):
            yield Issue(ERROR, "BlendShapeArrays", path,
                        f"skel:blendShapes has {len(names)} names but skel:blendShapeTargets "
                        f"{len(targets)} targets",
                        "author one channel name per BlendShape target, in the same order")
        for target in targets:
            tprim = stage.GetPrimAtPath(target)
            if not tprim:
                yield Issue(ERROR, "BlendShapeArrays", path, f"blend-shape target {target} does not exist",
                            "remove the target or restore the BlendShape prim")
            elif not tprim.IsA(UsdSkel.BlendShape):
                yield Issue(ERROR, "BlendShapeArrays", path,
                            f"blend-shape target {target} is a {tprim.GetTypeName() or 'typeless prim'}, "
                            "not a BlendShape", "target BlendShape prims only")


def _shape_targets(stage):
    """(mesh prim, n_points, BlendShape) for every valid target of every blend-shape mesh."""
    UsdSkel = _skel()
    for prim in _blend_shape_meshes(stage):
        n = _n_points(prim)
        for target in _channels(prim)[1]:
            tprim = stage.GetPrimAtPath(target)
            if tprim and tprim.IsA(UsdSkel.BlendShape):
                yield prim, n, UsdSkel.BlendShape(tprim)


@_rule("BlendShapeOffsets", "offsets, normalOffsets, inbetweens match pointIndices (or point count); finite")
def _blend_shape_offsets(stage) -> Iterable[Issue]:
    from ..io.usd_rig import time_sampled_only

    for prim, n, shape in _shape_targets(stage):
        path = _path(shape.GetPrim())
        sampled = [what for attr, what in ((shape.GetPointIndicesAttr(), "pointIndices"),
                                           (shape.GetOffsetsAttr(), "offsets"),
                                           (shape.GetNormalOffsetsAttr(), "normalOffsets"))
                   + tuple((ib.GetAttr(), f"{ib.GetAttr().GetName()} offsets")
                           for ib in shape.GetInbetweens())
                   if time_sampled_only(attr)]
        if sampled:     # read at the default time they are missing: every count below would mislead
            for what in sampled:
                yield _sampled_issue("BlendShapeOffsets", path, what)
            continue
        offsets = shape.GetOffsetsAttr().Get()
        indices_attr = shape.GetPointIndicesAttr()
        indices = indices_attr.Get() if indices_attr.HasAuthoredValue() else None
        normals = shape.GetNormalOffsetsAttr().Get()
        if offsets is None or len(offsets) == 0:
            if normals is not None and len(normals):
                yield Issue(WARNING, "BlendShapeOffsets", path, "BlendShape has normalOffsets only; it moves "
                            "no points", "author offsets unless a shading-only shape is intended")
            else:
                yield Issue(ERROR, "BlendShapeOffsets", path, "BlendShape has no offsets",
                            "author offsets (one per pointIndices entry, or one per mesh point)")
            continue
        if indices is not None:
            expected, what = len(indices), f"pointIndices ({len(indices)})"
        else:
            expected, what = n, f"mesh {_path(prim)} points ({n})"
        if expected is not None and len(offsets) != expected:
            yield Issue(ERROR, "BlendShapeOffsets", path, f"{len(offsets)} offsets but {what}",
                        "author one offset per pointIndices entry (sparse) or per mesh point (dense)")
        if not np.isfinite(np.asarray(offsets, dtype=np.float64)).all():
            yield Issue(ERROR, "BlendShapeOffsets", path, "offsets contain NaN or infinity",
                        "re-export the shape; the mesh would explode when the channel is driven")
        if normals is not None and len(normals) and len(normals) != len(offsets):
            yield Issue(ERROR, "BlendShapeOffsets", path,
                        f"{len(normals)} normalOffsets but {len(offsets)} offsets",
                        "author normalOffsets with the same length as offsets, or remove them")
        for ib in shape.GetInbetweens():
            ib_offsets = ib.GetOffsets()
            if ib_offsets is not None and len(ib_offsets) != len(offsets):
                yield Issue(ERROR, "BlendShapeOffsets", path,
                            f"inbetween {ib.GetAttr().GetName()} has {len(ib_offsets)} offsets, the shape "
                            f"{len(offsets)}",
                            "inbetweens share the shape's pointIndices; author as many offsets")


@_rule("PointIndices", "pointIndices in range [0, n_points) and unique")
def _point_indices(stage) -> Iterable[Issue]:
    for prim, n, shape in _shape_targets(stage):
        attr = shape.GetPointIndicesAttr()
        if not attr.HasAuthoredValue() or attr.Get() is None:   # time-sampled only: BlendShapeOffsets tells
            continue
        idx = np.asarray(attr.Get(), dtype=np.int64)
        path = _path(shape.GetPrim())
        if idx.size == 0:
            continue
        bad = (idx < 0) | (idx >= n) if n is not None else idx < 0
        if bad.any():
            yield Issue(ERROR, "PointIndices", path,
                        f"{int(bad.sum())} pointIndices outside [0, {n}) of mesh {_path(prim)} "
                        f"(e.g. {int(idx[bad][0])})", "re-export the shape against this mesh's topology")
        uniq, counts = np.unique(idx, return_counts=True)
        if (counts > 1).any():
            dup = uniq[counts > 1]
            yield Issue(ERROR, "PointIndices", path,
                        f"{dup.size} pointIndices repeated (e.g. {int(dup[0])}); UsdSkel rejects the shape",
                        "list each vertex once (sum duplicate offsets)")


def _weight_text(w) -> str:
    """An inbetween weight as authored: USD stores it as a float, so -0.499 reads back as
    -0.49900001287460327; its shortest float32 spelling is what the file says."""
    if w is None:
        return "unset"
    import numpy as np

    return np.format_float_positional(np.float32(w), trim="-")


@_rule("Inbetweens", "inbetween weights strictly inside (0, 1)")
def _inbetweens(stage) -> Iterable[Issue]:
    for _prim, _n, shape in _shape_targets(stage):
        for ib in shape.GetInbetweens():
            w = ib.GetWeight()
            if w is None or not (0.0 < w < 1.0):
                name = ib.GetAttr().GetName()
                yield Issue(WARNING, "Inbetweens", _path(shape.GetPrim()),
                            f"inbetween {name} has weight {_weight_text(w)}, outside (0, 1)",
                            "place inbetweens strictly between 0 and 1 (ARKit weights never leave [0, 1])")


#: More channels of one mesh decorated the same way than this are reported in one line.
GROUP_AFTER = 3


def _closest(name: str, choices: Iterable[str], cutoff: float) -> str | None:
    """The one of ``choices`` ``name`` is most likely a misspelling of (case-insensitive, difflib ratio at
    least ``cutoff``), or None."""
    lowered = {n.lower(): n for n in choices}
    hit = difflib.get_close_matches(name.lower(), list(lowered), n=1, cutoff=cutoff)
    return lowered[hit[0]] if hit else None


def _close_arkit(name: str) -> str | None:
    return _closest(name, ARKIT_NAMES, 0.85)


@_rule("ArkitNames", "ARKit names canonical, unique per mesh, complete per skeleton (tongueOut optional)")
def _arkit_names(stage, name_map: dict | None = None) -> Iterable[Issue]:
    UsdSkel = _skel()
    per_skeleton: dict[str, set[str]] = {}
    unknown: dict[str, list[str]] = {}             # per skeleton: channels that are no ARKit name
    tokens: set[str] = set()                       # every channel as authored, for the map's unused entries
    for prim in _blend_shape_meshes(stage):
        names, targets = _channels(prim)
        tokens.update(names)
        path = _path(prim)
        fallbacks = [t.name for t in targets] if len(targets) == len(names) else None
        match = match_names(names, fallbacks, name_map)
        decorated: dict[str, list] = {}
        for given, canonical, how in match.inexact:
            if given == canonical:               # a map entry naming a channel as it is: nothing to say
                continue
            if how in ("spelling", "alias", "name-map"):
                yield Issue(INFO, "ArkitNames", path, f"channel {given!r} is a non-canonical spelling of "
                            f"{canonical!r} ({HOW_LABELS[how]})",
                            f"rename to {canonical!r} for tools that only know Apple's names")
            else:
                bare = match_name(given)[1]
                reason = {"suffix": "a DCC numeric suffix", "prefix": "a DCC node or namespace prefix"}.get(
                    bare, "only its target prim is named so")
                decorated.setdefault(reason, []).append((given, canonical))
        for reason, pairs in decorated.items():
            if len(pairs) > GROUP_AFTER:            # one line for a mesh a DCC renamed whole ('.001')
                shown = ", ".join(f"{g!r} -> {c!r}" for g, c in pairs[:3])
                group = (f"{len(pairs)} channels look like ARKit names only by their BlendShape prims' names"
                         if reason == "only its target prim is named so"
                         else f"{len(pairs)} channels look like ARKit names with {reason}")
                yield Issue(WARNING, "ArkitNames", path, f"{group}: {shown} (+{len(pairs) - 3} more)",
                            "rename the channels to their ARKit names; drivers that match by name will miss "
                            "them")
                continue
            for given, canonical in pairs:
                yield Issue(WARNING, "ArkitNames", path, f"channel {given!r} looks like {canonical!r} "
                            f"({reason})",
                            f"rename the channel to {canonical!r}; drivers that match by name will miss it")
        for given in match.unknown:
            close = _close_arkit(given)
            if close:
                yield Issue(WARNING, "ArkitNames", path, f"channel {given!r} is not an ARKit name; misspelt "
                            f"{close!r}?", f"rename it to {close!r}")
            else:
                yield Issue(INFO, "ArkitNames", path, f"channel {given!r} is not an ARKit shape",
                            "fine for extra shapes (usdface keeps it but does not personalize it); if it "
                            "is an ARKit shape under the rig's own name, map it with --name-map FILE")
        kept = {c: k for _g, c, k in match_names(names, fallbacks, name_map, resolve=True).conflicts}
        for dup in sorted(set(match.duplicates)):
            given = [g for g, c in zip(names, match.canonical, strict=True) if c == dup]
            using = f"; usdface uses {kept[dup]!r}" if dup in kept else ""
            yield Issue(ERROR, "ArkitNames", path, f"channels {given} all mean {dup!r}{using}",
                        "keep one channel per ARKit shape")
        skel = UsdSkel.BindingAPI(prim).GetInheritedSkeleton()
        key = str(skel.GetPath()) if skel else path
        per_skeleton.setdefault(key, set()).update(c for c in match.canonical if c in ARKIT_SET)
        unknown.setdefault(key, []).extend(g for g in match.unknown if g not in unknown[key])
    if name_map:      # as 'inspect --name-map' notes them: a typo in the map, or another rig's map
        unused = unused_map_entries(name_map, tokens)
        if unused:
            yield Issue(INFO, "ArkitNames", _path(stage.GetPseudoRoot()),
                        f"name map entries that match no channel: {', '.join(map(repr, unused[:8]))}"
                        f"{' ...' if len(unused) > 8 else ''}",
                        "check the map's spelling of the channels (or that it is this rig's map)")
    for key, found in per_skeleton.items():
        missing = [n for n in ARKIT_NAMES if n not in found and n not in OPTIONAL_NAMES]
        if not found:
            yield Issue(WARNING, "ArkitNames", key, "no channel of the meshes bound here is an ARKit shape",
                        "name the channels with Apple's ARKit names (eyeBlinkLeft, jawOpen, ...)")
        elif missing:
            # a studio's own channel names (JawDrop) read as missing shapes: the map is the fix
            own = unknown.get(key) or []
            mapped = (f"if the rig has them under its own channel names ({', '.join(map(repr, own[:4]))}"
                      f"{', ...' if len(own) > 4 else ''}), map them with --name-map FILE (docs/names.md); "
                      "else " if own else "")
            yield Issue(ERROR, "ArkitNames", key, f"{len(missing)} ARKit shape(s) missing: "
                        f"{', '.join(missing[:8])}{' ...' if len(missing) > 8 else ''}",
                        f"{mapped}add the missing shapes (tongueOut is optional)")


@_rule("AnimationNames", "the bound SkelAnimation names every channel exactly; one weight per name")
def _animation_names(stage) -> Iterable[Issue]:
    UsdSkel = _skel()
    by_anim: dict[str, tuple] = {}
    for prim in _blend_shape_meshes(stage):
        skel = UsdSkel.BindingAPI(prim).GetInheritedSkeleton()
        if not skel:
            continue  # reported by SkelBinding
        anim_prim = UsdSkel.BindingAPI(skel.GetPrim()).GetInheritedAnimationSource()
        if not anim_prim or not anim_prim.IsA(UsdSkel.Animation):
            continue
        entry = by_anim.setdefault(str(anim_prim.GetPath()), (UsdSkel.Animation(anim_prim), []))
        entry[1].append(prim)
    for anim_path, (anim, meshes) in by_anim.items():
        anim_names = [str(n) for n in anim.GetBlendShapesAttr().Get() or []]
        known = set(anim_names)
        for prim in meshes:
            names, _ = _channels(prim)
            unanimated = [n for n in names if n not in known]
            if unanimated:
                yield Issue(WARNING, "AnimationNames", _path(prim),
                            f"{len(unanimated)} channel(s) not named by SkelAnimation {anim_path} "
                            "never animate: "
                            f"{', '.join(unanimated[:6])}{' ...' if len(unanimated) > 6 else ''}",
                            "use the same tokens in the mesh's skel:blendShapes and the "
                            "animation's blendShapes")
        weights_attr = anim.GetBlendShapeWeightsAttr()
        samples = weights_attr.GetTimeSamples()
        probe = [samples[0]] if samples else []
        values = [weights_attr.Get(t) for t in probe] if probe else [weights_attr.Get()]
        for v in values:
            if v is not None and len(v) != len(anim_names):
                yield Issue(ERROR, "AnimationNames", anim_path,
                            f"blendShapeWeights has {len(v)} values, blendShapes {len(anim_names)} names",
                            "author one weight per blendShapes name at every time sample")


_HEX64 = re.compile(r"^[0-9a-f]{64}$")


def _digest(path: Path) -> str | None:
    try:
        from ..io.layers import file_digest
    except ImportError:
        file_digest = None
    if file_digest is not None:
        return str(file_digest(path))
    if not path.is_file():
        return None
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _prim_specs(layer) -> list:
    """Every prim spec of ``layer`` outside variants, parents first."""
    from ..io.layers import prim_specs

    return prim_specs(layer)


def _personalizing_layers(prim) -> list[str]:
    """The usdface layers (identifiers, strongest first) that author the personalization variant set on
    ``prim``: more than one when a shot stacks two personalized layers of one avatar (v002 over v001)."""
    from ..io.usd_rig import PERSONALIZATION_VARIANT_SET

    out: list[str] = []
    for spec in prim.GetPrimStack():
        layer = spec.layer
        if (PERSONALIZATION_VARIANT_SET in spec.variantSets and "usdface" in (layer.customLayerData or {})
                and layer.identifier not in out):
            out.append(layer.identifier)
    return out


def _provenance_base(prim) -> Path | None:
    """The folder of the layer that authored ``prim``'s ``usdface:provenance:inputs`` (its strongest spec),
    which the recorded paths are relative to; None when it has no real path."""
    attr = prim.GetAttribute("usdface:provenance:inputs")
    for spec in (attr.GetPropertyStack() if attr else []):
        if spec.layer.realPath:
            return Path(spec.layer.realPath).parent
    return None


@_rule("Provenance", "a usdface layer's provenance present, consistent, and its inputs unchanged")
def _provenance(stage) -> Iterable[Issue]:
    from pxr import Usd

    from ..io.layers import recorded_path
    from ..io.usd_rig import _from_cwd

    prov_prims = [p for p in stage.Traverse(Usd.TraverseInstanceProxies())
                  if "UsdFaceProvenanceAPI" in p.GetAppliedSchemas()
                  or p.GetAttribute("usdface:provenance:version").HasAuthoredValue()]
    root = stage.GetRootLayer()
    record = (root.customLayerData or {}).get("usdface")
    # a personalize result: usdface's record names inputs and the layer sits over an avatar (a capture.usda
    # also carries a "usdface" record, with a "format" and no inputs: not a result layer)
    looks_usdface = (isinstance(record, dict) and ("inputs" in record or "inputDigests" in record)
                     and bool(root.subLayerPaths))
    if not prov_prims:
        if looks_usdface:
            # the prims it wrote the provenance on, gone from the composed stage: the avatar's SkelRoot was
            # renamed or moved after the layer was written (AvatarMatch names it), no hand edit
            kept = [str(p.path) for p in _prim_specs(root) if "usdface:provenance:version" in p.attributes]
            if kept:
                yield Issue(ERROR, "Provenance", kept[0],
                            f"layer {root.identifier} records its provenance on {', '.join(kept)}, which the "
                            "avatar it sublayers no longer defines (its SkelRoot renamed or moved after the "
                            "layer was written)",
                            "re-run usdface personalize on the revised avatar (--force to replace the layer)")
            else:
                yield Issue(ERROR, "Provenance", "/", f"layer {root.identifier} was written by usdface but "
                            "has no UsdFaceProvenanceAPI prim",
                            "re-run usdface personalize; do not hand-edit the layer")
        elif not record and "usdfaceFlatten" not in (root.customLayerData or {}):
            from ..io.usd_rig import dcc_export_marks_in

            marks = dcc_export_marks_in(stage)      # Blender's export of a personalized layer
            if marks:
                yield Issue(WARNING, "Provenance", marks[0],
                            f"a DCC export (Blender, ...) of a usdface output layer: it has {marks[0]}, "
                            "which usdface writes only into a personalized layer or its flattened export, "
                            "but no provenance or variant set; its shapes are the personalized ones and "
                            "personalize refuses it as an avatar",
                            "publish the usdface layer itself, or export the original avatar from the DCC")
        return
    base = Path(root.realPath).parent if root.realPath else Path.cwd()
    for prim in prov_prims:
        path = _path(prim)
        stacked = _personalizing_layers(prim)
        if len(stacked) > 1:
            shown, hidden = stacked[0], stacked[1:]
            yield Issue(WARNING, "Provenance", path,
                        f"{len(stacked)} usdface layers personalize {path}: {shown} (the stronger: its "
                        f"shapes, provenance and variant set show) over {', '.join(hidden)} (overridden: "
                        "none of its shapes shows where the stronger authors them, and its inputs go "
                        "unchecked)",
                        "compose one personalized layer per avatar (to switch versions, swap the sublayer or "
                        "reference, e.g. v001 -> v002)")

        def get(name, prim=prim):
            attr = prim.GetAttribute(f"usdface:provenance:{name}")
            return attr.Get() if attr and attr.HasAuthoredValue() else None

        for name in ("version", "command"):
            if not get(name):
                yield Issue(ERROR, "Provenance", path, f"usdface:provenance:{name} is empty",
                            "re-run the usdface command that wrote the layer (personalize, landmarks) to "
                            "rewrite its provenance")
        # the recorded paths are relative to the layer that wrote them, not to the stage's root layer: a
        # shot that sublayers or references the published layer from another folder checked them against
        # its own folder and said 'not reachable from here; digest unchecked' for inputs right there
        folder = _provenance_base(prim) or base
        inputs = list(get("inputs") or [])
        digests = list(get("inputDigests") or [])
        if len(inputs) != len(digests):
            yield Issue(ERROR, "Provenance", path,
                        f"{len(inputs)} provenance inputs but {len(digests)} inputDigests",
                        "re-run usdface personalize to rewrite the layer's provenance")
            continue
        if not inputs:
            yield Issue(ERROR, "Provenance", path, "provenance names no input files",
                        "re-run usdface personalize to rewrite the layer's provenance")
        for given, digest in zip(inputs, digests, strict=True):
            if not _HEX64.match(str(digest)):
                yield Issue(ERROR, "Provenance", path,
                            f"digest of input {given!r} is not a sha256 hex string",
                            "re-run usdface personalize to rewrite the layer's provenance")
                continue
            file = recorded_path(folder, given)       # by name, as USD anchors the layer's own paths
            if not file.exists():
                yield Issue(INFO, "Provenance", path,
                            f"input {given!r} not reachable from here; digest unchecked", "")
                continue
            now = _digest(file)
            if now is not None and now != digest:
                # named as it opens from where the command runs (as review's and export's warning and the
                # avatar-revised fix name it), not by the path recorded relative to the layer's folder
                yield Issue(WARNING, "Provenance", path,
                            f"input {_from_cwd(file)} changed after this layer was written (sha256 differs)",
                            "re-run usdface personalize on the current inputs")


@_rule("AvatarMatch", "a usdface layer still fits the avatar it sublayers: its prims, channels, mesh "
                      "topology and units are the avatar's (an avatar revised after the layer was written "
                      "is told, with what changed)")
def _avatar_match(stage) -> Iterable[Issue]:
    """A personalized layer holds overrides written for the avatar as it was: revised upstream (a mesh
    renamed, the SkelRoot moved, a shape added or removed, the mesh re-modelled, units or axis changed), the
    layer composes over the new avatar without a USD error, and what it does is wrong or nothing. Each such
    change is an error naming the prim and the fix (re-run personalize on the revised avatar):
    :func:`usdface.io.layers.avatar_mismatches`."""
    from ..io.layers import avatar_mismatches

    nudged: list = []
    for prim, message, fix in avatar_mismatches(stage, nudged=nudged):
        yield Issue(ERROR, "AvatarMatch", prim, message, fix)
    for prim, message, fix in nudged:       # below what the record resolves (or float noise): a warning
        yield Issue(WARNING, "AvatarMatch", prim, message, fix)


@_rule("Readable", "the avatar reader accepts the rig (runs last; what the readers refuse is an error "
                   "here too: NaN/inf points, bad faces, meshes without faces, bad units or up axis, several "
                   "characters' face rigs without face_mesh, ...)")
def _readable(stage, name_map: dict | None = None, face_mesh: str | None = None) -> Iterable[Issue]:
    """Run the reader every usdface command uses (``usdface.io.usd_rig``) on the stage; a refusal is an
    error, so a publish validator never passes a rig the tools then reject. A stage with several characters'
    face rigs (a shot) is refused as personalize refuses it (:func:`usdface.motion.refuse_several_characters`)
    unless ``face_mesh`` names one (then that name must name one mesh, as personalize's ``--face-mesh``)."""
    from ..arkit import ARKIT_NAMES
    from ..errors import UsdFaceError
    from ..io.file_kind import Kind, file_kind, is_weights_take
    from ..io.take import has_frame_weights
    from ..io.usd_rig import _read_avatar_stage
    from ..motion import meshes_by_motion, refuse_several_characters

    layer = stage.GetRootLayer()
    found = file_kind(layer.realPath, stage=stage)      # its root layer: a capture's or take's record
    take = bool(layer.realPath) and found.kind is Kind.TAKE     # marked, or its layer defines one
    weights_take = is_weights_take(stage)
    if not weights_take and take and not has_frame_weights(stage):
        # time-sampled points, no blend shapes, no weights (Pixar's lbs.baked.usda): called a take, with
        # the fix 'usdface inspect FILE', whose take reader then refused it for lack of weights
        yield Issue(INFO, "Readable", "/", "this is a mesh cache (time-sampled points, no blend shapes, no "
                    "per-frame weights: baked skinning or a simulation?), neither an avatar nor a take: "
                    "check judges avatars and usdface layers",
                    "pass the avatar whose meshes carry the blend shapes, not a bake of it")
        return
    if weights_take or take:
        yield Issue(INFO, "Readable", "/", "this is a take (a recording: blend-shape weights, and meshes if "
                    "it has them), not an avatar: check judges avatars and usdface layers",
                    "usdface inspect FILE summarises the take")
        return
    if found.kind in (Kind.CAPTURE, Kind.TAKE) and found.by == "format":
        # not an avatar: the capture/take readers own those files; said, so "0 errors" is not read as a pass
        kind = found.format
        yield Issue(INFO, "Readable", "/", f"this is a usdface {kind}, not an avatar: check judges avatars "
                    "and usdface layers", f"usdface inspect FILE summarises the {kind}")
        return
    if found.kind is Kind.ERROR_MAPS and found.by == "format":      # (the file's kind, read above)
        # 'usdface evaluate --usd': '0 error(s), 0 warning(s), 0 info' read as a pass of a file that is none
        # of the things check judges (a trial, stop 42), as a capture's is said
        yield Issue(INFO, "Readable", "/", "this is a usdface error-map file ('usdface evaluate --usd'), not "
                    "an avatar: check judges avatars and usdface layers",
                    "usdface inspect FILE summarises the error maps")
        return
    if not _blend_shape_meshes(stage):
        from pxr import Usd, UsdGeom, UsdSkel

        prims = list(stage.Traverse(Usd.TraverseInstanceProxies()))
        if any(p.IsA(UsdSkel.Root) for p in prims) and any(p.IsA(UsdGeom.Mesh) for p in prims):
            yield Issue(ERROR, "Readable", "/", "no mesh with blend shapes: not a face rig personalize "
                        "can use", "export the avatar with its shape keys / blend shapes (ARKit names)")
        return  # no skinned geometry (a take, usdface's error maps, a schema file): not judged as an avatar
    try:
        import warnings

        with warnings.catch_warnings(record=True) as said:      # what the reader says goes into the report
            warnings.simplefilter("always")
            avatar = _read_avatar_stage(stage, Path(layer.realPath or layer.identifier), name_map=name_map)
        for w in said:
            if issubclass(w.category, UserWarning):
                text, own_fix = _split_fix(str(w.message))    # a warning that carries its fix: told once
                yield Issue(WARNING, "Readable", _prim_in(text), text,
                            own_fix or "author what the reader assumed (see the message), or accept it")
        from ..io.usd_rig import refuse_instanced, refuse_unwritable_shapes

        # as personalize, unless the file composes a usdface layer's personalized variant (or is the
        # flattened export of one): personalize refuses it as already personalized before it would get
        # there (check passes such a shot when it is not instanced), and a crowd instancing the published
        # layer shows each instance's variant
        flattened = (layer.customLayerData or {}).get("usdfaceFlatten") or {}
        ranked = meshes_by_motion(avatar.meshes, ARKIT_NAMES)
        if (not any(_brings_personalization(stage, m) for m in avatar.meshes)
                and flattened.get("variant") != "personalized"):
            refuse_instanced(avatar, [m.key for m in avatar.meshes], "the personalized layer")
            refuse_unwritable_shapes(avatar, None, "the personalized layer")
            # a shot with two characters: personalize refuses it unless --face-mesh names one (a layer
            # personalizing one of them, checked after it is written, is not refused: it is not an input)
            if face_mesh:
                from ..io.layers import avatar_mesh

                avatar_mesh(avatar, face_mesh, "with blend shapes in the avatar (--face-mesh)")
            else:
                refuse_several_characters(avatar, ranked)
        if not ranked:
            # on the mesh with blend shapes (it said "/"), as personalize's refusal names it
            where = avatar.meshes[0].source.prim if avatar.meshes and avatar.meshes[0].source else "/"
            if any(n in ARKIT_NAMES for m in avatar.meshes for n in m.names):   # named, moving nothing
                yield Issue(ERROR, "Readable", where, "the ARKit-named blend shapes move no point (zero "
                            "offsets, or normalOffsets only): personalize finds no face mesh",
                            "author the shapes' point offsets")
            else:
                yield Issue(ERROR, "Readable", where, "no face-like blend shapes (no ARKit-named shape that "
                            "moves): personalize finds no face mesh", "name the face shapes as ARKit does "
                            "(eyeBlinkLeft, jawOpen, ...) or pass the studio's names with --name-map")
    except UsdFaceError as exc:
        yield Issue(ERROR, "Readable", exc.prim or "/", exc.message,
                    exc.fix or "repair the rig; usdface inspect FILE shows what it reads")
    except Exception as exc:  # noqa: BLE001  (a reader crash is a finding, not a crash of the validator)
        yield Issue(ERROR, "Readable", "/", f"the avatar reader failed ({type(exc).__name__}: "
                    f"{str(exc).strip()[:160]})", "re-export the avatar; usdface inspect FILE")
