"""float32 solves with x64 enabled, the solvers' default tolerances per dtype, and the checks of
noise models (per-pose shapes at trace time, concrete values on construction).

The float32 problems are 15-pose CDRA trials simulated in float64 and rounded to float32 (the
arm's frames stay float64: the solvers cast them to the measurements' dtype). Every batch
holds noise-free trials, noisy ones and one with a NaN measurement, which must end
``nonfinite`` without touching the others.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdra_jax import simulation
from cdra_jax.calibration import (
    NoiseModel,
    calibrate_lm,
    calibrate_paper,
    calibrate_robust,
    gauss_newton,
    levenberg_marquardt,
    result_names,
)

M = 15
NOISE = NoiseModel(0.08, 1e-3)
NOISE_FREE, NOISY = [0, 1], [2, 3]  # trials of the batch; trial 4 has a NaN measurement
BROKEN = 4

SOLVES = {
    "paper": lambda arm, q, T: calibrate_paper(arm, q, T, throw=False),
    "weighted": lambda arm, q, T: calibrate_paper(arm, q, T, NOISE, throw=False),
    "lm": lambda arm, q, T: calibrate_lm(arm, q, T, throw=False),
    "lm-weighted": lambda arm, q, T: calibrate_lm(arm, q, T, NOISE, throw=False),
    "robust": lambda arm, q, T: calibrate_robust(arm, q, T, throw=False).solution,
    "robust-lm": lambda arm, q, T: (
        calibrate_robust(arm, q, T, NOISE, solver="lm", throw=False).solution
    ),
}


@eqx.filter_jit
def _batch(name, arm, q, T):
    return jax.vmap(lambda qq, tt: SOLVES[name](arm, qq, tt))(q, T)


@eqx.filter_jit
def _trials(arm):
    """Five noise-free trials (one simulation program), then noise on the NOISY ones."""
    keys = jax.random.split(jax.random.PRNGKey(11), 6)
    q, T, *_ = jax.vmap(lambda k: simulation.simulate_trial(k, arm, M))(keys[:5])
    T = T.at[NOISY[0] :].set(simulation.add_measurement_noise(keys[5], T[NOISY[0] :], NOISE))
    return q, T.at[BROKEN, 3, 0, 3].set(jnp.nan)


@pytest.fixture(scope="module")
def trials64(cdra):
    return tuple(np.asarray(a) for a in jax.device_get(_trials(cdra)))


@pytest.fixture(scope="module")
def trials32(trials64):
    return tuple(a.astype(np.float32) for a in trials64)


# --------------------------------------------------------------------------- float32


@pytest.mark.parametrize("name", list(SOLVES))
def test_float32_solves_stay_float32_and_converge_with_the_default_tolerances(cdra, trials32, name):
    """Before: LM raised "Vector and operator structures do not match" (its damping was
    float64), the robust solver a while_loop carry error (its MAD scale was float64), and the
    paper, weighted and robust solvers ended every float32 solve with max_iterations_reached
    (tol = 1e-10 is below float32's rounding floor of the step norm, ~1e-4)."""
    sol = jax.device_get(_batch(name, cdra, *trials32))
    for field in ("frames", "errors", "step_norm", "delta_p", "delta_R", "singular_values"):
        assert getattr(sol, field).dtype == np.float32, field
    assert sol.cost.dtype == np.float32
    names = result_names(sol.result)
    assert names[BROKEN] == "nonfinite"
    assert list(np.delete(names, BROKEN)) == ["successful"] * 4, names
    assert np.all(np.isfinite(np.delete(sol.frames, BROKEN, axis=0)))
    # As accurate as float32 allows: the fit to noise-free poses is at float32 rounding
    # (measured over 100 trials: final dp at most 1e-3 mm; float64: 1e-12).
    dp, dR = np.asarray(sol.final_delta_p), np.asarray(sol.final_delta_R)
    assert np.all(dp[NOISE_FREE] < 5e-3) and np.all(dR[NOISE_FREE] < 1e-5), (dp, dR)
    if not name.startswith("robust"):
        # A few steps, not a run to the iteration cap (measured 3-4 for the paper solver;
        # LM 4-21, median 4-10; with LM's float64 tolerances median 29-31 steps, up to 50).
        assert np.all(sol.iterations[:BROKEN] <= (6 if name in ("paper", "weighted") else 25))


@pytest.mark.parametrize("name", ["paper", "lm"])
def test_float32_solves_agree_with_float64(cdra, trials64, trials32, name):
    """The float32 solve is the float64 one up to float32 rounding: noisy trials fit to the
    same Eq. 20 deviation (the noise, 0.08 mm, dominates). LM minimises the cost, and its
    minimum is flat along directions that move the Eq. 20 deviation: stopped by float32's
    tolerances, the deviation differed from float64's by more than 2 % on 12-13 of 64 noisy
    trials (up to 10-14 %; 80 um / 1e-3 rad, 15 poses), the cost by at most 1.2e-4 of it.
    For LM the cost is compared."""
    s64 = jax.device_get(_batch(name, cdra, *trials64))
    s32 = jax.device_get(_batch(name, cdra, *trials32))
    if name == "lm":
        cost32, cost64 = np.asarray(s32.cost), np.asarray(s64.cost)
        np.testing.assert_allclose(cost32[NOISY], cost64[NOISY], rtol=2e-4)
    else:
        dp32, dp64 = np.asarray(s32.final_delta_p), np.asarray(s64.final_delta_p)
        np.testing.assert_allclose(dp32[NOISY], dp64[NOISY], rtol=0.02)
    # base and tool errors (identifiable on the CDRA): float32 rounding, mm and rad
    e32, e64 = s32.errors[:BROKEN][:, [0, -1]], s64.errors[:BROKEN][:, [0, -1]]
    np.testing.assert_allclose(e32, e64, atol=5e-3)


def test_explicit_tolerances_still_apply_in_float32(cdra, trials32):
    """tol = 1e-10 (the float64 default) is still honoured when asked for: in float32 the step
    norm never gets there, so the solve runs to max_iterations."""
    sol = eqx.filter_jit(calibrate_paper)(
        cdra, trials32[0][0], trials32[1][0], tol=1e-10, max_iterations=8, throw=False
    )
    assert result_names(sol.result) == "max_iterations_reached"
    assert np.all(np.asarray(sol.step_norm)[3:] > 1e-7)  # the float32 floor: steps of ~1e-4


def test_default_tolerances_depend_on_the_dtype():
    assert gauss_newton.default_tol(jnp.float64) == 1e-10
    assert gauss_newton.default_tol(jnp.float32) == gauss_newton.TOL_FLOAT32 == 1e-3
    assert (levenberg_marquardt.RTOL_FLOAT64, levenberg_marquardt.ATOL_FLOAT64) == (1e-12, 1e-11)
    assert (levenberg_marquardt.RTOL_FLOAT32, levenberg_marquardt.ATOL_FLOAT32) == (1e-6, 1e-3)


def test_float64_default_tolerance_is_the_old_one_bitwise(cdra, trials64):
    """tol=None in float64 is tol=1e-10: the same program and bitwise the same answer."""
    q, T = (a[NOISY[0]] for a in trials64)
    a = jax.device_get(calibrate_paper(cdra, q, T, NOISE))
    b = jax.device_get(calibrate_paper(cdra, q, T, NOISE, tol=1e-10))
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        assert np.asarray(x).tobytes() == np.asarray(y).tobytes()


# --------------------------------------------------------------------------- noise shapes


BAD_SHAPES = [
    (NoiseModel(np.full(5, 0.08), 1e-3), "position_mm", r"\(5,\)"),
    (NoiseModel(np.full((M, 1), 0.08), 1e-3), "position_mm", rf"\({M}, 1\)"),
    (NoiseModel(0.08, np.full(7, 1e-3)), "rotation_rad", r"\(7,\)"),
]


@pytest.fixture(scope="module")
def problem(trials64):
    """One noisy 15-pose trial in float64, as jax arrays."""
    q, T = (jnp.asarray(a[NOISY[0]]) for a in trials64)
    return q, T


@pytest.mark.parametrize(("noise", "field", "shape"), BAD_SHAPES)
@pytest.mark.parametrize("solve", [calibrate_paper, calibrate_lm], ids=["paper", "lm"])
def test_per_pose_noise_of_the_wrong_shape_raises_naming_the_field(
    cdra, problem, solve, noise, field, shape
):
    """Before: JAX's unnamed "Incompatible shapes for broadcasting" or a TypeError."""
    q, T = problem
    expected = rf"noise\.{field} must be a number \(shape \(\)\) or one std per pose "
    expected += rf"\(shape \(m,\) = \({M},\)\), got shape {shape}"
    with pytest.raises(ValueError, match=expected):
        solve(cdra, q, T, noise)
    with pytest.raises(ValueError, match=expected):  # at trace time, under jit and vmap
        jax.jit(jax.vmap(lambda qq, tt: solve(cdra, qq, tt, noise, throw=False)))(q[None], T[None])


@pytest.mark.parametrize(("noise", "field", "shape"), BAD_SHAPES)
def test_robust_and_simulation_name_a_noise_field_of_the_wrong_shape(
    cdra, problem, noise, field, shape
):
    q, T = problem
    with pytest.raises(ValueError, match=rf"noise\.{field} must be a number \(shape \(\)\)"):
        calibrate_robust(cdra, q, T, noise)
    key = jax.random.PRNGKey(1)
    with pytest.raises(ValueError, match=rf"noise\.{field} .*\({M},\).*got shape {shape}"):
        simulation.add_measurement_noise(key, T, noise)
    with pytest.raises(ValueError, match=rf"noise\.{field}"):
        simulation.measure(key, cdra, q, noise)


def test_noise_of_the_right_shapes_is_accepted(problem):
    _, T = problem
    key = jax.random.PRNGKey(1)
    for noise in (NoiseModel(0.08, 1e-3), NoiseModel(np.full(M, 0.08), np.full(M, 1e-3))):
        assert simulation.add_measurement_noise(key, T, noise).shape == T.shape
    # batched poses (trials, m): stds per pose or per trial broadcast against the leading axes
    Tb = jnp.asarray(np.stack([T, T]))
    for std in (np.full(M, 0.08), np.full((2, 1), 0.08), np.full((2, M), 0.08)):
        out = simulation.add_measurement_noise(key, Tb, NoiseModel(std, 1e-3))
        assert out.shape == Tb.shape


# --------------------------------------------------------------------------- noise values


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: NoiseModel(jnp.array(-0.08), 1e-3), r"position_mm must be a positive .*-0\.08"),
        (lambda: NoiseModel(np.float32(-0.1), 1e-3), r"position_mm must be a positive .*-0\.1"),
        (lambda: NoiseModel(0.08, np.float64(0.0)), r"rotation_rad must be a positive .*0\.0"),
        (lambda: NoiseModel(jnp.array(np.nan), 1e-3), r"position_mm must be a positive .*nan"),
        (lambda: NoiseModel(np.array(np.inf), 1e-3), r"position_mm must be a positive .*inf"),
        (lambda: NoiseModel(-1.0, 1e-3), r"position_mm must be a positive finite number"),
        (
            lambda: NoiseModel(jnp.array([0.08] * 7 + [0.0]), 1e-3),
            r"position_mm must be positive in every entry .*got 0\.0 at pose 7",
        ),
        (
            lambda: NoiseModel(0.08, np.array([1e-3, -1e-3, 1e-3])),
            r"rotation_rad must be positive in every entry .*got -0\.001 at pose 1",
        ),
        (
            lambda: NoiseModel(0.08, np.array([1e-3, 1e-3, np.nan])),
            r"rotation_rad must be positive in every entry .*got nan at pose 2",
        ),
        (
            lambda: NoiseModel(jnp.array([0.08, -np.inf]), 1e-3),
            r"position_mm must be positive in every entry .*got -inf at pose 1",
        ),
        (lambda: NoiseModel("0.08", 1e-3), r"position_mm must be a number"),
    ],
)
def test_concrete_noise_values_are_checked(make, message):
    """Before: only Python numbers were checked; arrays, numpy scalars and per-pose entries of
    zero (which made the whole solve non-finite) or below passed."""
    with pytest.raises(ValueError, match=rf"NoiseModel: noise\.{message}"):
        make()


def test_infinite_per_pose_std_is_weight_zero_and_traced_values_are_not_checked(cdra):
    NoiseModel(jnp.array([0.08, np.inf, 0.08]), np.array([1e-3, np.inf, 1e-3]))  # weight 0
    # Inside jit the values are unknown at construction: no check, no error.
    out = jax.jit(lambda s: NoiseModel(s, 1e-3).position_mm)(jnp.asarray(-1.0))
    assert float(out) == -1.0
    out = jax.vmap(lambda s: NoiseModel(s, 1e-3).position_mm)(jnp.asarray([0.0, 1.0]))
    assert out.shape == (2,)


def test_robust_rejection_of_a_failed_trial_outside_jit_reports_nonfinite(cdra, problem):
    """The rejection refit of a trial that failed (NaN measurements: a NaN residual scale) is
    discarded; outside jit it must not trip NoiseModel's value check on its way there."""
    q, T = problem
    T = np.array(T)
    T[2, 0, 3] = np.nan
    out = calibrate_robust(cdra, q, T, reject_outliers=True, throw=False)
    assert result_names(out.solution.result) == "nonfinite"
