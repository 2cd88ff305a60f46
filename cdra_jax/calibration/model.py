"""The local-POE calibration model (Eqs. 5-9) and the deviation metrics (Eqs. 20-21).

The unknowns are the error twists of the K+1 fixed transforms, stacked as
``X = [dt_0; ...; dt_K]`` (``6 (K+1)``, Eq. 8; each twist ``(v, w)``, mm and rad), ordered as
``arm.param_names``. Errors are left-multiplied, ``F_j^a = exp(hat(dt_j)) F_j`` (Eqs. 11-14).

For one pose the residual is the world-frame twist ``Y = log(T_meas T_model^-1)^v`` (Eq. 7) and
the calibration Jacobian is ``D = [I, Ad(P_1), ..., Ad(P_K)]`` (Eq. 8) with ``P_i`` the world
pose after module ``i`` (T_OS, T_OE, T_OW for the CDRA), so that ``Y ~= D X`` to first order.

Noise weighting. A measured tool pose with a position error ``dp`` (mm) and a world-frame
rotation error ``dth`` (rad) gives ``Y = [dp + hat(p) dth; dth]`` to first order, where ``p``
is the tool position: the translational part of the twist mixes position noise with
orientation noise lever-armed by ``|p|`` (hundreds of mm). :class:`NoiseModel` whitens this:
``r = diag(1/s_pos, 1/s_rot) [[I, -hat(p)], [0, I]] Y``, so that each entry of ``r`` has unit
variance when the measurement noise is isotropic Gaussian with those standard deviations. With
no noise model the paper's unweighted form ``r = Y`` is used.

Per-pose weights. The two standard deviations may also be arrays of shape ``(m,)``, one entry per
pose (or anything that broadcasts against the pose axis, e.g. ``(trials, m)`` under ``vmap``):
pose ``i`` is then whitened by its own ``s_pos[i]``, ``s_rot[i]``. A weight ``w_i`` on the
squared residual of pose ``i`` is the noise model ``(s_pos / sqrt(w_i), s_rot / sqrt(w_i))``;
this is how :mod:`.robust` feeds its iteratively reweighted least squares through the
unchanged solvers.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from .. import lie
from ..arm import Arm, chain, module_poses


class NoiseModel(eqx.Module):
    """Isotropic measurement noise of the tool pose: position (mm) and orientation (rad) std.

    Used to weight the residual (see the module docstring) and by the simulator. Each std is a
    number, or an array with one entry per pose (``(m,)``, broadcast against the pose axis of
    the measured poses ``(..., m, 4, 4)``) for per-pose weights.

    Concrete values (numbers, numpy arrays, JAX arrays outside ``jit``/``vmap``) are checked
    on construction: a number must be positive and finite; an entry of a per-pose array must
    be positive, and may be ``+inf`` (that pose gets weight 0, as :mod:`.robust` uses it), but
    not zero, negative or NaN (a zero entry would make the whole solve non-finite). Traced
    values cannot be checked and are taken as given.
    """

    position_mm: float | Array
    rotation_rad: float | Array

    def __check_init__(self) -> None:
        for name, v in (("position_mm", self.position_mm), ("rotation_rad", self.rotation_rad)):
            _check_std(name, v)


def _check_std(name: str, v) -> None:
    """Value check of a concrete noise std (see :class:`NoiseModel`); tracers are skipped."""
    if isinstance(v, jax.core.Tracer):
        return
    try:
        a = np.asarray(v)
    except Exception as exc:  # e.g. a JAX array deleted or on no host
        raise ValueError(
            f"NoiseModel: noise.{name} must be a number or an array, got {v!r}"
        ) from exc
    if a.dtype.kind not in "iuf":
        raise ValueError(
            f"NoiseModel: noise.{name} must be a number or an array of them, got {v!r}"
        )
    if a.ndim == 0:
        if not (np.isfinite(a) and a > 0):
            raise ValueError(
                f"NoiseModel: noise.{name} must be a positive finite number, got {a[()]!s}"
            )
        return
    bad = np.argwhere(~(a > 0))  # zero, negative, -inf and NaN; +inf is weight 0
    if bad.size:
        idx = tuple(int(i) for i in bad[0])
        where = f"pose {idx[0]}" if a.ndim == 1 else f"index {idx}"
        raise ValueError(
            f"NoiseModel: noise.{name} must be positive in every entry (+inf for weight 0), got "
            f"{a[idx]!s} at {where}"
        )


def residual_twist(measured: ArrayLike, model: ArrayLike) -> Array:
    """``Y = log(T_meas T_model^-1)^v`` (Eq. 7): ``(..., 4, 4) x2 -> (..., 6)``, world frame."""
    return lie.se3_log(jnp.asarray(measured) @ lie.inverse(model))


def point_residual(measured: ArrayLike, tool: ArrayLike, xyz: ArrayLike) -> Array:
    """``e = p_meas - T_tool x`` (mm, world frame): measured points against the model.

    Args:
        measured: ``(..., m, P, 3)`` measured points.
        tool: ``(..., m, 4, 4)`` model tool poses.
        xyz: ``(..., P, 3)`` the points' positions in the tool frame (mm).

    Returns:
        ``(..., m, P, 3)``.
    """
    return jnp.asarray(measured) - tool_points(tool, xyz)


def tool_points(tool: ArrayLike, xyz: ArrayLike) -> Array:
    """World positions ``T_tool x`` ``(..., m, P, 3)`` of tool-frame points ``xyz (..., P, 3)``
    at the tool poses ``(..., m, 4, 4)`` (mm)."""
    tool = jnp.asarray(tool)
    pts = jnp.einsum("...mij,...pj->...mpi", tool[..., :3, :3], jnp.asarray(xyz))
    return pts + tool[..., None, :3, 3]


def whitening(measured: ArrayLike, noise: NoiseModel | None) -> Array | None:
    """Per-pose whitening matrices ``G (..., 6, 6)`` for the residual, or ``None`` (paper form).

    ``measured`` is ``(..., 4, 4)``; the noise stds are scalars or arrays that broadcast against
    its leading (pose) dimensions ``(...)``, e.g. ``(m,)`` per-pose stds.
    """
    if noise is None:
        return None
    measured = jnp.asarray(measured)
    p = lie.translation(measured)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=measured.dtype), p.shape[:-1] + (3, 3))
    # [..., None, None]: a per-pose std (m,) scales the (m, 3, 3) blocks of its own pose.
    sp = jnp.asarray(noise.position_mm, dtype=measured.dtype)[..., None, None]
    sr = jnp.asarray(noise.rotation_rad, dtype=measured.dtype)[..., None, None]
    top = jnp.concatenate([eye / sp, -lie.hat3(p) / sp], axis=-1)
    bottom = jnp.concatenate([jnp.zeros_like(eye), eye / sr], axis=-1)
    return jnp.concatenate([top, bottom], axis=-2)


def calibration_jacobian(after: ArrayLike) -> Array:
    """``D = [I, Ad(P_1), ..., Ad(P_K)]`` (Eq. 8) from the poses after each module.

    Args:
        after: ``(..., K, 4, 4)`` world pose after each module.

    Returns:
        ``(..., 6, 6 (K+1))``.
    """
    after = jnp.asarray(after)
    ads = lie.adjoint(after)  # (..., K, 6, 6)
    eye = jnp.broadcast_to(jnp.eye(6, dtype=after.dtype), ads.shape[:-3] + (1, 6, 6))
    blocks = jnp.concatenate([eye, ads], axis=-3)  # (..., K+1, 6, 6)
    return jnp.concatenate([blocks[..., j, :, :] for j in range(blocks.shape[-3])], axis=-1)


def stacked_system(
    arm: Arm, q: ArrayLike, measured: ArrayLike, noise: NoiseModel | None = None
) -> tuple[Array, Array]:
    """Stacked, optionally whitened, ``(Y~, D~)`` of Eq. 9 at the current model.

    Args:
        arm: current model.
        q: ``(m, dof)`` module states.
        measured: ``(m, 4, 4)`` measured tool poses.

    Returns:
        ``Y~ (6m,)`` and ``D~ (6m, 6(K+1))``.
    """
    tool, after = chain(arm.frames, module_poses(arm, q))
    return _stack(tool, after, jnp.asarray(measured), whitening(measured, noise))


def _stack(tool: Array, after: Array, measured: Array, G: Array | None) -> tuple[Array, Array]:
    Y = residual_twist(measured, tool)
    D = calibration_jacobian(after)
    if G is not None:
        Y = jnp.einsum("...ij,...j->...i", G, Y)
        D = G @ D
    n = D.shape[-1]
    return Y.reshape(Y.shape[:-2] + (-1,)), D.reshape(D.shape[:-3] + (-1, n))


def deviation_metrics(measured: ArrayLike, model: ArrayLike) -> tuple[Array, Array]:
    """Deviation metrics between measured ('a') and model ('c') tool poses over the pose axis.

    ``dp = sqrt(mean |P_a - P_c|^2)`` (Eq. 20, mm) and
    ``dR = sqrt(mean |log(R_a^-1 R_c)^v|^2)`` (Eq. 21, rad).

    Args:
        measured, model: ``(..., m, 4, 4)``.

    Returns:
        ``(dp, dR)``, each of shape ``(...)``.
    """
    measured = jnp.asarray(measured)
    model = jnp.asarray(model)
    dpos = lie.translation(measured) - lie.translation(model)
    Rrel = jnp.swapaxes(lie.rotation(measured), -1, -2) @ lie.rotation(model)
    w = lie.so3_log(Rrel)
    dp = _root(jnp.mean(jnp.sum(dpos * dpos, axis=-1), axis=-1))
    dR = _root(jnp.mean(jnp.sum(w * w, axis=-1), axis=-1))
    return dp, dR


def pose_errors(measured: ArrayLike, model: ArrayLike) -> tuple[Array, Array]:
    """Per-pose position error norm (mm) and rotation error angle (rad): each ``(..., m)``."""
    measured = jnp.asarray(measured)
    model = jnp.asarray(model)
    dpos = _norm(lie.translation(measured) - lie.translation(model))
    Rrel = jnp.swapaxes(lie.rotation(measured), -1, -2) @ lie.rotation(model)
    return dpos, lie.rotation_angle(Rrel)


# The square roots of the metrics, with derivative 0 where their argument is 0 (an exact fit),
# as a subgradient: the plain ``sqrt`` gives 0 * inf = NaN there. A ``custom_jvp`` rather than a
# "double where", so that the values stay bitwise those of the plain ``sqrt`` / ``norm`` (a
# double where reordered the robust refit's rounding).
@jax.custom_jvp
def _root(x: Array) -> Array:
    """``sqrt(x)`` for a sum of squares ``x >= 0``; derivative 0 at ``x = 0``."""
    return jnp.sqrt(x)


@_root.defjvp
def _root_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    root = jnp.sqrt(x)
    positive = x > 0
    return root, jnp.where(positive, dx / (2 * jnp.where(positive, root, 1)), 0)


@jax.custom_jvp
def _norm(v: Array) -> Array:
    """``|v|`` over the last axis; derivative 0 at ``v = 0``."""
    return jnp.linalg.norm(v, axis=-1)


@_norm.defjvp
def _norm_jvp(primals, tangents):
    (v,), (dv,) = primals, tangents
    norm = jnp.linalg.norm(v, axis=-1)
    positive = norm > 0
    return norm, jnp.where(positive, jnp.sum(v * dv, axis=-1) / jnp.where(positive, norm, 1), 0)
