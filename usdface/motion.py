"""How much blend shapes move each vertex, and which vertices move at all (pure numpy).

Computed once per rig and passed on: on a production mesh (225k vertices x 51 shapes) every norm over the
dense offsets costs 0.1-0.2 s, and the pipeline used to take it a dozen times.

* :func:`shape_norms` - ``|deltas[k,v]|`` ``[K,n]``;
* :func:`peak_motion` - the largest motion of each vertex over the shapes, ``[n]``;
* :func:`moving_vertices` - the vertices some shape moves, with a tolerance: float noise of a DCC export
  (offsets re-stored in float32 around head-sized coordinates) is not motion;
* :func:`meshes_by_motion` - the meshes by how many vertices their named shapes move, the most first (the
  first is an avatar's face mesh);
* :func:`refuse_several_characters` - refuse a stage holding several characters' face rigs (a shot), where
  no one face mesh is to be picked (personalize, check, landmarks, render);
* :func:`shape_changes` - how far one set of shapes moves each vertex from another (RMS over shapes), and
  each shape's largest change: the personalization's heat map (``--inspect``, ``review``, ``render``).

Units: whatever the deltas are in (metres in usdface).
"""

from __future__ import annotations

import numpy as np

__all__ = ["MOVING_TOLERANCE", "FLOAT32_NOISE", "shape_norms", "peak_motion", "moving_vertices",
           "shape_changes"]

#: A vertex moves when some shape moves it by more than this fraction of the mesh's largest motion ...
MOVING_TOLERANCE = 1e-6
#: ... and by more than this many float32 steps of its coordinates (an offset stored in float32 next to
#: coordinates of size c is only known to about 1.2e-7 c).
FLOAT32_NOISE = 8 * float(np.finfo(np.float32).eps)


def shape_norms(deltas) -> np.ndarray:
    """``[K,n]`` length of every shape's offset at every vertex (``deltas[K,n,3]``)."""
    d = np.asarray(deltas, dtype=np.float64)
    return np.sqrt(np.einsum("knc,knc->kn", d, d))


def peak_motion(deltas) -> np.ndarray:
    """``[n]`` the largest offset of each vertex over the shapes (``deltas[K,n,3]``; zeros for K = 0)."""
    d = np.asarray(deltas, dtype=np.float64)
    square = np.zeros(d.shape[1])
    for k in range(d.shape[0]):                      # shape by shape: no [K,n] temporary (92 MB at 225k x 51)
        np.maximum(square, np.einsum("nc,nc->n", d[k], d[k]), out=square)
    return np.sqrt(square)


def moving_vertices(peak, points=None, *, tolerance: float = MOVING_TOLERANCE) -> np.ndarray:
    """``[n]`` bool: the vertices whose ``peak`` motion (:func:`peak_motion`) exceeds ``tolerance`` of the
    largest and, given the rest ``points[n,3]``, the float32 noise of coordinates that size."""
    peak = np.asarray(peak, dtype=np.float64)
    if peak.size == 0:
        return np.zeros(0, dtype=bool)
    floor = tolerance * float(peak.max())
    if points is not None and len(points):
        floor = max(floor, FLOAT32_NOISE * float(np.abs(np.asarray(points, dtype=np.float64)).max()))
    return peak > floor


def meshes_by_motion(meshes, names) -> list:
    """``[(rig, moving vertices)]`` of the ``meshes`` (:class:`usdface.model.FaceRig`) whose shapes named in
    ``names`` move any vertex (:func:`moving_vertices`: float noise of an export is not motion), most moving
    first, ties in the meshes' order."""
    counted = []
    for rig in meshes:
        idx = [rig.index(n) for n in names if n in rig.names]
        if not idx:
            continue
        # all the rig's shapes: its peak motion, computed once (:meth:`usdface.model.FaceRig.peak_motion`)
        peak = rig.peak_motion() if len(set(idx)) == len(rig.deltas) else peak_motion(rig.deltas[idx])
        moving = int(moving_vertices(peak, rig.neutral).sum())
        if moving:
            counted.append((rig, moving))
    return sorted(counted, key=lambda pair: -pair[1])                  # stable: ties in order


#: What the refusal of several characters tells personalize's caller to do besides naming the face mesh.
OWN_AVATAR = "; or personalize the character's own avatar asset and reference the layer in the shot"


def several_characters(ranked) -> dict:
    """``{SkelRoot path: face mesh prim}`` of the characters in ``ranked`` (:func:`meshes_by_motion` of an
    avatar's meshes), the first (most moving) one's first, when there are several; ``{}`` for one character.
    Another character is another SkelRoot whose most moving mesh lies apart from the first's face mesh
    (bounding boxes disjoint): a rig split into several SkelRoots around one head (Blender writes one per mesh
    with shape keys and no armature: teeth, lashes) overlaps the head and is one character."""
    if not ranked:
        return {}
    face = ranked[0][0]
    root = face.source.skel_root if face.source is not None else None
    lo, hi = face.neutral.min(axis=0), face.neutral.max(axis=0)
    others: dict = {}
    for rig, _ in ranked[1:]:
        other = rig.source.skel_root if rig.source is not None else None
        if not other or not root or other == root or other in others:
            continue
        olo, ohi = rig.neutral.min(axis=0), rig.neutral.max(axis=0)
        apart = bool(np.any(olo > hi) or np.any(ohi < lo))
        others[other] = rig.source.prim if apart else None
    apart = {r: prim for r, prim in others.items() if prim}
    return {root: face.source.prim, **apart} if apart else {}


def refuse_several_characters(avatar, ranked, option: str = "--face-mesh (face_mesh=)",
                              also: str = OWN_AVATAR) -> None:
    """A stage with several characters (a shot with the hero and an extra, one avatar referenced twice side
    by side) has no one face mesh to pick: until stop 45 the mesh the shapes move most was taken, the first
    in the file on a tie, and the person's shapes went to whichever character that was, without a word.
    Refused (:class:`~usdface.errors.RigError`) naming each character's face mesh, so the TD says which with
    ``option`` (personalize's ``--face-mesh``, ``landmarks``/``render``'s ``--mesh``); ``also`` ends the fix.
    The one test personalize, ``check`` (rule ``Readable``), ``landmarks`` and ``render`` make
    (:func:`several_characters`)."""
    found = several_characters(ranked)
    if found:
        from .errors import RigError

        roots, prims = list(found), list(found.values())
        raise RigError(f"the stage holds {len(found)} characters' face rigs (SkelRoots {', '.join(roots)}): "
                       "which one is the person's is not for usdface to guess", path=avatar.file,
                       prim=roots[0],
                       fix=f"name the face mesh with {option}: one of {', '.join(prims)}{also}")


def shape_changes(personalized, generic) -> tuple[np.ndarray, np.ndarray]:
    """``(rms[n], largest[K])``: per vertex the RMS over shapes of ``|personalized - generic|`` and per shape
    the largest vertex change (metres), for offsets ``[K, n, 3]``; shape by shape (the whole difference,
    its squares and norms at once were ~1 GB of temporaries on a 225k-vertex head's review)."""
    K = len(personalized)
    n = len(personalized[0]) if K else 0
    total, largest = np.zeros(n), np.zeros(K)
    for k in range(K):
        d = np.asarray(personalized[k], dtype=np.float64) - generic[k]
        sq = np.einsum("ij,ij->i", d, d)
        total += sq
        largest[k] = np.sqrt(sq.max()) if n else 0.0
    return np.sqrt(total / max(K, 1)), largest
