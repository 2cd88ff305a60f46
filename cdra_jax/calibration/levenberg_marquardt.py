"""Levenberg-Marquardt calibration with optimistix on the same residual as the paper solver.

The parameters are the error twists ``X`` (Eq. 8) of all fixed transforms at once,
``F_j(X) = exp(hat(X_j)) F_j`` (Eqs. 11-14 in one step rather than accumulated), and the
residual is the (optionally whitened) stacked ``log(T_meas T(X)^-1)^v`` of Eq. 7. The Jacobian
comes from autodiff. The loop drives ``optimistix.LevenbergMarquardt`` step by step so that the
deviation metrics (Eqs. 20-21) are recorded at every step, as for the paper solver.

Scaling. The optimiser works in whitened coordinates ``u`` of the identifiable subspace:
``X = V S^+ u`` from the SVD ``D~ = U S V^T`` of the stacked Jacobian at the nominal model
(Eq. 9, the same rank cut-off ``rcond`` as the paper solver). The Jacobian in ``u`` is then
close to orthonormal, so the trust region is well scaled (mm and rad columns differ by the
lever arm, hundreds of mm, and by the weights), and the unidentifiable directions (the CDRA's
two, see :mod:`cdra_jax.identifiability`) have exactly zero columns: they are never moved
and the damped steps never wander along them on rounding noise. Without this the unscaled
damped steps at the rounding floor are mostly rejected and the solve needs tens of extra steps.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax.typing import ArrayLike

from .. import lie
from ..arm import Arm, chain, module_poses
from .linear import default_rcond, min_norm_lstsq
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
    ``step_norm`` history holds ``||X_k - X_{k-1}||`` (zero for rejected steps). The
    unidentifiable directions of the nominal linearisation (rank cut-off ``rcond``) are left
    at zero, as the paper solver's minimum-norm steps do to first order.
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
    # X = basis @ u: whitened coordinates of the identifiable subspace (module docstring).
    basis = _identifiable_basis(frames0, poses, measured, G, rcond)

    def frames_of(X):
        return lie.se3_exp(X.reshape(k_frames, 6)) @ frames0

    def fn(u, _):
        tool, after = chain(frames_of(basis @ u), poses)
        Y, _ = _stack(tool, after, measured, G)
        return Y, None  # optimistix' internal step API expects (out, aux)

    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    y0 = jnp.zeros(basis.shape[-1], dtype)
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
        k, u, dyn_state, steps, dps, dRs, _, _ = carry
        dp, dR = metrics(basis @ u)
        state = eqx.combine(static_state, dyn_state)
        u_new, state, _ = solver.step(fn, u, None, options, state, tags)
        done, _ = solver.terminate(fn, u, None, options, state, tags)
        done = done | _converged(state.y_eval - u_new, u_new, state.f_info, rtol, atol)
        dyn_state, _ = eqx.partition(state, eqx.is_array)
        step = jnp.linalg.norm(basis @ (u_new - u))
        ok = jnp.all(jnp.isfinite(u_new))
        return (
            k + 1,
            u_new,
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
    k, u, _, steps, dps, dRs, done, ok = jax.lax.while_loop(cond, body, init)
    frames = frames_of(basis @ u)
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


def _identifiable_basis(frames, poses, measured, G, rcond):
    """``(n, r)`` map ``X = B u`` onto the identifiable subspace at the nominal model.

    ``B = V S^+`` from the thin SVD of the (whitened) stacked Jacobian ``D~`` (Eq. 9): the
    columns are the right singular vectors divided by their singular values, and zero for
    singular values below ``rcond * s_max``, so that ``D~ B`` has orthonormal (or zero) columns.
    ``r = min(6 m, n)``.
    """
    tool, after = chain(frames, poses)
    _, D = _stack(tool, after, measured, G)
    _, s, Vt = jnp.linalg.svd(D, full_matrices=False)
    rcond = default_rcond(D.dtype) if rcond is None else rcond
    keep = s > rcond * s[..., :1]
    scale = jnp.where(keep, 1.0 / jnp.where(keep, s, 1.0), 0.0)
    return jnp.swapaxes(Vt, -1, -2) * scale


def _converged(proposal, y, f_info, rtol, atol):
    """MINPACK-style tests on the *next* proposed step, accepted or not.

    optimistix tests for convergence only after an accepted step, and only on the change of
    ``y`` and of the residual. Near the optimum the trust-region ratio test compares changes of
    the cost at its rounding level (noise-free data) or far below any meaningful size (noisy
    data), so most further steps are rejected and the damping is raised step after step before
    optimistix' test can fire: tens of wasted steps, and a count that depends on rounding. So
    also stop when the next step

    * cannot move ``y`` by more than ``atol + rtol |y|`` (``xtol``; optimistix' max norm), or
    * is predicted to lower the cost ``0.5 |r|^2`` by at most ``rtol * cost + 0.5 atol^2``
      (``ftol``; the linear model's reduction ``-(r . J dy + 0.5 |J dy|^2)``, computed
      without cancellation).
    """
    small_step = jnp.max(jnp.abs(proposal) / (atol + rtol * jnp.abs(y))) < 1
    r = f_info.residual
    Jd = f_info.jac.mv(proposal)
    predicted = -(jnp.sum(r * Jd) + 0.5 * jnp.sum(Jd * Jd))
    cost = 0.5 * jnp.sum(r * r)
    no_progress = predicted <= rtol * cost + 0.5 * atol * atol
    return small_step | no_progress
