"""Result codes and the solution object shared by the calibration solvers."""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from ..arm import Arm, error_twists, module_axes, module_poses
from . import implicit, kernels
from .model import NoiseModel
from .validation import check_noise, check_problem


class RESULTS(eqx.Enumeration):
    """Per-trial outcome of a calibration solve (one entry per trial under ``vmap``)."""

    successful = ""
    max_iterations_reached = (
        "the calibration did not converge within max_iterations; raise it or loosen tol"
    )
    nonfinite = "a non-finite value (NaN or inf) appeared in the measurements or the iterates"


class CalibrationSolution(eqx.Module):
    """What a calibration solver returns (batched leading dimensions under ``vmap``).

    Attributes:
        frames: calibrated fixed transforms ``(..., K+1, 4, 4)`` (T^c of Eq. 19).
        errors: identified error twists w.r.t. the nominal frames ``(..., K+1, 6)``
            (Eqs. 15-18, ``(v, w)``, mm and rad).
        result: :class:`RESULTS` code.
        iterations: number of steps taken ``(...)``.
        step_norm: ``||X||`` of each step ``(..., max_iterations)``, NaN past the last step.
        delta_p: Eq. 20 on the fitting poses ``(..., max_iterations + 1)``: entry 0 for the
            nominal model, entry k after k steps, NaN past the end (mm).
        delta_R: the same for Eq. 21 (rad).
        rank: numerical rank of the (weighted) stacked Jacobian at the solution ``(...)``.
        singular_values: its singular values ``(..., n_params)``; NaN where the solver was
            called with ``singular_values=False`` (the rank is then the solve's own: the
            generic rank of :mod:`.nullspace`, or that of its SVD steps).
        cost: final weighted sum of squared residuals (paper form: unweighted) ``(...)``.
        solver: ``"paper"``, ``"weighted"``, ``"lm"`` or ``"lm_optimistix"``.

    Derivatives (``jax.grad``, ``jax.jvp``, ...): ``frames``, ``errors`` and ``cost`` carry the
    derivative of the solution with respect to the data through its optimality condition
    (:mod:`.implicit`); the other fields are diagnostics with zero derivative.
    """

    frames: Array
    errors: Array
    result: RESULTS
    iterations: Array
    step_norm: Array
    delta_p: Array
    delta_R: Array
    rank: Array
    singular_values: Array
    cost: Array
    solver: str = eqx.field(static=True)

    def calibrated_arm(self, nominal: Arm) -> Arm:
        """The nominal arm with the calibrated frames (Eq. 19).

        For a batched solution the arm's frames are batched too ``(..., K+1, 4, 4)``: map
        per-trial functions over it with ``jax.vmap``.
        """
        return nominal.with_frames(self.frames)

    @property
    def converged(self) -> Array:
        """Boolean ``(...)``: the solve ended with :attr:`RESULTS.successful`."""
        return self.result == RESULTS.successful

    @property
    def final_delta_p(self) -> Array:
        """Eq. 20 after the last step ``(...)``."""
        return jnp.take_along_axis(self.delta_p, self.iterations[..., None], axis=-1)[..., 0]

    @property
    def final_delta_R(self) -> Array:
        """Eq. 21 after the last step ``(...)``."""
        return jnp.take_along_axis(self.delta_R, self.iterations[..., None], axis=-1)[..., 0]


def dtype_default(value: float | None, dtype, *, float64: float, float32: float) -> float:
    """``value``, or where it is ``None`` the default of a solve in ``dtype``: ``float64`` for
    float64 problems, ``float32`` otherwise (the only other dtype that
    :func:`.validation.check_problem` gives, e.g. float64 input with x64 disabled)."""
    if value is not None:
        return value
    return float64 if jnp.dtype(dtype) == jnp.float64 else float32


def result_names(result: RESULTS) -> np.ndarray:
    """Name (``"successful"``, ``"max_iterations_reached"``, ...) of each entry of a code."""
    names = list(RESULTS._name_to_item)
    idx = np.asarray(result._value)
    return np.vectorize(lambda i: names[int(i)], otypes=[object])(idx)


def result_messages(result: RESULTS) -> np.ndarray:
    """Human-readable message of each entry of a (batched) result code."""
    msgs = [m or "successful" for m in RESULTS._index_to_message]
    idx = np.asarray(result._value)
    return np.vectorize(lambda i: msgs[int(i)], otypes=[object])(idx)


def _solve_problem(
    make_solver: Callable[[np.dtype], Callable[..., CalibrationSolution]],
    arm: Arm,
    q: ArrayLike,
    measured: ArrayLike,
    noise: NoiseModel | None,
    *,
    allow_underdetermined: bool,
    throw: bool,
    extra: Callable[[np.dtype], tuple[Array, ...]] | None = None,
) -> CalibrationSolution:
    """Check a calibration problem, run a per-trial solver on it and apply ``throw``.

    ``make_solver(dtype)`` gives one of the solvers' compiled per-trial functions for the
    problem's dtype (float32 or float64: the default tolerances depend on it),
    ``solve(frames0 (K+1, 4, 4), q (m, dof), measured (m, 4, 4), axes (K, 3)[, extra...][,
    s_pos, s_rot])``: the solver computes the module poses itself
    (:func:`~cdra_jax.arm.module_poses` with the modules' ``axes``, :func:`~cdra_jax.arm.
    module_axes`), per chunk of trials under ``vmap`` rather than for the whole batch; the
    noise stds (scalars, or ``(m,)`` per pose) are passed only when a noise model is given.
    Shapes are checked by :func:`.validation.check_problem` and
    :func:`.validation.check_noise` (``ValueError`` at trace time). ``extra(dtype)``: further
    arrays the solver takes after the modules' axes (the structural null generators of
    :mod:`.nullspace`), without derivatives.
    """
    q, measured = check_problem(arm, q, measured, allow_underdetermined=allow_underdetermined)
    check_noise(noise, measured.shape[0])
    dtype = measured.dtype
    args: tuple[Array, ...] = (jnp.asarray(arm.frames, dtype), module_poses(arm, q), measured)
    if noise is not None:
        args += (jnp.asarray(noise.position_mm, dtype), jnp.asarray(noise.rotation_rad, dtype))
    # The solvers iterate; their derivatives come from the optimality condition instead
    # (:mod:`.implicit`), so the iterations run on inputs without derivatives.
    more = (module_axes(arm, dtype),) + (() if extra is None else tuple(extra(dtype)))
    solver_args = (args[0], q, measured) + more + args[3:]
    sol = make_solver(dtype)(*jax.lax.stop_gradient(solver_args))
    frames, errors, cost = implicit.attach(
        "lm" if sol.solver in ("lm", "lm_optimistix") else "gauss_newton",
        sol.frames,
        sol.errors,
        sol.cost,
        sol.rank,
        *args,
    )
    sol = eqx.tree_at(lambda s: (s.frames, s.errors, s.cost), sol, (frames, errors, cost))
    if throw:
        sol = sol.result.error_if(sol, sol.result != RESULTS.successful)
    return sol


def _assemble_solution(
    frames: Array,
    nominal: Array,
    *,
    ok: Array,
    done: Array,
    iterations: Array,
    step_norm: Array,
    delta_p: Array,
    delta_R: Array,
    rank: Array,
    singular_values: Array,
    cost: Array,
    solver: str,
) -> CalibrationSolution:
    """The :class:`CalibrationSolution` of a finished (unbatched) solve.

    The result code is ``nonfinite`` unless ``ok``, else ``successful`` when ``done`` and
    ``max_iterations_reached`` otherwise; the errors are ``log(F^c F^-1)`` against the
    ``nominal`` frames ``(K+1, 4, 4)`` (Eqs. 15-18); the singular values are padded with zeros
    to ``6 (K+1)`` (fewer than that when ``6 m < n``).
    """
    result = RESULTS.where(
        ok,
        RESULTS.where(done, RESULTS.successful, RESULTS.max_iterations_reached),  # type: ignore[arg-type]
        RESULTS.nonfinite,  # type: ignore[arg-type]
    )
    n = 6 * nominal.shape[-3]
    return CalibrationSolution(
        frames=frames,
        errors=error_twists(frames, nominal),
        result=result,
        iterations=iterations,
        step_norm=step_norm,
        delta_p=delta_p,
        delta_R=delta_R,
        rank=rank,
        singular_values=jnp.pad(singular_values, (0, max(0, n - singular_values.shape[-1]))),
        cost=cost,
        solver=solver,
    )


def _singular_values(DT: Array, rcond: float | None) -> tuple[Array, Array]:
    """The singular values of ``D~`` (given transposed, ``(n, 6m)``) and its rank (cut-off
    ``rcond``, default :func:`.linear.default_rcond`): ``(s (min(n, 6m),), rank)``."""
    from .linear import default_rcond

    # The singular values of D~ (6m x n) are those of the triangular factor of its QR
    # decomposition (Householder, backward stable): an SVD of n x n instead of 6m x n.
    s = jnp.linalg.svd(jnp.linalg.qr(DT.T, mode="r"), compute_uv=False)
    rc = default_rcond(DT.dtype) if rcond is None else rcond
    return s, jnp.sum(s > rc * s[..., :1], axis=-1)


def _finished_solution(
    frames: Array,
    frames0: Array,
    poses: Array,
    measured: Array,
    noise: NoiseModel | None,
    *,
    singular_values: bool,
    rcond: float | None,
    rank: Array,
    iterations: Array,
    step_norm: Array,
    delta_p: Array,
    delta_R: Array,
    cost: Array,
    done: Array,
    ok: Array,
    solver: str,
) -> CalibrationSolution:
    """:func:`_assemble_solution` of a solve that recorded its histories and cost as it went
    (``delta_p[iterations]`` and ``delta_R[iterations]`` are those of ``frames``): with
    ``singular_values`` (static) those of the Jacobian at ``frames`` and their rank (a QR and an
    SVD, once), else NaN and ``rank``, the solve's own. ``poses`` ``(K, 3, 4, m)`` and
    ``measured`` ``(3, 4, m)`` in the pose-last layout of :mod:`.kernels`."""
    n = 6 * frames0.shape[-3]
    if singular_values:
        sv, rank = _singular_values(kernels.linearise(frames, poses, measured, noise).DT, rcond)
    else:
        sv = jnp.full((n,), jnp.nan, measured.dtype)
    k = iterations
    return _assemble_solution(
        frames,
        frames0,
        ok=ok & jnp.isfinite(delta_p[k]) & jnp.isfinite(delta_R[k]),
        done=done,
        iterations=k,
        step_norm=step_norm,
        delta_p=delta_p,
        delta_R=delta_R,
        rank=rank,
        singular_values=sv,
        cost=cost,
        solver=solver,
    )
