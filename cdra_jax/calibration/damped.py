"""Levenberg-Marquardt on the host, for residuals whose Jacobian comes from a compiled function.

The robust ``auto`` solver, the calibration of a model with effects and the diagnosis' joint
refit each minimise ``|r(u)|^2`` over a few dozen parameters, with a compiled ``(r, J)`` and a
handful of steps between reweighting rounds. A compiled loop would compile one more
program per problem (most of a minute on two CPU cores for the extended models); this loop adds
no compilation, and its rank-revealing step takes no component along directions the data do
not determine.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

Linearisation = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
"""``f(u) -> (r (N,), J (N, n))``: the residual and its Jacobian at ``u``."""


@dataclass
class DampedSolution:
    """What :func:`levenberg_marquardt` returns.

    Attributes:
        u: the parameters at the end.
        converged: the cost stopped decreasing (relative change below ``rtol``, a vanishing
            step, or no damped step decreases it: the minimum to rounding).
        steps: accepted steps.
        finite: the residual and Jacobian stayed finite.
        r, J: the residual and Jacobian at ``u``.
    """

    u: np.ndarray
    converged: bool
    steps: int
    finite: bool
    r: np.ndarray
    J: np.ndarray


def levenberg_marquardt(
    f: Linearisation,
    u0: np.ndarray,
    *,
    max_steps: int = 50,
    rtol: float = 1e-10,
    on_accept: Callable[[np.ndarray, float], None] | None = None,
) -> DampedSolution:
    """Minimise ``|r(u)|^2`` from ``u0`` by Levenberg-Marquardt.

    Each step solves the damped, column-scaled problem ``[J S; sqrt(lam) I] dz = [-r; 0]``
    (``S`` the inverse column norms of the first Jacobian) by rank-revealing least squares, so
    that columns of very different units (mm, rad, compliances) are treated alike and the step
    has no component along directions that ``J`` does not see. A step is accepted when the cost
    does not rise (``lam`` / 10), else ``lam`` x 10.

    Args:
        f: the linearisation (:data:`Linearisation`).
        u0: ``(n,)`` the start.
        max_steps: accepted steps at most (and ten times as many tries).
        rtol: relative decrease of the cost below which it has converged.
        on_accept: called as ``on_accept(u, step_norm)`` after every accepted step.
    """
    u = np.array(u0, dtype=float)
    r, J = f(u)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
        return DampedSolution(u, False, 0, False, r, J)
    cost = float(r @ r)
    norms = np.linalg.norm(J, axis=0)
    scale = np.where(norms > 0, 1.0 / np.where(norms > 0, norms, 1.0), 1.0)
    lam = 1e-6
    steps = tries = 0
    while steps < max_steps and tries < 10 * max_steps:
        tries += 1
        Js = J * scale
        A = np.vstack([Js, np.sqrt(lam) * np.eye(Js.shape[1])])
        b = np.concatenate([-r, np.zeros(Js.shape[1])])
        dz = np.linalg.lstsq(A, b, rcond=1e-12)[0]
        du = scale * dz
        r_t, J_t = f(u + du)
        cost_t = float(r_t @ r_t)
        if np.isfinite(cost_t) and cost_t <= cost and np.all(np.isfinite(J_t)):
            small = cost - cost_t <= rtol * max(cost, 1e-300) or np.linalg.norm(dz) < 1e-12
            u, r, J, cost = u + du, r_t, J_t, cost_t
            steps += 1
            lam = max(lam / 10.0, 1e-12)
            if on_accept is not None:
                on_accept(u, float(np.linalg.norm(du)))
            if small or cost == 0.0:
                return DampedSolution(u, True, steps, True, r, J)
        else:
            lam *= 10.0
            if lam > 1e12:  # no damped step decreases the cost: at the minimum to rounding
                return DampedSolution(u, True, steps, True, r, J)
    return DampedSolution(u, False, steps, True, r, J)
