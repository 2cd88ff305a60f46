"""The paper's iterative least-squares calibration (Eqs. 9-19, Fig. 4), jit- and vmap-able.

Each iteration stacks ``Y~`` and ``D~`` at the current model (Eq. 9), solves for ``X`` by
rank-revealing minimum-norm least squares (Eq. 10, see :mod:`.linear`), and left-multiplies
every fixed transform by ``exp(hat(X_j))`` (Eqs. 11-14) until ``||X|| < tol``. The identified
errors are ``log(F_j^c F_j^-1)`` (Eqs. 15-18) and the deviation metrics (Eqs. 20-21) are
recorded at every iteration.

Performance (see ``benchmarks/README.md``). The solver is written for Monte-Carlo batches:

* Eq. 9 is assembled in the pose-last layout of :mod:`.kernels` (the module poses, constant
  during a calibration, are computed once);
* in float64, with more than ``1.5 n`` rows in Eq. 9 (:func:`.linear.normal_equations_apply`), the
  step solves the normal equations ``D^T D X = D^T Y`` knowing their null space: the structural
  null space of ``D`` is known in closed form at every iterate (:mod:`.nullspace`: for the CDRA
  the rotation about and translation along the elbow axis, moved between ``upper_arm`` and
  ``forearm``), so ``(N + Z Z^T) X = D^T Y`` (Jacobi-scaled) is positive definite and its
  plain Cholesky solution is the minimum-norm step of the SVD, ``N^+ D^T Y``
  (:func:`.linear.null_space_solve`), at a fraction of the cost of an SVD, or of a pivoted
  factorisation, per iteration. Whether the data resolve every identifiable direction is
  tested once, at the first step (an eigenvalue bound from the Cholesky factor): it is a
  property of the pose set. In lower precision, or with fewer rows, the step is the SVD of
  ``D~`` (:func:`.linear.min_norm_lstsq`); trials whose data lose more directions than the
  structural ones (too few or degenerate poses) are solved again with SVD steps, gathered into
  chunks of their own;
* the rank, conditioning and singular values are not part of the iteration: the reported
  ``rank`` is the solve's own (``n - k`` where the fast step was trusted, else that of its SVD
  steps), and ``singular_values=True`` asks for the QR and SVD of ``D~`` at the solution, once
  (a fifth of a 15-pose solve);
* the iteration stops once the remaining steps are predicted below ``tol``
  (``predictive_stop``, :data:`PREDICTIVE_MARGIN`): one step fewer, answers within 1e-10 mm of
  the plain stop on the paper's problem;
* under ``vmap`` the trials run in chunks of :data:`CHUNK_SIZE`, the loop written at the level
  of the chunk (:func:`.batching.chunked_loop`): a chunk stops once all but a few of its trials
  have converged (:data:`STRAGGLERS`) and the few are solved again in chunks of their own,
  rather than holding the whole chunk for their last steps.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from ..arm import Arm, module_poses
from . import kernels
from .batching import chunked_loop, set_entry
from .linear import (
    RESOLVED_PIVOT,
    STRUCTURAL_TOL,
    min_norm_lstsq,
    normal_equations_apply,
    null_space_solve,
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
"""Trials per chunk when the solver is vmapped (see :mod:`.batching`). Smaller chunks keep the
working set (``D~`` alone is 17 kB per CDRA trial of 15 poses) in the core's cache: 4096
trials of the paper's problem took 80, 84 and 89 us per trial with chunks of 32, 64 and 128
(interleaved, process CPU time, a loaded machine)."""

TOL_FLOAT64 = 1e-10
"""Default ``tol`` (step norm ``||X||``, mm and rad mixed) of a float64 solve."""

TOL_FLOAT32 = 1e-3
"""Default ``tol`` of a float32 solve. Rounding stops float32 iterations far above
:data:`TOL_FLOAT64`: once converged, the steps of a 15-pose CDRA solve stay at 2e-5 to 5e-4
(median 1e-4, paper and weighted forms, noise-free and with 80 um / 1e-3 rad noise, 200 trials
each, 15 steps past convergence), so a float32 solve never met 1e-10 and always ended
``max_iterations_reached``. 1e-3 is 10x the median of that floor and 2x its largest value;
the solve stops after 3-4 steps, at its first step on the floor, as accurate as after 20 (final
``delta_p`` of noise-free trials: median 3e-4 mm unweighted, 6e-5 mm weighted, either way).
The floor scales with the arm's size (mm): pass ``tol`` for much larger arms."""

STRAGGLERS = 16
"""A chunk of the first pass stops once at most ``1 / STRAGGLERS`` of its trials still step;
those are solved again, from the start, in chunks of their own (see :func:`_paper_solver`)."""

_FAST, _CONTINUE, _SVD = 0, 1, 2
"""The passes of a batched solve (:func:`.batching.chunked_passes`): fast steps with
stragglers handed on, fast steps to the end, SVD steps."""

PREDICTIVE_MARGIN = 0.1
"""``predictive_stop``: stop after step ``k`` once ``|X_k|^2 / (|X_{k-1}| - |X_k|)``, the sum of
the steps still to come were they to shrink geometrically at the rate of the last two, is below
``PREDICTIVE_MARGIN * tol``."""


def default_tol(dtype) -> float:
    """The default ``tol`` of :func:`calibrate_paper` for problems in ``dtype``."""
    return dtype_default(None, dtype, float64=TOL_FLOAT64, float32=TOL_FLOAT32)


def calibrate_paper(
    arm: Arm,
    q: ArrayLike,
    measured: ArrayLike,
    noise: NoiseModel | None = None,
    *,
    max_iterations: int = 20,
    tol: float | None = None,
    rcond: float | None = None,
    allow_underdetermined: bool = False,
    throw: bool = True,
    singular_values: bool = False,
    predictive_stop: bool = True,
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
        tol: stop once the step norm ``||X||`` (mm and rad mixed, as in the paper) is below it;
            ``None``: 1e-10 for float64 problems (:data:`TOL_FLOAT64`), 1e-3 for float32 ones
            (:data:`TOL_FLOAT32`, above float32's rounding floor of the step norm).
        rcond: relative singular-value cut-off of the least-squares step and of the reported
            rank (see :mod:`.linear`; the step's cut-off is :func:`.linear.normal_cutoff`).
        allow_underdetermined: accept fewer than 4 poses (the paper's lower bound); the step is
            then the minimum-norm one.
        throw: raise at run time when the result is not successful. Use ``throw=False`` under
            ``vmap`` and read ``result`` per trial.
        singular_values: also compute the singular values of ``D~`` at the solution (a QR and
            an SVD per trial, once, after the iteration; static) and report the rank they
            give. By default the rank is the solve's own (the generic rank ``n - k`` of
            :mod:`.nullspace` where the fast step was trusted, else that of the SVD steps;
            equal to the other wherever the fast step is trusted) and the singular values are
            NaN: ask for them where they are read (the command line does), not in Monte-Carlo
            batches (they cost about a fifth of a 15-pose solve).
        predictive_stop: also stop after step ``k`` once the steps still to come are
            predicted to move less than ``PREDICTIVE_MARGIN * tol`` in all: ``|X_k|^2 /
            (|X_{k-1}| - |X_k|)``, their sum were they to shrink geometrically at the rate of
            the last two (Gauss-Newton converges at least that fast near the solution). Saves
            the last, negligible step (about one of five iterations of a 15-pose CDRA solve);
            the frames differ from those of the plain stop by about that step (below 1e-11 mm
            on the paper's problem, noise-free and noisy). ``False``: the paper's stop,
            ``||X|| < tol`` alone.

    Returns:
        A :class:`CalibrationSolution`.

    Differentiable with respect to ``q``, ``measured``, the frames of ``arm`` and the noise
    stds, through the optimality condition ``D~^T Y~ = 0`` (Eq. 10), not through the
    iterations: see :mod:`.implicit` (``frames``, ``errors`` and ``cost`` carry the
    derivative).
    """

    null_modules, _ = null_generators(arm)

    def make_solver(dtype):
        return _paper_solver(
            arm,
            max_iterations=max_iterations,
            tol=dtype_default(tol, dtype, float64=TOL_FLOAT64, float32=TOL_FLOAT32),
            rcond=rcond,
            weighted=noise is not None,
            solver="paper" if noise is None else "weighted",
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


def _paper_solver(
    arm,
    *,
    max_iterations,
    tol,
    rcond,
    weighted,
    solver,
    null_modules=(),
    singular_values=False,
    predictive_stop=True,
):
    """The per-trial solver for one static configuration, chunked under ``vmap``; ``arm``
    gives the module structure that turns the states ``q`` into module poses (its arrays come
    as arguments: the frames, the axes, the null generators).

    The step is taken from the normal equations (``fast``, float64 with the default ``rcond``)
    or from the SVD of ``D~``. The fast step knows the structural null space of ``D~`` in
    closed form (:mod:`.nullspace`, rebuilt at every iterate from the current frames) and
    solves ``(N + c Z Z^T) X = D~^T Y~`` by a plain Cholesky factorisation
    (:func:`.linear.null_space_solve`), which is the minimum-norm step ``N^+ D~^T Y~`` of the
    SVD solver, with rank ``n - k``. A fast solve is redone with SVD steps where it cannot be
    trusted to equal the SVD solver's: where the data lose more than the structural directions
    or resolve an identifiable one poorly (too few or degenerate poses: the eigenvalue bound of
    :func:`.linear.null_space_solve` at the first step below :data:`.linear.RESOLVED_PIVOT`,
    or a factorisation that breaks down later), or where the analytic basis is not null
    (module poses that are not the modules' own motions, :data:`.linear.STRUCTURAL_TOL`,
    tested at the first step: it does not depend on the frames). With ``singular_values`` the
    SVD of ``D~`` at the solution is computed too and a trial whose step rank differs from its
    rank is redone as well. A trial stops stepping at its first unresolved step (it is to be
    redone anyway). The result is therefore the SVD solver's, up to rounding.

    Under ``vmap`` (:func:`.batching.chunked_loop`) the batch runs in three passes of one
    compiled loop, gathering the trials of a later pass into chunks of their own
    (:func:`.batching.multi_pass`): fast steps, a chunk stopping once at most
    ``1 / STRAGGLERS`` of its trials still step (:data:`_FAST`); those trials again from the
    start, to the end (:data:`_CONTINUE`); the trials to redo with SVD steps (:data:`_SVD`).
    The pass and the chunk's step counter are real branches (``lax.cond``) of the one loop.
    (Such a gather inside a loop once deadlocked with the batch on two CPU devices; the cause
    was jaxlib's LAPACK thread pool, fixed by :mod:`cdra_jax.parallel`.)
    """
    n_null = len(null_modules)

    def init(mode, frames0, q, measured, axes, xi, *noise_std):
        """A trial's start: ``(state, data)``, ``data`` the pose-last module and measured poses
        (Eq. 9's layout), the null generators and the noise model."""
        dtype = measured.dtype
        noise = NoiseModel(*noise_std) if weighted else None
        poses = module_poses(arm, q, axes)  # (m, K, 4, 4), per chunk under vmap
        P = jnp.moveaxis(poses[..., :3, :], 0, -1)  # (K, 3, 4, m)
        T = kernels.pose_stack(measured)  # (3, 4, m)
        finite_in = jnp.all(jnp.isfinite(measured)) & jnp.all(jnp.isfinite(poses))
        n = 6 * frames0.shape[0]
        nan = jnp.asarray(jnp.nan, dtype)
        state = (
            jnp.asarray(0, jnp.int32),  # steps taken
            frames0,
            jnp.full((max_iterations,), nan),  # step norms
            jnp.full((max_iterations + 1,), nan),  # Eq. 20 at every model
            jnp.full((max_iterations + 1,), nan),  # Eq. 21
            nan,  # the cost of the last model evaluated
            (jnp.asarray(n), jnp.asarray(0), jnp.asarray(True)),  # step ranks, all resolved
            jnp.asarray(False),  # converged
            finite_in,  # all finite so far
        )
        return state, (frames0, P, T, xi, noise)

    def running(state):
        k, _, _, _, _, _, (_, _, resolved), done, ok = state
        return (k < max_iterations) & ~done & ok & resolved

    def body(it, mode, step, state, data):
        """Evaluate the current model (Eq. 7, Eqs. 20-21, the cost) and, with ``step``, take a
        Gauss-Newton step where the trial still runs (``it``, ``mode`` and ``step`` are the
        chunk's: real branches)."""
        k, frames, steps, dps, dRs, _, ranks, done, ok = state
        _, P, T, xi, noise = data
        tool, after = kernels.chain(frames, P)
        Y, dp, dR = kernels.residual_and_metrics(T, tool)
        Yw = Y if noise is None else kernels.whiten(Y, T, noise)
        dps, dRs = set_entry(dps, k, dp), set_entry(dRs, k, dR)
        state = (k, frames, steps, dps, dRs, jnp.sum(Yw * Yw))
        state = state + (ranks, done, ok)
        if_step = functools.partial(_step, it, mode, state, after, Yw, data)
        return jax.lax.cond(step, if_step, lambda: state)

    def _step(it, mode, state, after, Yw, data):
        k, frames, steps, dps, dRs, cost, (rank_lo, rank_hi, resolved), done, ok = state
        _, _, T, xi, noise = data
        dtype = T.dtype
        n = 6 * frames.shape[0]

        def svd_step():
            DT = kernels.jacobian_transposed(after, T, noise)
            X, rank, _ = min_norm_lstsq(DT.T, Yw.reshape(-1), rcond)
            return X, rank, jnp.asarray(True)

        def null_step():
            N, g = kernels.normal_equations(after, Yw, T, noise)
            Z = null_basis(frames, null_modules, xi)
            # Whether the data resolve every identifiable direction, and whether the analytic
            # basis is null, are properties of the pose set: tested at the first step only.
            X, smallest, structural = null_space_solve(N, g, Z, check=it == 0)
            trusted = (smallest >= RESOLVED_PIVOT) & (structural <= STRUCTURAL_TOL)
            # A factorisation that broke down (NaN) on finite data is not a non-finite
            # problem: the step is not taken and the trial is redone with SVD steps.
            finite = jnp.all(jnp.isfinite(Yw))
            trusted = trusted & jnp.all(jnp.isfinite(X))
            X = jnp.where(finite, jnp.where(trusted, X, 0), jnp.asarray(jnp.nan, dtype))
            return X, jnp.asarray(n - n_null), trusted

        if normal_equations_apply(dtype, rcond, Yw.size, n):
            X, rank, res = jax.lax.cond(mode == _SVD, svd_step, null_step)
        else:
            X, rank, res = svd_step()
        stepping = running(state)
        step = jnp.linalg.norm(X)
        finite = jnp.isfinite(step)
        moved = kernels.step_frames(X, frames)
        converged = step < tol
        if predictive_stop:
            # What the steps after this one would still move, predicted from the last two:
            # |X_k|^2 / (|X_{k-1}| - |X_k|), the geometric tail (module docstring).
            previous = steps[jnp.maximum(k - 1, 0)]
            tail = (k > 0) & (step * step < PREDICTIVE_MARGIN * tol * (previous - step))
            converged = converged | tail
        return (
            k + stepping,
            jnp.where(stepping & finite, moved, frames),
            set_entry(steps, k, step, stepping),
            dps,
            dRs,
            cost,
            (
                jnp.where(stepping, jnp.minimum(rank_lo, rank), rank_lo),
                jnp.where(stepping, jnp.maximum(rank_hi, rank), rank_hi),
                resolved & (res | ~stepping),
            ),
            jnp.where(stepping, converged, done),
            jnp.where(stepping, finite, ok),
        )

    def finish(mode, state, data):
        """The solution of one trial from its last evaluation (with the singular values asked
        for: the QR and SVD of its Jacobian, once) and whether it is to be redone with SVD
        steps."""
        k, frames, steps, dps, dRs, cost, (rank_lo, rank_hi, resolved), done, ok = state
        frames0, P, T, _, noise = data
        n = 6 * frames0.shape[0]
        fast = normal_equations_apply(T.dtype, rcond, 6 * T.shape[-1], n)
        sol = _finished_solution(
            frames,
            frames0,
            P,
            T,
            noise,
            singular_values=singular_values,
            rcond=rcond,
            rank=rank_hi,
            iterations=k,
            step_norm=steps,
            delta_p=dps,
            delta_R=dRs,
            cost=cost,
            done=done,
            ok=ok,
            solver=solver,
        )
        rank = sol.rank
        redo = (sol.result != RESULTS.nonfinite) & (k > 0) & fast & (mode != _SVD)
        redo = redo & ((rank_lo != rank) | (rank_hi != rank) | ~resolved)
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
