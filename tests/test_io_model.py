"""Model TOML: round trip of the embedded CDRA, and errors that name the file and the entry."""

from __future__ import annotations

import numpy as np
import pytest
import tomli_w

from cdra_jax.io import (
    ModelFileError,
    arm_from_dict,
    arm_to_dict,
    dumps_model,
    load_model,
    loads_model,
)


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


def _set_frame(key, value):
    def edit(d):
        d["frames"][2] = {"name": "forearm", key: value}
        if key == "xyz":
            d["frames"][2]["rotvec"] = [0.0, 0.0, 0.0]

    return edit


def _set_module(key, value, module=1):
    def edit(d):
        d["modules"][module][key] = value

    return edit


def _elbow_cable(j, base=None, platform=None, offset=None):
    def edit(d):
        c = d["modules"][1]["cables"][j]
        if base is not None:
            c["base"] = base
        if platform is not None:
            c["platform"] = platform
        if offset is not None:
            c["offset"] = offset

    return edit


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        (_set_frame("xyz", ["0", "0", "250"]), ["frames[2] (forearm).xyz", "3 numbers", "'250'"]),
        (_set_frame("xyz", [0.0, True, 250.0]), ["frames[2] (forearm).xyz", "3 numbers"]),
        (_set_frame("matrix", [["1", 0, 0, 0]] * 4), ["frames[2] (forearm)", "4 rows of 4"]),
        (_set_module("limits", [["0", "2"]]), ["modules[1] (elbow).limits", "1 pairs"]),
        (_set_module("axis", ["0", "1", "0"]), ["modules[1] (elbow).axis", "3 numbers"]),
        (
            _set_module("mass", 10**400),
            ["modules[1] (elbow).mass", "positive number of kg up to 1e+06"],
        ),
        (_elbow_cable(0, offset=10**400), ["modules[1] (elbow).cables[0].offset", "a number"]),
        (
            _elbow_cable(0, base=[15.0, 0.0, 30.0], platform=[15.0, 0.0, 30.0]),
            ["modules[1] (elbow).cables[0]", "base and platform are the same point", "zero length"],
        ),
        (_set_module("name", "el.bow"), ["modules[1] (el.bow)", "cannot contain '.'"]),
        (_set_module("name", "el,bow"), ["modules[1] (el,bow)", "cannot contain ','"]),
        (_set_module("name", "elbow "), ["modules[1] (elbow )", "start or end with a space"]),
        (_set_module("name", "measured"), ["modules[1] (measured)", "'measured' is reserved"]),
        (_set_module("name", "approach"), ["modules[1] (approach)", "'approach' is reserved"]),
        (_set_module("name", "pose", 0), ["modules[0] (pose)", "'pose' is reserved"]),
        (_set_module("name", "time_s", 2), ["modules[2] (time_s)", "reserved"]),
    ],
    ids=[
        "xyz as strings",
        "bool in xyz",
        "matrix of strings",
        "limits as strings",
        "axis as strings",
        "huge mass",
        "huge cable offset",
        "zero-length cable",
        "dot in module name",
        "comma in module name",
        "space around module name",
        "module named measured",
        "module named approach",
        "module named pose",
        "module named time_s",
    ],
)
def test_model_values_and_names_that_break_the_files_are_refused(cdra, edit, expected):
    spec = arm_to_dict(cdra)
    edit(spec)
    with pytest.raises(ModelFileError) as info:
        arm_from_dict(spec, "arm.toml")
    msg = str(info.value)
    assert msg.startswith("arm.toml: ")
    for part in expected:
        assert part in msg, msg
