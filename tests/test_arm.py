"""Module poses, forward kinematics and frame errors (cdra_jax.arm) against hand-built numpy.

Oracles: rotation matrices written out by hand or from ``scipy.spatial.transform.Rotation``,
chain products in numpy, ``scipy.linalg.expm`` for the frame errors, the Denavit-Hartenberg
product of the UR5 and its published home position.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from scipy.spatial.transform import Rotation

from cdra_jax import arm as arm_mod
from cdra_jax.arm import (
    Arm,
    Module,
    apply_frame_errors,
    forward_kinematics,
    frame_errors,
    module_poses,
)

fk = jax.jit(forward_kinematics)
poses_of = jax.jit(module_poses)


def _pose(R: np.ndarray, p=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T


def _rot_z(t: float) -> np.ndarray:
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_x(t: float) -> np.ndarray:
    c, s = np.cos(t), np.sin(t)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(t: float) -> np.ndarray:
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rodrigues(axis: np.ndarray, t: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.cos(t) * np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * np.outer(a, a)


def _hat6(xi: np.ndarray) -> np.ndarray:
    X = np.zeros((4, 4))
    w = xi[3:]
    X[:3, :3] = [[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]]
    X[:3, 3] = xi[:3]
    return X


# --------------------------------------------------------------------------- modules


def test_spherical_module_pose_is_rotation_about_origin():
    m = arm_mod.spherical("s")
    q = np.random.default_rng(0).uniform(-1, 1, size=(5, 3))
    expected = np.stack([_pose(R) for R in Rotation.from_rotvec(q).as_matrix()])
    np.testing.assert_allclose(m.pose(q), expected, rtol=0, atol=2e-15)
    assert m.dof == 3 and m.state_names == ("s.rx", "s.ry", "s.rz")


@pytest.mark.parametrize(
    ("axis", "hand_built"),
    [([0, 0, 1], _rot_z), ([1, 0, 0], _rot_x), ([0, 1, 0], _rot_y), ([0, 0, 5], _rot_z)],
)
def test_revolute_module_pose_about_coordinate_axes(axis, hand_built):
    m = arm_mod.revolute("r", axis)  # non-unit axes are normalised by the constructor
    for t in (-2.5, -0.3, 0.0, 1e-9, 1.2, np.pi):
        np.testing.assert_allclose(m.pose(jnp.array([t])), _pose(hand_built(t)), atol=2e-15)
    assert m.dof == 1 and m.state_names == ("r.q",)


def test_revolute_module_pose_about_oblique_axis_batched():
    axis = np.array([1.0, -2.0, 2.0])
    m = arm_mod.revolute("r", axis)
    t = np.linspace(-3.0, 3.0, 7)
    expected = np.stack([_pose(_rodrigues(axis, ti)) for ti in t])
    np.testing.assert_allclose(m.pose(t[:, None]), expected, rtol=0, atol=2e-15)


def test_prismatic_module_pose_is_translation_along_axis():
    axis = np.array([3.0, 0.0, 4.0])
    m = arm_mod.prismatic("p", axis)
    d = np.array([[-20.0], [0.0], [55.5]])
    expected = np.stack([_pose(np.eye(3), di * axis / 5.0) for di in d[:, 0]])
    np.testing.assert_allclose(m.pose(d), expected, rtol=0, atol=1e-14)


# --------------------------------------------------------------------------- the CDRA chain


def _cdra_numpy(frames: np.ndarray, q: np.ndarray, elbow_axis: np.ndarray):
    """Eq. 1 written out: F0 S(q_s) F1 E(q_e) F2 W(q_w) F3, and the poses after each module."""
    S = _pose(Rotation.from_rotvec(q[:3]).as_matrix())
    E = _pose(_rodrigues(elbow_axis, q[3]))
    W = _pose(Rotation.from_rotvec(q[4:]).as_matrix())
    OS = frames[0] @ S
    OE = OS @ frames[1] @ E
    OW = OE @ frames[2] @ W
    return OW @ frames[3], np.stack([OS, OE, OW])


def test_cdra_forward_kinematics_matches_numpy_product(cdra):
    rng = np.random.default_rng(1)
    # Non-trivial fixed frames: the nominal ones perturbed by large errors.
    X = np.concatenate([rng.uniform(-20, 20, (4, 3)), rng.uniform(-0.7, 0.7, (4, 3))], -1)
    arm = apply_frame_errors(cdra, X)
    lim = arm.state_limits
    q = lim[:, 0] + rng.uniform(size=(9, arm.dof)) * (lim[:, 1] - lim[:, 0])
    tool, after = fk(arm, q)
    assert tool.shape == (9, 4, 4) and after.shape == (9, 3, 4, 4)
    frames = np.asarray(arm.frames)
    axis = np.asarray(arm.module("elbow").axis)
    for i in range(len(q)):
        t_np, after_np = _cdra_numpy(frames, q[i], axis)
        np.testing.assert_allclose(tool[i], t_np, rtol=0, atol=1e-12)
        np.testing.assert_allclose(after[i], after_np, rtol=0, atol=1e-12)
    # The unbatched call agrees with the batched one.
    tool0, after0 = fk(arm, q[0])
    np.testing.assert_allclose(tool0, tool[0], atol=1e-12)
    np.testing.assert_allclose(after0, after[0], atol=1e-12)
    assert arm.state_names == (
        "shoulder.rx", "shoulder.ry", "shoulder.rz", "elbow.q", "wrist.rx", "wrist.ry", "wrist.rz"
    )  # fmt: skip
    assert arm.dof == 7 and arm.n_params == 24
    assert arm.param_names[:7] == (*(f"base.{c}" for c in arm_mod.TWIST_COMPONENTS), "upper_arm.vx")


def test_module_poses_stack_in_chain_order(cdra):
    q = np.array([0.1, -0.2, 0.3, 1.1, -0.4, 0.5, -0.6])
    P = poses_of(cdra, q)
    assert P.shape == (3, 4, 4)
    np.testing.assert_allclose(P[0], _pose(Rotation.from_rotvec(q[:3]).as_matrix()), atol=2e-15)
    np.testing.assert_allclose(P[1], _pose(_rot_y(q[3])), atol=2e-15)  # the elbow axis is y
    np.testing.assert_allclose(P[2], _pose(Rotation.from_rotvec(q[4:]).as_matrix()), atol=2e-15)


def test_module_poses_take_the_axes_as_an_array(cdra):
    """``module_poses(arm, q, axes)`` (as the solvers call it, the axes an argument) equals
    the arm's own, and other axes move the revolute module about them."""
    q = np.array([[0.1, -0.2, 0.3, 1.1, -0.4, 0.5, -0.6], [0.0, 0.2, -0.1, -0.7, 0.3, 0.0, 0.2]])
    axes = arm_mod.module_axes(cdra)
    assert axes.shape == (3, 3)
    np.testing.assert_array_equal(module_poses(cdra, q, axes), module_poses(cdra, q))
    other = axes.at[1].set(jnp.array([0.0, 0.0, 1.0]))
    P = module_poses(cdra, q, other)
    z = Rotation.from_rotvec([0.0, 0.0, 1.1]).as_matrix()
    np.testing.assert_allclose(P[0, 1], _pose(z), atol=2e-15)


@pytest.mark.parametrize("scale", [1.0, 50.0])
def test_frame_errors_round_trip(cdra, scale):
    rng = np.random.default_rng(2)
    # Paper range (1 mm, 0.05 rad) and large errors (50 mm, 2.5 rad: still below pi).
    X = np.concatenate([rng.uniform(-1, 1, (4, 3)), rng.uniform(-0.05, 0.05, (4, 3))], -1) * scale
    actual = apply_frame_errors(cdra, X.reshape(-1))
    # Left-multiplied, Eqs. 11-14: F_j^a = expm(hat(dt_j)) F_j.
    expected = np.stack(
        [scipy.linalg.expm(_hat6(x)) @ F for x, F in zip(X, cdra.frames, strict=True)]
    )
    np.testing.assert_allclose(actual.frames, expected, rtol=0, atol=1e-11)
    # The (K+1, 6) form is the same.
    np.testing.assert_allclose(apply_frame_errors(cdra, X).frames, actual.frames, atol=0)
    # Eqs. 15-18 recover the twists.
    np.testing.assert_allclose(frame_errors(actual, cdra), X, rtol=0, atol=1e-11)
    np.testing.assert_allclose(frame_errors(cdra, cdra), np.zeros((4, 6)), atol=1e-15)
    assert actual.module_names == cdra.module_names  # nothing else changes


# --------------------------------------------------------------------------- a 6R industrial arm

# The UR5's Denavit-Hartenberg table (mm, rad): d, a, alpha per joint; written independently
# of the model in conftest.UR5_TOML.
UR5_DH = np.array(
    [
        [89.159, 0.0, np.pi / 2],
        [0.0, -425.0, 0.0],
        [0.0, -392.25, 0.0],
        [109.15, 0.0, np.pi / 2],
        [94.65, 0.0, -np.pi / 2],
        [82.3, 0.0, 0.0],
    ]
)


def _dh_product(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    T = np.eye(4)
    after = []
    for t, (d, a, alpha) in zip(theta, UR5_DH, strict=True):
        T = T @ _pose(_rot_z(t))
        after.append(T)
        T = T @ _pose(np.eye(3), (0, 0, d)) @ _pose(np.eye(3), (a, 0, 0)) @ _pose(_rot_x(alpha))
    return T, np.stack(after)


def test_6r_arm_through_the_same_code(ur5):
    assert ur5.dof == 6 and ur5.n_params == 42 and len(ur5.modules) == 6
    # The published UR5 home position of the flange (mm).
    tool0, _ = forward_kinematics(ur5, jnp.zeros(6))
    np.testing.assert_allclose(tool0[:3, 3], [-817.25, -191.45, -5.491], atol=1e-9)
    q = np.random.default_rng(3).uniform(-3, 3, size=(8, 6))
    tool, after = fk(ur5, q)
    for i in range(len(q)):
        t_np, after_np = _dh_product(q[i])
        np.testing.assert_allclose(tool[i], t_np, rtol=0, atol=1e-11)
        np.testing.assert_allclose(after[i], after_np, rtol=0, atol=1e-11)


# --------------------------------------------------------------------------- errors


def test_wrong_state_shape_raises(cdra):
    with pytest.raises(
        ValueError, match=r"7 state entries.*shoulder\.rx.*got trailing dimension 6"
    ):
        forward_kinematics(cdra, jnp.zeros(6))
    with pytest.raises(ValueError, match=r"'elbow' \(revolute\) takes 1 state entries.*got.* 3"):
        cdra.module("elbow").pose(jnp.zeros(3))


def test_unknown_module_and_frame_names_raise(cdra):
    with pytest.raises(
        ValueError, match=r"no module 'x'; modules: \('shoulder', 'elbow', 'wrist'\)"
    ):
        cdra.module("x")
    with pytest.raises(ValueError, match=r"no frame 'x'; frames: \('base', 'upper_arm'"):
        cdra.frame_index("x")
    assert cdra.frame_index("tool") == 3 and cdra.module("elbow").kind == "revolute"


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: arm_mod.revolute("j", [0, 0, 1], limits=(1.0, -1.0)), "'j'.*low 1.0 .*high -1.0"),
        (lambda: arm_mod.revolute("j", [0, 0, 1], limits=(0.5, 0.5)), "'j'.*low 0.5"),
        (lambda: arm_mod.spherical("s", limits=[(-1, 1)] * 2), "'s'.*needs 3 .*limits, got 2"),
        (lambda: arm_mod.prismatic("p", [1, 0, 0], limits=(np.nan, 1.0)), "'p'.*finite"),
        (lambda: arm_mod.revolute("j", [0, 0, 1], limits=(-np.inf, 1.0)), "'j'.*finite"),
    ],
)
def test_bad_limits_raise(make, message):
    with pytest.raises(ValueError, match=message):
        make()


@pytest.mark.parametrize("axis", [[0, 0, 0], [1, 0], [np.nan, 0, 1], [np.inf, 0, 0]])
def test_bad_axis_raises(axis):
    with pytest.raises(ValueError, match="'j': axis must be a finite non-zero 3-vector"):
        arm_mod.revolute("j", axis)
    with pytest.raises(ValueError, match="'j': axis must be a finite non-zero 3-vector"):
        arm_mod.prismatic("j", axis)


def test_module_built_directly_needs_a_unit_axis():
    # Module() itself cannot normalise (it is a frozen pytree): a non-unit axis would silently
    # scale the joint angle, so it is refused with a pointer to the normalising constructors.
    with pytest.raises(ValueError, match=r"'j'.*unit.*revolute\(\)"):
        Module(name="j", kind="revolute", axis=jnp.array([0.0, 0.0, 2.0]), limits=((-1.0, 1.0),))
    with pytest.raises(ValueError, match="'j'.*axis"):
        Module(name="j", kind="prismatic", axis=jnp.zeros(2), limits=((-1.0, 1.0),))
    ok = Module(name="j", kind="revolute", axis=jnp.array([0.0, 0.6, 0.8]), limits=((-1.0, 1.0),))
    assert ok.dof == 1


def test_unknown_kind_and_bad_arm_raise(cdra):
    with pytest.raises(ValueError, match=r"'b': unknown kind 'ball'"):
        Module(name="b", kind="ball", axis=jnp.zeros(3), limits=((-1.0, 1.0),) * 3)
    with pytest.raises(ValueError, match="3 modules need 4 fixed frames"):
        Arm(frames=cdra.frames[:3], modules=cdra.modules, frame_names=cdra.frame_names[:3])
    with pytest.raises(ValueError, match=r"unique.*'elbow'"):
        Arm(
            frames=cdra.frames,
            modules=cdra.modules,
            frame_names=("base", "elbow", "forearm", "tool"),
        )
    with pytest.raises(ValueError, match=r"24 error parameters.*'base'.*shape \(23,\)"):
        apply_frame_errors(cdra, np.zeros(23))


def test_with_frames_and_frame_errors_check_their_shapes(cdra):
    """``with_frames`` skipped the constructor's check (3 frames for 3 modules was accepted and
    ``tool_pose`` clamped the missing index to the last frame); ``apply_frame_errors`` accepted
    any array of 24 numbers, so a transposed ``(6, 4)`` was silently paired wrongly."""
    with pytest.raises(
        ValueError, match=r"with_frames needs 4 fixed frames .* got frames of shape \(3, 4, 4\)"
    ):
        cdra.with_frames(jnp.stack([jnp.eye(4)] * 3))
    assert cdra.with_frames(2 * cdra.frames).frames.shape == (4, 4, 4)
    with pytest.raises(ValueError, match=r"pass \(24,\) or \(4, 6\), got errors of shape \(6, 4\)"):
        apply_frame_errors(cdra, np.zeros((6, 4)))
    X = np.arange(24.0) * 1e-3
    np.testing.assert_array_equal(
        apply_frame_errors(cdra, X).frames, apply_frame_errors(cdra, X.reshape(4, 6)).frames
    )


def test_measurements_select_with_no_rows(cdra):
    """``select([])`` raised numpy's IndexError (an empty list is a float array)."""
    from cdra_jax.io import Measurements

    q = np.zeros((3, cdra.dof))
    meas = Measurements.from_arrays(cdra, q)
    assert meas.select([]).m == 0
    assert meas.select(np.array([2, 0])).m == 2
    assert meas.select(np.array([True, False, True])).m == 2
    with pytest.raises(ValueError, match="integer indices or a boolean mask"):
        meas.select(np.array([0.0, 1.0]))
