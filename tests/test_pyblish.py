"""Pyblish plugins: a real ``pyblish.util.publish`` run collects, validates (face-rig rules + OpenUSD
validators + capture), stops a bad rig before extraction, and personalizes a good one at publish time."""

from __future__ import annotations

from pathlib import Path

import pytest

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


def test_an_already_personalized_avatar_fails_validation(registered, tmp_path, samples):
    """A usdface output given as the avatar passed every validator and failed only in the extractor
    (AlreadyPersonalizedError), after the other instances' extractors had run; usdface batch refuses it
    before its first item. It fails ValidateUsdFaceRig now, naming the original avatar."""
    from usdface.api import personalize_avatar
    from usdface.errors import AlreadyPersonalizedError

    layer = tmp_path / "p.usda"
    personalize_avatar(samples / "avatar.usda", samples / "capture.usda", layer)
    calls = []
    pyblish_api.deregister_plugin(plugins.ExtractUsdFacePersonalized)

    class Extract(plugins.ExtractUsdFacePersonalized):
        def process(self, instance):
            calls.append(instance)

    pyblish_api.register_plugin(Extract)
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
def test_missing_option_files_and_a_cache_in_the_capture_fail_validation(registered, tmp_path, samples,
                                                                          sample_capture_folder, case,
                                                                          plugin, says):
    """A missing take or pins file, or a correspondence cache inside the capture folder, passed every
    validator and failed only in the extractor; 'usdface batch' refuses such a row before its first item."""
    calls = []
    pyblish_api.deregister_plugin(plugins.ExtractUsdFacePersonalized)

    class Extract(plugins.ExtractUsdFacePersonalized):
        def process(self, instance):
            calls.append(instance)

    pyblish_api.register_plugin(Extract)
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
