"""A studio's channel-name map: ``{"studio_channel": "arkitName"}`` from a JSON object or a two-column CSV.

For the names :mod:`usdface.arkit` does not recognise by itself (``Blink_L``, ``JawDrop``, a house prefix...).
The map is read and validated before any work: every target must be an ARKit name (any accepted spelling,
stored canonical), no ARKit name may be the target of two channels, keys must be unique and non-empty.

Formats:

* JSON: one object, ``{"Blink_L": "eyeBlinkLeft", "JawDrop": "jawOpen"}``;
* CSV: two columns ``studio channel, ARKit name`` (comma, semicolon or tab), an optional header row whose
  second cell is ``arkit``/``arkitName``/``arkit_name``/``target``, blank lines and ``#`` comments ignored.

Example::

    from usdface.io.name_map import read_name_map
    mapping = read_name_map("studio_names.csv")      # {"Blink_L": "eyeBlinkLeft", ...}
    avatar = usdface.read_avatar("avatar.usdc", name_map=mapping)
"""

from __future__ import annotations

import csv
import difflib
import io
import json
import os
from pathlib import Path

from .. import arkit
from ..errors import InputFileError

#: Second-column header cells of a CSV map.
CSV_HEADERS = frozenset({"arkit", "arkitname", "arkit_name", "arkit name", "target", "canonical"})


def _closest(name: str) -> str:
    """' (did you mean 'jawOpen'?)' for the nearest ARKit name, or the names' first ones when none is near."""
    lowered = [n.lower() for n in arkit.ARKIT_NAMES]
    hit = difflib.get_close_matches(str(name).lower(), lowered, n=1, cutoff=0.6)
    if not hit:
        return " (eyeBlinkLeft, jawOpen, ...)"
    return f" (did you mean {next(n for n in arkit.ARKIT_NAMES if n.lower() == hit[0])!r}?)"


def validate_name_map(pairs, source=None) -> dict[str, str]:
    """``pairs`` ([(studio name, ARKit name)] or a dict) -> {studio name: canonical ARKit name}.

    Raises :class:`InputFileError` naming ``source`` (the file, or None for a dict given in Python) on an
    empty map, a non-text or empty name, a key given twice, a target that is no ARKit name, or two channels
    mapped to the same ARKit name.
    """
    label = source if source is not None else "name map"
    items = list(pairs.items()) if isinstance(pairs, dict) else list(pairs)
    if not items:
        raise InputFileError("the name map is empty", path=label,
                             fix='give at least one {"studio_channel": "arkitName"} pair')
    out: dict[str, str] = {}
    claimed: dict[str, str] = {}
    for key, target in items:
        if not isinstance(key, str) or not isinstance(target, str) or not key.strip() or not target.strip():
            raise InputFileError(f"name map entry {key!r}: {target!r} is not a pair of non-empty names",
                                 path=label, fix='write each entry as "studio_channel": "arkitName"')
        key, target = key.strip(), target.strip()
        if key in out:
            raise InputFileError(f"name map lists channel {key!r} twice", path=label,
                                 fix="keep one entry per studio channel")
        canonical = arkit.normalize_name(target)
        if canonical is None:
            raise InputFileError(f"name map target {target!r} (for {key!r}) is not an ARKit name",
                                 path=label, fix=f"map it to one of the 52 ARKit names{_closest(target)}")
        if canonical in claimed:
            raise InputFileError(f"name map maps both {claimed[canonical]!r} and {key!r} to {canonical!r}",
                                 path=label, fix="map each ARKit name from one studio channel only")
        claimed[canonical] = key
        out[key] = canonical
    return out


def _parse_json(text: str, path: Path) -> list[tuple]:
    def pairs_hook(pairs):
        return pairs

    try:
        data = json.loads(text, object_pairs_hook=pairs_hook)
    except ValueError as exc:
        raise InputFileError(f"not valid JSON ({exc})", path=path,
                             fix='write the map as one JSON object {"studio_channel": "arkitName"}') from None
    if not isinstance(data, list) or not all(isinstance(p, tuple) for p in data):
        raise InputFileError("the JSON name map is not an object", path=path,
                             fix='write the map as one JSON object {"studio_channel": "arkitName"}')
    kind = dict(data).get("format")
    if isinstance(kind, str) and kind.startswith("usdface."):   # a retarget map ('map.json'), not names
        raise InputFileError(f"a usdface output ({kind}), not a name map", path=path,
                             fix='pass the name map: a JSON object {"studio_channel": "arkitName"} or a '
                                 "two-column CSV (docs/names.md)")
    return data


def _parse_csv(text: str, path: Path) -> list[tuple]:
    kept = [(i + 1, ln) for i, ln in enumerate(text.splitlines())
            if ln.strip() and not ln.lstrip().startswith("#")]
    lines = [ln for _, ln in kept]
    numbers = [i for i, _ in kept]      # the file's line of each row kept (blank lines and comments skipped)
    if not lines:
        return []
    try:
        dialect = csv.Sniffer().sniff(lines[0], delimiters=",;\t")
    except csv.Error:
        dialect = csv.excel
    rows = list(csv.reader(io.StringIO("\n".join(lines)), dialect))
    if len(rows) != len(numbers):       # a quoted cell over several lines: count rows instead
        numbers = list(range(1, len(rows) + 1))
    if rows and len(rows[0]) >= 2 and rows[0][1].strip().lower() in CSV_HEADERS:
        rows, numbers = rows[1:], numbers[1:]
    pairs = []
    for k, row in enumerate(rows):
        cells = [c.strip() for c in row]
        while cells and not cells[-1]:
            cells.pop()
        if len(cells) != 2:
            raise InputFileError(f"line {numbers[k]} ({', '.join(row)!r}) has {len(cells)} cells, not 2",
                                 path=path, fix="write one 'studio_channel,arkitName' pair per line")
        pairs.append((cells[0], cells[1]))
    return pairs


def read_name_map(source) -> dict[str, str] | None:
    """A name map from a JSON / CSV file (path), or a dict given in Python; None passes through.

    The file's format is taken from its suffix (``.json``; ``.csv``/``.tsv``/``.txt``), else from its first
    character (``{`` = JSON). Returns {studio channel: canonical ARKit name}; raises :class:`InputFileError`
    naming the file and the fix on an unreadable or invalid map (see :func:`validate_name_map`).
    """
    if source is None:
        return None
    if isinstance(source, dict):
        return validate_name_map(source)
    if not isinstance(source, str | os.PathLike):     # died with Python's TypeError from Path()
        from ..errors import OptionError

        raise OptionError("name_map must be a {studio channel: ARKit name} dict or a JSON / CSV file's "
                          f"path, not {type(source).__name__} ({source!r:.60})",
                          fix='pass e.g. {"Blink_L": "eyeBlinkLeft"} or "names.json"')
    path = Path(source)
    if not path.is_file():
        raise InputFileError("name map not found" if not path.exists() else "name map is not a file",
                             path=path, fix="pass a .json or .csv name map file to --name-map")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(f"cannot read the name map ({exc})", path=path,
                             fix="pass a readable UTF-8 .json or .csv file") from None
    suffix = path.suffix.lower()
    as_json = suffix == ".json" or (suffix not in (".csv", ".tsv", ".txt") and text.lstrip().startswith("{"))
    pairs = _parse_json(text, path) if as_json else _parse_csv(text, path)
    return validate_name_map(pairs, path)
