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
  factorisation, per iteration. In lower precision, or with fewer rows, the step is the SVD
  of ``D~`` (:func:`.linear.min_norm_lstsq`); trials whose data lose more directions than the
  structural ones (too few or degenerate poses, detected from the Cholesky factor) are solved
  again with SVD steps, gathered into chunks of their own (:func:`.batching.two_pass`);
* the reported ``rank`` and ``singular_values`` are those of the SVD of ``D~`` at the solution,
  with the singular-value cut-off ``rcond`` (:func:`.linear.default_rcond`), as before; with
  ``singular_values=False`` that QR and SVD are skipped (a fifth of a 15-pose solve) and the
  rank is the solve's own;
* ``predictive_stop=True`` stops one step earlier, once the remaining steps are predicted
  below ``tol`` (:data:`PREDICTIVE_MARGIN`);
* under ``vmap`` the trials run in chunks (:mod:`.batching`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from .. import lie
from ..arm import Arm
from . import kernels
from .batching import batched_like, chunked_vmap
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
    _solution_at,
    _solve_problem,
    dtype_default,
)

CHUNK_SIZE = 128
"""Trials per chunk when the solver is vmapped (see :mod:`.batching`)."""

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
    singular_values: bool = True,
    predictive_stop: bool = False,
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
        singular_values: compute the singular values of ``D~`` at the solution (a QR and an
            SVD per trial, static) and report the rank they give; ``False`` reports the solve's
            own rank (the generic rank ``n - k`` of :mod:`.nullspace` where the fast step was
            trusted, else that of the SVD steps; equal to the other wherever the fast step is
            trusted) and NaN singular values. Monte-Carlo sweeps that do not need them save
            about a fifth of the time.
        predictive_stop: also stop after step ``k`` when the *next* step is predicted to be
            below ``tol``: ``|X_k|^2 / |X_{k-1}| < tol`` (Gauss-Newton converges quadratically
            near a zero-residual solution, and the ratio of successive steps falls at least as
            fast with noise). Saves the last, negligible step (about one of five iterations of
            a 15-pose CDRA solve); the frames differ from those of the default stop by about
            that last step (below 1e-11 mm on the paper's problem, noise-free and noisy).

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
    *,
    max_iterations,
    tol,
    rcond,
    weighted,
    solver,
    null_modules=(),
    singular_values=True,
    predictive_stop=False,
):
    """The per-trial solver for one static configuration, chunked under ``vmap``.

    The step is taken from the normal equations (``fast``, float64 with the default ``rcond``)
    or from the SVD of ``D~``. The fast step knows the structural null space of ``D~`` in
    closed form (:mod:`.nullspace`, rebuilt at every iterate from the current frames) and
    solves ``(N + c Z Z^T) X = D~^T Y~`` by a plain Cholesky factorisation
    (:func:`.linear.null_space_solve`), which is the minimum-norm step ``N^+ D~^T Y~`` of the
    SVD solver, with rank ``n - k``. A fast solve is redone with SVD steps where it cannot be
    trusted to equal the SVD solver's: where the data lose more than the structural directions
    or resolve an identifiable one poorly (too few or degenerate poses: the eigenvalue bound of
    :func:`.linear.null_space_solve` below :data:`.linear.RESOLVED_PIVOT`), or where the
    analytic basis is not null (module poses that are not the modules' own motions,
    :data:`.linear.STRUCTURAL_TOL`). With ``singular_values`` the SVD of ``D~`` at the solution
    is computed too and a trial whose step rank differs from its rank is redone as well. A
    trial stops stepping at its first unresolved step (it is to be redone anyway). The batch is
    solved fast, in chunks, and the trials to redo are then gathered into chunks of their own
    and solved with SVD steps (:func:`.batching.two_pass`), so that the second pass costs in
    proportion to those trials, not to the chunks that hold one. The result is therefore the
    SVD solver's, up to rounding. (Such a gather inside a loop once deadlocked with the batch
    on two CPU devices; the cause was jaxlib's LAPACK thread pool, fixed by
    :mod:`cdra_jax.parallel`.)

    The two passes run the same compiled code: ``use_svd`` is a traced scalar shared by a
    chunk, so the choice of step is a real branch (``lax.cond``) even under ``vmap``, and the
    passes are iterations of one loop, so that the solver is traced and compiled once.
    """
    n_null = len(null_modules)

    def run(use_svd, frames0, poses, measured, xi, *noise_std):
        """One trial; ``use_svd`` (a boolean scalar, unbatched) picks the step."""
        dtype = measured.dtype
        n = frames0.shape[0] * 6
        k_frames = frames0.shape[0]
        noise = NoiseModel(*noise_std) if weighted else None
        P = jnp.moveaxis(poses[..., :3, :], 0, -1)  # (K, 3, 4, m)
        T = kernels.pose_stack(measured)  # (3, 4, m)
        nan = jnp.asarray(jnp.nan, dtype)
        finite_in = jnp.all(jnp.isfinite(measured)) & jnp.all(jnp.isfinite(poses))
        fast_allowed = normal_equations_apply(dtype, rcond, 6 * measured.shape[0], n)

        def svd_step(lin, frames):
            X, rank, _ = min_norm_lstsq(lin.DT.T, lin.Y, rcond)
            return X, rank, jnp.asarray(True)

        def null_step(lin, frames):
            N, g = lin.normal_equations()
            Z = null_basis(frames, null_modules, xi)
            X, smallest, structural = null_space_solve(N, g, Z)
            finite = jnp.all(jnp.isfinite(N)) & jnp.all(jnp.isfinite(g))
            trusted = (smallest >= RESOLVED_PIVOT) & (structural <= STRUCTURAL_TOL)
            # A factorisation that broke down (NaN) on finite data is not a non-finite
            # problem: the step is not taken and the trial is redone with SVD steps.
            X = jnp.where(finite, jnp.where(trusted, X, 0), nan)
            return X, jnp.asarray(n - n_null), trusted

        def step_of(lin, frames):
            if not fast_allowed:
                return svd_step(lin, frames)
            return jax.lax.cond(use_svd, svd_step, null_step, lin, frames)

        # One linearisation per pass: a pass steps while the iteration runs. With the singular
        # values asked for, the last pass only linearises the final model (for Eqs. 20-21, the
        # cost and the QR + SVD), so that the model (Eq. 9) is compiled once. Without them the
        # loop only steps (the carry then holds no linearisation, 17 kB per trial for the CDRA)
        # and the final model's residual and Eqs. 20-21 are evaluated after it: cheaper than a
        # whole pass, which under vmap every trial of a chunk runs.
        final_pass = singular_values

        def body(carry):
            k, frames, steps, dps, dRs, (rank_lo, rank_hi, resolved), done, ok = carry[:8]
            lin = kernels.linearise(frames, P, T, noise)
            dps = dps.at[k].set(lin.delta_p)
            dRs = dRs.at[k].set(lin.delta_R)
            # A fast step that cannot be trusted means a redo with SVD steps: stop stepping.
            stepping = stepping_at(k, done, ok, resolved)
            X, rank, res = step_of(lin, frames)
            step = jnp.linalg.norm(X)
            finite = jnp.isfinite(step)
            moved = lie.se3_exp(X.reshape(k_frames, 6)) @ frames
            converged = step < tol
            if predictive_stop:
                # What the steps after this one would still move, predicted from the last two:
                # |X_k|^2 / (|X_{k-1}| - |X_k|), the geometric tail (module docstring).
                previous = steps[jnp.maximum(k - 1, 0)]
                tail = (k > 0) & (step * step < PREDICTIVE_MARGIN * tol * (previous - step))
                converged = converged | tail
            out = (
                k + stepping,
                jnp.where(stepping & finite, moved, frames),
                jnp.where(stepping, steps.at[k].set(step), steps),
                dps,
                dRs,
                (
                    jnp.where(stepping, jnp.minimum(rank_lo, rank), rank_lo),
                    jnp.where(stepping, jnp.maximum(rank_hi, rank), rank_hi),
                    resolved & (res | ~stepping),
                ),
                jnp.where(stepping, converged, done),
                jnp.where(stepping, finite, ok),
            )
            return out + (~stepping, lin) if final_pass else out

        def stepping_at(k, done, ok, resolved):
            return (k < max_iterations) & ~done & ok & resolved

        head = (
            jnp.asarray(0),
            frames0,
            jnp.full((max_iterations,), nan),
            jnp.full((max_iterations + 1,), nan),
            jnp.full((max_iterations + 1,), nan),
            (jnp.asarray(n), jnp.asarray(0), jnp.asarray(True)),  # step ranks, all resolved
            jnp.asarray(False),
            finite_in,
        )
        if final_pass:
            lin0 = jax.eval_shape(lambda: kernels.linearise(frames0, P, T, noise))
            init = batched_like(
                finite_in,
                head
                + (
                    jnp.asarray(False),  # finished: the last pass has linearised the final model
                    jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), lin0),
                ),
            )
            k, frames, steps, dps, dRs, steps_ok, done, ok, _, lin = jax.lax.while_loop(
                lambda c: ~c[8], body, init
            )
        else:
            k, frames, steps, dps, dRs, steps_ok, done, ok = jax.lax.while_loop(
                lambda c: stepping_at(c[0], c[6], c[7], c[5][2]),
                body,
                batched_like(finite_in, head),
            )
            tool, _ = kernels.chain(frames, P)
            Y, dp, dR = kernels.residual_and_metrics(T, tool)
            if noise is not None:
                Y = kernels.whiten(Y, T, noise)
            dps = dps.at[k].set(dp)
            dRs = dRs.at[k].set(dR)
            empty = jnp.zeros((n, 0), dtype)  # no Jacobian: the rank is the steps'
            lin = kernels.Linearisation(Y=Y.reshape(-1), DT=empty, delta_p=dp, delta_R=dR)
        rank_lo, rank_hi, resolved = steps_ok
        sol = _solution_at(
            frames,
            frames0,
            lin,
            ok=ok,
            rcond=rcond,
            rank=None if singular_values else rank_hi,
            done=done,
            iterations=k,
            step_norm=steps,
            delta_p=dps,
            delta_R=dRs,
            solver=solver,
        )
        redo = (sol.result != RESULTS.nonfinite) & (k > 0) & fast_allowed & ~use_svd
        redo = redo & ((rank_lo != sol.rank) | (rank_hi != sol.rank) | ~resolved)
        return sol, redo

    return chunked_vmap(run, CHUNK_SIZE, second_pass=True)
