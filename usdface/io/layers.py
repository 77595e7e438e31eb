"""Layered USD output: a new layer over the untouched avatar, with personalized blend shapes and provenance.

:func:`write_avatar_layer` writes ONE new root layer that

* sublayers the input avatar by a relative asset path, so the input file is never modified (and the output
  follows it when both move together);
* repeats the input root layer's stage metadata (upAxis, metersPerUnit, defaultPrim, time codes...): USD reads
  stage metadata from the root layer only, and a layer without it would silently change units and axis;
* authors only ``over``s at the input's own prim paths (plus the few new prims below): for each
  personalized BlendShape the ``offsets`` in the mesh's local authored space (``inverse(to_internal)``
  linear part), with the sparsity re-derived (``pointIndices`` = the points whose offset is non-zero in
  effect; dense only where dense in effect), inbetweens kept consistent
  (``ib_i' = ib_i + w_i (primary' - primary)``) and normal offsets kept per point (re-indexed only if the
  point set changed);
* with ``variants=True``, adds on each SkelRoot a variant set ``usdfacePersonalization`` = {``personalized``
  (selected), ``generic``}. Opinions inside a variant are weaker than every local opinion of the layer stack
  (LIVRPS), so a variant cannot flip the original BlendShape prims. Instead each variant defines, under
  each mesh, ``usdfaceShapes/<shape>`` BlendShape prims: in ``personalized`` an internal reference to the
  original BlendShape (which composes the personalized ``over``), in ``generic`` an external reference to
  the same prim in the input file alone (the generic values); a local ``over`` of the mesh's
  ``skel:blendShapeTargets`` points at ``usdfaceShapes/<shape>`` in the same order. Pipelines that read the
  original BlendShape prims get the personalized offsets; the skeleton binding follows the variant switch;
* records provenance twice: ``customLayerData["usdface"]`` (version, command, parameters, input sha256
  digests, timings) and the ``UsdFaceProvenanceAPI`` schema applied on each SkelRoot;
* is written atomically (temporary file in the output directory + ``os.replace``) and refuses to overwrite an
  existing file unless ``force=True``.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import shlex
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import GeometryError, InputFileError, RigError, warn
from ..model import Avatar, FaceRig
from .usd_rig import PERSONALIZATION_VARIANT_SET, STAGE_METADATA_KEYS

#: File extensions the writer accepts (the format follows the extension; ``.usd`` is written as usdc).
LAYER_EXTENSIONS = (".usda", ".usdc", ".usd")
#: Scope (under each mesh, inside the variants) holding the BlendShape prims the binding points at.
SHAPES_SCOPE = "usdfaceShapes"
#: An offset is "non-zero in effect" when its length exceeds this fraction of the shape's largest offset.
SPARSE_RELATIVE_TOLERANCE = 1e-9


# ---------------------------------------------------------------------------------------------------------
# small public helpers
# ---------------------------------------------------------------------------------------------------------
def file_digest(path) -> str:
    """sha256 hex digest of a file, or of a directory (sorted relative paths + their file digests; hidden
    files and folders - a Finder's ``.DS_Store``, an editor's swap file - are not part of a capture)."""
    path = Path(path)
    if path.is_dir():
        h = hashlib.sha256()
        for child in sorted(p for p in path.rglob("*") if p.is_file()
                            and not any(part.startswith(".") for part in p.relative_to(path).parts)):
            h.update(child.relative_to(path).as_posix().encode())
            h.update(bytes.fromhex(file_digest(child)))
        return h.hexdigest()
    if not path.is_file():
        raise InputFileError("cannot digest: not found", path=path, fix="check the path")
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


class DigestsAhead:
    """:func:`file_digest` of a run's input files on a background thread, started once the run has read them:
    the file reads and the hashing release the GIL, so the digests the layer's provenance records are
    computed beside the run's work on a second core instead of in its write step (dev1: its avatar and its
    capture folder, 16 MB, 0.05 s). :meth:`get` waits for them; a path not given, or one whose digest
    failed, gives None, and the writer computes it (and reports its error) as before."""

    def __init__(self, paths):
        import threading

        self._paths = {str(p) for p in paths if p}         # ("" is no file: an in-memory input)
        self._found: dict[str, str] = {}
        self._thread = threading.Thread(target=self._run, name="usdface-digests", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        for p in sorted(self._paths):
            try:
                self._found[p] = file_digest(p)
            except Exception:  # noqa: BLE001 - the writer digests it again and says what failed
                pass

    def get(self, path) -> str | None:
        """The digest of ``path`` (as given), or None when it was not computed here."""
        if str(path) not in self._paths:
            return None
        self._thread.join()
        return self._found.get(str(path))


#: What a self-contained output (``export --flatten``) may be written as: a layer, or a ``.usdz`` package
#: of it (:func:`atomic_save_usdz`).
PACKAGE_EXTENSIONS = (*LAYER_EXTENSIONS, ".usdz")


def check_output_path(path, force: bool = False, inputs=(), what: str = "output layer",
                      example: str | None = None, usdz: bool = False, over_avatar: bool = True) -> Path:
    """Validate an output layer path before any work: a USD extension (``.usdz`` too with ``usdz``: a
    self-contained output, :func:`atomic_save_usdz`), not a directory (nor under a file), not one of the
    existing ``inputs``, and not an existing file unless ``force``. Raises InputFileError /
    OutputExistsError naming the file as ``what`` (a folder's fix names ``example`` inside it); returns the
    path as a Path. A ``.usdz`` output layer (``over_avatar``: a layer written over an avatar) is refused
    with the reason (:func:`_refuse_usdz_layer`)."""
    from .atomic import check_output_file

    if not usdz and over_avatar and what == "output layer":
        _refuse_usdz_layer(path)
    return check_output_file(path, force, suffixes=PACKAGE_EXTENSIONS if usdz else LAYER_EXTENSIONS,
                             what=what, inputs=inputs, example=example)


def _refuse_usdz_layer(path) -> None:
    """A ``.usdz`` given as the layer written over an avatar (``personalize -o``, ``landmarks -o``): a layer
    sublayers the avatar by its path and holds only overrides, where a package holds its layers and every
    file they use inside it (``UsdUtils.CreateNewUsdzPackage`` would copy the avatar in): the result would
    be no layer over the avatar, and would not follow its revisions. The fix: the layer, then its flattened
    export packaged as the ``.usdz`` asked for."""
    raw = os.fspath(path) if isinstance(path, str | os.PathLike) else str(path)
    p = Path(raw)
    if p.suffix.lower() != ".usdz" or raw.endswith(("/", os.sep)) or p.is_dir():
        return                                      # a folder named x.usdz: check_output_file says so
    layer = shlex.quote(str(p.with_suffix(".usda")))
    raise InputFileError(
        "output layer cannot be a .usdz package: the layer sublayers the avatar by its path and holds only "
        "the overrides, while a .usdz holds its layers and every file they use inside it (USD would package "
        "the avatar in: no longer a layer over the avatar, nor following its revisions)", path=path,
        fix=f"write the layer as {layer}; for one self-contained .usdz of the result, export it after that "
            f"(usdface export {layer} --flatten {shlex.quote(raw)})")


def _temp_path(path: Path) -> Path:
    from .atomic import temp_sibling

    return temp_sibling(path, create=False)  # USD creates the file itself; the unique name is what we need


def atomic_save(layer, path, force: bool = False) -> Path:
    """Write ``layer`` to ``path`` atomically: a temporary file in the same directory, then published with
    :func:`usdface.io.atomic.publish` (exclusive creation unless ``force``, so two writers of one new output
    cannot both succeed).

    Relative asset paths in the layer are written as authored, so they must be relative to ``path``'s
    directory. A layer already open at ``path`` in this process is reloaded.
    """
    from pxr import Sdf

    from .atomic import make_parents, publish, remove_made

    path = Path(path).absolute()
    tmp = None
    made: list[Path] = []
    done = False
    try:
        made = make_parents(path)
        tmp = _temp_path(path)
        if layer.realPath and Path(layer.realPath).parent == path.parent and not layer.anonymous:
            # a failed save leaves a partial file (a full disk: a .usda cut off mid-value): never published
            if not _usd_call(layer.Save, force=True):
                raise InputFileError("USD could not write the layer (is the disk full?)", path=path,
                                     fix="free disk space or write the output elsewhere (-o); an existing "
                                         "output was left as it was")
            publish(layer.realPath, path, force)
        else:
            if not _usd_call(layer.Export, str(tmp)):
                raise InputFileError("USD could not write the layer", path=path,
                                     fix="check the folder is writable and the disk has space")
            publish(tmp, path, force)
        done = True
    finally:
        if tmp is not None and tmp.exists():
            tmp.unlink()
        if not done:
            remove_made(made)     # a failure leaves no folder it made behind either
    cached = Sdf.Layer.Find(str(path))
    if cached is not None:
        cached.Reload(force=True)
    return path


def atomic_save_usdz(layer, path, force: bool = False) -> Path:
    """Write ``layer`` as the ``.usdz`` package ``path``, packaged by USD itself
    (``UsdUtils.CreateNewUsdzPackage``: the layer as ``<stem>.usdc`` inside, with every file its asset paths
    name, e.g. textures), atomically as :func:`atomic_save`: the layer exported to a hidden temporary
    ``.usdc`` beside ``path`` (its relative asset paths resolve as from ``path``'s folder), packaged to a
    hidden temporary ``.usdz`` beside it, then published (exclusive unless ``force``); the temporaries are
    removed whatever happens. For a self-contained layer (a flattened export): a layer that sublayers or
    references files would be packaged with them, no longer over them."""
    from pxr import Sdf, UsdUtils

    from .atomic import make_parents, publish, remove_made, temp_sibling

    path = Path(path).absolute()
    inner = package = None
    made: list[Path] = []
    done = False
    try:
        made = make_parents(path)
        inner = temp_sibling(path.with_suffix(".usdc"), create=False)
        package = temp_sibling(path, create=False)
        if not _usd_call(layer.Export, str(inner)):
            raise InputFileError("USD could not write the layer to package", path=path,
                                 fix="check the folder is writable and the disk has space")
        if not _usd_call(UsdUtils.CreateNewUsdzPackage, Sdf.AssetPath(str(inner)), str(package),
                         f"{path.stem}.usdc"):
            raise InputFileError("USD could not package the layer as .usdz", path=path,
                                 fix="check the folder is writable and the disk has space; or write a "
                                     ".usdc instead")
        publish(package, path, force)
        done = True
    finally:
        for tmp in (inner, package):
            if tmp is not None and tmp.exists():
                tmp.unlink()
        if not done:
            remove_made(made)
    cached = Sdf.Layer.Find(str(path))
    if cached is not None:
        cached.Reload(force=True)
    return path


def _usd_call(fn, *args, **kwargs):
    """Call a USD save/export; a ``Tf.ErrorException`` (disk full, permission) becomes an OSError-like
    failure return (False) so the caller reports it in one line."""
    try:
        return fn(*args, **kwargs)
    except Exception as exc:  # pxr.Tf.ErrorException: USD's own text
        if type(exc).__name__ == "ErrorException":
            return False
        raise


def _device(path: Path):
    """The file system (``st_dev``) holding ``path`` or, where it does not exist yet, its nearest existing
    ancestor; None when it cannot be told."""
    from .atomic import existing_ancestor

    try:
        return os.stat(existing_ancestor(path)).st_dev
    except OSError:
        return None


def _layer_path(target, folder) -> str:
    """How a layer in ``folder`` names its input ``target`` (POSIX separators): relative when the two belong
    to one project - they share a folder below the file system's root and lie on one file system - else
    absolute (an avatar library on another mount or drive: a relative ``../../../../work/lib/hero.usdc``
    broke as soon as the publish was copied to a folder of another depth, a user trial). Symlinks are kept
    (the paths as given); ``..`` in them is resolved by name first, so a relative input is judged by where
    it is."""
    target = Path(os.path.normpath(Path(target).absolute()))
    folder = Path(os.path.normpath(Path(folder).absolute()))
    try:
        common = Path(os.path.commonpath([target, folder]))
        rel = os.path.relpath(target, folder)
    except ValueError:  # different drives (Windows)
        return target.as_posix()
    a, b = _device(target), _device(folder)
    if common == Path(common.anchor) or (a is not None and b is not None and a != b):
        return target.as_posix()
    return Path(rel).as_posix()


def _relative_asset_path(target: Path, start_dir: Path) -> str:
    """The layer's asset path to its input ``target`` from the output's folder ``start_dir``
    (:func:`_layer_path`), a relative one anchored with ``./``."""
    path = _layer_path(target, start_dir)
    return path if path.startswith(".") or os.path.isabs(path) else f"./{path}"


def _usd_value(value):
    """Provenance values -> types USD dictionaries hold (dict, str, bool, int, float, lists of str/float)."""
    if isinstance(value, dict):
        return {str(k): _usd_value(v) for k, v in value.items()}
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value)
    if isinstance(value, (list, tuple, np.ndarray)):
        from pxr import Vt

        items = list(value)
        if items and all(isinstance(v, (int, float, np.number)) and not isinstance(v, (bool, np.bool_))
                         for v in items):
            return Vt.DoubleArray([float(v) for v in items])
        if all(isinstance(v, str) for v in items):
            return Vt.StringArray(items)
        return json.dumps(value.tolist() if isinstance(value, np.ndarray) else items, default=json_default)
    if value is None:
        return ""
    return str(value)


def json_default(value):
    """``json.dumps(default=...)`` for numpy values: arrays -> lists, scalars -> Python numbers, else str."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return str(value)


# ---------------------------------------------------------------------------------------------------------
# per-shape authoring data (pure numpy)
# ---------------------------------------------------------------------------------------------------------
def local_offsets(rig: FaceRig, deltas: np.ndarray) -> np.ndarray:
    """Internal offsets ``deltas[..., n, 3]`` (metres, Y up) -> the mesh's local authored space (linear
    part of ``inverse(rig.source.to_internal)``)."""
    inv = np.linalg.inv(rig.source.to_internal[:3, :3])
    return np.asarray(deltas, dtype=np.float64) @ inv.T


def effective_point_set(primary: np.ndarray, extra=(), rtol: float = SPARSE_RELATIVE_TOLERANCE) -> np.ndarray:
    """Boolean ``[n]``: points whose offset (primary ``[n,3]`` or any ``extra[n,3]``) is non-zero in effect,
    i.e. longer than ``rtol`` times the largest offset of that array."""
    # (imported here: scipy is not imported with this module, see the CLI's SOURCE_DATE_EPOCH check)
    from ..mesh import vector_lengths

    moved = np.zeros(len(primary), dtype=bool)
    for arr in (primary, *extra):
        norms = vector_lengths(arr)                 # np.linalg.norm(arr, axis=1) to the bit
        peak = norms.max() if norms.size else 0.0
        if peak > 0:
            moved |= norms > rtol * peak
    return moved


# ---------------------------------------------------------------------------------------------------------
# the writer
# ---------------------------------------------------------------------------------------------------------
def avatar_mesh(avatar: Avatar, key: str, context: str = "in the avatar") -> FaceRig:
    """``avatar.mesh(key)`` (prim name or path), raising :class:`~usdface.errors.RigError` naming the avatar
    file and the meshes it does have when there is no such mesh, and when a name (not a path) names meshes
    of several characters (two SkelRoots with a ``Head``: the first was taken until stop 45)."""
    same = [m.source.prim for m in avatar.meshes if m.source is not None and m.source.prim != key
            and (m.name == key or m.source.prim.endswith("/" + key.lstrip("/")))]
    if len(same) > 1:
        raise RigError(f"{len(same)} meshes are named {key!r} ({', '.join(same)}): which one is meant is "
                       "not for usdface to guess", path=avatar.file, prim=same[0],
                       fix=f"give the mesh's prim path: one of {', '.join(same)}")
    try:
        return avatar.mesh(key)
    except KeyError:
        meshes = ", ".join(m.key for m in avatar.meshes)
        fix = f"use one of {meshes}" if meshes else "pass an avatar with a face rig"
        static = [p for p in (avatar.metadata or {}).get("static_meshes", {})
                  if key in (p, p.rsplit("/", 1)[-1])]
        if static:       # it is there, without shapes (an eye bound to the skeleton): "no mesh" misled
            raise RigError(f"mesh {key!r} has no blend shapes (a static mesh, as an eye bound to the "
                           "skeleton only)", path=avatar.file, prim=static[0], fix=fix) from None
        raise RigError(f"no mesh {key!r} {context}", path=avatar.file, fix=fix) from None


def _resolve_offsets(avatar: Avatar, offsets: dict) -> list[tuple[FaceRig, object]]:
    from ..submesh import SparseOffsets

    out = []
    for key, deltas in offsets.items():
        rig = avatar_mesh(avatar, key)
        if rig.source is None or not rig.source.prim:
            raise RigError(f"mesh {key!r} has no USD source to write over", path=avatar.file,
                           fix="read the avatar with usdface.io.usd_rig.read_avatar")
        region = rig.source.region
        full = (rig.n_shapes, region.n if region is not None else rig.n_vertices, 3)
        if isinstance(deltas, SparseOffsets):
            if region is not None and not (np.array_equal(deltas.vertices, region.vertices)
                                           and _same_copies(deltas.copies, region.copies)):
                deltas = _on_region(rig, deltas, avatar.file)     # e.g. a welded part (its copies apart)
            values = deltas.values
        else:
            deltas = values = np.asarray(deltas, dtype=np.float64)
        if tuple(deltas.shape) != full:
            raise GeometryError(f"offsets for {rig.source.prim} have shape {tuple(deltas.shape)}, the rig "
                                f"{full} [K,n,3]", path=avatar.file, prim=rig.source.prim,
                                fix="give one [n,3] offset array per rig shape, in rig.names order")
        if not np.isfinite(values).all():
            raise GeometryError("offsets contain NaN/inf", path=avatar.file, prim=rig.source.prim,
                                fix="check the personalization step that produced them")
        if region is not None and not isinstance(deltas, SparseOffsets):   # dense over a cropped rig
            deltas = SparseOffsets(region.vertices, deltas[:, region.vertices], region.n,
                                   copies=region.copies)
        out.append((rig, deltas))
    return out


def _same_copies(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def _on_region(rig: FaceRig, deltas, file):
    """Sparse offsets given on another part of the mesh than the rig holds (the pipeline's welded part of a
    mesh the reader cropped: copies of a vertex held apart) re-expressed on the rig's own region: each of
    its vertices takes the value given for it (as a vertex or a copy), the rig's own offsets where none
    is; a vertex the region lacks but the offsets move is refused."""
    from ..submesh import SparseOffsets

    region = rig.source.region
    at = np.full(region.n, -1, dtype=np.int64)
    at[deltas.vertices] = np.arange(deltas.vertices.size)
    copies = deltas.copies
    if copies is not None:
        at[copies[0]] = copies[1]
    where = at[region.vertices]
    given = at >= 0                                       # a value is given there (a vertex or a copy)
    given[region.vertices] = False
    outside = np.flatnonzero(given)
    if outside.size:
        there = deltas.values[:, at[outside]]
        base = None if deltas.base is None else np.asarray(deltas.base)[:, outside]
        if np.abs(there).max() > 0 and (base is None or np.abs(base - there).max() > 0):
            raise GeometryError(f"sparse offsets for {rig.source.prim} move vertices the rig does not hold",
                                path=file, prim=rig.source.prim,
                                fix="give offsets on the rig's region (rig.source.region.vertices)")
    values = rig.deltas.copy()
    ok = where >= 0
    values[:, ok] = deltas.values[:, where[ok]]
    return SparseOffsets(region.vertices, values, region.n, copies=region.copies)


def _shape_support(rig: FaceRig, k: int, deltas) -> tuple:
    """Shape ``k``'s new and old offsets (internal metres) where the layer may author them:
    ``(points[p] or None for every vertex, new[p,3], old[p,3], [old inbetween[p,3], ...])``. A rig on its
    moving part (``rig.source.region``) adds the authored points outside it (``rig.source.residue``: kept
    as they were) and those with normal offsets; nothing of size ``[n]`` beyond them is formed."""
    from ..submesh import SparseOffsets

    src = rig.source
    ibs = rig.inbetweens.get(rig.names[k], [])
    region = src.region
    if region is None:
        if isinstance(deltas, SparseOffsets):
            new = rig.deltas[k].copy()
            at, values = deltas.shape_row(k)               # a welded part's copies with their twin's values
            new[at] = values
        else:
            new = deltas[k]
        return None, new, rig.deltas[k], [ib.offsets for ib in ibs]
    r_idx, r_off, r_ibs = (src.residue[k] if src.residue else
                           (np.zeros(0, dtype=np.int64), np.zeros((0, 3)), [np.zeros((0, 3))] * len(ibs)))
    old_idx = src.point_indices[k]
    extra = [np.zeros(0, dtype=np.int64)]
    normals = [src.normal_offsets[k] if src.normal_offsets else None] + [ib.normal_offsets for ib in ibs]
    for nrm in normals:
        if nrm is not None:
            rows = np.arange(region.n) if old_idx is None else np.asarray(old_idx, dtype=np.int64)
            extra.append(rows[np.abs(nrm).reshape(-1, 3).max(axis=1) > 0])
    if region.copies is not None:          # a welded part: each copy written as its twin (same generic)
        c_full, c_local = region.copies
        r_idx = np.concatenate([c_full, r_idx])
        r_new = np.concatenate([deltas.values[k][c_local], r_off])
        r_off = np.concatenate([rig.deltas[k][c_local], r_off])
        r_ibs = [np.concatenate([ib.offsets[c_local], r]) for ib, r in zip(ibs, r_ibs, strict=True)]
    else:
        r_new = r_off
    points = np.concatenate([region.vertices, r_idx])
    values_new = np.concatenate([deltas.values[k], r_new])
    values_old = np.concatenate([rig.deltas[k], r_off])
    ib_old = [np.concatenate([ib.offsets, r]) for ib, r in zip(ibs, r_ibs, strict=True)]
    more = np.concatenate(extra)
    if more.size:                                                      # normal offsets only: no motion
        seen = np.zeros(region.n, dtype=bool)
        seen[points] = True
        more = np.unique(more[~seen[more]])
    if r_idx.size == 0 and more.size == 0:                             # the region's own points, ascending
        return points, values_new, values_old, ib_old
    points = np.concatenate([points, more])
    order = np.argsort(points, kind="stable")
    pad = np.zeros((more.size, 3))

    def arrange(a):
        return np.concatenate([a, pad])[order]

    return points[order], arrange(values_new), arrange(values_old), [arrange(b) for b in ib_old]


def _original_shape_prims(stage, rig: FaceRig) -> list[str]:
    """The BlendShape prims to author over. Over an earlier usdface output the binding points at
    ``usdfaceShapes/<shape>`` (defined in a variant); author on the original prim they reference instead, so
    that both variants keep working (personalized: the new over; generic: the input alone)."""
    from pxr import Pcp, Usd

    out = []
    for path in rig.source.shape_prims:
        original = path
        prim = stage.GetPrimAtPath(path)
        if f"/{SHAPES_SCOPE}/" in path and prim:
            for arc in Usd.PrimCompositionQuery(prim).GetCompositionArcs():
                node = arc.GetTargetNode()
                if arc.GetArcType() == Pcp.ArcTypeReference and node.layerStack == prim.GetPrimIndex(
                        ).rootNode.layerStack:
                    original = str(node.path)
                    break
        out.append(original)
    return out


def _inbetween_types(stage, rig: FaceRig, shape_prims: list[str]) -> dict:
    """{(shape prim, inbetween name): attribute type} as composed from the input (read before authoring)."""
    from pxr import Sdf

    types = {}
    for k, name in enumerate(rig.names):
        prim = stage.GetPrimAtPath(shape_prims[k])
        for ib in rig.inbetweens.get(name, []):
            attr = prim.GetAttribute(f"inbetweens:{ib.name}") if prim else None
            types[(shape_prims[k], ib.name)] = (
                attr.GetTypeName() if attr else Sdf.ValueTypeNames.Point3fArray)
    return types


def _author_shape(layer, rig: FaceRig, k: int, support: tuple, ib_types: dict, shape_path: str):
    """Author the over of shape k of ``rig``: offsets, pointIndices, inbetweens, normal offsets.
    ``support`` = :func:`_shape_support` (the points considered and the new / old offsets there)."""
    from pxr import Sdf, Vt

    src = rig.source
    n = src.region.n if src.region is not None else rig.n_vertices
    points, new_primary, old_primary, ib_old = support
    new_primary_local = local_offsets(rig, new_primary)
    m = n if points is None else points.size
    old_idx = src.point_indices[k]
    if points is None:
        where_old = slice(None) if old_idx is None else old_idx     # positions of authored points
    else:
        rows = np.arange(n) if old_idx is None else np.asarray(old_idx, dtype=np.int64)
        pos = np.minimum(np.searchsorted(points, rows), max(m - 1, 0))
        found = points[pos] == rows if m else np.zeros(rows.size, dtype=bool)
        where_old = pos[found]

    def on_points(values):      # per authored point -> per considered point (those outside are zero)
        out = np.zeros((m, 3), dtype=np.float32)
        vals = np.asarray(values, dtype=np.float32).reshape(-1, 3)
        out[where_old] = vals if points is None else vals[found]
        return out

    ibs = rig.inbetweens.get(rig.names[k], [])
    # each inbetween moves by its weight's share of the primary's change (the old offsets read for it only)
    diff = new_primary_local - local_offsets(rig, old_primary) if ibs else None
    ib_new = [local_offsets(rig, old) + ib.weight * diff for ib, old in zip(ibs, ib_old, strict=True)]
    normals_dense = None
    ib_normals_dense = []
    keep = []
    if src.normal_offsets and src.normal_offsets[k] is not None:
        normals_dense = on_points(src.normal_offsets[k])
        keep.append(normals_dense.astype(np.float64))
    for ib in ibs:
        dense = None
        if ib.normal_offsets is not None:
            dense = on_points(ib.normal_offsets)
            keep.append(dense.astype(np.float64))
        ib_normals_dense.append(dense)
    moved = effective_point_set(new_primary_local, ib_new + keep)
    if moved.all() and m == n:
        new_idx = None if old_idx is None else np.arange(n)  # dense stays in the form it was authored in
        sel = slice(None)
    else:
        sel = np.flatnonzero(moved)
        new_idx = sel if points is None else points[sel]
    same_points = (old_idx is None and new_idx is None) or (
        old_idx is not None and new_idx is not None and np.array_equal(old_idx, new_idx))

    spec = Sdf.CreatePrimInLayer(layer, shape_path)

    def attr(name, type_name, value):
        a = spec.attributes.get(name)
        if a is None:
            a = Sdf.AttributeSpec(spec, name, type_name, Sdf.VariabilityUniform)
        a.default = value

    attr("offsets", Sdf.ValueTypeNames.Vector3fArray,
         Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(new_primary_local[sel], dtype=np.float32)))
    if not same_points:
        if new_idx is None:
            attr("pointIndices", Sdf.ValueTypeNames.IntArray, Sdf.ValueBlock())
        else:
            attr("pointIndices", Sdf.ValueTypeNames.IntArray, Vt.IntArray.FromNumpy(new_idx.astype(np.int32)))
        if normals_dense is not None:
            attr("normalOffsets", Sdf.ValueTypeNames.Vector3fArray,
                 Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(normals_dense[sel])))
    for ib, offsets, ib_normals, old in zip(ibs, ib_new, ib_normals_dense, ib_old, strict=True):
        name = f"inbetweens:{ib.name}"
        type_name = ib_types.get((shape_path, ib.name), Sdf.ValueTypeNames.Point3fArray)
        if not (np.allclose(offsets, local_offsets(rig, old), rtol=0, atol=0) and same_points):
            attr(name, type_name,
                 Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(offsets[sel], dtype=np.float32)))
        if ib_normals is not None and not same_points:
            attr(f"{name}:normalOffsets", Sdf.ValueTypeNames.Vector3fArray,
                 Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(ib_normals[sel])))


def _author_variants(layer, rigs: list[FaceRig], input_asset: str):
    """usdfacePersonalization = {personalized, generic} on each SkelRoot, retargeting the skel bindings."""
    from pxr import Sdf

    by_root: dict[str, list[FaceRig]] = {}
    for rig in rigs:
        root = rig.source.skel_root or rig.source.prim.rsplit("/", 1)[0]
        by_root.setdefault(root, []).append(rig)
    for root, root_rigs in by_root.items():
        root_spec = Sdf.CreatePrimInLayer(layer, root)
        root_spec.variantSetNameList.Prepend(PERSONALIZATION_VARIANT_SET)
        vset = Sdf.VariantSetSpec(root_spec, PERSONALIZATION_VARIANT_SET)
        variants = {name: Sdf.VariantSpec(vset, name) for name in ("personalized", "generic")}
        root_spec.variantSelections[PERSONALIZATION_VARIANT_SET] = "personalized"
        for rig in root_rigs:
            src = rig.source
            rel_mesh = Sdf.Path(src.prim).MakeRelativePath(Sdf.Path(root))
            names = []
            for p in src.shape_prims:  # unique prim names (targets may live under different parents)
                name, i = Sdf.Path(p).name, 1
                while name in names:
                    name, i = f"{Sdf.Path(p).name}_{i}", i + 1
                names.append(name)
            for variant_name, variant in variants.items():
                parent = variant.primSpec
                for element in [*rel_mesh.pathString.split("/"), SHAPES_SCOPE]:
                    if element in ("", "."):
                        continue
                    child = parent.nameChildren.get(element)
                    if child is None:
                        if element == SHAPES_SCOPE:
                            child = Sdf.PrimSpec(parent, element, Sdf.SpecifierDef, "Scope")
                        else:
                            child = Sdf.PrimSpec(parent, element, Sdf.SpecifierOver)
                    parent = child
                for name, shape_path in zip(names, src.shape_prims, strict=True):
                    shape = Sdf.PrimSpec(parent, name, Sdf.SpecifierDef, "BlendShape")
                    if variant_name == "personalized":
                        shape.referenceList.Prepend(Sdf.Reference(primPath=shape_path))
                    else:
                        shape.referenceList.Prepend(Sdf.Reference(assetPath=input_asset, primPath=shape_path))
            mesh_spec = Sdf.CreatePrimInLayer(layer, src.prim)
            rel = mesh_spec.relationships.get("skel:blendShapeTargets")
            if rel is None:
                rel = Sdf.RelationshipSpec(mesh_spec, "skel:blendShapeTargets", custom=False,
                                           variability=Sdf.VariabilityUniform)
            rel.targetPathList.explicitItems = [Sdf.Path(f"{src.prim}/{SHAPES_SCOPE}/{n}") for n in names]


def _author_primvars(stage, avatar: Avatar, primvars: dict):
    """Extra primvars on meshes, as local overs: {mesh: {name: (values, interpolation)}}."""
    from pxr import Sdf, UsdGeom, Vt

    for key, entries in primvars.items():
        rig = avatar_mesh(avatar, key, "for primvars")
        api = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath(rig.source.prim))
        for name, (values, interpolation) in entries.items():
            name = name.removeprefix("primvars:")
            arr = np.asarray(values)
            if not np.isfinite(arr.astype(np.float64)).all():
                raise GeometryError(f"primvar {name} contains NaN/inf", path=avatar.file,
                                    prim=rig.source.prim, fix="check the values passed as primvars")
            types = Sdf.ValueTypeNames
            if arr.ndim == 2 and arr.shape[1] == 3:
                type_name = types.Color3fArray if name in ("displayColor",) else types.Float3Array
                value = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(arr, dtype=np.float32))
            elif arr.dtype.kind in "iu":
                type_name, value = types.IntArray, Vt.IntArray.FromNumpy(arr.astype(np.int32).ravel())
            elif arr.dtype.kind == "b":
                type_name, value = types.BoolArray, Vt.BoolArray([bool(v) for v in arr.ravel()])
            else:
                type_name, value = types.FloatArray, Vt.FloatArray.FromNumpy(arr.astype(np.float32).ravel())
            api.CreatePrimvar(name, type_name, interpolation).Set(value)


def _relative_to_layer(path, out_path: Path) -> str:
    """``path`` relative to the directory of ``out_path`` (absolute when no relative path exists), through
    the same symlinks as the layer's sublayer path (:func:`_relative_asset_path`): an avatar read as
    ``lib/latest/hero.usda`` is recorded so, and a ``latest`` link moved to another version is an input that
    changed (its digest is checked where the link points now), not an unchanged ``v003``."""
    return _layer_path(path, Path(out_path).absolute().parent)        # as the sublayer's path


def recorded_inputs(layer_path, record: dict | None = None) -> dict[str, str] | None:
    """``{real path: sha256}`` of the inputs a usdface layer records (its provenance,
    :func:`usdface.io.usd_rig.usdface_output_provenance`, read here unless the caller has it as ``record``;
    paths relative to the layer), or None for a file that is not a usdface layer."""
    from .usd_rig import usdface_output_provenance

    record = usdface_output_provenance(layer_path) if record is None else record
    if record is None:
        return None
    folder = Path(layer_path).parent
    return {os.path.realpath(recorded_path(folder, p)): str(d)
            for p, d in zip(record.get("inputs") or [], record.get("inputDigests") or [], strict=False)}


def recorded_path(folder, recorded) -> Path:
    """A path a usdface layer in ``folder`` records (relative to it, or absolute), resolved as USD resolves
    the layer's relative asset paths and as :func:`_layer_path` wrote it: joined to the folder by name, a
    ``..`` taking off the name before it (after a symlinked folder, the link's parent, not its target's).
    The OS's reading of ``out/../avatars`` (``out -> /farm/out``: ``/farm/avatars``) looked for the inputs
    where they are not, so a batch whose output folder is a link took each layer it wrote for another
    avatar's (``StaleOutput``) and ``check`` left its digests unchecked (stop 51)."""
    p = Path(str(recorded))
    return Path(os.path.normpath(p if p.is_absolute() else Path(folder).absolute() / p))


def input_changed(real: str, recorded: str, digest: Callable = file_digest) -> bool:
    """Whether the input at ``real`` no longer has the sha256 ``recorded`` for it (False when none was
    recorded or the file is gone: its reader says so when it runs). ``digest``: how to hash it (a batch
    remembers its inputs' digests)."""
    if not recorded or not os.path.exists(real):
        return False
    try:
        return digest(real) != recorded
    except (InputFileError, OSError):
        return False


def stale_inputs(layer_path, given=(), record: dict | None = None) -> list[str]:
    """What makes a usdface layer's result stale for the files at hand: a recorded input changed since the
    layer was written (sha256 differs), and each of ``given`` (e.g. the capture a review scores) that is not
    among the layer's recorded inputs. Messages for a warning; [] when all agree or nothing is recorded.
    ``record``: the layer's provenance when the caller has read it (as :func:`missing_inputs`)."""
    recorded = recorded_inputs(layer_path, record)
    if recorded is None:
        return []
    out = [f"{Path(layer_path).name} was made from {real}, which changed after it was written (sha256 "
           "differs): re-run usdface personalize on the current inputs"
           for real, digest in recorded.items() if input_changed(real, digest)]
    for g in given:
        if g is not None and isinstance(g, str | Path) and os.path.realpath(g) not in recorded:
            out.append(f"{g} is not among the inputs {Path(layer_path).name} records (another capture or "
                       "person?): its figures describe that file, not this layer's capture")
    return out


def missing_inputs(layer_path, record: dict | None = None) -> list[str]:
    """The inputs a usdface layer records (its provenance's ``inputs`` and a fit rig's ``capture``, as
    recorded: relative to the layer or absolute) that are not there now, resolved as
    :func:`recorded_path` resolves them; [] when none is missing or the file is no usdface layer. ``record``:
    the layer's provenance when the caller has read it. ``inspect`` named a take moved away as if it were
    there (a TD's trial, stop 51); :func:`stale_inputs` passes over a missing file."""
    from .usd_rig import usdface_output_provenance

    record = usdface_output_provenance(layer_path) if record is None else record
    if not isinstance(record, dict):
        return []
    recorded = [*(record.get("inputs") or []), *([record["capture"]] if record.get("capture") else [])]
    folder = Path(layer_path).parent
    return [str(p) for p in dict.fromkeys(str(r) for r in recorded)
            if not os.path.exists(recorded_path(folder, p))]


#: Vertices per block of :func:`neutral_signature` (in index order).
NEUTRAL_BLOCK = 256


def neutral_signature(points: np.ndarray, block: int = NEUTRAL_BLOCK) -> np.ndarray:
    """The mean of each run of ``block`` consecutive vertices of a neutral, ``[ceil(n / block), 3]`` in the
    points' units (``points``: ``[n, 3]``; the last run may be shorter). Small enough to record in a layer
    (~100 blocks for a 25k-vertex head), and it tells a neutral re-sculpted after the layer was written
    (and where, by vertex range), where the file's digest tells only that the file changed."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    starts = np.arange(0, len(points), block)
    counts = np.diff(np.append(starts, len(points)))
    return np.add.reduceat(points, starts, axis=0) / counts[:, None] if len(points) else np.zeros((0, 3))


def neutral_digest(points: np.ndarray) -> str:
    """sha256 of a neutral's points as USD stores them (``point3f``: float32, ``[n, 3]`` in index order). A
    layer records it beside :func:`neutral_signature`: equal, the neutral is the one personalized to the
    bit; different while no block mean moved (:func:`neutral_moved`), some vertices moved by less than the
    block means resolve (one vertex moved by ``d`` moves its block's mean by ``d / 256``)."""
    return hashlib.sha256(np.ascontiguousarray(np.asarray(points, dtype=np.float32).reshape(-1, 3))
                          .tobytes()).hexdigest()


def storage_tolerance(points: np.ndarray) -> float:
    """What float32 storage can move a neutral's block mean by, in the points' units: 16 float32 steps at
    the mesh's largest coordinate (a DCC re-export of the same points), :func:`neutral_moved`'s threshold."""
    return 16 * np.finfo(np.float32).eps * max(float(np.abs(np.asarray(points)).max(initial=0.0)), 1e-30)


def neutral_moved(before, points: np.ndarray, block: int = NEUTRAL_BLOCK, *,
                  now: np.ndarray | None = None) -> tuple[int, float] | None:
    """``(block index, distance)`` of the block of the neutral ``points`` (``[n, 3]``) that moved the most
    from the signature ``before`` (:func:`neutral_signature`, flat or ``[b, 3]``), in the points' units;
    None when no block moved more than float32 storage can (16 float32 steps at the mesh's largest
    coordinate: a DCC re-export of the same points), or the signature does not fit the points. ``now``: the
    points' own signature when the caller has it."""
    before = np.asarray(before, dtype=np.float64).reshape(-1, 3)
    now = neutral_signature(points, block) if now is None else np.asarray(now, dtype=np.float64)
    now = now.reshape(-1, 3)
    if before.shape != now.shape or not len(now):
        return None
    moved = np.linalg.norm(now - before, axis=1)
    tolerance = storage_tolerance(points)
    worst = int(np.argmax(moved))
    return (worst, float(moved[worst])) if moved[worst] > tolerance else None


def mesh_topology(prim) -> dict | None:
    """``{"points": n, "topology": sha256, "neutral": [...], "neutralDigest": sha256}`` of a
    ``UsdGeom.Mesh`` prim as composed (its point count, the digest of its ``faceVertexCounts`` and
    ``faceVertexIndices``, its :func:`neutral_signature` flattened and its points' :func:`neutral_digest`),
    None for a prim that is not a mesh with points. A layer records it for every mesh it personalizes
    (``customLayerData["usdface"]["meshes"]``), so ``usdface check`` tells an avatar whose mesh was
    re-modelled after the layer was written: the layer's ``pointIndices`` and offsets address the old
    vertices (an edge loop added shifts every index after it, and nothing else in the composed stage shows
    it); or whose neutral was re-sculpted (the offsets were fitted and checked on the old one). Layers
    written before stop 50 record no ``neutralDigest``, before stop 49 no ``neutral``."""
    found = _mesh_record(prim)
    return None if found is None else found[0]


def _mesh_record(prim) -> tuple[dict, np.ndarray, np.ndarray] | None:
    """``(record, points[n,3], signature[b,3])``: :func:`mesh_topology`'s record of a mesh prim with the
    points (float64, the stage's units) and their :func:`neutral_signature` it was made from, read once
    (:func:`avatar_mismatches` compares both); None as :func:`mesh_topology`."""
    from pxr import UsdGeom

    if prim is None or not prim.IsValid() or not prim.IsA(UsdGeom.Mesh):
        return None
    mesh = UsdGeom.Mesh(prim)
    stored = mesh.GetPointsAttr().Get()
    if stored is None:
        return None
    stored = np.asarray(stored)
    h = hashlib.sha256()
    for attr in (mesh.GetFaceVertexCountsAttr(), mesh.GetFaceVertexIndicesAttr()):
        h.update(np.asarray(attr.Get() if attr.Get() is not None else [], dtype=np.int64).tobytes())
        h.update(b"|")
    points = np.asarray(stored, dtype=np.float64).reshape(-1, 3)
    signature = neutral_signature(points)
    return ({"points": len(points), "topology": h.hexdigest(), "neutral": signature.ravel().tolist(),
             "neutralDigest": neutral_digest(stored)}, points, signature)


def prim_specs(layer) -> list:
    """Every prim spec of the ``Sdf.Layer`` outside variants, parents first."""
    out: list = []

    def walk(spec):
        for child in spec.nameChildren:
            out.append(child)
            walk(child)

    walk(layer.pseudoRoot)
    return out


def _orphan_overs(layer, avatar_stage, stage) -> list[str]:
    """The top-most prims ``layer`` overrides (``over``, outside its variants) that neither the avatar alone
    nor the layer itself defines: prims renamed, moved or deleted in the avatar after the layer was written
    (their overrides now apply to nothing)."""
    from pxr import Sdf

    out: list[str] = []

    def walk(spec):
        for child in spec.nameChildren:
            if child.specifier == Sdf.SpecifierOver:
                there = avatar_stage.GetPrimAtPath(child.path)
                here = stage.GetPrimAtPath(child.path)
                if not (there and there.IsDefined()) and not (here and here.IsDefined()):
                    out.append(str(child.path))
                    continue                                  # its children are gone with it
            walk(child)

    walk(layer.pseudoRoot)
    return out


def avatar_mismatches(stage, neutral: bool = True, nudged: list | None = None) -> list[tuple[str, str, str]]:
    """``[(prim, message, fix)]``: how a usdface personalize layer (the root layer of ``stage``) no longer
    fits the avatar it sublayers, opened alone: a prim it overrides gone (a mesh or the SkelRoot renamed or
    moved, a shape deleted), a personalized mesh whose blend shapes are not those its
    ``skel:blendShapeTargets`` list (a shape added or removed), a mesh whose point count or faces differ
    from those recorded when the layer was written (re-modelled: :func:`mesh_topology`), the avatar's
    ``metersPerUnit`` / ``upAxis`` not those the layer repeats (re-exported in other units or axis), and
    (``neutral``) a personalized mesh's neutral moved (re-sculpted: :func:`neutral_moved`; layers written
    since stop 49 record it). USD composes all of these without a word. [] for a layer that fits, and for
    any other file.

    Why a moved neutral is a mismatch and a re-sculpted shape is not: the layer's offsets replace the
    personalized shapes' own, so over a re-sculpted shape the composed rig is still the one personalize
    checked (the edit is hidden, which ``Provenance`` warns about); over a moved neutral it is a rig nobody
    checked - offsets fitted on the old neutral (its correspondence with the capture, its lip and eyelid
    clearance) added to new positions.

    ``nudged``: a list that receives, in the same form, each personalized mesh whose neutral points differ
    from those the layer recorded (its points digest, layers written since stop 50) while no block mean moved
    beyond float32 storage: a vertex moved by less than the block means resolve, or a re-export's float
    noise, which the layer cannot tell apart. That is a warning (``check``; ``export``, ``review`` and
    ``render --compare`` print it), not a mismatch: refusing every re-export whose float bits changed would
    stop a pipeline for nothing."""
    from pxr import Sdf, Usd, UsdGeom, UsdSkel

    root = stage.GetRootLayer()
    record = (root.customLayerData or {}).get("usdface")
    if not (isinstance(record, dict) and "inputs" in record and root.subLayerPaths):
        return []
    asset = root.subLayerPaths[0]
    avatar_layer = Sdf.Layer.FindOrOpen(Sdf.ComputeAssetPathRelativeToLayer(root, asset))
    if avatar_layer is None:
        return []                                         # USD's composition error says so
    from .usd_open import quiet_stderr

    with quiet_stderr():       # a layer over a layer whose own avatar is gone: its reader names that
        avatar_stage = Usd.Stage.Open(avatar_layer, Usd.Stage.LoadAll)
    if avatar_stage is None or avatar_stage.GetCompositionErrors():
        return []              # (not "overrides prims the avatar no longer has": they are in the lost file)
    name = Path(root.realPath or root.identifier).name
    from .usd_rig import _from_cwd

    # the avatar by a path that opens from where the command runs (the sublayer path is the layer folder's:
    # '../../lib/avatar.usda' from pub/v001/, no file from the project folder the re-run is typed in)
    revised = _from_cwd(Path(avatar_layer.realPath)) if avatar_layer.realPath else asset
    fix = (f"re-run usdface personalize on the revised avatar ({revised}) with the capture, --force to "
           f"replace {name} (or publish a new version); a layer cannot be carried over to a changed avatar")
    out = []
    for key in ("metersPerUnit", "upAxis"):
        if root.pseudoRoot.HasInfo(key) and avatar_layer.pseudoRoot.HasInfo(key):
            mine, theirs = root.pseudoRoot.GetInfo(key), avatar_layer.pseudoRoot.GetInfo(key)
            if mine != theirs:
                out.append(("/", f"{name} was written over {asset} with {key} {mine}, but the avatar now "
                            f"authors {key} {theirs} (re-exported in other units or axis): the layer's "
                            "offsets are in the old ones, and its stage metadata overrides the avatar's",
                            fix))
    recorded = record.get("meshes") if isinstance(record.get("meshes"), dict) else {}
    for spec in prim_specs(root):
        if "skel:blendShapeTargets" not in spec.relationships:
            continue
        path = str(spec.path)
        mesh = avatar_stage.GetPrimAtPath(path)
        if not (mesh and mesh.IsDefined()):
            continue                                      # told above as gone
        now = [t.name for t in UsdSkel.BindingAPI(mesh).GetBlendShapeTargetsRel().GetTargets()]
        written = [t.name for t in spec.relationships["skel:blendShapeTargets"]
                   .targetPathList.GetAddedOrExplicitItems()]
        if now != written:
            added = [n for n in now if n not in written]
            removed = [n for n in written if n not in now]
            change = "; ".join(filter(None, (added and f"added {', '.join(added)}",
                                             removed and f"removed {', '.join(removed)}")))
            out.append((path, f"{asset}'s {path} now has {len(now)} blend shapes ({change or 'reordered'}), "
                        f"but {name}'s skel:blendShapeTargets list the {len(written)} it was written for: "
                        "the mesh's channels and targets no longer pair up", fix))
        before, found = recorded.get(path), _mesh_record(mesh)          # the points read once
        after, points, signature = found if found is not None else (None, None, None)
        if isinstance(before, dict) and after is not None and (
                before.get("points") != after["points"] or before.get("topology") != after["topology"]):
            points = (f"{before.get('points')} -> {after['points']} points"
                      if before.get("points") != after["points"]
                      else f"{after['points']} points, faces changed")
            out.append((path, f"{asset}'s {path} was re-modelled after {name} was written ({points}): the "
                        "layer's pointIndices and offsets address the old vertices", fix))
        elif (neutral and isinstance(before, dict) and before.get("neutral") is not None and after is not None
              and before.get("neutralDigest") != after["neutralDigest"]):   # equal: the points, to the bit
            moved = neutral_moved(before["neutral"], points, now=signature)
            if moved is not None:
                block, distance = moved
                mm = distance * UsdGeom.GetStageMetersPerUnit(avatar_stage) * 1000.0
                first, last = block * NEUTRAL_BLOCK, min((block + 1) * NEUTRAL_BLOCK, len(points)) - 1
                out.append((path, f"{asset}'s {path} neutral was re-sculpted after {name} was written (the "
                            f"vertices {first}-{last} moved {mm:.2f} mm on average): the layer's offsets "
                            "were fitted and checked (lip and eyelid clearance) on the old neutral",
                            fix + "; or pass --allow-moved-neutral to deliver it over the new neutral as "
                                  "it is"))
            elif before.get("neutralDigest") and nudged is not None:
                # no block mean moved beyond float32 storage, but the points are not those personalized: a few
                # vertices moved by up to NEUTRAL_BLOCK times that (a lip vertex nudged), or a re-export's
                # float noise; the layer cannot tell which or where (its record is the block means)
                mm = UsdGeom.GetStageMetersPerUnit(avatar_stage) * 1000.0
                limit = storage_tolerance(points) * NEUTRAL_BLOCK * mm
                nudged.append((path, f"{asset}'s {path} neutral points changed after {name} was written, "
                            f"each {NEUTRAL_BLOCK}-vertex block's mean by less than float32 storage resolves "
                            f"(a vertex moved by less than {limit:.2f} mm, or a re-export's float noise): "
                            "the layer's offsets were fitted and checked on the old neutral",
                            fix + " if a vertex was moved; nothing to do if the avatar was only re-exported"))
    # after the meshes' own findings: a shape removed is told as such first, its override's loss second
    for path in _orphan_overs(root, avatar_stage, stage):
        out.append((path, f"{name} overrides {path}, which {asset} no longer has (renamed, moved or deleted "
                    "in the avatar after the layer was written): its personalization applies to nothing",
                    fix))
    return out


def refuse_avatar_mismatch(layer_path, what: str, allow_moved_neutral: bool = False) -> None:
    """Raise :class:`usdface.errors.RigError` (naming the layer, the prim and the fix) when the usdface layer
    at ``layer_path`` no longer fits its revised avatar (:func:`avatar_mismatches`): ``what`` (an export, a
    review page, a comparison) would deliver overrides that land on nothing or on the wrong vertices, labelled
    personalized. A layer whose inputs merely changed (a re-sculpted shape) is only warned about, and so is
    one whose avatar's neutral moved when ``allow_moved_neutral`` (``--allow-moved-neutral``: the TD
    accepts the offsets over the new neutral), or whose neutral's points changed by less than the layer's
    record resolves (``avatar_mismatches``' ``nudged``: a vertex nudged, or a re-export's float noise)."""
    from pxr import Usd

    if Path(layer_path).suffix.lower() not in (".usda", ".usdc", ".usd") or not Path(layer_path).is_file():
        return                                   # not a layer (a take's CSV, a folder): its reader says so
    from .usd_open import quiet_stderr

    try:
        with quiet_stderr():    # a missing sublayer: the reader names it in one line later
            stage = Usd.Stage.Open(str(layer_path))
        nudged: list = []
        found = (avatar_mismatches(stage, neutral=not allow_moved_neutral, nudged=nudged)
                 if stage is not None else [])
    except Exception:  # noqa: BLE001  (a file USD cannot open: the reader after this names it)
        return
    for _, message, fix in ([] if found else nudged):     # below what the layer resolves: said, not refused
        warn(f"{message} (fix: {fix})")
    if found:
        prim, message, fix = found[0]
        more = (f" (and {len(found) - 1} more: usdface check {shlex.quote(str(layer_path))})"
                if len(found) > 1 else "")
        raise RigError(f"{message}{more}; refusing to make {what} of it", path=layer_path,
                       prim=None if prim == "/" else prim, fix=fix)


def _reproducible() -> bool:
    """Whether ``SOURCE_DATE_EPOCH`` is set (the reproducible-builds convention): then a layer's
    ``createdAt`` is that time and it records no timings, so the same inputs give the same bytes."""
    return bool(os.environ.get("SOURCE_DATE_EPOCH", "").strip())


def source_date_epoch() -> _dt.datetime | None:
    """``SOURCE_DATE_EPOCH`` (whole seconds since 1970) as a UTC time, None when unset; a value that is not
    a whole number is refused (:class:`usdface.errors.UsdFaceError`). The command line checks it before
    any work: numpy's f2py (which scipy imports) reads it with ``int()`` at import and died with a bare
    ``ValueError`` traceback."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH", "").strip()
    if not epoch:
        return None
    try:
        return _dt.datetime.fromtimestamp(int(epoch), _dt.UTC)
    except (ValueError, OverflowError, OSError):
        from ..errors import UsdFaceError

        raise UsdFaceError(f"SOURCE_DATE_EPOCH={epoch!r} is not a time",
                           fix="set it to whole seconds since 1970-01-01 UTC (e.g. $(git log -1 "
                               "--format=%ct)), or unset it") from None


def _created_at() -> str:
    """The layer's ``createdAt`` (UTC, ISO 8601): now, or ``SOURCE_DATE_EPOCH`` (seconds since 1970) when
    set; a value that is not a whole number is refused (:class:`usdface.errors.UsdFaceError`)."""
    when = source_date_epoch() or _dt.datetime.now(_dt.UTC)
    return when.strftime("%Y-%m-%dT%H:%M:%SZ")


def _provenance(avatar: Avatar, provenance: dict, out_path: Path, ahead: DigestsAhead | None = None) -> dict:
    from .atomic import usd_dependencies

    prov = dict(provenance or {})
    inputs = [str(avatar.file)] + [str(p) for p in prov.pop("inputs", []) if str(p) != str(avatar.file)]
    # the layers the avatar composes (a shot's referenced avatar, its sublayers): an edit of one of them
    # changes what this layer was computed from, so ``check`` verifies their digests too
    root = Path(avatar.file).resolve()
    inputs += [str(d) for d in usd_dependencies(Path(avatar.file))
               if d.resolve() != root and str(d) not in inputs]
    digests = {}
    for p in inputs:
        try:
            digests[p] = (ahead.get(p) if ahead is not None else None) or file_digest(p)
        except InputFileError:
            digests[p] = ""
    if (avatar.metadata or {}).get("name_map") and "nameMap" not in prov:
        prov["nameMap"] = dict(avatar.metadata["name_map"])   # read back by every reader of the layer
    # what wrote the layer: the CLI passes its command line; a script that gives none is named as the API
    prov["command"] = prov.get("command") or "usdface.io.layers.write_avatar_layer (Python API)"
    if str(prov["command"]).startswith("usdface ") and "workingDirectory" not in prov and not _reproducible():
        # the command's relative paths are relative to where it ran: without it the recorded line could
        # not be run again (the inputs are recorded relative to the layer, the command as typed); not
        # with SOURCE_DATE_EPOCH, whose layers are the same bytes wherever the same command ran
        prov["workingDirectory"] = os.getcwd()
    prov.setdefault("parameters", {})
    prov.setdefault("timings", {})
    prov["version"] = __version__
    # recorded relative to the layer (like its sublayer path), so the record stays checkable from anywhere
    prov["inputs"] = [_relative_to_layer(p, out_path) for p in inputs]
    if prov.get("take"):           # the take the inspection animation plays (personalize --take)
        prov["take"] = _relative_to_layer(prov["take"], out_path)
    prov["inputDigests"] = [digests[p] for p in inputs]
    prov["createdAt"] = _created_at()
    prov["output"] = out_path.name
    return prov


def _apply_provenance_schema(stage, roots, prov: dict):
    from .. import schemas

    for root in roots:
        prim = stage.OverridePrim(root)
        schemas.apply_api(prim, schemas.PROVENANCE_API)
        values = {
            "version": prov["version"], "command": str(prov.get("command", "")),
            "method": str(prov.get("method", "")),
            "parameters": json.dumps(prov.get("parameters", {}), sort_keys=True, default=str),
            "inputs": prov["inputs"], "inputDigests": prov["inputDigests"], "createdAt": prov["createdAt"],
        }
        for key in ("registrationScale", "registrationResidual", "elapsedSeconds"):
            if key in prov:
                values[key] = float(prov[key])
        for key, value in values.items():
            schemas.schema_attribute(prim, f"usdface:provenance:{key}", schemas.PROVENANCE_API).Set(value)


def _check_layer_arguments(avatar, offsets, provenance, primvars) -> None:
    """:func:`write_avatar_layer`'s arguments of the wrong kind refused as :class:`OptionError` naming the
    argument and the fix, before any work (docs/usd-io.md's script): the avatar's path, ``None`` for the
    offsets or a string as the provenance died with Python's ``AttributeError`` (``'str' object has no
    attribute 'file'``; a user trial)."""
    from collections.abc import Mapping

    from ..errors import expect_kind

    for name, value, kinds, none_ok, expected, fix in (
            ("avatar", avatar, (Avatar,), False, "an Avatar", "pass usdface.io.usd_rig.read_avatar(PATH)"),
            ("offsets", offsets, (Mapping,), False, "a {mesh prim path: deltas[K,n,3]} dict",
             "pass {} for none, or {rig.source.prim: deltas} per mesh"),
            ("provenance", provenance, (Mapping,), True, "a dict or None",
             'pass e.g. {"command": "my script", "method": "menzel"}'),
            ("primvars", primvars, (Mapping,), True, "a {mesh: {name: (values, interpolation)}} dict or None",
             "pass None, or a dict per mesh")):
        expect_kind(value, kinds, f"write_avatar_layer's {name}", expected, fix, none_ok=none_ok)


def write_avatar_layer(avatar: Avatar, out_path, offsets: dict, *, provenance: dict | None = None,
                       force: bool = False, variants: bool = True, primvars: dict | None = None,
                       edit: Callable | None = None, digests: DigestsAhead | None = None) -> Path:
    """Write a new USD layer over ``avatar.file`` carrying personalized blend-shape offsets.

    Parameters
    ----------
    avatar : the Avatar read by :func:`usdface.io.usd_rig.read_avatar` (``MeshSource`` says where to write).
    out_path : .usda / .usdc / .usd file to create (format follows the extension).
    offsets : {mesh prim path (or mesh name) -> deltas[K_mesh, n, 3]} in metres, internal frame (Y up), in
        ``rig.names`` order; meshes not listed are left untouched.
    provenance : {command, parameters (dict), method, timings (dict name -> s), inputs (paths besides the
        avatar, e.g. the capture), registrationScale, registrationResidual, elapsedSeconds, ...}; stored in
        ``customLayerData["usdface"]`` (plus version, input sha256 digests, createdAt) and in the
        ``UsdFaceProvenanceAPI`` schema on each SkelRoot.
    force : replace an existing output (atomically).
    variants : add the ``usdfacePersonalization`` {personalized, generic} variant set (see module doc).
    primvars : {mesh -> {name -> (values, interpolation)}} extra primvars authored as local overs on the
        meshes (e.g. ``displayColor`` heat maps: they change the look in every client, see docs/usd-io.md).
    edit : callback ``edit(stage)`` run on the composed stage (edit target = the new layer) before saving, to
        author extra prims (landmark Points, SkelAnimation...).
    digests : the inputs' digests computed ahead (:class:`DigestsAhead`), for those it holds.

    Returns the output path. Nothing is written if any check fails.
    """
    from pxr import Sdf, Usd

    _check_layer_arguments(avatar, offsets, provenance, primvars)
    start = time.perf_counter()
    in_path = Path(avatar.file).absolute()
    if not in_path.is_file():
        raise InputFileError("the avatar's file is gone", path=in_path,
                             fix="keep the input avatar in place while writing the layer")
    out_path = check_output_path(out_path, force, inputs=[in_path]).absolute()
    resolved = _resolve_offsets(avatar, offsets)
    from .usd_rig import refuse_unwritable_shapes

    refuse_unwritable_shapes(avatar, [rig.key for rig, _ in resolved], "the layer")
    input_asset = _relative_asset_path(in_path, out_path.parent)
    input_layer = Sdf.Layer.FindOrOpen(str(in_path))
    if input_layer is None:
        raise InputFileError("USD cannot open the avatar", path=in_path, fix="check the avatar file")

    from .atomic import make_parents, remove_made

    made = make_parents(out_path)
    work = None
    done = False
    try:
        work = _temp_path(out_path)
        layer = Sdf.Layer.CreateNew(str(work))
        for key in STAGE_METADATA_KEYS:
            if input_layer.pseudoRoot.HasInfo(key):
                layer.pseudoRoot.SetInfo(key, input_layer.pseudoRoot.GetInfo(key))
        what = ("a landmark layout" if (provenance or {}).get("method") == "landmarks" and not offsets
                else "personalized blend shapes")
        layer.documentation = f"usdface {__version__}: {what} over {input_asset}"
        layer.subLayerPaths.append(input_asset)
        prov = _provenance(avatar, provenance or {}, out_path, digests)
        stage = Usd.Stage.Open(layer, Usd.Stage.LoadAll)
        stage.SetEditTarget(stage.GetRootLayer())
        rigs = [rig for rig, _ in resolved]
        ib_types, shape_prims = {}, {}
        for rig in rigs:
            shape_prims[rig.source.prim] = _original_shape_prims(stage, rig)
            ib_types.update(_inbetween_types(stage, rig, shape_prims[rig.source.prim]))
        # a layer over an earlier usdface output: its bindings already point into usdfaceShapes/
        redirected = any(f"/{SHAPES_SCOPE}/" in p for rig in rigs for p in rig.source.shape_prims)
        with Sdf.ChangeBlock():
            for rig, deltas in resolved:
                for k in range(rig.n_shapes):
                    _author_shape(layer, rig, k, _shape_support(rig, k, deltas), ib_types,
                                  shape_prims[rig.source.prim][k])
            if variants and rigs and not redirected:
                _author_variants(layer, rigs, input_asset)
        roots = sorted({r.source.skel_root for r in rigs if r.source.skel_root}) or sorted(
            {m.source.skel_root for m in avatar.meshes if m.source and m.source.skel_root})
        if primvars:
            _author_primvars(stage, avatar, primvars)
        if edit is not None:
            edit(stage)
        prov["timings"] = {**{str(k): float(v) for k, v in dict(prov["timings"]).items()},
                           "write_layer": time.perf_counter() - start}
        if _reproducible():          # the same inputs give the same bytes: no clock readings in the layer
            prov["timings"] = {}
            prov.pop("elapsedSeconds", None)
        # each personalized mesh's point count and topology as the avatar had them (check: re-modelled?)
        meshes = {r.source.prim: mesh_topology(stage.GetPrimAtPath(r.source.prim)) for r in rigs}
        prov["meshes"] = {k: v for k, v in meshes.items() if v is not None}
        _apply_provenance_schema(stage, roots, prov)
        layer.customLayerData = {"usdface": _usd_value(prov)}
        atomic_save(layer, out_path, force)
        done = True
    finally:
        if work is not None and work.exists():
            work.unlink()
        if not done:
            remove_made(made)     # a failed write leaves no folder it made behind either
    return out_path


def personalization_variant(stage, skel_root: str, name: str | None = None) -> str:
    """Get (and with ``name``, set in the session layer) the ``usdfacePersonalization`` selection."""
    prim = stage.GetPrimAtPath(skel_root)
    vset = prim.GetVariantSets().GetVariantSet(PERSONALIZATION_VARIANT_SET)
    if name is not None:
        with_session = stage.GetSessionLayer()
        from pxr import Usd

        with Usd.EditContext(stage, with_session):
            vset.SetVariantSelection(name)
    return vset.GetVariantSelection()
