"""Colour-coded reconstruction-error maps as a USD stage (Menzel et al. 2022, Fig. 6): one Mesh per
(method, test frame) on the capture topology, laid out in a grid (rows = methods, columns = frames), with
per-vertex ``displayColor`` (0 mm blue -> >= 5 mm red) and the raw error as a ``primvars:usdface:errorMm``
float primvar. Written by ``usdface evaluate --usd``; open it in usdview.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["write_error_maps_usd"]


def _prim_name(text: str) -> str:
    out = "".join(c if (c.isalnum() or c == "_") else "_" for c in str(text))
    return out if out and not out[0].isdigit() else "_" + out


def write_error_maps_usd(path, triangles: np.ndarray, maps: dict, *, spacing: float | None = None,
                         force: bool = False) -> Path:
    """Write error maps to a new USD file (metres, Y up), atomically; refuses an existing file unless
    ``force``.

    ``maps``: ``{method: [(label, points[n,3] metres, error_mm[n], colors[n,3] in [0,1]), ...]}``. Meshes are
    placed at ``x = column * spacing``, ``y = -row * spacing`` (``spacing`` defaults to 1.2 x the meshes'
    largest width for the columns and 1.2 x their largest height for the rows: a face is taller than wide,
    and rows spaced by its width overlapped by 2 cm on dev1). Returns the written path.
    """
    from pxr import Gf, Sdf, Usd, UsdGeom, Vt

    from .layers import atomic_save, check_output_path

    path = check_output_path(path, force, what="error-map file")
    tris = np.asarray(triangles, dtype=np.int64)
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/ErrorMaps")
    stage.SetDefaultPrim(root.GetPrim())
    stage.GetRootLayer().customLayerData = {"usdface": {"format": "errorMaps"}}   # what it is, for readers
    root.GetPrim().SetDocumentation("reconstruction error per vertex: blue = 0 mm, red >= 5 mm "
                                    "(rows: methods, columns: test frames)")
    step_x = step_y = spacing
    if spacing is None:
        extents = [np.ptp(np.asarray(f[1], dtype=np.float64), axis=0)
                   for frames in maps.values() for f in frames]
        most = np.max(extents, axis=0) if extents else np.ones(3)
        step_x, step_y = (1.2 * float(most[0]) or 1.0), (1.2 * float(most[1]) or 1.0)
    for row, (method, frames) in enumerate(maps.items()):
        group = UsdGeom.Xform.Define(stage, f"/ErrorMaps/{_prim_name(method)}")
        for col, (label, points, err, colors) in enumerate(frames):
            pts = np.asarray(points, dtype=np.float64)
            mesh = UsdGeom.Mesh.Define(stage, group.GetPath().AppendChild(_prim_name(label)))
            mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts.astype(np.float32)))
            mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(tris)))
            mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(tris.ravel().astype(np.int32)))
            mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(
                Vt.Vec3fArray.FromNumpy(np.asarray(colors, dtype=np.float32)))
            UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("usdface:errorMm", Sdf.ValueTypeNames.FloatArray,
                                                    UsdGeom.Tokens.vertex).Set(
                Vt.FloatArray.FromNumpy(np.asarray(err, dtype=np.float32)))
            UsdGeom.XformCommonAPI(mesh).SetTranslate(Gf.Vec3d(col * step_x, -row * step_y, 0.0))
    return atomic_save(stage.GetRootLayer(), path, force)


def read_error_maps(path) -> dict[str, dict[str, np.ndarray]]:
    """The per-vertex errors of an error-map file (:func:`write_error_maps_usd`):
    ``{method prim name: {frame prim name: error_mm[n]}}``, in the file's order (``usdface inspect``)."""
    from pxr import UsdGeom

    from .usd_open import open_usd_stage

    stage = open_usd_stage(path, "error-map file", "pass a file written by 'usdface evaluate --usd'")
    root = stage.GetDefaultPrim() or stage.GetPrimAtPath("/ErrorMaps")
    out: dict[str, dict[str, np.ndarray]] = {}
    for group in (root.GetChildren() if root else []):
        frames = {}
        for prim in group.GetChildren():
            pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("usdface:errorMm") if prim.IsA(UsdGeom.Mesh) else None
            values = pv.Get() if pv else None
            if values is not None:
                frames[prim.GetName()] = np.asarray(values, dtype=np.float64)
        if frames:
            out[group.GetName()] = frames
    return out
