"""Synthetic measurements: pose sampling, preset frame errors and measurement noise (Section V).

The paper's simulation procedure: (1) draw random module states within the joint limits,
(2) preset errors ``dt'_j`` on the fixed transforms, uniform in ``+-d_v`` (mm) and ``+-d_w``
(rad) per component, (3) compute the 'actual' tool poses from the erroneous frames, and (for
Section VI) add measurement noise. Everything is pure JAX with explicit PRNG keys, so it jits
and vmaps over trials.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from . import lie
from .arm import Arm, apply_frame_errors, tool_pose
from .calibration.model import NoiseModel

StateSampler = Callable[[Array, Arm, int], Array]
"""``sampler(key, arm, m) -> (m, dof)`` module states."""


def sample_states(key: Array, arm: Arm, m: int, dtype=None) -> Array:
    """``m`` module states drawn uniformly within each state entry's limits: ``(m, dof)``.

    Spherical modules are sampled per rotation-vector component within their box limits.
    """
    lim = jnp.asarray(arm.state_limits, dtype=dtype or jnp.asarray(arm.frames).dtype)
    u = jax.random.uniform(key, (m, arm.dof), dtype=lim.dtype)
    return lim[:, 0] + u * (lim[:, 1] - lim[:, 0])


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

    The rotation noise is applied in the world frame, matching the whitening of
    :func:`cdra_jax.calibration.whitening`. ``noise=None`` returns ``poses`` unchanged.
    """
    poses = jnp.asarray(poses)
    if noise is None:
        return poses
    kp, kr = jax.random.split(key)
    shape = poses.shape[:-2] + (3,)
    dp = jnp.asarray(noise.position_mm, poses.dtype) * jax.random.normal(kp, shape, poses.dtype)
    dw = jnp.asarray(noise.rotation_rad, poses.dtype) * jax.random.normal(kr, shape, poses.dtype)
    R = lie.so3_exp(dw) @ lie.rotation(poses)
    return lie.make_pose(R, lie.translation(poses) + dp)


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
        sampler: module-state sampler (default :func:`sample_states`).
        errors: preset errors ``(6 (K+1),)`` instead of random ones.

    Returns:
        ``(q_cal (m, dof), T_cal (m, 4, 4), q_ver, T_ver, errors (6 (K+1),))``.
    """
    sampler = sampler or sample_states
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
