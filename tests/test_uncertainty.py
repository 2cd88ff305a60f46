"""Uncertainty: covariance, Cramer-Rao bound, predicted-pose covariance, intervals, efficiency."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from cdra_jax import NoiseModel, apply_frame_errors, calibrate_paper, lie, tool_pose
from cdra_jax.calibration import whitening
from cdra_jax.simulation import measure, random_frame_errors, sample_states
from cdra_jax.uncertainty import (
    analyze_uncertainty,
    cramer_rao_bound,
    parameter_covariance,
    pose_covariance,
    predicted_pose_covariance,
    uncertainty_dict,
)

NOISE = NoiseModel(0.08, 1e-3)
NOT_ALONE = {"upper_arm.vx", "upper_arm.vy", "upper_arm.wy", "forearm.vy", "forearm.wy"}


def _autodiff_jacobian(arm, q):
    """Oracle: world-frame twist of the tool pose w.r.t. the frame errors, by autodiff through
    apply_frame_errors and the chain (no adjoint formula involved): (m, 6, n)."""
    T0 = tool_pose(arm, q)

    def twist(X):
        return lie.se3_log(tool_pose(apply_frame_errors(arm, X), q) @ lie.inverse(T0))

    return jax.jit(jax.jacfwd(twist))(jnp.zeros(arm.n_params))


@pytest.fixture(scope="module")
def poses(cdra):
    return sample_states(jax.random.PRNGKey(3), cdra, 8)


def test_covariance_is_pinv_of_whitened_information(cdra, poses):
    J = _autodiff_jacobian(cdra, poses)
    G = whitening(tool_pose(cdra, poses), NOISE)
    Dw = np.asarray(G @ J).reshape(-1, cdra.n_params)
    expected = np.linalg.pinv(Dw.T @ Dw, rcond=1e-9, hermitian=True)
    unc = parameter_covariance(cdra, poses, NOISE)
    assert int(unc.rank) == 22
    scale = np.abs(expected).max()
    np.testing.assert_allclose(np.asarray(unc.covariance), expected, atol=1e-9 * scale)
    # the CDRA's two unidentifiable directions carry no variance
    P = np.asarray(unc.row_space_projector)
    np.testing.assert_allclose(P @ np.asarray(unc.covariance), unc.covariance, atol=1e-9 * scale)


def test_cramer_rao_bound(cdra, poses):
    names = cdra.param_names
    e = np.eye(cdra.n_params)
    c_ok = e[names.index("base.vx")]
    c_alone = e[names.index("upper_arm.wy")]
    # rotation about the elbow axis can move between upper_arm and forearm; the sum of the two
    # y rotations is orthogonal to both unidentifiable directions, so it is identifiable
    c_sum = e[names.index("upper_arm.wy")] + e[names.index("forearm.wy")]
    crb = np.asarray(cramer_rao_bound(cdra, poses, NOISE, np.stack([c_ok, c_alone, c_sum])))
    cov = np.asarray(parameter_covariance(cdra, poses, NOISE).covariance)
    assert crb[0] == pytest.approx(cov[0, 0], rel=1e-12)
    assert np.isinf(crb[1])
    assert np.isfinite(crb[2]) and crb[2] == pytest.approx(c_sum @ cov @ c_sum, rel=1e-12)
    # the bound is a lower bound: the unweighted estimator's (sandwich) covariance is larger
    J = np.asarray(_autodiff_jacobian(cdra, poses))
    G = np.asarray(whitening(tool_pose(cdra, poses), NOISE))
    Ginv = np.linalg.inv(G)
    D = J.reshape(-1, cdra.n_params)
    Sigma = np.zeros((D.shape[0],) * 2)
    for i in range(len(poses)):
        Sigma[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] = Ginv[i] @ Ginv[i].T
    P = np.linalg.pinv(D, rcond=1e-9)
    C_unweighted = P @ Sigma @ P.T
    rng = np.random.default_rng(0)
    proj = np.asarray(parameter_covariance(cdra, poses, NOISE).row_space_projector)
    for c in rng.normal(size=(20, cdra.n_params)) @ proj:
        assert c @ C_unweighted @ c >= (1 - 1e-9) * (c @ cov @ c)


def test_pose_covariance_matches_autodiff(cdra, poses):
    cov = parameter_covariance(cdra, poses, NOISE).covariance
    q_eval = sample_states(jax.random.PRNGKey(11), cdra, 3)
    pc = pose_covariance(cdra, q_eval, cov)
    T0 = tool_pose(cdra, q_eval)

    def position(X):
        return lie.translation(tool_pose(apply_frame_errors(cdra, X), q_eval))

    def rotation(X):  # world-frame orientation error
        R = lie.rotation(tool_pose(apply_frame_errors(cdra, X), q_eval))
        return lie.so3_log(R @ jnp.swapaxes(lie.rotation(T0), -1, -2))

    both = jax.jit(jax.jacfwd(lambda X: (position(X), rotation(X))))  # one compile
    Jp, Jr = (np.asarray(J) for J in both(jnp.zeros(cdra.n_params)))
    C = np.asarray(cov)
    exp_p = np.einsum("kai,ij,kbj->kab", Jp, C, Jp)
    exp_r = np.einsum("kai,ij,kbj->kab", Jr, C, Jr)
    np.testing.assert_allclose(pc.position, exp_p, rtol=1e-8, atol=1e-14)
    np.testing.assert_allclose(pc.rotation, exp_r, rtol=1e-8, atol=1e-18)
    np.testing.assert_allclose(
        pc.expected_delta_p, np.sqrt(np.mean(np.trace(exp_p, axis1=1, axis2=2))), rtol=1e-10
    )


def test_report_intervals_and_json(cdra, poses):
    est = np.linspace(-1, 1, cdra.n_params)
    rep = analyze_uncertainty(cdra, poses, NOISE, estimate=est)
    names = cdra.param_names
    assert {n for n, ok in zip(names, rep.identifiable, strict=True) if not ok} == NOT_ALONE
    i = names.index("tool.vz")
    lo, hi = rep.interval(i)
    assert (lo + hi) / 2 == pytest.approx(est[i])
    assert (hi - lo) / 2 == pytest.approx(1.959964 * rep.std[i], rel=1e-6)
    d = uncertainty_dict(cdra, poses, NOISE, estimate=est)
    text = json.dumps(d, allow_nan=False)
    back = json.loads(text)
    assert back["rank"] == 22 and back["n_params"] == 24
    assert back["parameters"]["upper_arm.wy"]["interval"] is None
    assert "not identifiable on its own" in back["parameters"]["upper_arm.wy"]["note"]
    assert "upper_arm.wy" in back["parameters"]["upper_arm.wy"]["note"]
    assert back["parameters"]["tool.vz"]["interval"] == pytest.approx([lo, hi])
    assert len(back["predicted_pose"]["position_rms_mm"]) == len(poses)
    summary = rep.summary()
    assert "not identifiable on its own" in summary and "tool.vz" in summary


def test_bad_input(cdra, poses):
    with pytest.raises(ValueError, match="NoiseModel"):
        parameter_covariance(cdra, poses, None)
    with pytest.raises(ValueError, match="confidence"):
        analyze_uncertainty(cdra, poses, NOISE, confidence=1.5)
    with pytest.raises(ValueError, match=r"shape \(m, 7\)"):
        analyze_uncertainty(cdra, poses[:, :5], NOISE)
    with pytest.raises(ValueError, match="24 values"):
        analyze_uncertainty(cdra, poses, NOISE, estimate=np.zeros(5))


def _chi2_bounds(dof, alpha):
    return stats.chi2.ppf(alpha / 2, dof) / dof, stats.chi2.ppf(1 - alpha / 2, dof) / dof


@pytest.mark.slow
def test_weighted_estimator_attains_crb(cdra):
    """Monte Carlo (fixed seeds): the weighted estimator's covariance is the predicted one.

    Along each principal axis u_i of the Fisher information the standardised estimate
    y_i = s_i u_i^T (X_hat - X_true) must have unit variance; checked per axis and pooled with
    chi-square bounds from the trial count, plus a likelihood-ratio (Wishart) test of the
    whole 22 x 22 covariance, and the predicted tool-position covariance at held-out states.
    """
    n, m = 1000, 10
    q = sample_states(jax.random.PRNGKey(21), cdra, m)
    X = random_frame_errors(jax.random.PRNGKey(22), cdra)
    actual = apply_frame_errors(cdra, X)
    q_h = sample_states(jax.random.PRNGKey(23), cdra, 3)

    def trial(key):
        sol = calibrate_paper(cdra, q, measure(key, actual, q, NOISE), NOISE, throw=False)
        e = lie.se3_log(sol.frames @ lie.inverse(actual.frames)).reshape(-1)
        dpos = lie.translation(tool_pose(cdra.with_frames(sol.frames), q_h)) - lie.translation(
            tool_pose(actual, q_h)
        )
        return e, dpos, sol.result._value

    e, dpos, res = jax.jit(jax.vmap(trial))(jax.random.split(jax.random.PRNGKey(24), n))
    assert np.all(np.asarray(res) == 0)
    unc = parameter_covariance(actual, q, NOISE, tool_pose(actual, q))
    r = int(unc.rank)
    assert r == 22
    s = np.asarray(unc.singular_values)[:r]
    y = np.asarray(e) @ np.asarray(unc.basis)[:r].T * s  # (n, r), ~ N(0, I) if efficient
    alpha = 1e-4
    lo, hi = _chi2_bounds(n, alpha)
    per_axis = np.mean(y**2, axis=0)
    assert np.all((per_axis > lo) & (per_axis < hi)), per_axis
    lo_all, hi_all = _chi2_bounds(n * r, alpha)
    pooled = np.mean(y**2)
    assert lo_all < pooled < hi_all, pooled
    # the pooled test has the power to see a 10 % error in the predicted covariance
    assert not lo_all < pooled / 1.1 < hi_all
    S = np.cov(y, rowvar=False)
    lr = (n - 1) * (np.trace(S) - np.linalg.slogdet(S)[1] - r)
    assert lr < stats.chi2.ppf(1 - alpha, r * (r + 1) // 2), lr
    # predicted tool-position covariance at held-out states (mm^2), Mahalanobis chi-square
    pc = predicted_pose_covariance(actual, q, NOISE, q_h, tool_pose(actual, q))
    d2 = np.einsum("nka,kab,nkb->nk", dpos, np.linalg.inv(np.asarray(pc.position)), dpos)
    lo3, hi3 = _chi2_bounds(3 * n, alpha)
    for k in range(3):
        assert lo3 < np.mean(d2[:, k]) / 3 < hi3, np.mean(d2, axis=0) / 3
