"""Measurement CSV: lossless round trips, scipy as the orientation oracle, every malformed input."""

from __future__ import annotations

import os

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cdra_jax.io import (
    MeasurementFileError,
    Measurements,
    OutputExistsError,
    check_pose_count,
    dumps_measurements,
    load_measurements,
    loads_measurements,
    save_measurements,
)

STATE = "shoulder.rx,shoulder.ry,shoulder.rz,elbow.q,wrist.rx,wrist.ry,wrist.rz"
POS = "measured.x,measured.y,measured.z"
RV = "measured.rx,measured.ry,measured.rz"
QUAT = "measured.qw,measured.qx,measured.qy,measured.qz"


def _rows(m: int = 5, seed: int = 0):
    """Random states, positions, rotation vectors and unit quaternions (float64)."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-1, 1, (m, 7))
    q[:, 3] = rng.uniform(0, 2, m)
    xyz = rng.uniform(-400, 400, (m, 3))
    rv = rng.uniform(-1.5, 1.5, (m, 3))
    quat = rng.normal(size=(m, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    return q, xyz, rv, quat


def _poses(m: int, seed: int = 0) -> np.ndarray:
    """``m`` random rigid transforms ``(m, 4, 4)`` (scipy, independent of the package)."""
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (m, 1, 1))
    T[:, :3, :3] = Rotation.random(m, random_state=seed).as_matrix()
    T[:, :3, 3] = rng.uniform(-400, 400, (m, 3))
    return T


def _csv(header: str, rows, comments=("made by hand", "second comment")) -> str:
    lines = [f"# {c}" for c in comments] + [header]
    for r in rows:
        lines.append(",".join(c if isinstance(c, str) else repr(float(c)) for c in r))
    return "\n".join(lines) + "\n"


@pytest.fixture(scope="module")
def good_text():
    """A valid 5-pose file: 2 comment lines, header on line 3, rows on lines 4-8."""
    q, xyz, rv, _ = _rows()
    ids = [f"p{i + 1:02d}" for i in range(5)]
    rows = [[ids[i], *q[i], *xyz[i], *rv[i]] for i in range(5)]
    return _csv(f"pose,{STATE},{POS},{RV}", rows)


def test_rotvec_round_trip_is_lossless_and_matches_scipy(cdra, good_text):
    meas = loads_measurements(good_text, cdra, source="data.csv")
    assert dumps_measurements(meas) == good_text  # byte for byte: comments, ids, order, digits
    q, xyz, rv, _ = _rows()
    assert meas.pose_ids == ("p01", "p02", "p03", "p04", "p05")
    assert meas.comments == ("made by hand", "second comment")
    assert meas.lines == (4, 5, 6, 7, 8)
    assert meas.state_names == cdra.state_names
    np.testing.assert_array_equal(meas.q, q)
    assert meas.orientation == "rotvec"
    np.testing.assert_array_equal(meas.measured[:, :3, 3], xyz)
    np.testing.assert_allclose(
        meas.measured[:, :3, :3], Rotation.from_rotvec(rv).as_matrix(), atol=1e-15
    )
    np.testing.assert_array_equal(meas.measured[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (5, 1)))


def test_quaternion_round_trip_with_aux_columns_odd_order_and_odd_ids(cdra):
    q, xyz, _, quat = _rows(seed=1)
    ids = ["007", "#hash", "with,comma", 'quo"te', " spaced "]
    header = f"{QUAT},time_s,pose,{POS},approach.elbow,{STATE},payload_kg,temperature_c"
    time_s = [0.0, 1.5, 3.0, 4.5, 6.0]
    approach = [1.0, -1.0, 1.0, 1.0, -1.0]
    rows = []
    for i in range(5):
        pid = '"' + ids[i].replace('"', '""') + '"' if any(c in ids[i] for c in ',"') else ids[i]
        rows.append([*quat[i], time_s[i], pid, *xyz[i], approach[i], *q[i], 0.25, 21.5 + i])
    text = _csv(header, rows)
    meas = loads_measurements(text, cdra, source="quat.csv")
    assert meas.pose_ids == tuple(ids)
    assert meas.columns == tuple(header.split(","))
    assert dumps_measurements(meas) == text
    assert meas.orientation == "quaternion"
    np.testing.assert_array_equal(meas.q, q)
    np.testing.assert_array_equal(meas.aux["time_s"], time_s)
    np.testing.assert_array_equal(meas.aux["approach.elbow"], approach)
    np.testing.assert_array_equal(meas.aux["temperature_c"], 21.5 + np.arange(5))
    assert list(meas.aux) == ["time_s", "approach.elbow", "payload_kg", "temperature_c"]
    expected = Rotation.from_quat(quat, scalar_first=True).as_matrix()
    np.testing.assert_allclose(meas.measured[:, :3, :3], expected, atol=1e-15)
    np.testing.assert_array_equal(meas.values["measured.qw"], quat[:, 0])  # kept as given


def test_from_arrays_save_load_round_trip(cdra, tmp_path):
    q, _, _, _ = _rows(m=6, seed=2)
    T = _poses(6, seed=2)
    for orientation in ("rotvec", "quaternion"):
        meas = Measurements.from_arrays(
            cdra,
            q,
            T,
            orientation=orientation,
            aux={"payload_kg": np.full(6, 0.5)},
            comments=["first", "", "  indented"],
        )
        path = tmp_path / f"{orientation}.csv"
        save_measurements(meas, path)
        back = load_measurements(path, cdra)
        assert back.pose_ids == ("p01", "p02", "p03", "p04", "p05", "p06")
        assert back.comments == ("first", "", "  indented")
        np.testing.assert_array_equal(back.q, q)
        for c in meas.columns[1:]:
            np.testing.assert_array_equal(back.values[c], meas.values[c])
        np.testing.assert_allclose(back.measured, T, rtol=0, atol=1e-12)
        assert path.read_text() == dumps_measurements(back)
        if orientation == "quaternion":
            assert np.all(back.values["measured.qw"] >= 0)


def test_save_refuses_to_overwrite_without_force(cdra, tmp_path, good_text):
    meas = loads_measurements(good_text, cdra)
    path = tmp_path / "out.csv"
    path.write_text("precious")
    with pytest.raises(OutputExistsError, match=r"out\.csv: file exists.*force"):
        save_measurements(meas, path)
    assert path.read_text() == "precious"
    save_measurements(meas, path, force=True)
    assert path.read_text() == good_text
    assert os.listdir(tmp_path) == ["out.csv"]  # no temporary file left behind


def test_reader_accepts_any_pose_count_but_calibration_needs_four(cdra, good_text):
    lines = good_text.splitlines(keepends=True)
    three = loads_measurements("".join(lines[:6]), cdra, source="three.csv")
    assert three.m == 3
    with pytest.raises(MeasurementFileError, match=r"three\.csv: 3 measured pose\(s\).*at least 4"):
        check_pose_count(three)
    empty = loads_measurements("".join(lines[:3]), cdra)
    assert empty.q.shape == (0, 7) and empty.measured.shape == (0, 4, 4)
    check_pose_count(loads_measurements(good_text, cdra))


def test_near_unit_quaternion_is_normalised_but_kept_as_given(cdra):
    q, xyz, _, quat = _rows(m=4, seed=3)
    quat[2] *= 1 + 8e-7
    text = _csv(
        f"pose,{STATE},{POS},{QUAT}", [[f"k{i}", *q[i], *xyz[i], *quat[i]] for i in range(4)]
    )
    meas = loads_measurements(text, cdra)
    R = meas.measured[2, :3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-15)
    np.testing.assert_array_equal(meas.values["measured.qx"], quat[:, 1])
    assert dumps_measurements(meas) == text


def test_pose_plan_without_measured_columns(cdra):
    q, _, _, _ = _rows(m=4)
    text = _csv(f"pose,{STATE}", [[f"x{i}", *q[i]] for i in range(4)], comments=())
    with pytest.raises(MeasurementFileError, match="missing column measured.x"):
        loads_measurements(text, cdra)
    plan = loads_measurements(text, cdra, require_measured=False)
    assert plan.measured is None and plan.orientation is None
    assert dumps_measurements(plan) == text
    np.testing.assert_array_equal(plan.q, q)


def test_select_keeps_rows_and_line_numbers(cdra, good_text):
    meas = loads_measurements(good_text, cdra)
    sub = meas.select([4, 0])
    assert sub.pose_ids == ("p05", "p01") and sub.lines == (8, 4)
    np.testing.assert_array_equal(sub.q, meas.q[[4, 0]])
    np.testing.assert_array_equal(sub.measured, meas.measured[[4, 0]])


def _replace(text: str, line: int, old: str, new: str) -> str:
    lines = text.splitlines(keepends=True)
    assert old in lines[line - 1], (old, lines[line - 1])
    lines[line - 1] = lines[line - 1].replace(old, new, 1)
    return "".join(lines)


def _cell(text: str, line: int, column: str, value: str) -> str:
    lines = text.splitlines(keepends=True)
    header = lines[2].rstrip("\n").split(",")
    cells = lines[line - 1].rstrip("\n").split(",")
    cells[header.index(column)] = value
    lines[line - 1] = ",".join(cells) + "\n"
    return "".join(lines)


def _header(text: str, old: str, new: str) -> str:
    return _replace(text, 3, old, new)


def _drop_column(text: str, column: str) -> str:
    lines = text.splitlines(keepends=True)
    j = lines[2].rstrip("\n").split(",").index(column)
    for k in range(2, len(lines)):
        cells = lines[k].rstrip("\n").split(",")
        del cells[j]
        lines[k] = ",".join(cells) + "\n"
    return "".join(lines)


def _add_column(text: str, column: str, value: str) -> str:
    lines = text.splitlines(keepends=True)
    lines[2] = lines[2].rstrip("\n") + f",{column}\n"
    for k in range(3, len(lines)):
        lines[k] = lines[k].rstrip("\n") + f",{value}\n"
    return "".join(lines)


BAD_CASES = {
    "missing header": (
        lambda t: "".join(t.splitlines(keepends=True)[:2] + t.splitlines(keepends=True)[3:]),
        ["line 3", "missing header row"],
    ),
    "only comments": (lambda t: "# nothing\n\n", ["data.csv", "missing header row"]),
    "missing pose column": (lambda t: _header(t, "pose,", "id,"), ["line 3", "'pose'"]),
    "missing state column": (
        lambda t: _drop_column(t, "wrist.rz"),
        ["line 3 (header row)", "column 'wrist.rz'", "missing column wrist.rz"],
    ),
    "missing position column": (
        lambda t: _drop_column(t, "measured.z"),
        ["line 3 (header row)", "column 'measured.z'", "missing column measured.z"],
    ),
    "missing module": (
        lambda t: _drop_column(t, "elbow.q"),
        ["column 'elbow.q'", "missing columns for module 'elbow'"],
    ),
    "unknown column": (
        lambda t: _add_column(t, "operator", "1"),
        ["line 3 (header row)", "column 'operator'", "unknown column"],
    ),
    "unknown measured column": (
        lambda t: _add_column(t, "measured.w", "1"),
        ["column 'measured.w'", "unknown column"],
    ),
    "unknown module prefix": (
        lambda t: _header(t, "elbow.q", "knee.q"),
        ["column 'knee.q'", "unknown module 'knee'", "shoulder, elbow, wrist"],
    ),
    "unknown approach module": (
        lambda t: _add_column(t, "approach.knee", "1"),
        ["column 'approach.knee'", "unknown module 'knee'"],
    ),
    "wrong suffix for a revolute module": (
        lambda t: _header(t, "elbow.q", "elbow.rx"),
        ["column 'elbow.rx'", "unknown column for module 'elbow'", "elbow.q"],
    ),
    "duplicate column": (
        lambda t: _header(t, "measured.x", "elbow.q"),
        ["column 'elbow.q'", "twice"],
    ),
    "non-numeric cell": (
        lambda t: _cell(t, 6, "elbow.q", "abc"),
        ["data.csv, line 6, column 'elbow.q'", "not a number: 'abc'"],
    ),
    "empty cell": (
        lambda t: _cell(t, 5, "measured.y", ""),
        ["line 5, column 'measured.y'", "empty cell"],
    ),
    "NaN cell": (lambda t: _cell(t, 7, "wrist.ry", "nan"), ["line 7, column 'wrist.ry'", "NaN"]),
    "inf cell": (
        lambda t: _cell(t, 4, "measured.rz", "-inf"),
        ["line 4, column 'measured.rz'", "not a finite number"],
    ),
    "duplicate pose id": (
        lambda t: _cell(t, 7, "pose", "p02"),
        ["line 7, column 'pose'", "duplicate pose identifier 'p02'", "line 5"],
    ),
    "empty pose id": (lambda t: _cell(t, 8, "pose", " "), ["line 8, column 'pose'", "empty"]),
    "too few fields": (
        lambda t: _replace(t, 5, ",", ";"),
        ["line 5", "expected 14 fields", "got 13"],
    ),
    "semicolon separated": (
        lambda t: t.replace(",", ";"),
        ["line 3", "separated by commas", "';'"],
    ),
    "comment after header": (
        lambda t: t + "# trailing remark\n",
        ["line 9", "comment line after the header"],
    ),
    "both orientation sets": (
        lambda t: _add_column(
            _add_column(
                _add_column(_add_column(t, "measured.qw", "1"), "measured.qx", "0"),
                "measured.qy",
                "0",
            ),
            "measured.qz",
            "0",
        ),
        ["line 3 (header row)", "column 'measured.qw'", "both orientation column sets"],
    ),
    "incomplete rotation vector": (
        lambda t: _drop_column(t, "measured.ry"),
        ["column 'measured.ry'", "missing column measured.ry"],
    ),
    "incomplete cable set": (
        lambda t: _header(
            t, "shoulder.rx,shoulder.ry,shoulder.rz", "shoulder.l1,shoulder.l2,shoulder.l3"
        ),
        ["line 3 (header row)", "column 'shoulder.l4'", "missing column shoulder.l4"],
    ),
    "joint and cable columns mixed": (
        lambda t: _add_column(t, "wrist.l1", "100"),
        ["column 'wrist.", "both joint coordinates and cable lengths"],
    ),
    "cable columns with a gap": (
        lambda t: _header(t, "wrist.rx,wrist.ry,wrist.rz", "wrist.l1,wrist.l3,wrist.l4"),
        ["column 'wrist.l2'", "missing column wrist.l2"],
    ),
    "approach not +-1": (
        lambda t: _cell(_add_column(t, "approach.wrist", "1"), 6, "approach.wrist", "0.5"),
        ["line 6, column 'approach.wrist'", "must be +1 or -1, got 0.5"],
    ),
}


@pytest.mark.parametrize("case", list(BAD_CASES))
def test_malformed_file_errors_name_file_line_and_column(cdra, good_text, case):
    mutate, expected = BAD_CASES[case]
    with pytest.raises(MeasurementFileError) as info:
        loads_measurements(mutate(good_text), cdra, source="data.csv")
    msg = str(info.value)
    assert msg.startswith("data.csv")
    for part in expected:
        assert part in msg, (case, msg)


@pytest.mark.parametrize("cell", ["1_0", "57_0.57", "1e1_0", "\u0661\u0662", "\uff11.5"])
def test_cells_python_float_accepts_but_are_not_decimal_numbers_are_refused(cdra, good_text, cell):
    # float() reads '1_0' as 10, '57_0.57' as 570.57 and Arabic-Indic or full-width digits.
    with pytest.raises(MeasurementFileError) as info:
        loads_measurements(_cell(good_text, 5, "elbow.q", cell), cdra, source="data.csv")
    assert str(info.value) == f"data.csv, line 5, column 'elbow.q': not a number: {cell!r}"


def test_decimal_spellings_are_still_read(cdra, good_text):
    for cell, value in [(" -1.5 ", -1.5), ("+.5", 0.5), ("2.", 2.0), ("1E-3", 1e-3)]:
        meas = loads_measurements(_cell(good_text, 5, "elbow.q", cell), cdra)
        assert meas.q[1, 3] == value, cell


def test_non_unit_quaternion_error_says_by_how_much(cdra):
    q, xyz, _, quat = _rows(m=4, seed=4)
    quat[1] *= 1.001
    text = _csv(
        f"pose,{STATE},{POS},{QUAT}", [[f"k{i}", *q[i], *xyz[i], *quat[i]] for i in range(4)]
    )
    with pytest.raises(MeasurementFileError) as info:
        loads_measurements(text, cdra, source="q.csv")
    msg = str(info.value)
    assert "q.csv, line 5, column 'measured.qw'" in msg
    assert "is not unit: its norm 1.001 differs from 1 by 0.001 (tolerance 1e-06)" in msg
    assert "np.float64" not in msg
    assert info.value.line == 5 and info.value.column == "measured.qw"


def test_unreadable_file_is_named(cdra, tmp_path):
    with pytest.raises(MeasurementFileError, match=r"nope\.csv: cannot read measurement file"):
        load_measurements(tmp_path / "nope.csv", cdra)


def test_from_arrays_rejects_bad_arrays(cdra):
    q, _, _, _ = _rows(m=4)
    T = _poses(4)
    with pytest.raises(ValueError, match=r"q must have shape \(m, 7\)"):
        Measurements.from_arrays(cdra, q[:, :6], T)
    with pytest.raises(ValueError, match="duplicate pose identifier 'a'"):
        Measurements.from_arrays(cdra, q, T, pose_ids=["a", "b", "a", "c"])
    bad = T.copy()
    bad[0, :3, :3] *= 1.01
    with pytest.raises(ValueError, match="rigid transforms"):
        Measurements.from_arrays(cdra, q, bad)
    with pytest.raises(ValueError, match="unknown auxiliary column 'humidity'"):
        Measurements.from_arrays(cdra, q, T, aux={"humidity": np.zeros(4)})


def test_spreadsheet_quirks_bom_and_crlf_are_accepted(cdra, good_text, tmp_path):
    path = tmp_path / "excel.csv"
    path.write_bytes(b"\xef\xbb\xbf" + good_text.replace("\n", "\r\n").encode())
    meas = load_measurements(path, cdra)
    assert meas.comments == ("made by hand", "second comment") and meas.lines[0] == 4
    assert dumps_measurements(meas) == good_text
    bad = _cell(good_text, 6, "elbow.q", "abc").replace("\n", "\r\n")
    with pytest.raises(MeasurementFileError, match="line 6, column 'elbow.q'"):
        loads_measurements("\ufeff" + bad, cdra)


def _cable_csv(arm, q, module="shoulder"):
    """A measurement CSV whose ``module`` state is given as cable lengths (exact IK)."""
    from cdra_jax import tool_pose
    from cdra_jax.io import Measurements, dumps_measurements
    from cdra_jax.modules.cable_data import arm_cable_lengths

    lengths = np.asarray(arm_cable_lengths(arm, q)[module])
    lines = dumps_measurements(
        Measurements.from_arrays(arm, q, np.asarray(tool_pose(arm, q)))
    ).splitlines()
    header = lines[0].split(",")
    drop = [header.index(c) for c in arm.module(module).state_names]
    new_header = [h for i, h in enumerate(header) if i not in drop]
    new_header += [f"{module}.l{j + 1}" for j in range(lengths.shape[1])]
    rows = []
    for k, line in enumerate(lines[1:]):
        cells = [c for i, c in enumerate(line.split(",")) if i not in drop]
        rows.append(",".join(cells + [repr(float(v)) for v in lengths[k]]))
    return "\n".join([",".join(new_header), *rows]) + "\n", lengths


def test_cable_length_columns_give_the_module_state(cdra):
    import jax

    from cdra_jax.io import dumps_measurements, loads_measurements
    from cdra_jax.simulation import sample_states

    q = np.asarray(sample_states(jax.random.PRNGKey(3), cdra, 6))
    text, _ = _cable_csv(cdra, q)
    meas = loads_measurements(text, cdra, source="c.csv")
    np.testing.assert_allclose(meas.q, q, atol=1e-9)
    assert dumps_measurements(meas) == text  # the lengths are kept as given


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        (lambda v: "-5.0", ["line 3", "column 'shoulder.l6'", "not positive"]),
        (lambda v: repr(float(v) + 20.0), ["line 3", "column 'shoulder.l", "no pose"]),
    ],
)
def test_bad_cable_lengths_name_row_and_column(cdra, edit, expected):
    import jax

    from cdra_jax.io import loads_measurements
    from cdra_jax.simulation import sample_states

    q = np.asarray(sample_states(jax.random.PRNGKey(4), cdra, 5))
    text, _ = _cable_csv(cdra, q)
    lines = text.splitlines()
    cells = lines[2].split(",")
    cells[-1] = edit(cells[-1])
    lines[2] = ",".join(cells)
    with pytest.raises(MeasurementFileError) as info:
        loads_measurements("\n".join(lines) + "\n", cdra, source="c.csv")
    for part in expected:
        assert part in str(info.value), str(info.value)


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        # a NaN length (a sensor dropout exported as text)
        ("nan", ["line 3, column 'wrist.l3'", "'nan' is not a finite number"]),
        # a fifth wrist cable the model does not have
        ("l5", ["line 1 (header row), column 'wrist.l5'", "module 'wrist' has 4 cables"]),
    ],
)
def test_nan_length_and_unknown_cable_column_name_file_line_and_column(
    cdra, tmp_path, edit, expected
):
    import jax

    from cdra_jax.simulation import sample_states

    q = np.asarray(sample_states(jax.random.PRNGKey(5), cdra, 5))
    text, _ = _cable_csv(cdra, q, module="wrist")
    lines = text.splitlines()
    if edit == "nan":
        cells = lines[2].split(",")
        cells[lines[0].split(",").index("wrist.l3")] = "nan"
        lines[2] = ",".join(cells)
    else:
        lines = [lines[0] + ",wrist.l5"] + [line + ",52.0" for line in lines[1:]]
    path = tmp_path / "cables.csv"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(MeasurementFileError) as info:
        load_measurements(path, cdra)
    message = str(info.value)
    assert message.startswith(f"{path}, "), message
    for part in expected:
        assert part in message, message
