"""The calibration model (Eqs. 7-9, 20-21) in a memory layout that vectorises over trials.

The solvers evaluate Eq. 9 a few times per trial and are run under ``jax.vmap`` over many
trials. Under ``vmap`` the batch axis leads, so the textbook layout of a pose stack,
``(m, 4, 4)``, becomes ``(trials, m, 4, 4)``: every elementwise operation then runs over rows of
3, 4 or 6 numbers and every component access (``R[..., 0, 1]``) is a strided gather, which the
CPU cannot vectorise. This module keeps the pose axis ``m`` *last*, ``(3, 4, m)`` (the top three
rows of each homogeneous matrix), and writes the few Lie-group operations the model needs as
explicit component arithmetic, so that every operation runs over contiguous rows of ``m`` poses.
The maths is that of :mod:`cdra_jax.lie`, :func:`cdra_jax.arm.chain`,
:func:`.model.residual_twist`, :func:`.model.calibration_jacobian`, :func:`.model.whitening` and
:func:`.model.deviation_metrics`; the tests check every function here against those to rounding.

Layout: a "pose stack" is ``(3, 4, m)``: ``S[:, :3]`` the rotations ``(3, 3, m)``, ``S[:, 3]``
the translations ``(3, m)`` in mm. The module poses of a trial are ``(K, 3, 4, m)``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from .. import lie
from ..arm import moved_frames
from .model import NoiseModel


class Linearisation(NamedTuple):
    """The stacked system of Eq. 9 at one model, for one trial.

    The rows of ``Y~`` and ``D~`` are ordered component-major here (all poses' ``vx``, then all
    poses' ``vy``, ...), a row permutation of Eq. 9's pose-by-pose stacking that changes neither
    ``D~^T D~``, ``D~^T Y~``, the singular values nor the cost, and ``D~`` is held transposed,
    which is the layout the products ``D~^T D~`` and ``D~^T Y~`` want.

    Attributes:
        Y: ``(6m,)`` residual twists ``log(T_meas T_model^-1)^v`` (Eq. 7), whitened when a
            noise model is given; ``Y.reshape(6, m)[:, k]`` is pose ``k``'s ``(v, w)``.
        DT: ``(6(K+1), 6m)`` the calibration Jacobian (Eqs. 8-9) transposed, whitened likewise;
            ``DT.reshape(n, 6, m)[:, :, k]`` is ``D_k^T``.
        delta_p: Eq. 20 (mm) of the model against the measurements.
        delta_R: Eq. 21 (rad).
    """

    Y: Array
    DT: Array
    delta_p: Array
    delta_R: Array

    def stacked(self) -> tuple[Array, Array]:
        """``(Y~ (6m,), D~ (6m, n))`` in Eq. 9's pose-by-pose order (as ``stacked_system``)."""
        n = self.DT.shape[0]
        m = self.Y.shape[0] // 6
        Y = self.Y.reshape(6, m).T.reshape(6 * m)
        D = jnp.transpose(self.DT.reshape(n, 6, m), (2, 1, 0)).reshape(6 * m, n)
        return Y, D

    def normal_equations(self) -> tuple[Array, Array]:
        """``(D~^T D~ (n, n), D~^T Y~ (n,))`` of Eq. 10."""
        return self.DT @ self.DT.T, self.DT @ self.Y


def pose_stack(T: ArrayLike) -> Array:
    """``(..., m, 4, 4)`` homogeneous poses to the pose-last layout ``(..., 3, 4, m)``."""
    T = jnp.asarray(T)
    return jnp.moveaxis(T[..., :3, :], -3, -1)


def compose(A: Array, B: Array) -> Array:
    """Product of two pose stacks ``(3, 4, ...)`` (broadcasting over the trailing axes).

    The columns of ``A`` and the rows of ``B``'s rotation are taken apart by
    :func:`jax.numpy.unstack`, one equation each, where indexing traces two or three per
    component (tracing, batching and lowering cost time per equation; the program is the
    same)."""
    a0, a1, a2, pA = jnp.unstack(A, axis=1)
    r0, r1, r2 = jnp.unstack(B[:, :3])
    q0, q1, q2 = jnp.unstack(B[:, 3])
    R = a0[:, None] * r0[None] + a1[:, None] * r1[None] + a2[:, None] * r2[None]
    p = a0 * q0 + a1 * q1 + a2 * q2 + pA
    return jnp.concatenate([R, p[:, None]], axis=1)


def left_multiply(E: Array, F: Array) -> Array:
    """``E F`` for homogeneous matrices ``(..., 4, 4)`` (broadcasting), as sums of elementwise
    products: for a few 4x4 matrices per trial under ``vmap`` cheaper than a matrix product
    call (the solvers' update of the frames, Eqs. 11-14)."""
    top = E[..., :3, 3:] * F[..., 3:, :]
    for c in range(3):
        top = top + E[..., :3, c : c + 1] * F[..., c : c + 1, :]
    return jnp.concatenate([top, jnp.broadcast_to(F[..., 3:, :], top.shape[:-2] + (1, 4))], -2)


def step_frames(X: Array, frames: Array) -> Array:
    """The frames after a step, ``exp(hat(X_j)) F_j`` (Eqs. 11-14, :func:`cdra_jax.arm.
    moved_frames`): ``X (6 (K+1),)`` (Eq. 8's order), ``frames (K+1, 4, 4)``, products as
    :func:`left_multiply`."""
    return left_multiply(lie.se3_exp(X.reshape(frames.shape[0], 6)), frames)


def chain(frames: Array, poses: Array) -> tuple[Array, Array]:
    """Eq. 1 on pose stacks: :func:`cdra_jax.arm.chain` in the pose-last layout.

    Args:
        frames: ``(K+1, 4, 4)`` fixed transforms (shared by the poses).
        poses: ``(K, 3, 4, m)`` module poses.

    Returns:
        ``(tool (3, 4, m), after (K, 3, 4, m))``.
    """
    frames = jnp.asarray(frames)[:, :3, :, None].astype(poses.dtype)
    k = poses.shape[0]
    T = jnp.broadcast_to(frames[0], poses.shape[1:])
    after = []
    for i in range(k):
        # The barrier changes no value; with it XLA compiles 7 % less code for the solvers
        # (``benchmarks/compile_split.py``; one after every product instead: 6 % more).
        T = jax.lax.optimization_barrier(compose(T, poses[i]))
        after.append(T)
        T = compose(T, frames[i + 1])
    return T, jnp.stack(after)


def _components(a) -> tuple:
    """The three components of a 3-sequence: a tuple or list as it is, an array unstacked along
    its leading axis (one equation, where indexing traces two per component)."""
    return tuple(a) if isinstance(a, (tuple, list)) else tuple(jnp.unstack(a))


def _cross(a, b):
    """Cross product of two 3-sequences of equally shaped arrays (the leading index)."""
    a0, a1, a2 = _components(a)
    b0, b1, b2 = _components(b)
    return (a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0)


def so3_log(R: Array) -> tuple[Array, Array]:
    """:func:`cdra_jax.lie.so3_log` for rotations ``(3, 3, ...)``: the rotation vector ``w (3,
    ...)`` and its squared norm ``|w|^2 (...)``.

    The same algorithm, component by component: Shepperd's quaternion (largest-pivot branch
    chosen before the square root, accurate near pi) and the quaternion logarithm with its
    small-angle series, ``w = f(q) q_xyz`` (``f``: :func:`cdra_jax.lie._quaternion_log_factor`,
    shared with :mod:`cdra_jax.lie`). The factor ``f`` multiplies the stacked vector
    part, and ``|w|^2 = f^2 |q_xyz|^2`` is read off it: XLA evaluates the arc tangent of ``f``
    inside every kernel that reads ``w``, and so emits its code once per kernel rather than
    once per component (and per reduction over them): a fifth less IR for the residual's
    logarithm, 4 % of the paper solver's (``benchmarks/compile_split.py``).
    """
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = (jnp.unstack(row) for row in jnp.unstack(R))
    t0 = 1 + m00 - m11 - m22
    t1 = 1 - m00 + m11 - m22
    t2 = 1 - m00 - m11 + m22
    t3 = 1 + m00 + m11 + m22
    c0, c1, c2 = m22 < 0, m00 > m11, m00 < -m11

    def pick(a, b, c, d):
        return jnp.where(c0, jnp.where(c1, a, b), jnp.where(c2, c, d))

    t = pick(t0, t1, t2, t3)
    qw = pick(m21 - m12, m02 - m20, m10 - m01, t3)
    qx = pick(t0, m10 + m01, m02 + m20, m21 - m12)
    qy = pick(m10 + m01, t1, m21 + m12, m02 - m20)
    qz = pick(m02 + m20, m21 + m12, t2, m10 - m01)
    # Quaternion (qw, qx, qy, qz) * 0.5 / sqrt(t), sign flipped to qw >= 0.
    s = 0.5 / jnp.sqrt(t)
    s = jnp.where(qw < 0, -s, s)
    qw, qx, qy, qz = qw * s, qx * s, qy * s, qz * s
    n_sq = qx * qx + qy * qy + qz * qz
    f = lie._quaternion_log_factor(qw, n_sq)
    return f * jnp.stack([qx, qy, qz]), f * f * n_sq


def se3_log(T: Array) -> Array:
    """:func:`cdra_jax.lie.se3_log` for pose stacks ``(3, 4, ...)``: ``-> (6, ...)``, ``(v, w)``.

    ``v = A^-1 p`` with ``A^-1 = I - hat(w)/2 + c hat(w)^2`` as in
    :func:`cdra_jax.lie.se3_log` (the same ``c``), applied as two cross products.
    """
    w, x = so3_log(T[:, :3])
    p = T[:, 3]
    c = lie._jacobian_inverse_coefficient(x)
    wxp = _cross(w, p)
    wwxp = _cross(w, wxp)
    v = jnp.stack([p[i] - 0.5 * wxp[i] + c * wwxp[i] for i in range(3)])
    return jnp.concatenate([v, w])


def _matmul3(A, B):
    """Product of 3x3 matrices stored ``(3, 3, ...)`` (broadcasting over the trailing axes)."""
    return A[:, 0, None] * B[None, 0] + A[:, 1, None] * B[None, 1] + A[:, 2, None] * B[None, 2]


def _hat(w):
    """``hat`` of vectors ``(3, ...) -> (3, 3, ...)``."""
    z = jnp.zeros_like(w[0])
    return jnp.stack(
        [jnp.stack([z, -w[2], w[1]]), jnp.stack([w[2], z, -w[0]]), jnp.stack([-w[1], w[0], z])]
    )


def _series_or_exact(x, series, exact):
    """``series(x)`` below the small-angle threshold of :mod:`cdra_jax.lie`, else
    ``exact(x, t, sin t, 1 - cos t, (t/2) cot(t/2))`` (``t = sqrt(x)``), from one sine and one
    cosine of ``t/2`` (XLA:CPU evaluates them per element: the coefficients of one pose share
    them)."""
    small = x < lie._SMALL_ANGLE_SQ
    safe = jnp.where(small, jnp.ones_like(x), x)
    t = jnp.sqrt(safe)
    sh, ch = jnp.sin(0.5 * t), jnp.cos(0.5 * t)
    trig = (safe, t, 2 * sh * ch, 2 * sh * sh, 0.5 * t * ch / sh)
    return tuple(jnp.where(small, s(x), e(*trig)) for s, e in zip(series, exact, strict=True))


def se3_left_jacobian_blocks(xi: Array) -> tuple[Array, Array]:
    """Blocks of the left Jacobian of SE(3), ``J_l(xi) = [[J, Q], [0, J]]``, for ``xi (6, ...)``.

    ``exp(hat(xi + d)) ~= exp(hat(J_l(xi) d)) exp(hat(xi))`` with twists ``(v, w)``: ``J`` is the
    left Jacobian of SO(3) (``A`` of Eq. 26, :func:`cdra_jax.lie.so3_left_jacobian`) and ``Q``
    the coupling block (Barfoot, *State Estimation for Robotics*, Eq. 7.86):

        Q = 1/2 V + c1 (W V + V W + W V W) + c2 (W^2 V + V W^2 - 3 W V W)
            + c3 (W V W^2 + W^2 V W),

    ``V = hat(v)``, ``W = hat(w)``, ``t = |w|``, ``c1 = (t - sin t) / t^3``,
    ``c2 = (t^2/2 + cos t - 1) / t^4``, ``c3 = (2t - 3 sin t + t cos t) / (2 t^5)``, with their
    Taylor series below the small-angle threshold.

    Returns:
        ``(J, Q)``, each ``(3, 3, ...)``.
    """
    v, w = xi[:3], xi[3:]
    x = jnp.sum(w * w, axis=0)
    c1, c2, c3, b = _series_or_exact(
        x,
        (
            lambda x: (1 - x / 20 * (1 - x / 42 * (1 - x / 72 * (1 - x / 110)))) / 6,
            lambda x: (1 - x / 30 * (1 - x / 56 * (1 - x / 90 * (1 - x / 132)))) / 24,
            lambda x: 1 / 120 - x / 2520 + x * x / 120960 - x * x * x / 9979200,
            lambda x: 0.5 * (1 - x / 12 * (1 - x / 30 * (1 - x / 56 * (1 - x / 90)))),
        ),
        (
            lambda x, t, s, omc, hcot: (t - s) / (x * t),
            lambda x, t, s, omc, hcot: (0.5 * x - omc) / (x * x),
            lambda x, t, s, omc, hcot: (2 * t - 3 * s + t * (1 - omc)) / (2 * x * x * t),
            lambda x, t, s, omc, hcot: omc / x,
        ),
    )
    # The products of hat matrices in closed form (d = w.v, u = w x v; a b^T - b a^T =
    # hat(b x a)): W^2 = w w^T - x I, W V + V W = v w^T + w v^T - 2 d I, W V W = -d W,
    # W^2 V + V W^2 - 3 W V W = hat(w x u) + d W = 2 d W - x V, W V W^2 + W^2 V W = -2 d W^2.
    W, V = _hat(w), _hat(v)
    d = jnp.sum(w * v, axis=0)
    eye = jnp.eye(3, dtype=xi.dtype).reshape((3, 3) + (1,) * (xi.ndim - 1))
    ww = w[:, None] * w[None, :]
    W2 = ww - x * eye
    J = eye + b * W + c1 * W2
    Q = (
        (0.5 - c2 * x) * V
        + (2 * c2 - c1) * d * W
        + c1 * (v[:, None] * w[None, :] + w[:, None] * v[None, :])
        - 2 * d * (c1 * eye + c3 * W2)
    )
    return J, Q


def se3_left_jacobian(xi: Array) -> Array:
    """``J_l(xi) = [[J, Q], [0, J]]`` (see :func:`se3_left_jacobian_blocks`): ``(6, 6, ...)``."""
    J, Q = se3_left_jacobian_blocks(xi)
    return jnp.concatenate(
        [jnp.concatenate([J, Q], axis=1), jnp.concatenate([jnp.zeros_like(J), J], axis=1)]
    )


def se3_left_jacobian_inverse_blocks(xi: Array) -> tuple[Array, Array]:
    """Blocks of ``J_l(xi)^-1 = [[J^-1, B], [0, J^-1]]`` for ``xi (6, ...)``, each ``(3, 3, ...)``.

    ``J^-1 = I - 1/2 W + c W^2`` (``W = hat(w)``, ``c = (1 - (t/2) cot(t/2)) / t^2``,
    ``t = |w|``) is the inverse left Jacobian of SO(3), and ``B = -J^-1 Q J^-1``
    (:func:`se3_left_jacobian_blocks`) is the derivative of ``J^-1(w)`` along ``v``:

        B = -1/2 V + c (W V + V W) + 2 c' (w . v) W^2,     c' = dc / d(t^2),

    since ``J_l^-1 = ad / (exp(ad) - I)`` is a function of ``ad(xi) = [[W, V], [0, W]]``, whose
    top-right block is the derivative of the same function of ``W`` along ``V`` (checked
    against the inverse of :func:`se3_left_jacobian` by the test suite). With ``W V + V W = v
    w^T + w v^T - 2 (w . v) I`` and ``W^2 = w w^T - t^2 I`` it costs what ``Q`` costs, without
    the two 3x3 products of ``J^-1 Q J^-1``. ``c' = ((t/2) cot(t/2) / 2 + t^2 / (4 (1 - cos t))
    - 1) / t^4``, with their Taylor series below the small-angle threshold.
    """
    v, w = xi[:3], xi[3:]
    x = jnp.sum(w * w, axis=0)
    c, dc = _series_or_exact(
        x,
        (
            lambda x: 1 / 12 + x / 720 + x * x / 30240 + x * x * x / 1209600,
            lambda x: 1 / 720 + x / 15120 + x * x / 403200 + x * x * x / 11975040,
        ),
        (
            lambda x, t, s, omc, hcot: (1 - hcot) / x,
            lambda x, t, s, omc, hcot: (0.5 * hcot + 0.25 * x / omc - 1) / (x * x),
        ),
    )
    W, V = _hat(w), _hat(v)
    d = jnp.sum(w * v, axis=0)
    eye = jnp.eye(3, dtype=xi.dtype).reshape((3, 3) + (1,) * (xi.ndim - 1))
    W2 = w[:, None] * w[None, :] - x * eye
    J_inv = eye - 0.5 * W + c * W2
    B = -0.5 * V + c * (v[:, None] * w[None, :] + w[:, None] * v[None, :] - 2 * d * eye)
    return J_inv, B + 2 * dc * d * W2


def se3_left_jacobian_inverse(xi: Array) -> Array:
    """``J_l(xi)^-1 = [[J^-1, -J^-1 Q J^-1], [0, J^-1]]``: ``(6, ...) -> (6, 6, ...)``
    (:func:`se3_left_jacobian_inverse_blocks`)."""
    Ji, B = se3_left_jacobian_inverse_blocks(xi)
    top = jnp.concatenate([Ji, B], axis=1)
    return jnp.concatenate([top, jnp.concatenate([jnp.zeros_like(Ji), Ji], axis=1)])


def residual(measured: Array, tool: Array) -> Array:
    """Eq. 7, ``log(T_meas T_model^-1)^v``, for pose stacks: ``(3, 4, m) x2 -> (6, m)``."""
    m0, m1, m2, pm = jnp.unstack(measured, axis=1)  # the columns of R_m, and p_m
    t0, t1, t2, pt = jnp.unstack(tool, axis=1)
    # T_meas T_model^-1 = [R_m R_t^T, p_m - R_m R_t^T p_t]
    R = m0[:, None] * t0[None] + m1[:, None] * t1[None] + m2[:, None] * t2[None]
    c0, c1, c2 = jnp.unstack(R, axis=1)
    p0, p1, p2 = jnp.unstack(pt)
    p = pm - (c0 * p0 + c1 * p1 + c2 * p2)
    return se3_log(jnp.concatenate([R, p[:, None]], axis=1))


def adjoint_transpose(T: Array) -> Array:
    """``Ad_T^T = [[R^T, 0], [(hat(p) R)^T, R^T]]`` (Eq. 25) for pose stacks: ``-> (6, 6, ...)``."""
    R, p = T[:, :3], T[:, 3]
    Rt = jnp.swapaxes(R, 0, 1)
    Ht = jnp.swapaxes(jnp.stack(_cross(p[:, None], R)), 0, 1)  # hat(p) R: column j = p x R[:, j]
    return jnp.concatenate(
        [jnp.concatenate([Rt, jnp.zeros_like(Rt)], axis=1), jnp.concatenate([Ht, Rt], axis=1)]
    )


def whiten(A: Array, measured: Array, noise: NoiseModel) -> Array:
    """Apply each pose's whitening ``G`` (:func:`.model.whitening`) to the leading twist axis.

    Args:
        A: ``(6, ..., m)``: for each pose ``k`` (last axis) twists ``(v, w)`` along the first
            axis (a residual, or the rows of a Jacobian).
        measured: ``(3, 4, m)`` measured tool poses (their positions ``p`` are the lever arms).
        noise: the noise model.

    Returns:
        ``G A``: ``((v - p x w) / s_pos, w / s_rot)``.
    """
    dtype = A.dtype
    sp = jnp.asarray(noise.position_mm, dtype)
    sr = jnp.asarray(noise.rotation_rad, dtype)
    p = measured[:, 3].reshape((3,) + (1,) * (A.ndim - 2) + measured.shape[-1:])
    v, w = A[:3], A[3:]
    return jnp.concatenate([(v - jnp.stack(_cross(p, w))) / sp, w / sr])


def linearise(
    frames: ArrayLike,
    poses: Array,
    measured: Array,
    noise: NoiseModel | None = None,
) -> Linearisation:
    """``Y~``, ``D~`` (Eq. 9) and the deviation metrics (Eqs. 20-21) of one trial.

    Args:
        frames: ``(K+1, 4, 4)`` current fixed transforms.
        poses: ``(K, 3, 4, m)`` module poses (:func:`pose_stack` of
            :func:`cdra_jax.arm.module_poses`), constant during a calibration.
        measured: ``(3, 4, m)`` measured tool poses (:func:`pose_stack`).
        noise: whitening as :func:`.model.whitening`, or ``None`` (the paper's form).

    Returns:
        A :class:`Linearisation`; :meth:`Linearisation.stacked` equals
        :func:`.model.stacked_system`.

    Eq. 21's ``|log(R_a^-1 R_c)|`` is the rotation angle of ``R_a R_c^-1`` (a conjugate of
    its inverse), i.e. the norm of the rotational part of Eq. 7's residual, so the metric
    reuses that logarithm instead of taking a second one.
    """
    tool, after = chain(jnp.asarray(frames), poses)
    Y, delta_p, delta_R = residual_and_metrics(measured, tool)  # Y: (6, m)
    if noise is not None:  # G Y, G applied to the rows (v, w)
        Y = whiten(Y, measured, noise)
    DT = jacobian_transposed(after, measured, noise)
    return Linearisation(Y=Y.reshape(-1), DT=DT, delta_p=delta_p, delta_R=delta_R)


def jacobian_transposed(after: Array, measured: Array, noise: NoiseModel | None = None) -> Array:
    """``D~^T (6(K+1), 6m)`` of Eq. 9 in the layout of :class:`Linearisation`, from the world
    poses before each fixed frame (``after`` of :func:`chain`, ``(K, 3, 4, m)``) and, for the
    whitening, the measured poses ``(3, 4, m)``."""
    dtype = after.dtype
    m = after.shape[-1]
    # D_k^T = [I; Ad(P_1)^T; ...; Ad(P_K)^T] as (K+1, 6, 6, m): (frame, column, row, pose)
    eye = jnp.broadcast_to(jnp.eye(6, dtype=dtype)[:, :, None], (6, 6, m))
    blocks = jnp.stack([eye] + [adjoint_transpose(a) for a in after])
    if noise is not None:  # G D_k, G applied to the rows (v, w)
        blocks = jnp.moveaxis(whiten(jnp.moveaxis(blocks, 2, 0), measured, noise), 0, 2)
    return blocks.reshape(6 * blocks.shape[0], 6 * m)


def normal_equations(
    after: Array, Y: Array, measured: Array, noise: NoiseModel | None = None
) -> tuple[Array, Array]:
    """``(D~^T D~ (n, n), D~^T Y~ (n,))`` of Eq. 10, as :meth:`Linearisation.normal_equations`
    of :func:`linearise` to rounding, without the zeros of ``D~``.

    Pose ``k``'s rows of ``D`` are ``[Ad(P_0), ..., Ad(P_K)]`` (Eq. 8, ``P_0 = I``), ``Ad(P) =
    [[R, H], [0, R]]`` with ``H = hat(p) R`` (Eq. 25): a block's rotation rows do not depend
    on its translation parameters. The whitening keeps that (:func:`whiten`: ``G = S
    Ad(Tr(-p_meas))``, so ``G Ad(P) = S Ad(P')`` with ``P'`` the pose moved by ``-p_meas`` and
    ``S = diag(I / s_pos, I / s_rot)``). So ``N = V^T V + W^T W`` with ``V`` the translation
    rows (all ``n`` parameters: ``[R, H] / s_pos`` per block) and ``W`` the rotation rows of
    the rotation parameters only (``R / s_rot``), which are those of ``V``'s translation
    parameters times ``s_pos / s_rot``: ``W^T W`` is read off ``V^T V`` (:func:`_split_gram`),
    half the multiplications of ``D~^T D~`` and no zero block.

    Args:
        after: ``(K, 3, 4, m)`` world poses before each fixed frame after the first (``after``
            of :func:`chain`).
        Y: ``(6, m)`` the residual of Eq. 7, whitened with ``noise`` (:func:`whiten`).
        measured: ``(3, 4, m)`` measured tool poses (for the whitening).
        noise: the noise model, or ``None`` (the paper's form).
    """
    dtype = after.dtype
    R, p = _blocks(after)
    if noise is not None:
        p = p - measured[:, 3]
    H = _hat_times(p, R)
    # V (K+1, 6, 3, m): parameter (v, w) of each block, then the translation row and the pose
    V = jnp.concatenate([jnp.swapaxes(R, 1, 2), jnp.swapaxes(H, 1, 2)], axis=1)
    if noise is None:
        return _split_gram(V, Y)
    sp = jnp.asarray(noise.position_mm, dtype)
    return _split_gram(V / sp, Y, sp / jnp.asarray(noise.rotation_rad, dtype))


def lm_normal_equations(
    after: Array, r: Array, measured: Array, noise: NoiseModel | None = None
) -> tuple[Array, Array, Array]:
    """``(J^T J (n, n), J^T r~ (n,), r~ (6, m))``: the normal equations of LM's residual for a
    step ``dX`` on the left of the frames at which ``after`` and ``r`` were evaluated, ``F_j ->
    exp(hat(dX_j)) F_j``, without ``J`` itself.

    ``J = -G J_r^-1(r) D`` (:func:`residual_jacobian` at ``X = 0`` about those frames): per
    pose the rows of ``D`` (Eq. 8) are moved by ``M = G J_r^-1(r) = [[a, b], [0, c]]`` (3x3
    blocks: ``J_r^-1`` and the whitening ``G`` are both block upper triangular), which keeps the
    rotation rows of a block free of its translation parameters, so that ``(M D)^T (M D)``
    splits as in :func:`normal_equations`: translation rows ``[a R, a H + b R]`` of every
    parameter and rotation rows ``c R`` of the rotation parameters. The test suite checks ``N``
    and ``g`` against ``J`` of :func:`residual_jacobian`.

    Args:
        after: ``(K, 3, 4, m)`` world poses before the fixed frames (:func:`chain`).
        r: ``(6, m)`` Eq. 7's residual there (unwhitened).
        measured: ``(3, 4, m)`` measured tool poses. noise: the noise model, or ``None``.
    """
    dtype = after.dtype
    Ji, B = se3_left_jacobian_inverse_blocks(-r)  # J_r^-1(r) = J_l^-1(-r) = [[Ji, B], [0, Ji]]
    # a and b computed once (_computed_once), not again inside every element that reads them.
    a, b = _computed_once(jnp.stack([Ji, B]))  # c = a (_split_gram)
    rw, rotation_scale = r, None
    if noise is not None:  # G = S [[I, -hat(p_meas)], [0, I]], S = diag(I / s_pos, I / s_rot)
        sp = jnp.asarray(noise.position_mm, dtype)
        b = (b - _matmul3(_hat(measured[:, 3]), a)) / sp
        a = a / sp
        rotation_scale = sp / jnp.asarray(noise.rotation_rad, dtype)  # c R = (a R) s_pos / s_rot
        rw = whiten(r, measured, noise)
    R, p = _blocks(after)
    H = _hat_times(p, R)
    V = jnp.concatenate([_rows_times(a, R), _rows_times(a, H) + _rows_times(b, R)], axis=1)
    N, g = _split_gram(V, rw, rotation_scale, in_place=False)
    return N, -g, rw  # the sign of J on g


def _computed_once(M: Array) -> Array:
    """``M (..., m)`` unchanged, through a product with the identity over its last (pose)
    axis. XLA:CPU fuses element-wise work into each of its consumers and evaluates it there
    for every element of the consumer's output, but it never fuses a matrix product: the
    product's result is computed once and read. (An optimisation barrier does not do this:
    XLA:CPU removes it.) Over the pose axis the product is one ``(rows, m) x (m, m)`` product
    in the layout in which ``M`` is computed and read; over a 3x3 block axis XLA laid ``M``
    out with that axis first, and the fusion that wrote it took more time than the whole
    evaluation of ``J_r^-1``. Finite entries come out exactly; a non-finite entry makes its
    whole row non-finite (``0 * inf``), which only non-finite poses or frames cause, whose trial is
    non-finite anyway."""
    return jnp.einsum("...p,pq->...q", M, jnp.eye(M.shape[-1], dtype=M.dtype))


def _rows_times(a: Array, M: Array) -> Array:
    """``(a M_j)^T`` per block and pose in the layout of :func:`_split_gram`: ``a (3, 3, m)``
    (rows, inner, pose) and ``M (K+1, 3, 3, m)`` (block, inner, column, pose) ->
    ``(K+1, 3, 3, m)`` (block, column, row, pose)."""
    out = a[None, None, :, 0] * M[:, 0, :, None]
    for e in (1, 2):
        out = out + a[None, None, :, e] * M[:, e, :, None]
    return out


def _blocks(after: Array) -> tuple[Array, Array]:
    """The rotations ``(K+1, 3, 3, m)`` and translations ``(K+1, 3, m)`` of the poses before
    every fixed frame, the first (the world frame) the identity."""
    dtype = after.dtype
    m = after.shape[-1]
    eye = jnp.broadcast_to(jnp.eye(3, dtype=dtype)[:, :, None], (3, 3, m))
    R = jnp.concatenate([eye[None], after[:, :, :3]])
    p = jnp.concatenate([jnp.zeros((1, 3, m), dtype), after[:, :, 3]])
    return R, p


def _hat_times(p: Array, R: Array) -> Array:
    """``hat(p) R`` per block and pose: ``(K+1, 3, m), (K+1, 3, 3, m) -> (K+1, 3, 3, m)``
    (column ``c``: ``p x R[:, c]``)."""
    return jnp.stack(_cross(jnp.moveaxis(p, 1, 0)[:, :, None], jnp.moveaxis(R, 1, 0)), axis=1)


def _split_gram(
    V: Array, Y: Array, rotation_scale: Array | None = None, *, in_place: bool = True
) -> tuple[Array, Array]:
    """``N = V^T V + W^T W``, ``g = V^T Y_v + W^T Y_w`` (see :func:`normal_equations`) from the
    translation rows ``V (K+1, 6, 3, m)`` of every parameter (parameter block, parameter, row,
    pose) and the residual ``Y (6, m)``, where ``W``, the rotation rows of the rotation
    parameters, is ``rotation_scale`` (``None``: 1; a scalar or one per pose, ``(m,)``) times
    the translation rows of the translation parameters, ``V[:, :3]`` (true of ``D~`` and of LM's
    ``J``: those rows are ``a R`` and ``c R``, with ``c = a`` up to the whitening's scales).
    With one scale for all poses, ``W^T W`` is the translation-translation block of ``V^T V``
    times its square, without a product of its own. ``in_place=False`` adds it to the rotation
    block by a select over the whole of ``N`` instead of an in-place update of the block: XLA
    then fuses the sum into the consumer where ``N`` is selected and carried between passes
    (LM: 8 % faster), but into every reading of ``N`` where it is read several times (the
    paper solver: 3 % slower with it)."""
    k1, m = V.shape[0], V.shape[-1]
    Yv, Yw = Y[:3].reshape(3 * m), Y[3:].reshape(3 * m)
    rows = V.reshape(6 * k1, 3 * m)
    N = (rows @ rows.T).reshape(k1, 2, 3, k1, 2, 3)
    if rotation_scale is not None and jnp.ndim(rotation_scale) > 0:  # one scale per pose
        W = (V[:, :3] * rotation_scale).reshape(3 * k1, 3 * m)
        NW, gw = (W @ W.T).reshape(k1, 3, k1, 3), W @ Yw
    else:
        NW, gw = N[:, 0, :, :, 0, :], V[:, :3].reshape(3 * k1, 3 * m) @ Yw
        if rotation_scale is not None:
            NW, gw = NW * (rotation_scale * rotation_scale), gw * rotation_scale
    if in_place:
        N = N.at[:, 1, :, :, 1, :].add(NW)
    else:  # the same sums, as a select over the whole matrix
        rotation_block = np.zeros((1, 2, 1, 1, 2, 1), bool)
        rotation_block[:, 1, :, :, 1, :] = True
        N = N + jnp.where(rotation_block, NW[:, None, :, :, None, :], 0.0)
    g = (rows @ Yv).reshape(k1, 2, 3).at[:, 1].add(gw.reshape(k1, 3))
    n = 6 * k1
    return N.reshape(n, n), g.reshape(n)


def residual_and_metrics(measured: Array, tool: Array) -> tuple[Array, Array, Array]:
    """Eq. 7's residual ``(6, m)`` and Eqs. 20-21 from it, for pose stacks ``(3, 4, m)``.

    Eq. 21's ``|log(R_a^-1 R_c)|`` is the norm of the residual's rotational part (see
    :func:`linearise`), so the logarithm is taken once.
    """
    # The barrier changes no value; with it XLA compiles 8 % less code for the solvers, which
    # consume the residual in several places (``benchmarks/compile_split.py``).
    Y = jax.lax.optimization_barrier(residual(measured, tool))
    dpos = measured[:, 3] - tool[:, 3]
    m = dpos.shape[-1]
    return Y, jnp.sqrt(jnp.sum(dpos * dpos) / m), jnp.sqrt(jnp.sum(Y[3:] * Y[3:]) / m)


def deviation_metrics(measured: Array, tool: Array) -> tuple[Array, Array]:
    """Eqs. 20-21 for pose stacks ``(3, 4, m)`` (see :func:`linearise` for Eq. 21)."""
    _, delta_p, delta_R = residual_and_metrics(measured, tool)
    return delta_p, delta_R


def _sum6(term: Callable[[int], Array]) -> Array:
    """``term(0) + ... + term(5)``."""
    total = term(0)
    for i in range(1, 6):
        total = total + term(i)
    return total


def residual_jacobian(
    X: Array, frames0: Array, poses: Array, measured: Array, noise: NoiseModel | None = None
) -> tuple[Array, tuple[Array, Array], Array]:
    """The LM residual at ``X``, the deviation metrics of its model and its Jacobian.

    With ``T(X) = E_0 F_0 M_1 E_1 F_1 ... M_K E_K F_K``, ``E_j = exp(hat(X_j))`` and
    ``Delta = T_meas T(X)^-1``, the residual is ``r = log(Delta)^v`` (Eq. 7) and, differentiating
    ``E_j`` on the left (``d exp(xi) = hat(J_l(xi) d xi) exp(xi)``, ``J_l`` the left Jacobian of
    SE(3)) and ``log`` on the right,

        dr = -J_r^-1(r) [I, Ad(P_1), ..., Ad(P_K)] diag(J_l(X_0), ..., J_l(X_K)) dX,

    where the middle factor is the paper's ``D`` (Eq. 8) at the frames ``F_j(X)`` and
    ``J_r^-1(r) = d log(Delta exp(hat(e)))^v / de = J_l^-1(-r)`` at ``e = 0``, both in closed form
    (:func:`se3_left_jacobian`); the test suite checks the product against
    ``jax.jacfwd`` of the residual.

    Args:
        X: ``(6 (K+1),)`` error twists.
        frames0: ``(K+1, 4, 4)`` nominal frames.
        poses: ``(K, 3, 4, m)`` module poses (pose-last).
        measured: ``(3, 4, m)`` measured tool poses (pose-last).
        noise: whitening, or ``None``.

    Returns:
        ``(r (6m,), (delta_p, delta_R), J (6m, 6 (K+1)))``; ``r`` component-major
        (``r.reshape(6, m)[:, k]`` is pose ``k``), as the rows of ``J``.
    """
    k1 = frames0.shape[0]
    n = 6 * k1
    xi = X.reshape(k1, 6)
    frames = moved_frames(frames0, xi)
    lin = linearise(frames, poses, measured)  # unwhitened: D = [I, Ad(P_i)] at F(X)
    m = measured.shape[-1]
    r = lin.Y.reshape(6, m)  # log(Delta)^v, Delta = T_meas T(X)^-1
    jr_inv = se3_left_jacobian_inverse(-r)  # J_r^-1(r) = J_l^-1(-r): (6, 6, m)
    jl = jnp.moveaxis(se3_left_jacobian(xi.T), -1, 0)  # (K+1, 6, 6)
    DT = lin.DT.reshape(k1, 6, 6, m)  # (frame, column, row, pose): D_k^T
    # The small contractions as explicit sums of 6 products over the pose axis (XLA turns
    # einsums with the pose axis as a batch axis into transposes and tiny matrix products).
    # (J_r^-1 D_k)^T = D_k^T J_r^-1^T: contract the row axis b.
    A = _sum6(lambda b: DT[:, :, b, None, :] * jr_inv[None, None, :, b, :])
    # diag(J_l)^T on the left: column c of frame j is sum_d J_l[j][d, c] (column d).
    A = _sum6(lambda d: jl[:, d, :, None, None] * A[:, d, None, :, :])
    J = -jnp.transpose(A.reshape(n, 6, m), (1, 2, 0))  # (row, pose, column)
    if noise is not None:
        r = whiten(r, measured, noise)
        J = whiten(jnp.moveaxis(J, 2, 1), measured, noise)  # (row, column, pose)
        J = jnp.moveaxis(J, 1, 2)
    return r.reshape(6 * m), (lin.delta_p, lin.delta_R), J.reshape(6 * m, n)
