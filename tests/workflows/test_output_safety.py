"""Outputs never touch inputs, and ``--force`` replaces only what usdface writes (issue: new-user trial, data
loss). Every repro runs the ``usdface`` command as a user would (a subprocess in a scratch folder) and checks
the exit status, the message (the input and the fix named) and that every input and unrelated file is
byte-identical afterwards. Each one deleted or overwrote a file before the fix."""

from __future__ import annotations

import json
import os
import shutil

import pytest
from wfutil import digest, no_temp_left, run


def refused(proc, *needles):
    """Exit 2, one line naming ``needles`` and a fix, no traceback."""
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr
    for needle in needles:
        assert needle in proc.stderr, proc.stderr
    assert "(fix: " in proc.stderr


def tree(folder) -> dict:
    """Every file under ``folder`` with its sha256 (the folder's full content: nothing added or removed)."""
    return {os.path.relpath(k, folder): v for k, v in digest(folder).items()}


@pytest.fixture(scope="module")
def person_files(sample_set, tmp_path_factory):
    """``sa/avatar.usda`` + ``sa/capture.usda`` and ``out/person.usda`` personalized from them (a layer that
    sublayers ../sa/avatar.usda), made once; tests work on copies (:func:`project`)."""
    root = tmp_path_factory.mktemp("person")
    (root / "sa").mkdir()
    for name in ("avatar.usda", "capture.usda"):
        shutil.copy(sample_set / name, root / "sa" / name)
    (root / "out").mkdir()
    run("personalize", "sa/avatar.usda", "sa/capture.usda", "-o", "out/person.usda", "-q", cwd=root)
    return root


@pytest.fixture
def project(person_files, tmp_path):
    """A fresh copy of :func:`person_files` (relative sublayer paths kept) in this test's scratch folder."""
    shutil.copytree(person_files, tmp_path, dirs_exist_ok=True)
    return tmp_path


@pytest.fixture(scope="module")
def take_file(sample_take, tmp_path_factory):
    """A continuous USD take of the sample person (``take.usdc``)."""
    from usdface.io.take import write_take_usd

    return write_take_usd(sample_take, tmp_path_factory.mktemp("take") / "take.usdc")


# ------------------------------------------------------------------- 1. --force on a folder output
def test_export_obj_dir_holding_the_input_layer_is_refused(project):
    """``export out/person.usda --obj-dir out --force`` deleted out/person.usda (the input)."""
    before = tree(project)
    proc = run("export", "out/person.usda", "--obj-dir", "out", "--force", cwd=project, ok=False)
    refused(proc, "out: output folder holds the input out/person.usda", "even with --force")
    assert tree(project) == before


def test_export_obj_dir_holding_a_sublayer_of_the_input_is_refused(project):
    """The avatar person.usda sublayers is an input too: a folder holding it is refused."""
    before = tree(project)
    proc = run("export", "out/person.usda", "--obj-dir", "sa", "--force", cwd=project, ok=False)
    refused(proc, "holds the input", "avatar.usda (a layer the input out/person.usda composes)")
    assert tree(project) == before


def test_export_force_into_a_folder_keeps_unrelated_files(project):
    """``--force`` replaces the OBJs export writes and keeps every other file at the top (it emptied the
    folder); a stale file inside a folder export writes (a shape OBJ of another run, which a DCC would import
    as a shape) is refused, changing nothing, until it is deleted."""
    objs = project / "objs"
    run("export", "out/person.usda", "--obj-dir", "objs", cwd=project)
    written = tree(objs)
    (objs / "notes.txt").write_text("mine")
    (objs / "Head" / "old_shape.obj").write_text("stale, but not usdface's to delete")
    proc = run("export", "out/person.usda", "--obj-dir", "objs", cwd=project, ok=False)
    assert proc.returncode == 2 and "not empty" in proc.stderr and "--force" in proc.stderr
    before = tree(objs)
    proc = run("export", "out/person.usda", "--obj-dir", "objs", "--force", cwd=project, ok=False)
    assert proc.returncode == 2 and "old_shape.obj" in proc.stderr
    assert "read as part of this output" in proc.stderr
    assert tree(objs) == before
    (objs / "Head" / "old_shape.obj").unlink()
    proc = run("export", "out/person.usda", "--obj-dir", "objs", "--force", cwd=project)
    assert "kept 1 file(s)" in proc.stdout
    after = tree(objs)
    assert after.pop("notes.txt")
    assert after == written  # the same files, rewritten with the same bytes
    assert (objs / "notes.txt").read_text() == "mine"
    no_temp_left(project)
    assert sorted(p.name for p in project.iterdir()) == ["objs", "out", "sa"]


def test_export_to_a_symlink_of_the_input_folder_is_refused(project):
    (project / "link").symlink_to("out", target_is_directory=True)
    before = tree(project / "out")
    proc = run("export", "out/person.usda", "--obj-dir", "link", "--force", cwd=project, ok=False)
    refused(proc, "holds the input")
    assert tree(project / "out") == before


def test_capture_select_into_the_takes_folder_is_refused(take_file, tmp_path):
    """``capture select t3/take.usdc -o t3 --force`` deleted the take and t3/notes.txt."""
    t3 = tmp_path / "t3"
    t3.mkdir()
    shutil.copy(take_file, t3 / "take.usdc")
    (t3 / "notes.txt").write_text("session notes")
    before = tree(t3)
    proc = run("capture", "select", "t3/take.usdc", "-o", "t3", "--force", cwd=tmp_path, ok=False)
    refused(proc, "t3: capture folder holds the input t3/take.usdc")
    assert tree(t3) == before
    # a folder elsewhere is fine, and --force there keeps what usdface does not write
    (tmp_path / "cap").mkdir()
    (tmp_path / "cap" / "notes.txt").write_text("keep me")
    run("capture", "select", "t3/take.usdc", "-o", "cap", "--force", "-q", cwd=tmp_path)
    assert (tmp_path / "cap" / "notes.txt").read_text() == "keep me"
    assert (tmp_path / "cap" / "neutral.obj").is_file() and tree(t3) == before


def test_capture_import_into_the_project_folder_is_refused(sample_set, tmp_path):
    """``capture import proj/cap -o proj --force`` deleted proj/cap and proj/avatar.usda."""
    proj = tmp_path / "proj"
    shutil.copytree(sample_set / "capture", proj / "cap")
    shutil.copy(sample_set / "avatar.usda", proj / "avatar.usda")
    before = tree(proj)
    proc = run("capture", "import", "proj/cap", "-o", "proj", "--force", cwd=tmp_path, ok=False)
    refused(proc, "proj: capture folder holds the input folder proj/cap")
    # the input folder itself, and a folder inside it, are refused too
    proc = run("capture", "import", "proj/cap", "-o", "proj/cap", "--force", cwd=tmp_path, ok=False)
    refused(proc, "would overwrite an input: it is the input folder proj/cap")
    proc = run("capture", "import", "proj/cap", "-o", "proj/cap/again", cwd=tmp_path, ok=False)
    refused(proc, "is inside the input folder proj/cap")
    assert tree(proj) == before
    no_temp_left(tmp_path)


def test_sample_force_keeps_unrelated_files(tmp_path):
    """``sample dir --force`` deleted every other file in dir."""
    d = tmp_path / "dir"
    d.mkdir()
    (d / "notes.txt").write_text("notes")
    (d / "truth").mkdir()
    (d / "truth" / "mine.txt").write_text("mine")
    proc = run("sample", "dir", cwd=tmp_path, ok=False)
    assert proc.returncode == 2 and "not empty" in proc.stderr
    run("sample", "dir", "--force", "-q", cwd=tmp_path)
    assert (d / "notes.txt").read_text() == "notes" and (d / "truth" / "mine.txt").read_text() == "mine"
    assert {"avatar.usda", "capture.usda", "README.txt"} <= {p.name for p in d.iterdir()}
    assert (d / "truth" / "meta.json").is_file()
    no_temp_left(tmp_path)


# ------------------------------------------------------------------- 2. a file output that is an input
@pytest.mark.parametrize("how", ["same", "hardlink", "symlink"])
def test_fit_over_its_capture_is_refused(person_files, tmp_path, how):
    """``fit capture.usda -o capture.usda --force`` replaced the capture (also through links)."""
    cap = tmp_path / "capture.usda"
    shutil.copy(person_files / "sa" / "capture.usda", cap)
    out = {"same": cap, "hardlink": tmp_path / "hard.usda", "symlink": tmp_path / "soft.usda"}[how]
    if how == "hardlink":
        os.link(cap, out)
    elif how == "symlink":
        out.symlink_to(cap.name)
    before = digest(cap)
    proc = run("fit", "capture.usda", "-o", out.name, "--force", "-q", cwd=tmp_path, ok=False)
    refused(proc, "would overwrite an input: it is the input capture.usda")
    assert digest(cap) == before


@pytest.mark.parametrize("option,needle", [
    (["--usd", "capture.usda"], "would overwrite an input: it is the input capture.usda"),
    (["--json", "capture.usda"], "JSON report must end in .json"),
    (["--json", "report.txt"], "JSON report must end in .json"),
    (["--plot", "capture.usda"], "plot format 'usda' is not supported"),
])
def test_evaluate_outputs_are_checked(person_files, tmp_path, option, needle):
    """``evaluate capture.usda --usd capture.usda --force`` (or ``--json capture.usda``) destroyed the
    capture; ``--json`` had no extension check."""
    shutil.copy(person_files / "sa" / "capture.usda", tmp_path / "capture.usda")
    before = tree(tmp_path)
    proc = run("evaluate", "capture.usda", "--methods", "dt", *option, "--force", "-q", cwd=tmp_path,
               ok=False)
    refused(proc, needle)
    assert tree(tmp_path) == before


def test_export_flatten_over_the_sublayered_avatar_is_refused(project):
    """``export person.usda --flatten sa/avatar.usda --force`` overwrote the avatar person.usda sublayers."""
    before = tree(project)
    proc = run("export", "out/person.usda", "--flatten", "sa/avatar.usda", "--force", cwd=project, ok=False)
    refused(proc, "(a layer the input out/person.usda composes)")
    proc = run("export", "out/person.usda", "--gltf", "sa/avatar.glb", "--flatten", "out/person.usda",
               "--force", cwd=project, ok=False)
    refused(proc, "would overwrite an input")
    assert tree(project) == before


def test_personalize_over_the_avatars_sublayer_is_refused(project):
    """A layer the avatar composes (here: person.usda's avatar) is an input of personalize too."""
    (project / "wrap.usda").write_text('#usda 1.0\n(\n    subLayers = [@sa/avatar.usda@]\n)\n')
    before = tree(project)
    proc = run("personalize", "wrap.usda", "sa/capture.usda", "-o", "sa/avatar.usda", "--force", "-q",
               cwd=project, ok=False)
    refused(proc, "sa/avatar.usda (a layer the input wrap.usda composes)")
    assert tree(project) == before


@pytest.mark.parametrize("argv,needle", [
    (["retarget", "sa/avatar.usda", "sa/capture.usda", "--name-map", "names.json", "-o", "names.json"],
     "it is the input names.json"),
    (["landmarks", "sa/avatar.usda", "--evaluate", "--takes", "t.csv", "--empirical", "names.json",
      "--json", "names.json"], "it is the input names.json"),
    (["render", "out/person.usda", "--compare", "mine.png", "-o", "mine.png"], "it is the input mine.png"),
    (["review", "out/person.usda", "--take", "page.html", "-o", "page.html"], "it is the input page.html"),
    (["batch", "names.json", "--report", "names.json"], "it is the input names.json"),
    (["sample", "newdir", "--picture", "mine.png"], "picture exists"),
])
def test_every_output_option_is_checked_before_work(project, argv, needle):
    """The audit: each command's other inputs (name maps, layouts, generic avatars, takes, manifests) and
    outputs go through the one check, before any work."""
    (project / "names.json").write_text(json.dumps([{"avatar": "sa/avatar.usda", "capture": "sa/capture.usda",
                                                     "output": "b.usda"}]))
    (project / "mine.png").write_bytes(b"\x89PNG mine")
    (project / "page.html").write_text("<p>mine</p>")
    (project / "t.csv").write_text("not read")
    before = tree(project)
    proc = run(*argv, "--force" if argv[0] != "sample" else "-q", cwd=project, ok=False)
    refused(proc, needle)
    assert tree(project) == before


@pytest.mark.parametrize("argv", [
    ["landmarks", "sa/avatar.usda", "--json", "-"],
    ["evaluate", "sa/capture.usda", "--json", "-"],
    ["render", "out/person.usda", "-o", "-"],
    ["personalize", "sa/avatar.usda", "sa/capture.usda", "-o", "-"],
])
def test_a_dash_for_standard_output_is_named(project, argv):
    """``--json -`` (or ``-o -``), the Unix way to ask for standard output, where a command writes a file
    (``landmarks`` and ``evaluate`` take ``--json FILE``; the others print with a ``--json`` flag): refused
    before any work saying so; it was told ``-: output must end in .json (fix: name it e.g. -.json)``."""
    before = tree(project)
    proc = run(*argv, cwd=project, ok=False)
    refused(proc, "not to standard output ('-')")
    assert "-.json" not in proc.stderr
    assert tree(project) == before


@pytest.mark.parametrize("argv,what,inside", [
    (["personalize", "sa/avatar.usda", "sa/capture.usda", "-o", "newdir/"], "output layer",
     "newdir/avatar.personalized.usda"),
    (["landmarks", "sa/avatar.usda", "-o", "newdir/"], "output layer", "newdir/avatar.landmarks.usda"),
    (["export", "out/person.usda", "--gltf", "newdir/"], "glTF output", "newdir/person.glb"),
    (["export", "out/person.usda", "--flatten", "newdir/"], "flattened USD file", "newdir/person.usdc"),
    (["personalize", "sa/avatar.usda", "sa/capture.usda", "-o", "out/"], "output layer",
     "out/avatar.personalized.usda"),
    # stop 54 (a TD's trial): a folder with a space was named bare, 'e.g. new dir/avatar.personalized.usda',
    # which does not paste; shell-quoted as every path in a fix (usd_rig._from_cwd)
    (["personalize", "sa/avatar.usda", "sa/capture.usda", "-o", "new dir/"], "output layer",
     "'new dir/avatar.personalized.usda'"),
])
def test_an_output_given_as_a_folder_is_told_to_name_a_file_inside_it(project, argv, what, inside):
    """``-o newdir/`` (a folder, by its trailing slash) was told 'name it e.g. newdir.usda', a sibling of the
    folder the user meant; it is named a folder and the fix names a file inside it (the command's own name
    for its output where it has one). An existing folder (``out/``) gets the same file name."""
    before = tree(project)
    proc = run(*argv, cwd=project, ok=False)
    refused(proc, f"{what} path ", "a folder", f"e.g. {inside}")
    assert "newdir.usda" not in proc.stderr and "newdir.glb" not in proc.stderr
    assert tree(project) == before and not (project / "newdir").exists()


# ------------------------------------------------------------------- 3. dry run and correspondence cache
def test_dry_run_says_an_existing_output_would_be_refused(project):
    proc = run("personalize", "sa/avatar.usda", "sa/capture.usda", "-o", "out/person.usda", "--dry-run",
               "-q", cwd=project, ok=False)
    assert proc.returncode == 1                               # a preflight: a real run would refuse
    assert "a real run would refuse to write: out/person.usda: output layer exists" in proc.stdout
    assert "would write out/person.usda" not in proc.stdout
    proc = run("personalize", "sa/avatar.usda", "sa/capture.usda", "-o", "sa/capture.usda", "--dry-run",
               "--force", "-q", cwd=project, ok=False)
    assert proc.returncode == 1
    assert "a real run would refuse to write" in proc.stdout and "overwrite an input" in proc.stdout
    proc = run("personalize", "sa/avatar.usda", "sa/capture.usda", "-o", "new.usda", "--dry-run", "-q",
               "--json", cwd=project)
    doc = json.loads(proc.stdout)
    assert doc["would_write"] == "new.usda" and doc["output_refused"] is None
    assert not (project / "new.usda").exists()


def test_correspondence_cache_of_another_avatar_is_rewritten_with_a_warning(project, sample_set):
    run("sample", "artist", "--template", "artist", "-q", cwd=project)
    run("personalize", "sa/avatar.usda", "sa/capture.usda", "-o", "a.usda", "--correspondence", "c.npz", "-q",
        cwd=project)
    proc = run("personalize", "sa/avatar.usda", "artist/capture.usda", "-o", "b.usda", "--correspondence",
               "c.npz", "-q", cwd=project)
    assert "cache: replaced" in proc.stdout
    assert "warning: --correspondence c.npz held the map of another avatar face, template" in proc.stdout
    proc = run("personalize", "sa/avatar.usda", "artist/capture.usda", "-o", "c.usda", "--correspondence",
               "c.npz", "-q", cwd=project)
    assert "cache: hit" in proc.stdout and "warning: --correspondence" not in proc.stdout
    # which face the map was registered from, as the cache recorded it (the sample's avatar is the person's)
    assert "on /Avatar/Head, from the person's scan (cache: hit)" in proc.stdout


# ------------------------------------------------------------------- the one check, directly
def test_check_not_input_sees_hard_links_inside_an_output_folder(tmp_path):
    from usdface.errors import InputFileError
    from usdface.io.atomic import check_not_input, check_output_dir

    src = tmp_path / "input.usda"
    src.write_text("#usda 1.0\n")
    (tmp_path / "out").mkdir()
    os.link(src, tmp_path / "out" / "copy.usda")
    with pytest.raises(InputFileError, match="holds the input"):
        check_output_dir(tmp_path / "out", force=True, inputs=[src])
    check_not_input(tmp_path / "new", [src], folder=True)          # a new folder elsewhere is fine
    check_not_input(tmp_path / "other.usda", [src, None, 3])       # None / non-paths are skipped


def test_the_place_beside_an_input_folder_is_named_by_the_option_that_gives_it(sample_set, tmp_path,
                                                                               monkeypatch):
    """A TD's trial (stop 54): an output inside an input folder is told the place beside it as ``-o PATH``,
    whatever gave the output: ``personalize --correspondence cap/corr.npz`` was told ``-o corr.npz`` (pasted,
    that replaces the layer's path, not the cache's), and the API and a Pyblish publish, which have no
    ``-o``, were told a command-line option. The command line names ``-o`` only for the output ``-o`` gives
    (its default too: ``capture import .`` inside the folder); every other caller gets the path alone."""
    cap = tmp_path / "cap"
    shutil.copytree(sample_set / "capture", cap)
    before = tree(cap)
    cache = run("personalize", sample_set / "avatar.usda", "cap", "-o", "p.usda", "--correspondence",
                "cap/corr.npz", "--dry-run", cwd=tmp_path, ok=False)
    refused(cache, "cap/corr.npz", "corr.npz, beside it")
    assert "-o corr.npz" not in cache.stderr, cache.stderr
    layer = run("personalize", sample_set / "avatar.usda", "cap", "-o", "cap/p.usda", cwd=tmp_path, ok=False)
    refused(layer, "(-o p.usda, beside it)")
    # the API: the same refusal, the path alone
    import usdface
    from usdface.errors import InputFileError

    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputFileError) as err:
        usdface.personalize_avatar(sample_set / "avatar.usda", "cap", "cap/p.usda")
    assert "(p.usda, beside it)" in err.value.fix and "-o" not in err.value.fix, err.value.fix
    assert tree(cap) == before


def test_a_dangling_link_as_the_output_is_refused_before_any_work(project):
    """A TD's trial (stop 54): ``-o p.usda`` where ``p.usda`` is a symbolic link to a file that does not exist
    (a publish area's link whose target was cleaned away) passed the check before the work (``exists()``
    follows the link), ran the whole personalize, and then failed 'output exists (written by another
    process meanwhile)': wrong, and after the work. The link is an existing output: refused at once without
    ``--force`` (the dry run says so too), replaced by the file with it (its target left as it was)."""
    (project / "p.usda").symlink_to("gone/p.usda")
    argv = ("personalize", "sa/avatar.usda", "sa/capture.usda", "-o", "p.usda")
    proc = run(*argv, cwd=project, ok=False)
    refused(proc, "p.usda", "symbolic link", "gone/p.usda", "--force")
    assert "meanwhile" not in proc.stderr and "registration" not in proc.stdout + proc.stderr, proc.stderr
    dry = run(*argv, "--dry-run", cwd=project, ok=False)
    assert "symbolic link" in dry.stdout + dry.stderr and "would write" not in dry.stdout, dry.stdout
    run(*argv, "--force", "-q", cwd=project)
    assert (project / "p.usda").is_file() and not (project / "p.usda").is_symlink()
    assert not (project / "gone").exists()
    no_temp_left(project)


def test_a_batch_rows_correspondence_cache_is_checked_before_the_first_item(sample_set, tmp_path):
    """A TD's trial (stop 54): a manifest's last row whose ``correspondence`` cache lies inside its capture
    folder failed only at its turn, after the rows before it had run (README: every row's paths, an output
    never inside an input, checked before the first item); a Pyblish publish validates the same cache before
    any extraction. Now the batch refuses it before any work, naming the row, as Pyblish does."""
    cap = tmp_path / "cap"
    shutil.copytree(sample_set / "capture", cap)
    before = tree(cap)
    avatar = sample_set / "avatar.usda"
    (tmp_path / "people.csv").write_text(f"avatar,capture,output,correspondence\n{avatar},cap,out/a.usda,\n"
                                         f"{avatar},cap,out/b.usda,cap/b.npz\n")
    proc = run("batch", "people.csv", "-j", "1", cwd=tmp_path, ok=False)
    refused(proc, "people.csv", "item 2", "cap/b.npz", "inside the input folder")
    assert not (tmp_path / "out").exists(), sorted(p.name for p in (tmp_path / "out").iterdir())
    assert tree(cap) == before
    # named by the manifest's column the user edits, not personalize's option (h107's loose end)
    assert "correspondence column" in proc.stderr and "--correspondence" not in proc.stderr, proc.stderr
    (tmp_path / "people.csv").write_text(f"avatar,capture,output,correspondence\n{avatar},cap,out/b.usda,"
                                         "out/b.usda\n")
    proc = run("batch", "people.csv", "-j", "1", cwd=tmp_path, ok=False)
    refused(proc, "people.csv", "item 1", "correspondence column and its output column name the same file")
    assert "--correspondence" not in proc.stderr, proc.stderr


def test_a_dry_run_names_the_place_beside_an_input_folder_as_the_real_run_does(sample_set, tmp_path):
    """Review of stop 54 (h113): the real run's refusal of a layer inside an input folder names ``-o`` with
    the place beside it (``cli.name_output_option``), but ``personalize --dry-run`` printed its early word on
    the output (and ``--json``'s ``output_refused``) without it: ``(p.usda, beside it)``, the API's wording,
    on the command line. One wording for both runs."""
    cap = tmp_path / "cap"
    shutil.copytree(sample_set / "capture", cap)
    before = tree(cap)
    argv = ("personalize", sample_set / "avatar.usda", "cap", "-o", "cap/p.usda", "--dry-run")
    dry = run(*argv, cwd=tmp_path, ok=False)
    assert dry.returncode == 1, dry.stdout + dry.stderr
    assert "(-o p.usda, beside it)" in dry.stderr, dry.stderr
    doc = json.loads(run(*argv, "--json", cwd=tmp_path, ok=False).stdout)
    assert "(-o p.usda, beside it)" in doc["output_refused"], doc["output_refused"]
    # a refused cache is not -o's output: the path alone, as the real run says it
    cache = run("personalize", sample_set / "avatar.usda", "cap", "-o", "p.usda", "--correspondence",
                "cap/corr.npz", "--dry-run", cwd=tmp_path, ok=False)
    assert "-o corr.npz" not in cache.stderr, cache.stderr
    assert tree(cap) == before


def test_the_librarys_picture_and_gltf_writers_refuse_a_dangling_link_as_every_output_check_does(tmp_path):
    """Review of stop 54 (h113): the dangling-link rule (``check_output_file``) was not the one rule of an
    existing output: ``usdface.render``'s pictures (``save_figure``) and ``usdface.io.gltf.write_gltf``
    kept ``exists()``, which follows the link: ``render_shapes(rig, out="p.png")`` over
    ``p.png -> gone/p.png`` drew the picture and then failed 'output exists (written by another process
    meanwhile)', wrong. Each refuses it as an existing output now (replaced with ``force``, the link's
    target left as it is)."""
    import numpy as np

    from usdface.errors import OutputExistsError
    from usdface.io.gltf import write_gltf
    from usdface.model import FaceRig
    from usdface.render import render_shapes

    pts = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], [0.01, 0.01, 0.002]], dtype=float)
    rig = FaceRig(pts, np.array([[0, 1, 2], [1, 3, 2]]), ["up"], np.full((1, 4, 3), 0.001), name="Face")
    for name, write in (("p.png", lambda out, **kw: render_shapes(rig, ["up"], out=out, **kw)),
                        ("p.glb", lambda out, **kw: write_gltf(out, [rig], **kw))):
        link = tmp_path / name
        link.symlink_to(f"gone/{name}")
        with pytest.raises(OutputExistsError, match="symbolic link") as err:
            write(link)
        assert "meanwhile" not in str(err.value), err.value
        write(link, force=True)
        assert link.is_file() and not link.is_symlink() and not (tmp_path / "gone").exists()


def test_a_batch_row_whose_output_is_a_dangling_link_is_refused_before_the_first_item(sample_set, tmp_path):
    """Review of stop 54 (h113): a manifest row whose output is a symbolic link to nothing passed the
    preflight as a finished row (``lexists``) while resume ran it as not done (``exists``): the rows before it
    ran, then it failed at its turn, told 'written meanwhile by another run of this output ... the next run
    skips it' (wrong twice: no other run, and the next run failed again). Refused before any work, as
    ``personalize -o`` refuses the link, naming the row; ``--force`` replaces the link with the layer."""
    avatar, capture = sample_set / "avatar.usda", sample_set / "capture"
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "b.usda").symlink_to("gone/b.usda")
    (tmp_path / "people.csv").write_text(f"avatar,capture,output\n{avatar},{capture},out/a.usda\n"
                                         f"{avatar},{capture},out/b.usda\n")
    proc = run("batch", "people.csv", "-j", "1", cwd=tmp_path, ok=False)
    refused(proc, "people.csv", "item 2", "symbolic link", "gone/b.usda", "--force")
    assert "meanwhile" not in proc.stdout + proc.stderr, proc.stdout + proc.stderr
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["b.usda"]
    run("batch", "people.csv", "-j", "1", "--force", "-q", cwd=tmp_path)
    assert (tmp_path / "out" / "b.usda").is_file() and not (tmp_path / "out" / "b.usda").is_symlink()
    assert not (tmp_path / "out" / "gone").exists()


def test_run_batch_does_not_call_a_refused_dangling_link_another_runs_output(tmp_path, monkeypatch):
    """Without the preflight (``run_batch``), a row whose output is a link to nothing fails at its turn with
    the worker's refusal alone: not 'written meanwhile by another run ... the next run skips it' (the note
    for a layer another run of the manifest wrote, which exists)."""
    from usdface.errors import OutputExistsError
    from usdface.pipeline import batch

    link = tmp_path / "b.usda"
    link.symlink_to("gone/b.usda")

    def refuse(item):
        raise OutputExistsError("output layer exists as a symbolic link to gone/b.usda, which does not exist",
                                path=item["output"], fix="pass --force")

    result = batch.run_item(refuse, {"index": 0, "avatar": "a", "capture": "c", "output": str(link)})
    assert result["status"] == batch.FAILED and "meanwhile" not in result["error"], result["error"]
    assert link.is_symlink()
