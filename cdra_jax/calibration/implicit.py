"""Derivatives of a calibration through its optimality condition (implicit function theorem).

The solvers iterate (``while_loop``), so JAX cannot differentiate them step by step, and it
should not: the derivative of a converged calibration depends on the data only through the
condition its solution satisfies, not on the path that found it. With the calibrated frames
``F*`` perturbed on the left, ``F = exp(d) F*`` (``d (6 (K+1),)``, twists ``(v, w)`` in mm and
rad, as the solvers step), and ``theta`` the data (module poses, measured tool poses, noise
standard deviations), the solution satisfies ``G(0, theta) = 0`` with

- the paper solver (``"paper"``, ``"weighted"``): ``G = D~^T Y~``, Eq. 9's normal equations
  (Eq. 10) with the analytic Jacobian of Eq. 8; their step is zero exactly where this is;
- LM (``"lm"``): ``G = grad_d 1/2 |Y~|^2``, the gradient of its cost (the two conditions differ
  by terms of the order of the residual squared, so the two fits differ slightly under noise,
  and so do their derivatives).

Differentiating ``G(d(theta), theta) = 0``: ``dd = -H^+ (dG/dtheta) dtheta`` with
``H = dG/dd (n, n)``. ``H`` has the rank of the calibration (22 for the paper's arm, 24
parameters): along the unidentifiable directions no data can move the solution, and the
pseudo-inverse (the ``rank`` largest singular values of ``H``) gives the derivative without a
component along them. The frames then move as ``dF_j = hat(dd_j) F*_j``. The nominal frames
are only the starting point: they do not enter ``G``, so the calibrated frames do not depend on
them (the errors ``log(F* F0^-1)`` do). What a user can identify (the predicted tool pose at any
state, the base and tool frames, the cost) therefore gets its exact derivative, the one that
finite differences of the converged solver give; along the unidentifiable directions the
solver's path decides, and the derivative is taken as zero there.

This is the approach of optimistix' ``ImplicitAdjoint`` for its root finders and least-squares
solvers, written out for the local-POE model. ``H`` carries the square of the calibration
Jacobian's condition number: in float32 the derivative is only good to a few per cent (2.5 % on
10 weighted CDRA poses); differentiate in float64.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import Array

from .. import lie
from ..arm import error_twists
from . import kernels
from .model import NoiseModel


def attach(
    kind: str,
    frames: Array,
    errors: Array,
    cost: Array,
    rank: Array,
    frames0: Array,
    poses: Array,
    measured: Array,
    *noise_std: Array,
) -> tuple[Array, Array, Array]:
    """``(frames, errors, cost)`` of a finished solve, unchanged, with implicit derivatives.

    Args:
        kind: ``"gauss_newton"`` (the paper solver's condition) or ``"lm"``.
        frames: ``(K+1, 4, 4)`` the solver's calibrated frames (computed without derivatives).
        errors: ``(K+1, 6)`` its identified errors against ``frames0``.
        cost: ``()`` its final cost ``|Y~|^2``.
        rank: ``()`` the numerical rank of the solve (how many directions are identified).
        frames0: ``(K+1, 4, 4)`` nominal frames.
        poses: ``(m, K, 4, 4)`` module poses.
        measured: ``(m, 4, 4)`` measured tool poses (mm).
        noise_std: ``(s_pos, s_rot)`` (scalars or ``(m,)``) of a weighted solve, else empty.

    Returns:
        The same three arrays, bitwise; their derivatives with respect to ``frames0``,
        ``poses``, ``measured`` and ``noise_std`` are those of the module docstring.
    """
    return _attach(kind, frames, errors, cost, rank, frames0, poses, measured, *noise_std)


def _condition(kind: str, d: Array, frames: Array, poses: Array, measured: Array, noise_std):
    """``G(d, theta)`` ``(n,)`` and the cost ``|Y~|^2`` at ``F = exp(d) F*``."""
    noise = NoiseModel(*noise_std) if noise_std else None
    P = jnp.moveaxis(poses[..., :3, :], 0, -1)  # (K, 3, 4, m)
    T = kernels.pose_stack(measured)  # (3, 4, m)

    if kind == "gauss_newton":
        moved = kernels.step_frames(d, frames)
        lin = kernels.linearise(moved, P, T, noise)
        return lin.DT @ lin.Y, jnp.sum(lin.Y * lin.Y)

    # LM's analytic Jacobian of the residual (closed-form left and right Jacobians of SE(3)):
    # the gradient J^T Y~ then needs first derivatives only, where autodiff's gradient would
    # be differentiated twice (a 4x larger program, 3x the compile time).
    Y, _, J = kernels.residual_jacobian(d, frames, P, T, noise)
    return J.T @ Y, jnp.sum(Y * Y)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _attach(kind, frames, errors, cost, rank, frames0, poses, measured, *noise_std):
    return frames, errors, cost


@_attach.defjvp
def _attach_jvp(kind, primals, tangents):
    frames, errors, cost, rank, frames0, poses, measured, *noise_std = primals
    _, _, _, _, dframes0, dposes, dmeasured, *dnoise = tangents
    n = 6 * frames.shape[0]
    d0 = jnp.zeros((n,), frames.dtype)
    data, ddata = (poses, measured, tuple(noise_std)), (dposes, dmeasured, tuple(dnoise))

    def condition(d, data):
        return _condition(kind, d, frames, *data)

    # dG/dtheta dtheta and the cost's derivative along theta, in one forward pass.
    (_, _), (dG, dcost_data) = jax.jvp(lambda data: condition(d0, data), (data,), (ddata,))
    # H = dG/dd, and the cost's gradient in d, from one forward-mode Jacobian.
    H, dcost_dd = jax.jacfwd(lambda d: condition(d, data))(d0)
    U, s, Vt = jnp.linalg.svd(H)
    keep = jnp.arange(n) < rank
    s_inv = jnp.where(keep, 1 / jnp.where(keep, s, 1), 0)  # double where: no 1/0 anywhere
    dd = -(Vt.T @ (s_inv * (U.T @ dG)))
    # The cost also moves with d (zero at an exact stationary point of the cost; kept, since
    # the paper's condition is not exactly that under noise).
    dcost_d = dcost_dd @ dd
    dframes = lie.hat(dd.reshape(-1, 6)) @ frames

    _, derrors = jax.jvp(error_twists, (frames, frames0), (dframes, dframes0))
    return (frames, errors, cost), (dframes, derrors, dcost_data + dcost_d)


def refuse_derivatives(message: str, tree):
    """``tree`` unchanged, but differentiating any of its floating-point arrays raises.

    For functions whose output is not a differentiable function of their input (discrete
    decisions such as reweighting rounds and outlier flags): without it, JAX fails deep inside
    a ``while_loop`` with a message that names none of the user's code.

    Args:
        message: the ``ValueError`` text, raised at trace time by ``jax.grad``, ``jax.jvp``,
            ``jax.jacfwd`` and the like.
        tree: a pytree (arrays, an :class:`~cdra_jax.arm.Arm`, a ``NoiseModel``, ...); leaves
            that are not JAX floating-point arrays pass through untouched.
    """

    def barrier(x):
        if isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jnp.inexact):
            return _refuse(message, x)
        return x

    return jax.tree.map(barrier, tree)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _refuse(message, x):
    return x


@_refuse.defjvp
def _refuse_jvp(message, primals, tangents):
    raise ValueError(message)
