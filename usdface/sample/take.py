"""A synthetic continuous take with known answers: every shape swept up and down in turn, with realistic
cross-talk and noise (for ``usdface capture select`` tests, benchmarks and demos).

The person's *true* rig deforms the mesh; the "phone" reports the true weights plus noise. Shape i's sweep is
a smooth bump ``peak_i * sin^2(pi u)`` over ``sweep_seconds`` (an odd number of frames, apex in the middle),
separated by ``rest_seconds`` of neutral; while shape i sweeps, the other shapes follow it by a fixed
cross-talk fraction (the mirror partner 0.2-0.45, a few random others 0.02-0.15), as ARKit solvers do. Peaks
are drawn in [0.75, 0.95] so that no reported weight saturates at 1 (a plateau would make "the peak frame"
ambiguous) and no cross-talk (<= 0.45 x 0.95) reaches the 0.5 threshold.

The truth (:class:`TakeTruth`) gives, per swept shape, its window, the noise-free apex frame, and the frame
where its *reported* weight is highest in its window: the frame Menzel et al.'s app keeps (section 3.1).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..arkit import mirror_name
from ..io.take import Take
from ..model import FaceRig

__all__ = ["TakeTruth", "make_take", "cross_talk_matrix"]


@dataclass
class TakeTruth:
    """Known answers of a generated take: ``swept`` shapes in recording order, their frame
    ``windows[s, 2]`` (start, stop), ``apex`` (noise-free) and ``peak_frames`` (highest reported weight in the
    window) by name, ``skipped`` shapes (never swept), ``true_weights[F, K]`` (noise-free) and the
    ``cross_talk[K, K]`` used."""

    swept: list[str]
    windows: np.ndarray
    apex: dict[str, int]
    peak_frames: dict[str, int]
    skipped: list[str] = field(default_factory=list)
    true_weights: np.ndarray | None = None
    cross_talk: np.ndarray | None = None


def cross_talk_matrix(names, rng, mirror=(0.2, 0.45), others=(0.02, 0.15), n_others: int = 3) -> np.ndarray:
    """``C[K, K]``: row i = how much every other shape moves while shape i is performed (zero diagonal)."""
    k = len(names)
    c = np.zeros((k, k))
    index = {n: i for i, n in enumerate(names)}
    for i, name in enumerate(names):
        pool = [j for j in range(k) if j != i]
        if pool:
            chosen = rng.choice(pool, size=min(n_others, len(pool)), replace=False)
            c[i, chosen] = rng.uniform(*others, size=len(chosen))
        partner = index.get(mirror_name(name))
        if partner is not None and partner != i:
            c[i, partner] = rng.uniform(*mirror)
    return c


def make_take(rig: FaceRig, template: FaceRig | None = None, *, shapes=None, skip=(), fps: float = 30.0,
              sweep_seconds: float = 1.0, rest_seconds: float = 0.4, cross_talk_scale: float = 1.0,
              weight_noise: float = 0.005, point_noise: float = 5e-5, include_neutral: bool = True,
              seed: int = 0) -> tuple[Take, TakeTruth]:
    """Generate a continuous take from the person's true ``rig`` (neutral[n,3] m, deltas[K,n,3] m).

    Parameters
    ----------
    rig : the person's true blendshapes; the take's meshes are ``rig.evaluate(true_weights) + noise``.
    template : generic rig on the same topology, stored in the take (needed to turn it into a capture).
    shapes : names to sweep, in order (default ``rig.names``); ``skip`` names are left out (never triggered).
    fps, sweep_seconds, rest_seconds : timing; a sweep has an odd number of frames.
    cross_talk_scale : multiplies the cross-talk matrix (0 = perfectly isolated shapes).
    weight_noise : std of the reported weights' Gaussian noise (clipped to [0, 1]).
    point_noise : std (metres) of the per-vertex Gaussian scan noise.
    include_neutral : store ``rig.neutral`` as the take's neutral scan.
    seed : everything is deterministic given the seed.

    Returns ``(take, truth)``.
    """
    rng = np.random.default_rng(seed)
    names = list(rig.names)
    order = [n for n in (shapes if shapes is not None else names) if n not in set(skip)]
    n_sweep = int(round(sweep_seconds * fps)) | 1  # odd: the apex is a sample
    n_rest = max(1, int(round(rest_seconds * fps)))
    c = cross_talk_scale * cross_talk_matrix(names, rng)
    peaks = rng.uniform(0.75, 0.95, size=len(names))
    u = (np.arange(n_sweep) + 0.5) / n_sweep
    bump = np.sin(np.pi * u) ** 2
    n_frames = n_rest + len(order) * (n_sweep + n_rest)
    true_w = np.zeros((n_frames, len(names)))
    windows = np.zeros((len(order), 2), dtype=np.int64)
    for s, name in enumerate(order):
        i = names.index(name)
        start = n_rest + s * (n_sweep + n_rest)
        row = c[i].copy()
        row[i] = 1.0
        true_w[start:start + n_sweep] = np.outer(bump * peaks[i], row)
        windows[s] = (start, start + n_sweep)
    true_w = np.clip(true_w, 0.0, 1.0)
    reported = np.clip(true_w + rng.normal(0.0, weight_noise, size=true_w.shape), 0.0, 1.0)
    points = rig.evaluate(true_w) + rng.normal(0.0, point_noise, size=(n_frames,) + rig.neutral.shape)
    apex, peak_frames = {}, {}
    for s, name in enumerate(order):
        i = names.index(name)
        a, b = windows[s]
        apex[name] = int(a + n_sweep // 2)
        peak_frames[name] = int(a + np.argmax(reported[a:b, i]))
    times = np.arange(n_frames) / float(fps)
    neutral = rig.neutral.copy() if include_neutral else None
    take = Take(reported, names, times, points, rig.triangles, neutral, template,
                source=f"usdface.sample.take(seed={seed})",
                metadata={"generator": "usdface.sample.take", "seed": seed})
    truth = TakeTruth(order, windows, apex, peak_frames, [n for n in names if n not in set(order)], true_w, c)
    return take, truth
