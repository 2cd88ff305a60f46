"""Levenberg-Marquardt calibration with optimistix on the same residual as the paper solver.

The parameters are the error twists ``X`` (Eq. 8) of all fixed transforms at once,
``F_j(X) = exp(hat(X_j)) F_j`` (Eqs. 11-14 in one step rather than accumulated), and the
residual is the (optionally whitened) stacked ``log(T_meas T(X)^-1)^v`` of Eq. 7. The loop
drives ``optimistix.LevenbergMarquardt`` step by step so that the deviation metrics
(Eqs. 20-21) are recorded at every step, as for the paper solver.

Scaling. The optimiser works in whitened coordinates ``u`` of the identifiable subspace:
``X = V S^+ u`` from the SVD ``D~ = U S V^T`` of the stacked Jacobian at the nominal model
(Eq. 9, the same rank cut-off ``rcond`` as the paper solver). The Jacobian in ``u`` is then
close to orthonormal, so the trust region is well scaled (mm and rad columns differ by the
lever arm, hundreds of mm, and by the weights), and the unidentifiable directions (the CDRA's
two, see :mod:`cdra_jax.identifiability`) have exactly zero columns: they are never moved
and the damped steps never wander along them on rounding noise. Without this the unscaled
damped steps at the rounding floor are mostly rejected and the solve needs tens of extra steps.
Besides optimistix' own termination the loop stops on MINPACK-style tests of the next
proposed step (:func:`_converged`).

In float64 (default ``rcond``, more than ``1.5 n`` rows:
:func:`.linear.normal_equations_apply`) the basis is taken from the normal equations and the
structural null space of ``D`` known in closed form (:mod:`.nullspace`), instead of an SVD:
``B = W S L^-T`` with ``W`` the orthonormal complement of the null basis and ``L`` the plain
Cholesky factor of the Jacobi-scaled ``W^T D~^T D~ W`` (:func:`.linear.null_space_basis`),
which spans the same subspace with ``D~ B`` orthonormal, an orthogonal change of the
coordinates ``u`` (LM's steps are invariant under it, its max-norm stopping tests to
rounding). As for the paper solver's steps, a trial whose data lose more directions than the
structural ones (the Cholesky factor's eigenvalue bound below :data:`.linear.RESOLVED_PIVOT`)
does not iterate and is solved again with the SVD basis, the trials to redo gathered into
chunks of their own (:func:`.batching.two_pass`). The analytic null space enters LM through
this basis and not through its steps: optimistix' damped step ``(J^T J + lambda I) du = -J^T r``
is already positive definite in ``u`` (the null directions' columns of ``J B`` are zero, so
only the damping acts on them and they never move), and its linear solve (``lineax``, a
24 x 24 Cholesky for the CDRA) is a small part of an LM step,
whose cost is the exact Jacobian (the SE(3) left and right Jacobians per pose) and optimistix'
trust-region bookkeeping.

Damping. optimistix starts its trust region at a step size of 1, i.e. a damping
``lambda = 1`` on ``J^T J``, which in the rescaled coordinates (``J^T J ~= I``) halves the
first Gauss-Newton step and costs about four extra steps before the region has grown. The
solver starts at ``lambda = tau max(diag(J^T J)) = tau`` with ``tau = 1e-6``
(:data:`INITIAL_DAMPING`), the choice of Madsen, Nielsen and Tingleff (*Methods for
non-linear least squares problems*, 2004, Sec. 3.2) for a starting point believed close to
the solution, as the nominal model is; the ratio test still shrinks the region wherever a
step fails to lower the cost. The damped step ``(J^T J + lambda I) du = -J^T r`` is solved
from the normal equations by Cholesky (``lineax.Normal(lineax.Cholesky())``): with the
columns of ``J`` near-orthonormal the normal equations lose nothing, and they cost a fraction
of optimistix' default QR of the augmented ``(6m + r, r)`` system.

Fixed point. LM minimises the exact sum of squares of Eq. 7's residual; the paper's iteration
uses the first-order Jacobian ``D`` of Eq. 8, which omits the derivative of the logarithm
(``J_r^-1(Y)``, identity at ``Y = 0``). Noise-free, both reach ``Y = 0``; with noise the
paper's fixed point solves ``D^T Y = 0`` and sits a second-order distance from the
least-squares minimum (for the CDRA at 80 um / 1e-3 rad, 15 poses: base and tool errors
differ by a median 3e-5, whitened cost lower for LM by ~4e-6).

Performance (see ``benchmarks/README.md``):

* the residual is evaluated in the pose-last layout of :mod:`.kernels`, and returns the
  deviation metrics of its point as optimistix' ``aux``, so that recording them costs nothing;
* its Jacobian is analytic (:func:`.kernels.residual_jacobian`, a ``jax.custom_jvp`` in ``u``):
  optimistix linearises the residual at every step and its QR solver materialises the
  Jacobian, which with autodiff costs one forward-mode pass through the chain and the
  logarithm per column and here two small matrix products;
* the residual and its Jacobian are traced once per solver trace (``jit`` with
  ``inline=True``; optimistix uses them in ``init`` and ``step``), and the nominal and the final
  model are linearised through one call site (two passes of a ``scan``), so that XLA compiles
  the model once there;
* under ``vmap`` the trials run in chunks (:func:`.batching.chunked_vmap`). (A work queue
  that refills the slot of a finished trial was tried and dropped: with the rescaled subspace
  and the stop tests above the iteration counts are uniform, 8 to 14 for the CDRA with noise,
  and the queue was slower, and it deadlocked under ``jit`` with the batch sharded over two
  CPU devices.)
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jax import Array
from jax.typing import ArrayLike

from .. import lie
from ..arm import Arm
from . import kernels
from .batching import batched_like, chunked_vmap
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
    _solution_at,
    _solve_problem,
    dtype_default,
)

CHUNK_SIZE = 128
"""Trials per chunk when the solver is vmapped (see :mod:`.batching`)."""

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
    singular_values: bool = True,
) -> CalibrationSolution:
    """Calibrate the fixed transforms of ``arm`` with optimistix's Levenberg-Marquardt.

    Arguments as :func:`cdra_jax.calibration.calibrate_paper`; ``rtol``/``atol`` are the
    optimistix step and cost tolerances (``None``: 1e-12 each for float64 problems; 1e-6 and
    1e-3 for float32 ones, :data:`RTOL_FLOAT32`, :data:`ATOL_FLOAT32`) and ``max_iterations``
    its ``max_steps``. The
    ``step_norm`` history holds ``||X_k - X_{k-1}||`` (zero for rejected steps). The
    unidentifiable directions of the nominal linearisation (rank cut-off ``rcond``) are left
    at zero, as the paper solver's minimum-norm steps do to first order. Differentiable like
    :func:`calibrate_paper`, through the condition ``J^T Y~ = 0`` (:mod:`.implicit`).
    ``singular_values=False`` skips the final QR and SVD as for :func:`calibrate_paper` (the
    rank is then that of the identifiable basis).
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


def _residual(
    X: Array, frames0: Array, poses: Array, measured: Array, noise: NoiseModel | None
) -> tuple[Array, tuple[Array, Array]]:
    """The residual and deviation metrics of :func:`.kernels.residual_jacobian`, without its
    Jacobian.

    The primal of the ``custom_jvp`` in :func:`_residual_fn`: JAX traces it next to the JVP
    rule, so keeping it free of the Jacobian's operations shortens the tracing.
    """
    frames = lie.se3_exp(X.reshape(frames0.shape[0], 6)) @ frames0
    tool, _ = kernels.chain(frames, poses)
    r, dp, dR = kernels.residual_and_metrics(measured, tool)  # r: (6, m), one logarithm
    if noise is not None:
        r = kernels.whiten(r, measured, noise)
    return r.reshape(-1), (dp, dR)


# optimistix traces the residual's linearisation twice, for the structure of its state in
# ``init`` (an ``eval_shape``) and in ``step``. As ``jit`` functions the residual and its
# Jacobian are traced once: the second use hits jit's trace cache. ``inline=True`` puts their
# equations into the caller's jaxpr as before, so the compiled program is unchanged (the
# lowered module differs only in the order of the loop's invariant operands); the first trace
# of the vmapped LM solver took 0.12-0.35 s less (4 runs of 1.55-2.06 s, side by side).
_residual_traced = jax.jit(_residual, inline=True)
_residual_jacobian_traced = jax.jit(kernels.residual_jacobian, inline=True)


def _residual_fn(frames0, poses, measured, noise, basis):
    """``u -> (r, (delta_p, delta_R))`` at ``X = basis @ u`` for optimistix, with the analytic
    Jacobian ``J(X) basis`` (:func:`.kernels.residual_jacobian`) as its JVP."""

    @jax.custom_jvp
    def residual(u):
        return _residual_traced(basis @ u, frames0, poses, measured, noise)

    @residual.defjvp
    def _jvp(primals, tangents):
        (u,), (du,) = primals, tangents
        r, aux, J = _residual_jacobian_traced(basis @ u, frames0, poses, measured, noise)
        zero = jax.tree.map(jnp.zeros_like, aux)
        return (r, aux), ((J @ basis) @ du, zero)

    return lambda u, _: residual(u)


def _lm_solver(
    *, max_iterations, rtol, atol, rcond, weighted, null_modules=(), singular_values=True
):
    """The per-trial LM solver for one static configuration, chunked under ``vmap``."""
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=lx.Normal(lx.Cholesky()))
    options: dict = {}
    tags: frozenset = frozenset()

    def setup(frames0, poses, measured, *noise_std):
        noise = NoiseModel(*noise_std) if weighted else None
        P = jnp.moveaxis(poses[..., :3, :], 0, -1)  # (K, 3, 4, m)
        T = kernels.pose_stack(measured)
        return P, T, noise

    def optx_state(fn, y0, m):
        # The output structure of fn, without tracing it: r (6m,) and the metrics (dp, dR).
        scalar = jax.ShapeDtypeStruct((), y0.dtype)
        f_struct, aux_struct = jax.ShapeDtypeStruct((6 * m,), y0.dtype), (scalar, scalar)
        state0 = solver.init(fn, y0, None, options, f_struct, aux_struct, tags)
        # The trust region's step size is 1 / damping (optimistix' DampedNewtonDescent), in
        # the dtype of the problem: optimistix starts it as a default-dtype array (float64
        # with x64 enabled), which in a float32 solve promotes the damped operator's output
        # to float64 and the linear solve rejects it.
        state0 = eqx.tree_at(
            lambda s: s.search_state.step_size,
            state0,
            jnp.asarray(1.0 / INITIAL_DAMPING, y0.dtype),
        )
        # As optimistix' own loop does: carry only the array part of the solver state.
        return eqx.partition(state0, eqx.is_array)

    def init(basis, finite_in, frames0, poses, measured, *noise_std):
        dtype = measured.dtype
        P, T, noise = setup(frames0, poses, measured, *noise_std)
        fn = _residual_fn(frames0, P, T, noise, basis)
        u0 = jnp.zeros(basis.shape[-1], dtype)
        nan = jnp.asarray(jnp.nan, dtype)
        dyn_state, static_state = optx_state(fn, u0, T.shape[-1])
        carry = (
            jnp.asarray(0),
            *batched_like(
                finite_in,
                (
                    u0,
                    basis,
                    dyn_state,
                    jnp.full((max_iterations,), nan),
                    jnp.full((max_iterations + 1,), nan),
                    jnp.full((max_iterations + 1,), nan),
                    jnp.asarray(False),
                ),
            ),
            finite_in,
        )
        return carry, static_state

    def running(carry):
        k, *_, done, ok = carry
        return (k < max_iterations) & ~done & ok

    def step(carry, static_state, *args):
        k, u, basis, dyn_state, steps, dps, dRs, _, _ = carry
        fn = _residual_fn(args[0], *setup(*args), basis)
        state = eqx.combine(static_state, dyn_state)
        # The aux that optimistix returns belongs to its input u: Eqs. 20-21 at X_k.
        u_new, state, (dp, dR) = solver.step(fn, u, None, options, state, tags)
        done, _ = solver.terminate(fn, u, None, options, state, tags)
        done = done | _converged(state.y_eval - u_new, u_new, state.f_info, rtol, atol)
        dyn_state, _ = eqx.partition(state, eqx.is_array)
        return (
            k + 1,
            u_new,
            basis,
            dyn_state,
            steps.at[k].set(jnp.linalg.norm(basis @ (u_new - u))),
            dps.at[k].set(dp),
            dRs.at[k].set(dR),
            done,
            jnp.all(jnp.isfinite(u_new)),
        )

    def result(carry):
        k, u, basis, _, steps, dps, dRs, done, ok = carry
        return k, basis @ u, steps, dps, dRs, done, ok

    def basis_of(lin0, use_svd, fast_allowed, frames0, xi):
        """``X = basis @ u``: whitened coordinates of the identifiable subspace (module
        docstring); ``(basis, rank, resolved)``. From the normal equations and the structural
        null space (fast) unless ``use_svd`` (an unbatched scalar: a real branch) or the fast
        basis does not apply."""

        def svd_basis(lin):
            basis = _identifiable_basis(lin, rcond)
            return basis, jnp.sum(jnp.any(basis != 0, axis=0)), jnp.asarray(True)

        def normal_basis(lin):
            N, _ = lin.normal_equations()
            Z = null_basis(frames0, null_modules, xi)
            basis, smallest, structural = null_space_basis(N, Z)
            trusted = (smallest >= RESOLVED_PIVOT) & (structural <= STRUCTURAL_TOL)
            trusted = trusted & jnp.all(jnp.isfinite(basis))
            # An untrusted basis (the trial is redone with the SVD basis): a finite one.
            basis = jnp.where(trusted, basis, jnp.eye(basis.shape[0], dtype=basis.dtype))
            return basis, jnp.asarray(basis.shape[0] - len(null_modules)), trusted

        if not fast_allowed:
            return svd_basis(lin0)
        return jax.lax.cond(use_svd, svd_basis, normal_basis, lin0)

    def run(use_svd, frames0, poses, measured, xi, *noise_std):
        """One trial: two passes of one loop, each linearising its model (Eq. 9) with the same
        code: pass 0 at the nominal frames, for the identifiable basis, then the LM iteration;
        pass 1 at the solution, for the rank and the final metrics. (Linearising before and
        after the iteration as two calls compiled the model twice: LM's compile took ~0.3 s
        longer.) Returns ``(solution, redo)``: redo with the SVD basis (``use_svd``) where the
        fast basis' rank differs from the SVD rank at the solution or its pivots are not
        resolved (:data:`.linear.RESOLVED_PIVOT`), as the paper solver does."""
        args = (frames0, poses, measured, *noise_std)
        P, T, noise = setup(*args)
        dtype = measured.dtype
        n = 6 * frames0.shape[0]
        finite_in = jnp.all(jnp.isfinite(measured)) & jnp.all(jnp.isfinite(poses))
        fast_allowed = normal_equations_apply(dtype, rcond, 6 * T.shape[-1], n)

        def iterate(lin0):
            basis, rank, resolved = basis_of(lin0, use_svd, fast_allowed, frames0, xi)
            # The static part of optimistix' state is the same at every step: taken once from
            # init (tracing solver.init again in the loop body doubled the tracing time).
            carry0, static_state = init(basis, finite_in, *args)
            # An untrusted fast basis: no iteration (the trial is redone with the SVD basis).
            carry0 = carry0[:7] + (carry0[7] | ~resolved,) + carry0[8:]
            carry = jax.lax.while_loop(running, lambda c: step(c, static_state, *args), carry0)
            k, X, steps, dps, dRs, done, ok = result(carry)
            frames = lie.se3_exp(X.reshape(frames0.shape[0], 6)) @ frames0
            return frames, (k, steps, dps, dRs, done, ok, rank, resolved)

        def apply(carry, p):
            frames, res = carry
            lin = kernels.linearise(frames, P, T, noise)
            # p is the scan's counter, unbatched under vmap: a real branch.
            carry = jax.lax.cond(p == 0, lambda: iterate(lin), lambda: (frames, res))
            return carry, lin

        nan = jnp.asarray(jnp.nan, dtype)
        history = jnp.full((max_iterations + 1,), nan)
        res0 = (
            jnp.asarray(0),
            history[1:],
            history,
            history,
            jnp.asarray(False),
            jnp.asarray(False),
            jnp.asarray(0),
            jnp.asarray(True),
        )
        # Batched from the start, so that JAX batches the scan's body once (batching.py).
        carry0 = batched_like(finite_in, (frames0.astype(dtype), res0))
        (frames, res), lins = jax.lax.scan(apply, carry0, jnp.arange(2))
        lin = jax.tree.map(lambda a: a[1], lins)
        k, steps, dps, dRs, done, ok, basis_rank, resolved = res
        sol = _solution_at(
            frames,
            frames0,
            lin,
            ok=ok,
            rcond=rcond,
            rank=None if singular_values else basis_rank,
            done=done,
            iterations=k,
            step_norm=steps,
            delta_p=dps.at[k].set(lin.delta_p),
            delta_R=dRs.at[k].set(lin.delta_R),
            solver="lm",
        )
        redo = (sol.result != RESULTS.nonfinite) & fast_allowed & ~use_svd
        return sol, redo & ((basis_rank != sol.rank) | ~resolved)

    return chunked_vmap(run, CHUNK_SIZE, second_pass=True)


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
    (:func:`.solution._solution_at`).
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
