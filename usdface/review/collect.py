"""Gather what the review page shows from a usdface layer (and its capture, and a take): both variants'
meshes and shapes, the change heat map, landmarks, the test expressions and a take to play, the layer's
provenance figures and the eq. 5 errors per test expression.

Files are read through :mod:`usdface.io` only; the result is a :class:`usdface.review.page.ReviewData` of
numpy arrays and text.
"""

from __future__ import annotations

import os
import shlex
from pathlib import Path

import numpy as np

from ..errors import InputFileError, RigError, warn
from ..motion import shape_changes
from .page import Listing, ReviewData, ReviewMesh, Sequence, framed_ranges

__all__ = ["collect_review", "recorded_capture"]

#: Seconds each test expression is held during playback.
TEST_HOLD_S = 0.75


#: A shape counts as changed where a vertex's offset moved by more than this (m), as in personalize's report
#: (``usdface.transfer.report.offset_changes``: ``moved_vertices``).
CHANGE_TOL_M = 1e-9


def recorded_capture(layer_path, info: dict) -> Path | None:
    """The capture a usdface layer was made from (the second input in the provenance of a personalize
    layer, which is recorded relative to the layer), when it still exists; else None (also for a layer of
    another command, e.g. ``usdface landmarks``)."""
    inputs = list(info.get("inputs") or [])
    if len(inputs) < 2 or not _fitted(info):
        return None       # a landmarks layer records the avatar (and its layers) only: no capture
    return _recorded_path(layer_path, inputs[1])


def _same_file(given, recorded: Path | None) -> bool:
    """Whether ``given`` (a path, or an object read already) is the file ``recorded`` (by identity: a link
    or another spelling of the same file counts); False when either is not a path to an existing file."""
    if recorded is None or not isinstance(given, str | Path):
        return False
    try:
        return os.path.samefile(given, recorded)
    except (OSError, ValueError):
        return False


def _capture_changed(layer_path, info: dict, path: Path | None) -> bool:
    """Whether ``path``, the capture a personalize layer records (:func:`recorded_capture`), is there but no
    longer has the sha256 the layer's provenance records for it (``inputDigests``); False when it is gone or
    no digest was recorded."""
    from ..io.layers import input_changed, recorded_inputs

    if path is None:
        return False
    real = os.path.realpath(path)
    return input_changed(real, (recorded_inputs(layer_path, info) or {}).get(real, ""))


def recorded_take(layer_path, info: dict) -> Path | None:
    """The take a personalize layer's inspection animation plays (``personalize --take``, recorded relative
    to the layer as ``take`` in its provenance), when it still exists; else None."""
    return _recorded_path(layer_path, info["take"]) if info.get("take") else None


def _recorded_path(layer_path, recorded) -> Path | None:
    """A path a layer's provenance records (relative to the layer, or absolute), resolved, when it exists."""
    from ..io.layers import recorded_path

    p = recorded_path(Path(layer_path).parent, recorded)       # by name, as USD anchors the layer's paths
    return p.resolve() if p.exists() else None


def _personalize_layer_below(layer_path) -> tuple[Path, dict] | None:
    """(path, provenance) of the first layer of the layer stack of ``layer_path`` below its root layer that
    ``usdface personalize`` wrote, or None: what a layer stacked over a personalization reviews."""
    from pxr import Usd

    from ..io.usd_rig import usdface_output_provenance

    stage = Usd.Stage.Open(str(layer_path), Usd.Stage.LoadNone)
    for layer in stage.GetLayerStack(includeSessionLayers=False)[1:]:
        if not layer.realPath:
            continue
        record = usdface_output_provenance(layer.realPath) or {}
        if record.get("inputs") and _fitted(record):
            return Path(layer.realPath), record
    return None


def _mm(v) -> str:
    return f"{float(v) * 1000.0:.2f} mm"


def _provenance_tables(info: dict) -> list[tuple[str, list[tuple[str, str]]]]:
    tables = []
    inputs = [str(p) for p in info.get("inputs") or []]
    if inputs:             # what the layer was made from, as recorded (relative to the layer)
        labels = (["avatar", "capture"] if _fitted(info) else ["avatar"]) + ["input"] * len(inputs)
        rows = [("take" if path == info.get("take") else label, path)
                for label, path in zip(labels, inputs, strict=False)]
        if info.get("command"):
            rows.append(("command", str(info["command"])))
        tables.append(("made from", rows))
    reg = info.get("registration") or {}
    if reg:
        rows = [("scale", f"{float(reg.get('scale', 1.0)):.4f}")]
        rot = reg.get("rotation")
        if rot is not None:
            r = np.asarray(rot if not isinstance(rot, str) else _parse_matrix(rot), dtype=np.float64)
            angle = np.degrees(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)))
            rows.append(("rotation", f"{angle:.2f} deg"))
        if reg.get("translation_m") is not None:
            rows.append(("translation", "(" + ", ".join(f"{float(v) * 100:.2f}" for v in reg["translation_m"])
                         + ") cm"))
        for key, label in (("residual_m", "ICP residual"), ("max_distance_m", "max distance")):
            if key in reg:
                rows.append((label, _mm(reg[key])))
        if "fitness" in reg:   # ICP's share of capture points with an avatar point in reach (was 0.99837...)
            rows.append(("fitness", f"{float(reg['fitness']) * 100:.1f} % of capture points matched"))
        if "initialiser" in reg:
            rows.append(("initialiser", str(reg["initialiser"])))
        tables.append(("registration (capture -> avatar)", rows))
    cor = info.get("correspondence") or {}
    if cor:
        rows = []
        for key, label in (("face_vertices", "avatar face vertices"), ("n", "capture vertices")):
            if key in cor:
                rows.append((label, str(cor[key])))
        for key, label in (("face_rms_distance_m", "face RMS distance"), ("nonrigid_rms_m", "non-rigid RMS"),
                           ("capture_mean_edge_m", "capture mean edge")):
            if key in cor:
                rows.append((label, _mm(cor[key])))
        if "nonrigid_matched" in cor:
            rows.append(("non-rigid matched", f"{float(cor['nonrigid_matched']) * 100:.1f} %"))
        rows.append(("cache", str(cor.get("cache", "off"))))
        tables.append(("correspondence", rows))
    params = dict(info.get("parameters") or {})
    if params or info.get("method"):
        rows = [("method", str(info.get("method", params.get("method", ""))))]
        rows += [(str(k), str(v)) for k, v in sorted(params.items()) if k != "method"]
        rows += [("usdface", str(info.get("version", ""))), ("created", str(info.get("createdAt", "")))]
        tables.append(("fit and transfer parameters", rows))
    return tables


def _parse_matrix(text: str):
    import json

    return json.loads(text)


def _mesh_pairs(personalized, generic) -> list[ReviewMesh]:
    meshes = []
    for rig in personalized.meshes:
        try:
            gen = generic.mesh(rig.key)
        except KeyError:
            raise RigError(f"mesh {rig.name!r} is missing from the generic variant", path=personalized.file,
                           fix="review a layer written by 'usdface personalize'") from None
        if gen.n_vertices != rig.n_vertices or not set(rig.names) <= set(gen.names):
            raise RigError(f"mesh {rig.name!r} differs between the variants", path=personalized.file,
                           fix="review a layer written by 'usdface personalize'")
        g = gen.subset(rig.names).deltas
        heat = shape_changes(rig.deltas, g)[0] if rig.n_shapes else None
        meshes.append(ReviewMesh(rig.name, rig.neutral, rig.triangles, list(rig.names), g, rig.deltas, heat))
    for prim, (points, triangles) in sorted(personalized.metadata.get("static_meshes", {}).items()):
        meshes.append(ReviewMesh(prim.rsplit("/", 1)[-1], points, triangles))
    return meshes


def _fitted(info: dict) -> bool:
    """Whether the layer's provenance is a personalize run's (a fit method), not another command's."""
    from ..personalize.api import METHODS

    params = dict(info.get("parameters") or {})
    return str(info.get("method") or params.get("method") or "menzel") in METHODS


def _layer_animation(layer_path, avatar) -> tuple | None:
    """The layer's inspection animation (``personalize --inspect`` or ``--take``) as the page's meshes name
    its channels: ``(names[K], weights[F, K], codes[F] time codes, time codes per second)``, the columns the
    avatar's channels (``avatar``: the personalized variant, whose channel tokens name them as the page's
    meshes do; a channel of two skeletons' animations read once). None when the layer has none, or its
    skeletons' animations disagree on their samples."""
    from pxr import UsdSkel

    from ..io.usd_inspection import ANIMATION_NAME
    from ..io.usd_open import open_usd_stage

    paths = sorted({str(m.source.animation) for m in avatar.meshes if m.source is not None
                    and m.source.animation and str(m.source.animation).rsplit("/", 1)[-1] == ANIMATION_NAME})
    if not paths:
        return None
    canonical = {}            # a channel token -> the name the page's meshes use
    for rig in avatar.meshes:
        tokens = (rig.source.channel_tokens if rig.source is not None else None) or rig.names
        canonical.update(zip(tokens, rig.names, strict=True))
    stage = open_usd_stage(layer_path, "layer", "check the path")
    names, columns, first = [], [], None
    for path in paths:        # one animation per Skeleton, authored on one timeline
        anim = UsdSkel.Animation(stage.GetPrimAtPath(path))
        attr = anim.GetBlendShapeWeightsAttr() if anim else None
        codes = list(attr.GetTimeSamples()) if attr else []
        if not codes or (first is not None and codes != first):
            return None
        first = codes
        w = np.array([np.asarray(attr.Get(t), dtype=np.float64) for t in codes])
        tokens = [str(t) for t in anim.GetBlendShapesAttr().Get() or []]
        if w.ndim != 2 or w.shape[1] != len(tokens):
            return None
        for k, token in enumerate(tokens):
            name = canonical.get(token, token)
            if name not in names:
                names.append(name)
                columns.append(w[:, k])
    rate = stage.GetTimeCodesPerSecond()
    return names, np.stack(columns, axis=1), np.asarray(first, dtype=np.float64), rate


def _scored_labels(info: dict) -> list[str]:
    """The labels of the test expressions the layer's provenance scored (``fitTestExpressions``)."""
    scored = info.get("fitTestExpressions")
    return [str(x) for x in (scored.get("labels") or [])] if isinstance(scored, dict) else []


def layer_test_expressions(layer_path, info: dict, avatar) -> tuple | None:
    """The capture's test expressions as the layer itself holds them, for when the capture it records is
    gone: ``(names[K], weights[F, K], labels[F])``, the first F frames of its inspection animation
    (``personalize --inspect`` or ``--take`` plays the capture's test expressions first, one every
    ``hold`` seconds: :func:`usdface.io.usd_inspection.inspection_animation`), F the test expressions its
    provenance scored (``fitTestExpressions``), the columns the avatar's channels (``avatar``: the
    personalized variant, whose channel tokens name them as the page's meshes do). None when the layer has
    no such animation or scored none."""
    labels = _scored_labels(info)
    held = _layer_animation(layer_path, avatar) if labels else None
    if held is None or len(held[2]) < len(labels):
        return None
    return held[0], held[1][:len(labels)], labels


def layer_take(layer_path, info: dict, avatar) -> tuple | None:
    """The take the layer was written with (``personalize --take``) as its inspection animation holds it,
    for when the take file it records is gone: ``(names[K], weights[F, K], times[F] seconds from the take's
    first frame)``, the animation's frames after the capture's test expressions (F of them, those its
    provenance scored: :func:`usdface.io.usd_inspection.inspection_animation` plays them first, then the
    take), at the layer's time codes per second. None when the layer records no take or holds no
    animation, or no frame follows the test expressions."""
    if not info.get("take"):
        return None
    held = _layer_animation(layer_path, avatar)
    first = len(_scored_labels(info))
    if held is None or len(held[2]) <= first:
        return None
    names, weights, codes, rate = held
    return names, weights[first:], (codes[first:] - codes[first]) / float(rate or 24.0)


def _layer_fit_errors(info: dict) -> dict | None:
    """Eq. 5 as the layer's provenance recorded it (``fitTestExpressions``: scored by ``personalize`` on the
    fit it implanted), without the capture; None when it recorded none."""
    scored = info.get("fitTestExpressions")
    if not isinstance(scored, dict) or not scored.get("labels"):
        return None
    return _errors_table(scored, "the layer's fit, as recorded in it (the capture itself was not found)")


def _errors_table(scored: dict, source: str) -> dict:
    """The review page's eq. 5 table of ``scored`` (:func:`usdface.personalize.evaluate.
    test_expression_errors`'s dict), titled with where the figures come from."""
    columns = {"generic RMSE": "generic_rmse_mm", "personalized RMSE": "personalized_rmse_mm",
               "generic max": "generic_max_mm", "personalized max": "personalized_max_mm"}
    return {"title": f"eq. 5 on the capture's test expressions (mm; {source})",
            "labels": list(scored["labels"]),
            "columns": {k: [float(v) for v in scored[key]] for k, key in columns.items()}}


def _fit_errors(capture, info: dict, *, recorded: bool) -> dict | None:
    """Eq. 5 on the capture's test expressions: the generic template vs the person's fitted shapes. The
    layer's own figures (``fitTestExpressions``, scored by ``personalize`` on the fit it implanted, prior,
    alignment and options included) when ``recorded`` (the capture is the one the layer records) and they
    cover these expressions; else (an older layer, another capture) a refit with the layer's recorded method
    and regularisation, said so in the title. The layer's fit scaled its ``amplitudes_read`` shapes by these
    very frames (:mod:`usdface.personalize.amplitude`, since stop 49), each frame scored with the others'
    readings (cross-fitted, since stop 51): the title says so."""
    from ..personalize import fit_personalized_shapes
    from ..personalize.api import left_out_scale
    from ..personalize.evaluate import test_expression_errors

    if len(capture.test) == 0:
        return None
    scored = info.get("fitTestExpressions") if recorded else None
    source = "the layer's fit"
    if not (isinstance(scored, dict) and scored.get("labels") == [str(s) for s in capture.test.label]):
        params = dict(info.get("parameters") or {})
        method = str(info.get("method") or params.get("method") or "menzel")
        if not _fitted(info):
            method = "menzel"      # a landmarks layer given a --capture: the default fit scores the capture
        reg = params.get("reg", "auto")
        try:
            reg = float(reg)
        except (TypeError, ValueError):
            reg = str(reg)
        fit = fit_personalized_shapes(capture, method=method, reg=reg)
        # a fit that read its amplitudes on these frames: each frame scored without its own reading
        scored = test_expression_errors(capture, fit.rig, left_out_scale(fit, capture.test))
        source = f"{method} refit"
    elif scored.get("amplitudes_read"):   # personalize's fit scaled shapes by these frames (stop 49)
        source += (f", which read {scored['amplitudes_read']} of its shapes' amplitudes on these frames "
                   "(each frame scored with the others' readings)")
    return _errors_table(scored, source)


def _named(prov: dict, k: int) -> str:
    """` (<path>)`: the k-th input the provenance records, as recorded, or '' when it records none."""
    inputs = list(prov.get("inputs") or [])
    return f" ({inputs[k]})" if len(inputs) > k else ""


def _gone(notes: list, text: str, layer_path: Path) -> None:
    """A recorded input that is no longer there: a note on the page and a warning where the command runs
    (the page silently lost its take's playback, or its test expressions and eq. 5 table; only the page
    said so)."""

    notes.append(text)
    warn(f"{Path(layer_path).name}: {text}")


def _input_kind(path: Path, prov: dict | None) -> str | None:
    """What ``path`` given as the layer is when it is an input of 'personalize' rather than its layer:
    "capture", "take" (meshes and weights), "weights" (a Live Link CSV, an 'anim import' SkelAnimation),
    "avatar" (blend shapes, not personalized), or None. ``prov``: the root layer's usdface data of a USD file
    whose stage opened (None: only folders and CSVs are looked at)."""
    from ..io.file_kind import Kind, file_kind

    found = file_kind(path)
    if found.kind is Kind.CAPTURE_FOLDER:
        return "capture"
    if found.kind is Kind.TAKE_FOLDER:
        return "take" if found.meshes else "weights"
    if found.kind is Kind.LIVELINK_CSV or (found.kind is Kind.MISSING and path.suffix.lower() == ".csv"):
        return "weights"
    if prov is None or found.kind is Kind.FOLDER:
        return None
    if found.kind in (Kind.CAPTURE, Kind.TAKE):        # marked so, or a take by the root layer's specs
        return str(found.kind)
    found = file_kind(path, compose=True)      # the root layer is held by the first answer: not parsed again
    if found.skel_root:
        return "avatar" if not prov and found.blend_shapes else None
    return "weights" if found.skel_animation else None


def _refuse_capture_or_take(path: Path, prov: dict | None) -> None:
    """An input of 'personalize' given to 'review' where its layer goes: say what it is and where it goes
    (a Live Link CSV was 'a USD USD file is expected', a capture folder 'USD file is a folder', a capture,
    a take and a plain avatar 'not a usdface layer')."""
    kind = _input_kind(path, prov)
    if kind is None:
        return
    from ..io.file_kind import folder_files

    csvs = folder_files(path, "*.csv") if kind == "weights" and path.is_dir() else []
    take = csvs[0] if len(csvs) == 1 else path / "TAKE.csv" if csvs else path
    # one word of the pasted command (a folder with a space); a command is never set in quotes of its own
    # (a quoted path inside read 'usdface personalize 'a b.usda' ...'): in parentheses, as pasted
    word = shlex.quote(str(path))
    what, fix = {
        "capture": ("a capture, not a layer written by 'usdface personalize'",
                    f"personalize an avatar with it (usdface personalize AVATAR {word} -o person.usda "
                    f"--review), or score a layer on it (usdface review LAYER --capture {word})"),
        "take": ("a recorded take (meshes and weights), not a layer written by 'usdface personalize'",
                 f"personalize an avatar with it (usdface personalize AVATAR {word} -o person.usda "
                 f"--review), or play it on a layer (usdface review LAYER --take {word})"),
        "weights": ("a take of weights only (a Live Link Face CSV or an 'anim import' SkelAnimation), not a "
                    "layer written by 'usdface personalize'",
                    "play it on a personalized layer (usdface review LAYER --take "
                    f"{shlex.quote(str(take))})"),
        "avatar": ("an avatar that is not personalized (no usdfacePersonalization variant set)",
                   "personalize it first, which writes the layer and its review page (usdface personalize "
                   f"{word} CAPTURE -o person.usda --review)"),
    }[kind]
    if kind == "avatar":
        from ..io.usd_rig import dcc_export_marks

        marks = dcc_export_marks(path)
        if marks:       # Blender's export of a personalized layer: 'personalize it first' would stack it
            raise InputFileError(
                f"this looks like a DCC export (Blender, ...) of a usdface output layer (it has {marks[0]}, "
                "which usdface writes only into a personalized layer or its flattened export): the DCC kept "
                "one variant and "
                "dropped the variant set and the fit figures, so there is no generic | personalized to "
                "compare", path=path, prim=marks[0],
                fix="review the usdface layer it was exported from ('usdface review person.usda'); to "
                    "compare in the DCC, import the original avatar beside the export")
    raise InputFileError(f"this is {what}", path=path, fix=fix)


def _decimate_for_display(meshes: list[ReviewMesh], max_vertices: int | None, box=None) -> list[str]:
    """Replace each mesh of more than ``max_vertices`` vertices (default
    :data:`usdface.mesh.DISPLAY_MAX_VERTICES`, 0: no limit) by a decimated subset of its own vertices
    (:func:`usdface.mesh.display_subset`: neutral, both variants' deltas, heat and landmarks indexed the
    same way; a landmark on the nearest kept vertex). ``box``: ``(lo[3], hi[3])`` the page's views are cut
    to (:func:`usdface.review.page.framed_ranges`): such a mesh keeps only the triangles that meet it
    (nothing beyond it is ever shown), decimated only if they are still over the limit. Returns the page's
    notes naming them."""
    from ..mesh import DISPLAY_MAX_VERTICES, display_subset, index_set, triangles_in_box

    limit = DISPLAY_MAX_VERTICES if max_vertices is None else int(max_vertices)
    notes = []
    for m in meshes:
        visible = (triangles_in_box(m.neutral, m.triangles, *box)
                   if box is not None and 0 < limit < len(m.neutral) else None)
        display = display_subset(m.neutral, m.triangles, limit, visible=visible)
        if display is None:
            continue
        keep, triangles = display
        n = len(m.neutral)
        whole = ("decimated to" if visible is None else
                 "cut to the part in the views' box," if len(keep) == len(index_set(
                     np.asarray(m.triangles)[visible], n)) else
                 "cut to the part in the views' box and decimated to")   # the part alone over the limit
        neutral = np.asarray(m.neutral)[keep]
        if m.landmarks is not None and len(m.landmarks):
            from scipy.spatial import cKDTree

            m.landmarks = cKDTree(neutral).query(np.asarray(m.neutral)[np.asarray(m.landmarks)])[1]
        m.neutral, m.triangles = neutral, triangles
        if m.generic is not None:
            m.generic = np.asarray(m.generic)[:, keep]
        if m.personalized is not None:
            m.personalized = np.asarray(m.personalized)[:, keep]
        if m.heat is not None:
            m.heat = np.asarray(m.heat)[keep]
        notes.append(f"{m.name} ({n:,} vertices) is shown {whole} {len(keep):,} of its vertices (the "
                     "tables' figures are the full mesh's; 'usdface review --max-vertices 0' shows every "
                     "vertex, in a larger and slower page)")
    return notes


def collect_review(layer_path, *, capture=None, take=None, fit_errors: bool = True,
                   max_vertices: int | None = None) -> ReviewData:
    """Everything :func:`usdface.review.page.build_review_html` needs for the usdface layer ``layer_path``.

    ``capture``: the capture (path or :class:`usdface.model.Capture`) whose test expressions are played and
    scored; default the one recorded in the layer's provenance, when it still exists (else no test
    expressions). ``take``: a Live Link Face CSV, USD take or take folder to play (path or
    :class:`usdface.io.take.Take`); default the take the layer was written with (``personalize --take``,
    :func:`recorded_take`), when it still exists. ``fit_errors``: score the generic template and the
    personalized shapes on the capture's test expressions (eq. 5): the layer's own figures
    (:func:`_fit_errors`), or one refit (a few seconds) for another capture or an older layer.
    ``max_vertices``: meshes with more vertices are shown decimated (:func:`_decimate_for_display`)."""
    from ..io import read_capture
    from ..io.flatten import read_avatar_variant
    from ..io.take import TAKE_NOT_CAPTURE_FIX, read_take, refuse_capture_as_take
    from ..io.usd_inspection import read_landmarks
    from ..io.usd_rig import _from_cwd, read_layer_info

    layer_path = Path(layer_path)
    _refuse_capture_or_take(layer_path, None)       # folders and CSVs: no USD reader says what they are
    info = read_layer_info(layer_path)
    prov = info.get("usdface") or {}
    flat = (info.get("flattened") or None) if not info.get("variants") else None
    if flat is not None:          # its provenance says 'usdface personalize': name what it is instead
        source = Path(str(flat.get("source", "")))         # recorded relative to the flattened file
        source = source if source.is_absolute() else layer_path.parent / source
        raise InputFileError(f"a flattened export of the {flat['variant']} variant ('usdface export "
                             "--flatten'): one variant baked in, no generic | personalized to compare",
                             path=layer_path,
                             fix=f"review the layer it was flattened from ({_from_cwd(source)})")
    if not info.get("variants"):
        _refuse_capture_or_take(layer_path, prov)
        command = str(prov.get("command") or "").split()
        what = ("a 'usdface fit' rig on the capture mesh" if prov.get("format") == "fit" else
                "a landmark layout layer ('usdface landmarks')" if prov.get("method") == "landmarks" else
                f"a layer written by '{' '.join(command[:2])}'" if command[:1] == ["usdface"] else
                "not a usdface layer")
        raise InputFileError(f"no usdfacePersonalization variant set ({what})", path=layer_path,
                             fix="review a layer written by 'usdface personalize'")
    personalized = read_avatar_variant(layer_path, "personalized")
    generic = read_avatar_variant(layer_path, "generic")
    meshes = _mesh_pairs(personalized, generic)
    layouts = read_landmarks(layer_path)
    for m, rig in zip(meshes, personalized.meshes, strict=False):
        if rig.source and rig.source.prim in layouts:
            m.landmarks = layouts[rig.source.prim]

    # a layer stacked over the personalize layer (a landmark layout: 'usdface landmarks LAYER -o OUT')
    # reviews that personalization: its capture, take and figures are the personalize layer's (the
    # landmarks layer's own inputs are the layer and the avatar, and its avatar was named as a capture that
    # 'was not found', with no test expressions)
    made_from = layer_path
    if not _fitted(prov):
        made_from, prov = _personalize_layer_below(layer_path) or (layer_path, prov)
    notes = []
    sequences = []
    # the capture the layer records, given by its path (a batch row's, a Pyblish instance's, --capture with
    # the same file): the layer's own figures, as without it; it was refitted as 'another' capture, seconds
    # a page and the capture's warnings again on a resume that wrote only the page (stop 53)
    recorded_file = recorded_capture(made_from, prov)
    recorded = capture is None or _same_file(capture, recorded_file)
    # ... unless the file changed since the layer was written (sha256 differs): the layer's figures were
    # scored on frames the page no longer plays; refitted, as before stop 53 for a given path (stop 53's
    # review)
    if recorded and _capture_changed(made_from, prov, recorded_file):
        recorded = False
        notes.append("the capture changed after the layer was written (sha256 differs): its test expressions "
                     "are scored by a refit, not by the layer's own figures (re-run usdface personalize on "
                     "the current capture)")
    held = None                # the test expressions the layer holds, when its capture is gone
    if capture is None:
        capture = recorded_file
        if capture is None:
            # the capture moved: the layer's own inspection animation plays its test expressions (the page
            # showed none, and no eq. 5 table, although the layer holds both)
            held = layer_test_expressions(layer_path, prov, personalized)
            lost = f"the capture recorded in the layer's provenance{_named(prov, 1)} was not found"
            if held is not None:
                _gone(notes, f"{lost}: its {len(held[2])} test expressions play as the layer's inspection "
                             "animation holds them, scored by the layer's own figures (pass --capture "
                             "CAPTURE to read them from the capture)", layer_path)
            elif prov.get("fitTestExpressions"):
                _gone(notes, f"{lost}, and the layer holds no inspection animation (personalized without "
                             "--inspect or --take): no test expressions to play, the eq. 5 table "
                             "is the layer's own figures (pass --capture CAPTURE, the capture it was "
                             "personalized from)", layer_path)
            else:
                _gone(notes, f"{lost}: no test expressions (the layer holds none of its own; pass --capture "
                             "CAPTURE, the capture it was personalized from)", layer_path)
    if isinstance(capture, str | Path):
        from ..errors import CaptureError
        from ..io.take import WEIGHTS_ONLY_FIX

        try:
            capture = read_capture(capture)
        except CaptureError as exc:   # a weights-only take has nothing to score, but the page plays it
            if exc.fix != WEIGHTS_ONLY_FIX:
                raise
            raise CaptureError(f"{exc.message}: a capture is scored on its test expressions", path=exc.path,
                               prim=exc.prim, fix=f"play it with --take {capture}, and give --capture "
                                                  "a capture with test frames (or leave it out)") from None
    errors = None
    if held is not None:
        sequences.append(Sequence("test expressions (as the layer holds them)", held[0], held[1],
                                  np.arange(len(held[2])) * TEST_HOLD_S, held[2]))
    if capture is None and recorded and fit_errors:     # the capture gone: the figures the layer recorded
        errors = _layer_fit_errors(prov)
    if capture is not None and len(capture.test):
        test = capture.test
        sequences.append(Sequence("test expressions", list(capture.names), test.weights,
                                  np.arange(len(test)) * TEST_HOLD_S, list(test.label)))
        if fit_errors:
            errors = _fit_errors(capture, prov, recorded=recorded)
    whole = capture.whole_take if capture is not None else None
    if whole and not len(capture.test):  # a take fitted whole: it plays itself, there is nothing to score
        notes.append("the capture is a take fitted whole: no held-out test expressions to score (score one "
                     "made by 'usdface capture select TAKE -o capture.usda --test-every 10', with --capture)")
    if isinstance(take, str | Path):         # given: a capture is no take (a recorded one plays as it did)
        refuse_capture_as_take(take, TAKE_NOT_CAPTURE_FIX)
    if take is None and prov.get("take"):   # the take the layer's inspection animation plays
        take = recorded_take(made_from, prov)
        lost = f"the take recorded in the layer's provenance ({prov['take']}) was not found"
        # the take moved: the layer's own inspection animation plays it (the page played none, although
        # the layer holds every frame of it, as the test expressions were played from it since stop 50)
        kept = layer_take(layer_path, prov, personalized) if take is None else None
        if kept is not None:
            sequences.append(Sequence(f"take {Path(str(prov['take'])).name} (as the layer holds it)",
                                      kept[0], kept[1], kept[2], []))
            _gone(notes, f"{lost}: it plays as the layer's inspection animation holds it, on the avatar's "
                         "channels (pass --take TAKE to read it from the take)", layer_path)
        elif take is None:
            _gone(notes, f"{lost}: not played (pass --take)", layer_path)
    if take is None and capture is not None:  # a take read whole as the capture: play it
        from ..io.take import whole_take_playback

        played = whole_take_playback(capture)
        if played is not None:
            name = Path(str(capture.source or "take")).name
            sequences.append(Sequence(f"take {name} (every frame fitted)", *played, []))
    if take is not None:
        data = take if not isinstance(take, str | Path) else read_take(take, meshes=False)  # played only
        if len(data):
            t = np.asarray(data.times, dtype=np.float64)
            name = Path(str(take if isinstance(take, str | Path) else data.source or "take")).name
            sequences.append(Sequence(f"take {name}", list(data.names), data.weights, t - t[0], []))

    tables = _provenance_tables(prov)
    changes = []
    for m in meshes:
        if m.names:
            top = shape_changes(m.personalized, m.generic)[1]
            changes.append((m.name, m.names, top))
    if changes:
        rows = []
        for name, names, top in changes:
            # changed: some vertex moved by more than 1 nm, the rule of personalize's report (a float32
            # rounding of an unchanged offset is no change)
            kept = [n for n, t in zip(names, top, strict=True) if t <= CHANGE_TOL_M]
            rows.append((f"{name}: shapes changed", f"{int((top > CHANGE_TOL_M).sum())} of {len(names)} "
                         f"(largest change {top.max() * 1000:.2f} mm)"))
            if len(kept) == len(names):
                why = (" (approximation=generic: meshes and regions the capture does not see keep the "
                       "avatar's generic shapes)"
                       if (prov.get("parameters") or {}).get("approximation") == "generic" else "")
                rows.append((f"{name}: left generic", f"all {len(names)} shapes{why}"))
            elif kept:      # the count and the first few; the whole list one click away
                rows.append((f"{name}: left generic", Listing(kept)))
        tables.append(("what changed", rows))
    for w in prov.get("warnings") or []:
        notes.append(f"warning: {w}")
    # the views' box from the full meshes (what moves), before the meshes beyond it are cut off
    box = framed_ranges(meshes)
    notes.extend(_decimate_for_display(meshes, max_vertices, box))   # after every figure of the full meshes
    title = f"usdface review: {layer_path.name}"
    return ReviewData(title, meshes, sequences, tables, errors, notes, view_box=box)
