"""Result JSON: structure, iteration indexing, exact round trip, no-clobber writes, bad files."""

from __future__ import annotations

import json
import os

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cdra_jax import RESULTS, CalibrationSolution, NoiseModel, apply_frame_errors, tool_pose
from cdra_jax.io import (
    OutputExistsError,
    ResultFileError,
    calibrated_arm_from_result,
    dumps_result,
    load_result,
    loads_result,
    result_frames,
    result_to_dict,
    save_result,
)

NAN = float("nan")


@pytest.fixture(scope="module")
def problem(cdra):
    """Preset errors X, states q and exact 'measured' poses of the erroneous arm (m = 6)."""
    rng = np.random.default_rng(7)
    X = rng.uniform(-1, 1, (4, 6)) * np.array([1.0] * 3 + [0.05] * 3)
    lim = cdra.state_limits
    q = lim[:, 0] + rng.uniform(size=(6, 7)) * (lim[:, 1] - lim[:, 0])
    actual = apply_frame_errors(cdra, X)
    measured = np.asarray(eqx.filter_jit(tool_pose)(actual, q))
    return X, q, actual, measured


def _solution(actual, X, *, result=RESULTS.successful, iterations=3, bad=False):
    """A solution with a known history: 3 steps of a 5-step budget (NaN past the end)."""
    steps = jnp.array([1.5, 0.25, 1e-11, NAN, NAN])
    dp = jnp.array([40.0, 2.0, 0.01, 1e-13, NAN, NAN])
    dR = jnp.array([0.08, 0.004, 2e-5, 3e-16, NAN, NAN])
    if bad:
        dp = dp.at[3].set(NAN)
    return CalibrationSolution(
        frames=actual.frames,
        errors=jnp.asarray(X),
        result=result,
        iterations=jnp.asarray(iterations),
        step_norm=steps,
        delta_p=dp,
        delta_R=dR,
        rank=jnp.asarray(22),
        singular_values=jnp.linspace(24.0, 1.0, 24),
        cost=jnp.asarray(1e-20),
        solver="paper",
    )


@pytest.fixture(scope="module")
def result(cdra, problem):
    X, q, actual, measured = problem
    return result_to_dict(
        cdra,
        _solution(actual, X),
        q,
        measured,
        pose_ids=[f"a{i}" for i in range(6)],
        inputs={"model": "m.toml", "data": "d.csv"},
    )


def test_structure_and_iteration_indexing(result):
    r = result
    assert r["format"] == "cdra_jax.calibration_result" and r["format_version"] == 1
    assert isinstance(r["cdra_jax_version"], str) and r["cdra_jax_version"]
    assert r["solver"] == "paper" and r["converged"] is True and r["result"] == "successful"
    assert r["message"] == "" and r["noise"] is None and r["n_poses"] == 6
    assert r["inputs"] == {"model": "m.toml", "data": "d.csv"}
    assert r["initial"] == {"delta_p_mm": 40.0, "delta_R_rad": 0.08}
    # iterations[k-1]: the norm of step k and the metrics after it (not before it)
    assert r["iterations"] == [
        {"iteration": 1, "step_norm": 1.5, "delta_p_mm": 2.0, "delta_R_rad": 0.004},
        {"iteration": 2, "step_norm": 0.25, "delta_p_mm": 0.01, "delta_R_rad": 2e-5},
        {"iteration": 3, "step_norm": 1e-11, "delta_p_mm": 1e-13, "delta_R_rad": 3e-16},
    ]
    assert r["final"]["delta_p_mm"] == 1e-13 and r["final"]["rank"] == 22
    assert len(r["final"]["singular_values"]) == 24


def test_frames_hold_nominal_calibrated_and_named_error_twists(cdra, problem, result):
    X, _, actual, _ = problem
    assert list(result["frames"]) == ["base", "upper_arm", "forearm", "tool"]
    for j, name in enumerate(cdra.frame_names):
        f = result["frames"][name]
        assert f["error_twist"] == dict(
            zip(("vx", "vy", "vz", "wx", "wy", "wz"), X[j], strict=True)
        )
        for key, T in (("nominal", cdra.frames[j]), ("calibrated", actual.frames[j])):
            T = np.asarray(T)
            np.testing.assert_array_equal(f[key]["matrix"], T)  # bit for bit
            np.testing.assert_allclose(f[key]["xyz"], T[:3, 3], rtol=0, atol=0)
            R = Rotation.from_rotvec(f[key]["rotvec"]).as_matrix()
            np.testing.assert_allclose(R, T[:3, :3], atol=1e-15)


def test_identifiability_and_residuals(result):
    ident = result["identifiability"]
    assert ident["rank"] == 22 and ident["n_params"] == 24 and ident["n_poses"] == 6
    assert len(ident["unidentifiable"]) == 2
    for text in ident["unidentifiable"]:
        assert "upper_arm." in text and "forearm." in text
    res = result["residuals"]
    assert [p["pose"] for p in res] == [f"a{i}" for i in range(6)]
    # calibrated = actual frames, so the calibrated model reproduces the 'measurements'
    assert max(p["calibrated_position_mm"] for p in res) < 1e-9
    assert max(p["calibrated_rotation_rad"] for p in res) < 1e-12
    assert min(p["nominal_position_mm"] for p in res) > 0.1


def test_nominal_residual_matches_an_independent_computation(cdra, problem, result):
    _, q, _, measured = problem
    T0 = np.asarray(eqx.filter_jit(tool_pose)(cdra, q))
    dpos = np.linalg.norm(measured[:, :3, 3] - T0[:, :3, 3], axis=1)
    ang = Rotation.from_matrix(np.swapaxes(measured[:, :3, :3], 1, 2) @ T0[:, :3, :3]).magnitude()
    got = result["residuals"]
    np.testing.assert_allclose([p["nominal_position_mm"] for p in got], dpos, rtol=1e-12)
    np.testing.assert_allclose([p["nominal_rotation_rad"] for p in got], ang, rtol=1e-9)


def test_save_load_round_trip_is_exact(cdra, problem, result, tmp_path):
    _, _, actual, _ = problem
    path = save_result(result, tmp_path / "r.json")
    back = load_result(path)
    assert back == json.loads(json.dumps(result))
    arm = calibrated_arm_from_result(back, cdra)
    np.testing.assert_array_equal(np.asarray(arm.frames), np.asarray(actual.frames))
    nominal = result_frames(back, "nominal")
    np.testing.assert_array_equal(nominal["tool"], np.asarray(cdra.frames[3]))


def test_refuses_to_overwrite_without_force(result, tmp_path):
    path = tmp_path / "r.json"
    path.write_text("keep me")
    with pytest.raises(OutputExistsError, match=r"r\.json: file exists.*force"):
        save_result(result, path)
    assert path.read_text() == "keep me"
    save_result(result, path, force=True)
    assert load_result(path)["solver"] == "paper"
    assert os.listdir(tmp_path) == ["r.json"]


def test_failed_solve_writes_nulls_not_nan(cdra, problem):
    X, q, actual, measured = problem
    sol = _solution(actual, X, result=RESULTS.nonfinite, bad=True)
    r = result_to_dict(cdra, sol, q, measured, noise=NoiseModel(0.08, 0.001))
    assert r["converged"] is False and r["result"] == "nonfinite"
    assert "non-finite" in r["message"]
    assert r["iterations"][2]["delta_p_mm"] is None and r["final"]["delta_p_mm"] is None
    assert r["noise"] == {"position_mm": 0.08, "rotation_rad": 0.001}
    text = dumps_result(r)
    assert ": NaN" not in text and "Infinity" not in text
    assert loads_result(text)["iterations"][2]["delta_p_mm"] is None


def test_batched_solution_is_refused(cdra, problem):
    X, q, actual, measured = problem
    sol = _solution(actual, X)
    batched = eqx.tree_at(lambda s: s.iterations, sol, jnp.array([3, 3]))
    with pytest.raises(ValueError, match="takes one calibration"):
        result_to_dict(cdra, batched, q, measured)


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        (lambda t: t[:-10], "not valid JSON (line"),
        (lambda t: t.replace('"frames"', '"framez"'), "missing key 'frames'"),
        (lambda t: t.replace('"cdra_jax.calibration_result"', '"other"'), "format: expected"),
        (
            lambda t: json.dumps(_drop(json.loads(t), "frames", "tool", "error_twist")),
            "frames.tool: missing key 'error_twist'",
        ),
        (
            lambda t: json.dumps(_set(json.loads(t), [[1.0, 0.0]], "frames", "base", "calibrated")),
            "frames.base.calibrated.matrix: expected 4 rows of 4",
        ),
        (
            lambda t: json.dumps(_drop(json.loads(t), "identifiability", "rank")),
            "identifiability: missing key 'rank'",
        ),
        (  # hypothesis found this one: a TypeError before
            lambda t: json.dumps({**json.loads(t), "identifiability": None}),
            "identifiability: expected an object",
        ),
    ],
)
def test_malformed_result_file_errors_name_file_and_key(result, tmp_path, edit, expected):
    path = tmp_path / "bad.json"
    path.write_text(edit(dumps_result(result)))
    with pytest.raises(ResultFileError) as info:
        load_result(path)
    assert str(info.value).startswith(str(path)) and expected in str(info.value)


def _drop(d, *keys):
    node = d
    for k in keys[:-1]:
        node = node[k]
    del node[keys[-1]]
    return d


def _set(d, matrix, *keys):
    node = d
    for k in keys:
        node = node[k]
    node["matrix"] = matrix
    return d


def test_json_text_puts_number_lists_on_one_line_and_reads_back_exactly():
    from cdra_jax.io.files import json_text

    doc = {
        "m": np.eye(4).tolist(),
        "many": [[0.1 * i, None] for i in range(12)],  # >10 leaves: token1 vs token10
        "names": ["a", "b"],
        "x": 1 / 3,
    }
    text = json_text(doc)
    assert json.loads(text) == doc
    assert "\n    [1.0, 0.0, 0.0, 0.0],\n" in text
    assert '"names": [\n' in text  # only lists of numbers are compacted
    with pytest.raises(ValueError):
        json_text({"bad": [float("nan")]})
