"""``usdface personalize``: fit the person's shapes on the capture, implant them into the avatar, write the
layer.

Steps (Menzel et al. 2022, sec. 3.2-3.3), each a pure function on arrays in another module:

1. fit the personalized capture shapes B_j (:func:`usdface.personalize.fit_personalized_shapes`);
2. register the capture neutral onto the avatar face (:mod:`.register`, ICP with scaling);
3. correspondence map M and face region (:mod:`.correspond`; guided by the shapes' motion and cached per
   avatar + template, :mod:`.face_map`);
4. automatic retargeting, eq. (4) (:mod:`.retarget`): weight map and approximations A_j;
5. seamless partial transfer (:mod:`.partial_dt`): face from B_j, adjacent region blended from the
   approximation, every other vertex and mesh follows the approximation;
6. eyelid-eyeball repair (:mod:`.eyelids`);
7. the layer (:func:`usdface.io.layers.write_avatar_layer`).

Every step works on the part of each mesh its shapes move (:mod:`usdface.submesh`: read that way, or cropped
after reading; the offsets go back as :class:`usdface.submesh.SparseOffsets`), and the face mesh's separate
pieces beyond the capture's reach are handled as another mesh (:func:`.face_map.reached_parts`). The options
and their checks are :mod:`.options`, the report's figures :mod:`.report`.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import CaptureError, RigError, warn
from ..memory import release_free_memory
from ..model import Avatar, Capture, FaceRig
from ..motion import meshes_by_motion, moving_vertices, peak_motion, refuse_several_characters
from ..personalize.api import left_out_scale, single_threaded_blas
from ..personalize.evaluate import test_expression_errors
from ..progress import steps
from ..submesh import SparseOffsets, crop, crop_avatar, crop_rig, rig_on, scatter
from .correspond import border_reach, save_correspondence
from .denoise import denoise_personalization
from .eyelids import find_eyeballs, repair_eyelids
from .face_map import (
    cached_correspondence,
    corr_transform,
    correspondence_semantics,
    reached_parts,
    rough_placement,
    semantic_poses,
)
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
from .options import (
    check_modes,
    check_numbers,
    fit_prior_options,
    pins_input,
    run_options,
)
from .partial_dt import implant_shapes
from .register import face_surface, motion_landmarks, register_face
from .report import changed_vertices, layer_provenance, lip_report, offset_changes, untrusted_map_rows
from .retarget import approximate, driven_gram, gaze_held, namesake_prior, retarget_weights
from .surface import mean_edge_length
from .trust import shape_trust

__all__ = ["PersonalizeResult", "personalize_avatar"]

#: Names this module held until stop 33, and the module that holds each now: still importable from here,
#: with a DeprecationWarning (:func:`__getattr__`), so a studio script written against the older layout keeps
#: working.
#: (The moved names this module still imports for its own use, as ``implant_shapes``, import as before.)
MOVED = {**dict.fromkeys(("FACE_TRANSFERS", "APPROXIMATIONS", "MODE_OPTIONS", "MODE_ONLY_OPTIONS",
                          "IMPLANT_OPTIONS", "PRIORS", "MAP_PRIORS", "option_name", "check_mode_options",
                          "modes_using", "default_approximation"), "options"),
         **dict.fromkeys(("SEMANTIC_SHAPES", "pose_by_length"), "face_map"),
         "LIP_SHAPES": "report"}


def __getattr__(name: str):
    """A name of :data:`MOVED`, from its module now, with a DeprecationWarning naming where it lives."""
    if name in MOVED:
        import importlib

        module = f"{__package__}.{MOVED[name]}"
        warn(f"usdface.transfer.pipeline.{name} moved to {module}.{name}; import it from there",
             DeprecationWarning)
        return getattr(importlib.import_module(module), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


#: Width of the join between the face region and the field beyond, in face radii: 1.1-1.2 cm on a head, so it
#: spans several edge rings even of a coarse 24k-vertex head (three; a 7 mm join spanned fewer than two and
#: left a step where the direct result and the field differ), and more on finer meshes.
SEAM_BAND = 0.2

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

    def __repr__(self) -> str:
        # one line (the dataclass repr printed every offset array: ~55 kB for a 4k-vertex avatar)
        meshes = ", ".join(map(str, self.offsets))
        if not self.offsets and len(self.avatar_names):  # usdface retarget's: the map, no implant
            return (f"<PersonalizeResult {self.out_path or '(not written)'}: retarget map of "
                    f"{len(self.names)} shapes onto {len(self.avatar_names)} avatar shapes of "
                    f"{self.face_mesh} (no implant)>")
        return (f"<PersonalizeResult {self.out_path or '(not written)'}: {len(self.names)} shapes implanted, "
                f"{len(self.offsets)} mesh(es) ({meshes}), face mesh {self.face_mesh}>")


def _face_mesh(avatar: Avatar, names: list[str]) -> FaceRig:
    """The mesh where the shared ARKit shapes move the most vertices (the face/head mesh); float noise of an
    export is not motion (the first of :func:`usdface.motion.meshes_by_motion`)."""
    ranked = meshes_by_motion(avatar.meshes, names)
    best = ranked[0][0] if ranked else None
    refuse_several_characters(avatar, ranked)
    if best is None:
        # say which channels the avatar has and what a name map did not match (a refusal that named no
        # prim and no channel left a TD with a Blender export's 'Key_1' guessing)
        shown = [f"{m.source.prim if m.source else m.name}: {', '.join(m.names[:6])}"
                 + (f" (+{len(m.names) - 6})" if len(m.names) > 6 else "") for m in avatar.meshes[:3]]
        unused = [n for n in avatar.metadata.get("notes", []) if n.startswith("name map entries that match")]
        prim = avatar.meshes[0].source.prim if avatar.meshes and avatar.meshes[0].source else None
        from ..arkit import ARKIT_NAMES

        if any(n in ARKIT_NAMES for m in avatar.meshes for n in m.names):
            # ARKit-named, but moving no point (Pixar's normalOffsets-only shapes under a name map): "name
            # them as ARKit does" was no fix
            raise RigError("the avatar's ARKit-named blend shapes move no point (zero offsets, or "
                           "normalOffsets only); its channels: " + "; ".join(shown), path=avatar.file,
                           prim=prim, fix="author the shapes' point offsets (usdface check AVATAR lists the "
                                          "shapes that move nothing)")
        raise RigError("the avatar has no face-like blend shapes (no ARKit-named shape that moves); its "
                       "channels: " + "; ".join(shown) + ("; " + "; ".join(unused) if unused else ""),
                       path=avatar.file, prim=prim,
                       fix="name the face shapes as ARKit does (eyeBlinkLeft, jawOpen, ...) or map the rig's "
                           "channel names with --name-map FILE (name_map=); 'usdface inspect AVATAR' lists "
                           "how each was mapped")
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
    return Float32Offsets.pack(rig.deltas, rig.source.to_internal[:3, :3], peak=rig.peak_motion())


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


@single_threaded_blas
def personalize_avatar(avatar, capture, out_path=None, *, method: str = "menzel", reg="auto",
                       mu="auto", correspondence=None, force: bool = False, dry_run: bool = False,
                       face_transfer: str = "person", approximation: str | None = None, falloff: float = 0.15,
                       support=(0.01, 0.03), eyelids: bool = True, eyes: dict | None = None,
                       rig: FaceRig | None = None, prior: str = "avatar", face_mesh: str | None = None,
                       name_map=None, extension_length: float | None = 1.0, command: str = "",
                       weight_bounds=(0.0, 1.0), map_prior: str = "namesake", map_gaze: str = "namesake",
                       layer_edit=None,
                       map_only: bool = False, extra_inputs: dict | None = None,
                       pending_cache: list | None = None, **fit_options) -> PersonalizeResult:
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
    pending_cache : a list that receives the ``correspondence`` cache's ``(path, npz bytes)`` for the caller
        to write once its own run has succeeded (:func:`usdface.api.write_retarget_map` writes its map after
        this returns); None (default): written here once the layer is (or, ``map_only``, the map made).
    extra_inputs : ``{role: path}``, more files the layer is made from (``{"take": path}``, the take its
        inspection animation plays): recorded with their digests among its inputs, so that editing one makes
        the layer stale, and each under its role in the provenance (relative to the layer, as the inputs),
        which ``usdface review`` reads back.
    layer_edit : ``layer_edit(offsets, face_prim) -> edit(stage)`` (or None): extra prims and primvars
        authored into the layer in the same atomic write (the inspection data of
        :func:`usdface.api.personalize_avatar`), from the offsets that are written.
    map_prior : what eq. (4)'s ridge shrinks each row towards: ``"namesake"`` (default: the avatar shape of
        the same ARKit name, weight 1, as a hand-made retargeting table) or ``"zero"`` (the paper).
    map_gaze : how eq. (4)'s map treats the gaze channels (``eyeLook*``, which an engine turns the eyes with):
        ``"namesake"`` (default): a gaze channel is driven by its namesake capture shape alone (the other
        rows' entries held at 0, :func:`usdface.transfer.retarget.gaze_held`); ``"free"``: eq. (4) as it is.
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
        approximation A_j (the paper). None (default): :func:`.options.default_approximation` of
        ``face_transfer``.
    extension_length : with ``"field"``, how far the person's field reaches beyond the face before it fades
        to the generic motion, in face radii (RMS radius of the face region; None = no fade).
    falloff, support : the join of the older modes (:func:`implant_shapes`); ``support`` also ramps the
        person's personalization. Which mode uses which: :data:`.options.MODE_OPTIONS` (the API and the
        commands refuse one the mode does not use, :func:`.options.check_mode_options`; this function takes
        them all).
    face_mesh : prim path (or name) of the face mesh; default: the mesh the shared ARKit shapes move most.
    eyelids : step 6; ``eyes`` = {name: (points[n,3], triangles[t,3])} internal metres, closed eye meshes
        (else taken from ``avatar.metadata["static_meshes"]`` when the reader provides it, or from avatar
        meshes that are eyeballs by name/geometry).
    """
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    report: dict = {"warnings": []}
    approximation = check_modes(face_transfer, approximation, prior, weight_bounds, map_prior, map_gaze)
    check_numbers(mu=mu, extension_length=extension_length, falloff=falloff, support=support)
    # a numeric string passes the check (as the CLI's "0.01" does), and is the number from here on: mu="0.01"
    # went on to retarget_weights' ValueError after the registration and the fit
    mu, extension_length, falloff = (float(v) if isinstance(v, str) and v != "auto" else v
                                     for v in (mu, extension_length, falloff))
    if rig is None:                                # the fit's options, before any work
        from ..personalize.api import check_fit_options

        check_fit_options(method, reg, **fit_prior_options(prior, method), **fit_options)
    own_cache = pending_cache is None             # the correspondence cache, written once the run succeeds
    pending_cache = [] if own_cache else pending_cache
    with steps("retarget" if map_only else "personalize", 5 if map_only else 8) as advance:
        advance.start("read")
        t = time.perf_counter()
        if out_path is not None and not dry_run:
            from ..io.layers import check_output_path

            check_output_path(out_path, force)
        avatar, generic_full, origin, regions = _read_avatar(avatar, name_map, out_path is not None, dry_run,
                                                             report)
        if eyes:
            eyes = {k: (np.asarray(p, dtype=np.float64) - origin, t) for k, (p, t) in eyes.items()}
        capture = _read_capture(capture, fitted=rig is None, every=fit_options.get("every", 1), rig=rig)
        digests = None
        if out_path is not None and not dry_run:   # the layer's input digests, beside the work from here on
            from ..io.layers import DigestsAhead

            digests = DigestsAhead([avatar.file, capture.source])
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
        names = _shapes_in_common(avatar, face, capture, cap_names, report)
        tmpl_idx = {n: i for i, n in enumerate(capture.template.names)}
        template_deltas = capture.template.deltas[[tmpl_idx[n] for n in names]]
        avatar_face_deltas = _shape_deltas(face, names, view=True)
        person_neutral0 = rig.neutral if rig is not None else capture.neutral

        # 2. registration of the person's neutral
        t = time.perf_counter()
        # separate pieces of the face mesh beyond the capture's reach (a body merged into the head's mesh,
        # its neck moved by the jaw) cannot say where the capture lies nor what it shows: the steps below
        # see the reached pieces as the face mesh and the rest as another mesh (joined back before write)
        reached = reached_parts(face.neutral, face.triangles, lambda: rough_placement(
            person_neutral0, template_deltas, face, avatar_face_deltas, capture))
        whole_face, beyond = face, None
        if reached is not None:
            avatar, whole_face, face, beyond, reached = _split_beyond_reach(avatar, face, reached, regions)
            avatar_face_deltas = _shape_deltas(face, names, view=True)
            rest = np.flatnonzero(~reached)
        # the face's peak motion, once for both registrations (the person's and the template's): the rig's
        # own when every shape is personalized (computed once, :meth:`usdface.model.FaceRig.peak_motion`)
        face_peak = (face.peak_motion() if len(set(names)) == face.n_shapes
                     else peak_motion(avatar_face_deltas))
        face_landmarks = motion_landmarks(face.neutral, avatar_face_deltas)         # the same for both too
        # and the face surface's closest-point scene (the twice-subdivided head's: 450k triangles), built
        # once: the template's registration (cached_correspondence) takes it from ``surfaces``
        surfaces = {"face": face_surface(face.neutral, face.triangles, face_peak)}
        registration = register_face(person_neutral0, template_deltas, face.neutral, avatar_face_deltas,
                                     avatar_triangles=face.triangles, capture_triangles=capture.triangles,
                                     path=capture.source or None, avatar_peak=face_peak,
                                     avatar_landmarks=face_landmarks,
                                     avatar_mesh=f"{face_prim} of {Path(avatar.file).name}",
                                     surface=surfaces["face"])
        timings["register"] = time.perf_counter() - t
        report["registration"] = _in_stage(registration.as_dict(), origin)
        sim = registration.transform
        advance("register")
        advance.start("correspond")

        # 3. correspondence (capture template <-> avatar face) and the avatar's shapes on the capture
        t = time.perf_counter()
        # ``surfaces``: the face surface above, then the posed avatar face, built once for both uses
        corr = cached_correspondence(face, capture, template_deltas, avatar_face_deltas, correspondence,
                                     names, initial=sim, target=registration.target, pending=pending_cache,
                                     # the deformation transfer's
                                     source_triangles=face_transfer != "person",
                                     avatar_peak=face_peak, avatar_landmarks=face_landmarks,
                                     surfaces=surfaces, person=(person_neutral0, registration))
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
            # eq. 5 of the fit the layer carries; it read its shapes' amplitudes on these frames too
            # (personalize.amplitude), so each frame is scored with the readings of the others (cross-fitted)
            scored = test_expression_errors(capture, rig, left_out_scale(fit, capture.test))
            if scored is not None:
                # how many shapes it scaled
                scale = (fit.info.get("test_amplitude") or {}).get("scale", [])
                scored["amplitudes_read"] = int(np.count_nonzero(np.asarray(scale) != 1.0))
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
        k_names = list(face.names)
        weights, mu_used = _retarget_map(avatar, face, beyond, corr, capture.triangles, person_deltas, names,
                                         mu, weight_bounds, map_prior, map_gaze)
        report["retarget"] = {"mu": mu_used,
                              "mu_choice": "leave one face region out" if mu == "auto" else "given",
                              "weight_min": float(weights.min()) if weights.size else 0.0,
                              "weight_max": float(weights.max()) if weights.size else 0.0,
                              "bounds": None if weight_bounds is None else list(weight_bounds),
                              "prior": map_prior, "gaze": map_gaze}
        approx_eq4 = {}
        if approximation == "retarget" and not map_only:
            for m in avatar.meshes:
                approx_eq4[m.key] = approximate(weights, _shape_deltas(m, k_names))
        timings["retarget"] = time.perf_counter() - t
        advance("retarget")
        if map_only:                 # the map is the product: the implant, eyelids and write are not needed
            # each mesh's own channel per shape (a studio's `JawDrop` for jawOpen, a Blender export's
            # `jawOpen2` on the teeth): what an engine drives; the map's columns drive every mesh
            report["retarget"]["channels"] = _own_channels(avatar, face, k_names)
            report["retarget"]["mesh_channels"] = {m.key: _own_channels(avatar, m, k_names)
                                                   for m in avatar.meshes
                                                   if m.key != face_prim and m is not beyond and m.names}
            trust, _, _ = shape_trust(fit, capture, rig, b_idx, person_deltas,
                                      _fit_prior(fit, names, capture, generic_on_capture, sim, prior),
                                      scale=sim.scale)
            _warn_untrusted_rows(report, weights, names, k_names, trust)
            if beyond is not None:   # the face mesh in one piece again (a body merged into the head's mesh)
                f = _join(f, reached, False, rest)
            face_all = scatter(f[:, None], regions[face_prim])[:, 0] if face_prim in regions else f
            if own_cache:
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
                rig, prior, generic_on_capture, person_deltas, tmpl_av, extension_length, support, report,
                face_peak)
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
        on_capture = (rig.neutral, capture.triangles, rig.deltas[b_idx], template_deltas)
        report["lips"] = lip_report(face.neutral, face.triangles, names, avatar_face_deltas, result,
                                    capture=on_capture)
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
            "options": run_options(method=method, reg=reg, mu=mu, weight_bounds=weight_bounds,
                                   map_prior=map_prior, map_gaze=map_gaze, face_transfer=face_transfer,
                                   approximation=approximation, prior=prior,
                                   extension_length=extension_length, falloff=falloff, support=support,
                                   eyelids=eyelids,
                                   fit_options=fit_options if fit is not None else None),
            "name_report": avatar.name_report,
            "changes": offset_changes(avatar, offsets, regions),
        })

        # 7. write
        t = time.perf_counter()
        written = None
        if out_path is not None and not dry_run:
            from ..io.layers import write_avatar_layer
            from .retarget import weight_map_rows

            inputs = (([str(capture.source)] if capture.source else [])
                      + ([str(name_map)] if isinstance(name_map, str | Path) else [])
                      + pins_input(fit_options.get("pins") if fit is not None else None, capture.source))
            prov = layer_provenance(report, timings, command=command, method=method, inputs=inputs,
                                    extra_inputs=extra_inputs, registration=registration,
                                    retarget_map=weight_map_rows(np.round(weights, 6), names, k_names),
                                    mu=mu_used)
            edit = layer_edit(offsets, face_prim) if layer_edit is not None else None
            written = write_avatar_layer(avatar, out_path, offsets, provenance=prov, force=force, edit=edit,
                                         digests=digests)
        if own_cache:                            # the correspondence cache, once the run has succeeded
            _write_pending(pending_cache)
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


def _read_avatar(avatar, name_map, writes: bool, dry_run: bool, report: dict):
    """Step 0, the avatar: read (a path) and checked for a layer (``writes``: instanced or unwritable
    shapes refused, or, with ``dry_run``, said in ``report``), moved near the origin (:func:`near_origin`)
    and cropped to what its shapes move (:func:`usdface.submesh.crop_avatar`). Returns ``(avatar,
    generic_full {mesh key: the caller's whole-mesh deltas}, origin[3], regions)``."""
    if not isinstance(avatar, Avatar):
        from ..io.usd_rig import read_avatar

        avatar = read_avatar(avatar, name_map=name_map, moving_only=True)
    if writes:                                    # an override under an instance would change nothing
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
    avatar, regions = crop_avatar(avatar)
    return avatar, generic_full, origin, regions


def _read_capture(capture, *, fitted: bool, every: int, rig: FaceRig | None = None) -> Capture:
    """Step 0, the capture: read (a path) and, when it is to be ``fitted``, refused now for what the fit
    would refuse later: a thinning (``every``) of what is not a take, a take of one held pose, proven
    exchanged sides. A given ``rig`` (implanted instead of a fit) must be on the capture's mesh."""
    if not isinstance(capture, Capture):
        from ..io import read_capture

        capture = read_capture(capture)
    if rig is not None:        # numpy's 'matmul: ... (1203 vs 1233)' in the registration (a user trial)
        from ..personalize.api import refuse_rig_of_another_capture

        refuse_rig_of_another_capture(rig, capture, what="the rig given to implant",
                                      fix="implant the rig fitted on this capture (usdface.fit_capture("
                                          "capture).rig), or leave rig= out and the capture is fitted")
    if not fitted:
        return capture
    from ..personalize.api import check_every, check_take_poses, refuse_swapped_sides

    if every != 1:                                    # a take's thinning: refused on a capture now
        check_every(every, capture)
    if capture.whole_take:                            # a take of one held pose: refused now
        check_take_poses(capture, every)
    refuse_swapped_sides(capture)                     # proven exchanged sides: refused now
    return capture


def _shapes_in_common(avatar: Avatar, face: FaceRig, capture: Capture, cap_names: list[str],
                      report: dict) -> list[str]:
    """The shapes personalized: the capture's (``cap_names``) that the face mesh and the capture's template
    have, in the capture's order; the others each way said in ``report``. Refused below 4 (the capture's
    fault when it has fewer, :class:`CaptureError`; else the avatar's, :class:`RigError`)."""
    avatar_all = sorted({n for m in avatar.meshes for n in m.names})
    in_template = set(capture.template.names)
    names = [n for n in cap_names if n in face.names and n in in_template]
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
                       path=avatar.file, prim=face.key,
                       fix="the avatar needs ARKit-named BlendShapes (eyeBlinkLeft, jawOpen, ...): "
                           "rename them, or pass the studio's names with --name-map FILE (name_map=); "
                           "'usdface inspect' lists how each channel was mapped")
    return names


def _split_beyond_reach(avatar: Avatar, face: FaceRig, reached, regions: dict):
    """The face mesh's separate pieces beyond the capture's reach (``reached[m]`` False: a body merged into
    the head's mesh) split off as another mesh, its still vertices left out (not worked on, not written;
    ``regions`` updated with the face's crop). Returns ``(avatar, whole_face, face, beyond, reached)``: the
    avatar with the reached face and the piece beyond as two meshes, the face mesh cropped whole (joined back
    before the write) and ``reached`` on its vertices."""
    keep = reached | moving_vertices(face.peak_motion(), face.neutral)
    whole_face, region = crop_rig(face, keep, regions.get(face.key))
    if not region.whole:
        regions[face.key] = region
    reached = reached[keep]
    if reached.all():
        # the pieces beyond the reach are all still (a helper piece or card in the head's mesh that no shape
        # moves): cropped away with the still vertices, they leave nothing beyond; an empty mesh there
        # crashed the steps after the field (numpy's max over zero vertices)
        avatar = dataclasses.replace(avatar, meshes=[whole_face if m.key == face.key else m
                                                     for m in avatar.meshes])
        return avatar, whole_face, whole_face, None, reached
    part, beyond = _split_rig(whole_face, reached)
    avatar = dataclasses.replace(avatar, meshes=[part if m.key == face.key else m
                                                 for m in avatar.meshes] + [beyond])
    return avatar, whole_face, part, beyond, reached


def _retarget_map(avatar: Avatar, face: FaceRig, beyond, corr, capture_triangles, person_deltas,
                  names: list[str], mu, weight_bounds, map_prior: str, map_gaze: str = "namesake"):
    """Step 4, eq. (4)'s weight map (:func:`usdface.transfer.retarget.retarget_weights`) from the person's
    shapes ``person_deltas[J,n,3]`` (avatar frame, metres) carried onto the face rows by the correspondence
    ``corr``. The map drives every mesh: with the namesake prior, what the face rows do not see on the other
    meshes (teeth, tongue, eyeballs) keeps the namesake's own motion (the paper's zero prior would hold it
    still); the face mesh's own rows beyond the face are not among them (a body merged into the head's mesh,
    split off as ``beyond``, gives the head alone's map). ``map_gaze="namesake"`` holds every entry of a gaze
    channel's column at 0 but its namesake's (:func:`usdface.transfer.retarget.gaze_held`). Returns
    ``(weights[J,K], mu)``."""
    k_names = list(face.names)
    mb_face = corr.apply(person_deltas, capture_triangles, rows=corr.face)     # M B_j on the face region
    namesake = map_prior == "namesake"
    others = [(m.names, m.deltas) for m in avatar.meshes if m.key != face.key and m is not beyond]
    return retarget_weights(
        face.deltas, mb_face, mu=mu, return_mu=True, rows=corr.face, bounds=weight_bounds,
        positions=face.neutral, prior=namesake_prior(names, k_names) if namesake else None,
        elsewhere=driven_gram(others, k_names) if namesake else None,
        held=gaze_held(names, k_names, map_gaze))


def _own_channels(avatar: Avatar, mesh: FaceRig, names: list[str]) -> list:
    """``mesh``'s own channel name (its ``skel:blendShapes`` token, as the reader mapped it) for each ARKit
    name of ``names``, None where the mesh has no such shape."""
    tokens = {c[1]: c[0] for c in avatar.name_report.get(mesh.key, {}).get("channels", ())
              if c[1] is not None and c[2] != "conflict"}
    have = set(mesh.names)
    return [tokens.get(n, n) if n in have else None for n in names]


def _warn_untrusted_rows(report: dict, weights, names: list[str], k_names: list[str], trust) -> None:
    """The map's rows of shapes the capture barely shows (``trust[J]``, :func:`.trust.shape_trust`), said in
    ``report``: the implant keeps such a shape near the generic one, but the map's row is the fit's shape as
    it is (a take's never-performed cheekPuff mapped to mouthRollLower 0.54, namesake 0.17, without a word: a
    user trial), with the shape's strongest entry (:func:`.report.untrusted_map_rows`)."""
    untrusted = untrusted_map_rows(weights, names, k_names, trust)
    if untrusted:
        report["warnings"].append(
            "map rows of shapes the capture barely shows follow a fit its frames hardly inform "
            "(personalize keeps these shapes near the avatar's generic ones): " + ", ".join(untrusted)
            + " (fix: record those expressions, or give their rows the namesake's weight 1 by hand)")


def _write_pending(pending: list) -> None:
    """Write the correspondence caches :func:`.face_map.cached_correspondence` held back (``(path, npz
    bytes)``)."""
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


def _fit(capture, names, generic_on_capture, prior, method, reg, fit_options):
    """Step 1 (:func:`usdface.personalize.fit_personalized_shapes`), after the correspondence: with
    ``prior="avatar"`` the avatar's own shapes on the capture (``generic_on_capture[J,n,3]``, capture frame,
    metres; NaN rows for the capture's shapes the avatar lacks) are the prior of menzel / laplacian
    (:func:`fit_prior_options`)."""
    from ..personalize import fit_personalized_shapes

    extra = fit_prior_options(prior, method)
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
                    report, face_peak=None) -> tuple[np.ndarray, np.ndarray, dict, np.ndarray]:
    """Step 5 of the default transfer: the person's motion on the face region (``A_j + c_j M s_j (B_j -
    P_j)``, :func:`usdface.transfer.implant.face_personalization`), extended as a rotation + scale field of
    the generic motion beyond it and onto the meshes that follow the skin (:mod:`.motion_field`).
    ``person_deltas[J,n,3]`` / ``tmpl_av[J,n,3]``: the person's and the template's capture shapes in the
    avatar frame (metres). Returns ``(result[J,m,3], adjacent[J,m] bool, {mesh key: [J,n_mesh,3]}, the
    face's generic offsets [J,m,3])`` and adds the confidence, mapping outliers and extension figures to
    ``report``. ``face_peak[m]``: :func:`usdface.motion.peak_motion` of the face's generic offsets of
    ``names`` when the caller has it.

    The face's generic offsets are held packed during the field (the run's peak) when they are large
    (:class:`_HeldPacked`): the caller lets go of its own references to them first."""
    f = corr.face
    b_idx = [rig.index(n) for n in names]
    prior_av = _fit_prior(fit, names, capture, generic_on_capture, sim, prior)
    conf, excitation, weak = shape_trust(fit, capture, rig, b_idx, person_deltas, prior_av, scale=sim.scale)
    info = fit.info if fit is not None and capture.whole_take else {}
    if (info.get("frame_variance") is not None and info.get("frame_white_noise_mm")
            and info.get("frame_noise_mm")):
        # a take's scan noise left in each fitted shape, the part independent from vertex to vertex (the
        # scans' own): smoothed out of the person's change by as much as lowers its estimated error on the
        # avatar's face, where the interpolation has averaged some of it already (Stein's unbiased risk
        # estimate). The trust stays the unsmoothed change's: the smoothing's bias is in no variance
        cap_idx = [list(capture.names).index(n) for n in names]
        white = (info["frame_white_noise_mm"] / info["frame_noise_mm"]) ** 2
        onto = corr.matrix(capture.triangles, person_deltas.shape[1], face_only=False, rows=np.flatnonzero(f))
        smooth, lam = denoise_personalization(
            person_deltas - prior_av, capture.triangles,
            np.asarray(info["frame_variance"])[:, cap_idx] * white * float(sim.scale) ** 2, metric=onto)
        person_deltas = prior_av + smooth
        del onto, smooth
        report["denoised"] = {n: round(float(v), 4) for n, v in zip(names, lam, strict=True) if v > 0}
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
    # ... where a slip of the map within the capture's resolution (one placed capture edge) could have made
    # the difference: the avatar's motion near the vertex's place reaches the person's
    places = corr.registered if corr.registered is not None and len(corr.registered) == len(capture.neutral) \
        else None
    near = None if places is None else (places, face.neutral, _shape_deltas(face, names, view=True),
                                        mean_edge_length(places, capture.triangles))
    outliers = mapping_outliers(person_deltas, prior_av, tmpl_av, triangles=capture.triangles, avatar=near)
    near = None
    report["correspondence"]["mapping_outliers"] = int(outliers.sum())
    weight = corr.weight if corr.weight is not None else corr.face.astype(float)
    # where the mapped template and the avatar disagree on what a semantic shape moves (a lid or a
    # lip on the other side), the capture is not trusted: the field from the neighbours fills in
    trusted = ~dilate(disagree, face.triangles, 2)
    weight = weight * trusted
    # the avatar vertices just past the capture's border (within one capture edge), where its value at the
    # border still measures the person's motion: the field is measured there too (the result there stays the
    # field's; the face region and its join are unchanged)
    border = border_reach(corr, capture.triangles, face.neutral, face.triangles) * trusted
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
            rows = np.flatnonzero(f | (border > 0))
            interpolation = corr.matrix(capture.triangles, person_deltas.shape[1], face_only=False, rows=rows)
            for lo in range(0, len(names), 8):
                js = slice(lo, lo + 8)
                change = face_personalization(corr, capture.triangles, person_deltas[js],
                                              prior_av[js], rows, support=support, outliers=outliers[js],
                                              matrix=interpolation)
                change *= conf[js, None, None]
                out[js, rows] += change
            return out

        release_free_memory()              # the read's and the fit's freed blocks, before the peak
        # the result is written over person_face (not used again): one [J,m,3] array fewer at the peak
        packed = held.packed(0)
        result, pfield = extend_personalization(face.neutral, face.triangles,
                                               _shape_deltas(face, names, view=True) if packed is None
                                               else packed, person_face, weight, length=length,
                                               band=SEAM_BAND * radius, smoothing=smoothing,
                                               keep_at=keep_at, overwrite=True, peak=face_peak,
                                               border_weight=border)
        packed = None                      # (person_face is not called again)
        release_free_memory()              # the field's freed working memory
    generic = _shape_deltas(face, names, view=True)       # the float64 generic offsets again, as read
    adjacent = changed_vertices(result, generic, weight < 1.0)
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


