"""One gauge for every solver: how the unidentifiable combinations are fixed.

Measurements determine the parameters only up to the unidentifiable directions ``N`` (the null
space of the stacked Jacobian: for the paper's CDRA a rotation about the elbow axis and a
translation along it, moved between ``upper_arm`` and ``forearm``). Any point of the solution
set fits the data equally well; a calibration result has to pick one. The package picks, for
every solver, **the point whose identified correction has no component along the
unidentifiable directions of the nominal model**:

    N_0^T theta = 0,   theta = [log(F_j F_j,nom^-1)^v ...; x - x_nom]

with ``N_0`` the orthonormal null basis of the (unweighted) Jacobian of the data's residual at
the nominal model (:func:`null_basis`), ``F_nom`` the nominal frames and ``x_nom`` the nominal
marker positions. Along ``N`` nothing is learnt from the data, so the result keeps the nominal
model's value there.

``lm`` and ``auto`` search only the identifiable subspace and so meet it by construction, up
to the base registration of ``auto``; the paper's iteration (minimum-norm steps at each iterate)
meets it to first order. :func:`to_nominal_gauge` moves any solution onto it exactly: along the
null directions at the solution, ``theta <- theta + N_c a`` with ``a`` from a few Newton steps
on ``N_0^T theta = 0``. Such a move changes no prediction when the direction is a symmetry of
the model (a rotation about a joint axis, a translation along it, moved between the frames on
either side: the structural unidentifiable directions); the move is kept only when every
predicted pose and point moves by less than :data:`EXACT_MM` (mm) and :data:`EXACT_RAD`
(rad), and otherwise the solution is returned unchanged, with ``moved = False``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import numpy as np

from ..arm import error_twists
from .linear import svd_rank
from .observations import Observations, apply_parameters, linearise, predictions

_error_twists = jax.jit(error_twists)
EXACT_MM = 1e-9
EXACT_RAD = 1e-12
NEWTON_STEPS = 6


class GaugeFix(NamedTuple):
    """A solution in the nominal gauge.

    Attributes:
        frames: ``(K+1, 4, 4)``.
        xyz: ``(P, 3)`` point positions in the tool frame.
        moved: whether the solution was moved (it already was, or the move was not exact).
        residual: ``|N_0^T theta|`` after the move (0 when every direction is identifiable).
        exact: whether the solution meets the gauge (to ``1e-9`` of ``|theta|``).
    """

    frames: np.ndarray
    xyz: np.ndarray
    moved: bool
    residual: float
    exact: bool


def null_basis(
    frames: np.ndarray,
    xyz: np.ndarray,
    obs: Observations,
    calibrated: tuple[int, ...],
    rcond: float | None = None,
) -> np.ndarray:
    """``(k, n)`` orthonormal basis of the unidentifiable directions at a model: the null space
    of the Jacobian of :func:`.observations.whitened_residual` (unit weights)."""
    m = obs.m
    n = 6 * frames.shape[0] + 3 * len(calibrated)
    ones = np.ones(m)
    sp = np.where(np.asarray(obs.pose_mask), ones, np.inf)
    s_pt = np.where(np.asarray(obs.seen), 1.0, np.inf)
    _, J = linearise(np.zeros(n), frames, xyz, obs, sp, sp, s_pt, calibrated)
    _, Vt, rank = svd_rank(J, rcond)
    return Vt[rank:]


def correction(
    frames: np.ndarray,
    xyz: np.ndarray,
    frames_nom: np.ndarray,
    xyz_nom: np.ndarray,
    calibrated: tuple[int, ...],
) -> np.ndarray:
    """``theta``: the error twists w.r.t. the nominal frames and the marker corrections."""
    X = np.asarray(_error_twists(frames, frames_nom)).reshape(-1)
    dx = [np.asarray(xyz[j]) - np.asarray(xyz_nom[j]) for j in calibrated]
    return np.concatenate([X, *dx]) if dx else X


def to_nominal_gauge(
    frames: np.ndarray,
    xyz: np.ndarray,
    frames_nom: np.ndarray,
    xyz_nom: np.ndarray,
    obs: Observations,
    calibrated: tuple[int, ...] = (),
) -> GaugeFix:
    """Move a solution along its unidentifiable directions onto the nominal gauge (module
    docstring). Returns it unchanged when there is nothing to move or no exact move."""
    frames = np.asarray(frames, dtype=float)
    xyz = np.asarray(xyz, dtype=float)
    N0 = null_basis(np.asarray(frames_nom, float), np.asarray(xyz_nom, float), obs, calibrated)
    theta = correction(frames, xyz, frames_nom, xyz_nom, calibrated)
    scale = max(float(np.linalg.norm(theta)), 1e-300)
    if N0.shape[0] == 0:
        return GaugeFix(frames, xyz, False, 0.0, True)
    res = float(np.linalg.norm(N0 @ theta))
    if res <= 1e-12 * scale:
        return GaugeFix(frames, xyz, False, res, True)
    tool0, pts0 = (np.asarray(a) for a in predictions(frames, xyz, obs))
    f, x = frames, xyz
    for _ in range(NEWTON_STEPS):
        Nc = null_basis(f, x, obs, calibrated)
        if Nc.shape[0] != N0.shape[0]:
            return GaugeFix(frames, xyz, False, res, False)
        g = N0 @ correction(f, x, frames_nom, xyz_nom, calibrated)
        if np.linalg.norm(g) <= 1e-13 * scale:
            break
        try:
            a = -np.linalg.solve(N0 @ Nc.T, g)
        except np.linalg.LinAlgError:
            return GaugeFix(frames, xyz, False, res, False)
        f, x = (np.asarray(v) for v in apply_parameters(Nc.T @ a, f, x, calibrated))
    tool1, pts1 = (np.asarray(v) for v in predictions(f, x, obs))
    dpos = np.max(np.abs(tool1[:, :3, 3] - tool0[:, :3, 3]), initial=0.0)
    drot = np.max(np.abs(tool1[:, :3, :3] - tool0[:, :3, :3]), initial=0.0)
    seen = np.asarray(obs.seen)
    dpts = np.max(np.abs(pts1 - pts0)[seen], initial=0.0)
    new_res = float(np.linalg.norm(N0 @ correction(f, x, frames_nom, xyz_nom, calibrated)))
    if max(dpos, dpts) > EXACT_MM or drot > EXACT_RAD or new_res > 1e-9 * scale:
        return GaugeFix(frames, xyz, False, res, res <= 1e-9 * scale)
    return GaugeFix(f, x, True, new_res, True)
