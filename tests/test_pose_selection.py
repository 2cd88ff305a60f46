"""Pose selection: I- and D-optimality on the identifiable subspace, O1, exchange, the
approximate-design bound and the plan-poses CLI."""

import csv
import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdra_jax import NoiseModel, lie, tool_pose
from cdra_jax.arm import chain, module_poses
from cdra_jax.calibration import calibration_jacobian, whitening
from cdra_jax.cli import main as cli_main
from cdra_jax.pose_selection import (
    identifiable_basis,
    information_blocks,
    log_det_information,
    prediction_bound,
    select_from_pool,
    select_poses,
)
from cdra_jax.simulation import sample_states
from cdra_jax.uncertainty import predicted_pose_covariance

NOISE = NoiseModel(0.08, 1e-3)


@eqx.filter_jit
def _core_blocks(arm, q, noise):
    tool, after = chain(arm.frames, module_poses(arm, q))
    D = calibration_jacobian(after)
    return D, (None if noise is None else whitening(tool, noise))


def _blocks_oracle(arm, q, noise):
    """Whitened blocks from the core's own pieces (chain, Eq. 8 Jacobian, whitening)."""
    D, G = _core_blocks(arm, jnp.asarray(q), noise)
    D = np.asarray(D)
    if noise is None:
        return D
    return np.asarray(G) @ D


_sample_states = jax.jit(sample_states, static_argnums=2)  # one program per state count


def _log_det(blocks, W):
    B = blocks @ W
    sign, ld = np.linalg.slogdet(np.einsum("kar,kas->rs", B, B))
    return ld if sign > 0 else -np.inf


@pytest.fixture(scope="module")
def pool(cdra):
    return np.asarray(_sample_states(jax.random.PRNGKey(5), cdra, 14))


def test_blocks_and_basis(cdra, pool):
    A = np.asarray(information_blocks(cdra, pool, NOISE))
    np.testing.assert_allclose(A, _blocks_oracle(cdra, pool, NOISE), rtol=1e-12, atol=1e-9)
    W = identifiable_basis(A)
    assert W.shape == (24, 22)
    np.testing.assert_allclose(W.T @ W, np.eye(22), atol=1e-12)
    # W spans the row space: the stacked Jacobian annihilates its complement
    stacked = A.reshape(-1, 24)
    N = np.linalg.svd(W.T)[2][22:]  # orthonormal complement (2, 24)
    assert np.abs(stacked @ N.T).max() < 1e-9 * np.abs(stacked).max()


def test_exchange_reaches_a_swap_local_optimum(cdra, pool):
    """Brute force over every single swap: none improves the selected set (determinant-lemma
    gains checked against explicit log-dets), and the set is the global optimum on this tiny
    pool (all 2002 subsets of 5 from 14 enumerated)."""
    m = 5
    sel = select_from_pool(cdra, pool, m, NOISE, criterion="d-opt")
    A = _blocks_oracle(cdra, pool, NOISE)
    W = identifiable_basis(A)
    chosen = list(sel.indices)
    assert len(set(chosen)) == m
    best = _log_det(A[chosen], W)
    assert sel.log_det == pytest.approx(best, abs=1e-8)
    assert sel.log_det >= sel.log_det_greedy - 1e-9
    for i, j in itertools.product(range(m), range(len(pool))):
        if j in chosen:
            continue
        swapped = chosen.copy()
        swapped[i] = j
        assert _log_det(A[swapped], W) <= best + 1e-8
    all_sets = [_log_det(A[list(c)], W) for c in itertools.combinations(range(len(pool)), m)]
    assert best == pytest.approx(max(all_sets), abs=1e-8)
    assert float(log_det_information(A[chosen], W)) == pytest.approx(best, abs=1e-8)


def test_selected_poses_predict_better_than_random(cdra):
    m = 6  # pool and m as in the CLI test below, so the jitted selection compiles once
    sel = select_poses(cdra, m, NOISE, key=jax.random.PRNGKey(0), pool_size=300)
    assert sel.states.shape == (m, 7) and sel.rank == 22
    # held-out states as many as the pool: the selection's own prediction program is reused
    q_eval = _sample_states(jax.random.PRNGKey(1), cdra, 300)
    chosen = float(predicted_pose_covariance(cdra, sel.states, NOISE, q_eval).expected_delta_p)
    rng = np.random.default_rng(0)
    random_sets = [
        float(
            predicted_pose_covariance(
                cdra, sel.pool[rng.choice(len(sel.pool), m, replace=False)], NOISE, q_eval
            ).expected_delta_p
        )
        for _ in range(10)
    ]
    assert chosen < 0.8 * min(random_sets)


def test_o1_index_and_sampler(cdra):
    def high_elbow(key, arm, m):  # a custom feasible-pose sampler: elbow bent beyond 1 rad
        q = np.array(_sample_states(key, arm, m))
        q[:, 3] = 1.0 + 0.5 * q[:, 3]
        return q

    m = 6
    sel = select_poses(
        cdra, m, key=jax.random.PRNGKey(2), pool_size=300, criterion="o1", sampler=high_elbow
    )
    assert np.all(sel.pool[:, 3] >= 1.0) and np.all(sel.states[:, 3] >= 1.0)
    D = _blocks_oracle(cdra, jnp.asarray(sel.states), None).reshape(-1, 24)
    s = np.linalg.svd(D, compute_uv=False)[:22]
    assert sel.o1 == pytest.approx(np.exp(np.mean(np.log(s))) / np.sqrt(m), rel=1e-8)


def test_bad_arguments(cdra, pool):
    with pytest.raises(ValueError, match="noise=NoiseModel"):
        select_from_pool(cdra, pool, 5)
    with pytest.raises(ValueError, match="criterion"):
        select_from_pool(cdra, pool, 5, NOISE, criterion="e-opt")
    with pytest.raises(ValueError, match="cannot select"):
        select_from_pool(cdra, pool, 15, NOISE)
    with pytest.raises(ValueError, match=r"shape \(N, 7\)"):
        select_from_pool(cdra, pool[:, :3], 5, NOISE)


def test_pose_count_must_be_an_integer_of_at_least_four(cdra, pool):
    """m < 4 (the paper's lower bound) used to give a finite garbage prediction, and m = 2.5
    silently selected 2; both are refused before anything is computed."""
    for m in (3, 0, 2.5, 5.0, True, "5"):
        with pytest.raises(ValueError, match=r"m must be (at least 4|an integer)"):
            select_from_pool(cdra, pool, m, NOISE)
        with pytest.raises(ValueError, match=r"m must be (at least 4|an integer)"):
            select_poses(cdra, m, NOISE, pool_size=20)
        with pytest.raises(ValueError, match=r"m must be (at least 4|an integer)"):
            prediction_bound(cdra, pool, m, NOISE)
    with pytest.raises(ValueError, match="max_exchanges must be at least 0"):
        select_from_pool(cdra, pool, 5, NOISE, max_exchanges=-1)
    with pytest.raises(ValueError, match="pool_size must be an integer"):
        select_poses(cdra, 5, NOISE, pool_size=20.5)
    with pytest.raises(ValueError, match=r"pool_size must be at least 5"):
        select_poses(cdra, 5, NOISE, pool_size=4)


def test_prediction_bound_arguments(cdra, pool):
    with pytest.raises(ValueError, match=r"noise=NoiseModel"):
        prediction_bound(cdra, pool, 7, None)
    for bad in (-1, 2.5, True):
        with pytest.raises(ValueError, match="iterations must be"):
            prediction_bound(cdra, pool, 7, NOISE, iterations=bad)


def test_unbounded_prediction_where_the_pool_identifies_too_little(cdra, pool):
    """A pool of one repeated state identifies only that tool pose (rank 6): its error is
    bounded there (4 poses: position covariance s_p^2 / 4 I, exact), unbounded (inf) at other
    reference states, for the selection's prediction and for the lower bound alike."""
    same = np.repeat(pool[:1], len(pool), axis=0)  # the pool's shape: compiled programs reused
    here = 0.08 * np.sqrt(3 / 4)
    sel = select_from_pool(cdra, same, 4, NOISE, criterion="d-opt", exchange=False)
    assert sel.rank == 6 and sel.prediction_rms == pytest.approx(here, rel=1e-8)
    # other states only, as many as the pool (the programs compiled above are reused)
    others = np.concatenate([pool[1:], pool[1:2]])
    elsewhere = select_from_pool(
        cdra, same, 4, NOISE, criterion="d-opt", exchange=False, reference=others
    )
    assert np.isinf(elsewhere.prediction_rms)
    b = prediction_bound(cdra, same, 4, NOISE, iterations=10)
    assert b.lower == pytest.approx(here, rel=1e-8) and b.approximate == pytest.approx(here)
    b = prediction_bound(cdra, same, 4, NOISE, reference=others, iterations=10)
    assert np.isinf(b.lower) and np.isinf(b.approximate)


def test_plan_poses_cli(cdra, tmp_path, capsys):
    out = tmp_path / "plan.csv"
    argv = ["--count", "6", "--pool", "300", "--seed", "4", "--out", str(out)]
    assert cli_main(["plan-poses", *argv]) == 0
    printed = capsys.readouterr().out
    assert "expected RMS accuracy" in printed and str(out) in printed
    lines = out.read_text().splitlines()
    comments = [ln for ln in lines if ln.startswith("#")]
    assert any("i-opt" in c for c in comments) and any("0.08 mm" in c for c in comments)
    rows = list(csv.reader(ln for ln in lines if not ln.startswith("#")))
    assert rows[0] == ["pose", *cdra.state_names]
    assert [r[0] for r in rows[1:]] == [f"P{i:02d}" for i in range(1, 7)]
    states = np.array([[float(v) for v in r[1:]] for r in rows[1:]])
    expected = select_poses(cdra, 6, NOISE, key=jax.random.PRNGKey(4), pool_size=300).states
    np.testing.assert_array_equal(states, expected)  # repr floats: exact round trip
    lim = cdra.state_limits
    assert np.all((states >= lim[:, 0]) & (states <= lim[:, 1]))
    # refuses to overwrite, and checks its flags
    assert cli_main(["plan-poses", *argv]) == 1
    assert "exists" in capsys.readouterr().err
    assert cli_main(["plan-poses", *argv, "--force", "--noise-pos", "0.05"]) == 1
    assert "go together" in capsys.readouterr().err
    assert cli_main(["plan-poses", *argv, "--force", "--criterion", "o1"]) == 0
    assert "by o1" in capsys.readouterr().out


def test_tool_positions_used_for_whitening(cdra, pool):
    """d-opt weighs orientation rows by the lever arm of the model tool position (Eq. 7)."""
    A = np.asarray(information_blocks(cdra, pool, NOISE))
    p = np.asarray(lie.translation(tool_pose(cdra, pool)))
    D = _blocks_oracle(cdra, pool, None)
    top = (D[:, :3] - np.einsum("kij,kjn->kin", np.asarray(lie.hat3(p)), D[:, 3:])) / 0.08
    np.testing.assert_allclose(A[:, :3], top, rtol=1e-10, atol=1e-8)


def test_i_opt_reaches_a_swap_local_optimum_of_the_predicted_heldout_error(cdra, pool):
    """The I-criterion is the predicted E[dp^2] at the reference states, computed here
    independently by the uncertainty module (SVD pseudo-inverse of the set's own Jacobian,
    propagated pose covariance): no single swap improves the I-optimal set, it beats the
    D-optimal one, and the approximate-design bound lies below all 2002 subsets of 5 from 14."""
    m = 5
    ref = np.asarray(_sample_states(jax.random.PRNGKey(6), cdra, 40))
    sel = select_from_pool(cdra, pool, m, NOISE, reference=ref)
    assert sel.criterion == "i-opt" and len(set(sel.indices)) == m
    swaps = [
        [j if k == i else c for k, c in enumerate(sel.indices)]
        for i in range(m)
        for j in sorted(set(range(len(pool))) - set(sel.indices))
    ]
    subsets = list(itertools.combinations(range(len(pool)), m))
    sets = np.array([list(sel.indices), *swaps, *subsets])  # one batch: one compile
    rms = np.asarray(
        jax.jit(
            jax.vmap(lambda q: predicted_pose_covariance(cdra, q, NOISE, ref).expected_delta_p)
        )(jnp.asarray(pool[sets]))
    )
    chosen, swapped, best = rms[0], rms[1 : 1 + len(swaps)].min(), rms[1 + len(swaps) :].min()
    assert sel.prediction_rms == pytest.approx(chosen, rel=1e-9)
    # 1e-6: the selection works with M + eps I (a 1e-9 relative ridge)
    assert chosen <= swapped * (1 + 1e-6)
    d_opt = select_from_pool(cdra, pool, m, NOISE, criterion="d-opt", reference=ref)
    assert chosen <= d_opt.prediction_rms * (1 + 1e-6)  # exchanged from the D-optimal start
    bound = prediction_bound(cdra, pool, m, NOISE, reference=ref)
    assert bound.lower <= best <= chosen
    assert bound.lower <= bound.approximate < best  # weights beat uniform weights on a subset
    assert bound.approximate - bound.lower < 1e-3 * bound.lower  # converged: the gap is small
    assert bound.weights.sum() == pytest.approx(1.0) and np.all(bound.weights >= 0)
