"""User trial, session 23 (a pipeline engineer's and a new user's): the fixes their findings asked for, each
pinned by a test that failed before the fix."""

from __future__ import annotations

from pathlib import Path

import pytest

from usdface.errors import UsdFaceError

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


# ------------------------------------------------------------------ numeric options: the API as the CLI
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
    written."""
    from usdface import api

    out = tmp_path / "map.json"
    with pytest.raises(UsdFaceError, match=needle) as err:
        api.write_retarget_map(A, C, out, **options)
    assert err.value.fix and not out.exists()
    with pytest.raises(UsdFaceError, match=needle):
        api.personalize_avatar(A, C, tmp_path / "p.usda", **options)
    assert not (tmp_path / "p.usda").exists()


def test_api_numbers_that_are_fine_pass_the_check():
    from usdface.transfer.pipeline import check_numbers

    check_numbers(mu="auto", extension_length=None, falloff=0, support=None)
    check_numbers(mu="1e-3", extension_length=0.5, falloff=0.15, support=(0.0, 0.0))
    check_numbers(mu=2, extension_length=2, falloff=1, support=[0.01, 0.03])
