"""The paper's iterative least-squares calibration (Eqs. 9-19, Fig. 4), jit- and vmap-able.

Each iteration stacks ``Y~`` and ``D~`` at the current model (Eq. 9), solves for ``X`` by
rank-revealing minimum-norm least squares (Eq. 10, see :mod:`.linear`), and left-multiplies
every fixed transform by ``exp(hat(X_j))`` (Eqs. 11-14) until ``||X|| < tol``. The identified
errors are ``log(F_j^c F_j^-1)`` (Eqs. 15-18) and the deviation metrics (Eqs. 20-21) are
recorded at every iteration.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from .. import lie
from ..arm import Arm, chain, module_poses
from .linear import min_norm_lstsq
from .model import NoiseModel, _stack, deviation_metrics, whitening
from .solution import RESULTS, CalibrationSolution
from .validation import check_problem


def calibrate_paper(
    arm: Arm,
    q: ArrayLike,
    measured: ArrayLike,
    noise: NoiseModel | None = None,
    *,
    max_iterations: int = 20,
    tol: float = 1e-10,
    rcond: float | None = None,
    allow_underdetermined: bool = False,
    throw: bool = True,
) -> CalibrationSolution:
    """Calibrate the fixed transforms of ``arm`` with the paper's iterative least squares.

    Args:
        arm: nominal model (its ``frames`` are the starting point and the reference of
            Eqs. 15-18).
        q: ``(m, dof)`` module states of the measured poses.
        measured: ``(m, 4, 4)`` measured tool poses in the world frame (mm).
        noise: optional :class:`NoiseModel`; ``None`` is the paper's unweighted form
            (solver ``"paper"``), otherwise the residual is whitened (solver ``"weighted"``).
        max_iterations: iteration cap (static).
        tol: stop once the step norm ``||X||`` (mm and rad mixed, as in the paper) is below it.
        rcond: relative singular-value cut-off of the least-squares step (see :mod:`.linear`).
        allow_underdetermined: accept fewer than 4 poses (the paper's lower bound); the step is
            then the minimum-norm one.
        throw: raise at run time when the result is not successful. Use ``throw=False`` under
            ``vmap`` and read ``result`` per trial.

    Returns:
        A :class:`CalibrationSolution`.
    """
    q, measured = check_problem(arm, q, measured, allow_underdetermined=allow_underdetermined)
    dtype = measured.dtype
    poses = module_poses(arm, q)
    G = whitening(measured, noise)
    n = arm.n_params
    k_frames = len(arm.frame_names)
    nan = jnp.asarray(jnp.nan, dtype)
    finite_in = jnp.all(jnp.isfinite(measured)) & jnp.all(jnp.isfinite(poses))

    def linearise(frames):
        tool, after = chain(frames, poses)
        Y, D = _stack(tool, after, measured, G)
        dp, dR = deviation_metrics(measured, tool)
        return Y, D, dp, dR

    def cond(carry):
        k, _, _, _, _, done, ok = carry
        return (k < max_iterations) & ~done & ok

    def body(carry):
        k, frames, steps, dps, dRs, _, _ = carry
        Y, D, dp, dR = linearise(frames)
        X, _, _ = min_norm_lstsq(D, Y, rcond)
        step = jnp.linalg.norm(X)
        ok = jnp.isfinite(step)
        frames = jnp.where(ok, lie.se3_exp(X.reshape(k_frames, 6)) @ frames, frames)
        return (
            k + 1,
            frames,
            steps.at[k].set(step),
            dps.at[k].set(dp),
            dRs.at[k].set(dR),
            step < tol,
            ok,
        )

    init = (
        jnp.asarray(0),
        jnp.asarray(arm.frames, dtype),
        jnp.full((max_iterations,), nan),
        jnp.full((max_iterations + 1,), nan),
        jnp.full((max_iterations + 1,), nan),
        jnp.asarray(False),
        finite_in,
    )
    k, frames, steps, dps, dRs, done, ok = jax.lax.while_loop(cond, body, init)
    Y, D, dp, dR = linearise(frames)
    _, rank, s = min_norm_lstsq(D, Y, rcond)
    dps = dps.at[k].set(dp)
    dRs = dRs.at[k].set(dR)
    ok = ok & jnp.isfinite(dp) & jnp.isfinite(dR)
    result = RESULTS.where(
        ok,
        RESULTS.where(done, RESULTS.successful, RESULTS.max_iterations_reached),
        RESULTS.nonfinite,
    )
    errors = lie.se3_log(frames @ lie.inverse(jnp.asarray(arm.frames, dtype)))
    sol = CalibrationSolution(
        frames=frames,
        errors=errors,
        result=result,
        iterations=k,
        step_norm=steps,
        delta_p=dps,
        delta_R=dRs,
        rank=rank,
        singular_values=jnp.pad(s, (0, max(0, n - s.shape[-1]))),
        cost=jnp.sum(Y * Y),
        solver="paper" if noise is None else "weighted",
    )
    if throw:
        sol = result.error_if(sol, result != RESULTS.successful)
    return sol
