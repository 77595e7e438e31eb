"""Defects found by a technical director's trial (session 29): the retarget map, batch options, docs."""

from __future__ import annotations

from pathlib import Path

DOCS = Path(__file__).resolve().parents[1] / "docs"


def test_doc_table_rows_stay_in_their_table():
    """A table row after a paragraph is no table row: personalize.md's `--dry-run` and `--force` rows came
    after the paragraph that followed the options table, and rendered as a line of pipes and text."""
    for page in sorted(DOCS.glob("*.md")):
        lines = page.read_text().splitlines()
        fenced = False
        for i, line in enumerate(lines):
            if line.startswith("```"):
                fenced = not fenced
            if fenced or not line.startswith("|") or i == 0:
                continue
            assert lines[i - 1].startswith("|") or (i + 1 < len(lines) and lines[i + 1].startswith("|---")), (
                f"{page.name}:{i + 1}: a table row outside a table: {line[:60]}")
