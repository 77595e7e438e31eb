"""``usdface personalize`` / ``usdface retarget`` command lines on the dev1 bench case and the sample assets
(inspection options)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from input_helpers import _capture

from usdface.cli import main
from usdface.errors import InputFileError

DOCS = Path(__file__).resolve().parents[1] / "docs"
ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


@pytest.mark.shared
def test_personalize_dry_run_writes_nothing(bench, tmp_path, capsys):
    out = tmp_path / "p.usda"
    code = main(["personalize", str(bench / "dev1" / "avatar.usdc"), str(bench / "dev1" / "capture"),
                 "-o", str(out), "--dry-run", "-q", "--correspondence", str(tmp_path / "c.npz")])
    text = capsys.readouterr().out
    assert code == 0
    assert not out.exists()
    assert "dry run:" in text and "/Avatar/Head/jawOpen: max" in text
    assert "registration: scale" in text
    assert (tmp_path / "c.npz").exists()


@pytest.mark.shared
def test_retarget_writes_csv_and_refuses_to_overwrite(bench, tmp_path, capsys):
    out = tmp_path / "map.csv"
    args = ["retarget", str(bench / "dev1" / "avatar.usdc"), str(bench / "dev1" / "capture"), "-o", str(out),
            "-q"]
    assert main(args) == 0
    rows = out.read_text().splitlines()
    assert rows[0].startswith("source,") and len(rows) == 52  # header + 51 capture shapes
    assert main(args) == 2  # exists, no --force
    assert "--force" in capsys.readouterr().err


def test_personalize_bad_input_exit_2(tmp_path, capsys):
    code = main(["personalize", str(tmp_path / "missing.usdc"), str(tmp_path / "nocapture"), "-o",
                 str(tmp_path / "o.usda"), "-q"])
    assert code == 2
    assert "missing.usdc" in capsys.readouterr().err


@pytest.mark.parametrize("flags, inspect, landmarks, take", [
    ([], False, False, None),
    (["--inspect"], True, False, None),
    (["--landmarks"], True, True, None),
    (["--take", "t.csv"], True, False, "t.csv"),
    (["--inspect", "--landmarks", "--take", "t.csv"], True, True, "t.csv"),
])
def test_inspection_flags_pass_through(monkeypatch, tmp_path, flags, inspect, landmarks, take):
    """--inspect / --landmarks / --take reach usdface.api.personalize_avatar (the last two imply
    --inspect)."""
    import usdface.api

    seen = {}

    def fake(avatar, capture, out, **kwargs):
        seen.update(kwargs)
        raise InputFileError("stop here", path=avatar, fix="none")

    monkeypatch.setattr(usdface.api, "personalize_avatar", fake)
    assert main(["personalize", "a.usda", "c.usda", "-o", str(tmp_path / "o.usda"), "-q", *flags]) == 2
    assert (seen["inspect"], seen["landmarks"], seen["take"]) == (inspect, landmarks, take)
    assert seen["eyelids"] is True and seen["method"] == "menzel"


def test_personalize_inspection_layer_on_the_sample(samples, tmp_path, capsys):
    """``--landmarks --take FILE`` writes the heat map, the landmark Points and one SkelAnimation playing the
    capture's test expressions followed by the take, into the result layer only."""
    from pxr import Sdf, Usd

    from usdface.io import read_capture
    from usdface.io.livelink import write_livelink_csv
    from usdface.io.usd_inspection import ANIMATION_NAME, HEAT_PRIMVAR, read_landmarks

    take_weights = np.array([[0.0, 0.0], [0.5, 0.2], [1.0, 0.4], [0.5, 0.6], [0.0, 1.0]])
    take = write_livelink_csv(tmp_path / "take.csv", ["jawOpen", "eyeBlinkLeft"], take_weights,
                              np.arange(5) / 30.0)
    out = tmp_path / "person.usda"
    avatar_bytes = (samples / "avatar.usda").read_bytes()
    assert main(["personalize", str(samples / "avatar.usda"), str(samples / "capture.usda"), "-o", str(out),
                 "-q", "--landmarks", "--take", str(take)]) == 0
    captured = capsys.readouterr()
    text = captured.out
    assert "inspection: change heat map" in text and "landmark Points" in text and "take.csv" in text
    # the shapes kept near generic because the person's difference is within the fit's noise: an information
    # line, not a warning (the sample records every shape on its own: nothing for the user to fix)
    assert "trust: kept near the avatar's generic shape" in text
    assert "warning" not in captured.err
    assert (samples / "avatar.usda").read_bytes() == avatar_bytes
    layer = Sdf.Layer.FindOrOpen(str(out))
    head = layer.GetPrimAtPath("/Avatar/Head")
    assert "primvars:displayColor" in head.properties and f"primvars:{HEAT_PRIMVAR}" in head.properties
    stage = Usd.Stage.Open(str(out))
    heat = np.asarray(stage.GetPrimAtPath("/Avatar/Head").GetAttribute(f"primvars:{HEAT_PRIMVAR}").Get())
    assert heat.shape == (3780,) and heat.max() > 1e-4 and (heat == 0).any()  # the face changed, the back not
    assert len(read_landmarks(stage)["/Avatar/Head"]) > 10
    anim = stage.GetPrimAtPath(f"/Avatar/Skel/{ANIMATION_NAME}")
    assert anim.GetTypeName() == "SkelAnimation"
    weights_attr = anim.GetAttribute("blendShapeWeights")
    times = weights_attr.GetTimeSamples()
    n_test = len(read_capture(samples / "capture.usda").test)
    assert len(times) == n_test + len(take_weights)
    channels = list(anim.GetAttribute("blendShapes").Get())
    last = np.asarray(weights_attr.Get(times[-1]))
    assert last[channels.index("jawOpen")] == pytest.approx(0.0, abs=1e-6)
    assert last[channels.index("eyeBlinkLeft")] == pytest.approx(1.0, abs=1e-6)


def test_inspection_animation_keeps_the_avatars_frame_rate_and_first_frame(samples, tmp_path):
    """personalize --take over an avatar authored at 30 time codes per second from frame 1001 (a shot's
    convention): the layer plays the inspection animation on that timeline. It wrote timeCodesPerSecond 24
    and startTimeCode 0 over the avatar's 30 and 1001 (a user trial: the personalized layer changed the
    stage's frame rate and frame range only when --inspect/--take was given)."""
    from cli_helpers import _usdface
    from pxr import Sdf, Usd, UsdSkel

    from usdface.io import read_capture
    from usdface.io.livelink import write_livelink_csv
    from usdface.io.usd_inspection import ANIMATION_NAME

    layer = Sdf.Layer.FindOrOpen(str(samples / "avatar.usda"))
    shot = Sdf.Layer.CreateAnonymous(".usda")
    shot.TransferContent(layer)
    shot.timeCodesPerSecond, shot.framesPerSecond = 30.0, 30.0
    shot.startTimeCode, shot.endTimeCode = 1001.0, 1100.0
    shot.Export(str(tmp_path / "avatar.usda"))
    take_weights = np.array([[0.0, 0.0], [0.5, 0.2], [1.0, 0.4], [0.5, 0.6], [0.0, 1.0]])
    write_livelink_csv(tmp_path / "take.csv", ["jawOpen", "eyeBlinkLeft"], take_weights, np.arange(5) / 30.0)
    res = _usdface("personalize", "avatar.usda", samples / "capture.usda", "--take", "take.csv", "-o",
                   "person.usda", "-q", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    stage = Usd.Stage.Open(str(tmp_path / "person.usda"))
    assert stage.GetTimeCodesPerSecond() == 30.0 and stage.GetFramesPerSecond() == 30.0
    anim = UsdSkel.Animation(stage.GetPrimAtPath(f"/Avatar/Skel/{ANIMATION_NAME}"))
    codes = anim.GetBlendShapeWeightsAttr().GetTimeSamples()
    n_test = len(read_capture(samples / "capture.usda").test)
    # test expressions every 0.5 s from frame 1001, the take 1 s after the last one, in 30 fps time codes
    assert codes[0] == stage.GetStartTimeCode() == 1001.0
    assert codes[1] - codes[0] == pytest.approx(15.0)
    take_start = 1001.0 + ((n_test - 1) * 0.5 + 1.0) * 30.0
    assert codes[n_test:] == pytest.approx(take_start + np.arange(5), abs=1e-6)
    assert stage.GetEndTimeCode() == pytest.approx(codes[-1])
    # a take whose samples fall between frames: the range is whole frames around them (h32's trial: the
    # layer ended at 1994.978, and usdview's frame slider stopped at 1994, short of the last sample)
    write_livelink_csv(tmp_path / "off.csv", ["jawOpen", "eyeBlinkLeft"], take_weights,
                       np.array([0.0, 1.0, 2.0, 3.0, 4.5]) / 30.0)
    res = _usdface("personalize", "avatar.usda", samples / "capture.usda", "--take", "off.csv", "-o",
                   "off.usda", "-q", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    stage = Usd.Stage.Open(str(tmp_path / "off.usda"))
    codes = UsdSkel.Animation(stage.GetPrimAtPath(f"/Avatar/Skel/{ANIMATION_NAME}")).GetBlendShapeWeightsAttr(
    ).GetTimeSamples()
    assert codes[-1] % 1 > 0.1 and stage.GetEndTimeCode() == np.ceil(codes[-1])
    assert stage.GetStartTimeCode() == np.floor(codes[0]) == 1001.0
    # the sample avatar authors no timeline: USD's 24 time codes per second from 0, as before
    res = _usdface("personalize", samples / "avatar.usda", samples / "capture.usda", "--inspect", "-o",
                   "plain.usda", "-q", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    stage = Usd.Stage.Open(str(tmp_path / "plain.usda"))
    codes = UsdSkel.Animation(stage.GetPrimAtPath(f"/Avatar/Skel/{ANIMATION_NAME}")).GetBlendShapeWeightsAttr(
    ).GetTimeSamples()
    assert stage.GetTimeCodesPerSecond() == 24.0 and codes[0] == 0.0 and codes[1] == pytest.approx(12.0)


class _ClosedPipe:
    def write(self, text):
        raise BrokenPipeError(32, "Broken pipe")

    def flush(self):
        raise BrokenPipeError(32, "Broken pipe")


def test_closed_pipe_exits_quietly(samples, monkeypatch, capsys):
    """``usdface inspect FILE | head``: the reader closing the pipe is no error (exit 141, no traceback)."""
    monkeypatch.setattr("sys.stdout", _ClosedPipe())
    assert main(["inspect", str(samples / "avatar.usda")]) == 141


def test_closed_pipe_in_a_real_process(samples):
    import subprocess
    import sys

    args = [sys.executable, "-m", "usdface.cli", "inspect", "--json", str(samples / "avatar.usda")]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # the reader is gone before the first write
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 141
    assert "Traceback" not in err and "BrokenPipe" not in err, err


@pytest.mark.parametrize("flags", [["--reg", "paper"], ["--reg", "0.01"],
                                   ["--method", "laplacian", "--reg", "0.01"]])
def test_personalize_with_a_fixed_reg_uses_the_avatar_prior(samples, tmp_path, capsys, flags):
    """``--reg`` other than ``auto`` (documented for personalize) used to fail after the registration with
    "avatar_prior given but prior='dt' ignores it": the avatar's shapes on the capture are the fit's prior
    with any ``reg``."""
    out = tmp_path / "p.usda"
    assert main(["personalize", str(samples / "avatar.usda"), str(samples / "capture.usda"), "-o", str(out),
                 "-q", "--json", *flags]) == 0
    report = json.loads(capsys.readouterr().out)
    assert set(report["fit"]["prior_choice"]) == {"avatar"}
    assert out.is_file()
    if "laplacian" in flags:      # the test frames' amplitudes are read by menzel's fit only
        assert "test_amplitude" not in report["fit"]
        return
    # the test frames' amplitude reading as JSON numbers (it printed numpy's repr, a string)
    amplitude = report["fit"]["test_amplitude"]
    assert all(isinstance(v, list) and len(v) == 52 and all(isinstance(x, float) for x in v)
               for v in (amplitude["reading"], amplitude["scale"]))


def test_personalize_refuses_a_fit_option_before_any_work(samples, tmp_path, capsys, monkeypatch):
    """An option the fit method would ignore is refused before reading the avatar (nothing runs)."""
    from usdface.transfer import pipeline

    monkeypatch.setattr(pipeline, "crop_avatar", lambda *a, **k: pytest.fail("work started"))
    assert main(["personalize", str(samples / "avatar.usda"), str(samples / "capture.usda"), "-o",
                 str(tmp_path / "p.usda"), "--method", "ebfr", "--reg", "0.01"]) == 2
    assert "not used by method 'ebfr': --reg (reg=0.01)" in capsys.readouterr().err
    assert not (tmp_path / "p.usda").exists()


def test_retarget_map_is_bounded_by_default_and_the_papers_on_request(samples, tmp_path, capsys):
    """The map an engine drives the avatar with: weights in [0, 1] by default (the sample's eq. 4 map went
    from -4.2 to 12.0, `cheekSquintRight` -> `eyeLookUpRight` 11.95); ``--unbounded --map-prior zero
    --map-gaze free`` is the paper's eq. (4)."""
    base = ["retarget", str(samples / "avatar.usda"), str(samples / "capture.usda"), "-q"]
    assert main([*base, "-o", str(tmp_path / "map.json")]) == 0
    doc = json.loads((tmp_path / "map.json").read_text())
    w = np.array(doc["weights"])
    assert w.min() >= 0.0 and w.max() <= 1.0
    assert main([*base, "-o", str(tmp_path / "paper.json"), "--unbounded", "--map-prior", "zero",
                 "--map-gaze", "free"]) == 0
    paper = np.array(json.loads((tmp_path / "paper.json").read_text())["weights"])
    # eq. (4) unbounded leaves [0, 1] on both sides, well past what the bounded solve's rounding could
    # (the sample's: -4.2 to 12.0 with the first correspondence; -0.96 to 1.48 since stop 49's registration)
    assert paper.max() > 1.2 and paper.min() < -0.5 and (paper < -0.05).sum() > 100
    assert main([*base, "-o", str(tmp_path / "bad.json"), "--weight-bounds", "1", "0"]) == 2
    assert "bad weight bounds" in capsys.readouterr().err


def test_retarget_computes_the_map_without_the_implant(samples, tmp_path, monkeypatch):
    """``usdface retarget`` writes eq. (4)'s map and stops there: the same weights a personalize run
    computes, and no implant, eyelid repair or layer (it ran the whole transfer after the map: ~30 s of a
    225k-vertex head for a file of 51 x 51 numbers)."""
    from usdface import api
    from usdface.transfer import pipeline

    full = api.personalize_avatar(samples / "avatar.usda", samples / "capture.usda", None)

    def no_implant(*args, **kwargs):
        raise AssertionError("the implant ran for a retarget map")

    monkeypatch.setattr(pipeline, "_implant_person", no_implant)
    monkeypatch.setattr(pipeline, "repair_eyelids", no_implant)
    assert main(["retarget", str(samples / "avatar.usda"), str(samples / "capture.usda"),
                 "-o", str(tmp_path / "map.json")]) == 0
    doc = json.loads((tmp_path / "map.json").read_text())
    assert doc["source"] == list(full.names) and doc["target"] == list(full.avatar_names)
    assert np.abs(np.array(doc["weights"]) - full.weights).max() <= 1e-6         # written to 6 decimals
    # the mu used, as chosen (one face region left out at a time), is recorded with the map and in the layer
    assert doc["meta"]["mu"] == full.report["retarget"]["mu"]
    assert doc["meta"]["mu_choice"] == "leave one face region out"


def test_retarget_map_records_its_inputs_relative_to_the_map(samples, tmp_path, monkeypatch):
    """A user trial: 'retarget sa/avatar.usda sa/capture.usda -o sub/map.json --pins pins.json' recorded the
    avatar as typed ('sa/avatar.usda', relative to the folder the command ran in: from the map's folder no
    such file), the capture absolute (the pins had it read first) and the pins not at all. All three are
    relative to the map's folder now, as a layer records its inputs."""
    import shutil

    for name in ("avatar.usda", "capture.usda"):
        shutil.copy(samples / name, tmp_path / name)
    (tmp_path / "sub").mkdir()
    (tmp_path / "pins.json").write_text(json.dumps({"pins": {"jawOpen": [12, 13]}}))
    monkeypatch.chdir(tmp_path)
    assert main(["retarget", "avatar.usda", "capture.usda", "-o", "sub/map.json", "--pins", "pins.json",
                 "-q"]) == 0
    meta = json.loads((tmp_path / "sub" / "map.json").read_text())["meta"]
    assert (meta["avatar"], meta["capture"], meta["pins"]) == ("../avatar.usda", "../capture.usda",
                                                               "../pins.json")


def test_retarget_map_rows_stay_on_their_namesake(samples, tmp_path):
    """With ``mu`` cross-validated over face regions the sample's map is a retargeting table: the median row
    puts less than 1.0 of weight on shapes other than its namesake (GCV over the rows: 2.4, its
    ``eyeBlinkLeft`` row drove ``eyeLookDownLeft`` and ``eyeWideLeft`` at 1.0 each), and the layer's
    provenance records the ``mu`` used."""
    from usdface.io.usd_rig import usdface_layer_data

    out = tmp_path / "p.usda"
    assert main(["personalize", str(samples / "avatar.usda"), str(samples / "capture.usda"), "-o", str(out),
                 "-q"]) == 0
    prov = usdface_layer_data(out)
    assert prov["retargetMuChoice"] == "leave one face region out" and 1e-6 < prov["retargetMu"] < 1.0
    rows = prov["retargetMap"]
    off = [sum(v for k, v in row.items() if k != shape) for shape, row in rows.items()]
    assert np.median(off) < 1.0


def test_the_correspondence_cache_path_is_checked_like_an_output_before_any_work(samples, tmp_path, capsys,
                                                                                monkeypatch):
    """User trial: ``--correspondence`` = ``-o`` ran the whole personalization, wrote the cache there, then
    refused its own file as "output layer exists" (with --force the layer overwrote the cache); a cache in
    a folder that cannot be written failed after the work, naming -o. Refused before any work now."""
    from usdface.transfer import pipeline

    def no_work(*args, **kwargs):
        raise AssertionError("the work started")

    monkeypatch.setattr(pipeline, "register_face", no_work)
    base = ["personalize", str(samples / "avatar.usda"), str(samples / "capture.usda"), "-q"]
    same = tmp_path / "x.usda"
    for extra in ([], ["--force"]):
        assert main([*base, "-o", str(same), "--correspondence", str(same), *extra]) == 2
        assert "--correspondence and -o name the same file" in capsys.readouterr().err
        assert not same.exists()
    (tmp_path / "afile").write_text("")
    assert main([*base, "-o", str(tmp_path / "o.usda"), "--correspondence",
                 str(tmp_path / "afile" / "c.npz")]) == 2
    err = capsys.readouterr().err
    assert "correspondence cache (--correspondence)" in err and "is a file, not a folder" in err
    assert main(["retarget", str(samples / "avatar.usda"), str(samples / "capture.usda"), "-q",
                 "-o", str(tmp_path / "m.json"), "--correspondence", str(tmp_path / "m.json")]) == 2
    assert "--correspondence and -o name the same file" in capsys.readouterr().err


def test_a_correspondence_cache_inside_an_input_folder_is_refused(bench, tmp_path, capsys):
    """User trial: ``-o capture/out.usda`` was refused (inside the input folder); a cache there was written
    into the input."""
    cache = bench / "dev1" / "capture" / "corr.npz"
    assert main(["personalize", str(bench / "dev1" / "avatar.usdc"), str(bench / "dev1" / "capture"), "-q",
                 "-o", str(tmp_path / "o.usda"), "--correspondence", str(cache)]) == 2
    assert "is inside the input folder" in capsys.readouterr().err and not cache.exists()


def test_personalize_with_artist_pins(samples, tmp_path, capsys):
    """``--pins`` reaches the fit (the option check before any work accepts every argument the fit takes)."""
    pins = tmp_path / "pins.json"
    pins.write_text(json.dumps({"pins": {"jawOpen": [0, 1, 2]}}))
    assert main(["personalize", str(samples / "avatar.usda"), str(samples / "capture.usda"), "--pins",
                 str(pins), "--dry-run", "--json", "-q", "-o", str(tmp_path / "o.usda")]) == 0
    assert json.loads(capsys.readouterr().out)["fit"]["pins"] == {"jawOpen": 3}


def test_correspondence_cache_extended_for_the_dt_modes_is_not_another_avatars(samples, tmp_path, capsys):
    """A cache of this avatar and template, written by the default mode, lacks the face triangles' source
    triangles the dt modes read: it is extended ("cache: extended"), not reported as another avatar's."""
    cache = tmp_path / "c.npz"
    base = ["personalize", str(samples / "avatar.usda"), str(samples / "capture.usda"), "--dry-run", "-q",
            "--correspondence", str(cache), "-o", str(tmp_path / "o.usda")]
    assert main([*base, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["correspondence"]["cache"] == "miss"
    assert main([*base, "--face-transfer", "dt", "--approximation", "generic"]) == 0
    said = capsys.readouterr()
    assert "cache: extended" in said.out and "another avatar" not in said.out + said.err
    assert main([*base, "--json", "--face-transfer", "dt", "--approximation", "generic"]) == 0
    assert json.loads(capsys.readouterr().out)["correspondence"]["cache"] == "hit"


def test_a_dry_run_answers_whether_a_real_run_would_write(samples, tmp_path, capsys):
    """A preflight: ``--dry-run`` onto an existing output did the work and exited 0 although a real run
    would refuse (a user trial). Exit status 1 then (text and JSON), 0 when a real run would write."""
    out = tmp_path / "p.usda"
    base = ["personalize", str(samples / "avatar.usda"), str(samples / "capture.usda"), "-o", str(out),
            "--dry-run", "-q", "--correspondence", str(tmp_path / "c.npz")]
    assert main(base) == 0 and "would write" in capsys.readouterr().out
    out.write_text("#usda 1.0\n")
    assert main(base) == 1
    assert "a real run would refuse to write" in capsys.readouterr().out
    assert main([*base, "--json"]) == 1
    doc = json.loads(capsys.readouterr().out)
    assert "exists" in doc["output_refused"] and doc["ok"] is False
    assert main([*base, "--force"]) == 0


def test_a_dry_run_says_a_real_run_would_refuse_before_it_computes(samples, tmp_path, capsys, monkeypatch):
    """``--dry-run`` onto an existing output fitted for seconds (minutes on a large capture) before saying a
    real run would refuse (a TD's trial): the refusal is one line on stderr, naming the output and the fix,
    before the work; the changes are still printed and the exit status is 1 (the JSON a single document)."""
    import usdface.api

    real, said = usdface.api.personalize_avatar, []

    def personalize(*args, **kwargs):     # what stderr held when the work began
        said.append(capsys.readouterr().err)
        return real(*args, **kwargs)

    monkeypatch.setattr(usdface.api, "personalize_avatar", personalize)
    out = tmp_path / "p.usda"
    out.write_text("#usda 1.0\n")
    base = ["personalize", str(samples / "avatar.usda"), str(samples / "capture.usda"), "-o", str(out),
            "--dry-run", "-q", "--correspondence", str(tmp_path / "c.npz")]
    assert main(base) == 1
    first = [line for line in said[-1].splitlines() if "would refuse" in line]
    assert len(first) == 1 and str(out) in first[0] and "output layer exists" in first[0]
    assert "fix: pass --force" in first[0]
    text = capsys.readouterr().out
    assert "dry run:" in text and "jawOpen: max" in text and "a real run would refuse to write" in text
    assert main([*base, "--json"]) == 1
    assert "would refuse" in said[-1]
    doc = json.loads(capsys.readouterr().out)
    assert doc["ok"] is False and "exists" in doc["output_refused"] and doc["changes"]
    assert main([*base, "--force"]) == 0
    assert "would refuse" not in said[-1] + capsys.readouterr().err



def test_a_dry_run_says_an_instanced_avatar_is_refused_before_it_computes(samples, tmp_path, capsys,
                                                                         monkeypatch):
    """An avatar under an ``instanceable`` prim (USD composes no override there): a real run refuses it
    before the fit, but a dry run said so only with the changes, after the fit (h82, stop 51: found inside
    the API). It is said in the dry run's checks before the work, as an existing output is (one line on
    stderr naming the prim and the fix); the changes are still printed and the exit status is 1. Told from
    the composed stage alone (its meshes with blend shapes and their targets), as the real run refuses it."""
    import usdface.api
    from usdface.errors import RigError
    from usdface.io.usd_rig import refuse_layer_over

    real, said = usdface.api.personalize_avatar, []

    def personalize(*args, **kwargs):     # what stderr held when the work began
        said.append(capsys.readouterr().err)
        return real(*args, **kwargs)

    monkeypatch.setattr(usdface.api, "personalize_avatar", personalize)
    shutil.copy(samples / "avatar.usda", tmp_path / "avatar.usda")
    shot = tmp_path / "shot.usda"
    shot.write_text('#usda 1.0\n(\n    defaultPrim = "Hero"\n    metersPerUnit = 0.01\n'
                    '    upAxis = "Y"\n)\n\ndef "Hero" (\n    prepend references = @./avatar.usda@\n'
                    '    instanceable = true\n)\n{\n}\n')
    refuse_layer_over(tmp_path / "avatar.usda")                        # the asset itself: fine
    with pytest.raises(RigError, match="instanceable prim /Hero"):
        refuse_layer_over(shot)
    out = tmp_path / "p.usda"
    base = ["personalize", str(shot), str(samples / "capture.usda"), "-o", str(out), "--dry-run", "-q"]
    assert main(base) == 1
    first = [line for line in said[-1].splitlines() if "would refuse" in line]
    assert len(first) == 1 and "instanceable prim /Hero" in first[0] and "instanceable = false" in first[0]
    text = capsys.readouterr().out
    assert "dry run:" in text and "a real run would refuse to write" in text and not out.exists()


_TRIANGLE = """
    def Mesh "{name}" (prepend apiSchemas = ["SkelBindingAPI"])
    {{
        point3f[] points = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]
        int[] faceVertexCounts = [3]
        int[] faceVertexIndices = [0, 1, 2]
        rel skel:skeleton = <{skel}>
        uniform token[] skel:blendShapes = ["jawOpen"]
        rel skel:blendShapeTargets = [<{at}/{name}/jawOpen>]
        def BlendShape "jawOpen"
        {{
            uniform vector3f[] offsets = [(0, -1, 0), (0, -1, 0), (0, -1, 0)]
        }}
    }}
"""
_STAGE = '#usda 1.0\n(\n    defaultPrim = "Root"\n    metersPerUnit = 0.01\n    upAxis = "Y"\n)\n'
_ROOT = 'def SkelRoot "Root"\n{\n    def Skeleton "Skel" {}\n'
_PROTO = 'def Xform "Proto"\n{' + _TRIANGLE.format(name="Head", skel="/Root/Skel", at="/Proto") + "}\n"
_FACE = _TRIANGLE.format(name="Face", skel="/Root/Skel", at="/Root")
#: (case, the avatar's text, the refusal's words or None): meshes reached through instances as the reader
#: reaches them (instance proxies), an inactive instance (skipped by both), one loaded as a payload, a mesh
#: that is itself the instance (its BlendShape child a proxy), a SkelRoot inside an instance
_LAYER_OVER_CASES = [
    ("instanced child", _STAGE + _ROOT + _FACE + '    def Xform "Lib" (instanceable = true\n'
     '        references = </Proto>)\n    {\n    }\n}\n' + _PROTO, "/Root/Lib/Head is inside"),
    ("inactive instance", _STAGE + _ROOT + _FACE + '    def Xform "Lib" (instanceable = true\n'
     '        active = false\n        references = </Proto>)\n    {\n    }\n}\n' + _PROTO, None),
    ("payload", _STAGE + _ROOT + _FACE + '    def Xform "Lib" (instanceable = true\n        payload = '
     '@./proto.usda@\n    )\n    {\n    }\n}\n', "/Root/Lib/Head is inside"),
    ("mesh is the instance", _STAGE + _ROOT + '    def "Head" (instanceable = true\n        references = '
     '</Proto/Head>)\n    {\n    }\n}\n' + _PROTO, "BlendShape /Root/Head/jawOpen is inside"),
    ("SkelRoot in an instance", _STAGE + 'def Xform "Root"\n{\n    def "Char" (instanceable = true\n'
     '        references = </Char>)\n    {\n    }\n}\ndef SkelRoot "Char"\n{\n    def Skeleton "Skel" {}\n'
     + _TRIANGLE.format(name="Head", skel="/Char/Skel", at="/Char") + "}\n", "/Root/Char/Head is inside"),
]


@pytest.mark.parametrize("case, text, refused", _LAYER_OVER_CASES, ids=[c[0] for c in _LAYER_OVER_CASES])
def test_the_dry_runs_early_refusal_agrees_with_the_readers(tmp_path, case, text, refused):
    """Stop 53 (h102): ``refuse_layer_over`` (a dry run's word before the fit, from the composed stage alone)
    and the real run's refusal after :func:`read_avatar` walk the same prims (SkelRoots through instance
    proxies, the default predicate: inactive and abstract prims skipped, payloads loaded, each mesh's
    forwarded BlendShape targets): they accept and refuse the same avatars with the same words."""
    from usdface.errors import RigError
    from usdface.io.usd_rig import read_avatar, refuse_instanced, refuse_layer_over, refuse_unwritable_shapes

    (tmp_path / "proto.usda").write_text(_STAGE.replace('"Root"', '"Proto"') + _PROTO)
    path = tmp_path / "avatar.usda"
    path.write_text(text)
    verdicts = []
    for check in (lambda: refuse_layer_over(path), lambda: (
            avatar := read_avatar(path, moving_only=True),         # as personalize reads and refuses it
            refuse_instanced(avatar, [m.key for m in avatar.meshes], "the personalized layer"),
            refuse_unwritable_shapes(avatar, None, "the personalized layer"))):
        try:
            check()
            verdicts.append(None)
        except RigError as exc:
            verdicts.append(exc.message)
    assert verdicts[0] == verdicts[1], verdicts
    assert (verdicts[0] is None) if refused is None else (refused in verdicts[0]), verdicts


def _studio_map(samples, tmp_path, channels: str, *options) -> dict:
    """The retarget JSON map of the sample avatar with its ``jawOpen`` channel in the ``skel:blendShapes``
    list that reads ``channels`` renamed ``JawDrop`` (a studio's name, mapped back by ``--name-map``)."""
    text = (samples / "avatar.usda").read_text().replace(channels, channels.replace('"jawOpen"', '"JawDrop"'))
    (tmp_path / "studio.usda").write_text(text)
    (tmp_path / "names.json").write_text('{"JawDrop": "jawOpen"}')
    out = tmp_path / "map.json"
    assert main(["retarget", str(tmp_path / "studio.usda"), str(samples / "capture.usda"), "-o", str(out),
                 "-q", "--name-map", str(tmp_path / "names.json"), *options]) == 0
    return json.loads(out.read_text())


def test_retarget_json_records_the_map_settings_and_the_avatar_channels(samples, tmp_path):
    """The JSON map says how it was solved (``meta``: the bounds and the ridge's centre beside ``mu``: an
    ``--unbounded --map-prior zero`` map read like the default one) and names the avatar's own channels
    (``target_channels``): with ``--name-map`` the targets are ARKit names the studio rig does not have, so
    an engine matching channels by name drove nothing for them."""
    doc = _studio_map(samples, tmp_path, '"jawRight", "jawOpen", "mouthClose"', "--unbounded", "--map-prior",
                      "zero", "--mu", "0.01")
    assert doc["meta"]["weight_bounds"] is None and doc["meta"]["map_prior"] == "zero"
    assert doc["meta"]["mu"] == 0.01 and doc["meta"]["mu_choice"] == "given"
    jaw = doc["target"].index("jawOpen")
    assert doc["target_channels"][jaw] == "JawDrop"
    assert [c for c, t in zip(doc["target_channels"], doc["target"], strict=True) if c != t] == ["JawDrop"]


def test_retarget_json_names_the_other_meshes_channels(samples, tmp_path):
    """The map's columns drive every mesh, but ``target_channels`` named only the face mesh's: a Blender
    export's teeth mesh (``jawOpen2``) or a studio's (``JawDrop``) had no names for an engine to drive
    (a trial). ``mesh_channels``: each other mesh's own channel per target, None where it has no such
    shape."""
    doc = _studio_map(samples, tmp_path, '"jawRight", "jawOpen", "tongueOut"]')
    mouth = doc["mesh_channels"]["/Avatar/Mouth"]
    assert len(mouth) == len(doc["target"]) and "/Avatar/Head" not in doc["mesh_channels"]
    assert {t: c for t, c in zip(doc["target"], mouth, strict=True) if c is not None} == {
        "jawForward": "jawForward", "jawLeft": "jawLeft", "jawRight": "jawRight", "jawOpen": "JawDrop",
        "tongueOut": "tongueOut"}
    assert doc["target_channels"][doc["target"].index("jawOpen")] == "jawOpen"      # the Head's own


def test_retarget_takes_the_fits_pins_and_the_face_mesh(samples, tmp_path, capsys):
    """``write_retarget_map(..., pins="pins.json")`` failed inside the fit ("pins mask has shape (),
    expected (52, 1233)": the file was never read), and ``usdface retarget`` offered neither ``--pins`` (a
    fit option: it changes the map) nor ``--face-mesh`` (the mesh whose shapes the map targets)."""
    from usdface import api

    pins = tmp_path / "pins.json"
    pins.write_text('{"pins": {"jawOpen": [1, 2, 3]}}')
    result = api.write_retarget_map(samples / "avatar.usda", samples / "capture.usda", tmp_path / "a.json",
                                    pins=str(pins))
    assert result.report["fit"]["pins"] == {"jawOpen": 3}
    assert result.out_path == tmp_path / "a.json"          # the map written (it was None: a user trial)
    args = ["retarget", str(samples / "avatar.usda"), str(samples / "capture.usda"), "-q"]
    assert main([*args, "-o", str(tmp_path / "b.json"), "--pins", str(pins), "--face-mesh", "Head"]) == 0
    doc = json.loads((tmp_path / "b.json").read_text())
    assert np.abs(np.array(doc["weights"]) - result.weights).max() <= 1e-6
    assert main([*args, "-o", str(tmp_path / "c.json"), "--face-mesh", "Nope"]) == 2
    assert "no mesh 'Nope'" in capsys.readouterr().err and not (tmp_path / "c.json").exists()


def test_retarget_says_which_capture_shapes_the_map_has_no_row_for(samples, tmp_path, capsys):
    """A studio avatar whose jawOpen is a channel (and prim) named ``JawDrop``, retargeted without a name
    map, wrote a map with no ``jawOpen`` row and said nothing (a user trial): the phone's jaw then drives
    nothing. ``personalize`` warns of the same skip; ``retarget`` now does too, with the fix."""
    (tmp_path / "studio.usda").write_text((samples / "avatar.usda").read_text().replace("jawOpen", "JawDrop"))
    out = tmp_path / "map.json"
    assert main(["retarget", str(tmp_path / "studio.usda"), str(samples / "capture.usda"), "-o", str(out),
                 "-q"]) == 0
    said = capsys.readouterr()
    assert "jawOpen" not in json.loads(out.read_text())["source"]
    text = said.out + said.err
    assert "capture shapes the avatar lacks (skipped): jawOpen" in text
    assert "the map has no row for jawOpen" in text and "--name-map" in text


def test_personalize_take_without_a_shapes_weights_says_it_stays_still(samples, tmp_path, capsys):
    """``personalize ... --take take.csv`` with a Live Link CSV that lacks the ``JawOpen`` column played the
    inspection animation with the jaw still and said nothing (a user trial)."""
    from usdface.arkit import ARKIT_NAMES

    names = [n[0].upper() + n[1:] for n in ARKIT_NAMES if n != "jawOpen"]
    rows = [f"00:00:00:{f:02d}.000,{len(names)}," + ",".join(["0.3" if f % 2 else "0.0"] * len(names))
            for f in range(6)]
    header = "Timecode,BlendShapeCount," + ",".join(names)
    (tmp_path / "take.csv").write_text("\n".join([header, *rows]) + "\n")
    args = ["personalize", str(samples / "avatar.usda"), str(samples / "capture.usda"), "--take",
            str(tmp_path / "take.csv"), "-q", "--json"]
    assert main([*args, "-o", str(tmp_path / "p.usda")]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert any("no weights for 1 of the avatar's ARKit shape(s): jawOpen; they stay still" in w
               for w in doc["warnings"])
    from usdface.io.usd_anim import write_animation_usd  # a take of no ARKit channel: said in one line

    keys = tmp_path / "keys.usda"
    write_animation_usd(keys, ["Key_1"], np.array([[0.0], [0.5], [0.0]]), np.arange(3) / 30.0)
    assert main([*args[:4], str(keys), "-q", "--json", "-o", str(tmp_path / "k.usda")]) == 0
    warned = json.loads(capsys.readouterr().out)["warnings"]
    assert any("none of the take's 1 weight channel(s) ('Key_1') is an ARKit shape" in w for w in warned)
    assert not any("eyeLookDownLeft" in w for w in warned if "take" in w)


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


def test_the_retarget_map_does_not_drive_the_tongue_to_match_a_few_face_rows(tmp_path):
    """``usdface retarget`` on the sample: the ``jawForward`` row took ``tongueOut`` at 0.82 (matching the
    lower lip's face rows; an engine driving every mesh with the map put the tongue out on every jaw slide).
    The map now holds what it drives on the other meshes at the namesake's motion (the Mouth mesh's rows):
    the tongue stays in, the namesake carries the row. With the paper's zero prior the face rows alone
    decide, as eq. (4)."""
    import json

    out = tmp_path / "map.json"
    assert main(["retarget", str(SAMPLES / "avatar.usda"), str(SAMPLES / "capture.usda"), "-o", str(out),
                 "-q"]) == 0
    doc = json.loads(out.read_text())
    row = dict(zip(doc["target"], doc["weights"][doc["source"].index("jawForward")], strict=True))
    assert row["tongueOut"] < 0.1 and row["jawForward"] > 0.95          # was 0.82 and 1.0
    tongue = [doc["weights"][j][doc["target"].index("tongueOut")] for j, s in enumerate(doc["source"])
              if s != "tongueOut"]
    assert max(tongue) < 0.1


def test_a_capture_with_too_few_shapes_is_named_not_the_avatar(tmp_path, capsys):
    """A capture of jawOpen alone was refused with 'only 1 of the capture's shapes exist on the avatar face
    mesh' naming the avatar, which has all 52; the capture is what is short."""
    from usdface.api import write_capture
    from usdface.model import Capture, Frames

    cap = _capture()
    k = list(cap.names).index("jawOpen")
    f = cap.frames
    one = Capture(cap.neutral, cap.triangles, cap.template.subset(["jawOpen"]),
                  Frames(f.points, f.weights[:, [k]], f.role, f.label), ["jawOpen"])
    path = tmp_path / "jaw_only.usda"
    write_capture(one, path)
    assert main(["personalize", str(A), str(path), "-o", str(tmp_path / "p.usda"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "jaw_only.usda" in err and "the capture has 1 shape(s) (jawOpen)" in err
    assert "avatar.usda" not in err


def test_inspect_of_a_capture_without_test_frames_says_no_animation(tmp_path, capsys):
    """User trial: with an empty test/ folder, personalize --inspect printed 'test-expression SkelAnimation'
    although it wrote none."""
    from usdface.api import write_capture
    from usdface.model import Capture, Frames

    cap = _capture()
    f = cap.frames
    keep = [i for i, r in enumerate(f.role) if r == "train"]
    train_only = Capture(cap.neutral, cap.triangles, cap.template,
                         Frames(f.points[keep], f.weights[keep], ["train"] * len(keep),
                                [f.label[i] for i in keep]), cap.names)
    path = tmp_path / "train_only.usda"
    write_capture(train_only, path)
    assert main(["personalize", str(A), str(path), "-o", str(tmp_path / "p.usda"), "--method", "dt",
                 "--inspect"]) == 0
    out = capsys.readouterr().out
    assert "no SkelAnimation (the capture has no test expressions" in out
    assert "usdfaceInspection" not in (tmp_path / "p.usda").read_text().split("SkelAnimation")[0][-200:]


def test_force_never_overwrites_the_input_capture(tmp_path, capfd):
    cap = tmp_path / "capture.usda"
    cap.write_bytes((SAMPLES / "capture.usda").read_bytes())
    before = cap.read_bytes()
    code = main(["personalize", str(SAMPLES / "avatar.usda"), str(cap), "-o", str(cap), "--force", "-q"])
    assert code == 2 and "overwrite an input" in capfd.readouterr().err
    assert cap.read_bytes() == before


def test_bad_take_fails_before_the_layer_is_written(tmp_path, capfd):
    """A bad --take used to fail after the layer was written (batch then called the item done)."""
    bad = tmp_path / "take.csv"
    bad.write_text("Timecode,BlendShapeCount,EyeBlinkLeft\n00:00:00:00.000,1,nan\n")
    out = tmp_path / "out.usda"
    code = main(["personalize", str(SAMPLES / "avatar.usda"), str(SAMPLES / "capture.usda"), "-o", str(out),
                 "--take", str(bad), "-q"])
    assert code == 2 and "NaN" in capfd.readouterr().err
    assert not out.exists()


def test_correspondence_cache_of_any_name(tmp_path):
    """``--correspondence corr.cache`` wrote a 0-byte file and a stray ``.corr.cache.*.tmp.cache.npz``."""
    from usdface.transfer.correspond import Correspondence, load_correspondence, save_correspondence

    corr = Correspondence(np.arange(4), np.full((4, 3), 1 / 3), np.zeros(4), np.ones(4, bool), np.arange(4),
                          np.ones(4), "key", {"a": 1})
    save_correspondence(corr, tmp_path / "corr.cache")
    assert [p.name for p in tmp_path.iterdir()] == ["corr.cache"]
    back = load_correspondence(tmp_path / "corr.cache", key="key")
    np.testing.assert_array_equal(back.triangle, corr.triangle)


def test_empty_correspondence_file_is_refused_before_work(tmp_path, capfd):
    (tmp_path / "c.npz").write_bytes(b"")
    code = main(["personalize", str(SAMPLES / "avatar.usda"), str(SAMPLES / "capture.usda"), "-o",
                 str(tmp_path / "o.usda"), "--correspondence", str(tmp_path / "c.npz"), "-q"])
    assert code == 2 and "not a usdface correspondence cache" in capfd.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.npz"]


def test_personalize_without_output_writes_to_the_cwd():
    from usdface.commands.personalize import _default_output

    assert _default_output("/assets/library/avatar.usdc") == Path("avatar.personalized.usda")


@pytest.mark.parametrize("command, module, writer, output, again_output", [
    ("personalize_avatar", "layers", "write_avatar_layer", "p.usda", "q.usda"),
    ("write_retarget_map", "atomic", "write_text_atomic", "map.json", "map2.csv"),
])
def test_a_failed_run_leaves_no_correspondence_cache(samples, tmp_path, monkeypatch, command, module, writer,
                                                     output, again_output):
    """A run that failed after the correspondence step (here: the write of its product, personalize's layer
    or ``usdface retarget``'s map) left its ``--correspondence`` cache behind, and the folder made for it:
    the one file of a failed run, for a next run to warn about (``cache: replaced``) when it was of a wrong
    ``--face-mesh``. The cache is written once the run succeeds; the next run writes it and reuses it."""
    import importlib

    import usdface
    from usdface.errors import UsdFaceError

    cache = tmp_path / "cache" / "c.npz"

    def broken(*args, **kwargs):
        raise UsdFaceError("the write failed")

    monkeypatch.setattr(importlib.import_module(f"usdface.io.{module}"), writer, broken)
    run = getattr(usdface, command)
    args = (samples / "avatar.usda", samples / "capture.usda", tmp_path / output)
    with pytest.raises(UsdFaceError, match="the write failed"):
        run(*args, correspondence=cache)
    assert not (tmp_path / "cache").exists() and not (tmp_path / output).exists()
    monkeypatch.undo()
    first = run(*args, correspondence=cache)
    assert cache.is_file() and first.report["correspondence"]["cache"] == "miss"
    again = run(*args[:2], tmp_path / again_output, correspondence=cache)
    assert again.report["correspondence"]["cache"] == "hit"


def test_a_retarget_cache_that_cannot_be_written_takes_the_new_map_with_it(samples, tmp_path, monkeypatch):
    """The map is written, then the ``--correspondence`` cache: a cache whose write failed (a full disk)
    left the new map behind, the one file of a failed run. The map goes with it (all or nothing, as the
    API's several outputs); a map that replaced an earlier one (``force``) stays."""
    import usdface
    from usdface.errors import UsdFaceError
    from usdface.transfer import correspond

    def broken(*args, **kwargs):
        raise UsdFaceError("the cache write failed")

    monkeypatch.setattr(correspond, "save_correspondence", broken)
    args = (samples / "avatar.usda", samples / "capture.usda", tmp_path / "map.json")
    with pytest.raises(UsdFaceError, match="the cache write failed"):
        usdface.write_retarget_map(*args, correspondence=tmp_path / "cache" / "c.npz")
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "map.json").write_text("{}")
    with pytest.raises(UsdFaceError, match="the cache write failed"):
        usdface.write_retarget_map(*args, correspondence=tmp_path / "cache" / "c.npz", force=True)
    assert [p.name for p in tmp_path.iterdir()] == ["map.json"]


def test_a_large_text_layer_is_noted_with_the_binary_alternative(tmp_path, capsys, monkeypatch):
    """The 225k-vertex head's layer written as .usda (as the README's examples name it) was 358 MB of text,
    100 MB as .usdc, and read back 2.2x slower by review, render and export: a note says so past 50 MB."""
    from usdface.commands import personalize

    monkeypatch.setattr(personalize, "TEXT_LAYER_NOTE_BYTES", 1000)
    for name, size in (("big.usda", 5000), ("small.usda", 500), ("big.usdc", 5000)):
        (tmp_path / name).write_bytes(b"#usda 1.0\n" + b" " * size)
        personalize._text_layer_note(tmp_path / name)
    out = capsys.readouterr().out
    assert out.count("note:") == 1 and "big.usda is 0 MB of text (.usda)" in out and "-o big.usdc" in out


def test_the_personalized_count_says_of_how_many_and_on_which_mesh(samples, tmp_path, capsys):
    """A user trial (stop 50): dev1 printed "51 shapes implanted" and then "47 BlendShapes personalized",
    read as 4 of the capture's shapes left out; the 47 were of 101 BlendShapes on two meshes (the head's 44
    of 51, the mouth's 3 of 50). The line says of how many, and per mesh, as the layer's variants show."""
    import re

    from usdface.io.flatten import read_avatar_variant

    out = tmp_path / "person.usda"
    assert main(["personalize", str(A), str(C), "-o", str(out), "-q"]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines() if "BlendShapes personalized" in ln)
    said = re.fullmatch(r"(\d+) of (\d+) BlendShapes personalized \((.*)\) -> (.*)", line)
    assert said and said.group(4) == str(out), line
    per_mesh = {m: (int(a), int(b)) for m, a, b in re.findall(r"(\S+) (\d+) of (\d+)", said.group(3))}
    generic, person = read_avatar_variant(out, "generic"), read_avatar_variant(out, "personalized")
    truth = {}
    for g, p in zip(generic.meshes, person.meshes, strict=True):
        moved = np.abs(np.asarray(p.deltas) - np.asarray(g.deltas)).max(axis=(1, 2)) > 1e-9
        truth[g.source.prim] = (int(moved.sum()), len(g.names))
    truth = {k: v for k, v in truth.items() if v[1]}                # the meshes with BlendShapes
    assert per_mesh == truth and len(truth) == 2, (line, truth)
    assert int(said.group(1)) == sum(a for a, _ in truth.values())
    assert int(said.group(2)) == sum(b for _, b in truth.values())
    assert 0 < int(said.group(1)) < int(said.group(2))
