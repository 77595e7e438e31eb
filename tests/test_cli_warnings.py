"""Warnings as the CLI says them: once, on stderr (never before a ``--json`` document on stdout), and carried
in the ``--json`` document, the readers' included."""

from __future__ import annotations

from pathlib import Path

from input_helpers import _capture

from usdface.cli import main

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


def test_json_documents_stay_parseable_when_something_warns(tmp_path, capsys, monkeypatch):
    """A warning line went to stdout before the ``--json`` document (seen with an ImportWarning of six's
    importer under Dask, and any library warning): stdout is the document alone, warnings go to stderr."""
    import json

    import usdface.personalize.api as fit_api
    from usdface.cli import main

    real = fit_api.check_capture
    monkeypatch.setattr(fit_api, "check_capture", lambda c, **kw: real(c, **kw) + ["a library warning"])
    assert main(["fit", str(C), "-o", str(tmp_path / "r.usda"), "--reg", "0.01", "--json"]) == 0
    out, err = capsys.readouterr()
    doc = json.loads(out)
    assert doc["ok"] and "a library warning" in doc["warnings"] and "warning: a library warning" in err
    assert main(["fit", str(C), "-o", str(tmp_path / "s.usda"), "--reg", "0.01", "-q"]) == 0
    assert "warning: a library warning" in capsys.readouterr().out       # text mode: as before


def test_json_documents_carry_the_readers_warnings(tmp_path, capsys):
    """User trial: `fit --json` listed the fit's own warnings only; a capture reader's (a frame weight for a
    shape the template lacks) went to stderr alone, so a pipeline reading the document never saw it."""
    import json

    from usdface.api import write_capture

    folder = tmp_path / "cap"
    write_capture(_capture(), folder)
    first = sorted((folder / "train").glob("*.json"))[0]
    data = json.loads(first.read_text())
    data["blendShapes"]["notAShape"] = 0.5
    first.write_text(json.dumps(data))
    for argv in (["fit", str(folder), "-o", str(tmp_path / "r.usda"), "--method", "dt", "--json"],
                 ["personalize", str(A), str(folder), "-o", str(tmp_path / "p.usda"), "--method", "dt",
                  "--json"]):
        assert main(argv) == 0
        doc = json.loads(capsys.readouterr().out)
        assert any("notAShape" in w for w in doc["warnings"]), doc["warnings"]


def test_warning_said_once(tmp_path, monkeypatch, capfd):
    """The same warning printed twice: a raw UserWarning and a 'warning:' line."""
    import warnings

    from usdface.commands import reset_warnings, say_warning

    reset_warnings()
    with warnings.catch_warnings():
        warnings.showwarning = lambda message, *_a, **_k: say_warning(message)
        warnings.warn("same text", UserWarning, stacklevel=1)
        say_warning("same text")
    out = capfd.readouterr()
    assert out.out.count("same text") == 1 and "UserWarning" not in out.err


def test_a_home_folder_matplotlib_cannot_write_adds_no_lines(tmp_path):
    """A farm's render user whose home folder cannot be written: every ``render`` (and ``evaluate --plot``,
    ``landmarks --plot``) printed matplotlib's two lines ``mkdir -p failed for path ~/.config/matplotlib``
    and ``Matplotlib created a temporary cache directory ... set the MPLCONFIGDIR environment variable``,
    which ``-q`` did not silence. The program gives matplotlib a private folder for the run, removed at
    exit. (The home folder is a regular file here: root, who runs CI, may write into read-only folders.)"""
    import os
    import subprocess
    import sys

    from cli_helpers import _env

    home = tmp_path / "home"
    home.write_text("not a folder")
    temp = tmp_path / "tmp"
    temp.mkdir()
    env = {k: v for k, v in _env().items() if k not in ("MPLCONFIGDIR", "XDG_CONFIG_HOME", "XDG_CACHE_HOME")}
    env.update(HOME=str(home), TMPDIR=str(temp))
    res = subprocess.run([sys.executable, "-c", "import sys; from usdface.cli import main; sys.exit(main())",
                          "render", str(SAMPLES / "avatar.usda"), "-o", str(tmp_path / "a.png"), "-q"],
                         capture_output=True, text=True, env=env, timeout=600)
    assert res.returncode == 0, res.stderr
    assert "matplotlib" not in res.stderr.lower() and "MPLCONFIGDIR" not in res.stderr, res.stderr
    assert (tmp_path / "a.png").is_file() and os.listdir(temp) == []
