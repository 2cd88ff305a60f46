"""Which calibration parameters a pose set can identify (rank, conditioning, null space).

From the nominal model and the module states of a pose set, the stacked Jacobian ``D~`` of
Eq. 9 (optionally whitened by a :class:`~cdra_jax.calibration.NoiseModel`) is decomposed by SVD.
Its numerical rank is the number of identifiable parameter combinations; the right singular
vectors with (numerically) zero singular values are the unidentifiable directions, reported as
named parameter combinations such as ``0.71 upper_arm.wy - 0.71 forearm.wy``. For the paper's
CDRA the rank is 22 of 24: a rotation about the elbow axis and a translation along it can be
moved between ``upper_arm`` and ``forearm`` without changing any tool pose.

The null-space basis is rotated to a readable form: each basis vector is made as sparse as the
subspace allows (a QR with column pivoting of the basis, so that each direction is anchored on
its largest parameter) and small coefficients (``< 1e-9``) are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax.numpy as jnp
import numpy as np
import scipy.linalg
from jax.typing import ArrayLike

from .arm import Arm, chain, module_poses
from .calibration.linear import default_rcond
from .calibration.model import NoiseModel, calibration_jacobian, whitening
from .calibration.validation import MIN_POSES


@dataclass(frozen=True)
class IdentifiabilityReport:
    """Identifiability of the ``n_params`` frame-error parameters from one pose set.

    Attributes:
        rank: numerical rank of the stacked Jacobian.
        n_params: number of parameters, ``6 (K+1)``.
        n_poses: number of poses.
        singular_values: ``(n_params,)`` in decreasing order (zero-padded if fewer rows).
        condition_number: ``s_max / s_min`` over the identifiable directions.
        null_space: ``(n_params - rank, n_params)`` orthonormal basis of unidentifiable
            directions (rows), in readable form.
        unidentifiable: those directions as text, e.g. ``"0.71 upper_arm.wy - 0.71 forearm.wy"``.
        param_names: names of the parameters, in the order of the columns.
        rcond: the relative singular-value cut-off used.
    """

    rank: int
    n_params: int
    n_poses: int
    singular_values: np.ndarray
    condition_number: float
    null_space: np.ndarray
    unidentifiable: tuple[str, ...]
    param_names: tuple[str, ...]
    rcond: float
    warnings: tuple[str, ...] = field(default=())

    @property
    def identifiable(self) -> bool:
        """True when every parameter combination is identifiable (full column rank)."""
        return self.rank == self.n_params

    def to_dict(self) -> dict:
        """JSON-ready mapping (``rank``, ``n_params``, ``unidentifiable`` ...)."""
        return {
            "rank": int(self.rank),
            "n_params": int(self.n_params),
            "n_poses": int(self.n_poses),
            "condition_number": float(self.condition_number),
            "rcond": float(self.rcond),
            "singular_values": [float(s) for s in self.singular_values],
            "unidentifiable": list(self.unidentifiable),
            "null_space": [
                {n: float(c) for n, c in zip(self.param_names, row, strict=True) if c != 0.0}
                for row in self.null_space
            ],
            "warnings": list(self.warnings),
        }

    def summary(self) -> str:
        """Multi-line plain-text summary."""
        lines = [
            f"identifiability: rank {self.rank} of {self.n_params} parameters from "
            f"{self.n_poses} poses, condition number {self.condition_number:.3g}"
        ]
        for d in self.unidentifiable:
            lines.append(f"  unidentifiable: {d}")
        for w in self.warnings:
            lines.append(f"  warning: {w}")
        return "\n".join(lines)


def stacked_jacobian(
    arm: Arm, q: ArrayLike, measured: ArrayLike | None = None, noise: NoiseModel | None = None
) -> np.ndarray:
    """``D~ (6m, 6(K+1))`` of Eq. 9 at the model ``arm`` (whitened when ``noise`` is given).

    Whitening needs the tool positions; without ``measured`` the model's are used.
    """
    q = jnp.asarray(q, jnp.asarray(arm.frames).dtype)
    tool, after = chain(arm.frames, module_poses(arm, q))
    D = calibration_jacobian(after)
    G = whitening(tool if measured is None else jnp.asarray(measured), noise)
    if G is not None:
        D = G @ D
    return np.asarray(D.reshape(-1, D.shape[-1]))


def format_combination(coeffs: np.ndarray, names: tuple[str, ...], tol: float = 1e-9) -> str:
    """``"0.71 upper_arm.wy - 0.71 forearm.wy"`` from coefficients and parameter names."""
    order = np.argsort(-np.abs(coeffs), kind="stable")
    parts = []
    for i in order:
        c = coeffs[i]
        if abs(c) < tol:
            continue
        mag = f"{abs(c):.3g}"
        if not parts:
            parts.append(("-" if c < 0 else "") + f"{mag} {names[i]}")
        else:
            parts.append(("- " if c < 0 else "+ ") + f"{mag} {names[i]}")
    return " ".join(parts) if parts else "0"


def _readable_basis(N: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Rotate an orthonormal basis (columns) of a subspace into a sparse, readable one (rows)."""
    if N.shape[1] == 0:
        return np.zeros((0, N.shape[0]))
    # Pivoted QR of N^T picks, for each direction, the parameter that dominates it; reduce the
    # basis to that "echelon" form, then orthonormalise in pivot order (Gram-Schmidt keeps the
    # sparsity pattern of the first vectors).
    _, _, piv = scipy.linalg.qr(N.T, pivoting=True)
    k = N.shape[1]
    B = N @ np.linalg.solve(N[piv[:k], :], np.eye(k))  # B[piv[:k]] = I
    Q, _ = np.linalg.qr(B)
    # Fix signs so that each vector's largest entry is positive.
    for j in range(k):
        i = np.argmax(np.abs(Q[:, j]))
        if Q[i, j] < 0:
            Q[:, j] = -Q[:, j]
    Q[np.abs(Q) < tol] = 0.0
    return Q.T


def analyze(
    arm: Arm,
    q: ArrayLike,
    measured: ArrayLike | None = None,
    noise: NoiseModel | None = None,
    *,
    rcond: float | None = None,
    allow_underdetermined: bool = False,
) -> IdentifiabilityReport:
    """Identifiability of the frame errors of ``arm`` from the pose set ``q (m, dof)``.

    Args:
        arm: model at which to linearise (the nominal one, or a calibrated one).
        q: module states of the pose set.
        measured: optional measured tool poses (for whitening; model poses otherwise).
        noise: optional noise model; singular values are then in units of the noise.
        rcond: relative singular-value cut-off (default as the solvers, ``eps ** (2/3)``).
        allow_underdetermined: accept fewer than 4 poses.

    Raises:
        ValueError: fewer than 4 poses (the paper's lower bound) without
            ``allow_underdetermined``, or a state array of the wrong shape.
    """
    q = np.asarray(q, dtype=float)
    if q.ndim != 2 or q.shape[1] != arm.dof:
        raise ValueError(
            f"module states must have shape (m, {arm.dof}) with columns {arm.state_names}, "
            f"got {q.shape}"
        )
    m = q.shape[0]
    if m < MIN_POSES and not allow_underdetermined:
        raise ValueError(
            f"{m} poses given; the calibration needs at least {MIN_POSES} (Section IV, Eq. 9). "
            "Pass allow_underdetermined=True to analyse an underdetermined pose set."
        )
    D = stacked_jacobian(arm, q, measured, noise)
    n = D.shape[1]
    rcond = default_rcond(D.dtype) if rcond is None else float(rcond)
    _, s, Vt = np.linalg.svd(D, full_matrices=True)
    s_full = np.zeros(n)
    s_full[: s.size] = s
    keep = s_full > rcond * s_full[0] if s_full[0] > 0 else np.zeros(n, bool)
    rank = int(keep.sum())
    null = _readable_basis(Vt[rank:].T)
    names = arm.param_names
    text = tuple(format_combination(v, names) for v in null)
    cond = float(s_full[0] / s_full[rank - 1]) if rank > 0 else float("inf")
    warns = []
    if m < MIN_POSES:
        warns.append(f"only {m} poses: fewer than the paper's lower bound of {MIN_POSES}")
    if rank < n:
        warns.append(
            f"{n - rank} parameter combination(s) cannot be identified from tool poses; the "
            "solvers return the minimum-norm answer, which leaves them at their nominal values"
        )
    return IdentifiabilityReport(
        rank=rank,
        n_params=n,
        n_poses=m,
        singular_values=s_full,
        condition_number=cond,
        null_space=null,
        unidentifiable=text,
        param_names=names,
        rcond=rcond,
        warnings=tuple(warns),
    )
