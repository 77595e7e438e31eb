"""The user's own rig: channel names as studios ship them, ``--name-map``, and how ``inspect`` reports them.

Spellings -> canonical ARKit names (unit tables), the best-of-two rule when two channels mean one shape,
name-map validation, and the sample avatar rewritten with studio-style channel and prim names, which must
personalize to the same offsets as the original.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from usdface import arkit
from usdface.cli import main
from usdface.errors import InputFileError, RigError
from usdface.io.name_map import read_name_map

# ----------------------------------------------------------------------------------------------------
# spellings
# ----------------------------------------------------------------------------------------------------
SPELLINGS = [
    # (given, canonical, how)
    ("eyeBlinkLeft", "eyeBlinkLeft", "exact"),
    ("eyeBlink_L", "eyeBlinkLeft", "spelling"),              # ARKit raw value
    ("EyeBlinkLeft", "eyeBlinkLeft", "spelling"),            # Live Link Face column
    ("eye_blink_left", "eyeBlinkLeft", "spelling"),          # snake case
    ("Eye_Blink_L", "eyeBlinkLeft", "spelling"),             # title case, CC4
    ("EyeBlink_L", "eyeBlinkLeft", "spelling"),
    ("EYE_BLINK_L", "eyeBlinkLeft", "spelling"),
    ("L_EyeBlink", "eyeBlinkLeft", "spelling"),              # side first
    ("eyeblinkleft", "eyeBlinkLeft", "spelling"),
    ("blendShape1.eyeBlinkLeft", "eyeBlinkLeft", "prefix"),  # Maya blendShape node
    ("head:eyeBlinkLeft", "eyeBlinkLeft", "prefix"),         # Maya namespace
    ("eyeBlinkLeft.001", "eyeBlinkLeft", "suffix"),          # Blender duplicate
    ("eyeBlinkLeft2", "eyeBlinkLeft", "suffix"),             # Blender second mesh
    ("blendShape1.Eye_Blink_L.001", "eyeBlinkLeft", "prefix"),
    ("eye_wide_right", "eyeWideRight", "spelling"),
    ("Jaw_Open", "jawOpen", "spelling"),                     # CC4
    ("Jaw_L", "jawLeft", "spelling"),
    ("Mouth_R", "mouthRight", "spelling"),
    ("Mouth_Smile_L", "mouthSmileLeft", "spelling"),
    ("Mouth_Close", "mouthClose", "spelling"),
    ("Mouth_Shrug_Upper", "mouthShrugUpper", "spelling"),
    ("Nose_Sneer_R", "noseSneerRight", "spelling"),
    ("Cheek_Puff", "cheekPuff", "spelling"),
    ("Tongue_Out", "tongueOut", "spelling"),
    ("Eye_L_Look_Down", "eyeLookDownLeft", "spelling"),
    ("Eye_R_Look_Up", "eyeLookUpRight", "spelling"),
    ("Eye_L_Look_L", "eyeLookOutLeft", "alias"),             # CC4: the left eye looking left looks out
    ("Eye_L_Look_R", "eyeLookInLeft", "alias"),
    ("Eye_R_Look_L", "eyeLookInRight", "alias"),
    ("Eye_R_Look_R", "eyeLookOutRight", "alias"),
    ("Brow_Drop_L", "browDownLeft", "alias"),
    ("Brow_Raise_Outer_R", "browOuterUpRight", "alias"),
    ("Cheek_Raise_L", "cheekSquintLeft", "alias"),
    ("Mouth_Down_Lower_R", "mouthLowerDownRight", "alias"),
    ("Mouth_Up_Upper_L", "mouthUpperUpLeft", "alias"),
    ("Mouth_Roll_In_Lower", "mouthRollLower", "alias"),
]
#: CC4 half shapes of a centre ARKit shape, other rigs' names and typos: never guessed.
UNKNOWN = ["Brow_Raise_Inner_L", "Cheek_Puff_L", "Mouth_Roll_In_Upper_L", "Mouth_Funnel_Up_L", "Blink_Left",
           "jawOpn", "eye_blink", "Eye_L_Look", "blendShape1", "Left", "", "123"]

SAMPLE = Path(__file__).resolve().parents[1] / "sample_assets"


@pytest.mark.parametrize("given, canonical, how", SPELLINGS, ids=[s[0] or "empty" for s in SPELLINGS])
def test_spelling_maps_to_canonical(given, canonical, how):
    assert arkit.match_name(given) == (canonical, how)
    if how in ("exact", "spelling"):
        assert arkit.normalize_name(given) == canonical


@pytest.mark.parametrize("given", UNKNOWN, ids=[u or "empty" for u in UNKNOWN])
def test_unknown_names_stay_unknown(given):
    assert arkit.match_name(given) == (None, "unknown")
    assert arkit.normalize_name(given) is None


@pytest.mark.parametrize("canonical", arkit.ARKIT_NAMES)
def test_every_arkit_name_in_every_generated_spelling(canonical):
    """All 52 names in the three original spellings and the studio ones read back to themselves."""
    snake = "_".join(w.lower() for w in arkit._WORD.findall(canonical))
    title = "_".join(w.capitalize() for w in arkit._WORD.findall(arkit.raw_name(canonical)))
    for spelling in (canonical, arkit.raw_name(canonical), arkit.livelink_name(canonical), snake, title,
                     f"blendShape1.{canonical}", f"{canonical}.001"):
        assert arkit.match_name(spelling)[0] == canonical, spelling


def test_cc_aliases_are_one_to_one():
    targets = list(arkit.CC_ALIASES.values())
    assert len(set(targets)) == len(targets) and set(targets) <= arkit.ARKIT_SET
    assert all(arkit.normalize_name(k) is None for k in arkit.CC_ALIASES)  # not mere respellings


def test_best_of_two_channels_keeps_the_shape():
    """exact beats a spelling variant beats a DCC suffix, whatever the order; the others keep their own
    names and are reported."""
    m = arkit.match_names(["eyeBlinkLeft.001", "EyeBlink_L", "eyeBlinkLeft", "jawOpen", "Jaw_Open"],
                          resolve=True)
    assert m.canonical == ["eyeBlinkLeft.001", "EyeBlink_L", "eyeBlinkLeft", "jawOpen", "Jaw_Open"]
    assert m.how == ["conflict", "conflict", "exact", "exact", "conflict"]
    assert m.conflicts == [("eyeBlinkLeft.001", "eyeBlinkLeft", "eyeBlinkLeft"),
                           ("EyeBlink_L", "eyeBlinkLeft", "eyeBlinkLeft"), ("Jaw_Open", "jawOpen", "jawOpen")]
    assert m.duplicates == []
    m = arkit.match_names(["mouthSmileLeft2", "Mouth_Smile_L"], resolve=True)
    assert m.canonical == ["mouthSmileLeft2", "mouthSmileLeft"] and m.how == ["conflict", "spelling"]
    # without resolve the old contract: both map, the clash is listed
    m = arkit.match_names(["eyeBlinkLeft", "eyeBlink_L"])
    assert m.canonical == ["eyeBlinkLeft", "eyeBlinkLeft"] and m.duplicates == ["eyeBlinkLeft"]


def test_name_map_comes_first_and_ranks_after_exact():
    mapping = {"Blink_L": "eyeBlinkLeft", "eyeBlinkRight": "eyeBlinkLeft2"}
    with pytest.raises(InputFileError, match="eyeBlinkLeft2"):
        read_name_map(mapping)
    mapping = read_name_map({"Blink_L": "eyeBlinkLeft", "JawDrop": "JawOpen"})
    assert mapping == {"Blink_L": "eyeBlinkLeft", "JawDrop": "jawOpen"}  # targets stored canonical
    assert arkit.match_name("Blink_L", name_map=mapping) == ("eyeBlinkLeft", "name-map")
    assert arkit.match_name("blendShape1.Blink_L", name_map=mapping) == ("eyeBlinkLeft", "name-map")
    # a map can remap an ARKit name (a mirrored rig)
    swap = read_name_map({"eyeBlinkLeft": "eyeBlinkRight", "eyeBlinkRight": "eyeBlinkLeft"})
    assert arkit.match_names(["eyeBlinkLeft", "eyeBlinkRight"], name_map=swap, resolve=True).canonical == [
        "eyeBlinkRight", "eyeBlinkLeft"]
    m = arkit.match_names(["Blink_L", "eyeBlinkLeft"], name_map=mapping, resolve=True)
    assert m.canonical == ["Blink_L", "eyeBlinkLeft"] and m.conflicts == [("Blink_L", "eyeBlinkLeft",
                                                                           "eyeBlinkLeft")]


# ----------------------------------------------------------------------------------------------------
# name-map files
# ----------------------------------------------------------------------------------------------------
def test_name_map_json_and_csv_read_the_same(tmp_path):
    mapping = {"Blink_L": "eyeBlinkLeft", "JawDrop": "jawOpen", "Lips Seal": "mouthClose"}
    (tmp_path / "m.json").write_text(json.dumps(mapping))
    (tmp_path / "m.csv").write_text("studio,arkit\n# house names\nBlink_L,eyeBlinkLeft\n\nJawDrop,jawOpen\n"
                                    '"Lips Seal",mouthClose\n')
    (tmp_path / "m.tsv").write_text("Blink_L\teyeBlinkLeft\nJawDrop\tjawOpen\nLips Seal\tmouthClose\n")
    (tmp_path / "noext").write_text(json.dumps(mapping))
    for name in ("m.json", "m.csv", "m.tsv", "noext"):
        assert read_name_map(tmp_path / name) == mapping, name
    assert read_name_map(None) is None


BAD_MAPS = {
    "unknown target": ("m.json", '{"Blink_L": "eyeBlinkLft"}', "not an ARKit name", "eyeBlinkLeft"),
    "duplicate target": ("m.json", '{"Blink_L": "eyeBlinkLeft", "blink_l2": "eyeBlink_L"}',
                         "both", "one studio channel"),
    "duplicate key": ("m.json", '{"Blink_L": "eyeBlinkLeft", "Blink_L": "eyeBlinkRight"}', "twice", None),
    "csv duplicate key": ("m.csv", "Blink_L,eyeBlinkLeft\nBlink_L,eyeBlinkRight\n", "twice", None),
    "csv three columns": ("m.csv", "Blink_L,eyeBlinkLeft,x\n", "3 cells", "pair per line"),
    # the file's line, after a header, a comment and a blank line ('CSV row 2' before: a user trial)
    "csv three columns, line 5": ("m.csv",
                                  "channel,arkitName\n# c\n\nBlink_L,eyeBlinkLeft\nJawDrop,jawOpen,x\n",
                                  "line 5 ('JawDrop, jawOpen, x') has 3 cells", None),
    "csv unknown target": ("m.csv", "Blink_L,blink\n", "not an ARKit name", None),
    "not JSON": ("m.json", '{"Blink_L": ', "not valid JSON", "JSON object"),
    "JSON list": ("m.json", '[["Blink_L", "eyeBlinkLeft"]]', "not an object", None),
    "non-text target": ("m.json", '{"Blink_L": 3}', "non-empty names", None),
    "empty": ("m.csv", "# nothing\n", "empty", None),
    "not UTF-8": ("m.csv", b"\xff\xfe\x00B\x00", "cannot read", "UTF-8"),
}


@pytest.mark.parametrize("case", list(BAD_MAPS))
def test_bad_name_map_names_file_and_fix(tmp_path, case):
    name, content, words, fix = BAD_MAPS[case]
    path = tmp_path / name
    (path.write_bytes if isinstance(content, bytes) else path.write_text)(content)
    with pytest.raises(InputFileError) as info:
        read_name_map(path)
    text = str(info.value)
    assert str(path) in text and "(fix: " in text and words in text
    if fix:
        assert fix in text


@pytest.mark.parametrize("kind", ["missing", "directory"])
def test_unreadable_name_map(tmp_path, kind):
    path = tmp_path / "map.json"
    if kind == "directory":
        path.mkdir()
    with pytest.raises(InputFileError, match="name map") as info:
        read_name_map(path)
    assert str(path) in str(info.value) and "--name-map" in str(info.value)


@pytest.mark.parametrize("given", [3, [("Blink_L", "eyeBlinkLeft")]])
def test_a_name_map_of_the_wrong_kind_is_an_option_error(samples, given):
    """``read_avatar(path, name_map=3)`` (or a list of pairs) died with Python's TypeError ('expected str,
    bytes or os.PathLike object, not int') from deep in the name-map reader; every function taking
    ``name_map`` (read_avatar, check, inspect_file, personalize_avatar) reads it there."""
    import usdface
    from usdface.errors import OptionError

    for call in (lambda: read_name_map(given),
                 lambda: usdface.read_avatar(samples / "avatar.usda", name_map=given),
                 lambda: usdface.check(samples / "avatar.usda", name_map=given)):
        with pytest.raises(OptionError, match="name_map must be a .* dict or a JSON / CSV file's") as info:
            call()
        assert info.value.fix


def test_bad_name_map_stops_every_command_before_work(samples, tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text('{"Blink_L": "blinky"}')
    avatar, capture = str(samples / "avatar.usda"), str(samples / "capture.usda")
    out = tmp_path / "out.usda"
    for argv in (["inspect", avatar], ["check", avatar], ["landmarks", avatar, "-o", str(out)],
                 ["render", avatar, "-o", str(tmp_path / "x.png")],
                 ["personalize", avatar, capture, "-o", str(out), "-q"],
                 ["retarget", avatar, capture, "-o", str(tmp_path / "m.json"), "-q"]):
        assert main([*argv, "--name-map", str(bad)]) == 2, argv
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and str(bad) in err and "'blinky'" in err, argv
    assert list(tmp_path.iterdir()) == [bad]


# ----------------------------------------------------------------------------------------------------
# the reader on a real rig
# ----------------------------------------------------------------------------------------------------
def test_reader_keeps_the_best_of_two_channels(tmp_path):
    """Two channels of one mesh meaning one shape: the exact one keeps it, the other keeps its own name
    (with its own offsets) and is reported in the name report and the notes."""
    from pxr import Vt
    from test_usd_rig import edit_stage, expected_rig, write_rig

    from usdface.io.usd_rig import read_avatar

    path = tmp_path / "a.usda"
    write_rig(path, "y_cm")
    truth = expected_rig()["Head"]["deltas"]
    edit_stage(path, lambda s: s.GetPrimAtPath("/Avatar/Head").GetAttribute("skel:blendShapes").Set(
        Vt.TokenArray(["eyeBlink_L", "eyeBlinkLeft", "mouthSmileLeft"])))
    head = read_avatar(path).mesh("Head")
    assert head.names == ["eyeBlink_L", "eyeBlinkLeft", "mouthSmileLeft"]
    np.testing.assert_allclose(head.deltas[head.index("eyeBlinkLeft")], truth[1], atol=1e-9)
    np.testing.assert_allclose(head.deltas[head.index("eyeBlink_L")], truth[0], atol=1e-9)
    avatar = read_avatar(path)
    entry = avatar.name_report["/Avatar/Head"]
    assert entry["conflicts"] == [["eyeBlink_L", "eyeBlinkLeft", "eyeBlinkLeft"]]
    assert ["eyeBlink_L", None, "conflict"] in entry["channels"]
    from usdface.inspect import summarize_avatar

    arkit_report = summarize_avatar(avatar)["meshes"][0]["arkit"]
    assert arkit_report["extra"] == ["eyeBlink_L"] and arkit_report["misspelt"] == {}
    assert any("'eyeBlink_L' also means 'eyeBlinkLeft'" in n for n in avatar.metadata["notes"])
    # a name map whose loser keeps a name another channel maps to is refused, naming both channels
    with pytest.raises(RigError, match="same ARKit shape twice") as info:
        read_avatar(path, name_map={"eyeBlinkLeft": "mouthSmileLeft"})
    assert "eyeBlink_L" in str(info.value) and "--name-map" in str(info.value)
    # map entries that match no channel are noted (a typo in the map would otherwise go unseen)
    notes = read_avatar(path, name_map={"Nope": "jawOpen", "blendShape9.mouthSmileLeft": "mouthSmileRight"}
                        ).metadata["notes"]
    assert "name map entries that match no channel: Nope, blendShape9.mouthSmileLeft" in notes


def _studio_name(canonical: str, k: int) -> str:
    """A studio-style channel name for ``canonical``, cycling through the spellings of the issue."""
    reverse = {v: c for c, v in arkit.CC_ALIASES.items()}
    if canonical in reverse:
        return reverse[canonical]
    words = arkit._WORD.findall(arkit.raw_name(canonical))
    styles = [
        "_".join(w.lower() for w in arkit._WORD.findall(canonical)),     # eye_blink_left
        "_".join(w.capitalize() for w in words),                          # Eye_Blink_L (CC4)
        f"blendShape1.{canonical}",                                       # Maya node prefix
        "".join(w.capitalize() for w in words[:-1]) + "_" + words[-1],   # EyeBlink_L
        arkit.raw_name(canonical),                                        # eyeBlink_L
        arkit.livelink_name(canonical),                                   # EyeBlinkLeft
        f"{canonical}.001",                                               # Blender duplicate
    ]
    name = styles[k % len(styles)]
    return name if name != canonical else styles[0]  # a centre shape's raw value is its canonical name


#: Channels only the studio's map can name.
HOUSE = {"jawOpen": "JawDrop", "mouthClose": "LipsSeal", "browInnerUp": "BrowsWorry"}


@pytest.fixture(scope="module")
def studio_avatar(samples, tmp_path_factory):
    """The sample avatar with every channel token renamed the way studios ship them (and the BlendShape
    prims renamed ``shape_NN`` so their names cannot rescue the tokens), plus the name map for the house
    names, as JSON and CSV."""
    from pxr import Sdf

    folder = tmp_path_factory.mktemp("studio")
    src = Sdf.Layer.FindOrOpen(str(samples / "avatar.usda"))
    layer = Sdf.Layer.CreateNew(str(folder / "studio.usda"))
    layer.TransferContent(src)
    studio = {c: HOUSE.get(c) or _studio_name(c, k) for k, c in enumerate(arkit.ARKIT_NAMES)}
    renamed = {}

    def visit(path):
        spec = layer.GetPrimAtPath(path)
        for attr_name in ("skel:blendShapes", "blendShapes"):
            attr = spec.attributes.get(attr_name) if spec else None
            if attr is not None and attr.default:
                attr.default = [studio[t] for t in attr.default]
        rel = spec.relationships.get("skel:blendShapeTargets") if spec else None
        if rel is not None:
            targets = list(rel.targetPathList.explicitItems)
            new = []
            for k, target in enumerate(targets):
                new_path = target.GetParentPath().AppendChild(f"shape_{k:02d}")
                renamed[target] = new_path
                new.append(new_path)
            rel.targetPathList.explicitItems = new

    layer.Traverse(Sdf.Path.absoluteRootPath, lambda p: visit(p) if p.IsPrimPath() else None)
    edit = Sdf.BatchNamespaceEdit()
    for old, new in renamed.items():
        edit.Add(old, new)
    assert layer.Apply(edit)
    layer.Save()
    house = {v: k for k, v in HOUSE.items()}
    (folder / "names.json").write_text(json.dumps(house))
    (folder / "names.csv").write_text("studio_channel,arkitName\n" + "".join(f"{k},{v}\n"
                                                                            for k, v in house.items()))
    return folder / "studio.usda", folder / "names.json", folder / "names.csv", studio


def test_studio_avatar_reads_to_the_sample_rig(samples, studio_avatar):
    from usdface.io.usd_rig import read_avatar

    path, json_map, csv_map, studio = studio_avatar
    original = read_avatar(samples / "avatar.usda")
    plain = read_avatar(path)
    head = plain.mesh("Head")
    assert head.source.channel_tokens[0] == studio["eyeBlinkLeft"] != "eyeBlinkLeft"
    assert "shape_00" in head.source.shape_prims[0]
    # without the map only the house names stay unknown (and are reported)
    assert sorted(plain.name_report["/Avatar/Head"]["unknown"]) == sorted(HOUSE.values())
    for name_map in (json_map, csv_map):
        mapped = read_avatar(path, name_map=name_map)
        for m in original.meshes:
            r = mapped.mesh(m.name)
            assert r.names == m.names
            np.testing.assert_array_equal(r.deltas, m.deltas)
        hows = {h for _, _, h in mapped.name_report["/Avatar/Head"]["channels"]}
        assert hows == {"spelling", "alias", "prefix", "suffix", "name-map"}


@pytest.fixture(scope="module")
def sample_fit(samples):
    from usdface.io import read_capture
    from usdface.personalize import fit_personalized_shapes

    capture = read_capture(samples / "capture.usda")
    return capture, fit_personalized_shapes(capture).rig


def test_studio_avatar_personalizes_to_the_same_offsets(samples, studio_avatar, sample_fit):
    """The same rig under studio names (and the name map as a file) gives the sample's offsets, to 1e-9 m."""
    from usdface.api import personalize_avatar

    path, json_map, _, _ = studio_avatar
    capture, rig = sample_fit
    from usdface.io.usd_rig import read_avatar

    ref = personalize_avatar(samples / "avatar.usda", capture, None, rig=rig)
    got = personalize_avatar(path, capture, None, rig=rig, name_map=json_map)
    generic = read_avatar(samples / "avatar.usda").mesh("Head").deltas
    assert got.names == ref.names and got.face_mesh == ref.face_mesh
    assert set(got.offsets) == set(ref.offsets)
    for key, want in ref.offsets.items():
        assert np.abs(got.offsets[key] - want).max() <= 1e-9, key
    assert np.abs(ref.offsets["/Avatar/Head"] - generic).max() > 1e-4  # something was personalized


def test_face_mesh_not_found_names_the_meshes(samples, sample_fit, monkeypatch):
    """A --face-mesh that is no mesh with blend shapes stops before the fit, naming the meshes there are."""
    import usdface.personalize
    from usdface.api import personalize_avatar

    def no_fit(*args, **kwargs):
        raise AssertionError("the fit ran before --face-mesh was checked")

    monkeypatch.setattr(usdface.personalize, "fit_personalized_shapes", no_fit)
    capture, _ = sample_fit
    with pytest.raises(RigError, match="no mesh 'Nose'") as info:
        personalize_avatar(samples / "avatar.usda", capture, None, face_mesh="Nose")
    assert "/Avatar/Head" in str(info.value) and "/Avatar/Mouth" in str(info.value)


def test_cli_passes_name_map_and_face_mesh(monkeypatch, tmp_path):
    import usdface.api

    seen = {}

    def fake(*args, **kwargs):
        seen.update(kwargs)
        raise InputFileError("stop here", fix="none")

    monkeypatch.setattr(usdface.api, "personalize_avatar", fake)
    monkeypatch.setattr(usdface.api, "write_retarget_map", fake)
    assert main(["personalize", "a.usda", "c.usda", "-o", str(tmp_path / "o.usda"), "-q",
                 "--name-map", "m.csv", "--face-mesh", "/Avatar/Head"]) == 2
    assert seen["name_map"] == "m.csv" and seen["face_mesh"] == "/Avatar/Head"
    seen.clear()
    assert main(["retarget", "a.usda", "c.usda", "-o", str(tmp_path / "m.json"), "-q",
                 "--name-map", "x.json"]) == 2
    assert seen["name_map"] == "x.json"


def test_name_map_round_trip_through_the_cli(samples, studio_avatar, tmp_path, capsys):
    """``personalize --name-map`` on the studio rig writes a layer over the studio rig's own prims; read back
    with the same map it holds the same shapes as the sample's layer; ``inspect``/``check`` list how every
    channel was mapped."""
    from usdface.io.usd_rig import read_avatar

    path, json_map, csv_map, studio = studio_avatar
    out = tmp_path / "studio_person.usda"
    before = path.read_bytes()
    assert main(["personalize", str(path), str(samples / "capture.usda"), "-o", str(out), "-q",
                 "--name-map", str(csv_map), "--face-mesh", "Head"]) == 0
    capsys.readouterr()
    assert path.read_bytes() == before
    layer = read_avatar(out, name_map=csv_map)
    assert layer.mesh("Head").source.channel_tokens == read_avatar(path).mesh("Head").source.channel_tokens
    generic = read_avatar(path, name_map=csv_map).mesh("Head")
    assert layer.mesh("Head").names == generic.names == list(arkit.ARKIT_NAMES)
    assert np.abs(layer.mesh("Head").deltas - generic.deltas).max() > 1e-4

    assert main(["inspect", str(path), "--name-map", str(json_map), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    channels = {c["channel"]: c for c in report["meshes"][0]["channels"]}
    assert len(channels) == 52
    assert channels["JawDrop"] == {"channel": "JawDrop", "arkit": "jawOpen", "how": "name-map",
                                   "label": "name map"}
    assert channels[studio["eyeBlinkLeft"]]["arkit"] == "eyeBlinkLeft"
    assert channels["Cheek_Raise_L"]["how"] == "alias"
    assert {c["how"] for c in channels.values()} == {"spelling", "alias", "prefix", "suffix", "name-map"}
    assert main(["inspect", str(path)]) == 0
    text = capsys.readouterr().out
    assert "channel names: 0 of 52 exact ARKit names" in text
    assert "JawDrop: unmapped (not an ARKit shape; map it with --name-map)" in text
    assert f"{studio['eyeBlinkLeft']} -> eyeBlinkLeft (spelling variant)" in text
    assert "Cheek_Raise_L -> cheekSquintLeft (Character Creator name)" in text
    assert main(["check", str(path), "--no-pixar", "--name-map", str(json_map), "--json"]) in (0, 1)
    issues = json.loads(capsys.readouterr().out)["issues"]
    assert not [i for i in issues if i["rule"] == "ArkitNames" and "missing" in i["message"]]
    assert any("'JawDrop'" in i["message"] and "name map" in i["message"] for i in issues)


def test_a_studio_prefix_without_its_name_map_is_named_not_registered_on_the_mouth(samples, tmp_path,
                                                                                   capsys):
    """Every Head channel and BlendShape prim renamed ``STU_<ARKit name>`` (a studio prefix the reader
    cannot undo) and no --name-map: the Mouth's few ARKit shapes made it the face and the run failed in the
    registration ("shrank the capture to a point ... /Avatar/Mouth", a user trial). Now the run stops before
    any work naming the Head, its lookalike names and --name-map; nothing is written."""
    from pxr import Sdf

    src = Sdf.Layer.FindOrOpen(str(samples / "avatar.usda"))
    layer = Sdf.Layer.CreateNew(str(tmp_path / "prefixed.usda"))
    layer.TransferContent(src)
    head = layer.GetPrimAtPath("/Avatar/Head")
    attr = head.attributes.get("skel:blendShapes")
    attr.default = [f"STU_{t}" for t in attr.default]
    rel = head.relationships.get("skel:blendShapeTargets")
    targets = list(rel.targetPathList.explicitItems)
    edit = Sdf.BatchNamespaceEdit()
    for t in targets:
        edit.Add(t, t.GetParentPath().AppendChild(f"STU_{t.name}"))
    rel.targetPathList.explicitItems = [t.GetParentPath().AppendChild(f"STU_{t.name}") for t in targets]
    assert layer.Apply(edit)
    layer.Save()
    out = tmp_path / "o.usda"
    assert main(["personalize", str(tmp_path / "prefixed.usda"), str(samples / "capture.usda"), "-o",
                 str(out)]) == 2
    err = capsys.readouterr().err
    assert "/Avatar/Head has 52 shapes whose names look like" in err
    assert "STU_eyeBlinkLeft -> eyeBlinkLeft" in err
    assert "--name-map" in err and not out.exists()


def test_a_second_mesh_with_prefixed_and_corrective_shapes_does_not_stop_the_face(samples, tmp_path):
    """A beard mesh carrying every shape as ``Beard_<name>`` plus a corrective ``jawOpen_mouthClose``: its
    lookalike names count as 52 distinct shapes, not 53, so the Head (all 52 capture names) stays the face
    (a review: refused as 'more than the 52 of /Avatar/Head')."""
    from usdface.io.avatar_writer import write_rig_usd
    from usdface.io.usd_rig import read_avatar
    from usdface.model import FaceRig
    from usdface.transfer import personalize_avatar

    avatar = read_avatar(samples / "avatar.usda")
    head = avatar.mesh("Head")
    beard_names = [f"Beard_{n}" for n in head.names] + ["jawOpen_mouthClose"]
    beard = FaceRig(head.neutral + [0.0, 0.0, 0.002], head.triangles, beard_names,
                    np.concatenate([head.deltas, head.deltas[[head.index("jawOpen")]] * 0.1]), name="Beard")
    rigs = [FaceRig(m.neutral, m.triangles, m.names, m.deltas, name=m.name) for m in avatar.meshes] + [beard]
    rigs += [FaceRig(p, t, [], np.zeros((0, len(p), 3)), name=k.rsplit("/", 1)[-1])
             for k, (p, t) in avatar.metadata["static_meshes"].items()]
    path = write_rig_usd(rigs, tmp_path / "beard.usda", meters_per_unit=avatar.meters_per_unit)
    result = personalize_avatar(path, samples / "capture.usda", None, dry_run=True)
    assert result.face_mesh == "/Avatar/Head"


def test_a_retarget_map_given_as_the_name_map_is_named(samples, tmp_path, capsys):
    """A user trial: '--name-map map.json' with the map 'usdface retarget' writes said "name map target
    'usdface.retarget/1' (for 'format') is not an ARKit name (fix: ... (did you mean 'eyeBlinkLeft, jawOpen,
    ...'?))"."""
    retarget_map = tmp_path / "map.json"
    retarget_map.write_text(json.dumps({"format": "usdface.retarget/1", "source": ["jawOpen"]}))
    assert main(["inspect", str(samples / "avatar.usda"), "--name-map", str(retarget_map)]) == 2
    err = capsys.readouterr().err
    assert "a usdface output (usdface.retarget/1), not a name map" in err and "did you mean" not in err
    with pytest.raises(InputFileError, match=r"one of the 52 ARKit names \(eyeBlinkLeft, jawOpen, \.\.\.\)"):
        read_name_map({"Brow_L": "zzzz"})
    with pytest.raises(InputFileError, match=r"did you mean 'jawOpen'\?"):
        read_name_map({"Jaw": "jawOpn"})


def test_check_notes_name_map_entries_that_match_no_channel(tmp_path, capsys):
    """``inspect --name-map`` notes map entries that match no channel (a typo in the map); ``check`` with
    the same map said nothing. A map entry naming a channel as it is (``eyeBlinkLeft`` -> ``eyeBlinkLeft``)
    is no 'non-canonical spelling'."""
    import json

    m = tmp_path / "m.json"
    m.write_text(json.dumps({"JawDrop": "jawOpen", "eyeBlinkLeft": "eyeBlinkLeft"}))
    assert main(["check", str(SAMPLE / "avatar.usda"), "--name-map", str(m), "--no-pixar", "--json"]) == 0
    found = [i for i in json.loads(capsys.readouterr().out)["issues"] if "name map" in i["message"]]
    assert len(found) == 1 and "'JawDrop'" in found[0]["message"]
    assert "eyeBlinkLeft" not in found[0]["message"]


def test_an_avatar_without_arkit_names_points_to_the_name_map(shared, samples, tmp_path):
    """A rig whose channels are no ARKit names (Blender's ``Key_1``) and no name map: personalize's fix
    said only 'the avatar needs ARKit-named BlendShapes', where 'usdface check' on the same file names
    --name-map too."""
    from usdface.api import personalize_avatar
    from usdface.errors import RigError

    avatar = shared / "data" / "usd-real-world" / "blender" / "blendshape.usda"
    with pytest.raises(RigError, match="no face-like blend shapes") as info:
        personalize_avatar(avatar, samples / "capture.usda", tmp_path / "o.usda")
    assert "--name-map FILE (name_map=)" in str(info.value) and "usdface inspect" in str(info.value)
    assert not list(tmp_path.iterdir())
