"""An avatar exported as a cache (every attribute time-sampled, no default value) is told for what it is: the
blend shape's arrays and channel names UsdSkel reads at the default time only, and the rest topology. Before
stop 45 only the primary ``offsets`` were named; the others read as empty and were refused as something else
('71 offsets but 0 pointIndices', '0 normalOffsets but 71 offsets', 'mesh has no faces', 'skel:blendShapes has
0 entries'), and ``usdface check`` crashed with a TypeError on time-sampled ``pointIndices``."""

from __future__ import annotations

import shutil

import pytest

import usdface.io  # noqa: F401  (schemas before the first stage)
from usdface.cli import main

pxr = pytest.importorskip("pxr")
from pxr import Gf, Usd, UsdSkel, Vt  # noqa: E402


def _to_samples(attr):
    value = attr.Get()
    attr.Clear()
    attr.Set(value, 1001)


def _point_indices(stage):
    for prim in stage.GetPrimAtPath("/Avatar/Head").GetChildren():
        if prim.IsA(UsdSkel.BlendShape) and prim.GetAttribute("pointIndices").HasAuthoredValue():
            _to_samples(prim.GetAttribute("pointIndices"))


def _normal_offsets(stage):
    for prim in stage.GetPrimAtPath("/Avatar/Head").GetChildren():
        if prim.IsA(UsdSkel.BlendShape):
            n = len(prim.GetAttribute("offsets").Get())
            UsdSkel.BlendShape(prim).CreateNormalOffsetsAttr().Set(Vt.Vec3fArray(n), 1001)


def _inbetween(stage):
    shape = UsdSkel.BlendShape(stage.GetPrimAtPath("/Avatar/Head/jawOpen"))
    half = [Gf.Vec3f(v) * 0.4 for v in shape.GetOffsetsAttr().Get()]
    inbetween = shape.CreateInbetween("half")
    inbetween.SetWeight(0.5)
    inbetween.GetAttr().Set(Vt.Vec3fArray(half), 1001)


def _topology(stage):
    head = stage.GetPrimAtPath("/Avatar/Head")
    _to_samples(head.GetAttribute("faceVertexCounts"))
    _to_samples(head.GetAttribute("faceVertexIndices"))


def _channel_names(stage):
    _to_samples(stage.GetPrimAtPath("/Avatar/Head").GetAttribute("skel:blendShapes"))


CASES = {"pointIndices": _point_indices, "normalOffsets": _normal_offsets,
         "inbetweens:half offsets": _inbetween, "faceVertexCounts": _topology,
         "skel:blendShapes": _channel_names}


@pytest.mark.parametrize("what", list(CASES))
def test_a_cache_exported_attribute_is_named_by_check_and_personalize(what, samples, tmp_path, capsys):
    avatar = tmp_path / "cache_avatar.usda"
    shutil.copy(samples / "avatar.usda", avatar)
    stage = Usd.Stage.Open(str(avatar))
    CASES[what](stage)
    stage.Save()
    del stage

    assert main(["check", str(avatar), "--no-pixar"]) == 1         # crashed (TypeError) for pointIndices
    out = capsys.readouterr().out
    assert f"{what} are time-sampled only" in out, out[-600:]
    assert "0 pointIndices" not in out and "0 normalOffsets" not in out and "has no faces" not in out

    layer = tmp_path / "out" / "person.usda"
    assert main(["personalize", str(avatar), str(samples / "capture.usda"), "-o", str(layer), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"{what} are time-sampled only" in err and "cache_avatar.usda, prim /Avatar/Head" in err, err
    assert "fix: author" in err
    assert not layer.parent.exists() or not any(layer.parent.iterdir())
