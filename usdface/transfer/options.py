"""The options of ``usdface personalize``'s implant and their checks, before any work: the face-transfer modes
and approximations, which options each mode uses (:data:`MODE_OPTIONS`), their names in the API's and the
command line's spelling, the numeric checks, and the fit options the implant passes on or records.

The one place the Python API, ``usdface personalize`` and ``usdface batch`` read these rules from, so the same
options give the same result (or the same refusal) from each."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import OptionError
from .retarget import GAZE_CHOICES

__all__ = ["FACE_TRANSFERS", "APPROXIMATIONS", "MODE_OPTIONS", "MODE_ONLY_OPTIONS", "IMPLANT_OPTIONS",
           "PRIORS", "MAP_PRIORS", "MAP_GAZES", "option_name", "check_mode_options", "modes_using",
           "default_approximation", "check_modes", "check_numbers", "recorded_fit_options", "pins_input",
           "fit_prior_options", "run_options"]

#: Face-region transfer modes (see :func:`usdface.transfer.partial_dt.implant_shapes` and ``"person"``,
#: :func:`usdface.transfer.pipeline.personalize_avatar`).
FACE_TRANSFERS = ("person", "offset", "dt", "dt-offset")


#: What the adjacent region and the other meshes are blended from / follow.
APPROXIMATIONS = ("field", "generic", "retarget")


#: The options of :func:`.pipeline.personalize_avatar` each face-transfer mode uses besides the fit's,
#: eq. (4)'s and ``eyelids`` (:func:`check_mode_options` refuses the others when given): the person's field
#: reaches ``extension_length`` face radii; the older modes join over ``falloff`` edge lengths; ``support``
#: ramps the personalization of ``person`` and the offset modes (``dt`` transfers the whole deformation).
MODE_OPTIONS = {
    "person": ("extension_length", "support"),
    "offset": ("falloff", "support"),
    "dt": ("falloff",),
    "dt-offset": ("falloff", "support"),
}


#: The options some face-transfer modes use and others not (those :func:`check_mode_options` checks).
MODE_ONLY_OPTIONS = frozenset(k for ks in MODE_OPTIONS.values() for k in ks)


#: The implant's options (step 5 and the eyelid repair): ``usdface retarget``, which writes the eq. (4) map
#: only, takes none of them.
IMPLANT_OPTIONS = ("face_transfer", "approximation", "extension_length", "falloff", "support", "eyelids",
                   "eyes")


#: Command-line spellings of options whose flag is not ``--`` + the name with dashes (None: API only).
_FLAGS = {"support": None, "eyes": None, "eyelids": "--no-eyelids", "weight_bounds": "--weight-bounds"}


def option_name(name: str) -> str:
    """``"falloff (--falloff)"``: an option of :func:`.pipeline.personalize_avatar` in both spellings, the
    API's and the command line's (``"support (Python API only)"`` for one the commands do not offer)."""
    flag = _FLAGS.get(name, "--" + name.replace("_", "-"))
    return f"{name} ({flag})" if flag else f"{name} (Python API only)"


def check_mode_options(face_transfer: str, given) -> None:
    """Refuse (:class:`usdface.errors.OptionError`), before any work, an option among ``given`` (the names
    the caller gave explicitly) that ``face_transfer`` does not use (:data:`MODE_OPTIONS`): it would be
    ignored without a word. An unknown ``face_transfer`` is left to :func:`check_modes`."""
    from ..errors import OptionError

    used = MODE_OPTIONS.get(face_transfer)
    if used is None:
        return
    for name in sorted(set(given) & MODE_ONLY_OPTIONS):
        if name not in used:
            raise OptionError(
                f"{option_name(name)} is not used by {option_name('face_transfer')} {face_transfer!r} "
                f"(it uses {', '.join(option_name(k) for k in used)})",
                fix=f"drop {option_name(name)}, or choose a {option_name('face_transfer')} that uses it: "
                    + ", ".join(modes_using(name)))


def modes_using(name: str) -> list[str]:
    """The face-transfer modes that use the option ``name`` (:data:`MODE_OPTIONS`)."""
    return [m for m, ks in MODE_OPTIONS.items() if name in ks]


def default_approximation(face_transfer: str) -> str:
    """The approximation a face-transfer mode gets when none is given: ``"field"`` for ``"person"`` (the only
    one it goes with), ``"generic"`` for the older modes. The one rule the Python API, ``usdface
    personalize`` and ``usdface batch`` share, so the same mode gives the same result from each."""
    return "field" if face_transfer == "person" else "generic"


#: Priors of the fit (see :func:`.pipeline.personalize_avatar`).
PRIORS = ("avatar", "template")


#: What eq. (4)'s ridge shrinks the retarget map towards (see :func:`.pipeline.personalize_avatar`).
MAP_PRIORS = ("namesake", "zero")


#: How the retarget map treats the gaze channels (:func:`usdface.transfer.retarget.gaze_held`).
MAP_GAZES = GAZE_CHOICES


def check_modes(face_transfer: str, approximation: str | None, prior: str, weight_bounds=None,
                 map_prior: str = "namesake", map_gaze: str = "namesake") -> str:
    """Refuse unknown or mismatched transfer modes and a bad retarget map setting before any work
    (:class:`usdface.errors.OptionError`); returns the approximation to use (``approximation``, or
    :func:`default_approximation` of ``face_transfer`` when None)."""
    if map_prior not in MAP_PRIORS:
        raise OptionError(f"unknown map prior {map_prior!r} ({option_name('map_prior')})",
                          fix=f"use one of {', '.join(MAP_PRIORS)}")
    if map_gaze not in MAP_GAZES:
        raise OptionError(f"unknown map gaze {map_gaze!r} ({option_name('map_gaze')})",
                          fix=f"use one of {', '.join(MAP_GAZES)} (namesake: a gaze channel driven by its "
                              "namesake alone; free: eq. 4 as it is)")
    if weight_bounds is not None:
        name = option_name("weight_bounds")
        try:
            if isinstance(weight_bounds, str):     # its characters are no bounds: "01" read as (0, 1)
                raise TypeError
            lo, hi = (float(b) for b in weight_bounds)
        except (TypeError, ValueError):
            raise OptionError(f"bad weight bounds {weight_bounds!r}: {name} takes two numbers",
                              fix="give two finite numbers LO < HI, e.g. (0, 1) ([0, 1] in a batch manifest "
                                  "or --set); for no bounds use weight_bounds=None (--unbounded), null in a "
                                  "batch manifest") from None
        if not (np.isfinite(lo) and np.isfinite(hi)):
            raise OptionError(f"bad weight bounds {lo:g} {hi:g}: {name} must be finite",
                              fix="give two finite numbers LO < HI, e.g. (0, 1); for no bounds use "
                                  "weight_bounds=None (--unbounded)")
        if not lo < hi:
            raise OptionError(f"bad weight bounds {lo:g} {hi:g}: {name} needs LO < HI",
                              fix="give LO < HI, e.g. (0, 1) (--weight-bounds 0 1); for no bounds use "
                                  "weight_bounds=None (--unbounded)")
    if face_transfer not in FACE_TRANSFERS:
        raise OptionError(f"unknown face transfer {face_transfer!r} ({option_name('face_transfer')})",
                          fix=f"use one of {', '.join(FACE_TRANSFERS)}")
    if approximation is None:
        approximation = default_approximation(face_transfer)
    if approximation not in APPROXIMATIONS:
        raise OptionError(f"unknown approximation {approximation!r} ({option_name('approximation')})",
                          fix=f"use one of {', '.join(APPROXIMATIONS)}")
    if prior not in PRIORS:
        raise OptionError(f"unknown prior {prior!r} ({option_name('prior')})",
                          fix=f"use one of {', '.join(PRIORS)}")
    if (face_transfer == "person") != (approximation == "field"):
        raise OptionError(f"{option_name('face_transfer')} {face_transfer!r} and "
                          f"{option_name('approximation')} {approximation!r} do not go together",
                          fix="use face_transfer='person' with approximation='field' (the default), or one "
                              "of the older modes with 'generic' or 'retarget' (leave the approximation out "
                              "for the mode's default)")
    return approximation


def check_numbers(*, mu="auto", extension_length=1.0, falloff=0.15, support=(0.01, 0.03)) -> None:
    """Refuse, before any work, numeric options of :func:`.pipeline.personalize_avatar` the work would choke
    on or silently misuse (NaN, inf, zero or negative where a size or a weight is meant, a non-number), as the
    CLI's argument types do (:mod:`usdface.commands.options`): ``mu`` ``"auto"`` or > 0, ``extension_length``
    None or > 0, ``falloff`` >= 0, ``support`` None or ``(low, high)`` with ``0 <= low <= high``."""
    from ..personalize.api import check_number

    def _number(name, value, **how):
        return check_number(name, value, error=OptionError, **how)

    _number("mu", mu, low=0.0, inclusive=False, fix="use 'auto' or a number > 0 (the eq. 4 ridge weight)",
            keywords=("auto",))
    if extension_length is not None:
        _number("extension_length", extension_length, low=0.0, inclusive=False,
                fix="a length in face radii > 0 (1 = the default), or None for no fade")
    _number("falloff", falloff, low=0.0, inclusive=True, fix="capture edge lengths >= 0 (0 = harmonic join)")
    if support is not None:
        try:
            if isinstance(support, str):            # its characters are no fractions: "01" read as (0, 1)
                raise TypeError
            lo, hi = support
        except (TypeError, ValueError):
            raise OptionError(f"bad support {support!r}", fix="give (low, high) fractions of each shape's "
                              "peak motion, e.g. (0.01, 0.03) ([0.01, 0.03] in a batch manifest), or None"
                              ) from None
        lo = _number("support low", lo, low=0.0, inclusive=True, fix="e.g. support=(0.01, 0.03)")
        hi = _number("support high", hi, low=0.0, inclusive=True, fix="e.g. support=(0.01, 0.03)")
        if lo > hi:
            raise OptionError(f"bad support {support!r}: low > high", fix="e.g. support=(0.01, 0.03)")


def recorded_fit_options(method: str, fit_options: dict) -> dict:
    """The fit's options a layer's provenance records besides the method and ``reg``: those given (numbers,
    words; the artist pins are recorded as ``pins`` and their file among the inputs) and the lip and eyelid
    ``contact`` (default ``"auto"``) when the method uses it."""
    from ..personalize.api import METHOD_TAKES

    out = {k: v for k, v in fit_options.items()
           if k not in ("pins", "contact") and (v is None or isinstance(v, int | float | str | bool))}
    if "contact" in METHOD_TAKES.get(method, ()):
        out["contact"] = fit_options.get("contact", "auto")
    return out


def pins_input(pins, capture_source) -> list[str]:
    """``[file]`` the artist ``pins`` were read from (:class:`usdface.io.pins.Pins`), for the layer's
    recorded inputs (with its digest, as the capture's); [] for pins given as arrays, or read from the
    capture itself."""
    source = getattr(pins, "source", None)
    if source is None:
        return []
    if capture_source and Path(source).resolve() == Path(capture_source).resolve():
        return []
    return [str(source)]


def fit_prior_options(prior: str, method: str) -> dict:
    """The fit's prior options for personalize's ``prior``: with ``"avatar"`` (menzel / laplacian) the
    avatar's own shapes on the capture are given and are the prior at every ``reg`` (``"auto"`` chooses the
    regularization's weight for that prior).

    Not chosen among the priors by cross-validation (as before stop 47; the fit API still offers that with
    ``prior="auto"``): the implant carries each shape's change from the prior the fit shrank towards
    (``A_j + c_j M (B_j - P_j)``), so the prior is also the implant's reference. A template prior that wins
    the fit's held-out score does so because it already holds part of the person; that part is then not in
    ``B_j - P_j`` and never reaches the avatar. With the template a quarter of the way from the capture's
    own to the person's true shapes, dev1's face went 0.29 -> 0.42 of the generic's error (dev2 half way:
    0.85 -> 0.97); with the avatar prior 0.28 and 0.85 (docs/personalize.md, step 4)."""
    if prior != "avatar" or method not in ("menzel", "laplacian"):
        return {}
    return {"avatar_prior": True, "prior": "avatar"}


def run_options(*, method: str, reg, mu, weight_bounds, map_prior: str, face_transfer: str,
                map_gaze: str = "namesake",
                approximation: str, prior: str, extension_length, falloff, support, eyelids: bool,
                fit_options: dict | None) -> dict:
    """The options a personalize run used, as its report and layer record them: of the mode's own
    (:data:`MODE_OPTIONS`), those it uses; the fit's (:func:`recorded_fit_options`) when it fitted
    (``fit_options`` None: a given rig)."""
    return {"method": method, "reg": reg, "mu": mu, "weight_bounds": weight_bounds, "map_prior": map_prior,
            "map_gaze": map_gaze,
            "face_transfer": face_transfer, "approximation": approximation, "prior": prior,
            **{k: v for k, v in (("extension_length", extension_length), ("falloff", falloff),
                                 ("support", support)) if k in MODE_OPTIONS[face_transfer]},
            "eyelids": eyelids,
            **(recorded_fit_options(method, fit_options) if fit_options is not None else {})}
