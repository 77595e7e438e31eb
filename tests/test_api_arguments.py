"""The API's arguments checked as the command line checks them: numbers out of range, strings where a list or
a number goes, arguments of the wrong kind, each refused before any work with a UsdFaceError naming the
fix."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from usdface.errors import OptionError, UsdFaceError
from usdface.io.livelink import write_livelink_csv

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


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
    with pytest.raises(OptionError, match=needle):
        api.personalize_avatar(A, C, tmp_path / "p.usda", **options, **mode)
    assert not (tmp_path / "p.usda").exists()


def test_api_numbers_that_are_fine_pass_the_check():
    from usdface.transfer.options import check_numbers

    check_numbers(mu="auto", extension_length=None, falloff=0, support=None)
    check_numbers(mu="1e-3", extension_length=0.5, falloff=0.15, support=(0.0, 0.0))
    check_numbers(mu=2, extension_length=2, falloff=1, support=[0.01, 0.03])


def test_api_refuses_what_it_cannot_use():
    from usdface import api

    with pytest.raises(UsdFaceError, match="must be a FaceRig, an Avatar or an avatar file"):
        api.compute_landmarks(3)
    with pytest.raises(OptionError, match="bad role 'bogus': not a frame role") as err:
        api.evaluate_capture(C, role="bogus")
    assert "role='train'" in err.value.fix


@pytest.mark.parametrize("call, needle", [
    (lambda api, tmp: api.evaluate_capture(C, role="val"), r"bad role 'val'"),
    (lambda api, tmp: api.write_retarget_map(A, C, tmp / "m.json", mu=-1), r"bad mu -1"),
    (lambda api, tmp: api.check_personalize_options(face_transfer="persn"), r"unknown face transfer 'persn' "
                                                                            r"\(face_transfer \(--face-"),
    (lambda api, tmp: api.check_personalize_options(prior="x"), r"unknown prior 'x' \(prior"),
    (lambda api, tmp: api.check_personalize_options(approximation="x"), r"unknown approximation 'x'"),
    (lambda api, tmp: api.check_personalize_options(map_prior="x"), r"unknown map prior 'x'"),
    (lambda api, tmp: api.check_personalize_options(support=(0.05, 0.01)), r"low > high"),
    (lambda api, tmp: api.check_personalize_options(dry_run="yes"),
     r"bad dry_run 'yes': personalize's dry_run is a boolean"),
    (lambda api, tmp: api.export_avatar(A, flatten=tmp / "f.usdc", variant="x"), r"unknown variant 'x'"),
    (lambda api, tmp: api.export_avatar(A), r"nothing to export"),
    (lambda api, tmp: api.check(A, rules=["NoSuchRule"]), r"unknown check rule"),
])
def test_bad_option_values_are_option_errors(tmp_path, call, needle):
    """User trial: ``evaluate_capture(role="val")``, ``mu=-1`` and the other option values out of their set
    or range raised a bare UsdFaceError, which a script cannot tell from a failed step: an OptionError (a
    UsdFaceError, so ``except UsdFaceError`` still catches it) naming the option and the fix."""
    from usdface import api

    with pytest.raises(OptionError, match=needle) as err:
        call(api, tmp_path)
    assert err.value.fix and not any(tmp_path.iterdir())


def test_weight_bounds_as_text_are_refused_with_the_manifest_spelling():
    """A manifest cell or ``--set weight_bounds=01`` reached the check as the string "01", whose characters
    passed as the bounds (0, 1) (and "0,2" was refused with a fix, ``(0, 1)`` / ``None``, that a manifest
    cannot spell either): a string is refused, and the fix names the JSON a manifest takes."""
    import pytest

    from usdface import api
    from usdface.errors import OptionError

    for text in ("01", "0,2", "(0, 2)", "None"):
        with pytest.raises(OptionError, match=r"bad weight bounds") as err:
            api.check_personalize_options(weight_bounds=text)
        assert "[0, 1] in a batch manifest" in str(err.value) and "null in a batch manifest" in str(err.value)
    api.check_personalize_options(weight_bounds=[0, 2])
    api.check_personalize_options(weight_bounds=None)


def test_support_as_text_is_refused_before_any_work():
    """``--set support=01`` passed the batch's preflight (the string's two characters as low and high) and
    the item failed after its fit with ``UFuncTypeError: ufunc 'subtract' did not contain a loop``."""
    import pytest

    from usdface import api
    from usdface.errors import UsdFaceError

    for text in ("01", "ab"):
        with pytest.raises(UsdFaceError, match=r"bad support") as err:
            api.check_personalize_options(support=text)
        assert "[0.01, 0.03] in a batch manifest" in str(err.value)
    api.check_personalize_options(support=[0.01, 0.03])


def test_api_arguments_of_the_wrong_kind_are_refused_with_the_fix(tmp_path):
    """A docs walk-through: ``select_capture_frames(take, per_shape=1.5)`` / ``test_every="5"`` died with
    numpy's TypeError, ``write_fit_rig("x", out)`` with AttributeError; each is a UsdFaceError naming the
    argument and the fix, before any work."""
    import usdface
    from usdface.errors import CaptureError, UsdFaceError

    take = tmp_path / "t.csv"
    write_livelink_csv(take, ["jawOpen"], np.full((4, 1), 0.5), np.arange(4) / 30.0)
    for kw, word in (({"per_shape": 1.5}, "per_shape"), ({"test_every": "5"}, "test_every"),
                     ({"per_shape": True}, "per_shape"), ({"threshold": "x"}, "threshold"),
                     ({"min_separation": -1}, "min_separation")):
        with pytest.raises(CaptureError, match=word):
            usdface.select_capture_frames(take, **kw)
    with pytest.raises(UsdFaceError, match="FitResult or a FaceRig") as err:
        usdface.write_fit_rig("x", tmp_path / "o.usda")
    assert "fit_capture" in err.value.fix and not (tmp_path / "o.usda").exists()


def test_check_rules_as_a_string_are_rule_names(samples):
    """``usdface.check(path, rules="ArkitNames")`` (one rule, as a Python user writes it; the CLI's
    ``--rules ArkitNames,PointIndices`` form) failed with "unknown check rule(s) ['A', 'r', 'k', ...]": the
    string was read letter by letter. A string is a rule name or comma-separated names."""
    import pytest as _pytest

    from usdface import api
    from usdface.errors import UsdFaceError

    assert api.check(samples / "avatar.usda", pixar=False, rules="ArkitNames") == []
    assert api.check(samples / "avatar.usda", pixar=False, rules="ArkitNames, PointIndices") == []
    with _pytest.raises(UsdFaceError, match=r"rule\(s\) 'ArkitName' \(did you mean ArkitNames\?\) \(fix"):
        api.check(samples / "avatar.usda", pixar=False, rules="ArkitName")


def test_evaluate_methods_takes_methods_as_a_string(samples):
    """``evaluate_methods(capture, methods="menzel")`` failed with 'unknown method(s) in --methods: m, e,
    n, z, e, l': the string was read letter by letter. One name or comma-separated names, as --methods."""
    import warnings

    from usdface import api

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        report = api.evaluate_methods(samples / "capture.usda", methods="dt")
    assert "dt" in report["methods"] and "menzel" not in report["methods"]


def test_write_capture_takes_one_input_path(samples, tmp_path):
    """``write_capture(capture, out, inputs="take.usda")`` (one path) took the string's characters as input
    paths, '.' and '/' among them, and refused every output as 'inside the input folder /'."""
    from usdface import api

    capture = api.read_capture(samples / "capture.usda")
    take = tmp_path / "take.usda"
    take.write_text("#usda 1.0\n")
    out = api.write_capture(capture, tmp_path / "c.usda", inputs=str(take), exact=False)
    assert out.exists()
    with pytest.raises(Exception, match="input"):
        api.write_capture(capture, take, force=True, inputs=str(take))


def test_compute_landmarks_refuses_a_camera_that_is_no_position_with_the_fix(samples):
    """api.md: bad input raises a UsdFaceError subclass with the fix. ``compute_landmarks(avatar,
    camera="0,1.6,0.35")`` (the CLI's spelling) died with numpy's 'ValueError: could not convert string to
    float' from inside the visibility code."""
    from usdface import api
    from usdface.errors import LandmarkError

    for bad in ("0,1.6,0.35", (0, 1.6), (0, float("nan"), 1)):
        with pytest.raises(LandmarkError, match="camera") as err:
            api.compute_landmarks(samples / "avatar.usda", camera=bad)
        assert "fix:" in str(err.value)


def test_a_numeric_string_mu_is_the_number_not_a_late_value_error(samples, tmp_path):
    """``personalize_avatar(..., mu="0.01")`` passed the options' check (a numeric string counts, as the CLI
    reads it) and then died after the registration and the fit with retarget's bare 'ValueError: mu must be
    a number or 'auto', not '0.01''. It is the number 0.01, as ``reg="1e-3"`` is for the fit."""
    pytest.importorskip("usdface.transfer")
    from usdface import api

    result = api.write_retarget_map(samples / "avatar.usda", samples / "capture.usda", tmp_path / "m.json",
                                    mu="0.01", method="dt")
    assert result.report["retarget"]["mu"] == pytest.approx(0.01)


class _FsPath:
    """A path object that is no ``pathlib.Path`` (an asset system's), an ``os.PathLike`` the checks take."""

    def __init__(self, path):
        self.path = str(path)

    def __fspath__(self):
        return self.path


def test_a_path_like_that_is_no_pathlib_path_is_read_as_a_path(tmp_path):
    """The argument checks take any ``os.PathLike``; personalize with ``inspect=True`` then took such an
    avatar for an ``Avatar`` ('object has no attribute mesh'), and fit_capture fitted such a capture but
    wrote a rig that recorded no capture file (its provenance lost the input a str or Path records)."""
    import os

    import usdface
    from usdface.io.usd_rig import usdface_layer_data

    assert isinstance(_FsPath(A), os.PathLike)
    out = usdface.personalize_avatar(_FsPath(A), _FsPath(C), _FsPath(tmp_path / "p.usda"),
                                     inspect=True).out_path
    assert out == (tmp_path / "p.usda").absolute() and out.is_file()
    usdface.fit_capture(C, "dt", out_path=tmp_path / "a.usda")
    usdface.fit_capture(_FsPath(C), "dt", out_path=tmp_path / "b.usda")
    recorded = [usdface_layer_data(tmp_path / f"{k}.usda") for k in "ab"]
    assert recorded[0]["captureDigest"] and recorded[1].get("captureDigest") == recorded[0]["captureDigest"]


def test_an_empty_output_path_is_refused_not_the_current_folder(tmp_path, monkeypatch):
    """``import_capture_folder(folder, "")`` (an unset variable) wrote the capture folder's files into the
    current folder: ``Path("")`` is ``.``."""
    import usdface
    from usdface.errors import OptionError

    monkeypatch.chdir(tmp_path)
    with pytest.raises(OptionError, match="out_path is an empty string"):
        usdface.import_capture_folder(tmp_path, "")
    with pytest.raises(OptionError, match="out_path is an empty string"):
        usdface.personalize_avatar("a.usda", "c.usda", "")
    assert list(tmp_path.iterdir()) == []


def _flag_calls(out: Path, layer: Path):
    """(call, argument) pairs: each documented API function's boolean arguments given as the string ``"no"``
    (a config file's or an environment variable's spelling), which Python counts as true."""
    from usdface import api

    take = ROOT / "tests" / "does-not-matter.csv"
    return [
        (lambda: api.personalize_avatar(A, C, out / "p.usda", force="no"), "force"),
        (lambda: api.personalize_avatar(A, C, out / "p.usda", inspect="no"), "inspect"),
        (lambda: api.personalize_avatar(A, C, out / "p.usda", landmarks="no"), "landmarks"),
        (lambda: api.personalize_avatar(A, C, out / "p.usda", dry_run="no"), "dry_run"),
        (lambda: api.write_retarget_map(A, C, out / "m.json", force="no"), "force"),
        (lambda: api.fit_capture(C, out_path=out / "r.usda", force="no"), "force"),
        (lambda: api.import_capture_folder(C, out / "c.usda", force="no"), "force"),
        (lambda: api.import_capture_folder(C, out / "c.usda", exact="no"), "exact"),
        (lambda: api.write_capture(api.read_capture(C), out / "c.usda", exact="no"), "exact"),
        (lambda: api.select_capture_frames(take, out / "c.usda", force="no"), "force"),
        (lambda: api.import_livelink_take(take, out / "t.usda", force="no"), "force"),
        (lambda: api.evaluate_methods(C, "dt", json_path=out / "e.json", force="no"), "force"),
        (lambda: api.personalize_batch(out / "m.csv", force="no"), "force"),
        (lambda: api.check(A, pixar="no"), "pixar"),
        (lambda: api.write_review(layer, out / "r.html", fit_errors="no"), "fit_errors"),
        (lambda: api.write_review(layer, out / "r.html", force="no"), "force"),
        (lambda: api.export_avatar(layer, gltf=out / "x.glb", skin="no"), "skin"),
        (lambda: api.export_avatar(layer, gltf=out / "x.glb", force="no"), "force"),
    ]


def test_boolean_arguments_given_as_strings_are_refused_before_any_work(tmp_path):
    """A user trial: ``force="no"`` counted as true and replaced an existing layer, ``skin="no"`` exported the
    skin, ``pixar="no"`` ran Pixar's validators, ``inspect="no"`` wrote the inspection data (the landmark
    functions' booleans were already refused so). Each is an OptionError naming the function, the argument
    and the fix, and nothing is written or replaced."""
    layer = tmp_path / "existing.usda"
    layer.write_text("#usda 1.0\n")             # an existing output a truthy "no" would have replaced
    for index, (call, name) in enumerate(_flag_calls(tmp_path, layer)):
        with pytest.raises(OptionError, match=rf"bad {name} 'no': \w+'s? {name} is a boolean") as err:
            call()
        assert err.value.fix == f"pass {name}=True or {name}=False", index
    assert sorted(p.name for p in tmp_path.iterdir()) == ["existing.usda"]
    assert layer.read_text() == "#usda 1.0\n"


def test_one_boolean_check_none_is_the_default(tmp_path):
    """Stop 43: the API's arguments (``_flags``), a batch row's / Pyblish instance's options
    (``check_item_options``) and ``personalize_batch(options=)`` checked booleans three ways: ``None``
    refused, refused, and let through to be refused by the row check with a third message. One check now
    (``usdface.errors.expect_flag``): ``None`` is the default everywhere, anything else but a boolean
    refused with one message."""
    from usdface import api
    from usdface.landmarks import compute_landmarks as core_landmarks

    assert api._flags("check", pixar=None) == (True,)                 # the signature's defaults
    assert api._flags("export_avatar", skin=None, force=None) == (True, False)
    assert api._flags("write_capture", force=np.True_, exact=None) == (True, True)
    assert api._flags("personalize_avatar", inspect=None, landmarks=None, force=None,
                      dry_run=None) == (False,) * 4
    api.check_item_options({"inspect": None, "force": None, "landmarks": None})   # a JSON row's null
    options = {"symmetric": None}
    api._refuse_unknown_keywords(core_landmarks, options, "compute_landmarks")
    assert options == {"symmetric": False}
    manifest = tmp_path / "people.csv"
    (tmp_path / "done.usda").write_text("#usda 1.0\n")          # resumed: skipped after the checks
    manifest.write_text(f"avatar,capture,output\n{A},{C},done.usda\n")
    api.personalize_batch(manifest, jobs=1, options={"inspect": None})   # was refused as the row's
    style = r"^bad inspect 'yes': .+ inspect is a boolean \(True or False; None: the default, False\)"
    for call in (lambda: api._flags("personalize_avatar", inspect="yes"),
                 lambda: api.check_item_options({"inspect": "yes"}),
                 lambda: api.personalize_batch(manifest, jobs=1, options={"inspect": "yes"})):
        with pytest.raises(OptionError, match=style) as err:
            call()
        assert err.value.fix


def test_an_existing_layer_is_not_replaced_by_force_no(tmp_path):
    """The case that mattered: ``personalize_avatar(..., force="no")`` over an existing output replaced it."""
    from usdface import api

    out = tmp_path / "person.usda"
    out.write_text("#usda 1.0\n# the studio's published layer\n")
    with pytest.raises(OptionError, match="personalize_avatar's force is a boolean"):
        api.personalize_avatar(A, C, out, force="no")
    assert out.read_text() == "#usda 1.0\n# the studio's published layer\n"


@pytest.mark.parametrize("value", [-1, "1000", 2.5, True])
def test_write_review_refuses_a_max_vertices_the_cli_refuses(personalized_sample, tmp_path, value):
    """``max_vertices=-1`` and ``"1000"`` were taken without a word (``--max-vertices -1`` is refused)."""
    from usdface import api

    with pytest.raises(OptionError, match=r"bad max_vertices .*whole number >= 0 or None") as err:
        api.write_review(personalized_sample, tmp_path / "r.html", max_vertices=value)
    assert "--max-vertices" in err.value.fix and not (tmp_path / "r.html").exists()


@pytest.mark.parametrize("radius", [-1, "x", float("nan"), True])
def test_compute_landmarks_refuses_a_radius_that_is_no_length(samples, radius):
    """``radius=-1`` and ``radius="x"`` were taken without a word (``--radius -1`` is refused)."""
    from usdface import api
    from usdface.errors import LandmarkError

    with pytest.raises(LandmarkError, match="multi-cover radius .* is not a length >= 0 in metres") as err:
        api.compute_landmarks(samples / "avatar.usda", radius=radius, multicover=2)
    assert "--radius" in err.value.fix


def test_compute_landmarks_takes_the_radii_it_documents(samples):
    from usdface import api

    rig = api.pick_mesh(api.read_avatar(samples / "avatar.usda"))
    for radius in (0, 0.01, None, np.float32(0.02)):
        assert len(api.compute_landmarks(rig, radius=radius, multicover=2).vertices) > 0


def test_write_landmarks_refuses_a_rig_or_layout_of_another_mesh(samples, tmp_path):
    """A user trial: ``write_landmarks(avatar, other_avatar.mesh("Head"), layout, out)`` with the bench's
    ``/Avatar/Head`` over the sample's (same prim path, 14,062 vertices against 3,780) died with numpy's
    ``IndexError: index 4164 is out of bounds`` while the layer was being authored. Now a RigError naming
    the avatar, the prim and the fix, before anything is written."""
    from usdface import api
    from usdface.errors import RigError
    from usdface.model import FaceRig

    avatar = api.read_avatar(samples / "avatar.usda")
    head, mouth = avatar.mesh("Head"), avatar.mesh("Mouth")
    layout = api.compute_landmarks(head)
    keep = np.all(head.triangles < 1000, axis=1)       # another avatar's head at the same prim path
    foreign = FaceRig(head.neutral[:1000], head.triangles[keep], head.names, head.deltas[:, :1000], {},
                      head.source, head.name)
    out = tmp_path / "lm.usda"
    with pytest.raises(RigError, match=r"prim /Avatar/Head: the rig has 1000 vertices, the avatar's mesh "
                                       r"3780: not this avatar's mesh") as err:
        api.write_landmarks(avatar, foreign, layout, out)
    assert "compute_landmarks(pick_mesh(avatar))" in err.value.fix
    with pytest.raises(RigError, match=r"prim /Avatar/Mouth: the layout's vertex indices reach \d+, the mesh "
                                       r"has 164 vertices"):
        api.write_landmarks(avatar, mouth, layout, out)     # the Head's layout on the Mouth
    assert not out.exists()
    assert api.write_landmarks(avatar, head, layout, out) == out    # the right pair is written


def test_evaluate_capture_refuses_a_rig_of_another_capture_naming_the_capture(samples):
    """A user trial: ``evaluate_capture(capture, fit_of_another_capture)`` raised Python's ``ValueError:
    'tongueOut' is not in list`` (the bench's rig has no tongueOut), and a rig on another mesh a GeometryError
    naming no file. Both are FitErrors naming the capture, what differs and the fix."""
    from usdface import api
    from usdface.errors import FitError
    from usdface.model import FaceRig

    capture = samples / "capture.usda"
    rig = api.fit_capture(capture, method="dt").rig
    with pytest.raises(FitError, match=r"capture.usda: the rig lacks 42 of the capture's shapes: ") as err:
        api.evaluate_capture(capture, rig.subset(rig.names[:10]))
    assert "fit_capture(capture)" in err.value.fix
    keep = np.all(rig.triangles < 1000, axis=1)
    other = FaceRig(rig.neutral[:1000], rig.triangles[keep], rig.names, rig.deltas[:, :1000])
    with pytest.raises(FitError, match=r"capture.usda: the rig has 1000 vertices, the capture mesh 1233"):
        api.evaluate_capture(capture, other)
    assert api.evaluate_capture(capture, rig)["mean_rmse_mm"] > 0      # its own rig is scored


def test_the_core_compute_landmarks_names_a_path_given_for_the_rig(samples):
    """docs/landmarks.md's script imports ``usdface.landmarks.compute_landmarks`` (a FaceRig in), while
    ``usdface.compute_landmarks`` also takes the avatar's file; the avatar's path given to the first died
    with ``AttributeError: 'str' object has no attribute 'source'`` (a user trial)."""
    from usdface.errors import LandmarkError
    from usdface.landmarks import compute_landmarks

    with pytest.raises(LandmarkError, match=r"takes a FaceRig, not str \('.*avatar.usda'\)") as err:
        compute_landmarks(str(samples / "avatar.usda"))
    assert "usdface.compute_landmarks" in err.value.fix and ".mesh('Head')" in err.value.fix


@pytest.mark.parametrize("kwargs, needle", [
    ({"options": ["inspect"]}, r"personalize_batch's options must be a \{option: value\} dict \(or None\), "
                               r"not list"),
    ({"scheduler": 8786}, r"personalize_batch's scheduler must be a Dask scheduler's address \(or None\), "
                          r"not int"),
    ({"worker": len}, r"personalize_batch's worker must be a 'module:function' string \(or None\)"),
    # was blamed on the manifest ('people.csv: item 1: bad inspect'), which has no such column (stop 42)
    ({"options": {"inspect": "true"}},
     r"^bad inspect 'true': personalize_batch's options' inspect is a boolean"),
])
def test_personalize_batch_refuses_arguments_of_the_wrong_kind(tmp_path, kwargs, needle):
    """``options=["inspect"]`` died with Python's ``ValueError: dictionary update sequence element #0 has
    length 7``; ``scheduler=8786`` (the port alone) was taken. OptionErrors naming the argument, before any
    item runs and before the report is written."""
    from usdface import api

    manifest = tmp_path / "people.csv"
    manifest.write_text(f"avatar,capture,output\n{A},{C},out.usda\n")
    with pytest.raises(OptionError, match=needle) as err:
        api.personalize_batch(manifest, jobs=1, **kwargs)
    assert err.value.fix
    assert sorted(p.name for p in tmp_path.iterdir()) == ["people.csv"]


def test_write_fit_rig_refuses_a_capture_that_is_no_path_or_not_there(samples, tmp_path):
    """``write_fit_rig(fit, out, capture=...)`` records the capture the rig was fitted on: a missing one said
    ``nope.usda: cannot digest: not found (fix: check the path)``, a ``Capture`` object died with Python's
    ``TypeError: expected str, bytes or os.PathLike object, not Capture`` (a user trial). Both refused
    before the output is checked or written, the second in one line."""
    from usdface import api
    from usdface.errors import InputFileError

    capture = samples / "capture.usda"
    fit = api.fit_capture(capture, method="dt")
    out = tmp_path / "rig.usda"
    with pytest.raises(InputFileError, match=r"nope.usda: capture not found \(the file the rig") as err:
        api.write_fit_rig(fit, out, capture=tmp_path / "nope.usda")
    assert "fitted on" in err.value.fix
    with pytest.raises(OptionError, match=r"capture must be a path \(a str or Path\) or None, not Capture") \
            as err:
        api.write_fit_rig(fit, out, capture=api.read_capture(capture))
    assert "\n" not in str(err.value) and not out.exists()
    assert api.write_fit_rig(fit, out, capture=capture) == out


def test_write_fit_rig_refuses_a_capture_the_rig_was_not_fitted_on(samples, tmp_path):
    """``write_fit_rig(fit, out, capture=OTHER)`` recorded OTHER as the rig's source, unchecked (stop 43): a
    capture of another vertex count, or of the same mesh with another neutral (another person on the same
    phone mesh: bench dev1 and dev3 share 1,203 vertices), is refused as ``evaluate_capture`` and
    ``personalize_avatar(rig=)`` refuse a rig of another capture, naming the capture; nothing written. The
    capture it was fitted on, written again (float32 points), is accepted."""
    import dataclasses

    from usdface import api
    from usdface.errors import FitError
    from usdface.model import FaceRig

    capture = api.read_capture(samples / "capture.usda")
    fit = api.fit_capture(capture, method="dt")
    out = tmp_path / "rig.usda"
    neutral = capture.neutral.copy()
    neutral[7, 0] += 0.0005                                  # one vertex 0.5 mm away: another scan
    other = api.write_capture(dataclasses.replace(capture, neutral=neutral), tmp_path / "other.usda")
    with pytest.raises(FitError, match=r"other.usda: the rig's neutral is 0.5 mm from the capture's neutral "
                                       r".*a rig fitted on another capture") as err:
        api.write_fit_rig(fit, out, capture=other)
    assert "fitted on" in err.value.fix and not out.exists()
    tri = np.array([[0, 1, 2]])
    with pytest.raises(FitError, match=r"capture.usda: the rig has 3 vertices, the capture mesh 1233"):
        api.write_fit_rig(FaceRig(np.eye(3), tri, ["jawOpen"], np.full((1, 3, 3), 0.01)), out,
                          capture=samples / "capture.usda")
    same = api.write_capture(capture, tmp_path / "same.usda", exact=False)     # float32: rounded points
    assert api.write_fit_rig(fit, out, capture=same) == out


def test_personalize_refuses_a_rig_of_another_capture_naming_the_capture(samples, tmp_path):
    """A user trial (stop 42): ``personalize_avatar(avatar, capture, out, rig=fit_of_another_capture)`` --
    the rig ``read_capture``'s own fix suggests -- ended in the registration with numpy's ``ValueError:
    matmul: ... (1203 vs 1233)``, naming nothing. It is a FitError naming the capture and the fix, raised
    before any output; the capture's own rig is implanted."""
    from usdface import api
    from usdface.errors import FitError
    from usdface.model import FaceRig

    capture = samples / "capture.usda"
    rig = api.fit_capture(capture, method="dt").rig
    keep = np.all(rig.triangles < 1000, axis=1)
    other = FaceRig(rig.neutral[:1000], rig.triangles[keep], rig.names, rig.deltas[:, :1000])
    out = tmp_path / "p.usda"
    with pytest.raises(FitError, match=r"capture.usda: the rig given to implant has 1000 vertices, the "
                                       r"capture mesh 1233") as err:
        api.personalize_avatar(samples / "avatar.usda", capture, out, rig=other)
    assert "fit_capture(capture).rig" in err.value.fix
    assert not list(tmp_path.iterdir())
    assert api.personalize_avatar(samples / "avatar.usda", capture, out, rig=rig).out_path == out


@pytest.mark.parametrize("rays", [0, -3, 2.5, "16", True])
def test_landmarks_refuse_a_ray_count_before_any_work(samples, monkeypatch, rays):
    """``compute_landmarks(rays=2.5)`` was taken as 2, ``rays="16"`` died in a ``TypeError`` and ``rays=0`` in
    a GeometryError without file or prim (saying "default 64"), each after the candidates and the skin
    samples were computed; ``landmark_diagnostics`` the same. Now a LandmarkError naming the file, the prim
    and the fix, before any work (``--rays`` is refused the same way)."""
    from usdface import api
    from usdface.errors import LandmarkError
    from usdface.landmarks import candidates

    rig = api.pick_mesh(api.read_avatar(samples / "avatar.usda"))

    def no_work(*args, **kwargs):
        raise AssertionError("work started before the options were checked")

    monkeypatch.setattr(candidates, "relative_displacement", no_work)
    for call in (api.compute_landmarks, api.landmark_diagnostics):
        with pytest.raises(LandmarkError, match=r"rays .* is not a whole number >= 1") as err:
            call(rig, rays=rays)
        assert "avatar.usda" in str(err.value) and "/Avatar/Head" in str(err.value)
        assert "rays=16" in err.value.fix


@pytest.mark.parametrize("options, said", [
    ({"multicover": 2.5}, "multicover 2.5 is not a whole number >= 1"),      # was taken as 2
    ({"multicover": "x"}, "multicover 'x' is not a whole number >= 1"),      # a ValueError of int()
    ({"multicover": True}, "multicover True is not a whole number >= 1"),    # was taken as 1
    ({"multicover": 2, "share": -1}, "share -1 is not in (0, 1]"),           # was taken
    ({"multicover": 2, "share": "x"}, "share 'x' is not in (0, 1]"),         # a TypeError after the rays
    ({"time_limit": -5}, "time_limit -5 is not a number of seconds > 0"),    # SCIP's errors, no landmark
])
def test_compute_landmarks_refuses_bad_cover_options_before_any_work(samples, monkeypatch, options, said):
    """``compute_landmarks``' multi-cover and solver options checked with the others, before any work, in a
    LandmarkError naming the file, the prim and the fix."""
    from usdface import api
    from usdface.errors import LandmarkError
    from usdface.landmarks import candidates

    rig = api.pick_mesh(api.read_avatar(samples / "avatar.usda"))
    monkeypatch.setattr(candidates, "relative_displacement",
                        lambda *a, **k: pytest.fail("work started before the options were checked"))
    with pytest.raises(LandmarkError) as err:
        api.compute_landmarks(rig, **options)
    assert said in str(err.value) and "/Avatar/Head" in str(err.value) and err.value.fix


@pytest.mark.parametrize("options", [
    {"radius": -1}, {"epsilon": 2}, {"alpha": 3}, {"alpha": "x"}, {"weighting": "x"}, {"backend": "x"},
    {"spacing": -1}, {"spacing": [0.01]}, {"spacing": float("inf")}, {"camera": "a"},
    {"time_limit": float("inf")},                             # an OverflowError in the solver set-up
    {"multicover": 2, "one_shot": True, "adaptive": False},   # the one ILP has no 10 % heuristic: ignored
    {"one_shot": True},                 # multicover 1: the single cover (the CLI refused it; stop 54, h112)
    {"multicover": 1, "one_shot": True},
])
def test_compute_landmarks_names_file_and_prim_in_every_refusal(samples, monkeypatch, options):
    """Every option ``compute_landmarks`` refuses names the rig's file and prim, not only the ones checked
    since stop 54 (a radius, epsilon, alpha, weighting, backend, spacing or camera said neither; ``alpha="x"``
    died in a ValueError), and ``adaptive=False`` with ``one_shot`` is refused as ``--no-adaptive`` with
    ``--one-shot`` is (it was ignored) - all before any work."""
    from usdface import api
    from usdface.errors import LandmarkError
    from usdface.landmarks import candidates

    rig = api.pick_mesh(api.read_avatar(samples / "avatar.usda"))
    monkeypatch.setattr(candidates, "relative_displacement",
                        lambda *a, **k: pytest.fail("work started before the options were checked"))
    with pytest.raises(LandmarkError) as err:
        api.compute_landmarks(rig, **options)
    assert "avatar.usda" in str(err.value) and "/Avatar/Head" in str(err.value) and err.value.fix
