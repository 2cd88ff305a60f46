"""Synthetic measurements: pose sampling, preset frame errors and measurement noise (Section V).

The paper's simulation procedure: (1) draw random module states within the joint limits that
satisfy the tension-closure condition (:func:`sample_poses`), (2) preset errors ``dt'_j`` on the
fixed transforms, uniform in ``+-d_v`` (mm) and ``+-d_w`` (rad) per component, (3) compute the
'actual' tool poses from the erroneous frames, and (for Section VI) add measurement noise.
Everything is pure JAX with explicit PRNG keys, so it jits and vmaps over trials.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from . import lie
from .arm import Arm, apply_frame_errors, sample_states, tool_pose
from .calibration.model import NoiseModel
from .modules.tension import sample_feasible_states

StateSampler = Callable[[Array, Arm, int], Array]
"""``sampler(key, arm, m) -> (m, dof)`` module states."""


def sample_poses(key: Array, arm: Arm, m: int, dtype=None, *, throw: bool = True) -> Array:
    """Section V step 1: ``m`` states within the joint limits that the arm can hold: ``(m, dof)``.

    When a module of ``arm`` has cables in the model, states are drawn uniformly within the
    limits and rejected unless every module with cables has tension closure with a margin
    (:func:`cdra_jax.modules.sample_feasible_states` with its default margin); the states of
    modules without cables impose no condition and stay uniform within their limits. Without
    cables anywhere this is :func:`sample_states`. Jit- and vmap-able (a fixed number of draws;
    raises at run time in the rare case that too few of them are feasible, see
    :func:`~cdra_jax.modules.sample_feasible_states`; ``throw=False``: NaN states instead).
    The default sampler of :func:`simulate_trial`, of the paper reproduction, of
    ``cdra-jax simulate`` and of the pose-selection pool; the sweeps use it with
    ``throw=False``.
    """
    if any(mod.n_cables > 0 for mod in arm.modules):
        return sample_feasible_states(key, arm, m, dtype, throw=throw)
    return sample_states(key, arm, m, dtype)


def random_frame_errors(
    key: Array, arm: Arm, d_v: float = 1.0, d_w: float = 0.05, dtype=None
) -> Array:
    """Preset errors ``X (6 (K+1),)``: each component uniform in ``+-d_v`` mm / ``+-d_w`` rad.

    The paper's range (Section V) is ``d_v = 1 mm``, ``d_w = 0.05 rad``.
    """
    dtype = dtype or jnp.asarray(arm.frames).dtype
    k = len(arm.frame_names)
    u = jax.random.uniform(key, (k, 6), dtype=dtype, minval=-1.0, maxval=1.0)
    scale = jnp.asarray([d_v] * 3 + [d_w] * 3, dtype=dtype)
    return (u * scale).reshape(-1)


def add_measurement_noise(key: Array, poses: ArrayLike, noise: NoiseModel | None) -> Array:
    """Perturb measured poses: ``p + N(0, s_pos^2 I)``, ``R -> exp(hat(N(0, s_rot^2 I))) R``.

    The stds may be per-pose arrays ``(m,)`` (see :class:`~cdra_jax.calibration.NoiseModel`),
    or any shape that broadcasts against the leading axes of ``poses (..., 4, 4)`` without
    changing them; others raise ``ValueError`` naming the field.

    The rotation noise is applied in the world frame, matching the whitening of
    :func:`cdra_jax.calibration.whitening`. ``noise=None`` returns ``poses`` unchanged.
    """
    poses = jnp.asarray(poses)
    if noise is None:
        return poses
    lead = poses.shape[:-2]
    for name in ("position_mm", "rotation_rad"):
        shape = np.shape(getattr(noise, name))
        try:
            ok = np.broadcast_shapes(shape, lead) == lead
        except ValueError:
            ok = False
        if not ok:
            raise ValueError(
                f"noise.{name} must be a number (shape ()) or one std per pose (shape (m,) = "
                f"({lead[-1] if lead else 1},), broadcast against the poses' leading axes "
                f"{lead}), got shape {shape}"
            )
    kp, kr = jax.random.split(key)
    shape = poses.shape[:-2] + (3,)
    # [..., None]: per-pose stds (m,) broadcast against the pose axis, as in the whitening.
    sp = jnp.asarray(noise.position_mm, poses.dtype)[..., None]
    sr = jnp.asarray(noise.rotation_rad, poses.dtype)[..., None]
    dp = sp * jax.random.normal(kp, shape, poses.dtype)
    dw = sr * jax.random.normal(kr, shape, poses.dtype)
    R = lie.so3_exp(dw) @ lie.rotation(poses)
    return lie.make_pose(R, lie.translation(poses) + dp)


def add_outliers(
    key: Array,
    poses: ArrayLike,
    n_outliers: int,
    position_mm: float = 5.0,
    rotation_rad: float = 0.05,
) -> tuple[Array, Array]:
    """Corrupt ``n_outliers`` randomly chosen poses with a gross error (a mis-seated probe).

    Each chosen pose gets a position offset of length ``position_mm`` along a random direction
    and a world-frame rotation of angle ``rotation_rad`` about a random axis (applied as in
    :func:`add_measurement_noise`); the other poses are unchanged.

    Args:
        key: PRNG key.
        poses: ``(m, 4, 4)`` measured tool poses.
        n_outliers: how many poses to corrupt (static, ``0 <= n_outliers <= m``).
        position_mm, rotation_rad: size of the gross error.

    Returns:
        ``(corrupted (m, 4, 4), mask (m,) bool)``: the poses and which of them were corrupted.
    """
    poses = jnp.asarray(poses)
    m = poses.shape[-3]
    if not 0 <= n_outliers <= m:
        raise ValueError(f"n_outliers must be between 0 and the pose count {m}, got {n_outliers}")
    k_pick, k_dir, k_axis = jax.random.split(key, 3)
    mask = jnp.zeros(m, bool).at[jax.random.permutation(k_pick, m)[:n_outliers]].set(True)

    def unit(k):
        v = jax.random.normal(k, (m, 3), poses.dtype)
        return v / jnp.linalg.norm(v, axis=-1, keepdims=True)

    dp = jnp.where(mask[:, None], position_mm * unit(k_dir), 0.0)
    dw = jnp.where(mask[:, None], rotation_rad * unit(k_axis), 0.0)
    R = lie.so3_exp(dw) @ lie.rotation(poses)
    return lie.make_pose(R, lie.translation(poses) + dp), mask


def measure(key: Array, arm_actual: Arm, q: ArrayLike, noise: NoiseModel | None = None) -> Array:
    """Simulated measured tool poses ``(m, 4, 4)`` of the actual arm at states ``q (m, dof)``."""
    return add_measurement_noise(key, tool_pose(arm_actual, q), noise)


def simulate_trial(
    key: Array,
    arm: Arm,
    m: int,
    *,
    d_v: float = 1.0,
    d_w: float = 0.05,
    noise: NoiseModel | None = None,
    m_verify: int | None = None,
    sampler: StateSampler | None = None,
    errors: ArrayLike | None = None,
) -> tuple[Array, Array, Array, Array, Array]:
    """One trial of the paper's procedure (Section V steps 1-3, plus noise for Section VI).

    Args:
        key: PRNG key.
        arm: nominal arm.
        m: number of calibration poses (static).
        d_v, d_w: preset error ranges (mm, rad), used when ``errors`` is ``None``.
        noise: measurement noise, or ``None`` for noise-free 'measurements'.
        m_verify: number of verification poses (default ``m``).
        sampler: module-state sampler ``sampler(key, arm, m)`` (default :func:`sample_poses`:
            uniform within the joint limits and, for modules with cables, with tension closure;
            pass :func:`sample_states` for plain uniform states).
        errors: preset errors ``(6 (K+1),)`` instead of random ones.

    Returns:
        ``(q_cal (m, dof), T_cal (m, 4, 4), q_ver, T_ver, errors (6 (K+1),))``.
    """
    sampler = sampler or sample_poses
    k_err, k_cal, k_ver, k_n1, k_n2 = jax.random.split(key, 5)
    if errors is None:
        X = random_frame_errors(k_err, arm, d_v, d_w)
    else:
        X = jnp.asarray(errors, jnp.asarray(arm.frames).dtype).reshape(-1)
    actual = apply_frame_errors(arm, X)
    q_cal = sampler(k_cal, arm, m)
    q_ver = sampler(k_ver, arm, m if m_verify is None else m_verify)
    return (
        q_cal,
        measure(k_n1, actual, q_cal, noise),
        q_ver,
        measure(k_n2, actual, q_ver, noise),
        X,
    )
