"""The compiled pieces of a diagnosis: whitened residual of the extended model, its Jacobian,
the geometric fit and the joint (geometric + physical) Levenberg-Marquardt refit.

The parameters of the extended model are ``y = (X, dx, theta)``: the error twists
``X (6 (K+1),)`` left-multiplied on the fixed frames of a reference model (Eqs. 11-14), the
corrections ``dx (3 c,)`` of the ``c`` calibrated marker positions (mm, tool frame) and the
physical parameters ``theta (p,)`` of the feature columns (:class:`cdra_jax.physics.Features`):
first those of the model's own ``[[effects]]`` (part of the base model, fitted with the frames),
then those of the candidates.
The residual is the stacked whitened residual of :mod:`cdra_jax.calibration.observations`: the
Eq. 7 twist of every full pose, then every measured point (``6 m + 3 m P`` entries, exact zeros
where nothing was measured).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from ..arm import Arm
from ..calibration import calibrate_paper
from ..calibration.damped import levenberg_marquardt
from ..calibration.observations import Observations, apply_parameters, stacked_residual
from ..compilation import filter_jit
from ..physics import Aux, Candidate, Features
from ..physics.base import feature_corrections, perturbed_tool_pose, stacked_features


@functools.partial(filter_jit, fast_compile=True)
def all_features(cands: tuple[Candidate, ...], arm: Arm, q: Array, aux: Aux) -> Features:
    """Features of every candidate in ``cands`` (static), concatenated; compiled once, without
    XLA's optimisation passes (``fast_compile``: one large program that runs once per
    diagnosis, in milliseconds either way). Built by
    :func:`cdra_jax.physics.base.stacked_features` (terms that several forms need enter the
    program once, one pass finds the rounding-level columns of all candidates): for the default
    arm's 110 candidates and 30 poses it traces and compiles in 4.6 s, against 14.2 s for each
    candidate's own features concatenated (``benchmarks/diagnosis_compile.py``; the same
    features to 2e-17 of each column's largest entry)."""
    return stacked_features(cands, arm, q, aux)


class Extended(eqx.Module):
    """Everything the extended model's residual needs besides ``y`` (one diagnosis).

    Attributes:
        arm: the reference model (its frames are where ``X = 0``).
        q: ``(m, dof)`` module states.
        obs: the measured full poses and points (:class:`~cdra_jax.calibration.observations.
            Observations`).
        sigma_pos, sigma_rot: ``(m,)`` standard deviations of the full poses' position (mm)
            and rotation (rad), ``inf`` where a row has none.
        sigma_pt: ``(m, P)`` those of the points (mm), ``inf`` where not seen.
        xyz: ``(P, 3)`` reference tool-frame positions of the points (mm; ``0``: the origin).
        calibrated: indices of the points whose position is a parameter (static).
        features: the feature columns: the model's own effects, then the candidates.
        n_model_effects: how many leading feature columns are the model's own effects (static).
    """

    arm: Arm
    q: Array
    obs: Observations
    sigma_pos: Array
    sigma_rot: Array
    sigma_pt: Array
    xyz: Array
    features: Features
    calibrated: tuple[int, ...] = eqx.field(static=True, default=())
    n_model_effects: int = eqx.field(static=True, default=0)

    @property
    def n_frames_markers(self) -> int:
        """Entries of ``(X, dx)``: ``6 (K+1) + 3 c``."""
        return self.arm.n_params + 3 * len(self.calibrated)

    @property
    def n_geometric(self) -> int:
        """Entries of the base model (everything fitted before any candidate): ``(X, dx)`` and
        the parameters of the model's own effects."""
        return self.n_frames_markers + self.n_model_effects


def whitened_residual(y: Array, problem: Extended) -> Array:
    """``(6 m + 3 m P,)`` whitened residual of the extended model at ``y`` (module docstring)."""
    n = problem.n_frames_markers
    corrections = feature_corrections(problem.features, jnp.asarray(y[n:], problem.q.dtype))
    return _residual_at(y[:n], corrections, problem)


def _residual_at(
    y_frames: Array, corrections: tuple[Array, Array, Array], problem: Extended
) -> Array:
    """The whitened residual at the frame and marker entries ``y_frames (6 (K+1) + 3 c,)`` of
    ``y`` and the per-pose corrections (:func:`cdra_jax.physics.base.feature_corrections`)
    that its physical parameters make."""
    frames, xyz = apply_parameters(
        y_frames, jnp.asarray(problem.arm.frames, y_frames.dtype), problem.xyz, problem.calibrated
    )
    tool = perturbed_tool_pose(problem.arm.with_frames(frames), problem.q, *corrections)
    return stacked_residual(
        tool, xyz, problem.obs, problem.sigma_pos, problem.sigma_rot, problem.sigma_pt
    )


def residual_and_jacobian(y: Array, problem: Extended) -> tuple[Array, Array]:
    """Residual ``(N,)`` and its Jacobian ``(N, len(y))``, every column.

    The frame and marker columns by forward mode, one tangent each; the physical parameters'
    (hundreds: every candidate's) through the per-pose corrections that they move, by the chain
    rule: the corrections ``u_i = F_i theta`` of pose ``i`` (``dof + 6 K + 6 (K+1)`` entries)
    are linear in ``theta`` and move only that pose's rows, so ``dr_i/dtheta = (dr_i/du_i)
    F_i``, with ``dr/du`` from one tangent per correction entry (the same unit entry at every
    pose): ``dof + 12 K + 6`` tangents (49 for the CDRA) instead of one per parameter. Equal to
    ``jax.jacfwd`` of :func:`whitened_residual` to rounding."""
    return _residual_and_full_jacobian(y, problem)


@filter_jit
def _residual_and_full_jacobian(y: Array, problem: Extended) -> tuple[Array, Array]:
    """:func:`residual_and_jacobian`, compiled once per problem shape."""
    n = problem.n_frames_markers
    m = problem.q.shape[0]
    f = problem.features
    corrections = feature_corrections(f, jnp.asarray(y[n:], problem.q.dtype))
    r, tangent = jax.linearize(lambda yf, u: _residual_at(yf, u, problem), y[:n], corrections)
    shapes = [u.shape[1:] for u in corrections]
    sizes = [int(np.prod(s)) for s in shapes]

    def at_every_pose(v: Array) -> tuple[Array, ...]:
        """A tangent of the corrections: the same ``v (sum(sizes),)`` at every pose."""
        parts = jnp.split(v, np.cumsum(sizes)[:-1])
        return tuple(
            jnp.broadcast_to(p.reshape(s), (m, *s)) for p, s in zip(parts, shapes, strict=True)
        )

    no_frames = jnp.zeros(n, y.dtype)
    no_corrections = tuple(jnp.zeros_like(u) for u in corrections)
    J_frames = jax.vmap(lambda t: tangent(t, no_corrections))(jnp.eye(n, dtype=y.dtype)).T
    if f.n_params == 0:  # no physical parameters: the base model of a model without effects
        return r, J_frames
    dr_du = jax.vmap(lambda v: tangent(no_frames, at_every_pose(v)))(
        jnp.eye(sum(sizes), dtype=y.dtype)
    )  # (dof + 12 K + 6, N)
    F = jnp.concatenate(
        [a.reshape(m, -1, f.n_params) for a in (f.state, f.module_twist, f.frame_deflection)],
        axis=1,
    )  # (m, dof + 12 K + 6, p): u_i = F_i theta
    poses, points = dr_du[:, : 6 * m], dr_du[:, 6 * m :]  # rows pose-major (stacked_residual)
    J_theta = jnp.concatenate(
        [
            jnp.einsum("cmr,mcp->mrp", part.reshape(part.shape[0], m, -1), F).reshape(
                -1, f.n_params
            )
            for part in (poses, points)
        ]
    )
    return r, jnp.concatenate([J_frames, J_theta.astype(J_frames.dtype)], axis=1)


def residual_and_columns(
    y: Array, problem: Extended, columns: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residual ``(N,)`` and the columns ``columns`` (indices into ``y``) of its Jacobian,
    ``(N, len(columns))``, as numpy arrays: the columns of :func:`residual_and_jacobian`, so
    that the refits of a problem share its one compiled program whichever entries of ``y`` they
    free (the analyser forms every column at each refit's solution anyway). Forward mode with
    one tangent per free column (the frames and a candidate's parameters, a few dozen) runs
    quicker per step but is a program of its own for every number of free columns
    (``python benchmarks/diagnosis_jacobian.py``: 30 poses, 25 free columns, 7.0 ms per step
    sliced against 3.8 ms, and 1.96 s to compile the latter's program)."""
    r, J = _residual_and_full_jacobian(y, problem)
    return np.asarray(r), np.asarray(J)[:, np.asarray(columns, int)]


@filter_jit
def geometric_fit(arm: Arm, q: Array, measured: Array, noise):
    """Weighted Gauss-Newton of the paper (:func:`cdra_jax.calibration.calibrate_paper`)."""
    return calibrate_paper(arm, q, measured, noise, max_iterations=30, throw=False)


def joint_refit(
    y0: np.ndarray,
    free: np.ndarray,
    problem: Extended,
    *,
    max_steps: int = 50,
    rtol: float = 1e-10,
) -> tuple[np.ndarray, bool, int, tuple[np.ndarray, np.ndarray]]:
    """Levenberg-Marquardt on the whitened residual over the entries ``free`` of ``y``.

    The frame errors and the selected candidate's parameters are refitted jointly; the other
    entries of ``y0`` stay fixed. Each step calls :func:`residual_and_columns` of the full
    extended model (the features of every candidate; one compiled program per problem,
    whichever candidate is selected) inside
    :func:`cdra_jax.calibration.damped.levenberg_marquardt` (rank-revealing steps: the frame
    errors have unidentifiable directions; no compilation of its own).

    Returns:
        ``(y, converged, steps, (r, J))`` with ``r (N,)`` the residual and ``J (N, len(y))``
        the Jacobian of every entry of ``y`` at the solution (:func:`residual_and_jacobian`,
        once).
    """
    y = np.array(y0, float)
    dtype = jnp.asarray(problem.arm.frames).dtype

    def evaluate(u):
        yy = y.copy()
        yy[free] = u
        r, J = residual_and_columns(jnp.asarray(yy, dtype), problem, free)
        return np.asarray(r, float), np.asarray(J, float)

    sol = levenberg_marquardt(evaluate, y[free], max_steps=max_steps, rtol=rtol)
    y[free] = sol.u
    # every column at the solution, once (the other candidates are scored there)
    r, J = residual_and_jacobian(jnp.asarray(y, dtype), problem)
    return y, sol.converged, sol.steps, (np.asarray(r, float), np.asarray(J, float))
