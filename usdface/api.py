"""usdface's small, stable Python API (also re-exported as ``usdface.<name>``).

Thin wrappers over the modules that do the work, imported lazily so ``import usdface`` stays cheap. The CLI
calls these functions, so the command line and a pipeline script behave identically. Every failure on bad
input raises a :class:`usdface.errors.UsdFaceError` subclass that names the file, the prim and the fix.

Example::

    import usdface
    issues = usdface.check("avatar.usdc")                  # list[Issue], errors first
    avatar = usdface.read_avatar("avatar.usdc")            # Avatar (metres, Y up)
    capture = usdface.read_capture("capture/")             # Capture
    out = usdface.personalize_avatar("avatar.usdc", "capture/", "avatar_person.usda")
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from .model import Avatar, Capture, FaceRig
    from .pipeline.check import Issue
    from .transfer import PersonalizeResult

PathLike = str | Path

__all__ = [
    "personalize_avatar", "fit_capture", "evaluate_capture", "compute_landmarks", "read_avatar",
    "read_capture", "import_capture_folder", "check", "inspect_file",
]


def read_avatar(path: PathLike) -> Avatar:
    """Read a UsdSkel avatar: every skinned mesh with blend shapes, converted to metres / Y up, ARKit names
    canonicalised (see :func:`usdface.io.usd_rig.read_avatar`)."""
    from .io.usd_rig import read_avatar as _read

    return _read(path)


def read_capture(path: PathLike) -> Capture:
    """Read a capture folder (OBJ + JSON) or a capture ``.usda`` (see :func:`usdface.io.read_capture`)."""
    from .io import read_capture as _read

    return _read(path)


def import_capture_folder(folder: PathLike, out_path: PathLike, force: bool = False) -> Path:
    """Convert a capture folder into one ``capture.usda`` (``usdface capture import``); returns the path
    written. Refuses to overwrite an existing file unless ``force``."""
    from .io.capture_folder import read_capture_folder
    from .io.usd_capture import write_capture_usd

    return Path(write_capture_usd(read_capture_folder(folder), out_path, force=force))


def _as_capture(capture) -> Capture:
    return read_capture(capture) if isinstance(capture, str | Path) else capture


def fit_capture(capture: Capture | PathLike, method: str = "menzel", **options: Any):
    """Fit personalized blendshapes on the capture mesh (``usdface fit``); returns a ``FitResult`` whose
    ``.rig`` is a :class:`usdface.model.FaceRig` (neutral = the person's neutral, deltas = personalized
    shapes).
    ``method`` is one of ``dt``, ``ebfr``, ``menzel``, ``laplacian``; ``options`` go to
    :func:`usdface.personalize.fit_personalized_shapes`."""
    from .personalize import fit_personalized_shapes

    return fit_personalized_shapes(_as_capture(capture), method=method, **options)


def evaluate_capture(capture: Capture | PathLike, rig: FaceRig | None = None, role: str = "test") -> dict:
    """Paper eq. 5 on the capture's held-out ``test`` (or ``train``) expressions: per-frame RMSE and max
    vertex error in mm of ``rig`` with the frames' weights (``usdface evaluate``); see
    :func:`usdface.personalize.evaluate_rig`. ``rig`` defaults to the generic baseline: the template's deltas
    on the person's neutral. ``rig`` may also be a ``FitResult`` (its ``.rig`` is used)."""
    from .model import FaceRig as _FaceRig
    from .personalize import evaluate_rig

    capture = _as_capture(capture)
    if rig is None:
        t = capture.template
        rig = _FaceRig(capture.neutral, capture.triangles, t.names, t.deltas, t.inbetweens, t.source,
                       "generic")
    rig = getattr(rig, "rig", rig)
    return evaluate_rig(rig.subset(capture.names) if list(rig.names) != list(capture.names) else rig,
                        capture.frames.select(role))


def personalize_avatar(avatar_path: PathLike | Avatar, capture_path: PathLike | Capture,
                       out_path: PathLike | None, *, inspect: bool = False, take: PathLike | None = None,
                       landmarks: bool = False, **options: Any) -> PersonalizeResult:
    """Personalize an avatar from a capture and write the result as a USD layer over the untouched avatar
    (``usdface personalize``); returns the ``PersonalizeResult`` (``.out_path`` = the layer written).

    ``options`` go to :func:`usdface.transfer.personalize_avatar` (``method``, ``force``, ``mu``, ...). With
    ``inspect=True`` the layer also gets inspection data for usdview (:mod:`usdface.io.usd_inspection`): a
    ``displayColor`` heat map of how much each vertex changed (RMS over shapes) and a ``SkelAnimation`` that
    plays the capture's test expressions on the personalized avatar, followed by ``take`` (a Live Link Face
    CSV or a take imported with ``usdface anim import``) when given, and with ``landmarks=True`` the landmark
    layout of the personalized face mesh as ``Points`` (about 10 s more on the bench avatars)."""
    from .transfer import personalize_avatar as _personalize

    if not inspect:
        return _personalize(avatar_path, capture_path, out_path, **options)
    avatar = avatar_path if not isinstance(avatar_path, str | Path) else read_avatar(avatar_path)
    capture = _as_capture(capture_path)
    result = _personalize(avatar, capture, out_path, **options)
    if getattr(result, "out_path", None):
        from .io.take import read_take
        from .io.usd_inspection import add_inspection, change_heat, inspection_animation, inspection_edit

        animation = inspection_animation(capture, read_take(take) if take is not None else None)
        layouts = None
        if landmarks:
            from .model import FaceRig as _FaceRig

            face = avatar.mesh(result.face_mesh)
            personalized = _FaceRig(face.neutral, face.triangles, face.names,
                                    result.offsets[face.source.prim], face.inbetweens, face.source, face.name)
            layouts = {face.source.prim: compute_landmarks(personalized)}
        add_inspection(result.out_path, inspection_edit(avatar, heat=change_heat(avatar, result.offsets),
                                                        landmarks=layouts, animation=animation, fps=24.0))
    return result


def compute_landmarks(rig: FaceRig, epsilon: float = 0.5, alpha: float = 0.5, **options: Any):
    """A landmark layout for ``rig`` (``usdface landmarks``); see
    :func:`usdface.landmarks.compute_landmarks`."""
    from .landmarks import compute_landmarks as _landmarks

    return _landmarks(rig, epsilon=epsilon, alpha=alpha, **options)


def check(file_or_stage: PathLike | Any, pixar: bool = True,
          rules: Iterable[str] | None = None) -> list[Issue]:
    """Validate a face-rig USD file (or an open ``Usd.Stage``): usdface's face-rig rules plus, with ``pixar``,
    OpenUSD's own validators, merged and sorted errors first (``usdface check``). Never modifies the file."""
    from .pipeline.validators import validate_file, validate_stage

    if isinstance(file_or_stage, str | Path):
        return validate_file(file_or_stage, pixar=pixar, rules=rules)
    return validate_stage(file_or_stage, pixar=pixar, rules=rules)


def inspect_file(path: PathLike) -> dict:
    """A summary of a USD avatar, capture or usdface layer (``usdface inspect``): meshes, shapes, units,
    name report, provenance."""
    from .inspect import inspect_file as _inspect

    return _inspect(path)
