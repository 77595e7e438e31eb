"""Fuzzing the avatar readers with hypothesis: malformed USD must raise a UsdFaceError subclass, nothing else.

Three families of malformed input, all derived from a small valid avatar:

* text mutations of the .usda (truncation, numbers replaced by nan/inf/huge/negative values, deleted or
  duplicated lines, swapped type names);
* truncated .usdc files;
* well-formed USD with semantically wrong values (random arrays of random length and type in the rig's
  attributes and relationships).

Not fuzzed: random byte flips inside a .usdc. With usd-core 26.11 a few flipped bytes can make USD's crate
reader hang inside ``Usd.Stage.Open`` (C++; nothing Python can catch), see docs/usd-io.md.
"""

from __future__ import annotations

import re
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_usd_rig import write_rig

import usdface.io  # noqa: F401
from usdface.errors import UsdFaceError
from usdface.inspect import inspect_file
from usdface.io.usd_rig import read_avatar

SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow],
                    derandomize=True)
_WORK = Path(tempfile.mkdtemp(prefix="usdface-fuzz-"))


def _base_files():
    usda = _WORK / "base.usda"
    if not usda.exists():
        write_rig(usda, "y_cm")
        from pxr import Usd

        Usd.Stage.Open(str(usda)).Export(str(_WORK / "base.usdc"))
    return usda.read_text(), (_WORK / "base.usdc").read_bytes()


BASE_TEXT, BASE_USDC = _base_files()
LINES = BASE_TEXT.splitlines()
NUMBERS = [m.span() for m in re.finditer(r"-?\d+(?:\.\d+)?(?:e-?\d+)?", BASE_TEXT)]
REPLACEMENTS = ["nan", "inf", "-inf", "-1", "-7", "0", "1e40", "2147483647", "99999", "", "1.5", "3"]
WORDS = ["BlendShape", "Mesh", "SkelRoot", "Skeleton", "int[]", "uint[]", "float[]", "vector3f[]",
         "point3f[]", "token[]", "uniform", "rel", "def", "over", "class", "faceVertexCounts", "pointIndices",
         "offsets", "skel:blendShapes", "skel:blendShapeTargets", "metersPerUnit", "upAxis"]


def _check(path: Path):
    """Read with every reader: success or a UsdFaceError; anything else fails the test."""
    for reader in (read_avatar, inspect_file):
        try:
            result = reader(path)
        except UsdFaceError as exc:
            assert str(path) in str(exc) or exc.path, exc
        else:
            if reader is read_avatar:
                for rig in result.meshes:
                    assert np.isfinite(rig.neutral).all() and np.isfinite(rig.deltas).all()
                    assert rig.triangles.min() >= 0 and rig.triangles.max() < rig.n_vertices


mutation = st.one_of(
    st.tuples(st.just("truncate"), st.floats(0.0, 1.0)),
    st.tuples(st.just("number"), st.integers(0, len(NUMBERS) - 1), st.sampled_from(REPLACEMENTS)),
    st.tuples(st.just("delete"), st.integers(0, len(LINES) - 1), st.integers(1, 4)),
    st.tuples(st.just("duplicate"), st.integers(0, len(LINES) - 1)),
    st.tuples(st.just("word"), st.sampled_from(WORDS), st.sampled_from(WORDS)),
)


def _mutate(text: str, ops) -> str:
    for op in ops:
        if op[0] == "truncate":
            text = text[: int(len(text) * op[1])]
        elif op[0] == "number":
            spans = [m.span() for m in re.finditer(r"-?\d+(?:\.\d+)?(?:e-?\d+)?", text)]
            if spans:
                a, b = spans[op[1] % len(spans)]
                text = text[:a] + op[2] + text[b:]
        elif op[0] == "delete":
            lines = text.splitlines()
            i = op[1] % max(len(lines), 1)
            text = "\n".join(lines[:i] + lines[i + op[2]:])
        elif op[0] == "duplicate":
            lines = text.splitlines()
            i = op[1] % max(len(lines), 1)
            text = "\n".join(lines[: i + 1] + lines[i:])
        elif op[0] == "word":
            text = text.replace(op[1], op[2], 1)
    return text


@SETTINGS
@given(ops=st.lists(mutation, min_size=1, max_size=4))
def test_usda_text_mutations(ops):
    path = _WORK / "mutated.usda"
    path.write_text(_mutate(BASE_TEXT, ops))
    _check(path)


@SETTINGS
@given(cut=st.integers(0, len(BASE_USDC) - 1))
def test_truncated_usdc(cut):
    path = _WORK / "truncated.usdc"
    path.write_bytes(BASE_USDC[:cut])
    _check(path)


TARGETS = {
    "/Avatar/Head.points": "point3f[]", "/Avatar/Head.faceVertexCounts": "int[]",
    "/Avatar/Head.faceVertexIndices": "int[]", "/Avatar/Head.skel:blendShapes": "token[]",
    "/Avatar/Head/jawOpen.offsets": "vector3f[]", "/Avatar/Head/jawOpen.pointIndices": "int[]",
    "/Avatar/Head/jawOpen.inbetweens:half": "point3f[]",
    "/Avatar/Head/eyeBlinkLeft.normalOffsets": "vector3f[]",
    "/Avatar/Mouth/mouthSmileLeft.pointIndices": "int[]", "/Avatar/Mouth.points": "point3f[]",
}
floats = st.floats(allow_nan=True, allow_infinity=True, width=32)
ints = st.integers(-(2 ** 31), 2 ** 31 - 1) | st.integers(-3, 40)


@SETTINGS
@given(edits=st.lists(st.tuples(st.sampled_from(sorted(TARGETS)),
                                st.lists(ints, max_size=45), st.lists(floats, max_size=135),
                                st.booleans()), min_size=1, max_size=3),
       drop_targets=st.integers(0, 3))
def test_semantic_values(edits, drop_targets):
    from pxr import Sdf, Usd, Vt

    path = _WORK / "semantic.usda"
    path.write_text(BASE_TEXT)
    layer = Sdf.Layer.FindOrOpen(str(path))
    layer.Reload(force=True)
    stage = Usd.Stage.Open(layer)
    for target, int_values, float_values, block in edits:
        attr = stage.GetAttributeAtPath(target)
        if not attr:
            prim = stage.GetPrimAtPath(target.split(".")[0])
            attr = prim.CreateAttribute(target.split(".", 1)[1], Sdf.ValueTypeNames.Point3fArray)
        kind = TARGETS[target]
        if block:
            attr.Block()
        elif kind == "int[]":
            attr.Set(Vt.IntArray(int_values))
        elif kind == "token[]":
            attr.Set(Vt.TokenArray([f"t{v % 7}" for v in int_values]))
        else:
            values = np.array(float_values[: len(float_values) // 3 * 3], dtype=np.float32).reshape(-1, 3)
            attr.Set(Vt.Vec3fArray.FromNumpy(values))
    rel = stage.GetPrimAtPath("/Avatar/Head").GetRelationship("skel:blendShapeTargets")
    rel.SetTargets(rel.GetTargets()[: 3 - drop_targets] if drop_targets < 3 else
                   rel.GetTargets() + [Sdf.Path("/Avatar/Nowhere")])
    layer.Save()
    del stage
    _check(path)


def test_fuzz_inputs_are_really_malformed():
    """The fuzz families do produce errors (a fuzz test whose inputs are all valid proves nothing)."""
    path = _WORK / "check.usda"
    path.write_text(_mutate(BASE_TEXT, [("truncate", 0.5)]))
    with pytest.raises(UsdFaceError):
        read_avatar(path)
    path.write_text(_mutate(BASE_TEXT, [("word", "BlendShape", "Mesh")]))
    with pytest.raises(UsdFaceError):
        read_avatar(path)
