"""The commands a refusal's fix tells paste into a shell as shown (stop 43): each path in them one shell word
(``shlex.quote``), and the command itself set in parentheses, never in quotes of its own. A quoted path inside
a quoted command read ``'usdface personalize AVATAR 'shoot day/cap.usda' -o person.usda --review'``: the
outer quotes, copied with it, make another command."""

from __future__ import annotations

import re
import shlex
import shutil
from pathlib import Path

import pytest

from usdface import api
from usdface.cli import main
from usdface.errors import UsdFaceError

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"


def _commands(text: str) -> list[list[str]]:
    """Every ``(usdface ...)`` in ``text``, split as a shell splits it."""
    return [shlex.split(m) for m in re.findall(r"\((usdface (?:'[^']*'|[^'()])*)\)", text)]


def _pasteable(text: str, path: Path) -> list[list[str]]:
    assert not re.search(r"'usdface [^']*'[^ ]", text), text        # no quoted command around a quoted word
    commands = _commands(text)
    assert commands and any(str(path) in argv for argv in commands), text
    return commands


@pytest.fixture()
def spaced(tmp_path) -> Path:
    if not (SAMPLES / "capture.usda").exists():
        pytest.skip("sample_assets not generated yet")
    folder = tmp_path / "shoot day"
    folder.mkdir()
    for name in ("capture.usda", "avatar.usda"):
        shutil.copy(SAMPLES / name, folder / name.replace(".", " x."))
    return folder


def test_review_fixes_are_pasteable(spaced, tmp_path):
    for name in ("capture x.usda", "avatar x.usda"):
        with pytest.raises(UsdFaceError) as err:
            api.write_review(spaced / name, tmp_path / "r.html")
        _pasteable(err.value.fix, spaced / name)


def test_export_and_usdz_fixes_are_pasteable(spaced, tmp_path):
    with pytest.raises(UsdFaceError) as err:
        api.export_avatar(spaced / "capture x.usda", gltf=tmp_path / "o.glb")
    _pasteable(err.value.fix, spaced / "capture x.usda")
    from usdface.io.layers import _refuse_usdz_layer

    with pytest.raises(UsdFaceError) as err:
        _refuse_usdz_layer(spaced / "p x.usdz")
    assert _pasteable(err.value.fix, spaced / "p x.usda")[0][-2:] == ["--flatten", str(spaced / "p x.usdz")]


def test_render_landmarks_fix_is_pasteable(spaced, tmp_path, capsys):
    argv = ["render", str(spaced / "avatar x.usda"), "-o", str(tmp_path / "l m.png"), "--landmarks"]
    assert main(argv) == 2
    write, draw = _pasteable(capsys.readouterr().err, spaced / "avatar x.usda")
    assert write[:2] == ["usdface", "landmarks"] and draw[:2] == ["usdface", "render"]
    assert draw[2] == write[write.index("-o") + 1] and draw[4] == str(tmp_path / "l m.png")
