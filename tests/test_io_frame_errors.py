"""Frame-error files (``simulate --errors``): numbers only, finite, errors naming file and entry."""

from __future__ import annotations

import numpy as np
import pytest

from cdra_jax.io import load_frame_errors
from cdra_jax.io.frame_errors import FrameErrorFileError


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ('{"frames": {"base": {"vx": 1' + "0" * 400 + "}}}", "frames.base.vx: expected a finite"),
        ('{"frames": {"tool": [0, 0, -1' + "0" * 400 + ", 0, 0, 0]}}", "frames.tool[2]: expected"),
        ('{"frames": {"base": {"vx": "1.0"}}}', "frames.base.vx: expected a finite number"),
        ('{"frames": {"base": {"wz": true}}}', "frames.base.wz: expected a finite number"),
        ('{"frames": {"base": {"vx": 1' + "0" * 5000 + "}}}", "not valid JSON"),
    ],
    ids=["huge integer", "huge negative integer in a list", "string", "bool", "5001 digits"],
)
def test_bad_numbers_name_the_file_and_entry(cdra, tmp_path, text, expected):
    path = tmp_path / "e.json"
    path.write_text(text)
    with pytest.raises(FrameErrorFileError) as info:
        load_frame_errors(path, cdra)
    msg = str(info.value)
    assert msg.startswith(f"{path}: ") and expected in msg and len(msg) < 300, msg


def test_integers_and_floats_are_read(cdra, tmp_path):
    path = tmp_path / "e.toml"
    path.write_text("[frames.base]\nvx = 2\nwz = 0.01\n")
    X = load_frame_errors(path, cdra)
    np.testing.assert_array_equal(X[0], [2.0, 0, 0, 0, 0, 0.01])
    assert not X[1:].any()
