"""usdface: personalized ARKit facial blendshapes from a phone capture, implanted into UsdSkel avatars.

The stable Python API lives in :mod:`usdface.api` and is re-exported here lazily, so ``import usdface`` stays
cheap and never fails because an optional dependency is missing.
"""

from __future__ import annotations

__version__ = "0.1.0"

_API = {
    "personalize_avatar", "fit_capture", "write_fit_rig", "evaluate_capture", "evaluate_methods",
    "compute_landmarks", "read_avatar", "pick_mesh", "read_capture", "write_capture", "import_capture_folder",
    "select_capture_frames", "import_livelink_take", "write_landmarks", "evaluate_landmarks",
    "write_retarget_map", "personalize_batch", "check", "inspect_file",
}
_API |= {"write_review", "export_avatar"}  # usdface review / usdface export
_API |= {"landmark_diagnostics"}  # usdface render --landmarks --diagnostics


#: Submodules the docs name as ``usdface.<module>`` after only ``import usdface``
#: (``usdface.progress.set_enabled(False)``, ``except usdface.errors.UsdFaceError``, the numerical core):
#: loaded on first use, as the API is; they raised ``AttributeError: progress``.
_SUBMODULES = {"api", "arkit", "errors", "io", "landmarks", "mesh", "model", "personalize", "pipeline",
               "progress", "render", "review", "transfer"}


def __getattr__(name):
    if name in _API:
        from . import api

        return getattr(api, name)
    if name in _SUBMODULES:
        import importlib

        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module 'usdface' has no attribute {name!r}")


def __dir__():
    """The lazily re-exported API among the module's names (``dir(usdface)``, a shell's completion), which
    listed none of them."""
    return sorted(set(globals()) | _API | _SUBMODULES)
