"""Names given as one comma-separated string or as a list: ``--rules ArkitNames,PointIndices``,
``--shapes jawOpen,eyeBlinkLeft``, ``check(path, rules="ArkitNames")``, ``evaluate_methods(c, ["dt"])``.

Shared by the core (its functions take either) and the commands (their options are strings); imports
nothing of usdface but its errors.
"""

from __future__ import annotations

from collections.abc import Iterable

from .errors import OptionError

__all__ = ["name_list"]


def name_list(value: str | Iterable[str] | None, what: str, noun: str, fix: str) -> list[str] | None:
    """The names in ``value``, in order, each stripped, empty items and repeats dropped; ``None`` stays
    ``None`` (the caller's default: all rules, the default shapes...).

    ``value``: one string, a name or comma-separated names (``"dt, menzel"``; ``list()`` of it made letters),
    or an iterable of such strings (``["dt", "menzel"]``). ``what`` names the option or argument and ``noun``
    one of its names in the errors (``"--rules"``, ``"rule"``), ``fix`` is the fix for one naming nothing.
    Raises :class:`~usdface.errors.OptionError` if ``value`` names nothing (``""``, ``","``, ``[]``: no rule
    run and a broken rig passed, the neutral drawn alone) or is neither a string nor strings (a number,
    bytes).

    Examples
    --------
    >>> name_list(" dt,, menzel ,", "--methods", "method", "name some")
    ['dt', 'menzel']
    >>> name_list(["dt", "ebfr,menzel"], "methods", "method", "name some")
    ['dt', 'ebfr', 'menzel']
    >>> name_list("dt,menzel,dt", "--methods", "method", "name some")
    ['dt', 'menzel']
    """
    if value is None:
        return None
    items = [value] if isinstance(value, str) else \
        list(value) if isinstance(value, Iterable) and not isinstance(value, bytes | bytearray) else None
    if items is None or not all(isinstance(item, str) for item in items):
        raise OptionError(f"{what} takes a {noun} name, comma-separated names or a list of names, not "
                          f"{value!r}", fix=f"give {what} as a string such as 'a,b' or a list of strings")
    # a name given twice once: '--rules ArkitNames,ArkitNames' ran the rule twice and reported (and counted)
    # each finding twice, '--shapes jawOpen,jawOpen' drew the shape twice and called the heat map an RMS
    # over 2 shapes
    names = list(dict.fromkeys(name.strip() for item in items for name in item.split(",") if name.strip()))
    if not names:
        raise OptionError(f"{what} {value!r} names no {noun}", fix=fix)
    return names
