"""Compact facial landmark layouts by weighted set cover (Zell & McDonnell, Eurographics 2022).

Public API: :func:`compute_landmarks` -> :class:`LandmarkLayout`; reconstruction from landmarks in
:mod:`usdface.landmarks.reconstruct`; baselines and the evaluation sweep in :mod:`.baselines` /
:mod:`.evaluate`.
"""

from .layout import LandmarkLayout, compute_landmarks

__all__ = ["LandmarkLayout", "compute_landmarks"]
