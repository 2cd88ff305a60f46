"""Levenberg-Marquardt calibration with optimistix on the same residual as the paper solver.

The parameters are the error twists ``X`` (Eq. 8) of all fixed transforms at once,
``F_j(X) = exp(hat(X_j)) F_j`` (Eqs. 11-14 in one step rather than accumulated), and the
residual is the (optionally whitened) stacked ``log(T_meas T(X)^-1)^v`` of Eq. 7. Rank
deficiency (the CDRA's two unidentifiable directions) is handled by the damping. The loop
drives ``optimistix.LevenbergMarquardt`` step by step so that the deviation metrics
(Eqs. 20-21) are recorded at every step, as for the paper solver.

Performance (see ``benchmarks/README.md``):

* the residual is evaluated in the pose-last layout of :mod:`.kernels`, and returns the
  deviation metrics of its point as optimistix' ``aux``, so that recording them costs nothing;
* its Jacobian is analytic (:func:`residual_jacobian`, a ``jax.custom_jvp``): optimistix
  linearises the residual at every step and its QR solver materialises the Jacobian, which with
  autodiff costs 24 forward-mode passes through the chain and the logarithm and here one small
  matrix product;
* under ``vmap`` the trials run through a work queue (:func:`.batching.queued_vmap`): a fixed
  number of slots iterate side by side and a finished trial's slot takes the next trial.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax import Array
from jax.typing import ArrayLike

from .. import lie
from ..arm import Arm, module_poses
from . import kernels
from .batching import Iteration, queued_vmap
from .linear import default_rcond
from .model import NoiseModel
from .solution import RESULTS, CalibrationSolution
from .validation import check_problem

SLOTS = 64
"""Trials iterated side by side when the solver is vmapped (the work queue of :mod:`.batching`).

LM's iteration count varies a lot between trials (9 to more than 30 for the CDRA, mostly steps
rejected once converged), so a vmapped ``while_loop``, even chunked, would spend most of its
time on the slowest trials; the queue refills a slot as soon as its trial has finished.
"""

CHUNK_SIZE = 128
"""Trials per chunk of the final evaluation (rank, metrics) under ``vmap``."""


def calibrate_lm(
    arm: Arm,
    q: ArrayLike,
    measured: ArrayLike,
    noise: NoiseModel | None = None,
    *,
    max_iterations: int = 50,
    rtol: float = 1e-12,
    atol: float = 1e-12,
    rcond: float | None = None,
    allow_underdetermined: bool = False,
    throw: bool = True,
) -> CalibrationSolution:
    """Calibrate the fixed transforms of ``arm`` with optimistix's Levenberg-Marquardt.

    Arguments as :func:`cdra_jax.calibration.calibrate_paper`; ``rtol``/``atol`` are the
    optimistix step and cost tolerances and ``max_iterations`` its ``max_steps``. The
    ``step_norm`` history holds ``||X_k - X_{k-1}||`` (zero for rejected steps).
    """
    q, measured = check_problem(arm, q, measured, allow_underdetermined=allow_underdetermined)
    dtype = measured.dtype
    poses = module_poses(arm, q)
    frames0 = jnp.asarray(arm.frames, dtype)
    solve = _lm_solver(
        max_iterations=max_iterations, rtol=rtol, atol=atol, rcond=rcond, weighted=noise is not None
    )
    args = (frames0, poses, measured)
    if noise is not None:
        args += (jnp.asarray(noise.position_mm, dtype), jnp.asarray(noise.rotation_rad, dtype))
    sol = solve(*args)
    if throw:
        sol = sol.result.error_if(sol, sol.result != RESULTS.successful)
    return sol


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
    (:func:`.kernels.se3_left_jacobian`); the test suite checks the product against
    ``jax.jacfwd`` of the residual.

    Args:
        X: ``(6 (K+1),)`` error twists.
        frames0: ``(K+1, 4, 4)`` nominal frames.
        poses: ``(K, 3, 4, m)`` module poses (pose-last, :mod:`.kernels`).
        measured: ``(3, 4, m)`` measured tool poses (pose-last).
        noise: whitening, or ``None``.

    Returns:
        ``(r (6m,), (delta_p, delta_R), J (6m, 6 (K+1)))``; ``r`` component-major
        (``r.reshape(6, m)[:, k]`` is pose ``k``), as the rows of ``J``.
    """
    k1 = frames0.shape[0]
    n = 6 * k1
    xi = X.reshape(k1, 6)
    frames = lie.se3_exp(xi) @ frames0
    lin = kernels.linearise(frames, poses, measured)  # unwhitened: D = [I, Ad(P_i)] at F(X)
    m = measured.shape[-1]
    r = lin.Y.reshape(6, m)  # log(Delta)^v, Delta = T_meas T(X)^-1
    jr_inv = kernels.se3_left_jacobian_inverse(-r)  # J_r^-1(r) = J_l^-1(-r): (6, 6, m)
    jl = jnp.moveaxis(kernels.se3_left_jacobian(xi.T), -1, 0)  # (K+1, 6, 6)
    DT = lin.DT.reshape(k1, 6, 6, m)  # (frame, column, row, pose): D_k^T
    # The small contractions as explicit sums of 6 products over the pose axis (XLA turns
    # einsums with the pose axis as a batch axis into transposes and tiny matrix products).
    # (J_r^-1 D_k)^T = D_k^T J_r^-1^T: contract the row axis b.
    A = sum(DT[:, :, b, None, :] * jr_inv[None, None, :, b, :] for b in range(6))
    # diag(J_l)^T on the left: column c of frame j is sum_d J_l[j][d, c] (column d).
    A = sum(jl[:, d, :, None, None] * A[:, d, None, :, :] for d in range(6))
    J = -jnp.transpose(A.reshape(n, 6, m), (1, 2, 0))  # (row, pose, column)
    if noise is not None:
        r = kernels.whiten(r, measured, noise)
        J = kernels.whiten(jnp.moveaxis(J, 2, 1), measured, noise)  # (row, column, pose)
        J = jnp.moveaxis(J, 1, 2)
    return r.reshape(6 * m), (lin.delta_p, lin.delta_R), J.reshape(6 * m, n)


def _residual_fn(frames0, poses, measured, noise):
    """``X -> (r, (delta_p, delta_R))`` for optimistix, with the analytic Jacobian as its JVP."""

    @jax.custom_jvp
    def residual(X):
        r, aux, _ = residual_jacobian(X, frames0, poses, measured, noise)
        return r, aux

    @residual.defjvp
    def _jvp(primals, tangents):
        (X,), (dX,) = primals, tangents
        r, aux, J = residual_jacobian(X, frames0, poses, measured, noise)
        zero = jax.tree.map(jnp.zeros_like, aux)
        return (r, aux), (J @ dX, zero)

    return lambda X, _: residual(X)


def _lm_solver(*, max_iterations, rtol, atol, rcond, weighted):
    """The per-trial LM solver for one static configuration, a work queue under ``vmap``."""
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    options: dict = {}
    tags: frozenset = frozenset()

    def setup(frames0, poses, measured, *noise_std):
        noise = NoiseModel(*noise_std) if weighted else None
        P = jnp.moveaxis(poses[..., :3, :], 0, -1)  # (K, 3, 4, m)
        T = kernels.pose_stack(measured)
        return _residual_fn(frames0, P, T, noise), P, T, noise

    def optx_state(fn, y0):
        f_struct, aux_struct = jax.eval_shape(lambda: fn(y0, None))
        state0 = solver.init(fn, y0, None, options, f_struct, aux_struct, tags)
        # As optimistix' own loop does: carry only the array part of the solver state.
        return eqx.partition(state0, eqx.is_array)

    def init(frames0, poses, measured, *noise_std):
        dtype = measured.dtype
        fn = setup(frames0, poses, measured, *noise_std)[0]
        y0 = jnp.zeros(6 * frames0.shape[0], dtype)
        nan = jnp.asarray(jnp.nan, dtype)
        finite_in = jnp.all(jnp.isfinite(measured)) & jnp.all(jnp.isfinite(poses))
        return (
            jnp.asarray(0),
            y0,
            optx_state(fn, y0)[0],
            jnp.full((max_iterations,), nan),
            jnp.full((max_iterations + 1,), nan),
            jnp.full((max_iterations + 1,), nan),
            jnp.asarray(False),
            finite_in,
        )

    def running(carry):
        k, _, _, _, _, _, done, ok = carry
        return (k < max_iterations) & ~done & ok

    def step(carry, *args):
        k, X, dyn_state, steps, dps, dRs, _, _ = carry
        fn = setup(*args)[0]
        state = eqx.combine(optx_state(fn, X)[1], dyn_state)
        # The aux that optimistix returns belongs to its input X: Eqs. 20-21 at X_k.
        X_new, state, (dp, dR) = solver.step(fn, X, None, options, state, tags)
        done, _ = solver.terminate(fn, X, None, options, state, tags)
        dyn_state, _ = eqx.partition(state, eqx.is_array)
        return (
            k + 1,
            X_new,
            dyn_state,
            steps.at[k].set(jnp.linalg.norm(X_new - X)),
            dps.at[k].set(dp),
            dRs.at[k].set(dR),
            done,
            jnp.all(jnp.isfinite(X_new)),
        )

    def result(carry):
        k, X, _, steps, dps, dRs, done, ok = carry
        return k, X, steps, dps, dRs, done, ok

    def finish(res, frames0, poses, measured, *noise_std):
        k, X, steps, dps, dRs, done, ok = res
        _, P, T, noise = setup(frames0, poses, measured, *noise_std)
        dtype = measured.dtype
        k_frames = frames0.shape[0]
        n = 6 * k_frames
        frames = lie.se3_exp(X.reshape(k_frames, 6)) @ frames0
        lin = kernels.linearise(frames, P, T, noise)
        s = jnp.linalg.svd(lin.DT, compute_uv=False)
        rc = default_rcond(dtype) if rcond is None else rcond
        dps = dps.at[k].set(lin.delta_p)
        dRs = dRs.at[k].set(lin.delta_R)
        ok = ok & jnp.isfinite(lin.delta_p) & jnp.isfinite(lin.delta_R)
        result = RESULTS.where(
            ok,
            RESULTS.where(done, RESULTS.successful, RESULTS.max_iterations_reached),
            RESULTS.nonfinite,
        )
        return CalibrationSolution(
            frames=frames,
            errors=lie.se3_log(frames @ lie.inverse(frames0)),
            result=result,
            iterations=k,
            step_norm=steps,
            delta_p=dps,
            delta_R=dRs,
            rank=jnp.sum(s > rc * s[..., :1], axis=-1),
            singular_values=jnp.pad(s, (0, max(0, n - s.shape[-1]))),
            cost=jnp.sum(lin.Y * lin.Y),
            solver="lm",
        )

    it = Iteration(init=init, step=step, running=running, result=result, finish=finish)
    return queued_vmap(it, SLOTS, CHUNK_SIZE)
