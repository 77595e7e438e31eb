"""The transfer options as the Python API, ``usdface personalize`` and ``usdface batch`` take them: one rule
for each mode's default approximation, options a mode does not use refused, the provenance of what was
given (user trial findings; each test failed before its fix)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from usdface.cli import main

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


def _layer_offsets(path) -> dict:
    """{attribute path: offsets[n,3]} of every ``offsets`` the layer authors (both variants)."""
    from pxr import Sdf

    layer, found = Sdf.Layer.FindOrOpen(str(path)), {}

    def visit(p):
        if p.IsPropertyPath() and p.name == "offsets":
            found[str(p)] = np.asarray(layer.GetAttributeAtPath(p).default, dtype=np.float64)

    layer.Traverse("/", visit)
    return found


@pytest.mark.parametrize("mode", ["person", "offset", "dt", "dt-offset"])
def test_every_face_transfer_mode_has_its_default_approximation_in_the_api(mode):
    """``face_transfer='offset'`` (any older mode) without an approximation was refused by the API and by a
    batch row ("'offset' and approximation 'field' do not go together") while the CLI chose 'generic'."""
    from usdface import api
    from usdface.transfer.pipeline import default_approximation

    assert default_approximation(mode) == ("field" if mode == "person" else "generic")
    api.check_personalize_options(face_transfer=mode)           # batch's check of a row: passes


def test_the_api_and_the_cli_give_the_same_layer_for_an_older_mode(tmp_path, capsys):
    """``usdface personalize --face-transfer offset`` and ``usdface.personalize_avatar(...,
    face_transfer='offset')`` write the same offsets and record the same resolved approximation."""
    import usdface
    from usdface.io.usd_rig import usdface_output_provenance

    cli, py = tmp_path / "cli.usda", tmp_path / "api.usda"
    assert main(["personalize", str(A), str(C), "-o", str(cli), "--face-transfer", "offset", "-q"]) == 0
    result = usdface.personalize_avatar(A, C, py, face_transfer="offset")
    assert result.report["options"]["approximation"] == "generic"
    a, b = _layer_offsets(cli), _layer_offsets(py)
    assert a and a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    for layer in (cli, py):
        assert usdface_output_provenance(layer)["parameters"]["approximation"] == "generic"
