"""``cdra-jax calibrate`` under bad data: the failure-mode table (one error line, exit 1), robust
losses with per-pose outlier flags, warnings for degenerate pose sets (exit 0)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tomli_w
from _robust_data import M, problem

from cdra_jax import cli
from cdra_jax.io import Measurements, arm_to_dict, dumps_measurements, save_measurements


def _run(*argv) -> int:
    return cli.main([str(a) for a in argv])


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """Clean and contaminated 12-pose measurement files of ``problem(0)``."""
    d = tmp_path_factory.mktemp("robust_cli")
    p = problem(0)
    save_measurements(Measurements.from_arrays(p.arm, p.q, p.T), d / "clean.csv")
    save_measurements(Measurements.from_arrays(p.arm, p.q, p.T_bad), d / "bad.csv")
    return d, p


def _errors(capsys) -> tuple[list[str], str]:
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err
    return [line for line in cap.err.splitlines() if line], cap.out


# --------------------------------------------------------------------------- robust losses


def test_cauchy_flags_the_corrupted_poses_in_summary_and_json(files, capsys):
    d, p = files
    out = d / "cauchy.json"
    assert _run("calibrate", "--data", d / "bad.csv", "--out", out, "--loss", "cauchy") == 0
    r = json.loads(out.read_text())
    assert r["converged"] and r["solver"] == "weighted+cauchy"
    assert r["robust"]["loss"] == "cauchy" and r["robust"]["tuning_constant"] == 2.385
    assert r["robust"]["inner_solver"] == "paper" and r["robust"]["rounds"] >= 1
    bad_ids = [f"p{i + 1:02d}" for i in np.flatnonzero(p.mask)]
    assert r["outliers"]["poses"] == bad_ids and r["outliers"]["scale"]["source"] == "MAD"
    for x in r["residuals"]:
        assert x["outlier"] is (x["pose"] in bad_ids)
        assert (x["weight"] < 0.01) if x["outlier"] else (x["weight"] > 0.5)
    assert len(r["iterations"]) == r["robust"]["rounds"] + 1
    err, printed = _errors(capsys)
    assert "solver: cauchy (robust, c = 2.385)" in printed
    assert f"from the MAD): {len(bad_ids)}\n  {bad_ids[0]}: z = " in printed or (
        f"from the MAD): {len(bad_ids)}\n  {bad_ids[1]}: z = " in printed
    )
    assert err == [
        next(w for w in r["warnings"] if "look like outliers" in w).join(("warning: ", ""))
    ]
    assert "the robust fit down-weighted them" in err[0]


def test_reject_outliers_refits_without_the_flagged_poses(files, capsys):
    d, p = files
    out = d / "reject.json"
    argv = ("calibrate", "--data", d / "bad.csv", "--out", out, "--loss", "huber")
    assert _run(*argv, "--reject-outliers", "--noise-pos", 0.08, "--noise-rot", 0.001) == 0
    r = json.loads(out.read_text())
    assert r["converged"] and r["solver"] == "weighted+huber+reject"
    assert r["robust"]["reject_outliers"] is True and r["robust"]["refit_without_flagged"] is True
    bad_ids = [f"p{i + 1:02d}" for i in np.flatnonzero(p.mask)]
    assert r["outliers"]["poses"] == bad_ids
    assert [x["weight"] for x in r["residuals"]] == [0.0 if m else 1.0 for m in p.mask]
    assert len(r["iterations"]) == r["robust"]["rounds"] + 2
    assert r["uncertainty"]["weights"] == [0.0 if m else 1.0 for m in p.mask]
    err, printed = _errors(capsys)
    assert (
        f"then least squares without the {len(bad_ids)} flagged pose(s) (--reject-outliers)"
        in printed
    )
    assert any("the final fit left them out" in line for line in err), err
    # without a robust loss there is nothing to flag: a clear usage error, no file
    assert (
        _run("calibrate", "--data", d / "bad.csv", "--out", d / "x.json", "--reject-outliers") == 1
    )
    err, _ = _errors(capsys)
    assert err == [
        "error: --reject-outliers needs a robust loss to flag the outliers: add --loss huber or "
        "--loss cauchy"
    ]
    assert not (d / "x.json").exists()


def test_least_squares_result_has_unit_weights_and_flags(files, capsys):
    d, _ = files
    out = d / "ls.json"
    assert _run("calibrate", "--data", d / "clean.csv", "--out", out, "--solver", "paper") == 0
    r = json.loads(out.read_text())
    assert r["robust"] is None and r["solver"] == "paper"
    assert all(x["weight"] == 1.0 and x["outlier"] is False for x in r["residuals"])
    assert r["outliers"]["poses"] == [] and r["conditioning"]["ill_conditioned"] is False
    # the identifiability warning is in the JSON (and the printed summary), not on stderr
    assert any("cannot be identified" in w for w in r["warnings"])
    err, printed = _errors(capsys)
    assert err == [] and "from the MAD): none" in printed


# --------------------------------------------------------------------------- degenerate sets


def _write(d, name, p, q, T):
    path = d / name
    save_measurements(Measurements.from_arrays(p.arm, q, T), path, force=True)
    return path


def test_degenerate_pose_sets_warn_and_give_the_min_norm_answer(files, capsys):
    d, p = files
    from cdra_jax import tool_pose

    actual = p.arm.with_frames(p.actual_frames)
    same = np.repeat(p.q[:1], M, axis=0)
    data = _write(d, "same.csv", p, same, np.asarray(tool_pose(actual, same)))
    # 12 rows of one configuration: refused, naming how many are distinct; nothing written
    assert _run("calibrate", "--data", data, "--out", d / "same.json") == cli.EXIT_ERROR
    err, _ = _errors(capsys)
    assert err == [
        f"error: {data}: 12 rows but only 1 distinct module configuration(s); the calibration "
        "needs at least 4 distinct ones (Section IV, Eq. 9): repeated configurations measure "
        "the same pose again"
    ]
    assert not (d / "same.json").exists()

    elbow = p.q.copy()
    elbow[:, 3] = 1.1
    data = _write(d, "elbow.csv", p, elbow, np.asarray(tool_pose(actual, elbow)))
    assert _run("calibrate", "--data", data, "--out", d / "elbow.json") == 0
    r = json.loads((d / "elbow.json").read_text())
    assert r["identifiability"]["rank"] == 18 and r["final"]["delta_p_mm"] < 1e-8
    assert all(np.isfinite(v) for f in r["frames"].values() for v in f["error_twist"].values())
    err, printed = _errors(capsys)
    assert "rank 18 of 24" in printed
    assert "warning: module 'elbow' never moves in this pose set (constant state)" in "\n".join(err)
    assert any(e.startswith("warning: degenerate pose set: rank 18 of 24") for e in err)

    # 0.03 rad around one state: condition number ~9e3 of the column-scaled Jacobian. (At
    # 0.003 rad, ~4e5, the step norm's rounding floor, ~2e-10, is above the paper solver's
    # tol = 1e-10: whether it converges then depends on the compiler's rounding.)
    near = p.q[:1] + 0.03 * np.random.default_rng(1).standard_normal((M, 7))
    data = _write(d, "near.csv", p, near, np.asarray(tool_pose(actual, near)))
    # (The paper solver's unweighted Jacobian; the auto solver weighs rows by the noise scales.)
    assert _run("calibrate", "--data", data, "--out", d / "near.json", "--solver", "paper") == 0
    r = json.loads((d / "near.json").read_text())
    assert r["conditioning"]["ill_conditioned"] is True and r["conditioning"]["weak_directions"]
    err, _ = _errors(capsys)
    assert any(e.startswith("warning: poorly conditioned pose set") for e in err)
    assert any(w.startswith("poorly conditioned pose set") for w in r["warnings"])


# --------------------------------------------------------------------------- failure modes


def _csv_edit(text: str, row: int, column: str, value: str) -> str:
    lines = text.splitlines(keepends=True)
    header = lines[0].rstrip("\n").split(",")
    cells = lines[row].rstrip("\n").split(",")
    cells[header.index(column)] = value
    lines[row] = ",".join(cells) + "\n"
    return "".join(lines)


def _add_column(text: str, name: str, value: str) -> str:
    lines = text.splitlines()
    return "\n".join([lines[0] + f",{name}"] + [line + f",{value}" for line in lines[1:]]) + "\n"


def _drop_column(text: str, name: str) -> str:
    rows = [line.split(",") for line in text.splitlines()]
    j = rows[0].index(name)
    return "".join(",".join(r[:j] + r[j + 1 :]) + "\n" for r in rows)


def _scaled(text: str, columns, factor) -> str:
    lines = text.splitlines(keepends=True)
    header = lines[0].rstrip("\n").split(",")
    idx = [header.index(c) for c in columns]
    for k in range(1, len(lines)):
        cells = lines[k].rstrip("\n").split(",")
        for j in idx:
            cells[j] = repr(float(cells[j]) * factor)
        lines[k] = ",".join(cells) + "\n"
    return "".join(lines)


def _model(p, edit) -> str:
    spec = arm_to_dict(p.arm, exact=True)
    edit(spec)
    return tomli_w.dumps(spec)


def _cables(spec):
    spec["modules"][0]["cables"] = [
        {"base": [60.0 * np.cos(a), 60.0 * np.sin(a), 0.0], "platform": [20.0, 0.0, 30.0]}
        for a in (0.0, 2.1, 4.2)
    ]


def _left_handed(spec):
    spec["frames"][3]["matrix"][2][2] = -1.0


def _skewed(spec):
    spec["frames"][1]["matrix"][0][1] = 0.02


XYZ = ("measured.x", "measured.y", "measured.z")
RV = ("measured.rx", "measured.ry", "measured.rz")
QUAT = ("measured.qw", "measured.qx", "measured.qy", "measured.qz")


def _quaternion_text(_rotvec_text: str) -> str:
    """The same poses with unit quaternions (w, x, y, z) instead of rotation vectors."""
    p = problem(0)
    return dumps_measurements(Measurements.from_arrays(p.arm, p.q, p.T, orientation="quaternion"))


def _scaled_row(text: str, row: int, columns, factor) -> str:
    lines = text.splitlines(keepends=True)
    header = lines[0].rstrip("\n").split(",")
    cells = lines[row].rstrip("\n").split(",")
    for c in columns:
        cells[header.index(c)] = repr(float(cells[header.index(c)]) * factor)
    lines[row] = ",".join(cells) + "\n"
    return "".join(lines)


def _scalar_last(text: str) -> str:
    """Quaternion columns holding (x, y, z, w) under the header (w, x, y, z)."""
    lines = text.splitlines(keepends=True)
    header = lines[0].rstrip("\n").split(",")
    j = [header.index(c) for c in QUAT]
    for k in range(1, len(lines)):
        cells = lines[k].rstrip("\n").split(",")
        w, x, y, z = (cells[i] for i in j)
        for i, v in zip(j, (x, y, z, w), strict=True):
            cells[i] = v
        lines[k] = ",".join(cells) + "\n"
    return "".join(lines)


# name -> (csv edit | None, model edit | None, extra argv, expected parts of the error line)
FAILURES = {
    "missing header row": (
        lambda t: "".join(t.splitlines(keepends=True)[1:]),
        None,
        [],
        ["data.csv, line 1", "missing header row"],
    ),
    "unknown column": (
        lambda t: _add_column(t, "humidity", "0.4"),
        None,
        [],
        ["data.csv, line 1 (header row), column 'humidity'", "unknown column", "expected"],
    ),
    "missing column": (
        lambda t: _drop_column(t, "measured.z"),
        None,
        [],
        ["data.csv, line 1 (header row), column 'measured.z'", "missing column measured.z"],
    ),
    "extra field (unquoted comma)": (
        lambda t: _csv_edit(t, 3, "elbow.q", "1,2"),
        None,
        [],
        ["data.csv, line 4", "expected 14 fields"],
    ),
    "text in a number cell": (
        lambda t: _csv_edit(t, 3, "elbow.q", "abc"),
        None,
        [],
        ["data.csv, line 4, column 'elbow.q'", "not a number: 'abc'"],
    ),
    "duplicated pose id": (
        lambda t: _csv_edit(t, 5, "pose", "p02"),
        None,
        [],
        ["data.csv, line 6, column 'pose'", "duplicate pose identifier 'p02'", "line 3"],
    ),
    "NaN": (
        lambda t: _csv_edit(t, 2, "wrist.ry", "NaN"),
        None,
        [],
        ["data.csv, line 3, column 'wrist.ry'", "NaN and inf are not allowed"],
    ),
    "inf": (
        lambda t: _csv_edit(t, 7, "measured.y", "inf"),
        None,
        [],
        ["data.csv, line 8, column 'measured.y'", "not a finite number"],
    ),
    "unknown module": (
        lambda t: t.replace("elbow.q", "knee.q", 1),
        None,
        [],
        ["column 'knee.q'", "unknown module 'knee'", "shoulder, elbow, wrist"],
    ),
    "wrong cable count": (
        lambda t: t.replace(
            "shoulder.rx,shoulder.ry,shoulder.rz", "shoulder.l1,shoulder.l2,shoulder.l4", 1
        ),
        _cables,
        [],
        ["column 'shoulder.l4'", "has 3 cables in the model, so shoulder.l4 does not exist"],
    ),
    "model missing a frame": (
        None,
        lambda s: s["frames"].pop(2),
        [],
        ["arm.toml: top level", "3 modules need 4 [[frames]]", "got 3"],
    ),
    "left-handed model frame": (
        None,
        _left_handed,
        [],
        ["arm.toml: frames[3] (tool)", "reflection", "left-handed"],
    ),
    "non-orthonormal model frame": (
        None,
        _skewed,
        [],
        ["arm.toml: frames[1] (upper_arm)", "not orthonormal"],
    ),
    "positions in metres": (
        lambda t: _scaled(t, XYZ, 1e-3),
        None,
        [],
        ["data.csv, column 'measured.x'", "look like metres", "multiply by 1000?"],
    ),
    "rotation vectors in degrees": (
        lambda t: _scaled(t, RV, 180 / np.pi),
        None,
        [],
        ["data.csv, column 'measured.rx'", "look like degrees", "multiply by pi/180?"],
    ),
    "positions in centimetres": (
        lambda t: _scaled(t, XYZ, 0.1),
        None,
        [],
        ["data.csv, column 'measured.x'", "look like centimetres", "multiply by 10?"],
    ),
    "positions in inches": (
        lambda t: _scaled(t, XYZ, 1 / 25.4),
        None,
        [],
        ["column 'measured.x'", "look like inches", "multiply by 25.4?"],
    ),
    "positions in micrometres (or a model in metres)": (
        lambda t: _scaled(t, XYZ, 1e3),
        None,
        [],
        ["column 'measured.x'", "look like micrometres (or the model file is in metres)"],
    ),
    "positions off by another factor": (
        lambda t: _scaled(t, XYZ, 3.0),
        None,
        [],
        ["column 'measured.x'", "times the", "wrong units (the file must be in mm)"],
    ),
    "quaternion not unit": (
        lambda t: _scaled_row(_quaternion_text(t), 4, QUAT, 1.001),
        None,
        [],
        [
            "data.csv, line 5, column 'measured.qw': quaternion (measured.qw, .qx, .qy, .qz) = (",
            "is not unit: its norm 1.001 differs from 1 by 0.001 (tolerance 1e-06)",
        ],
    ),
    "quaternions written scalar-last": (
        lambda t: _scalar_last(_quaternion_text(t)),
        None,
        [],
        ["column 'measured.qw'", "look scalar-last (x, y, z, w)", "put the scalar part w first?"],
    ),
    "inverse rotation": (
        lambda t: _scaled(t, RV, -1.0),
        None,
        [],
        ["column 'measured.rx'", "look like the inverse rotation", "negate the rotation vector"],
    ),
    "joint angles in degrees": (
        lambda t: _scaled(t, ["elbow.q"], 180 / np.pi),
        None,
        [],
        ["column 'elbow.q'", "looks like degrees", "multiply by pi/180?"],
    ),
    "fewer than 4 poses": (
        lambda t: "".join(t.splitlines(keepends=True)[:4]),
        None,
        [],
        ["data.csv: 3 measured pose(s); the calibration needs at least 4"],
    ),
    "output exists": (None, None, ["--out", "{exists}"], ["file exists", "--force"]),
}


@pytest.mark.parametrize("case", list(FAILURES))
def test_failure_modes_give_one_error_line_and_exit_1(files, tmp_path, capsys, case):
    d, p = files
    csv_edit, model_edit, extra, expected = FAILURES[case]
    text = dumps_measurements(Measurements.from_arrays(p.arm, p.q, p.T))
    data = tmp_path / "data.csv"
    data.write_text(csv_edit(text) if csv_edit else text)
    argv = ["calibrate", "--data", data, "--out", tmp_path / "r.json"]
    if model_edit:
        (tmp_path / "arm.toml").write_text(_model(p, model_edit))
        argv += ["--model", tmp_path / "arm.toml"]
    exists = tmp_path / "exists.json"
    exists.write_text("{}")
    argv += [a.format(exists=exists) if isinstance(a, str) else a for a in extra]
    assert _run(*argv) == cli.EXIT_ERROR
    err, _ = _errors(capsys)
    assert len(err) == 1 and err[0].startswith("error: "), err
    for part in expected:
        assert part in err[0], (case, err[0])
    assert exists.read_text() == "{}" and not (tmp_path / "r.json").exists()


# --------------------------------------------------------------------------- warning rows


def _text(p, q, T) -> str:
    return dumps_measurements(Measurements.from_arrays(p.arm, q, T))


def _typo(p) -> str:
    T = p.T.copy()
    T[4, 0, 3] += 400.0  # one row's measured.x off by 400 mm
    return _text(p, p.q, T)


def _beyond_limits(p) -> str:
    from cdra_jax import tool_pose

    q, T = p.q.copy(), p.T.copy()
    lo, hi = p.arm.module("shoulder").limits[0]
    q[6, 0] = hi + 0.2 * (hi - lo)
    T[6] = np.asarray(tool_pose(p.arm.with_frames(p.actual_frames), q))[6]
    return _text(p, q, T)


def _offset(p) -> str:
    T = p.T.copy()
    T[:, 2, 3] += 300.0  # measuring device not registered to the world frame
    return _text(p, p.q, T)


def _beyond_pi(p) -> str:
    """Row 4's rotation vector as the same rotation by angle + 2 pi: a component beyond pi."""
    text = _text(p, p.q, p.T)
    header = text.splitlines()[0].split(",")
    rv = np.array([float(text.splitlines()[4].split(",")[header.index(c)]) for c in RV])
    rv = rv * (1.0 + 2.0 * np.pi / np.linalg.norm(rv))
    for c, v in zip(RV, rv, strict=True):
        text = _csv_edit(text, 4, c, repr(float(v)))
    return text


def _turned_orientations(p) -> str:
    T = p.T.copy()
    c, s = np.cos(1.0), np.sin(1.0)
    T[:, :3, :3] = T[:, :3, :3] @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return _text(p, p.q, T)


TYPO = "warning: pose 'p05' (line 6), column 'measured.x': measured position 4"
LARGE = "warning: implausibly large identified frame errors: "

# name -> (data, extra argv, exit code, expected stderr lines (prefixes))
WARNINGS = {
    "a typo, least squares": (
        _typo,
        ["--solver", "paper"],
        cli.EXIT_UNTRUSTED,  # the typo pulls the fit further from the points than nominal
        [
            TYPO,
            LARGE,
            "warning: not converged: the calibration did not converge",
            "error: untrusted result: the calibrated model is worse than the nominal one",
        ],
    ),
    "a typo, robust loss": (
        _typo,
        ["--loss", "cauchy"],
        cli.EXIT_OK,
        # the robust fit's upper_arm/forearm frames end up far off (along the unidentifiable
        # directions): the implausibility warning flags them
        # (in the nominal gauge the upper arm's error stays small: no implausibility warning)
        [TYPO, "warning: 1 pose(s) look like outliers (z > 1.93): p05 (z = "],
    ),
    "joint state outside the limits": (
        _beyond_limits,
        [],
        cli.EXIT_OK,
        [
            "warning: column 'shoulder.rx': 1 of 12 poses outside the model's limits [-1, 1] "
            "rad (first: pose 'p07' (line 8), 1.4); used as given"
        ],
    ),
    "device not registered": (
        _offset,
        ["--solver", "paper"],
        cli.EXIT_OK,
        [
            "warning: measured positions are a median 293.4 mm from the model's predictions",
            LARGE + "base (|v| = 301.5 mm",
        ],
    ),
    "rotation-vector component beyond pi": (
        _beyond_pi,
        [],
        cli.EXIT_OK,
        [
            "warning: pose 'p04' (line 5): a rotation-vector component beyond pi (measured.rx, "
            "measured.ry, measured.rz); rotation vectors are in rad, degrees?"
        ],
    ),
    "orientations far from the model's": (
        _turned_orientations,
        ["--solver", "paper"],
        cli.EXIT_OK,
        [
            "warning: measured orientations differ from the model's predictions by a median "
            "1.02 rad (more than 0.5): check the orientation convention",
            LARGE + "tool (|v| = 20.84 mm, |w| = 1.02 rad)",
        ],
    ),
}


@pytest.mark.parametrize("case", list(WARNINGS))
def test_warning_rows_give_warning_lines_and_write_the_result(files, tmp_path, capsys, case):
    _, p = files
    make, extra, code, expected = WARNINGS[case]
    data, out = tmp_path / "data.csv", tmp_path / "r.json"
    data.write_text(make(p))
    assert _run("calibrate", "--data", data, "--out", out, *extra) == code
    err, _ = _errors(capsys)
    assert len(err) == len(expected), err
    for line, prefix in zip(err, expected, strict=True):
        assert line.startswith(prefix), (case, line)
    r = json.loads(out.read_text())  # written in every case, converged or not
    assert r["converged"] is (code == cli.EXIT_OK)
    assert r["trusted"] is (code != cli.EXIT_UNTRUSTED)
    for line in err:
        if line.startswith("error: untrusted result: "):
            assert line.removeprefix("error: untrusted result: ") == r["trust"]["reason"]
        elif not line.startswith("warning: not converged"):
            assert line.removeprefix("warning: ") in r["warnings"]
