"""The compiled pieces of a diagnosis: whitened residual of the extended model, its Jacobian,
the geometric fit and the joint (geometric + physical) Levenberg-Marquardt refit.

The parameters of the extended model are ``y = (X, theta)``: the error twists ``X (6 (K+1),)``
left-multiplied on the fixed frames of a reference model (Eqs. 11-14) and the physical
parameters ``theta (p,)`` of the feature columns (:class:`cdra_jax.physics.Features`). The
residual is the whitened Eq. 7 twist of every pose, stacked ``(6 m,)``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .. import lie
from ..arm import Arm
from ..calibration import calibrate_paper
from ..calibration.model import residual_twist
from ..compilation import filter_jit
from ..physics import Aux, Candidate, Features, corrected_tool_pose


@filter_jit
def all_features(cands: tuple[Candidate, ...], arm: Arm, q: Array, aux: Aux) -> Features:
    """Features of every candidate in ``cands`` (static), concatenated; compiled once."""
    return Features.concatenate([c.features(arm, q, aux) for c in cands])


def whitened_residual(
    y: Array, arm: Arm, q: Array, measured: Array, G: Array, features: Features
) -> Array:
    """``(6 m,)`` whitened residual ``G log(T_meas T(y)^-1)^v`` of the extended model."""
    n = arm.n_params
    X = y[:n].reshape(-1, 6)
    theta = y[n:]
    moved = arm.with_frames(lie.se3_exp(X) @ jnp.asarray(arm.frames, y.dtype))
    tool = corrected_tool_pose(moved, q, features, theta)
    Y = residual_twist(measured, tool)
    return jnp.einsum("mij,mj->mi", G, Y).reshape(-1)


@filter_jit
def residual_and_jacobian(
    y: Array, arm: Arm, q: Array, measured: Array, G: Array, features: Features
) -> tuple[Array, Array]:
    """Residual ``(6 m,)`` and its Jacobian ``(6 m, len(y))`` (``jax.jacfwd``), compiled once
    per shape."""
    fn = lambda yy: whitened_residual(yy, arm, q, measured, G, features)
    return fn(y), jax.jacfwd(fn)(y)


@filter_jit
def geometric_fit(arm: Arm, q: Array, measured: Array, noise):
    """Weighted Gauss-Newton of the paper (:func:`cdra_jax.calibration.calibrate_paper`)."""
    return calibrate_paper(arm, q, measured, noise, max_iterations=30, throw=False)


def joint_refit(
    y0: np.ndarray,
    free: np.ndarray,
    arm: Arm,
    q: Array,
    measured: Array,
    G: Array,
    features: Features,
    *,
    max_steps: int = 50,
    rtol: float = 1e-10,
) -> tuple[np.ndarray, bool, int]:
    """Levenberg-Marquardt on the whitened residual over the entries ``free`` of ``y``.

    The frame errors and the selected candidate's parameters are refitted jointly; the other
    entries of ``y0`` stay fixed. Each step calls the compiled :func:`residual_and_jacobian`
    of the full extended model (compiled once for the whole diagnosis, whichever candidate is
    selected) and solves the damped, column-scaled step ``[J D; sqrt(lam) I] dz = [-r; 0]``
    by rank-revealing least squares (the frame errors have 2 unidentifiable directions). An
    optimistix LM compiles its own program per problem, which costs most of a minute on two
    CPU cores for this model; this loop adds no compile at all.

    Returns:
        ``(y, converged, steps)``.
    """
    y = np.array(y0, float)
    dtype = jnp.asarray(arm.frames).dtype

    def evaluate(yy):
        r, J = residual_and_jacobian(jnp.asarray(yy, dtype), arm, q, measured, G, features)
        return np.asarray(r, float), np.asarray(J, float)[:, free]

    r, J = evaluate(y)
    cost = float(r @ r)
    norms = np.linalg.norm(J, axis=0)
    scale = np.where(norms > 0, 1.0 / np.where(norms > 0, norms, 1.0), 1.0)
    lam = 1e-6
    steps = 0
    converged = False
    for steps in range(1, max_steps + 1):  # noqa: B007
        Js = J * scale
        A = np.vstack([Js, np.sqrt(lam) * np.eye(Js.shape[1])])
        b = np.concatenate([-r, np.zeros(Js.shape[1])])
        dz = np.linalg.lstsq(A, b, rcond=1e-12)[0]
        trial = y.copy()
        trial[free] += scale * dz
        r_t, J_t = evaluate(trial)
        cost_t = float(r_t @ r_t)
        if np.isfinite(cost_t) and cost_t <= cost:
            small = cost - cost_t <= rtol * max(cost, 1e-300) or np.linalg.norm(dz) < 1e-10
            y, r, J, cost = trial, r_t, J_t, cost_t
            lam = max(lam / 10.0, 1e-12)
            if small:
                converged = True
                break
        else:
            lam *= 10.0
            if lam > 1e12:
                break
    return y, converged, steps
