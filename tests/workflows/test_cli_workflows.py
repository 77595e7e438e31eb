"""The documented command chains, run as subprocesses exactly as README.md and docs/ show them (issue 11).

Each test checks the exit status, that every output opens in USD and passes ``usdface check``, that no
temporary file is left and that the inputs are byte-identical afterwards. The sample set is made once per
session with ``usdface sample DIR --folder``; the ``shared`` tests use the bench cases when ../shared exists.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

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


def test_fit_summary_says_which_optional_steps_ran(sample_set, tmp_path):
    """A TD's trial: ``fit --no-amplitude`` printed the default's summary line word for word (method, reg,
    train RMSE): nothing told what the option changed. The summary names each optional step and what it did
    (switched off, applied, or on and not applied with the reason), and --json carries the same record."""
    def steps(*options):
        text = run("fit", sample_set / "capture.usda", "-o", "rig.usda", "--force", "-q", *options,
                   cwd=tmp_path).stdout
        line = next((x for x in text.splitlines() if x.startswith("steps: ")), None)
        assert line, text
        return line

    default, no_amplitude = steps(), steps("--no-amplitude")
    assert default != no_amplitude
    assert "amplitude applied" in default and "amplitude off" in no_amplitude, (default, no_amplitude)
    assert default.replace("amplitude applied", "amplitude off") == no_amplitude
    other = steps("--no-align", "--no-reweight", "--contact", "off", "--weak-prior")
    for said in ("alignment off", "weight re-estimation off", "contact off", "weak prior applied"):
        assert said in other, other
    for said in ("alignment ", "weight re-estimation ", "contact ", "weak prior off"):
        assert said in default, default
    doc = json.loads(run("fit", sample_set / "capture.usda", "-o", "rig.usda", "--force", "-q", "--json",
                         "--no-amplitude", cwd=tmp_path).stdout)
    assert doc["steps"]["amplitude"] == "off" and set(doc["steps"]) == {
        "align", "reweight", "contact", "amplitude", "weak_prior"}
    assert "steps: alignment" in run("fit", sample_set / "capture.usda", "-o", "rig.usda", "--force", "-q",
                                     "--method", "ebfr", cwd=tmp_path).stdout


def test_imports_name_their_output_after_the_input_without_o(sample_set, take_files, tmp_path):
    """A TD's trial (stop 53): ``capture import`` and ``anim import`` required ``-o`` where ``personalize``
    and ``review`` name their output after the input. The two imports now do, as personalize does: in the
    current folder, never beside the source (``capture/`` -> ``capture.usda``, ``take.csv`` ->
    ``take.usda``); an existing one is refused without --force, and a default that is the input itself
    (a capture file rewritten in its own folder) is refused, not overwritten."""
    before = digest(sample_set / "capture", take_files / "take.csv")
    proc = run("capture", "import", sample_set / "capture", "-q", cwd=tmp_path)
    assert (tmp_path / "capture.usda").is_file() and "capture.usda:" in proc.stdout, proc.stdout
    assert_valid_usd(tmp_path / "capture.usda", checked=False)
    run("personalize", sample_set / "avatar.usda", "capture.usda", "-q", cwd=tmp_path)   # its default, too
    assert (tmp_path / "avatar.personalized.usda").is_file()
    refused = run("capture", "import", sample_set / "capture", "-q", cwd=tmp_path, ok=False)
    assert refused.returncode == 2 and "--force" in refused.stderr, refused.stderr
    same = run("capture", "import", "capture.usda", "-q", "--force", cwd=tmp_path, ok=False)
    assert same.returncode == 2 and "input" in same.stderr, same.stderr
    proc = run("anim", "import", take_files / "take.csv", "-q", cwd=tmp_path)
    assert (tmp_path / "take.usda").is_file() and "take.usda:" in proc.stdout, proc.stdout
    assert digest(sample_set / "capture", take_files / "take.csv") == before
    no_temp_left(tmp_path)


def test_imports_default_names_for_a_folder_given_as_dot(sample_set, take_files, tmp_path):
    """Stop 53 (h102): ``capture import .`` run inside the capture folder named its default after the
    folder's real name but in the current folder, inside the input: refused with 'write it outside .', the
    user left to guess ``-o``. The rule kept (docs/capture-format.md): the default stays in the current
    folder; the refusal's fix names the exact ``-o`` beside the input folder, and that command works.
    ``anim import .`` (any folder) defaulted to ``.usda`` and was told it was a hidden file's name (a
    folder whose ``<name>.usda`` existed: that it exists): now refused as no CSV, before the output."""
    import shutil

    cap = tmp_path / "cap"
    shutil.copytree(sample_set / "capture", cap)
    before = digest(cap, take_files / "take.csv")
    refused = run("capture", "import", ".", "-q", cwd=cap, ok=False)
    assert refused.returncode == 2 and "-o ../cap.usda" in refused.stderr, refused.stderr
    assert "input folder . (cap)" in refused.stderr, refused.stderr
    run("capture", "import", ".", "-q", "-o", "../cap.usda", cwd=cap)          # the fix, pasted
    assert_valid_usd(tmp_path / "cap.usda", checked=False)
    for where, arg in ((cap, "."), (tmp_path, "cap")):          # cap.usda exists beside 'cap': not named
        proc = run("anim", "import", arg, "-q", cwd=where, ok=False)
        assert proc.returncode == 2 and "Live Link CSV is a folder" in proc.stderr, proc.stderr
        assert "pass the .csv" in proc.stderr, proc.stderr
    proc = run("anim", "import", take_files, "-q", cwd=tmp_path, ok=False)      # a take folder: its CSV named
    assert proc.returncode == 2 and str(take_files / "take.csv") in proc.stderr, proc.stderr
    assert not list(cap.glob(".usda")) and not (tmp_path / ".usda").exists()
    assert digest(cap, take_files / "take.csv") == before
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


def test_the_same_batch_run_twice_at_once_keeps_both_runs_work(sample_set, tmp_path):
    """Stop 53 (h102): one manifest given to two ``usdface batch`` at once (two shells, a farm's retry):
    the end-of-batch clean-up (the output folders a run made, taken away when empty; a failed item's output
    set aside; the report) must not delete or clobber the other run's work in progress. Every output ends
    finished, valid and in place (none moved to ``.failed``), no temporary file is left, the shared
    report is one run's whole JSON, and a third run skips every row."""
    import subprocess

    from wfutil import usdface_cmd

    run("capture", "import", sample_set / "capture", "-o", "capture.usda", cwd=tmp_path)
    rows = "".join(f"{sample_set / 'avatar.usda'},capture.usda,out/{n}.usda,true\n" for n in ("anna", "ben"))
    (tmp_path / "people.csv").write_text("avatar,capture,output,review\n" + rows)
    env = dict(os.environ, COLUMNS="100")
    procs = [subprocess.Popen(usdface_cmd() + ["batch", "people.csv", "-j", "1", "-q"], cwd=tmp_path, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    said = [p.communicate(timeout=600) for p in procs]
    for p, (_, err) in zip(procs, said, strict=True):
        assert p.returncode in (0, 1) and "Traceback" not in err, err
    report = json.loads((tmp_path / "people.report.json").read_text())
    for item in report["items"]:       # the run that lost a row's race says so; the row is the other's
        assert item["status"] == "done" or "written meanwhile by another run" in item["error"], item
    for name in ("anna", "ben"):
        assert_valid_usd(tmp_path / "out" / f"{name}.usda")
        assert (tmp_path / "out" / f"{name}.review.html").is_file()
    assert not list((tmp_path / "out").glob("*.failed")), sorted(os.listdir(tmp_path / "out"))
    no_temp_left(tmp_path)
    again = run("batch", "people.csv", "-j", "1", "-q", cwd=tmp_path)
    report = json.loads((tmp_path / "people.report.json").read_text())
    assert [i["status"] for i in report["items"]] == ["skipped", "skipped"], (report, again.stdout)


def test_batch_manifest_review_column_writes_the_pages(sample_set, tmp_path):
    """docs/pipeline.md#batch: the manifest a Pyblish publish reads, with its ``review`` column, given to
    ``usdface batch`` (a TD's trial, stop 52: refused as 'unknown personalize option(s): review'): each row
    with review true gets ``<layer>.review.html`` beside its layer, made from that layer, and the report
    names it; a row with review false gets none."""
    (tmp_path / "people.csv").write_text(
        "avatar,capture,output,method,review\n"
        f"{sample_set / 'avatar.usda'},{sample_set / 'capture.usda'},out/anna.usda,menzel,true\n"
        f"{sample_set / 'avatar.usda'},{sample_set / 'capture.usda'},out/ben.usda,menzel,false\n")
    before = digest(sample_set / "avatar.usda", sample_set / "capture.usda")
    run("batch", "people.csv", "-j", "1", "-q", cwd=tmp_path)
    report = json.loads((tmp_path / "people.report.json").read_text())
    assert [(i["status"], Path(i["review"]).name if i["review"] else "") for i in report["items"]] == \
        [("done", "anna.review.html"), ("done", "")], report
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["anna.review.html", "anna.usda",
                                                                    "ben.usda"]
    page = (tmp_path / "out" / "anna.review.html").read_text(encoding="utf-8")
    assert page.lstrip().lower().startswith("<!doctype html") and "anna.usda" in page
    assert digest(sample_set / "avatar.usda", sample_set / "capture.usda") == before
    no_temp_left(tmp_path)


def test_batch_resumed_with_a_review_column_added_writes_the_pages_alone(sample_set, tmp_path):
    """docs/pipeline.md#batch, Resume (a TD's trial, stop 53): a manifest run, then given the ``review``
    column its Pyblish publish reads: the next ``usdface batch`` refused every finished row as a
    ``StaleOutput``; it writes the missing page beside each layer and leaves the layers as they were.
    ``--force`` then redoes every row, also the one whose ``force`` column is false (it failed
    'output layer exists')."""
    rows = [f"{sample_set / 'avatar.usda'},{sample_set / 'capture.usda'},out/{name}.usda"
            for name in ("anna", "ben")]
    (tmp_path / "people.csv").write_text("avatar,capture,output\n" + "\n".join(rows) + "\n")
    run("batch", "people.csv", "-j", "1", "-q", cwd=tmp_path)
    layers = {n: (tmp_path / "out" / f"{n}.usda").read_bytes() for n in ("anna", "ben")}
    (tmp_path / "people.csv").write_text("avatar,capture,output,review,force\n"
                                         f"{rows[0]},true,false\n{rows[1]},false,\n")
    proc = run("batch", "people.csv", "-j", "1", cwd=tmp_path)
    assert "anna.review.html (the review page of anna.usda alone) done" in proc.stderr, proc.stderr
    report = json.loads((tmp_path / "people.report.json").read_text())
    assert [(i["status"], Path(i["review"]).name if i["review"] else "") for i in report["items"]] == \
        [("done", "anna.review.html"), ("skipped", "")], report
    assert {n: (tmp_path / "out" / f"{n}.usda").read_bytes() for n in layers} == layers
    page = (tmp_path / "out" / "anna.review.html").read_text(encoding="utf-8")
    assert page.lstrip().lower().startswith("<!doctype html") and "anna.usda" in page
    run("batch", "people.csv", "-j", "1", "-q", "--force", cwd=tmp_path)
    report = json.loads((tmp_path / "people.report.json").read_text())
    assert [i["status"] for i in report["items"]] == ["done", "done"], report
    no_temp_left(tmp_path)


@pytest.mark.shared
def test_batch_resume_writing_a_page_alone_does_not_warn_again(bench_case, tmp_path):
    """A TD's trial (stop 53): dev3 batched, then the manifest given its ``review`` column: the resume wrote
    the page alone and printed the capture's repeated-frames warning again, as if the capture had been fitted
    anew. It had been: the page refitted the capture the layer records because the row named it (a given
    capture counted as another one). The page now scores the layer's own figures, as ``usdface review``
    does, and the resume prints no warning of the earlier run's."""
    run("capture", "import", bench_case / "dev3" / "capture", "-o", "capture.usda", "-q", cwd=tmp_path)
    row = f"{bench_case / 'dev3' / 'avatar.usdc'},capture.usda,out/d3.usda"
    (tmp_path / "m.csv").write_text(f"avatar,capture,output\n{row}\n")
    first = run("batch", "m.csv", "-j", "1", "-q", cwd=tmp_path)
    assert "repeat another frame exactly" in first.stderr + first.stdout    # the capture's, said once
    (tmp_path / "m.csv").write_text(f"avatar,capture,output,review\n{row},true\n")
    proc = run("batch", "m.csv", "-j", "1", cwd=tmp_path)
    assert "d3.review.html (the review page of d3.usda alone) done" in proc.stderr, proc.stderr
    assert "warning" not in (proc.stderr + proc.stdout).lower(), proc.stderr
    report = json.loads((tmp_path / "m.report.json").read_text())
    assert report["items"][0]["warnings"] == [], report
    page = (tmp_path / "out" / "d3.review.html").read_text(encoding="utf-8")
    assert "(mm; the layer&#x27;s fit" in page and " refit)" not in page


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


def test_review_of_a_landmarks_layer_reviews_the_personalization_under_it(sample_set, tmp_path):
    """``review`` of a landmark layout stacked over a personalize layer (``landmarks p.usda -o lm.usda``)
    plays and scores the capture that personalize layer records, found relative to it (it took the
    landmarks layer's second input, the avatar, for the capture: "the capture recorded in the layer's
    provenance (avatar.usda) was not found", and the page had no test expressions, eq. 5 table or
    registration)."""
    import re
    import shutil

    for name in ("avatar.usda", "capture.usda"):
        shutil.copy(sample_set / name, tmp_path / name)
    run("personalize", "avatar.usda", "capture.usda", "-o", "pers/p.usda", "-q", cwd=tmp_path)
    run("landmarks", "pers/p.usda", "-o", "lm.usda", "-q", cwd=tmp_path)
    proc = run("review", "lm.usda", "-q", cwd=tmp_path)
    assert "not found" not in proc.stdout + proc.stderr, proc.stdout
    page = (tmp_path / "lm.review.html").read_text(encoding="utf-8")
    assert "<caption>eq. 5 on the capture" in page and "<caption>registration" in page
    assert re.search(r'"title":\s*"test expressions"', page)


@pytest.mark.parametrize("argv", [
    ["export", "p.usda", "--gltf", "p.glb"],
    ["review", "p.usda"],
    ["render", "p.usda", "--compare", "-o", "c.png"],
    ["personalize", "p.usda", "capture.usda", "-o", "again.usda"],
    ["retarget", "p.usda", "capture.usda", "-o", "map.json"],
])
def test_a_layer_whose_avatar_moved_is_refused_in_one_line(sample_set, tmp_path, argv):
    """A layer whose avatar was moved away (a layer copied without it): one line naming the missing sublayer
    and the fix, and nothing written. ``export``, ``review``, ``personalize`` and ``retarget`` printed USD's
    own ``Warning: in _ReportErrors at line 3326 of .../stage.cpp -- Could not load sublayer ...`` first
    (a stage opened for a check before the reader, without its diagnostics held back)."""
    import shutil

    for name in ("avatar.usda", "capture.usda"):
        shutil.copy(sample_set / name, tmp_path / name)
    run("personalize", "avatar.usda", "capture.usda", "-o", "p.usda", "-q", cwd=tmp_path)
    (tmp_path / "avatar.usda").rename(tmp_path / "moved.usda")
    before = sorted(os.listdir(tmp_path))
    proc = run(*argv, "-q", cwd=tmp_path, ok=False)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Could not load sublayer" in lines[0] and "(fix: " in lines[0], proc.stderr
    assert sorted(os.listdir(tmp_path)) == before


@pytest.mark.parametrize("argv", [["review", "lm.usda"], ["export", "lm.usda", "--gltf", "lm.glb"]])
def test_a_layer_over_a_layer_whose_avatar_moved_is_refused_in_one_line(sample_set, tmp_path, argv):
    """A landmark layout stacked over a personalize layer whose avatar was moved away: the missing sublayer
    named in one line, as for the personalize layer itself. ``review`` printed USD's ``Could not load
    sublayer`` warning and then said the layout overrides ``/Avatar``, "which ./p.usda no longer has" (the
    prims were in the lost avatar, not gone from it)."""
    import shutil

    for name in ("avatar.usda", "capture.usda"):
        shutil.copy(sample_set / name, tmp_path / name)
    run("personalize", "avatar.usda", "capture.usda", "-o", "p.usda", "-q", cwd=tmp_path)
    run("landmarks", "p.usda", "-o", "lm.usda", "-q", cwd=tmp_path)
    (tmp_path / "avatar.usda").rename(tmp_path / "moved.usda")
    before = sorted(os.listdir(tmp_path))
    proc = run(*argv, "-q", cwd=tmp_path, ok=False)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Could not load sublayer" in lines[0], lines
    assert "no longer has" not in lines[0], lines
    assert sorted(os.listdir(tmp_path)) == before


def test_a_capture_folder_copied_from_a_mac_reads_as_the_original(sample_set, tmp_path):
    """macOS leaves an AppleDouble file (``._jawOpen.obj``, binary) beside every file it copies to a
    non-Apple disk, and ``.DS_Store`` in each folder: they are not the capture's. ``capture import`` and
    ``personalize`` refused the folder ("the same shape has several template files: ._jawOpen.obj,
    jawOpen.obj"; in train/, "._000.obj: not a text OBJ file"); now it reads as the original does."""
    import shutil

    mac = tmp_path / "from mac"
    shutil.copytree(sample_set / "capture", mac)
    for f in [p for p in mac.rglob("*") if p.is_file()]:
        (f.parent / f"._{f.name}").write_bytes(b"\x00\x05\x16\x07\x00\x02\x00\x00Mac OS X        ")
    for d in [mac, *[p for p in mac.rglob("*") if p.is_dir()]]:
        (d / ".DS_Store").write_bytes(b"\x00\x00\x00\x01Bud1")
    run("capture", "import", sample_set / "capture", "-o", "clean.usda", "-q", cwd=tmp_path)
    run("capture", "import", mac, "-o", "mac.usda", "-q", cwd=tmp_path)
    clean, copied = (json.loads(run("inspect", f, "--json", cwd=tmp_path).stdout)
                     for f in ("clean.usda", "mac.usda"))
    assert copied["frames"] == clean["frames"] and copied["roles"] == clean["roles"]
    assert copied["vertices"] == clean["vertices"]
    run("personalize", sample_set / "avatar.usda", mac, "-o", "p.usda", "-q", cwd=tmp_path)
    assert_valid_usd(tmp_path / "p.usda")


@pytest.mark.parametrize("renamed", ["template/jawOpen.obj", "train/000_eyeBlinkLeft.obj", "neutral.obj"])
def test_an_upper_case_extension_in_a_capture_folder_is_named(sample_set, tmp_path, renamed):
    """A capture folder with ``.OBJ`` files (some Windows tools): the reader takes ``*.obj``, so
    ``template/jawOpen.OBJ`` was left out without a word (the capture imported without jawOpen, its frames'
    weights set aside), a frame's ``.OBJ`` was "no scan" beside its ``.json``, and ``neutral.OBJ`` "missing
    neutral.obj". Refused, naming the file and the rename; nothing written."""
    import shutil

    folder = tmp_path / "capture"
    shutil.copytree(sample_set / "capture", folder)
    path = folder / renamed
    path.rename(path.with_suffix(".OBJ"))
    for argv in (["capture", "import", "capture", "-o", "c.usda"],
                 ["personalize", sample_set / "avatar.usda", "capture", "-o", "p.usda"]):
        proc = run(*argv, "-q", cwd=tmp_path, ok=False)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
        assert f"{path.stem}.OBJ" in proc.stderr and f"(e.g. {path.name})" in proc.stderr, proc.stderr
    assert sorted(os.listdir(tmp_path)) == ["capture"]


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


def _livelink_take(kind, take_files, tmp_path):
    """The Live Link Face CSV the chain plays: the generated take's (always there) or a real recording from
    ../shared (skipped without it)."""
    import shutil

    from wfutil import SHARED

    if kind == "generated":
        return shutil.copy(take_files / "take.csv", tmp_path / "take.csv")
    real = SHARED / "data" / "livelinkface" / "facial.csv"
    if not real.exists():
        pytest.skip("../shared data not present")
    return shutil.copy(real, tmp_path / "take.csv")


@pytest.mark.parametrize("kind", ["generated", pytest.param("livelink", marks=pytest.mark.shared)])
def test_documented_chain_from_capture_folder_to_retarget(sample_set, take_files, tmp_path, kind):
    """README's command table and docs/ as one session, through the CLI on files: ``capture import`` ->
    ``personalize`` -> ``anim import`` -> ``personalize --take`` -> ``review`` -> ``check`` -> ``retarget``.
    Each step is only covered alone elsewhere; here every step reads what the one before wrote, as a user's
    session does, and what each gives is checked: the layer is closer to the person than the avatar, the take
    plays after the test expressions in usdview and on the review page (without --take again: the layer
    records it), the result checks clean, and the map's weights are the documented [0, 1]."""
    import numpy as np

    from usdface.io import read_capture
    from usdface.io.usd_rig import read_avatar

    avatar, folder = sample_set / "avatar.usda", sample_set / "capture"
    csv = _livelink_take(kind, take_files, tmp_path)
    before = digest(avatar, folder, csv)

    run("capture", "import", folder, "-o", "capture.usda", cwd=tmp_path)
    summary = json.loads(run("inspect", "capture.usda", "--json", cwd=tmp_path).stdout)
    assert summary["kind"] == "capture"
    assert {r: v["count"] for r, v in summary["roles"].items()} == {"train": 52, "test": 20}

    run("personalize", avatar, "capture.usda", "-o", "person.usda", "-q", cwd=tmp_path)
    assert_valid_usd(tmp_path / "person.usda")
    truth = np.load(sample_set / "truth" / "avatar_truth.npz")
    generic, person = read_avatar(avatar).mesh("Head"), read_avatar(tmp_path / "person.usda").mesh("Head")
    assert person.names == generic.names
    true = np.stack([truth[f"Head/{n}"] for n in generic.names]) / 100                  # cm -> m

    def rmse(d):
        return float(np.sqrt(np.mean(np.sum((d - true) ** 2, axis=-1))))

    assert rmse(person.deltas) < 0.5 * rmse(generic.deltas)          # 0.097 vs 0.343 mm (sample-assets.md)

    run("anim", "import", "take.csv", "-o", "take.usda", cwd=tmp_path)
    take = json.loads(run("inspect", "take.usda", "--json", cwd=tmp_path).stdout)
    rows = len(csv.read_text().strip().splitlines()) - 1
    assert take["kind"] == "take" and take["frames"] == rows and take["shapes"] == 52

    run("personalize", avatar, "capture.usda", "--take", "take.usda", "-o", "person_take.usda", "-q",
        cwd=tmp_path)
    layer = json.loads(run("inspect", "person_take.usda", "--json", cwd=tmp_path).stdout)
    assert layer["inspectionAnimation"]["frames"] == 20 + rows        # test expressions, then the take
    assert layer["provenance"]["take"] == "take.usda"
    # the personalization is the same with or without the take to play
    with_take = read_avatar(tmp_path / "person_take.usda").mesh("Head")
    assert np.array_equal(with_take.deltas, person.deltas)

    run("review", "person_take.usda", "-o", "person.review.html", cwd=tmp_path)
    html = (tmp_path / "person.review.html").read_text()
    start = html.index("window.USDFACE_DATA = ") + len("window.USDFACE_DATA = ")
    page = json.JSONDecoder().raw_decode(html, start)[0]
    assert [(s["title"], s["frames"]) for s in page["sequences"]] == [("test expressions", 20),
                                                                     ("take take.usda", rows)]

    report = json.loads(run("check", "person_take.usda", "--json", cwd=tmp_path).stdout)
    assert report["ok"] and report["counts"]["error"] == 0, report

    run("retarget", avatar, "capture.usda", "-o", "map.json", cwd=tmp_path)
    retarget = json.loads((tmp_path / "map.json").read_text())
    weights = np.array(retarget["weights"])
    assert retarget["source"] == read_capture(tmp_path / "capture.usda").names
    assert retarget["target"] == generic.names and weights.shape == (52, 52)
    assert weights.min() >= 0 and weights.max() <= 1                 # the default --weight-bounds 0 1
    # the default namesake prior: each capture shape drives mostly its namesake (sample: 0.94 on average)
    assert np.mean(np.diag(weights)) > 0.8 and np.mean(np.argmax(weights, axis=1) == np.arange(52)) > 0.9

    assert digest(avatar, folder, csv) == before
    no_temp_left(tmp_path)
