"""Levenberg-Marquardt calibration on the same residual as the paper solver, jit- and vmap-able.

The residual is the (optionally whitened) stacked ``log(T_meas T^-1)^v`` of Eq. 7 and LM
minimises its exact sum of squares over the fixed transforms; the deviation metrics (Eqs.
20-21) are recorded at every step, as for the paper solver. Like the paper's iteration (Eqs.
11-14), a step ``dX`` moves the frames on the left, ``F_j <- exp(hat(dX_j)) F_j``, and the next
step is taken at the moved frames.

The iteration is the damped Gauss-Newton method of Madsen, Nielsen and Tingleff (*Methods for
non-linear least squares problems*, 2004, Alg. 3.16): the step solves ``(J^T J + lambda N_0) dX
= -J^T r``; a step that lowers the cost is taken and ``lambda`` shrinks by ``max(1/3, 1 - (2 rho
- 1)^3)`` (``rho`` the actual over the predicted reduction), otherwise ``lambda`` grows by
``nu`` (doubling at each refusal in a row). ``lambda`` starts at ``tau = 1e-6``
(:data:`INITIAL_DAMPING`), their choice for a start believed close to the solution, as the
nominal model is: the first step is a full Gauss-Newton step. Each pass evaluates the model at
the proposed step, decides on it, and proposes the next step from the normal equations where
it stands; the MINPACK-style tests of :func:`_converged` on that proposal stop the trial before
another pass would evaluate it. Once the iteration contracts fast, the predictive stop takes the
last proposal without another pass (``predictive_stop``, :func:`calibrate_lm`).

Scaling. The damping's metric ``N_0`` is ``J^T J`` of the nominal model (Jacobi-scaled, as the
whole system): in the coordinates that whiten the nominal Jacobian it is the identity, so that
``lambda`` shortens every identifiable direction alike, whatever its units (mm and rad columns
differ by the lever arm, hundreds of mm, and by the weights). A damping ``lambda diag(J^T J)``
(Marquardt's) would instead hold back the weakly determined combinations of the CDRA's
parameters, whose eigenvalues in the Jacobi-scaled system are far below ``tau``, and slow the
convergence to linear.

The step. ``J = -G J_r^-1(r) D`` for a step on the left of the current frames, in closed form
(:func:`.kernels.residual_jacobian` at ``X = 0``, checked against ``jax.jacfwd``); its normal
equations are assembled, as the paper solver's (:func:`.kernels.normal_equations`), from the
rows of ``J`` that are not zero (:func:`.kernels.lm_normal_equations`): ``J`` itself is never
formed. In float64 (default ``rcond``, more than ``1.5 n`` rows:
:func:`.linear.normal_equations_apply`) the damped system is solved as the paper solver's step,
knowing the structural null space of ``J`` (the same as that of ``D``, :mod:`.nullspace`, at
every iterate): ``(J^T J + lambda N_0 + Z Z^T) dX = -J^T r`` by a plain Cholesky factorisation
and ``dX`` projected off ``Z`` (:func:`.linear.null_space_solve`), so that the unidentifiable
directions (the CDRA's two, see :mod:`cdra_jax.identifiability`) are never moved: the steps are
minimum-norm, as the paper solver's. Whether the data resolve every identifiable direction is
tested once, on the nominal normal equations (below); a trial whose data lose more directions
than the structural ones (the eigenvalue bound below :data:`.linear.RESOLVED_PIVOT`) does not
iterate and is solved again with SVD steps, the trials to redo gathered into chunks of their
own: the same damped system in the identifiable basis ``B = V S^+`` of the SVD ``D~ = U S V^T``
at the nominal model (Eq. 9, rank cut-off ``rcond``; :func:`_identifiable_basis`), where its
normal equations ``B^T (J^T J + lambda N_0) B`` are close to the identity and the directions
the data do not determine have zero columns, by Cholesky, the step projected off the structural
null space. The two agree on everything the data determine; the frames' unidentifiable
components follow the path of the steps, which the two solves share to ``O(lambda)`` (within
1e-7 mm on 7-pose sets). The test of the pose set is that of the first proposal: there ``J^T J
= N_0``, so that the damped system is ``(1 + lambda) N_0`` and its tests those of the undamped
one.

Not through optimistix (:func:`.optimistix_lm.calibrate_lm_optimistix` is that solver, kept
as the reference this one is tested against). Its least-squares solvers
(``optimistix.LevenbergMarquardt``) take every step from the Jacobian operator that they build
by linearising the residual (``jax.linearize``) in fixed coordinates; the API has no entry for
normal equations computed otherwise, nor for steps taken on the left of the current frames.
Each step there materialises the Jacobian, forms the normal equations of the damped augmented
``(6m + n, n)`` system, and carries its whole state through its branches: the optimistix solve
of the same minimisation (in the identifiable coordinates of the nominal model, with the same
analytic Jacobian) took 10x the time of this one, 11.5 steps against 4.0, and 1.3x its compile
time (15 CDRA poses, 2048 trials, one process). Its minimisers that accept a Hessian (the
quasi-Newton family) take the gradient by autodiff and give the Hessian update no access to the
residual's auxiliary output, so the model would be evaluated twice per step.

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

from ..arm import Arm, module_poses
from . import kernels
from .batching import chunked_loop, set_entry
from .linear import (
    RESOLVED_PIVOT,
    STRUCTURAL_TOL,
    cholesky_of_symmetric,
    default_rcond,
    normal_equations_apply,
    null_space_solve,
    off_null_space,
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
"""The passes of a batched solve: fast steps with stragglers handed on, fast steps to the end,
SVD steps."""

RTOL_FLOAT64 = 1e-12
ATOL_FLOAT64 = 1e-11
"""Default ``rtol`` and ``atol`` of a float64 solve, in the units of the rescaled residual (mm
unweighted, standard deviations with a noise model). With noise, ``rtol`` decides: the solve
stops once the next step would lower the cost by less than ``rtol`` of it, within ~1e-6 mm of
the exact minimum at 80 um / 1e-3 rad (whitened, 15 CDRA poses; a flat unweighted minimum
4e-4 mm). Noise-free (the cost goes to zero) ``atol`` decides: the next step would change the
residual by less than 1e-11 mm; held-out tool positions within 2e-9 mm of the exact minimum,
4.04 steps on average (2048 trials). With ``atol = 1e-12`` half of those trials took a fifth
step, and whether they did depended on rounding (the two XLA:CPU emitters disagreed)."""

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

PREDICTIVE_RATE = 0.01
"""``predictive_stop`` applies once the proposed step is below this fraction of the step just
taken (the iteration contracts fast: its quadratic phase)."""

PREDICTIVE_SLACK = 100.0
"""``predictive_stop``: the step after the proposal, predicted from the last ones, must pass the
step test of :func:`_converged` with ``atol`` and ``rtol`` this many times larger (noise-free:
a change of the residual below 1e-9 mm) or its cost test as it is."""

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
    predictive_stop: bool = True,
) -> CalibrationSolution:
    """Calibrate the fixed transforms of ``arm`` by Levenberg-Marquardt (module docstring).

    Arguments as :func:`cdra_jax.calibration.calibrate_paper`; ``rtol``/``atol`` are the step
    and cost tolerances of :func:`_converged` (``None``: 1e-12 and 1e-11 for float64 problems,
    :data:`RTOL_FLOAT64`, :data:`ATOL_FLOAT64`; 1e-6 and 1e-3 for float32 ones,
    :data:`RTOL_FLOAT32`, :data:`ATOL_FLOAT32`) and ``max_iterations`` caps the steps tried,
    taken or refused. ``iterations`` counts them; the ``step_norm`` history holds the norm of
    each step ``||dX||`` (zero for refused steps). The steps have no component along the
    unidentifiable directions at their iterate (rank cut-off ``rcond``), as the paper solver's
    minimum-norm steps. Differentiable like :func:`calibrate_paper`, through the condition ``J^T
    Y~ = 0`` (:mod:`.implicit`). ``singular_values=True`` also computes the singular values of
    ``D~`` at the solution (a QR and an SVD, once) and reports their rank; by default the rank
    is the solve's own (``n - k`` where the fast steps apply, else that of the SVD of ``J~`` at
    the nominal model) and the singular values are NaN, as for :func:`calibrate_paper`.

    ``predictive_stop`` (default) saves the last pass of the loop (normal equations and a
    solve), as the paper solver's predictive stop does. Once the iteration contracts fast (the
    step just evaluated was taken with a gain ratio above 3/4 and the proposal is below
    :data:`PREDICTIVE_RATE` of it), the step after the proposal is predicted from the last
    three, its ratio to the proposal shrinking as the last ratio did. When that step would pass
    the step test of :func:`_converged` with tolerances :data:`PREDICTIVE_SLACK` times larger,
    or its reduction of the cost (the proposal's times the square of the last ratio) the cost
    test as it is, the proposal is taken without another pass, and the model is evaluated once
    at the end. Plain LM takes that same step and then stops, or takes one more step of about
    that predicted size. A proposal that would raise the cost is not taken: the trial is solved
    again from the start without the predictive stop. ``False``: the tests of
    :func:`_converged` alone.
    """
    null_modules, _ = null_generators(arm)

    def make_solver(dtype):
        return _lm_solver(
            arm,
            max_iterations=max_iterations,
            rtol=dtype_default(rtol, dtype, float64=RTOL_FLOAT64, float32=RTOL_FLOAT32),
            atol=dtype_default(atol, dtype, float64=ATOL_FLOAT64, float32=ATOL_FLOAT32),
            rcond=rcond,
            weighted=noise is not None,
            null_modules=null_modules,
            singular_values=singular_values,
            predictive_stop=predictive_stop,
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
    arm,
    *,
    max_iterations,
    rtol,
    atol,
    rcond,
    weighted,
    null_modules=(),
    singular_values=False,
    predictive_stop=True,
):
    """The per-trial LM solver for one static configuration, chunked under ``vmap``
    (:func:`.batching.chunked_loop`; passes as the paper solver's); ``arm`` as for the paper
    solver (:func:`.gauss_newton._paper_solver`)."""
    n_null = len(null_modules)

    def init(mode, frames0, q, measured, axes, xi, *noise_std):
        """A trial's start: nothing evaluated yet (the first pass of the loop evaluates the
        nominal model and tests the pose set there)."""
        dtype = measured.dtype
        noise = NoiseModel(*noise_std) if weighted else None
        poses = module_poses(arm, q, axes)  # (m, K, 4, 4), per chunk under vmap
        P = jnp.moveaxis(poses[..., :3, :], 0, -1)  # (K, 3, 4, m)
        T = kernels.pose_stack(measured)
        n = 6 * frames0.shape[0]
        finite_in = jnp.all(jnp.isfinite(measured)) & jnp.all(jnp.isfinite(poses))
        nan = jnp.asarray(jnp.nan, dtype)
        zero = jnp.zeros((), dtype)
        eye = jnp.eye(n, dtype=dtype)
        state = (
            jnp.asarray(0, jnp.int32),  # steps tried
            jnp.zeros(n, dtype),  # u: the scaled steps taken, summed (the step test's scale)
            frames0,  # the frames
            (zero, jnp.zeros((n, n), dtype), jnp.zeros(n, dtype)),  # |r~|^2, J^T J, J^T r~
            (zero, jnp.asarray(2.0, dtype)),  # lambda, nu
            # N_0, the basis of SVD steps (transposed), their rank, fast steps apply
            (eye, eye, jnp.asarray(n), jnp.asarray(True)),
            # the next step dX, scaled, its predicted gain, and the frames it moves to
            (jnp.zeros(n, dtype), jnp.zeros(n, dtype), zero, frames0),
            (
                jnp.full((max_iterations,), nan),  # step norms
                jnp.full((max_iterations + 1,), nan),  # Eq. 20 at every model
                jnp.full((max_iterations + 1,), nan),  # Eq. 21
            ),
            jnp.asarray(False),  # converged
            finite_in,  # ok
            # predictive stop: the proposal is taken unevaluated; the last ratio of two steps
            (jnp.asarray(False), jnp.ones((), dtype)),
        )
        return state, (frames0, P, T, xi, noise)

    def running(state):
        k, *_, (_, _, _, resolved), _, _, done, ok, _ = state
        return (k < max_iterations) & ~done & ok & resolved

    def svd_steps(mode, T, n):
        """Whether the steps are taken in the identifiable basis of the SVD (static where the
        fast steps do not apply, else the SVD pass)."""
        if normal_equations_apply(T.dtype, rcond, 6 * T.shape[-1], n):
            return mode == _SVD
        return jnp.asarray(True)

    def nominal(mode, N, after, T, noise):
        """``(N_0, basis^T, rank, resolved)`` at the nominal model (normal equations ``N``): the
        damping metric, and for SVD steps the identifiable basis of the SVD of ``D~``
        (:func:`_identifiable_basis`) and its rank (a real branch); for fast steps the rank is
        the generic one and ``resolved`` is decided by the first proposal's tests."""
        n = N.shape[0]

        def svd_basis():
            DT = kernels.jacobian_transposed(after, T, noise)
            zero = jnp.zeros((), T.dtype)
            basis = _identifiable_basis(kernels.Linearisation(DT[0], DT, zero, zero), rcond)
            # Carried transposed, in the layout of the SVD's V^T: held as it is, XLA copied it
            # into the other layout and back in every pass of the loop.
            return basis.T, jnp.sum(jnp.any(basis != 0, axis=0))

        def generic():
            return jnp.eye(n, dtype=T.dtype), jnp.asarray(n - n_null)

        basis, rank = jax.lax.cond(svd_steps(mode, T, n), svd_basis, generic)
        return N, basis, rank, jnp.asarray(True)

    def proposal(mode, first, frames, N, g, damping, bases, xi, T):
        """The damped step ``dX`` at ``frames`` (module docstring) and whether fast steps apply
        (tested at the first proposal, where ``N = N_0`` and the damped system is ``(1 +
        lambda) N``: the tests of the undamped one to ``lambda``): the scaled null-space solve
        of ``(J^T J + lambda N_0) dX = -J^T r~`` (:func:`.linear.null_space_solve`), or the
        same system in the identifiable basis (a real branch), projected off the structural
        null space."""
        N0, basis_t, _, resolved = bases
        n = N.shape[0]
        Z = null_basis(frames, null_modules, xi)

        def fast():
            x, smallest, structural = null_space_solve(N, -g, Z, check=first, damping=damping * N0)
            trusted = (smallest >= RESOLVED_PIVOT) & (structural <= STRUCTURAL_TOL)
            return x, jnp.where(first, trusted & jnp.all(jnp.isfinite(x)), resolved)

        def in_basis():
            basis = basis_t.T
            used = jnp.any(basis != 0, axis=0)
            A = basis.T @ ((N + damping * N0) @ basis) + jnp.diag(jnp.where(used, 0.0, 1.0))
            du = jax.scipy.linalg.cho_solve((cholesky_of_symmetric(A), True), basis.T @ g)
            x = -basis @ du
            return off_null_space(x, Z), resolved

        return jax.lax.cond(svd_steps(mode, T, n), in_basis, fast)

    def body(it, mode, step, state, data):
        """One damped step where the trial still runs; the chunk's first pass (``it == 0``,
        always taken) evaluates the nominal model instead and tests the pose set there (``it``,
        ``mode`` and ``step`` are the chunk's: real branches); the last pass, without a step,
        takes the proposals that the predictive stop left to it. Every pass evaluates the model
        at the proposed step first (the first pass: at the nominal model, ``dX = 0``)."""
        _, P, T, _, _ = data
        frames_t = state[6][3]
        tool, after = kernels.chain(frames_t, P)
        model = (frames_t, after) + kernels.residual_and_metrics(T, tool)
        return jax.lax.cond(
            step | (it == 0),
            lambda: _step(it, mode, state, data, model),
            lambda: _take_pending(state, data, model) if predictive_stop else state,
        )

    def _take_pending(state, data, model):
        """The proposal of a trial that the predictive stop ended, taken where it does not
        raise the cost; else the trial stays where it was, still pending (``finish`` has it
        solved again). ``model``: the model evaluated at the proposal (``body``)."""
        k, u, frames, (cost, N, g), damping, bases, proposed, hist, done, ok, ahead = state
        pending, last_rate = ahead
        steps, dps, dRs = hist
        _, _, T, _, noise = data
        dX = proposed[0]
        frames_t, _, r, dp, dR = model
        Yw = r if noise is None else kernels.whiten(r, T, noise)
        cost_t = jnp.sum(Yw * Yw)
        take = pending & (cost_t <= cost) & jnp.all(jnp.isfinite(frames_t))
        hist = (
            set_entry(steps, k, jnp.linalg.norm(dX), take),
            set_entry(dps, k + 1, dp, take),
            set_entry(dRs, k + 1, dR, take),
        )
        frames = jnp.where(take, frames_t, frames)
        cost = jnp.where(take, cost_t, cost)
        ahead = (pending & ~take, last_rate)
        return (k + take, u, frames, (cost, N, g), damping, bases, proposed, hist, done, ok, ahead)

    def _step(it, mode, state, data, model):
        k, u, frames, (cost, N, g), (damping, nu), bases, proposed, hist, done, ok, ahead = state
        pending, last_rate = ahead
        steps, dps, dRs = hist
        dX, scaled, predicted, _ = proposed
        _, _, T, xi, noise = data
        first = it == 0
        trying = running(state) & ~first
        # The normal equations at the proposed step (the first pass: the nominal model), and
        # whether the step is taken.
        frames_t, after, r, dp, dR = model
        N_t, g_t, Yw = kernels.lm_normal_equations(after, r, T, noise)
        bases = jax.lax.cond(first, lambda: nominal(mode, N_t, after, T, noise), lambda: bases)
        cost_t = jnp.sum(Yw * Yw)
        rho = (0.5 * (cost - cost_t)) / predicted
        take = first | (trying & (rho > 0) & jnp.isfinite(cost_t))
        shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
        damping_t = jnp.where(take, damping * shrink, damping * nu)
        damping_t = jnp.where(first, INITIAL_DAMPING, damping_t)
        nu_t = jnp.where(take, 2.0, jnp.minimum(2.0 * nu, MAX_DAMPING_GROWTH))

        def pick(new, old):
            return jax.tree.map(lambda a, b: jnp.where(take, a, b), new, old)

        moved = jnp.linalg.norm(dX)
        at = jnp.where(first, 0, k + 1)  # Eqs. 20-21 of the nominal model, or after step k
        live = trying | first
        hist = (
            set_entry(steps, k, jnp.where(take, moved, 0.0), trying),
            set_entry(dps, at, jnp.where(take, dp, dps[k]), live),
            set_entry(dRs, at, jnp.where(take, dR, dRs[k]), live),
        )
        u = pick(u + scaled, u)
        frames, (cost, N, g) = pick((frames_t, (cost_t, N_t, g_t)), (frames, (cost, N, g)))
        damping, nu = jax.tree.map(
            lambda a, b: jnp.where(live, a, b), (damping_t, nu_t), (damping, nu)
        )
        # The next step, proposed now, and the stopping tests on it: a trial that has
        # converged stops before the pass that would evaluate it.
        dX_next, resolved = proposal(mode, first, frames, N, g, damping, bases, xi, T)
        bases = bases[:3] + (resolved,)
        predicted_next = -(jnp.dot(g, dX_next) + 0.5 * jnp.dot(dX_next, N @ dX_next))
        scaled_next = jnp.sqrt(jnp.maximum(jnp.diagonal(N), 0.0)) * dX_next  # units of r~
        converged = _converged(scaled_next, u, predicted_next, cost, rtol, atol)
        if predictive_stop:
            # The step after the proposal, predicted from the last three (calibrate_lm).
            rate = jnp.linalg.norm(scaled_next) / jnp.linalg.norm(scaled)
            fast = trying & take & (rho > 0.75) & (rate < PREDICTIVE_RATE) & (mode == _FAST)
            ratio = rate * jnp.minimum(1.0, rate / last_rate)  # after the proposal
            small = _converged(
                scaled_next * (ratio / PREDICTIVE_SLACK),
                u + scaled_next,
                predicted_next * rate * rate,
                jnp.maximum(cost - 2.0 * predicted_next, 0.0),
                rtol,
                atol,
            )
            unevaluated = fast & small & (k + 1 < max_iterations) & ~converged
            converged = converged | unevaluated
            pending = pending | unevaluated
            last_rate = jnp.where(trying & take, rate, last_rate)
        proposed = jax.tree.map(
            lambda a, b: jnp.where(live, a, b),
            (dX_next, scaled_next, predicted_next, kernels.step_frames(dX_next, frames)),
            proposed,
        )
        finite = jnp.all(jnp.isfinite(frames)) & (jnp.isfinite(cost_t) | ~first)
        return (
            k + trying,
            u,
            frames,
            (cost, N, g),
            (damping, nu),
            bases,
            proposed,
            hist,
            done | (live & converged),
            ok & finite,
            (pending, last_rate),
        )

    def finish(mode, state, data):
        """The solution of one trial, and whether it is to be redone with SVD steps (where the
        fast steps are not resolved, or their rank is not that of the singular values), or
        without the predictive stop (where it left a proposal that raised the cost)."""
        k, _, frames, (cost, _, _), _, bases, _, hist, done, ok, (pending, _) = state
        _, _, step_rank, resolved = bases
        steps, dps, dRs = hist
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
            rank=step_rank,
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
        redo = redo & ((step_rank != rank) | ~resolved)
        again = pending & (sol.result != RESULTS.nonfinite)
        return sol, jnp.where(redo, _SVD, jnp.where(again, _CONTINUE, 0))

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
