"""``usdface personalize``: fit the person's shapes on the capture, implant them into the avatar, write the
layer.

Steps (Menzel et al. 2022, sec. 3.2-3.3), each a pure function on arrays in another module:

1. fit the personalized capture shapes B_j (:func:`usdface.personalize.fit_personalized_shapes`);
2. register the capture neutral onto the avatar face (:mod:`.register`, ICP with scaling);
3. correspondence map M and face region (:mod:`.correspond`, cached per avatar + template);
4. automatic retargeting, eq. (4) (:mod:`.retarget`): weight map and approximations A_j;
5. seamless partial transfer (:mod:`.partial_dt`): face from B_j, adjacent region blended from the
   approximation, every other vertex and mesh follows the approximation;
6. eyelid-eyeball repair (:mod:`.eyelids`);
7. the layer (:func:`usdface.io.layers.write_avatar_layer`).

Every step works on the part of each mesh its shapes move (:mod:`usdface.submesh`: read that way, or cropped
after reading; the offsets go back as :class:`usdface.submesh.SparseOffsets`), and the face mesh's separate
pieces beyond the capture's reach are handled as another mesh (:func:`reached_parts`).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import CaptureError, GeometryError, RigError, UsdFaceError
from ..memory import release_free_memory
from ..mesh import deformation_gradients
from ..model import Avatar, Capture, FaceRig
from ..motion import meshes_by_motion, most_moving_mesh, moving_vertices, peak_motion, shape_norms
from ..personalize.api import single_threaded_blas
from ..personalize.evaluate import test_expression_errors
from ..progress import steps
from ..submesh import SparseOffsets, crop, crop_avatar, crop_rig, rig_on, scatter
from .correspond import (
    Correspondence,
    PosedSurface,
    correspondence_map,
    correspondence_npz,
    geometry_digest,
    load_correspondence,
    nonrigid_register,
    save_correspondence,
)
from .eyelids import find_eyeballs, repair_eyelids
from .implant import (
    avatar_shapes_on_capture,
    extend_personalization,
    face_personalization,
    face_radius,
    follow_field,
    mapping_outliers,
    rigid_shapes,
)
from .motion_field import dilate
from .partial_dt import blend_adjacent, face_deformation_transfer, personalization_support
from .register import motion_landmarks, register_face
from .retarget import approximate, driven_gram, namesake_prior, retarget_weights
from .trust import shape_trust

__all__ = ["PersonalizeResult", "personalize_avatar", "implant_shapes", "FACE_TRANSFERS", "APPROXIMATIONS",
           "default_approximation", "MODE_OPTIONS", "MODE_ONLY_OPTIONS", "IMPLANT_OPTIONS",
           "check_mode_options", "modes_using", "option_name"]

#: Face-region transfer modes (see :func:`implant_shapes`).
FACE_TRANSFERS = ("person", "offset", "dt", "dt-offset")
#: What the adjacent region and the other meshes are blended from / follow.
APPROXIMATIONS = ("field", "generic", "retarget")


#: The options of :func:`personalize_avatar` each face-transfer mode uses besides the fit's, eq. (4)'s and
#: ``eyelids`` (:func:`check_mode_options` refuses the others when given): the person's field reaches
#: ``extension_length`` face radii; the older modes join over ``falloff`` edge lengths; ``support`` ramps
#: the personalization of ``person`` and the offset modes (``dt`` transfers the whole deformation).
MODE_OPTIONS = {
    "person": ("extension_length", "support"),
    "offset": ("falloff", "support"),
    "dt": ("falloff",),
    "dt-offset": ("falloff", "support"),
}
#: The options some face-transfer modes use and others not (those :func:`check_mode_options` checks).
MODE_ONLY_OPTIONS = frozenset(k for ks in MODE_OPTIONS.values() for k in ks)
#: The implant's options (step 5 and the eyelid repair): ``usdface retarget``, which writes the eq. (4) map
#: only, takes none of them.
IMPLANT_OPTIONS = ("face_transfer", "approximation", "extension_length", "falloff", "support", "eyelids",
                   "eyes")
#: Command-line spellings of options whose flag is not ``--`` + the name with dashes (None: API only).
_FLAGS = {"support": None, "eyes": None, "eyelids": "--no-eyelids", "weight_bounds": "--weight-bounds"}


def option_name(name: str) -> str:
    """``"falloff (--falloff)"``: an option of :func:`personalize_avatar` in both spellings, the API's and the
    command line's (``"support (Python API only)"`` for one the commands do not offer)."""
    flag = _FLAGS.get(name, "--" + name.replace("_", "-"))
    return f"{name} ({flag})" if flag else f"{name} (Python API only)"


def check_mode_options(face_transfer: str, given) -> None:
    """Refuse (:class:`usdface.errors.OptionError`), before any work, an option among ``given`` (the names
    the caller gave explicitly) that ``face_transfer`` does not use (:data:`MODE_OPTIONS`): it would be
    ignored without a word. An unknown ``face_transfer`` is left to :func:`_check_modes`."""
    from ..errors import OptionError

    used = MODE_OPTIONS.get(face_transfer)
    if used is None:
        return
    for name in sorted(set(given) & MODE_ONLY_OPTIONS):
        if name not in used:
            raise OptionError(
                f"{option_name(name)} is not used by {option_name('face_transfer')} {face_transfer!r} "
                f"(it uses {', '.join(option_name(k) for k in used)})",
                fix=f"drop {option_name(name)}, or choose a {option_name('face_transfer')} that uses it: "
                    + ", ".join(modes_using(name)))


def modes_using(name: str) -> list[str]:
    """The face-transfer modes that use the option ``name`` (:data:`MODE_OPTIONS`)."""
    return [m for m, ks in MODE_OPTIONS.items() if name in ks]


def default_approximation(face_transfer: str) -> str:
    """The approximation a face-transfer mode gets when none is given: ``"field"`` for ``"person"`` (the only
    one it goes with), ``"generic"`` for the older modes. The one rule the Python API, ``usdface
    personalize`` and ``usdface batch`` share, so the same mode gives the same result from each."""
    return "field" if face_transfer == "person" else "generic"

#: Width of the join between the face region and the field beyond, in face radii: 1.1-1.2 cm on a head, so it
#: spans several edge rings even of a coarse 24k-vertex head (three; a 7 mm join spanned fewer than two and
#: left a step where the direct result and the field differ), and more on finer meshes.
SEAM_BAND = 0.2
#: Priors of the fit (see :func:`personalize_avatar`).
PRIORS = ("avatar", "template")
#: What eq. (4)'s ridge shrinks the retarget map towards (see :func:`personalize_avatar`).
MAP_PRIORS = ("namesake", "zero")


@dataclass
class PersonalizeResult:
    """Everything ``personalize`` computed.

    ``offsets``: {mesh prim path -> deltas[K_mesh,n,3]} metres internal, rig.names order (the layer's); for a
    mesh worked on by its moving part a :class:`usdface.submesh.SparseOffsets` (``np.asarray`` is the dense
    array; outside the part the input's offsets, or 0 for float noise read from a file).
    ``names``: the capture shapes that were implanted (J). ``weights``: eq. (4) retarget map ``[J,K]`` with
    ``avatar_names`` (K, the face mesh's shapes). ``approximation``: {mesh -> A_j [J,n,3]} eq. (4).
    ``face``/``adjacent``: face-mesh regions (``[n]``, ``[J,n]``). ``report``: figures for people
    (registration, correspondence, name mismatches, timings...). ``out_path``: the layer (None if not
    written).
    """

    offsets: dict
    names: list
    avatar_names: list
    weights: np.ndarray
    approximation: dict
    face_mesh: str
    face: np.ndarray
    adjacent: np.ndarray
    report: dict = field(default_factory=dict)
    out_path: Path | None = None
    fit: object | None = None


def _face_mesh(avatar: Avatar, names: list[str]) -> FaceRig:
    """The mesh where the shared ARKit shapes move the most vertices (the face/head mesh); float noise of an
    export is not motion (:func:`usdface.motion.most_moving_mesh`)."""
    best = most_moving_mesh(avatar.meshes, names)
    if best is None:
        raise RigError("the avatar has no face-like blend shapes (no ARKit-named shape that moves)",
                       path=avatar.file,
                       fix="the avatar needs ARKit-named BlendShapes (eyeBlinkLeft, jawOpen, ...): rename "
                           "them, or pass the studio's names with --name-map FILE (name_map=); "
                           "'usdface inspect' lists how each channel was mapped")
    return best


def empty_face_region(avatar_file, meshes, face_prim: str, names: list[str], chosen: bool) -> RigError:
    """The error for a face mesh ``face_prim`` of which no vertex lies on the registered capture surface:
    the capture covers none of it, so it can move none of it (``--face-mesh Mouth``: the mouth socket, the
    teeth or an eye, not the skin). Names the other ``meshes`` (:class:`usdface.model.FaceRig`) the shapes
    in ``names`` move, most moving vertices first, as the ``--face-mesh`` to pick (``chosen``: the mesh was
    given with ``--face-mesh``; else it was the one the shapes move most)."""
    ranked = [(m.key, n) for m, n in meshes_by_motion(meshes, names)]      # the order the automatic pick uses
    others = [f"{key} ({n} moving vertices)" for key, n in ranked if key != face_prim]
    listed = f": {', '.join(others)}" if others else " (this avatar has no other mesh the shapes move)"
    if chosen:
        message = ("the face mesh given with --face-mesh has no vertex the capture covers: none lies on the "
                   "registered capture surface, so the capture moves none of it (not the face's skin: a "
                   "mouth, teeth or eye mesh?)")
        best = ranked[0][0] if ranked else None
        fix = (f"pick the skin mesh with --face-mesh (candidates{listed})"
               + (f"; without --face-mesh usdface picks {best}, the mesh the shapes move most"
                  if best is not None and best != face_prim else ""))
    else:
        message = ("no vertex of the face mesh (the mesh the shapes move most) lies on the registered "
                   "capture surface: the capture covers and moves none of it")
        fix = ("check that the capture and the avatar show the same face; if this mesh is not the face's "
               f"skin, pick the skin mesh with --face-mesh{listed}")
    return RigError(message, path=avatar_file, prim=face_prim, fix=fix)


def _refuse_unmapped_face(avatar: Avatar, face: FaceRig, names: list[str]) -> None:
    """Refuse a face mesh found by its ARKit names when another mesh has more shapes whose names only look
    like the capture's (:func:`usdface.arkit.lookalike`: a studio prefix, ``STU_eyeBlinkLeft``): the real
    face is that one, read without its name map, and the run would register the capture on the wrong mesh
    (a user trial: "registration shrank the capture to a point ... /Avatar/Mouth")."""
    from ..arkit import lookalike

    wanted = set(names)
    ours = sum(n in wanted for n in face.names)
    for m in avatar.meshes:
        if m is face:
            continue
        look = {n: a for n in m.names if (a := lookalike(n)) is not None and a in wanted}
        meant = len(set(look.values()))     # distinct shapes: a corrective 'jawOpen_mouthClose' is one
        if meant > ours:
            shown = ", ".join(f"{n} -> {a}" for n, a in list(look.items())[:3])
            raise RigError(f"{m.key} has {meant} shapes whose names look like the capture's ARKit names "
                           f"in another spelling ({shown}, ...), more than the {ours} of {face.key}, which "
                           "would be taken for the face", path=avatar.file, prim=m.key,
                           fix="map the names with --name-map FILE (a JSON or CSV {channel: ARKit name}, see "
                           "docs/names.md), or choose the face mesh with --face-mesh")


def _shape_deltas(rig: FaceRig, names: list[str], *, view: bool = False) -> np.ndarray:
    """``[len(names), n, 3]`` deltas of ``rig`` for ``names`` (zero for shapes the mesh lacks). With ``view``
    and ``names`` the rig's own shapes in its order, a read-only view of ``rig.deltas`` (no copy: 24 B per
    vertex and shape; a step that wrote into it would raise)."""
    if view and list(names) == list(rig.names) and rig.deltas.dtype == np.float64:
        out = rig.deltas.view()
        out.flags.writeable = False
        return out
    out = np.zeros((len(names), rig.n_vertices, 3))
    for i, n in enumerate(names):
        if n in rig.names:
            out[i] = rig.deltas[rig.index(n)]
    return out


#: Face offsets from this size on are held packed during the field (a head of about 80k vertices and
#: more; below, the packing's passes over them cost more than the memory is worth).
PACK_BYTES = 100 * 2 ** 20


class _HeldPacked:
    """Context manager: inside the block, the generic offsets of each ``(rig, names)`` of ``parts`` that
    :func:`_packed_generic` packs are held packed only - ``rig.deltas`` and the entries of ``generic_full``
    that are that array are let go, so the float64 array is not alive at the run's peak - and on exit they are
    the float64 array again (the same values to the last bit, :class:`usdface.memory.Float32Offsets`).
    ``parts``' None entries are skipped. :meth:`packed` gives a part's packed offsets inside the block (None:
    kept as float64); after the block nothing here refers to them."""

    def __init__(self, generic_full: dict, parts):
        self._generic_full = generic_full
        self._parts = parts
        self._held: list = []

    def __enter__(self):
        for part in self._parts:
            rig, names = part if part is not None else (None, None)
            packed = _packed_generic(rig, names) if rig is not None else None
            keys = [k for k, v in self._generic_full.items() if packed is not None and v is rig.deltas]
            if packed is not None:
                self._generic_full.update(dict.fromkeys(keys))
                rig.deltas = None
            self._held.append((rig, packed, keys))
        return self

    def packed(self, i: int):
        return self._held[i][1] if self._held else None

    def __exit__(self, *exc):
        held, self._held = self._held, []
        while held:
            rig, packed, keys = held.pop()
            if packed is not None:
                rig.deltas = packed.expand()
                self._generic_full.update(dict.fromkeys(keys, rig.deltas))
            del packed
        return False


def _packed_generic(rig: FaceRig, names: list[str]):
    """``rig.deltas`` as :class:`usdface.memory.Float32Offsets` (the authored float32 offsets and the reader's
    conversion, the same values to the last bit) when ``names`` are the rig's own shapes in its order, the
    rig was read from a file and its offsets take ``PACK_BYTES`` or more; else None (keep the float64
    array)."""
    from ..memory import Float32Offsets

    if (rig.source is None or list(names) != list(rig.names) or rig.deltas.dtype != np.float64
            or rig.deltas.nbytes < PACK_BYTES):
        return None
    return Float32Offsets.pack(rig.deltas, rig.source.to_internal[:3, :3])


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
    direction = np.sum(avatar_delta * la[:, None], axis=0)
    size = float(np.linalg.norm(direction))
    if pt <= 0 or pa <= 0 or size <= 0:
        return None
    direction /= size
    return (lt * (pa / pt))[:, None] * direction, la[:, None] * direction


def _correspondence(face: FaceRig, capture: Capture, template_deltas, avatar_deltas, cache, names=(),
                    initial=None, target=None, source_triangles: bool = True, avatar_peak=None,
                    avatar_landmarks=None, surfaces: dict | None = None, pending: list | None = None):
    """The correspondence (:func:`correspondence_map`), from the ``cache`` file when it holds this avatar face
    and template's (and, with ``source_triangles``, the face triangles' source triangles); written there
    otherwise. ``avatar_peak``, ``avatar_landmarks``: the face's peak motion and motion landmarks, for
    :func:`register_face`. ``surfaces``: a dict
    that receives the posed avatar face surface the registration built (``"avatar"``, a
    :class:`PosedSurface`), for the avatar's shapes on the capture (:func:`avatar_shapes_on_capture`).
    ``pending``: a list that receives ``(cache, npz bytes)`` instead of the cache being written now, for a
    caller that writes it only once its run succeeds (a run that failed after this step left its cache
    behind, with the folder made for it)."""
    names = list(names)
    sem = [n for n in SEMANTIC_SHAPES if n in names]
    key = geometry_digest(face.neutral, face.triangles, capture.template.neutral, capture.triangles,
                          *[template_deltas[names.index(n)] for n in sem],
                          *[avatar_deltas[names.index(n)] for n in sem])
    stale = False
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
                          avatar_peak=avatar_peak, avatar_landmarks=avatar_landmarks)
    placed = reg_t.transform.apply(capture.template.neutral)
    poses, used = semantic_poses(names, template_deltas, avatar_deltas, reg_t.transform)
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
    corr.info = {**corr.info, **nr_info, "template_registration": reg_t.as_dict(),
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
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    from ..mesh import vertex_adjacency

    p = np.asarray(points, dtype=np.float64)
    count, label = connected_components(vertex_adjacency(triangles, len(p)), directed=False)
    if count < 2:
        return None
    q = np.asarray(placed() if callable(placed) else placed, dtype=np.float64)
    limit = reach * float(np.linalg.norm(np.ptp(q, axis=0)))
    near = np.isfinite(cKDTree(q).query(p, distance_upper_bound=limit)[0])
    keep = np.isin(label, np.unique(label[near]))
    return None if keep.all() or not keep.any() else keep


def _rough_placement(person_neutral, template_deltas, face: FaceRig, avatar_deltas, capture) -> np.ndarray:
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


def _split_rig(rig: FaceRig, keep) -> tuple[FaceRig, FaceRig]:
    """``rig`` as two rigs: on the vertices ``keep[m]`` (sharing its source, so its key) and on the rest (no
    source: another mesh for the steps, named after it); the triangles within each, re-indexed."""
    def part(mask, source, name):
        sub = crop(rig.triangles, mask)
        return rig_on(rig, sub.vertices, sub.triangles, source, name)

    return part(keep, rig.source, rig.name), part(~keep, None, f"{rig.key} (beyond the capture)")


def _join(reached_values, reached, rest_values, rest) -> np.ndarray:
    """Values of a split face mesh (:func:`_split_rig`; ``[k]``, ``[J,k]`` or ``[J,k,3]``) in one array
    again: ``reached_values`` at the vertices ``reached[m]``, ``rest_values`` (array or fill) at ``rest``."""
    a = np.asarray(reached_values)
    axis = 0 if a.ndim == 1 else 1                          # [m] masks, [J,m] and [J,m,3] per shape
    shape = list(a.shape)
    shape[axis] = reached.size
    out = np.zeros(shape, dtype=a.dtype)
    idx = [slice(None)] * a.ndim
    idx[axis] = np.flatnonzero(reached)
    out[tuple(idx)] = a
    idx[axis] = rest
    out[tuple(idx)] = rest_values
    return out


def _jacobians(neutral, deltas, triangles):
    return deformation_gradients(neutral, neutral[None] + deltas, triangles)


def implant_shapes(face_neutral, face_triangles, corr: Correspondence, capture_triangles, person_neutral,
                   person_deltas, template_deltas, avatar_deltas, approx, *, face_transfer: str = "offset",
                   anchor_weight: float = 1.0, falloff: float | None = None, support=(0.01, 0.03)):
    """Steps 5 on arrays: the face region from the personalized shapes, seamlessly joined to ``approx``.

    ``person_neutral[n,3]``, ``person_deltas[J,n,3]``, ``template_deltas[J,n,3]``: capture mesh, already in
    the avatar frame (registered). ``avatar_deltas[J,m,3]`` the avatar's generic shapes for the same J names,
    ``approx[J,m,3]`` what the adjacent region is blended from. ``face_transfer``:

    * ``"offset"`` (default, most accurate on the bench): face = avatar's generic shape + M (B_j - T_j), i.e.
      the person's deviation from the generic template, mapped through the correspondence onto the avatar's
      own generic shape (its detail is kept, only the personalization is transferred);
    * ``"dt"``: deformation transfer of B_j (Sumner & Popovic) onto the face, anchored to M B_j (the paper);
    * ``"dt-offset"``: deformation transfer of the gradients' deviation ``S(B_j) - S(T_j)`` onto the generic
      shape.

    ``support=(low, high)``: for the offset modes, the personalization ``B_j - T_j`` is kept only where B_j or
    T_j moves more than ``low..high`` of its peak (:func:`personalization_support`); None keeps it everywhere.

    Returns ``(result[J,m,3], adjacent[J,m])``.
    """
    # only the face rows of M B_j, M T_j are used (the transfer and the blend read d_face on the face only)
    f = np.flatnonzero(corr.face)

    def on_face(values_face):
        full = np.zeros(avatar_deltas.shape[:1] + (len(corr.face), 3))
        full[:, f] = values_face
        return full

    if face_transfer == "dt":
        dface = face_deformation_transfer(face_neutral, face_triangles, corr.face, corr.source_triangle,
                                          _jacobians(person_neutral, person_deltas, capture_triangles)
                                          - np.eye(3),
                                          on_face(corr.apply(person_deltas, capture_triangles, rows=f)),
                                          anchor_weight=anchor_weight)
    elif face_transfer in ("offset", "dt-offset"):
        if support is not None:
            # only the personalization inside the shape's support is transferred (personalization_support)
            keep = personalization_support(person_deltas, template_deltas, low=support[0], high=support[1])
            offset_f = corr.apply((person_deltas - template_deltas) * keep[..., None], capture_triangles,
                                  rows=f)
        else:
            offset_f = (corr.apply(person_deltas, capture_triangles, rows=f)
                        - corr.apply(template_deltas, capture_triangles, rows=f))
        offset = np.array(avatar_deltas, dtype=np.float64, copy=True)
        offset[:, f] += offset_f                                             # avatar_deltas + M B_j - M T_j
        if face_transfer == "offset":
            dface = offset
        else:
            jac = (_jacobians(person_neutral, person_deltas, capture_triangles)
                   - _jacobians(person_neutral, template_deltas, capture_triangles))
            dface = face_deformation_transfer(face_neutral, face_triangles, corr.face, corr.source_triangle,
                                              jac, offset, base=avatar_deltas,
                                              anchor_weight=anchor_weight)
    else:
        raise ValueError(f"face_transfer must be one of {FACE_TRANSFERS}")
    return blend_adjacent(face_neutral, face_triangles, corr.face, dface, approx, falloff=falloff,
                          face_weight=corr.weight)


@single_threaded_blas
def personalize_avatar(avatar, capture, out_path=None, *, method: str = "menzel", reg="auto",
                       mu="auto", correspondence=None, force: bool = False, dry_run: bool = False,
                       face_transfer: str = "person", approximation: str | None = None, falloff: float = 0.15,
                       support=(0.01, 0.03), eyelids: bool = True, eyes: dict | None = None,
                       rig: FaceRig | None = None, prior: str = "avatar", face_mesh: str | None = None,
                       name_map=None, extension_length: float | None = 1.0, command: str = "",
                       weight_bounds=(0.0, 1.0), map_prior: str = "namesake", layer_edit=None,
                       map_only: bool = False, extra_inputs: dict | None = None,
                       **fit_options) -> PersonalizeResult:
    """Personalize ``avatar`` (path or :class:`Avatar`) from ``capture`` (folder / capture USD path or
    :class:`Capture`) and, unless ``dry_run`` or ``out_path`` is None, write the layer to ``out_path``.

    Parameters
    ----------
    method, reg, fit_options : step 1, passed to :func:`usdface.personalize.fit_personalized_shapes`.
    prior : what the fit shrinks the person's shapes towards where the capture does not inform them:
        ``"avatar"`` (default): the avatar's own generic shapes sampled on the capture mesh, so that a shape
        the capture barely shows stays the avatar's; ``"template"``: the capture's template rig (the paper).
    rig : skip step 1 and implant this capture-mesh rig (neutral = person's B0, deltas = B_j).
    name_map : the studio's {channel: ARKit name} map (dict or JSON/CSV file) for reading ``avatar``
        (:func:`usdface.io.usd_rig.read_avatar`).
    mu : eq. (4) ridge weight (relative, see :func:`retarget_weights`) of the retarget map; ``"auto"`` chooses
        it by cross-validation, leaving out one region of the face rows at a time (the 3 x 3 split of their
        extent, :func:`usdface.transfer.retarget.choose_mu_by_regions`).
    weight_bounds : ``(lo, hi)`` range of the eq. (4) map's weights (default ``(0, 1)``, the range an ARKit
        rig's channels are authored for); None: any real weights, as the paper.
    map_only : stop after eq. (4) (``usdface retarget``: the weight map is the product): no implant, no
        layer; the result's ``offsets`` and ``approximation`` are empty, ``weights`` the map.
    extra_inputs : ``{role: path}``, more files the layer is made from (``{"take": path}``, the take its
        inspection animation plays): recorded with their digests among its inputs, so that editing one makes
        the layer stale, and each under its role in the provenance (relative to the layer, as the inputs),
        which ``usdface review`` reads back.
    layer_edit : ``layer_edit(offsets, face_prim) -> edit(stage)`` (or None): extra prims and primvars
        authored into the layer in the same atomic write (the inspection data of
        :func:`usdface.api.personalize_avatar`), from the offsets that are written.
    map_prior : what eq. (4)'s ridge shrinks each row towards: ``"namesake"`` (default: the avatar shape of
        the same ARKit name, weight 1, as a hand-made retargeting table) or ``"zero"`` (the paper).
    correspondence : cache file for step 3, reused when it belongs to this avatar face and template (same
        geometry, topology and semantic shapes), rewritten otherwise.
    force : overwrite an existing output layer.
    face_transfer : ``"person"`` (default): the face region receives the person's motion,
        ``A_j + M (B_j - P_j)`` (:func:`usdface.transfer.implant.face_personalization`); the older modes map
        the deviation from the capture's template: ``"offset"`` (``A_j + M (B_j - T_j)``), ``"dt"`` (the
        paper's deformation transfer), ``"dt-offset"`` (:func:`implant_shapes`).
    approximation : beyond the face region and on the other meshes: ``"field"`` the person's motion as a
        rotation + scale field of the generic motion, extended smoothly (:mod:`.motion_field`; the only one
        ``"person"`` goes with); ``"generic"`` the avatar's generic shape; ``"retarget"`` the eq. (4)
        approximation A_j (the paper). None (default): :func:`default_approximation` of ``face_transfer``.
    extension_length : with ``"field"``, how far the person's field reaches beyond the face before it fades
        to the generic motion, in face radii (RMS radius of the face region; None = no fade).
    falloff, support : the join of the older modes (:func:`implant_shapes`); ``support`` also ramps the
        person's personalization. Which mode uses which: :data:`MODE_OPTIONS` (the API and the commands
        refuse one the mode does not use, :func:`check_mode_options`; this function takes them all).
    face_mesh : prim path (or name) of the face mesh; default: the mesh the shared ARKit shapes move most.
    eyelids : step 6; ``eyes`` = {name: (points[n,3], triangles[t,3])} internal metres, closed eye meshes
        (else taken from ``avatar.metadata["static_meshes"]`` when the reader provides it, or from avatar
        meshes that are eyeballs by name/geometry).
    """
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    report: dict = {"warnings": []}
    approximation = _check_modes(face_transfer, approximation, prior, weight_bounds, map_prior)
    check_numbers(mu=mu, extension_length=extension_length, falloff=falloff, support=support)
    # a numeric string passes the check (as the CLI's "0.01" does), and is the number from here on: mu="0.01"
    # went on to retarget_weights' ValueError after the registration and the fit
    mu, extension_length, falloff = (float(v) if isinstance(v, str) and v != "auto" else v
                                     for v in (mu, extension_length, falloff))
    if rig is None:                                # the fit's options, before any work
        from ..personalize.api import check_fit_options

        check_fit_options(method, reg, **_fit_prior_options(prior, method, reg), **fit_options)
    pending_cache: list = []                      # the correspondence cache, written once the run succeeds
    with steps("retarget" if map_only else "personalize", 5 if map_only else 8) as advance:
        advance.start("read")
        t = time.perf_counter()
        if out_path is not None and not dry_run:
            from ..io.layers import check_output_path

            check_output_path(out_path, force)
        if not isinstance(avatar, Avatar):
            from ..io.usd_rig import read_avatar

            avatar = read_avatar(avatar, name_map=name_map, moving_only=True)
        if out_path is not None:                  # an override under an instance would change nothing
            from ..io.usd_rig import refuse_instanced, refuse_unwritable_shapes

            try:
                refuse_instanced(avatar, [m.key for m in avatar.meshes], "the personalized layer")
                refuse_unwritable_shapes(avatar, None, "the personalized layer")     # every mesh
            except RigError as exc:
                if not dry_run:
                    raise
                report["warnings"].append(f"a real run would refuse: {exc.message} (fix: {exc.fix})")
                report["would_refuse"] = f"{exc.message} (fix: {exc.fix})"
        # every step works on the part of each mesh its shapes move; scattered back at the end (write)
        generic_full = {m.key: m.deltas for m in avatar.meshes       # the caller's whole-mesh arrays
                        if m.source is None or m.source.region is None}
        avatar, origin = near_origin(avatar)
        if eyes:
            eyes = {k: (np.asarray(p, dtype=np.float64) - origin, t) for k, (p, t) in eyes.items()}
        avatar, regions = crop_avatar(avatar)
        if not isinstance(capture, Capture):
            from ..io import read_capture

            capture = read_capture(capture)
        if rig is None and fit_options.get("every", 1) != 1:   # a take's thinning: refused on a capture now
            from ..personalize.api import check_every

            check_every(fit_options["every"], capture)
        if rig is None and capture.whole_take:                # a take of one held pose: refused now
            from ..personalize.api import check_take_poses

            check_take_poses(capture, fit_options.get("every", 1))
        if rig is None:                                       # proven exchanged sides: refused now
            from ..personalize.api import refuse_swapped_sides

            refuse_swapped_sides(capture)
        chosen_face = None
        if face_mesh:  # checked before the fit
            from ..io.layers import avatar_mesh

            chosen_face = avatar_mesh(avatar, face_mesh, "with blend shapes in the avatar (--face-mesh)")
        release_free_memory()                      # USD's buffers and the per-shape arrays read
        timings["read"] = time.perf_counter() - t
        advance("read")
        advance.start("register")

        # names: capture shapes vs avatar shapes
        cap_names = list(rig.names) if rig is not None else list(capture.names)
        face = chosen_face if chosen_face is not None else _face_mesh(avatar, cap_names)
        if chosen_face is None:
            _refuse_unmapped_face(avatar, face, cap_names)
        face_prim = face.key
        avatar_all = sorted({n for m in avatar.meshes for n in m.names})
        tmpl_idx = {n: i for i, n in enumerate(capture.template.names)}
        names = [n for n in cap_names if n in face.names and n in tmpl_idx]
        report["capture_shapes_missing_from_avatar"] = [n for n in cap_names if n not in face.names]
        report["avatar_shapes_missing_from_capture"] = [n for n in avatar_all if n not in cap_names]
        if report["capture_shapes_missing_from_avatar"]:
            report["warnings"].append("capture shapes the avatar lacks (skipped): "
                                      + ", ".join(report["capture_shapes_missing_from_avatar"]))
        if report["avatar_shapes_missing_from_capture"]:
            report["warnings"].append("avatar shapes the capture lacks (kept generic): "
                                      + ", ".join(report["avatar_shapes_missing_from_capture"]))
        if len(names) < 4 and len(cap_names) < 4:      # the capture is what is short
            shown = ", ".join(cap_names) or "none"
            raise CaptureError(f"the capture has {len(cap_names)} shape(s) ({shown}); personalizing needs at "
                               "least 4 ARKit-named shapes",
                               path=getattr(capture, "source", None) or None,
                               fix="capture the ARKit expressions (eyeBlinkLeft, jawOpen, ...) with their "
                               "template shapes")
        if len(names) < 4:
            raise RigError(f"only {len(names)} of the capture's shapes exist on the avatar face mesh",
                           path=avatar.file, prim=face_prim,
                           fix="the avatar needs ARKit-named BlendShapes (eyeBlinkLeft, jawOpen, ...): "
                               "rename them, or pass the studio's names with --name-map FILE (name_map=); "
                               "'usdface inspect' lists how each channel was mapped")
        template_deltas = capture.template.deltas[[tmpl_idx[n] for n in names]]
        avatar_face_deltas = _shape_deltas(face, names, view=True)
        person_neutral0 = rig.neutral if rig is not None else capture.neutral

        # 2. registration of the person's neutral
        t = time.perf_counter()
        # separate pieces of the face mesh beyond the capture's reach (a body merged into the head's mesh,
        # its neck moved by the jaw) cannot say where the capture lies nor what it shows: the steps below
        # see the reached pieces as the face mesh and the rest as another mesh (joined back before write)
        reached = reached_parts(face.neutral, face.triangles, lambda: _rough_placement(
            person_neutral0, template_deltas, face, avatar_face_deltas, capture))
        whole_face, beyond = face, None
        if reached is not None:
            # the still vertices beyond are left as they are (out of the part worked on and written)
            keep = reached | moving_vertices(peak_motion(face.deltas), face.neutral)
            whole_face, region = crop_rig(face, keep, regions.get(face_prim))
            if not region.whole:
                regions[face_prim] = region
            reached = reached[keep]
            face, beyond = _split_rig(whole_face, reached)
            avatar_face_deltas = _shape_deltas(face, names, view=True)
            rest = np.flatnonzero(~reached)
            avatar = dataclasses.replace(avatar, meshes=[face if m.key == face_prim else m
                                                         for m in avatar.meshes] + [beyond])
        # the face's peak motion, once for both registrations (the person's and the template's)
        face_peak = peak_motion(avatar_face_deltas)
        face_landmarks = motion_landmarks(face.neutral, avatar_face_deltas)         # the same for both too
        registration = register_face(person_neutral0, template_deltas, face.neutral, avatar_face_deltas,
                                     avatar_triangles=face.triangles, capture_triangles=capture.triangles,
                                     path=capture.source or None, avatar_peak=face_peak,
                                     avatar_landmarks=face_landmarks,
                                     avatar_mesh=f"{face_prim} of {Path(avatar.file).name}")
        timings["register"] = time.perf_counter() - t
        report["registration"] = _in_stage(registration.as_dict(), origin)
        sim = registration.transform
        advance("register")
        advance.start("correspond")

        # 3. correspondence (capture template <-> avatar face) and the avatar's shapes on the capture
        t = time.perf_counter()
        surfaces = {}                              # the posed avatar face, built once for both uses
        corr = _correspondence(face, capture, template_deltas, avatar_face_deltas, correspondence, names,
                               initial=sim, target=registration.target, pending=pending_cache,
                               source_triangles=face_transfer != "person",   # the deformation transfer's
                               avatar_peak=face_peak, avatar_landmarks=face_landmarks, surfaces=surfaces)
        report["correspondence"] = {k: v for k, v in (corr.info or {}).items()}
        placed = report["correspondence"].get("template_registration")
        if isinstance(placed, dict) and "translation_m" in placed:
            report["correspondence"]["template_registration"] = _in_stage(placed, origin)
        if not corr.face.any():
            # the meshes as the run holds them, the face whole again (its pieces beyond are no mesh to pick)
            meshes = [whole_face if m.key == face_prim else m for m in avatar.meshes if m is not beyond]
            raise empty_face_region(avatar.file, meshes, face_prim, cap_names, chosen_face is not None)
        placed_by = corr_transform(corr, sim)                  # the similarity that placed the template
        semantic, disagree = correspondence_semantics(corr, capture.triangles, names, template_deltas,
                                                      avatar_face_deltas, placed_by)
        report["correspondence"].update(semantic)
        if semantic["opposing_share"] > 0.02:
            report["warnings"].append(
                f"correspondence: {semantic['opposing_share'] * 100:.1f}% of the moving face vertices move "
                "against the avatar's own generic motion under the mapped template shapes (lips or lids "
                "swapped?); check the registration")
        generic_on_capture = None
        if prior == "avatar" or face_transfer == "person":
            poses, _ = semantic_poses(names, template_deltas, avatar_face_deltas, placed_by)
            g_av, _ = avatar_shapes_on_capture(corr.registered, face.neutral, face.triangles,
                                               avatar_face_deltas, poses=poses,
                                               surface=surfaces.get("avatar"))
            del poses                              # not needed after this: three [m,3] pairs fewer
            generic_on_capture = sim.inverse_vectors(g_av)                  # capture frame, person's rig
        surfaces.clear()                           # its scenes (77 B per triangle and pose) before the fit
        timings["correspond"] = time.perf_counter() - t
        advance("correspond")
        advance.start("fit")

        # 1. fit (after the correspondence: the avatar's shapes on the capture are its prior)
        t = time.perf_counter()
        fit = None
        if rig is None:
            fit = _fit(capture, names, generic_on_capture, prior, method, reg, fit_options)
            rig = fit.rig
            report["fit"] = {k: v for k, v in fit.info.items() if not isinstance(v, np.ndarray)}
            report["fit"]["prior"] = prior
            scored = test_expression_errors(capture, rig)    # eq. 5 of the fit the layer carries
            if scored is not None:
                report["fit"]["test_expressions"] = scored
        if capture.whole_take:                     # the inspection plays it: no test expressions
            report["whole_take"] = {"frames": capture.whole_take["frames"], "fps": capture.whole_take["fps"]}
        timings["fit"] = time.perf_counter() - t
        advance("fit")
        advance.start("retarget")
        b_idx = [rig.index(n) for n in names]
        person_neutral = sim.apply(rig.neutral)
        person_deltas = sim.apply_vectors(rig.deltas[b_idx])
        tmpl_av = sim.apply_vectors(template_deltas)

        # 4. retargeting, eq. (4): the weight map (and the paper's approximations A_j)
        t = time.perf_counter()
        f = corr.face
        mb_face = corr.apply(person_deltas, capture.triangles, rows=f)          # M B_j on the face region
        k_names = list(face.names)
        # the map drives every mesh: with the namesake prior, what the face rows do not see on the other
        # meshes (teeth, tongue, eyeballs) keeps the namesake's own motion (the paper's zero prior would hold
        # it still). The face mesh's own rows beyond the face are not among them: a body merged into the
        # head's mesh (split off as `beyond`) gives the head alone's map
        namesake = map_prior == "namesake"
        others = [(m.names, m.deltas) for m in avatar.meshes if m.key != face.key and m is not beyond]
        weights, mu_used = retarget_weights(
            face.deltas, mb_face, mu=mu, return_mu=True, rows=f, bounds=weight_bounds,
            positions=face.neutral, prior=namesake_prior(names, k_names) if namesake else None,
            elsewhere=driven_gram(others, k_names) if namesake else None)
        del mb_face                                                       # [J, face, 3]: not used again
        report["retarget"] = {"mu": mu_used,
                              "mu_choice": "leave one face region out" if mu == "auto" else "given",
                              "weight_min": float(weights.min()) if weights.size else 0.0,
                              "weight_max": float(weights.max()) if weights.size else 0.0,
                              "bounds": None if weight_bounds is None else list(weight_bounds),
                              "prior": map_prior}
        approx_eq4 = {}
        if approximation == "retarget" and not map_only:
            for m in avatar.meshes:
                approx_eq4[m.key] = approximate(weights, _shape_deltas(m, k_names))
        timings["retarget"] = time.perf_counter() - t
        advance("retarget")
        if map_only:                 # the map is the product: the implant, eyelids and write are not needed
            # the face mesh's own channel per shape (a studio's `JawDrop` for jawOpen): what an engine drives
            tokens = {c[1]: c[0] for c in avatar.name_report.get(face_prim, {}).get("channels", ())
                      if c[1] is not None and c[2] != "conflict"}
            report["retarget"]["channels"] = [tokens.get(n, n) for n in k_names]
            # the implant keeps a shape the capture barely shows near the generic one; the map's row is
            # the fit's shape as it is (a take's never-performed cheekPuff mapped to mouthRollLower 0.54,
            # namesake 0.17, without a word: a user trial). Said, with the shape's strongest entry.
            trust, _, _ = shape_trust(fit, capture, rig, b_idx, person_deltas,
                                      _fit_prior(fit, names, capture, generic_on_capture, sim, prior))
            untrusted = []
            for j in np.flatnonzero(trust < 0.5):
                top = int(np.argmax(weights[j]))
                if k_names[top] != names[j]:
                    own = weights[j, k_names.index(names[j])] if names[j] in k_names else 0.0
                    untrusted.append(f"{names[j]} -> {k_names[top]} {weights[j, top]:.2f} "
                                     f"({names[j]} {own:.2f})")
            if untrusted:
                report["warnings"].append(
                    "map rows of shapes the capture barely shows follow a fit its frames hardly inform "
                    "(personalize keeps these shapes near the avatar's generic ones): " + ", ".join(untrusted)
                    + " (fix: record those expressions, or give their rows the namesake's weight 1 by hand)")
            face_all = scatter(f[:, None], regions[face_prim])[:, 0] if face_prim in regions else f
            _write_pending(pending_cache)
            timings["total"] = time.perf_counter() - t_start
            report["timings"] = timings
            return PersonalizeResult({}, names, k_names, weights, {}, face_prim, face_all,
                                     np.zeros((len(names), len(face_all)), dtype=bool), report, None, fit)
        advance.start("transfer")

        # 5. the implant
        t = time.perf_counter()
        if face_transfer == "person":
            avatar_face_deltas = None           # held by the implant (packed at the run's peak); read after
            result, adjacent, other, avatar_face_deltas = _implant_person(
                avatar, face, whole_face, generic_full, regions, capture, corr, disagree, sim, names, fit,
                rig, prior, generic_on_capture, person_deltas, tmpl_av, extension_length, support, report)
        else:
            base = {m.key: (approx_eq4[m.key] if approximation == "retarget" else _shape_deltas(m, names))
                    for m in avatar.meshes}
            # measured on the capture as placed on the avatar (avatar metres): no second registration scale
            edge = float(corr.info.get("capture_mean_edge_m", 0.0)) if corr.info else 0.0
            result, adjacent = implant_shapes(
                face.neutral, face.triangles, corr, capture.triangles, person_neutral, person_deltas, tmpl_av,
                avatar_face_deltas, base[face_prim], face_transfer=face_transfer,
                falloff=(falloff * edge if falloff and edge > 0 else None), support=support)
            other = {k: v for k, v in base.items() if k != face_prim}
        timings["transfer"] = time.perf_counter() - t
        advance("transfer")
        advance.start("eyelids")

        # 6. eyelids
        t = time.perf_counter()
        if eyelids:
            result = _repair_lids(avatar, face, regions, eyes, result, avatar_face_deltas, report)
        report["lips"] = lip_report(face.neutral, face.triangles, names, avatar_face_deltas, result)
        f = corr.face
        if beyond is not None:                   # the face mesh in one piece again: reached + beyond
            result = _join(result, reached, other.pop(beyond.key), rest)
            f, adjacent = _join(f, reached, False, rest), _join(adjacent, reached, False, rest)
            if beyond.key in approx_eq4:
                approx_eq4[face_prim] = _join(approx_eq4[face_prim], reached, approx_eq4.pop(beyond.key),
                                              rest)
            face = whole_face
            avatar = dataclasses.replace(avatar, meshes=[face if m.key == face_prim else m
                                                         for m in avatar.meshes if m is not beyond])
        timings["eyelids"] = time.perf_counter() - t
        advance("eyelids")
        advance.start("write")

        # offsets for every mesh, in rig.names order; shapes the capture lacks stay generic
        offsets = _layer_offsets(avatar, face, result, other, names, regions, generic_full)
        report.update({
            "face_mesh": face_prim, "shapes": names, "face_vertices": int(f.sum()),
            "adjacent_vertices_max": int(adjacent.sum(axis=1).max()) if adjacent.size else 0,
            # the options the run used: of the mode's own, those it uses (MODE_OPTIONS)
            "options": {"method": method, "reg": reg, "mu": mu, "weight_bounds": weight_bounds,
                        "map_prior": map_prior,
                        "face_transfer": face_transfer,
                        "approximation": approximation, "prior": prior,
                        **{k: v for k, v in (("extension_length", extension_length), ("falloff", falloff),
                                             ("support", support)) if k in MODE_OPTIONS[face_transfer]},
                        "eyelids": eyelids,
                        **(_recorded_fit_options(method, fit_options) if fit is not None else {})},
            "name_report": avatar.name_report,
            "changes": _changes(avatar, offsets, regions),
        })

        # 7. write
        t = time.perf_counter()
        written = None
        if out_path is not None and not dry_run:
            from ..io.layers import write_avatar_layer
            from .retarget import weight_map_rows

            extra = {role: str(p) for role, p in (extra_inputs or {}).items() if isinstance(p, str | Path)}
            prov = {"command": command or "usdface personalize",
                    "parameters": {k: (v if isinstance(v, int | float | str | bool) else str(v))
                                   for k, v in report["options"].items()},
                    "method": method,
                    "inputs": ([str(capture.source)] if capture.source else [])
                    + ([str(name_map)] if isinstance(name_map, str | Path) else [])
                    + _pins_input(fit_options.get("pins") if fit is not None else None, capture.source)
                    + list(extra.values()),
                    **extra,
                    "registrationScale": float(sim.scale),
                    "registrationResidual": float(registration.residual),
                    "registration": dict(report["registration"]),
                    "correspondence": {k: v for k, v in report["correspondence"].items()
                                       if isinstance(v, int | float | str)},
                    **({"fitTestExpressions": report["fit"]["test_expressions"]}
                       if "test_expressions" in report.get("fit", {}) else {}),
                    "retargetMap": weight_map_rows(np.round(weights, 6), names, k_names, threshold=1e-6),
                    "retargetMu": float(mu_used), "retargetMuChoice": report["retarget"]["mu_choice"],
                    "warnings": list(report["warnings"]),
                    "timings": dict(timings)}
            if (report.get("fit") or {}).get("pins"):          # the artist pins: {shape: pinned vertices}
                prov["pins"] = {str(k): int(v) for k, v in report["fit"]["pins"].items()}
            edit = layer_edit(offsets, face_prim) if layer_edit is not None else None
            written = write_avatar_layer(avatar, out_path, offsets, provenance=prov, force=force, edit=edit)
        _write_pending(pending_cache)            # the correspondence cache, once the run has succeeded
        timings["write"] = time.perf_counter() - t
        advance("write")
    timings["total"] = time.perf_counter() - t_start
    report["timings"] = timings
    if face_prim in regions:                                      # the face mesh's regions on every vertex
        f, adjacent = scatter(f[:, None], regions[face_prim])[:, 0], scatter(adjacent[..., None],
                                                                           regions[face_prim])[..., 0]
    approx_eq4 = {k: (SparseOffsets(regions[k].vertices, v, regions[k].n, copies=regions[k].copies)
                      if k in regions else v)
                  for k, v in approx_eq4.items()}
    return PersonalizeResult(offsets, names, k_names, weights, approx_eq4, face_prim, f, adjacent, report,
                             written, fit)


#: An avatar whose main mesh's centre lies within this many of its sizes from the origin is left where it is
#: (the bench heads and an avatar at the stage's origin: their answers unchanged to the bit).
NEAR_ORIGIN = 20.0


def _write_pending(pending: list) -> None:
    """Write the correspondence caches :func:`_correspondence` held back (``(path, npz bytes)``)."""
    for path, data in pending:
        save_correspondence(None, path, data=data)
    pending.clear()


def _in_stage(similarity: dict, origin) -> dict:
    """A similarity's record (``translation_m`` among its keys) found on the avatar moved by ``-origin``
    (:func:`near_origin`), as it places the capture in the stage's frame."""
    return {**similarity, "translation_m": (np.asarray(similarity["translation_m"]) + origin).tolist()}


def near_origin(avatar: Avatar) -> tuple[Avatar, np.ndarray]:
    """``(avatar, origin[3])``: the avatar with every mesh's rest points (its part's full points, the static
    meshes) moved by ``-origin``, the centre of its main mesh's (the one with the most shapes, then
    vertices) bounding box: where its points are, whether placed by transforms or baked into the points.
    Offsets do not change with a translation, and the steps then see coordinates of a head's size: an
    avatar placed 50 m or 500 m from the stage's origin gives the answer it gives at the origin (the float32
    noise floor of :func:`usdface.motion.moving_vertices` grows with the coordinates' size: at 500 m it took
    0.5 mm motions for float noise, and 26 shapes changed by more than 10 %). An avatar already there (its
    centre within :data:`NEAR_ORIGIN` of its size from the origin, or without a source) is returned as is."""
    rigs = [m for m in avatar.meshes if m.source is not None]
    if not rigs:
        return avatar, np.zeros(3)
    main = max(rigs, key=lambda m: (m.n_shapes, m.n_vertices))
    if main.n_vertices == 0:
        return avatar, np.zeros(3)
    origin = 0.5 * (main.neutral.min(axis=0) + main.neutral.max(axis=0))
    if np.all(np.abs(origin) <= NEAR_ORIGIN * float(np.ptp(main.neutral, axis=0).max())):
        return avatar, np.zeros(3)

    def moved(m: FaceRig) -> FaceRig:
        src = m.source
        if src is not None and src.region is not None and src.region.points is not None:
            src = dataclasses.replace(src, region=dataclasses.replace(src.region,
                                                                      points=src.region.points - origin))
        return dataclasses.replace(m, neutral=m.neutral - origin, source=src)

    meta = dict(avatar.metadata)
    if meta.get("static_meshes"):
        meta["static_meshes"] = {k: (np.asarray(p, dtype=np.float64) - origin, t)
                                 for k, (p, t) in meta["static_meshes"].items()}
    return dataclasses.replace(avatar, meshes=[moved(m) for m in avatar.meshes], metadata=meta), origin


def _check_modes(face_transfer: str, approximation: str | None, prior: str, weight_bounds=None,
                 map_prior: str = "namesake") -> str:
    """Refuse unknown or mismatched transfer modes and a bad retarget map setting before any work
    (:class:`usdface.errors.UsdFaceError`); returns the approximation to use (``approximation``, or
    :func:`default_approximation` of ``face_transfer`` when None)."""
    if map_prior not in MAP_PRIORS:
        raise UsdFaceError(f"unknown map prior {map_prior!r}", fix=f"use one of {', '.join(MAP_PRIORS)}")
    if weight_bounds is not None:
        from ..errors import OptionError

        name = option_name("weight_bounds")
        try:
            if isinstance(weight_bounds, str):     # its characters are no bounds: "01" read as (0, 1)
                raise TypeError
            lo, hi = (float(b) for b in weight_bounds)
        except (TypeError, ValueError):
            raise OptionError(f"bad weight bounds {weight_bounds!r}: {name} takes two numbers",
                              fix="give two finite numbers LO < HI, e.g. (0, 1) ([0, 1] in a batch manifest "
                                  "or --set); for no bounds use weight_bounds=None (--unbounded), null in a "
                                  "batch manifest") from None
        if not (np.isfinite(lo) and np.isfinite(hi)):
            raise OptionError(f"bad weight bounds {lo:g} {hi:g}: {name} must be finite",
                              fix="give two finite numbers LO < HI, e.g. (0, 1); for no bounds use "
                                  "weight_bounds=None (--unbounded)")
        if not lo < hi:
            raise OptionError(f"bad weight bounds {lo:g} {hi:g}: {name} needs LO < HI",
                              fix="give LO < HI, e.g. (0, 1) (--weight-bounds 0 1); for no bounds use "
                                  "weight_bounds=None (--unbounded)")
    if face_transfer not in FACE_TRANSFERS:
        raise UsdFaceError(f"unknown face transfer {face_transfer!r}",
                           fix=f"use one of {', '.join(FACE_TRANSFERS)}")
    if approximation is None:
        approximation = default_approximation(face_transfer)
    if approximation not in APPROXIMATIONS:
        raise UsdFaceError(f"unknown approximation {approximation!r}",
                           fix=f"use one of {', '.join(APPROXIMATIONS)}")
    if prior not in PRIORS:
        raise UsdFaceError(f"unknown prior {prior!r}", fix=f"use one of {', '.join(PRIORS)}")
    if (face_transfer == "person") != (approximation == "field"):
        from ..errors import OptionError

        raise OptionError(f"{option_name('face_transfer')} {face_transfer!r} and "
                          f"{option_name('approximation')} {approximation!r} do not go together",
                          fix="use face_transfer='person' with approximation='field' (the default), or one "
                              "of the older modes with 'generic' or 'retarget' (leave the approximation out "
                              "for the mode's default)")
    return approximation


def check_numbers(*, mu="auto", extension_length=1.0, falloff=0.15, support=(0.01, 0.03)) -> None:
    """Refuse, before any work, numeric options of :func:`personalize_avatar` the work would choke on or
    silently misuse (NaN, inf, zero or negative where a size or a weight is meant, a non-number), as the CLI's
    argument types do (:mod:`usdface.commands.options`): ``mu`` ``"auto"`` or > 0, ``extension_length`` None
    or > 0, ``falloff`` >= 0, ``support`` None or ``(low, high)`` with ``0 <= low <= high``."""
    from ..personalize.api import check_number

    def _number(name, value, **how):
        return check_number(name, value, error=UsdFaceError, **how)

    _number("mu", mu, low=0.0, inclusive=False, fix="use 'auto' or a number > 0 (the eq. 4 ridge weight)",
            keywords=("auto",))
    if extension_length is not None:
        _number("extension_length", extension_length, low=0.0, inclusive=False,
                fix="a length in face radii > 0 (1 = the default), or None for no fade")
    _number("falloff", falloff, low=0.0, inclusive=True, fix="capture edge lengths >= 0 (0 = harmonic join)")
    if support is not None:
        try:
            if isinstance(support, str):            # its characters are no fractions: "01" read as (0, 1)
                raise TypeError
            lo, hi = support
        except (TypeError, ValueError):
            raise UsdFaceError(f"bad support {support!r}", fix="give (low, high) fractions of each shape's "
                               "peak motion, e.g. (0.01, 0.03) ([0.01, 0.03] in a batch manifest), or None"
                               ) from None
        lo = _number("support low", lo, low=0.0, inclusive=True, fix="e.g. support=(0.01, 0.03)")
        hi = _number("support high", hi, low=0.0, inclusive=True, fix="e.g. support=(0.01, 0.03)")
        if lo > hi:
            raise UsdFaceError(f"bad support {support!r}: low > high", fix="e.g. support=(0.01, 0.03)")


def _recorded_fit_options(method: str, fit_options: dict) -> dict:
    """The fit's options a layer's provenance records besides the method and ``reg``: those given (numbers,
    words; the artist pins are recorded as ``pins`` and their file among the inputs) and the lip and eyelid
    ``contact`` (default ``"auto"``) when the method uses it."""
    from ..personalize.api import METHOD_TAKES

    out = {k: v for k, v in fit_options.items()
           if k not in ("pins", "contact") and (v is None or isinstance(v, int | float | str | bool))}
    if "contact" in METHOD_TAKES.get(method, ()):
        out["contact"] = fit_options.get("contact", "auto")
    return out


def _pins_input(pins, capture_source) -> list[str]:
    """``[file]`` the artist ``pins`` were read from (:class:`usdface.io.pins.Pins`), for the layer's
    recorded inputs (with its digest, as the capture's); [] for pins given as arrays, or read from the
    capture itself."""
    source = getattr(pins, "source", None)
    if source is None:
        return []
    if capture_source and Path(source).resolve() == Path(capture_source).resolve():
        return []
    return [str(source)]


def _fit_prior_options(prior: str, method: str, reg) -> dict:
    """The fit's prior options for personalize's ``prior``: with ``"avatar"`` (menzel / laplacian) the
    avatar's own shapes on the capture are given, chosen among the priors by cross-validation with
    ``reg="auto"`` and used as the prior with any other ``reg``; ``{"avatar_prior": True}`` marks that."""
    if prior != "avatar" or method not in ("menzel", "laplacian"):
        return {}
    return {"avatar_prior": True} if isinstance(reg, str) and reg == "auto" else {"avatar_prior": True,
                                                                                  "prior": "avatar"}


def _fit(capture, names, generic_on_capture, prior, method, reg, fit_options):
    """Step 1 (:func:`usdface.personalize.fit_personalized_shapes`), after the correspondence: with
    ``prior="avatar"`` the avatar's own shapes on the capture (``generic_on_capture[J,n,3]``, capture frame,
    metres; NaN rows for the capture's shapes the avatar lacks) are the prior of menzel / laplacian
    (:func:`_fit_prior_options`)."""
    from ..personalize import fit_personalized_shapes

    extra = _fit_prior_options(prior, method, reg)
    if extra.pop("avatar_prior", False):
        full = np.full((len(capture.names), capture.template.n_vertices, 3), np.nan)
        full[[list(capture.names).index(n) for n in names]] = generic_on_capture
        extra["avatar_prior"] = full
    # the implant's trust reads each shape's sensitivity to the weights' noise (sensitivity_trust)
    return fit_personalized_shapes(capture, method=method, reg=reg, sensitivity=True, **extra, **fit_options)


def _repair_lids(avatar, face, regions, eyes, result, generic, report) -> np.ndarray:
    """Step 6: the eyelid repair (:func:`usdface.transfer.eyelids.repair_eyelids`) of ``result[J,m,3]``
    against the avatar's eyeballs - ``eyes`` ({name: (points, triangles)}), the reader's static meshes, or
    the other meshes that are eyeballs by the *whole* mesh's shape - with ``generic[J,m,3]`` as the
    clearance reference. Returns the repaired offsets (in place); adds ``report["eyelids"]``."""
    eye_meshes = dict(eyes or avatar.metadata.get("static_meshes") or {})
    for m in avatar.meshes:
        if m is not face:
            eye_meshes.setdefault(m.key, (m.neutral, m.triangles))
    # an eyeball is found by the whole mesh's shape, not by its moving part
    eye_meshes.update({k: (regions[k].points, regions[k].vertices[v[1]])
                       for k, v in eye_meshes.items() if k in regions})
    rejected: list[str] = []
    found = find_eyeballs({k: v[0] for k, v in eye_meshes.items()}, face=face.neutral, rejected=rejected)
    repaired = 0
    if found:
        result, repaired = repair_eyelids(face.neutral, result, [(e, *eye_meshes[e.name]) for e in found],
                                          reference=generic, overwrite=True)
    report["eyelids"] = {"eyeballs": [e.name for e in found], "repaired_vertex_shapes": repaired}
    if not found:
        report["warnings"].append("no eyeball meshes found: eyelid repair skipped"
                                  + (" (" + "; ".join(rejected) + ")" if rejected else ""))
    return result


def _layer_offsets(avatar, face, result, other, names, regions, generic_full) -> dict:
    """{mesh key: offsets in the mesh's own shape order} for the layer: ``result[J,m,3]`` on the face mesh,
    ``other[key][J,n,3]`` on the others, the input's offsets for the shapes not in ``names``; a mesh worked
    on by its moving part as :class:`usdface.submesh.SparseOffsets` over the caller's whole-mesh array."""
    offsets = {}
    for m in avatar.meshes:
        key = m.key
        src = result if m is face else other.get(key)
        if m is face and list(names) == list(m.names) and np.shape(result) == m.deltas.shape:
            new = result                      # every shape personalized, in the rig's order: no copy
        else:
            new = m.deltas.copy()
        if src is not None and new is not src:
            for j, n in enumerate(names):
                if n in m.names:
                    new[m.index(n)] = src[j]
        region = regions.get(key)
        if region is None:
            offsets[key] = new
            continue
        base = generic_full.get(key)
        offsets[key] = SparseOffsets(region.vertices, new, region.n,
                                     base=base if base is not None and base.shape[1] == region.n else None,
                                     copies=region.copies)
    return offsets


def _implant_person(avatar, face, whole_face, generic_full, regions, capture, corr, disagree, sim, names, fit,
                    rig, prior, generic_on_capture, person_deltas, tmpl_av, extension_length, support,
                    report) -> tuple[np.ndarray, np.ndarray, dict, np.ndarray]:
    """Step 5 of the default transfer: the person's motion on the face region (``A_j + c_j M s_j (B_j -
    P_j)``, :func:`usdface.transfer.implant.face_personalization`), extended as a rotation + scale field of
    the generic motion beyond it and onto the meshes that follow the skin (:mod:`.motion_field`).
    ``person_deltas[J,n,3]`` / ``tmpl_av[J,n,3]``: the person's and the template's capture shapes in the
    avatar frame (metres). Returns ``(result[J,m,3], adjacent[J,m] bool, {mesh key: [J,n_mesh,3]}, the
    face's generic offsets [J,m,3])`` and adds the confidence, mapping outliers and extension figures to
    ``report``.

    The face's generic offsets are held packed during the field (the run's peak) when they are large
    (:class:`_HeldPacked`): the caller lets go of its own references to them first."""
    f = corr.face
    b_idx = [rig.index(n) for n in names]
    prior_av = _fit_prior(fit, names, capture, generic_on_capture, sim, prior)
    conf, excitation, weak = shape_trust(fit, capture, rig, b_idx, person_deltas, prior_av)
    if excitation:
        report["excitation"] = excitation
    report["shape_confidence"] = {n: round(float(c), 3) for n, c in zip(names, conf, strict=True)}
    low = conf < 0.5
    barely = [n for n, lo, wk in zip(names, low, weak, strict=True) if lo and wk]
    noisy = [n for n, lo, wk in zip(names, low, weak, strict=True) if lo and not wk]
    if barely:
        report["warnings"].append("the capture barely shows (kept closer to the avatar's generic "
                                  "shape): " + ", ".join(barely))
    # shown, but the person's difference from the prior is no larger than the fit's noise in them (a shape
    # only ever shown beside another at nearly the same weights, another shape's weight error leaking into
    # it, or a person who differs little there): kept near the avatar's, as the data cannot tell better
    report["within_noise"] = noisy
    # capture vertices the correspondence got wrong for a shape (the avatar's motion there is
    # incompatible with the person's and the template's): no personalization from them
    outliers = mapping_outliers(person_deltas, prior_av, tmpl_av, triangles=capture.triangles)
    report["correspondence"]["mapping_outliers"] = int(outliers.sum())
    weight = corr.weight if corr.weight is not None else corr.face.astype(float)
    # where the mapped template and the avatar disagree on what a semantic shape moves (a lid or a
    # lip on the other side), the capture is not trusted: the field from the neighbours fills in
    weight = weight * ~dilate(disagree, face.triangles, 2)
    radius = face_radius(face.neutral[weight >= 1.0 - 1e-9])
    length = extension_length * radius if extension_length else None
    eyeballs_static = set((avatar.metadata.get("static_meshes") or {}).keys())
    others = [m for m in avatar.meshes if m is not face and m.key not in eyeballs_static]
    followers = [m for m in others if not _is_eyeball(m, regions)]      # eyeballs keep their shapes
    keep_at = np.concatenate([m.neutral for m in followers]) if followers else np.zeros((0, 3))
    # the field is known at the capture's resolution: averaged over one placed capture edge
    # (the correspondence measured it on the placed capture, in avatar metres: the registration's scale is
    # in it once already)
    smoothing = float((corr.info or {}).get("capture_mean_edge_m", 0.0)) or None
    # during the field (the run's peak) the face's generic offsets - and those of the whole face
    # mesh when it was split (reached + beyond), used only after the field - are held as the
    # authored float32 and the reader's conversion (the same values to the last bit)
    split = (whole_face, whole_face.names) if whole_face is not face else None
    with _HeldPacked(generic_full, [(face, names), split]) as held:

        def person_face():
            """``A_j + c_j M s_j (B_j - P_j)`` on the face rows (a few shapes at a time), formed by
            the field once its extension is factorized (:func:`extend_personalization`)."""
            out = packed.expand() if packed is not None else _shape_deltas(face, names, view=True).copy()
            for lo in range(0, len(names), 8):
                js = slice(lo, lo + 8)
                change = face_personalization(corr, capture.triangles, person_deltas[js],
                                              prior_av[js], f, support=support, outliers=outliers[js])
                change *= conf[js, None, None]
                out[js, f] += change
            return out

        release_free_memory()              # the read's and the fit's freed blocks, before the peak
        # the result is written over person_face (not used again): one [J,m,3] array fewer at the peak
        packed = held.packed(0)
        result, pfield = extend_personalization(face.neutral, face.triangles,
                                               _shape_deltas(face, names, view=True) if packed is None
                                               else packed, person_face, weight, length=length,
                                               band=SEAM_BAND * radius, smoothing=smoothing,
                                               keep_at=keep_at, overwrite=True)
        packed = None                      # (person_face is not called again)
        release_free_memory()              # the field's freed working memory
    generic = _shape_deltas(face, names, view=True)       # the float64 generic offsets again, as read
    adjacent = _changed(result, generic, weight < 1.0)
    other = {}
    for m in others:
        sub = _shape_deltas(m, names)
        other[m.key] = (follow_field(m.neutral, sub, pfield, rigid=rigid_shapes(m.neutral, sub))
                        if any(m is x for x in followers) else sub)
    report["extension"] = {"length_m": length, "face_radius_m": radius, "smoothing_rings": pfield.rings}
    return result, adjacent, other, generic


def _is_eyeball(m: FaceRig, regions: dict | None = None) -> bool:
    region = (regions or {}).get(m.key)
    return bool(find_eyeballs({m.key: m.neutral if region is None else region.points}))


def corr_transform(corr, fallback):
    """The similarity that placed the capture template for ``corr`` (from its info), else ``fallback``."""
    from .register import Similarity

    reg = (corr.info or {}).get("template_registration")
    if not reg:
        return fallback
    return Similarity(float(reg["scale"]), np.asarray(reg["rotation"]), np.asarray(reg["translation_m"]))


def correspondence_semantics(corr, capture_triangles, names, template_deltas, avatar_deltas, transform,
                             *, moving: float = 0.1) -> dict:
    """How well the map keeps the shapes' meaning: for the semantic shapes (jawOpen, the blinks), over the
    face vertices that move (more than ``moving`` of the peak on either rig), the share whose mapped template
    motion opposes the avatar's own (negative dot product), and the lip/lid *side swaps*: vertices that move
    more than half the peak on one rig and less than a fifth on the other. Returns ``(figures, swapped[m])``,
    the second the face-mesh vertices of those swaps."""
    f = np.flatnonzero(corr.face)
    sig_total, opposing, swaps = 0, 0, {}
    disagree = np.zeros(len(corr.face), dtype=bool)
    for name in SEMANTIC_SHAPES:
        if name not in names:
            continue
        j = names.index(name)
        mt = corr.apply(transform.apply_vectors(template_deltas[j])[None], capture_triangles, rows=f)[0]
        a = np.asarray(avatar_deltas[j])[f]
        na, nm = np.linalg.norm(a, axis=1), np.linalg.norm(mt, axis=1)
        pa = max(float(na.max()), 1e-300)
        pm = max(float(np.linalg.norm(transform.apply_vectors(template_deltas[j]), axis=1).max()), 1e-300)
        ra, rm = na / pa, nm / pm
        sig = np.maximum(ra, rm) > moving
        sig_total += int(sig.sum())
        opposing += int((sig & (np.einsum("ij,ij->i", a, mt) < 0)).sum())
        swapped = ((ra > 0.5) & (rm < 0.2)) | ((ra < 0.2) & (rm > 0.5))
        swaps[name] = int(swapped.sum())
        disagree[f[swapped]] = True
    return {"opposing_share": opposing / max(sig_total, 1), "side_swaps": int(sum(swaps.values())),
            **{f"side_swaps_{k}": v for k, v in swaps.items()}}, disagree


#: Shapes whose lips the lip check looks at (``mouthClose`` posed on ``jawOpen``, as ARKit authors it).
LIP_SHAPES = ("mouthClose", "mouthPressLeft", "mouthPressRight", "mouthRollLower", "mouthRollUpper",
              "mouthPucker", "mouthFunnel", "mouthShrugLower")


def lip_report(points, triangles, names, generic, output) -> dict:
    """Lower-lip vertices past the upper lip (:func:`usdface.personalize.contact.lip_crossings`, the lips
    found by their motion under the generic ``jawOpen``) per lip shape, generic beside output:
    ``{shape: {"generic": [count, deepest mm], "output": [count, deepest mm]}}``; ``{}`` without jawOpen.
    ``generic``/``output`` ``[J,m,3]`` in ``names`` order."""
    from ..personalize.contact import lip_crossings, lip_pairs_from_motion

    if "jawOpen" not in names:
        return {}
    jaw = names.index("jawOpen")
    try:
        pairs = lip_pairs_from_motion(points, generic[jaw])
    except GeometryError:
        return {}
    out = {}
    for name in LIP_SHAPES:
        if name not in names:
            continue
        j = names.index(name)
        row = {}
        for label, d in (("generic", generic), ("output", output)):
            pose = d[j] + (d[jaw] if name == "mouthClose" else 0.0)
            c = lip_crossings(points, triangles, pose, openings=[], pairs=pairs)
            row[label] = [c.count, round(c.max_depth * 1e3, 3)]
        out[name] = row
    return out


def _fit_prior(fit, names, capture, generic_on_capture, sim, prior):
    """The prior ``P_j`` the fit shrank each shape towards, in the avatar frame (``[J,n,3]``): the fit's own
    (``info["prior_deltas"]``, menzel/laplacian); for dt/ebfr the deformation transfer of the chosen prior;
    for a given rig (no fit) the prior itself."""
    cap_idx = [list(capture.names).index(n) for n in names]
    used = fit.info.get("prior_deltas") if fit is not None else None
    if used is not None:
        return sim.apply_vectors(np.asarray(used)[cap_idx])
    template = capture.template.deltas[[capture.template.names.index(n) for n in names]]
    if fit is None:   # a given rig: measured against the avatar's shapes on the capture where there are any
        return sim.apply_vectors(generic_on_capture if generic_on_capture is not None else template)
    base = generic_on_capture if prior == "avatar" else template
    from ..personalize.dt import deformation_transfer

    return sim.apply_vectors(deformation_transfer(capture.template.neutral, base, capture.neutral,
                                                  capture.triangles, names=list(names)))


def _changed(result, generic, where) -> np.ndarray:
    """``[J,m]`` bool: vertices ``where[m]`` whose offset in ``result[J,m,3]`` differs from ``generic[J,m,3]``
    by more than 1e-9 m, formed shape by shape (no ``[J,m,3]`` difference)."""
    out = np.zeros(result.shape[:2], dtype=bool)
    for j in range(len(out)):
        out[j] = where & (shape_norms(result[j:j + 1] - generic[j:j + 1])[0] > 1e-9)
    return out


def _changes(avatar: Avatar, offsets: dict, regions: dict | None = None) -> list[dict]:
    """Per mesh and shape: largest and RMS change of the offsets (m) - what ``--dry-run`` prints. A mesh held
    on its moving part (``regions``, offsets :class:`usdface.submesh.SparseOffsets`) changes nowhere else."""
    rows = []
    for m in avatar.meshes:
        key = m.key
        new = offsets[key]
        copies = new.copies if isinstance(new, SparseOffsets) else None
        new = new.values if isinstance(new, SparseOffsets) else new
        K, held = m.deltas.shape[:2]
        n_full = regions[key].n if regions and key in regions else m.n_vertices
        # a welded part's vertex stands for itself and its copies (written with its offsets)
        count = (1 + np.bincount(copies[1], minlength=held) if copies is not None
                 else np.ones(held, dtype=np.int64))
        peak, rms, moved = np.zeros(K), np.zeros(K), np.zeros(K, dtype=np.int64)
        for k in range(K):                   # shape by shape: no [K,n] array (the twice-subdivided head's
            d = new[k] - m.deltas[k]         # 94 MB of them set the run's peak, +125 MB)
            sq = np.einsum("nc,nc->n", d, d)                             # squared change on the part held
            peak[k] = np.sqrt(sq.max()) if held else 0.0
            rms[k] = np.sqrt(sq @ count / max(n_full, 1))
            moved[k] = (sq > 1e-18) @ count
        for k, n in enumerate(m.names):
            rows.append({"mesh": key, "shape": n, "max_change_m": float(peak[k]),
                         "rms_change_m": float(rms[k]), "moved_vertices": int(moved[k])})
    return rows
