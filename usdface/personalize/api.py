"""The public entry point: :func:`fit_personalized_shapes` (method dispatch, input checks, options)."""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import FitError, GeometryError
from ..errors import warn as _warn
from ..locks import SharedWhileInside
from ..mesh import boundary_loops, check_triangles, mesh_scale, squared_lengths
from ..model import Capture, FaceRig
from .align import distinct_frames, expression_weights, rigid_transforms, rigid_transforms_sets
from .amplitude import (
    amplitude_terms,
    combined_amplitude,
    each_frame_left_out,
    held_out_amplitude,
    peak_amplitude_variance,
)
from .crossval import choose_regularization, cv_vertices
from .dt import deformation_transfer
from .fit import (
    D_CLAMP,
    FitSystem,
    PositionFit,
    _take1,
    blend,
    data_share,
    estimate_variance,
    fit_blendshapes,
    frame_error_variance,
    james_stein,
    regularization_weights,
    take_frame_noise,
    take_white_noise,
    weight_leak_direction,
    weight_leak_variance,
)
from .weak import WEIGHT_NOISE, toward_prior, weak_ramp
from .weights import (
    held_weights,
    reestimate_weights,
    reestimate_weights_batched,
    shape_basis,
    weight_error_variance,
    weight_noise,
    weight_residuals,
)

__all__ = ["METHODS", "FitResult", "fit_personalized_shapes", "check_capture", "check_fit_options"]

#: Methods of :func:`fit_personalized_shapes`.
METHODS = ("dt", "ebfr", "menzel", "laplacian")

#: Prior widths (std of the phone's weight error) tried by ``weight_sigma="auto"``.
WEIGHT_SIGMAS = (0.01, 0.02, 0.05)
#: Principal axes of the face the re-estimation CV splits along (1: the two halves across the longest axis;
#: 2 gave the same decisions on dev1-dev3 and the sample at twice the cost).
REWEIGHT_SPLIT_AXES = 1

#: A shape whose largest training weight is below this is "never activated".
ACTIVATION_MIN = 0.05
#: A take read whole must show at least this many distinct poses (:func:`usdface.personalize.takefit.
#: distinct_poses`), as a capture must hold at least this many shapes.
MIN_TAKE_POSES = 4
#: Significance level of the tests that switch the beyond-paper steps on (:func:`significantly_better`).
SIGNIFICANCE = 0.05
#: Alignment passes (each frame to the leave-one-out prediction of the fit on the others).
ALIGN_PASSES = 2


@dataclass
class FitResult:
    """Result of :func:`fit_personalized_shapes`.

    ``rig``: FaceRig on the capture mesh (neutral = B0 [n,3] m, deltas = personalized B_j [K,n,3] m,
    names = capture.names). ``info``: method, chosen ``reg``, ``timings`` (s), ``warnings`` (list of str),
    per-option figures (e.g. ``loo_rmse_mm`` of the regularisation search, ``train_rmse_mm``).
    """

    rig: FaceRig
    info: dict = field(default_factory=dict)

    def __repr__(self) -> str:
        # one line (the dataclass repr printed the rig's arrays and the info's per-frame figures)
        info = self.info if isinstance(self.info, dict) else {}
        reg = f", reg {info['reg']:g}" if isinstance(info.get("reg"), int | float) else ""
        return f"<FitResult {info.get('method', '?')}{reg}: {self.rig!r}; info: {', '.join(map(str, info))}>"


def check_capture(capture: Capture, *, train=None) -> list[str]:
    """Validate a capture for fitting; raise on unusable input, return warnings for degraded input.

    Raises :class:`GeometryError` (vertex-count mismatch, degenerate template triangles, non-finite points)
    or :class:`FitError` (no training frames, no shapes). Warns (returned strings) about fewer training
    frames than shapes, shapes never activated in training (by name) and training frames that repeat another
    exactly (:func:`duplicate_frames`, by label). ``train``: the capture's training frames if the caller
    has them (``capture.train`` copies them).
    """
    src = capture.source or None
    n = len(capture.neutral)
    tmpl = capture.template
    if len(capture.names) == 0:
        raise FitError("the capture has no blendshapes", path=src, fix="add template shapes to the capture")
    if tmpl.n_vertices != n:
        raise GeometryError(f"template has {tmpl.n_vertices} vertices, the neutral scan {n}", path=src,
                            fix="the template must be on the capture's topology")
    pts = capture.frames.points
    if pts.ndim != 3 or pts.shape[1:] != (n, 3):
        bad = [lab for lab, p in zip(capture.frames.label, pts, strict=False) if p.shape != (n, 3)]
        raise GeometryError(f"frames have a different vertex count than the neutral ({n}): "
                            f"{', '.join(bad[:5]) or pts.shape}", path=src,
                            fix="every frame must be on the capture topology, in the same vertex order")
    check_triangles(tmpl.neutral, capture.triangles, what="template neutral", path=src)
    check_triangles(capture.neutral, capture.triangles, what="neutral scan", path=src)
    train = capture.train if train is None else train
    if len(train) == 0:
        raise FitError("no training frames", path=src, fix="add frames with role 'train' (train/ folder)")
    if not np.all(np.isfinite(train.points)) or not np.all(np.isfinite(train.weights)):
        raise GeometryError("non-finite training points or weights", path=src, fix="repair the frames")
    _check_frames_like_neutral(capture, src)
    if not np.any(np.abs(train.weights) >= ACTIVATION_MIN):
        raise FitError(f"no training frame activates any shape (every weight below {ACTIVATION_MIN})",
                       path=src, fix="the frames' blendshape weights are missing or zero: export them with "
                       "the scans (weights.json / the take's weight channels)")
    warn = []
    # frames that are one frame (points and weights to the bit): found once, for the swapped-sides test and
    # the repeated-frames warning
    groups = None if capture.whole_take else distinct_frames(train.points, train.weights)
    swapped = refuse_swapped_sides(capture, train=train, groups=groups)
    if swapped is not None:
        warn.append(_swapped_message(swapped, capture) + " (fix: turn the app's mirroring off and export "
                    "again, or exchange the Left/Right weight names)")
    K = len(capture.names)
    if len(train) < K:
        warn.append(f"{len(train)} training frames for {K} shapes: the fit is underdetermined; shapes the "
                    f"frames do not determine are held to the template")
    never = [nm for nm, w in zip(capture.names, train.weights.max(axis=0), strict=True) if w < ACTIVATION_MIN]
    if never:
        warn.append(f"shape(s) never activated in training (max weight < {ACTIVATION_MIN}): "
                    f"{', '.join(never)}; the frames barely measure them: the fit holds them towards the "
                    "prior only as far as the regularization does (personalize keeps them generic)")
    # a take read whole holds near-repeats by nature (a held pose, a doubled frame rate): its frame weights
    # count a pose once (takefit); the message is about a capture app's picked frames
    groups = [] if capture.whole_take else duplicate_frames(train.points, train.weights, groups=groups)
    if groups:
        repeats = sum(len(g) - 1 for g in groups)
        shown = "; ".join(" = ".join(train.label[i] for i in g[:4]) + (f" (+{len(g) - 4})" if len(g) > 4
                                                                         else "")
                          for g in sorted(groups, key=len, reverse=True)[:3])
        more = f"; and {len(groups) - 3} more group(s)" if len(groups) > 3 else ""
        warn.append(f"{repeats} training frame(s) repeat another frame exactly (the same scan and "
                    f"weights under another label: {shown}{more}): {len(train) - repeats} distinct frames; "
                    "the capture app kept one frame for several requested shapes, so those shapes are not "
                    "measured separately (record them again to personalize each)")
    return warn


#: The exchanged labels are taken as proven, and the capture refused, when they explain at least this many
#: times as many frames distinctly better as the reported ones do (and at least 10) ...
SIDES_PROVEN_FRAMES = 10
#: ... with an RMS residual at most this share of the reported labels' (the sample and dev1-dev3 exchanged:
#: 0.39-0.74; as reported the exchanged labels explain the scans 1.4-2.6x worse).
SIDES_PROVEN_RATIO = 0.8


def _swapped_message(swapped: dict, capture: Capture) -> str:
    what = "take's" if capture.whole_take else "capture's"
    return (f"the {what} Left and Right weights look exchanged: with every *Left/*Right weight swapped the "
            f"template explains the scans better ({swapped['swapped_mm']:.2f} mm RMS against "
            f"{swapped['reported_mm']:.2f} mm as reported; {swapped['frames_swapped']} frame(s) better "
            f"swapped, {swapped['frames_reported']} as reported). A capture app showing a mirrored (selfie) "
            "view may write the sides exchanged; the fit would learn each side's shape from the other side's "
            "motion")


#: A fitted rig's neutral is its capture's own neutral (the person's scan, B0): two agree to this share of the
#: capture mesh's edge length (:func:`usdface.mesh.mesh_scale`, ~3 mm on a phone mask: ~3 um), far above a
#: float32 file's rounding (~1e-8 m) and far below any two scans' difference (scan noise alone ~0.15 mm).
SAME_NEUTRAL = 1e-3


def refuse_rig_of_another_capture(rig: FaceRig, capture: Capture, *, fix: str, what: str = "the rig",
                                  path=None, same_neutral: bool = False) -> None:
    """A capture-mesh ``rig`` whose vertex count is not the capture mesh's (a rig fitted on another capture:
    scored by ``evaluate_capture``, implanted by ``personalize_avatar(rig=)``) refused with
    :class:`FitError` naming the capture (``path``, default its source), both counts and ``fix``: it died
    in numpy (``matmul: ... (1203 vs 1233)``) or as a GeometryError naming no file. ``same_neutral``: the
    rig is one *fitted on* the capture (``write_fit_rig(capture=)`` records it as its source), so its neutral
    must also be the capture's (within :data:`SAME_NEUTRAL` of an edge): another capture of the same phone
    mesh (bench dev1 and dev3, 1,203 vertices each; every ARKit face mesh has 1,220) has the count."""
    where = path if path is not None else (capture.source or None)
    n = capture.neutral.shape[0]
    if rig.n_vertices != n:
        raise FitError(f"{what} has {rig.n_vertices} vertices, the capture mesh {n}: a rig fitted on another "
                       "capture", path=where, fix=fix)
    if same_neutral:
        moved = float(np.sqrt(np.max(squared_lengths(rig.neutral - capture.neutral))))
        if moved > SAME_NEUTRAL * mesh_scale(capture.neutral, capture.triangles):
            raise FitError(f"{what}'s neutral is {moved * 1e3:.3g} mm from the capture's neutral at its "
                           "furthest vertex: a rig fitted on another capture", path=where, fix=fix)


def refuse_swapped_sides(capture: Capture, *, train=None, groups=None) -> dict | None:
    """:func:`swapped_sides` on the capture's training frames: refused (:class:`FitError`) when the
    exchanged labels are proven (:data:`SIDES_PROVEN_FRAMES`, :data:`SIDES_PROVEN_RATIO`: a user trial's
    mirrored take was personalized 2.85x further from the person than generic, jawLeft 5.7 mm worse, after a
    warning); the weaker finding is returned for a warning, None when the sides look right. ``train``: the
    capture's training frames if the caller has them (``capture.train`` copies them); ``groups``: their
    :func:`.align.distinct_frames` (in points and weights) if the caller has them."""
    train = capture.train if train is None else train
    if len(train) == 0:
        return None
    found = swapped_sides(train.points, capture.neutral, capture.template.deltas, train.weights,
                          capture.names, groups=groups)
    if found is None:
        return None
    if (found["frames_swapped"] >= SIDES_PROVEN_FRAMES * max(found["frames_reported"], 1)
            and found["swapped_mm"] <= SIDES_PROVEN_RATIO * found["reported_mm"]):
        where = ("the take's CSV header (or the USD take's weight names)" if capture.whole_take
                 else "every frame's JSON (train/ and test/)")
        raise FitError(_swapped_message(found, capture), path=capture.source or None,
                       fix="turn the capture app's mirroring off and record or export again, or exchange "
                       f"Left and Right in the weight names of {where}")
    return found


#: A frame is explained distinctly better by one labelling than the other when its residual is at most this
#: share of the other's.
SIDE_MARGIN = 0.9


def swapped_sides(points, neutral, template_deltas, weights, names, *, chunk: int = 64,
                  groups=None) -> dict | None:
    """Whether the capture's Left/Right weights are exchanged (a mirrored capture app): the residual of
    the scans ``points[F,n,3]`` (m) from ``neutral[n,3]`` plus the template's motion
    ``template_deltas[K,n,3]`` under the reported ``weights[F,K]``, against the same with every
    ``*Left``/``*Right`` column exchanged
    (:func:`usdface.arkit.mirror_name`). Returns ``{"reported_mm", "swapped_mm", "frames_reported",
    "frames_swapped"}`` when the exchanged labels explain the scans better overall and in more frames (at
    least 3) distinctly (:data:`SIDE_MARGIN`); None otherwise (also when no shape has a partner). On the
    sample and dev1-dev3, templates by another artist included, the reported labels explain the scans
    1.4-2.6x better. Each frame is first placed rigidly on the neutral by the vertices no template shape
    moves (:func:`usdface.personalize.align.rigid_transforms`): 1-5 degrees of head motion between scans
    hid a swap (a review). ``||x - w T||^2 = ||x||^2 - 2 w.(T x) + w^T (T T^T) w``: frames in chunks of
    ``chunk``, no ``[F,n,3]`` temporary. ``groups``: :func:`.align.distinct_frames` of ``points`` and
    ``weights`` if the caller has them (a repeated frame - the same scan and weights - is placed and scored
    once and counted by its copies; None: not known, no ``[F,n,3]`` copy is made to find them - a whole
    take's thousands of frames)."""
    from ..arkit import mirror_name
    from .align import rigid_transforms, static_vertices

    names = list(names)
    where = {n: i for i, n in enumerate(names)}
    perm = np.array([where.get(mirror_name(n), i) for i, n in enumerate(names)])
    w = np.asarray(weights, dtype=np.float64)
    if (perm == np.arange(len(names))).all() or len(w) == 0:
        return None
    static = static_vertices(template_deltas)
    inverse = None
    if groups:                               # each distinct frame once: every step works frame by frame
        first, inverse = groups
        points, w = np.take(np.asarray(points), first, axis=0), w[first]
        rot, shift = rigid_transforms(points, neutral, static, groups=False)
    else:                                    # the rigid fit finds frames repeated on the static vertices
        rot, shift = rigid_transforms(points, neutral, static)
    t = np.asarray(template_deltas, dtype=np.float64).reshape(len(names), -1)      # [K,3n]
    b = np.asarray(neutral, dtype=np.float64).reshape(-1)
    gram = t @ t.T
    r_rep = np.empty(len(w))
    r_sw = np.empty(len(w))
    for lo in range(0, len(w), chunk):
        placed = np.matmul(np.asarray(points[lo:lo + chunk], dtype=np.float64),
                           np.swapaxes(rot[lo:lo + chunk], 1, 2)) + shift[lo:lo + chunk, None, :]
        x = placed.reshape(-1, b.size) - b                                                 # [c,3n]
        xx = np.einsum("fi,fi->f", x, x)
        cx = x @ t.T                                                                       # [c,K]
        for out, ww in ((r_rep, w[lo:lo + chunk]), (r_sw, w[lo:lo + chunk][:, perm])):
            out[lo:lo + len(x)] = np.maximum(xx - 2.0 * np.einsum("fk,fk->f", ww, cx)
                                             + np.einsum("fk,kl,fl->f", ww, gram, ww), 0.0)
    if inverse is not None:
        r_rep, r_sw = r_rep[inverse], r_sw[inverse]
    better_sw = int(np.sum(r_sw < SIDE_MARGIN ** 2 * r_rep))
    better_rep = int(np.sum(r_rep < SIDE_MARGIN ** 2 * r_sw))
    n = max(len(b) // 3, 1)
    rep_mm, sw_mm = (1e3 * float(np.sqrt(r.mean() / n)) for r in (r_rep, r_sw))
    if sw_mm < rep_mm and better_sw > better_rep and better_sw >= 3:
        return {"reported_mm": rep_mm, "swapped_mm": sw_mm, "frames_reported": better_rep,
                "frames_swapped": better_sw}
    return None


def duplicate_frames(points: np.ndarray, weights: np.ndarray, *, groups=False) -> list[list[int]]:
    """Groups of training frames that are exactly the same frame: ``points[F,n,3]`` and ``weights[F,K]``
    equal to the last bit (a capture app that keeps one frame for several requested shapes writes it once per
    shape). Returns the groups of two or more frame indices, ascending, in order of their first frame; [] if
    every frame is distinct. :func:`.align.distinct_frames` (one vectorised pass, each repeat confirmed bit
    for bit; no copy of the frames), which the fit's alignment and leave-one-out use too; ``groups``: its
    result if the caller has it (False: found here)."""
    groups = distinct_frames(points, weights) if groups is False else groups
    if groups is None:
        return []
    inverse = groups[1]
    members = np.split(np.argsort(inverse, kind="stable"), np.cumsum(np.bincount(inverse))[:-1])
    return [g.tolist() for g in members if len(g) > 1]


def _generic_shapes(capture: Capture, eyelids: bool, loops: list | None = None) -> np.ndarray:
    """The template's shapes transferred onto the capture's neutral (:func:`.dt.deformation_transfer`),
    ``[K,n,3]`` m; ``loops``: the mesh's :func:`usdface.mesh.boundary_loops` if the caller has them."""
    t = capture.template
    return deformation_transfer(t.neutral, t.deltas, capture.neutral, capture.triangles, names=capture.names,
                                eyelids=eyelids, loops=loops)


#: The process's ``threadpoolctl.ThreadpoolController`` and ``len(sys.modules)`` when it was made.
_BLAS_CONTROLLER: list = [None, -1]


def _blas_controller():
    """One ``ThreadpoolController`` per process, made again only after new modules were imported (an
    extension module may have loaded another BLAS): ``threadpool_limits`` lists every loaded library on each
    call (~1.4 ms, every fit), the controller's ``limit`` only sets the thread counts (~0.04 ms)."""
    import sys

    from threadpoolctl import ThreadpoolController

    if _BLAS_CONTROLLER[0] is None or _BLAS_CONTROLLER[1] != len(sys.modules):
        _BLAS_CONTROLLER[0] = ThreadpoolController()
        _BLAS_CONTROLLER[1] = len(sys.modules)
    return _BLAS_CONTROLLER[0]


def _blas_control(take: bool) -> None:
    """Make the calling thread the one that may set OpenBLAS's thread count (``take``), or give that up.

    threadpoolctl (3.8 here) lets only one thread change the process-wide thread count of an OpenBLAS
    built on pthreads, the first that did while it is alive, and silently ignores every other thread's
    limit. A host's main thread outlives everything: after one ``personalize_avatar`` there, every later one
    on the host's worker threads (a thread pool, a DCC's background job, a Dask worker's threads) ran with
    the multi-threaded BLAS, its fit 4-6x slower on a busy 2-core machine, and when the last one out was on
    another thread than the first in, the host's thread counts were not put back. The limit is
    process-wide by design here (:data:`_ONE_BLAS_THREAD`), so the thread that sets or puts back the counts
    takes control for that moment and gives it up afterwards."""
    try:
        from threadpoolctl import OpenBLASController
    except ImportError:                      # an older threadpoolctl: every thread may set the counts
        return
    clear = getattr(OpenBLASController, "clear_controlling_thread", None)
    if clear is not None:
        clear(force=take)                    # giving up (force=False) clears only this thread's control


def _limit_blas():
    from ..natives import blas_started_single_threaded

    if blas_started_single_threaded():     # the program started every BLAS at one thread: nothing to limit
        return None
    _blas_control(take=True)
    try:
        return _blas_controller().limit(limits=1, user_api="blas")
    finally:
        _blas_control(take=False)


def _restore_blas(limiter) -> None:
    if limiter is None:
        return
    _blas_control(take=True)
    try:
        limiter.restore_original_limits()
    finally:
        _blas_control(take=False)


#: BLAS at one thread while any thread is inside; the host's thread counts put back by the last one out.
_ONE_BLAS_THREAD = SharedWhileInside(_limit_blas, _restore_blas)


def one_blas_thread() -> SharedWhileInside:
    """BLAS limited to one thread while any thread of the process is inside; the host's thread counts are
    put back when the last one leaves. The limit is process-wide, so calls on several threads at once (a
    host's thread pool, a Dask worker's threads) share one: each with its own ``threadpool_limits`` put back
    the counts it found, which another had already lowered, and the host was left with a one-thread BLAS."""
    return _ONE_BLAS_THREAD


def single_threaded_blas(func):
    """Run ``func`` with BLAS limited to one thread (:func:`one_blas_thread`): thousands of tiny (K x K)
    LAPACK calls and the mid-sized products of the fit and the transfer run 2-3x slower (seconds at high
    load) with a multi-threaded BLAS on a busy 2-core machine."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with one_blas_thread():
            return func(*args, **kwargs)

    return wrapper


_single_threaded_blas = single_threaded_blas


@_single_threaded_blas
def fit_personalized_shapes(capture: Capture, method: str = "menzel", reg="auto", *, prior: str | None = None,
                            align: bool | None = None, reweight: bool | None = None, eyelids: bool = True,
                            clamp: float = D_CLAMP, weight_sigma="auto", rounds: int = 1,
                            avatar_prior=None, frame_weights=None, pins=None, contact: str = "auto",
                            every: int = 1, sensitivity: bool = False, amplitude: bool | None = None,
                            weak_prior: bool = False, **options) -> FitResult:
    """Personalized blendshapes on the capture mesh.

    Parameters
    ----------
    capture : the capture (neutral B0 [n,3] m, template rig on the same topology, train frames S_i [F,n,3]
        with weights [F,K]).
    method : "menzel" (eqs. 1-3, default), "dt", "ebfr" or "laplacian".
    reg : balance of E_reg against E_fit for menzel/laplacian: "auto" (leave-one-frame-out cross-validation,
        :func:`usdface.personalize.crossval.choose_regularization`), "paper" (1.0, the paper's plain sum) or a
        number.
    prior : the generic shapes T_j of eq. (2): "dt" (the paper: template transferred to B0), "template" (the
        template's deltas as they are, same topology) or "auto" (a blend of both chosen by the same
        cross-validation; needs ``reg="auto"``). Default: "auto" with ``reg="auto"``, else "dt". The weights
        D_j of eq. (3) always come from the DT shapes.
    align : robust rigid pre-alignment of every training frame (menzel/laplacian/ebfr): each frame is aligned
        to its leave-one-out prediction (the fit on the other frames), twice, on the moving vertices
        (:mod:`.align`) - if it generalises: a transform estimated on one spatial half of the face must lower
        the other half's leave-one-out residual (:func:`_alignment_generalises`), otherwise the frames are
        left as they are (``info["align"]["applied"]``). Default: on, except with ``reg="paper"``.
    reweight : alternate the shape fit with re-estimating each training frame's weights (bounded to [0,1],
        anchored to the phone's with prior std ``weight_sigma``), ``rounds`` times (:mod:`.weights`; default
        one: the re-estimation from the phone-weight shapes that the gate validates - a later round
        re-estimates from shapes already refitted to the previous round's weights, which took part of their
        errors in, and drifts with them: dev2's truth error 0.3305 / 0.3458 / 0.3527 mm after 1 / 2 / 3
        rounds) - if it helps by a spatially split cross-validation (:func:`_reweight_helps`), else a no-op
        (``info["reweight"]["applied"]``). ``weight_sigma="auto"`` picks the prior width from
        :data:`WEIGHT_SIGMAS` by the same criterion. Shapes the phone never activates keep its weights, and
        each shape keeps its weight in its peak frame (the frame of its largest weight: there weight and
        amplitude are not separately identifiable, :func:`.weights.held_weights`).
        Default: on, except with ``reg="paper"``.
    avatar_prior : optional ``deltas[K,n,3]`` (metres, capture frame, ``capture.names`` order): the avatar's
        own generic shapes mapped onto the capture mesh; a row of NaN = the avatar lacks that shape. With
        ``prior="auto"`` (the default with ``reg="auto"``) the candidates for T_j of eq. (2) are today's
        blend of DT and template (alpha in {0, 1/2, 1}) and the avatar prior (the blend where it is NaN),
        each with its own CV-tuned ``reg``; the exact leave-one-frame-out criterion picks one. The choice is
        one for all shapes, not per shape: a per-shape choice among {DT, template, blend, avatar} (the LOO
        error is an exact quadratic in the one-hot choice; minimising it shape by shape was tried) overfits
        the selection - on dev3 it lowered the LOO error but left the truth error at 0.44 mm, where the one
        global choice reaches 0.21 mm. The fit still falls back per shape where the data are silent: eq. (2)
        holds the shapes (and the combinations of shapes) the frames do not determine at the prior, and a
        shape with zero weight in every frame is returned as its prior exactly. The capture template is
        another artist's rig, so there the avatar's own shape is the safe fall-back (transferring it back onto
        the avatar changes nothing). ``prior="avatar"`` forces it (DT where NaN), with any ``reg``.
        Menzel/laplacian only.
    frame_weights : optional per-training-frame weights ``omega[F] >= 0`` of E_fit (and of the LOO
        criterion), or ``"balanced"`` (:func:`usdface.personalize.takefit.balanced_frame_weights`): for
        fitting on every frame of a take. Menzel/laplacian; alignment and re-estimation are then off
        (they act on the frames as scanned; asking for them is refused). Default None: ``"balanced"`` for a
        whole-take capture (``capture.metadata["whole_take"]``, a take read as a capture), else unweighted.
    every : for a take read whole (``capture.metadata["whole_take"]``): fit every ``every``-th frame (1: all).
        A long take's fit costs O(n F r) time and memory; most of the gain stays at 2-4 (docs/takes.md).
        Refused (:class:`FitError`) for a capture of picked frames.
    pins : artist constraints (Hable): parts of shapes pinned to the artist's version, the template's
        deltas - ``{shape name: vertex indices or bool[n]}`` or a bool ``[K,n]`` mask. A pinned vertex of a
        shape is returned exactly as the template has it (within rounding); the other shapes at that vertex
        and the shape elsewhere are fitted around it. Menzel/laplacian.
    contact : lip and eyelid contact (Hable), :mod:`.contact`: the pairs of vertices across the mouth and eye
        openings that the template's ``mouthClose`` (on ``jawOpen``), ``mouthPress*``, ``mouthRoll*`` and
        blinks bring into contact are kept at the template's gap by a smooth (Laplacian) correction of the
        fitted shape. ``"auto"`` (default): only for shapes whose training frames agree with contact (a
        likelihood-ratio test; a no-op where the person's own frames show the sides apart), ``"on"``: every
        shape with pairs, ``"off"``: no correction (the gaps are still measured). ``info["contact"]``
        reports per shape the pairs, whether the correction was applied and the largest gap (mm, vs the
        template's) before and after.
        Menzel/laplacian (``"on"`` with another method is refused).
    eyelids : virtual eyelid triangles in the deformation transfer.
    sensitivity : also measure each shape's sensitivity to the weights' noise, ``info["weight_sensitivity"]``
        (:func:`weight_sensitivity`; menzel on a capture of picked frames; one more re-estimation and solve,
        ~0.03 s on dev1), and the weights' noise as the capture shows it, ``info["weight_noise"]``
        (:func:`.weights.weight_noise`), with the error it puts into each shape at each vertex,
        ``info["weight_leak"][n,K]`` (m^2, :func:`.fit.weight_leak_variance` of each reported weight's error
        variance by its side of the phone's clip, :func:`weight_error_variance`, from the final fit's own
        factorization, :class:`.fit.FitSystem`; ~0.02 s): what the implant trusts a shape by
        (``personalize`` asks for it). On a capture with test frames it also scales each fitted shape by
        its amplitude as they read it (``amplitude``).
    amplitude : menzel on a capture of picked frames with test frames: scale each fitted shape by its
        amplitude as the fit's peak-frame weight and the capture's test frames read it together
        (:mod:`.amplitude`, ``info["test_amplitude"]``). A shape's size is otherwise fixed by its one weight
        in its peak frame (the training frames hold no second reading of it), so the phone's error in that
        weight is the shape's; the test frames are independent readings. They then set K numbers of the
        fit, so eq. 5 on them is scored cross-fitted: ``info["test_scale_left_out"][T,K]``, the scale of
        each shape read without test frame ``t`` relative to the one applied
        (:func:`.amplitude.each_frame_left_out`), which :func:`.evaluate.evaluate_rig` takes as ``scale``
        (:func:`left_out_scale`). Default: on, except with ``reg="paper"`` without ``sensitivity`` (the
        paper's fit). Generated captures: the fit's truth error fell on 122 of 144, rose on 21; dev2 0.828
        -> 0.750 of the template's.
    weak_prior : menzel/laplacian, off by default: return each shape the training frames show too weakly to
        measure towards its prior ``T_j`` of eq. (2), by the implant's ramp over its effective weight (the
        root of its training energy) between 4 and 10 times the phone's weight noise
        (:func:`.weak.weak_ramp`; ``info["weak"]``: the factor of each shape below 1). On the phone-mesh
        captures what the one frame that shows such a shape leaves unexplained goes into it at ~1/weight
        and the leave-one-frame-out criterion cannot see it (leaving that frame out returns the shape to
        its prior): truth error dev1 0.1940 -> 0.1744 mm, dev2 0.2998 -> 0.2969, dev3 0.4761 -> 0.4283.
        Not the default: on generated captures missing a third of their frames (``/minus3``), whose weakly
        shown shapes the frames do measure, 20 of 22 got worse (by up to 0.22 mm; summed ratio to the
        template 9.55 -> 11.56), dev3/minus3 0.584 -> 0.600 (docs/fit.md, stop 52). ``personalize``'s
        implant applies the same ramp relative to the avatar's shapes itself.
    clamp : eq. (3) clamp (1e5).
    options : method-specific (ebfr: ``beta`` (0.5, or "auto"), ``kappa``, ``theta``, ``translation_ridge``;
        laplacian: ``laplacian_weight`` ("auto": K-fold CV of the Laplacian fit, or a number),
        ``mask_threshold``, ``tol``, ``max_iter``). Options a method cannot use raise :class:`FitError`.

    Returns a :class:`FitResult`. Raises FitError / GeometryError on unusable input (see
    :func:`check_capture`); warnings are in ``result.info["warnings"]`` and issued as ``UserWarning``.
    For menzel/laplacian ``info`` also holds ``prior_choice`` (list[str] per shape: "dt", "template", "blend"
    (``prior_alpha`` DT + rest template when no avatar prior is given) or "avatar") and ``shape_confidence``
    (``[K]`` in [0, 1]: how much the capture determines each shape, the diagonal of the hat matrix
    ``A_v^-1 W^T W`` of eqs. (1)+(2) for that shape - the fraction of ``b_vj`` that follows the frames rather
    than the prior - averaged over vertices with weights ``|T_vj|^2`` of the DT shape, at the chosen ``reg``
    with the phone's weights: 0 for a shape with zero training weight, ~1 for a shape isolated at weight 1
    in clean data; :meth:`usdface.personalize.fit.PositionFit.data_share`).
    """
    check_fit_options(method, reg, prior=prior, align=align, reweight=reweight, clamp=clamp,
                      weight_sigma=weight_sigma, contact=contact, avatar_prior=avatar_prior is not None,
                      path=capture.source or None, amplitude=amplitude, weak_prior=weak_prior, **options)
    check_every(every, capture)
    if pins is not None:
        _pin_mask(pins, capture, method)                  # validate before the work starts
    auto = isinstance(reg, str) and reg == "auto"
    paper = isinstance(reg, str) and reg == "paper"
    align_arg, reweight_arg = bool(align), bool(reweight)
    align = (not paper) if align is None else bool(align)
    reweight = (not paper) if reweight is None else bool(reweight)
    # personalize (sensitivity) reads them at any reg, as it has since stop 49; a plain fit at the paper's
    # balance is the paper's method
    amplitude = (sensitivity or not paper) if amplitude is None else bool(amplitude)
    prior = prior or ("auto" if auto else "dt")
    avatar, avatar_ok = _check_avatar_prior(avatar_prior, capture, method, prior)
    timings = {}
    t0 = time.perf_counter()
    train = capture.train                  # one copy of the training frames for the checks and the fit
    n_test = capture.frames.role.count("test")
    warn = check_capture(capture, train=train)
    for w in warn:
        _warn(w)                                # at the caller's line
    info: dict = {"method": method, "warnings": warn, "timings": timings}
    t1 = time.perf_counter()
    # the mesh's holes, found once for the eyelids of the transfer and the contact step's openings
    loops = (boundary_loops(capture.triangles, len(capture.neutral))
             if eyelids or method in ("menzel", "laplacian") else None)
    generic = _generic_shapes(capture, eyelids, loops)
    timings["dt"] = time.perf_counter() - t1
    points, weights = train.points, train.weights
    if every > 1:
        points, weights = points[::every], weights[::every]
        info["whole_take_every"] = int(every)
    if capture.whole_take:
        info["take_poses"] = round(check_take_poses(capture, every), 1)
    tmpl = capture.template
    if frame_weights is None and capture.whole_take and method in ("menzel", "laplacian"):
        frame_weights = "balanced"          # every frame of a take: a held pose counts once (takefit)
    elif frame_weights is None and capture.whole_take and method == "ebfr":
        info["frame_weights"] = {"min": 1.0, "max": 1.0, "effective_frames": float(len(weights)),
                                 "frames": len(weights), "mode": "equally (ebfr takes no frame weights)"}
    if frame_weights is not None:
        from .takefit import balanced_frame_weights, weighted_frames

        if method not in ("menzel", "laplacian"):
            raise FitError(f"frame_weights is not used by method {method!r}", fix="use menzel or laplacian")
        if align_arg or reweight_arg:
            raise FitError("frame_weights with align/reweight", fix="drop align/reweight (they act on the "
                           "frames as scanned) or frame_weights")
        bad = FitError(f"frame_weights {str(frame_weights)[:40]!r} is not a weighting",
                       fix=f"pass 'balanced', or one weight >= 0 per training frame ({len(weights)} numbers; "
                           "all 1 weights every frame equally)")
        if isinstance(frame_weights, str) and frame_weights != "balanced":
            raise bad
        try:
            omega = (balanced_frame_weights(weights) if isinstance(frame_weights, str)
                     else np.asarray(frame_weights, dtype=np.float64))
        except (TypeError, ValueError):
            raise bad from None
        if (omega.shape != (len(weights),) or not np.all(np.isfinite(omega)) or np.any(omega < 0)
                or not np.any(omega > 0)):
            raise FitError(f"frame_weights must be {len(weights)} finite numbers >= 0, not all 0 (or "
                           "'balanced')", fix="one weight per training frame")
        points, weights = weighted_frames(capture.neutral, points, weights, omega)
        align = reweight = False
        n_eff = float(omega.sum() ** 2 / max(np.sum(omega ** 2), 1e-300))
        info["frame_weights"] = {"min": float(omega.min()), "max": float(omega.max()),
                                 "effective_frames": n_eff, "frames": len(omega),
                                 "mode": frame_weights if isinstance(frame_weights, str) else "given"}
    if method == "dt":
        deltas = generic
    elif method == "ebfr":
        from .ebfr import ebfr_blendshapes
        if align:
            D = regularization_weights(generic, clamp=clamp)
            cand = cv_vertices(D, clamp)
            pf = PositionFit(capture.neutral[cand], points[:, cand], weights, generic[:, cand], D[:, cand])
            reg_a, _ = choose_regularization(None, None, None, None, None, fit=pf, vertices=cand)
            helps, test = _alignment_generalises(pf, points[:, cand], reg_a, info)
            info["align"] = {"applied": helps, "held_out_rmse_mm": test, "passes": 0,
                             "max_rotation_deg": 0.0, "max_translation_mm": 0.0}
            if helps:
                points = _align_frames(capture.neutral, points, weights, generic, info, timings,
                                       cv={"fit": pf, "vertices": cand}, reg=reg_a, D=D)
        t1 = time.perf_counter()
        deltas = ebfr_blendshapes(capture.neutral, capture.triangles, points, weights, tmpl.neutral,
                                  tmpl.deltas, generic, names=capture.names, eyelids=eyelids,
                                  info=info, **options)
        timings["ebfr"] = time.perf_counter() - t1
    else:
        alt = tmpl.deltas if prior == "auto" else None
        K = len(capture.names)
        main = {"template": tmpl.deltas, "avatar": None}.get(prior, generic)
        if prior == "avatar":
            main = np.where(avatar_ok[:, None, None], avatar, generic)
        # eq. (3)'s D_j from the prior T_j that eq. (2) pulls towards: with the avatar prior, the avatar's
        # shapes (a template by another artist that leaves part of a shape still would clamp the person's
        # motion there to the prior; with the prior's own D the fit does not depend on the template's shapes)
        D = regularization_weights(main if prior == "avatar" else generic, clamp=clamp)
        lam, alpha = _balance(reg, capture.neutral, points, weights, main, D, alt, prior, info, timings,
                              clamp=clamp)
        prior_deltas = alpha * generic + (1.0 - alpha) * tmpl.deltas if alpha < 1.0 else main
        choice = None
        per_shape = False                      # a prior other than alpha * DT + (1 - alpha) * template
        if avatar is not None and prior == "auto":
            lam, prior_deltas, choice, per_shape = _choose_priors(capture, generic, avatar, avatar_ok, lam,
                                                                  alpha, info, timings,
                                                                  ties_to_avatar=frame_weights is not None)
        if align:
            cv = info.get("crossval")
            if cv is None or "fit" not in cv:
                cand = cv_vertices(D, clamp)
                pf = PositionFit(capture.neutral[cand], _take1(points, cand), weights,
                                 _take1(prior_deltas, cand), D[:, cand])
                info["crossval"] = {"fit": pf, "vertices": cand}
            else:
                pf, cand = cv["fit"], cv["vertices"]
                pf.set_prior(_take1(prior_deltas, cand))
            helps, test = _alignment_generalises(pf, _take1(points, cand), lam, info)
            info["align"] = {"applied": helps, "held_out_rmse_mm": test, "passes": 0,
                             "max_rotation_deg": 0.0, "max_translation_mm": 0.0}
            for _ in range(ALIGN_PASSES if helps else 0):
                points = _align_frames(capture.neutral, points, weights, generic, info, timings,
                                       cv=info.get("crossval"), reg=lam, prior_deltas=prior_deltas, D=D,
                                       alt=tmpl.deltas, alpha=alpha, clamp=clamp)
                if auto:
                    cv = info["crossval"]
                    cv["fit"].set_points(_take1(points, cv["vertices"]))
                    # re-tune around the previous choice only (same prior, +-1 decade)
                    lam, a2 = _balance(reg, capture.neutral, points, weights, main, D, alt, prior, info,
                                       timings, fit=cv["fit"], vertices=cv["vertices"],
                                       grid=np.log10(lam) + np.array([-1.0, 0.0, 1.0]), alphas=(alpha,),
                                       keep_prior=per_shape)
                    if not per_shape:
                        alpha = a2
                    info["prior_alpha"] = alpha
        if choice is None:
            choice = (["avatar" if ok else "dt" for ok in avatar_ok] if prior == "avatar"
                      else [prior if prior in ("dt", "template") else _BLEND_NAME.get(alpha, "blend")] * K)
        info["prior_choice"] = choice
        info["prior_deltas"] = prior_deltas          # T_j of eq. (2) as used, [K,n,3] (the implant's P_j)
        info["shape_confidence"], reliable = _shape_confidence(capture, points, weights, generic, D,
                                                               prior_deltas, lam, info, clamp)
        # the data share itself (shape_confidence is capped by the reliability below): how far the ridge
        # shrinks each shape's personalization towards its prior (the implant's trust undoes it)
        info["data_share"] = np.array(info["shape_confidence"], dtype=np.float64)
        D_fit, prior_fit = D, prior_deltas
        if pins is not None:
            mask = _pin_mask(pins, capture, method)
            # a pinned entry's E_reg weight reg * D^2 becomes 1e14 (a hard constraint in double precision: the
            # other terms of its row are O(1)), towards the artist's (template) delta
            D_fit = np.where(mask, np.sqrt(1e14 / lam), D)
            prior_fit = np.where(mask[:, :, None], tmpl.deltas, prior_deltas)
            info["pins"] = {capture.names[k]: int(mask[k].sum()) for k in np.flatnonzero(mask.any(axis=1))}
        solve = _make_solver(method, capture, D_fit, prior_fit, options, clamp, (points, weights, lam), info)
        # the weights' leak (sensitivity) needs the gain A_v^-1 W^T of the final fit's systems: the final
        # full-mesh solve keeps it from its own factorization (FitSystem), so the re-estimation test (which
        # works on the prepared CV fit only) runs first: it says which solve is the final one
        leak = sensitivity and method == "menzel" and frame_weights is None and len(weights) > 0
        final_system = None
        sigma = None
        if reweight:
            t1 = time.perf_counter()
            # held at the phone's values (bounds lo = hi, :func:`.weights.held_weights`): every weight of a
            # shape the phone never activates (the geometry cannot tell it from the residual of the others,
            # and its prior must stay what the fit returns), and each shape's weight in its peak frame (there
            # the weight and the shape's amplitude are not separately identifiable)
            held = held_weights(weights, ACTIVATION_MIN)
            lo = np.where(held, weights, 0.0)
            hi = np.where(held, weights, 1.0)

            def first_weights(parts, sigmas):
                """The first re-estimation on each vertex set ``v`` of ``parts = [(v, phone-weight shapes
                there), ...]``, for every prior width in ``sigmas``: ``[H,S,F,K]``, one batched loop."""
                probs, anchors = [], []
                for v, deltas in parts:
                    res = points[:, v] - capture.neutral[v][None] - blend(weights, deltas)
                    anchors.append(float(np.mean(res ** 2)) / np.asarray(sigmas, dtype=np.float64) ** 2)
                    probs.append((capture.neutral[v], deltas, points[:, v]))
                return reestimate_weights_batched(probs, weights, np.array(anchors), lower=lo, upper=hi)

            sigmas = WEIGHT_SIGMAS if weight_sigma == "auto" else (float(weight_sigma),)
            sigma, loo = _reweight_helps(capture, points, weights, D, prior_deltas, lam, info, first_weights,
                                         sigmas, clamp)
            timings["reweight"] = time.perf_counter() - t1

        def fit(w, final):
            """The full-mesh fit with weights ``w``; the final one keeps its system for the leak."""
            nonlocal final_system
            if not (leak and final):
                return solve(points, w, lam)
            final_system = FitSystem(w, D_fit, lam, gain=True)
            return fit_blendshapes(capture.neutral, points, w, prior_fit, D_fit, lam, system=final_system)

        t1 = time.perf_counter()
        deltas = fit(weights, sigma is None)
        timings["fit"] = time.perf_counter() - t1
        w_cur = weights
        if reweight:
            t1 = time.perf_counter()

            def reestimate(neutral, P, deltas, sigma, n_rounds=rounds):
                """``n_rounds`` alternations of weight re-estimation (prior std ``sigma``) and the shape fit
                with the new weights; returns the weights and the shapes fitted with them."""
                w = weights
                for r in range(n_rounds):
                    res = P - neutral[None] - blend(w, deltas)
                    w = reestimate_weights(neutral, deltas, P, weights, anchor=float(np.mean(res ** 2))
                                           / sigma ** 2, lower=lo, upper=hi)
                    deltas = fit(w, r == n_rounds - 1)
                return w, deltas

            if sigma is not None:
                w_cur, deltas = reestimate(capture.neutral, points, deltas, sigma)
                info["train_weights"] = w_cur
            info["reweight"] = {"rounds": rounds, "weight_sigma": sigma, "applied": sigma is not None,
                                "held_out_rmse_mm": loo,
                                "mean_abs_change": float(np.abs(w_cur - weights).mean()),
                                "max_abs_change": float(np.abs(w_cur - weights).max())}
            timings["reweight"] += time.perf_counter() - t1
        from .contact import keep_contact

        t1 = time.perf_counter()
        res = points - capture.neutral[None] - blend(w_cur, deltas)          # the contact test's and E_fit's
        # picked frames (a take has its own noise model); menzel (a Laplacian solve costs seconds)
        variance = basis = None
        if sensitivity and method == "menzel" and frame_weights is None and len(w_cur):
            # the entries re-estimation holds (the phone's weights: the same as the test's above)
            held_cur = held if reweight and w_cur is weights else held_weights(w_cur, ACTIVATION_MIN)
            info["weight_sensitivity"] = weight_sensitivity(
                capture.neutral, points, w_cur, deltas, res, lambda w: solve(points, w, lam), held=held_cur)
            # the weights' noise as this capture shows it, and what it puts into each shape (the leak), from
            # the final fit's own systems (final_system: its gain kept)
            free = ~held_cur
            # the frames' weights re-estimated on the final shapes once, for the noise over every free entry
            # and over the phone's inside ones (weight_error_variance)
            # (one SVD of the fitted shapes: the test frames' amplitude reads the training frames as scanned
            # on the same shapes when the contact step leaves them, _test_frames_amplitude)
            basis = shape_basis(deltas)
            residuals = weight_residuals(capture.neutral, points, w_cur, deltas, basis=basis)
            info["weight_noise"] = weight_noise(capture.neutral, points, w_cur, deltas, free,
                                                residuals=residuals)
            # the phone's reports, each entry at its own side of the clip: a weight reported inside (0, 1)
            # errs by the phone's whole noise, one reported at a bound only by the little the clip leaves
            # (weight_error_variance).
            # Re-estimated weights are the geometry's, not the phone's (their error drifts with the shapes,
            # at a bound or not): one level for every entry, as before
            phone = w_cur is weights
            variance = (weight_error_variance(capture.neutral, points, w_cur, deltas, free,
                                              residuals=residuals) if phone
                        else info["weight_noise"] ** 2 * free)
            info["weight_leak"] = weight_leak_variance(w_cur, D_fit, lam, deltas, variance,
                                                       system=final_system)
            # ... and the one pattern it is largest along, over the vertices each shape's personalization
            # moves (as the implant's trust reads it: transfer.trust.weight_error_trust)
            change = squared_lengths(deltas - prior_deltas).T                               # [n,K]
            moving = change > 0.01 * np.maximum(change.max(axis=0), 1e-300)
            info["weight_leak_direction"], info["weight_leak_along"] = weight_leak_direction(
                w_cur, D_fit, lam, deltas, variance, moving, system=final_system)
            final_system = None                 # its [n,r,r] inverse: not needed past the leak
            timings["sensitivity"] = time.perf_counter() - t1
            t1 = time.perf_counter()
        elif sensitivity and method == "menzel" and frame_weights is not None and len(w_cur):
            # a take read whole: no re-estimation, so every weight the phone reports errs, at the noise the
            # take shows frame to frame (takefit.weight_noise); in the frame-weighted fit (points and weights
            # scaled by sqrt(omega), takefit.weighted_frames) frame f's error counts omega_f times
            from .takefit import weight_noise as take_weight_noise

            jitter = take_weight_noise(train.weights[::every] if every > 1 else train.weights)
            if np.isfinite(jitter):
                erring = np.broadcast_to(omega[:, None], w_cur.shape)
                # (no gain kept: the K x K systems' per-vertex form, not the [n,K,F] gain of a long take)
                info["weight_leak"] = jitter ** 2 * weight_leak_variance(w_cur, D_fit, lam, deltas, erring)
            # and no leave-one-frame-out reliability (a frame's neighbours predict it), but hundreds of
            # frames for ~50 shapes: their least-squares residual measures the scans' noise, and its
            # sandwich the error it leaves in each shape (a small shape performed once was its noise)
            offsets = points - capture.neutral[None]                 # the weighted frames' motion, once
            noise = take_frame_noise(offsets, w_cur, omega)
            if np.isfinite(noise):
                info["frame_noise_mm"] = float(np.sqrt(noise) * 1e3)
                energy = np.broadcast_to(3.0 * noise * omega[:, None], (len(omega), len(capture.neutral)))
                info["frame_variance"] = frame_error_variance(w_cur, D_fit, lam, energy)
                # of which independent from vertex to vertex (the scans' own): what smoothing can remove
                white = take_white_noise(offsets, w_cur, omega, capture.triangles)
                if np.isfinite(white):
                    info["frame_white_noise_mm"] = float(np.sqrt(min(white, noise)) * 1e3)
            del offsets
            timings["sensitivity"] = time.perf_counter() - t1
            t1 = time.perf_counter()
        deltas, info["contact"] = keep_contact(capture.neutral, capture.triangles, tmpl.neutral, tmpl.deltas,
                                               capture.names, deltas, mode=contact, points=points,
                                               weights=w_cur, pinned=mask if pins is not None else None,
                                               residuals=res, loops=loops, weight_variance=variance)
        timings["contact"] = time.perf_counter() - t1
        unmeasured = info["contact"].pop("unmeasured")
        if any(v["applied"] for v in info["contact"]["shapes"].values()):
            basis = None                          # the shapes corrected: not those decomposed above
            res = points - capture.neutral[None] - blend(w_cur, deltas)
            # the corrections' part the frames' evidence does not carry (the template's gap, not an
            # estimate): the trust reads the fit without it (transfer.trust.shape_trust)
            info["contact_correction"] = unmeasured
        info["train_rmse_mm"] = float(np.sqrt(np.mean(squared_lengths(res))) * 1000)
        if reliable is not None and frame_weights is None:
            # no more than the personalization stands above its estimate's noise (a take has its own model)
            info["shape_reliability"] = reliable(deltas)
            info["shape_confidence"] = np.minimum(info["shape_confidence"], info["shape_reliability"])
        if amplitude and method == "menzel" and frame_weights is None and n_test and len(w_cur):
            deltas = _test_frames_amplitude(capture, deltas, info, mask if pins is not None else None,
                                            basis=basis, train=train)
        if weak_prior and len(w_cur):
            # a shape no frame measures returns to its prior (a pinned vertex, at the template in both, stays)
            excitation = np.sum(np.asarray(info.get("train_weights", w_cur), dtype=np.float64) ** 2, axis=0)
            ramp, _ = weak_ramp(capture, excitation, list(range(K)))
            deltas = toward_prior(deltas, prior_fit, ramp)
            info["weak"] = {capture.names[k]: round(float(ramp[k]), 3) for k in np.flatnonzero(ramp < 1.0)}
    info["steps"] = fit_steps(info, method, align=align, reweight=reweight, amplitude=amplitude,
                              weak_prior=bool(weak_prior), take=frame_weights is not None,
                              test_frames=n_test)
    info.pop("crossval_fit", None)
    if "crossval" in info:
        info["crossval"] = {k: v for k, v in info["crossval"].items() if k not in ("fit", "vertices")}
        if not info["crossval"]:
            del info["crossval"]
    timings["total"] = time.perf_counter() - t0
    rig = FaceRig(capture.neutral, capture.triangles, list(capture.names), deltas, name="FaceMask")
    return FitResult(rig, info)


#: The optional steps of each method, in the order :func:`fit_personalized_shapes` runs them.
FIT_STEPS = {"dt": (), "ebfr": ("align",),
             "menzel": ("align", "reweight", "contact", "amplitude", "weak_prior"),
             "laplacian": ("align", "reweight", "contact", "weak_prior")}


def fit_steps(info: dict, method: str, *, align: bool, reweight: bool, amplitude: bool, weak_prior: bool,
              take: bool, test_frames: int) -> dict:
    """What each optional step of ``method`` (:data:`FIT_STEPS`) did in the fit whose ``info`` this is:
    ``{step: "applied" | "applied (...)" | "not applied (why)" | "off" | "off (why)"}``. ``align``,
    ``reweight``, ``amplitude``, ``weak_prior`` as the fit resolved them (on or off), ``take``: the frames
    were weighted (a whole take), ``test_frames``: the capture's count. A step switched on can still not
    apply: alignment and re-estimation are kept only where cross-validation shows them generalising, the
    amplitude reading needs test frames and a measurable weight noise. The options alone did not say it:
    ``fit --no-amplitude`` printed the default's summary."""
    def gated(key, on):
        if not on:
            return "off (whole take)" if take else "off"
        applied = (info.get(key) or {}).get("applied")
        return "applied" if applied else "not applied (no gain in cross-validation)"

    out = {}
    for step in FIT_STEPS.get(method, ()):
        if step in ("align", "reweight"):
            out[step] = gated(step, align if step == "align" else reweight)
        elif step == "amplitude":
            out[step] = ("off (whole take)" if take else "off" if not amplitude
                         else "not applied (no test frames)" if not test_frames
                         else "applied" if "test_amplitude" in info
                         else "not applied (no weight noise measurable in the training frames)")
        elif step == "contact":
            contact = info.get("contact") or {}
            shapes = contact.get("shapes") or {}
            fixed = sum(bool(r.get("applied")) for r in shapes.values())
            out[step] = ("off (gaps measured only)" if contact.get("mode") == "off"
                         else f"{contact.get('mode', 'auto')}: {fixed} of {len(shapes)} shape(s) corrected")
        elif step == "weak_prior":
            weak = info.get("weak") or {}
            out[step] = ("off" if not weak_prior else
                         f"applied ({len(weak)} shape(s) towards the prior)" if weak
                         else "applied (no shape too weak)")
    return out


def left_out_scale(result, frames) -> np.ndarray | None:
    """``[T,K]``: the scale each of ``frames`` (the capture's test frames the fit ``result`` read its shapes'
    amplitudes on) scores its shapes with, each frame's own reading left out (``info["test_scale_left_out"]``,
    eq. 5 cross-fitted: :func:`.evaluate.evaluate_rig`'s ``scale``); None when the fit read none on them."""
    info = getattr(result, "info", None)
    scale = info.get("test_scale_left_out") if isinstance(info, dict) else None
    if scale is None or np.shape(scale) != np.shape(frames.weights):
        return None
    return np.asarray(scale, dtype=np.float64)


def _test_frames_amplitude(capture, deltas, info, pinned=None, *, basis=None, train=None) -> np.ndarray:
    """The fitted ``deltas[K,n,3]`` each scaled by its amplitude as the fit's peak-frame weight and the
    capture's test frames read it together (:mod:`.amplitude`); ``info["test_amplitude"]`` the test frames'
    reading and the scale applied (``{"reading": [K], "scale": [K], "weight_noise": s}``, lists). The
    phone's weights' noise ``s`` is the training frames' (every report inside the clip); a shape an artist
    pinned keeps its scale (``pinned[K,n]``). ``basis``: :func:`.weights.shape_basis` of these ``deltas``
    when the fit has it (its sensitivity step decomposed them); ``train``: the capture's training frames if
    the caller has them (``capture.train`` copies them)."""
    train, test = (capture.train if train is None else train), capture.test
    every = np.ones(train.weights.shape, dtype=bool)
    residuals = weight_residuals(capture.neutral, train.points, train.weights, deltas, basis=basis)
    fit_var = weight_error_variance(capture.neutral, train.points, train.weights, deltas, every,
                                    residuals=residuals)
    noise = float(np.sqrt(fit_var.max()))
    if noise <= 0.0:
        return deltas
    test_var = weight_error_variance(capture.neutral, test.points, test.weights, deltas,
                                     np.ones(test.weights.shape, dtype=bool), noise=noise)
    # the test frames' terms (the shapes' Gram matrix, every frame's projection on them) formed once for the
    # reading and its leave-one-frame-out copies
    terms = amplitude_terms(capture.neutral, test.points, test.weights, deltas, test_var)
    reading, reading_var = held_out_amplitude(capture.neutral, test.points, test.weights, deltas, test_var,
                                              terms=terms)
    peak_var = peak_amplitude_variance(train.weights, fit_var)
    scale = combined_amplitude(reading, reading_var, peak_var)
    # each test frame's own reading left out: the scale eq. 5 scores that frame with (cross-fitted)
    left_out = combined_amplitude(*each_frame_left_out(capture.neutral, test.points, test.weights, deltas,
                                                       test_var, terms=terms), peak_var)
    if pinned is not None:
        held = np.asarray(pinned).any(axis=1)
        scale = np.where(held, 1.0, scale)
        left_out = np.where(held[None], 1.0, left_out)
    info["test_scale_left_out"] = left_out / np.where(scale != 0.0, scale, 1.0)
    # lists, as the rest of a fit's report (personalize --json prints it; an array would print as its repr)
    info["test_amplitude"] = {"reading": reading.tolist(), "scale": scale.tolist(), "weight_noise": noise}
    return deltas * scale[:, None, None]


def weight_sensitivity(neutral, points, weights, deltas, residuals, solve, *, held=None) -> np.ndarray:
    """``[K,n,3]`` (metres): how much each fitted shape changes when the training frames' weights are
    re-estimated from the geometry within the phone's uncertainty (:data:`WEIGHT_NOISE`, the prior width of
    :func:`.weights.reestimate_weights`; each shape's weight in its peak frame and shapes never activated
    held, :func:`.weights.held_weights`) and the shapes refitted with them (``solve(weights[F,K]) ->
    deltas``, the same points, prior and ``reg``). A perturbation estimate of the error the weights' noise
    puts into each shape: a phone that reports ``jawOpen`` 0.05 in a frame that shows no jaw makes the fit
    subtract 5 % of a 16 mm jaw from that frame's shape (a generated capture's ``mouthShrugLower``: 0.40 mm
    from the truth; 0.10 mm with that one weight at 0), and the geometry re-estimates it at 0.01.
    ``points[F,n,3]``, ``weights[F,K]``, ``deltas[K,n,3]`` the fit's, ``residuals[F,n,3]`` its training
    residuals (their mean square over ``WEIGHT_NOISE^2`` anchors the weights); ``held``: the weights'
    :func:`.weights.held_weights` at :data:`ACTIVATION_MIN` if the caller has them."""
    held = held_weights(weights, ACTIVATION_MIN) if held is None else held
    lo, hi = np.where(held, weights, 0.0), np.where(held, weights, 1.0)
    anchor = float(np.mean(np.asarray(residuals) ** 2)) / WEIGHT_NOISE ** 2
    alt = reestimate_weights(neutral, deltas, points, weights, anchor=anchor, lower=lo, upper=hi)
    return solve(alt) - deltas


_BLEND_NAME = {1.0: "dt", 0.0: "template"}


#: Method-specific options of :func:`fit_personalized_shapes` (``**options``).
METHOD_OPTIONS = {"ebfr": ("beta", "kappa", "theta", "translation_ridge"),
                  "laplacian": ("laplacian_weight", "mask_threshold", "tol", "max_iter"),
                  "menzel": (), "dt": ()}


#: The options of :func:`fit_personalized_shapes` each method uses besides its :data:`METHOD_OPTIONS` (what
#: a refusal lists as the method's options).
_POSITION_FIT_TAKES = ("reg", "prior", "align", "reweight", "clamp", "weight_sigma", "rounds", "contact",
                       "pins", "frame_weights", "every", "eyelids", "weak_prior")
METHOD_TAKES = {"menzel": (*_POSITION_FIT_TAKES, "amplitude"), "laplacian": _POSITION_FIT_TAKES,
                "ebfr": ("align", "eyelids"), "dt": ("eyelids",)}

#: The command line's spelling of each fit option (``fit``, ``evaluate``, ``personalize``), named beside the
#: option in a refusal: ``fit --method dt --no-align`` was told ``align=False``, a name it never typed.
FIT_FLAGS = {"reg": "--reg", "prior": "--prior", "align": "--no-align", "reweight": "--no-reweight",
             "amplitude": "--no-amplitude", "contact": "--contact", "eyelids": "--no-eyelids",
             "pins": "--pins", "every": "--every", "weak_prior": "--weak-prior"}


def _spelt(name: str, value=None, show_value: bool = True) -> str:
    """``name=value`` (or ``name``) with its command-line flag, as ``--no-align (align=False)``."""
    given = f"{name}={value!r}" if show_value else name
    return f"{FIT_FLAGS[name]} ({given})" if name in FIT_FLAGS else given


def check_take_poses(capture: Capture, every: int = 1) -> float:
    """The distinct poses a take read whole shows (:func:`usdface.personalize.takefit.distinct_poses`, every
    ``every``-th frame); refused (:class:`FitError`) below :data:`MIN_TAKE_POSES`: a take that holds one
    expression throughout cannot tell its shapes apart (a user trial: 600 frames of one pose personalized
    2.3x further from the person than the generic avatar, a shape 4.8 mm worse)."""
    from .takefit import distinct_poses

    weights = capture.train.weights[::every]
    poses = distinct_poses(weights)
    if poses < MIN_TAKE_POSES:
        fix = ("record a take that performs the expressions one after another (a range of motion), or give a "
               "capture of one frame per shape")
        thinned = ""
        if every > 1:
            thinned = f" (every {every} frames)"
            whole = distinct_poses(capture.train.weights)
            if whole >= MIN_TAKE_POSES:                     # the take is fine: --every thinned it to nothing
                fix = (f"use a smaller --every: the whole take shows {whole:.0f} distinct poses in "
                       f"{len(capture.train)} frames")
        raise FitError(f"the take shows {poses:.1f} distinct pose(s) in {len(weights)} frames{thinned} "
                       "(frames whose weights lie within 0.05 of each other are one pose): too few to tell "
                       "its shapes apart; the fit would give one pose's motion to every shape in it",
                       path=capture.source or None, fix=fix)
    return poses


def check_every(every, capture=None) -> None:
    """``every`` is a whole number >= 1, and above 1 only for a take read whole."""
    if isinstance(every, bool) or not isinstance(every, int | np.integer) or every < 1:
        raise FitError(f"every must be a whole number >= 1, got {every!r}",
                       fix="fit every N-th frame of a take: 1 (all), 2, 3, ...")
    if every > 1 and capture is not None and not capture.whole_take:
        raise FitError(f"every={every} thins a take read whole; this capture holds frames picked one per "
                       "shape",
                       path=capture.source or None,
                       fix="leave out --every, or pass the take itself (fit TAKE, personalize AVATAR TAKE)")


def check_fit_options(method: str = "menzel", reg="auto", *, prior: str | None = None, align=None,
                      reweight=None, clamp: float = D_CLAMP, weight_sigma="auto", contact: str = "auto",
                      avatar_prior: bool = False, path=None, eyelids: bool = True, rounds: int = 1,
                      frame_weights=None, pins=None, every: int = 1, amplitude=None, weak_prior=None,
                      **options) -> None:
    """Refuse, before any work, options :func:`fit_personalized_shapes` would refuse (same arguments;
    ``avatar_prior``: whether one will be given): an unknown method, options the method would accept and
    ignore, a bad ``contact`` or ``prior``, an avatar prior the chosen ``prior`` ignores. Raises
    :class:`FitError` naming the option and the fix. (``frame_weights`` and ``pins`` need the capture: the
    fit checks them.)"""
    del frame_weights, pins
    check_every(every)
    if method not in METHODS:
        raise FitError(f"unknown method {method!r}", path=path, fix=f"use one of {', '.join(METHODS)}")
    _check_fit_values(reg, align, reweight, clamp, weight_sigma, eyelids, rounds, options)
    if amplitude is not None and not isinstance(amplitude, bool | np.bool_):
        raise FitError(f"bad amplitude {amplitude!r}: not a boolean", fix="amplitude=true or false")
    _refuse_unused_options(method, reg, prior, align, reweight, clamp, weight_sigma, options)
    if amplitude is not None and method != "menzel":         # given at all, as reweight for dt/ebfr
        raise FitError(f"{_spelt('amplitude', amplitude)} is not used by method {method!r}", path=path,
                       fix="use menzel, or drop it")
    if weak_prior is not None and not isinstance(weak_prior, bool | np.bool_):
        raise FitError(f"bad weak_prior {weak_prior!r}: not a boolean", fix="weak_prior=true or false")
    if weak_prior and method not in ("menzel", "laplacian"):
        raise FitError(f"{_spelt('weak_prior', weak_prior)} is not used by method {method!r}", path=path,
                       fix="use menzel or laplacian, or drop it")
    if contact not in ("auto", "on", "off"):
        raise FitError(f"bad contact {contact!r}", fix="use 'auto', 'on' or 'off'")
    if contact != "auto" and method not in ("menzel", "laplacian"):
        raise FitError(f"{_spelt('contact', contact)} is not used by method {method!r}",
                       fix="use menzel or laplacian, or drop it")
    auto = isinstance(reg, str) and reg == "auto"
    prior = prior or ("auto" if auto else "dt")
    if prior == "auto" and not auto:
        # 'bad prior' for a valid prior named the wrong option: it is the reg that rules 'auto' out
        raise FitError(f"prior='auto' is chosen by the cross-validation, which reg={reg!r} turns off",
                       fix="drop --reg (reg='auto'), or choose the prior: 'dt' or 'template'")
    if prior not in ("auto", "dt", "template", "avatar"):
        raise FitError(f"bad prior {prior!r}",
                       fix="use 'dt', 'template', 'avatar' or 'auto' (with reg='auto')")
    if avatar_prior and method not in ("menzel", "laplacian"):
        raise FitError(f"avatar_prior is not used by method {method!r}",
                       fix="use it with menzel or laplacian, or drop it")
    if avatar_prior and prior in ("dt", "template"):
        raise FitError(f"avatar_prior given but prior={prior!r} ignores it",
                       fix="use prior='auto' (with reg='auto') or 'avatar'")
    if not avatar_prior and prior == "avatar":
        raise FitError("prior='avatar' needs avatar_prior", fix="pass avatar_prior=deltas[K,n,3]")


def check_number(name: str, value, *, low: float, inclusive: bool, fix: str, keywords=(),
                 error: type = FitError):
    """``value`` as a finite float ``> low`` (``>= low`` with ``inclusive``; a numeric string counts), or one
    of the ``keywords`` as given; else ``error`` naming the option, what it expects and ``fix``. The API's
    refusal of what the CLI's argument types refuse (:mod:`usdface.commands.options`), for the fit's options
    and personalize's (:func:`usdface.transfer.options.check_numbers`)."""
    if isinstance(value, str) and value in keywords:
        return value
    number = f"a finite number {'>=' if inclusive else '>'} {low:g}"
    expected = " or ".join([*(repr(k) for k in keywords), number])
    bad = error(f"bad {name} {value!r}: expected {expected}", fix=fix)
    if isinstance(value, bool):
        raise bad
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise bad from None
    if not np.isfinite(x) or x < low or (x == low and not inclusive):
        raise bad
    return x


def _check_fit_values(reg, align, reweight, clamp, weight_sigma, eyelids, rounds, options) -> None:
    """The option *values* :func:`fit_personalized_shapes` would choke on later, refused now (FitError): a
    ``reg`` that is not "auto", "paper" or a finite number > 0 (0 was let through here and refused after the
    deformation transfer); a ``clamp`` not > 0; ``weight_sigma`` not
    "auto" or > 0; ``rounds`` not a whole number >= 1; ``align``/``reweight``/``eyelids`` not booleans (a
    manifest's string "False" would count as true); ebfr's ``beta`` not "auto" or a number > 0."""
    check_number("reg", reg, low=0.0, inclusive=False, fix="use 'auto', 'paper' or a number > 0",
                 keywords=("auto", "paper"))
    check_number("clamp", clamp, low=0.0, inclusive=False, fix="a number > 0 (eq. 3's clamp, 1e5)")
    check_number("weight_sigma", weight_sigma, low=0.0, inclusive=False, fix="use 'auto' or a number > 0",
                 keywords=("auto",))
    if isinstance(rounds, bool) or not isinstance(rounds, int | np.integer) or rounds < 1:
        raise FitError(f"bad rounds {rounds!r}", fix="a whole number >= 1 (1)")
    for name, value in (("align", align), ("reweight", reweight), ("eyelids", eyelids)):
        if value is not None and not isinstance(value, bool | np.bool_):
            raise FitError(f"bad {name} {value!r}: not a boolean", fix=f"{name}=true or false")
    if "beta" in options:
        # beta 0 is the unregularised least squares: singular with fewer frames than shapes
        check_number("beta", options["beta"], low=0.0, inclusive=False,
                     fix="use 'auto' or a number > 0 (Li et al.: 0.5)", keywords=("auto",))


def _refuse_unused_options(method, reg, prior, align, reweight, clamp, weight_sigma, options):
    """Raise :class:`FitError` naming every option that ``method`` would accept and ignore."""
    bad = []
    if method in ("dt", "ebfr"):
        if not (isinstance(reg, str) and reg == "auto"):
            bad.append(_spelt("reg", reg))
        if prior is not None:
            bad.append(_spelt("prior", prior))
        if clamp != D_CLAMP:
            bad.append("clamp")
        # given at all (``--no-reweight``, ``--no-align`` too): evaluate refuses them for these methods
        if reweight is not None:
            bad.append(_spelt("reweight", reweight))
        if not (isinstance(weight_sigma, str) and weight_sigma == "auto"):
            bad.append("weight_sigma")
        if method == "dt" and align is not None:
            bad.append(_spelt("align", align))
    allowed = METHOD_OPTIONS[method]
    bad += sorted(set(options) - set(allowed))
    if bad:
        takes = [_spelt(n, show_value=False) for n in METHOD_TAKES[method] + allowed]
        raise FitError(f"option(s) not used by method {method!r}: {', '.join(bad)}",
                       fix=f"drop them; {method} takes {', '.join(takes)}")


def _pin_mask(pins, capture, method) -> np.ndarray:
    """``pins`` (dict name -> indices / bool[n], or bool[K,n]) as a bool ``[K,n]`` mask; FitError if bad."""
    K, n = len(capture.names), len(capture.neutral)
    if method not in ("menzel", "laplacian"):
        raise FitError(f"pins are not used by method {method!r}", fix="use menzel or laplacian")
    if isinstance(pins, dict):
        mask = np.zeros((K, n), bool)
        for name, v in pins.items():
            if name not in capture.names:
                raise FitError(f"pins name a shape the capture lacks: {name!r}", fix="use capture.names")
            v = np.asarray(v)
            if v.dtype == bool:
                if v.shape != (n,):
                    raise FitError(f"pin mask of {name} has {v.shape}, expected ({n},)", fix="one per vertex")
                mask[capture.names.index(name)] |= v
            else:
                v = v.astype(np.int64).ravel()
                if v.size and (v.min() < 0 or v.max() >= n):
                    raise FitError(f"pins of {name} index outside 0..{n - 1}", fix="capture vertex indices")
                mask[capture.names.index(name), v] = True
        return mask
    mask = np.asarray(pins, dtype=bool)
    if mask.shape != (K, n):
        raise FitError(f"pins mask has shape {mask.shape}, expected {(K, n)}", fix="bool [shapes, vertices]")
    return mask


def _check_avatar_prior(avatar_prior, capture, method, prior):
    """Validate ``avatar_prior[K,n,3]``: returns ``(deltas with NaN rows zeroed, available[K])`` or
    ``(None, None)``."""
    if avatar_prior is None:                   # the options were checked (:func:`check_fit_options`)
        return None, None
    a = np.asarray(avatar_prior, dtype=np.float64)
    K, n = len(capture.names), len(capture.neutral)
    if a.shape != (K, n, 3):
        raise FitError(f"avatar_prior has shape {a.shape}, expected {(K, n, 3)} (shapes, vertices, 3)",
                       fix="map the avatar's generic shapes onto the capture mesh, in capture.names order")
    fin = np.isfinite(a).reshape(K, -1)
    ok = fin.all(axis=1)
    partial = ~ok & fin.any(axis=1)
    if partial.any():
        bad = [capture.names[k] for k in np.flatnonzero(partial)]
        raise FitError(f"avatar_prior rows partly non-finite: {', '.join(bad[:5])}",
                       fix="a shape the avatar lacks must be a whole row of NaN")
    return np.where(ok[:, None, None], a, 0.0), ok


def _standard_error_of_mean(series, weights) -> float:
    """The standard error of the mean of a take's per-frame ``series[F]`` (time order): batch means over
    blocks of the weights' correlation time (``weights[F,K]``, :func:`usdface.personalize.takefit.
    correlation_frames`), since neighbouring frames' errors are correlated (lag-1 autocorrelation 0.89 on
    the sample's take: ``std / sqrt(F)`` was 2.3x too small, a review); the plain formula for fewer than
    4 blocks."""
    from .takefit import correlation_frames

    x = np.asarray(series, dtype=np.float64)
    F = len(x)
    if F < 2:
        return 0.0
    b = correlation_frames(weights)
    nb = F // max(b, 1)
    if b <= 1 or nb < 4:
        return float(x.std(ddof=1) / np.sqrt(F))
    means = x[:nb * b].reshape(nb, b).mean(axis=1)
    return float(means.std(ddof=1) / np.sqrt(nb))


def _choose_priors(capture, generic, avatar, avatar_ok, lam, alpha, info, timings, ties_to_avatar=False):
    """The avatar prior (today's blend where it lacks a shape) against the CV-chosen blend of DT and template,
    by the same leave-one-frame-out criterion, each at its own CV-tuned ``reg``, on the prepared fit (no new
    decomposition). Returns ``(reg, prior_deltas[K,n,3], choice names, avatar_won)``.

    ``ties_to_avatar`` (a frame-weighted fit: a whole take): the avatar prior whatever the scores (their
    paired per-frame difference and its standard error by batch means, :func:`_standard_error_of_mean`,
    are reported). There the frames decide every shape, the prior barely changes the fit and the two
    scores tie (0.01-0.02 % apart on generated artist-template takes), but the prior is also what the
    implant measures the person's change from: a coin flip for the template landed the template's mismatch
    with the avatar on it (face error 1.04x generic instead of 0.24x). Taking the other prior only past one
    standard error (the rule before stop 45) still flipped: 2 of 13 generated takes crossed it by chance
    (1.36 and 1.47 standard errors; the avatar's face error 1.95x and 1.20x generic, stop 45). On a capture
    of a few dozen frames the plain comparison stands: there a template that is the avatar's own rig wins by
    0.5-1 standard error and is the better fit (no correspondence error), measured on the sample and
    generated cases. ``usdface personalize`` no longer asks (stop 47): there the prior is also the implant's
    reference, and a template that wins because it holds part of the person hides that part from the avatar
    (:func:`usdface.transfer.options.fit_prior_options`)."""
    t1 = time.perf_counter()
    cv = info["crossval"]
    pf, cand = cv["fit"], cv["vertices"]
    tmpl = capture.template.deltas
    blend_prior = alpha * generic + (1.0 - alpha) * tmpl
    fallback = _BLEND_NAME.get(alpha, "blend")
    av = np.where(avatar_ok[:, None, None], avatar, blend_prior)
    pf.set_prior(av[:, cand])
    lam_av, cv_av = choose_regularization(None, None, None, None, None, fit=pf, vertices=cand,
                                          keep_prior=True)
    scores = {fallback: cv["loo_rmse_best_mm"], "avatar": cv_av["loo_rmse_best_mm"]}
    info["prior_search"] = {"loo_rmse_mm": scores, "reg": {fallback: lam, "avatar": lam_av}}
    K = len(capture.names)
    won = scores["avatar"] < scores[fallback]
    if ties_to_avatar and not won:
        # reported, not a reason to leave the avatar: on a take the frames decide every shape, the scores
        # tie and a margin of one standard error is crossed by chance (one take in six)
        e_av = pf.loo_frame_errors(lam_av)                      # the avatar prior is still set
        pf.set_prior_mix(alpha)
        diff = e_av - pf.loo_frame_errors(lam)
        se = _standard_error_of_mean(diff, pf.W)
        info["prior_search"].update(mean_difference_mm2=float(diff.mean()) * 1e6, standard_error_mm2=se * 1e6)
        pf.set_prior(av[:, cand])
        won = True
    if won:
        cv_av["alpha"] = alpha
        info["crossval"] = cv_av
        info["reg"] = lam = lam_av
        prior, choice = av, ["avatar" if ok else fallback for ok in avatar_ok]
    else:
        pf.set_prior_mix(alpha)
        prior, choice = (blend_prior if alpha < 1.0 else generic), [fallback] * K
    timings["prior"] = time.perf_counter() - t1
    return lam, prior, choice, won


def _shape_confidence(capture, points, weights, generic, D, prior_deltas, lam, info, clamp=D_CLAMP):
    """``([K], reliable)``: the data share of each shape (hat-matrix diagonal), |T|^2-weighted mean over
    the cross-validation's vertices; and ``reliable(deltas) -> [K]`` (None without a cross-validated
    noise), the James-Stein factor of the fitted shapes' personalization against their estimates' variance
    there (:func:`.fit.estimate_variance` times the leave-one-frame-out error's variance summed over a
    vertex's coordinates, :func:`.fit.james_stein`)."""
    cv = info.get("crossval")
    if cv is not None and "fit" in cv:
        cand = cv["vertices"]
        share = cv["fit"].data_share(lam)                                     # [m,K]
        spread = cv["fit"].estimate_variance
    else:                                # diag(A_v^-1 W^T W): one batched r x r solve, no eigh
        cand = cv_vertices(D, clamp)
        share = data_share(weights, D[:, cand], lam)
        spread = functools.partial(estimate_variance, weights, D[:, cand])
    w = squared_lengths(generic[:, cand]).T                                  # [m,K]
    w = np.where(w.sum(axis=0, keepdims=True) > 0, w, 1.0)
    share = np.clip(np.sum(w * share, axis=0) / np.sum(w, axis=0), 0.0, 1.0)
    loo = (cv or {}).get("loo_rmse_best_mm")
    if loo is None:
        return share, None
    # the leave-one-frame-out error is per vertex coordinate (PositionFit.loo_error), the personalization's
    # |B_j - T_j|^2 the sum of a vertex's coordinates: the estimate's variance per vertex is the sum too
    coords = np.shape(prior_deltas)[-1]
    variance = spread(lam) * coords * (float(loo) * 1e-3) ** 2                              # [m,K] m^2
    prior = np.asarray(prior_deltas)[:, cand]
    return share, lambda deltas: james_stein(np.asarray(deltas)[:, cand] - prior, variance, w)


#: A frame whose mask is turned more than this against the neutral's (degrees), or scaled by more than
#: this factor (either way), is in other axes or units than the neutral: no expression does that.
FRAME_TURN_MAX_DEG = 30.0
FRAME_SCALE_MAX = 1.5
#: The face mask's diagonal a capture in metres has, roughly (m): outside it, the units are suspect.
FACE_DIAGONAL_M = (0.03, 1.5)


def _check_frames_like_neutral(capture, src) -> None:
    """Refuse a frame in other units or axes than the neutral (one OBJ exported in millimetres or Z up among
    metre Y-up ones fitted as a 'train RMSE 9690 mm' rig): each frame's mask against the neutral's, by the
    best rotation (Kabsch, one batched 3x3 SVD) and the ratio of their RMS radii. Warn when the neutral
    itself is not face-sized in metres (a capture in millimetres read as metres)."""
    from ..errors import GeometryError

    n0 = np.asarray(capture.neutral, dtype=np.float64)
    c0 = n0 - n0.mean(axis=0)
    r0 = np.sqrt(np.mean(np.sum(c0 * c0, axis=1)))
    diagonal = float(np.linalg.norm(np.ptp(n0, axis=0)))
    if not FACE_DIAGONAL_M[0] <= diagonal <= FACE_DIAGONAL_M[1]:
        _warn(f"{src or 'capture'}: the neutral scan is {diagonal:.3g} m across (a face mask in "
              "metres is ~0.15-0.3 m): are its units right? (OBJ captures are read as metres; a USD "
              "capture's metersPerUnit says its unit)")
    frames = capture.frames
    P = np.asarray(frames.points, dtype=np.float64)
    if not len(P) or r0 <= 0:
        return
    # no centred [F,n,3] copy: c0 sums to zero, so P^T c0 is the centred frames' moments, and the RMS radius
    # is sqrt(mean |p|^2 - |mean p|^2) (a check against a 1.5x threshold: rounding is immaterial)
    flat = P.reshape(len(P), -1)
    mean = np.einsum("fnc->fc", P) / P.shape[1]               # [F,3]; P.mean(axis=1), 4x cheaper
    radius = np.sqrt(np.maximum(np.einsum("fi,fi->f", flat, flat) / P.shape[1]
                                - np.einsum("fc,fc->f", mean, mean), 0.0))          # [F]
    u, _, vt = np.linalg.svd(np.matmul(np.swapaxes(P, 1, 2), c0))                   # [F,3,3] Kabsch
    flip = np.ones((len(P), 3))
    flip[:, 2] = np.sign(np.linalg.det(u @ vt))                                     # a rotation, not a mirror
    rot = (u * flip[:, None, :]) @ vt
    angle = np.degrees(np.arccos(np.clip((np.trace(rot, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))
    scale = radius / r0
    bad = np.flatnonzero((angle > FRAME_TURN_MAX_DEG) | (scale > FRAME_SCALE_MAX)
                         | (scale < 1.0 / FRAME_SCALE_MAX))
    if bad.size:
        f = int(bad[0])
        raise GeometryError(f"frame {frames.label[f]!r} is turned {angle[f]:.0f} degrees and scaled "
                            f"x{scale[f]:.3g} against the neutral scan ({bad.size} such frame(s)): not in "
                            "the neutral's units or axes", path=src,
                            fix="export every frame as the neutral is (same units, same up axis)")


def _balance(reg, neutral, points, weights, generic, D, alt, prior, info, timings, fit=None, vertices=None,
             **search):
    """(reg, alpha): the E_reg weight and the prior blend (alpha * DT + (1 - alpha) * template)."""
    t1 = time.perf_counter()
    alpha = {"dt": 1.0, "template": 0.0}.get(prior, 1.0)
    if isinstance(reg, str) and reg == "auto":
        lam, cv = choose_regularization(neutral, points, weights, generic, D,
                                        alt_deltas=alt if prior == "auto" else None, fit=fit,
                                        vertices=vertices, **search)
        if prior == "auto":
            alpha = cv["alpha"]
        info["crossval"] = cv
    elif isinstance(reg, str) and reg == "paper":
        lam = 1.0
    else:
        try:
            lam = float(reg)
        except (TypeError, ValueError):
            raise FitError(f"bad reg {reg!r}", fix="use 'auto', 'paper' or a positive number") from None
        if not lam > 0:
            raise FitError(f"bad reg {reg!r}", fix="use 'auto', 'paper' or a positive number")
    timings["reg"] = timings.get("reg", 0.0) + time.perf_counter() - t1
    info["reg"] = lam
    info["prior_alpha"] = alpha
    return lam, alpha


def significantly_better(per_frame_new, per_frame_old, *, level: float = SIGNIFICANCE,
                         comparisons: int = 1) -> bool:
    """One-sided paired t-test over frames: is the held-out squared error ``per_frame_new[F]`` of a
    beyond-paper step (aligned frames, re-estimated weights) below the plain fit's ``per_frame_old[F]``
    at significance ``level`` (Bonferroni-corrected for ``comparisons`` candidates chosen on the same data)?
    Frames are the independent units (a frame's vertices share its noise and its misalignment). A gain within
    the noise is not evidence the step helps on this capture, so the step stays off (the plain fit).
    The critical value is Student's t quantile ``scipy.special.stdtrit`` (``scipy.stats`` took 1-2 s to
    import on a cold ``personalize``)."""
    from scipy.special import stdtrit

    d = np.asarray(per_frame_old, dtype=np.float64) - np.asarray(per_frame_new, dtype=np.float64)
    F = len(d)
    if F < 2 or not d.sum() > 0:
        return False
    sd = d.std(ddof=1)
    if sd == 0:
        return True
    return bool(d.mean() / (sd / np.sqrt(F)) > stdtrit(F - 1, 1.0 - level / comparisons))


def _prepared_fit(capture, points, weights, D, prior_deltas, info, clamp=D_CLAMP):
    """The CV's :class:`PositionFit` on its vertices with the current ``points`` and prior (one
    decomposition for every reg, prior and step), built once if the CV did not run. ``(fit, vertices)``."""
    cv = info.get("crossval")
    if cv is not None and "fit" in cv:
        pf, cand = cv["fit"], cv["vertices"]
        pf.set_points(_take1(points, cand))
        pf.set_prior(_take1(prior_deltas, cand))
        return pf, cand
    cand = cv_vertices(D, clamp)
    pf = PositionFit(capture.neutral[cand], _take1(points, cand), weights, _take1(prior_deltas, cand),
                     D[:, cand])
    info["crossval"] = {"fit": pf, "vertices": cand}
    return pf, cand


def _reweight_helps(capture, points, weights, D, prior_deltas, lam, info, first_weights, sigmas,
                    clamp=D_CLAMP):
    """Cross-validated decision on the weight re-estimation and its prior width, by spatially separated
    halves of the (subsampled) vertices (either side of the neutral's centroid along its principal axis,
    :data:`REWEIGHT_SPLIT_AXES`) - with the one decomposition of the prepared fit (:func:`_prepared_fit`).

    The position fit is separable per vertex, so weights re-estimated on one half (``first_weights([(vertex
    indices, phone-weight shapes there), ...], sigmas) -> [H,S,F,K]``) are independent of the other half's
    data. On the other half each training frame is predicted by the shapes fitted (phone's weights) on the
    *other* frames (exact leave-one-frame-out downdate), once with the re-estimated weights of that frame and
    once with the phone's: if the phone's weights are off, the independent estimate explains the held-out
    geometry better. Each prior width in ``sigmas`` is scored; the best is kept if its gain is significant
    (:func:`significantly_better`, Bonferroni over ``sigmas``) - on clean weights it is a no-op. Returns
    ``(best sigma or None, {"phone": mm, "sigma=...": mm} held-out RMSE)``."""
    pf, cand = _prepared_fit(capture, points, weights, D, prior_deltas, info, clamp)
    phone_loo, phone_fit = pf.loo_residuals(lam), pf.solve(lam)
    nb = capture.neutral[cand] - capture.neutral[cand].mean(axis=0)
    splits = []
    for ax in np.linalg.svd(nb, full_matrices=False)[2][:REWEIGHT_SPLIT_AXES]:
        side = np.flatnonzero(nb @ ax > 0)
        other = np.setdiff1d(np.arange(len(cand)), side)
        splits += [(side, other), (other, side)]
    F = len(weights)
    e = {"phone": np.zeros(F), **{sg: np.zeros(F) for sg in sigmas}}
    n_res = 0
    estimates = first_weights([(cand[ia], phone_fit[:, ia]) for ia, _ in splits], sigmas)   # [H,S,F,K]
    for (_, ib), ws in zip(splits, estimates, strict=True):
        e_b = phone_loo[:, ib]
        e["phone"] += np.sum(e_b ** 2, axis=(1, 2))
        held_out = pf.loo_residuals(lam, predict_weights=ws, vertices=ib, loo=e_b)       # [S,F,m,3]
        for sg, res in zip(sigmas, held_out, strict=True):
            e[sg] += np.sum(res ** 2, axis=(1, 2))
        n_res += e_b.size
    best = min(sigmas, key=lambda k: e[k].sum())
    scores = {(k if k == "phone" else f"sigma={k:g}"): float(np.sqrt(v.sum() / n_res) * 1000)
              for k, v in e.items()}
    if not significantly_better(e[best], e["phone"], comparisons=len(sigmas)):
        return None, scores
    return float(best), scores


def _alignment_generalises(pf, points, reg, info):
    """Cross-validated decision on the rigid alignment, by spatially separated halves of the (subsampled)
    vertices: a head misalignment is one rigid motion of the whole face, so a transform estimated on one half
    (each frame to its leave-one-out prediction, :func:`.align.rigid_align`) must also lower the other half's
    leave-one-out residual; a "motion" fitted to model error in one region (the lips' non-linear motion, say)
    does not carry over to the other. Halves: either side of the neutral's centroid along its two principal
    axes (top/bottom and left/right of a face), four estimates in all. (A paired t-test over frames, as the
    re-estimation uses, would refuse it on dev1/dev3, where the gain is concentrated in the few misaligned
    frames; six parameters per frame chosen by no search need no multiple-comparison guard.)
    ``points[F,m,3]`` on ``pf``'s vertices.
    Returns ``(helps, {"aligned", "original"} held-out RMSE in mm)``."""
    pf.set_points(points)
    residuals = pf.loo_residuals(reg)
    target = points - residuals
    groups = pf.frame_groups() or False                 # frames equal in points and weights: equal targets
    base = expression_weights(pf.W, pf.T, residuals)    # each frame on what its expression leaves still
    nb = pf.neutral - pf.neutral.mean(axis=0)
    axes = np.linalg.svd(nb, full_matrices=False)[2][:2]
    before, after = np.zeros(len(points)), np.zeros(len(points))
    unaligned = (points - target) ** 2                       # [F,m,3] squared residuals as the frames are
    count = 0
    halves = []
    for ax in axes:
        side = nb @ ax > 0
        for half in (side, ~side):
            est, out = np.flatnonzero(half), np.flatnonzero(~half)
            if len(est) >= 6 and len(out):
                halves.append((est, out))
    # the halves' robust fits side by side (one batched 3x3 SVD an iteration), each as it is alone
    fits = rigid_transforms_sets(points, target, [est for est, _ in halves], groups=groups, weights=base)
    for (_, out), (R, t) in zip(halves, fits, strict=True):
        p_out = np.take(points, out, axis=1)
        moved = np.matmul(p_out, np.swapaxes(R, 1, 2)) + t[:, None]
        before += np.sum(np.take(unaligned, out, axis=1), axis=(1, 2))
        after += np.sum((moved - np.take(target, out, axis=1)) ** 2, axis=(1, 2))
        count += p_out.size
    count = max(count, 1)
    return bool(after.sum() < before.sum()), {"aligned": float(np.sqrt(after.sum() / count) * 1000),
                                                 "original": float(np.sqrt(before.sum() / count) * 1000)}


def _align_frames(neutral, points, weights, generic, info, timings, *, cv=None, reg=None, alpha=1.0, D=None,
                  alt=None, prior_deltas=None, clamp=D_CLAMP):
    """Rigidly align every frame to its leave-one-out prediction on (a subsample of) the moving vertices."""
    t1 = time.perf_counter()
    if D is None:
        D = regularization_weights(generic, clamp=clamp)
    if cv is None or "fit" not in cv:
        if reg is None:
            reg, cv = choose_regularization(neutral, points, weights, generic, D, clamp=clamp)
        else:
            _, cv = choose_regularization(neutral, points, weights, generic, D, alt_deltas=alt, clamp=clamp,
                                          grid=np.array([np.log10(reg)]), refine=0)
            info["crossval"] = cv
    pf, cand = cv["fit"], cv["vertices"]
    on_cand = np.take(points, cand, axis=1)                       # points[:, cand], gathered once
    pf.set_points(on_cand)
    if prior_deltas is not None:
        pf.set_prior(_take1(prior_deltas, cand))
    else:
        pf.set_prior_mix(alpha)
    residuals = pf.loo_residuals(reg)
    target = on_cand - residuals
    R, tr = rigid_transforms(on_cand, target, np.arange(len(cand)), groups=pf.frame_groups() or False,
                             weights=expression_weights(pf.W, pf.T, residuals))
    aligned = np.matmul(points, np.swapaxes(R, 1, 2)) + tr[:, None]
    ang = np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    prev = info.setdefault("align", {"max_rotation_deg": 0.0, "max_translation_mm": 0.0, "passes": 0})
    prev.update({"vertices": int(len(cand)), "passes": prev["passes"] + 1,
                     "max_rotation_deg": prev["max_rotation_deg"] + float(ang.max()),
                 "max_translation_mm": prev["max_translation_mm"] + float(np.linalg.norm(tr, axis=1).max()
                                                                         * 1000)})
    timings["align"] = timings.get("align", 0.0) + time.perf_counter() - t1
    return aligned


def _make_solver(method, capture, D, generic, options, clamp=D_CLAMP, cv_data=None, info=None):
    """A function ``(points, weights, reg) -> deltas`` for the position-based methods. Laplacian with
    ``laplacian_weight="auto"`` (default): the weight is chosen on ``cv_data = (points, weights, reg)`` by
    :meth:`LaplacianFit.choose_weight`."""
    if method == "laplacian":
        from .laplacian import LAPLACIAN_GRID, LaplacianFit
        opts = dict(options)
        mu = opts.pop("laplacian_weight", "auto")
        lf = LaplacianFit(capture.neutral, capture.triangles, generic, D, clamp=clamp,
                          laplacian_weight=0.0 if isinstance(mu, str) else float(mu), **opts)
        if isinstance(mu, str):
            if mu != "auto":
                raise FitError(f"bad laplacian_weight {mu!r}", fix="use 'auto' or a number >= 0")
            from ..progress import steps

            # nearly all of the method's time (~26 CPU-s on dev3): a step per weight, not one silent step
            with steps("laplacian weight", len(LAPLACIAN_GRID)) as p:
                cv = lf.choose_weight(*cv_data, progress=p.start)
            if info is not None:
                info["laplacian_cv"] = cv
        if info is not None:
            info["laplacian_weight"] = lf.mu
        return lambda P, W, lam: lf.solve(P, W, lam)
    return lambda P, W, lam: fit_blendshapes(capture.neutral, P, W, generic, D, lam)


# keep PositionFit importable from here for callers that want the prepared solver
_ = PositionFit
