"""docs/math.md maps paper equations to functions: every function named for a numbered equation (or
algorithm) says in its docstring which paper and which equation it implements."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

PAGE = Path(__file__).resolve().parents[1] / "docs" / "math.md"
AUTHORS = ("Menzel", "Zell", "Sumner", "Li", "Hable")


def _resolve(dotted: str):
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        for attr in parts[cut:]:
            obj = getattr(obj, attr)
        return obj
    raise ImportError(dotted)


def equation_rows() -> list[tuple[str, str, str]]:
    """(paper author, equation cell, first function) for every table row whose first cell names a numbered
    equation or algorithm."""
    rows, author = [], None
    for line in PAGE.read_text().splitlines():
        if line.startswith("## "):
            author = next((a for a in AUTHORS if a in line), None)
        cells = [c.strip() for c in line.strip().strip("|").split("|")] if line.startswith("|") else []
        if len(cells) < 3 or not re.search(r"^(\w+ (& \w+ |et al\. ))?(eqs?\.|Algorithm)\s*\d", cells[0]):
            continue
        functions = re.findall(r"`(usdface(?:\.\w+)+)`", cells[-1])
        row_author = next((a for a in AUTHORS if a in cells[0]), author)
        rows.append((row_author, cells[0], functions[0]))
    return rows


def test_math_page_has_equation_rows():
    if not PAGE.exists():
        pytest.skip("docs/math.md not present")
    rows = equation_rows()
    assert len(rows) >= 15 and all(author for author, _, _ in rows)


@pytest.mark.parametrize("author, equation, function", equation_rows() if PAGE.exists() else [])
def test_docstring_names_paper_and_equation(author, equation, function):
    doc = " ".join((_resolve(function).__doc__ or "").split())
    number = re.search(r"(?:eqs?\.|Algorithm)\s*(\d+)", equation).group(1)
    assert author in doc, f"{function}: docstring does not name {author}"
    assert number in cited_numbers(doc), f"{function}: docstring does not name {equation}"


def cited_numbers(doc: str) -> set[str]:
    """Equation / algorithm numbers a docstring cites: ``eq. 3``, ``eqs. (1)+(2)``, ``eqs. (3)-(5)``,
    ``Eqs. 5a-c``, ``Algorithm 1`` (ranges expanded)."""
    found = set()
    for span in re.findall(r"(?:[Ee]qs?\.|Algorithm)\s*([()\d\sa-c+,\-]+)", doc):
        found.update(re.findall(r"\d+", span))
        for lo, hi in re.findall(r"(\d+)\)?\s*-\s*\(?(\d+)", span):
            found.update(str(k) for k in range(int(lo), int(hi) + 1))
    return found
