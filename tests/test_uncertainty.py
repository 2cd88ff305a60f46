"""Uncertainty: covariance, Cramer-Rao bound, predicted-pose covariance, intervals, efficiency."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats
from scipy.spatial.transform import Rotation

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


@pytest.fixture(scope="module")
def jacobian(cdra, poses):
    """The autodiff oracle at ``poses`` (numpy), shared by the tests that compare with it."""
    return np.asarray(_autodiff_jacobian(cdra, poses))


@pytest.fixture(scope="module")
def whitener(cdra, poses):
    """The per-pose whitening ``G (m, 6, 6)`` of the model tool poses at ``poses`` (numpy; one
    compiled program rather than its operations one by one)."""
    return np.asarray(jax.jit(whitening)(tool_pose(cdra, poses), NOISE))


@pytest.fixture(scope="module")
def q_eval(cdra):
    """Three held-out states at which the tool poses are predicted."""
    return sample_states(jax.random.PRNGKey(11), cdra, 3)


def test_covariance_is_pinv_of_whitened_information(cdra, poses, jacobian, whitener):
    Dw = (whitener @ jacobian).reshape(-1, cdra.n_params)
    expected = np.linalg.pinv(Dw.T @ Dw, rcond=1e-9, hermitian=True)
    unc = parameter_covariance(cdra, poses, NOISE)
    assert int(unc.rank) == 22
    scale = np.abs(expected).max()
    np.testing.assert_allclose(np.asarray(unc.covariance), expected, atol=1e-9 * scale)
    # the CDRA's two unidentifiable directions carry no variance
    P = np.asarray(unc.row_space_projector)
    np.testing.assert_allclose(P @ np.asarray(unc.covariance), unc.covariance, atol=1e-9 * scale)


def test_cramer_rao_bound(cdra, poses, jacobian, whitener):
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
    Ginv = np.linalg.inv(whitener)
    D = jacobian.reshape(-1, cdra.n_params)
    Sigma = np.zeros((D.shape[0],) * 2)
    for i in range(len(poses)):
        Sigma[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] = Ginv[i] @ Ginv[i].T
    P = np.linalg.pinv(D, rcond=1e-9)
    C_unweighted = P @ Sigma @ P.T
    rng = np.random.default_rng(0)
    proj = np.asarray(parameter_covariance(cdra, poses, NOISE).row_space_projector)
    for c in rng.normal(size=(20, cdra.n_params)) @ proj:
        assert c @ C_unweighted @ c >= (1 - 1e-9) * (c @ cov @ c)


def test_pose_covariance_matches_autodiff(cdra, poses, q_eval):
    cov = parameter_covariance(cdra, poses, NOISE).covariance
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


def test_prediction_unbounded_where_the_poses_leave_directions_unidentified(cdra, poses, q_eval):
    """A rank-deficient pose set cannot bound the error at states it does not pin down: inf,
    not the pseudo-inverse's finite number. The CDRA's two structural directions (move no
    tool pose) never count: full-rank sets predict the same finite values as before."""
    same = jnp.repeat(poses[:1], 8, axis=0)  # one state measured 8 times: rank 6 of 24
    pc = predicted_pose_covariance(cdra, same, NOISE, q_eval)
    assert np.isinf(pc.expected_delta_p) and np.isinf(pc.expected_delta_R)
    assert np.all(np.isinf(pc.position_rms)) and np.all(np.isinf(pc.twist))
    assert not np.any(pc.bounded)
    # at the repeated state itself the tool pose is the mean of 8 measurements: whitened
    # residual (dp / s_p, w / s_r), so the position covariance is s_p^2 / 8 I (exact); evaluated
    # there three times (k = 3, the shape of q_eval: the same compiled program)
    own = predicted_pose_covariance(cdra, same, NOISE, same[:3])
    assert np.all(np.asarray(own.bounded))
    np.testing.assert_allclose(own.position_rms, 0.08 * np.sqrt(3 / 8), rtol=1e-8)
    np.testing.assert_allclose(own.rotation_rms, 1e-3 * np.sqrt(3 / 8), rtol=1e-8)
    # no poses at all: nothing identified, nothing bounded
    assert np.isinf(predicted_pose_covariance(cdra, poses[:0], NOISE, q_eval).expected_delta_p)
    # a full set (rank 22) at the nominal and at a calibrated model: finite, and equal to the
    # face-value propagation of its covariance (the structural null space is ~1e-16 relative)
    frames = np.array(cdra.frames)  # a calibrated-like model: every frame off by ~0.02 mm, rad
    small = 0.02 * np.sin(np.arange(frames.shape[0] * 6).reshape(-1, 2, 3))
    frames[:, :3, :3] = Rotation.from_rotvec(small[:, 1]).as_matrix() @ frames[:, :3, :3]
    frames[:, :3, 3] += small[:, 0]
    for arm in (cdra, cdra.with_frames(jnp.asarray(frames))):
        unc = parameter_covariance(arm, poses, NOISE)
        assert int(unc.rank) == 22
        full = predicted_pose_covariance(arm, poses, NOISE, q_eval)
        plain = pose_covariance(arm, q_eval, unc.covariance)
        assert np.all(np.asarray(full.bounded))
        for got, want in ((full.position, plain.position), (full.rotation, plain.rotation)):
            np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9 * np.abs(want).max())


def test_report_marks_unbounded_prediction(cdra, poses, q_eval):
    """The report says so, and stays JSON-safe (null, no Infinity)."""
    same = jnp.repeat(poses[:1], 8, axis=0)
    rep = analyze_uncertainty(cdra, same, NOISE, q_eval=q_eval)
    assert np.isinf(rep.expected_delta_p) and list(rep.unbounded_poses) == [0, 1, 2]
    pred = json.loads(json.dumps(rep.to_dict(), allow_nan=False))["predicted_pose"]
    assert pred["bounded"] is False and pred["expected_delta_p_mm"] is None
    assert pred["position_rms_mm"] == [None] * 3 and "unbounded" in pred["note"]
    assert "unbounded (inf) at 3 of 3" in rep.summary()
    assert uncertainty_dict(cdra, poses, NOISE)["predicted_pose"]["bounded"] is True


def test_predicted_accuracy_gradients(cdra, poses, q_eval):
    """Differentiable despite the two zero singular values: jacfwd = jacrev = central finite
    differences; at an unbounded (inf) prediction the gradient is finite too."""

    def f(q):
        pc = predicted_pose_covariance(cdra, q, NOISE, q_eval)
        return jnp.stack([pc.expected_delta_p, 1e2 * pc.expected_delta_R, pc.position[1, 0, 2]])

    q0 = jnp.asarray(poses)
    jacrev = jax.jit(jax.jacrev(f))
    J_rev = np.asarray(jacrev(q0))
    J_fwd = np.asarray(jax.jit(jax.jacfwd(f))(q0))
    assert np.all(np.isfinite(J_rev)) and np.abs(J_rev).max() > 0
    np.testing.assert_allclose(J_rev, J_fwd, rtol=1e-8, atol=1e-9 * np.abs(J_rev).max())
    fj = jax.jit(f)
    rng = np.random.default_rng(1)
    for _ in range(2):
        v = rng.normal(size=q0.shape)
        h = 1e-5
        fd = (np.asarray(fj(q0 + h * v)) - np.asarray(fj(q0 - h * v))) / (2 * h)
        np.testing.assert_allclose(
            fd, np.einsum("aij,ij->a", J_rev, v), rtol=1e-5, atol=1e-9 * np.abs(fd).max()
        )
    same = jnp.repeat(q0[:1], 8, axis=0)
    assert np.all(np.isinf(np.asarray(fj(same))))
    assert np.all(np.isfinite(np.asarray(jacrev(same))))


def test_per_pose_noise_and_measured_shape(cdra, poses):
    """(m,) noise stds: pose i with noise (s_p, s_r) / sqrt(w_i) is the robust-weights form
    with weights w_i; equal stds are the scalar model. Wrong shapes name the argument."""
    w = np.linspace(0.2, 1.0, len(poses))
    per_pose = NoiseModel(0.08 / np.sqrt(w), 1e-3 / np.sqrt(w))
    a = analyze_uncertainty(cdra, poses, per_pose)
    b = analyze_uncertainty(cdra, poses, NOISE, weights=w)
    scale = np.abs(b.covariance).max()
    np.testing.assert_allclose(a.covariance, b.covariance, atol=1e-10 * scale)
    assert a.expected_delta_p == pytest.approx(b.expected_delta_p, rel=1e-9)
    c = analyze_uncertainty(cdra, poses, NoiseModel(jnp.full(len(poses), 0.08), 1e-3))
    d = analyze_uncertainty(cdra, poses, NOISE)
    np.testing.assert_allclose(c.std, d.std, rtol=1e-10)
    noise = json.loads(json.dumps(a.to_dict(), allow_nan=False))["noise"]
    assert noise["position_mm"] == pytest.approx(list(0.08 / np.sqrt(w)))
    assert "(per pose)" in a.summary().splitlines()[0]
    with pytest.raises(ValueError, match=r"noise\.position_mm .*\(8,\), got shape \(5,\)"):
        analyze_uncertainty(cdra, poses, NoiseModel(jnp.full(5, 0.08), 1e-3))
    with pytest.raises(ValueError, match=r"noise\.position_mm .*\(8,\), got shape \(5,\)"):
        predicted_pose_covariance(cdra, poses, NoiseModel(jnp.full(5, 0.08), 1e-3))
    with pytest.raises(ValueError, match=r"noise\.rotation_rad must be positive.*pose 2"):
        analyze_uncertainty(cdra, poses, NoiseModel(0.08, np.array([1e-3] * 2 + [0.0] * 6)))
    T = tool_pose(cdra, poses)
    for call in (
        lambda: analyze_uncertainty(cdra, poses, NOISE, T[:5]),
        lambda: predicted_pose_covariance(cdra, poses, NOISE, None, T[:5]),
    ):
        with pytest.raises(ValueError, match=r"measured .*\(8, 4, 4\), got \(5, 4, 4\)"):
            call()
    with pytest.raises(ValueError, match=r"q_eval must have shape \(k, 7\)"):
        analyze_uncertainty(cdra, poses, NOISE, q_eval=poses[:, :6])


def test_cramer_rao_bound_directions(cdra, poses):
    e = np.eye(cdra.n_params)
    one = cramer_rao_bound(cdra, poses, NOISE, e[0])  # a single direction: a scalar
    assert np.shape(one) == ()
    # ... the first of k = 3 rows (the shape of test_cramer_rao_bound: the same program)
    assert float(one) == pytest.approx(float(cramer_rao_bound(cdra, poses, NOISE, e[:3])[0]))
    unc = parameter_covariance(cdra, poses, NOISE)
    assert float(unc.bound(e[0])) == pytest.approx(float(one))
    for bad in (np.eye(23), np.zeros(()), np.zeros((3, 25))):
        with pytest.raises(ValueError, match=r"directions must have shape \(k, n_params\)"):
            cramer_rao_bound(cdra, poses, NOISE, bad)
    with pytest.raises(ValueError, match="directions"):
        unc.identifiable(np.eye(23))


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
