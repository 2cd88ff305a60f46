"""Model TOML: round trip of the embedded CDRA, and errors that name the file and the entry."""

from __future__ import annotations

import numpy as np
import pytest
import tomli_w

from cdra_jax.io import ModelFileError, arm_to_dict, dumps_model, load_model, loads_model


def test_model_round_trip(cdra, tmp_path):
    exact = loads_model(dumps_model(cdra, exact=True))
    np.testing.assert_array_equal(np.asarray(exact.frames), np.asarray(cdra.frames))
    readable = loads_model(dumps_model(cdra))
    np.testing.assert_allclose(np.asarray(readable.frames), np.asarray(cdra.frames), atol=1e-13)
    assert readable.frame_names == cdra.frame_names
    assert readable.state_names == cdra.state_names
    assert [m.limits for m in readable.modules] == [m.limits for m in cdra.modules]


def _frame_pop(d):
    d["frames"].pop(2)


def _skew_matrix(d):
    d["frames"][2]["matrix"][1][2] = 0.01


def _bad_kind(d):
    d["modules"][1]["kind"] = "ball"


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        (_frame_pop, ["top level", "3 modules need 4 [[frames]]", "got 3"]),
        (_skew_matrix, ["frames[2] (forearm)", "not orthonormal", "|R^T R - I| = 1"]),
        (_bad_kind, ["modules[1] (elbow)", "'kind' must be one of", "'ball'"]),
    ],
    ids=["missing frame", "non-orthonormal matrix", "unknown module kind"],
)
def test_model_errors_name_file_and_entry(cdra, tmp_path, edit, expected):
    spec = arm_to_dict(cdra, exact=True)  # frames as 4x4 matrices
    edit(spec)
    path = tmp_path / "arm.toml"
    path.write_text(tomli_w.dumps(spec))
    with pytest.raises(ModelFileError) as info:
        load_model(path)
    msg = str(info.value)
    assert msg.startswith(f"{path}: ")
    for part in expected:
        assert part in msg, msg
