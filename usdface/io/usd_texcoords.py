"""Per-corner primvars of an avatar's meshes for the exports: texture coordinates (each mesh's ``st``
primvar, or its first texture-coordinate primvar) and authored normals (``primvars:normals``, else
``normals``), per triangle corner of the triangles usdface reads the mesh into; and the shapes' authored
``normalOffsets`` in the internal frame.

USD gives these per point (``vertex``/``varying``), per face corner (``faceVarying``, what DCCs write: a UV
seam or a hard edge has two values at one point), per face (``uniform``) or once (``constant``), optionally
indexed; glTF has one value per vertex, so the writer (:func:`usdface.io.gltf.write_gltf`) splits the points
where their corners differ. Here they are only gathered per triangle corner: ``uv[t, 3, 2]`` (USD's
``(s, t)``, ``t`` up), ``normals[t, 3, 3]`` (internal frame, unit length)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["read_texcoords", "read_normals", "normal_offsets"]


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


def _authored_normals(prim):
    """``(values, interpolation)`` of the mesh's authored normals: ``primvars:normals`` (which UsdGeom says
    wins) or the ``normals`` attribute; None when it has none."""
    from pxr import Usd, UsdGeom

    primvar = UsdGeom.PrimvarsAPI(prim).GetPrimvar("normals")
    if primvar and primvar.HasValue():
        return primvar.ComputeFlattened(Usd.TimeCode.Default()), primvar.GetInterpolation()
    mesh = UsdGeom.Mesh(prim)
    attr = mesh.GetNormalsAttr()
    if attr.HasAuthoredValue():
        return attr.Get(Usd.TimeCode.Default()), mesh.GetNormalsInterpolation()
    return None


def _per_corner(prim, values, interpolation, triangles, width: int):
    """``values`` of the mesh ``prim`` (``width`` components, USD ``interpolation``) per corner of
    ``triangles`` ``[t, 3]`` (as usdface reads the mesh: its faces fan-triangulated, reversed for a
    left-handed or mirrored mesh): ``[t, 3, width]``, or None when they do not fit its topology or are not
    finite."""
    from pxr import UsdGeom

    from .mesh_io import fan_triangulate

    if values is None or not len(values):
        return None
    values = np.asarray(values, dtype=np.float64).reshape(-1, width)
    mesh = UsdGeom.Mesh(prim)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(), dtype=np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64)
    tris = fan_triangulate(counts, indices)
    corners = fan_triangulate(counts, np.arange(indices.size))
    triangles = np.asarray(triangles, dtype=np.int64)
    if not np.array_equal(triangles, tris):                 # wound the other way (left-handed)
        tris, corners = tris[:, ::-1], corners[:, ::-1]
        if not np.array_equal(triangles, tris):
            return None
    points = mesh.GetPointsAttr().Get()
    if interpolation in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying) and points is not None \
            and len(values) == len(points):
        out = values[tris]
    elif interpolation == UsdGeom.Tokens.faceVarying and len(values) == indices.size:
        out = values[corners]
    elif interpolation == UsdGeom.Tokens.uniform and len(values) == counts.size:
        out = np.repeat(values[np.repeat(np.arange(counts.size), counts - 2)][:, None], 3, axis=1)
    elif interpolation == UsdGeom.Tokens.constant:
        out = np.broadcast_to(values[0], (len(tris), 3, width)).copy()
    else:
        return None
    return out if np.isfinite(out).all() else None


def _mesh_prims(path, meshes):
    from pxr import UsdGeom

    from .usd_rig import _open_stage

    stage = _open_stage(Path(path))
    for prim_path, *rest in meshes:
        prim = stage.GetPrimAtPath(str(prim_path))
        if prim and prim.IsA(UsdGeom.Mesh):
            yield prim, rest


def read_texcoords(path, meshes) -> dict:
    """``{name: uv[t, 3, 2]}`` for ``meshes`` ``[(prim path, name, triangles[t, 3])]`` of the USD file
    ``path`` (``triangles`` as usdface reads the mesh: its faces fan-triangulated, reversed for a
    left-handed or mirrored mesh). A mesh without texture coordinates, or whose primvar does not fit its
    topology, is left out."""
    from pxr import Usd

    out = {}
    for prim, (name, triangles) in _mesh_prims(path, meshes):
        primvar = _texcoord_primvar(prim)
        if primvar is None:
            continue
        uv = _per_corner(prim, primvar.ComputeFlattened(Usd.TimeCode.Default()), primvar.GetInterpolation(),
                         triangles, 2)
        if uv is not None:
            out[name] = uv
    return out


def read_normals(path, meshes) -> dict:
    """``{name: normals[t, 3, 3]}`` (internal frame, unit length) for ``meshes`` ``[(prim path, name,
    triangles[t, 3], to_internal[4, 4])]`` of the USD file ``path`` that author normals (``to_internal``:
    the placement the mesh's points were read with, :attr:`usdface.model.MeshSource.to_internal`; normals
    take its inverse transpose). A mesh without normals, or whose normals do not fit its topology, is left
    out; a zero authored normal is NaN here (no direction: the writer gives that corner the computed one)."""
    out = {}
    for prim, (name, triangles, to_internal) in _mesh_prims(path, meshes):
        authored = _authored_normals(prim)
        normals = _per_corner(prim, *authored, triangles, 3) if authored is not None else None
        if normals is None:
            continue
        normals = normals @ np.linalg.inv(np.asarray(to_internal, dtype=np.float64)[:3, :3])  # n' = L^-T n
        length = np.linalg.norm(normals, axis=-1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            out[name] = np.where(length > 0, normals / length, np.nan)
    return out


def normal_offsets(rig) -> list | None:
    """The shapes' authored ``normalOffsets`` of ``rig`` (:class:`usdface.model.FaceRig` read from USD) in
    the internal frame, one ``[n, 3]`` per shape on every point (zero off its ``pointIndices``), or None for
    a shape without them; None when no shape has them (or the rig is cropped). UsdSkel adds a shape's
    weighted ``normalOffsets`` to the mesh's normals and normalises, as glTF does with a target's ``NORMAL``:
    the offsets take the inverse transpose of the placement times its scale, which keeps that sum exactly the
    placed one for a rotation, a uniform scale and a translation."""
    src = rig.source
    if src is None or not src.normal_offsets or src.region is not None \
            or len(src.normal_offsets) != rig.n_shapes or not any(x is not None for x in src.normal_offsets):
        return None
    linear = np.asarray(src.to_internal, dtype=np.float64)[:3, :3]
    placed = np.linalg.inv(linear) * np.cbrt(abs(np.linalg.det(linear)))
    out = []
    for k, offsets in enumerate(src.normal_offsets):
        if offsets is None:
            out.append(None)
            continue
        offsets = np.asarray(offsets, dtype=np.float64).reshape(-1, 3)
        dense = np.zeros((rig.n_vertices, 3))
        idx = src.point_indices[k]
        if idx is None:
            if len(offsets) != rig.n_vertices:
                out.append(None)
                continue
            dense[:] = offsets
        else:
            dense[np.asarray(idx, dtype=np.int64)] = offsets
        out.append(dense @ placed)
    return out
