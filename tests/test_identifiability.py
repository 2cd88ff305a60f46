"""Identifiability of the frame errors (cdra_jax.identifiability) against analytic null spaces.

The oracle: a module's motion commutes with every screw it leaves invariant, so moving such a
screw ``g`` from the frame after the module to the frame before it,
``F_before -> F_before exp(g)``, ``F_after -> exp(-g) F_after``, changes no tool pose. In the
left-multiplied error parameters (Eqs. 11-14) that is ``X_before = Ad(F_before) g``,
``X_after = -g``. For a revolute module the invariant screws are the rotation about its axis
and the translation along it; a module that never moves leaves every screw invariant.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

from cdra_jax import identifiability, lie, simulation
from cdra_jax.arm import apply_frame_errors, tool_pose

tool_poses = jax.jit(lambda arm, X, q: tool_pose(apply_frame_errors(arm, X), q))


def _states(arm, m, seed):
    return np.array(simulation.sample_states(jax.random.PRNGKey(seed), arm, m))


def _moved_screws(arm, module: str, screws: np.ndarray) -> np.ndarray:
    """Parameter directions ``(len(screws), n_params)`` moving ``screws`` across ``module``.

    ``screws`` are twists in the module's base frame (the frame before the module).
    """
    i = arm.module_names.index(module)
    F_before = np.asarray(arm.frames[i])
    out = np.zeros((len(screws), len(arm.frame_names), 6))
    out[:, i] = np.einsum("ij,nj->ni", np.asarray(lie.adjoint(F_before)), screws)
    out[:, i + 1] = -screws
    return out.reshape(len(screws), -1)


def _elbow_directions(arm) -> np.ndarray:
    a = np.asarray(arm.module("elbow").axis)
    screws = np.array([np.r_[np.zeros(3), a], np.r_[a, np.zeros(3)]])  # rotation, translation
    return _moved_screws(arm, "elbow", screws)


def _assert_same_span(A: np.ndarray, B: np.ndarray, tol: float) -> None:
    """Rows of A and rows of B span the same subspace."""
    Qa = np.linalg.qr(A.T)[0]
    Qb = np.linalg.qr(B.T)[0]
    assert Qa.shape == Qb.shape
    # Each basis lies in the other's span: cosines of all principal angles are 1.
    s = np.linalg.svd(Qa.T @ Qb, compute_uv=False)
    np.testing.assert_allclose(s, 1.0, atol=tol)


def test_cdra_rank_22_and_the_elbow_null_space(cdra):
    q = _states(cdra, 15, 0)
    rep = identifiability.analyze(cdra, q)
    assert (rep.rank, rep.n_params, rep.n_poses) == (22, 24, 15)
    assert not rep.identifiable
    assert rep.null_space.shape == rep.directions.shape == (2, 24)
    assert np.all(rep.singular_values[:22] > 1e3 * rep.rcond * rep.singular_values[0])
    assert np.all(rep.singular_values[22:] < 1e-12 * rep.singular_values[0])
    np.testing.assert_allclose(rep.null_space @ rep.null_space.T, np.eye(2), atol=1e-12)
    true = _elbow_directions(cdra)
    _assert_same_span(rep.null_space, true, 1e-10)
    _assert_same_span(rep.directions, true, 1e-10)
    # Moving the frames along these directions, by finite amounts, changes no tool pose.
    q_other = _states(cdra, 20, 1)
    T0 = np.asarray(tool_poses(cdra, np.zeros(24), q_other))
    for d in np.concatenate([true, rep.directions]):
        for eps in (1e-3, 0.3):
            T = np.asarray(tool_poses(cdra, eps * d / np.linalg.norm(d), q_other))
            np.testing.assert_allclose(T, T0, rtol=0, atol=1e-9)
    # A direction that is not in the null space does move the tool (the check can fail).
    T = np.asarray(tool_poses(cdra, 1e-3 * np.eye(24)[10], q_other))  # upper_arm.wy alone
    assert np.abs(T - T0).max() > 1e-2


def test_cdra_directions_read_as_named_combinations(cdra):
    rep = identifiability.analyze(cdra, _states(cdra, 15, 2))
    # Upper arm: 300 mm along z, elbow axis y: rotation a about y in both frames comes with a
    # -300 a mm shift along x of upper_arm (rotation part normalised: 0.707 -> 212 mm).
    assert rep.unidentifiable == (
        "0.707 rad upper_arm.wy - 0.707 rad forearm.wy - 212 mm upper_arm.vx",
        "0.707 mm upper_arm.vy - 0.707 mm forearm.vy",
    )
    d = rep.directions
    rot = [n.split(".")[1].startswith("w") for n in rep.param_names]
    np.testing.assert_allclose(np.linalg.norm(d[0, rot]), 1.0, atol=1e-12)
    np.testing.assert_allclose(
        d[0, rep.param_names.index("upper_arm.vx")], -300 / 2**0.5, atol=1e-9
    )
    np.testing.assert_allclose(np.linalg.norm(d[1]), 1.0, atol=1e-12)
    js = rep.to_dict()
    assert js["rank"] == 22 and js["n_params"] == 24
    assert js["unidentifiable"] == list(rep.unidentifiable)
    assert set(js["directions"][1]) == {"upper_arm.vy", "forearm.vy"}
    assert "rank 22 of 24" in rep.summary() and rep.unidentifiable[0] in rep.summary()


def test_elbow_never_moved_loses_six_directions(cdra):
    q = _states(cdra, 15, 3)
    q[:, cdra.state_names.index("elbow.q")] = 1.1
    rep = identifiability.analyze(cdra, q)
    # upper_arm, the (now constant) elbow and forearm act as one fixed transform: 6 of the
    # 12 parameters of upper_arm and forearm cannot be told apart.
    assert rep.rank == 18 and len(rep.unidentifiable) == 6
    assert any("'elbow' never moves" in w for w in rep.warnings)
    assert "rank 18 of 24" in rep.summary() and "'elbow' never moves" in rep.summary()
    # Every screw (in the elbow's base frame, at the elbow's fixed angle) moves across it.
    i = cdra.module_names.index("elbow")
    M = np.asarray(cdra.module("elbow").pose(np.array([1.1])))
    F = np.asarray(cdra.frames[i]) @ M  # up to the elbow platform
    true = np.zeros((6, 4, 6))
    true[:, i] = np.asarray(lie.adjoint(F)).T  # row n: X_before = Ad(F) e_n
    true[:, i + 1] = -np.eye(6)
    true = true.reshape(6, -1)
    _assert_same_span(rep.null_space, true, 1e-10)
    T0 = np.asarray(tool_poses(cdra, np.zeros(24), q))
    for d in rep.directions:
        T = np.asarray(tool_poses(cdra, 0.01 * d / np.linalg.norm(d), q))
        np.testing.assert_allclose(T, T0, rtol=0, atol=1e-9)
    # The same arm with the elbow moving again: back to rank 22, no warning about it.
    assert identifiability.analyze(cdra, _states(cdra, 15, 3)).rank == 22


def test_6r_arm_rank_30(ur5):
    """Six revolute joints: each leaves its axis screw (rotation about, translation along) free.

    42 - 2 * 6 = 30 identifiable parameters, the classical 4R + 2P + 6 count of a complete,
    minimal model of a serial arm.
    """
    q = _states(ur5, 15, 4)
    rep = identifiability.analyze(ur5, q)
    assert (rep.rank, rep.n_params, len(rep.unidentifiable)) == (30, 42, 12)
    z = np.array([0.0, 0.0, 1.0])
    true = np.concatenate(
        [
            _moved_screws(
                ur5, f"joint{j}", np.array([np.r_[np.zeros(3), z], np.r_[z, np.zeros(3)]])
            )
            for j in range(1, 7)
        ]
    )
    _assert_same_span(rep.null_space, true, 1e-10)


def test_fewer_than_four_poses(cdra):
    q = _states(cdra, 3, 5)
    with pytest.raises(ValueError, match="3 poses given; the calibration needs at least 4"):
        identifiability.analyze(cdra, q)
    rep = identifiability.analyze(cdra, q, allow_underdetermined=True)
    assert rep.rank <= 18 and rep.n_poses == 3
    assert any("only 3 poses" in w for w in rep.warnings)
    assert rep.null_space.shape == (24 - rep.rank, 24)
    np.testing.assert_allclose(rep.null_space @ rep.null_space.T, np.eye(24 - rep.rank), atol=1e-9)
    with pytest.raises(ValueError, match=r"shape \(m, 7\)"):
        identifiability.analyze(cdra, q[:, :6], allow_underdetermined=True)


def test_readable_directions_of_a_known_subspace():
    names = ("a.vx", "a.vy", "a.vz", "a.wx", "a.wy", "a.wz", "b.vx", "b.vy", "b.vz", "b.wx")
    rot = np.zeros(10)
    rot[[4, 9, 0, 1]] = [1.0, -1.0, 50.0, 10.0]  # a.wy - b.wx with lever arms in a.vx, a.vy
    trans = np.zeros(10)
    trans[[1, 7]] = [1.0, 1.0]  # a.vy + b.vy
    # Any orthonormal basis of span{rot, trans} gives the same readable directions.
    Q = np.linalg.qr(np.stack([rot + 3 * trans, rot - trans], axis=1))[0]
    directions, ortho = identifiability.readable_directions(Q, names)
    # The lever arm loses its component along the pure translation: a.vy 10 -> 5, b.vy -5.
    lever = rot - 5.0 * trans
    np.testing.assert_allclose(directions[0], lever / 2**0.5, atol=1e-12)
    np.testing.assert_allclose(directions[1], trans / 2**0.5, atol=1e-12)
    np.testing.assert_allclose(ortho @ ortho.T, np.eye(2), atol=1e-12)
    _assert_same_span(ortho, directions, 1e-12)
    text = identifiability.format_combination(directions[0], names)
    assert text == "0.707 rad a.wy - 0.707 rad b.wx + 35.4 mm a.vx + 3.54 mm a.vy - 3.54 mm b.vy"
