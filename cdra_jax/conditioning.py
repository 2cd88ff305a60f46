"""How well a pose set determines the identifiable frame errors: the conditioning check.

:func:`cdra_jax.identifiability.analyze` finds the directions a pose set loses entirely (the
rank). A pose set can keep its rank and still pin some directions down badly: all poses nearly
the same, the elbow barely moving. The solvers then return an answer whose component along
those directions is dominated by measurement noise (and amplified by it). This module measures
that and names the directions.

Measure. The condition number (:func:`cdra_jax.identifiability.scaled_svd`, the package's one
definition) ``s_max / s_min`` (over the numerically nonzero singular values,
same ``rcond`` as the solvers) of the **column-scaled** stacked Jacobian ``D~ S`` of Eq. 9,
``S = diag(1 / ||column_j||)``. Column scaling removes the unit mix of the parameters (mm and
rad) and the arbitrary size of each one, so the number compares pose sets, not units (the usual
scaled observability index of robot calibration). The rows are those the solver sees: whitened
by the noise model when one is given, the paper's unweighted twist otherwise.

Threshold: :data:`CONDITION_WARNING` ``= 1e3``. Measured on the CDRA (20-pose sets unless
stated): random poses within the joint limits give ``~20-60`` with a noise model
(0.08 mm / 0.001 rad) and ``~15-40`` in the paper's unweighted form (``~2500`` for 5 poses in
that form, whose rotation rows carry little weight); poses scattered by ``0.01`` rad around one
pose give ``~3e3`` (weighted) / ``~5e4`` (unweighted); an elbow that moves by ``1e-3`` rad
``~2.5e4``. Above the threshold, a noise level of 0.1 % of the best-determined signal moves the
answer along the weak directions as much as the signal itself.

Weak directions: the right singular vectors of ``D~ S`` whose singular value is below
``s_max / threshold``, mapped back to parameter units (``S v``, unit norm) and written as named
combinations (coefficients below 5 % of the largest dropped), weakest first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from jax.typing import ArrayLike

from .arm import Arm
from .calibration.model import NoiseModel
from .identifiability import format_combination, scaled_svd, stacked_jacobian

CONDITION_WARNING = 1e3
"""Warn when the column-scaled condition number of the stacked Jacobian exceeds this."""
_DROP = 0.05  # coefficients below this fraction of the largest are left out of the text


@dataclass(frozen=True)
class ConditioningReport:
    """Conditioning of the identifiable part of the calibration problem of one pose set.

    Attributes:
        condition_number: condition number of the column-scaled stacked Jacobian.
        threshold: the warning threshold it was compared with.
        rank: numerical rank used (as :func:`~cdra_jax.identifiability.analyze`).
        weak_space: ``(k, n_params)`` weak directions in parameter units (rows, unit norm),
            weakest first.
        weak_directions: the same as text, e.g. ``"0.9 tool.wz - 0.4 base.wz"``.
        weak_singular_values: ``(k,)`` their scaled singular values relative to ``s_max``.
        param_names: parameter names, in the order of the columns.
    """

    condition_number: float
    threshold: float
    rank: int
    weak_space: np.ndarray
    weak_directions: tuple[str, ...]
    weak_singular_values: np.ndarray
    param_names: tuple[str, ...]

    @property
    def ill_conditioned(self) -> bool:
        """True when the condition number exceeds the threshold."""
        return bool(self.condition_number > self.threshold)

    @property
    def warning(self) -> str | None:
        """The warning text, or ``None`` for a well-conditioned pose set."""
        if not self.ill_conditioned:
            return None
        return (
            f"poorly conditioned pose set: condition number {self.condition_number:.3g} of the "
            f"column-scaled Jacobian exceeds {self.threshold:g}; the answer along "
            f"{len(self.weak_directions)} direction(s) is dominated by measurement noise: "
            + "; ".join(self.weak_directions)
            + " (spread the poses over the joint ranges, or move every module)"
        )

    def to_dict(self) -> dict:
        """JSON-ready mapping."""
        return {
            "condition_number": float(self.condition_number),
            "threshold": float(self.threshold),
            "ill_conditioned": self.ill_conditioned,
            "rank": int(self.rank),
            "weak_directions": list(self.weak_directions),
            "weak_relative_singular_values": [float(s) for s in self.weak_singular_values],
        }


def conditioning(
    arm: Arm,
    q: ArrayLike,
    measured: ArrayLike | None = None,
    noise: NoiseModel | None = None,
    *,
    rcond: float | None = None,
    threshold: float = CONDITION_WARNING,
) -> ConditioningReport:
    """Conditioning of the frame-error calibration from the pose set ``q (m, dof)``.

    Args:
        arm: model at which to linearise (the nominal one, or a calibrated one).
        q: ``(m, dof)`` module states.
        measured: optional measured tool poses (for whitening; model poses otherwise).
        noise: optional noise model (rows whitened as the weighted solvers do).
        rcond: relative singular-value cut-off for the rank (default as the solvers).
        threshold: warning threshold on the column-scaled condition number.

    Raises:
        ValueError: ``q`` of the wrong shape.
    """
    q = np.asarray(q, dtype=float)
    if q.ndim != 2 or q.shape[1] != arm.dof or q.shape[0] < 1:
        raise ValueError(
            f"module states must have shape (m, {arm.dof}) with m >= 1 and columns "
            f"{arm.state_names}, got {q.shape}"
        )
    D = stacked_jacobian(arm, q, measured, noise)
    return conditioning_from_jacobian(D, arm.param_names, rcond=rcond, threshold=threshold)


def conditioning_from_jacobian(
    D: np.ndarray,
    names: tuple[str, ...],
    *,
    rcond: float | None = None,
    threshold: float = CONDITION_WARNING,
) -> ConditioningReport:
    """:func:`conditioning` of any stacked (whitened) Jacobian ``D (rows, n)`` whose columns
    are the parameters ``names`` (full poses, points, markers)."""
    D = np.asarray(D, dtype=float)
    if not np.all(np.isfinite(D)):
        raise ValueError("the stacked Jacobian is not finite (NaN or inf in the inputs)")
    cond, rank, s, Vt, scale = scaled_svd(D, rcond)
    weak = [i for i in range(rank - 1, -1, -1) if s[i] * threshold < s[0]]
    dirs = np.array([scale * Vt[i] for i in weak]).reshape(len(weak), D.shape[1])
    if dirs.size:
        dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        for d in dirs:  # sign: largest coefficient positive
            if d[np.argmax(np.abs(d))] < 0:
                d *= -1.0
    text = tuple(format_combination(d, names, tol=_DROP * float(np.max(np.abs(d)))) for d in dirs)
    return ConditioningReport(
        condition_number=cond,
        threshold=float(threshold),
        rank=rank,
        weak_space=dirs,
        weak_directions=text,
        weak_singular_values=np.array([s[i] / s[0] for i in weak]),
        param_names=names,
    )
