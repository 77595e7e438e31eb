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


def _row(section: str, equation: str) -> str:
    """The 'meaning' cell of the row ``equation`` in the section whose heading contains ``section``."""
    current = None
    for line in PAGE.read_text().splitlines():
        if line.startswith("## "):
            current = line
        cells = [c.strip() for c in line.strip().strip("|").split("|")] if line.startswith("|") else []
        if current and section in current and cells and cells[0] == equation:
            return cells[1]
    raise AssertionError(f"no row {equation!r} under a heading with {section!r}")


def _norm(x):
    import numpy as np

    return np.linalg.norm(x, axis=-1)


# the formula each row states (verbatim), and that formula written in numpy: the page must state it and the
# function must compute it
FORMULAS = {
    ("Menzel", "eq. 3"): (
        "(D_j)_vv = min(max_k ‖T_j(k)‖ / ‖T_j(v)‖, clamp)",
        "usdface.personalize.fit.regularization_weights",
        lambda T, clamp=1e5: __import__("numpy").minimum(
            _norm(T).max(axis=1, keepdims=True) / _norm(T), clamp)),
    ("Zell", "eq. 1"): (
        "q_n^k = (1 − α) r_n^k + α l_n",
        "usdface.landmarks.candidates.landmark_quality",
        lambda r, l, alpha: (1 - alpha) * r + alpha * l[None, :]),
    ("Zell", "eq. 2"): (
        "r_n^k = ‖Δv_n^k‖ / max_m ‖Δv_m^k‖",
        "usdface.landmarks.candidates.relative_displacement",
        lambda mag: mag / mag.max(axis=1, keepdims=True)),
}


@pytest.mark.parametrize("key", list(FORMULAS))
def test_stated_formula_is_what_the_function_computes(key):
    import numpy as np

    if not PAGE.exists():
        pytest.skip("docs/math.md not present")
    text, function, formula = FORMULAS[key]
    assert text in _row(*key), f"docs/math.md {key}: the row does not state {text!r}"
    fn = _resolve(function)
    rng = np.random.default_rng(0)
    if key == ("Menzel", "eq. 3"):
        T = rng.normal(size=(3, 20, 3)) * 1e-3
        assert np.allclose(fn(T), formula(T), rtol=1e-12)
    elif key == ("Zell", "eq. 1"):
        r, vis = rng.uniform(size=(4, 15)), rng.uniform(size=15)
        for alpha in (0.0, 0.2, 0.5, 0.9):
            assert np.allclose(fn(r, vis, alpha), formula(r, vis, alpha), rtol=1e-12)
    else:
        mag = rng.uniform(0.1, 1.0, size=(4, 15))
        assert np.allclose(fn(mag), formula(mag), rtol=1e-12)
