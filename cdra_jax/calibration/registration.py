"""Closed-form start for a calibration in the measuring device's own frame.

A laser tracker or a motion-capture system measures in its own frame, which can sit metres and
any angle away from the robot's base; rough marker positions on the tool can be centimetres off.
Gauss-Newton from the nominal model then starts far outside its basin. Before the iterations:

1. the base frame is registered: the rigid transform ``(R, t)`` that best maps the nominal
   model's points (tool origins of full poses, seen markers) onto the measured ones, by the
   SVD solution of Kabsch / Umeyama (without scale) (:func:`rigid_registration`), becomes
   ``F_0 <- [R t] F_0``;
2. markers with ``calibrate = true`` are placed at the least-squares position in the tool frame,
   ``x_j = mean_k R_k^T (p_kj - t_k)`` over the rows that see them (:func:`marker_positions`);

and the two steps alternate a few times. The start is kept only where it lowers the sum of
squared point errors of the nominal model.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .. import lie
from .observations import Observations, predictions

ALTERNATIONS = 4
"""Rounds of base registration and marker placement."""


def rigid_registration(
    source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``(R (3, 3), t (3,))`` minimising ``sum_i w_i |target_i - (R source_i + t)|^2``.

    The SVD solution (Kabsch 1976; Umeyama 1991 without scale): with centred point sets
    ``H = sum w_i s_i d_i^T = U S V^T``, ``R = V diag(1, 1, det(V U^T)) U^T`` (a rotation,
    never a reflection), ``t = mean(target) - R mean(source)``.

    Args:
        source, target: ``(n, 3)`` corresponding points.
        weights: ``(n,)`` non-negative weights (default 1).

    Raises:
        ValueError: fewer than 3 points, or points (of positive weight) on one line.
    """
    source = np.asarray(source, dtype=float)
    target = np.asarray(target, dtype=float)
    w = np.ones(len(source)) if weights is None else np.asarray(weights, dtype=float)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3:
        raise ValueError(f"source and target must be (n, 3), got {source.shape}, {target.shape}")
    if np.count_nonzero(w > 0) < 3:
        raise ValueError("a rigid registration needs at least 3 points")
    w = w / w.sum()
    cs = w @ source
    ct = w @ target
    S = source - cs
    D = target - ct
    s = np.linalg.svd(S * np.sqrt(w)[:, None], compute_uv=False)
    if s[1] <= 1e-9 * max(s[0], 1e-300):
        raise ValueError("the points lie on one line: their rotation about it is undetermined")
    H = (S * w[:, None]).T @ D
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, ct - R @ cs


def marker_positions(
    tool: np.ndarray, points: np.ndarray, seen: np.ndarray, current: np.ndarray
) -> np.ndarray:
    """Least-squares tool-frame positions ``(P, 3)`` of points seen from tool poses ``(m, 4, 4)``:
    ``x_j = mean_k R_k^T (p_kj - t_k)``; ``current`` where a point is never seen."""
    R = tool[:, :3, :3]
    t = tool[:, :3, 3]
    local = np.einsum("mji,mpj->mpi", R, points - t[:, None, :])
    count = seen.sum(0)
    mean = np.where(seen[..., None], local, 0.0).sum(0) / np.maximum(count, 1)[:, None]
    return np.where(count[:, None] > 0, mean, current)


class Start(NamedTuple):
    """The closed-form start: frames, point positions and what was done."""

    frames: np.ndarray
    xyz: np.ndarray
    registered: bool
    placed: tuple[int, ...]
    rms_before_mm: float
    rms_after_mm: float


def initial_guess(
    frames: np.ndarray, xyz: np.ndarray, obs: Observations, calibrated: tuple[int, ...]
) -> Start:
    """Register the base frame and place the calibrated markers (module docstring).

    Args:
        frames: ``(K+1, 4, 4)`` nominal frames.
        xyz: ``(P, 3)`` nominal point positions in the tool frame.
        obs: the measurements.
        calibrated: indices of the points whose position is calibrated.

    Returns:
        The start; the nominal frames and positions unchanged (``registered`` false) when the
        points do not determine a rigid transform or it does not lower the point errors.
    """
    frames0 = np.asarray(frames, dtype=float)
    xyz0 = np.asarray(xyz, dtype=float)
    pose_mask = np.asarray(obs.pose_mask)
    seen = np.asarray(obs.seen)
    measured_pts = np.asarray(obs.points)
    measured_pos = np.asarray(obs.full_poses)[:, :3, 3]

    def pairs(frames, xyz):
        tool, pts = (np.asarray(a) for a in predictions(frames, xyz, obs))
        src = np.concatenate([tool[pose_mask, :3, 3], np.asarray(pts)[seen]])
        dst = np.concatenate([measured_pos[pose_mask], measured_pts[seen]])
        return tool, src, dst

    def rms(frames, xyz):
        _, src, dst = pairs(frames, xyz)
        return float(np.sqrt(np.mean(np.sum((dst - src) ** 2, axis=-1)))) if len(src) else 0.0

    before = rms(frames0, xyz0)
    frames_k, xyz_k = frames0.copy(), xyz0.copy()
    registered = False
    for _ in range(ALTERNATIONS):
        _, src, dst = pairs(frames_k, xyz_k)
        try:
            R, t = rigid_registration(src, dst)
        except ValueError:
            break
        registered = True
        frames_k = frames_k.copy()
        frames_k[0] = np.asarray(lie.make_pose(R, t)) @ frames_k[0]
        if not calibrated:
            break
        tool, _, _ = pairs(frames_k, xyz_k)
        placed = marker_positions(tool, measured_pts, seen, xyz_k)
        xyz_k = xyz_k.copy()
        xyz_k[list(calibrated)] = placed[list(calibrated)]
    after = rms(frames_k, xyz_k) if registered else before
    if not registered or not after < before:
        return Start(frames0, xyz0, False, (), before, before)
    return Start(frames_k, xyz_k, True, tuple(calibrated), before, after)
