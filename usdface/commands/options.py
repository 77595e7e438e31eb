"""argparse value types that refuse what the work would choke on later (NaN, inf, negative, zero), so a bad
option fails at once with ``usdface CMD: error: argument --x: ...`` (exit 2) instead of writing a broken
output or a traceback after minutes of work."""

from __future__ import annotations

import argparse
import math


def _number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def finite_float(text: str) -> float:
    """Any finite number."""
    return _number(text)


def weight_bound(text: str) -> float:
    """A finite number: one end of ``--weight-bounds`` (``inf`` is no bound: that is ``--unbounded``)."""
    try:
        return _number(text)
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"{exc} (for no bounds use --unbounded)") from None


def positive_float(text: str) -> float:
    """A finite number > 0."""
    value = _number(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return value


def nonnegative_float(text: str) -> float:
    """A finite number >= 0."""
    value = _number(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return value


def unit_float(text: str) -> float:
    """A finite number in [0, 1]."""
    value = _number(text)
    if not 0 <= value <= 1:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}")
    return value


def _int_at_least(low: int):
    """An argparse type: a whole number >= ``low``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"expected a whole number >= {low}, got {text!r}")
        return value

    return parse


#: An integer >= 1.
positive_int = _int_at_least(1)
#: An integer >= 0.
nonnegative_int = _int_at_least(0)


def _keyword_or(number, keywords: tuple[str, ...], expected: str):
    """An argparse type: one of ``keywords`` as is, else ``number(text)``, one message for both."""

    def parse(text: str):
        if text in keywords:
            return text
        try:
            return number(text)
        except argparse.ArgumentTypeError:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None

    return parse


#: ``auto`` or a finite number > 0 (the eq. (4) ridge weight).
mu_value = _keyword_or(positive_float, ("auto",), "auto or a number > 0")
#: ``auto``, ``paper`` or a finite number > 0 (the fit's E_reg weight; 0 would leave a shape no frame shows
#: undetermined, and the fit refuses it).
reg_value = _keyword_or(positive_float, ("auto", "paper"), "auto, paper or a number > 0")


def vector3(text: str) -> list[float]:
    """Three finite comma-separated numbers ``X,Y,Z``."""
    parts = text.split(",")
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z (three comma-separated numbers), got {text!r}")
    try:
        return [_number(p) for p in parts]
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z (three finite numbers), got {text!r}") from None


def refuse_camera_with_rays(camera, rays, error=None) -> None:
    """``--camera`` sees from one point (one visibility ray per vertex): ``--rays`` (hemisphere rays) given
    with it would be ignored, so the pair is refused (``error``: the command's error class, default
    :class:`usdface.errors.OptionError`)."""
    if camera is not None and rays is not None:
        from ..errors import OptionError

        raise (error or OptionError)("--rays counts hemisphere rays; --camera sees from one point, so the "
                                     "rays would be ignored", fix="give --camera or --rays, not both")


def add_quiet(parser) -> None:
    """``--quiet``/``-q``: no progress on stderr (a bar on a terminal, step lines in logs); ``usdface.cli``
    reads it, and ``--json`` (printed on stdout) silences progress too."""
    parser.add_argument("--quiet", "-q", action="store_true", help="no progress on stderr")
