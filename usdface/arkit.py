"""The 52 ARKit blendshape names, the spellings studios ship them in, and left/right pairs.

Spellings that mean the same shape (:func:`normalize_name`, case- and separator-insensitive):

* Apple's ``ARFaceAnchor.BlendShapeLocation`` case names: ``eyeBlinkLeft`` (canonical here);
* ARKit raw values: ``eyeBlink_L``; Live Link Face CSV columns: ``EyeBlinkLeft``;
* snake / title case with either side word: ``eye_blink_left``, ``Eye_Blink_L``, ``EyeBlink_L``,
  ``EYE_BLINK_L``; the side may also lead (``L_eyeBlink``) or follow the first word (``Eye_L_Look_Down``);
* Character Creator (CC3+/CC4 "Extended" facial profile) names with a one-to-one ARKit equivalent
  (:data:`CC_ALIASES`: ``Brow_Drop_L``, ``Cheek_Raise_L``, ``Mouth_Up_Upper_L``, ``Eye_L_Look_R``...).
  CC's half shapes of a centre ARKit shape (``Brow_Raise_Inner_L``, ``Cheek_Puff_L``,
  ``Mouth_Roll_In_Upper_L``) are one side of ``browInnerUp`` / ``cheekPuff`` / ``mouthRollUpper``, not
  the shape: they stay unknown.

:func:`match_name` also undoes DCC decorations (Blender's ``eyeBlinkLeft.001`` / ``eyeBlinkLeft2``, a Maya
blendShape node prefix ``blendShape1.eyeBlinkLeft``, a namespace ``head:eyeBlinkLeft``) and applies a studio's
own name map first; :func:`match_names` maps a whole list, reports how each name was mapped, what was unknown
and missing, and (with ``resolve=True``) keeps only the best of several channels that mean the same shape.
"""

from __future__ import annotations

import functools
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
#: The gaze channels: in an engine (Live Link, Unity's ARKit face) they drive the eyes' rotation (the eye
#: bones or the eyeball meshes), not only the lid skin their blend shapes move on the face mesh.
GAZE_NAMES = frozenset(f"eyeLook{d}{s}" for d in ("Down", "In", "Out", "Up") for s in ("Left", "Right"))
#: Shapes a complete rig may omit.
OPTIONAL_NAMES = frozenset({"tongueOut"})
#: Similarity (difflib ratio) above which an unknown name is taken as a likely misspelling of an ARKit name.
MISSPELLING_CUTOFF = 0.8

#: Character Creator (Reallusion CC3+/CC4 Extended profile) morph names whose ARKit equivalent is not a mere
#: respelling. The others (``Eye_Blink_L``, ``Mouth_Smile_L``, ``Jaw_Open``, ``Jaw_L``, ``Mouth_Close``,
#: ``Nose_Sneer_L``...) are spellings and need no entry. CC's eye looks name the gaze direction per eye:
#: the left eye looking right looks in (towards the nose).
CC_ALIASES: dict[str, str] = {
    "Brow_Drop_L": "browDownLeft", "Brow_Drop_R": "browDownRight",
    "Brow_Raise_Outer_L": "browOuterUpLeft", "Brow_Raise_Outer_R": "browOuterUpRight",
    "Cheek_Raise_L": "cheekSquintLeft", "Cheek_Raise_R": "cheekSquintRight",
    "Eye_L_Look_L": "eyeLookOutLeft", "Eye_L_Look_R": "eyeLookInLeft",
    "Eye_R_Look_L": "eyeLookInRight", "Eye_R_Look_R": "eyeLookOutRight",
    "Mouth_Down_Lower_L": "mouthLowerDownLeft", "Mouth_Down_Lower_R": "mouthLowerDownRight",
    "Mouth_Up_Upper_L": "mouthUpperUpLeft", "Mouth_Up_Upper_R": "mouthUpperUpRight",
    "Mouth_Roll_In_Lower": "mouthRollLower", "Mouth_Roll_In_Upper": "mouthRollUpper",
}

#: How a name was mapped (:func:`match_name`), best first, with the words reports use.
HOW_LABELS: dict[str, str] = {
    "exact": "exact", "name-map": "name map", "spelling": "spelling variant",
    "alias": "Character Creator name",
    "fallback": "BlendShape prim name", "suffix": "DCC suffix", "prefix": "DCC node prefix",
    "unknown": "unmapped", "conflict": "unmapped: same shape as a better channel",
}
_RANK = {how: i for i, how in enumerate(HOW_LABELS) if how != "conflict"}


def raw_name(name: str) -> str:
    """ARKit raw value of a canonical name: ``eyeBlinkLeft`` -> ``eyeBlink_L``."""
    for side, suffix in (("Left", "_L"), ("Right", "_R")):
        if name.endswith(side):
            return name[: -len(side)] + suffix
    return name


def livelink_name(name: str) -> str:
    """Live Link Face column of a canonical name: ``eyeBlinkLeft`` -> ``EyeBlinkLeft``."""
    return name[:1].upper() + name[1:]


_WORD = re.compile(r"[A-Z]+(?=[A-Z][a-z])|[A-Z]?[a-z]+|[A-Z]+|\d+")
_SIDES = {"l": "left", "left": "left", "r": "right", "right": "right"}


def spelling_key(name: str) -> str:
    """A name reduced to what every spelling of it shares: its words lower-cased and joined, one side word
    (``L``/``Left``/``R``/``Right``, wherever it stands) moved to the end as ``left``/``right``.

    ``eyeBlinkLeft``, ``eyeBlink_L``, ``EyeBlinkLeft``, ``eye_blink_left``, ``Eye_Blink_L``, ``L_EyeBlink``
    -> ``eyeblinkleft``. A name with two side words (``Eye_L_Look_R``) keeps them in place.
    """
    words = [w.lower() for w in _WORD.findall(name)]
    sides = [i for i, w in enumerate(words) if w in _SIDES]
    if len(sides) == 1 and len(words) > 1:
        side = _SIDES[words.pop(sides[0])]
        words.append(side)
    return "".join(words)


def _build_lookup() -> dict[str, str]:
    lookup: dict[str, str] = {}
    for n in ARKIT_NAMES:
        key = spelling_key(n)
        assert key not in lookup, f"two ARKit names share the spelling key {key!r}"
        lookup[key] = n
    return lookup


_LOOKUP = _build_lookup()
_ALIASES = {spelling_key(k): v for k, v in CC_ALIASES.items()}


def normalize_name(name: str) -> str | None:
    """Canonical ARKit name for any spelling of it (see the module doc), or None if it is not one."""
    return _LOOKUP.get(spelling_key(str(name)))


def lookalike(name: str) -> str | None:
    """The ARKit name an unknown ``name`` looks like: one spelled inside it after a studio's prefix or before
    its suffix (``STU_eyeBlinkLeft``, ``jawOpen_geo``: the longest such), else a close misspelling (difflib
    ratio >= :data:`MISSPELLING_CUTOFF`); None for a name that is one (:func:`normalize_name`) or looks like
    none. What a ``--name-map`` would map."""
    import difflib

    if normalize_name(name) is not None:
        return None
    key = spelling_key(str(name))
    inside = [n for k, n in _LOOKUP.items() if len(k) >= 6 and (key.endswith(k) or key.startswith(k))]
    if inside:
        return max(inside, key=len)
    hit = difflib.get_close_matches(key, list(_LOOKUP), n=1, cutoff=MISSPELLING_CUTOFF)
    return _LOOKUP[hit[0]] if hit else None


def mirror_name(name: str) -> str:
    """The left/right counterpart of a canonical name (the name itself for centre shapes)."""
    if name.endswith("Left"):
        return name[:-4] + "Right"
    if name.endswith("Right"):
        return name[:-5] + "Left"
    return name


_SUFFIX = re.compile(r"^(.*?)(?:[._]?\d+)$")
_PREFIX = re.compile(r"^.*[.:|](?=[^.:|]+$)")


def _spelled(name: str) -> tuple[str | None, str]:
    if name in ARKIT_SET:
        return name, "exact"
    key = spelling_key(name)
    if key in _LOOKUP:
        return _LOOKUP[key], "spelling"
    if key in _ALIASES:
        return _ALIASES[key], "alias"
    return None, "unknown"


def undecorated(name: str) -> list[tuple[str, str]]:
    """``name`` without the decorations DCCs add, as ``[(bare name, "suffix" | "prefix")]``: a numeric suffix
    (Blender ``.001``, ``2``; Maya ``1``) and a node / namespace prefix (``blendShape1.``, ``head:``,
    ``|head|``), each alone and both together."""
    out = []
    m = _SUFFIX.match(name)
    bare = m.group(1) if m and m.group(1) else name
    if bare != name:
        out.append((bare, "suffix"))
    stripped = _PREFIX.sub("", bare)
    if stripped != bare and stripped:
        out.append((stripped, "prefix"))
    return out


def unused_map_entries(name_map, channels) -> list[str]:
    """The entries of ``name_map`` ({studio name: ARKit name}) that match none of ``channels`` (the names as
    authored) nor their undecorated forms (:func:`undecorated`): a typo in the map, or another rig's map.
    What ``inspect`` notes and ``check`` reports."""
    forms = set(channels)
    forms |= {bare for t in list(forms) for bare, _ in undecorated(t)}
    return [k for k in name_map or {} if k not in forms]


def match_name(name: str, fallback: str | None = None,
               name_map: dict[str, str] | None = None) -> tuple[str | None, str]:
    """Map one name (or a fallback such as a BlendShape prim name) to ARKit.

    ``name_map`` ({studio name: canonical ARKit name}, validated by :func:`usdface.io.name_map.read_name_map`)
    is tried first, on the name and on its undecorated forms. Returns (canonical or None, how), ``how`` one of
    :data:`HOW_LABELS`: ``exact``, ``name-map``, ``spelling``, ``alias`` (Character Creator), ``fallback``
    (the BlendShape prim's name), ``suffix`` / ``prefix`` (DCC decoration), ``unknown``.
    """
    name = str(name)
    if not name_map:                       # pure in (name, fallback): every frame's weights repeat them
        return _match_plain(name, None if fallback is None else str(fallback))
    return _match(name, fallback, name_map)


@functools.lru_cache(maxsize=8192)
def _match_plain(name: str, fallback: str | None) -> tuple[str | None, str]:
    return _match(name, fallback, None)


def _match(name: str, fallback, name_map) -> tuple[str | None, str]:
    bare = undecorated(name)
    if name_map:
        for candidate in [name] + [b for b, _ in bare]:
            if candidate in name_map:
                return name_map[candidate], "name-map"
    hit, how = _spelled(name)
    if hit:
        return hit, how
    if fallback is not None:
        hit, _ = _spelled(str(fallback))
        if hit:
            return hit, "fallback"
    for candidate, how in bare:
        hit, _ = _spelled(candidate)
        if hit:
            return hit, how
    return None, "unknown"


@dataclass
class NameMatch:
    """How a list of names maps to ARKit.

    canonical[i] is the ARKit name of names[i] (or names[i] itself when it is unknown or lost a conflict);
    how[i] how it was mapped (:data:`HOW_LABELS`); inexact lists (given, canonical, how) for every mapping
    that was not an exact canonical spelling; conflicts (given, canonical, kept) the channels that meant the
    same shape as a better one (``kept``) and were left unmapped (``resolve=True``); duplicates the canonical
    names claimed twice (``resolve=False``).
    """

    names: list[str]
    canonical: list[str]
    inexact: list[tuple[str, str, str]] = field(default_factory=list)
    unknown: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    duplicates: list[str] = field(default_factory=list)
    how: list[str] = field(default_factory=list)
    conflicts: list[tuple[str, str, str]] = field(default_factory=list)

    @property
    def mapping(self) -> dict[str, str]:
        return dict(zip(self.names, self.canonical, strict=True))

    @property
    def channels(self) -> list[tuple[str, str | None, str]]:
        """(given, canonical ARKit name or None, how) per name, in order."""
        return [(n, c if h not in ("unknown", "conflict") else None, h)
                for n, c, h in zip(self.names, self.canonical, self.how, strict=True)]


def match_names(names, fallbacks=None, name_map: dict[str, str] | None = None,
                resolve: bool = False) -> NameMatch:
    """Map a list of names to canonical ARKit names, reporting inexact, unknown, missing and duplicates.

    Unknown names are kept (canonical = the name itself), never dropped. With ``resolve``, when several names
    map to one ARKit shape the best mapping keeps it (order of :data:`HOW_LABELS`: exact, name map, spelling,
    alias, prim name, suffix, prefix; the first on a tie) and the others keep their own name, listed in
    ``conflicts`` with how ``"conflict"``; without it they are listed in ``duplicates``.
    """
    names = [str(n) for n in names]
    fallbacks = list(fallbacks) if fallbacks is not None else [None] * len(names)
    hits = [match_name(n, fb, name_map) for n, fb in zip(names, fallbacks, strict=True)]
    canonical = [hit if hit is not None else n for n, (hit, _) in zip(names, hits, strict=True)]
    how = [h for _, h in hits]
    conflicts: list[tuple[str, str, str]] = []
    if resolve:
        best: dict[str, int] = {}
        for i, (hit, h) in enumerate(hits):
            if hit is not None and (hit not in best or _RANK[h] < _RANK[how[best[hit]]]):
                best[hit] = i
        for i, (hit, _) in enumerate(hits):
            if hit is not None and best[hit] != i:
                conflicts.append((names[i], hit, names[best[hit]]))
                canonical[i], how[i] = names[i], "conflict"
    inexact = [(n, c, h) for n, c, h in zip(names, canonical, how, strict=True)
               if h not in ("exact", "unknown", "conflict")]
    unknown = [n for n, h in zip(names, how, strict=True) if h == "unknown"]
    seen, dup = set(), []
    for c in canonical:
        if c in seen:
            dup.append(c)
        seen.add(c)
    missing = [n for n in ARKIT_NAMES if n not in seen]
    return NameMatch(names, canonical, inexact, unknown, missing, dup, how, conflicts)
