"""Tension closure: exact verdicts and margins against scipy oracles, and the feasible sampler."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import linprog
from scipy.spatial import ConvexHull

from cdra_jax.arm import Arm
from cdra_jax.modules import (
    DEFAULT_MIN_MARGIN,
    arm_closure_margins,
    arm_tension_closure,
    closure_margin,
    hull_margin,
    lever_scale,
    sample_feasible_states,
    structure_matrix,
    tension_closure,
)
from cdra_jax.simulation import sample_poses, sample_states, simulate_trial


def _oracle_closure(A: np.ndarray) -> bool:
    """linprog: is there t >= 1 with A t = 0 (strictly positive null vector), and rank d?"""
    d, n = A.shape
    if np.linalg.matrix_rank(A) < d:
        return False
    res = linprog(np.zeros(n), A_eq=A, b_eq=np.zeros(d), bounds=[(1, None)] * n, method="highs")
    return res.status == 0


def _oracle_margin(A: np.ndarray) -> float:
    """Distance from the origin to the boundary of the convex hull of the columns (inside)."""
    if A.shape[0] == 1:
        return min(A.max(), -A.min())
    hull = ConvexHull(A.T)
    # facets: n . x + c <= 0 inside, with unit normals n; the origin's distance is -c
    return float(np.min(-hull.equations[:, -1]))


_closure = jax.jit(lambda A: (tension_closure(A), hull_margin(A)))
M = 40
R = 4 * M + 16  # rows of every arm-state batch below (the sampler's draw count), one compile
_margins = jax.jit(arm_closure_margins)


def _states(cdra, index, u):
    """Arm states ``(R, dof)`` with module ``index`` at ``u`` and the others at home."""
    q = np.zeros((R, cdra.dof))
    start = sum(m.dof for m in cdra.modules[:index])
    q[:, start : start + cdra.modules[index].dof] = u
    return jnp.asarray(q)


@pytest.mark.parametrize("index", [0, 1, 2])
def test_closure_verdicts_and_margins_agree_with_scipy(cdra, index):
    module = cdra.modules[index]
    lim = np.asarray(module.limits)
    centre, half = lim.mean(1), (lim[:, 1] - lim[:, 0])
    # twice the joint box, so that poses with and without tension closure both occur
    u = np.asarray(
        jax.random.uniform(jax.random.PRNGKey(index), (R, module.dof), minval=-1, maxval=1)
    )
    q = centre + u * half
    A = np.asarray(structure_matrix(module, q))
    verdict, margin = map(np.asarray, _closure(A))
    oracle = np.array([_oracle_closure(a) for a in A])
    assert 5 <= oracle.sum() <= len(oracle) - 5, "both feasible and infeasible poses must occur"
    np.testing.assert_array_equal(verdict, oracle)
    np.testing.assert_array_equal(margin > 0, oracle)
    inside = np.nonzero(oracle)[0][:40]
    np.testing.assert_allclose(margin[inside], [_oracle_margin(A[i]) for i in inside], rtol=1e-9)
    # the dimensionless margin of the arm is this one over the largest lever arm max |a_i|
    scale = np.max(np.linalg.norm(np.asarray(module.cable_platform), axis=-1))
    assert float(lever_scale(module)) == scale
    rel = np.asarray(_margins(cdra, _states(cdra, index, q)))[:, index]
    np.testing.assert_allclose(rel, margin / scale, rtol=1e-12, atol=1e-15)


def test_closure_of_random_planar_and_spatial_matrices():
    rng = np.random.default_rng(0)
    for d, n in ((2, 4), (3, 5)):
        A = rng.normal(size=(60, d, n)) + rng.normal(size=(60, d, 1))  # biased: both verdicts
        verdict, margin = map(np.asarray, _closure(jnp.asarray(A)))
        oracle = np.array([_oracle_closure(a) for a in A])
        assert 0 < oracle.sum() < len(oracle)
        np.testing.assert_array_equal(verdict, oracle)
        np.testing.assert_array_equal(margin > 0, oracle)
        for i in np.nonzero(oracle)[0][:20]:
            assert margin[i] == pytest.approx(_oracle_margin(A[i]), rel=1e-9)
    # degenerate: coplanar columns (rank 2) and parallel ones (rank 1) never close
    flat = np.array([[1.0, -1, 0, 0], [0, 0, 1, -1], [0, 0, 0, 0]])
    line = np.array([[1.0, -1, 2], [0, 0, 0], [0, 0, 0]])
    assert not bool(tension_closure(flat)) and not bool(tension_closure(line))
    assert float(hull_margin(flat)) <= 0 and float(hull_margin(line)) <= 0
    # the regular simplex around the origin: closure with margin 1/3 of the vertex radius
    tet = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float).T
    assert bool(tension_closure(tet))
    assert float(hull_margin(tet)) == pytest.approx(np.sqrt(3) / 3)  # inradius, R / 3


def test_default_modules_hold_their_home_pose_and_the_elbow_its_whole_range(cdra):
    q = _states(cdra, 1, np.linspace(0.0, 2.0, R)[:, None])
    margins = np.asarray(_margins(cdra, q))
    assert np.all(margins[0] > 0.05)  # home pose (elbow at 0), every module
    assert margins[:, 1].min() > 0.3  # the elbow over its whole range


_sample = jax.jit(sample_feasible_states, static_argnums=(2,), static_argnames=("oversample",))


def test_sampler_returns_only_feasible_states_within_the_limits(cdra):
    q = _sample(jax.random.PRNGKey(0), cdra, M)
    assert q.shape == (M, cdra.dof)
    lim = cdra.state_limits
    assert np.all((np.asarray(q) >= lim[:, 0]) & (np.asarray(q) <= lim[:, 1]))
    assert np.all(np.asarray(_margins(cdra, q)) > 0.05)
    # independent verdicts for every module at every returned pose
    for mod, qi in zip(cdra.modules, cdra.split_state(q), strict=True):
        assert all(_oracle_closure(a) for a in np.asarray(structure_matrix(mod, qi)))
    # the uniform draws it starts from include states it rejects (the wrist's, ~12 %), and it
    # keeps the feasible ones in draw order
    raw = np.asarray(sample_states(jax.random.PRNGKey(0), cdra, R))
    ok = np.all(np.asarray(_margins(cdra, raw)) > 0.05, axis=-1)
    assert 0.02 < 1 - ok.mean() < 0.5
    np.testing.assert_array_equal(np.asarray(q), raw[ok][:M])


@pytest.mark.slow
def test_sampler_plugs_into_simulation_and_vmaps(cdra):
    keys = jax.random.split(jax.random.PRNGKey(1), 3)
    qs = jax.jit(jax.vmap(lambda k: sample_feasible_states(k, cdra, M)))(keys)
    assert qs.shape == (3, M, cdra.dof)
    np.testing.assert_array_equal(qs[1], _sample(keys[1], cdra, M))
    q_cal, _, q_ver, _, _ = simulate_trial(jax.random.PRNGKey(2), cdra, M, sampler=_sample)
    q = jnp.concatenate([q_cal, q_ver, jnp.zeros((R - 2 * M, cdra.dof))])
    assert np.all(np.asarray(_margins(cdra, q)) > 0.05)


def test_sampler_raises_when_too_few_states_are_feasible(cdra):
    # an elbow-only arm whose joint range lies where the extensor has lost its lever arm
    elbow = dataclasses.replace(cdra.module("elbow"), limits=((2.3, 2.6),))
    arm = Arm(frames=cdra.frames[:2], modules=(elbow,), frame_names=("base", "tool"))
    with pytest.raises(Exception, match="fewer than m of the oversample"):
        jax.block_until_ready(_sample(jax.random.PRNGKey(0), arm, 4))
    # throw=False (the sweeps): NaN states for that batch element only, so its solve ends
    # nonfinite while the others go on
    both = jax.jit(
        jax.vmap(lambda k, a: sample_feasible_states(k, a, 4, throw=False), in_axes=(0, None))
    )
    q = np.asarray(both(jax.random.split(jax.random.PRNGKey(0), 2), arm))
    assert q.shape == (2, 4, 1) and np.all(np.isnan(q))
    ok = np.asarray(sample_feasible_states(jax.random.PRNGKey(0), cdra, M, throw=False))
    np.testing.assert_array_equal(ok, np.asarray(_sample(jax.random.PRNGKey(0), cdra, M)))


def test_arm_closure_gives_the_verdicts_of_tension_closure_and_hull_margin(cdra):
    """arm_tension_closure's fused test of the spherical modules against the reference
    functions (exact verdict, margin over all hull directions), inside and beyond the box."""

    def reference(q, min_margin):
        ok = np.ones(q.shape[0], bool)
        for mod, qi in zip(cdra.modules, cdra.split_state(q), strict=True):
            verdict, margin = map(np.asarray, _closure(structure_matrix(mod, qi)))
            ok &= verdict & (margin / float(lever_scale(mod)) > min_margin)
        return ok

    fused = jax.jit(arm_tension_closure)  # one program for every min_margin
    u = np.asarray(sample_states(jax.random.PRNGKey(11), cdra, 20 * R))
    for q in (u, 1.6 * u):  # 1.6 x the box: every module also loses closure
        for min_margin in (0.0, DEFAULT_MIN_MARGIN, 0.2):
            ok = np.asarray(fused(cdra, jnp.asarray(q), min_margin))
            expected = reference(q, min_margin)
            assert 0 < expected.sum() < len(q)
            np.testing.assert_array_equal(ok, expected)


def _without_cables(module):
    return dataclasses.replace(module, cable_base=None, cable_platform=None, cable_offset=None)


def test_sample_poses_conditions_only_the_modules_with_cables(cdra):
    key = jax.random.PRNGKey(4)
    # no cables anywhere: plain uniform states
    bare = dataclasses.replace(cdra, modules=tuple(_without_cables(m) for m in cdra.modules))
    np.testing.assert_array_equal(sample_poses(key, bare, M), sample_states(key, bare, M))
    # the wrist alone has cables: its poses close, the others stay uniform (not thinned)
    mixed = dataclasses.replace(
        cdra, modules=tuple(m if m.name == "wrist" else _without_cables(m) for m in cdra.modules)
    )
    q = np.asarray(sample_poses(key, mixed, M))
    np.testing.assert_array_equal(q, sample_feasible_states(key, mixed, M))
    raw = np.asarray(sample_states(key, mixed, R))
    wrist = cdra.module("wrist")
    q_wrist = mixed.split_state(raw)[2]
    kept = np.asarray(_closure(structure_matrix(wrist, q_wrist))[0]) & (
        np.asarray(closure_margin(wrist, q_wrist)) > DEFAULT_MIN_MARGIN
    )
    assert 0 < (~kept).sum(), "some wrist draws must be rejected"
    np.testing.assert_array_equal(q, raw[kept][:M])


@pytest.mark.slow
def test_simulate_trial_draws_only_poses_with_tension_closure(cdra):
    """simulate_trial's default sampler (the sweeps' too): every calibration and held-out pose
    of a vmapped batch of trials has tension closure with the sampler's margin."""
    keys = jax.random.split(jax.random.PRNGKey(8), 64)
    q_cal, _, q_ver, _, _ = jax.jit(jax.vmap(lambda k: simulate_trial(k, cdra, 15, m_verify=50)))(
        keys
    )
    q = np.concatenate(
        [np.asarray(q_cal).reshape(-1, cdra.dof), np.asarray(q_ver).reshape(-1, cdra.dof)]
    )
    assert q.shape == (64 * 65, cdra.dof)
    assert np.all(np.asarray(_margins(cdra, q)) > DEFAULT_MIN_MARGIN)
    # the uniform draws they replace would include poses without closure
    u = np.asarray(sample_states(jax.random.PRNGKey(8), cdra, len(q)))
    assert np.mean(np.asarray(_margins(cdra, u)).min(-1) <= DEFAULT_MIN_MARGIN) > 0.05
