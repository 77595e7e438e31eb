"""The 52 ARKit blendshape names, their three spellings in real use, and left/right pairs.

Spellings that mean the same shape:

* Apple's ``ARFaceAnchor.BlendShapeLocation`` case names: ``eyeBlinkLeft`` (canonical here);
* ARKit raw values: ``eyeBlink_L``;
* Live Link Face CSV columns: ``EyeBlinkLeft``.

:func:`normalize_name` maps any of them to the canonical name; :func:`match_names` maps a whole list and
reports what was not exact (DCC numeric suffixes such as Blender's ``eyeBlinkLeft2``), unknown and missing.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

#: Apple's 52 names, in ARKit documentation order.
ARKIT_NAMES: tuple[str, ...] = (
    "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft", "eyeSquintLeft",
    "eyeWideLeft", "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight",
    "eyeSquintRight", "eyeWideRight", "jawForward", "jawLeft", "jawRight", "jawOpen", "mouthClose",
    "mouthFunnel", "mouthPucker", "mouthLeft", "mouthRight", "mouthSmileLeft", "mouthSmileRight",
    "mouthFrownLeft", "mouthFrownRight", "mouthDimpleLeft", "mouthDimpleRight", "mouthStretchLeft",
    "mouthStretchRight", "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper",
    "mouthPressLeft", "mouthPressRight", "mouthLowerDownLeft", "mouthLowerDownRight", "mouthUpperUpLeft",
    "mouthUpperUpRight", "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft",
    "browOuterUpRight",
    "cheekPuff", "cheekSquintLeft", "cheekSquintRight", "noseSneerLeft", "noseSneerRight", "tongueOut",
)
ARKIT_SET = frozenset(ARKIT_NAMES)
#: Shapes a complete rig may omit.
OPTIONAL_NAMES = frozenset({"tongueOut"})


def raw_name(name: str) -> str:
    """ARKit raw value of a canonical name: ``eyeBlinkLeft`` -> ``eyeBlink_L``."""
    for side, suffix in (("Left", "_L"), ("Right", "_R")):
        if name.endswith(side):
            return name[: -len(side)] + suffix
    return name


def livelink_name(name: str) -> str:
    """Live Link Face column of a canonical name: ``eyeBlinkLeft`` -> ``EyeBlinkLeft``."""
    return name[:1].upper() + name[1:]


_LOOKUP: dict[str, str] = {}
for _n in ARKIT_NAMES:
    for _spelling in (_n, raw_name(_n), livelink_name(_n)):
        _LOOKUP[_spelling] = _n
        _LOOKUP[_spelling.lower()] = _n


def normalize_name(name: str) -> str | None:
    """Canonical ARKit name for any of the three spellings (case-insensitive), or None if it is not one."""
    return _LOOKUP.get(name) or _LOOKUP.get(name.lower())


def mirror_name(name: str) -> str:
    """The left/right counterpart of a canonical name (the name itself for centre shapes)."""
    if name.endswith("Left"):
        return name[:-4] + "Right"
    if name.endswith("Right"):
        return name[:-5] + "Left"
    return name


_SUFFIX = re.compile(r"^(.*?)(?:[._]?\d+)$")


@dataclass
class NameMatch:
    """How a list of names maps to ARKit.

    canonical[i] is the ARKit name of names[i] (or names[i] itself when it is unknown); inexact lists
    (given, canonical, how) for every mapping that was not an exact canonical spelling.
    """

    names: list[str]
    canonical: list[str]
    inexact: list[tuple[str, str, str]] = field(default_factory=list)
    unknown: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    duplicates: list[str] = field(default_factory=list)

    @property
    def mapping(self) -> dict[str, str]:
        return dict(zip(self.names, self.canonical, strict=True))


def match_name(name: str, fallback: str | None = None) -> tuple[str | None, str]:
    """Map one name (or a fallback such as a BlendShape prim name) to ARKit.

    Returns (canonical or None, how) with how one of ``exact``, ``spelling``, ``fallback``, ``suffix``,
    ``unknown``.
    """
    if name in ARKIT_SET:
        return name, "exact"
    hit = normalize_name(name)
    if hit:
        return hit, "spelling"
    if fallback is not None:
        hit = normalize_name(fallback)
        if hit:
            return hit, "fallback"
    m = _SUFFIX.match(name)
    if m:
        hit = normalize_name(m.group(1))
        if hit:
            return hit, "suffix"
    return None, "unknown"


def match_names(names, fallbacks=None) -> NameMatch:
    """Map a list of names to canonical ARKit names, reporting inexact, unknown, missing and duplicates.

    Unknown names are kept (canonical = the name itself), never dropped.
    """
    names = [str(n) for n in names]
    fallbacks = list(fallbacks) if fallbacks is not None else [None] * len(names)
    canonical, inexact, unknown = [], [], []
    for n, fb in zip(names, fallbacks, strict=True):
        hit, how = match_name(n, fb)
        if hit is None:
            unknown.append(n)
            canonical.append(n)
        else:
            canonical.append(hit)
            if how != "exact":
                inexact.append((n, hit, how))
    seen, dup = set(), []
    for c in canonical:
        if c in seen:
            dup.append(c)
        seen.add(c)
    missing = [n for n in ARKIT_NAMES if n not in seen]
    return NameMatch(names, canonical, inexact, unknown, missing, dup)
