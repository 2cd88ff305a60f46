"""SO(3) and SE(3) maps of the paper's appendix (Eqs. 22-27), batched and differentiable.

Conventions (used everywhere in :mod:`cdra_jax`):

* A pose is a homogeneous matrix ``T = [[R, p], [0, 1]]`` (Eq. 22), shape ``(..., 4, 4)``;
  translations in millimetres.
* A twist is ordered as in the paper, **translation first**: ``xi = (v, w)``, shape ``(..., 6)``
  (Eq. 23); ``w`` in radians.
* ``hat(xi) = [[hat(w), v], [0, 0]]`` and ``exp(hat(xi)) = [[exp(hat(w)), A v], [0, 1]]`` (Eq. 26).
* The adjoint is ``Ad_T = [[R, hat(p) R], [0, R]]`` (Eq. 25), so that
  ``T exp(hat(xi)) T^-1 = exp(hat(Ad_T xi))`` (Eq. 6).

Every function broadcasts over leading batch dimensions, jits, vmaps and differentiates.
Called on concrete arrays, each public map runs as one compiled program per shape and dtype
(:func:`cdra_jax.compilation.compiled_when_eager`); inside ``jit``, ``vmap`` or ``grad`` it is
traced inline.
Near zero rotation the closed forms are replaced by Taylor series behind the "double where"
shim, so that values *and* gradients stay finite. The SO(3) logarithm goes through a
quaternion (Shepperd's method), which stays accurate near a rotation of pi where the paper's
formula ``phi / (2 sin phi) (R - R^T)`` (Eq. 27) loses every digit; the SE(3) logarithm uses
``A^{-1} = I - hat(w)/2 + c hat(w)^2`` with ``c = (1 - phi sin(phi) / (2 (1 - cos(phi)))) / phi^2``,
which is finite at pi, unlike the ``sin`` in the denominator of Eq. 27.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from .compilation import compiled_when_eager as _compiled_when_eager

# Below this squared angle (rad^2) the closed forms switch to their Taylor series. At 1e-2 the
# series truncation error (first omitted term ~ phi^10 / 10!) and the cancellation error of the
# closed forms (eps / phi^2) are both below 1e-13 relative.
_SMALL_ANGLE_SQ = 1e-2


def _shaped(x: ArrayLike, trailing: tuple[int, ...], fn: str, arg: str) -> Array:
    """``x`` as an array, after checking its trailing shape (static: a ``ValueError`` at trace
    time). Indexing past a short axis would otherwise clamp silently under ``jit``."""
    x = jnp.asarray(x)
    if x.shape[max(x.ndim - len(trailing), 0) :] != trailing:
        want = ", ".join(["..."] + [str(d) for d in trailing])
        raise ValueError(f"lie.{fn}: {arg} must have shape ({want}), got {x.shape}")
    return x


@_compiled_when_eager
def hat3(w: ArrayLike) -> Array:
    """Skew-symmetric matrix of a 3-vector: ``(..., 3) -> (..., 3, 3)``, ``hat(w) x = w x x``."""
    w = _shaped(w, (3,), "hat3", "w")
    x, y, z = jnp.unstack(w, axis=-1)
    o = jnp.zeros_like(x)
    return jnp.stack(
        [
            jnp.stack([o, -z, y], axis=-1),
            jnp.stack([z, o, -x], axis=-1),
            jnp.stack([-y, x, o], axis=-1),
        ],
        axis=-2,
    )


@_compiled_when_eager
def vee3(W: ArrayLike) -> Array:
    """Inverse of :func:`hat3` (uses the skew part): ``(..., 3, 3) -> (..., 3)``."""
    W = _shaped(W, (3, 3), "vee3", "W")
    return 0.5 * jnp.stack(
        [W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]],
        axis=-1,
    )


@_compiled_when_eager
def hat(xi: ArrayLike) -> Array:
    """se(3) matrix of a twist ``(v, w)`` (Eq. 23): ``(..., 6) -> (..., 4, 4)``."""
    xi = _shaped(xi, (6,), "hat", "xi")
    top = jnp.concatenate([hat3(xi[..., 3:]), xi[..., :3, None]], axis=-1)
    bottom = jnp.zeros(xi.shape[:-1] + (1, 4), dtype=top.dtype)
    return jnp.concatenate([top, bottom], axis=-2)


@_compiled_when_eager
def vee(X: ArrayLike) -> Array:
    """Twist ``(v, w)`` of an se(3) matrix: ``(..., 4, 4) -> (..., 6)``."""
    X = _shaped(X, (4, 4), "vee", "X")
    return jnp.concatenate([X[..., :3, 3], vee3(X[..., :3, :3])], axis=-1)


def _hat3_squared(w: Array) -> Array:
    """``hat(w)^2 = w w^T - |w|^2 I`` for ``w (..., 3)``: ``(..., 3, 3)``.

    The small products of this module are written out element-wise: under ``vmap`` XLA:CPU
    compiles every matrix product into a kernel of its own (compile time) and calls it per
    batch, where the element-wise form fuses with its neighbours.
    """
    eye = jnp.eye(3, dtype=w.dtype)
    x = _squared_norm3(w)
    return w[..., :, None] * w[..., None, :] - x[..., None, None] * eye


def _squared_norm3(v: Array) -> Array:
    """``|v|^2`` of vectors ``(..., 3) -> (...)``, as a sum of three products: element-wise
    code that XLA fuses with what computes ``v`` (a reduction over the last axis is a fusion
    boundary, and every fusion that reads it evaluates ``v`` again). The components are taken
    apart by one :func:`jax.numpy.unstack` (indexing traces two equations per component;
    tracing and lowering cost time per equation)."""
    x, y, z = jnp.unstack(v, axis=-1)
    return x * x + y * y + z * z


def _matmul3(A: Array, B: Array) -> Array:
    """``A B`` for ``A (..., 3, 3)`` and ``B (..., 3, k)``, element-wise (see
    :func:`_hat3_squared`): the columns of ``A`` times the rows of ``B``, summed."""
    columns, rows = jnp.unstack(A, axis=-1), jnp.unstack(B, axis=-2)
    out = columns[0][..., :, None] * rows[0][..., None, :]
    for j in (1, 2):
        out = out + columns[j][..., :, None] * rows[j][..., None, :]
    return out


def _matvec3(A: Array, v: Array) -> Array:
    """``A v`` for ``A (..., 3, 3)`` and ``v (..., 3)``, element-wise (as
    :func:`_hat3_squared`)."""
    return _matmul3(A, v[..., :, None])[..., 0]


def _angle_coefficients(theta_sq: Array) -> tuple[Array, Array, Array]:
    """``sin(t)/t``, ``(1-cos t)/t^2`` and ``(t - sin t)/t^3`` of ``t = sqrt(theta_sq)``.

    Finite with finite gradients at ``theta_sq = 0`` (double-where shim).
    """
    small = theta_sq < _SMALL_ANGLE_SQ
    safe_sq = jnp.where(small, jnp.ones_like(theta_sq), theta_sq)
    t = jnp.sqrt(safe_sq)
    s, c = jnp.sin(t), jnp.cos(t)
    x = theta_sq
    a_taylor = 1.0 - x / 6.0 * (1.0 - x / 20.0 * (1.0 - x / 42.0 * (1.0 - x / 72.0)))
    b_taylor = 0.5 * (1.0 - x / 12.0 * (1.0 - x / 30.0 * (1.0 - x / 56.0 * (1.0 - x / 90.0))))
    c_taylor = (1.0 - x / 20.0 * (1.0 - x / 42.0 * (1.0 - x / 72.0 * (1.0 - x / 110.0)))) / 6.0
    a = jnp.where(small, a_taylor, s / t)
    b = jnp.where(small, b_taylor, (1.0 - c) / safe_sq)
    cc = jnp.where(small, c_taylor, (t - s) / (safe_sq * t))
    return a, b, cc


@_compiled_when_eager
def so3_exp(w: ArrayLike) -> Array:
    """Rotation matrix of a rotation vector (Rodrigues, Eq. 26): ``(..., 3) -> (..., 3, 3)``."""
    w = _shaped(w, (3,), "so3_exp", "w")
    a, b, _ = _angle_coefficients(_squared_norm3(w))
    W = hat3(w)
    W2 = _hat3_squared(w)
    eye = jnp.eye(3, dtype=W.dtype)
    return eye + a[..., None, None] * W + b[..., None, None] * W2


@_compiled_when_eager
def so3_left_jacobian(w: ArrayLike) -> Array:
    """The matrix ``A`` of Eq. 26 (left Jacobian of SO(3)): ``(..., 3) -> (..., 3, 3)``."""
    w = _shaped(w, (3,), "so3_left_jacobian", "w")
    _, b, c = _angle_coefficients(_squared_norm3(w))
    W = hat3(w)
    eye = jnp.eye(3, dtype=W.dtype)
    return eye + b[..., None, None] * W + c[..., None, None] * _hat3_squared(w)


@_compiled_when_eager
def rotation_to_quaternion(R: ArrayLike) -> Array:
    """Unit quaternion ``(w, x, y, z)`` of a rotation matrix (Shepperd / Day): ``(..., 4)``.

    The branch with the largest pivot is selected before the square root, so every rotation,
    including those near pi, is converted to full precision. The sign is not normalised.
    """
    m = _shaped(R, (3, 3), "rotation_to_quaternion", "R")
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    t0 = 1 + m00 - m11 - m22
    q0 = jnp.stack([m21 - m12, t0, m10 + m01, m02 + m20], axis=-1)
    t1 = 1 - m00 + m11 - m22
    q1 = jnp.stack([m02 - m20, m10 + m01, t1, m21 + m12], axis=-1)
    t2 = 1 - m00 - m11 + m22
    q2 = jnp.stack([m10 - m01, m02 + m20, m21 + m12, t2], axis=-1)
    t3 = 1 + m00 + m11 + m22
    q3 = jnp.stack([t3, m21 - m12, m02 - m20, m10 - m01], axis=-1)
    c0 = m22 < 0
    c1 = m00 > m11
    c2 = m00 < -m11
    t = jnp.where(c0, jnp.where(c1, t0, t1), jnp.where(c2, t2, t3))
    q = jnp.where(c0[..., None], jnp.where(c1[..., None], q0, q1), jnp.where(c2[..., None], q2, q3))
    return q * (0.5 / jnp.sqrt(t))[..., None]


@_compiled_when_eager
def quaternion_to_rotation(q: ArrayLike) -> Array:
    """Rotation matrix of a unit quaternion ``(w, x, y, z)``: ``(..., 4) -> (..., 3, 3)``."""
    q = _shaped(q, (4,), "quaternion_to_rotation", "q")
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


@_compiled_when_eager
def quaternion_log(q: ArrayLike) -> Array:
    """Rotation vector of a unit quaternion ``(w, x, y, z)``: ``(..., 4) -> (..., 3)``.

    The result has norm in ``[0, pi]``; the double cover is resolved by flipping to ``w >= 0``.
    """
    return _quaternion_log(_shaped(q, (4,), "quaternion_log", "q"))[0]


def _quaternion_log(q: Array) -> tuple[Array, Array]:
    """:func:`quaternion_log` and the squared norm of its result, ``(..., 3), (...)``: the
    result is ``f v`` (``v`` the vector part) and its squared norm ``f^2 |v|^2``."""
    q = jnp.where(q[..., :1] < 0, -q, q)
    w, v = q[..., 0], q[..., 1:]
    n_sq = _squared_norm3(v)
    f = _quaternion_log_factor(w, n_sq)
    return f[..., None] * v, f * f * n_sq


def _quaternion_log_factor(w: Array, n_sq: Array) -> Array:
    """``f`` with ``log(q) = f v`` for a unit quaternion ``(w, v)``, ``w >= 0``, ``n_sq =
    |v|^2``: ``2 atan2(|v|, w) / |v|``, its series for small ``|v|`` (double-where shim)."""
    small = n_sq < 1e-12
    safe_n = jnp.sqrt(jnp.where(small, jnp.ones_like(n_sq), n_sq))
    safe_w = jnp.where(small, w, jnp.ones_like(w))
    exact = 2.0 * jnp.arctan2(safe_n, w) / safe_n
    # 2 atan(n / w) / n = (2 / w) (1 - n^2 / (3 w^2) + ...), with w ~ 1 on this branch.
    taylor = 2.0 / safe_w * (1.0 - n_sq / (3.0 * safe_w * safe_w))
    return jnp.where(small, taylor, exact)


@_compiled_when_eager
def so3_log(R: ArrayLike) -> Array:
    """Rotation vector of a rotation matrix, norm in ``[0, pi]``: ``(..., 3, 3) -> (..., 3)``.

    Accurate for every rotation, near zero and near pi (see the module docstring).
    """
    R = _shaped(R, (3, 3), "so3_log", "R")
    return quaternion_log(rotation_to_quaternion(R))


@_compiled_when_eager
def so3_left_jacobian_inverse(w: ArrayLike) -> Array:
    """The matrix ``A*`` of Eq. 27, ``A^{-1}``: ``(..., 3) -> (..., 3, 3)``; finite up to pi."""
    w = _shaped(w, (3,), "so3_left_jacobian_inverse", "w")
    c = _jacobian_inverse_coefficient(_squared_norm3(w))
    W = hat3(w)
    eye = jnp.eye(3, dtype=W.dtype)
    return eye - 0.5 * W + c[..., None, None] * _hat3_squared(w)


def _jacobian_inverse_coefficient(x: Array) -> Array:
    """``c`` of ``A^-1 = I - hat(w) / 2 + c hat(w)^2`` (:func:`so3_left_jacobian_inverse`)
    from ``x = |w|^2``: ``(1 - t sin t / (2 (1 - cos t))) / t^2`` (``t = |w|``), its series
    below the small-angle threshold; ``(...) -> (...)``."""
    small = x < _SMALL_ANGLE_SQ
    safe_x = jnp.where(small, jnp.ones_like(x), x)
    t = jnp.sqrt(safe_x)
    # 1 - cos t = 2 sin^2(t/2) avoids cancellation.
    exact = (1.0 - 0.5 * t * jnp.sin(t) / (2.0 * jnp.sin(0.5 * t) ** 2)) / safe_x
    taylor = 1.0 / 12.0 + x / 720.0 + x * x / 30240.0 + x * x * x / 1209600.0
    return jnp.where(small, taylor, exact)


@_compiled_when_eager
def make_pose(R: ArrayLike, p: ArrayLike) -> Array:
    """Homogeneous matrix from ``R (..., 3, 3)`` and ``p (..., 3)`` (Eq. 22): ``(..., 4, 4)``."""
    R = _shaped(R, (3, 3), "make_pose", "R")
    p = _shaped(jnp.asarray(p, dtype=R.dtype), (3,), "make_pose", "p")
    R, p = jnp.broadcast_arrays(R, p[..., None, :])
    p = p[..., 0, :]
    top = jnp.concatenate([R, p[..., :, None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], dtype=R.dtype), R.shape[:-2] + (1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


def rotation(T: ArrayLike) -> Array:
    """Rotation block ``R`` of a pose: ``(..., 4, 4) -> (..., 3, 3)``."""
    return _shaped(T, (4, 4), "rotation", "T")[..., :3, :3]


def translation(T: ArrayLike) -> Array:
    """Translation ``p`` of a pose (mm): ``(..., 4, 4) -> (..., 3)``."""
    return _shaped(T, (4, 4), "translation", "T")[..., :3, 3]


@_compiled_when_eager
def se3_exp(xi: ArrayLike) -> Array:
    """Pose of a twist ``(v, w)`` (Eq. 26): ``(..., 6) -> (..., 4, 4)``."""
    xi = _shaped(xi, (6,), "se3_exp", "xi")
    v, w = xi[..., :3], xi[..., 3:]
    a, b, c = _angle_coefficients(_squared_norm3(w))
    W = hat3(w)
    W2 = _hat3_squared(w)
    eye = jnp.eye(3, dtype=W.dtype)
    R = eye + a[..., None, None] * W + b[..., None, None] * W2
    A = eye + b[..., None, None] * W + c[..., None, None] * W2
    return make_pose(R, _matvec3(A, v))


@_compiled_when_eager
def se3_log(T: ArrayLike) -> Array:
    """Twist ``(v, w)`` of a pose (Eq. 27, made robust near pi): ``(..., 4, 4) -> (..., 6)``."""
    T = _shaped(T, (4, 4), "se3_log", "T")
    w, x = _quaternion_log(rotation_to_quaternion(T[..., :3, :3]))
    # v = A^-1 p = p - (w x p) / 2 + c w x (w x p)
    p = T[..., :3, 3]
    wxp = jnp.cross(w, p)
    v = p - 0.5 * wxp + _jacobian_inverse_coefficient(x)[..., None] * jnp.cross(w, wxp)
    return jnp.concatenate([v, w], axis=-1)


@_compiled_when_eager
def inverse(T: ArrayLike) -> Array:
    """Inverse pose ``[[R^T, -R^T p], [0, 1]]``: ``(..., 4, 4) -> (..., 4, 4)``."""
    T = _shaped(T, (4, 4), "inverse", "T")
    Rt = jnp.swapaxes(T[..., :3, :3], -1, -2)
    return make_pose(Rt, -_matvec3(Rt, T[..., :3, 3]))


@_compiled_when_eager
def compose(*poses: ArrayLike) -> Array:
    """Product of poses, left to right (broadcasting): ``T_ab T_bc -> T_ac``."""
    if not poses:
        raise ValueError("compose needs at least one pose")
    out = jnp.asarray(poses[0])
    for T in poses[1:]:
        out = out @ jnp.asarray(T)
    return out


@_compiled_when_eager
def adjoint(T: ArrayLike) -> Array:
    """Adjoint ``[[R, hat(p) R], [0, R]]`` of a pose (Eq. 25): ``(..., 4, 4) -> (..., 6, 6)``."""
    T = _shaped(T, (4, 4), "adjoint", "T")
    R, p = T[..., :3, :3], T[..., :3, 3]
    top = jnp.concatenate([R, _matmul3(hat3(p), R)], axis=-1)
    bottom = jnp.concatenate([jnp.zeros_like(R), R], axis=-1)
    return jnp.concatenate([top, bottom], axis=-2)


@_compiled_when_eager
def from_xyz_rotvec(xyz: ArrayLike, rotvec: ArrayLike) -> Array:
    """Pose from a translation (mm) and a rotation vector (rad): ``(..., 3) x2 -> (..., 4, 4)``.

    Note this is *not* ``se3_exp((xyz, rotvec))``: ``xyz`` is the translation itself.
    """
    return make_pose(so3_exp(rotvec), xyz)


@_compiled_when_eager
def to_xyz_rotvec(T: ArrayLike) -> tuple[Array, Array]:
    """Inverse of :func:`from_xyz_rotvec`: translation (mm) and rotation vector (rad)."""
    return translation(T), so3_log(rotation(T))


@_compiled_when_eager
def rotation_angle(R: ArrayLike) -> Array:
    """Angle of a rotation in ``[0, pi]`` (rad), accurate at both ends: ``(..., 3, 3) -> (...)``.

    The angle is not differentiable at the identity (a cone, like ``|x|``); there its gradient
    is taken as zero (double where) rather than NaN.
    """
    q = rotation_to_quaternion(_shaped(R, (3, 3), "rotation_angle", "R"))
    n_sq = _squared_norm3(q[..., 1:])
    positive = n_sq > 0
    n = jnp.where(positive, jnp.sqrt(jnp.where(positive, n_sq, 1.0)), 0.0)
    return 2.0 * jnp.arctan2(n, jnp.abs(q[..., 0]))
