"""Author a landmark layout as a USD layer over the untouched avatar.

The layer (written with :func:`usdface.io.layers.write_avatar_layer`: sublayers the input, copies the stage
metadata, provenance in ``customLayerData`` and on the SkelRoot, atomic save) adds:

* on the mesh: ``primvars:usdface:landmarks`` (int[], constant) - the landmark vertex indices - and
  ``primvars:usdface:landmarkCoverage`` (string[], constant) - per landmark, the shapes it represents
  (comma-separated names);
* a ``UsdGeom.Points`` prim ``<mesh>_landmarks`` next to the mesh, with the mesh's local transform, the
  landmark positions (the mesh's own authored points at those indices), ``widths`` and a ``displayColor`` per
  landmark (red = first cover, orange/yellow = later multi-cover rounds), so usdview shows them on the face;
  the ``UsdFaceLandmarksAPI`` schema applied to it carries epsilon, alpha, solver status, optimality gap,
  count, symmetric, multicover, the vertex indices and a relationship to the mesh.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import RigError
from ..model import Avatar, FaceRig

#: Landmark sphere diameter, metres.
LANDMARK_WIDTH = 0.004
_ROUND_COLOURS = np.array([[0.9, 0.1, 0.1], [1.0, 0.55, 0.0], [1.0, 0.9, 0.1], [0.2, 0.8, 0.2],
                           [0.1, 0.6, 1.0], [0.6, 0.3, 0.9]])
_SOLVER_TOKENS = ("notSolved", "optimal", "feasible", "infeasible", "timeLimit", "heuristic")


def points_prim_path(mesh_prim: str) -> str:
    """Where the landmark Points prim of a mesh goes: a sibling named ``<mesh>_landmarks``."""
    return f"{mesh_prim}_landmarks"


def author_landmarks(stage, rig: FaceRig, layout, meters_per_unit: float) -> None:
    """Author ``layout`` on an open stage (edit target = the output layer): the mesh primvars, the Points
    prim and its ``UsdFaceLandmarksAPI`` (see the module docstring). ``meters_per_unit`` of the stage."""
    from pxr import Sdf, UsdGeom, Vt

    from .. import schemas

    mesh_prim = stage.GetPrimAtPath(rig.source.prim)
    if not mesh_prim or not mesh_prim.IsA(UsdGeom.Mesh):
        raise RigError("mesh prim not found in the composed stage", path=rig.source.file,
                       prim=rig.source.prim, fix="pass the avatar the layout was computed on")
    mesh = UsdGeom.Mesh(mesh_prim)
    vertices = np.array(layout.vertices, dtype=np.int64)
    pv = UsdGeom.PrimvarsAPI(mesh_prim)
    pv.CreatePrimvar("usdface:landmarks", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.constant).Set(
        Vt.IntArray([int(v) for v in vertices]))
    coverage = [",".join(layout.shape_names[k] for k in np.flatnonzero(row)) for row in layout.coverage]
    pv.CreatePrimvar("usdface:landmarkCoverage", Sdf.ValueTypeNames.StringArray, UsdGeom.Tokens.constant).Set(
        Vt.StringArray(coverage))

    local = np.array(mesh.GetPointsAttr().Get(), dtype=np.float64)[vertices]
    xf = mesh.GetLocalTransformation()
    points = UsdGeom.Points.Define(stage, points_prim_path(rig.source.prim))
    points.MakeMatrixXform().Set(xf)      # one transform op, also over an earlier layout (a layer under this)
    points.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(local.astype(np.float32)))
    to_world = np.array(UsdGeom.Xformable(mesh_prim).ComputeLocalToWorldTransform(0.0), dtype=np.float64)
    scale = abs(np.linalg.det(to_world[:3, :3])) ** (1.0 / 3.0) or 1.0
    width = LANDMARK_WIDTH / (meters_per_unit * scale)
    points.CreateWidthsAttr(Vt.FloatArray([float(width)] * len(vertices)))
    points.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
    colours = _ROUND_COLOURS[(np.array(layout.rounds, dtype=np.int64) - 1) % len(_ROUND_COLOURS)]
    points.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(
        Vt.Vec3fArray.FromNumpy(colours.astype(np.float32)))
    ppv = UsdGeom.PrimvarsAPI(points)
    ppv.CreatePrimvar("usdface:vertexIndex", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex).Set(
        Vt.IntArray([int(v) for v in vertices]))
    ppv.CreatePrimvar("usdface:shapeCount", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex).Set(
        Vt.IntArray([int(n) for n in np.array(layout.coverage).sum(axis=1)]))

    prim = points.GetPrim()
    schemas.apply_api(prim, schemas.LANDMARKS_API)
    status = layout.status if layout.status in _SOLVER_TOKENS else "notSolved"
    values = {"epsilon": float(layout.epsilon), "alpha": float(layout.alpha), "solverStatus": status,
              "optimalityGap": float(layout.gap), "count": int(layout.count),
              "symmetric": bool(layout.symmetric),
              "multicover": int(layout.multicover), "vertexIndices": Vt.IntArray([int(v) for v in vertices])}
    types = {"epsilon": Sdf.ValueTypeNames.Float, "alpha": Sdf.ValueTypeNames.Float,
             "solverStatus": Sdf.ValueTypeNames.Token, "optimalityGap": Sdf.ValueTypeNames.Double,
             "count": Sdf.ValueTypeNames.Int, "symmetric": Sdf.ValueTypeNames.Bool,
             "multicover": Sdf.ValueTypeNames.Int, "vertexIndices": Sdf.ValueTypeNames.IntArray}
    for key, value in values.items():
        name = f"usdface:landmarks:{key}"
        attr = prim.GetAttribute(name) or prim.CreateAttribute(name, types[key], custom=False)
        attr.Set(value)
    rel = prim.GetRelationship("usdface:landmarks:mesh") or prim.CreateRelationship("usdface:landmarks:mesh")
    rel.SetTargets([Sdf.Path(rig.source.prim)])


def write_landmark_layer(avatar: Avatar, rig: FaceRig, layout, out_path, *, force: bool = False,
                         provenance: dict | None = None) -> Path:
    """Write ``layout`` (a :class:`usdface.landmarks.LandmarkLayout` computed on ``rig``, a mesh of
    ``avatar``) as a new layer over ``avatar.file`` -> the output path. Refuses to overwrite without ``force``
    (:class:`usdface.errors.OutputExistsError`); the input is never modified."""
    from .layers import write_avatar_layer

    if rig.source is None or not rig.source.prim:
        raise RigError("the rig has no source mesh prim", path=avatar.file,
                       fix="read the avatar with usdface.io.usd_rig.read_avatar")
    _refuse_foreign_rig(avatar, rig, layout)
    prov = dict(provenance or {})
    prov.setdefault("method", "landmarks")
    prov["command"] = prov.get("command") or "usdface.api.write_landmarks (Python API)"
    return write_avatar_layer(avatar, out_path, {}, provenance=prov, force=force, variants=False,
                              edit=lambda stage: author_landmarks(stage, rig, layout, avatar.meters_per_unit))


def _refuse_foreign_rig(avatar: Avatar, rig: FaceRig, layout) -> None:
    """Refuse, before any write, a ``rig`` that is no mesh of ``avatar`` as read (another avatar's mesh at the
    same prim path, the bench's ``/Avatar/Head`` over the sample's) or a ``layout`` whose vertices it lacks:
    the layer died with numpy's ``IndexError`` while it was being authored (a user trial)."""
    mesh = next((m for m in avatar.meshes if m.source is not None and m.source.prim == rig.source.prim), None)
    if mesh is None:
        meshes = ", ".join(m.source.prim for m in avatar.meshes if m.source is not None)
        raise RigError("the rig's mesh is no mesh with blend shapes of this avatar", path=avatar.file,
                       prim=rig.source.prim, fix="pass a mesh of this avatar (usdface.pick_mesh(avatar)), "
                       f"the one the layout was computed on; its meshes: {meshes}")
    if mesh.n_vertices != rig.n_vertices:
        raise RigError(f"the rig has {rig.n_vertices} vertices, the avatar's mesh {mesh.n_vertices}: not "
                       f"this avatar's mesh (the rig was read from {rig.source.file or 'elsewhere'})",
                       path=avatar.file, prim=rig.source.prim,
                       fix="compute the layout on this avatar's mesh: compute_landmarks(pick_mesh(avatar))")
    vertices = np.asarray(layout.vertices, dtype=np.int64)
    if vertices.size and (vertices.min() < 0 or vertices.max() >= rig.n_vertices):
        raise RigError(f"the layout's vertex indices reach {int(vertices.max())}, the mesh has "
                       f"{rig.n_vertices} vertices: a layout of another mesh", path=avatar.file,
                       prim=rig.source.prim, fix="compute the layout on this mesh: compute_landmarks(rig)")


_author = author_landmarks  # former private name, used by usdface.io.usd_inspection
