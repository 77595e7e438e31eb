"""``usdface personalize ... --review``: the layer and its review page come as a pair (issue: stop 38's CLI
trial). ``--json --review`` wrote the layer and no page (the JSON report returned before the page), and a
page that failed after the layer (Ctrl-C, a full disk) left the new layer behind, so the rerun was refused
(``output layer exists``)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from wfutil import ROOT, assert_valid_usd, no_temp_left, run

#: A prologue that makes the review page's build send SIGINT (Ctrl-C) to its own process: the layer is
#: written by then (deterministic, as tests/test_signals.py's prologues).
SIGINT_IN_THE_PAGE = ("import os, signal, sys\n"
                      "import usdface.review.page as page\n"
                      "def build_review_html(*a, **k):\n"
                      "    assert os.path.exists(sys.argv[-1]), 'the layer is written first'\n"
                      "    os.kill(os.getpid(), signal.SIGINT)\n"
                      "page.build_review_html = build_review_html\n"
                      "from usdface.cli import main\n")


def _interactive_signals() -> None:
    """In the child: SIGINT at its default, as a terminal's foreground job has it. A suite started under a
    background job or nohup (as CI starts it) passes SIGINT on ignored, and Python then installs no
    KeyboardInterrupt handler: the page's Ctrl-C would not arrive (tests/test_signals.py does the same)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_json_review_writes_the_page_and_names_it(sample_set, tmp_path):
    """``--json --review``: the page is written beside the layer and the document names it (``review``)."""
    proc = run("personalize", sample_set / "avatar.usda", sample_set / "capture.usda", "-o", "p.usda",
               "--review", "--json", cwd=tmp_path)
    doc = json.loads(proc.stdout)
    page = tmp_path / "p.review.html"
    assert doc["ok"] and doc["review"] == str(page) and doc["output"] == str(tmp_path / "p.usda")
    assert page.read_text(encoding="utf-8").lstrip().lower().startswith("<!doctype html")
    assert_valid_usd(tmp_path / "p.usda", checked=False)


def test_a_dry_run_with_review_names_the_page_it_would_write(sample_set, tmp_path):
    """``--dry-run --json --review`` said ``"review": null`` and nothing of the page: the page a real run
    would write is named beside the layer's ``would_write`` (``would_write_review``), and the text says it;
    a page that exists makes it a refusal (null, exit 1). Nothing is written."""
    args = ("personalize", sample_set / "avatar.usda", sample_set / "capture.usda", "-o", "p.usda",
            "--review", "--dry-run", "-q")
    doc = json.loads(run(*args, "--json", cwd=tmp_path).stdout)
    assert doc["ok"] and doc["review"] is None and doc["output_refused"] is None
    assert doc["would_write"] == "p.usda" and doc["would_write_review"] == "p.review.html"
    assert "would write p.usda and its review page p.review.html" in run(*args, cwd=tmp_path).stdout
    assert sorted(os.listdir(tmp_path)) == []
    (tmp_path / "p.review.html").write_text("<p>mine</p>")
    proc = run(*args, "--json", cwd=tmp_path, ok=False)
    doc = json.loads(proc.stdout)
    assert proc.returncode == 1 and doc["would_write_review"] is None and "review page exists" in \
        doc["output_refused"]


def test_a_review_page_stopped_takes_the_new_layer_and_its_folder(sample_set, tmp_path):
    """Ctrl-C while the page is built: exit status 130, and neither the layer nor the folder made for it is
    left (the output is the pair); a rerun is not refused."""
    out = tmp_path / "new" / "deeper" / "p.usda"
    argv = ["usdface", "personalize", str(sample_set / "avatar.usda"), str(sample_set / "capture.usda"),
            "--review", "-q", "-o", str(out)]
    proc = subprocess.run([sys.executable, "-c", SIGINT_IN_THE_PAGE + f"sys.argv = {argv!r}\n"
                           "sys.exit(main())\n"], cwd=tmp_path, capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)},
                          preexec_fn=_interactive_signals)
    assert proc.returncode == 130, proc.stderr
    assert "interrupted" in proc.stderr and "Traceback" not in proc.stderr
    assert sorted(os.listdir(tmp_path)) == [], list(Path(tmp_path).rglob("*"))
    run(*argv[1:], cwd=tmp_path)
    assert out.exists() and out.with_name("p.review.html").exists()
    no_temp_left(tmp_path)


def test_a_review_page_stopped_leaves_a_layer_it_replaced(sample_set, tmp_path):
    """With ``--force`` over an earlier layer, the run replaced it before the page failed: the new layer
    stays (its old version is gone either way, as export's outputs), and no page appears."""
    run("personalize", sample_set / "avatar.usda", sample_set / "capture.usda", "-o", "p.usda", "-q",
        cwd=tmp_path)
    argv = ["usdface", "personalize", str(sample_set / "avatar.usda"), str(sample_set / "capture.usda"),
            "--review", "--force", "-q", "-o", "p.usda"]
    proc = subprocess.run([sys.executable, "-c", SIGINT_IN_THE_PAGE + f"sys.argv = {argv!r}\n"
                           "sys.exit(main())\n"], cwd=tmp_path, capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)},
                          preexec_fn=_interactive_signals)
    assert proc.returncode == 130, proc.stderr
    assert sorted(os.listdir(tmp_path)) == ["p.usda"]
    assert_valid_usd(tmp_path / "p.usda", checked=False)
