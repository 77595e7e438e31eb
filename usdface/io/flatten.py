"""One variant of a usdface layer: read it, or flatten it into one self-contained USD file.

A layer written by :func:`usdface.io.layers.write_avatar_layer` carries the ``usdfacePersonalization``
variant set {``personalized``, ``generic``} on each SkelRoot. :func:`variant_stage` opens the layer with the
chosen selection authored in the stage's session layer (the files are never modified);
:func:`read_avatar_variant` reads that composed avatar (metres, Y up, like
:func:`usdface.io.usd_rig.read_avatar`) and :func:`flatten_variant` writes ``Usd.Stage.Flatten()`` of it:
one layer, no sublayers or references, for places that do not take layers.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import InputFileError, OptionError, RigError, UsdFaceError
from ..model import Avatar
from .layers import PERSONALIZATION_VARIANT_SET, check_output_path

__all__ = ["VARIANTS", "AS_AUTHORED", "baked_variant", "exported_variant", "variant_stage",
           "read_avatar_variant", "flatten_variant"]

#: The variants of ``usdfacePersonalization``.
VARIANTS = ("personalized", "generic")


def _check_variant(variant: str) -> None:
    if variant not in VARIANTS:
        raise OptionError(f"unknown variant {variant!r}", fix=f"choose one of {', '.join(VARIANTS)}")


#: What :func:`exported_variant` says of a plain avatar (no ``usdfacePersonalization`` variant set).
AS_AUTHORED = "authored"


def _personalization_prims(stage) -> list:
    from pxr import Usd

    return [p for p in stage.Traverse(Usd.TraverseInstanceProxies())
            if p.GetVariantSets().HasVariantSet(PERSONALIZATION_VARIANT_SET)]


def baked_variant(path) -> dict | None:
    """``{"source", "variant"}`` when ``path`` is a flattened export (``usdface export --flatten``) of a
    usdface layer's ``personalized`` or ``generic`` variant: a file with no ``usdfacePersonalization``
    variant set whose ``customLayerData["usdfaceFlatten"]`` records the variant baked in (``source``
    relative to ``path``'s folder); None for a usdface layer, a plain avatar or a flattened plain avatar."""
    from .usd_rig import _open_stage, flattened_from

    path = Path(path)
    if _personalization_prims(_open_stage(path, "layer")):
        return None
    baked = flattened_from(path)
    return baked if baked and baked.get("variant") in VARIANTS else None


def exported_variant(path, variant: str = "personalized") -> str:
    """What exporting ``path`` with ``variant`` actually gives: ``variant`` for a usdface layer; for a
    flattened export of a layer, the variant baked into it (:func:`baked_variant`: its shapes are that
    variant's, exported as authored); else :data:`AS_AUTHORED` ("authored": a plain avatar has no
    personalized variant; it exports as authored)."""
    from .usd_rig import _open_stage

    _check_variant(variant)
    if _personalization_prims(_open_stage(Path(path), "layer")):
        return variant
    baked = baked_variant(path)
    return baked["variant"] if baked else AS_AUTHORED


def variant_stage(path, variant: str = "personalized"):
    """Open ``path`` with ``variant`` selected on every prim that has the ``usdfacePersonalization`` variant
    set (authored in the session layer). Raises :class:`~usdface.errors.InputFileError` when the file has no
    such variant set (not a usdface layer) and ``generic`` was asked for, or is a flattened export of the
    personalized variant (naming the layer it came from); ``personalized`` of a plain avatar is the avatar as
    authored, and either variant of a flattened *generic* export is the generic baked in."""
    from pxr import Usd

    from .usd_rig import _open_stage, flattened_source

    _check_variant(variant)
    path = Path(path)
    stage = _open_stage(path, "layer")
    prims = _personalization_prims(stage)
    baked = baked_variant(path) if not prims and variant == "generic" else None
    if baked is not None and baked["variant"] == "personalized":
        # a flattened export of the personalized variant: it was 'not a usdface layer', of a file usdface
        # wrote and that names the layer it came from
        source = flattened_source(path, baked)     # from here, not from the export (stop 52)
        raise InputFileError(f"a flattened export of the personalized variant of {source or '?'}: "
                             "only the person's shapes are baked in, the generic variant is not in it",
                             path=path, fix=f"export the generic variant of the layer it was flattened from "
                                            f"({source or 'LAYER'}) or use the original avatar")
    if not prims and variant == "generic" and baked is None:
        from .usd_rig import dcc_export_marks

        marks = dcc_export_marks(path)
        if marks:           # Blender's export of a usdface layer: its shapes are the variant it composed
            raise InputFileError(
                f"this looks like a DCC export (Blender, ...) of a usdface output layer (it has {marks[0]}): "
                "the DCC baked in the variant it composed ('personalized' unless switched) and dropped the "
                "variant set, so the generic shapes are not in it", path=path, prim=marks[0],
                fix="export the generic variant of the usdface layer itself ('usdface export person.usda "
                    "--variant generic ...') or use the original avatar")
        raise InputFileError(f"no {PERSONALIZATION_VARIANT_SET} variant set (not a usdface layer)", path=path,
                             fix="pass a layer written by 'usdface personalize'")
    with Usd.EditContext(stage, stage.GetSessionLayer()):
        for prim in prims:
            prim.GetVariantSets().GetVariantSet(PERSONALIZATION_VARIANT_SET).SetVariantSelection(variant)
    return stage


def read_avatar_variant(path, variant: str = "personalized") -> Avatar:
    """The avatar composed with ``variant`` selected (see :func:`variant_stage`), as an
    :class:`usdface.model.Avatar` in metres / Y up."""
    from pxr import Tf

    from .usd_rig import _read_avatar_stage, recorded_name_map

    path = Path(path)
    stage = variant_stage(path, variant)
    try:          # a layer over a studio-named avatar reads with the name map it was written with
        return _read_avatar_stage(stage, path, name_map=recorded_name_map(stage))
    except UsdFaceError:
        raise
    except (Tf.ErrorException, ValueError, TypeError, IndexError, KeyError) as exc:
        from .usd_open import tf_error_text

        what = tf_error_text(exc, path, 200) if isinstance(exc, Tf.ErrorException) else str(exc).strip()[:200]
        raise RigError(f"malformed UsdSkel data ({type(exc).__name__}: {what})", path=path,
                       fix="re-export the avatar; run `usdface inspect` on it for details") from None


def flatten_variant(path, out_path, variant: str = "personalized", *, force: bool = False) -> Path:
    """Write ``path`` composed with ``variant`` selected as ONE flattened USD file (``.usda``/``.usdc``/
    ``.usd``, or a ``.usdz`` package of it: :func:`usdface.io.layers.atomic_save_usdz`): every sublayer and
    reference resolved into it, the variant selection baked in. Returns the path written (atomically; an
    existing file needs ``force``). The input is never modified."""
    from pxr import Vt

    from .layers import atomic_save, atomic_save_usdz

    _check_variant(variant)
    src = Path(path).absolute()
    out = check_output_path(out_path, force, inputs=[src], what="flattened USD file", usdz=True).absolute()
    try:
        stage = variant_stage(src, variant)
    except UsdFaceError as exc:        # the layer named as the caller gave it (stop 52: its absolute path)
        if exc.path == str(src):
            exc.path = str(path)
        raise
    targets = _shape_redirections(stage)
    flat = stage.Flatten()
    _bake_redirections(flat, targets)
    data = dict(flat.customLayerData)
    # the variant actually baked in ("authored" for a plain avatar): personalize refuses a personalized one.
    # A flattened export flattened again keeps what the first baked in and the layer it came from (it said
    # "authored", and personalize then took that file for an avatar and stacked the personalization again)
    baked = None if _personalization_prims(stage) else baked_variant(src)
    data["usdfaceFlatten"] = (
        {"source": _rebase(baked.get("source") or src.name, src, out), "variant": baked["variant"]} if baked
        else {"source": _rebase(src.name, src, out),
              "variant": variant if _personalization_prims(stage) else AS_AUTHORED})
    record = data.get("usdface")
    if hasattr(record, "get") and record.get("inputs"):        # provenance paths, relative to the new file
        record = dict(record)
        record["inputs"] = Vt.StringArray([_rebase(p, src, out) for p in record["inputs"]])
        if record.get("take"):                                  # the take among them (personalize --take)
            record["take"] = _rebase(record["take"], src, out)
        data["usdface"] = record
    flat.customLayerData = data
    if data["usdfaceFlatten"]["variant"] == "personalized":
        _mark_personalized(flat, stage)
    _rebase_provenance_attributes(flat, src, out)
    _relative_asset_paths(flat, out)
    if out.suffix.lower() == ".usdz":           # one self-contained file: packaged by USD (recorded paths
        return atomic_save_usdz(flat, out, force)   # are relative to the package's folder, as for a .usdc)
    return atomic_save(flat, out, force)


#: an empty Scope under each SkelRoot of a flattened export of the ``personalized`` variant: a DCC keeps
#: it (Blender: an Empty, written back as an Xform) where it drops ``customLayerData``, so a DCC's export
#: of the flattened file is still refused as personalized (:func:`usdface.io.usd_rig.dcc_export_marks`)
PERSONALIZED_MARK = "usdfacePersonalized"


def _mark_personalized(layer, stage) -> None:
    """:data:`PERSONALIZED_MARK` under each prim that had the personalization variant set (a flattened export
    flattened again keeps the marks Flatten copied)."""
    from pxr import Sdf

    for prim in _personalization_prims(stage):
        parent = layer.GetPrimAtPath(prim.GetPath())
        if parent is None or PERSONALIZED_MARK in parent.nameChildren:
            continue
        mark = Sdf.PrimSpec(parent, PERSONALIZED_MARK, Sdf.SpecifierDef, "Scope")
        mark.documentation = ("usdface: the blend shapes of this avatar are a person's personalized ones "
                              "(usdface export --flatten of the personalized variant); delete this prim only "
                              "if they are the generic ones")


def _shape_redirections(stage) -> dict[str, list[tuple[str, str]]]:
    """``{mesh path: [(usdfaceShapes/<shape> path, original BlendShape path), ...]}`` in binding order, for
    the meshes whose ``skel:blendShapeTargets`` a usdface layer redirected into its variant scope: each
    scope prim's first reference arc targets the original prim (internal in ``personalized``, into the input
    file in ``generic``)."""
    from pxr import Pcp, Usd, UsdSkel

    from .layers import SHAPES_SCOPE

    out = {}
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        if not prim.HasAPI(UsdSkel.BindingAPI):
            continue
        rel = UsdSkel.BindingAPI(prim).GetBlendShapeTargetsRel()
        targets = rel.GetTargets() if rel else []
        if not targets or not all(t.GetParentPath().name == SHAPES_SCOPE for t in targets):
            continue
        pairs = []
        for t in targets:
            arcs = [a for a in Usd.PrimCompositionQuery(stage.GetPrimAtPath(t)).GetCompositionArcs()
                    if a.GetArcType() == Pcp.ArcTypeReference]
            if not arcs:
                break
            pairs.append((str(t), str(arcs[0].GetTargetNode().path)))
        else:
            out[str(prim.GetPath())] = pairs
    return out


def _bake_redirections(layer, redirections: dict) -> None:
    """In the flattened ``layer``: the variant's values (on ``usdfaceShapes/<shape>``) moved onto the
    original BlendShape prims, the bindings pointed back at those, and the scopes removed. The flattened file
    is then an avatar like the one the layer was made over, with the chosen values: personalizing a
    flattened *generic* export writes its own variant set again (its targets no longer lead into a scope
    without variants), and DCCs see the avatar's own BlendShape paths."""
    from pxr import Sdf

    for mesh, pairs in redirections.items():
        if any(scoped == original or layer.GetPrimAtPath(original) is None for scoped, original in pairs):
            continue                              # an original not in the flattened file: keep the scope
        for scoped, original in pairs:
            src, dst = layer.GetPrimAtPath(scoped), layer.GetPrimAtPath(original)
            # the original's own properties go first, also those the chosen values lack: the layer
            # authors the personalized shapes' sparse pointIndices on the original prims (outside the
            # variants), and the generic variant's dense shape has none; kept, they paired the generic
            # dense offsets with the sparse indices (a --variant generic export that check refused and
            # readers could not read)
            for name in [prop.name for prop in dst.properties]:
                del dst.properties[name]
            for prop in list(src.properties):
                Sdf.CopySpec(layer, prop.path, layer, dst.path.AppendProperty(prop.name))
        rel = layer.GetRelationshipAtPath(Sdf.Path(mesh).AppendProperty("skel:blendShapeTargets"))
        rel.targetPathList.explicitItems = [Sdf.Path(original) for _, original in pairs]
        scope = Sdf.Path(pairs[0][0]).GetParentPath()
        del layer.GetPrimAtPath(scope.GetParentPath()).nameChildren[scope.name]


def _rebase(path, src: Path, out: Path) -> str:
    """A path recorded relative to ``src``'s folder, relative to ``out``'s folder (a flattened file written
    elsewhere keeps a provenance that ``check`` can follow)."""
    from .layers import _relative_to_layer

    p = Path(str(path))
    return _relative_to_layer(p if p.is_absolute() else src.parent / p, out)


def _relative_asset_paths(layer, out: Path) -> None:
    """The flattened layer's asset paths (textures, any ``asset`` value), which ``Stage.Flatten`` anchors as
    absolute paths, relative to ``out``'s folder again by the rule of the layer's sublayer path
    (:func:`usdface.io.layers._relative_asset_path`: relative within one project, absolute across file
    systems or with only the root in common), so a delivery copied or mounted elsewhere with its textures
    finds them. Paths into a package (``a.usdz[tex.png]``) and non-file paths are kept."""
    from pxr import UsdUtils

    from .layers import _relative_asset_path

    def rebase(asset: str) -> str:
        if not asset or "[" in asset or not os.path.isabs(asset):
            return asset
        return _relative_asset_path(Path(asset), out.parent)

    UsdUtils.ModifyAssetPaths(layer, rebase)


def _rebase_provenance_attributes(layer, src: Path, out: Path) -> None:
    """``usdface:provenance:inputs`` on the flattened prims, rebased as the layer's record
    (:func:`_rebase`)."""
    from pxr import Sdf, Vt

    def visit(spec_path):
        if spec_path.IsPropertyPath() and spec_path.name == "usdface:provenance:inputs":
            spec = layer.GetAttributeAtPath(spec_path)
            if spec is not None and spec.default:
                spec.default = Vt.StringArray([_rebase(p, src, out) for p in spec.default])

    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
