"""Property tests (hypothesis): every public entry point returns finite output or raises its
documented error (a ``ValueError`` subclass naming the place) -- never NaN silently, never an
unexpected exception type.

Strategies: SE(3) elements (near the identity, generic, near and beyond pi), arms (random K,
module kinds, frames, axes, limits), measurement CSV text (random column subsets and orders,
random cells, junk lines), mutated model TOML, frame-error and result mappings, random
measured poses fed to the compiled solvers (paper, LM, robust), degenerate and non-finite pose
sets fed to the uncertainty analysis and the pose selection, random cable lengths, structure
matrices, loads and states for the CDPM modules (forward kinematics, tension closure, statics),
and noise levels, sweep tables and sweep settings. Each test reuses one compiled program (fixed
shapes; noise levels as arrays, not static floats). Set ``CDRA_FUZZ_EXAMPLES`` to run more
examples.
"""

from __future__ import annotations

import copy
import csv
import io
import json
import math
import os
import re
import tempfile

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import tomli_w
from _robust_data import M, problem
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

from cdra_jax import lie
from cdra_jax.arm import Arm, forward_kinematics, prismatic, revolute, spherical
from cdra_jax.calibration import (
    RESULTS,
    Cauchy,
    Huber,
    NoiseModel,
    calibrate_lm,
    calibrate_paper,
    calibrate_robust,
)
from cdra_jax.conditioning import conditioning
from cdra_jax.identifiability import analyze
from cdra_jax.io import (
    FrameErrorFileError,
    MeasurementFileError,
    ModelFileError,
    ResultFileError,
    arm_to_dict,
    check_plausibility,
    default_arm,
    dumps_model,
    frame_errors_from_mapping,
    loads_measurements,
    loads_model,
    loads_result,
    rigid_transform_problem,
)
from cdra_jax.modules import (
    CableFKResult,
    TensionResult,
    cable_forward_kinematics,
    cable_lengths,
    distribute_tensions,
    holding_tensions,
    hull_margin,
    tension_closure,
)
from cdra_jax.modules.statics import module_floor
from cdra_jax.pose_selection import select_from_pool
from cdra_jax.sweeps import COLUMNS as SWEEP_COLUMNS
from cdra_jax.sweeps import SweepTable, parse_noise_levels, read_sweep, run_sweep
from cdra_jax.uncertainty import analyze_uncertainty

N = int(os.environ.get("CDRA_FUZZ_EXAMPLES", "0"))


def fuzz(n: int):
    """Modest example counts (scaled up by ``CDRA_FUZZ_EXAMPLES``), no deadline; the same
    examples on every run (a CI run must not depend on chance) unless ``CDRA_FUZZ_EXAMPLES``
    asks for a search."""
    return settings(
        max_examples=max(n, N),
        deadline=None,
        derandomize=N == 0,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
    )


finite = st.floats(allow_nan=False, allow_infinity=False)


def _device(a) -> jax.Array:
    """``a`` (numbers, numpy) as a JAX array, as ``jnp.asarray`` gives it, without compiling:
    ``jnp.asarray`` of a numpy array compiles a copy program for each new shape."""
    return jax.device_put(np.array(a))


# --------------------------------------------------------------------------- SE(3)


@st.composite
def rotvecs(draw):
    v = np.array(draw(st.tuples(*[st.floats(-1.0, 1.0)] * 3)))
    assume(np.linalg.norm(v) > 1e-3)
    angle = draw(
        st.one_of(
            st.floats(0.0, 1e-7),  # near the identity
            st.floats(0.0, math.pi),
            st.floats(math.pi - 1e-6, math.pi),  # near pi
            st.just(math.pi),
            st.floats(math.pi, 3 * math.pi),  # beyond pi: another vector of the same rotation
        )
    )
    return v / np.linalg.norm(v) * angle


twists = st.builds(
    lambda w, v: np.concatenate([v, w]),
    rotvecs(),
    st.tuples(*[st.floats(-1e3, 1e3)] * 3).map(np.array),
)
BATCH = 8  # one shape: the compiled maps are reused across examples


@jax.jit
def _se3_round_trip(xi):
    T = lie.se3_exp(xi)
    log = lie.se3_log(T)
    q = lie.rotation_to_quaternion(lie.rotation(T))
    return T, log, lie.se3_exp(log), q, lie.quaternion_to_rotation(q), T @ lie.inverse(T)


@fuzz(40)
@given(st.lists(twists, min_size=BATCH, max_size=BATCH))
def test_se3_maps_are_finite_rigid_and_round_trip(xis):
    xi = np.stack(xis)
    T, log, T2, q, R2, eye = (np.asarray(a) for a in _se3_round_trip(_device(xi)))
    for a in (T, log, T2, q, R2, eye):
        assert np.all(np.isfinite(a))
    for i in range(BATCH):
        assert rigid_transform_problem(T[i], tol=1e-12) is None
    assert np.all(np.linalg.norm(log[:, 3:], axis=-1) <= math.pi + 1e-12)
    scale = 1.0 + np.abs(xi[:, :3]).max()
    np.testing.assert_allclose(T2, T, atol=1e-9 * scale)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(R2, T[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(eye, np.broadcast_to(np.eye(4), eye.shape), atol=1e-9 * scale)


@jax.jit
def _losses(z):
    return [(f.rho(z), f.influence(z), f.weight(z)) for f in (Huber(), Cauchy())]


@fuzz(25)
@given(st.lists(st.floats(-1e300, 1e300), min_size=16, max_size=16))
def test_robust_losses_are_finite_with_weights_in_0_1(zs):
    for rho, psi, w in _losses(_device(zs)):
        rho, psi, w = np.asarray(rho), np.asarray(psi), np.asarray(w)
        assert np.all(np.isfinite(rho)) and np.all(np.isfinite(psi)) and np.all(rho >= 0)
        assert np.all((w >= 0) & (w <= 1)) and np.all(w[np.abs(np.asarray(zs)) < 1e100] > 0)


# --------------------------------------------------------------------------- arms


@st.composite
def arms(draw):
    k = draw(st.integers(1, 3))
    modules = []
    for i in range(k):
        kind = draw(st.sampled_from(["spherical", "revolute", "prismatic"]))
        lo = draw(st.floats(-2.0, 1.0))
        hi = lo + draw(st.floats(0.1, 2.0))
        axis = draw(st.tuples(*[st.floats(-1.0, 1.0)] * 3))
        assume(np.linalg.norm(axis) > 1e-2)
        if kind == "spherical":
            modules.append(spherical(f"m{i}", [(lo, hi)] * 3))
        elif kind == "revolute":
            modules.append(revolute(f"m{i}", axis, (lo, hi)))
        else:
            modules.append(prismatic(f"m{i}", axis, (100 * lo, 100 * hi)))
    xis = draw(st.lists(twists, min_size=k + 1, max_size=k + 1))
    frames = np.asarray(lie.se3_exp(_device(np.stack(xis))))
    return Arm(
        frames=_device(frames),
        modules=tuple(modules),
        frame_names=tuple(f"f{j}" for j in range(k + 1)),
    )


@fuzz(6)
@given(arms(), st.integers(0, 2**31 - 1))
def test_random_arms_have_finite_kinematics_identifiability_and_round_trip(arm, seed):
    rng = np.random.default_rng(seed)
    lim = arm.state_limits
    q = lim[:, 0] + rng.uniform(size=(5, arm.dof)) * (lim[:, 1] - lim[:, 0])
    tool, after = (np.asarray(a) for a in forward_kinematics(arm, _device(q)))
    assert np.all(np.isfinite(tool)) and np.all(np.isfinite(after))
    for T in tool:
        assert rigid_transform_problem(T, tol=1e-9) is None
    rep = analyze(arm, q)
    assert 0 < rep.rank <= rep.n_params and np.all(np.isfinite(rep.singular_values))
    k = rep.n_params - rep.rank
    np.testing.assert_allclose(rep.null_space @ rep.null_space.T, np.eye(k), atol=1e-8)
    cond = conditioning(arm, q)
    assert cond.rank == rep.rank or abs(cond.rank - rep.rank) <= 1  # scaled vs raw cut-off
    assert np.isfinite(cond.condition_number) and all(cond.weak_directions)
    back = loads_model(dumps_model(arm, exact=True))
    np.testing.assert_array_equal(np.asarray(back.frames), np.asarray(arm.frames))
    assert back.state_names == arm.state_names and back.state_limits.tolist() == lim.tolist()


# --------------------------------------------------------------------------- model files


def _junk():
    return st.one_of(
        st.none(),
        st.booleans(),
        st.integers(-(10**6), 10**6),
        st.floats(allow_nan=True, allow_infinity=True),
        st.text(max_size=8),
        st.lists(st.floats(-1e3, 1e3), max_size=5),
        st.lists(st.lists(st.floats(-2.0, 2.0), min_size=4, max_size=4), min_size=3, max_size=5),
        st.dictionaries(st.text(max_size=5), st.integers(), max_size=2),
    )


def _paths(obj, prefix=()):
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, (*prefix, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _paths(v, (*prefix, i))


@st.composite
def mutated(draw, base):
    spec = copy.deepcopy(base)
    for _ in range(draw(st.integers(1, 3))):
        paths = [p for p in _paths(spec) if p]
        path = draw(st.sampled_from(paths))
        parent = spec
        for key in path[:-1]:
            parent = parent[key]
        action = draw(st.sampled_from(["delete", "replace", "add"]))
        if action == "delete":
            del parent[path[-1]]
        elif action == "replace":
            parent[path[-1]] = draw(_junk())
        elif isinstance(parent, dict):
            parent[draw(st.sampled_from(["extra", "name", "kind", "matrix", "xyz"]))] = draw(
                _junk()
            )
        else:
            parent.append(draw(_junk()))
    return spec


MODEL = arm_to_dict(default_arm())
MODEL_EXACT = arm_to_dict(default_arm(), exact=True)


def _toml(spec) -> str:
    def clean(o):  # TOML has no null: drop None entries (the mutation still counts)
        if isinstance(o, dict):
            return {str(k): clean(v) for k, v in o.items() if v is not None}
        if isinstance(o, list):
            return [clean(v) for v in o if v is not None]
        return o

    try:
        return tomli_w.dumps(clean(spec))
    except (TypeError, ValueError):
        assume(False)
        raise


@fuzz(60)
@given(st.one_of(mutated(MODEL), mutated(MODEL_EXACT)))
def test_mutated_model_files_load_or_raise_model_file_error(spec):
    text = _toml(spec)
    try:
        arm = loads_model(text, source="m.toml")
    except ModelFileError as e:
        assert str(e).startswith("m.toml: ")
        return
    frames = np.asarray(arm.frames)
    assert np.all(np.isfinite(frames)) and np.all(np.isfinite(np.asarray(arm.gravity)))
    for T in frames:
        assert rigid_transform_problem(T) is None


@fuzz(20)
@given(st.text(max_size=200))
def test_random_text_as_model_file(text):
    try:
        loads_model(text, source="m.toml")
    except ModelFileError:
        pass


# --------------------------------------------------------------------------- measurement CSV

ARM = default_arm()
COLUMNS = [
    "pose",
    *ARM.state_names,
    "measured.x",
    "measured.y",
    "measured.z",
    "measured.rx",
    "measured.ry",
    "measured.rz",
]
EXTRA = [
    "measured.qw",
    "measured.qx",
    "measured.qy",
    "measured.qz",
    "time_s",
    "approach.elbow",
    "shoulder.l1",
    "knee.q",
    "",
    " pose",
]

cells = st.one_of(
    st.floats(-1.0, 1.0).map(repr),
    st.floats(-700.0, 700.0).map(repr),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["", " ", "nan", "inf", "-inf", "1e999", "abc", "1,5", '"', "#", "p01", "1"]),
    st.text(max_size=6),
)


@st.composite
def csv_texts(draw):
    valid = draw(st.booleans())
    cols = list(COLUMNS)
    if not valid:
        cols = draw(st.lists(st.sampled_from(COLUMNS + EXTRA), min_size=1, max_size=18))
    cols = draw(st.permutations(cols))
    m = draw(st.integers(0, 4))
    rng = np.random.default_rng(draw(st.integers(0, 2**31 - 1)))
    rows = []
    for i in range(m):
        row = []
        for c in cols:
            if c == "pose":
                row.append(f"p{i}")
            elif c.startswith("measured.") and c[-1] in "xyz" and len(c) == 10:
                row.append(repr(rng.uniform(-600, 600)))
            else:
                row.append(repr(rng.uniform(-1.0, 1.0)))
        rows.append(row)
    for _ in range(draw(st.integers(0 if valid else 1, 3))):  # corrupt some cells
        if rows:
            r, j = draw(st.integers(0, m - 1)), draw(st.integers(0, len(cols) - 1))
            rows[r][j] = draw(cells)
    out = io.StringIO()
    for line in draw(st.lists(st.sampled_from(["# comment", "", "#"]), max_size=2)):
        out.write(line + "\n")
    w = csv.writer(out, lineterminator=draw(st.sampled_from(["\n", "\r\n"])))
    w.writerow(cols)
    w.writerows(rows)
    text = out.getvalue()
    if draw(st.integers(0, 4)) == 0:  # raw junk somewhere
        junk = draw(st.text(max_size=20))
        at = draw(st.integers(0, len(text)))
        text = text[:at] + junk + text[at:]
    return text


def _check_measurements(text):
    try:
        meas = loads_measurements(text, ARM, source="d.csv")
    except MeasurementFileError as e:
        assert str(e).startswith("d.csv")
        return None
    assert np.all(np.isfinite(meas.q)) and meas.q.shape == (meas.m, ARM.dof)
    assert meas.has_measurements
    if meas.full_poses is not None:
        for T in meas.full_poses[meas.pose_rows]:
            assert rigid_transform_problem(T) is None
    if meas.points is not None:
        seen = np.isfinite(meas.points)
        assert np.all(seen.all(-1) == seen.any(-1))  # a point is all given or all empty
        assert np.all(seen.any(-1).any(-1) | meas.pose_rows)  # every row measures something
    try:
        warnings = check_plausibility(ARM, meas)
    except MeasurementFileError as e:
        assert str(e).startswith("d.csv")
        return meas
    assert all(isinstance(w, str) and w for w in warnings)
    return meas


@fuzz(60)
@given(csv_texts())
def test_measurement_csv_parses_or_raises_measurement_file_error(text):
    _check_measurements(text)


@fuzz(30)
@given(st.text(max_size=300))
def test_random_text_as_measurement_file(text):
    _check_measurements(text)


# --------------------------------------------------------------------------- other files

components = st.sampled_from(["vx", "vy", "vz", "wx", "wy", "wz", "twist", "v", ""])
entries = st.one_of(
    st.dictionaries(components, st.one_of(finite, _junk()), max_size=3),
    st.lists(st.one_of(finite, _junk()), max_size=7),
    _junk(),
)


@fuzz(40)
@given(
    st.one_of(
        st.dictionaries(
            st.just("frames"),
            st.dictionaries(st.sampled_from([*ARM.frame_names, "elbow", "x"]), entries),
        ),
        _junk(),
    )
)
def test_frame_error_mappings_parse_or_raise_frame_error_file_error(spec):
    try:
        X = frame_errors_from_mapping(spec, ARM, "e.json")
    except FrameErrorFileError as e:
        assert str(e).startswith("e.json: ")
        return
    assert X.shape == (4, 6) and np.all(np.isfinite(X))


def _result() -> dict:
    frames = {
        name: {
            "nominal": {"matrix": np.asarray(F).tolist()},
            "calibrated": {"matrix": np.asarray(F).tolist()},
            "error_twist": dict.fromkeys(("vx", "vy", "vz", "wx", "wy", "wz"), 0.0),
        }
        for name, F in zip(ARM.frame_names, ARM.frames, strict=True)
    }
    return {
        "format": "cdra_jax.calibration_result",
        "solver": "paper",
        "converged": True,
        "result": "successful",
        "initial": {"delta_p_mm": 1.0, "delta_R_rad": 0.01},
        "iterations": [{"iteration": 1, "step_norm": 1.0, "delta_p_mm": 0.1, "delta_R_rad": 0.0}],
        "frames": frames,
        "identifiability": {"rank": 22, "n_params": 24},
    }


@fuzz(60)
@given(mutated(_result()))
def test_mutated_result_files_load_or_raise_result_file_error(spec):
    try:
        text = json.dumps(spec)
    except (TypeError, ValueError):
        assume(False)
    try:
        d = loads_result(text, "r.json")
    except ResultFileError as e:
        assert str(e).startswith("r.json: ")
        return
    for f in d["frames"].values():
        for key in ("nominal", "calibrated"):
            assert rigid_transform_problem(np.asarray(f[key]["matrix"], dtype=float)) is None


# --------------------------------------------------------------------------- solvers

paper = eqx.filter_jit(calibrate_paper)
robust = eqx.filter_jit(calibrate_robust)
lm = eqx.filter_jit(calibrate_lm)


@st.composite
def measured_sets(draw):
    """The 12 measured poses of problem(0), some replaced by random poses, NaN or huge values."""
    p = problem(0)
    T = p.T.copy()
    for _ in range(draw(st.integers(1, 4))):
        i = draw(st.integers(0, M - 1))
        what = draw(st.sampled_from(["random", "nan", "huge", "shift"]))
        if what == "random":
            T[i] = np.asarray(lie.se3_exp(_device(draw(twists))))
        elif what == "nan":
            T[i, draw(st.integers(0, 2)), draw(st.integers(0, 3))] = np.nan
        elif what == "huge":
            T[i, :3, 3] = draw(st.floats(1e6, 1e12))
        else:
            T[i, :3, 3] += draw(st.floats(-50.0, 50.0))
    return T


@fuzz(8)
@given(measured_sets())
def test_solvers_never_report_success_with_nan(T):
    p = problem(0)
    finite_in = bool(np.all(np.isfinite(T)))
    for sol in (
        paper(p.arm, p.q, T, throw=False),
        lm(p.arm, p.q, T, throw=False),
        robust(p.arm, p.q, T, None, loss="cauchy", solver="paper", throw=False).solution,
    ):
        frames_ok = bool(np.all(np.isfinite(np.asarray(sol.frames))))
        code = int(sol.result._value)
        if not finite_in:
            assert code == int(RESULTS.nonfinite._value)
        elif code == int(RESULTS.successful._value):
            assert frames_ok and np.all(np.isfinite(np.asarray(sol.errors)))
        assert frames_ok or code != int(RESULTS.successful._value)


def test_huge_rotation_vector_is_a_named_error():
    # Found by the fuzzer in CI: a rotation vector of 1.9e152 rad gave a non-orthonormal matrix.
    header = ",".join(COLUMNS)
    huge = "1.8831635608913214e+152"
    row = ["p0" if c == "pose" else huge if c == "measured.rx" else "0.1" for c in COLUMNS]
    with pytest.raises(
        MeasurementFileError,
        match=r"d\.csv, line 2, column 'measured\.rx'.*beyond 1e\+07 in magnitude",
    ):
        loads_measurements(header + "\n" + ",".join(row) + "\n", ARM, source="d.csv")


# --------------------------------------------------------------------------- uncertainty, poses

NOISE_LEVELS = st.tuples(st.floats(1e-6, 1e3), st.floats(1e-9, 1.0))


def _noise(levels) -> NoiseModel:
    # Arrays, not Python floats: equinox treats floats as static, which would compile again.
    return NoiseModel(jnp.asarray(levels[0]), jnp.asarray(levels[1]))


@st.composite
def state_sets(draw, m: int):
    """``m`` CDRA states: spread, repeated, far beyond the limits, nearly equal, a state entry
    that never moves, or with a NaN / inf entry."""
    lim = ARM.state_limits
    rng = np.random.default_rng(draw(st.integers(0, 2**31 - 1)))
    q = lim[:, 0] + rng.uniform(size=(m, ARM.dof)) * (lim[:, 1] - lim[:, 0])
    kind = draw(st.sampled_from(["spread", "repeated", "beyond", "near", "fixed", "nonfinite"]))
    if kind == "repeated":
        q[:] = q[0]
    elif kind == "beyond":
        q *= draw(st.floats(1.0, 100.0))
    elif kind == "near":
        q = q[0] + 1e-7 * rng.standard_normal(q.shape)
    elif kind == "fixed":
        q[:, draw(st.integers(0, ARM.dof - 1))] = 0.5
    elif kind == "nonfinite":
        q[draw(st.integers(0, m - 1)), draw(st.integers(0, ARM.dof - 1))] = draw(
            st.sampled_from([np.nan, np.inf, -np.inf])
        )
    return q


@fuzz(8)
@given(
    state_sets(8),
    NOISE_LEVELS,
    st.one_of(st.none(), st.lists(st.floats(1e-8, 1.0), min_size=8, max_size=8)),
)
def test_uncertainty_is_finite_or_names_the_bad_state(q, levels, weights):
    try:
        r = analyze_uncertainty(ARM, q, _noise(levels), weights=weights)
    except ValueError as e:
        assert not np.all(np.isfinite(q)), e
        assert re.search(r"module states must be finite: row \d+, column '[a-z.]+' is", str(e))
        return
    assert np.all(np.isfinite(r.covariance)) and np.all(r.std >= 0) and 0 <= r.rank <= 24
    # inf where a pose sees a direction the set leaves unidentified (e.g. a noise ratio of 5e9
    # mm/rad, where the rank cut-off drops a real direction); never NaN.
    for v in (r.expected_delta_p, r.expected_delta_R):
        assert v >= 0 and (np.isfinite(v) or len(r.unbounded_poses) > 0)
    json.dumps(r.to_dict(), allow_nan=False)  # the result file's entry has no NaN or inf
    assert "nan" not in r.summary()


@fuzz(4)
@given(state_sets(24), NOISE_LEVELS)
def test_pose_selection_picks_distinct_poses_or_names_the_bad_state(pool, levels):
    # The default i-opt runs both the determinant-lemma (D-optimal start) and the Woodbury
    # (I) passes; m is static, so it stays 5. Each rank of the pool compiles the passes once
    # (they work in the identifiable subspace), hence few examples.
    try:
        sel = select_from_pool(ARM, pool, 5, _noise(levels))
    except ValueError as e:
        assert not np.all(np.isfinite(pool)), e
        assert re.search(r"pool must be finite: row \d+, column '[a-z.]+' is", str(e))
        return
    idx = sel.indices.tolist()
    assert len(set(idx)) == 5 and all(0 <= i < 24 for i in idx)
    np.testing.assert_array_equal(sel.states, pool[sel.indices])
    assert 0 <= sel.rank <= 24 and np.isfinite(sel.o1) and sel.o1 >= 0
    assert sel.prediction_rms >= 0  # inf (never NaN) where the set leaves the reference unbounded
    assert np.isfinite(sel.log_det) or sel.rank == 0


# --------------------------------------------------------------------------- CDPM modules

_fk = jax.jit(cable_forward_kinematics)
_lengths = jax.jit(cable_lengths)
_closure = jax.jit(tension_closure)
_margin = jax.jit(hull_margin)
_distribute = jax.jit(distribute_tensions)
_holding = eqx.filter_jit(holding_tensions)

cable_cells = st.one_of(
    st.floats(-1e3, 1e3),
    st.floats(1e6, 1e15),
    st.sampled_from([0.0, -0.0, np.nan, np.inf, -np.inf]),
)


@fuzz(10)
@given(
    st.lists(cable_cells, min_size=24, max_size=24),
    st.lists(st.floats(-1.0, 1.0), min_size=12, max_size=12),
    st.floats(0.0, 50.0),
)
def test_cable_forward_kinematics_reports_every_row(junk, states, noise):
    """Rows 0-3 random lengths, rows 4-7 lengths of shoulder states plus noise: one code each,
    a finite state when successful, ``nonfinite`` exactly for non-finite input."""
    shoulder = ARM.module("shoulder")
    exact = np.asarray(_lengths(shoulder, _device(np.reshape(states, (4, 3)))))
    L = np.concatenate([np.reshape(junk, (4, 6)), exact + noise])
    sol = _fk(shoulder, _device(L))
    codes = np.asarray(sol.result._value)
    assert set(codes.tolist()) <= set(range(len(CableFKResult._name_to_item)))
    nonfinite = ~np.all(np.isfinite(L), axis=1)
    np.testing.assert_array_equal(codes == int(CableFKResult.nonfinite._value), nonfinite)
    ok = codes == int(CableFKResult.successful._value)
    assert np.all(np.isfinite(np.asarray(sol.state)[ok]))
    assert np.all(np.asarray(sol.residual_rms)[ok] <= 0.1)


@fuzz(15)
@given(
    st.lists(
        st.one_of(st.floats(-1e3, 1e3), st.just(0.0), st.just(np.nan)), min_size=18, max_size=18
    ),
    st.lists(st.floats(-1e4, 1e4), min_size=3, max_size=3),
    st.floats(0.0, 100.0),
)
@example(A=[0.0] * 18, wrench=[0.0, 0.0, 1.0], floor=0.0)  # all cables through the centre
def test_tension_closure_margin_and_distribution_agree(A, wrench, floor):
    A = np.reshape(A, (3, 6))
    closure = bool(_closure(A))
    margin = float(_margin(A))
    sol = _distribute(A, np.asarray(wrench), floor)
    code = int(sol.result._value)
    assert 0 <= code < len(TensionResult._name_to_item)
    if not np.all(np.isfinite(A)):
        assert code == int(TensionResult.nonfinite._value) and not closure
        return
    assert np.isfinite(margin)
    if abs(margin) > 1e-9 * max(np.abs(A).max(), 1.0):
        assert closure == (margin > 0)
    if code == int(TensionResult.successful._value):
        t = np.asarray(sol.tensions)
        assert np.all(np.isfinite(t)) and np.all(t >= floor - 1e-9 * max(floor, 1.0))
        err = np.linalg.norm(A @ t - np.asarray(wrench))
        assert err <= 1e-6 * (1.0 + np.linalg.norm(A) * np.linalg.norm(t) + np.linalg.norm(wrench))


@fuzz(8)
@given(state_sets(8), st.floats(0.0, 1e3))
def test_holding_tensions_are_finite_or_flagged(q, payload):
    """Statics: gravity loads (with payload) and the tension distribution of every module."""
    payload = jnp.asarray(payload)  # an array: one compile for every payload
    sols = _holding(ARM, _device(q), payload)
    assert set(sols) == {"shoulder", "elbow", "wrist"}
    rows = np.all(np.isfinite(q), axis=1)
    for name, sol in sols.items():
        codes = np.asarray(sol.result._value)
        assert set(codes.tolist()) <= set(range(len(TensionResult._name_to_item)))
        assert np.all(codes[~rows] == int(TensionResult.nonfinite._value))
        ok = codes == int(TensionResult.successful._value)
        t = np.asarray(sol.tensions)[ok]
        assert np.all(np.isfinite(t)) and np.all(t >= module_floor(ARM.module(name)) - 1e-6)
        assert np.all(np.isfinite(np.asarray(sol.residual)[ok]))


# --------------------------------------------------------------------------- sweeps

levels_in = st.lists(
    st.one_of(
        st.floats(0.0, 10.0), st.just(0.0), st.floats(-1.0, 0.0), st.sampled_from([np.nan, np.inf])
    ),
    min_size=0,
    max_size=3,
)


@fuzz(40)
@given(levels_in, levels_in)
def test_noise_levels_are_finite_pairs_or_a_value_error(positions, rotations):
    try:
        levels = parse_noise_levels(positions, rotations)
    except ValueError as e:
        assert str(e)
        return
    assert len(levels) == len(positions) >= 1
    for sp, sr in levels:
        assert math.isfinite(sp) and math.isfinite(sr) and sp >= 0 and sr >= 0
        assert (sp == 0) == (sr == 0)


def _sweep_csv() -> str:
    n = 2
    cols = {c: np.zeros(n) for c in SWEEP_COLUMNS}
    cols.update(
        m=np.full(n, 5),
        trial=np.arange(n),
        seed=np.zeros(n, int),
        iterations=np.full(n, 3),
        rank=np.full(n, 22),
        solver=np.array(["paper", "lm"], dtype=object),
        result=np.array(["successful", "successful"], dtype=object),
        converged=np.ones(n, bool),
    )
    with tempfile.TemporaryDirectory() as d:
        return SweepTable(cols, {"seed": "0"}).to_csv(os.path.join(d, "t.csv")).read_text()


SWEEP_CSV = _sweep_csv()


@fuzz(30)
@given(st.data())
def test_mutated_sweep_tables_read_or_raise_value_error(tmp_path_factory, data):
    lines = SWEEP_CSV.splitlines()
    for _ in range(data.draw(st.integers(1, 3))):
        k = data.draw(st.integers(0, len(lines) - 1))
        cells = lines[k].split(",")
        j = data.draw(st.integers(0, len(cells) - 1))
        cells[j] = data.draw(
            st.one_of(
                st.sampled_from(["", "nan", "inf", "x", "1.5", "-1", "true", "maybe", "1,2"]),
                st.text(max_size=5),
            )
        )
        lines[k] = ",".join(cells)
    if data.draw(st.booleans()):
        lines = lines[: data.draw(st.integers(0, len(lines)))]
    path = tmp_path_factory.mktemp("sweep") / "t.csv"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    try:
        table = read_sweep(path)
    except ValueError as e:
        assert str(path) in str(e)
        return
    assert set(table.columns) == set(SWEEP_COLUMNS)
    assert len({len(v) for v in table.columns.values()}) == 1


# The cell of tests/test_sweeps.py (m = 5, "weighted", chunk 4, 10 held-out states): compiled
# once per process, so in a whole-suite run the sweeps below cost no compile.
SWEEP_CELL = dict(solvers=["weighted"], chunk=4, m_verify=10, progress=False)


@fuzz(3)
@given(
    st.lists(st.tuples(st.floats(1e-4, 50.0), st.floats(1e-6, 0.5)), min_size=1, max_size=2),
    st.integers(0, 2**31 - 1),
    st.integers(1, 2),
)
def test_sweep_rows_are_finite_when_converged(levels, seed, trials):
    t = run_sweep(ARM, levels, [5], trials=trials, seed=seed, **SWEEP_CELL)
    assert len(t) == len(levels) * trials
    conv = np.asarray(t["converged"])
    for c in ("dp_fit", "dR_fit", "dp_heldout", "dR_heldout", "param_err"):
        v = np.asarray(t[c], dtype=float)
        assert np.all(np.isfinite(v[conv])) and np.all(v[conv] >= 0), c
    assert set(t["result"][~conv]) <= set(RESULTS._name_to_item) - {"successful"}


BAD_SWEEPS = {
    "negative noise": ([(-1.0, 0.1)], [5], ["paper"], {}, "non-negative"),
    "one zero std": ([(0.1, 0.0)], [5], ["paper"], {}, "both are zero"),
    "weighted without noise": ([(0.0, 0.0)], [5], ["weighted"], {}, "needs a noise model"),
    "too few poses": ([(0.1, 0.1)], [3], ["paper"], {}, "below the paper's minimum"),
    "unknown solver": ([(0.1, 0.1)], [5], ["gn"], {}, "unknown solver"),
    "no trials": ([(0.1, 0.1)], [5], ["paper"], {"trials": 0}, "must be >= 1"),
    "no pose count": ([(0.1, 0.1)], [], ["paper"], {}, "at least one pose count"),
}


@pytest.mark.parametrize("case", list(BAD_SWEEPS))
def test_bad_sweep_settings_raise_value_error_before_any_work(case):
    levels, counts, solvers, kwargs, match = BAD_SWEEPS[case]
    with pytest.raises(ValueError, match=match):
        run_sweep(ARM, levels, counts, solvers, progress=False, **kwargs)
