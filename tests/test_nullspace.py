"""The analytic structural null space of the calibration Jacobian (:mod:`.calibration.nullspace`)
and the solver paths built on it: the null-space step, the SVD redo where the data lose more,
``singular_values=False`` and ``predictive_stop``."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdra_jax import arm as arm_lib
from cdra_jax import lie, simulation
from cdra_jax.arm import tool_pose
from cdra_jax.calibration import (
    NoiseModel,
    calibrate_lm,
    calibrate_paper,
    default_rcond,
    min_norm_lstsq,
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
    frames = lie.from_xyz_rotvec(
        jnp.asarray(rng.normal(size=(k1, 3)) * 200.0), jnp.asarray(rng.normal(size=(k1, 3)))
    )
    return arm_lib.Arm(
        frames=frames, modules=tuple(mods), frame_names=tuple(f"f{j}" for j in range(k1))
    )


def _data(arm, seed, m, noise=None):
    q = arm_lib.sample_states(jax.random.PRNGKey(seed), arm, m)
    T = tool_pose(arm, q)
    return q, T


@pytest.mark.parametrize("seed", range(12))
def test_null_basis_is_the_svd_null_space_on_random_arms(seed):
    """``D Z = 0`` at random frames and poses, ``Z`` orthonormal, and its dimension is the
    numerical nullity of ``D`` (generic poses, 30 of them), also away from the arm's frames."""
    arm = random_arm(seed)
    # frames moved off the arm's own: the basis follows the current frames
    moved = arm.with_frames(lie.se3_exp(jnp.full((len(arm.frame_names), 6), 0.1)) @ arm.frames)
    for a in (arm, moved):
        q, T = _data(a, seed, 30)
        _, D = stacked_system(a, q, T, NoiseModel(0.05, 1e-3) if seed % 2 else None)
        D = np.asarray(D)
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


def test_default_arm_null_space_is_the_elbow_axis(cdra):
    """The paper's arm: rank 22 of 24, the two elbow-axis directions."""
    assert structural_nullity(cdra) == 2
    Z = np.asarray(structural_null_space(cdra))
    # only upper_arm (block 1) and forearm (block 2) are involved
    assert np.abs(Z[:6]).max() == 0 and np.abs(Z[18:]).max() == 0


@pytest.mark.parametrize("seed", range(6))
def test_null_space_solve_is_the_pseudo_inverse_step(seed):
    arm = random_arm(100 + seed)
    q, T = _data(arm, seed, 25)
    frames = (
        lie.se3_exp(
            jnp.asarray(np.random.default_rng(seed).normal(size=(len(arm.frame_names), 6)) * 0.01)
        )
        @ arm.frames
    )
    Y, D = stacked_system(arm.with_frames(frames), q, T, NoiseModel(0.05, 1e-3))
    x_ref, _, _ = min_norm_lstsq(D, Y)
    Z = structural_null_space(arm, frames)
    x, smallest, structural = null_space_solve(D.T @ D, D.T @ Y, Z)
    assert float(smallest) >= RESOLVED_PIVOT and float(structural) <= STRUCTURAL_TOL
    np.testing.assert_allclose(
        np.asarray(x), np.asarray(x_ref), rtol=0, atol=1e-9 * float(np.abs(x_ref).max())
    )
    if Z.shape[1]:
        assert np.abs(np.asarray(Z).T @ np.asarray(x)).max() < 1e-12 * np.abs(np.asarray(x)).max()


def test_null_space_solve_flags_data_rank_deficiency(cdra):
    """Poses repeated: the data lose more than the structural directions; the bound says so."""
    q, T = _data(cdra, 0, 3)
    q, T = jnp.tile(q, (3, 1)), jnp.tile(T, (3, 1, 1))  # 9 poses, 3 distinct
    Y, D = stacked_system(cdra, q, T)
    _, smallest, _ = null_space_solve(D.T @ D, D.T @ Y, structural_null_space(cdra))
    assert not float(smallest) >= RESOLVED_PIVOT  # tiny, or NaN


@eqx.filter_jit
def _solves(arm, q, T, noise, kw_a, kw_b, solve=None):
    def one(qq, tt, kw):
        return (solve or calibrate_paper)(arm, qq, tt, noise, throw=False, **kw)

    a = jax.vmap(lambda qq, tt: one(qq, tt, dict(kw_a)))(q, T)
    b = jax.vmap(lambda qq, tt: one(qq, tt, dict(kw_b)))(q, T)
    return a, b


def _frozen(**kw):
    return tuple(sorted(kw.items()))


@pytest.mark.slow
def test_degenerate_pose_sets_are_redone_with_svd_steps(cdra):
    """Pose sets of 8-9 poses whose data lose directions beyond the structural ones (repeated
    poses) fail the null-space step's test and are solved again with SVD steps, mixed in one
    batch with generic ones: everything as the SVD solver (an explicit ``rcond``)."""
    qs, Ts = [], []
    for seed in range(6):
        q, T, _, _, _ = simulation.simulate_trial(jax.random.PRNGKey(seed), cdra, 9)
        if seed % 2:  # 3 distinct poses, each three times
            q, T = jnp.tile(q[:3], (3, 1)), jnp.tile(T[:3], (3, 1, 1))
        qs.append(q)
        Ts.append(T)
    q, T = jnp.stack(qs), jnp.stack(Ts)
    fast, exact = _solves(cdra, q, T, None, _frozen(), _frozen(rcond=default_rcond(jnp.float64)))
    np.testing.assert_array_equal(fast.rank, exact.rank)
    assert set(np.asarray(fast.rank)[1::2]) != {22} and set(np.asarray(fast.rank)[::2]) == {22}
    np.testing.assert_array_equal(fast.result._value, exact.result._value)
    np.testing.assert_array_equal(fast.iterations, exact.iterations)
    for field in ("frames", "errors", "delta_p", "singular_values"):
        a, b = np.asarray(getattr(fast, field)), np.asarray(getattr(exact, field))
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-8, err_msg=field)


@pytest.mark.slow
@pytest.mark.parametrize("kinds", [("prismatic", "revolute", "spherical"), ("revolute",) * 4])
def test_random_arm_calibration_is_the_svd_solution(kinds):
    """Calibrations of arms with prismatic and several revolute modules (4-6 structural null
    directions): the null-space steps give the SVD solver's frames."""
    arm = random_arm(7, kinds)
    X = jnp.asarray(np.random.default_rng(7).uniform(-1, 1, (3, len(arm.frame_names), 6)))
    X = X * jnp.asarray([1.0, 1.0, 1.0, 0.02, 0.02, 0.02])
    q = jnp.stack([arm_lib.sample_states(jax.random.PRNGKey(t), arm, 20) for t in range(3)])
    truth = jax.vmap(lambda x: lie.se3_exp(x) @ arm.frames)(X)
    T = jax.vmap(lambda fr, qq: tool_pose(arm.with_frames(fr), qq))(truth, q)
    fast, exact = _solves(arm, q, T, None, _frozen(), _frozen(rcond=default_rcond(jnp.float64)))
    assert np.all(np.asarray(fast.converged))
    np.testing.assert_array_equal(fast.rank, arm.n_params - structural_nullity(arm))
    np.testing.assert_array_equal(fast.iterations, exact.iterations)
    np.testing.assert_allclose(np.asarray(fast.frames), np.asarray(exact.frames), atol=1e-8)


@pytest.fixture(scope="module")
def paper15(cdra):
    keys = jax.random.split(jax.random.PRNGKey(3), 32)
    out = {}
    for name, noise in (("clean", None), ("noisy", NoiseModel(0.08, 1e-3))):
        sim = jax.vmap(
            lambda k, noise=noise: simulation.simulate_trial(k, cdra, 15, noise=noise, m_verify=5)
        )
        q, T, q_ver, _, _ = jax.jit(sim)(keys)
        out[name] = (q, T, q_ver, noise)
    return out


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

    def predict(frames):
        return jax.vmap(lambda fr, qq: tool_pose(cdra.with_frames(fr), qq))(frames, q_ver)

    np.testing.assert_allclose(
        np.asarray(predict(new.frames)), np.asarray(predict(ref.frames)), rtol=0, atol=1e-8
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

    def predict(frames):
        return jax.vmap(lambda fr, qq: tool_pose(cdra.with_frames(fr), qq))(frames, q_ver)

    np.testing.assert_allclose(
        np.asarray(predict(new.frames)), np.asarray(predict(ref.frames)), rtol=0, atol=1e-8
    )
