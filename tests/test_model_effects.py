"""The model file's ``[[effects]]``: read and written exactly, checked against the vocabulary,
simulated, predicted by validate, refined by calibrate, noted by export."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cdra_jax import lie
from cdra_jax.arm import EffectRecord
from cdra_jax.calibration import NoiseModel
from cdra_jax.cli import main
from cdra_jax.io import ModelFileError, dumps_model, load_model, loads_model, save_model
from cdra_jax.io.urdf import not_held
from cdra_jax.physics import effect_records, model_effects, model_tool_pose
from cdra_jax.workflows import calibrate, simulate, validate

PERIODIC = EffectRecord(
    "periodic_error", "elbow", "k=1", (("q_sin1", 0.003, "rad"), ("q_cos1", -0.002, "rad"))
)
DRIFT = EffectRecord(
    "thermal_drift",
    "base",
    "",
    tuple(
        (f"rate_{c}", v, "mm/s" if c[0] == "v" else "rad/s")
        for c, v in zip(
            ("vx", "vy", "vz", "wx", "wy", "wz"), (4e-4, -2e-4, 1e-4, 0.0, 1e-6, 0.0), strict=True
        )
    ),
)
NOISE = NoiseModel(0.01, 1e-4)
DEVICE_ROTVEC = (0.3, -0.2, 2.0)


@pytest.fixture(scope="module")
def truth():
    from cdra_jax import default_arm

    return default_arm().with_effects([PERIODIC, DRIFT])


def _model_text(arm, effects_toml: str) -> str:
    """The model file of ``arm`` without its effects, with ``effects_toml`` (top-level keys
    first, tables at the end)."""
    if effects_toml.startswith("[["):
        return dumps_model(arm.with_effects(())) + "\n" + effects_toml
    return effects_toml + dumps_model(arm.with_effects(()))


def test_effects_round_trip_exactly(truth, tmp_path):
    odd = PERIODIC.with_values([0.1 + 0.2, -1.2345678901234567e-3])
    arm = truth.with_effects([odd, DRIFT])
    for exact in (True, False):
        back = loads_model(dumps_model(arm, exact=exact))
        assert back.effects == arm.effects
    path = save_model(arm, tmp_path / "m.toml")
    assert load_model(path).effects == arm.effects
    assert 'effect = "periodic_error"' in path.read_text()
    # parameters in another order than the vocabulary's: theta follows the vocabulary
    text = _model_text(
        arm,
        '[[effects]]\neffect = "periodic_error"\nlocation = "elbow"\nvariant = "k=1"\n'
        '[effects.parameters]\nq_cos1 = { value = -0.002, unit = "rad" }\n'
        'q_sin1 = { value = 0.003, unit = "rad" }\n',
    )
    cands, theta = model_effects(loads_model(text))
    assert cands[0].label == "periodic_error@elbow"
    np.testing.assert_array_equal(theta, [0.003, -0.002])
    # a record built from a fitted candidate and values (what a refit writes)
    assert effect_records(truth, cands, [0.003, -0.002]) == (PERIODIC,)


_GOOD = '[[effects]]\neffect = "periodic_error"\nlocation = "elbow"\nvariant = "k=1"\n'


@pytest.mark.parametrize(
    ("effects", "expected"),
    [
        ("effects = 3\n", "effects: expected [[effects]] tables"),
        ('[[effects]]\nlocation = "elbow"\n', "effects[0].effect: needs 'effect'"),
        (_GOOD, "effects[0] (periodic_error@elbow).parameters: expected a table"),
        (
            _GOOD + "[effects.parameters]\nq_sin1 = 0.003\n",
            "effects[0] (periodic_error@elbow).parameters.q_sin1: expected { value",
        ),
        (
            _GOOD + '[effects.parameters]\nq_sin1 = { value = "a", unit = "rad" }\n',
            "parameters.q_sin1.value: expected a finite number",
        ),
        (
            _GOOD + "[effects.parameters]\nq_sin1 = { value = 1.0, unit = 3 }\n",
            "parameters.q_sin1.unit: expected a string",
        ),
        (
            _GOOD + 'colour = "red"\n[effects.parameters]\nq = { value = 1.0, unit = "rad" }\n',
            "unknown keys ['colour']",
        ),
    ],
)
def test_effect_file_errors_name_file_entry_and_key(truth, tmp_path, effects, expected):
    path = tmp_path / "bad.toml"
    path.write_text(_model_text(truth, effects))
    with pytest.raises(ModelFileError) as e:
        load_model(path)
    assert str(path) in str(e.value) and expected in str(e.value)


def _entry(effect="periodic_error", location="elbow", variant="k=1", params=None):
    params = params or {"q_sin1": (0.003, "rad"), "q_cos1": (-0.002, "rad")}
    text = f'[[effects]]\neffect = "{effect}"\nlocation = "{location}"\n'
    if variant:
        text += f'variant = "{variant}"\n'
    text += "[effects.parameters]\n"
    text += "".join(f'{n} = {{ value = {v}, unit = "{u}" }}\n' for n, (v, u) in params.items())
    return text


@pytest.mark.parametrize(
    ("entry", "expected"),
    [
        (_entry(effect="gear_wobble"), ["unknown effect 'gear_wobble'", "periodic_error"]),
        (_entry(variant="k=one"), ["effects[0] (periodic_error@elbow).variant", "'k=1'"]),
        (_entry(location="upper_arm"), [".location", "its locations: shoulder, elbow, wrist"]),
        (
            _entry(params={"q_sin1": (0.003, "rad"), "q_sin2": (0.0, "rad")}),
            ["unknown parameter(s) ['q_sin2']", "missing parameter(s) ['q_cos1']", "q_cos1 [rad]"],
        ),
        (
            _entry(params={"q_sin1": (0.003, "deg"), "q_cos1": (0.0, "rad")}),
            ["parameters.q_sin1.unit: expected 'rad', got 'deg'"],
        ),
    ],
)
def test_effects_checked_against_the_vocabulary_by_every_command(truth, tmp_path, entry, expected):
    path = tmp_path / "bad.toml"
    path.write_text(_model_text(truth, entry))
    load_model(path)  # the structure is fine; the vocabulary is checked by the commands
    for run in (
        lambda: validate(path, "unused.csv"),
        lambda: simulate(path, 5),
    ):
        with pytest.raises(ValueError) as e:
            run()
        assert str(path) in str(e.value)
        for text in expected:
            assert text in str(e.value)


@pytest.fixture(scope="module")
def clean_run(truth):
    """Measurements of the model itself (no frame errors) with its effects and noise."""
    return simulate(truth, 30, seed=3, errors="zero", noise=NOISE)


def test_simulate_writes_the_effects_and_their_columns(clean_run, tmp_path):
    meas = clean_run.measurements
    assert set(meas.aux) == {"time_s"}  # the drift needs time; the periodic error nothing
    assert clean_run.truth["effects"][0]["effect"] == "periodic_error"
    paths = clean_run.save(tmp_path / "d.csv", tmp_path / "t.json")
    text = paths[-1].read_text()
    header = next(line for line in text.splitlines() if not line.startswith("#"))
    assert "time_s" in header.split(",")
    assert "simulated with the model's effects: periodic_error@elbow (k=1)" in text
    assert json.loads(paths[0].read_text())["effects"][1]["effect"] == "thermal_drift"


def test_validate_with_the_effects_reaches_the_noise_floor(truth, clean_run, tmp_path):
    model = save_model(truth, tmp_path / "m.toml")
    data = clean_run.save(tmp_path / "d.csv")[-1]
    v = validate(model, data, compare=truth.with_effects(()))
    d = v.to_dict()
    floor = NOISE.position_mm * np.sqrt(3)  # mean |3-D Gaussian| ~ 1.6 sigma
    assert d["position_error_mm"]["mean"] < 1.3 * floor
    assert d["compare"]["position_error_mm"]["mean"] > 10 * floor
    assert d["effects"] == ["periodic_error@elbow (k=1)", "thermal_drift@base"]
    assert "predicted with the model's effects" in v.report()
    # the same through the command line
    assert main(["validate", "--model", str(model), "--data", str(data)]) == 0


def test_effects_need_their_columns(truth, clean_run):
    meas = clean_run.measurements
    bare = type(meas).from_arrays(truth, meas.q, meas.measured)
    with pytest.raises(ValueError, match=r"thermal_drift@base: no time_s column"):
        validate(truth, bare)


@pytest.fixture(scope="module")
def calibrated(truth):
    """Noise-free data of the arm with random frame errors and its effects, in a measuring
    device's frame far from the robot's, calibrated from a model whose effect values are zero."""
    run = simulate(truth, 30, seed=5, d_w=0.01, device_frame=[1500.0, -300, 200, *DEVICE_ROTVEC])
    start = truth.with_effects([e.with_values([0.0] * len(e.parameters)) for e in truth.effects])
    return run, calibrate(start, run.measurements)


def test_calibrate_refines_the_effects_with_the_frames(truth, calibrated, tmp_path):
    run, cal = calibrated
    assert cal.converged and cal.trusted
    got = cal.calibrated_arm.effects
    np.testing.assert_allclose(got[0].values, PERIODIC.values, rtol=1e-6)
    # The drift of the mount is identified in the measuring device's frame: rotated by it.
    R = np.asarray(lie.so3_exp(np.asarray(DEVICE_ROTVEC)))
    want = np.concatenate([R @ DRIFT.values[:3], R @ DRIFT.values[3:]])
    np.testing.assert_allclose(got[1].values, want, rtol=1e-6, atol=1e-6 * np.abs(want).max())
    r = cal.to_dict()
    p = r["effect_parameters"]["periodic_error@elbow.q_sin1"]
    assert p["unit"] == "rad" and p["start"] == 0.0 and p["identifiable"]
    assert r["final"]["delta_p_mm"] < 1e-6
    assert "effects refined with the frames" in cal.report()
    assert r["registration"]["registered"] and "base frame registered" in cal.report()
    # the calibrated model file predicts the data; so does the result applied to the model
    model = cal.save_model(tmp_path / "cal.toml")
    assert load_model(model).effects == got
    v = validate(model, run.measurements)
    assert v.to_dict()["position_error_mm"]["max"] < 1e-6
    path = cal.save(tmp_path / "r.json")
    v = validate(cal.arm, run.measurements, result=path)
    assert v.to_dict()["position_error_mm"]["max"] < 1e-6
    assert v.to_dict()["nominal"]["position_error_mm"]["mean"] > 0.1


def test_calibrate_with_effects_from_points(truth):
    """A laser tracker's points (the tool origin, some rows occluded) refine the effects too;
    the tool frame's rotation, which points at the origin do not see, stays in the gauge."""
    run = simulate(truth, 30, seed=4, d_w=0.01, points=True)
    start = truth.with_effects([e.with_values([0.0] * len(e.parameters)) for e in truth.effects])
    cal = calibrate(start, run.measurements)
    assert cal.converged and cal.trusted
    for want, have in zip(truth.effects, cal.calibrated_arm.effects, strict=True):
        np.testing.assert_allclose(have.values, want.values, rtol=1e-6, atol=1e-12)
    assert cal.to_dict()["noise"]["points_mm"] is not None
    v = validate(cal.calibrated_arm, run.measurements)
    assert v.to_dict()["position_error_mm"]["max"] < 1e-6


def test_calibrate_with_effects_refuses_rough_markers_and_robust_losses(truth, clean_run):
    """A marker with calibrate = true (its points measured on the simulated tool poses) and a
    robust loss are refused for a model with effects."""
    from cdra_jax.arm import Marker
    from cdra_jax.io import Measurements

    xyz = np.array([0.0, 40.0, 20.0])
    marked = truth.with_markers([Marker("m1", tuple(xyz), calibrate=True)])
    meas = clean_run.measurements
    T = np.asarray(meas.measured)
    m1 = T[:, :3, :3] @ xyz + T[:, :3, 3]
    pts = Measurements.from_arrays(marked, meas.q, None, aux=meas.aux, points={"m1": m1})
    with pytest.raises(ValueError, match=r"markers m1 have calibrate = true"):
        calibrate(marked, pts)
    with pytest.raises(ValueError, match=r"robust losses"):
        calibrate(truth, meas, loss="huber")


def test_model_tool_pose_without_effects_is_the_chain(truth, clean_run):
    from cdra_jax.arm import tool_pose

    arm = truth.with_effects(())
    q = clean_run.measurements.q  # 30 sampled feasible poses
    # To rounding, not bitwise: the two are separate programs, and how XLA fuses them (its
    # optimisation level, the device) decides the last bit (1 ulp of a 93 mm entry at O1-O3).
    np.testing.assert_allclose(
        np.asarray(model_tool_pose(arm, q)), np.asarray(tool_pose(arm, q)), rtol=1e-14, atol=1e-12
    )


def test_export_notes_the_effects(truth):
    notes = not_held(truth)
    assert any("periodic_error@elbow (k=1)" in n and "q_sin1 = 0.003 rad" in n for n in notes)
    assert any("thermal_drift@base" in n for n in notes)


def test_sweep_refuses_and_plan_poses_notes_the_effects(truth):
    from cdra_jax.workflows import plan_poses, sweep

    with pytest.raises(ValueError, match=r"the sweep simulates and calibrates the fixed frames"):
        sweep(truth, [0.01], [1e-4], [10], trials=2)
    plan = plan_poses(truth, 6, pool=12)
    assert "the model's effects (periodic_error@elbow (k=1), thermal_drift@base)" in plan.report()
    assert any("record also the columns the effects need: time_s" in c for c in plan.comments())


def test_variants_beyond_the_vocabulary_list(truth):
    two = EffectRecord(
        "periodic_error",
        "elbow",
        "k=1,2",
        tuple((f"q_{f}{k}", 0.0, "rad") for k in (1, 2) for f in ("sin", "cos")),
    )
    cands, theta = model_effects(truth.with_effects([two]))
    assert cands[0].effect.harmonics == (1, 2) and theta.shape == (4,)
    # the same variant gives the same effect object (candidates compare by identity)
    assert model_effects(truth.with_effects([two]))[0] == cands
    with pytest.raises(ValueError, match=r"or any 'k=<k>\[,<k>...\]'"):
        model_effects(truth.with_effects([EffectRecord("periodic_error", "elbow", "k=0")]))


def test_a_load_dependent_effect_is_refined_in_the_gauge(truth):
    """A gravity-load effect depends (weakly) on the frames, also along the directions that the
    tool poses do not determine; the refit keeps the start along them (the gauge), so the
    noise-free recovery is to the small coupling (~1e-5 relative), and it converges."""
    rec = EffectRecord("joint_compliance", "shoulder", "", (("compliance", 2e-6, "rad/(N*mm)"),))
    model = truth.with_effects([rec])
    run = simulate(model, 30, seed=2, d_w=0.01)
    cal = calibrate(model.with_effects([rec.with_values([0.0])]), run.measurements)
    assert cal.converged and cal.trusted
    np.testing.assert_allclose(cal.calibrated_arm.effects[0].values, [2e-6], rtol=1e-3)
    r = cal.to_dict()
    assert r["identifiability"]["rank"] == 22 and r["final"]["rank"] == 23
