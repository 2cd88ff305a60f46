"""Levenberg-Marquardt calibration on the same residual as the paper solver, jit- and vmap-able.

The parameters are the error twists ``X`` (Eq. 8) of all fixed transforms at once,
``F_j(X) = exp(hat(X_j)) F_j`` (Eqs. 11-14 in one step rather than accumulated), and the
residual is the (optionally whitened) stacked ``log(T_meas T(X)^-1)^v`` of Eq. 7. LM minimises
its exact sum of squares; the deviation metrics (Eqs. 20-21) are recorded at every step, as for
the paper solver.

The iteration is the damped Gauss-Newton method of Madsen, Nielsen and Tingleff (*Methods for
non-linear least squares problems*, 2004, Alg. 3.16): the step solves ``(J^T J + lambda I) du =
-J^T r``; a step that lowers the cost is taken and ``lambda`` shrinks by ``max(1/3, 1 - (2 rho -
1)^3)`` (``rho`` the actual over the predicted reduction), otherwise ``lambda`` grows by
``nu`` (doubling at each refusal in a row). ``lambda`` starts at ``tau max(diag(J^T J))`` with
``tau = 1e-6`` (:data:`INITIAL_DAMPING`), their choice for a start believed close to the
solution, as the nominal model is: the first step is a full Gauss-Newton step. The loop stops on
MINPACK-style tests of the next proposed step (:func:`_converged`), before evaluating it.

Scaling. The iteration works in whitened coordinates ``u`` of the identifiable subspace:
``X = V S^+ u`` from the SVD ``D~ = U S V^T`` of the stacked Jacobian at the nominal model
(Eq. 9, the same rank cut-off ``rcond`` as the paper solver). ``J^T J`` in ``u`` is then close
to the identity, so a damping ``lambda I`` is well scaled (mm and rad columns differ by the
lever arm, hundreds of mm, and by the weights), and the unidentifiable directions (the CDRA's
two, see :mod:`cdra_jax.identifiability`) have exactly zero columns: they are never moved. In
float64 (default ``rcond``, more than ``1.5 n`` rows: :func:`.linear.normal_equations_apply`) the
basis is taken from the normal equations and the structural null space of ``D`` known in closed
form (:mod:`.nullspace`), instead of an SVD: ``B = W S L^-T`` with ``W`` the orthonormal
complement of the null basis and ``L`` the plain Cholesky factor of the Jacobi-scaled ``W^T D~^T
D~ W`` (:func:`.linear.null_space_basis`), which spans the same subspace with ``D~ B``
orthonormal (an orthogonal change of the coordinates ``u``; the steps are invariant under it,
the max-norm stopping tests to rounding). As for the paper solver's steps, a trial whose data
lose more directions than the structural ones (the Cholesky factor's eigenvalue bound below
:data:`.linear.RESOLVED_PIVOT`) does not iterate and is solved again with the SVD basis, the
trials to redo gathered into chunks of their own.

The step. ``J = -G J_r^-1(r) D diag(J_l(X_j))`` in closed form (:func:`.kernels.residual_jacobian`,
checked against ``jax.jacfwd``), and its normal equations are assembled, as the paper solver's
(:func:`.kernels.normal_equations`), from the rows of ``J`` that are not zero
(:func:`.kernels.lm_normal_equations`): ``J`` itself is never formed. ``J^T J`` in ``u`` is
``B^T (J^T J) B``; the damped system is solved by Cholesky.

Not through optimistix (:func:`.optimistix_lm.calibrate_lm_optimistix` is that solver, kept
as the reference this one is tested against). Its least-squares solvers
(``optimistix.LevenbergMarquardt``) take every step from the Jacobian operator that they
build by linearising the residual
(``jax.linearize``); the API has no entry for normal equations computed otherwise. Each step
there materialises ``J B`` (a product with the identity), forms the normal equations of the
damped augmented ``(6m + n, n)`` system, and carries its whole state through its branches:
with the same basis, residual and analytic Jacobian, the optimistix solve took 2.4x the time
of this one and 1.1x its compile time (15 CDRA poses, 4096 trials, interleaved in one
process). Its minimisers that accept a Hessian (the quasi-Newton family) take the gradient by
autodiff and give the Hessian update no access to the residual's auxiliary output, so the
model would be evaluated twice per step.

Fixed point. LM minimises the exact sum of squares of Eq. 7's residual; the paper's iteration
uses the first-order Jacobian ``D`` of Eq. 8, which omits the derivative of the logarithm
(``J_r^-1(Y)``, identity at ``Y = 0``). Noise-free, both reach ``Y = 0``; with noise the
paper's fixed point solves ``D^T Y = 0`` and sits a second-order distance from the
least-squares minimum (for the CDRA at 80 um / 1e-3 rad, 15 poses: base and tool errors
differ by a median 3e-5, whitened cost lower for LM by ~4e-6).

Under ``vmap`` the trials run in chunks, the loop written at the level of the chunk
(:func:`.batching.chunked_loop`, as the paper solver's): a chunk stops once all but a few of
its trials have converged, and those are solved again in chunks of their own.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from .. import lie
from ..arm import Arm
from . import kernels
from .batching import chunked_loop
from .linear import (
    RESOLVED_PIVOT,
    STRUCTURAL_TOL,
    default_rcond,
    normal_equations_apply,
    null_space_basis,
)
from .model import NoiseModel
from .nullspace import null_basis, null_generators
from .solution import (
    RESULTS,
    CalibrationSolution,
    _finished_solution,
    _solve_problem,
    dtype_default,
)

CHUNK_SIZE = 32
"""Trials per chunk when the solver is vmapped (see :mod:`.batching` and
:data:`.gauss_newton.CHUNK_SIZE`)."""

STRAGGLERS = 16
"""A chunk of the first pass stops once at most ``1 / STRAGGLERS`` of its trials still step
(see :func:`.batching.chunked_loop`)."""

_FAST, _CONTINUE, _SVD = 0, 1, 2
"""The passes of a batched solve: the basis from the normal equations with stragglers handed
on, the same to the end, the SVD basis."""

RTOL_FLOAT64 = ATOL_FLOAT64 = 1e-12
"""Default ``rtol`` and ``atol`` of a float64 solve."""

RTOL_FLOAT32 = 1e-6
ATOL_FLOAT32 = 1e-3
"""Default ``rtol`` and ``atol`` of a float32 solve. With 1e-12 a float32 solve reaches its
rounding floor in a few steps and then spends tens more on rejected steps until the damping
is high enough for the tests of :func:`_converged` to fire (15-pose CDRA, 200 trials per
case, noise-free and 80 um / 1e-3 rad, unweighted and weighted: median 29-31 steps against
4-9 in float64, and up to 17 % of the trials ``max_iterations_reached`` at 50). ``atol`` is in
the units of the rescaled residual (mm unweighted, standard deviations with a noise model):
1e-4 still stalled (median 15 and 21 steps noise-free), 1e-2 stopped a noise-free trial at
0.38 mm; 1e-3 with ``rtol = 1e-6`` takes a median 4-7 steps and ends as accurate as the
1e-12 runs (final ``delta_p`` noise-free: median 3.1e-4 against 5.1e-4 mm unweighted, 5.7e-5
against 5.2e-5 mm weighted; with noise the same deviations to 1 %)."""

INITIAL_DAMPING = 1e-6
"""Initial Levenberg-Marquardt damping relative to ``max(diag(J^T J))`` (= 1 in the rescaled
coordinates; see the module docstring)."""

MAX_DAMPING_GROWTH = 2.0**30
"""Cap of the damping's growth factor ``nu`` (it doubles at every refused step in a row)."""


def calibrate_lm(
    arm: Arm,
    q: ArrayLike,
    measured: ArrayLike,
    noise: NoiseModel | None = None,
    *,
    max_iterations: int = 50,
    rtol: float | None = None,
    atol: float | None = None,
    rcond: float | None = None,
    allow_underdetermined: bool = False,
    throw: bool = True,
    singular_values: bool = False,
) -> CalibrationSolution:
    """Calibrate the fixed transforms of ``arm`` by Levenberg-Marquardt (module docstring).

    Arguments as :func:`cdra_jax.calibration.calibrate_paper`; ``rtol``/``atol`` are the step
    and cost tolerances of :func:`_converged` (``None``: 1e-12 each for float64 problems; 1e-6
    and 1e-3 for float32 ones, :data:`RTOL_FLOAT32`, :data:`ATOL_FLOAT32`) and
    ``max_iterations`` caps the steps tried, taken or refused. ``iterations`` counts them; the
    ``step_norm`` history holds ``||X_k - X_{k-1}||`` (zero for refused steps). The
    unidentifiable directions of the nominal linearisation (rank cut-off ``rcond``) are left
    at zero, as the paper solver's minimum-norm steps do to first order. Differentiable like
    :func:`calibrate_paper`, through the condition ``J^T Y~ = 0`` (:mod:`.implicit`).
    ``singular_values=True`` also computes the singular values of ``D~`` at the solution (a QR
    and an SVD, once) and reports their rank; by default the rank is that of the identifiable
    basis and the singular values are NaN, as for :func:`calibrate_paper`.
    """
    null_modules, _ = null_generators(arm)

    def make_solver(dtype):
        return _lm_solver(
            max_iterations=max_iterations,
            rtol=dtype_default(rtol, dtype, float64=RTOL_FLOAT64, float32=RTOL_FLOAT32),
            atol=dtype_default(atol, dtype, float64=ATOL_FLOAT64, float32=ATOL_FLOAT32),
            rcond=rcond,
            weighted=noise is not None,
            null_modules=null_modules,
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
        extra=lambda dtype: (null_generators(arm, dtype)[1],),
    )


def _lm_solver(
    *, max_iterations, rtol, atol, rcond, weighted, null_modules=(), singular_values=False
):
    """The per-trial LM solver for one static configuration, chunked under ``vmap``
    (:func:`.batching.chunked_loop`; passes as the paper solver's)."""
    n_null = len(null_modules)

    def init(mode, frames0, poses, measured, xi, *noise_std):
        """A trial's start: nothing evaluated yet (the first pass of the loop evaluates the
        nominal model and takes the identifiable basis there)."""
        dtype = measured.dtype
        noise = NoiseModel(*noise_std) if weighted else None
        P = jnp.moveaxis(poses[..., :3, :], 0, -1)  # (K, 3, 4, m)
        T = kernels.pose_stack(measured)
        n = 6 * frames0.shape[0]
        finite_in = jnp.all(jnp.isfinite(measured)) & jnp.all(jnp.isfinite(poses))
        nan = jnp.asarray(jnp.nan, dtype)
        zero = jnp.zeros((), dtype)
        state = (
            jnp.asarray(0, jnp.int32),  # steps tried
            jnp.zeros(n, dtype),  # u
            frames0,  # the frames at u
            (zero, jnp.zeros((n, n), dtype), jnp.zeros(n, dtype)),  # |r~|^2, N_u, g_u at u
            (zero, jnp.asarray(2.0, dtype)),  # lambda, nu
            (jnp.eye(n, dtype=dtype), jnp.asarray(n), jnp.asarray(True)),  # basis, rank, ok
            jnp.full((max_iterations,), nan),
            jnp.full((max_iterations + 1,), nan),
            jnp.full((max_iterations + 1,), nan),
            jnp.asarray(False),  # converged
            finite_in,  # ok
        )
        return state, (frames0, P, T, xi, noise)

    def running(state):
        k, *_, (_, _, resolved), _, _, _, done, ok = state
        return (k < max_iterations) & ~done & ok & resolved

    def basis_at(mode, frames0, after, Yw, T, xi, noise):
        """``X = basis @ u``: whitened coordinates of the identifiable subspace of ``D~`` at the
        nominal model (module docstring); ``(basis, rank, resolved)``. From the normal
        equations and the structural null space (fast) unless in the SVD pass (a real branch)
        or the fast basis does not apply."""
        n = 6 * frames0.shape[0]
        dtype = T.dtype

        def svd_basis():
            DT = kernels.jacobian_transposed(after, T, noise)
            lin = kernels.Linearisation(Y=Yw.reshape(-1), DT=DT, delta_p=Yw[0, 0], delta_R=Yw[0, 0])
            basis = _identifiable_basis(lin, rcond)
            return basis, jnp.sum(jnp.any(basis != 0, axis=0)), jnp.asarray(True)

        def normal_basis():
            N, _ = kernels.normal_equations(after, Yw, T, noise)
            Z = null_basis(frames0, null_modules, xi)
            basis, smallest, structural = null_space_basis(N, Z)
            trusted = (smallest >= RESOLVED_PIVOT) & (structural <= STRUCTURAL_TOL)
            trusted = trusted & jnp.all(jnp.isfinite(basis))
            # An untrusted basis (the trial is redone with the SVD basis): a finite one.
            basis = jnp.where(trusted, basis, jnp.eye(n, dtype=dtype))
            return basis, jnp.asarray(n - n_null), trusted

        if normal_equations_apply(dtype, rcond, Yw.size, n):
            return jax.lax.cond(mode == _SVD, svd_basis, normal_basis)
        return svd_basis()

    def body(it, mode, step, state, data):
        """One damped step where the trial still runs; the chunk's first pass (``it == 0``,
        always taken) evaluates the nominal model instead and takes the basis there (``it``,
        ``mode`` and ``step`` are the chunk's: real branches; a later pass without a step has
        nothing left to evaluate)."""
        return jax.lax.cond(step | (it == 0), lambda: _step(it, mode, state, data), lambda: state)

    def _step(it, mode, state, data):
        k, u, frames, (cost, N, g), (damping, nu), bases, steps, dps, dRs, done, ok = state
        frames0, P, T, xi, noise = data
        first = it == 0
        stepping = running(state)
        n = u.shape[0]
        A = N + jnp.where(first, 1.0, damping) * jnp.eye(n, dtype=N.dtype)
        du = -jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(A), True), g)
        du = jnp.where(first, 0.0, du)
        predicted = -(jnp.dot(g, du) + 0.5 * jnp.dot(du, N @ du))  # of cost / 2
        converged = _converged(du, u, predicted, cost, rtol, atol) & ~first
        trying = stepping & ~converged
        # The model at u + du (the one place it is evaluated).
        basis = bases[0]
        X = basis @ (u + du)
        frames_t = kernels.left_multiply(lie.se3_exp(X.reshape(frames0.shape[0], 6)), frames0)
        tool, after = kernels.chain(frames_t, P)
        r, dp, dR = kernels.residual_and_metrics(T, tool)
        Yw = r if noise is None else kernels.whiten(r, T, noise)
        bases = jax.lax.cond(
            first, lambda: basis_at(mode, frames0, after, Yw, T, xi, noise), lambda: bases
        )
        basis = bases[0]
        N_t, g_t, _ = kernels.lm_normal_equations(X, after, r, T, noise, basis)
        cost_t = jnp.sum(Yw * Yw)
        rho = (0.5 * (cost - cost_t)) / predicted
        take = first | (trying & (rho > 0) & jnp.isfinite(cost_t))
        shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
        damping_t = jnp.where(take, damping * shrink, damping * nu)
        damping_t = jnp.where(first, INITIAL_DAMPING * jnp.max(jnp.diagonal(N_t)), damping_t)
        nu_t = jnp.where(take, 2.0, jnp.minimum(2.0 * nu, MAX_DAMPING_GROWTH))
        counted = trying & ~first

        def pick(new, old):
            return jax.tree.map(lambda a, b: jnp.where(take, a, b), new, old)

        moved = jnp.linalg.norm(basis @ du)
        at = jnp.where(first, 0, k + 1)  # Eqs. 20-21 of the nominal model, or after step k
        return (
            k + counted,
            pick(u + du, u),
            pick(frames_t, frames),
            pick((cost_t, N_t, g_t), (cost, N, g)),
            jax.tree.map(lambda a, b: jnp.where(trying, a, b), (damping_t, nu_t), (damping, nu)),
            bases,
            jnp.where(counted, steps.at[k].set(jnp.where(take, moved, 0.0)), steps),
            jnp.where(trying, dps.at[at].set(jnp.where(take, dp, dps[k])), dps),
            jnp.where(trying, dRs.at[at].set(jnp.where(take, dR, dRs[k])), dRs),
            done | (stepping & converged),
            ok & jnp.all(jnp.isfinite(pick(u + du, u))) & (jnp.isfinite(cost_t) | ~first),
        )

    def finish(mode, state, data):
        """The solution of one trial, and whether it is to be redone with the SVD basis (where
        the fast basis is not resolved, or its rank is not that of the singular values)."""
        k, _, frames, (cost, _, _), _, (_, basis_rank, resolved), steps, dps, dRs, done, ok = state
        frames0, P, T, _, noise = data
        dtype = T.dtype
        n = 6 * frames0.shape[0]
        sol = _finished_solution(
            frames,
            frames0,
            P,
            T,
            noise,
            singular_values=singular_values,
            rcond=rcond,
            rank=basis_rank,
            iterations=k,
            step_norm=steps,
            delta_p=dps,
            delta_R=dRs,
            cost=cost,
            done=done,
            ok=ok,
            solver="lm",
        )
        rank = sol.rank
        fast = normal_equations_apply(dtype, rcond, 6 * T.shape[-1], n)
        redo = (sol.result != RESULTS.nonfinite) & fast & (mode != _SVD)
        redo = redo & ((basis_rank != rank) | ~resolved)
        return sol, jnp.where(redo, _SVD, 0)

    return chunked_loop(
        init,
        body,
        running,
        finish,
        chunk_size=CHUNK_SIZE,
        passes=3,
        stragglers=STRAGGLERS,
    )


def _identifiable_basis(lin: kernels.Linearisation, rcond: float | None) -> Array:
    """``(n, r)`` map ``X = B u`` onto the identifiable subspace at the nominal model.

    ``B = V S^+`` from the thin SVD of the (whitened) stacked Jacobian ``D~ = U S V^T`` (Eq. 9,
    held transposed by ``lin``, so that ``V`` is the left factor of ``D~^T``): the columns are
    the right singular vectors divided by their singular values, and zero for singular values
    below ``rcond * s_max``, so that ``D~ B`` has orthonormal (or zero) columns.
    ``r = min(6 m, n)``.

    ``V`` and ``S`` are taken from the SVD of the ``(n, n)`` triangular factor ``R`` of the
    QR decomposition ``D~ = Q R`` (Householder, backward stable): ``R = U_R S V^T``, so that
    ``D~ = (Q U_R) S V^T``. That costs about 0.7 of the SVD of the ``(6m, n)`` matrix itself
    (15 CDRA poses: 118 against 161 us per trial, batched), as for the reported singular values
    (:func:`.solution._singular_values`).
    """
    A = lin.DT.T
    if A.shape[-2] > A.shape[-1]:
        A = jnp.linalg.qr(A, mode="r")
    _, s, Vt = jnp.linalg.svd(A, full_matrices=False)
    V = jnp.swapaxes(Vt, -1, -2)
    rcond = default_rcond(lin.DT.dtype) if rcond is None else rcond
    keep = s > rcond * s[..., :1]
    scale = jnp.where(keep, 1.0 / jnp.where(keep, s, 1.0), 0.0)
    return V * scale


def _converged(step, u, predicted, cost, rtol, atol):
    """MINPACK-style tests on the *next* proposed step, before it is evaluated.

    Near the optimum the gain ratio compares changes of the cost at its rounding level
    (noise-free data) or far below any meaningful size (noisy data), so further steps would be
    refused and the damping raised step after step: wasted steps, and a count that depends on
    rounding. So stop when the next step

    * cannot move ``u`` by more than ``atol + rtol |u|`` (``xtol``, in the max norm), or
    * is predicted to lower the cost ``0.5 |r|^2`` by at most ``rtol * 0.5 |r|^2 + 0.5 atol^2``
      (``ftol``; ``predicted``: the linear model's reduction ``-(g . du + 0.5 du^T N du)``).
    """
    small_step = jnp.max(jnp.abs(step) / (atol + rtol * jnp.abs(u))) < 1
    no_progress = predicted <= rtol * 0.5 * cost + 0.5 * atol * atol
    return small_step | no_progress
