"""What kind of input a path is, told by one rule: :func:`file_kind` (the avatar reader's refusals,
``inspect``'s dispatch, ``review``'s refusal of a personalize input, the take and capture checks, ``check``'s
Readable rule and ``render`` ask it).

The cheap facts come first and decide most files without composing a stage:

* the path itself: missing, a folder (by what it holds: ``train/``; ``frames/`` or a ``*.csv``;
  ``neutral.obj``), a ``.csv``, a file that is not USD;
* a USD file's root layer (``Sdf.Layer``, header and specs only): the record usdface wrote in its
  ``customLayerData`` (``usdface.format``: capture, take, fit, errorMaps; ``usdfaceFlatten``: a flattened
  export; ``usdface.inputs``: a layer written over an avatar), else whether the layer itself *defines* a take
  (a mesh with time-sampled ``points``, no capture ``usdface:frames:role``, no blend shapes outside the take's
  own ``Template`` rig);
* only when asked (``compose=True``), the composed stage (whether it has a SkelRoot, a BlendShape, a
  SkelAnimation prim), which decides a file the root layer left undecided, or judged a take by its specs alone
  (then only with a kind that is no avatar): usdface's capture/take layout (default prim with
  ``Frames`` and ``Template``), an error-map file written before the maps carried their format (default prim
  ``/ErrorMaps``, no SkelRoot), a take of weights only (a SkelAnimation as the default prim, or else a
  top-level prim, and no SkelRoot), a ``UsdFaceCaptureAPI`` prim, an avatar (a SkelRoot).

What decided the answer is kept in :attr:`FileKind.by`, so a caller can weigh the evidence (the avatar reader
does not refuse a mesh cache that only the layer-spec test calls a take).

Example::

    from usdface.io.file_kind import Kind, file_kind
    fk = file_kind("capture.usda")
    fk.kind is Kind.CAPTURE, fk.by              # (True, "format")
    file_kind("avatar.usdc", compose=True).kind  # Kind.AVATAR
"""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

__all__ = ["Kind", "FileKind", "file_kind", "is_weights_take", "top_animation", "USD_SUFFIXES", "NOT_AVATAR",
           "plain", "folder_files"]

#: The file name endings USD files are told by.
USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")


class Kind(StrEnum):
    """The kinds of input :func:`file_kind` tells apart (the value is a short name for messages and JSON)."""

    MISSING = "missing"                 #: nothing at the path (``os.path.exists`` is False)
    CAPTURE_FOLDER = "capture folder"   #: a folder with ``train/``, or ``neutral.obj`` and no take in it
    TAKE_FOLDER = "take folder"         #: a folder with ``frames/`` or a ``*.csv`` and no ``train/``
    FOLDER = "folder"                   #: any other folder
    LIVELINK_CSV = "Live Link CSV"      #: a ``.csv`` that is no folder (its reader judges the content)
    CAPTURE = "capture"                 #: a capture USD file ('capture import/select')
    TAKE = "take"                       #: a USD take (meshes, and their weights)
    WEIGHTS_TAKE = "animation"          #: a USD take of weights only (a SkelAnimation, 'anim import')
    FIT = "fit"                         #: a 'usdface fit' result (the person's shapes on the capture mesh)
    ERROR_MAPS = "errorMaps"            #: an error-map file ('evaluate --usd')
    FLATTENED = "flattened"             #: a flattened export of a usdface layer ('export --flatten')
    LAYER = "usdface layer"             #: a layer usdface wrote over an avatar (personalize, landmarks)
    AVATAR = "avatar"                   #: composed only: a SkelRoot in a file the root layer left open
    USD = "USD"                         #: a USD file none of the above (or not composed, or unreadable)
    OTHER = "other"                     #: a file that is neither USD nor CSV, or no regular file


#: The kinds of USD file that are no avatar although some carry a SkelRoot (a capture's template rig).
NOT_AVATAR = frozenset({Kind.CAPTURE, Kind.TAKE, Kind.WEIGHTS_TAKE, Kind.ERROR_MAPS})

#: ``customLayerData["usdface"]["format"]`` -> kind ("animation" is the weights-only take's name in messages).
_FORMATS = {"capture": Kind.CAPTURE, "take": Kind.TAKE, "animation": Kind.WEIGHTS_TAKE, "fit": Kind.FIT,
            "errorMaps": Kind.ERROR_MAPS}


@dataclass(frozen=True)
class FileKind:
    """What :func:`file_kind` found.

    Attributes
    ----------
    path : the path asked about.
    kind : the :class:`Kind`.
    by : what told it: ``"path"`` (missing, not a regular file, no USD suffix); ``"suffix"`` (a ``.csv``,
        or a USD file whose root layer cannot be opened); ``"train/"``, ``"frames/"``, ``"*.csv"``,
        ``"neutral.obj"`` (what a folder holds); ``"format"`` (``usdface.format`` in the root layer),
        ``"flatten"`` (``usdfaceFlatten``), ``"inputs"`` (``usdface.inputs``), ``"layer specs"`` (the root
        layer defines a take); ``"layout"`` (default prim with ``Frames`` and ``Template``), ``"legacy"``
        (default prim ``/ErrorMaps``, no SkelRoot), ``"stage"`` (weights only; a SkelRoot), ``"schema"`` (a
        ``UsdFaceCaptureAPI`` prim), from the composed stage; ``"nothing"`` (a readable USD file none of
        these describe).
    usdface : the root layer's ``customLayerData["usdface"]`` as plain Python values, {} without one.
    flattened : ``customLayerData["usdfaceFlatten"]`` (``source``, ``variant``) when it names a variant, else
        None.
    meshes : for a folder, whether it holds OBJ meshes (``frames/``, or any ``*.obj``: ``neutral.obj``
        counts); else False.
    skel_root, blend_shapes, skel_animation : whether the composed stage has a SkelRoot / a BlendShape / a
        SkelAnimation prim anywhere (instance proxies included); None when no stage was looked at.
    layer : the root ``Sdf.Layer`` opened to tell (None for folders, other files and unreadable ones): hold
        the FileKind while the file is read and USD parses it once (a stage opened later finds the layer in
        USD's registry).
    """

    path: Path
    kind: Kind
    by: str
    usdface: dict = field(default_factory=dict)
    flattened: dict | None = None
    meshes: bool = False
    skel_root: bool | None = None
    blend_shapes: bool | None = None
    skel_animation: bool | None = None
    layer: object = field(default=None, repr=False, compare=False)

    @property
    def format(self) -> str:
        """``usdface.format`` as recorded ("" without one)."""
        return str(self.usdface.get("format") or "")

    @property
    def provenance(self) -> dict | None:
        """The provenance of a file usdface wrote from recorded inputs (a ``personalize`` or ``landmarks``
        layer, a flattened export of one, a ``fit`` result): ``usdface`` when it records ``inputs`` and the
        file is none of :data:`NOT_AVATAR`, else None."""
        if self.kind in NOT_AVATAR or not self.usdface.get("inputs"):
            return None
        return self.usdface


def plain(value):
    """USD values (VtArrays, dictionaries, tokens) -> plain Python for JSON."""
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (str, bool, int, float)) or value is None:
        return value
    try:
        return [plain(v) for v in value]
    except TypeError:
        return str(value)


def file_kind(path, *, stage=None, compose: bool = False) -> FileKind:
    """What kind of input ``path`` is (see the module doc for the rules, in the order they are asked).

    Parameters
    ----------
    path : a file or folder (str or Path); need not exist.
    stage : the ``Usd.Stage`` of ``path`` already opened by the caller: its root layer is read instead of
        opening the file (``path`` only names it), and it is the stage ``compose`` asks.
    compose : ask the composed stage too: ``stage``, or else the stage of a USD file whose root layer opens,
        opened as the readers open it (one with composition errors is not asked: the reader that follows
        names the problem).

    Never raises for a missing, unreadable or malformed input: :attr:`Kind.MISSING`, :attr:`Kind.USD` or
    :attr:`Kind.OTHER` say so, and the reader that follows names the problem.
    """
    path = Path(path)
    if stage is not None:
        return _usd_kind(path, stage.GetRootLayer(), stage if compose else None, compose)
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):   # as os.path.exists: missing, a dangling link, a folder one may not enter
        return FileKind(path, Kind.MISSING, "path")
    if stat.S_ISDIR(mode):
        return _folder_kind(path)
    suffix = path.suffix.lower()
    if suffix == ".csv":
        return FileKind(path, Kind.LIVELINK_CSV, "suffix")
    if suffix not in USD_SUFFIXES or not stat.S_ISREG(mode):
        return FileKind(path, Kind.USD if suffix in USD_SUFFIXES else Kind.OTHER, "path")
    from pxr import Sdf

    try:
        layer = Sdf.Layer.FindOrOpen(str(path))
    except Exception:  # noqa: BLE001 - unreadable: the reader that follows names the problem
        layer = None
    if layer is None:
        return FileKind(path, Kind.USD, "suffix")
    return _usd_kind(path, layer, None, compose)


def folder_files(folder, pattern: str) -> list[Path]:
    """The files of ``folder`` matching ``pattern`` (``"*.obj"``), sorted, without hidden ones: a name
    starting with a dot is a system's, not the capture's (macOS writes ``._000.obj`` AppleDouble files beside
    every file copied to a non-Apple disk; ``Path.glob`` matches them: a capture folder copied from a Mac was
    refused, "the same shape has several template files: ._jawOpen.obj, jawOpen.obj")."""
    return sorted(p for p in Path(folder).glob(pattern) if not p.name.startswith("."))


def _folder_kind(path: Path) -> FileKind:
    frames = (path / "frames").is_dir()
    meshes = frames or bool(folder_files(path, "*.obj"))
    if (path / "train").is_dir():
        return FileKind(path, Kind.CAPTURE_FOLDER, "train/", meshes=meshes)
    if frames or folder_files(path, "*.csv"):
        return FileKind(path, Kind.TAKE_FOLDER, "frames/" if frames else "*.csv", meshes=meshes)
    if (path / "neutral.obj").is_file():
        return FileKind(path, Kind.CAPTURE_FOLDER, "neutral.obj", meshes=meshes)
    return FileKind(path, Kind.FOLDER, "path", meshes=meshes)


def _usd_kind(path: Path, layer, stage, compose: bool) -> FileKind:
    custom = dict(layer.customLayerData)
    data = plain(custom.get("usdface", {}))
    data = data if isinstance(data, dict) else {}
    flat = plain(custom.get("usdfaceFlatten", {}))
    flat = flat if isinstance(flat, dict) and flat.get("variant") else None
    fmt = str(data.get("format") or "")
    if fmt in _FORMATS:
        kind, by = _FORMATS[fmt], "format"
    elif flat is not None:
        kind, by = Kind.FLATTENED, "flatten"
    elif data.get("inputs"):
        kind, by = Kind.LAYER, "inputs"
    elif _defines_a_take(layer):
        kind, by = Kind.TAKE, "layer specs"
    else:
        kind, by = Kind.USD, "nothing"
    facts = {}
    if compose and stage is None:
        stage = _open(path)
    if stage is not None:
        found, facts = _composed(stage)
        # the composed stage decides what the root layer left open; over the layer-spec take test it wins
        # only with a kind that is no avatar (a mesh cache with a SkelRoot stays what the specs said)
        if found is not None and (by == "nothing" or by == "layer specs" and found[0] in NOT_AVATAR):
            kind, by = found
    return FileKind(path, kind, by, data, flat, layer=layer, **facts)


def _open(path: Path):
    """The composed stage as the readers open it, or None when it does not open cleanly."""
    from .usd_open import open_usd_stage

    try:
        return open_usd_stage(path, "file", "check the path")
    except Exception:  # noqa: BLE001 - unreadable: the reader that follows names the problem
        return None


def _composed(stage):
    """``((kind, by) or None, {"skel_root": ..., "blend_shapes": ..., "skel_animation": ...})`` from the
    composed stage."""
    from pxr import Usd, UsdSkel

    skel_root = blend_shapes = skel_animation = capture_api = False
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        skel_root = skel_root or prim.IsA(UsdSkel.Root)
        blend_shapes = blend_shapes or prim.IsA(UsdSkel.BlendShape)
        skel_animation = skel_animation or prim.IsA(UsdSkel.Animation)
        # as authored (GetAppliedSchemas() leaves out schemas USD's registry does not know: usdface's, in a
        # host that opened a stage before usdface registered them), and a tenth of its cost
        capture_api = capture_api or "UsdFaceCaptureAPI" in prim.GetPrimTypeInfo().GetAppliedAPISchemas()
    facts = {"skel_root": skel_root, "blend_shapes": blend_shapes, "skel_animation": skel_animation}
    root = stage.GetDefaultPrim()
    if root and root.GetChild("Frames") and root.GetChild("Template"):
        # a capture's frames carry their roles (train/test); a take's (usdface's or another tool's) do not
        role = root.GetChild("Frames").GetAttribute("usdface:frames:role")
        return ((Kind.CAPTURE if role else Kind.TAKE), "layout"), facts
    if root and str(root.GetPath()) == "/ErrorMaps" and not skel_root:
        return (Kind.ERROR_MAPS, "legacy"), facts        # written before the maps carried their format
    if top_animation(stage) is not None and not skel_root:
        return (Kind.WEIGHTS_TAKE, "stage"), facts
    if capture_api:
        return (Kind.CAPTURE, "schema"), facts
    if skel_root:
        return (Kind.AVATAR, "stage"), facts
    return None, facts


def top_animation(stage):
    """The default prim, or else the first top-level prim, that is a SkelAnimation; None."""
    from pxr import UsdSkel

    root = stage.GetDefaultPrim()
    tops = [root] if root else list(stage.GetPseudoRoot().GetChildren())
    return next((p for p in tops if p.IsA(UsdSkel.Animation)), None)


def is_weights_take(stage) -> bool:
    """A weights-only take (``usdface anim import``, :func:`usdface.io.usd_anim.write_animation_usd`, or any
    file whose default prim, or else a top-level prim, is a SkelAnimation) with no SkelRoot anywhere (instance
    proxies included): the stage rule :func:`file_kind` calls :attr:`Kind.WEIGHTS_TAKE`."""
    from pxr import Usd, UsdSkel

    if top_animation(stage) is None:
        return False
    return not any(p.IsA(UsdSkel.Root) for p in stage.Traverse(Usd.TraverseInstanceProxies()))


def _defines_a_take(layer) -> bool:
    """Whether the root layer itself *defines* a mesh with time-sampled ``points`` and has no capture
    ``usdface:frames:role`` and no blend shapes outside the take's own ``Template`` rig.

    The layer's own specs, not a composed stage: opening one here would report its composition errors (a
    missing sublayer) a second time, outside the reader that names them with their fix. An avatar (blend
    shapes bound to a mesh outside a take's own Template rig) is not a take even where one of its meshes is
    an animated cache (a hair cache, a baked ground truth); nor is a shot file whose animated mesh is an
    ``over`` of something it composes (a cache over a referenced avatar): a take *defines* its frames mesh.
    Arcs and sublayers elsewhere (a take's looks, its template in a file of its own) do not change the
    answer."""
    from pxr import Sdf

    seen = {"role": False, "points": False, "blend": False}

    def visit(spec_path):
        if spec_path.IsPropertyPath():
            if spec_path.name == "usdface:frames:role":
                seen["role"] = True
            elif spec_path.name == "points" and layer.GetNumTimeSamplesForPath(spec_path) > 1:
                owner = layer.GetPrimAtPath(spec_path.GetPrimPath())
                if owner is not None and owner.specifier == Sdf.SpecifierDef:
                    seen["points"] = True
            elif spec_path.name == "skel:blendShapes" and not _in_template(spec_path):
                seen["blend"] = True
        elif spec_path.IsPrimPath():
            spec = layer.GetPrimAtPath(spec_path)
            if spec is not None and spec.typeName == "BlendShape" and not _in_template(spec_path):
                seen["blend"] = True

    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    return seen["points"] and not seen["role"] and not seen["blend"]


def _in_template(spec_path) -> bool:
    """Whether a spec path lies in a take's own template rig, ``/<root>/Template/...`` (read_take_usd)."""
    prefixes = spec_path.GetPrefixes()
    return len(prefixes) > 1 and prefixes[1].name == "Template"
