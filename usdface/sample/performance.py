"""What the sample person performs: ARKit weights with realistic cross-talk for the training and test frames.

Training frame *j* asks the person for shape *j* alone; like a real ARKit capture, the reported weights also
show the shapes that move with it (both eyes blink together, a smile brings the squint and cheek, mouthClose
needs the jaw open, the eyes look left with eyeLookOutLeft + eyeLookInRight ...) and low-level background
activity. Test frames are mixed expressions (smile, surprise, anger, visemes ...). The phone's reported
weights are the true weights plus noise (clipped to [0, 1]).
"""

from __future__ import annotations

import numpy as np

from ..arkit import ARKIT_NAMES, mirror_name

_INDEX = {n: k for k, n in enumerate(ARKIT_NAMES)}

#: shape asked for -> [(co-activated shape, low, high)]; Right shapes use the mirrored Left rule.
CROSS_TALK = {
    "eyeBlinkLeft": [
        ("eyeBlinkRight", 0.1, 0.35),
        ("eyeSquintLeft", 0.05, 0.2),
        ("eyeLookDownLeft", 0.05, 0.15),
    ],
    "eyeLookDownLeft": [
        ("eyeLookDownRight", 0.8, 1.0),
        ("eyeBlinkLeft", 0.1, 0.3),
        ("eyeBlinkRight", 0.1, 0.3),
    ],
    "eyeLookInLeft": [("eyeLookOutRight", 0.7, 0.95)],
    "eyeLookOutLeft": [("eyeLookInRight", 0.7, 0.95)],
    "eyeLookUpLeft": [("eyeLookUpRight", 0.8, 1.0), ("browInnerUp", 0.0, 0.15)],
    "eyeSquintLeft": [
        ("cheekSquintLeft", 0.1, 0.3),
        ("eyeSquintRight", 0.1, 0.3),
        ("mouthSmileLeft", 0.0, 0.1),
    ],
    "eyeWideLeft": [("eyeWideRight", 0.2, 0.5), ("browOuterUpLeft", 0.05, 0.2), ("browInnerUp", 0.05, 0.2)],
    "jawForward": [("jawOpen", 0.0, 0.1), ("mouthClose", 0.0, 0.05)],
    "jawLeft": [("mouthLeft", 0.05, 0.2)],
    "jawOpen": [
        ("mouthFunnel", 0.0, 0.1),
        ("mouthLowerDownLeft", 0.05, 0.2),
        ("mouthLowerDownRight", 0.05, 0.2),
        ("mouthClose", 0.0, 0.05),
    ],
    "mouthClose": [("jawOpen", 0.3, 0.45)],
    "mouthFunnel": [("mouthPucker", 0.1, 0.3), ("jawOpen", 0.05, 0.2)],
    "mouthPucker": [("mouthFunnel", 0.1, 0.3)],
    "mouthLeft": [("jawLeft", 0.0, 0.1)],
    "mouthSmileLeft": [
        ("eyeSquintLeft", 0.1, 0.3),
        ("cheekSquintLeft", 0.1, 0.3),
        ("mouthSmileRight", 0.05, 0.2),
        ("mouthUpperUpLeft", 0.0, 0.1),
    ],
    "mouthFrownLeft": [("mouthFrownRight", 0.1, 0.3), ("mouthShrugLower", 0.0, 0.15)],
    "mouthDimpleLeft": [("mouthDimpleRight", 0.05, 0.2), ("mouthSmileLeft", 0.0, 0.1)],
    "mouthStretchLeft": [("mouthStretchRight", 0.1, 0.3), ("jawOpen", 0.0, 0.1)],
    "mouthRollLower": [("mouthRollUpper", 0.1, 0.3)],
    "mouthRollUpper": [("mouthRollLower", 0.1, 0.3)],
    "mouthShrugLower": [("mouthShrugUpper", 0.1, 0.3)],
    "mouthShrugUpper": [("mouthShrugLower", 0.1, 0.3)],
    "mouthPressLeft": [("mouthPressRight", 0.2, 0.5)],
    "mouthLowerDownLeft": [("mouthLowerDownRight", 0.1, 0.3), ("jawOpen", 0.0, 0.1)],
    "mouthUpperUpLeft": [("mouthUpperUpRight", 0.1, 0.3), ("noseSneerLeft", 0.0, 0.15)],
    "browDownLeft": [("browDownRight", 0.2, 0.5), ("eyeSquintLeft", 0.0, 0.15), ("noseSneerLeft", 0.0, 0.1)],
    "browInnerUp": [("browOuterUpLeft", 0.05, 0.2), ("browOuterUpRight", 0.05, 0.2)],
    "browOuterUpLeft": [
        ("browOuterUpRight", 0.1, 0.3),
        ("browInnerUp", 0.05, 0.2),
        ("eyeWideLeft", 0.0, 0.15),
    ],
    "cheekPuff": [("mouthPucker", 0.0, 0.1)],
    "cheekSquintLeft": [("eyeSquintLeft", 0.2, 0.4), ("mouthSmileLeft", 0.05, 0.2)],
    "noseSneerLeft": [
        ("noseSneerRight", 0.2, 0.5),
        ("mouthUpperUpLeft", 0.1, 0.3),
        ("browDownLeft", 0.05, 0.2),
    ],
    "tongueOut": [("jawOpen", 0.2, 0.35)],
}

#: Test expressions: name -> {shape: weight} ("*" = both sides).
EXPRESSIONS = {
    "smile": {"mouthSmile*": 0.7, "cheekSquint*": 0.3, "eyeSquint*": 0.3},
    "laugh": {"mouthSmile*": 0.9, "jawOpen": 0.35, "mouthUpperUp*": 0.3, "cheekSquint*": 0.4},
    "surprise": {"jawOpen": 0.5, "browInnerUp": 0.8, "browOuterUp*": 0.7, "eyeWide*": 0.6},
    "anger": {"browDown*": 0.8, "noseSneer*": 0.4, "mouthPress*": 0.3, "eyeSquint*": 0.3},
    "sadness": {"mouthFrown*": 0.6, "browInnerUp": 0.6, "mouthShrugLower": 0.3},
    "blink": {"eyeBlink*": 0.9},
    "winkLeft": {"eyeBlinkLeft": 0.95, "eyeBlinkRight": 0.2, "mouthSmileLeft": 0.3, "cheekSquintLeft": 0.3},
    "kiss": {"mouthPucker": 0.8, "mouthFunnel": 0.2},
    "visemeAA": {"jawOpen": 0.6, "mouthLowerDown*": 0.3},
    "visemeOO": {"mouthFunnel": 0.6, "mouthPucker": 0.3, "jawOpen": 0.2},
    "visemeEE": {"mouthStretch*": 0.5, "mouthSmile*": 0.2, "jawOpen": 0.15},
    "disgust": {"noseSneer*": 0.7, "mouthUpperUp*": 0.5, "browDown*": 0.3},
    "lookLeft": {"eyeLookOutLeft": 0.8, "eyeLookInRight": 0.8},
    "lookUp": {"eyeLookUp*": 0.8, "browInnerUp": 0.2},
    "puff": {"cheekPuff": 0.8, "mouthPucker": 0.2},
    "jawSide": {"jawRight": 0.6, "mouthRight": 0.4},
    "tongue": {"tongueOut": 0.8, "jawOpen": 0.3},
    "lipsIn": {"mouthRollLower": 0.6, "mouthRollUpper": 0.6, "mouthPress*": 0.2},
    "smirk": {"mouthSmileLeft": 0.7, "mouthDimpleLeft": 0.3, "cheekSquintLeft": 0.2},
    "mixed": {},
}


def _expand(spec: dict) -> dict:
    out = {}
    for key, w in spec.items():
        for n in [key.replace("*", "Left"), key.replace("*", "Right")] if "*" in key else [key]:
            out[n] = w
    return out


def _background(rng, w, p=0.1, high=0.05):
    hit = rng.random(len(w)) < p
    return np.maximum(w, np.where(hit, rng.uniform(0.0, high, len(w)), 0.0))


def training_weights(rng: np.random.Generator) -> np.ndarray:
    """True weights ``[52, 52]`` of the training frames: row j asks for ARKIT_NAMES[j] (with cross-talk)."""
    out = np.zeros((len(ARKIT_NAMES), len(ARKIT_NAMES)))
    for j, name in enumerate(ARKIT_NAMES):
        w = _background(rng, np.zeros(len(ARKIT_NAMES)))
        w[j] = rng.uniform(0.85, 1.0)
        right = name.endswith("Right")
        rules = CROSS_TALK.get(mirror_name(name) if right else name, [])
        for other, lo, hi in rules:
            out_name = mirror_name(other) if right else other
            w[_INDEX[out_name]] = rng.uniform(lo, hi)
        out[j] = w
    return out


def test_weights(rng: np.random.Generator) -> tuple[list[str], np.ndarray]:
    """Labels and true weights ``[T, 52]`` of the mixed test expressions."""
    labels, rows = [], []
    for label, spec in EXPRESSIONS.items():
        w = _background(rng, np.zeros(len(ARKIT_NAMES)), p=0.15)
        spec = _expand(spec)
        if not spec:  # a random mixture of five shapes
            for k in rng.choice(len(ARKIT_NAMES), 5, replace=False):
                w[k] = rng.uniform(0.1, 0.6)
        scale = rng.uniform(0.8, 1.1)
        for n, v in spec.items():
            w[_INDEX[n]] = v * scale
        labels.append(label)
        rows.append(np.clip(w, 0.0, 1.0))
    return labels, np.array(rows)


def reported_weights(rng: np.random.Generator, true_weights: np.ndarray, noise: float = 0.02) -> np.ndarray:
    """What the phone reports: true weights + Gaussian noise, clipped to [0, 1], 4 decimals."""
    w = true_weights + noise * rng.standard_normal(true_weights.shape)
    return np.round(np.clip(w, 0.0, 1.0), 4)
