"""Statics: gravity loads, equilibrium of the holding tensions, optimality of the distribution."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import minimize

from cdra_jax import forward_kinematics
from cdra_jax.arm import Arm, revolute
from cdra_jax.modules import (
    TensionResult,
    distribute_tensions,
    gravity_loads,
    gravity_torques,
    holding_tensions,
    result_names,
    sample_feasible_states,
    structure_matrix,
    total_mass,
)

M = 40
PAYLOAD = 0.3


@pytest.fixture(scope="module")
def poses(cdra):
    q = jax.jit(sample_feasible_states, static_argnums=2)(jax.random.PRNGKey(3), cdra, M)
    tensions = jax.jit(holding_tensions)(cdra, q, PAYLOAD)
    return q, tensions


def _world_equilibrium(cdra, q, tensions, payload):
    """Independent numpy check: cable torques + gravity torques about each module centre.

    Everything in the world frame from the tool/after poses of the core forward kinematics:
    cable i of module k pulls the body distal to module k at its platform attachment towards
    its base attachment with tension t_i; gravity pulls every distal body at its centre of mass.
    Returns the net torque about each module centre (3 components for spherical modules, the
    component along the joint axis for revolute ones).
    """
    tool, after = map(np.asarray, forward_kinematics(cdra, q))
    poses = [
        np.asarray(m.pose(qi)) for m, qi in zip(cdra.modules, cdra.split_state(q), strict=True)
    ]
    g = np.asarray(cdra.gravity)
    out = []
    for k, mod in enumerate(cdra.modules):
        T_plat = after[:, k]
        T_base = T_plat @ np.linalg.inv(poses[k])
        c = T_plat[:, :3, 3]
        p_w = np.einsum("mij,nj->mni", T_plat[:, :3, :3], np.asarray(mod.cable_platform))
        p_w += T_plat[:, None, :3, 3]
        b_w = np.einsum("mij,nj->mni", T_base[:, :3, :3], np.asarray(mod.cable_base))
        b_w += T_base[:, None, :3, 3]
        u = (b_w - p_w) / np.linalg.norm(b_w - p_w, axis=-1, keepdims=True)
        t = np.asarray(tensions[mod.name].tensions)
        tau = np.einsum("mni->mi", np.cross(p_w - c[:, None], u * t[..., None]))
        for j in range(k, len(cdra.modules)):
            body = cdra.modules[j]
            x = np.einsum("mij,j->mi", after[:, j, :3, :3], np.asarray(body.com))
            x += after[:, j, :3, 3]
            tau += np.cross(x - c, body.mass * g)
        tau += np.cross(tool[:, :3, 3] - c, payload * g)
        if mod.kind == "revolute":
            axis_w = np.einsum("mij,j->mi", T_base[:, :3, :3], np.asarray(mod.axis))
            tau = np.einsum("mi,mi->m", tau, axis_w)[:, None]
        out.append(tau)
    return out


def test_holding_tensions_are_in_equilibrium_and_above_the_floor(cdra, poses):
    q, tensions = poses
    for mod in cdra.modules:
        sol = tensions[mod.name]
        assert np.all(result_names(sol.result) == "successful")
        t = np.asarray(sol.tensions)
        assert float(np.min(t)) >= mod.pretension - 1e-9
        assert float(np.max(t)) > mod.pretension + 1.0  # the load is carried
    for mod, net in zip(cdra.modules, _world_equilibrium(cdra, q, tensions, PAYLOAD), strict=True):
        assert np.max(np.abs(net)) < 1e-9, (mod.name, np.max(np.abs(net)))


def test_distribution_is_the_minimum_norm_one(cdra, poses):
    """KKT conditions, the closed form for n = d + 1, and scipy's SLSQP."""
    q, tensions = poses
    loads = cdra.split_state(gravity_loads(cdra, q, PAYLOAD))
    for mod, qi, load in zip(cdra.modules, cdra.split_state(q), loads, strict=True):
        A = np.asarray(structure_matrix(mod, qi))
        w = -np.asarray(load)
        t = np.asarray(tensions[mod.name].tensions)
        f = mod.pretension
        # KKT: t = max(f, A^T lam) for the lam that fits the free cables
        free = t > f + 1e-9
        for k in range(M):
            Af = A[k][:, free[k]]
            lam = np.linalg.lstsq(Af.T, t[k, free[k]], rcond=None)[0]
            np.testing.assert_allclose(Af.T @ lam, t[k, free[k]], atol=1e-8)
            assert np.all(A[k][:, ~free[k]].T @ lam <= f + 1e-8)  # multipliers >= 0
        d, n = A.shape[1:]
        if n == d + 1:
            # closed form: t = t_p + s h, h the positive null vector, s as small as allowed
            for k in range(M):
                h = np.linalg.svd(A[k])[2][-1]
                h = h if h.sum() > 0 else -h
                tp = np.linalg.lstsq(A[k], w[k], rcond=None)[0]
                s = max(-(tp @ h) / (h @ h), np.max((f - tp) / h))
                np.testing.assert_allclose(t[k], tp + s * h, rtol=1e-9, atol=1e-9)
        for k in range(5):
            Ak, wk = A[k], w[k]
            res = minimize(
                lambda x: 1e-4 * (x @ x),
                np.full(n, 50.0),
                jac=lambda x: 2e-4 * x,
                constraints=[
                    {
                        "type": "eq",
                        "fun": lambda x, Ak=Ak, wk=wk: Ak @ x - wk,
                        "jac": lambda x, Ak=Ak: Ak,
                    }
                ],
                bounds=[(f, None)] * n,
                method="SLSQP",
                options={"ftol": 1e-12, "maxiter": 500},
            )
            assert np.abs(Ak @ res.x - wk).max() < 1e-6 * np.abs(wk).max() + 1e-6
            np.testing.assert_allclose(t[k], res.x, rtol=1e-6, atol=1e-5)


def test_gravity_torque_of_a_one_link_arm_by_hand():
    # one revolute module about y at 100 mm height, a 2 kg body with its centre 200 mm along x,
    # a 0.5 kg payload at the tool 300 mm along x
    frames = np.stack([np.eye(4)] * 2)
    frames[0, 2, 3], frames[1, 0, 3] = 100.0, 300.0
    arm = Arm(
        frames=jnp.asarray(frames),
        modules=(revolute("hinge", [0, 1, 0], mass=2.0, com=jnp.asarray([200.0, 0, 0])),),
        frame_names=("base", "tool"),
    )
    tau = gravity_torques(arm, jnp.asarray([0.0]), 0.5)
    # torque about y of a weight -m g z at +x: (x, 0, 0) x (0, 0, -m g) = (0, m g x, 0)
    expect = 9.81 * (2.0 * 200.0 + 0.5 * 300.0)
    np.testing.assert_allclose(tau[0], [0.0, expect, 0.0], atol=1e-9)
    np.testing.assert_allclose(gravity_loads(arm, jnp.asarray([0.0]), 0.5), [expect], atol=1e-9)
    # turned by 90 deg about y the body points down (-z): no torque
    tau = gravity_torques(arm, jnp.asarray([np.pi / 2]), 0.5)
    np.testing.assert_allclose(tau[0], 0.0, atol=1e-9)


def test_default_arm_mass_and_home_load(cdra):
    assert total_mass(cdra) == pytest.approx(0.95)
    # at home the arm stands upright: only the hand's 10 mm centre offset and the tool's 20 mm
    # make a torque about y, in every module
    tau = np.asarray(gravity_torques(cdra, jnp.zeros(7), 0.0))
    np.testing.assert_allclose(tau[:, [0, 2]], 0.0, atol=1e-12)
    np.testing.assert_allclose(tau[:, 1], 0.25 * 9.81 * 10.0, rtol=1e-12)


def test_infeasible_load_is_reported_not_raised():
    A = np.asarray([[[1.0, 2.0, 0.5]]])  # every cable pushes the same way: cannot hold -1
    sol = distribute_tensions(A, np.asarray([[-1.0]]), 0.0)
    assert result_names(sol.result)[0] == "unbalanced"
    sol = distribute_tensions(A, np.asarray([[3.0]]), 0.0)  # but +3 is fine
    assert bool(sol.result == TensionResult.successful)
    np.testing.assert_allclose(A[0] @ np.asarray(sol.tensions)[0], [3.0], atol=1e-12)
