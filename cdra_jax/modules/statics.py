"""Statics of a cable-driven arm: gravity loads on the modules and the cable tensions holding them.

Bodies. Module ``i`` moves body ``i`` (``module.mass`` kg, centre of mass ``module.com`` mm in
its platform frame; a module without mass properties moves a massless body). An optional
payload (kg) sits at the tool-frame origin. Gravity is ``arm.gravity`` (m/s^2, world frame), so
weights are in N, lever arms in mm and torques in N mm.

Loads. Module ``i`` carries the weight of every body distal to it (bodies ``i .. K-1`` and the
payload). :func:`gravity_torques` gives their torque about the module origin (its centre of
rotation) in the module base frame. The joint carries all force components and, for a revolute
module, the moments about the axes other than the joint axis; the cables must balance the
generalised gravity load of :func:`gravity_loads`: the three torque components of a spherical
module, the torque about the axis of a revolute one, the force along the axis of a prismatic
one. Cables of a module act between its base and its platform only (they are internal to the
bodies distal to any earlier module), so the modules are balanced independently:
``A_i t_i + g_i = 0`` with ``A_i`` the structure matrix of :mod:`.tension`.

Tension distribution. Of the infinitely many balancing tensions (``n > d``) we take the one of
minimum Euclidean norm above the pretension floor, the strictly convex QP ::

    min_t ||t||^2   subject to   A t = w,   t >= f

(``w = -g``, ``f`` = ``module.pretension`` unless given). Its dual is a smooth concave
maximisation over ``lambda`` (d entries), with primal ``t(lambda) = max(f, A^T lambda)``;
:func:`distribute_tensions` solves it by a damped semismooth Newton method with an Armijo line
search, which terminates in a few iterations for these piecewise-linear optimality conditions;
the result is checked by the residual ``|A t - w|``. For ``n = d + 1`` the same solver
reproduces the closed form (one null-space direction; tested).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from .. import lie
from ..arm import Arm, Module, chain, module_poses
from ..compilation import batched_like, compiled_when_eager_args
from ._results import select
from .tension import structure_matrix


def _masses(arm: Arm, dtype) -> tuple[Array, Array]:
    """``(mass (K,), com (K, 3))`` of the bodies moved by the modules (0 / origin when absent)."""
    mass = jnp.asarray([0.0 if m.mass is None else m.mass for m in arm.modules], dtype)
    com = jnp.stack(
        [jnp.zeros(3, dtype) if m.com is None else jnp.asarray(m.com, dtype) for m in arm.modules]
    )
    return mass, com


def total_mass(arm: Arm) -> float:
    """Mass of the moving bodies of ``arm`` (kg), without payload."""
    return float(sum(0.0 if m.mass is None else m.mass for m in arm.modules))


@compiled_when_eager_args("q")
def world_frames(arm: Arm, q: Array) -> tuple[Array, Array, Array]:
    """World poses of the tool ``(..., 4, 4)``, the module platforms and the module bases
    ``(..., K, 4, 4)``."""
    poses = module_poses(arm, q)
    tool, after = chain(jnp.asarray(arm.frames, q.dtype), poses)
    before = after @ lie.inverse(poses)
    return tool, after, before


@compiled_when_eager_args("q", "payload_kg")
def gravity_torques(arm: Arm, q: ArrayLike, payload_kg: ArrayLike = 0.0) -> Array:
    """Torque of gravity about each module's origin from the bodies distal to it: ``(..., K, 3)``.

    Args:
        arm: the arm (masses and centres of mass from its modules, ``arm.gravity`` m/s^2).
        q: ``(..., dof)`` joint states.
        payload_kg: payload at the tool-frame origin, kg (scalar or ``(...)``).

    Returns:
        N mm, each expressed in its module's base frame (the frame of the structure matrix).
    """
    q = jnp.asarray(q)
    if not jnp.issubdtype(q.dtype, jnp.floating):
        q = q.astype(jnp.asarray(arm.frames).dtype)
    dtype = q.dtype
    tool, after, before = world_frames(arm, q)
    mass, com = _masses(arm, dtype)
    g = jnp.asarray(arm.gravity, dtype)
    x = jnp.einsum("...kij,kj->...ki", after[..., :3, :3], com) + after[..., :3, 3]  # (..., K, 3)
    w = mass[:, None] * g  # (K, 3) N
    payload = jnp.asarray(payload_kg, dtype)
    w_pay = payload[..., None] * g  # (..., 3)
    x_pay = tool[..., :3, 3]
    centre = after[..., :3, 3]  # module origins (= base origins for rotations)
    k = len(arm.modules)
    out = []
    for i in range(k):
        c = centre[..., i, :]
        tau = jnp.cross(x_pay - c, w_pay)
        for j in range(i, k):
            tau = tau + jnp.cross(x[..., j, :] - c, w[j])
        out.append(jnp.einsum("...ji,...j->...i", before[..., i, :3, :3], tau))
    return jnp.stack(out, axis=-2)


def _distal_weight(arm: Arm, q: Array, payload_kg: ArrayLike) -> Array:
    """World weight force (N) of the bodies distal to each module: ``(..., K, 3)``."""
    mass, _ = _masses(arm, q.dtype)
    g = jnp.asarray(arm.gravity, q.dtype)
    tail = jnp.cumsum(mass[::-1])[::-1]  # mass distal to each module
    payload = jnp.asarray(payload_kg, q.dtype)
    total = tail + payload[..., None]
    return total[..., None] * g


@compiled_when_eager_args("q", "payload_kg")
def gravity_loads(arm: Arm, q: ArrayLike, payload_kg: ArrayLike = 0.0) -> Array:
    """Generalised gravity load each module's cables must cancel, flat ``(..., dof)``.

    In ``arm.state_names`` order: the torque (N mm, base frame) for spherical modules, the
    torque about the axis (N mm) for revolute ones, the force along the axis (N) for prismatic
    ones. The cables balance it when ``A t = -load``.
    """
    q = jnp.asarray(q)
    if not jnp.issubdtype(q.dtype, jnp.floating):
        q = q.astype(jnp.asarray(arm.frames).dtype)
    tau = gravity_torques(arm, q, payload_kg)
    force = None
    out = []
    for i, m in enumerate(arm.modules):
        axis = jnp.asarray(m.axis, q.dtype)
        if m.kind == "spherical":
            out.append(tau[..., i, :])
        elif m.kind == "revolute":
            out.append(jnp.einsum("...i,i->...", tau[..., i, :], axis)[..., None])
        else:
            if force is None:
                _, _, before = world_frames(arm, q)
                force = jnp.einsum(
                    "...kji,...kj->...ki", before[..., :3, :3], _distal_weight(arm, q, payload_kg)
                )
            out.append(jnp.einsum("...i,i->...", force[..., i, :], axis)[..., None])
    return jnp.concatenate(out, axis=-1)


class TensionResult(eqx.Enumeration):
    """Outcome of a tension distribution (one entry per pose)."""

    successful = ""
    unbalanced = (
        "no tensions above the floor balance the load (the pose lacks tension closure for this "
        "load) or the solver did not converge within max_iterations"
    )
    nonfinite = "a non-finite value (NaN or inf) appeared in the structure matrix or the load"


class TensionSolution(eqx.Module):
    """Cable tensions of one module (batched leading dimensions ``...``).

    Attributes:
        tensions: ``(..., n)`` N, all ``>= floor`` when successful.
        residual: ``(...)`` ``|A t - w|`` (N mm for torque rows).
        iterations: ``(...)`` Newton iterations.
        result: :class:`TensionResult` code ``(...)``.
    """

    tensions: Array
    residual: Array
    iterations: Array
    result: TensionResult

    @property
    def successful(self) -> Array:
        return self.result == TensionResult.successful


@compiled_when_eager_args("A", "wrench", "floor", "rtol")
def distribute_tensions(
    A: ArrayLike,
    wrench: ArrayLike,
    floor: ArrayLike = 0.0,
    *,
    max_iterations: int = 50,
    rtol: float = 1e-12,
) -> TensionSolution:
    """Minimum-norm tensions ``t >= floor`` with ``A t = wrench`` (see the module docstring).

    Args:
        A: ``(..., d, n)`` structure matrix.
        wrench: ``(..., d)`` generalised force the cables must produce (``-`` the load).
        floor: ``(..., n)`` or scalar minimum tension, N.
        max_iterations: Newton iteration cap (static).
        rtol: convergence tolerance on ``|A t - w|`` relative to ``|A| (|t| + |w| / |A|)``.

    Returns:
        A :class:`TensionSolution`; never raises for one bad pose.
    """
    A = jnp.asarray(A)
    dtype = A.dtype
    w = jnp.asarray(wrench, dtype)
    d, n = A.shape[-2:]
    if w.shape[-1] != d:
        raise ValueError(f"wrench needs {d} entries (rows of A), got shape {w.shape}")
    batch = jnp.broadcast_shapes(A.shape[:-2], w.shape[:-1])
    f = jnp.broadcast_to(jnp.asarray(floor, dtype), batch + (n,))
    A = jnp.broadcast_to(A, batch + (d, n))
    w = jnp.broadcast_to(w, batch + (d,))
    At = jnp.swapaxes(A, -1, -2)
    a_norm = jnp.linalg.norm(A, axis=(-2, -1))
    eye = jnp.eye(d, dtype=dtype)

    def primal(lam):
        return jnp.maximum(f, jnp.einsum("...nd,...d->...n", At, lam))

    def dual(lam):
        c = jnp.einsum("...nd,...d->...n", At, lam)
        t = jnp.maximum(f, c)
        return jnp.einsum("...d,...d->...", lam, w) + jnp.sum(0.5 * t * t - c * t, axis=-1)

    def residual(lam):
        t = primal(lam)
        r = w - jnp.einsum("...dn,...n->...d", A, t)
        tol = rtol * (a_norm * jnp.linalg.norm(t, axis=-1) + jnp.linalg.norm(w, axis=-1))
        return t, r, tol

    # Start from the unconstrained minimum-norm solution t = A^T lambda, A A^T lambda = w.
    AAt = A @ At
    reg0 = AAt + 1e-14 * jnp.trace(AAt, axis1=-2, axis2=-1)[..., None, None] * eye
    lam0 = jnp.linalg.solve(reg0, w[..., None])[..., 0]

    def cond(carry):
        k, _, done = carry[0], carry[1], carry[2]
        return (k < max_iterations) & ~jnp.all(done)

    def body(carry):
        k, lam, done, iters = carry
        t, r, tol = residual(lam)
        active = (jnp.einsum("...nd,...d->...n", At, lam) > f).astype(dtype)
        H = jnp.einsum("...dn,...n,...en->...de", A, active, A)
        H = H + (1e-12 * jnp.trace(AAt, axis1=-2, axis2=-1))[..., None, None] * eye
        step = jnp.linalg.solve(H, r[..., None])[..., 0]
        d0 = dual(lam)
        slope = jnp.einsum("...d,...d->...", r, step)  # gradient of the dual is r

        r_norm = jnp.linalg.norm(r, axis=-1)

        def accept(alpha):
            # Armijo ascent of the dual, or (near the solution, where differences of the dual
            # drown in round-off) a halved optimality residual.
            trial = lam + alpha[..., None] * step
            _, r_new, _ = residual(trial)
            armijo = dual(trial) >= d0 + 1e-4 * alpha * slope
            return armijo | (jnp.linalg.norm(r_new, axis=-1) <= 0.5 * r_norm)

        def backtrack(_, carry):
            alpha, found = carry
            found = found | accept(alpha)
            return jnp.where(found, alpha, 0.5 * alpha), found

        alpha, _ = jax.lax.fori_loop(
            0, 40, backtrack, (jnp.ones(batch, dtype), jnp.zeros(batch, bool))
        )
        new = lam + alpha[..., None] * step
        conv = jnp.linalg.norm(r, axis=-1) <= tol
        lam = jnp.where((done | conv)[..., None], lam, new)
        iters = jnp.where(done | conv, iters, k + 1)
        return k + 1, lam, done | conv | ~jnp.all(jnp.isfinite(new), axis=-1), iters

    # The carry batched from the start under vmap: JAX batches the body once less.
    rest = (lam0, jnp.zeros(batch, bool), jnp.zeros(batch, jnp.int32))
    init = (jnp.asarray(0), *batched_like(jnp.sum(lam0), rest))
    _, lam, _, iters = jax.lax.while_loop(cond, body, init)
    # Polish: one undamped Newton step on the final active set solves the piecewise-linear
    # optimality conditions to round-off when the active set is the optimal one.
    t, r, tol = residual(lam)
    active = (jnp.einsum("...nd,...d->...n", At, lam) > f).astype(dtype)
    H = jnp.einsum("...dn,...n,...en->...de", A, active, A)
    H = H + (1e-15 * jnp.trace(AAt, axis1=-2, axis2=-1))[..., None, None] * eye
    polished = lam + jnp.linalg.solve(H, r[..., None])[..., 0]
    _, r_pol, _ = residual(polished)
    better = jnp.linalg.norm(r_pol, axis=-1) < jnp.linalg.norm(r, axis=-1)
    lam = jnp.where(better[..., None], polished, lam)
    t, r, tol = residual(lam)
    res = jnp.linalg.norm(r, axis=-1)
    finite = jnp.all(jnp.isfinite(A), axis=(-2, -1)) & jnp.all(jnp.isfinite(w), axis=-1)
    finite = finite & jnp.all(jnp.isfinite(t), axis=-1)
    ok = res <= 10 * tol
    result = select(
        finite,
        select(ok, TensionResult.successful, TensionResult.unbalanced),
        TensionResult.nonfinite,
    )
    return TensionSolution(tensions=t, residual=res, iterations=iters, result=result)


def module_floor(module: Module) -> float:
    """Tension floor of a module: its ``pretension`` (N), or 0 when the model gives none."""
    return 0.0 if module.pretension is None else float(module.pretension)


@compiled_when_eager_args("q", "payload_kg", "floor")
def holding_tensions(
    arm: Arm,
    q: ArrayLike,
    payload_kg: ArrayLike = 0.0,
    *,
    floor: ArrayLike | None = None,
    max_iterations: int = 50,
) -> dict[str, TensionSolution]:
    """Cable tensions holding the arm still against gravity at states ``q (..., dof)``.

    Args:
        arm: the arm; modules without cables are skipped.
        q: joint states.
        payload_kg: payload at the tool-frame origin, kg (scalar or ``(...)``).
        floor: tension floor (N) for every module; default each module's ``pretension``.
        max_iterations: Newton iteration cap.

    Returns:
        ``{module name: TensionSolution}`` with tensions ``(..., n)`` N of each module that has
        cables, solving ``A t = -load`` (:func:`gravity_loads`) by :func:`distribute_tensions`.
    """
    q = jnp.asarray(q)
    if not jnp.issubdtype(q.dtype, jnp.floating):
        q = q.astype(jnp.asarray(arm.frames).dtype)
    loads = arm.split_state(gravity_loads(arm, q, payload_kg))
    out = {}
    for m, qi, load in zip(arm.modules, arm.split_state(q), loads, strict=True):
        if not m.n_cables:
            continue
        f = module_floor(m) if floor is None else floor
        out[m.name] = distribute_tensions(
            structure_matrix(m, qi), -load, f, max_iterations=max_iterations
        )
    return out
