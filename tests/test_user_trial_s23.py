"""User trial, session 23 (a pipeline engineer's and a new user's): the fixes their findings asked for, each
pinned by a test that failed before the fix."""

from __future__ import annotations

from pathlib import Path

import pytest

from usdface.errors import UsdFaceError

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


# ------------------------------------------------------------------ numeric options: the API as the CLI
@pytest.mark.parametrize("options, needle", [
    ({"mu": float("nan")}, "bad mu nan"),
    ({"mu": float("inf")}, "bad mu inf"),
    ({"mu": -1}, "bad mu -1"),
    ({"mu": 0.0}, "bad mu 0.0"),
    ({"mu": "abc"}, "bad mu 'abc'"),
    ({"mu": True}, "bad mu True"),
    ({"extension_length": -1.0}, "bad extension_length -1.0"),
    ({"extension_length": float("nan")}, "bad extension_length nan"),
    ({"falloff": -1}, "bad falloff -1"),
    ({"support": (0.05, 0.01)}, "low > high"),
    ({"support": 0.1}, "bad support 0.1"),
])
def test_api_refuses_the_numbers_the_cli_refuses(tmp_path, options, needle):
    """A script and the CLI behave identically: ``mu=nan`` wrote a "successful" map of 2,704 NaN, ``mu=0``
    raised numpy's LinAlgError, ``extension_length=-1`` was taken as 1. Refused before any work, nothing
    written. The implant's options are not the retarget map's (refused as such); falloff is the older
    modes'."""
    from usdface import api

    out = tmp_path / "map.json"
    implant = {"extension_length", "falloff", "support"} & set(options)
    with pytest.raises(UsdFaceError, match="not used by the retarget map" if implant else needle) as err:
        api.write_retarget_map(A, C, out, **options)
    assert err.value.fix and not out.exists()
    mode = {"face_transfer": "offset"} if "falloff" in options else {}
    with pytest.raises(UsdFaceError, match=needle):
        api.personalize_avatar(A, C, tmp_path / "p.usda", **options, **mode)
    assert not (tmp_path / "p.usda").exists()


def test_api_numbers_that_are_fine_pass_the_check():
    from usdface.transfer.pipeline import check_numbers

    check_numbers(mu="auto", extension_length=None, falloff=0, support=None)
    check_numbers(mu="1e-3", extension_length=0.5, falloff=0.15, support=(0.0, 0.0))
    check_numbers(mu=2, extension_length=2, falloff=1, support=[0.01, 0.03])


# ------------------------------------------------------------------ check agrees with what the readers do
HERO = 'def "Hero" (\n    instanceable = true\n    prepend references = @AVATAR@\n)\n{\n}\n'


def _shot(tmp_path: Path, header: str) -> Path:
    """A shot file referencing the sample avatar under an instanceable prim ``/Hero``."""
    path = tmp_path / "shot.usda"
    path.write_text(("#usda 1.0\n(\n" + header + ")\n" + HERO).replace("AVATAR", A.as_posix()))
    return path


def test_check_refuses_the_instanced_avatar_personalize_refuses(tmp_path, capsys):
    """``check`` (and so the publish validator) passed a shot that references the avatar under an
    instanceable prim, which personalize then refuses: check runs the refusal too."""
    from usdface.cli import main

    shot = _shot(tmp_path, '    defaultPrim = "Hero"\n    metersPerUnit = 0.01\n    upAxis = "Y"\n')
    assert main(["check", str(shot)]) == 1
    out = capsys.readouterr().out
    assert "[Readable]" in out and "instanceable prim /Hero" in out and "instanceable = false" in out
    assert main(["personalize", str(shot), str(C), "-o", str(tmp_path / "o.usda"), "-q"]) == 2


def test_check_runs_the_reader_after_an_unrelated_error(tmp_path):
    """A missing metersPerUnit (an error of the StageMetadata rule the reader tolerates) no longer hides what
    the reader refuses: both are told in one run, not the second after the first is fixed."""
    from usdface.api import check as check_file

    inst = _shot(tmp_path, '    defaultPrim = "Hero"\n    upAxis = "Y"\n')
    rules = {i.rule for i in check_file(inst) if i.severity == "error"}
    assert {"StageMetadata", "Readable"} <= rules


def test_an_avatar_with_an_animated_cache_is_not_a_take(tmp_path, capsys):
    """``inspect`` took an avatar whose root layer also holds a time-sampled mesh (a hair cache) for a take
    and failed on it ('no per-frame weights'); read_avatar, check and personalize accept it."""
    from usdface.cli import main
    from usdface.io.take import is_take

    cache = ('def Mesh "HairCache"\n    {\n        int[] faceVertexCounts = [3]\n'
             '        int[] faceVertexIndices = [0, 1, 2]\n'
             '        point3f[] points.timeSamples = {\n'
             '            1: [(0, 0, 0), (1, 0, 0), (0, 1, 0)],\n'
             '            2: [(0, 0, 1), (1, 0, 1), (0, 1, 1)],\n'
             '            3: [(0, 0, 2), (1, 0, 2), (0, 1, 2)],\n        }\n    }\n')
    text = A.read_text()
    at = text.index('def SkelRoot "Avatar"')
    at = text.index("{", at) + 1
    path = tmp_path / "avatar_cache.usda"
    path.write_text(text[:at] + "\n    " + cache + text[at:])
    assert not is_take(path)
    assert main(["inspect", str(path)]) == 0
    assert "avatar" in capsys.readouterr().out.splitlines()[0]


def test_api_layers_pass_check_without_a_command(tmp_path):
    """``write_landmarks`` / ``write_avatar_layer`` with the documented default ``provenance=None`` wrote an
    empty ``usdface:provenance:command``, which ``check`` calls an error: the API names itself."""
    from usdface import api
    from usdface.api import check as check_file

    av = api.read_avatar(A)
    rig = api.pick_mesh(av)
    out = api.write_landmarks(av, rig, api.compute_landmarks(A), tmp_path / "lm.usda")
    assert not [i for i in check_file(out) if i.severity == "error"]
    from pxr import Usd

    stage = Usd.Stage.Open(str(out))
    command = stage.GetPrimAtPath("/Avatar").GetAttribute("usdface:provenance:command").Get()
    assert "write_landmarks" in command


def test_api_refuses_what_it_cannot_use():
    from usdface import api

    with pytest.raises(UsdFaceError, match="expected a FaceRig, an Avatar or an avatar file"):
        api.compute_landmarks(3)
    with pytest.raises(UsdFaceError, match="unknown frame role 'bogus'"):
        api.evaluate_capture(C, role="bogus")


def test_source_date_epoch_makes_the_layer_reproducible(tmp_path, monkeypatch):
    """The same inputs twice gave layers that differed in createdAt and the timings: with SOURCE_DATE_EPOCH
    (the reproducible-builds convention) the bytes are the same, createdAt is that time."""
    from usdface.cli import main

    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    for sub in ("a", "b"):
        (tmp_path / sub).mkdir()
        monkeypatch.chdir(tmp_path / sub)
        assert main(["personalize", str(A), str(C), "-o", "p.usda", "-q"]) == 0
    one, two = (tmp_path / "a" / "p.usda").read_bytes(), (tmp_path / "b" / "p.usda").read_bytes()
    assert one == two and b'createdAt = "2023-11-14T22:13:20Z"' in one
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "yesterday")
    monkeypatch.chdir(tmp_path / "a")
    assert main(["personalize", str(A), str(C), "-o", "q.usda", "-q"]) == 2
    assert not (tmp_path / "a" / "q.usda").exists()


# ------------------------------------------------------------------ SIGTERM cleans up as Ctrl-C does
#: A prologue that makes the export's tenth OBJ write send SIGTERM to its own process (deterministic).
SIGTERM_AT_TENTH_OBJ = ("import os, signal, sys\n"
                        "import usdface.io.mesh_io as m\n"
                        "real, n = m.write_obj, [0]\n"
                        "def write_obj(*a, **k):\n"
                        "    n[0] += 1\n"
                        "    if n[0] == 10:\n"
                        "        os.kill(os.getpid(), signal.SIGTERM)\n"
                        "    return real(*a, **k)\n"
                        "m.write_obj = write_obj\n"
                        "from usdface.cli import main\n")


def _python(code: str, cwd: Path):
    import os
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})


def test_sigterm_leaves_no_temporary_files(tmp_path):
    """A farm's kill (SIGTERM) in the middle of an export left the hidden temporary folder (51 MB on dev1)
    behind; Ctrl-C did not. The signal arrives while the tenth OBJ is written (deterministically: the process
    sends it to itself), the command exits 143 and the output folder holds nothing."""
    import os

    proc = _python(SIGTERM_AT_TENTH_OBJ
                   + f"sys.argv = ['usdface', 'export', {str(A)!r}, '--obj-dir', 'objs', '-q']\n"
                   "sys.exit(main())\n", tmp_path)      # as the console script runs it (argv from sys.argv)
    assert proc.returncode == 143, proc.stderr
    assert "terminated" in proc.stderr and "Traceback" not in proc.stderr
    assert sorted(os.listdir(tmp_path)) == []


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


# ------------------------------------------------------------------ takes and captures told apart
@pytest.fixture(scope="module")
def weights_take(tmp_path_factory) -> Path:
    """A weights-only take as ``anim import`` writes it (the sample's test weights as a 30 fps recording)."""
    import numpy as np

    from usdface.io.usd_anim import write_animation_usd

    rng = np.random.default_rng(0)
    from usdface.arkit import ARKIT_NAMES

    w = rng.uniform(0.0, 0.45, size=(60, len(ARKIT_NAMES)))
    w[10, ARKIT_NAMES.index("jawOpen")] = 0.93
    out = tmp_path_factory.mktemp("take") / "take.usda"
    write_animation_usd(out, list(ARKIT_NAMES), w, np.arange(60) / 30.0)
    return out


def test_inspect_summarises_a_weights_only_take(weights_take, capsys):
    """``inspect`` refused the take ``anim import`` had just written ('this is a take ..., not an avatar');
    index.md promises a summary: frames, rate, and the shapes never above 0.5."""
    from usdface.cli import main

    assert main(["inspect", str(weights_take)]) == 0
    out = capsys.readouterr().out
    assert "take" in out.splitlines()[0] and "60 frames at 30 fps" in out
    assert "never above 0.5 (51)" in out and "jawOpen" not in out.split("never above")[1].split("\n")[0]


def test_capture_select_refuses_a_capture_and_an_empty_selection(weights_take, tmp_path, capsys):
    """A capture given to ``capture select`` was re-selected (its test frames became training frames), and a
    threshold no shape reaches wrote a capture of 0 frames with exit 0: both refused, nothing written."""
    from usdface.cli import main

    assert main(["capture", "select", str(C), "-o", str(tmp_path / "cc.usda")]) == 2
    assert "this is a capture" in capsys.readouterr().err and not (tmp_path / "cc.usda").exists()
    assert main(["capture", "select", str(weights_take), "-o", str(tmp_path / "y.usda"),
                 "--threshold", "0.99"]) == 2
    err = capsys.readouterr().err
    assert "no shape peaks above --threshold 0.99" in err and "jawOpen 0.93" in err
    assert not (tmp_path / "y.usda").exists()


# ------------------------------------------------------------------ errors that say what was given
def test_errors_name_what_the_file_is(tmp_path, capsys):
    """--correspondence naming the avatar said 'delete it'; a capture folder given as the avatar said only
    'is a folder'; a fitted rig given as the capture said 'not a usdface capture (no /Capture with ...)'."""
    from usdface.cli import main

    avatar = tmp_path / "avatar.usda"
    avatar.write_bytes(A.read_bytes())
    assert main(["personalize", str(avatar), str(C), "-o", str(tmp_path / "p.usda"),
                 "--correspondence", str(avatar)]) == 2
    err = capsys.readouterr().err
    assert "names one of this run's inputs" in err and "delete" not in err
    assert avatar.read_bytes() == A.read_bytes()
    cap = tmp_path / "cap"
    (cap / "train").mkdir(parents=True)
    assert main(["personalize", str(cap), str(A), "-o", str(tmp_path / "q.usda")]) == 2
    assert "arguments swapped?" in capsys.readouterr().err
    assert main(["personalize", str(A), str(A), "-o", str(tmp_path / "r.usda")]) == 2
    assert "this is a rig" in capsys.readouterr().err


def test_stale_layers_and_other_captures_are_not_exported_or_reviewed_silently(tmp_path):
    """``check`` warned that a layer's avatar changed after it was written, but ``export`` and ``review``
    used the layer without a word, and ``review --capture`` scored another person's capture under the
    layer's name: both warn now (the files are still written: a warning, not a refusal)."""
    from usdface import api

    avatar, capture = tmp_path / "avatar.usda", tmp_path / "capture.usda"
    avatar.write_bytes(A.read_bytes())
    capture.write_bytes(C.read_bytes())
    layer = tmp_path / "p.usda"
    api.personalize_avatar(avatar, capture, layer)
    with pytest.warns(UserWarning) as rec:             # the layer's own inputs: no word
        import warnings

        warnings.warn("sentinel", UserWarning, stacklevel=1)
        api.export_avatar(layer, gltf=tmp_path / "a.glb")
    assert [str(w.message) for w in rec] == ["sentinel"]
    avatar.write_bytes(A.read_bytes() + b"\n")          # the avatar re-exported since
    with pytest.warns(UserWarning, match="changed after it was written"):
        api.export_avatar(layer, gltf=tmp_path / "b.glb")
    assert (tmp_path / "b.glb").is_file()
    other = tmp_path / "other.usda"
    other.write_bytes(C.read_bytes())
    with pytest.warns(UserWarning, match="other.usda is not among the inputs p.usda records"):
        api.write_review(layer, tmp_path / "r.html", capture=other, fit_errors=False)


def test_render_takes_the_meshs_own_channel_names_on_a_name_mapped_layer(tmp_path):
    """troubleshooting.md: '--shapes names shapes as the mesh has them'; on a layer written with --name-map
    only the ARKit name worked ('mesh Head has no shape ch17_ctrl'). Both work now, and a comparison names
    the shape as ARKit does."""
    import json
    import re

    from usdface.arkit import ARKIT_NAMES
    from usdface.cli import main

    idx = {n: i for i, n in enumerate(ARKIT_NAMES)}
    words = re.compile(r"\b(" + "|".join(sorted(ARKIT_NAMES, key=len, reverse=True)) + r")\b")
    studio = tmp_path / "studio.usda"
    studio.write_text(words.sub(lambda m: f"ch{idx[m.group(1)]:02d}_ctrl", A.read_text()))
    names = tmp_path / "names.json"
    names.write_text(json.dumps({f"ch{k:02d}_ctrl": n for n, k in idx.items()}))
    assert main(["personalize", str(studio), str(C), "-o", str(tmp_path / "p.usda"), "--name-map", str(names),
                 "-q"]) == 0
    for shapes in ("ch17_ctrl", "jawOpen", "ch17_ctrl,eyeBlinkLeft"):
        out = tmp_path / f"{shapes.replace(',', '_')}.png"
        assert main(["render", str(tmp_path / "p.usda"), "--compare", "--shapes", shapes, "-o", str(out),
                     "-q"]) == 0
        assert out.is_file()


def test_a_host_calling_main_keeps_its_own_sigterm_handling(tmp_path):
    """Called in-process with arguments (a DCC, a farm wrapper), ``main`` leaves SIGTERM to the host: the
    host's handler runs (the review found it swallowed and the host's SIG_IGN lost)."""
    host = "calls = []\nimport signal\nsignal.signal(signal.SIGTERM, lambda *a: calls.append(1))\n"
    proc = _python(host + SIGTERM_AT_TENTH_OBJ
                   + f"code = main(['export', {str(A)!r}, '--obj-dir', 'objs', '-q'])\nprint(code, calls)\n",
                   tmp_path)
    assert proc.returncode == 0 and proc.stdout.splitlines()[-1] == "0 [1]", (proc.stdout, proc.stderr)


def test_json_documents_stay_parseable_when_something_warns(tmp_path, capsys, monkeypatch):
    """A warning line went to stdout before the ``--json`` document (seen with an ImportWarning of six's
    importer under Dask, and any library warning): stdout is the document alone, warnings go to stderr."""
    import json

    import usdface.personalize.api as fit_api
    from usdface.cli import main

    real = fit_api.check_capture
    monkeypatch.setattr(fit_api, "check_capture", lambda c: real(c) + ["a library warning"])
    assert main(["fit", str(C), "-o", str(tmp_path / "r.usda"), "--reg", "0.01", "--json"]) == 0
    out, err = capsys.readouterr()
    doc = json.loads(out)
    assert doc["ok"] and "a library warning" in doc["warnings"] and "warning: a library warning" in err
    assert main(["fit", str(C), "-o", str(tmp_path / "s.usda"), "--reg", "0.01", "-q"]) == 0
    assert "warning: a library warning" in capsys.readouterr().out       # text mode: as before


def test_review_of_a_landmarks_layer(tmp_path, capsys):
    """``review`` of a ``usdface landmarks`` layer took the avatar (its second recorded input) for the
    capture ('this is a rig, not a capture') and, given --capture, refit with method 'landmarks'."""
    from usdface.cli import main

    assert main(["personalize", str(A), str(C), "-o", str(tmp_path / "p.usda"), "-q"]) == 0
    assert main(["landmarks", str(tmp_path / "p.usda"), "-o", str(tmp_path / "lm.usda"), "-q"]) == 0
    capsys.readouterr()
    assert main(["review", str(tmp_path / "lm.usda"), "-o", str(tmp_path / "a.html"), "-q"]) == 0
    assert main(["review", str(tmp_path / "lm.usda"), "-o", str(tmp_path / "b.html"), "--capture", str(C),
                 "-q"]) == 0
    out = capsys.readouterr()
    assert "not among the inputs" not in out.out + out.err
    assert "menzel refit" in (tmp_path / "b.html").read_text()


def test_check_of_a_take_says_what_it_is(weights_take, capsys):
    """``check`` of an ``anim import`` take printed a bare '0 error(s)' as if it were a valid rig."""
    from usdface.cli import main

    assert main(["check", str(weights_take)]) == 0
    out = capsys.readouterr().out
    assert "this is a take" in out and "1 info" in out


def test_a_flattened_export_elsewhere_keeps_a_provenance_check_can_follow(tmp_path):
    """A flattened file written into another folder copied its provenance paths (relative to the layer's
    folder), so ``check`` found the inputs 'not reachable' and the stale-input check was off."""
    from usdface import api
    from usdface.io.layers import recorded_inputs

    layer = tmp_path / "p.usda"
    api.personalize_avatar(A, C, layer)
    flat = tmp_path / "deliver" / "x" / "flat.usda"
    flat.parent.mkdir(parents=True)
    api.export_avatar(layer, flatten=flat, variant="generic")
    assert set(recorded_inputs(flat)) == {str(A.resolve()), str(C.resolve())}
    issues = api.check(flat)
    assert not [i for i in issues if "not reachable" in i.message], issues


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
