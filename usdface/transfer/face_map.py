"""The correspondence of the capture mesh onto the avatar's face mesh as ``usdface personalize`` forms it:
guided by what the shapes do (:data:`SEMANTIC_SHAPES` posed by their motion's length, :func:`semantic_poses`),
registered from the template's neutral or the person's, whichever lies closer to the avatar
(:func:`choose_source`), cached per avatar face, template and neutral (:func:`cached_correspondence`), checked
for the shapes' meaning (:func:`correspondence_semantics`: lips and lids on the right side), and the face
mesh's pieces within the capture's reach (:func:`reached_parts`). The registration and the map themselves are
:mod:`.register` and :mod:`.correspond`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..model import Capture, FaceRig
from .correspond import (
    PosedSurface,
    correspondence_map,
    correspondence_npz,
    geometry_digest,
    load_correspondence,
    nonrigid_register,
    save_correspondence,
)
from .register import register_face

__all__ = ["SEMANTIC_SHAPES", "REACH", "semantic_poses", "pose_by_length", "cached_correspondence",
           "choose_source", "reached_parts", "rough_placement", "corr_transform", "correspondence_semantics",
           "opening_direction", "opening_side"]

#: Shapes whose poses guide the correspondence: they open what the neutral keeps shut (the lips, the lids).
SEMANTIC_SHAPES = ("jawOpen", "eyeBlinkLeft", "eyeBlinkRight")


def semantic_poses(names, template_deltas, avatar_deltas, transform=None) -> tuple[list, list]:
    """The ``(capture_deltas[n,3], avatar_deltas[m,3])`` pairs of :data:`SEMANTIC_SHAPES` both rigs move,
    the capture side in the avatar frame (``transform``). Only where and how much each side moves is used,
    not the direction: each vertex moves by its own motion's length, scaled to the avatar shape's peak motion
    (two artists' amplitudes differ), along one common direction, the avatar's motion-weighted mean
    (:func:`pose_by_length`). A posed lower lip is then centimetres from the upper lip on both rigs, while a
    template ``jawOpen`` hinged or tilted otherwise than the avatar's (another artist's) does not drag the
    jaw line's correspondence sideways to where the two artists' directions happen to agree.
    Returns ``(pairs, names)``."""
    pairs, used = [], []
    for name in SEMANTIC_SHAPES:
        if name not in names:
            continue
        j = names.index(name)
        t = np.asarray(template_deltas[j], dtype=np.float64)
        if transform is not None:
            t = transform.apply_vectors(t)
        a = np.asarray(avatar_deltas[j], dtype=np.float64)
        pair = pose_by_length(t, a)
        if pair is None:
            continue
        pairs.append(pair)
        used.append(name)
    return pairs, used


def pose_by_length(template_delta, avatar_delta):
    """``(template[n,3], avatar[m,3])``: one shape of the two rigs as the semantic pose of the
    correspondence, each vertex moved by its motion's length (the template's scaled to the avatar's peak)
    along the avatar's motion-weighted mean direction (m); None when either side does not move."""
    lt = np.linalg.norm(template_delta, axis=1)
    la = np.linalg.norm(avatar_delta, axis=1)
    pt, pa = float(lt.max(initial=0.0)), float(la.max(initial=0.0))
    direction = opening_direction(avatar_delta)
    if pt <= 0 or pa <= 0 or not direction.any():
        return None
    return (lt * (pa / pt))[:, None] * direction, la[:, None] * direction


def cached_correspondence(face: FaceRig, capture: Capture, template_deltas, avatar_deltas, cache, names=(),
                    initial=None, target=None, source_triangles: bool = True, avatar_peak=None,
                    avatar_landmarks=None, surfaces: dict | None = None, pending: list | None = None,
                    person=None):
    """The correspondence (:func:`correspondence_map`), from the ``cache`` file when it holds this avatar face
    and template's (and, with ``source_triangles``, the face triangles' source triangles); written there
    otherwise. ``avatar_peak``, ``avatar_landmarks``: the face's peak motion and motion landmarks, for
    :func:`register_face`. ``surfaces``: a dict
    that receives the posed avatar face surface the registration built (``"avatar"``, a
    :class:`PosedSurface`), for the avatar's shapes on the capture
    (:func:`.implant.avatar_shapes_on_capture`); it may hold the face surface the person was registered
    onto (``"face"``, :func:`.register.face_surface`), which the template's registration reuses and which
    is taken out of it (released) before the non-rigid step builds its own scenes.
    ``pending``: a list that receives ``(cache, npz bytes)`` instead of the cache being written now, for a
    caller that writes it only once its run succeeds (a run that failed after this step left its cache
    behind, with the folder made for it).

    ``person``: ``(neutral[n,3], registration)``, the person's neutral on the capture topology and its
    :func:`register_face` result (``initial`` is its similarity). The map is registered from whichever of the
    two capture-topology faces, the template's neutral or the person's, lies closer to the avatar face after
    the similarity (:func:`choose_source`): both index the same points of a face (the capture mesh's vertex
    ``i`` is one landmark on every face it shows), so either gives the anatomical correspondence, and the
    closer one leaves the non-rigid step less to slide. For an avatar of the person (a digital double, the
    bench cases) that is the person's scan: 2.5-3.7x less residual than the template on dev1-dev3."""
    names = list(names)
    sem = [n for n in SEMANTIC_SHAPES if n in names]
    key = geometry_digest(face.neutral, face.triangles, capture.template.neutral, capture.triangles,
                          *[template_deltas[names.index(n)] for n in sem],
                          *[avatar_deltas[names.index(n)] for n in sem],
                          *([person[0]] if person is not None else []))
    stale = False
    face_query = surfaces.pop("face", None) if surfaces is not None else None
    if cache is not None:
        corr = load_correspondence(cache, key)
        if corr is not None and (corr.source_triangle is not None or not source_triangles):
            corr.info = {**(corr.info or {}), "cache": "hit"}
            return corr
        # rewritten: a cache of another avatar face / template (or version), or this one's without the face
        # triangles' source triangles a deformation-transfer mode needs ("extended")
        stale = "extended" if corr is not None else Path(cache).exists()
    reg_t = register_face(capture.template.neutral, template_deltas, face.neutral, avatar_deltas,
                          avatar_triangles=face.triangles, capture_triangles=capture.triangles,
                          path=capture.source or None, initial=initial, target=target,
                          avatar_peak=avatar_peak, avatar_landmarks=avatar_landmarks, surface=face_query)
    del face_query                            # its scene (the face's triangles) before the posed surfaces'
    source, reg_s = choose_source(reg_t, person)
    placed = reg_s.transform.apply(person[0] if source == "person" else capture.template.neutral)
    poses, used = semantic_poses(names, template_deltas, avatar_deltas, reg_s.transform)
    surface = PosedSurface(face.neutral, face.triangles, [p[1] for p in poses])
    if surfaces is not None:
        surfaces["avatar"] = surface
    registered, nr_info = nonrigid_register(placed, capture.triangles, face.neutral, face.triangles,
                                            poses=poses, surface=surface)
    del surface
    corr = correspondence_map(registered, capture.triangles, face.neutral, face.triangles, poses=poses,
                              source_triangles=source_triangles)
    corr.registered = registered
    nr_info["semantic_shapes"] = ",".join(used)
    corr.key = key
    corr.info = {**corr.info, **nr_info, "source": source, "template_registration": reg_t.as_dict(),
                 "placement": reg_s.as_dict(),
                 "cache": stale if isinstance(stale, str) else "replaced" if stale
                 else "miss" if cache is not None else "off"}
    if cache is not None and pending is not None:
        pending.append((cache, correspondence_npz(corr)))
    elif cache is not None:
        save_correspondence(corr, cache)
    return corr


#: A separate piece of the face mesh is within the capture's reach when some vertex of it lies within this
#: share of the placed capture's diagonal of a capture vertex: the registration's first (widest) ICP
#: correspondence distance (:func:`.register.register_icp`).
REACH = 0.08


def reached_parts(points, triangles, placed, *, reach: float = REACH):
    """``keep[m]`` bool: the face mesh's connected pieces the capture reaches, or None when it reaches every
    piece (one connected head).

    ``points[m,3]``, ``triangles[t,3]`` the face mesh (as held: its moving part and margin), ``placed[q,3]``
    the capture placed on it (or a function returning it, called only for a mesh in several pieces). A
    connected piece none of whose vertices is within ``reach`` x the capture's
    diagonal of a capture vertex (a body merged into the head's mesh, whose neck the jaw moves) cannot say
    where the capture lies, and its triangles must not take part in the face's closest-point queries."""
    from ..mesh import distances_within, vertex_components

    p = np.asarray(points, dtype=np.float64)
    count, label = vertex_components(triangles, len(p))
    if count < 2:
        return None
    q = np.asarray(placed() if callable(placed) else placed, dtype=np.float64)
    limit = reach * float(np.linalg.norm(np.ptp(q, axis=0)))
    near = np.isfinite(distances_within(q, p, limit))
    keep = np.isin(label, np.unique(label[near]))
    return None if keep.all() or not keep.any() else keep


def rough_placement(person_neutral, template_deltas, face: FaceRig, avatar_deltas, capture) -> np.ndarray:
    """The person's neutral ``[q,3]`` placed on the face mesh roughly (for :func:`reached_parts`): by the
    shape-motion landmarks (:func:`.register.motion_initialiser`), else by a full registration."""
    from .register import RegistrationError, motion_initialiser

    try:
        return motion_initialiser(person_neutral, template_deltas, face.neutral, avatar_deltas).apply(
            person_neutral)
    except RegistrationError:
        return register_face(person_neutral, template_deltas, face.neutral, avatar_deltas,
                             avatar_triangles=face.triangles, capture_triangles=capture.triangles,
                             path=capture.source or None).transform.apply(person_neutral)


def choose_source(template_registration, person=None):
    """``(source, registration)``: the capture-topology face the correspondence is registered from,
    ``"person"`` when the person's neutral (``person = (neutral[n,3], registration)``) lies closer to the
    avatar face after its similarity registration than the template's neutral
    (:meth:`.register.Registration.rank`, the order :func:`register_face` ranks its candidates by: more of
    it within the final distance, then a lower ICP residual, the RMS distance of the placed face to the
    avatar's surface), else ``"template"``; and that face's registration."""
    if person is not None and person[1].rank() > template_registration.rank():
        return "person", person[1]
    return "template", template_registration


def corr_transform(corr, fallback):
    """The similarity that placed the capture face the map ``corr`` was registered from (the template's
    neutral or the person's, :func:`choose_source`; from its info), else ``fallback``."""
    from .register import Similarity

    info = corr.info or {}
    reg = info.get("placement") or info.get("template_registration")
    if not reg:
        return fallback
    return Similarity(float(reg["scale"]), np.asarray(reg["rotation"]), np.asarray(reg["translation_m"]))


def correspondence_semantics(corr, capture_triangles, names, template_deltas, avatar_deltas, transform,
                             *, moving: float = 0.1) -> dict:
    """How well the map keeps the shapes' meaning: for the semantic shapes (jawOpen, the blinks), over the
    face vertices that move (more than ``moving`` of the peak on either rig), the share whose mapped template
    motion opposes the avatar's own (negative dot product), and the lip/lid *side swaps*.

    A swap is an avatar face vertex that one rig moves the way the shape opens (more than half the peak along
    the avatar's opening direction, :func:`opening_direction`: the lower lip, the upper lid) and the other
    keeps shut (still, or moving only against the opening, less than a fifth of the peak otherwise:
    :func:`opening_side`): an avatar lower lip on the capture's upper lip, an avatar lower lid on the
    capture's upper lid. Not the motion's length alone, as until stop 47: a template whose blink closes in
    the middle (its lower lid rises half as far as the upper lid falls) moves its lower lid by half the peak
    too, and an avatar lower lid mapped onto it, the right lid, was counted; nor the travel alone: a template
    lid pushed forward over the upper lid does not travel down there, and the avatar's upper lid mapped onto
    it, the right lid again, would count (a direction the rigs disagree on is ``opposing_share``'s).
    Returns ``(figures, swapped[m])``, the second the face-mesh vertices of those swaps."""
    f = np.flatnonzero(corr.face)
    sig_total, opposing, swaps = 0, 0, {}
    disagree = np.zeros(len(corr.face), dtype=bool)
    for name in SEMANTIC_SHAPES:
        if name not in names:
            continue
        j = names.index(name)
        t = transform.apply_vectors(template_deltas[j])                              # [n,3] avatar frame
        mt = corr.apply(t[None], capture_triangles, rows=f)[0]
        a = np.asarray(avatar_deltas[j])[f]
        na, nm = np.linalg.norm(a, axis=1), np.linalg.norm(mt, axis=1)
        pa = max(float(na.max()), 1e-300)
        pm = max(float(np.linalg.norm(t, axis=1).max()), 1e-300)
        sig = np.maximum(na / pa, nm / pm) > moving
        sig_total += int(sig.sum())
        opposing += int((sig & (np.einsum("ij,ij->i", a, mt) < 0)).sum())
        # each rig's side, on the avatar's opening direction (the semantic poses' common direction)
        direction = opening_direction(avatar_deltas[j])
        open_a, shut_a = opening_side(a / pa, direction)
        open_m, shut_m = opening_side(mt / pm, direction)
        swapped = (open_a & shut_m) | (shut_a & open_m)
        swaps[name] = int(swapped.sum())
        disagree[f[swapped]] = True
    return {"opposing_share": opposing / max(sig_total, 1), "side_swaps": int(sum(swaps.values())),
            **{f"side_swaps_{k}": v for k, v in swaps.items()}}, disagree


def opening_side(motion, direction, *, opens: float = 0.5, still: float = 0.2):
    """``(opening[n], shut[n])`` bool: which side of a shape's opening each point is on, from its motion
    ``motion[n,3]`` in units of the shape's peak motion and the opening ``direction[3]`` (unit,
    :func:`opening_direction`). *Opening*: it travels more than ``opens`` along the direction (the lower lip
    under ``jawOpen``, the upper lid under a blink). *Shut*: it travels less than ``still`` along it and moves
    less than ``still`` across it (the upper lip, the lower lid, the cheek: still, or moving only against the
    opening, as a lower lid that rises to meet the upper one). A point moved across the direction (an
    artist's lid pushed forward) is neither."""
    m = np.asarray(motion, dtype=np.float64)
    travel = m @ direction
    across = np.linalg.norm(m - travel[:, None] * direction, axis=1)
    return travel > opens, (travel < still) & (across < still)


def opening_direction(deltas) -> np.ndarray:
    """``[3]`` unit vector: a shape's motion-weighted mean direction ``sum_i |d_i| d_i`` over ``deltas[n,3]``
    (normalised), the way it moves what it opens or shuts (``jawOpen``: down, a blink: the upper lid down);
    zeros when nothing moves. The common direction of the semantic poses (:func:`pose_by_length`)."""
    d = np.asarray(deltas, dtype=np.float64)
    direction = np.sum(d * np.linalg.norm(d, axis=1)[:, None], axis=0)
    size = float(np.linalg.norm(direction))
    return direction / size if size > 0 else np.zeros(3)
