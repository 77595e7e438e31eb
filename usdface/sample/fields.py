"""The 52 ARKit expressions as smooth deformation fields in 3-D, generic and personalised.

A field maps reference points ``X[n,3]`` (cm, head frame of :mod:`usdface.sample.head`) to displacements
``D[n,3]`` (cm) at weight 1. Fields are anatomically placed sums of *terms*:

* ``gauss``: ``a * exp(-|(X - c) / s|^2 / 2) * mask(X)``, ``a`` a displacement vector, ``c`` a centre on the
  face, ``s`` per-axis widths; ``mask`` is 1, the upper or lower lip (a steep sigmoid across the mouth line:
  the lips are separated by the mouth slit), or the jaw region;
* ``lid``: eyelid motion: above the eye line the upper lid moves by ``up * 2 * b * sqrt(1 - t^2)`` (``b`` the
  opening's half-height, ``t`` the normalised distance from the eye's centre line), fading away from the lid
  margin; below, the lower lid by ``low * ...``; a blink (``up_y + low_y = -1``) closes the opening exactly;
* ``jaw``: the jaw region rotates by ``angle`` about a hinge axis (x) through ``hinge`` (jawOpen), or
  translates by ``a`` (jawLeft/Right/Forward).

Only the left-side and centre shapes are defined; ``<shape>Right`` is the mirror image of ``<shape>Left``
(``D_R(X) = M D_L(M X)``, ``M = diag(-1, 1, 1)``), and centre shapes are built symmetric, so every rig is
exactly left/right symmetric. :func:`personalize_fields` draws a person's TRUE fields from the generic ones:
per term an amplitude factor, a direction tilt, a centre shift and a width factor, plus one extra small term
per shape that the generic rig does not have (differences of a few millimetres, as between real people).
"""

from __future__ import annotations

import copy

import numpy as np

from ..arkit import ARKIT_NAMES
from .head import EYE_CENTER, EYE_RADII, MIRROR, MOUTH_HALF_WIDTH, Y_MOUTH, front_point

#: Displacements smaller than this (cm) are set to exactly zero, so shapes have compact support (sparse).
SUPPORT_CUTOFF = 1e-3
#: Shapes that also move the teeth/tongue block (the Mouth mesh); every other shape moves the Head only.
MOUTH_MESH_SHAPES = ("jawForward", "jawLeft", "jawRight", "jawOpen", "tongueOut")

_LIP_W = 0.02    # cm: width of the lip-side sigmoid (the slit is 1.6 mm wide at the centre)


def _p(x, y, dz=0.0):
    """A landmark on the reference surface in front of (x, y), optionally pushed along z."""
    return front_point(x, y)[0] + np.array([0.0, 0.0, dz])


def _g(a, c, s, mask=None, pair=False, region="head"):
    return {"kind": "gauss", "a": np.asarray(a, float), "c": np.asarray(c, float), "s": np.asarray(s, float),
            "mask": mask, "pair": pair, "region": region}


def _lid(up, low, sigma_up=0.7, sigma_low=0.5):
    return {"kind": "lid", "up": np.asarray(up, float), "low": np.asarray(low, float),
            "sigma_up": sigma_up, "sigma_low": sigma_low, "closes": False}


def _jaw(angle=0.0, a=(0, 0, 0)):
    return {"kind": "jaw", "angle": float(angle), "a": np.asarray(a, float),
            "hinge": np.array([0.0, Y_MOUTH + 1.3, -0.5]), "w": 0.4}


def generic_fields() -> dict[str, list[dict]]:
    """The generic (template) rig: left/centre shape name -> list of terms."""
    yc, xc = Y_MOUTH, MOUTH_HALF_WIDTH
    corner = _p(xc, yc)
    ex, ey = EYE_CENTER
    blink = _lid((0, -0.97, 0.0), (0, 0.03, 0))
    blink["closes"] = True
    f = {
        "eyeBlinkLeft": [blink],
        "eyeLookDownLeft": [_lid((0, -0.3, 0.03), (0, -0.12, 0))],
        "eyeLookInLeft": [_lid((-0.12, 0, 0), (-0.12, 0, 0))],
        "eyeLookOutLeft": [_lid((0.12, 0, 0), (0.12, 0, 0))],
        "eyeLookUpLeft": [_lid((0, 0.2, 0), (0, 0.08, 0))],
        "eyeSquintLeft": [_lid((0, -0.12, 0), (0, 0.3, 0.03)), _g((0.02, 0.12, 0.02), _p(ex + 0.3, ey - 1.3),
                                                                   (1.2, 0.7, 1.5))],
        "eyeWideLeft": [_lid((0, 0.35, 0.02), (0, -0.05, 0))],
        "jawForward": [_jaw(a=(0, 0, 0.6))],
        "jawLeft": [_jaw(a=(0.7, 0, 0))],
        "jawOpen": [_jaw(angle=0.3)],
        "mouthClose": [_g((0, 1.4, 0.5), _p(0, yc - 0.4), (2.2, 1.0, 1.5), "lower"),
                       _g((0, -0.9, 0.1), _p(0, yc + 0.4), (2.0, 0.8, 1.5), "upper")],
        "mouthFunnel": [_g((0, 0.2, 0.45), _p(0, yc + 0.3), (1.6, 0.6, 1.5), "upper"),
                        _g((0, -0.25, 0.45), _p(0, yc - 0.3), (1.6, 0.6, 1.5), "lower")],
        "mouthPucker": [_g((0, 0, 0.6), _p(0, yc), (1.8, 0.9, 1.5)),
                        _g((-0.5, 0, 0.1), corner, (0.8, 0.8, 1.2), pair=True)],
        "mouthLeft": [_g((0.6, 0, -0.05), _p(0, yc), (2.6, 1.2, 2.0))],
        "mouthSmileLeft": [_g((0.35, 0.55, -0.3), corner, (1.1, 1.0, 1.5))],
        "mouthFrownLeft": [_g((0.05, -0.45, 0.0), corner, (1.0, 0.9, 1.5))],
        "mouthDimpleLeft": [_g((0.15, 0.05, -0.35), corner, (0.8, 0.8, 1.2))],
        "mouthStretchLeft": [_g((0.5, -0.2, -0.15), corner, (1.2, 1.0, 1.5))],
        "mouthRollLower": [_g((0, 0.2, -0.35), _p(0, yc - 0.35), (1.8, 0.4, 1.0), "lower")],
        "mouthRollUpper": [_g((0, -0.2, -0.35), _p(0, yc + 0.35), (1.8, 0.4, 1.0), "upper")],
        "mouthShrugLower": [_g((0, 0.3, 0.15), _p(0, yc - 1.2), (1.8, 1.3, 1.5), "lower")],
        "mouthShrugUpper": [_g((0, 0.2, 0.1), _p(0, yc + 0.5), (1.8, 0.6, 1.2), "upper")],
        "mouthPressLeft": [_g((0, -0.12, 0.05), _p(1.2, yc + 0.2), (1.0, 0.35, 1.0), "upper"),
                           _g((0, 0.12, 0.05), _p(1.2, yc - 0.2), (1.0, 0.35, 1.0), "lower")],
        "mouthLowerDownLeft": [_g((0, -0.4, 0.08), _p(1.1, yc - 0.4), (1.0, 0.7, 1.2), "lower")],
        "mouthUpperUpLeft": [_g((0, 0.4, 0.05), _p(1.1, yc + 0.5), (1.0, 0.6, 1.2), "upper")],
        "browDownLeft": [_g((-0.25, -0.45, 0.05), _p(3.0, 5.3), (1.6, 1.0, 1.5))],
        "browInnerUp": [_g((0, 0.55, 0.05), _p(1.4, 5.2), (1.1, 1.1, 1.5), pair=True)],
        "browOuterUpLeft": [_g((0, 0.55, 0), _p(4.6, 5.0), (1.3, 1.2, 1.5))],
        "cheekPuff": [_g((0.55, 0, 0.45), _p(4.0, yc + 0.8), (1.6, 1.6, 2.0), pair=True)],
        "cheekSquintLeft": [_g((0.05, 0.35, 0.08), _p(3.6, 1.9), (1.3, 0.9, 1.5))],
        "noseSneerLeft": [_g((0.03, 0.35, 0.05), _p(1.1, -0.6), (0.7, 0.9, 1.0)),
                          _g((-0.05, -0.1, 0), _p(1.3, 4.6), (0.8, 0.8, 1.0))],
        "tongueOut": [_g((0, -0.3, 2.2), _p(0, yc - 0.5, dz=-1.2), (1.2, 0.8, 1.5), region="mouth"),
                      _g((0, -0.3, 0.25), _p(0, yc - 0.4), (1.2, 0.5, 1.0), "lower"),
                      _jaw(angle=0.05)],
    }
    return f


def _sigmoid(t):
    return 0.5 * (1.0 + np.tanh(0.5 * t))


def _lip_mask(X, upper: bool):
    d = (X[:, 1] - Y_MOUTH) / _LIP_W
    return _sigmoid(d if upper else -d)


def _jaw_mask(X, term):
    """1 on the jaw (below the plane through the hinge axis and the mouth line), 0 above; steep at the lips"""
    h = term["hinge"]
    lips = _p(0, Y_MOUTH)
    slope = (Y_MOUTH - h[1]) / (lips[2] - h[2])
    below = h[1] + (X[:, 2] - h[2]) * slope - X[:, 1]
    plane = _sigmoid(below / term["w"]) * _sigmoid((X[:, 2] - h[2] + 0.5) / 0.8)
    plane = plane * _sigmoid((X[:, 1] - (Y_MOUTH - 5.5)) / 0.8)
    near = np.exp(-0.5 * ((X[:, 0] / 2.8) ** 2 + ((X[:, 1] - Y_MOUTH) / 0.9) ** 2))
    near = near * _sigmoid((X[:, 2] - (lips[2] - 1.5)) / 0.3)
    return near * _lip_mask(X, upper=False) + (1.0 - near) * plane


def _term(X, term, region):
    kind = term["kind"]
    if kind == "gauss":
        if term["region"] != region:
            return np.zeros_like(X)
        g = np.exp(-0.5 * np.sum(((X - term["c"]) / term["s"]) ** 2, axis=1))
        if term["mask"] == "upper":
            g = g * _lip_mask(X, True)
        elif term["mask"] == "lower":
            g = g * _lip_mask(X, False)
        return g[:, None] * term["a"]
    if kind == "lid":
        if region != "head":
            return np.zeros_like(X)
        t = (X[:, 0] - EYE_CENTER[0]) / EYE_RADII[0]
        q = np.sqrt(np.clip(1.0 - t * t, 0.0, None))
        dy = X[:, 1] - EYE_CENTER[1]
        edge = EYE_RADII[1] * q
        up = _sigmoid(dy / 0.05) * np.exp(-0.5 * (np.clip(dy - edge, 0, None) / term["sigma_up"]) ** 2)
        low = _sigmoid(-dy / 0.05) * np.exp(-0.5 * (np.clip(-dy - edge, 0, None) / term["sigma_low"]) ** 2)
        scale = 2.0 * EYE_RADII[1] * q
        front = _sigmoid((X[:, 2] - 5.0) / 0.5)
        # lids slide over the eye: moving across the opening also moves them in depth, from one lid's margin
        # depth to the other's (per unit of vertical travel, as a fraction of the opening)
        x = np.clip(X[:, 0], EYE_CENTER[0] - EYE_RADII[0], EYE_CENTER[0] + EYE_RADII[0])
        dz = (front_point(x, EYE_CENTER[1] - edge)[:, 2] - front_point(x, EYE_CENTER[1] + edge)[:, 2])
        depth = (dz / np.maximum(scale, 1e-9))[:, None] * np.array([0.0, 0.0, 1.0])
        up_vec = term["up"] - term["up"][1] * depth
        low_vec = term["low"] - term["low"][1] * depth
        return (scale * front)[:, None] * (up[:, None] * up_vec + low[:, None] * low_vec)
    if kind == "jaw":
        m = _jaw_mask(X, term)
        h = term["hinge"]
        c, s = np.cos(term["angle"]), np.sin(term["angle"])
        r = X - h
        rot = np.stack([r[:, 0], c * r[:, 1] - s * r[:, 2], s * r[:, 1] + c * r[:, 2]], 1) - r
        return m[:, None] * (rot + term["a"])
    raise ValueError(kind)


def _field(X, terms, region):
    out = np.zeros_like(X)
    for term in terms:
        out += _term(X, term, region)
        if term.get("pair"):
            out += _term(X * MIRROR, term, region) * MIRROR
    return out


def evaluate_fields(fields: dict[str, list[dict]], X: np.ndarray, region: str = "head",
                    names=ARKIT_NAMES) -> np.ndarray:
    """Displacements ``[K, n, 3]`` (cm) of shapes ``names`` at reference points ``X[n,3]``.

    ``region`` is ``"head"`` (skin) or ``"mouth"`` (teeth/tongue block: only :data:`MOUTH_MESH_SHAPES`).
    Right shapes are mirrored left shapes. Displacements below :data:`SUPPORT_CUTOFF` are zeroed.
    """
    X = np.asarray(X, float)
    out = np.zeros((len(names), len(X), 3))
    for k, name in enumerate(names):
        if region == "mouth" and name not in MOUTH_MESH_SHAPES:
            continue
        if name.endswith("Right"):
            d = _field(X * MIRROR, fields[name[:-5] + "Left"], region) * MIRROR
        else:
            d = _field(X, fields[name], region)
        d[np.linalg.norm(d, axis=1) < SUPPORT_CUTOFF] = 0.0
        out[k] = d
    return out


def _tilt(rng, vec, deg, centre: bool):
    """Rotate ``vec`` by a random small rotation (about x only for centre terms, keeping symmetry)."""
    if centre:
        axis = np.array([1.0, 0.0, 0.0])
    else:
        axis = rng.standard_normal(3)
        axis /= np.linalg.norm(axis)
    ang = np.deg2rad(deg) * rng.standard_normal()
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + np.sin(ang) * k + (1 - np.cos(ang)) * (k @ k)
    return rot @ vec


def personalize_fields(generic: dict[str, list[dict]], rng: np.random.Generator, *, amplitude_std=0.3,
                       tilt_deg=15.0, shift_std=0.3, width_std=0.12, extra=0.2) -> dict[str, list[dict]]:
    """A person's TRUE fields: each generic term perturbed (amplitude, direction, centre, width) and one extra
    small Gaussian term per shape. Centre shapes stay symmetric (no x shift, tilt about x only)."""
    out = {}
    for name in sorted(generic):
        centre = not name.endswith("Left")
        terms = []
        for term in generic[name]:
            t = copy.deepcopy(term)
            sym = centre and not t.get("pair")
            amp = float(np.clip(1.0 + amplitude_std * rng.standard_normal(), 0.6, 1.5))
            if t["kind"] == "gauss":
                t["a"] = _tilt(rng, t["a"], tilt_deg, sym) * amp
                shift = shift_std * rng.standard_normal(3)
                if sym:
                    shift[0] = 0.0
                t["c"] = t["c"] + shift
                t["s"] = t["s"] * np.clip(1.0 + width_std * rng.standard_normal(3), 0.7, 1.4)
            elif t["kind"] == "lid":
                t["up"] = _tilt(rng, t["up"], tilt_deg, False) * amp
                t["low"] = _tilt(rng, t["low"], tilt_deg, False) * amp
                if t["closes"]:     # a blink still closes the eye: upper + lower travel = the opening
                    t["low"][1] = float(np.clip(t["low"][1], 0.0, 0.15))
                    t["up"][1] = -(1.0 - t["low"][1])
                t["sigma_up"] *= float(np.clip(1.0 + width_std * rng.standard_normal(), 0.7, 1.4))
                t["sigma_low"] *= float(np.clip(1.0 + width_std * rng.standard_normal(), 0.7, 1.4))
            elif t["kind"] == "jaw":
                t["angle"] *= float(np.clip(1.0 + 0.5 * amplitude_std * rng.standard_normal(), 0.8, 1.2))
                t["a"] = _tilt(rng, t["a"], tilt_deg, sym) * amp
                t["hinge"] = t["hinge"] + np.array([0.0, *(0.3 * rng.standard_normal(2))])
            terms.append(t)
        # one extra component near the shape's main term that the template lacks
        main = next((t for t in terms if t["kind"] == "gauss"), None)
        c = main["c"] if main is not None else (_p(EYE_CENTER[0], EYE_CENTER[1] + 0.8) if "eye" in name
                                                else _p(0, Y_MOUTH - 1.0))
        direction = rng.standard_normal(3)
        offset = 0.5 * rng.standard_normal(3)
        if centre:
            direction[0] = 0.0
            offset[0] = 0.0
        direction /= np.linalg.norm(direction)
        size = extra * (0.5 + abs(rng.standard_normal()))
        mask = main["mask"] if main is not None else None
        if "eye" in name:
            mask = None
        pair = bool(main is not None and main.get("pair"))   # off-midline centre term: mirrored, symmetric
        if pair:
            direction = rng.standard_normal(3)
            direction /= np.linalg.norm(direction)
        terms.append(_g(size * direction, c + offset, (0.9, 0.9, 1.2), mask, pair=pair))
        out[name] = terms
    return out
