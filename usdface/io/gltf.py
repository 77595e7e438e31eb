"""glTF 2.0 export (``.glb`` binary or ``.gltf`` with the data embedded) of face rigs, and a reader.

Written with pygltflib (the container: JSON, buffers, GLB chunks); this module only lays out the arrays:

* one glTF mesh per rig, one triangle primitive: ``POSITION`` (float32, metres, Y up, the internal frame
  usdface reads avatars into, which is glTF's), ``NORMAL`` (the mesh's authored normals when it has some,
  split at a hard edge as at a UV seam; else area-weighted vertex normals of the neutral; +Z at a vertex no
  triangle of any area touches, which has none) and ``indices`` (uint16 or uint32);
* one morph target per shape: ``POSITION`` deltas (float32) and (unless ``morph_normals=False``) ``NORMAL``
  deltas (the shape's authored
  ``normalOffsets`` when it has some, else the area-weighted vertex normals of the neutral plus the shape,
  minus the neutral's: an engine adds them, weighted as the positions, and normalises, so a shape is shaded
  as posed and not with the neutral's normals), each stored as a
  *sparse* accessor (the changed vertices only: indices + values, zeros elsewhere) unless dense is smaller;
  the target names in
  ``mesh.extras.targetNames`` (the convention three.js, Babylon.js, Unity glTFast and Blender read), default
  ``mesh.weights`` all 0;
* ``TEXCOORD_0`` when the avatar's mesh has texture coordinates (its ``st`` primvar), the points split into
  one vertex per distinct (point, coordinates) pair, as glTF has one value per vertex (a point on a UV seam
  becomes two vertices with its position, normal, offsets and joints);
* meshes without shapes (eyes bound to the skeleton only) as plain meshes;
* optionally skins, one per skeleton: joint nodes (local rest transforms), ``inverseBindMatrices`` and
  per-vertex ``JOINTS_0`` / ``WEIGHTS_0`` (:class:`GltfSkin`); with several, each skeleton's joints under a
  node of its name.

Arrays: ``neutral[n, 3]`` metres, ``triangles[t, 3]``, ``deltas[K, n, 3]`` metres. Every written value is the
float32 rounding of the input, so :func:`read_gltf` gives back ``float32(neutral)`` and ``float32(deltas)``
exactly.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import GeometryError, InputFileError

__all__ = ["GltfSkin", "write_gltf", "read_gltf", "GLTF_EXTENSIONS"]

#: File extensions :func:`write_gltf` accepts (binary GLB, or JSON with base64-embedded buffers).
GLTF_EXTENSIONS = (".glb", ".gltf")

_FLOAT, _U16, _U32, _U8 = 5126, 5123, 5125, 5121
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


@dataclass
class GltfSkin:
    """A skeleton for glTF: ``joints[J]`` names with ``parents[J]`` (-1 = root), ``rest_local[J, 4, 4]`` the
    joints' local rest transforms and ``bind_world[J, 4, 4]`` their world bind transforms (column-vector
    matrices, metres, Y up); ``influences`` {mesh name: (joint_indices[n, m], joint_weights[n, m])}."""

    joints: list[str]
    parents: list[int]
    rest_local: np.ndarray
    bind_world: np.ndarray
    influences: dict = field(default_factory=dict)
    name: str = "Skeleton"


class _Blob:
    """The binary buffer being assembled: each array gets its own 4-byte aligned bufferView."""

    def __init__(self, gltf):
        self.gltf = gltf
        self.data = bytearray()

    def view(self, array: np.ndarray, target: int | None = None) -> int:
        import pygltflib

        raw = np.ascontiguousarray(array).tobytes()
        while len(self.data) % 4:
            self.data.append(0)
        self.gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=len(self.data),
                                                          byteLength=len(raw), target=target))
        self.data.extend(raw)
        return len(self.gltf.bufferViews) - 1

    def accessor(self, array: np.ndarray, kind: str, *, target: int | None = None,
                 bounds: bool = False) -> int:
        import pygltflib

        array = np.asarray(array)
        comp = {np.dtype(np.float32): _FLOAT, np.dtype(np.uint16): _U16, np.dtype(np.uint32): _U32,
                np.dtype(np.uint8): _U8}[array.dtype]
        acc = pygltflib.Accessor(bufferView=self.view(array, target), componentType=comp,
                                 count=int(array.shape[0]), type=kind)
        if bounds:
            acc.min = np.atleast_1d(array.min(axis=0)).astype(float).tolist()
            acc.max = np.atleast_1d(array.max(axis=0)).astype(float).tolist()
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1

    def target(self, delta: np.ndarray) -> int:
        """A morph target's POSITION or NORMAL accessor: sparse (changed vertices only) unless dense is
        smaller."""
        import pygltflib

        n = delta.shape[0]
        moved = np.flatnonzero(np.any(delta != 0.0, axis=1))
        lo = delta.min(axis=0).astype(float).tolist() if n else [0.0] * 3
        hi = delta.max(axis=0).astype(float).tolist() if n else [0.0] * 3
        if moved.size * 16 >= n * 12:  # dense is no larger
            acc = pygltflib.Accessor(bufferView=self.view(delta, _ARRAY_BUFFER), componentType=_FLOAT,
                                     count=n, type="VEC3", min=lo, max=hi)
        elif moved.size == 0:  # no bufferView and no sparse: all zeros
            acc = pygltflib.Accessor(componentType=_FLOAT, count=n, type="VEC3", min=lo, max=hi)
        else:
            idx = moved.astype(np.uint16 if n <= 65535 else np.uint32)
            sparse = pygltflib.Sparse(
                count=int(moved.size),
                indices=pygltflib.AccessorSparseIndices(bufferView=self.view(idx), componentType=(
                    _U16 if idx.dtype == np.uint16 else _U32)),
                values=pygltflib.AccessorSparseValues(bufferView=self.view(delta[moved])))
            acc = pygltflib.Accessor(componentType=_FLOAT, count=n, type="VEC3", min=lo, max=hi,
                                     sparse=sparse)
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1


#: The normal given to a vertex no triangle of any area touches (a loose vertex, one among degenerate
#: triangles only): glTF requires unit normals (the Khronos validator's ACCESSOR_NON_UNIT error, and engines
#: normalise a zero normal into NaN), and such a vertex has no direction of its own; +Z is glTF's front.
UNDEFINED_NORMAL = np.array([0.0, 0.0, 1.0])


def _unit_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals ``[n, 3]``, :data:`UNDEFINED_NORMAL` where there is none."""
    from ..mesh import vertex_normals

    normals = vertex_normals(points, triangles)
    normals[~np.any(normals, axis=1)] = UNDEFINED_NORMAL
    return normals


def _split_at_seams(triangles: np.ndarray, corner_values: np.ndarray, n: int):
    """glTF's one value per vertex from values per triangle corner (``corner_values[t, 3, w]``: texture
    coordinates, authored normals, side by side): one vertex per distinct (point, values) pair, so a point
    on a UV seam or a hard edge becomes as many vertices as it has values there. Returns ``(point[m],
    triangles[t, 3] over the new vertices, values[m, w])``; every new vertex of ``point[i]`` takes that
    point's position, offsets and joints. Points no triangle uses stay, with NaN values."""
    corner_values = np.asarray(corner_values, dtype=np.float64)
    width = corner_values.shape[-1]
    rows = np.column_stack([triangles.reshape(-1).astype(np.float64), corner_values.reshape(-1, width)])
    unique, inverse = np.unique(rows, axis=0, return_inverse=True)
    loose = np.setdiff1d(np.arange(n), triangles)
    point = np.concatenate([unique[:, 0].astype(np.int64), loose])
    values = np.vstack([unique[:, 1:], np.full((len(loose), width), np.nan)])
    return point, np.asarray(inverse).reshape(-1, 3), values


def _normal_delta(neutral, triangles, delta, computed, given) -> np.ndarray:
    """A shape's ``NORMAL`` target per point: its authored normal offsets ``given`` when there are some,
    else the posed area-weighted normals minus the neutral's ``computed``."""
    if given is not None:
        return np.asarray(given, dtype=np.float64)
    return _unit_normals(neutral + delta, triangles) - computed


def _check(rigs) -> None:
    for rig in rigs:
        p = np.asarray(rig.neutral)
        if p.ndim != 2 or p.shape[1] != 3 or not len(p):
            raise GeometryError(f"mesh {rig.name!r}: no vertices", fix="export an avatar with meshes")
        if not np.isfinite(p).all() or not np.isfinite(np.asarray(rig.deltas)).all():
            raise GeometryError(f"mesh {rig.name!r}: NaN or infinite points or offsets",
                                fix="repair the avatar first")


def _skin(gltf, blob: _Blob, skin: GltfSkin, root_children: list[int]) -> int:
    import pygltflib

    first = len(gltf.nodes)
    for j, name in enumerate(skin.joints):
        matrix = np.asarray(skin.rest_local[j], dtype=float).T.ravel().tolist()  # glTF: column-major
        gltf.nodes.append(pygltflib.Node(name=name.rsplit("/", 1)[-1], matrix=matrix))
    for j, parent in enumerate(skin.parents):
        if parent < 0:
            root_children.append(first + j)
        else:
            gltf.nodes[first + parent].children.append(first + j)
    inverse = np.linalg.inv(np.asarray(skin.bind_world, dtype=np.float64))
    ibm = np.ascontiguousarray(np.transpose(inverse, (0, 2, 1)).reshape(-1, 16), dtype=np.float32)
    gltf.skins.append(pygltflib.Skin(name=skin.name, joints=list(range(first, first + len(skin.joints))),
                                     inverseBindMatrices=blob.accessor(ibm, "MAT4"),
                                     skeleton=first + skin.parents.index(-1)))
    return len(gltf.skins) - 1


def _joints_attributes(blob: _Blob, indices: np.ndarray, weights: np.ndarray) -> tuple[int, int]:
    """JOINTS_0 / WEIGHTS_0 from per-vertex influences [n, m]: the 4 largest, renormalised."""
    indices = np.asarray(indices, dtype=np.int64)
    weights = np.asarray(weights, dtype=np.float64)
    if indices.shape[1] < 4:
        pad = 4 - indices.shape[1]
        indices = np.pad(indices, ((0, 0), (0, pad)))
        weights = np.pad(weights, ((0, 0), (0, pad)))
    order = np.argsort(-weights, axis=1)[:, :4]
    w = np.take_along_axis(weights, order, axis=1)
    j = np.take_along_axis(indices, order, axis=1)
    total = w.sum(axis=1, keepdims=True)
    w = np.where(total > 0, w / np.where(total > 0, total, 1.0), np.array([1.0, 0, 0, 0]))
    j = np.where(w > 0, j, 0)
    jt = np.uint8 if j.max(initial=0) < 256 else np.uint16
    return (blob.accessor(j.astype(jt), "VEC4", target=_ARRAY_BUFFER),
            blob.accessor(w.astype(np.float32), "VEC4", target=_ARRAY_BUFFER))


def write_gltf(path, rigs, *, skin: GltfSkin | list[GltfSkin] | None = None, root_name: str = "Avatar",
               extras: dict | None = None, node_extras: dict | None = None, texcoords: dict | None = None,
               normals: dict | None = None, target_normals: dict | None = None, morph_normals: bool = True,
               force: bool = False) -> Path:
    """Write ``rigs`` (:class:`usdface.model.FaceRig`, shapes or none) as one glTF 2.0 scene: a root node
    ``root_name`` with the joints of each ``skin`` (one :class:`GltfSkin`, or a list: one glTF skin per
    skeleton, each mesh skinned by the skin whose ``influences`` name it, the first that does) and the meshes
    no skin names, each skinned mesh a root node of
    the scene beside it (glTF places a skinned mesh by its joints alone, and the Khronos validator warns of a
    skinned mesh under a parent), morph targets as described in the module doc. ``.glb``: binary; ``.gltf``:
    JSON with the buffer embedded as a data URI. ``extras`` go to the scene's ``extras``; ``node_extras`` to
    the root node's and every mesh node's (Blender's importer makes node extras object custom properties,
    which its USD exporter writes as ``userProperties:<key>``, where the scene's are lost). ``texcoords``
    ``{rig name: uv[t, 3, 2]}`` per triangle corner (:func:`usdface.io.usd_texcoords.read_texcoords`) become
    ``TEXCOORD_0``, the vertices split where their corners' coordinates differ (:func:`_split_at_seams`).
    ``normals`` ``{rig name: normals[t, 3, 3]}`` per triangle corner (the mesh's authored normals, unit, NaN
    where a corner has none: :func:`usdface.io.usd_texcoords.read_normals`) are its ``NORMAL`` instead of the
    computed ones, the vertices split where they differ (a hard edge); ``target_normals`` ``{rig name: [K]
    per-point normal offsets[n, 3] or None}`` (the shapes' ``normalOffsets``,
    :func:`usdface.io.usd_texcoords.normal_offsets`) are the targets' ``NORMAL`` deltas where given.
    ``morph_normals=False``: the targets carry ``POSITION`` deltas only (about half the file; an engine that
    recomputes a posed mesh's normals, or shades the shapes with the neutral's, needs no more).
    Returns the path written (atomically; an existing file needs ``force``)."""
    import pygltflib

    from .. import __version__
    from .atomic import atomic_file, refuse_existing

    path = Path(path)
    if path.suffix.lower() not in GLTF_EXTENSIONS:
        raise InputFileError("a glTF output must end in .glb or .gltf", path=path,
                             fix="name it e.g. avatar.glb")
    refuse_existing(path, force)
    rigs = list(rigs)
    _check(rigs)
    gltf = pygltflib.GLTF2(asset=pygltflib.Asset(version="2.0", generator=f"usdface {__version__}"))
    blob = _Blob(gltf)
    gltf.nodes.append(pygltflib.Node(name=root_name, extras=dict(node_extras or {})))
    root_children: list[int] = []
    scene_nodes = [0]       # the root, and the skinned meshes: glTF skins them by the joints alone, so the
    #                         Khronos validator warns of a parent (NODE_SKINNED_MESH_NON_ROOT)
    skins = [] if skin is None else [skin] if isinstance(skin, GltfSkin) else list(skin)
    skin_of = {}                                            # mesh name -> (glTF skin index, GltfSkin)
    for one in skins:
        parent = root_children
        if len(skins) > 1:   # a node per skeleton holding its joints: Blender's importer makes an armature
            gltf.nodes.append(pygltflib.Node(name=one.name))   # of each (of all in one, joints side by side)
            root_children.append(len(gltf.nodes) - 1)
            parent = gltf.nodes[-1].children
        index = _skin(gltf, blob, one, parent)
        for name in one.influences:
            skin_of.setdefault(name, (index, one))
    for rig in rigs:
        tris = np.asarray(rig.triangles, dtype=np.int64)
        computed = _unit_normals(rig.neutral, tris)         # on the mesh as authored: no seams in the shading
        uv = (texcoords or {}).get(rig.name)
        corner_normals = (normals or {}).get(rig.name)
        if corner_normals is not None:                      # a corner without a direction: the computed one
            corner_normals = np.where(np.isnan(corner_normals), computed[tris], corner_normals)
        if uv is not None or corner_normals is not None:
            parts = [np.asarray(a, dtype=np.float64) for a in (uv, corner_normals) if a is not None]
            keep, tris_out, values = _split_at_seams(tris, np.concatenate(parts, axis=-1), len(rig.neutral))
            if uv is not None:
                uv = np.nan_to_num(values[:, :2])
            vertex_normals = computed[keep]
            if corner_normals is not None:
                authored = values[:, -3:]
                vertex_normals = np.where(np.isnan(authored), vertex_normals, authored)
        else:
            keep, tris_out, vertex_normals = slice(None), tris, computed
        neutral = np.asarray(rig.neutral, dtype=np.float32)[keep]
        itype = np.uint16 if len(neutral) <= 65535 else np.uint32
        attrs = pygltflib.Attributes(
            POSITION=blob.accessor(neutral, "VEC3", target=_ARRAY_BUFFER, bounds=True),
            NORMAL=blob.accessor(vertex_normals.astype(np.float32), "VEC3", target=_ARRAY_BUFFER))
        if uv is not None:                                  # glTF's v runs down the image, USD's t up
            attrs.TEXCOORD_0 = blob.accessor(np.column_stack([uv[:, 0], 1.0 - uv[:, 1]]).astype(np.float32),
                                             "VEC2", target=_ARRAY_BUFFER)
        skin_index, owner = skin_of.get(rig.name, (None, None))
        if owner is not None:
            joints, weights = owner.influences[rig.name]
            attrs.JOINTS_0, attrs.WEIGHTS_0 = _joints_attributes(blob, np.asarray(joints)[keep],
                                                                 np.asarray(weights)[keep])
        deltas = np.asarray(rig.deltas, dtype=np.float64)
        offsets = (target_normals or {}).get(rig.name) or [None] * len(deltas)
        targets = [{"POSITION": blob.target(d[keep].astype(np.float32))} | (
                   {"NORMAL": blob.target(_normal_delta(rig.neutral, tris, d, computed, given)[keep]
                                          .astype(np.float32))} if morph_normals else {})
                   for d, given in zip(deltas, offsets, strict=True)]
        prim = pygltflib.Primitive(attributes=attrs, indices=blob.accessor(
            tris_out.ravel().astype(itype), "SCALAR", target=_ELEMENT_ARRAY_BUFFER, bounds=True), mode=4,
            targets=targets or None)
        mesh = pygltflib.Mesh(name=rig.name, primitives=[prim])
        if rig.n_shapes:
            mesh.weights = [0.0] * rig.n_shapes
            mesh.extras = {"targetNames": list(rig.names)}
        gltf.meshes.append(mesh)
        node = pygltflib.Node(name=rig.name, mesh=len(gltf.meshes) - 1, extras=dict(node_extras or {}))
        gltf.nodes.append(node)
        if skin_index is not None:
            node.skin = skin_index
            scene_nodes.append(len(gltf.nodes) - 1)
        else:
            root_children.append(len(gltf.nodes) - 1)
    gltf.nodes[0].children = root_children
    gltf.scenes = [pygltflib.Scene(name=root_name, nodes=scene_nodes, extras=dict(extras or {}))]
    gltf.scene = 0
    gltf.buffers = [pygltflib.Buffer(byteLength=len(blob.data))]
    gltf.set_binary_blob(bytes(blob.data))
    with atomic_file(path, force=force) as tmp:
        if path.suffix.lower() == ".glb":
            gltf.save_binary(str(tmp))
        else:
            gltf.convert_buffers(pygltflib.BufferFormat.DATAURI)
            gltf.save_json(str(tmp))
    return path


_DTYPES = {_FLOAT: np.float32, _U16: np.uint16, _U32: np.uint32, _U8: np.uint8, 5121: np.uint8,
           5122: np.int16, 5120: np.int8}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def _read_accessor(gltf, blob: bytes, index: int) -> np.ndarray:
    acc = gltf.accessors[index]
    width = _WIDTH[acc.type]
    dtype = _DTYPES[acc.componentType]

    def view(view_index, count, dt, w, offset=0):
        bv = gltf.bufferViews[view_index]
        start = (bv.byteOffset or 0) + (offset or 0)
        if bv.byteStride and bv.byteStride != np.dtype(dt).itemsize * w:
            raise InputFileError("interleaved glTF buffer views are not supported", fix="re-export unpacked")
        return np.frombuffer(blob, dtype=dt, count=count * w, offset=start).reshape(count, w)

    out = (view(acc.bufferView, acc.count, dtype, width, acc.byteOffset).copy() if acc.bufferView is not None
           else np.zeros((acc.count, width), dtype=dtype))
    if acc.sparse is not None and acc.sparse.count:
        sp = acc.sparse
        idx = view(sp.indices.bufferView, sp.count, _DTYPES[sp.indices.componentType], 1,
                   sp.indices.byteOffset).ravel().astype(np.int64)
        out[idx] = view(sp.values.bufferView, sp.count, dtype, width, sp.values.byteOffset)
    return out if width > 1 else out.ravel()


def _target(t, attribute: str = "POSITION") -> int | None:
    return t.get(attribute) if isinstance(t, dict) else getattr(t, attribute, None)


def read_gltf(path) -> dict:
    """Read a glTF written by :func:`write_gltf` (or any glTF with plain triangle primitives) back into
    arrays: {mesh name: {"positions": float32[n, 3], "normals", "indices": [t, 3], "target_names": [K],
    "targets": float32[K, n, 3], "target_normals": float32[K, n, 3] (when the targets have NORMAL),
    "texcoords": float32[n, 2] (glTF's, v down), "joints", "weights" (when skinned)}} for the first
    primitive of each mesh."""
    import pygltflib

    path = Path(path)
    if not path.is_file():
        raise InputFileError("glTF file not found", path=path, fix="check the path")
    gltf = pygltflib.GLTF2().load(str(path))
    if gltf is None:
        raise InputFileError("not a glTF file", path=path, fix="pass a .glb or .gltf")
    blob = gltf.binary_blob()
    if blob is None and gltf.buffers and gltf.buffers[0].uri:
        blob = gltf.get_data_from_buffer_uri(gltf.buffers[0].uri)
    out = {}
    for mesh in gltf.meshes:
        prim = mesh.primitives[0]
        a = prim.attributes
        positions = _read_accessor(gltf, blob, a.POSITION)
        entry = {"positions": positions,
                 "indices": _read_accessor(gltf, blob, prim.indices).reshape(-1, 3).astype(np.int64),
                 "target_names": list((mesh.extras or {}).get("targetNames", [])),
                 "targets": np.stack([_read_accessor(gltf, blob, _target(t)) for t in prim.targets])
                 if prim.targets else np.zeros((0, len(positions), 3), dtype=np.float32)}
        if a.NORMAL is not None:
            entry["normals"] = _read_accessor(gltf, blob, a.NORMAL)
        if prim.targets and all(_target(t, "NORMAL") is not None for t in prim.targets):
            entry["target_normals"] = np.stack([_read_accessor(gltf, blob, _target(t, "NORMAL"))
                                                for t in prim.targets])
        if a.TEXCOORD_0 is not None:
            entry["texcoords"] = _read_accessor(gltf, blob, a.TEXCOORD_0)
        if a.JOINTS_0 is not None:
            entry["joints"] = _read_accessor(gltf, blob, a.JOINTS_0)
            entry["weights"] = _read_accessor(gltf, blob, a.WEIGHTS_0)
        out[mesh.name] = entry
    return out
