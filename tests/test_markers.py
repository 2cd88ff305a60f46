"""Points and markers: the model and CSV contracts, the auto solver, registration, the gauge,
validate on points, and the command line end to end."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

from cdra_jax import cli, lie, workflows
from cdra_jax.arm import Marker, apply_frame_errors, sample_states, tool_pose
from cdra_jax.calibration import (
    NoiseModel,
    calibrate_auto,
    calibrate_lm,
    calibrate_paper,
    make_observations,
    rigid_registration,
    to_nominal_gauge,
)
from cdra_jax.compilation import cached_filter_jit
from cdra_jax.io import (
    MeasurementFileError,
    Measurements,
    ModelFileError,
    default_arm,
    default_model_text,
    dumps_measurements,
    dumps_model,
    loads_measurements,
    loads_model,
    save_measurements,
    save_model,
)

MARKERS = (
    Marker("a", (0.0, 40.0, 25.0), True),
    Marker("b", (30.0, -20.0, 10.0), True),
    Marker("c", (-25.0, -20.0, 40.0), False),
)
TRUE_XYZ = np.array([[20.0, 60.0, 5.0], [50.0, -40.0, 30.0], [-25.0, -20.0, 40.0]])
"""True marker positions: the two calibrated ones 20 mm per component from the model's."""
DEVICE = np.asarray(lie.from_xyz_rotvec(np.array([400.0, 0.0, 0.0]), np.array([0, 0, np.pi / 2])))
"""The robot world frame in the measuring device's frame: 0.4 m and 90 degrees away."""
M_POINTS = 30
"""Rows of every marker data set (the auto solver, validate, the command line): one shape, so
that the tests share the compiled programs."""
M_POSES = 8
"""Full poses of the solver comparisons (few: the guard test needs an unweighted fit that ends
worse than nominal): one shape for the paper, LM and auto solvers."""
M_HELD_OUT = 40
"""Held-out states on which a calibration's predictions are compared with the truth."""


@pytest.fixture(scope="module")
def arm():
    return default_arm().with_markers(MARKERS)


@pytest.fixture(scope="module")
def truth(arm):
    rng = np.random.default_rng(0)
    err = np.concatenate([rng.uniform(-1, 1, (4, 3)), rng.uniform(-0.05, 0.05, (4, 3))], 1)
    actual = apply_frame_errors(arm, err)
    frames = np.asarray(actual.frames).copy()
    frames[0] = DEVICE @ frames[0]
    return actual.with_frames(frames)


def _points(truth, m, key, noise=0.0, occlusion=0.2, seed=1):
    q = np.asarray(sample_states(jax.random.PRNGKey(key), truth, m))
    T = np.asarray(tool_pose(truth, q))
    pts = np.einsum("mij,pj->mpi", T[:, :3, :3], TRUE_XYZ) + T[:, None, :3, 3]
    rng = np.random.default_rng(seed)
    pts = pts + noise * rng.standard_normal(pts.shape)
    hidden = rng.uniform(size=(m, 3)) < occlusion
    hidden[:, 2] = False  # every row sees one marker
    pts[hidden] = np.nan
    return q, T, pts


def _held_out_error(truth, cal_frames, cal_xyz, m=M_HELD_OUT):
    q = np.asarray(sample_states(jax.random.PRNGKey(99), truth, m))
    Tt = np.asarray(tool_pose(truth, q))
    Tc = np.asarray(tool_pose(truth.with_frames(cal_frames), q))
    pt = np.einsum("mij,pj->mpi", Tt[:, :3, :3], TRUE_XYZ) + Tt[:, None, :3, 3]
    pc = np.einsum("mij,pj->mpi", Tc[:, :3, :3], cal_xyz) + Tc[:, None, :3, 3]
    return float(np.abs(pt - pc).max())


# --------------------------------------------------------------------------- contracts


def test_markers_round_trip_through_the_model_file(arm, tmp_path):
    text = dumps_model(arm)
    back = loads_model(text)
    assert back.markers == arm.markers
    path = save_model(arm, tmp_path / "m.toml")
    assert loads_model(path.read_text()).markers == MARKERS


@pytest.mark.parametrize(
    ("entry", "expected"),
    [
        ('name = "a"', "markers[0] (a): needs 'xyz'"),
        ('name = "a"\nxyz = [1, 2]', "markers[0] (a).xyz"),
        ('name = "a"\nxyz = [1, 2, "x"]', "markers[0] (a).xyz"),
        ('name = "a"\nxyz = [1, 2, 3]\ncalibrate = "yes"', "markers[0] (a).calibrate"),
        ('name = "a.b"\nxyz = [1, 2, 3]', "cannot contain '.'"),
        ('name = "origin"\nxyz = [1, 2, 3]', "rename the marker"),
        ('name = "a"\nxyz = [1, 2, 3]\nsize = 3', "unknown keys ['size']"),
    ],
)
def test_bad_markers_name_the_file_and_the_entry(entry, expected):
    text = default_model_text() + "\n[[markers]]\n" + entry + "\n"
    with pytest.raises(ModelFileError) as info:
        loads_model(text, source="arm.toml")
    assert str(info.value).startswith("arm.toml: ") and expected in str(info.value)


def test_twice_the_same_marker_is_refused():
    text = default_model_text() + '\n[[markers]]\nname = "a"\nxyz = [1, 2, 3]\n' * 2
    with pytest.raises(ModelFileError, match="used twice"):
        loads_model(text, source="arm.toml")


def _header(arm, extra):
    return ",".join(["pose", *arm.state_names, *extra])


STATES = "0.1,0.2,-0.1,1.2,0.0,0.1,-0.1"
A_COLS = ["measured.a.x", "measured.a.y", "measured.a.z"]
Q_COLS = ["measured.q.x", "measured.q.y", "measured.q.z"]
POSE_COLS = [f"measured.{c}" for c in ("x", "y", "z", "rx", "ry", "rz")]


def test_points_occlusions_and_mixed_rows_parse_and_round_trip(arm):
    cols = [*(f"measured.{c}" for c in ("x", "y", "z", "rx", "ry", "rz"))]
    cols += [f"measured.{n}.{c}" for n in ("a", "b") for c in "xyz"]
    text = "\n".join(
        [
            _header(arm, cols),
            f"p1,{STATES},1,2,3,0.1,0,0,,,,4,5,6",  # full pose, b seen, a hidden
            f"p2,{STATES},7,8,9,,,,1,1,1,,,",  # tool origin and a
            f"p3,{STATES},,,,,,,1,1,1,,,",  # a only
        ]
    )
    meas = loads_measurements(text + "\n", arm, source="d.csv")
    assert meas.measured is None and meas.point_names == ("origin", "a", "b")
    assert list(meas.pose_rows) == [True, False, False]
    np.testing.assert_array_equal(meas.points[1, 0], [7, 8, 9])
    assert np.isnan(meas.points[0, 0]).all()  # a full pose's origin is in the pose residual
    assert np.isnan(meas.points[0, 1]).all() and np.isnan(meas.points[2, 2]).all()
    back = loads_measurements(dumps_measurements(meas), arm)
    np.testing.assert_array_equal(np.isnan(back.points), np.isnan(meas.points))
    np.testing.assert_array_equal(np.nan_to_num(back.points), np.nan_to_num(meas.points))
    np.testing.assert_allclose(back.full_poses[0], meas.full_poses[0])


@pytest.mark.parametrize(
    ("header", "row", "expected"),
    [
        (A_COLS, "1,,3", "line 2, column 'measured.a.y': empty cell"),
        (A_COLS, ",,", "line 2, column 'measured.a.x': the row measures nothing"),
        (Q_COLS, "1,2,3", "column 'measured.q.x': unknown column"),
        (A_COLS[:2], "1,2", "column 'measured.a.z': missing column measured.a.z"),
        (POSE_COLS, ",,,0.1,0,0", "line 2, column 'measured.x': a measured orientation needs"),
        (A_COLS, "1,x,3", "line 2, column 'measured.a.y': not a number"),
    ],
)
def test_bad_point_cells_name_file_line_and_column(arm, header, row, expected):
    text = _header(arm, header) + f"\np1,{STATES},{row}\n"
    with pytest.raises(MeasurementFileError) as info:
        loads_measurements(text, arm, source="d.csv")
    assert str(info.value).startswith("d.csv, ") and expected in str(info.value), info.value


def test_marker_columns_without_markers_in_the_model_say_where_to_declare_them():
    arm = default_arm()
    text = _header(arm, ["measured.a.x", "measured.a.y", "measured.a.z"]) + f"\np,{STATES},1,2,3\n"
    with pytest.raises(MeasurementFileError, match=r"\[\[markers\]\]"):
        loads_measurements(text, arm, source="d.csv")


# --------------------------------------------------------------------------- registration


def test_rigid_registration_recovers_a_rigid_motion_and_refuses_a_line():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(20, 3)) * 100
    R = np.asarray(lie.so3_exp(np.array([0.3, -2.0, 1.0])))
    dst = src @ R.T + np.array([400.0, -5.0, 30.0])
    R_hat, t_hat = rigid_registration(src, dst)
    np.testing.assert_allclose(R_hat, R, atol=1e-12)
    np.testing.assert_allclose(t_hat, [400.0, -5.0, 30.0], atol=1e-9)
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="one line"):
        rigid_registration(line, line)


# --------------------------------------------------------------------------- auto solver


def test_markers_with_occlusions_recover_the_arm_from_a_far_device_frame(arm, truth):
    # Noise-free, base 0.4 m / 90 degrees off, two markers 20 mm off per component: every
    # prediction exact.
    q, _, pts = _points(truth, M_POINTS, key=1)
    sol = calibrate_auto(arm, q, None, pts, ("a", "b", "c"))
    assert sol.converged and sol.start.registered and sol.start.placed == (0, 1)
    assert _held_out_error(truth, sol.frames, sol.xyz) < 1e-6
    assert sol.gauge_reference in ("nominal", "start")
    assert not np.any(sol.z_points > sol.outlier_threshold)


def test_tool_positions_only_recover_what_points_can_see(truth):
    # A laser tracker at the tool point: 3 residuals per row; the tool's orientation is not
    # identifiable and is kept at nominal, positions are predicted exactly.
    arm = default_arm()
    q = np.asarray(sample_states(jax.random.PRNGKey(5), arm, M_POINTS))
    T = np.asarray(tool_pose(truth, q))
    sol = calibrate_auto(arm, q, None, T[:, None, :3, 3], ("origin",))
    assert sol.converged
    q2 = np.asarray(sample_states(jax.random.PRNGKey(6), arm, M_HELD_OUT))
    p_true = np.asarray(tool_pose(truth, q2))[:, :3, 3]
    p_cal = np.asarray(tool_pose(arm.with_frames(sol.frames), q2))[:, :3, 3]
    assert np.abs(p_true - p_cal).max() < 1e-6
    assert sol.rank == 24 - 2 - 3  # the CDRA's two, and the tool frame's rotation


def test_noise_scales_are_estimated_and_clean_data_are_not_flagged(arm, truth):
    q, _, pts = _points(truth, M_POINTS, key=2, noise=0.05, seed=4)
    sol = calibrate_auto(arm, q, None, pts, ("a", "b", "c"))
    assert sol.converged and sol.noise_source == "estimated"
    np.testing.assert_allclose(sol.sigma_points_mm, 0.05, rtol=0.2)
    assert not np.any(sol.z_points > sol.outlier_threshold)
    assert _held_out_error(truth, sol.frames, sol.xyz) < 0.1


def test_a_gross_point_error_is_flagged_and_down_weighted(arm, truth):
    q, _, pts = _points(truth, M_POINTS, key=3, noise=0.05, seed=5)
    row = int(np.flatnonzero(np.isfinite(pts[:, 2, 0]))[0])
    pts[row, 2] += [30.0, 0.0, 0.0]
    sol = calibrate_auto(arm, q, None, pts, ("a", "b", "c"))
    assert sol.z_points[row, 2] > sol.outlier_threshold
    assert sol.weights_points[row, 2] < 0.05
    assert _held_out_error(truth, sol.frames, sol.xyz) < 0.15


# --------------------------------------------------------------------------- one gauge


@pytest.mark.slow
def test_every_solver_returns_the_same_frames_in_the_nominal_gauge():
    arm = default_arm()
    rng = np.random.default_rng(3)
    err = np.concatenate([rng.uniform(-1, 1, (4, 3)), rng.uniform(-0.05, 0.05, (4, 3))], 1)
    true = apply_frame_errors(arm, err)
    q = np.asarray(sample_states(jax.random.PRNGKey(1), arm, M_POSES))
    T = np.asarray(tool_pose(true, q))
    obs = make_observations(arm, q, T, None)
    none = np.zeros((0, 3))
    nominal = np.asarray(arm.frames)
    frames = {}
    # The paper solver compiled as the workflow below compiles it (one program for both).
    paper = cached_filter_jit(calibrate_paper)(arm, q, T, None, throw=False, singular_values=True)
    assert paper.converged, paper.result
    for name, sol in (("paper", paper), ("lm", calibrate_lm(arm, q, T))):
        g = to_nominal_gauge(np.asarray(sol.frames), none, nominal, none, obs)
        assert g.exact
        frames[name] = g.frames
    frames["auto"] = calibrate_auto(arm, q, T).frames
    # without the gauge the paper solver's minimum-norm steps drift along the elbow directions
    assert np.abs(np.asarray(paper.frames) - frames["lm"]).max() > 1e-4
    for name in ("paper", "auto"):
        np.testing.assert_allclose(frames[name], frames["lm"], atol=1e-9)
    # ... and through the workflow: the same identified errors
    meas = Measurements.from_arrays(arm, q, T)
    twists = [workflows.calibrate(arm, meas, solver=s).result["frames"] for s in ("paper", "auto")]
    for other in twists[1:]:
        for f in arm.frame_names:
            a, b = twists[0][f]["error_twist"], other[f]["error_twist"]
            assert max(abs(a[c] - b[c]) for c in a) < 1e-8


# --------------------------------------------------------------------------- workflows, CLI


def test_validate_on_points_equals_an_independent_computation(arm, truth):
    q, _, pts = _points(truth, M_POINTS, key=7, noise=0.0)
    meas = Measurements.from_arrays(arm, q, points={"a": pts[:, 0], "b": pts[:, 1], "c": pts[:, 2]})
    v = workflows.validate(arm, meas)
    T = np.asarray(tool_pose(arm, q))
    model = np.einsum("mij,pj->mpi", T[:, :3, :3], np.array([m.xyz for m in MARKERS]))
    model = model + T[:, None, :3, 3]
    e = np.linalg.norm(pts - model, axis=-1)
    e = e[np.isfinite(e)]
    d = v.to_dict()["position_error_mm"]
    assert d["n"] == e.size
    np.testing.assert_allclose(
        [d["mean"], d["rms"], d["max"]], [e.mean(), np.sqrt(np.mean(e**2)), e.max()], rtol=1e-12
    )
    assert v.to_dict()["rotation_error_rad"]["n"] == 0
    assert set(v.to_dict()["rows"][0]["points"]) <= {"a", "b", "c"}


def test_cli_simulate_calibrate_model_out_validate_on_markers(arm, tmp_path, capsys):
    model = save_model(arm, tmp_path / "arm.toml")
    common = ["--model", model, "--points", "--noise-pos", "0.03", "--noise-rot", "1e-4"]
    common += ["--device-frame", "300", "-250", "100", "0", "0", "1.5708"]

    def run(*argv):
        return cli.main([str(a) for a in argv])

    fit, test, truth = tmp_path / "fit.csv", tmp_path / "test.csv", tmp_path / "truth.json"
    assert run("simulate", *common, "--poses", M_POINTS, "--seed", 1, "--occlusion", 0.2,
               "--marker-error", 20, "--out", fit, "--truth", truth) == 0  # fmt: skip
    assert run("simulate", *common, "--poses", M_POINTS, "--seed", 2, "--errors", truth,
               "--out", test) == 0  # fmt: skip
    assert set(json.loads(truth.read_text())["markers"]) == {"a", "b", "c"}
    out, cal = tmp_path / "r.json", tmp_path / "cal.toml"
    capsys.readouterr()
    assert run("calibrate", "--model", model, "--data", fit, "--out", out, "--model-out", cal) == 0
    printed = capsys.readouterr().out
    assert "solver: auto (Huber loss, estimated noise scales" in printed
    assert "base frame registered to the measuring device's frame" in printed
    r = json.loads(out.read_text())
    assert r["trusted"] and r["converged"] and r["registration"]["registered"]
    assert set(r["noise"]["points_mm"]) == {"a", "b", "c"}
    assert r["gauge"]["reference"] in ("nominal", "start")
    assert r["markers"]["c"]["calibrated"] == list(MARKERS[2].xyz)  # known: not moved
    assert not any("implausibly large" in w for w in r["warnings"])  # the base holds the device
    v = tmp_path / "v.json"
    assert run("validate", "--model", cal, "--data", test, "--compare", model, "--out", v) == 0
    held = json.loads(v.read_text())
    assert held["position_error_mm"]["mean"] < 0.1  # noise 0.03 mm per coordinate
    assert held["compare"]["position_error_mm"]["mean"] > 100  # nominal, not registered


def test_point_data_with_a_pose_solver_is_refused(arm, truth):
    q, _, pts = _points(truth, M_POINTS, key=8)
    meas = Measurements.from_arrays(arm, q, points={"a": pts[:, 0], "b": pts[:, 1], "c": pts[:, 2]})
    with pytest.raises(ValueError, match="fits full tool poses; these data measure points"):
        workflows.calibrate(arm, meas, solver="paper")


def test_the_guard_fires_when_an_unweighted_fit_is_worse_than_nominal(tmp_path):
    # Full poses whose orientations are very noisy and positions exact, few poses: the paper's
    # unweighted fit trades position for orientation and ends worse than the nominal model on
    # the measured positions; the default estimates the scales and is trusted.
    arm = default_arm()
    rng = np.random.default_rng(2)
    err = np.concatenate([rng.uniform(-0.5, 0.5, (4, 3)), rng.uniform(-0.002, 0.002, (4, 3))], 1)
    q = np.asarray(sample_states(jax.random.PRNGKey(11), arm, M_POSES))
    T = np.asarray(tool_pose(apply_frame_errors(arm, err), q)).copy()
    for k in range(len(T)):
        T[k, :3, :3] = np.asarray(lie.so3_exp(rng.normal(size=3) * 0.05)) @ T[k, :3, :3]
    path = save_measurements(Measurements.from_arrays(arm, q, T), tmp_path / "d.csv")
    paper = workflows.calibrate(None, path, solver="paper")
    assert not paper.trusted and "worse than the nominal" in paper.result["trust"]["reason"]
    assert cli.main(["calibrate", "--data", str(path), "--out", str(tmp_path / "r.json"),
                     "--solver", "paper"]) == cli.EXIT_UNTRUSTED  # fmt: skip
    assert json.loads((tmp_path / "r.json").read_text())["trusted"] is False
    assert workflows.calibrate(None, path).trusted


def test_plan_poses_for_a_model_measured_by_markers(arm):
    plan = workflows.plan_poses(arm, 6, noise=NoiseModel(0.05, 1e-3), pool=200, seed=1)
    assert plan.states.shape == (6, arm.dof)
    assert np.isfinite(plan.expected_dp_mm) and np.isnan(plan.expected_dR_rad)
    # the planned poses predict the marker positions better than the median random set
    assert plan.expected_dp_mm < np.median(plan.random_dp_mm)
    assert "(marker positions)" in plan.report()
    assert plan.to_dict()["expected_dR_rad"] is None


def test_diagnose_calibrates_rough_markers_before_it_looks_for_missing_physics(arm, truth):
    """Markers with ``calibrate = true`` placed 20 mm off, the device frame far away, clean
    noisy points: the geometric fit registers the frame and places the markers (their
    coordinates are parameters of the fit), and nothing is missing."""
    q, _, pts = _points(truth, 24, key=9, noise=0.05)
    meas = Measurements.from_arrays(arm, q, points={"a": pts[:, 0], "b": pts[:, 1], "c": pts[:, 2]})
    run = workflows.diagnose(arm, meas)
    d = run.diagnosis
    n_cal = sum(mk.calibrate for mk in arm.markers)
    assert d.details["geometric_fit"]["n_params"] == arm.n_params + 3 * n_cal
    assert d.details["geometric_fit"]["n_marker_coordinates"] == 3 * n_cal
    assert f"{3 * n_cal} marker coordinates" in d.report
    assert (d.effect, d.mismatch) == ("none", False), d.report
    assert d.heldout_before.delta_p_mm < 0.2


def test_validate_register_places_the_reference_in_the_device_frame(arm, truth):
    q, _, pts = _points(truth, M_POINTS, key=10)
    meas = Measurements.from_arrays(arm, q, points={"a": pts[:, 0], "b": pts[:, 1], "c": pts[:, 2]})
    plain = workflows.validate(truth, meas, compare=arm)
    registered = workflows.validate(truth, meas, compare=arm, register_reference=True)
    far = plain.to_dict()["compare"]["position_error_mm"]["mean"]
    near = registered.to_dict()["compare"]["position_error_mm"]["mean"]
    assert far > 300 and near < 30  # the tracker's pose, then only the frame and marker errors
    assert registered.to_dict()["position_error_mm"] == plain.to_dict()["position_error_mm"]
    assert "registered to the measuring device's frame" in registered.report()


def test_the_auto_solver_asks_for_float64(arm):
    q = np.zeros((4, arm.dof))
    with jax.enable_x64(False), pytest.raises(ValueError, match="needs float64"):
        calibrate_auto(arm, q, None, np.zeros((4, 3, 3)), ("a", "b", "c"))


def test_huber_constants_are_the_chi_square_ones():
    """The auto solver's Huber threshold and consistency factor (literal and closed form, so
    that importing the package does not load scipy.stats) against scipy."""
    import math

    import scipy.integrate
    import scipy.stats

    from cdra_jax.calibration import auto

    c = math.sqrt(float(scipy.stats.chi2.ppf(0.95, 3)))
    assert auto.UNIT_HUBER_C == pytest.approx(c, rel=1e-15)
    chi3 = scipy.stats.chi(3)
    inner = scipy.integrate.quad(lambda r: r * r * chi3.pdf(r), 0.0, c)[0]
    outer = scipy.integrate.quad(lambda r: c * r * chi3.pdf(r), c, np.inf)[0]
    assert auto.HUBER_CONSISTENCY == pytest.approx((inner + outer) / 3.0, rel=1e-12)
