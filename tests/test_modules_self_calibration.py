"""Module self-calibration from redundant cable lengths: recovery, noise, identifiability."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import chi2

from cdra_jax import lie
from cdra_jax.io import dumps_model, loads_model
from cdra_jax.modules import (
    analyze_self_calibration,
    cable_lengths,
    gauge_invariants,
    module_parameters,
    parameter_names,
    result_names,
    sample_feasible_states,
    self_calibrate,
    with_module,
    with_parameters,
)
from cdra_jax.modules.self_calibration import _fix_gauge, _to_var

M = 40  # sampler batch shared with the other module tests; two batches give 80 poses
_sample = jax.jit(sample_feasible_states, static_argnums=2)
_solve = jax.jit(lambda module, lengths: self_calibrate(module, lengths, throw=False))


def _study(cdra, index, seed):
    """Nominal module, true module with preset errors, and its states (80 feasible poses)."""
    nominal = cdra.modules[index]
    q = np.concatenate([_sample(jax.random.PRNGKey(seed + i), cdra, M) for i in range(2)])
    truth, states, lengths = _truth(nominal, cdra.split_state(q)[index], jax.random.PRNGKey(seed))
    return nominal, truth, states, lengths


@jax.jit
def _truth(nominal, states, key):
    # preset errors: +-1 mm on every attachment coordinate, +-2 mm length offsets
    n = nominal.n_cables
    err = jax.random.uniform(key, (n, 7), minval=-1, maxval=1) * jnp.asarray([1.0] * 6 + [2.0])
    truth = with_parameters(nominal, module_parameters(nominal) + err.reshape(-1))
    return truth, states, cable_lengths(truth, states)


@jax.jit
def _canonical(nominal, module, states):
    """Parameters and states of ``module`` in the gauge the solver reports (nominal-aligned)."""
    return _fix_gauge(
        nominal, module_parameters(nominal), module_parameters(module), _to_var(nominal, states)
    )


@pytest.fixture(scope="module")
def solved(cdra):
    """``(index, seed) -> (nominal, truth, states, lengths, solution)``, each study solved once
    per module."""
    cache = {}

    def get(index, seed):
        if (index, seed) not in cache:
            nominal, truth, states, lengths = _study(cdra, index, seed)
            cache[index, seed] = (nominal, truth, states, lengths, _solve(nominal, lengths))
        return cache[index, seed]

    return get


@pytest.mark.parametrize("index", [0, pytest.param(2, marks=pytest.mark.slow)])
def test_noise_free_recovery_of_spherical_modules(solved, index):
    nominal, truth, states, lengths, sol = solved(index, 10 * index)
    assert result_names(sol.result) == "successful"
    assert float(sol.residual_rms) < 1e-10
    theta, R = _canonical(nominal, truth, states)
    assert np.max(np.abs(np.asarray(sol.parameters) - np.asarray(theta))) < 1e-8
    # the errors were large: the nominal model misfits the lengths by about a millimetre
    assert float(np.asarray(sol.rms_history)[0]) > 0.1
    # the estimated states are the true ones, in the same gauge
    np.testing.assert_allclose(lie.so3_exp(sol.states), R, atol=1e-9)


@pytest.mark.slow
def test_noise_free_recovery_of_the_elbow_invariants(cdra):
    nominal, truth, states, lengths = _study(cdra, 1, 5)
    sol = _solve(nominal, lengths)
    assert result_names(sol.result) == "successful"
    assert float(sol.residual_rms) < 1e-10
    want, got = gauge_invariants(truth), gauge_invariants(sol.module)
    assert set(want) == {"offset", "c", "p", "phase"}
    for key in want:
        np.testing.assert_allclose(got[key], want[key], rtol=1e-10, atol=1e-8)
    # noisy lengths: badly conditioned (2 cables, one redundant length per pose), but the damped
    # iteration converges to a residual of the size the noise implies instead of diverging
    noisy = np.asarray(lengths) + 0.02 * np.asarray(
        jax.random.normal(jax.random.PRNGKey(4), lengths.shape)
    )
    sol = _solve(nominal, noisy)
    assert result_names(sol.result) == "successful"
    m = lengths.shape[0]
    expect = 0.02 * np.sqrt((m * (2 - 1) - 7) / (m * 2))
    assert 0.7 < float(sol.residual_rms) / expect < 1.3


def test_recovery_with_length_noise_is_within_its_predicted_uncertainty(cdra):
    sigma = 0.02  # mm
    nominal, truth, states, lengths = _study(cdra, 0, 40)
    noisy = np.asarray(lengths) + sigma * np.asarray(
        jax.random.normal(jax.random.PRNGKey(3), states.shape[:1] + (nominal.n_cables,))
    )
    sol = _solve(nominal, noisy)
    assert result_names(sol.result) == "successful"
    n, d, m = nominal.n_cables, nominal.dof, states.shape[0]
    report = analyze_self_calibration(truth, states)
    # residual of the right size: E[rms^2] = s^2 (mn - dof m - rank) / (mn)
    dof_res = m * n - d * m - report.rank
    ratio = float(sol.residual_rms) ** 2 / (sigma**2 * dof_res / (m * n))
    assert chi2.ppf(0.001, dof_res) / dof_res < ratio < chi2.ppf(0.999, dof_res) / dof_res
    # parameter error in the identifiable subspace: Mahalanobis distance ~ chi^2(rank)
    err = np.asarray(sol.parameters) - np.asarray(_canonical(nominal, truth, states)[0])
    cov = report.covariance(sigma)
    stat = err @ np.linalg.pinv(cov, rcond=1e-12, hermitian=True) @ err
    assert stat < chi2.ppf(0.999, report.rank), stat
    std = np.sqrt(np.diag(cov))
    assert np.max(np.abs(err) / std) < 4.5
    assert 0.005 < np.median(std) < 0.5  # tens of micrometres to a few tenths: informative


def test_identifiability_report_names_the_gauge_freedoms(cdra):
    summaries = []
    for index, rank in ((0, 36), (1, 7), (2, 22)):
        module = cdra.modules[index]
        states = cdra.split_state(_sample(jax.random.PRNGKey(index), cdra, M))[index]
        report = analyze_self_calibration(module, states)
        assert report.n_params == 7 * module.n_cables
        assert report.rank == rank
        assert len(report.unidentifiable) == report.n_params - rank
        assert report.param_names == parameter_names(module)
        assert report.null_space.shape == (report.n_params - rank, report.n_params)
        # the null space is exactly spanned by the named symmetries
        assert report.symmetries == report.unidentifiable
        d = report.to_dict()
        assert d["rank"] == rank and d["module"] == module.name
        summaries.append(report.summary())
    assert "rotation of all shoulder base points about the module centre (x)" in summaries[0]
    assert "rotation of all wrist platform points about the module centre (z)" in summaries[2]
    assert "shift of elbow cable 2's two points along the joint axis" in summaries[1]


def test_calibrated_module_goes_into_the_arm_and_the_model_file(cdra, solved):
    sol = solved(0, 0)[-1]
    arm = with_module(cdra, sol.module)
    assert arm.modules[0].cable_offset is not None
    back = loads_model(dumps_model(arm))
    np.testing.assert_array_equal(back.modules[0].cable_offset, sol.module.cable_offset)
    np.testing.assert_array_equal(back.modules[0].cable_base, sol.module.cable_base)
    with pytest.raises(ValueError, match="has no module 'hand'"):
        with_module(cdra, dataclasses.replace(sol.module, name="hand"))


def test_too_few_poses_are_refused(cdra):
    wrist = cdra.modules[2]
    lengths = np.asarray(cable_lengths(wrist, np.zeros((20, 3))))
    with pytest.raises(ValueError, match="fewer than the 28 parameters; measure at least 28"):
        self_calibrate(wrist, lengths)
    with pytest.raises(ValueError, match=r"lengths must be \(m, 4\)"):
        self_calibrate(wrist, lengths[:, :3])
