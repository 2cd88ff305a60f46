"""The analytic structural null space of the calibration Jacobian (:mod:`.calibration.nullspace`)
and the solver paths built on it: the null-space step, the SVD redo where the data lose more,
``singular_values=False`` and ``predictive_stop``."""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cdra_jax import arm as arm_lib
from cdra_jax import lie, simulation
from cdra_jax.arm import tool_pose
from cdra_jax.calibration import (
    NoiseModel,
    calibrate_lm,
    calibrate_paper,
    default_rcond,
    min_norm_lstsq,
    nullspace,
    stacked_system,
)
from cdra_jax.calibration.linear import (
    RESOLVED_PIVOT,
    STRUCTURAL_TOL,
    null_space_solve,
)
from cdra_jax.calibration.nullspace import (
    null_directions,
    null_generators,
    structural_null_space,
    structural_nullity,
)

KINDS = ("spherical", "revolute", "prismatic")


def _pose(xyz, rotvec):
    """Poses ``(..., 4, 4)`` from translations and rotation vectors (scipy's ``Rotation``: test
    data without a compiled program per shape)."""
    xyz, rotvec = (np.array(a) for a in np.broadcast_arrays(np.asarray(xyz, float), rotvec))
    T = np.broadcast_to(np.eye(4), rotvec.shape[:-1] + (4, 4)).copy()
    T[..., :3, :3] = (
        Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_matrix().reshape(T[..., :3, :3].shape)
    )
    T[..., :3, 3] = xyz
    return T


def _tool_poses(arm: arm_lib.Arm, frames: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Tool poses ``(m, 4, 4)`` of ``arm`` with ``frames`` at states ``q (m, dof)`` (numpy:
    test data)."""
    T, j = frames[0], 0
    for i, mod in enumerate(arm.modules):
        qi = q[:, j : j + mod.dof]
        j += mod.dof
        axis = np.asarray(mod.axis)
        if mod.kind == "spherical":
            M = _pose(np.zeros(3), qi)
        elif mod.kind == "revolute":
            M = _pose(np.zeros(3), qi * axis)
        else:
            M = _pose(qi * axis, np.zeros(3))
        T = T @ M @ frames[i + 1]
    return T


def random_arm(seed: int, kinds: tuple[str, ...] | None = None) -> arm_lib.Arm:
    """An arm of 1-5 random modules (or ``kinds``) with random frames (|p| ~ 200 mm)."""
    rng = np.random.default_rng(seed)
    if kinds is None:
        kinds = tuple(rng.choice(KINDS, size=int(rng.integers(1, 6))))
    mods = []
    for i, kind in enumerate(kinds):
        if kind == "spherical":
            mods.append(arm_lib.spherical(f"m{i}"))
        elif kind == "revolute":
            mods.append(arm_lib.revolute(f"m{i}", rng.normal(size=3)))
        else:
            mods.append(arm_lib.prismatic(f"m{i}", rng.normal(size=3)))
    k1 = len(kinds) + 1
    frames = _pose(rng.normal(size=(k1, 3)) * 200.0, rng.normal(size=(k1, 3)))
    return arm_lib.Arm(
        frames=jnp.asarray(frames),
        modules=tuple(mods),
        frame_names=tuple(f"f{j}" for j in range(k1)),
    )


_NOISE = NoiseModel(0.05, 1e-3)
_SHIFT = _pose(np.full(3, 0.1), np.full(3, 0.1))
"""Each frame is moved by this pose to take the arm off its own frames."""


@functools.cache
def _random_arm_data(seed: int) -> tuple[arm_lib.Arm, np.ndarray]:
    """``random_arm(seed)`` and 30 generic states (uniform within the limits)."""
    arm = random_arm(seed)
    lim = arm.state_limits
    u = np.random.default_rng(seed).uniform(size=(30, arm.dof))
    return arm, lim[:, 0] + u * (lim[:, 1] - lim[:, 0])


@pytest.mark.parametrize("seed", range(12))
def test_null_basis_is_the_svd_null_space_on_random_arms(seed):
    """``D Z = 0`` at random frames and poses, ``Z`` orthonormal, and its dimension is the
    numerical nullity of ``D`` (generic poses, 30 of them), also away from the arm's frames;
    odd seeds whitened."""
    # Eagerly: the package's small operations are compiled once per shape and shared by the
    # arms (compiled whole, one program per arm, the null spaces of many modules cost more).
    arm, q = _random_arm_data(seed)
    frames = np.asarray(arm.frames)
    for a in (arm, arm.with_frames(_SHIFT @ frames)):
        T = _tool_poses(a, np.asarray(a.frames), q)
        D = np.asarray(stacked_system(a, q, T, _NOISE if seed % 2 else None)[1])
        Z = np.asarray(structural_null_space(a))
        k = structural_nullity(a)
        assert Z.shape == (a.n_params, k)
        np.testing.assert_allclose(Z.T @ Z, np.eye(k), atol=1e-12)
        s, Vt = np.linalg.svd(D)[1:]
        nullity = int(np.sum(s < default_rcond(np.float64) * s[0]))
        assert nullity == k, (seed, [m.kind for m in a.modules])
        scale = np.abs(D).max()
        assert np.abs(D @ Z).max() <= 1e-13 * scale if k else True
        if k:  # the same subspace as the SVD's
            V0 = Vt[a.n_params - k :].T
            np.testing.assert_allclose(Z @ Z.T, V0 @ V0.T, atol=1e-9)
            # Orthonormal also with the columns scaled as null_space_solve scales them
            # (Cholesky QR: accurate while the equilibrated columns are well conditioned)
            B = Z * np.sqrt(np.diag(D.T @ D))[:, None]
            Q = np.asarray(nullspace.orthonormalise(B))
            np.testing.assert_allclose(Q.T @ Q, np.eye(k), atol=1e-13)
            np.testing.assert_allclose(Q @ (Q.T @ B), B, atol=1e-12 * np.abs(B).max())


@pytest.mark.parametrize("k", [3, 12])
def test_orthonormalise_by_householder_is_cholesky_qr(monkeypatch, k):
    """Above ``UNROLLED_COLUMNS`` the basis is a signed Householder QR: the same columns, in
    the same order and orientation, as the unrolled Cholesky QR's (to rounding), for columns
    of very different scales."""
    A = np.random.default_rng(k).normal(size=(42, k)) * np.logspace(0, 3, k)
    monkeypatch.setattr(nullspace, "UNROLLED_COLUMNS", 64)
    cholesky = np.asarray(nullspace.orthonormalise(A))
    np.testing.assert_allclose(cholesky.T @ cholesky, np.eye(k), atol=1e-13)
    monkeypatch.setattr(nullspace, "UNROLLED_COLUMNS", 0)
    assert not nullspace.unrolled(k)
    qr = np.asarray(nullspace.orthonormalise(A))
    np.testing.assert_allclose(qr.T @ qr, np.eye(k), atol=1e-13)
    np.testing.assert_allclose(qr, cholesky, atol=1e-12)


def test_null_space_products_in_both_forms_agree(monkeypatch):
    """The null-space step with the products written column by column and as matrix products
    (``UNROLLED_COLUMNS`` below the nullity): the same step and tests, to rounding."""
    arm, q = _random_arm_data(3)
    T = _tool_poses(arm, np.asarray(arm.frames), q)
    Y, D = stacked_system(arm, q, T, _NOISE)
    Z = np.asarray(structural_null_space(arm))
    N, g = np.asarray(D.T @ D), np.asarray(D.T @ Y)
    k = Z.shape[1]
    assert k > 0
    # Each form compiled whole, by a jit of its own (the form is chosen when traced).
    monkeypatch.setattr(nullspace, "UNROLLED_COLUMNS", k)
    columns = [np.asarray(v) for v in jax.jit(lambda *a: null_space_solve(*a))(N, g, Z)]
    monkeypatch.setattr(nullspace, "UNROLLED_COLUMNS", k - 1)
    matrices = [np.asarray(v) for v in jax.jit(lambda *a: null_space_solve(*a))(N, g, Z)]
    np.testing.assert_allclose(
        matrices[0], columns[0], rtol=0, atol=1e-10 * np.abs(columns[0]).max()
    )
    np.testing.assert_allclose(matrices[1], columns[1], rtol=1e-8)
    np.testing.assert_allclose(matrices[2], columns[2], atol=1e-12)


def test_generators_per_module_kind():
    arm = random_arm(0, ("spherical", "revolute", "prismatic"))
    modules, xi = null_generators(arm)
    assert modules == (1, 1, 2, 2, 2, 2)
    a1, a2 = np.asarray(arm.modules[1].axis), np.asarray(arm.modules[2].axis)
    np.testing.assert_allclose(np.asarray(xi[0]), np.r_[a1, 0, 0, 0])
    np.testing.assert_allclose(np.asarray(xi[1]), np.r_[0, 0, 0, a1])
    np.testing.assert_allclose(np.asarray(xi[5]), np.r_[0, 0, 0, a2])
    A = np.asarray(null_directions(arm.frames, modules, xi))
    # block i + 1 holds xi, block i holds -Ad(F_i) xi
    np.testing.assert_allclose(A[12:18, 0], np.asarray(xi[0]))
    Ad = np.asarray(lie.adjoint(arm.frames[1]))
    np.testing.assert_allclose(A[6:12, 0], -Ad @ np.asarray(xi[0]))
    assert structural_nullity(random_arm(1, ("spherical",) * 3)) == 0
    assert structural_null_space(random_arm(1, ("spherical",) * 3)).shape == (24, 0)


@pytest.fixture(scope="module")
def cdra_repeated_poses_step(cdra):
    """The paper's arm at its own frames, 9 poses, 3 distinct (each three times): its
    structural null space ``Z`` and :func:`null_space_solve`'s ``(x, smallest, structural)``."""
    lim = cdra.state_limits
    q = lim[:, 0] + np.random.default_rng(0).uniform(size=(3, cdra.dof)) * (lim[:, 1] - lim[:, 0])
    q = np.tile(q, (3, 1))
    Y, D = stacked_system(cdra, q, _tool_poses(cdra, np.asarray(cdra.frames), q))
    Z = structural_null_space(cdra)
    return (np.asarray(Z),) + tuple(np.asarray(v) for v in null_space_solve(D.T @ D, D.T @ Y, Z))


def test_default_arm_null_space_is_the_elbow_axis(cdra, cdra_repeated_poses_step):
    """The paper's arm: rank 22 of 24, the two elbow-axis directions."""
    assert structural_nullity(cdra) == 2
    Z = cdra_repeated_poses_step[0]
    assert Z.shape == (24, 2)
    # only upper_arm (block 1) and forearm (block 2) are involved
    assert np.abs(Z[:6]).max() == 0 and np.abs(Z[18:]).max() == 0


@pytest.mark.parametrize("seed", range(6))
def test_null_space_solve_is_the_pseudo_inverse_step(seed):
    """On random arms (those of the null-basis test) at frames off their own, the data
    measured at their own and whitened: the null-space step is the SVD's minimum-norm step,
    orthogonal to the structural null space, and its tests pass."""
    arm, q = _random_arm_data(seed)
    T = _tool_poses(arm, np.asarray(arm.frames), q)
    rng = np.random.default_rng(100 + seed)
    k1 = len(arm.frame_names)
    frames = _pose(rng.normal(size=(k1, 3)) * 0.01, rng.normal(size=(k1, 3)) * 0.01) @ np.asarray(
        arm.frames
    )
    Y, D = stacked_system(arm.with_frames(frames), q, T, _NOISE)
    x_ref = np.asarray(min_norm_lstsq(D, Y)[0])
    Z = structural_null_space(arm, frames)
    x, smallest, structural = null_space_solve(D.T @ D, D.T @ Y, Z)
    x, Z = np.asarray(x), np.asarray(Z)
    assert float(smallest) >= RESOLVED_PIVOT and float(structural) <= STRUCTURAL_TOL
    np.testing.assert_allclose(x, x_ref, rtol=0, atol=1e-9 * float(np.abs(x_ref).max()))
    if Z.shape[1]:
        assert np.abs(Z.T @ x).max() < 1e-12 * np.abs(x).max()


def test_null_space_solve_flags_data_rank_deficiency(cdra_repeated_poses_step):
    """Poses repeated: the data lose more than the structural directions; the bound says so."""
    smallest = cdra_repeated_poses_step[2]
    assert not float(smallest) >= RESOLVED_PIVOT  # tiny, or NaN


@eqx.filter_jit
def _solve(arm, q, T, noise, kw, solve):
    """``solve`` (a solver function) on each trial of ``q (N, m, dof)``, ``T (N, m, 4, 4)``,
    with the options ``kw`` (:func:`_frozen`): one compiled program per solver, options, arm
    and shape, shared by the tests."""
    return jax.vmap(lambda qq, tt: solve(arm, qq, tt, noise, throw=False, **dict(kw)))(q, T)


def _solves(arm, q, T, noise, kw_a, kw_b, solve=calibrate_paper):
    return _solve(arm, q, T, noise, kw_a, solve), _solve(arm, q, T, noise, kw_b, solve)


def _frozen(**kw):
    return tuple(sorted(kw.items()))


@eqx.filter_jit
def _simulate(arm, keys, noise):
    """:func:`simulation.simulate_trial` with ``noise``, 15 calibration and 5 verification poses
    for each key, and the calibration poses without the noise."""

    def one(k):
        q, T, q_ver, _, X = simulation.simulate_trial(k, arm, 15, noise=noise, m_verify=5)
        return q, T, q_ver, tool_pose(arm_lib.apply_frame_errors(arm, X), q)

    return jax.vmap(one)(keys)


@pytest.fixture(scope="module")
def paper15(cdra):
    """32 trials of the paper's problem (15 poses, 5 verification poses): ``clean`` (noise-free),
    ``noisy`` (the same with ``NoiseModel(0.08, 1e-3)``) and ``degenerate`` (the clean trials,
    the odd ones with their first 3 poses each repeated five times instead of 15 poses)."""
    noise = NoiseModel(0.08, 1e-3)
    keys = jax.random.split(jax.random.PRNGKey(3), 32)
    q, T, q_ver, T_clean = (np.asarray(x) for x in _simulate(cdra, keys, noise))
    q_deg, T_deg = q.copy(), T_clean.copy()
    q_deg[1::2] = np.tile(q[1::2, :3], (1, 5, 1))
    T_deg[1::2] = np.tile(T_clean[1::2, :3], (1, 5, 1, 1))
    return {
        "clean": (q, T_clean, q_ver, None),
        "noisy": (q, T, q_ver, noise),
        "degenerate": (q_deg, T_deg, q_ver, None),
    }


@pytest.mark.slow
def test_degenerate_pose_sets_are_redone_with_svd_steps(cdra, paper15):
    """Pose sets of 15 poses whose data lose directions beyond the structural ones (3 distinct
    poses, each five times) fail the null-space step's test and are solved again with SVD
    steps, mixed in one batch with generic ones: everything as the SVD solver (an explicit
    ``rcond``)."""
    q, T, _, _ = paper15["degenerate"]
    fast, exact = _solves(cdra, q, T, None, _frozen(), _frozen(rcond=default_rcond(jnp.float64)))
    np.testing.assert_array_equal(fast.rank, exact.rank)
    assert set(np.asarray(fast.rank)[1::2]) != {22} and set(np.asarray(fast.rank)[::2]) == {22}
    np.testing.assert_array_equal(fast.result._value, exact.result._value)
    np.testing.assert_array_equal(fast.iterations, exact.iterations)
    for field in ("frames", "errors", "delta_p", "singular_values"):
        a, b = np.asarray(getattr(fast, field)), np.asarray(getattr(exact, field))
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-8, err_msg=field)


@eqx.filter_jit
def _random_arm_trials(arm, X, seeds):
    """20 states per seed (``PRNGKey(seed)``) and the tool poses of the arm with its frames
    moved by ``X (N, K+1, 6)``, one trial each."""
    q = jax.vmap(lambda s: arm_lib.sample_states(jax.random.PRNGKey(s), arm, 20))(seeds)
    truth = jax.vmap(lambda x: lie.se3_exp(x) @ arm.frames)(X)
    return q, jax.vmap(lambda fr, qq: tool_pose(arm.with_frames(fr), qq))(truth, q)


@pytest.mark.slow
@pytest.mark.parametrize("kinds", [("prismatic", "revolute", "spherical"), ("revolute",) * 4])
def test_random_arm_calibration_is_the_svd_solution(kinds):
    """Calibrations of arms with prismatic and several revolute modules (4-6 structural null
    directions): the null-space steps give the SVD solver's frames."""
    arm = random_arm(7, kinds)
    X = np.random.default_rng(7).uniform(-1, 1, (3, len(arm.frame_names), 6))
    X = X * np.array([1.0, 1.0, 1.0, 0.02, 0.02, 0.02])
    q, T = _random_arm_trials(arm, jnp.asarray(X), jnp.arange(3))
    fast, exact = _solves(arm, q, T, None, _frozen(), _frozen(rcond=default_rcond(jnp.float64)))
    assert np.all(np.asarray(fast.converged))
    np.testing.assert_array_equal(fast.rank, arm.n_params - structural_nullity(arm))
    np.testing.assert_array_equal(fast.iterations, exact.iterations)
    np.testing.assert_allclose(np.asarray(fast.frames), np.asarray(exact.frames), atol=1e-8)


@eqx.filter_jit
def _predict(arm, frames, q_ver):
    """Tool poses ``(N, m, 4, 4)`` of the arm with each trial's frames at its states."""
    return jax.vmap(lambda fr, qq: tool_pose(arm.with_frames(fr), qq))(frames, q_ver)


@pytest.mark.slow
@pytest.mark.parametrize(
    "case, weighted", [("clean", False), ("noisy", True), ("noisy", False)], ids=str
)
def test_lm_predictive_stop_keeps_the_answers(cdra, paper15, case, weighted):
    """LM's predictive stop on the paper's problem (m = 15): every trial converged, with the
    result codes of the plain stop, no more steps, frames and predicted tool poses within 1e-8
    mm (noise-free: the plain stop takes at most one more step, of about 1e-11; the flat
    unweighted noisy minimum converges linearly and the predictive stop does not apply)."""
    q, T, q_ver, noise = paper15[case]
    noise = noise if weighted else None
    ref, new = _solves(
        cdra, q, T, noise, _frozen(predictive_stop=False), _frozen(), solve=calibrate_lm
    )
    np.testing.assert_array_equal(new.result._value, ref.result._value)
    assert np.all(np.asarray(new.converged))
    assert np.all(np.asarray(new.iterations) <= np.asarray(ref.iterations))
    np.testing.assert_allclose(np.asarray(new.frames), np.asarray(ref.frames), rtol=0, atol=1e-8)
    np.testing.assert_allclose(
        np.asarray(_predict(cdra, new.frames, q_ver)),
        np.asarray(_predict(cdra, ref.frames, q_ver)),
        rtol=0,
        atol=1e-8,
    )


@pytest.mark.slow
@pytest.mark.parametrize("case", ["clean", "noisy"])
@pytest.mark.parametrize("weighted", [False, True], ids=["paper", "weighted"])
def test_predictive_stop_keeps_the_answers(cdra, paper15, case, weighted):
    """The defaults (``predictive_stop``, no ``singular_values``) on the paper's problem
    (m = 15): frames and predicted tool poses within 1e-8 mm of the plain stop, fewer
    iterations, the same rank and result codes, NaN singular values."""
    q, T, q_ver, noise = paper15[case]
    noise = (noise or NoiseModel(0.08, 1e-3)) if weighted else None
    ref, new = _solves(
        cdra, q, T, noise, _frozen(predictive_stop=False, singular_values=True), _frozen()
    )
    np.testing.assert_array_equal(new.rank, ref.rank)
    np.testing.assert_array_equal(new.result._value, ref.result._value)
    assert np.all(np.asarray(new.converged))
    assert np.all(np.isnan(np.asarray(new.singular_values)))
    it_ref, it_new = np.asarray(ref.iterations), np.asarray(new.iterations)
    assert np.all(it_new <= it_ref) and it_new.mean() < it_ref.mean()
    np.testing.assert_allclose(np.asarray(new.frames), np.asarray(ref.frames), rtol=0, atol=1e-8)
    np.testing.assert_allclose(
        np.asarray(_predict(cdra, new.frames, q_ver)),
        np.asarray(_predict(cdra, ref.frames, q_ver)),
        rtol=0,
        atol=1e-8,
    )
