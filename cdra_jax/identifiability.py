"""Which calibration parameters a pose set can identify (rank, conditioning, null space).

From the nominal model and the module states of a pose set, the stacked Jacobian ``D~`` of
Eq. 9 (optionally whitened by a :class:`~cdra_jax.calibration.NoiseModel`) is decomposed by SVD.
Its numerical rank is the number of identifiable parameter combinations; the right singular
vectors with (numerically) zero singular values are the unidentifiable directions, reported as
named parameter combinations such as ``0.707 mm upper_arm.vy - 0.707 mm forearm.vy``. For the
paper's CDRA the rank is 22 of 24: a rotation about the elbow axis and a translation along it can be
moved between ``upper_arm`` and ``forearm`` without changing any tool pose.

Readable directions. Parameters mix units (mm and rad), so the unidentifiable subspace is
reported in two forms:

* ``directions`` (and the text in ``unidentifiable``): first the rotational directions, then
  the translation-only ones. Each direction is anchored on a parameter of its own (a QR with
  column pivoting chooses the anchors, rotation parameters for the rotational directions) and
  is zero on the anchors of the others, which keeps it sparse. A rotational direction is scaled
  so that its *rotation part has unit norm*; its translation coefficients are then the
  lever-arm translations in mm per rad that must accompany the rotation, e.g. for the CDRA
  ``0.707 rad upper_arm.wy - 0.707 rad forearm.wy - 212 mm upper_arm.vx``: rotate the upper arm
  frame by +a and the forearm frame by -a about the elbow axis (y), and shift the upper arm frame by
  -300 a mm along x, since the elbow axis sits 300 mm from its origin. These lever arms are
  orthogonal to every translation-only direction. A translation-only direction has unit norm
  (mm), e.g. ``0.707 mm upper_arm.vy - 0.707 mm forearm.vy``. Directions are not mutually orthogonal
  in general (for the CDRA they are). The first sizeable coefficient in parameter order is
  positive.
* ``null_space``: an orthonormal basis (Euclidean in the mixed units, as the solvers'
  minimum-norm steps) of the same subspace, the directions above orthonormalised in order;
  use it for projections.

Coefficients below ``1e-9`` are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
import scipy.linalg
from jax.typing import ArrayLike

from .arm import Arm, chain, module_poses
from .calibration.linear import default_rcond, svd_rank
from .calibration.model import NoiseModel, calibration_jacobian, whitening
from .calibration.validation import MIN_POSES, require_finite_states
from .compilation import filter_jit


@dataclass(frozen=True)
class IdentifiabilityReport:
    """Identifiability of the ``n_params`` frame-error parameters from one pose set.

    Attributes:
        rank: numerical rank of the stacked Jacobian.
        n_params: number of parameters, ``6 (K+1)``.
        n_poses: number of poses.
        singular_values: ``(n_params,)`` in decreasing order (zero-padded if fewer rows).
        condition_number: the column-scaled condition number of the stacked Jacobian
            (:func:`scaled_svd`), the one number of conditioning the package reports.
        null_space: ``(n_params - rank, n_params)`` orthonormal basis of the unidentifiable
            subspace (rows), in the order of ``directions``.
        unidentifiable: ``directions`` as text, e.g.
            ``"0.707 mm upper_arm.vy - 0.707 mm forearm.vy"`` (see the module docstring).
        param_names: names of the parameters, in the order of the columns.
        rcond: the relative singular-value cut-off used.
        warnings: plain-text warnings (few poses, rank deficiency, modules that never move).
        directions: ``(n_params - rank, n_params)`` readable basis of the same subspace (rows):
            rotational directions with unit-norm rotation part and lever-arm translations
            (mm/rad), then unit-norm translation-only directions (module docstring).
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
    directions: np.ndarray | None = None

    @property
    def identifiable(self) -> bool:
        """True when every parameter combination is identifiable (full column rank)."""
        return self.rank == self.n_params

    def to_dict(self) -> dict:
        """JSON-ready mapping (``rank``, ``n_params``, ``unidentifiable``, ``directions`` ...)."""
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
            "directions": [
                {n: float(c) for n, c in zip(self.param_names, row, strict=True) if c != 0.0}
                for row in (self.null_space if self.directions is None else self.directions)
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
    return np.asarray(_stacked_jacobian(arm, q, measured, noise))


@filter_jit
def _stacked_jacobian(arm, q, measured, noise):
    # Compiled once per shape: analyze() is called in loops (pose-set design, sweeps).
    tool, after = chain(arm.frames, module_poses(arm, q))
    D = calibration_jacobian(after)
    G = whitening(tool if measured is None else jnp.asarray(measured), noise)
    if G is not None:
        D = G @ D
    return D.reshape(-1, D.shape[-1])


def _is_rotation(name: str) -> bool:
    """``<frame>.wx|wy|wz`` parameters are rotations (rad); ``.vx|vy|vz`` translations (mm)."""
    return name.rsplit(".", 1)[-1].startswith("w")


def format_combination(coeffs: np.ndarray, names: tuple[str, ...], tol: float = 1e-9) -> str:
    """``"0.707 rad upper_arm.wy - 0.707 rad forearm.wy - 212 mm upper_arm.vx"``.

    Each coefficient carries the unit of its parameter (``rad`` for the rotation components
    ``w*``, ``mm`` for translations and marker positions): the direction is the simultaneous
    change of the listed parameters by these amounts (per unit of the direction: a rotational
    direction has a unit-norm rotation part, a translation-only one unit norm in mm).
    Rotation parameters come first, then translations; each group by decreasing magnitude
    (ties in parameter order); coefficients below ``tol`` are left out.
    """
    coeffs = np.asarray(coeffs, dtype=float)
    is_trans = np.array([not _is_rotation(n) for n in names])
    # Magnitudes rounded so that equal coefficients (up to rounding) keep the parameter order.
    order = np.lexsort((np.arange(len(names)), -np.round(np.abs(coeffs), 9), is_trans))
    parts: list[str] = []
    for i in order:
        c = coeffs[i]
        if abs(c) < tol:
            continue
        mag = f"{abs(c):.3g} {'rad' if _is_rotation(names[i]) else 'mm'}"
        if not parts:
            parts.append(("-" if c < 0 else "") + f"{mag} {names[i]}")
        else:
            parts.append(("- " if c < 0 else "+ ") + f"{mag} {names[i]}")
    return " ".join(parts) if parts else "0"


def _echelon(N: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Combine the columns of ``N`` so that each is 1 on its own pivot and 0 on the others.

    Pivots are chosen among ``rows`` by a QR with column pivoting (largest entries first).
    """
    _, _, piv = scipy.linalg.qr(N[rows].T, pivoting=True)
    pivots = rows[piv[: N.shape[1]]]
    return N @ np.linalg.inv(N[pivots])


def _normalise(B: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Scale each column to unit norm over ``rows``, its first sizeable entry there positive."""
    B = B / np.linalg.norm(B[rows], axis=0)
    for j in range(B.shape[1]):
        c = B[rows, j]
        first = np.flatnonzero(np.abs(c) > 1e-6 * np.abs(c).max())[0]
        if c[first] < 0:
            B[:, j] = -B[:, j]
    return B


def sparse_basis(N: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Rotate an orthonormal basis (columns) of any subspace into a sparse, readable one (rows).

    A pivoted QR of ``N^T`` picks, for each direction, the parameter that dominates it; the basis
    is reduced to that echelon form and orthonormalised in pivot order (Gram-Schmidt keeps the
    sparsity of the first vectors). Each vector's largest entry is made positive and entries
    below ``tol`` are zeroed. Used where parameters have no frame/twist structure (e.g. the
    module self-calibration); :func:`readable_directions` is the frame-aware form.
    """
    if N.shape[1] == 0:
        return np.zeros((0, N.shape[0]))
    _, _, piv = scipy.linalg.qr(N.T, pivoting=True)
    k = N.shape[1]
    B = N @ np.linalg.solve(N[piv[:k], :], np.eye(k))  # B[piv[:k]] = I
    Q, _ = np.linalg.qr(B)
    for j in range(k):
        i = np.argmax(np.abs(Q[:, j]))
        if Q[i, j] < 0:
            Q[:, j] = -Q[:, j]
    Q[np.abs(Q) < tol] = 0.0
    return Q.T


def readable_directions(
    N: np.ndarray, names: tuple[str, ...], tol: float = 1e-9
) -> tuple[np.ndarray, np.ndarray]:
    """Readable and orthonormal bases (rows) of the subspace spanned by the columns of ``N``.

    Args:
        N: ``(n_params, k)`` orthonormal basis (columns) of a subspace of parameter space.
        names: parameter names (``<frame>.<vx|vy|vz|wx|wy|wz>``).
        tol: coefficients below it are set to zero.

    Returns:
        ``(directions, orthonormal)``, each ``(k, n_params)``: rotational directions (unit-norm
        rotation part, lever-arm translations in mm/rad) then translation-only directions
        (unit norm), see the module docstring; and the same directions orthonormalised in order.
    """
    n, k = N.shape
    if k == 0:
        return np.zeros((0, n)), np.zeros((0, n))
    rot = np.array([i for i, name in enumerate(names) if _is_rotation(name)], dtype=int)
    trans = np.array([i for i, name in enumerate(names) if not _is_rotation(name)], dtype=int)
    # Split the subspace: combinations with no rotation content, and their orthogonal
    # complement in it (N is orthonormal and the rows of Qt are orthogonal), whose translation
    # parts, the lever arms, are therefore orthogonal to every pure translation.
    _, sw, Qt = np.linalg.svd(N[rot], full_matrices=True)
    r = int(np.sum(sw > 1e-8))
    N_trans = N @ Qt[r:].T
    N_trans[rot] = 0.0
    N_rot = N @ Qt[:r].T
    blocks = []
    if r:
        blocks.append(_normalise(_echelon(N_rot, rot), rot))
    if k - r:
        blocks.append(_normalise(_echelon(N_trans, trans), trans))
    D = np.concatenate(blocks, axis=1)
    D[np.abs(D) < tol] = 0.0
    Q, R = np.linalg.qr(D)
    Q = Q * np.sign(np.diag(R))  # same orientation as the readable directions
    Q[np.abs(Q) < tol] = 0.0
    return D.T, Q.T


def generic_rank(
    arm: Arm, m: int, noise: NoiseModel | None = None, *, rcond: float | None = None
) -> int:
    """The rank that ``m`` poses spread over the joint ranges give: what the model allows.

    The stacked Jacobian at ``m`` module states drawn uniformly within the limits (a fixed
    seed: generic states, rank-deficient only where the model is, e.g. 22 of 24 for the CDRA
    with ``m >= 4``). A pose set whose :func:`analyze` rank is below it is degenerate (repeated
    poses, a module that never moves) rather than the model being unidentifiable.
    """
    lim = np.asarray(arm.state_limits, dtype=float)
    u = np.random.default_rng(0).uniform(size=(m, arm.dof))
    q = lim[:, 0] + u * (lim[:, 1] - lim[:, 0])
    return analyze(arm, q, None, noise, rcond=rcond, allow_underdetermined=True).rank


class ScaledSVD(NamedTuple):
    """SVD of the column-scaled stacked Jacobian ``D S`` (see :func:`scaled_svd`)."""

    condition_number: float
    rank: int
    singular_values: np.ndarray
    Vt: np.ndarray
    scale: np.ndarray


def scaled_svd(D: np.ndarray, rcond: float | None = None) -> ScaledSVD:
    """The condition number of a calibration: ``s_max / s_min`` of the **column-scaled**
    stacked Jacobian ``D S`` (Eq. 9), ``S = diag(1 / ||column_j||)``, over the singular values
    above ``rcond * s_max`` (default as the solvers).

    Column scaling removes the unit mix of the parameters (mm and rad), so the number compares
    pose sets, not units (the scaled observability index of robot calibration). This is the
    one definition the package uses: :func:`analyze` reports it and
    :func:`cdra_jax.conditioning.conditioning` warns on it.

    Args:
        D: ``(rows, n)`` stacked Jacobian (whitened or not).
        rcond: relative singular-value cut-off.

    Returns:
        The condition number (``inf`` at rank 0), the rank, the singular values of ``D S``,
        its right singular vectors ``Vt`` and the column scale ``diag(S)``.
    """
    norms = np.linalg.norm(D, axis=0)
    scale = 1.0 / np.where(norms > 0, norms, 1.0)
    _, s, Vt = np.linalg.svd(D * scale, full_matrices=False)
    rcond = default_rcond(D.dtype) if rcond is None else float(rcond)
    rank = int(np.sum(s > rcond * s[0])) if s.size and s[0] > 0 else 0
    cond = float(s[0] / s[rank - 1]) if rank > 0 else float("inf")
    return ScaledSVD(cond, rank, s, Vt, scale)


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
            ``allow_underdetermined``, or a state array of the wrong shape or with a
            non-finite entry.
    """
    q = np.asarray(q, dtype=float)
    if q.ndim != 2 or q.shape[1] != arm.dof:
        raise ValueError(
            f"module states must have shape (m, {arm.dof}) with columns {arm.state_names}, "
            f"got {q.shape}"
        )
    require_finite_states(arm, q)
    m = q.shape[0]
    if m < MIN_POSES and not allow_underdetermined:
        raise ValueError(
            f"{m} poses given; the calibration needs at least {MIN_POSES} (Section IV, Eq. 9). "
            "Pass allow_underdetermined=True to analyse an underdetermined pose set."
        )
    D = stacked_jacobian(arm, q, measured, noise)
    warns = pose_set_warnings(arm, q)
    return report_from_jacobian(D, arm.param_names, m, rcond=rcond, warnings=warns)


def pose_set_warnings(arm: Arm, q: ArrayLike) -> list[str]:
    """Warnings about a pose set itself: fewer poses than the paper's bound, modules that never
    move."""
    q = np.asarray(q, dtype=float)
    m = q.shape[0]
    warns = []
    if m < MIN_POSES:
        warns.append(f"only {m} poses: fewer than the paper's lower bound of {MIN_POSES}")
    for mod, qi in zip(arm.modules, arm.split_state(q), strict=True):
        if m > 1 and np.all(np.ptp(np.asarray(qi), axis=0) == 0.0):
            warns.append(
                f"module {mod.name!r} never moves in this pose set (constant state): the fixed "
                "frames on either side of it cannot be told apart"
            )
    return warns


def report_from_jacobian(
    D: np.ndarray,
    names: tuple[str, ...],
    n_poses: int,
    *,
    rcond: float | None = None,
    warnings: list[str] | tuple[str, ...] = (),
) -> IdentifiabilityReport:
    """The identifiability of the parameters ``names`` (the columns) from a stacked, whitened
    Jacobian ``D (rows, n)`` of any residual: full poses (Eq. 9), points, markers.

    Frame parameters are ``<frame>.<vx..wz>``; marker positions ``<marker>.x/y/z`` (mm) are
    translations."""
    D = np.asarray(D, dtype=float)
    n = D.shape[1]
    rcond = default_rcond(D.dtype) if rcond is None else float(rcond)
    s_full, Vt, rank = svd_rank(D, rcond)
    directions, null = readable_directions(Vt[rank:].T, names)
    text = tuple(format_combination(v, names) for v in directions)
    cond = scaled_svd(D, rcond).condition_number
    warns = list(warnings)
    if rank < n:
        warns.append(
            f"{n - rank} parameter combination(s) cannot be identified from these measurements; "
            "the calibration keeps the nominal model along them (the gauge: the identified "
            "correction has no component along these directions of the nominal model)"
        )
    m = n_poses
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
        directions=directions,
    )
