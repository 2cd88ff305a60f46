"""Degenerate pose sets: identical poses, an elbow that never moves, nearly identical poses,
too few poses. The answer is finite and minimum-norm, and the reports name what is lost."""

from __future__ import annotations

import equinox as eqx
import numpy as np
import pytest
from _robust_data import NOISE, M, problem

from cdra_jax import tool_pose
from cdra_jax.calibration import calibrate_paper, calibrate_robust
from cdra_jax.conditioning import CONDITION_WARNING, conditioning
from cdra_jax.identifiability import analyze

paper = eqx.filter_jit(calibrate_paper)
robust = eqx.filter_jit(calibrate_robust)
fk = eqx.filter_jit(tool_pose)


def _measure(p, q):
    """Noise-free measured poses of the simulated actual arm at states ``q``."""
    return np.asarray(fk(p.arm.with_frames(p.actual_frames), q))


def _check_min_norm_fit(p, q, T, rank):
    sol = paper(p.arm, q, T, throw=False)
    assert np.all(np.isfinite(np.asarray(sol.frames))) and np.all(np.isfinite(sol.errors))
    assert int(sol.rank) == rank
    # the poses are reproduced exactly (noise-free data), whatever is unidentifiable
    np.testing.assert_allclose(np.asarray(fk(p.arm.with_frames(sol.frames), q)), T, atol=1e-8)
    # minimum norm: nothing moves along the unidentifiable directions of the report
    rep = analyze(p.arm, q)
    assert rep.rank == rank and len(rep.unidentifiable) == 24 - rank
    along = rep.null_space @ np.asarray(sol.errors).reshape(-1)
    assert np.abs(along).max() < 1e-3 * np.linalg.norm(np.asarray(sol.errors)), along
    return sol, rep


def test_identical_poses_keep_six_parameters_and_name_the_other_eighteen():
    p = problem(0)
    q = np.repeat(p.q[:1], M, axis=0)
    _, rep = _check_min_norm_fit(p, q, _measure(p, q), rank=6)
    assert any("18 parameter combination(s) cannot be identified" in w for w in rep.warnings)
    assert any("keeps the nominal model along them" in w for w in rep.warnings)
    # the robust fit of the same data stays finite too (zero residuals: the scale floor)
    r = robust(p.arm, q, _measure(p, q), None, loss="cauchy", solver="paper", throw=False)
    assert np.all(np.isfinite(np.asarray(r.frames))) and np.all(np.isfinite(np.asarray(r.z)))
    assert not np.any(np.asarray(r.outliers))


def test_elbow_never_moved_loses_six_more_directions():
    p = problem(0)
    q = p.q.copy()
    q[:, 3] = 1.1  # elbow.q
    _, rep = _check_min_norm_fit(p, q, _measure(p, q), rank=18)
    text = " ".join(rep.unidentifiable)
    assert "upper_arm" in text and "forearm" in text
    assert "base." not in text and "tool." not in text  # only the frames around the elbow


def test_nearly_identical_poses_are_reported_as_poorly_conditioned():
    p = problem(0)
    rng = np.random.default_rng(0)
    q = p.q[:1] + 0.01 * rng.standard_normal((M, 7))
    q[:, 3] = np.abs(q[:, 3])
    rep = conditioning(p.arm, q, noise=NOISE)
    assert rep.ill_conditioned and rep.condition_number > CONDITION_WARNING
    assert rep.warning is not None and "dominated by measurement noise" in rep.warning
    assert len(rep.weak_directions) >= 1 and all(rep.weak_directions)
    assert rep.weak_space.shape == (len(rep.weak_directions), 24)
    np.testing.assert_allclose(np.linalg.norm(rep.weak_space, axis=1), 1.0)
    # ... and the weak directions are the ones the data barely see: moving the frames by
    # 1e-3 along the weakest changes the tool poses far less than along a random direction
    D = _jacobian(p, q)
    weak = np.linalg.norm(D @ rep.weak_space[0])
    random = np.linalg.norm(D @ rng.standard_normal(24)) / np.sqrt(24)
    assert weak < 1e-2 * random
    # the same data at well spread poses: no warning
    good = conditioning(p.arm, p.q, noise=NOISE)
    assert not good.ill_conditioned and good.warning is None and good.weak_directions == ()
    assert good.condition_number < 100


def _jacobian(p, q):
    from cdra_jax.identifiability import stacked_jacobian

    return stacked_jacobian(p.arm, q, noise=NOISE)


def test_fewer_poses_than_the_lower_bound_stop_or_go_min_norm():
    p = problem(0)
    q, T = p.q[:3], p.T[:3]
    for fn in (calibrate_paper, calibrate_robust):
        with pytest.raises(ValueError, match="3 measured poses given; the calibration needs at"):
            fn(p.arm, q, T)
    with pytest.raises(ValueError, match="at least 4"):
        analyze(p.arm, q)
    rep = analyze(p.arm, q, allow_underdetermined=True)
    assert rep.rank < 22 and any("only 3 poses" in w for w in rep.warnings)
