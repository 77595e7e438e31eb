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
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import RigError, UsdFaceError
from ..mesh import deformation_gradients
from ..model import Avatar, Capture, FaceRig
from ..personalize.api import single_threaded_blas
from ..progress import steps
from .correspond import (
    Correspondence,
    correspondence_map,
    geometry_digest,
    load_correspondence,
    nonrigid_register,
    save_correspondence,
)
from .eyelids import find_eyeballs, repair_eyelids
from .partial_dt import blend_adjacent, face_deformation_transfer, personalization_support
from .register import register_face
from .retarget import approximate, retarget_weights

__all__ = ["PersonalizeResult", "personalize_avatar", "implant_shapes", "FACE_TRANSFERS", "APPROXIMATIONS"]

#: Face-region transfer modes (see :func:`implant_shapes`).
FACE_TRANSFERS = ("offset", "dt", "dt-offset")
#: What the adjacent region and the other meshes are blended from / follow.
APPROXIMATIONS = ("generic", "retarget")


@dataclass
class PersonalizeResult:
    """Everything ``personalize`` computed.

    ``offsets``: {mesh prim path -> deltas[K_mesh,n,3]} metres internal, rig.names order (the layer's).
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
    """The mesh where the shared ARKit shapes move the most vertices (the face/head mesh)."""
    best, score = None, 0
    for rig in avatar.meshes:
        idx = [rig.index(n) for n in names if n in rig.names]
        if not idx:
            continue
        moving = int((np.linalg.norm(rig.deltas[idx], axis=2).max(axis=0) > 0).sum())
        if moving > score:
            best, score = rig, moving
    if best is None:
        raise RigError("the avatar has no face-like blend shapes (no ARKit-named shape that moves)",
                       path=avatar.file,
                       fix="the avatar needs ARKit-named BlendShapes (eyeBlinkLeft, jawOpen, ...)")
    return best


def _shape_deltas(rig: FaceRig, names: list[str]) -> np.ndarray:
    """``[len(names), n, 3]`` deltas of ``rig`` for ``names`` (zero for shapes the mesh lacks)."""
    out = np.zeros((len(names), rig.n_vertices, 3))
    for i, n in enumerate(names):
        if n in rig.names:
            out[i] = rig.deltas[rig.index(n)]
    return out


def _correspondence(face: FaceRig, capture: Capture, template_deltas, avatar_deltas, cache):
    key = geometry_digest(face.neutral, face.triangles, capture.template.neutral, capture.triangles)
    if cache is not None:
        corr = load_correspondence(cache, key)
        if corr is not None:
            corr.info = {**(corr.info or {}), "cache": "hit"}
            return corr
    reg_t = register_face(capture.template.neutral, template_deltas, face.neutral, avatar_deltas,
                          avatar_triangles=face.triangles, capture_triangles=capture.triangles,
                          path=capture.source or None)
    placed = reg_t.transform.apply(capture.template.neutral)
    registered, nr_info = nonrigid_register(placed, capture.triangles, face.neutral, face.triangles)
    corr = correspondence_map(registered, capture.triangles, face.neutral, face.triangles)
    corr.key = key
    corr.info = {**corr.info, **nr_info, "template_registration": reg_t.as_dict(),
                 "cache": "miss" if cache is not None else "off"}
    if cache is not None:
        save_correspondence(corr, cache)
    return corr


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
                       mu: float = 1e-3, correspondence=None, force: bool = False, dry_run: bool = False,
                       face_transfer: str = "offset", approximation: str = "generic", falloff: float = 0.15,
                       support=(0.01, 0.03), eyelids: bool = True, eyes: dict | None = None,
                       rig: FaceRig | None = None, name_map=None, face_mesh: str | None = None,
                       command: str = "", **fit_options) -> PersonalizeResult:
    """Personalize ``avatar`` (path or :class:`Avatar`) from ``capture`` (folder / capture USD path or
    :class:`Capture`) and, unless ``dry_run`` or ``out_path`` is None, write the layer to ``out_path``.

    Parameters
    ----------
    method, reg, fit_options : step 1, passed to :func:`usdface.personalize.fit_personalized_shapes`.
    rig : skip step 1 and implant this capture-mesh rig (neutral = person's B0, deltas = B_j).
    name_map : the studio's {channel: ARKit name} map (dict or JSON/CSV file) for reading ``avatar``
        (:func:`usdface.io.usd_rig.read_avatar`).
    face_mesh : prim name or path of the face mesh (default: the mesh the shared shapes move most).
    mu : eq. (4) ridge weight (relative, see :func:`retarget_weights`) of the retarget map.
    correspondence : cache file (``.npz``) for step 3, reused when it belongs to this avatar face and
        template (same geometry and topology), rewritten otherwise.
    force : overwrite an existing output layer.
    face_transfer : ``"offset"`` | ``"dt"`` | ``"dt-offset"`` (:func:`implant_shapes`).
    approximation : ``"generic"`` (default): the adjacent region and the other meshes start from the
        avatar's own generic shape B~_j; ``"retarget"``: from the eq. (4) approximation A_j (the paper).
    falloff : width of the seamless join beyond the face, in capture mean edge lengths (screened harmonic
        blend); 0 = plain harmonic over the whole adjacent region (the paper).
    support : ``(low, high)`` fractions of each shape's peak motion below which its personalization is not
        transferred (:func:`usdface.transfer.partial_dt.personalization_support`); None = everywhere.
    eyelids : step 6; ``eyes`` = {name: (points[n,3], triangles[t,3])} internal metres, closed eye meshes
        (else taken from ``avatar.metadata["static_meshes"]`` when the reader provides it, or from avatar
        meshes that are eyeballs by name/geometry).
    """
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    report: dict = {"warnings": []}
    if face_transfer not in FACE_TRANSFERS:
        raise UsdFaceError(f"unknown face transfer {face_transfer!r}",
                           fix=f"use one of {', '.join(FACE_TRANSFERS)}")
    if approximation not in APPROXIMATIONS:
        raise UsdFaceError(f"unknown approximation {approximation!r}",
                           fix=f"use one of {', '.join(APPROXIMATIONS)}")
    with steps("personalize", 8) as advance:
        t = time.perf_counter()
        if out_path is not None and not dry_run:
            from ..io.layers import check_output_path

            check_output_path(out_path, force)
        if not isinstance(avatar, Avatar):
            from ..io.usd_rig import read_avatar

            avatar = read_avatar(avatar, name_map=name_map)
        if not isinstance(capture, Capture):
            from ..io import read_capture

            capture = read_capture(capture)
        chosen_face = None
        if face_mesh:  # checked before the fit
            from ..io.layers import avatar_mesh

            chosen_face = avatar_mesh(avatar, face_mesh, "with blend shapes in the avatar (--face-mesh)")
        timings["read"] = time.perf_counter() - t
        advance("read")

        # 1. fit
        t = time.perf_counter()
        fit = None
        if rig is None:
            from ..personalize import fit_personalized_shapes

            fit = fit_personalized_shapes(capture, method=method, reg=reg, **fit_options)
            rig = fit.rig
            report["fit"] = {k: v for k, v in fit.info.items() if not isinstance(v, np.ndarray)}
        timings["fit"] = time.perf_counter() - t
        advance("fit")

        # names: capture shapes vs avatar shapes
        face = chosen_face if chosen_face is not None else _face_mesh(avatar, [n for n in rig.names])
        face_prim = face.source.prim if face.source else face.name
        avatar_all = sorted({n for m in avatar.meshes for n in m.names})
        names = [n for n in rig.names if n in face.names]
        tmpl_idx = {n: i for i, n in enumerate(capture.template.names)}
        names = [n for n in names if n in tmpl_idx]
        report["capture_shapes_missing_from_avatar"] = [n for n in rig.names if n not in face.names]
        report["avatar_shapes_missing_from_capture"] = [n for n in avatar_all if n not in rig.names]
        if report["capture_shapes_missing_from_avatar"]:
            report["warnings"].append("capture shapes the avatar lacks (skipped): "
                                      + ", ".join(report["capture_shapes_missing_from_avatar"]))
        if report["avatar_shapes_missing_from_capture"]:
            report["warnings"].append("avatar shapes the capture lacks (kept generic): "
                                      + ", ".join(report["avatar_shapes_missing_from_capture"]))
        if len(names) < 4:
            raise RigError(f"only {len(names)} of the capture's shapes exist on the avatar face mesh",
                           path=avatar.file, prim=face_prim,
                           fix="the avatar needs ARKit-named BlendShapes (eyeBlinkLeft, jawOpen, ...)")
        b_idx = [rig.index(n) for n in names]
        template_deltas = capture.template.deltas[[tmpl_idx[n] for n in names]]
        avatar_face_deltas = _shape_deltas(face, names)

        # 2. registration of the person's neutral
        t = time.perf_counter()
        registration = register_face(rig.neutral, template_deltas, face.neutral, avatar_face_deltas,
                                     avatar_triangles=face.triangles, capture_triangles=capture.triangles,
                                     path=capture.source or None)
        timings["register"] = time.perf_counter() - t
        report["registration"] = registration.as_dict()
        advance("register")

        # 3. correspondence
        t = time.perf_counter()
        corr = _correspondence(face, capture, template_deltas, avatar_face_deltas, correspondence)
        timings["correspond"] = time.perf_counter() - t
        report["correspondence"] = {k: v for k, v in (corr.info or {}).items()}
        if not corr.face.any():
            raise RigError("no avatar vertex lies on the registered capture surface (empty face region)",
                           path=avatar.file, prim=face_prim,
                           fix="check that the capture and the avatar are faces")
        advance("correspond")

        # 4. retargeting, eq. (4)
        t = time.perf_counter()
        sim = registration.transform
        person_neutral = sim.apply(rig.neutral)
        person_deltas = sim.apply_vectors(rig.deltas[b_idx])
        tmpl_av = sim.apply_vectors(template_deltas)
        f = corr.face
        mb_face = corr.apply(person_deltas, capture.triangles, rows=f)          # M B_j on the face region
        k_names = list(face.names)
        weights = retarget_weights(face.deltas[:, f], mb_face, mu=mu)
        approx_eq4 = {}
        for m in avatar.meshes:
            key = m.source.prim if m.source else m.name
            approx_eq4[key] = approximate(weights, _shape_deltas(m, k_names))
        timings["retarget"] = time.perf_counter() - t
        advance("retarget")

        # 5. seamless partial transfer on the face mesh; other meshes follow the approximation
        t = time.perf_counter()
        base = {key: (approx_eq4[key] if approximation == "retarget"
                      else _shape_deltas(m, names)) for key, m in
                zip(approx_eq4, avatar.meshes, strict=True)}
        edge = float(corr.info.get("capture_mean_edge_m", 0.0)) * sim.scale if corr.info else 0.0
        result, adjacent = implant_shapes(
            face.neutral, face.triangles, corr, capture.triangles, person_neutral, person_deltas, tmpl_av,
            avatar_face_deltas, base[face_prim], face_transfer=face_transfer,
            falloff=(falloff * edge if falloff and edge > 0 else None), support=support)
        timings["transfer"] = time.perf_counter() - t
        advance("transfer")

        # 6. eyelids
        t = time.perf_counter()
        repaired = 0
        if eyelids:
            eye_meshes = dict(eyes or avatar.metadata.get("static_meshes") or {})
            for m in avatar.meshes:
                if m is not face:
                    eye_meshes.setdefault(m.source.prim if m.source else m.name, (m.neutral, m.triangles))
            found = find_eyeballs({k: v[0] for k, v in eye_meshes.items()})
            if found:
                result, repaired = repair_eyelids(face.neutral, result,
                                                  [(e, *eye_meshes[e.name]) for e in found],
                                                  reference=avatar_face_deltas)
            report["eyelids"] = {"eyeballs": [e.name for e in found], "repaired_vertex_shapes": repaired}
            if not found:
                report["warnings"].append("no eyeball meshes found: eyelid repair skipped")
        timings["eyelids"] = time.perf_counter() - t
        advance("eyelids")

        # offsets for every mesh, in rig.names order; shapes the capture lacks stay generic
        offsets = {}
        for m in avatar.meshes:
            key = m.source.prim if m.source else m.name
            new = m.deltas.copy()
            src = result if m is face else base[key]
            for j, n in enumerate(names):
                if n in m.names:
                    new[m.index(n)] = src[j]
            offsets[key] = new
        report.update({
            "face_mesh": face_prim, "shapes": names, "face_vertices": int(f.sum()),
            "adjacent_vertices_max": int(adjacent.sum(axis=1).max()) if adjacent.size else 0,
            "options": {"method": method, "reg": reg, "mu": mu, "face_transfer": face_transfer,
                        "approximation": approximation, "falloff": falloff, "support": support,
                        "eyelids": eyelids},
            "name_report": avatar.name_report,
            "changes": _changes(avatar, offsets),
        })

        # 7. write
        t = time.perf_counter()
        written = None
        if out_path is not None and not dry_run:
            from ..io.layers import write_avatar_layer
            from .retarget import weight_map_rows

            prov = {"command": command or "usdface personalize",
                    "parameters": {k: (v if isinstance(v, int | float | str | bool) else str(v))
                                   for k, v in report["options"].items()},
                    "method": method, "inputs": [str(capture.source)] if capture.source else [],
                    "registrationScale": float(sim.scale),
                    "registrationResidual": float(registration.residual),
                    "registration": registration.as_dict(),
                    "correspondence": {k: v for k, v in report["correspondence"].items()
                                       if isinstance(v, int | float | str)},
                    "retargetMap": weight_map_rows(np.round(weights, 6), names, k_names, threshold=1e-6),
                    "warnings": list(report["warnings"]),
                    "timings": dict(timings)}
            written = write_avatar_layer(avatar, out_path, offsets, provenance=prov, force=force)
        timings["write"] = time.perf_counter() - t
        advance("write")
    timings["total"] = time.perf_counter() - t_start
    report["timings"] = timings
    return PersonalizeResult(offsets, names, k_names, weights, approx_eq4, face_prim, f, adjacent, report,
                             written, fit)


def _changes(avatar: Avatar, offsets: dict) -> list[dict]:
    """Per mesh and shape: largest and RMS change of the offsets (m) - what ``--dry-run`` prints."""
    rows = []
    for m in avatar.meshes:
        key = m.source.prim if m.source else m.name
        sq = np.sum((offsets[key] - m.deltas) ** 2, axis=2)  # [K,n] squared change
        peak, rms = np.sqrt(sq.max(axis=1)), np.sqrt(sq.mean(axis=1))
        moved = (sq > 1e-18).sum(axis=1)
        for k, n in enumerate(m.names):
            rows.append({"mesh": key, "shape": n, "max_change_m": float(peak[k]),
                         "rms_change_m": float(rms[k]), "moved_vertices": int(moved[k])})
    return rows
