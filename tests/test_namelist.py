"""usdface.namelist.name_list: names as one comma-separated string (the options) or a list (the API)."""

from __future__ import annotations

import pytest

from usdface.cli import main
from usdface.errors import OptionError
from usdface.namelist import name_list


@pytest.mark.parametrize("value, names", [
    ("ArkitNames", ["ArkitNames"]),
    ("ArkitNames,PointIndices", ["ArkitNames", "PointIndices"]),
    ("  ArkitNames ,  PointIndices  ", ["ArkitNames", "PointIndices"]),      # spaces around names
    ("ArkitNames,,PointIndices,", ["ArkitNames", "PointIndices"]),           # empty items dropped
    (["ArkitNames", " PointIndices"], ["ArkitNames", "PointIndices"]),       # a list where a string is usual
    (("dt", "ebfr,menzel"), ["dt", "ebfr", "menzel"]),                       # items comma-separated too
    ((n for n in ("dt", "menzel")), ["dt", "menzel"]),
    ("ArkitNames,PointIndices,ArkitNames", ["ArkitNames", "PointIndices"]),  # a repeat once, first place
    (["dt", "menzel,dt"], ["dt", "menzel"]),
    (None, None),                                                            # the caller's default
])
def test_names(value, names):
    assert name_list(value, "--rules", "rule", fix="name some") == names


@pytest.mark.parametrize("value", ["", ",", " , ", [], [""], [" , "]])
def test_naming_nothing_is_refused_with_the_fix(value):
    with pytest.raises(OptionError, match="--rules .* names no rule") as err:
        name_list(value, "--rules", "rule", fix="leave --rules out to run all")
    assert err.value.fix == "leave --rules out to run all"


@pytest.mark.parametrize("value", [3, b"dt,menzel", ["dt", 3], [["dt"]]])
def test_neither_a_string_nor_strings_is_refused(value):
    with pytest.raises(OptionError, match="methods takes a method name") as err:
        name_list(value, "methods", "method", fix="name some")
    assert "list of strings" in err.value.fix


def test_api_check_takes_a_list_a_string_and_refuses_an_empty_list(samples):
    """``check(path, rules=[])`` ran none of the rules (a broken rig passed them), where ``--rules ,`` is
    refused: the API refuses it as the command does."""
    from usdface import api

    assert api.check(samples / "avatar.usda", pixar=False, rules=["ArkitNames", "PointIndices"]) == \
        api.check(samples / "avatar.usda", pixar=False, rules=" ArkitNames,PointIndices ") == []
    with pytest.raises(OptionError, match="rules .* names no rule") as err:
        api.check(samples / "avatar.usda", pixar=False, rules=[])
    assert "ArkitNames" in err.value.fix


def test_api_evaluate_methods_refuses_a_list_naming_no_method(samples, tmp_path):
    from usdface import api

    with pytest.raises(OptionError, match="methods .* names no method"):
        api.evaluate_methods(samples / "capture.usda", methods=[" "], json_path=tmp_path / "r.json")
    assert not (tmp_path / "r.json").exists()


@pytest.mark.parametrize("argv, said", [
    (["check", "{avatar}", "--rules", " , "], "--rules ' , ' names no rule"),
    (["render", "{avatar}", "-o", "{out}", "--shapes", ","], "--shapes ',' names no shape"),
    (["evaluate", "{capture}", "--methods", " ,", "--plot", "{out}"], "--methods ' ,' names no method"),
])
def test_commands_refuse_an_option_naming_nothing(samples, tmp_path, capsys, argv, said):
    argv = [a.format(avatar=samples / "avatar.usda", capture=samples / "capture.usda", out=tmp_path / "x.png")
            for a in argv]
    assert main(argv) == 2
    assert said in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()
