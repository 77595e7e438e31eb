"""Training-frame selection from a continuous take (Menzel et al. 2022, section 3.1). Pure numpy/scipy.

The capture app of Menzel et al. records continuously and keeps, for each requested shape i, "the frame where
its weight w_ii exceeds a threshold and reaches its maximum over time (starts decreasing)", together with the
whole weight vector and the mesh of that frame. :func:`select_frames` applies the same rule offline to
``weights[F, K]`` of a recorded take:

* a *peak* of shape i is a local maximum over time of ``w[:, i]`` (:func:`scipy.signal.find_peaks`: a sample
  higher than its left neighbour after which the weight decreases; plateaus count once, at their middle)
  whose height exceeds ``threshold``;
* peaks of one shape closer than ``min_separation`` frames are one peak (the higher one wins);
* the ``per_shape`` highest peaks are kept (Hable et al. used about two scans per shape);
* ``dominance`` = ``w_ii - max_{j != i} w_ij`` at the chosen frame says how cleanly the shape was isolated
  (bilateral pairs such as eyeBlinkLeft/Right are naturally low);
* shapes with no peak above the threshold are reported as never triggered, with their maximum weight (a pose
  held from the first frame that then relaxes is a peak; one still rising or held at the last frame is not);
* with ``test_every = K > 0``, every K-th take frame that shows an expression (a weight of at least
  :data:`REST_WEIGHT`) and is at least ``min_separation`` frames away from any training frame is held out as
  a test frame (Menzel et al.'s eq. 5 evaluation set): a rest held out is predicted as the neutral by every
  fitting method, so it cannot tell them apart (before stop 52 rests were held out too, and a take of
  expressions between long rests gave rests only).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.signal import find_peaks

from .errors import CaptureError, warn

#: A frame whose weights all stay below this shows no expression (a rest): never held out as a test frame.
REST_WEIGHT = 0.15
#: How to hold out frames with expressions instead (``capture select`` and ``evaluate`` say the same).
REST_FIX = ("hold out frames nearer the expressions: 'usdface capture select TAKE -o capture.usda "
            "--test-every 5 --min-separation 0.2'")

__all__ = ["ShapePick", "Selection", "select_frames", "format_coverage"]


@dataclass
class ShapePick:
    """Selection outcome for one shape: chosen ``frames`` (best first), their ``peak`` weights and
    ``dominance``, the strongest competing shape at each frame (``rival``), and the shape's maximum weight
    over the take (``max_weight``, to say by how much a never-triggered shape missed)."""

    name: str
    frames: list[int] = field(default_factory=list)
    peak: list[float] = field(default_factory=list)
    dominance: list[float] = field(default_factory=list)
    rival: list[str] = field(default_factory=list)
    max_weight: float = 0.0

    @property
    def triggered(self) -> bool:
        return bool(self.frames)


@dataclass
class Selection:
    """Result of :func:`select_frames`.

    ``train[m]`` take frame indices (unique, in shape order) with ``train_shape[m]`` the shape each was picked
    for (the first one if several shapes peak at the same frame) and ``labels[m]`` (``NNN_<shape>``);
    ``test[t]`` held-out frame indices; ``shapes`` one :class:`ShapePick` per shape; ``missing`` the names
    never triggered.
    """

    names: list[str]
    shapes: list[ShapePick]
    train: np.ndarray
    train_shape: list[str]
    test: np.ndarray
    threshold: float
    per_shape: int

    @property
    def missing(self) -> list[str]:
        return [s.name for s in self.shapes if not s.triggered]

    @property
    def labels(self) -> list[str]:
        return [f"{m:03d}_{name}" for m, name in enumerate(self.train_shape)]

    @property
    def test_labels(self) -> list[str]:
        return [f"{t:03d}" for t in range(len(self.test))]


def _number(value) -> bool:
    """``value`` a real number: an int or a float, Python's or numpy's, not a bool."""
    return not isinstance(value, bool) and isinstance(value, int | float | np.integer | np.floating)


def _whole(value, low: int) -> bool:
    """``value`` a whole number (an int, numpy's, or a float such as 15.0) >= ``low``."""
    return _number(value) and bool(np.isfinite(value)) and float(value).is_integer() and value >= low


def _check_counts(threshold, per_shape, test_every, min_separation) -> tuple[int, int, int]:
    """:func:`select_frames`' numbers, each refused naming it (they were refused together as "per_shape and
    min_separation must be >= 1, test_every >= 0" with a command line's fix, whichever was wrong; a
    ``min_separation=0.5`` meant as the CLI's seconds was one of them, and ``threshold=2`` picked nothing
    without a word: a user trial of docs/takes.md's script). Returns them as ints (15.0 is 15)."""
    if not (_number(threshold) and 0.0 <= threshold <= 1.0):
        raise CaptureError(f"threshold {threshold!r} is outside [0, 1]", fix="pass a weight in [0, 1] (0.5)")
    for name, value, low, fix in (
            ("per_shape", per_shape, 1, "pass per_shape=1 (one peak per shape; 2: Hable's two)"),
            ("test_every", test_every, 0, "pass test_every=40 (0: no test frames)"),
            ("min_separation", min_separation, 1,
             "pass frames here: min_separation=max(1, round(seconds * take.fps)) (the command line's "
             "--min-separation and select_capture_frames take seconds)")):
        if not _whole(value, low):
            raise CaptureError(f"bad {name} {value!r}: select_frames' {name} is a whole number >= {low}"
                               + (" of frames" if name == "min_separation" else ""), fix=fix)
    return int(per_shape), int(test_every), int(min_separation)


def select_frames(weights, threshold: float = 0.5, per_shape: int = 1, test_every: int = 0, *, names=None,
                  min_separation: int = 15) -> Selection:
    """Pick training frames from a continuous take by Menzel et al.'s rule (section 3.1).

    Parameters
    ----------
    weights : ``[F, K]`` per-frame weights in [0, 1] (columns follow ``names``).
    threshold : a peak counts only if ``w_ii > threshold``.
    per_shape : number of distinct peaks kept per shape (highest first).
    test_every : hold out every K-th take frame that shows an expression (a weight >= :data:`REST_WEIGHT`)
        away from training frames as a test frame (0: none).
    names : ``[K]`` shape names (default ``shape0 ..``).
    min_separation : frames between two peaks of one shape, and between test and training frames.

    Returns a :class:`Selection`. Raises CaptureError on malformed input.

    Examples
    --------
    >>> w = np.zeros((9, 2))
    >>> w[:, 0] = [0, .3, .8, .6, 0, 0, 0, 0, 0]
    >>> w[:, 1] = [0, 0, 0, 0, 0, .4, .9, .9, 0]
    >>> sel = select_frames(w, names=["jawOpen", "eyeBlinkLeft"], min_separation=2)
    >>> sel.train.tolist(), sel.missing
    ([2, 6], [])
    """
    w = np.asarray(weights, dtype=np.float64)
    if w.ndim != 2:
        raise CaptureError(f"weights must be [frames, shapes], got shape {w.shape}",
                           fix="pass one row of shape weights per take frame")
    n_frames, n_shapes = w.shape
    names = [f"shape{k}" for k in range(n_shapes)] if names is None else [str(n) for n in names]
    if len(names) != n_shapes:
        raise CaptureError(f"{len(names)} names for {n_shapes} weight columns",
                           fix="pass one name per column")
    if not np.isfinite(w).all():
        raise CaptureError("weights contain NaN or infinite values", fix="repair the take's weights")
    per_shape, test_every, min_separation = _check_counts(threshold, per_shape, test_every, min_separation)
    picks, train, train_shape = [], [], []
    # Rival weight at every frame and shape: the largest *other* weight (top-2 trick, no K x K loop).
    if n_shapes > 1:
        order = np.argsort(w, axis=1)
        top, second = order[:, -1], order[:, -2]
        rows = np.arange(n_frames)
    for k, name in enumerate(names):
        col = w[:, k]
        # a pose held from the take's first frame that then relaxes has peaked (the paper's rule: it reached
        # its maximum and starts decreasing); find_peaks never returns an end sample, so the column is
        # started below everything. A weight still rising or held at the take's end has not peaked.
        peaks, props = find_peaks(np.concatenate([[-np.inf], col]), height=threshold + 1e-12,
                                  distance=min_separation)
        peaks = peaks - 1
        best = peaks[np.argsort(-props["peak_heights"], kind="stable")][:per_shape] if len(peaks) else peaks
        pick = ShapePick(name, max_weight=float(col.max()) if n_frames else 0.0)
        for f in best.tolist():
            if n_shapes > 1:
                other = second[f] if top[f] == k else top[f]
                pick.rival.append(names[other])
                pick.dominance.append(float(col[f] - w[rows[f], other]))
            else:
                pick.rival.append("")
                pick.dominance.append(float(col[f]))
            pick.frames.append(int(f))
            pick.peak.append(float(col[f]))
            if f not in train:
                train.append(int(f))
                train_shape.append(name)
        picks.append(pick)
    train_arr = np.array(train, dtype=np.int64)
    test = np.zeros(0, dtype=np.int64)
    if test_every and n_frames:
        far = np.ones(n_frames, dtype=bool)
        if len(train_arr):
            dist = np.abs(np.arange(n_frames)[:, None] - train_arr[None, :]).min(axis=1)
            far = dist >= min_separation
        expression = w.max(axis=1) >= REST_WEIGHT if n_shapes else np.zeros(n_frames, dtype=bool)
        candidates = np.flatnonzero(far & expression)
        test = candidates[test_every // 2::test_every]
        if far.any() and not len(candidates):
            warn(f"the {int(far.sum())} frames away from the training frames show no expression (largest "
                 f"weight {w[far].max(initial=0.0):.2f}): none is held out as a test frame (every fitting "
                 "method predicts a rest as the neutral), and 'usdface evaluate' refuses a capture without "
                 f"test frames (fix: {REST_FIX})")
    return Selection(names, picks, train_arr, train_shape, test, float(threshold), int(per_shape))


def format_coverage(selection: Selection, times=None) -> str:
    """A plain-text coverage table: shape, chosen frame (and time), peak weight, dominance over the strongest
    other shape; then the never-triggered shapes by name with the maximum weight they reached."""
    times = None if times is None else np.asarray(times, dtype=np.float64)
    head = f"{'shape':<22}{'frame':>7}{'time s':>9}{'peak':>7}{'dominance':>11}  strongest other"
    lines = [head, "-" * len(head)]
    for s in selection.shapes:
        if not s.triggered:
            why = (f"above {selection.threshold:g} only at the take's end, still rising or held "
                   f"(max {s.max_weight:.2f})" if s.max_weight > selection.threshold
                   else f"never above {selection.threshold:g} (max {s.max_weight:.2f})")
            lines.append(f"{s.name:<22}{'-':>7}{'-':>9}{'-':>7}{'-':>11}  {why}")
            continue
        for i, f in enumerate(s.frames):
            t = f"{times[f]:.2f}" if times is not None else "-"
            label = s.name if i == 0 else ""
            lines.append(f"{label:<22}{f:>7}{t:>9}{s.peak[i]:>7.2f}{s.dominance[i]:>+11.2f}  {s.rival[i]}")
    n_hit = sum(s.triggered for s in selection.shapes)
    lines.append("")
    lines.append(f"{n_hit}/{len(selection.shapes)} shapes triggered; {len(selection.train)} training frames, "
                 f"{len(selection.test)} test frames")
    if selection.missing:
        lines.append(f"never triggered (record again): {', '.join(selection.missing)}")
    return "\n".join(lines)
