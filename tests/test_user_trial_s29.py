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


def test_weight_bounds_as_text_are_refused_with_the_manifest_spelling():
    """A manifest cell or ``--set weight_bounds=01`` reached the check as the string "01", whose characters
    passed as the bounds (0, 1) (and "0,2" was refused with a fix, ``(0, 1)`` / ``None``, that a manifest
    cannot spell either): a string is refused, and the fix names the JSON a manifest takes."""
    import pytest

    from usdface import api
    from usdface.errors import OptionError

    for text in ("01", "0,2", "(0, 2)", "None"):
        with pytest.raises(OptionError, match=r"bad weight bounds") as err:
            api.check_personalize_options(weight_bounds=text)
        assert "[0, 1] in a batch manifest" in str(err.value) and "null in a batch manifest" in str(err.value)
    api.check_personalize_options(weight_bounds=[0, 2])
    api.check_personalize_options(weight_bounds=None)


def test_support_as_text_is_refused_before_any_work():
    """``--set support=01`` passed the batch's preflight (the string's two characters as low and high) and
    the item failed after its fit with ``UFuncTypeError: ufunc 'subtract' did not contain a loop``."""
    import pytest

    from usdface import api
    from usdface.errors import UsdFaceError

    for text in ("01", "ab"):
        with pytest.raises(UsdFaceError, match=r"bad support") as err:
            api.check_personalize_options(support=text)
        assert "[0.01, 0.03] in a batch manifest" in str(err.value)
    api.check_personalize_options(support=[0.01, 0.03])


def test_a_non_usd_file_where_usd_is_expected_is_named_as_such(tmp_path, capsys):
    """The retarget map (``map.json``) given to ``render --heatmap``, ``inspect`` or ``check``, or an exported
    OBJ to ``export``, said USD's "Cannot determine file format for @map.json@ (fix: check that it is a
    valid USD layer (usdcat FILE))": the message names the file's type and asks for the USD file."""
    from usdface.cli import main

    bad = tmp_path / "map.json"
    bad.write_text('{"format": "usdface.retarget/1"}')
    obj = tmp_path / "neutral.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    for args in (["inspect", str(bad)], ["check", str(bad)], ["export", str(obj), "--gltf",
                                                                 str(tmp_path / "o.glb")]):
        assert main(args) == 2
        err = capsys.readouterr().err
        assert "Cannot determine file format" not in err and "where a USD" in err and "USD USD" not in err
        assert "pass the USD file here" in err
    assert not (tmp_path / "o.glb").exists()


def test_a_batch_row_with_dry_run_is_refused(tmp_path):
    """A manifest row (or ``--set``) with ``dry_run`` true wrote nothing and the report counted the item
    ``done`` (with its avatars per minute); refused before any work."""
    import json

    import pytest

    from usdface import api
    from usdface.errors import InputFileError

    samples = Path(__file__).resolve().parents[1] / "sample_assets"
    manifest = tmp_path / "m.json"
    manifest.write_text(json.dumps([{"avatar": str(samples / "avatar.usda"),
                                     "capture": str(samples / "capture.usda"), "output": "a.usda",
                                     "dry_run": True}]))
    with pytest.raises(InputFileError, match="item 1: dry_run writes no output") as err:
        api.personalize_batch(manifest, jobs=1)
    assert "--dry-run" in err.value.fix
    assert not (tmp_path / "m.report.json").exists() and not (tmp_path / "a.usda").exists()


def test_dry_run_help_says_the_correspondence_cache_is_written(capsys):
    """``personalize --dry-run --correspondence c.npz`` writes the cache (by design: the real run reuses it)
    while the help and the docs said "write nothing"."""
    import pytest

    from usdface.cli import main

    with pytest.raises(SystemExit):
        main(["personalize", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    dry = text[text.index("--dry-run compute"):][:200]
    assert "write nothing" not in dry and "--correspondence cache is still written" in dry
    assert "write nothing" not in (DOCS / "troubleshooting.md").read_text().split("--dry-run")[1][:80]


def test_an_empirical_layout_of_another_mesh_names_its_file(tmp_path, capsys):
    """``landmarks --evaluate --empirical vertex_indices.json`` with indices beyond the mesh said "empirical
    layout indices out of range ..." without naming the file (the user gives two files and a mesh)."""
    from usdface.cli import main

    samples = Path(__file__).resolve().parents[1] / "sample_assets"
    layout = tmp_path / "vertex_indices.json"
    layout.write_text("[1, 2, 99999]")
    take = tmp_path / "take.csv"
    take.write_text("Timecode,BlendShapeCount,JawOpen\n00:00:00:00.000,1,0.5\n")
    assert main(["landmarks", str(samples / "avatar.usda"), "--evaluate", "--takes", str(take),
                 "--empirical", str(layout), "-q"]) == 2
    err = capsys.readouterr().err
    assert f"{layout}, prim /Avatar/Head: empirical layout indices out of range" in err
