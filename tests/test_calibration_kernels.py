"""The fast paths of the calibration solvers against the reference implementations.

* :mod:`cdra_jax.calibration.kernels` (pose-last Eq. 7-9) against :mod:`cdra_jax.lie` and
  :func:`cdra_jax.calibration.stacked_system`;
* the normal-equation step (:func:`.linear.min_norm_solve_normal`) against the SVD
  pseudo-inverse;
* the analytic LM Jacobian against ``jax.jacfwd``;
* the fast paper solver against its SVD-step variant, also where it has to redo trials.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdra_jax import lie, simulation
from cdra_jax.arm import apply_frame_errors, module_poses, tool_pose
from cdra_jax.calibration import (
    NoiseModel,
    calibrate_lm,
    calibrate_paper,
    default_rcond,
    deviation_metrics,
    gauss_newton,
    kernels,
    residual_twist,
    stacked_system,
    whitening,
)
from cdra_jax.calibration.kernels import residual_jacobian
from cdra_jax.calibration.linear import (
    RESOLVED_PIVOT,
    min_norm_lstsq,
    min_norm_solve_normal,
    normal_cutoff,
    normal_equations_apply,
    pivoted_cholesky,
)

NOISE = NoiseModel(position_mm=0.05, rotation_rad=1e-3)


@eqx.filter_jit
def _simulate(arm, keys, noise):
    """:func:`simulation.simulate_trial` of 15 poses with ``noise`` for each key, and for each
    trial the module poses pose-last ``P``, the measured poses as :func:`kernels.pose_stack`,
    and the poses without the noise, both ways: one compiled simulation for the module."""

    def one(k):
        q, T, _, _, X = simulation.simulate_trial(k, arm, 15, noise=noise)
        P = jnp.moveaxis(module_poses(arm, q)[..., :3, :], 0, -1)
        T_clean = tool_pose(apply_frame_errors(arm, X), q)
        return q, T, P, kernels.pose_stack(T), X, T_clean, kernels.pose_stack(T_clean)

    return jax.vmap(one)(keys)


@pytest.fixture(scope="module")
def trials(cdra):
    """48 trials of 15 poses of the paper's arm, as :func:`_simulate` gives them (``NOISE``),
    as numpy arrays."""
    keys = jax.random.split(jax.random.PRNGKey(11), 48)
    return tuple(np.asarray(x) for x in _simulate(cdra, keys, NOISE))


def _problem(trials, i, noisy=True):
    """Trial ``i`` of ``trials``: ``(q, T, P, Ts, X)``, measured with ``NOISE`` or without."""
    q, T, P, Ts, X, T_clean, Ts_clean = (x[i] for x in trials)
    return (q, T, P, Ts, X) if noisy else (q, T_clean, P, Ts_clean, X)


@eqx.filter_jit
def _both_normal_equations(frames, P, Ts, noise):
    """:func:`kernels.normal_equations` and those of :func:`kernels.linearise`."""
    tool, after = kernels.chain(frames, P)
    Y = kernels.residual(Ts, tool)
    Y = Y if noise is None else kernels.whiten(Y, Ts, noise)
    fast = kernels.normal_equations(after, Y, Ts, noise)
    return fast, kernels.linearise(frames, P, Ts, noise).normal_equations()


@eqx.filter_jit
def _metrics(arm, q, T):
    """The deviation metrics (Eqs. 20-21) of the arm's tool poses at ``q`` from ``T``."""
    return deviation_metrics(T, tool_pose(arm, q))


@pytest.mark.parametrize("noise", [None, NOISE], ids=["paper", "weighted"])
def test_linearise_is_the_stacked_system(cdra, trials, noise):
    q, T, P, Ts, X = _problem(trials, 1)
    frames = apply_frame_errors(cdra, 0.5 * X).frames  # not the nominal model
    lin = eqx.filter_jit(kernels.linearise)(frames, P, Ts, noise)
    Y, D = (
        np.asarray(x) for x in eqx.filter_jit(stacked_system)(cdra.with_frames(frames), q, T, noise)
    )
    Yk, Dk = lin.stacked()
    scale = float(np.max(np.abs(D)))
    np.testing.assert_allclose(Yk, Y, rtol=0, atol=1e-12 * max(1.0, float(np.max(np.abs(Y)))))
    np.testing.assert_allclose(Dk, D, rtol=0, atol=1e-13 * scale)
    N, g = lin.normal_equations()
    np.testing.assert_allclose(N, D.T @ D, rtol=0, atol=1e-13 * scale**2)
    np.testing.assert_allclose(g, D.T @ Y, rtol=1e-12, atol=1e-12 * scale)
    # The same from the nonzero rows only (the fast step's; weighted: per-pose noise).
    nm = None if noise is None else NoiseModel(np.linspace(0.04, 0.06, 15), 1e-3)
    (N_s, g_s), (N_d, g_d) = _both_normal_equations(frames, P, Ts, nm)
    np.testing.assert_allclose(N_s, N_d, rtol=0, atol=1e-13 * float(np.abs(N_d).max()))
    np.testing.assert_allclose(g_s, g_d, rtol=0, atol=1e-13 * float(np.abs(g_d).max()))
    # Eqs. 20-21 (the rotation metric from the residual's logarithm).
    dp, dR = _metrics(cdra.with_frames(frames), q, T)
    np.testing.assert_allclose([lin.delta_p, lin.delta_R], [dp, dR], rtol=1e-12)


@eqx.filter_jit
def _whitenings(Y, T, Ts, noise):
    """:func:`kernels.whiten` of ``Y (15, 6)`` (pose-last) and the model's whitening of it."""
    expected = jnp.einsum("kij,kj->ki", whitening(T, noise), Y)
    return kernels.whiten(Y.T, Ts, noise).T, expected


def test_whiten_is_model_whitening(trials):
    _, T, _, Ts, _ = _problem(trials, 2)
    Y = np.random.default_rng(0).normal(size=(15, 6))
    got, expected = _whitenings(Y, T, Ts, NOISE)
    np.testing.assert_allclose(got, expected, rtol=1e-13, atol=1e-13)


@functools.cache
def _rotations():
    rng = np.random.default_rng(0)
    w = rng.normal(size=(200, 3))
    w = w / np.linalg.norm(w, axis=-1, keepdims=True)
    angles = np.concatenate(
        [rng.uniform(0, np.pi, 150), [0.0, 1e-12, 1e-7, 1e-3, 0.1, np.pi - 1e-9, np.pi]]
        + [np.full(43, np.pi - 1e-6)]
    )
    return lie.so3_exp(jnp.asarray(w * angles[:, None]))


def test_so3_log_is_lie_so3_log():
    R = _rotations()
    w, angle_sq = jax.jit(kernels.so3_log)(jnp.moveaxis(R, 0, -1))
    expected = np.asarray(lie.so3_log(R))
    np.testing.assert_allclose(w.T, expected, rtol=0, atol=1e-14)
    np.testing.assert_allclose(angle_sq, np.sum(expected**2, axis=-1), rtol=1e-14, atol=1e-300)


def test_se3_log_is_lie_se3_log():
    R = _rotations()
    p = np.random.default_rng(1).normal(size=(R.shape[0], 3)) * 300.0
    T = lie.make_pose(R, p)
    got = jax.jit(kernels.se3_log)(jnp.moveaxis(T[:, :3], 0, -1)).T
    np.testing.assert_allclose(got, lie.se3_log(T), rtol=1e-12, atol=1e-11)


def _left_jacobian_autodiff(xi):
    inv = lie.inverse(lie.se3_exp(xi))
    return jax.jacfwd(lambda e: lie.se3_log(lie.se3_exp(xi + e) @ inv))(jnp.zeros(6))


def test_se3_left_jacobian_is_the_derivative_of_exp():
    rng = np.random.default_rng(3)
    scales = [[30.0] * 3 + [1.0] * 3, [1.0] * 3 + [0.05] * 3, [1.0] * 3 + [1e-5] * 3]
    xis = np.concatenate([rng.normal(size=(8, 6)) * s for s in scales])
    # Both sides of the small-angle switch, zero rotation, and rotations near pi.
    edges = [[1, 2, 3, 0, 0, 0], [1, 2, 3, 0.0999, 0, 0], [1, 2, 3, 0.1001, 0, 0]]
    edges += [[1, 2, 3, 1e-9, 0, 0], [1, -2, 3, 3.0, 0.9, -0.4], [-3, 2, 1, 0, 0, 3.1]]
    xis = np.concatenate([xis, edges])
    xis = jnp.asarray(xis)
    J = jnp.moveaxis(jax.jit(kernels.se3_left_jacobian)(xis.T), -1, 0)
    J_inv = jnp.moveaxis(jax.jit(kernels.se3_left_jacobian_inverse)(xis.T), -1, 0)
    ref = jax.jit(jax.vmap(_left_jacobian_autodiff))(xis)
    np.testing.assert_allclose(J, ref, rtol=0, atol=1e-12 * float(jnp.max(jnp.abs(ref))))
    np.testing.assert_allclose(J_inv @ ref, np.broadcast_to(np.eye(6), ref.shape), atol=1e-12)
    # The inverse's blocks in closed form against the inverse of J's: B = -J^-1 Q J^-1.
    Jb, Qb = kernels.se3_left_jacobian_blocks(xis.T)
    Ji, B = kernels.se3_left_jacobian_inverse_blocks(xis.T)
    Ji, B, Jb, Qb = (np.moveaxis(np.asarray(m), -1, 0) for m in (Ji, B, Jb, Qb))
    np.testing.assert_allclose(Ji @ Jb, np.broadcast_to(np.eye(3), Jb.shape), atol=1e-13)
    np.testing.assert_allclose(B, -Ji @ Qb @ Ji, rtol=0, atol=1e-13 * np.abs(B).max())


@eqx.filter_jit
def _reference_residual(arm, q, T, X, noise):
    """The residual of :func:`residual_jacobian` from the reference model (component-major),
    and its ``jax.jacfwd`` at ``X``."""

    def residual(X):
        Y = residual_twist(T, tool_pose(apply_frame_errors(arm, X), q))
        if noise is not None:
            Y = jnp.einsum("kij,kj->ki", whitening(T, noise), Y)
        return Y.T.reshape(-1)  # component-major, as residual_jacobian

    return residual(X), jax.jacfwd(residual)(X)


@pytest.mark.parametrize("noise", [None, NOISE], ids=["paper", "weighted"])
def test_lm_jacobian_is_the_derivative_of_the_residual(cdra, trials, noise):
    q, T, P, Ts, X = _problem(trials, 3)
    X = 0.7 * X + 0.01  # away from the solution and from zero
    r, (dp, dR), J = _residual_jacobian(X, cdra.frames, P, Ts, noise)
    r_ref, ref = (np.asarray(x) for x in _reference_residual(cdra, q, T, X, noise))
    np.testing.assert_allclose(r, r_ref, rtol=0, atol=1e-11)
    np.testing.assert_allclose(J, ref, rtol=0, atol=1e-13 * float(np.max(np.abs(ref))))
    # LM's normal equations without J, for a step on the left of the frames exp(X) F (its
    # Jacobian: the one above at X = 0 about those frames): J^T J, J^T r.
    frames = lie.se3_exp(X.reshape(-1, 6)) @ cdra.frames
    r0, _, J0 = (np.asarray(x) for x in _residual_jacobian(np.zeros_like(X), frames, P, Ts, noise))
    np.testing.assert_allclose(r0, r, rtol=0, atol=1e-11)
    N, g, rw = _lm_normal_equations(frames, P, Ts, noise)
    np.testing.assert_allclose(rw.reshape(-1), r0, rtol=0, atol=1e-13)
    np.testing.assert_allclose(N, J0.T @ J0, rtol=0, atol=1e-12 * float(np.abs(N).max()))
    np.testing.assert_allclose(g, J0.T @ r0, rtol=0, atol=1e-12 * float(np.abs(g).max()))


_residual_jacobian = eqx.filter_jit(residual_jacobian)


@eqx.filter_jit
def _lm_normal_equations(frames, P, Ts, noise):
    tool, after = kernels.chain(frames, P)
    return kernels.lm_normal_equations(after, kernels.residual(Ts, tool), Ts, noise)


# --------------------------------------------------------------------------- normal equations


def _rank_deficient(seed, rows=90, n=24, null=2):
    rng = np.random.default_rng(seed)
    D = rng.normal(size=(rows, n)) * np.logspace(0, -3, n)  # graded, condition ~1e3
    D[:, :null] = D[:, null : 2 * null] @ rng.normal(size=(null, null))
    return D, rng.normal(size=rows)


def test_pivoted_cholesky_factorises_and_reveals_the_rank():
    D, _ = _rank_deficient(0, null=3)
    N = D.T @ D
    L, rank = jax.jit(pivoted_cholesky)(N, normal_cutoff(np.float64))
    assert int(rank) == 21
    np.testing.assert_allclose(L @ L.T, N, rtol=0, atol=1e-14 * np.abs(N).max())
    assert np.all(np.asarray(L)[:, 21:] == 0)  # the dropped steps are the trailing columns
    assert int(jax.jit(pivoted_cholesky)(np.zeros((5, 5)), 1e-11)[1]) == 0


_min_norm_solve_normal = jax.jit(min_norm_solve_normal)
_min_norm_lstsq = jax.jit(min_norm_lstsq)


def test_min_norm_solve_normal_is_the_pseudo_inverse():
    for seed in range(4):
        D, Y = _rank_deficient(seed)
        x, rank, smallest = _min_norm_solve_normal(D.T @ D, D.T @ Y)
        expected = np.linalg.pinv(D, rcond=1e-10) @ Y
        assert int(rank) == 22
        assert 1e-9 < float(smallest) < 1.0
        np.testing.assert_allclose(x, expected, rtol=0, atol=1e-11 * np.abs(expected).max())
        _, null_space = np.linalg.eigh(D.T @ D)
        assert np.abs(null_space[:, :2].T @ np.asarray(x)).max() < 1e-11 * np.abs(expected).max()
        x_svd, rank_svd, _ = _min_norm_lstsq(D, Y)
        assert int(rank_svd) == 22
        np.testing.assert_allclose(x, x_svd, rtol=0, atol=1e-11 * np.abs(expected).max())


def test_normal_cutoff():
    assert normal_cutoff(np.float64) == pytest.approx(default_rcond(np.float64))
    assert normal_cutoff(np.float64, 1e-3) == pytest.approx(1e-6)
    assert normal_cutoff(np.float64, 1e-12) == normal_cutoff(np.float64)  # the floor


def test_fast_steps_apply_in_float64_with_enough_rows():
    """The normal-equation steps and basis: float64, the default rcond, > 1.5 n rows."""
    assert normal_equations_apply(np.float64, None, 42, 24)
    assert not normal_equations_apply(np.float64, None, 36, 24)  # 6 CDRA poses: SVD steps
    assert not normal_equations_apply(np.float64, 1e-10, 90, 24)
    assert not normal_equations_apply(np.float32, None, 90, 24)


# --------------------------------------------------------------------------- the paper solver


@eqx.filter_jit
def _smallest_pivot(arm, q, T):
    def one(qq, tt):
        P = jnp.moveaxis(module_poses(arm, qq)[..., :3, :], 0, -1)
        lin = kernels.linearise(arm.frames, P, kernels.pose_stack(tt))
        return min_norm_solve_normal(*lin.normal_equations())[2]

    return jax.vmap(one)(q, T)


@pytest.fixture(scope="module")
def trials7(cdra, trials):
    """The noise-free first 7 poses of ``trials`` (42 rows, the fewest for which the fast step
    is tried: 48 sets), shared by the fast-path tests, with the smallest pivots of their normal
    equations at the nominal model."""
    q, T = trials[0][:, :7], trials[5][:, :7]
    return q, T, np.asarray(_smallest_pivot(cdra, q, T))


@pytest.fixture(scope="module")
def exact7(cdra, trials7):
    """The SVD-step paper solves of ``trials7`` (an explicit rcond; the default chunk size)."""
    q, T, _ = trials7
    return _batch(cdra, q, T, True)


@eqx.filter_jit
def _batch(arm, q, T, exact):
    # An explicit rcond (here the default value) selects the SVD step.
    rcond = default_rcond(jnp.float64) if exact else None
    return jax.vmap(lambda qq, tt: calibrate_paper(arm, qq, tt, rcond=rcond, throw=False))(q, T)


@pytest.mark.slow
@pytest.mark.parametrize("chunk_size", [128, 5])
def test_fast_paper_solver_is_the_svd_solver(cdra, trials7, exact7, chunk_size, monkeypatch):
    """7 poses (42 rows, the fewest for which the fast step is tried): some sets have an
    identifiable direction that the normal equations do not resolve (pivot below
    RESOLVED_PIVOT, or dropped): those are redone with SVD steps, in one chunk, or (chunks of
    5) gathered from several chunks into chunks of their own."""
    q, T, smallest = trials7
    monkeypatch.setattr(gauss_newton, "CHUNK_SIZE", chunk_size)
    # Both paths are exercised: some sets are resolved at the nominal model, some are not.
    resolved = smallest >= RESOLVED_PIVOT
    assert 0 < resolved.sum() < resolved.size
    # A fresh jit: the chunk size is read when the solver is traced. The reference is the SVD
    # solver (an explicit rcond), compiled once for the module.
    fast = eqx.filter_jit(lambda *a: _batch.__wrapped__(*a))(cdra, q, T, False)
    exact = exact7
    np.testing.assert_array_equal(fast.iterations, exact.iterations)
    np.testing.assert_array_equal(fast.rank, exact.rank)
    np.testing.assert_array_equal(fast.result._value, exact.result._value)
    for field in ("frames", "errors", "delta_p", "singular_values"):
        a, b = np.asarray(getattr(fast, field)), np.asarray(getattr(exact, field))
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-8, err_msg=field)


@pytest.mark.slow
def test_lm_fast_steps_are_redone_where_unresolved(cdra, trials7, monkeypatch):
    """LM's fast steps (the damped normal equations with the structural null space known),
    and SVD steps for the trials (7 poses: some sets) whose pivots are not resolved or whose
    rank differs, gathered from chunks of 5: the rank and the result codes are those of SVD
    steps everywhere (an explicit ``rcond``), the identifiable results (base and tool errors,
    the final deviations) equal to rounding. The frames' unidentifiable components follow the
    path of the multiplicative steps, which the two damped solves share to ``O(lambda)``:
    within 1e-6 mm."""
    from cdra_jax.calibration import levenberg_marquardt

    monkeypatch.setattr(levenberg_marquardt, "CHUNK_SIZE", 5)
    q, T, smallest = trials7
    assert 0 < (smallest >= RESOLVED_PIVOT).sum() < smallest.size

    def batch(rcond):
        f = jax.vmap(lambda qq, tt: calibrate_lm(cdra, qq, tt, rcond=rcond, throw=False))
        return eqx.filter_jit(f)(q, T)

    fast, exact = batch(None), batch(default_rcond(jnp.float64))
    np.testing.assert_array_equal(fast.rank, exact.rank)
    np.testing.assert_array_equal(fast.result._value, exact.result._value)
    assert np.all(np.asarray(fast.converged))
    assert np.abs(np.asarray(fast.iterations) - np.asarray(exact.iterations)).max() <= 1
    ends = [0, -1]  # base and tool: identifiable
    a, b = np.asarray(fast.errors)[:, ends], np.asarray(exact.errors)[:, ends]
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-8)
    np.testing.assert_allclose(_final(fast.delta_p), _final(exact.delta_p), rtol=0, atol=1e-8)
    np.testing.assert_allclose(np.asarray(fast.frames), np.asarray(exact.frames), rtol=0, atol=1e-6)


def _final(history):
    """The last recorded value of each trial's ``(N, iterations + 1)`` history."""
    h = np.asarray(history)
    last = np.sum(np.isfinite(h), axis=1) - 1
    return h[np.arange(h.shape[0]), last]


def test_lm_first_step_is_the_gauss_newton_step(cdra, trials):
    """LM starts at damping 1e-6 (INITIAL_DAMPING): its first move is a full Gauss-Newton step
    (with a damping of 1 it would be about half of one), and the noise-free solve needs about
    as many steps as the paper's. The step is LM's exact-Jacobian one, which differs from the
    paper's first-order step by the derivative of the logarithm at the nominal residual
    (1 mm / 0.05 rad errors: ~1 %)."""
    q, T, _, _, _ = _problem(trials, 5, noisy=False)
    lm = eqx.filter_jit(calibrate_lm)(cdra, q, T)
    paper = eqx.filter_jit(calibrate_paper)(cdra, q, T)
    np.testing.assert_allclose(lm.step_norm[0], paper.step_norm[0], rtol=0.05)
    assert int(lm.iterations) <= int(paper.iterations) + 2
