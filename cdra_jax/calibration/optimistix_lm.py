"""Levenberg-Marquardt through optimistix: an independent solver of the same problem.

:func:`calibrate_lm_optimistix` minimises the same sum of squares as
:func:`cdra_jax.calibration.calibrate_lm` (Eq. 7's residual ``log(T_meas T(X)^-1)^v``,
optionally whitened, over the error twists ``X`` of Eq. 8) with ``optimistix.least_squares``
and ``optimistix.LevenbergMarquardt``, in the same coordinates: ``X = B u`` with ``B = V S^+``
from the SVD of the stacked Jacobian ``D~`` at the nominal model (Eq. 9), so that the damping
is well scaled and the unidentifiable directions are never moved. The residual's Jacobian is
the analytic one (:func:`.kernels.residual_jacobian`, a ``jax.custom_jvp`` in ``u``); the damped
normal equations are solved by lineax (``lineax.Normal(lineax.Cholesky())``).

It is the reference the fast solver is checked against (the test suite compares their frames)
and the entry point for optimistix' other least-squares solvers. It is a plain ``vmap`` of one
trial: no chunking, no analytic null space, and optimistix' own stopping rule (after an
accepted step, on the change of ``u`` and of the residual), so it takes more steps and more time
than :func:`calibrate_lm` (``benchmarks/throughput.py --solvers lm_optimistix``). The step and
deviation histories hold the nominal model (entry 0) and the solution (entry ``iterations``)
only, the entries between and the step norms are NaN (optimistix does not expose its
iterates).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jax.typing import ArrayLike

from ..arm import Arm, module_poses
from . import kernels
from .levenberg_marquardt import _identifiable_basis
from .model import NoiseModel
from .solution import CalibrationSolution, _finished_solution, _solve_problem, dtype_default

RTOL_FLOAT64 = ATOL_FLOAT64 = 1e-10
"""Default ``rtol`` and ``atol`` of a float64 solve (optimistix' tests on the change of ``u``
and of the residual, in the units of the rescaled residual: mm unweighted, standard deviations
with a noise model)."""

RTOL_FLOAT32 = 1e-5
ATOL_FLOAT32 = 1e-3
"""Default ``rtol`` and ``atol`` of a float32 solve."""


def calibrate_lm_optimistix(
    arm: Arm,
    q: ArrayLike,
    measured: ArrayLike,
    noise: NoiseModel | None = None,
    *,
    max_iterations: int = 100,
    rtol: float | None = None,
    atol: float | None = None,
    rcond: float | None = None,
    allow_underdetermined: bool = False,
    throw: bool = True,
    singular_values: bool = False,
) -> CalibrationSolution:
    """Calibrate the fixed transforms of ``arm`` with ``optimistix.LevenbergMarquardt``.

    Arguments as :func:`cdra_jax.calibration.calibrate_lm`: ``arm`` the nominal model,
    ``q (m, n_joints)`` joint states, ``measured (m, 4, 4)`` tool poses in the base frame (mm),
    ``noise`` whitens the residual; ``rtol``/``atol`` are optimistix' tolerances (``None``:
    :data:`RTOL_FLOAT64`, :data:`ATOL_FLOAT64`, or the float32 ones) and ``max_iterations``
    its ``max_steps``. Under ``jax.vmap`` each trial has its own result code; use
    ``throw=False`` there. Differentiable like :func:`calibrate_lm` (its optimality condition,
    :mod:`.implicit`).

    Returns:
        A :class:`.CalibrationSolution` with ``solver == "lm_optimistix"``; ``iterations`` is
        optimistix' step count (accepted and rejected).
    """

    def make_solver(dtype):
        return _optimistix_solver(
            arm,
            max_iterations=max_iterations,
            rtol=dtype_default(rtol, dtype, float64=RTOL_FLOAT64, float32=RTOL_FLOAT32),
            atol=dtype_default(atol, dtype, float64=ATOL_FLOAT64, float32=ATOL_FLOAT32),
            rcond=rcond,
            weighted=noise is not None,
            singular_values=singular_values,
        )

    return _solve_problem(
        make_solver,
        arm,
        q,
        measured,
        noise,
        allow_underdetermined=allow_underdetermined,
        throw=throw,
    )


def _optimistix_solver(arm, *, max_iterations, rtol, atol, rcond, weighted, singular_values):
    """The per-trial solver for one static configuration (``vmap`` batches it as it is);
    ``arm`` gives the module structure that turns the states ``q`` into module poses (its
    arrays come as arguments)."""
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=lx.Normal(lx.Cholesky()))

    def run(frames0, q, measured, axes, *noise_std):
        dtype = measured.dtype
        noise = NoiseModel(*noise_std) if weighted else None
        poses = module_poses(arm, q, axes)  # (m, K, 4, 4)
        P = jnp.moveaxis(poses[..., :3, :], 0, -1)  # (K, 3, 4, m)
        T = kernels.pose_stack(measured)  # (3, 4, m)
        nominal = kernels.linearise(frames0, P, T, noise)  # Eq. 9 and Eqs. 20-21 at F_0
        basis = _identifiable_basis(nominal, rcond)

        def frames_at(u):
            return kernels.step_frames(basis @ u, frames0)

        def residual_and_metrics(frames):
            """The (whitened) residual ``(6, m)`` of Eq. 7 and Eqs. 20-21 at ``frames``."""
            tool, _ = kernels.chain(frames, P)
            r, dp, dR = kernels.residual_and_metrics(T, tool)
            return (r if noise is None else kernels.whiten(r, T, noise)), dp, dR

        @jax.custom_jvp
        def residual(u):
            return residual_and_metrics(frames_at(u))[0].reshape(-1)

        @residual.defjvp
        def _jvp(primals, tangents):
            (u,), (du,) = primals, tangents
            r, _, J = kernels.residual_jacobian(basis @ u, frames0, P, T, noise)
            return r, (J @ basis) @ du

        u0 = jnp.zeros(basis.shape[-1], dtype)
        found = optx.least_squares(
            lambda u, _: residual(u), solver, u0, max_steps=max_iterations, throw=False
        )
        frames = frames_at(found.value)
        r, dp, dR = residual_and_metrics(frames)
        dp0, dR0 = nominal.delta_p, nominal.delta_R
        k = jnp.asarray(found.stats["num_steps"], jnp.int32)
        nan = jnp.full((max_iterations + 1,), jnp.nan, dtype)
        finite = jnp.all(jnp.isfinite(measured)) & jnp.all(jnp.isfinite(poses))
        return _finished_solution(
            frames,
            frames0,
            P,
            T,
            noise,
            singular_values=singular_values,
            rcond=rcond,
            rank=jnp.sum(jnp.any(basis != 0, axis=0)),
            iterations=k,
            step_norm=nan[1:],
            delta_p=nan.at[0].set(dp0).at[k].set(dp),
            delta_R=nan.at[0].set(dR0).at[k].set(dR),
            cost=jnp.sum(r * r),
            done=found.result == optx.RESULTS.successful,
            ok=finite & jnp.all(jnp.isfinite(found.value)),
            solver="lm_optimistix",
        )

    return run
