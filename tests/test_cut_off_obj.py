"""A capture OBJ cut off (an interrupted copy to the farm, a full disk) is told as cut off, naming the file,
not as a modelling problem: a frame cut inside its vertices read 'mesh has no faces (fix: export the mesh with
its faces, not as points)', one cut inside its faces 'face 1794 has 2 vertices (fix: remove points/lines from
the mesh ...)', and a neutral.obj cut inside its last face blamed template/neutral.obj ('faces differ from
neutral.obj's')."""

from __future__ import annotations

import json
import shutil

import pytest

from usdface.cli import main


def _cut(folder, rel, fraction):
    path = folder / rel
    data = path.read_bytes()
    end = int(len(data) * fraction)
    while data[end - 1:end] in (b"\n", b"\r"):         # a cut at a line end cannot be told from a whole file
        end -= 1
    path.write_bytes(data[:end])
    return path


@pytest.mark.parametrize("rel, fraction", [("train/004_eyeLookUpLeft.obj", 0.2),     # inside the vertices
                                           ("train/004_eyeLookUpLeft.obj", 0.9),     # inside the faces
                                           ("neutral.obj", 0.999)])                  # inside the last face
def test_a_cut_off_capture_obj_is_named_as_cut_off(sample_capture_folder, tmp_path, capsys, rel, fraction):
    capture = tmp_path / "anna"
    shutil.copytree(sample_capture_folder, capture)
    cut = _cut(capture, rel, fraction)
    out = tmp_path / "anna.usda"
    assert main(["capture", "import", str(capture), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"{cut}: the file ends in the middle of a line, so it was probably cut off" in err, err
    assert "fix: copy or export the file again" in err
    assert not out.exists()


def test_a_batch_reports_the_cut_off_frame(samples, sample_capture_folder, tmp_path, capsys):
    """The batch goes on past the item and its report says which file to copy again."""
    capture = tmp_path / "bad"
    shutil.copytree(sample_capture_folder, capture)
    cut = _cut(capture, "train/004_eyeLookUpLeft.obj", 0.2)
    manifest = tmp_path / "people.csv"
    manifest.write_text(f"avatar,capture,output,method\n{samples / 'avatar.usda'},bad,out/bad.usda,dt\n"
                        f"{samples / 'avatar.usda'},{samples / 'capture.usda'},out/good.usda,dt\n")
    assert main(["batch", str(manifest), "-j", "1", "-q"]) == 1
    report = json.loads((tmp_path / "people.report.json").read_text())
    bad, good = report["items"]
    assert bad["status"] == "failed" and bad["error_type"] == "InputFileError"
    assert bad["error"].startswith(f"{cut}: the file ends in the middle of a line")
    assert good["status"] == "done" and (tmp_path / "out" / "good.usda").is_file()
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["good.usda"]


def test_a_capture_obj_cut_at_a_line_end_inside_its_faces_says_so(sample_capture_folder, tmp_path, capsys):
    """A user trial (stop 52): a frame cut at a line end inside its faces (``head -n``, a copy stopped between
    two lines) read whole, and the refusal was only "faces differ from neutral.obj's"; its faces are the
    neutral's first ones, which says it was cut off: the refusal counts them and says so."""
    capture = tmp_path / "anna"
    shutil.copytree(sample_capture_folder, capture)
    path = capture / "train" / "004_eyeLookUpLeft.obj"
    lines = path.read_text().splitlines(keepends=True)
    faces = [i for i, line in enumerate(lines) if line.startswith("f ")]
    keep = faces[len(faces) // 3]                      # a third of the faces, cut at a line end
    path.write_text("".join(lines[:keep]))
    out = tmp_path / "anna.usda"
    assert main(["capture", "import", str(capture), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    # the sample's faces are triangles: one OBJ face, one triangle
    assert f"{path}: only the first {len(faces) // 3} of neutral.obj's {len(faces)} triangles" in err, err
    assert "cut off" in err and "fix: copy or export the file again" in err, err
    assert not out.exists()


def test_a_capture_obj_cut_at_a_line_end_inside_its_vertices_says_so(sample_capture_folder, tmp_path, capsys):
    """A user trial (stop 52): a frame cut at a line end inside its vertices (no face line left) said
    "mesh has no faces (fix: export the mesh with its faces, not as points)", a modelling fix for a copy
    stopped short; with fewer vertices than the neutral's, it says it was cut off, counting them."""
    capture = tmp_path / "anna"
    shutil.copytree(sample_capture_folder, capture)
    for rel in ("train/004_eyeLookUpLeft.obj", "template/jawOpen.obj"):
        path = capture / rel
        whole = path.read_text()
        lines = whole.splitlines(keepends=True)
        n = sum(line.startswith("v ") for line in lines)
        path.write_text("".join(lines[:n // 2]))        # at a line end: ends_mid_line cannot see it
        kept = sum(line.startswith("v ") for line in lines[:n // 2])
        out = tmp_path / "anna.usda"
        assert main(["capture", "import", str(capture), "-o", str(out), "-q"]) == 2
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert f"{path}: only {kept} of " in err and f"'s {n} vertices and no faces" in err, err
        assert "cut off" in err and "fix: copy or export the file again" in err, err
        assert not out.exists()
        path.write_text(whole)
