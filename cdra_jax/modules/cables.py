"""Cable kinematics of one CDPM module: lengths of a state (inverse) and state of lengths (forward).

Model. Cable ``i`` of a module runs in a straight line from its attachment ``a_i`` on the moving
platform (mm, platform frame) to ``b_i`` on the module base (mm, base frame). At state ``q`` the
platform pose in the base frame is ``T(q) = module.pose(q)`` (a rotation about the module origin
for spherical and revolute modules, a translation along the axis for prismatic ones), the
platform attachment sits at ``p_i = R(q) a_i + t(q)`` and the *measured* cable length is ::

    l_i(q) = ||b_i - p_i|| + o_i

where ``o_i`` is the optional constant length offset of the cable (``module.cable_offset``,
default 0: the difference between what the winch encoder reports and the straight-line
attachment distance; identified by :mod:`.self_calibration`). ``u_i = (b_i - p_i) / ||b_i - p_i||``
is the unit vector from the platform attachment towards the base attachment, the direction in
which the cable pulls the platform.

Forward kinematics from measured lengths is a nonlinear least-squares problem over the
redundant cables (``n > dof``). The derivative of the length under a left-multiplied rotation
``R -> exp(hat(d)) R`` of the platform is ``dl_i = -(p_i x u_i) . d``: the Jacobian is minus the
transposed structure matrix of :mod:`.tension`. Spherical modules are solved by Gauss-Newton on
SO(3) with left-multiplied exponential updates; revolute and prismatic ones by 1-D Gauss-Newton.
Every solve starts from a small fixed set of states (the home pose plus a few well-spread ones
inside the joint limits) and keeps the start with the smallest residual, so that it converges
over the whole workspace without a user-supplied guess; everything is batched over leading
dimensions, jit- and vmap-able.

The solution carries the RMS of the length residuals. With ``n`` cables and ``dof`` state
entries, noise of standard deviation ``s`` on each length gives an expected mean-square residual
``s^2 (n - dof) / n``; lengths that no pose can produce show up as a residual far above that.
:data:`DEFAULT_RESIDUAL_TOL` (0.1 mm RMS) is the default line between the two: about six times
the length quantisation of a 10 mm radius drum read by a 4096-count encoder (0.015 mm), and
about ten times the RMS residual of the 0.02 mm length noise assumed in the tests.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from .. import lie
from ..arm import Module
from ..compilation import batched_like, compiled_when_eager_args
from ._linalg import small_solve
from ._results import select

DEFAULT_RESIDUAL_TOL = 0.1
"""Default largest RMS length residual (mm) of a consistent set of cable lengths."""

_MAX_ROTATION_STEP = 0.5  # rad: Gauss-Newton steps are clipped to this norm on SO(3)


def require_cables(module: Module) -> tuple[Array, Array, Array]:
    """``(b (n, 3), a (n, 3), o (n,))`` of a module, or ``ValueError`` if it has no cables."""
    if module.cable_base is None or module.cable_platform is None:
        raise ValueError(
            f"module {module.name!r} has no cables: give 'cables' in its [[modules]] entry of the "
            "model file"
        )
    b = jnp.asarray(module.cable_base)
    a = jnp.asarray(module.cable_platform)
    o = jnp.zeros(b.shape[0], b.dtype) if module.cable_offset is None else module.cable_offset
    return b, a, jnp.asarray(o)


def cable_length_names(module: Module) -> tuple[str, ...]:
    """Measurement-file columns of the module's cable lengths: ``<module>.l1 ... <module>.lN``."""
    return tuple(f"{module.name}.l{i + 1}" for i in range(module.n_cables))


@compiled_when_eager_args("state")
def platform_points(module: Module, state: ArrayLike) -> Array:
    """Platform attachments ``p_i = R(q) a_i + t(q)``, module base frame: ``(..., n, 3)`` mm."""
    _, a, _ = require_cables(module)
    T = module.pose(state)
    return jnp.einsum("...ij,nj->...ni", T[..., :3, :3], a.astype(T.dtype)) + T[..., None, :3, 3]


@compiled_when_eager_args("state")
def cable_vectors(module: Module, state: ArrayLike) -> tuple[Array, Array, Array]:
    """Platform points, unit pull directions and straight-line lengths at ``state (..., dof)``.

    Returns:
        ``(p (..., n, 3), u (..., n, 3), d (..., n))``: platform attachments in the base frame
        (mm), unit vectors from each platform attachment towards its base attachment, and the
        attachment distances (mm, without the length offset).
    """
    b, _, _ = require_cables(module)
    p = platform_points(module, state)
    v = b.astype(p.dtype) - p
    d = jnp.linalg.norm(v, axis=-1)
    return p, v / d[..., None], d


@compiled_when_eager_args("state")
def cable_lengths(module: Module, state: ArrayLike) -> Array:
    """Inverse kinematics: measured cable lengths ``(..., n)`` mm at module states ``(..., dof)``.

    ``l_i = ||b_i - (R(q) a_i + t(q))|| + o_i`` (see the module docstring).
    """
    _, _, o = require_cables(module)
    _, _, d = cable_vectors(module, state)
    return d + o.astype(d.dtype)


@compiled_when_eager_args("state")
def length_jacobian(module: Module, state: ArrayLike) -> Array:
    """Derivative of the cable lengths w.r.t. the state increment: ``(..., n, dof)``.

    For spherical modules the increment is the left-multiplied rotation ``exp(hat(d)) R`` (rad),
    giving rows ``-(p_i x u_i)``; for revolute modules ``dq`` (rad), rows
    ``-axis . (p_i x u_i)``; for prismatic modules ``dq`` (mm), rows ``-axis . u_i``.
    """
    p, u, _ = cable_vectors(module, state)
    return _length_jacobian(module, p, u)


def _length_jacobian(module: Module, p: Array, u: Array) -> Array:
    axis = jnp.asarray(module.axis, p.dtype)
    if module.kind == "spherical":
        return -jnp.cross(p, u)
    if module.kind == "revolute":
        return -jnp.einsum("...ni,i->...n", jnp.cross(p, u), axis)[..., None]
    return -jnp.einsum("...ni,i->...n", u, axis)[..., None]


class CableFKResult(eqx.Enumeration):
    """Outcome of a forward-kinematics solve from cable lengths (one entry per row)."""

    successful = ""
    max_iterations_reached = (
        "the forward kinematics did not converge within max_iterations (lengths far from any pose?)"
    )
    nonfinite = "a non-finite value (NaN or inf) appeared in the cable lengths or the iterates"
    inconsistent_lengths = (
        "no state of the module reproduces these cable lengths "
        "(the RMS residual is above residual_tol)"
    )


class CableFKSolution(eqx.Module):
    """Module state recovered from cable lengths (batched leading dimensions ``...``).

    Attributes:
        state: ``(..., dof)`` module state (rotation vector, angle or displacement).
        residual_rms: ``(...)`` RMS of the length residuals at the solution, mm.
        residuals: ``(..., n)`` model minus measured length of each cable, mm.
        iterations: ``(...)`` Gauss-Newton iterations of the retained start.
        result: :class:`CableFKResult` code ``(...)``.
    """

    state: Array
    residual_rms: Array
    residuals: Array
    iterations: Array
    result: CableFKResult

    @property
    def successful(self) -> Array:
        """Boolean ``(...)``: converged to lengths consistent within the tolerance."""
        return self.result == CableFKResult.successful


def _spherical_starts(dtype) -> Array:
    """Home plus rotations of 0.8 rad about +-x, +-y, +-z: ``(7, 3, 3)`` start orientations."""
    rv = np.concatenate([np.zeros((1, 3)), 0.8 * np.eye(3), -0.8 * np.eye(3)])
    return lie.so3_exp(jnp.asarray(rv, dtype))


def _scalar_starts(module: Module, dtype) -> Array:
    """Home (clipped into the limits) plus 4 points spread over the limits: ``(5, 1)``."""
    lo, hi = module.limits[0]
    home = min(max(0.0, lo), hi)
    grid = lo + (hi - lo) * np.array([0.125, 0.375, 0.625, 0.875])
    return jnp.asarray(np.concatenate([[home], grid])[:, None], dtype)


@compiled_when_eager_args("lengths", "initial", "tol", "residual_tol")
def cable_forward_kinematics(
    module: Module,
    lengths: ArrayLike,
    *,
    initial: ArrayLike | None = None,
    max_iterations: int = 50,
    tol: float = 1e-12,
    residual_tol: float | ArrayLike = DEFAULT_RESIDUAL_TOL,
) -> CableFKSolution:
    """Forward kinematics: the module state that best reproduces measured cable lengths.

    Least squares over all cables, ``min_q sum_i (l_i(q) - l_i^meas)^2``: Gauss-Newton on SO(3)
    with left-multiplied exponential updates for spherical modules, 1-D Gauss-Newton otherwise.
    The solve runs from every start of a small fixed set (home plus spread states, or only
    ``initial`` when given) and keeps the one with the smallest residual.

    Args:
        module: a module with cables.
        lengths: ``(..., n)`` measured cable lengths, mm.
        initial: optional ``(..., dof)`` start state (e.g. the previous pose of a trajectory);
            it replaces the default starts.
        max_iterations: iteration cap per start (static).
        tol: stop once the step norm (rad, or mm for prismatic modules) is below it.
        residual_tol: RMS residual (mm) above which the lengths count as inconsistent
            (default :data:`DEFAULT_RESIDUAL_TOL`).

    Returns:
        A :class:`CableFKSolution`. Nothing raises for a bad row; read ``result``.
    """
    b, a, o = require_cables(module)
    lengths = jnp.asarray(lengths)
    if not jnp.issubdtype(lengths.dtype, jnp.floating):
        lengths = lengths.astype(jnp.asarray(b).dtype)
    n = b.shape[0]
    if lengths.ndim < 1 or lengths.shape[-1] != n:
        raise ValueError(
            f"module {module.name!r} has {n} cables ({', '.join(cable_length_names(module))}); "
            f"got lengths of shape {lengths.shape}"
        )
    dtype = lengths.dtype
    batch = lengths.shape[:-1]
    target = lengths - o.astype(dtype)
    b = b.astype(dtype)
    a = a.astype(dtype)
    spherical = module.kind == "spherical"
    if initial is not None:
        init = jnp.asarray(initial, dtype)
        if init.shape[-1] != module.dof:
            raise ValueError(
                f"module {module.name!r}: initial state needs {module.dof} entries, "
                f"got shape {init.shape}"
            )
        init = jnp.broadcast_to(init, batch + (module.dof,))[None]
        starts = lie.so3_exp(init) if spherical else init
    else:
        s = _spherical_starts(dtype) if spherical else _scalar_starts(module, dtype)
        starts = jnp.broadcast_to(
            s[(slice(None),) + (None,) * len(batch)], s.shape[:1] + batch + s.shape[1:]
        )
    n_starts = starts.shape[0]
    tgt = jnp.broadcast_to(target, (n_starts,) + target.shape)
    x, iters = _gauss_newton(module, b, a, tgt, starts, max_iterations, tol)
    p = _points(module, a, x)
    v = b - p
    resid = jnp.linalg.norm(v, axis=-1) - tgt
    cost = jnp.sum(resid * resid, axis=-1)
    best = jnp.argmin(jnp.where(jnp.isfinite(cost), cost, jnp.inf), axis=0)
    pick = lambda arr: jnp.take_along_axis(
        arr, best.reshape((1,) + batch + (1,) * (arr.ndim - 1 - len(batch))), axis=0
    )[0]
    x_best = pick(x)
    resid = pick(resid)
    iters = pick(iters)
    state = lie.so3_log(x_best) if spherical else x_best
    rms = jnp.sqrt(jnp.mean(resid * resid, axis=-1))
    finite = jnp.all(jnp.isfinite(lengths), axis=-1) & jnp.isfinite(rms)
    result = select(
        finite,
        select(
            iters < max_iterations,
            select(
                rms <= residual_tol, CableFKResult.successful, CableFKResult.inconsistent_lengths
            ),
            CableFKResult.max_iterations_reached,
        ),
        CableFKResult.nonfinite,
    )
    return CableFKSolution(
        state=state, residual_rms=rms, residuals=resid, iterations=iters, result=result
    )


def _points(module: Module, a: Array, x: Array) -> Array:
    """Platform points for the solver variable ``x``: rotations ``(..., 3, 3)`` or ``(..., 1)``."""
    if module.kind == "spherical":
        return jnp.einsum("...ij,nj->...ni", x, a)
    axis = jnp.asarray(module.axis, x.dtype)
    if module.kind == "revolute":
        R = lie.so3_exp(x * axis)
        return jnp.einsum("...ij,nj->...ni", R, a)
    return a + (x * axis)[..., None, :]


def _gauss_newton(
    module: Module, b: Array, a: Array, target: Array, x0: Array, max_iterations: int, tol: float
) -> tuple[Array, Array]:
    """Batched Gauss-Newton on the length residual; each batch entry stops on its own."""
    spherical = module.kind == "spherical"
    batch = target.shape[:-1]
    if module.kind == "prismatic":
        lo, hi = module.limits[0]
        max_step = 0.25 * (hi - lo)
    else:
        max_step = _MAX_ROTATION_STEP

    def step(x):
        p = _points(module, a, x)
        v = b - p
        d = jnp.linalg.norm(v, axis=-1)
        u = v / d[..., None]
        r = d - target
        J = _length_jacobian(module, p, u)  # (..., n, dof)
        H = jnp.einsum("...ni,...nj->...ij", J, J)
        g = jnp.einsum("...ni,...n->...i", J, r)
        # A tiny Levenberg term keeps the solve defined at a singular pose.
        eye = jnp.eye(H.shape[-1], dtype=H.dtype)
        H = H + 1e-14 * jnp.trace(H, axis1=-2, axis2=-1)[..., None, None] * eye
        delta = -small_solve(H, g)
        norm = jnp.linalg.norm(delta, axis=-1)
        delta = delta * jnp.minimum(1.0, max_step / jnp.maximum(norm, 1e-300))[..., None]
        return delta, norm

    def cond(carry):
        k, _, done, _ = carry
        return (k < max_iterations) & ~jnp.all(done)

    def body(carry):
        k, x, done, iters = carry
        delta, norm = step(x)
        if spherical:
            x_new = lie.so3_exp(delta) @ x
        else:
            x_new = x + delta
        keep = done | ~jnp.isfinite(norm)
        if spherical:
            x = jnp.where(keep[..., None, None], x, x_new)
        else:
            x = jnp.where(keep[..., None], x, x_new)
        iters = jnp.where(done, iters, k + 1)
        done = done | (norm < tol) | ~jnp.isfinite(norm)
        return k + 1, x, done, iters

    # The carry batched from the start under vmap: JAX batches the body once less.
    init = (
        jnp.asarray(0),
        *batched_like(jnp.sum(target), (x0, jnp.zeros(batch, bool), jnp.zeros(batch, jnp.int32))),
    )
    _, x, done, iters = jax.lax.while_loop(cond, body, init)
    iters = jnp.where(done, iters, max_iterations)
    return x, iters
