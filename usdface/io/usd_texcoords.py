"""Texture coordinates of an avatar's meshes for the glTF export: each mesh's ``st`` primvar (or its first
texture-coordinate primvar), per triangle corner of the triangles usdface reads the mesh into.

USD gives texture coordinates per point (``vertex``/``varying``), per face corner (``faceVarying``, what DCCs
write: a UV seam has two values at one point), per face (``uniform``) or once (``constant``), optionally
indexed; glTF has one value per vertex, so the writer (:func:`usdface.io.gltf.write_gltf`) splits the points
where their corners differ. Here they are only gathered per triangle corner, ``uv[t, 3, 2]`` (USD's
``(s, t)``, ``t`` up)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["read_texcoords"]


def _texcoord_primvar(prim):
    """The mesh's ``st`` primvar, or else its first texture-coordinate (``texCoord2*[]``) primvar by name."""
    from pxr import Sdf, UsdGeom

    api = UsdGeom.PrimvarsAPI(prim)
    st = api.GetPrimvar("st")
    if st and st.HasValue():
        return st
    roles = (Sdf.ValueTypeNames.TexCoord2fArray, Sdf.ValueTypeNames.TexCoord2dArray,
             Sdf.ValueTypeNames.TexCoord2hArray)
    found = sorted((p for p in api.GetPrimvarsWithValues() if p.GetTypeName() in roles),
                   key=lambda p: p.GetPrimvarName())
    return found[0] if found else None


def read_texcoords(path, meshes) -> dict:
    """``{name: uv[t, 3, 2]}`` for ``meshes`` ``[(prim path, name, triangles[t, 3])]`` of the USD file
    ``path`` (``triangles`` as usdface reads the mesh: its faces fan-triangulated, reversed for a
    left-handed or mirrored mesh). A mesh without texture coordinates, or whose primvar does not fit its
    topology, is left out."""
    from pxr import Usd, UsdGeom

    from .mesh_io import fan_triangulate
    from .usd_rig import _open_stage

    stage = _open_stage(Path(path))
    out = {}
    for prim_path, name, triangles in meshes:
        prim = stage.GetPrimAtPath(str(prim_path))
        primvar = _texcoord_primvar(prim) if prim and prim.IsA(UsdGeom.Mesh) else None
        values = primvar.ComputeFlattened(Usd.TimeCode.Default()) if primvar else None
        if values is None or not len(values):
            continue
        values = np.asarray(values, dtype=np.float64).reshape(-1, 2)
        mesh = UsdGeom.Mesh(prim)
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(), dtype=np.int64)
        indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64)
        tris = fan_triangulate(counts, indices)
        corners = fan_triangulate(counts, np.arange(indices.size))
        triangles = np.asarray(triangles, dtype=np.int64)
        if not np.array_equal(triangles, tris):                 # wound the other way (left-handed)
            tris, corners = tris[:, ::-1], corners[:, ::-1]
            if not np.array_equal(triangles, tris):
                continue
        interpolation = primvar.GetInterpolation()
        points = mesh.GetPointsAttr().Get()
        if interpolation in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying) and points is not None \
                and len(values) == len(points):
            uv = values[tris]
        elif interpolation == UsdGeom.Tokens.faceVarying and len(values) == indices.size:
            uv = values[corners]
        elif interpolation == UsdGeom.Tokens.uniform and len(values) == counts.size:
            uv = np.repeat(values[np.repeat(np.arange(counts.size), counts - 2)][:, None], 3, axis=1)
        elif interpolation == UsdGeom.Tokens.constant:
            uv = np.broadcast_to(values[0], (len(tris), 3, 2)).copy()
        else:
            continue
        if np.isfinite(uv).all():
            out[name] = uv
    return out
