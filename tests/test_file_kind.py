"""io.file_kind: one rule tells what kind of input a path is. One test per kind (and per piece of evidence
where a kind has several), on small layers written here and on the bundled sample_assets."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import usdface.io  # noqa: F401  (registers the schemas before a test opens a stage)
from usdface.io.file_kind import NOT_AVATAR, Kind, file_kind

SAMPLES = Path(__file__).resolve().parents[1] / "sample_assets"


def _usda(path: Path, body: str = "", data: str = "", default: str = "") -> Path:
    """A .usda with ``customLayerData`` ``data`` (usda dictionary entries), ``defaultPrim`` and ``body``."""
    meta = []
    if data:
        meta.append(f"customLayerData = {{\n{data}\n}}")
    if default:
        meta.append(f'defaultPrim = "{default}"')
    head = f"#usda 1.0\n(\n{chr(10).join(meta)}\n)\n" if meta else "#usda 1.0\n"
    path.write_text(head + body)
    return path


_TIME_SAMPLED_MESH = '''
def Xform "Take" {
    def Mesh "Frames" {
        int[] faceVertexCounts = [3]
        int[] faceVertexIndices = [0, 1, 2]
        point3f[] points.timeSamples = {0: [(0,0,0), (1,0,0), (0,1,0)], 1: [(0,0,1), (1,0,1), (0,1,1)]}
    }
}
'''

_SKEL_ANIMATION = '''
def SkelAnimation "Anim" {
    uniform token[] blendShapes = ["jawOpen"]
    float[] blendShapeWeights.timeSamples = {0: [0], 1: [1]}
}
'''


# ------------------------------------------------------------------------------------ paths and folders
def test_missing(tmp_path):
    found = file_kind(tmp_path / "nope.usda")
    assert found.kind is Kind.MISSING and found.usdface == {} and found.layer is None


def test_capture_folder_by_train(tmp_path):
    (tmp_path / "cap" / "train").mkdir(parents=True)
    (tmp_path / "cap" / "take.csv").write_text("Timecode\n")      # train/ wins over a CSV
    found = file_kind(tmp_path / "cap")
    assert (found.kind, found.by) == (Kind.CAPTURE_FOLDER, "train/")


def test_capture_folder_by_neutral_obj(tmp_path):
    (tmp_path / "cap").mkdir()
    (tmp_path / "cap" / "neutral.obj").write_text("v 0 0 0\n")
    found = file_kind(tmp_path / "cap")
    assert (found.kind, found.by, found.meshes) == (Kind.CAPTURE_FOLDER, "neutral.obj", True)


def test_take_folder_with_frames(tmp_path):
    (tmp_path / "take" / "frames").mkdir(parents=True)
    (tmp_path / "take" / "neutral.obj").write_text("v 0 0 0\n")    # a take's optional neutral
    found = file_kind(tmp_path / "take")
    assert (found.kind, found.by, found.meshes) == (Kind.TAKE_FOLDER, "frames/", True)


def test_take_folder_of_a_csv_with_and_without_objs(tmp_path):
    (tmp_path / "t").mkdir()
    (tmp_path / "t" / "take.csv").write_text("Timecode\n")
    found = file_kind(tmp_path / "t")
    assert (found.kind, found.by, found.meshes) == (Kind.TAKE_FOLDER, "*.csv", False)   # weights only
    (tmp_path / "t" / "f0001.obj").write_text("v 0 0 0\n")
    assert file_kind(tmp_path / "t").meshes


def test_other_folder(tmp_path):
    assert file_kind(SAMPLES).kind is Kind.FOLDER
    assert file_kind(tmp_path).kind is Kind.FOLDER


def test_livelink_csv(tmp_path):
    csv = tmp_path / "take.CSV"
    csv.write_text("Timecode,jawOpen\n")
    assert (file_kind(csv).kind, file_kind(csv).by) == (Kind.LIVELINK_CSV, "suffix")


def test_other_file_and_a_pipe_named_usda(tmp_path):
    other = tmp_path / "map.json"
    other.write_text("{}")
    assert file_kind(other).kind is Kind.OTHER and file_kind(other).layer is None
    pipe = tmp_path / "p.usda"
    os.mkfifo(pipe)
    found = file_kind(pipe)                 # never opened: the reader says it is a pipe
    assert (found.kind, found.by, found.layer) == (Kind.USD, "path", None)


def test_unreadable_usd(tmp_path):
    bad = tmp_path / "bad.usda"
    bad.write_text("#usda 1.0\ndef Xform \"A\" {\n")
    found = file_kind(bad, compose=True)
    assert (found.kind, found.by, found.skel_root) == (Kind.USD, "suffix", None)


# ------------------------------------------------------------------------------- the root layer's record
def test_capture_by_format_sample():
    found = file_kind(SAMPLES / "capture.usda")
    assert (found.kind, found.by, found.format) == (Kind.CAPTURE, "format", "capture")
    assert found.provenance is None and found.layer is not None


def test_take_by_format(tmp_path):
    found = file_kind(_usda(tmp_path / "t.usda", data='dictionary usdface = {string format = "take"}'))
    assert (found.kind, found.by) == (Kind.TAKE, "format")


def test_fit_by_format(tmp_path):
    path = _usda(tmp_path / "fit.usda",
                 data='dictionary usdface = {string format = "fit"\nstring[] inputs = ["cap.usda"]}')
    found = file_kind(path)
    assert (found.kind, found.by) == (Kind.FIT, "format")
    assert found.provenance == {"format": "fit", "inputs": ["cap.usda"]}


def test_error_maps_by_format(tmp_path):
    found = file_kind(_usda(tmp_path / "e.usda", data='dictionary usdface = {string format = "errorMaps"}'))
    assert (found.kind, found.by) == (Kind.ERROR_MAPS, "format") and found.kind in NOT_AVATAR


def test_flattened_export(tmp_path):
    path = _usda(tmp_path / "flat.usdc.usda", data='dictionary usdface = {string[] inputs = ["a.usda"]}\n'
                 'dictionary usdfaceFlatten = {string source = "p.usda"\nstring variant = "personalized"}')
    found = file_kind(path)
    assert (found.kind, found.by) == (Kind.FLATTENED, "flatten")
    assert found.flattened == {"source": "p.usda", "variant": "personalized"}
    assert found.provenance == {"inputs": ["a.usda"]}


def test_flatten_record_without_a_variant_is_none(tmp_path):
    path = _usda(tmp_path / "f.usda", data='dictionary usdfaceFlatten = {string source = "p.usda"}')
    assert file_kind(path).flattened is None and file_kind(path).kind is Kind.USD


def test_usdface_layer_by_inputs(tmp_path):
    path = _usda(tmp_path / "p.usda", data='dictionary usdface = {string[] inputs = ["a.usda", "c.usda"]}')
    found = file_kind(path)
    assert (found.kind, found.by, found.provenance["inputs"]) == (Kind.LAYER, "inputs", ["a.usda", "c.usda"])


def test_a_capture_recording_inputs_has_no_provenance(tmp_path):
    path = _usda(tmp_path / "c.usda",
                 data='dictionary usdface = {string format = "capture"\nstring[] inputs = ["x"]}')
    assert file_kind(path).kind is Kind.CAPTURE and file_kind(path).provenance is None


# ------------------------------------------------------------------------------- the root layer's specs
def test_take_by_layer_specs(tmp_path):
    found = file_kind(_usda(tmp_path / "t.usda", _TIME_SAMPLED_MESH, default="Take"))
    assert (found.kind, found.by) == (Kind.TAKE, "layer specs")


def test_an_over_of_an_animated_mesh_is_no_take(tmp_path):
    found = file_kind(_usda(tmp_path / "shot.usda", _TIME_SAMPLED_MESH.replace('def Mesh', 'over')))
    assert (found.kind, found.by) == (Kind.USD, "nothing")


def test_blend_shapes_outside_the_template_make_no_take(tmp_path):
    shape = 'def BlendShape "jawOpen" {\nuniform vector3f[] offsets = [(0,0,0)]\n}\n'
    inside = _TIME_SAMPLED_MESH.replace('def Mesh "Frames"', f'def SkelRoot "Template" {{\n{shape}}}\n'
                                        'def Mesh "Frames"')
    assert file_kind(_usda(tmp_path / "t.usda", inside, default="Take")).kind is Kind.TAKE
    outside = _TIME_SAMPLED_MESH.replace('def Mesh "Frames"', f'{shape}def Mesh "Frames"')
    assert file_kind(_usda(tmp_path / "a.usda", outside, default="Take")).kind is Kind.USD


def test_a_capture_role_makes_no_take(tmp_path):
    body = _TIME_SAMPLED_MESH.replace("int[] faceVertexCounts", 'uniform token[] usdface:frames:role = '
                                      '["train"]\nint[] faceVertexCounts')
    assert file_kind(_usda(tmp_path / "c.usda", body, default="Take")).kind is Kind.USD


# ------------------------------------------------------------------------------------ the composed stage
def test_avatar_sample_only_when_composed():
    plain = file_kind(SAMPLES / "avatar.usda")
    assert (plain.kind, plain.by, plain.skel_root) == (Kind.USD, "nothing", None)
    found = file_kind(SAMPLES / "avatar.usda", compose=True)
    assert (found.kind, found.by, found.skel_root, found.blend_shapes) == (Kind.AVATAR, "stage", True, True)
    assert found.kind not in NOT_AVATAR


@pytest.mark.parametrize("role", [True, False])
def test_capture_or_take_by_layout(tmp_path, role):
    attr = 'uniform token[] usdface:frames:role = ["train"]\n' if role else ""
    body = f'def Xform "Capture" {{\ndef Mesh "Frames" {{\n{attr}}}\ndef SkelRoot "Template" {{}}\n}}\n'
    path = _usda(tmp_path / "c.usda", body, default="Capture")
    assert file_kind(path).kind is Kind.USD
    found = file_kind(path, compose=True)
    assert (found.kind, found.by) == ((Kind.CAPTURE if role else Kind.TAKE), "layout")


def test_capture_by_schema(tmp_path):
    body = 'def Xform "Cap" (\nprepend apiSchemas = ["UsdFaceCaptureAPI"]\n) {}\n'
    found = file_kind(_usda(tmp_path / "c.usda", body, default="Cap"), compose=True)
    assert (found.kind, found.by) == (Kind.CAPTURE, "schema")


def test_legacy_error_maps(tmp_path):
    path = _usda(tmp_path / "e.usda", 'def Xform "ErrorMaps" {}\n', default="ErrorMaps")
    found = file_kind(path, compose=True)
    assert (found.kind, found.by) == (Kind.ERROR_MAPS, "legacy")
    with_root = _usda(tmp_path / "r.usda", 'def Xform "ErrorMaps" {\ndef SkelRoot "R" {}\n}\n',
                      default="ErrorMaps")
    assert file_kind(with_root, compose=True).kind is Kind.AVATAR


def test_weights_take(tmp_path):
    path = _usda(tmp_path / "anim.usda", _SKEL_ANIMATION, data='dictionary usdface = {string version = "1"}',
                 default="Anim")
    assert file_kind(path).kind is Kind.USD
    found = file_kind(path, compose=True)
    assert (found.kind, found.by, found.skel_animation) == (Kind.WEIGHTS_TAKE, "stage", True)
    nested = _usda(tmp_path / "nested.usda", 'def Xform "Root" {\n' + _SKEL_ANIMATION + '}\n', default="Root")
    found = file_kind(nested, compose=True)     # not at the top: no take, though it has a SkelAnimation
    assert (found.kind, found.skel_animation) == (Kind.USD, True)


def test_composed_stage_overrides_the_spec_test_only_with_a_kind_that_is_no_avatar(tmp_path):
    """A mesh cache beside a SkelRoot stays a take by its specs (the avatar reader does not refuse it);
    with a top-level SkelAnimation and no SkelRoot the composed stage calls it a weights-only take."""
    cache = _usda(tmp_path / "cache.usda", _TIME_SAMPLED_MESH + 'def SkelRoot "Rig" {}\n')
    found = file_kind(cache, compose=True)
    assert (found.kind, found.by, found.skel_root) == (Kind.TAKE, "layer specs", True)
    both = _usda(tmp_path / "both.usda", _TIME_SAMPLED_MESH + _SKEL_ANIMATION)
    assert file_kind(both).kind is Kind.TAKE
    assert (file_kind(both, compose=True).kind, file_kind(both, compose=True).by) == (Kind.WEIGHTS_TAKE,
                                                                                        "stage")


def test_a_given_stage_is_read_not_the_file(tmp_path):
    from pxr import Usd

    stage = Usd.Stage.CreateInMemory()
    stage.GetRootLayer().customLayerData = {"usdface": {"format": "capture"}}
    found = file_kind(tmp_path / "not-there.usda", stage=stage)
    assert (found.kind, found.by, found.skel_root) == (Kind.CAPTURE, "format", None)
    stage.DefinePrim("/Anim", "SkelAnimation")
    stage.GetRootLayer().customLayerData = {}
    assert file_kind(tmp_path / "x.usda", stage=stage).kind is Kind.USD
    assert file_kind(tmp_path / "x.usda", stage=stage, compose=True).kind is Kind.WEIGHTS_TAKE


def test_composition_errors_leave_it_undecided(tmp_path):
    path = _usda(tmp_path / "a.usda", 'def SkelRoot "R" {}\n')
    path.write_text(path.read_text().replace("#usda 1.0\n", '#usda 1.0\n(\nsubLayers = [@gone.usda@]\n)\n'))
    found = file_kind(path, compose=True)
    assert (found.kind, found.skel_root) == (Kind.USD, None)


def test_take_wrappers_agree(tmp_path):
    from usdface.io.take import is_take, probe_take

    take = _usda(tmp_path / "t.usda", _TIME_SAMPLED_MESH, default="Take")
    assert is_take(take) and probe_take(take)[1] is file_kind(take).layer
    assert not is_take(SAMPLES / "capture.usda") and probe_take(tmp_path)[1] is None
