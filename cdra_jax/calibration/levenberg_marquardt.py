"""Levenberg-Marquardt calibration with optimistix on the same residual as the paper solver.

The parameters are the error twists ``X`` (Eq. 8) of all fixed transforms at once,
``F_j(X) = exp(hat(X_j)) F_j`` (Eqs. 11-14 in one step rather than accumulated), and the
residual is the (optionally whitened) stacked ``log(T_meas T(X)^-1)^v`` of Eq. 7. The Jacobian
comes from autodiff; rank deficiency (the CDRA's two unidentifiable directions) is handled by
the damping. The loop drives ``optimistix.LevenbergMarquardt`` step by step so that the
deviation metrics (Eqs. 20-21) are recorded at every step, as for the paper solver.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax.typing import ArrayLike

from .. import lie
from ..arm import Arm, chain, module_poses
from .linear import min_norm_lstsq
from .model import NoiseModel, _stack, deviation_metrics, whitening
from .solution import RESULTS, CalibrationSolution
from .validation import check_problem


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
    G = whitening(measured, noise)
    frames0 = jnp.asarray(arm.frames, dtype)
    k_frames = len(arm.frame_names)
    n = arm.n_params
    nan = jnp.asarray(jnp.nan, dtype)
    finite_in = jnp.all(jnp.isfinite(measured)) & jnp.all(jnp.isfinite(poses))

    def frames_of(X):
        return lie.se3_exp(X.reshape(k_frames, 6)) @ frames0

    def fn(X, _):
        tool, after = chain(frames_of(X), poses)
        Y, _ = _stack(tool, after, measured, G)
        return Y, None  # optimistix' internal step API expects (out, aux)

    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    y0 = jnp.zeros(n, dtype)
    f_struct = jax.eval_shape(lambda: fn(y0, None)[0])
    options: dict = {}
    tags: frozenset = frozenset()
    state0 = solver.init(fn, y0, None, options, f_struct, None, tags)
    # As optimistix' own loop does: carry only the array part of the solver state.
    dyn_state0, static_state = eqx.partition(state0, eqx.is_array)

    def metrics(X):
        tool, _ = chain(frames_of(X), poses)
        return deviation_metrics(measured, tool)

    def cond(carry):
        k, _, _, _, _, _, done, ok = carry
        return (k < max_iterations) & ~done & ok

    def body(carry):
        k, X, dyn_state, steps, dps, dRs, _, _ = carry
        dp, dR = metrics(X)
        state = eqx.combine(static_state, dyn_state)
        X_new, state, _ = solver.step(fn, X, None, options, state, tags)
        done, _ = solver.terminate(fn, X, None, options, state, tags)
        dyn_state, _ = eqx.partition(state, eqx.is_array)
        step = jnp.linalg.norm(X_new - X)
        ok = jnp.all(jnp.isfinite(X_new))
        return (
            k + 1,
            X_new,
            dyn_state,
            steps.at[k].set(step),
            dps.at[k].set(dp),
            dRs.at[k].set(dR),
            done,
            ok,
        )

    init = (
        jnp.asarray(0),
        y0,
        dyn_state0,
        jnp.full((max_iterations,), nan),
        jnp.full((max_iterations + 1,), nan),
        jnp.full((max_iterations + 1,), nan),
        jnp.asarray(False),
        finite_in,
    )
    k, X, _, steps, dps, dRs, done, ok = jax.lax.while_loop(cond, body, init)
    frames = frames_of(X)
    tool, after = chain(frames, poses)
    Y, D = _stack(tool, after, measured, G)
    dp, dR = deviation_metrics(measured, tool)
    _, rank, s = min_norm_lstsq(D, Y, rcond)
    dps = dps.at[k].set(dp)
    dRs = dRs.at[k].set(dR)
    ok = ok & jnp.isfinite(dp) & jnp.isfinite(dR)
    result = RESULTS.where(
        ok,
        RESULTS.where(done, RESULTS.successful, RESULTS.max_iterations_reached),
        RESULTS.nonfinite,
    )
    sol = CalibrationSolution(
        frames=frames,
        errors=lie.se3_log(frames @ lie.inverse(frames0)),
        result=result,
        iterations=k,
        step_norm=steps,
        delta_p=dps,
        delta_R=dRs,
        rank=rank,
        singular_values=jnp.pad(s, (0, max(0, n - s.shape[-1]))),
        cost=jnp.sum(Y * Y),
        solver="lm",
    )
    if throw:
        sol = result.error_if(sol, result != RESULTS.successful)
    return sol
