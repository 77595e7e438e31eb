"""The command line itself: ``python -m usdface`` and ``usdface`` alone, unknown options named by their
command or action, ``--debug`` after the command, option values and output extensions checked before any
work."""

from __future__ import annotations

from pathlib import Path

import pytest
from cli_helpers import _usdface

import usdface.io  # noqa: F401  (registers the schemas before a test opens a stage)
from usdface.cli import main

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


def test_python_dash_m_usdface_runs_the_cli():
    """``python -m usdface`` (a venv without the console script on PATH) is the ``usdface`` command."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "usdface", "--version"], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0 and proc.stdout.startswith("usdface "), proc.stderr


def test_unknown_options_are_named_by_their_command(capsys):
    """``usdface export X --json`` said ``usdface: error: unrecognized arguments``; the command's own parser
    says it now, and ``-q`` exists on every command that prints progress."""
    from usdface.cli import main

    with pytest.raises(SystemExit) as exit_:
        main(["export", str(A), "--bogus"])
    assert exit_.value.code == 2
    assert "usdface export: error: unrecognized arguments: --bogus" in capsys.readouterr().err
    for command in ("review", "export", "batch"):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        assert "--quiet" in capsys.readouterr().out


@pytest.mark.parametrize("argv", [["capture", "import", "cap", "-o", "c.usda", "--json"],
                                  ["anim", "import", "t.csv", "-o", "t.usda", "--bogus"]])
def test_unknown_options_of_an_action_are_named_by_the_action(argv, capsys):
    """A user trial: 'capture import DIR -o c.usda --json' said "usdface capture: error: unrecognized
    arguments: --json (see 'usdface capture --help')", a help page that lists only the actions."""
    from usdface.cli import main

    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    name, err = " ".join(argv[:2]), capsys.readouterr().err
    assert f"usdface {name}: error: unrecognized arguments" in err and f"see 'usdface {name} --help'" in err


@pytest.mark.parametrize("args", [["anim", "import", "{d}/missing.csv", "-o", "{d}/x.usda"],
                                  ["capture", "select", "{d}/missing.csv", "-o", "{d}/x.usda"]])
def test_an_actions_error_names_the_command_as_typed(tmp_path, capsys, args):
    """Errors of the commands with actions said 'usdface anim: error' for 'usdface anim import': they name
    the command as typed."""
    argv = [a.format(d=tmp_path) for a in args]
    assert main(argv) == 2
    assert capsys.readouterr().err.startswith(f"usdface {argv[0]} {argv[1]}: error: "), argv


@pytest.mark.parametrize("argv,needle", [
    (["capture", "import", "{S}/capture.usda", "-o", "c.obj"], "as .usda/.usdc/.usd or as a folder"),
    (["render", "{S}/avatar.usda", "-o", "x.jpg"], "must end in .png"),
    (["landmarks", "{S}/avatar.usda", "--plot", "x.jpg"], "must end in .png"),
])
def test_output_extension_is_checked(tmp_path, monkeypatch, capfd, argv, needle):
    monkeypatch.chdir(tmp_path)
    code = main([a.replace("{S}", str(SAMPLES)) for a in argv])
    assert code == 2 and needle in capfd.readouterr().err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv", [
    ["anim", "import", "t.csv", "-o", "t.usda", "--timecode-rate", "0"],
    ["anim", "import", "t.csv", "-o", "t.usda", "--timecode-rate", "-60"],
    ["anim", "import", "t.csv", "-o", "t.usda", "--timecode-rate", "nan"],
    ["retarget", "a.usda", "c.usda", "-o", "m.json", "--mu", "nan"],
    ["personalize", "a.usda", "c.usda", "--mu", "-1"],
    ["personalize", "a.usda", "c.usda", "--falloff", "nan"],
    ["fit", "c.usda", "-o", "r.usda", "--reg", "inf"],
    ["landmarks", "a.usda", "--camera", "0,nan,1"],
    ["capture", "select", "t.usda", "--threshold", "nan"],
])
def test_option_values_are_validated(tmp_path, monkeypatch, capfd, argv):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capfd.readouterr().err.strip()
    assert exc.value.code == 2 and len(err.splitlines()) == 1 and "argument --" in err
    assert list(tmp_path.iterdir()) == []


def test_debug_after_the_command_shows_the_traceback(tmp_path, capsys):
    """User trial: ``usdface personalize ... --debug`` (added to the failed command line) said
    'unrecognized arguments: --debug'; it worked only as ``usdface --debug personalize``. Both work now,
    in sub-commands too; without it the one-line error stays."""
    from usdface.cli import main
    from usdface.errors import InputFileError

    line = ["personalize", str(tmp_path / "nothere.usda"), str(tmp_path / "c.usda"),
            "-o", str(tmp_path / "o.usda")]
    assert main(line) == 2 and "avatar not found" in capsys.readouterr().err
    for argv in ([*line, "--debug"], ["--debug", *line]):
        with pytest.raises(InputFileError, match="avatar not found"):
            main(argv)
    with pytest.raises(InputFileError, match="capture not found"):
        main(["capture", "import", str(tmp_path / "none"), "-o", str(tmp_path / "c.usda"), "--debug"])


def test_usdface_alone_prints_its_usage_on_stderr_and_exits_2(tmp_path, capsys):
    """``usdface`` without a command printed the help on stdout and exited 0, so a script's ``usdface $CMD``
    with ``$CMD`` unset passed; now a usage error (exit 2, as ``usdface capture`` alone); ``--help``: 0."""
    from usdface.cli import main

    with pytest.raises(SystemExit) as code:
        main([])
    out, err = capsys.readouterr()
    assert code.value.code == 2 and out == ""
    assert err.startswith("usage: usdface ") and "required: COMMAND (see 'usdface --help')" in err
    res = _usdface(cwd=tmp_path)
    assert (res.returncode, res.stdout) == (2, "") and "usage: usdface " in res.stderr, res.stderr
    assert "Traceback" not in res.stderr
    res = _usdface("--help", cwd=tmp_path)
    assert res.returncode == 0 and "personalize" in res.stdout and res.stderr == ""


def test_help_pages_say_what_the_options_take(capsys):
    """'capture import --help' said '-o: output .usda/.usdc' (it writes a capture folder too) and 'fit
    --help' '--reg ... or a number' (0 and below are refused)."""
    for argv, said in ((["capture", "import", "--help"], "a capture folder"),
                       (["fit", "--help"], "or a number > 0"),
                       (["personalize", "--help"], "or a number > 0")):
        with pytest.raises(SystemExit):
            main(argv)
        assert said in " ".join(capsys.readouterr().out.split()), argv


@pytest.mark.parametrize("argv", [
    ["capture", "import", "CAP", "-o", ""],
    ["personalize", "a.usda", "c.usda", "-o", ""],
    ["personalize", "a.usda", "c.usda", "--output="],
    ["export", "p.usda", "--obj-dir", ""],
    ["personalize", "", "c.usda"],
])
def test_an_empty_argument_is_a_usage_error(tmp_path, monkeypatch, capfd, argv):
    """An unset variable in a job template (``-o "$OUT"``) passes an empty value, which Python reads as the
    current folder: ``capture import CAP -o ""`` wrote the capture's OBJs and sub-folders into the current
    folder, ``personalize -o ""`` wrote its default output there. Refused before anything is read."""
    cap = tmp_path / "in" / "CAP"
    cap.mkdir(parents=True)
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    with pytest.raises(SystemExit) as exc:
        main([str(cap) if a == "CAP" else a for a in argv])
    err = capfd.readouterr().err.strip()
    assert exc.value.code == 2 and len(err.splitlines()) == 1, err
    assert "empty" in err and "unset variable" in err, err
    assert list(work.iterdir()) == []


def _commands_as_typed() -> list[list[str]]:
    """Every command and action of the parser (``["personalize"]``, ``["capture", "import"]``, ...)."""
    import argparse

    from usdface.cli import build_parser

    def walk(parser, words):
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs:
            return [words]
        return [w for name, p in subs[0].choices.items() for w in walk(p, words + [name])]

    return walk(build_parser(), [])


@pytest.mark.parametrize("command", _commands_as_typed(), ids=" ".join)
def test_an_unknown_option_is_said_before_missing_arguments(command, tmp_path, monkeypatch, capsys):
    """``usdface personalize --hlep`` said 'the following arguments are required: avatar, capture' (argparse
    checks the required arguments inside the parse, the unknown ones after it): the misspelt flag, the
    mistake, went unsaid. Now every command and action says the unknown option first, with the option it
    most looks like, one line, exit status 2, as argparse."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        main([*command, "--hlep"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and len(err.strip().splitlines()) == 1, err
    name = " ".join(command)
    said = f"usdface {name}: error: unrecognized arguments: --hlep (did you mean --help?)"
    assert err.startswith(said), err
    assert "required" not in err and f"see 'usdface {name} --help'" in err, err
    assert list(tmp_path.iterdir()) == []


def test_missing_arguments_are_still_said_without_an_unknown_option(capsys):
    """Without an unknown option, argparse's own message stands (and a value that only looks like an
    option, a negative number, is not called unknown)."""
    for argv, said in ((["personalize"], "the following arguments are required: avatar, capture"),
                       (["personalize", "a.usda"], "the following arguments are required: capture"),
                       (["render", "a.usda", "-1"], "the following arguments are required: -o/--output"),
                       (["capture"], "the following arguments are required: ACTION")):
        with pytest.raises(SystemExit) as exit_:
            main(argv)
        assert exit_.value.code == 2 and said in capsys.readouterr().err, argv


def test_an_unknown_option_is_said_first_by_the_program_and_in_json(tmp_path):
    """As a user runs it: the ``usdface`` program, and ``--json``'s error document."""
    import json

    proc = _usdface("personalize", "--hlep", cwd=tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.strip() == ("usdface personalize: error: unrecognized arguments: --hlep (did you mean "
                                   "--help?) (see 'usdface personalize --help')"), proc.stderr
    proc = _usdface("personalize", "--hlep", "--forse", "--json", cwd=tmp_path)
    doc = json.loads(proc.stdout)["error"]
    assert proc.returncode == 2 and doc["type"] == "UsageError", proc.stdout
    assert doc["message"] == ("unrecognized arguments: --hlep --forse (--hlep: did you mean --help?; "
                              "--forse: did you mean --force?)"), doc


@pytest.mark.parametrize("argv, close", [
    (["personalise", "a.usda", "b.usda"], "'personalize'"),       # the British spelling, a command
    (["capture", "improt", "x"], "'import'"),                     # an action
    (["fit", "c.usda", "--method", "menzle"], "'menzel'"),        # an option's choices
])
def test_a_misspelt_choice_is_told_the_one_it_looks_like(argv, close, tmp_path, monkeypatch, capsys):
    """A user trial: ``usdface personalise`` was told the fourteen commands and not which one it meant
    (argparse before 3.14 lists the choices, with no "did you mean"); nothing is read or written."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and "invalid choice" in err, err
    assert f"did you mean {close}?" in err and err.count("did you mean") == 1, err
    assert list(tmp_path.iterdir()) == []


def test_a_choice_like_none_gets_no_guess(capsys):
    """A value like no choice is refused with the choices alone (no guess that would mislead)."""
    with pytest.raises(SystemExit):
        main(["xyzzy"])
    err = capsys.readouterr().err
    assert "invalid choice: 'xyzzy'" in err and "did you mean" not in err, err


def test_an_unknown_option_before_the_command_is_said_first(tmp_path, monkeypatch, capsys):
    """``usdface --hlep personalize`` was told the command's missing arguments (argparse sets an unknown
    option of ``usdface`` aside and parses on); usdface's own options and their abbreviations still work."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        main(["--hlep", "personalize"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.strip() == (
        "usdface: error: unrecognized arguments: --hlep (did you mean --help?) (see 'usdface --help')"), err
    assert main(["--deb", "check", str(A), "-q"]) == 0           # --debug, abbreviated as argparse allows
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:
        main(["--version", "check"])
    assert exit_.value.code == 0 and "usdface" in capsys.readouterr().out
    assert list(tmp_path.iterdir()) == []


def test_option_value_types_at_their_boundaries():
    """Each argparse type of ``commands/options.py`` at the edges of what it takes: 0 and 1 for a unit
    value, 0 for a non-negative one (not for a positive one), the lowest whole number, three numbers for a
    vector, keywords as given; inf and NaN nowhere."""
    import argparse

    from usdface.commands import options as o

    def refused(fn, text):
        with pytest.raises(argparse.ArgumentTypeError):
            fn(text)

    assert o.unit_float("0") == 0.0 and o.unit_float("1") == 1.0
    refused(o.unit_float, "1.0000001")
    refused(o.unit_float, "-1e-9")
    assert o.nonnegative_float("0") == 0.0
    refused(o.nonnegative_float, "-1e-300")
    assert o.positive_float("1e-300") == 1e-300
    refused(o.positive_float, "0")
    assert o.positive_int("1") == 1 and o.nonnegative_int("0") == 0
    refused(o.positive_int, "0")
    refused(o.nonnegative_int, "-1")
    assert o.vector3("1,2,3") == [1.0, 2.0, 3.0]
    refused(o.vector3, "1,2")
    refused(o.vector3, "1,2,3,4")
    for fn in (o.finite_float, o.weight_bound, o.positive_float, o.nonnegative_float, o.unit_float):
        for bad in ("inf", "-inf", "nan"):
            refused(fn, bad)
    assert o.mu_value("auto") == "auto" and o.reg_value("paper") == "paper" and o.mu_value("2") == 2.0
    refused(o.mu_value, "0")


def test_help_lists_the_commands_in_the_readmes_order():
    """A TD's trial (stop 54): ``usdface --help`` listed the commands in another order than README's command
    table. One order, a new user's: personalize and what follows it (review, export, batch), the inputs
    (capture, anim), looking at files (inspect, check), the stages alone (fit, evaluate, retarget,
    landmarks), pictures and the sample."""
    import re

    from usdface.cli import build_parser

    table = re.findall(r"^\| `usdface ([a-z]+)", (ROOT / "README.md").read_text(), re.MULTILINE)
    readme = list(dict.fromkeys(table))
    actions = [a for a in build_parser()._actions if a.dest == "command"]
    listed = [choice.dest for choice in actions[0]._choices_actions]
    assert listed == readme
