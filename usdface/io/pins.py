"""Artist pins (Hable's artist constraints) from a file: which vertices of which shapes the fit must keep at
the template's (the artist's) version.

Two sources, both read into ``{capture shape name: vertex indices}`` for
:func:`usdface.personalize.fit_personalized_shapes` (``pins=``):

* a JSON file: ``{"pins": {"jawOpen": [12, 13, 14], "eyeBlink_L": [...]}}`` (or the inner mapping alone);
  shape names in any ARKit spelling, vertex indices of the capture mesh;
* a USD file (e.g. the capture ``.usda`` itself, after an artist painted it): per-vertex primvars
  ``primvars:usdface:pin:<shape>`` (float or bool, ``vertex`` interpolation; a vertex is pinned where the
  value is > 0.5) on a Mesh with the capture's vertex count (the Template's mesh is read first).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..arkit import MISSPELLING_CUTOFF, lookalike, normalize_name
from ..errors import InputFileError

__all__ = ["read_pins", "Pins", "PIN_PRIMVAR"]

#: Namespace of the per-vertex pin primvars (``primvars:usdface:pin:<shape>``).
PIN_PRIMVAR = "usdface:pin:"


class Pins(dict):
    """Artist pins read from a file: ``{capture shape name: vertex indices[int64]}`` (a dict, as
    :func:`usdface.personalize.fit_personalized_shapes` takes them) that remembers the file (``source``), so
    a layer personalized with them records that file and its digest among its inputs."""

    def __init__(self, pins=(), source=None):
        super().__init__(pins)
        self.source = None if source is None else Path(source)


def _shape_index(names) -> dict:
    index = {}
    for nm in names:
        index[str(nm)] = nm
        canon = normalize_name(nm)
        if canon is not None:
            index.setdefault(canon, nm)
    return index


def _resolve(name, index, path, prim=None):
    key = normalize_name(name) or str(name)
    if str(name) in index:
        return index[str(name)]
    if key in index:
        return index[key]
    shapes = list(dict.fromkeys(index.values()))
    listed = ", ".join(map(str, shapes[:8])) + (f" ... (+{len(shapes) - 8})" if len(shapes) > 8 else "")
    meant = _meant(name, index)
    fix = (f"did you mean {meant!r}? " if meant else "") + \
        f"use the capture's shape names (any ARKit spelling): {listed}"
    raise InputFileError(f"pins name a shape the capture lacks: {name!r}", path=path, prim=prim, fix=fix)


def _meant(name, index):
    """The capture's shape a misspelt pin name (``jawOpne``) was meant as, or None: the ARKit name it looks
    like (:func:`usdface.arkit.lookalike`), else the closest of the capture's own names (a studio name)."""
    import difflib

    canon = lookalike(str(name))
    if canon is not None and canon in index:
        return str(index[canon])
    hit = difflib.get_close_matches(str(name), [str(k) for k in index], n=1, cutoff=MISSPELLING_CUTOFF)
    return str(index[hit[0]]) if hit else None


def _read_json(path: Path, names, n: int) -> dict:
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputFileError(f"cannot read pins: {exc}", path=path,
                             fix='write JSON like {"pins": {"jawOpen": [12, 13]}}') from None
    if isinstance(doc, dict) and "pins" in doc and not isinstance(doc["pins"], dict):
        # it was read as a shape named 'pins' ("pins name a shape the capture lacks: 'pins'")
        raise InputFileError(f"\"pins\" is a {type(doc['pins']).__name__}, not a mapping of shape names to "
                             "vertex lists", path=path, fix='write JSON like {"pins": {"jawOpen": [12, 13]}}')
    if isinstance(doc, dict) and isinstance(doc.get("pins"), dict):
        index = _shape_index(names)
        beside = [k for k in doc if k != "pins" and (str(k) in index or normalize_name(k) in index)]
        if beside:
            # shapes beside the "pins" mapping were dropped without a word (an artist's pins lost)
            raise InputFileError(f"shape(s) {', '.join(map(repr, beside))} beside the \"pins\" mapping, "
                                 "outside it: they would be ignored", path=path,
                                 fix="move them into \"pins\" (or drop the \"pins\" level and list every "
                                     "shape at the top)")
        doc = doc["pins"]
    elif isinstance(doc, dict) and not all(isinstance(v, list) for v in doc.values()):
        raise InputFileError("not a pins file: no \"pins\" mapping, and not shape names to vertex lists "
                             f"(keys {', '.join(list(map(repr, doc))[:3])}...)", path=path,
                             fix='pass the pins file, JSON like {"pins": {"jawOpen": [12, 13]}}')
    if not isinstance(doc, dict):
        raise InputFileError("pins file is not a mapping of shape names to vertex lists", path=path,
                             fix='write JSON like {"pins": {"jawOpen": [12, 13]}}')
    index, out = _shape_index(names), {}
    for name, verts in doc.items():
        shape = _resolve(name, index, path)
        if not isinstance(verts, list) or not all(isinstance(v, int) and not isinstance(v, bool)
                                                  for v in verts):
            raise InputFileError(f"pins of {name!r} are not a list of vertex indices", path=path,
                                 fix="give integer vertex indices of the capture mesh")
        v = np.asarray(verts, dtype=np.int64)
        if v.size and (v.min() < 0 or v.max() >= n):
            raise InputFileError(f"pins of {name!r} index outside 0..{n - 1}", path=path,
                                 fix="use vertex indices of the capture mesh")
        out[shape] = np.union1d(out.get(shape, np.zeros(0, np.int64)), v)
    return out


def _read_usd(path: Path, names, n: int) -> dict:
    from pxr import UsdGeom

    from .usd_open import open_usd_stage

    stage = open_usd_stage(path, "pins file", "pass a .usd/.usda/.usdc")
    meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    meshes.sort(key=lambda p: (0 if "Template" in str(p.GetPath()) else 1, str(p.GetPath())))
    index, out = _shape_index(names), {}
    for prim in meshes:
        api = UsdGeom.PrimvarsAPI(prim)
        pvs = [pv for pv in api.GetPrimvars() if pv.GetPrimvarName().startswith(PIN_PRIMVAR)]
        if not pvs:
            continue
        for pv in pvs:
            name = pv.GetPrimvarName()[len(PIN_PRIMVAR):]
            values = pv.Get()
            vals = np.asarray(values if values is not None else [], dtype=np.float64).ravel()
            if vals.shape != (n,) or pv.GetInterpolation() != UsdGeom.Tokens.vertex:
                raise InputFileError(f"pin primvar {pv.GetPrimvarName()} has {vals.size} values "
                                     f"({pv.GetInterpolation()}), expected {n} per vertex", path=path,
                                     prim=prim.GetPath(), fix="author one value per capture vertex, "
                                     "interpolation 'vertex'")
            out[_resolve(name, index, path, prim.GetPath())] = np.flatnonzero(vals > 0.5)
        return out
    raise InputFileError(f"no {PIN_PRIMVAR}<shape> primvars on any Mesh", path=path,
                         fix="paint per-vertex primvars primvars:usdface:pin:<shape> on the Template mesh")


def read_pins(path, names, n_vertices: int) -> Pins:
    """Artist pins from ``path`` (JSON or USD, see the module doc) as :class:`Pins` ``{shape name in names:
    vertex indices[int64]}`` (``.source`` = ``path``) for a capture with shape ``names`` and ``n_vertices``
    vertices. Raises
    :class:`InputFileError` naming the file (and prim) for a missing file, an unknown shape, indices out of
    range or primvars of the wrong size."""
    p = Path(path)
    if not p.is_file():
        raise InputFileError("pins file not found", path=p, fix="pass an existing .json or .usd file")
    if p.suffix.lower() in (".usd", ".usda", ".usdc", ".usdz"):
        return Pins(_read_usd(p, names, int(n_vertices)), source=p)
    return Pins(_read_json(p, names, int(n_vertices)), source=p)
