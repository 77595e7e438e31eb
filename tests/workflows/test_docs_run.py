"""The docs paste and run as written (issue 11): the Python snippets of README.md, docs/index.md,
docs/api.md and docs/schemas.md, and the getting-started shell commands of docs/index.md, in a fresh
temporary folder holding only what they name (made with ``usdface sample``)."""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from wfutil import ROOT, assert_valid_usd, run, usdface_cmd


def blocks(page: Path, lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", page.read_text(encoding="utf-8"), flags=re.S)


@pytest.fixture(scope="module")
def doc_folder(sample_set, tmp_path_factory) -> Path:
    """What the snippets refer to: ``sample_assets/`` (as in the repository root), ``avatar.usdc``,
    ``capture/``, an empty ``out/``."""
    from pxr import Usd

    d = tmp_path_factory.mktemp("docs")
    (d / "sample_assets").mkdir()
    for name in ("avatar.usda", "capture.usda", "truth"):
        src = sample_set / name
        (shutil.copytree if src.is_dir() else shutil.copy)(src, d / "sample_assets" / name)
    Usd.Stage.Open(str(sample_set / "avatar.usda")).Export(str(d / "avatar.usdc"))
    shutil.copytree(sample_set / "capture", d / "capture")
    return d


PAGES = ("README.md", "docs/index.md", "docs/api.md", "docs/schemas.md")
SNIPPETS = [(page, i) for page in PAGES for i in range(len(blocks(ROOT / page, "python")))]
#: What a snippet prints, where the page says what it gives (a comment beside the print).
PRINTS = {("docs/schemas.md", 0): "0.5\n"}


def test_pages_have_python_snippets():
    assert {p for p, _ in SNIPPETS} == set(PAGES)


@pytest.mark.parametrize("page,index", SNIPPETS, ids=[f"{p}#{i}" for p, i in SNIPPETS])
def test_python_snippet_runs_as_written(doc_folder, tmp_path, page, index):
    code = blocks(ROOT / page, "python")[index]
    work = tmp_path / "cwd"
    shutil.copytree(doc_folder, work)
    proc = subprocess.run([sys.executable, "-c", code], cwd=work, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, f"{page} snippet {index} failed:\n{code}\n{proc.stderr}"
    assert "Traceback" not in proc.stderr
    if (page, index) in PRINTS:
        assert proc.stdout == PRINTS[page, index], proc.stdout
    for out in work.rglob("*.usda"):
        if out.name.startswith("person") or out.parent.name == "out":
            assert_valid_usd(out)


ALL_SNIPPETS = [(page, i, code) for page in ["README.md", *sorted(f"docs/{p.name}" for p in
                                                                  (ROOT / "docs").glob("*.md"))]
                for i, code in enumerate(blocks(ROOT / page, "python"))]


def _undefined_names(code: str) -> list[str]:
    """The names ``code`` reads but neither imports, defines nor gets from builtins."""
    import ast
    import builtins

    tree = ast.parse(code)
    defined = set(dir(builtins))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import | ast.ImportFrom):
            defined.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            defined.add(node.name)
        elif isinstance(node, ast.Name) and not isinstance(node.ctx, ast.Load):
            defined.add(node.id)
        elif isinstance(node, ast.arg):
            defined.add(node.arg)
        elif isinstance(node, ast.ExceptHandler) and node.name:
            defined.add(node.name)
    return sorted({n.id for n in ast.walk(tree) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Load)}
                  - defined)


@pytest.mark.parametrize("page,index,code", ALL_SNIPPETS, ids=[f"{p}#{i}" for p, i, _ in ALL_SNIPPETS])
def test_every_python_snippet_imports_what_it_uses(page, index, code):
    """Every page's Python snippets (also those that need data or a host to run: pyblish, a take) parse and
    import every name they use: docs/pipeline.md's "personalize with a take" used ``usdface`` without
    ``import usdface``."""
    assert _undefined_names(code) == [], f"{page} snippet {index}:\n{code}"


def _getting_started() -> list[list[str]]:
    """The usdface commands of docs/index.md's getting-started block (comments stripped)."""
    text = (ROOT / "docs" / "index.md").read_text(encoding="utf-8")
    section = text[text.index("## Getting started"):]
    cmds = []
    for line in blocks_in(section)[0].splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            cmds.append(line)
    return cmds


def blocks_in(text: str) -> list[str]:
    return re.findall(r"```bash\n(.*?)```", text, flags=re.S)


def test_getting_started_commands_paste_and_run(tmp_path):
    """Run every line of the getting-started block in a fresh folder (``mkdir X && cd X`` followed; usdview,
    which usd-core does not ship, is only checked to be explained on the page)."""
    cwd = tmp_path
    ran = []
    for line in _getting_started():
        for part in (p.strip() for p in line.split("&&")):
            argv = shlex.split(part)
            if argv[0] == "mkdir":
                (cwd / argv[1]).mkdir()
            elif argv[0] == "cd":
                cwd = cwd / argv[1]
            elif argv[0] == "usdview":
                assert "usdview** is not part of `usd-core`" in (ROOT / "docs" / "index.md").read_text()
            else:
                assert argv[0] == "usdface", part
                run(*argv[1:], cwd=cwd)
                ran.append(argv[1])
    assert ran[:2] == ["sample", "check"] and "personalize" in ran
    assert_valid_usd(cwd / "person.usda")
    assert (cwd / "compare.png").read_bytes()[:4] == b"\x89PNG"


def test_readme_setup_command_personalizes(tmp_path):
    """README's set-up command 1 (after its install part): the personalize line as written, from a checkout
    root that holds sample_assets/."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    line = next(ln for ln in blocks_in(readme)[0].splitlines() if "usdface personalize" in ln)
    part = line.split("&&")[-1].strip()
    argv = shlex.split(part)
    assert argv[0].endswith("usdface")
    shutil.copytree(ROOT / "sample_assets", tmp_path / "sample_assets")
    run(*argv[1:], cwd=tmp_path)
    assert_valid_usd(tmp_path / "out" / "avatar_personalized.usda")
    assert usdface_cmd()
