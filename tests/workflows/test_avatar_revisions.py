"""A published personalized layer, and the avatar it sublayers revised upstream afterwards.

The layer holds overrides written for the avatar as it was. Revised (a mesh renamed, the SkelRoot moved, a
blend shape added or removed, the mesh re-modelled, units or up axis changed), the avatar still composes
under the layer without a USD error, and what the layer does is wrong or nothing: its overrides land on no
prim, its ``skel:blendShapeTargets`` no longer pair with the mesh's channels, its ``pointIndices`` address
the old vertices, its stage metadata overrides the avatar's new units. ``usdface check`` said at most
"input changed (sha256 differs)", a warning (exit status 0: a publish validator let it through), and for a
moved SkelRoot "do not hand-edit the layer". Now each is an ``AvatarMatch`` error naming the prim, what
changed and the fix (re-run personalize on the revised avatar)."""

from __future__ import annotations

import json
import shutil

import pytest
from wfutil import run


@pytest.fixture(scope="module")
def published(sample_set, tmp_path_factory):
    """``usdface personalize lib/avatar.usda ... -o pub/v001/person.usda`` once; returns the folder."""
    root = tmp_path_factory.mktemp("revisions")
    (root / "lib").mkdir()
    shutil.copy(sample_set / "avatar.usda", root / "lib" / "avatar.usda")
    run("personalize", "lib/avatar.usda", sample_set / "capture.usda", "-o", "pub/v001/person.usda", cwd=root)
    return root


def _project(published, tmp_path):
    """A copy of the published project (lib/avatar.usda, pub/v001/person.usda) to revise the avatar in."""
    shutil.copytree(published / "lib", tmp_path / "lib")
    shutil.copytree(published / "pub", tmp_path / "pub")
    return tmp_path / "lib" / "avatar.usda"


def _text(old, new):
    def revise(path):
        text = path.read_text()
        for a, b in zip(old, new, strict=True):
            assert a in text, a
            text = text.replace(a, b)
        path.write_text(text)
    return revise


def _channels(change):
    """Add (``change="add"``) a copy of jawOpen as a new channel, or remove cheekPuff, on /Avatar/Head."""
    def revise(path):
        from pxr import Sdf, Usd, UsdSkel

        stage = Usd.Stage.Open(str(path))
        binding = UsdSkel.BindingAPI(stage.GetPrimAtPath("/Avatar/Head"))
        names = list(binding.GetBlendShapesAttr().Get())
        targets = list(binding.GetBlendShapeTargetsRel().GetTargets())
        if change == "add":
            layer = stage.GetRootLayer()
            Sdf.CopySpec(layer, "/Avatar/Head/jawOpen", layer, "/Avatar/Head/jawOpenWide")
            names.append("jawOpenWide")
            targets.append(Sdf.Path("/Avatar/Head/jawOpenWide"))
        else:
            i = names.index("cheekPuff")
            names.pop(i)
            targets.pop(i)
            stage.RemovePrim("/Avatar/Head/cheekPuff")
        binding.GetBlendShapesAttr().Set(names)
        binding.GetBlendShapeTargetsRel().SetTargets(targets)
        stage.Save()
    return revise


def _remodel(path):
    """Three points and a triangle added at the front of /Avatar/Head's points (an artist's new piece): every
    index after them shifts, the shapes' pointIndices with them, as a DCC re-exports them."""
    from pxr import Gf, Usd, UsdGeom, UsdSkel, Vt

    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Avatar/Head"))
    points = list(mesh.GetPointsAttr().Get())
    mesh.GetPointsAttr().Set(Vt.Vec3fArray([points[0] + Gf.Vec3f(0, 0, -1), points[0] + Gf.Vec3f(0, 1, -1),
                                            points[0] + Gf.Vec3f(1, 0, -1)] + points))
    mesh.GetFaceVertexIndicesAttr().Set(Vt.IntArray([i + 3 for i in mesh.GetFaceVertexIndicesAttr().Get()]
                                                    + [0, 1, 2]))
    mesh.GetFaceVertexCountsAttr().Set(Vt.IntArray(list(mesh.GetFaceVertexCountsAttr().Get()) + [3]))
    for child in mesh.GetPrim().GetChildren():
        indices = UsdSkel.BlendShape(child).GetPointIndicesAttr() if child.IsA(UsdSkel.BlendShape) else None
        if indices is not None and indices.HasAuthoredValue():
            indices.Set(Vt.IntArray([i + 3 for i in indices.Get()]))
    stage.Save()


def _move_neutral(path):
    """Forty of /Avatar/Head's neutral points (300-339) moved 3 mm forward (an artist's re-sculpt): same
    prims, channels, topology and units."""
    from pxr import Gf, Usd, UsdGeom, Vt

    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Avatar/Head"))
    points = list(mesh.GetPointsAttr().Get())
    for i in range(300, 340):
        points[i] = points[i] + Gf.Vec3f(0, 0, 0.3)                          # cm
    mesh.GetPointsAttr().Set(Vt.Vec3fArray(points))
    stage.Save()


def _nudge_vertex(path):
    """One of /Avatar/Head's neutral points (1000) moved 0.1 mm forward (a lip vertex nudged): its block's
    mean moves 0.1 / 256 mm, below what float32 storage resolves at the head's coordinates; the layer's
    points digest tells it."""
    from pxr import Gf, Usd, UsdGeom, Vt

    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Avatar/Head"))
    points = list(mesh.GetPointsAttr().Get())
    points[1000] = points[1000] + Gf.Vec3f(0, 0, 0.01)                                 # cm
    mesh.GetPointsAttr().Set(Vt.Vec3fArray(points))
    stage.Save()


REVISIONS = {
    "mesh renamed": (_text(['/Avatar/Head', 'Mesh "Head"'], ['/Avatar/Face', 'Mesh "Face"']),
                     "/Avatar/Head", "no longer has"),
    "SkelRoot renamed": (_text(['</Avatar/', 'SkelRoot "Avatar"', 'defaultPrim = "Avatar"'],
                               ['</Hero/', 'SkelRoot "Hero"', 'defaultPrim = "Hero"']),
                         "/Avatar", "no longer has"),
    "shape added": (_channels("add"), "/Avatar/Head", "added jawOpenWide"),
    "shape removed": (_channels("remove"), "/Avatar/Head", "removed cheekPuff"),
    "re-modelled": (_remodel, "/Avatar/Head", "3780 -> 3783 points"),
    "neutral moved": (_move_neutral, "/Avatar/Head", "neutral was re-sculpted after person.usda was written "
                                                     "(the vertices 256-511 moved 0.47 mm on average)"),
    "metres": (_text(["metersPerUnit = 0.01"], ["metersPerUnit = 1"]), "/", "metersPerUnit 1"),
    "Z up": (_text(['upAxis = "Y"'], ['upAxis = "Z"']), "/", "upAxis Z"),
}


@pytest.mark.parametrize("revision", list(REVISIONS))
def test_check_tells_a_layer_that_no_longer_fits_its_revised_avatar(published, tmp_path, revision):
    revise, prim, needle = REVISIONS[revision]
    revise(_project(published, tmp_path))
    proc = run("check", "pub/v001/person.usda", "--json", cwd=tmp_path, ok=False)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    found = [i for i in json.loads(proc.stdout)["issues"] if i["rule"] == "AvatarMatch"]
    assert any(i["severity"] == "error" and i["prim"] == prim and needle in i["message"]
               and "person.usda" in i["message"] and "../../lib/avatar.usda" in i["message"]
               and "re-run usdface personalize on the revised avatar" in i["fix"] for i in found), found
    if revision == "SkelRoot renamed":      # not 'do not hand-edit the layer': the avatar's root moved
        prov = [i for i in json.loads(proc.stdout)["issues"] if i["rule"] == "Provenance"]
        assert prov and all("hand-edit" not in i["fix"] for i in prov), prov
        assert any("no longer defines" in i["message"] for i in prov), prov


def test_an_unchanged_or_resculpted_avatar_is_no_avatar_match_error(published, tmp_path):
    """The layer over its own avatar checks clean; a re-sculpted shape (same prims, channels, topology and
    units) is the Provenance warning it was (the layer still fits; its personalization is of the old
    sculpt), not an AvatarMatch error."""
    avatar = _project(published, tmp_path)
    proc = run("check", "pub/v001/person.usda", "--json", cwd=tmp_path)
    assert json.loads(proc.stdout)["issues"] == []
    from pxr import Gf, Sdf, Vt

    layer = Sdf.Layer.FindOrOpen(str(avatar))
    offsets = layer.GetAttributeAtPath("/Avatar/Head/jawOpen.offsets")
    offsets.default = Vt.Vec3fArray([Gf.Vec3f(v) * 1.3 for v in offsets.default])    # the jaw opens wider
    layer.Save()
    proc = run("check", "pub/v001/person.usda", "--json", cwd=tmp_path)
    issues = json.loads(proc.stdout)["issues"]
    assert [i["rule"] for i in issues] == ["Provenance"] and "changed after" in issues[0]["message"], issues


def _resculpt(avatar) -> None:
    """The avatar's jawOpen re-sculpted (30% wider): same prims, channels, topology and units."""
    from pxr import Gf, Sdf, Vt

    layer = Sdf.Layer.FindOrOpen(str(avatar))
    offsets = layer.GetAttributeAtPath("/Avatar/Head/jawOpen.offsets")
    offsets.default = Vt.Vec3fArray([Gf.Vec3f(v) * 1.3 for v in offsets.default])
    layer.Save()


@pytest.mark.parametrize("where", [".", "pub", "pub/v001"])
def test_check_names_a_changed_input_as_it_opens_from_where_check_runs(published, tmp_path, where):
    """check's Provenance warning named the changed avatar by the path the layer records, relative to the
    layer's folder ('input '../../lib/avatar.usda' changed'), which from the project folder is no file
    (review's and export's warning name the file itself). Now it names the file as it opens from where check
    runs, one shell word, as the avatar-revised fix does."""
    import shlex

    _resculpt(_project(published, tmp_path))
    cwd = tmp_path / where
    layer = (tmp_path / "pub" / "v001" / "person.usda").relative_to(cwd)
    proc = run("check", layer, "--json", cwd=cwd)
    (issue,) = json.loads(proc.stdout)["issues"]
    assert issue["rule"] == "Provenance" and issue["severity"] == "warning", issue
    named = issue["message"].removeprefix("input ").split(" changed after this layer was written")[0]
    assert named != issue["message"], issue
    assert (cwd / shlex.split(named)[0]).resolve() == (tmp_path / "lib" / "avatar.usda").resolve(), named
    assert named == {".": "lib/avatar.usda", "pub": "../lib/avatar.usda"}.get(
        where, str(tmp_path / "lib" / "avatar.usda")), named      # two folders up: absolute
    text = run("check", layer, cwd=cwd).stdout
    assert f"input {named} changed after this layer was written" in text, text


@pytest.mark.parametrize("revision", list(REVISIONS))
def test_export_refuses_a_layer_its_revised_avatar_no_longer_fits(published, tmp_path, revision):
    """Exported, such a layer was a generic face (its overrides on a renamed mesh), or offsets on shifted
    vertices / in the old units, labelled '[personalized]', with only the 'changed after' warning. Now
    refused before any work, naming the prim and the fix; no output is written."""
    revise, prim, needle = REVISIONS[revision]
    revise(_project(published, tmp_path))
    proc = run("export", "pub/v001/person.usda", "--gltf", "out.glb", cwd=tmp_path, ok=False)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert needle in proc.stderr and "refusing to make an export" in proc.stderr, proc.stderr
    assert "re-run usdface personalize on the revised avatar" in proc.stderr, proc.stderr
    assert not (tmp_path / "out.glb").exists()


def test_a_moved_neutral_is_delivered_only_when_allowed(published, tmp_path):
    """A TD's trial (stop 48): the avatar's neutral re-sculpted 3 mm under a published layer was only the
    Provenance warning, and export and review wrote with it: offsets fitted and checked on the old neutral,
    delivered over the new one. Refused now, naming the file, the prim and the fix (re-run personalize);
    ``--allow-moved-neutral`` delivers it as it is, with the warning."""
    _move_neutral(_project(published, tmp_path))
    for args in (["export", "pub/v001/person.usda", "--gltf", "out.glb"],
                 ["review", "pub/v001/person.usda", "-o", "r.html"],
                 ["render", "pub/v001/person.usda", "-o", "r.png", "--compare", "--shapes", "jawOpen"]):
        proc = run(*args, cwd=tmp_path, ok=False)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
        assert "person.usda" in proc.stderr and "/Avatar/Head" in proc.stderr, proc.stderr
        assert "neutral was re-sculpted" in proc.stderr, proc.stderr
        assert "--allow-moved-neutral" in proc.stderr, proc.stderr
        proc = run(*args, "--allow-moved-neutral", cwd=tmp_path)
        assert "warning: " in proc.stdout + proc.stderr and "changed after" in proc.stdout + proc.stderr, proc
    assert all((tmp_path / name).is_file() for name in ("out.glb", "r.html", "r.png"))


def test_a_nudged_vertex_is_a_warning_not_a_refusal(published, tmp_path):
    """One neutral vertex moved 0.1 mm: the layer's block means cannot see it, its points digest can, but
    cannot tell it from a re-export's float noise. ``check`` warns (AvatarMatch, exit 0) naming the prim and
    the fix; export writes, with the warning (refusing every re-export whose float bits changed would stop a
    pipeline for nothing)."""
    _nudge_vertex(_project(published, tmp_path))
    proc = run("check", "pub/v001/person.usda", "--json", cwd=tmp_path)
    found = [i for i in json.loads(proc.stdout)["issues"] if i["rule"] == "AvatarMatch"]
    assert [(i["severity"], i["prim"]) for i in found] == [("warning", "/Avatar/Head")], found
    assert "neutral points changed after person.usda was written" in found[0]["message"], found
    assert "re-run usdface personalize on the revised avatar" in found[0]["fix"], found
    for args in (["export", "pub/v001/person.usda", "--gltf", "out.glb"],     # review and render --compare
                 ["review", "pub/v001/person.usda", "-o", "r.html"],          # too, as pipeline.md and
                 ["render", "pub/v001/person.usda", "-o", "r.png", "--compare", "--shapes", "jawOpen"]):
        proc = run(*args, cwd=tmp_path)                                       # review.md say (stop 50)
        assert "neutral points changed after person.usda was written" in proc.stdout + proc.stderr, proc
    assert all((tmp_path / name).is_file() for name in ("out.glb", "r.html", "r.png"))
    # inspect's notes say it too, as they say check's errors (it listed the layer's meshes without a word)
    notes = json.loads(run("inspect", "pub/v001/person.usda", "--json", cwd=tmp_path).stdout)["notes"]
    assert any("neutral points changed after person.usda was written" in n for n in notes), notes


def test_a_layer_without_the_points_digest_reads_the_block_means_alone(published, tmp_path):
    """Layers written before stop 50 record the neutral's block means but no points digest: over them a
    vertex nudged 0.1 mm is no mismatch (as when they were written) and 40 vertices moved 3 mm still are."""
    from pxr import Sdf

    avatar = _project(published, tmp_path)
    layer = Sdf.Layer.FindOrOpen(str(tmp_path / "pub" / "v001" / "person.usda"))
    data = dict(layer.customLayerData)
    meshes = dict(data["usdface"]["meshes"])
    assert all("neutralDigest" in m for m in meshes.values())
    old = {k: {key: v for key, v in m.items() if key != "neutralDigest"} for k, m in meshes.items()}
    data["usdface"] = {**data["usdface"], "meshes": old}
    layer.customLayerData = data
    layer.Save()
    _nudge_vertex(avatar)
    issues = json.loads(run("check", "pub/v001/person.usda", "--json", cwd=tmp_path).stdout)["issues"]
    assert [i["rule"] for i in issues] == ["Provenance"], issues
    _move_neutral(avatar)
    proc = run("check", "pub/v001/person.usda", "--json", cwd=tmp_path, ok=False)
    assert any(i["rule"] == "AvatarMatch" and "neutral was re-sculpted" in i["message"]
               for i in json.loads(proc.stdout)["issues"]), proc.stdout


def test_review_render_and_inspect_name_the_revision(published, tmp_path):
    """review and render --compare refuse the re-modelled avatar's layer as export does; inspect of a layer
    whose avatar gained a shape said 'skel:blendShapes has 53 entries but skel:blendShapeTargets has 52 (fix:
    give exactly one BlendShape target per channel token)', a fix for an avatar, not for a published layer."""
    avatar = _project(published, tmp_path)
    original = avatar.read_bytes()
    _remodel(avatar)
    for args in (["review", "pub/v001/person.usda", "-o", "r.html"],
                 ["render", "pub/v001/person.usda", "-o", "r.png", "--compare", "--shapes", "jawOpen"]):
        proc = run(*args, cwd=tmp_path, ok=False)
        assert proc.returncode == 2 and "3780 -> 3783 points" in proc.stderr, proc.stderr
        assert "re-run usdface personalize on the revised avatar" in proc.stderr, proc.stderr
    avatar.write_bytes(original)
    _channels("add")(avatar)
    proc = run("inspect", "pub/v001/person.usda", cwd=tmp_path, ok=False)
    assert proc.returncode == 2 and "added jawOpenWide" in proc.stderr, proc.stderr
    assert "re-run usdface personalize on the revised avatar" in proc.stderr, proc.stderr


def test_inspect_notes_a_revised_avatar_and_a_changed_input(published, tmp_path):
    """inspect of a layer over a re-modelled (or renamed, re-sculpted) avatar listed its meshes and shapes
    as its result, with no word of the revision: now its notes say what check's AvatarMatch and Provenance
    say (JSON: in ``notes``)."""
    avatar = _project(published, tmp_path)
    _remodel(avatar)
    proc = run("inspect", "pub/v001/person.usda", "--json", cwd=tmp_path)
    notes = json.loads(proc.stdout)["notes"]
    assert any("3780 -> 3783 points" in n and "re-run usdface personalize on the revised avatar" in n
               for n in notes), notes
    assert any("changed after it was written" in n for n in notes), notes
    proc = run("inspect", "pub/v001/person.usda", cwd=tmp_path)
    assert "note: ../../lib/avatar.usda's /Avatar/Head was re-modelled" in proc.stdout, proc.stdout


def test_the_fix_names_the_revised_avatar_from_where_the_command_runs(published, sample_set, tmp_path):
    """The fix named the avatar by the layer's sublayer path (``../../lib/avatar.usda``, relative to
    ``pub/v001/``), which from the folder the command ran in is no file: the re-run it told failed with
    'avatar not found'. Now the path opens from there, and the re-run it tells, pasted, restores the layer."""
    import re
    import shlex

    _remodel(_project(published, tmp_path))
    proc = run("review", "pub/v001/person.usda", "-o", "r.html", cwd=tmp_path, ok=False)
    assert proc.returncode == 2, proc.stderr
    found = re.search(r"re-run usdface personalize on the revised avatar \((.+?)\) with the capture",
                      proc.stderr)
    assert found, proc.stderr
    avatar = shlex.split(found.group(1))[0]
    assert (tmp_path / avatar).resolve() == (tmp_path / "lib" / "avatar.usda").resolve(), avatar
    run("personalize", avatar, sample_set / "capture.usda", "-o", "pub/v001/person.usda", "--force", "-q",
        cwd=tmp_path)
    run("review", "pub/v001/person.usda", "-o", "r.html", cwd=tmp_path)
