"""Pyblish plugins: a real ``pyblish.util.publish`` run collects, validates (face-rig rules + OpenUSD
validators + capture), stops a bad rig before extraction, and personalizes a good one at publish time."""

from __future__ import annotations

from pathlib import Path

import pytest
from input_helpers import _livelink_csv

pyblish_api = pytest.importorskip("pyblish.api")
import pyblish.util  # noqa: E402

from usdface.pipeline import pyblish_plugins as plugins  # noqa: E402


@pytest.fixture
def registered():
    pyblish_api.deregister_all_plugins()
    plugins.register()
    plugins.register()  # idempotent
    yield
    pyblish_api.deregister_all_plugins()


@pytest.fixture
def extractions(registered) -> list:
    """The personalize extractor replaced by one that records its instances and writes nothing: a publish
    whose validators refuse an item must leave this list empty."""
    calls = []
    pyblish_api.deregister_plugin(plugins.ExtractUsdFacePersonalized)

    class Extract(plugins.ExtractUsdFacePersonalized):
        def process(self, instance):
            calls.append(instance)

    pyblish_api.register_plugin(Extract)
    return calls


def _results(context):
    # an Instance is a list (of its members): empty means falsy, so compare with None
    return {(r["plugin"].__name__, None if r["instance"] is None else r["instance"].name): r
            for r in context.data["results"]}


def _bad_avatar(path: Path) -> Path:
    """A UsdSkel avatar whose one BlendShape has an out-of-range point index (and no ARKit names)."""
    path.write_text("""#usda 1.0
(
    defaultPrim = "Avatar"
    metersPerUnit = 0.01
    upAxis = "Y"
)
def SkelRoot "Avatar"
{
    def Skeleton "Skel" {}
    def Mesh "Head" (prepend apiSchemas = ["SkelBindingAPI"])
    {
        point3f[] points = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]
        int[] faceVertexCounts = [3]
        int[] faceVertexIndices = [0, 1, 2]
        rel skel:skeleton = </Avatar/Skel>
        uniform token[] skel:blendShapes = ["jawOpen"]
        rel skel:blendShapeTargets = [</Avatar/Head/jawOpen>]
        def BlendShape "jawOpen"
        {
            uniform vector3f[] offsets = [(0, 0, 1)]
            uniform int[] pointIndices = [7]
        }
    }
}
""")
    return path


def test_bad_rig_stops_the_publish(registered, tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(plugins.ExtractUsdFacePersonalized, "personalize",
                        staticmethod(lambda *a, **k: calls.append(a)))
    pyblish_api.deregister_plugin(plugins.ValidateUsdFaceCapture)  # only the rig matters here
    context = pyblish_api.Context()
    context.data["usdfaceItems"] = [{"avatar": str(_bad_avatar(tmp_path / "bad.usda")),
                                     "capture": str(tmp_path / "capture"),
                                     "output": str(tmp_path / "out.usda")}]
    pyblish.util.publish(context)
    results = _results(context)
    assert results[("CollectUsdFaceItems", None)]["success"]
    failed = results[("ValidateUsdFaceRig", "out")]
    assert not failed["success"]
    assert "PointIndices" in str(failed["error"]) and "bad.usda" in str(failed["error"])
    assert ("ExtractUsdFacePersonalized", "out") not in results and calls == []
    instance = next(iter(context))
    assert any(i["rule"] == "PointIndices" for i in instance.data["usdfaceCheck"])


def test_missing_capture_fails_validation(registered, tmp_path, bench):
    context = pyblish_api.Context()
    context.data["usdfaceItems"] = [{"avatar": str(bench / "dev1" / "avatar.usdc"),
                                     "capture": str(tmp_path / "nowhere"),
                                     "output": str(tmp_path / "o.usda")}]
    pyblish.util.publish(context)
    results = _results(context)
    assert results[("ValidateUsdFaceRig", "o")]["success"]
    assert not results[("ValidateUsdFaceCapture", "o")]["success"]
    assert not (tmp_path / "o.usda").exists()


def test_publish_personalizes(registered, tmp_path, samples):
    """Real Pyblish run on the project's sample assets with the real personalize, collected from a batch
    manifest, with inspection data requested through the instance."""
    pytest.importorskip("usdface.transfer")
    manifest = tmp_path / "publish.csv"
    manifest.write_text("avatar,capture,output,inspect\n"
                        f"{samples / 'avatar.usda'},{samples / 'capture.usda'},person.usda,true\n")
    context = pyblish_api.Context()
    context.data["usdfaceManifest"] = str(manifest)
    pyblish.util.publish(context)
    errors = [r["error"] for r in context.data["results"] if not r["success"]]
    assert errors == []
    instance = next(iter(context))
    out = Path(instance.data["usdfaceLayer"])
    assert out == tmp_path / "person.usda" and out.exists()
    assert instance.data["representations"][0]["files"] == "person.usda"
    assert instance.data["usdfaceCaptureSummary"]["train"] > 0
    assert instance.data["usdfaceOptions"] == {"inspect": True}
    from pxr import Usd

    from usdface.api import check
    from usdface.io.usd_inspection import ANIMATION_NAME

    assert [i for i in check(out) if i.severity == "error"] == []
    stage = Usd.Stage.Open(str(out))
    assert any(p.GetName() == ANIMATION_NAME for p in stage.Traverse())  # inspection data is there


def test_a_name_mapped_rig_validates_and_publishes(registered, tmp_path, samples):
    """User trial: an avatar with studio control names (ch17_ctrl for jawOpen) and usdfaceOptions' name_map
    failed ValidateUsdFaceRig with 'missing: jawOpen' (check ran without the map), although check
    --name-map and personalize --name-map accept it; and its message carried two '(fix: ...)' clauses."""
    import json

    studio = tmp_path / "studio.usda"
    studio.write_text((samples / "avatar.usda").read_text().replace("jawOpen", "ch17_ctrl"))
    name_map = tmp_path / "studio map.json"
    name_map.write_text(json.dumps({"ch17_ctrl": "jawOpen"}))
    context = pyblish_api.Context()
    context.data["usdfaceItems"] = [{"avatar": str(studio), "capture": str(samples / "capture.usda"),
                                     "output": str(tmp_path / "person.usda"),
                                     "usdfaceOptions": {"name_map": str(name_map), "method": "dt"}}]
    pyblish.util.publish(context)
    errors = [str(r["error"]) for r in context.data["results"] if not r["success"]]
    assert errors == []
    assert (tmp_path / "person.usda").exists()
    pyblish_api.deregister_all_plugins()
    plugins.register()
    context = pyblish_api.Context()                      # without the map: refused once, one fix clause
    context.data["usdfaceItems"] = [{"avatar": str(studio), "capture": str(samples / "capture.usda"),
                                     "output": str(tmp_path / "other.usda")}]
    pyblish.util.publish(context)
    failed = [str(r["error"]) for r in context.data["results"] if not r["success"]]
    assert failed and "jawOpen" in failed[0] and failed[0].count("(fix:") == 1


def test_bad_options_fail_validation_not_the_extractor(registered, tmp_path, samples, monkeypatch):
    """An option the face-transfer mode does not use (``extension_length`` with ``offset``) passed every
    validator and failed the (slow) extractor, after the other instances' work; it fails validation now, and
    a studio's own ``personalize`` step (its own options) is not second-guessed."""
    context = pyblish_api.Context()
    item = {"avatar": str(samples / "avatar.usda"), "capture": str(samples / "capture.usda"),
            "output": str(tmp_path / "o.usda")}
    context.data["usdfaceItems"] = [{**item, "usdfaceOptions": {"face_transfer": "offset",
                                                                "extension_length": 2}}]
    ran = []
    monkeypatch.setattr(plugins.ExtractUsdFacePersonalized, "process", lambda self, instance: ran.append(1))
    pyblish.util.publish(context)
    results = _results(context)
    assert not results[("ValidateUsdFaceOptions", "o")]["success"]
    assert "extension_length" in str(results[("ValidateUsdFaceOptions", "o")]["error"])
    assert ran == []

    monkeypatch.setattr(plugins.ExtractUsdFacePersonalized, "personalize",
                        staticmethod(lambda avatar, capture, output, **options: None))
    context = pyblish_api.Context()
    context.data["usdfaceItems"] = [{**item, "usdfaceOptions": {"studio_lod": 2}}]
    pyblish.util.publish(context)
    assert _results(context)[("ValidateUsdFaceOptions", "o")]["success"] and ran == [1]


def test_a_take_and_force_among_the_options_validate_as_the_extractors_take_them(registered, tmp_path,
                                                                                 samples):
    """``usdfaceOptions`` with a take (a manifest column): the outputs' validator passed it twice to
    personalize_inputs (a TypeError, the publish failed in validation); and its ``force`` is the review
    page's too, as both extractors take it (the review extractor preferred the instance's)."""
    import numpy as np

    from usdface.io.livelink import write_livelink_csv

    take = write_livelink_csv(tmp_path / "t.csv", ["jawOpen"], np.full((4, 1), 0.5), np.arange(4) / 30.0)
    out = tmp_path / "person.usda"
    out.write_text("#usda 1.0\n")                                  # left by an earlier publish
    (tmp_path / "person.review.html").write_text("old")
    context = pyblish_api.Context()
    context.data["usdfaceItems"] = [{"avatar": str(samples / "avatar.usda"),
                                     "capture": str(samples / "capture.usda"), "output": str(out),
                                     "review": True, "force": False,
                                     "usdfaceOptions": {"take": str(take), "force": True}}]
    pyblish.util.publish(context)
    assert [r["error"] for r in context.data["results"] if not r["success"]] == []
    assert (tmp_path / "person.review.html").read_text() != "old"


def _publish(api, items):
    import pyblish.util

    context = api.Context()
    context.data["usdfaceItems"] = items
    pyblish.util.publish(context)
    return context, {(r["plugin"].__name__, None if r["instance"] is None else r["instance"].name): r
                     for r in context.data["results"]}


def _small_take(path: Path, peak: float = 1.0) -> Path:
    """A Live Link Face CSV of 30 rows at 30 fps (jawOpen up to ``peak`` and a smile)."""

    import numpy as np

    from usdface.arkit import ARKIT_NAMES

    t = np.arange(30)
    w = np.zeros((30, len(ARKIT_NAMES)))
    w[:, ARKIT_NAMES.index("jawOpen")] = peak * np.sin(np.pi * t / 29)
    w[:, ARKIT_NAMES.index("mouthSmileLeft")] = 0.5 * np.sin(np.pi * t / 29) ** 2
    return _livelink_csv(path, w, [f"10:00:00:{2 * i:02d}.000" for i in range(len(w))])


def test_publish_with_dry_run_fails_validation_not_the_extractor(pyblish_registered, samples, tmp_path,
                                                                  monkeypatch):
    """``usdfaceOptions`` ``{"dry_run": true}`` passed every validator; the extractor then ran the whole
    personalization, wrote nothing and failed with 'o.usda: file not found (fix: pass an existing .usd file)'.
    It fails validation now, naming dry_run and the fix (as ``usdface batch`` refuses such a row)."""
    from usdface.pipeline import pyblish_plugins

    ran = []
    monkeypatch.setattr(pyblish_plugins.ExtractUsdFacePersonalized, "process",
                        lambda self, instance: ran.append(1))
    _, results = _publish(pyblish_registered, [
        {"avatar": str(samples / "avatar.usda"), "capture": str(samples / "capture.usda"),
         "output": str(tmp_path / "o.usda"), "usdfaceOptions": {"dry_run": True}}])
    result = results[("ValidateUsdFaceOptions", "o")]
    assert not result["success"]
    assert "dry_run" in str(result["error"]) and "fix:" in str(result["error"])
    assert ran == []
    _, results = _publish(pyblish_registered, [                  # a typo's refusal does not offer dry_run
        {"avatar": str(samples / "avatar.usda"), "capture": str(samples / "capture.usda"),
         "output": str(tmp_path / "o.usda"), "usdfaceOptions": {"methd": "menzel"}}])
    error = str(results[("ValidateUsdFaceOptions", "o")]["error"])
    assert "unknown personalize option(s): methd" in error and "dry_run" not in error.split("use one of")[1]
    assert ran == []


def test_publish_take_plays_in_the_layer_as_on_the_review_page(pyblish_registered, samples, tmp_path):
    """Instance data ``take`` reached the review page only: the layer's inspection animation (usdview) played
    the test expressions without it, where ``usdface personalize --take FILE --review`` plays the take in
    both. The take now goes to personalize too (it turns the inspection on, as ``--take`` does)."""
    pytest.importorskip("usdface.transfer")
    from pxr import Usd

    take = _small_take(tmp_path / "take.csv")
    context, results = _publish(pyblish_registered, [
        {"avatar": str(samples / "avatar.usda"), "capture": str(samples / "capture.usda"),
         "output": str(tmp_path / "person.usda"), "take": str(take), "review": True,
         "usdfaceOptions": {"method": "dt"}}])
    assert [str(r["error"]) for r in results.values() if not r["success"]] == []
    instance = next(iter(context))
    assert Path(instance.data["usdfaceReview"]).exists()
    stage = Usd.Stage.Open(str(tmp_path / "person.usda"))
    from usdface.io.usd_inspection import ANIMATION_NAME

    anims = [p for p in stage.Traverse() if p.GetName() == ANIMATION_NAME]
    assert anims, "no inspection animation in the published layer"
    times = anims[0].GetAttribute("blendShapeWeights").GetTimeSamples()
    assert len(times) >= 20 + 30     # the 20 test expressions, then the take's 30 frames


def test_publish_from_a_manifest_writes_the_review_page_and_forces_it(pyblish_registered, samples, tmp_path):
    """A publish collected from a batch manifest (``context.data["usdfaceManifest"]``) could not ask for the
    review page: a 'review' column became a personalize option and failed ValidateUsdFaceOptions as unknown.
    And a 'force' column (or ``usdfaceOptions`` force) replaced the layer but not its review page, so the
    second publish failed in ExtractUsdFaceReview with 'review page exists'."""
    pytest.importorskip("usdface.transfer")
    import pyblish.util

    manifest = tmp_path / "publish.csv"
    manifest.write_text("avatar,capture,output,method,review,force\n"
                        f"{samples / 'avatar.usda'},{samples / 'capture.usda'},person.usda,dt,true,true\n")
    for _ in range(2):                                   # the second publish replaces the layer and the page
        context = pyblish_registered.Context()
        context.data["usdfaceManifest"] = str(manifest)
        pyblish.util.publish(context)
        assert [str(r["error"]) for r in context.data["results"] if not r["success"]] == []
        instance = next(iter(context))
        assert instance.data["usdfaceReview"] == str(tmp_path / "person.review.html")
        assert "review" not in instance.data["usdfaceOptions"]
    assert (tmp_path / "person.review.html").stat().st_size > 0


def test_publish_records_personalize_warnings_in_the_plugin_log(pyblish_registered, bench, tmp_path):
    """The personalization's warnings (dev1: 23 training frames repeat another exactly; shapes the capture
    barely shows) went to stderr as Python warnings, outside the publish's records, so a publish UI showed a
    clean extraction. They are logged by the extractor and kept in ``instance.data["usdfaceWarnings"]``."""
    pytest.importorskip("usdface.transfer")
    context, results = _publish(pyblish_registered, [
        {"avatar": str(bench / "dev1" / "avatar.usdc"), "capture": str(bench / "dev1" / "capture"),
         "output": str(tmp_path / "person.usda")}])
    extract = results[("ExtractUsdFacePersonalized", "person")]
    assert extract["success"], extract["error"]
    logged = [r.getMessage() for r in extract["records"] if r.levelname == "WARNING"]
    assert any("repeat another frame exactly" in m for m in logged), logged
    instance = next(iter(context))
    assert set(logged) <= set(instance.data["usdfaceWarnings"])


def test_publish_layer_and_review_page_play_the_same_take(pyblish_registered, samples, tmp_path, monkeypatch):
    """With a take both in ``usdfaceOptions`` and in the instance data, the layer's inspection played the
    options' one and the review page the instance's; both play the one personalize gets."""
    from types import SimpleNamespace

    from usdface import api
    from usdface.pipeline import pyblish_plugins

    got = {}

    def personalize(avatar, capture, output, **options):
        got["layer"] = options.get("take")
        Path(output).write_text("#usda 1.0\n")
        return SimpleNamespace(out_path=Path(output), report={"warnings": []})

    def write_review(layer, out, *, capture=None, take=None, force=False):
        got["page"] = take
        return Path(out)

    monkeypatch.setattr(pyblish_plugins.ExtractUsdFacePersonalized, "personalize", staticmethod(personalize))
    monkeypatch.setattr(api, "write_review", write_review)
    monkeypatch.setattr(api, "check", lambda *a, **k: [])
    _, results = _publish(pyblish_registered, [
        {"avatar": str(samples / "avatar.usda"), "capture": str(samples / "capture.usda"),
         "output": str(tmp_path / "p.usda"), "take": "instance.csv", "review": True,
         "usdfaceOptions": {"take": "options.csv"}}])
    assert [str(r["error"]) for r in results.values() if not r["success"]] == []
    assert got == {"layer": "options.csv", "page": "options.csv"}


def _publish_item(pyblish_api, **item):
    import pyblish.util

    context = pyblish_api.Context()
    context.data["usdfaceItems"] = [item]
    pyblish.util.publish(context)
    return {r["plugin"].__name__: r["error"] for r in context.data["results"] if r["error"] is not None}


def test_pyblish_refuses_an_existing_review_page_before_writing_the_layer(pyblish_registered, samples,
                                                                          tmp_path):
    """A publish with review=True whose review page was left by an earlier publish passed validation, wrote
    the layer, then failed in the review extractor: the failed publish left the layer behind, and its
    retry failed on it ('output layer exists')."""
    out = tmp_path / "person.usda"
    (tmp_path / "person.review.html").write_text("an earlier publish's page")
    errors = _publish_item(pyblish_registered, avatar=str(samples / "avatar.usda"),
                      capture=str(samples / "capture.usda"), output=str(out), review=True)
    assert "review page exists" in str(errors.get("ValidateUsdFaceOutputs"))
    assert "instance's data force=True" in str(errors.get("ValidateUsdFaceOutputs"))
    assert "ExtractUsdFacePersonalized" not in errors
    assert not out.exists()


@pytest.mark.parametrize("case", ["exists", "input"])
def test_pyblish_validates_the_layer_output(pyblish_registered, samples, tmp_path, case):
    """An output that exists (no force) or is an input failed only in the extractor, after validation
    passed."""
    out = tmp_path / "person.usda"
    if case == "exists":
        out.write_text("#usda 1.0\n")
    else:
        out = samples / "capture.usda"
    errors = _publish_item(pyblish_registered, avatar=str(samples / "avatar.usda"),
                      capture=str(samples / "capture.usda"), output=str(out), force=case == "input")
    assert "ValidateUsdFaceOutputs" in errors, errors
    assert "ExtractUsdFacePersonalized" not in errors
    if case == "exists":     # the fix in the publish's terms, not the command line's '--force'
        assert "instance's data force=True" in str(errors["ValidateUsdFaceOutputs"])
        assert "--force" not in str(errors["ValidateUsdFaceOutputs"])


@pytest.mark.parametrize("item, says", [
    ({"avatar": "a.usdc", "capture": "capture/", "out": "o.usda"},
     'usdfaceItems"][0] lacks output (has avatar, capture, out)'),
    ("a.usdc", 'usdfaceItems"][0] is a str'),
])
def test_a_malformed_item_fails_the_collector_naming_it(registered, item, says):
    """A misspelt key failed the collector with a bare KeyError: 'output'; a path for a dict, TypeError."""
    from usdface.errors import InputFileError

    context = pyblish_api.Context()
    context.data["usdfaceItems"] = [item]
    pyblish.util.publish(context)
    error = _results(context)[("CollectUsdFaceItems", None)]["error"]
    assert isinstance(error, InputFileError) and says in str(error)
    assert "fix: give" in str(error) and len(context) == 0


def test_an_already_personalized_avatar_fails_validation(extractions, tmp_path, samples):
    """A usdface output given as the avatar passed every validator and failed only in the extractor
    (AlreadyPersonalizedError), after the other instances' extractors had run; usdface batch refuses it
    before its first item. It fails ValidateUsdFaceRig now, naming the original avatar."""
    from usdface.api import personalize_avatar
    from usdface.errors import AlreadyPersonalizedError

    layer = tmp_path / "p.usda"
    personalize_avatar(samples / "avatar.usda", samples / "capture.usda", layer)
    calls = extractions
    context = pyblish_api.Context()
    context.data["usdfaceItems"] = [{"avatar": str(layer), "capture": str(samples / "capture.usda"),
                                     "output": str(tmp_path / "again.usda")}]
    pyblish.util.publish(context)
    error = _results(context)[("ValidateUsdFaceRig", "again")]["error"]
    assert isinstance(error, AlreadyPersonalizedError) and "avatar.usda" in error.fix
    assert calls == [] and not (tmp_path / "again.usda").exists()


@pytest.mark.parametrize("case, plugin, says", [
    ("take", "ValidateUsdFaceOptions", "nope.csv: take not found"),
    ("pins", "ValidateUsdFaceOptions", "nope.json: pins file not found"),
    ("correspondence", "ValidateUsdFaceOutputs", "is inside the input folder"),
])
def test_missing_option_files_and_a_cache_in_the_capture_fail_validation(extractions, tmp_path, samples,
                                                                          sample_capture_folder, case,
                                                                          plugin, says):
    """A missing take or pins file, or a correspondence cache inside the capture folder, passed every
    validator and failed only in the extractor; 'usdface batch' refuses such a row before its first item."""
    calls = extractions
    item = {"avatar": str(samples / "avatar.usda"), "capture": str(sample_capture_folder),
            "output": str(tmp_path / "o.usda")}
    if case == "take":
        item["take"] = str(tmp_path / "nope.csv")
    else:
        item["usdfaceOptions"] = {"pins": str(tmp_path / "nope.json")} if case == "pins" else {
            "correspondence": str(sample_capture_folder / "c.npz")}
    context = pyblish_api.Context()
    context.data["usdfaceItems"] = [item]
    pyblish.util.publish(context)
    error = _results(context)[(plugin, "o")]["error"]
    assert error is not None and says in str(error), error
    assert calls == [] and not (tmp_path / "o.usda").exists()


@pytest.mark.parametrize("take, says", [
    ("avatar.usda", "avatar.usda, prim /Avatar: this is an avatar, not a take"),
    ("capture.usda", "capture.usda: this is a capture"),
    ("notes.csv", "notes.csv: not a Live Link Face CSV"),
])
def test_a_take_of_another_kind_fails_validation(extractions, tmp_path, samples, take, says):
    """A user trial: the avatar given as the instance's take passed every validator and failed only in the
    extractor (after other instances' extractors had run); the take's kind is read before the first one."""
    calls = extractions
    (tmp_path / "notes.csv").write_text("name,value\njaw,1\n")
    path = tmp_path / take if take == "notes.csv" else samples / take
    context = pyblish_api.Context()
    context.data["usdfaceItems"] = [{"avatar": str(samples / "avatar.usda"),
                                     "capture": str(samples / "capture.usda"),
                                     "output": str(tmp_path / "o.usda"), "take": str(path)}]
    pyblish.util.publish(context)
    error = _results(context)[("ValidateUsdFaceOptions", "o")]["error"]
    assert error is not None and says in str(error) and "(fix: " in str(error), error
    assert calls == [] and not (tmp_path / "o.usda").exists()


def test_an_instance_with_avatar_and_capture_swapped_fails_validation(extractions, tmp_path, samples):
    """A user trial: the capture given as the avatar passed every validator (usdface check only notes 'this
    is a usdface capture, not an avatar') and failed only in the extractor, after other instances'
    extractors had run; the avatar's kind is read before the first one, as 'usdface batch' reads it."""
    calls = extractions
    context = pyblish_api.Context()
    context.data["usdfaceItems"] = [{"avatar": str(samples / "capture.usda"),
                                     "capture": str(samples / "avatar.usda"),
                                     "output": str(tmp_path / "o.usda")}]
    pyblish.util.publish(context)
    error = _results(context)[("ValidateUsdFaceOptions", "o")]["error"]
    assert error is not None and "capture.usda, prim /Capture: this is a usdface capture" in str(error), error
    assert "(fix: " in str(error) and calls == [] and not (tmp_path / "o.usda").exists()


def _writes_a_layer(avatar, capture, output, **options):
    """A personalize step that writes a (trivial) layer at once."""
    from types import SimpleNamespace

    Path(output).write_text("#usda 1.0\n")
    return SimpleNamespace(out_path=Path(output), report={"warnings": []})


def test_a_layer_failing_its_recheck_is_set_aside(pyblish_registered, samples, tmp_path, monkeypatch):
    """A user trial: the written layer failed the extractor's re-check and stayed at the output, where the
    retry failed on it ('output layer exists'); it is set aside as ``<layer>.failed`` (as batch sets aside a
    failed item's output) for 'usdface check', and the error says so."""
    from usdface import api
    from usdface.pipeline.check import Issue

    monkeypatch.setattr(plugins.ExtractUsdFacePersonalized, "personalize", staticmethod(_writes_a_layer))
    monkeypatch.setattr(api, "check", lambda path, **k: [Issue("error", "Readable", "/", "broken")]
                        if Path(path).name == "p.usda" else [])
    context, results = _publish(pyblish_registered, [
        {"avatar": str(samples / "avatar.usda"), "capture": str(samples / "capture.usda"),
         "output": str(tmp_path / "p.usda"), "review": True}])
    error = str(results[("ExtractUsdFacePersonalized", "p")]["error"])
    assert "fails the check" in error and "set aside as p.usda.failed, not published" in error, error
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.usda.failed"]
    instance = next(iter(context))
    assert not instance.data.get("files") and not instance.data.get("representations")


@pytest.mark.parametrize("force", [False, True])
def test_a_failed_review_page_takes_the_new_layer_with_it(pyblish_registered, samples, tmp_path, monkeypatch,
                                                          force):
    """A user trial: the review extractor failed (a full disk) after the layer was written, and the layer
    stayed on disk and among the instance's files; the layer this publish made is removed and withdrawn,
    one that replaced an earlier layer (force) is left, and the error says which."""
    from usdface import api

    def no_space(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(plugins.ExtractUsdFacePersonalized, "personalize", staticmethod(_writes_a_layer))
    monkeypatch.setattr(api, "check", lambda *a, **k: [])
    monkeypatch.setattr(api, "write_review", no_space)
    if force:
        (tmp_path / "p.usda").write_text("#usda 1.0\n# the earlier layer\n")
        (tmp_path / "p.review.html").write_text("the earlier layer's page")
    context, results = _publish(pyblish_registered, [
        {"avatar": str(samples / "avatar.usda"), "capture": str(samples / "capture.usda"),
         "output": str(tmp_path / "p.usda"), "review": True, "force": force}])
    error = results[("ExtractUsdFaceReview", "p")]["error"]
    said = " ".join([str(error), *getattr(error, "__notes__", [])])
    instance = next(iter(context))
    assert not instance.data.get("files") and not instance.data.get("representations")
    assert "usdfaceLayer" not in instance.data
    if force:      # the earlier page reviewed the layer replaced: removed (stop 53)
        assert "replaced the earlier one (force) and is left there" in said, said
        assert "the earlier review page p.review.html was removed" in said, said
        assert (tmp_path / "p.usda").read_text() == "#usda 1.0\n"
        assert not (tmp_path / "p.review.html").exists()
    else:
        assert "p.usda this publish wrote was removed" in said, said
        assert list(tmp_path.iterdir()) == []


def test_the_inspect_flag_validated_is_the_one_used(extractions, tmp_path, samples):
    """``usdfaceOptions``' ``inspect`` is the one personalize gets over the instance data's (stop 51's review:
    the data's was still validated, so a data ``inspect="no"`` failed a publish whose options set
    ``inspect=True``). The one used is the one checked: the options' word fails validation, the data's
    unused one does not."""
    from usdface.errors import OptionError

    def publish(data: dict, options: dict):
        context = pyblish_api.Context()
        context.data["usdfaceItems"] = [{"avatar": str(samples / "avatar.usda"),
                                         "capture": str(samples / "capture.usda"),
                                         "output": str(tmp_path / "anna.usda"), **data,
                                         "usdfaceOptions": options}]
        pyblish.util.publish(context)
        return [r["error"] for r in context.data["results"] if r["error"] is not None]

    assert publish({"inspect": "no"}, {"inspect": True}) == []
    assert len(extractions) == 1 and plugins._personalize_options(extractions[0])["inspect"] is True
    errors = publish({"inspect": True}, {"inspect": "no"})
    assert errors and all(isinstance(e, OptionError) and "inspect" in str(e) for e in errors)
    assert len(extractions) == 1
    assert publish({"inspect": True}, {}) == [] and plugins._personalize_options(extractions[1])["inspect"]


class _Instance:
    def __init__(self, data):
        self.data = data

    def __str__(self):
        return "anna"


def test_inspect_follows_the_options_over_the_data():
    """``inspect``: ``usdfaceOptions``' value over the instance data's, the one used the one checked (a word
    in the unused one does not fail), the data's when the options have none; absent from both, left to
    personalize's default."""
    from usdface.errors import OptionError

    def chosen(data, options):
        return plugins._personalize_options(_Instance({**data, "usdfaceOptions": options}))

    assert chosen({"inspect": "no"}, {"inspect": True})["inspect"] is True   # the data's word: unused
    assert chosen({"inspect": True}, {"inspect": False})["inspect"] is False
    assert chosen({"inspect": True}, {})["inspect"] is True
    assert chosen({"inspect": None}, {})["inspect"] is False
    with pytest.raises(OptionError, match="usdfaceOptions inspect=True"):
        chosen({"inspect": True}, {"inspect": "no"})
    with pytest.raises(OptionError, match="data inspect=True"):
        chosen({"inspect": "no"}, {})
    assert "inspect" not in chosen({}, {})


def test_force_is_true_when_the_data_or_the_options_say_so():
    """Stop 53: ``force`` as ``usdface batch`` takes it (docs/pipeline.md): the batch's ``--force`` redoes
    every row and a row's ``force`` column true its own, a row's false adding nothing. A publish's options'
    ``force`` False (a manifest's column) beat the instance data's True, which a publish then refused as an
    existing layer. Either one true now replaces; each one given is checked."""
    from usdface.errors import OptionError

    def force(data, options):
        return plugins._personalize_options(_Instance({**data, "usdfaceOptions": options}))["force"]

    assert force({"force": True}, {"force": False}) is True
    assert force({"force": False}, {"force": True}) is True
    assert force({"force": False}, {"force": False}) is False
    assert force({"force": None}, {}) is False and force({}, {}) is False
    with pytest.raises(OptionError, match="usdfaceOptions force=True"):
        force({"force": True}, {"force": "no"})
    with pytest.raises(OptionError, match="data force=True"):
        force({"force": "no"}, {"force": True})


@pytest.mark.parametrize("data, plugin", [
    ({"force": "no"}, "ValidateUsdFaceOutputs"),
    ({"review": "no"}, "ValidateUsdFaceOutputs"),
    ({"inspect": "false "}, "ValidateUsdFaceOutputs"),
])
def test_an_instances_flag_given_as_a_word_fails_validation(extractions, tmp_path, samples, data, plugin):
    """A TD's trial (stop 51): instance data ``force="no"`` (a publish tool's setting as text) replaced the
    existing layer and its review page, and ``review`` "no" (a manifest cell) wrote the page: both counted
    as true (``bool("no")``), where personalize's own options refuse a string (api.md). They fail
    validation now, naming the instance, the flag and how to set it; the layer is untouched."""
    from usdface.errors import OptionError

    layer = tmp_path / "anna.usda"
    name = next(iter(data))
    if name == "force":
        layer.write_text("#usda 1.0\n")                  # an earlier publish's layer (stands for one)
    context = pyblish_api.Context()
    context.data["usdfaceItems"] = [dict({"avatar": str(samples / "avatar.usda"),
                                          "capture": str(samples / "capture.usda"), "output": str(layer)},
                                         **data)]
    pyblish.util.publish(context)
    error = _results(context)[(plugin, "anna")]["error"]
    assert isinstance(error, OptionError) and f"bad {name}" in str(error) and "instance anna's" in str(error)
    assert f"{name}=True or {name}=False" in error.fix
    assert extractions == []
    assert layer.read_text() == "#usda 1.0\n" if name == "force" else not layer.exists()
    assert not (tmp_path / "anna.review.html").exists()


def test_an_existing_layer_of_a_manifest_row_names_the_force_column(extractions, tmp_path, samples):
    """A TD's trial (stop 53): publishing a batch manifest whose layers exist failed 'output layer exists
    (fix: set the instance's data force=True (or force among its usdfaceOptions) ...)', Python terms for a
    user whose handle is the manifest; the fix names the row's force column too."""
    (tmp_path / "anna.usda").write_text("#usda 1.0\n")
    manifest = tmp_path / "people.csv"
    manifest.write_text(f"avatar,capture,output\n{samples / 'avatar.usda'},{samples / 'capture.usda'},"
                        "anna.usda\n")
    context = pyblish_api.Context()
    context.data["usdfaceManifest"] = str(manifest)
    pyblish.util.publish(context)
    error = _results(context)[("ValidateUsdFaceOutputs", "anna")]["error"]
    assert "output layer exists" in str(error) and "the row's force column true" in error.fix, error
    assert extractions == []


def test_a_refused_publish_logs_one_line_and_a_bug_its_traceback(tmp_path, samples):
    """A TD's trial (stop 54): the publish of docs/pipeline.md run again over its layer printed Pyblish's
    logging of the validator's refusal as two tracebacks (Pyblish logs a failed plugin with
    ``log.exception``) around the one-line error, on every refusal: a plain refusal read as a crash. A
    refusal (a :class:`usdface.errors.UsdFaceError`) is now logged as its one line, naming file and fix; an
    unexpected error in a plugin keeps its traceback."""
    import subprocess
    import sys

    from cli_helpers import _env

    script = tmp_path / "publish.py"
    script.write_text(f"""import pyblish.api, pyblish.util
from usdface.pipeline import pyblish_plugins

pyblish_plugins.register()
context = pyblish.api.Context()
context.data["usdfaceItems"] = [
    {{"avatar": {str(samples / 'avatar.usda')!r}, "capture": {str(samples / 'capture.usda')!r},
     "output": "hero_anna.usda", "usdfaceOptions": {{"method": "menzel"}}}},
]
pyblish.util.publish(context)
for result in context.data["results"]:
    if not result["success"]:
        print(result["plugin"].__name__, result["instance"], result["error"])

class Broken(pyblish.api.ContextPlugin):           # a studio plugin with a bug: its traceback stays
    order = pyblish.api.CollectorOrder
    def process(self, context):
        raise ZeroDivisionError("a bug")

import sys
print("--- a studio plugin", file=sys.stderr, flush=True)
pyblish.api.deregister_all_plugins()
pyblish.api.register_plugin(Broken)
pyblish.util.publish(pyblish.api.Context())
""")
    (tmp_path / "hero_anna.usda").write_text("#usda 1.0\n")       # an earlier publish's layer
    res = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True,
                         env=_env(), timeout=300)
    assert res.returncode == 0, res.stderr
    refusal, _, bug = res.stderr.partition("--- a studio plugin")
    assert "Traceback" not in refusal and "OutputExistsError" not in refusal, res.stderr
    assert [line for line in refusal.splitlines() if "output layer exists" in line] == [
        "hero_anna.usda: output layer exists (fix: set the instance's data force=True (or force among its "
        "usdfaceOptions: in a batch manifest, the row's force column true) to replace it, or publish to "
        "another output)"], res.stderr
    assert "ValidateUsdFaceOutputs hero_anna hero_anna.usda: output layer exists" in res.stdout
    assert "Traceback" in bug and "ZeroDivisionError: a bug" in bug, res.stderr


def test_the_refusal_filter_is_added_once_to_pyblishs_logger_alone_and_deregister_removes_it():
    """Review of stop 54 (h113): ``register()`` twice adds the one-line filter once, only to the logger
    Pyblish logs a failed plugin on (a studio's own logger keeps a usdface error's traceback);
    ``deregister()`` removes it (twice, or without a register, is a no-op), and the refusals are Pyblish's
    tracebacks again."""
    import logging

    from usdface.errors import OutputExistsError

    plugin_log, studio_log = logging.getLogger("pyblish.plugin"), logging.getLogger("studio.publish")
    seen = []

    class Keep(logging.Handler):
        def emit(self, record):
            seen.append((record.name, record.getMessage(), record.exc_info is not None))

    handler = Keep()
    for log in (plugin_log, studio_log):
        log.addHandler(handler)
    try:
        plugins.deregister()
        plugins.deregister()                                  # without a register: nothing to remove
        plugins.register()
        plugins.register()
        assert [f for f in plugin_log.filters if isinstance(f, plugins._RefusalsAsOneLine)] == [
            plugins._REFUSALS]
        error = OutputExistsError("output layer exists", path="p.usda", fix="pass --force")
        for log in (plugin_log, studio_log):
            try:
                raise error
            except OutputExistsError:
                log.exception("Traceback (most recent call last): ...")
        assert seen == [("pyblish.plugin", str(error), False),
                        ("studio.publish", "Traceback (most recent call last): ...", True)], seen
        plugins.deregister()
        assert not any(isinstance(f, plugins._RefusalsAsOneLine) for f in plugin_log.filters)
        seen.clear()
        try:
            raise error
        except OutputExistsError:
            plugin_log.exception("Traceback (most recent call last): ...")
        assert seen == [("pyblish.plugin", "Traceback (most recent call last): ...", True)], seen
    finally:
        for log in (plugin_log, studio_log):
            log.removeHandler(handler)
        pyblish_api.deregister_all_plugins()
