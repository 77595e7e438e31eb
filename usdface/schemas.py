"""usdface's codeless USD schemas: registration with USD's plugin system.

The schemas live in ``schemas/`` (``schema.usda`` is the source; ``generatedSchema.usda`` and
``plugInfo.json`` are made from it by ``python -m pxr.Usd.usdGenSchema schemas/schema.usda schemas``). They
are *codeless* applied API schemas, so no compiled code is needed; USD only has to be told where
``plugInfo.json`` is, and that must happen **before the first stage or the schema registry is created** (the
registry reads the plugins once). ``import usdface.io`` calls :func:`register`, so any code path that reads or
writes USD through usdface has them.

Schemas (attributes in the ``usdface:`` namespace; see ``docs/schemas.md``):

* ``UsdFaceCaptureAPI``: capture metadata (device, units note, train/test counts, shape names, source digest);
* ``UsdFaceLandmarksAPI``: a landmark layout's parameters and solver outcome (epsilon, alpha, solverStatus,
  optimalityGap, count, symmetric, multicover, vertexIndices, mesh);
* ``UsdFaceProvenanceAPI``: personalization provenance (version, command, method, parameters, input digests,
  registration scale/residual, createdAt).

Example::

    import usdface.schemas
    usdface.schemas.register()
    from pxr import Usd
    stage = Usd.Stage.CreateInMemory()
    prim = stage.DefinePrim("/Face")
    prim.ApplyAPI(usdface.schemas.LANDMARKS_API)
    prim.GetAttribute("usdface:landmarks:epsilon").Get()   # 0.5 (the schema's fallback)
"""

from __future__ import annotations

import os
from pathlib import Path

from .errors import warn

CAPTURE_API = "UsdFaceCaptureAPI"
LANDMARKS_API = "UsdFaceLandmarksAPI"
PROVENANCE_API = "UsdFaceProvenanceAPI"
SCHEMA_NAMES = (CAPTURE_API, LANDMARKS_API, PROVENANCE_API)

#: Environment variable that points at a schemas directory (overrides the built-in search).
ENV_VAR = "USDFACE_SCHEMAS"

_registered: Path | None = None
_late: Path | None = None       # registered after USD's schema registry was built: warned about once


def schema_dir() -> Path:
    """The directory holding ``plugInfo.json`` + ``generatedSchema.usda``.

    Searched in order: ``$USDFACE_SCHEMAS``; ``usdface/schemas/`` inside the installed package (a wheel's
    package data); ``schemas/`` at the root of a source checkout (editable install).
    """
    here = Path(__file__).resolve().parent
    candidates = []
    if os.environ.get(ENV_VAR):
        candidates.append(Path(os.environ[ENV_VAR]))
    candidates += [here / "schemas", here.parent / "schemas"]
    for c in candidates:
        if (c / "plugInfo.json").is_file() and (c / "generatedSchema.usda").is_file():
            return c
    from .errors import InputFileError

    raise InputFileError("usdface schemas not found (plugInfo.json + generatedSchema.usda)",
                         path=", ".join(str(c) for c in candidates),
                         fix=f"reinstall usdface, or set {ENV_VAR} to the repository's schemas/ directory")


def register(strict: bool = False) -> Path:
    """Register usdface's schemas with USD (idempotent). Returns the schemas directory.

    Must run before the first ``Usd.Stage`` or ``Usd.SchemaRegistry`` is created in the process. If the schema
    registry was already built without them, warns (``strict=False``; usdface then still works, but applied
    schemas have no fallbacks) or raises :class:`usdface.errors.UsdFaceError` (``strict=True``).
    """
    global _registered, _late
    if _registered is not None:
        return _registered
    if _late is not None and not strict:     # told once: each later call (usdface.io, the validators, ...)
        return _late                         # repeated the same warning from its own line
    from pxr import Plug, Usd

    directory = schema_dir()
    Plug.Registry().RegisterPlugins(str(directory))
    if Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(LANDMARKS_API) is None:
        from .errors import UsdFaceError

        error = UsdFaceError(
            "USD's schema registry was created before usdface registered its schemas (a stage was opened "
            "first, e.g. inside a DCC); usdface still writes the same data and records the applied schemas, "
            "only their fallback values are unknown to this process",
            path=directory,
            fix=f"set PXR_PLUGINPATH_NAME={directory} before starting the host, or import usdface.io before "
                "opening any USD stage")
        if strict:
            raise error
        warn(str(error))
        _late = directory
        return directory
    _registered = directory
    return directory


def is_registered() -> bool:
    """True when the three usdface API schemas are known to USD's schema registry."""
    from pxr import Usd

    return all(Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(n) is not None for n in SCHEMA_NAMES)


def apply_api(prim, name: str) -> None:
    """Apply the usdface API schema ``name`` to ``prim``: ``ApplyAPI`` when USD's registry knows it, else (the
    registry was built before :func:`register`, as inside a DCC) the same ``apiSchemas`` entry is authored
    with ``AddAppliedSchema``; :func:`schema_attribute` then creates the attributes with their schema types.
    The file written is the same either way (:func:`register` already warned once)."""
    from pxr import Usd

    if Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(name) is not None:
        prim.ApplyAPI(name)
    else:
        prim.AddAppliedSchema(name)


def schema_attribute(prim, attr_name: str, api_name: str):
    """The schema attribute ``attr_name`` of ``api_name`` on ``prim``; created with the type declared in
    ``generatedSchema.usda`` when this process's schema registry does not define it."""
    attr = prim.GetAttribute(attr_name)
    if attr:
        return attr
    return prim.CreateAttribute(attr_name, _attribute_types(api_name)[attr_name], custom=False)


_types_cache: dict = {}


def _attribute_types(api_name: str) -> dict:
    """{attribute name: Sdf.ValueTypeName} of an API schema, read from ``generatedSchema.usda`` (Sdf level:
    works without the schema registry)."""
    if api_name not in _types_cache:
        from pxr import Sdf

        layer = Sdf.Layer.FindOrOpen(str(schema_dir() / "generatedSchema.usda"))
        spec = layer.GetPrimAtPath(f"/{api_name}")
        _types_cache[api_name] = {a.name: a.typeName for a in spec.attributes} if spec else {}
    return _types_cache[api_name]
