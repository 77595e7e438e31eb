"""usdface's codeless API schemas are registered on `import usdface.io` and found by USD's schema registry."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import usdface.io  # noqa: F401  (registers the schemas before any stage exists)
from usdface import schemas

pxr = pytest.importorskip("pxr")
from pxr import Sdf, Usd  # noqa: E402

FALLBACKS = {
    schemas.LANDMARKS_API: {
        "usdface:landmarks:epsilon": 0.5, "usdface:landmarks:alpha": 0.5,
        "usdface:landmarks:solverStatus": "notSolved", "usdface:landmarks:optimalityGap": 0.0,
        "usdface:landmarks:count": 0, "usdface:landmarks:symmetric": False, "usdface:landmarks:multicover": 1,
    },
    schemas.PROVENANCE_API: {
        "usdface:provenance:version": "", "usdface:provenance:command": "", "usdface:provenance:method": "",
        "usdface:provenance:parameters": "{}", "usdface:provenance:registrationScale": 1.0,
        "usdface:provenance:registrationResidual": 0.0, "usdface:provenance:createdAt": "",
    },
    schemas.CAPTURE_API: {
        "usdface:capture:device": "", "usdface:capture:trainCount": 0, "usdface:capture:testCount": 0,
        "usdface:capture:sourceDigest": "",
    },
}
TYPES = {
    "usdface:landmarks:epsilon": Sdf.ValueTypeNames.Float,
    "usdface:landmarks:alpha": Sdf.ValueTypeNames.Float,
    "usdface:landmarks:solverStatus": Sdf.ValueTypeNames.Token,
    "usdface:landmarks:optimalityGap": Sdf.ValueTypeNames.Double,
    "usdface:landmarks:count": Sdf.ValueTypeNames.Int, "usdface:landmarks:symmetric": Sdf.ValueTypeNames.Bool,
    "usdface:landmarks:multicover": Sdf.ValueTypeNames.Int,
    "usdface:provenance:inputDigests": Sdf.ValueTypeNames.StringArray,
    "usdface:provenance:parameters": Sdf.ValueTypeNames.String,
    "usdface:capture:shapeNames": Sdf.ValueTypeNames.TokenArray,
}

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"


def test_registry_finds_all_schemas():
    reg = Usd.SchemaRegistry()
    assert schemas.is_registered()
    for name in schemas.SCHEMA_NAMES:
        definition = reg.FindAppliedAPIPrimDefinition(name)
        assert definition is not None, name
        assert reg.GetSchemaKind(reg.GetTypeFromSchemaTypeName(name)) == Usd.SchemaKind.SingleApplyAPI
        assert all(p.startswith("usdface:") for p in definition.GetPropertyNames())
    assert schemas.register() == schemas.schema_dir()  # idempotent


@pytest.mark.parametrize("api", schemas.SCHEMA_NAMES)
def test_apply_api_gives_fallbacks(api):
    stage = Usd.Stage.CreateInMemory()
    prim = stage.DefinePrim("/Face", "Xform")
    assert not prim.HasAPI(api)
    assert prim.ApplyAPI(api)
    assert prim.HasAPI(api) and api in prim.GetAppliedSchemas()
    for attr_name, fallback in FALLBACKS[api].items():
        attr = prim.GetAttribute(attr_name)
        assert attr.IsValid() and not attr.HasAuthoredValue(), attr_name
        assert attr.Get() == fallback, attr_name
    for attr_name, type_name in TYPES.items():
        if attr_name.split(":")[1] == api[len("UsdFace"):-len("API")].lower():
            assert prim.GetAttribute(attr_name).GetTypeName() == type_name, attr_name


def test_solver_status_allowed_tokens():
    definition = Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(schemas.LANDMARKS_API)
    spec = definition.GetSchemaAttributeSpec("usdface:landmarks:solverStatus")
    assert {"optimal", "feasible", "infeasible", "timeLimit"} <= set(spec.allowedTokens)


def test_authored_values_round_trip_through_usda(tmp_path):
    path = tmp_path / "p.usda"
    stage = Usd.Stage.CreateNew(str(path))
    prim = stage.DefinePrim("/Avatar", "SkelRoot")
    prim.ApplyAPI(schemas.PROVENANCE_API)
    prim.GetAttribute("usdface:provenance:inputDigests").Set(["ab" * 32])
    prim.GetAttribute("usdface:provenance:registrationScale").Set(0.01)
    stage.Save()
    del prim, stage
    again_stage = Usd.Stage.Open(str(path))
    again = again_stage.GetPrimAtPath("/Avatar")
    assert again.HasAPI(schemas.PROVENANCE_API)
    assert list(again.GetAttribute("usdface:provenance:inputDigests").Get()) == ["ab" * 32]
    assert again.GetAttribute("usdface:provenance:registrationScale").Get() == pytest.approx(0.01)


def test_plugin_files_are_consistent():
    directory = schemas.schema_dir()
    info = json.loads("\n".join(line for line in (directory / "plugInfo.json").read_text().splitlines()
                                if not line.lstrip().startswith("#")))
    types = info["Plugins"][0]["Info"]["Types"]
    assert {t["schemaIdentifier"] for t in types.values()} == set(schemas.SCHEMA_NAMES)
    assert "@PLUG_INFO" not in (directory / "plugInfo.json").read_text()
    generated = (directory / "generatedSchema.usda").read_text()
    for name in schemas.SCHEMA_NAMES:
        assert f'class "{name}"' in generated


def test_late_registration_is_reported():
    """A process that opened a stage before usdface could register gets a clear warning (strict: an error)."""
    code = (
        "import warnings\n"
        "from pxr import Usd\n"
        "Usd.Stage.CreateInMemory(); Usd.SchemaRegistry()\n"
        "from usdface import schemas\n"
        "from usdface.errors import UsdFaceError\n"
        "try:\n"
        "    schemas.register(strict=True)\n"
        "except UsdFaceError as e:\n"
        "    print('ERR', e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         cwd=Path(__file__).resolve().parents[1])
    assert "ERR" in out.stdout and "before opening any USD stage" in out.stdout, out.stdout + out.stderr


def test_late_registration_is_reported_once():
    """A host that opened a stage first got the same warning from every place that registers (importing
    ``usdface.io``, ``register_validators()``, ...): one warning is the news, the rest noise in its log."""
    code = (
        "import warnings\n"
        "warnings.simplefilter('default')\n"
        "from pxr import Usd\n"
        "Usd.Stage.CreateInMemory(); Usd.SchemaRegistry()\n"
        "import usdface.io\n"
        "from usdface.pipeline.validators import register_validators\n"
        "register_validators()\n"
        "from usdface import schemas\n"
        "schemas.register()\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         cwd=Path(__file__).resolve().parents[1])
    assert out.returncode == 0 and out.stderr.count("schema registry was created before") == 1, out.stderr


def test_inspect_lists_the_applied_schemas_in_a_host_that_opened_a_stage_first(tmp_path):
    """In a DCC (a stage opened before usdface registers its schemas) ``inspect_file`` listed no usdface
    schema on a layer that applies them: ``GetAppliedSchemas`` leaves out what the registry does not know."""
    from usdface.io.usd_rig import read_layer_info

    layer = tmp_path / "lm.usda"
    layer.write_text('#usda 1.0\n(\n    defaultPrim = "Avatar"\n)\n'
                     'def Xform "Avatar" (\n    prepend apiSchemas = ["UsdFaceProvenanceAPI"]\n)\n{\n'
                     '    def Points "Head_landmarks" (\n'
                     '        prepend apiSchemas = ["UsdFaceLandmarksAPI"]\n    )\n    {\n    }\n}\n')
    expected = {p: v["schemas"] for p, v in read_layer_info(layer)["schemas"].items()}
    assert expected == {"/Avatar": ["UsdFaceProvenanceAPI"],
                        "/Avatar/Head_landmarks": ["UsdFaceLandmarksAPI"]}
    samples = Path(__file__).resolve().parents[1] / "sample_assets"
    code = ("import json, warnings\nwarnings.simplefilter('ignore')\nfrom pxr import Usd\n"
            f"Usd.Stage.Open({str(samples / 'avatar.usda')!r})\n"
            "from usdface.io.usd_rig import read_layer_info\n"
            f"info = read_layer_info({str(layer)!r})\n"
            "print(json.dumps({p: v['schemas'] for p, v in info['schemas'].items()}))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         cwd=Path(__file__).resolve().parents[1])
    assert json.loads(out.stdout.strip().splitlines()[-1]) == expected, out.stdout + out.stderr


def test_inside_a_dcc_that_opened_a_stage_first(tmp_path):
    """Inside Maya-USD, Houdini, usdview or a Pyblish host a stage exists before usdface is imported:
    personalize_avatar failed with 'ApplyAPI: Cannot find a valid schema ... UsdFaceProvenanceAPI'."""
    script = textwrap.dedent(f"""
        import warnings
        from pxr import Usd
        Usd.Stage.Open({str(SAMPLES / 'avatar.usda')!r})   # the host's scene, before usdface is imported
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            import usdface
            usdface.personalize_avatar({str(SAMPLES / 'avatar.usda')!r},
                                       {str(SAMPLES / 'capture.usda')!r}, "person.usda", method="dt")
        print(len([w for w in said if "PXR_PLUGINPATH_NAME" in str(w.message)]))
    """)
    proc = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split()[-1] == "1"  # said once, with the fix
    from pxr import Usd

    import usdface

    stage = Usd.Stage.Open(str(tmp_path / "person.usda"))
    prim = stage.GetPrimAtPath("/Avatar")
    assert "UsdFaceProvenanceAPI" in prim.GetMetadata("apiSchemas").GetAddedOrExplicitItems()
    assert prim.GetAttribute("usdface:provenance:version").Get() == usdface.__version__
    assert json.loads(prim.GetAttribute("usdface:provenance:parameters").Get())["method"] == "dt"
    assert not [i for i in usdface.check(tmp_path / "person.usda") if i.severity == "error"]
