"""The UsdSkel skeleton of an avatar, as a :class:`usdface.io.gltf.GltfSkin` (metres, Y up, column-vector
matrices): joints and parents, local rest transforms, world bind transforms and each skinned mesh's joint
influences (mapped to the skeleton's joint order, constant influences expanded per vertex).

Frames: a USD matrix ``M`` (row vectors, stage units and up axis) becomes ``C @ M.T @ inv(C)`` with
``C = stage_to_internal(up_axis, metersPerUnit)``, so that it maps internal points to internal points; at the
rest pose ``world_rest @ inv(bind_world)`` then leaves the internal neutral points where they are when rest
equals bind, as UsdSkel does. Each joint's uniform scale (a skeleton under a prim scaled 0.01) is taken out
of both its rest and bind transforms (:func:`_unscaled`): the skinning is unchanged, and neither the joint
nodes nor the inverse bind matrices are scaled (Blender's glTF importer drops that scale from its bind pose).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..model import Avatar
from .gltf import GltfSkin

__all__ = ["read_gltf_skins"]


def _to_internal(matrices, c: np.ndarray) -> np.ndarray:
    m = np.asarray([np.asarray(x, dtype=np.float64) for x in matrices]).reshape(-1, 4, 4)
    return c @ np.transpose(m, (0, 2, 1)) @ np.linalg.inv(c)


def _unscaled(rest_world: np.ndarray, bind_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``rest_world[J, 4, 4]`` and ``bind_world[J, 4, 4]`` with each joint's uniform bind scale ``s_j``
    (``cbrt(|det|)`` of its bind transform's 3 x 3) taken out of both: ``M_j @ diag(1/s_j, 1/s_j, 1/s_j,
    1)``. The skinning ``rest_j @ inv(bind_j)`` is unchanged (the factor cancels) and so are the points, but
    neither the joint nodes nor the inverse bind matrices carry the scale of a skeleton under a scaled prim
    (Blender's export: 0.01): Blender's glTF importer builds its bind pose from the inverse bind matrices
    with their scale dropped (edit bones have none) and put the 0.01 in the pose, so the mesh without its
    Armature modifier was 100 times too large; the joints' translations stay in metres."""
    scale = np.cbrt(np.abs(np.linalg.det(bind_world[:, :3, :3])))
    factor = np.where(np.isfinite(scale) & (scale > 0), 1.0 / np.where(scale > 0, scale, 1.0), 1.0)
    unscale = np.tile(np.eye(4), (len(factor), 1, 1))
    unscale[:, :3, :3] *= factor[:, None, None]
    return rest_world @ unscale, bind_world @ unscale


def _skeleton_skin(skel, query, c: np.ndarray, xf) -> GltfSkin | None:
    """One UsdSkel ``Skeleton`` (its ``SkelQuery``) as a :class:`GltfSkin` without influences, or None when
    it has no joints."""
    joints = [str(j) for j in query.GetJointOrder()]
    if not joints:
        return None
    topology = query.GetTopology()
    parents = [int(topology.GetParent(j)) for j in range(len(joints))]
    rest_world = _to_internal(query.ComputeJointWorldTransforms(xf, True), c)
    bind = skel.GetBindTransformsAttr().Get()
    # the bind transforms are in the skeleton's space (UsdSkel skins with inv(bind) @ the joints' skeleton-
    # space transforms), the joints' world transforms above include the Skeleton prim's own transform: the
    # bind transforms get it too, so a rest pose equal to the bind pose leaves the points where they are.
    # Without it, a skeleton under a scaled or turned prim (Blender's export: 0.01 and Z up) made every
    # glTF viewer draw the skinned avatar a hundredth of its size and turned 90 degrees
    skel_world = xf.GetLocalToWorldTransform(skel.GetPrim())
    bind_world = _to_internal([b * skel_world for b in bind], c) if bind else rest_world.copy()
    rest_world, bind_world = _unscaled(rest_world, bind_world)
    rest_local = np.array([rest_world[j] if p < 0 else np.linalg.inv(rest_world[p]) @ rest_world[j]
                           for j, p in enumerate(parents)])
    return GltfSkin(joints, parents, rest_local, bind_world, {}, name=str(skel.GetPrim().GetName()))


def _influences(sq, joints: list[str], n_vertices: int):
    """``(joint_indices[n, m], joint_weights[n, m])`` of a mesh's ``SkinningQuery`` in its skeleton's
    joint order (constant influences expanded per vertex), or None."""
    if not sq or not sq.HasJointInfluences():
        return None
    res = sq.ComputeJointInfluences()
    if not res:
        return None
    idx, w = res
    size = sq.GetNumInfluencesPerComponent()
    idx = np.asarray(idx, dtype=np.int64).reshape(-1, size)
    w = np.asarray(w, dtype=np.float64).reshape(-1, size)
    order = sq.GetJointOrder()
    if order:  # the mesh's own joint list -> skeleton joint indices
        remap = np.array([joints.index(str(j)) for j in order], dtype=np.int64)
        idx = remap[idx]
    if sq.IsRigidlyDeformed() or len(idx) == 1:
        idx = np.repeat(idx[:1], n_vertices, axis=0)
        w = np.repeat(w[:1], n_vertices, axis=0)
    return (idx, w) if len(idx) == n_vertices else None


def read_gltf_skins(path, avatar: Avatar, stage=None, names: dict | None = None) -> list[GltfSkin]:
    """One :class:`GltfSkin` per Skeleton with joints that skins some of ``avatar``'s meshes in the USD file
    ``path`` (or the open ``stage``), each with the influences of the meshes that Skeleton skins, keyed by
    ``names`` ``{mesh prim path: name in the glTF}`` (default: the prim's name). A shot with two SkelRoots
    (two avatars, or one referenced twice) gives two skins, each mesh skinned by its own skeleton, as
    UsdSkel binds them. Empty when no mesh is bound to a Skeleton with joints."""
    from pxr import Usd, UsdGeom, UsdSkel

    from .usd_open import quiet_stderr
    from .usd_rig import stage_to_internal

    if stage is None:
        from .usd_rig import _open_stage

        stage = _open_stage(Path(path))
    names = dict(names or {})
    sizes = {rig.source.prim: rig.n_vertices for rig in avatar.meshes if rig.source}
    sizes.update({prim: len(points)
                  for prim, (points, _) in avatar.metadata.get("static_meshes", {}).items()})
    roots = list(dict.fromkeys(rig.source.skel_root for rig in avatar.meshes
                               if rig.source and rig.source.skel_root))
    c = stage_to_internal(avatar.up_axis, avatar.meters_per_unit)
    xf = UsdGeom.XformCache(Usd.TimeCode.Default())
    cache = UsdSkel.Cache()
    predicate = Usd.TraverseInstanceProxies()
    skins: dict[str, GltfSkin] = {}
    taken: set[str] = set()
    for root_path in roots:
        root = stage.GetPrimAtPath(root_path)
        if not root:
            continue
        # UsdSkel's warnings on malformed influences: the avatar's reader kept them as notes
        with quiet_stderr():
            cache.Populate(UsdSkel.Root(root), predicate)
            bindings = cache.ComputeSkelBindings(UsdSkel.Root(root), predicate)
        for binding in bindings:
            skel = binding.GetSkeleton()
            key = str(skel.GetPath())
            if key not in skins:
                query = cache.GetSkelQuery(skel)
                made = _skeleton_skin(skel, query, c, xf) if query else None
                if made is None:
                    continue
                skins[key] = made
            skin = skins[key]
            for sq in binding.GetSkinningTargets():
                prim = str(sq.GetPrim().GetPath())
                if prim not in sizes or prim in taken:
                    continue
                with quiet_stderr():
                    found = _influences(sq, skin.joints, sizes[prim])
                if found is not None:
                    skin.influences[names.get(prim, prim.rsplit("/", 1)[-1])] = found
                    taken.add(prim)
    out = {path: skin for path, skin in skins.items() if skin.influences}
    if len({skin.name for skin in out.values()}) < len(out):     # two avatars' "Skel": named by prim path
        for path, skin in out.items():
            skin.name = path.strip("/").replace("/", "_")
    return list(out.values())
