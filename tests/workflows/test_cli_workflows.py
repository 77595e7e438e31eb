"""The documented command chains, run as subprocesses exactly as README.md and docs/ show them (issue 11).

Each test checks the exit status, that every output opens in USD and passes ``usdface check``, that no
temporary file is left and that the inputs are byte-identical afterwards. The sample set is made once per
session with ``usdface sample DIR --folder``; the ``shared`` tests use the bench cases when ../shared exists.
"""

from __future__ import annotations

import json

import pytest
from wfutil import assert_valid_usd, digest, no_temp_left, run


@pytest.fixture(scope="module")
def take_files(sample_take, tmp_path_factory):
    """A continuous take of the sample person (``take.usda``, USD take with template) and its weights as a
    Live Link Face CSV (``take.csv``), as a phone app would record them."""
    from usdface.io.livelink import write_livelink_csv
    from usdface.io.take import write_take_usd

    take = sample_take
    d = tmp_path_factory.mktemp("take")
    write_take_usd(take, d / "take.usda")
    write_livelink_csv(d / "take.csv", take.names, take.weights[:40], take.times[:40])
    return d


@pytest.mark.parametrize("ext,exact", [(".usda", True), (".usdc", False)])
def test_capture_import_then_personalize(sample_set, tmp_path, ext, exact):
    """README/docs: ``usdface capture import DIR -o capture.usda`` then ``usdface personalize AVATAR
    capture.usda -o OUT`` (the flow that crashed with 'array is not writeable')."""
    before = digest(sample_set / "avatar.usda", sample_set / "capture")
    cap = f"capture{ext}"
    run("capture", "import", sample_set / "capture", "-o", cap, *([] if exact else ["--no-exact"]),
        cwd=tmp_path)
    assert_valid_usd(tmp_path / cap, checked=False)
    run("personalize", sample_set / "avatar.usda", cap, "-o", "person.usda", "-q", cwd=tmp_path)
    assert_valid_usd(tmp_path / "person.usda")
    run("check", "person.usda", cwd=tmp_path)
    assert digest(sample_set / "avatar.usda", sample_set / "capture") == before
    no_temp_left(tmp_path)


def test_retarget_and_fit_from_imported_capture(sample_set, tmp_path):
    before = digest(sample_set / "avatar.usda", sample_set / "capture.usda")
    run("capture", "import", sample_set / "capture", "-o", "capture.usdc", cwd=tmp_path)
    run("retarget", sample_set / "avatar.usda", "capture.usdc", "-o", "map.json", cwd=tmp_path)
    data = json.loads((tmp_path / "map.json").read_text())  # strict JSON: no NaN literals
    assert data
    run("fit", "capture.usdc", "-o", "rig.usda", "--method", "dt", cwd=tmp_path)
    assert_valid_usd(tmp_path / "rig.usda", checked=False)
    assert digest(sample_set / "avatar.usda", sample_set / "capture.usda") == before
    no_temp_left(tmp_path)


def test_capture_select_then_personalize(sample_set, take_files, tmp_path):
    """docs/takes.md: ``usdface capture select take.usda -o capture.usda`` then personalize."""
    before = digest(take_files, sample_set / "avatar.usda")
    proc = run("capture", "select", take_files / "take.usda", "-o", "capture.usda", cwd=tmp_path)
    assert f"wrote {tmp_path / 'capture.usda'}" in proc.stdout          # the written path, absolute
    run("personalize", sample_set / "avatar.usda", "capture.usda", "-o", "person.usda", "-q", cwd=tmp_path)
    assert_valid_usd(tmp_path / "person.usda")
    assert digest(take_files, sample_set / "avatar.usda") == before
    no_temp_left(tmp_path)


def test_anim_import_then_personalize_take(sample_set, take_files, tmp_path):
    """docs/pipeline.md: ``usdface anim import take.csv -o take.usda``, then ``personalize --take take.usda``
    (refused before: 'no mesh with time-sampled points')."""
    before = digest(take_files, sample_set / "avatar.usda", sample_set / "capture.usda")
    run("anim", "import", take_files / "take.csv", "-o", "take.usda", cwd=tmp_path)
    assert_valid_usd(tmp_path / "take.usda", checked=False)
    run("personalize", sample_set / "avatar.usda", sample_set / "capture.usda", "-o", "person.usda", "-q",
        "--take", "take.usda", cwd=tmp_path)
    assert_valid_usd(tmp_path / "person.usda")
    assert digest(take_files, sample_set / "avatar.usda", sample_set / "capture.usda") == before
    no_temp_left(tmp_path)


def test_landmarks_check_render_inspect(sample_set, tmp_path):
    """docs/landmarks.md, docs/pipeline.md: landmarks -o/--json, check, inspect, render."""
    before = digest(sample_set / "avatar.usda")
    run("landmarks", sample_set / "avatar.usda", "-o", "landmarks.usda", "--json", "layout.json",
        cwd=tmp_path)
    assert_valid_usd(tmp_path / "landmarks.usda", checked=False)
    assert json.loads((tmp_path / "layout.json").read_text())
    run("check", sample_set / "avatar.usda", cwd=tmp_path)
    report = json.loads(run("check", sample_set / "avatar.usda", "--json", cwd=tmp_path).stdout)
    assert report["ok"]
    run("inspect", sample_set / "avatar.usda", cwd=tmp_path)
    run("render", sample_set / "avatar.usda", "-o", "shapes.png", "--shapes", "jawOpen,eyeBlinkLeft",
        cwd=tmp_path)
    assert (tmp_path / "shapes.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert digest(sample_set / "avatar.usda") == before
    no_temp_left(tmp_path)


def test_batch_with_manifest(sample_set, tmp_path):
    """docs/pipeline.md#batch: a CSV manifest with relative paths; rerun skips the finished item."""
    run("capture", "import", sample_set / "capture", "-o", "capture.usda", cwd=tmp_path)
    (tmp_path / "people.csv").write_text(f"avatar,capture,output\n{sample_set / 'avatar.usda'},capture.usda,"
                                         "out/anna.usda\n")
    before = digest(sample_set / "avatar.usda", tmp_path / "capture.usda")
    run("batch", "people.csv", "-j", "1", cwd=tmp_path)
    report = json.loads((tmp_path / "people.report.json").read_text())
    assert [i["status"] for i in report["items"]] == ["done"], report
    assert_valid_usd(tmp_path / "out" / "anna.usda")
    assert digest(sample_set / "avatar.usda", tmp_path / "capture.usda") == before
    no_temp_left(tmp_path)


@pytest.mark.shared
@pytest.mark.parametrize("case", ["dev1", "dev2", "dev3"])
def test_bench_capture_import_then_personalize(bench_case, tmp_path, case):
    d = bench_case / case
    before = digest(d / "avatar.usdc", d / "capture")
    run("capture", "import", d / "capture", "-o", "capture.usdc", cwd=tmp_path)
    run("personalize", d / "avatar.usdc", "capture.usdc", "-o", "person.usdc", "-q", "--method", "dt",
        cwd=tmp_path)
    assert_valid_usd(tmp_path / "person.usdc")
    assert digest(d / "avatar.usdc", d / "capture") == before
    no_temp_left(tmp_path)


@pytest.mark.shared
def test_bench_blender_export(bench_case, tmp_path):
    d = bench_case / "dev1"
    before = digest(d / "avatar_blender.usdc")
    run("inspect", d / "avatar_blender.usdc", cwd=tmp_path)
    run("personalize", d / "avatar_blender.usdc", d / "capture", "-o", "person.usda", "-q", "--method", "dt",
        cwd=tmp_path)
    assert_valid_usd(tmp_path / "person.usda")
    assert digest(d / "avatar_blender.usdc") == before
    no_temp_left(tmp_path)


def test_studio_named_avatar_needs_the_name_map_once(sample_set, tmp_path):
    """README "studio names": personalize a studio-named avatar with ``--name-map``; the layer records the
    map (and the map file's digest), so ``check`` and ``render`` of the layer need no ``--name-map`` again
    (check reported the layer's jawOpen missing, render "rig Head has no shape 'jawOpen'")."""
    renamed = {"jawOpen": "JawDrop", "eyeBlinkLeft": "Blink_L", "eyeBlinkRight": "Blink_R"}
    text = (sample_set / "avatar.usda").read_text()
    lines = []
    for line in text.splitlines():
        if "blendShapes = [" in line:
            for a, b in renamed.items():
                line = line.replace(f'"{a}"', f'"{b}"')
        lines.append(line)
    (tmp_path / "studio.usda").write_text("\n".join(lines) + "\n")
    (tmp_path / "names.json").write_text(json.dumps({b: a for a, b in renamed.items()}))
    before = digest(tmp_path / "studio.usda", tmp_path / "names.json")
    run("personalize", "studio.usda", sample_set / "capture.usda", "--name-map", "names.json", "-o",
        "studio_p.usda", "-q", cwd=tmp_path)
    from pxr import Usd

    stage = Usd.Stage.Open(str(tmp_path / "studio_p.usda"))
    data = dict(stage.GetRootLayer().customLayerData)["usdface"]
    assert dict(data["nameMap"]) == {b: a for a, b in renamed.items()}
    assert any(str(p).endswith("names.json") for p in data["inputs"])
    report = json.loads(run("check", "studio_p.usda", "--json", cwd=tmp_path).stdout)
    assert report["ok"], report
    run("render", "studio_p.usda", "--compare", "--shapes", "jawOpen", "-o", "c.png", cwd=tmp_path)
    run("render", "studio_p.usda", "--compare", "-o", "c2.png", cwd=tmp_path)  # the generic with the map too
    run("render", "studio_p.usda", "--heatmap", "-o", "h.png", cwd=tmp_path)
    run("landmarks", "studio_p.usda", "-o", "lm.usda", "-q", cwd=tmp_path)       # a layer over the layer
    assert json.loads(run("check", "lm.usda", "--json", cwd=tmp_path).stdout)["ok"]
    run("landmarks", "studio.usda", "--name-map", "names.json", "-o", "lm_s.usda", "-q", cwd=tmp_path)
    assert json.loads(run("check", "lm_s.usda", "--json", cwd=tmp_path).stdout)["ok"]
    assert digest(tmp_path / "studio.usda", tmp_path / "names.json") == before


def test_layers_stacked_over_usdface_layers(sample_set, tmp_path):
    """A landmarks layer over the plain avatar personalizes like the avatar (it was refused as "already
    personalized"); a landmarks layer over that personalized layer is refused, naming the unpersonalized
    layer under both, and ``render --compare`` compares with it (it compared the personalized layer with
    itself as "generic"); a second layout over a layer that has one replaces it (it crashed)."""
    from usdface.io.usd_rig import generic_input

    avatar, capture = sample_set / "avatar.usda", sample_set / "capture.usda"
    run("landmarks", avatar, "-o", "lm.usda", "-q", cwd=tmp_path)
    run("personalize", "lm.usda", capture, "-o", "p.usda", "-q", cwd=tmp_path)
    run("landmarks", "p.usda", "-o", "lm_p.usda", "-q", cwd=tmp_path)
    assert generic_input(tmp_path / "lm_p.usda") == (tmp_path / "lm.usda").resolve()
    assert generic_input(tmp_path / "lm.usda") == avatar.resolve()
    again = run("personalize", "lm_p.usda", capture, "-o", "pp.usda", cwd=tmp_path, ok=False)
    assert again.returncode == 2 and "already personalized" in again.stderr
    assert str((tmp_path / "lm.usda").resolve()) in again.stderr
    assert not (tmp_path / "pp.usda").exists()


def test_provenance_covers_the_layers_the_avatar_composes(sample_set, tmp_path):
    """A shot that references the avatar: the layer's provenance records the referenced avatar's digest
    too, so ``check`` notices when that file changes after personalizing (it hashed only the shot)."""
    import shutil

    shutil.copy(sample_set / "avatar.usda", tmp_path / "avatar.usda")
    (tmp_path / "shot.usda").write_text(
        '#usda 1.0\n(\n    defaultPrim = "Hero"\n    metersPerUnit = 0.01\n    upAxis = "Y"\n)\n\n'
        'def "Hero" (\n    prepend references = @./avatar.usda@\n)\n{\n}\n')
    run("personalize", "shot.usda", sample_set / "capture.usda", "-o", "p.usda", "-q", cwd=tmp_path)
    clean = json.loads(run("check", "p.usda", "--json", cwd=tmp_path).stdout)
    assert not [i for i in clean["issues"] if "changed" in i["message"]]
    with open(tmp_path / "avatar.usda", "a") as f:
        f.write("\n")                                       # an edit of the referenced avatar
    edited = json.loads(run("check", "p.usda", "--json", cwd=tmp_path).stdout)
    assert [i for i in edited["issues"] if "avatar.usda" in i["message"] and "changed" in i["message"]]
