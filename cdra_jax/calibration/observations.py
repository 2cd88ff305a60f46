"""Measured full poses and measured points (markers, the tool origin) as one residual.

A measuring device gives, per row ``k`` of a measurement file, a full tool pose (a
full-pose tracker), or points only: the tool-frame origin (a laser tracker's reflector at the
tool point) and markers at known or roughly known positions ``x_j`` on the tool (motion
capture), any of which may be missing in a row (occlusion). This module stacks all of them:

* a full pose: the world-frame twist ``Y = log(T_meas T_model^-1)^v`` of Eq. 7, whitened by
  :func:`.model.whitening` (position rows in mm / ``s_pos``, rotation rows in rad / ``s_rot``);
* a point: ``e = p_meas - T_model x_j`` (mm, world frame, :func:`.model.point_residual`)
  divided by its standard deviation.

The parameters are ``theta = [X; dx]``: the error twists ``X`` of the K+1 fixed transforms
(Eq. 8, left-multiplied: ``F_j = exp(hat(X_j)) F_j^0``) and the corrections ``dx`` of the marker
positions that are calibrated (``calibrate = true`` in the model), 3 per marker, mm in the tool
frame. Rows that are not measured (a point not seen, a row without a full pose) carry an infinite
standard deviation and so contribute exact zeros.

Layout of the residual vector: the ``6 m`` pose rows (pose by pose, ``(v, w)``), then the
``3 m P`` point rows (row by row, point by point, ``x y z``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from .. import lie
from ..arm import Arm, chain, module_poses, moved_frames
from ..compilation import device_array
from .model import NoiseModel, point_residual, residual_twist, tool_points, whitening


class Observations(eqx.Module):
    """The measured data of one calibration as arrays (no missing values: masks instead).

    Attributes:
        poses: ``(m, K, 4, 4)`` module poses from the module states.
        full_poses: ``(m, 4, 4)`` measured tool poses; the identity where ``pose_mask`` is false.
        pose_mask: ``(m,)`` rows that measure a full pose.
        points: ``(m, P, 3)`` measured points (mm, world frame); zero where not seen.
        seen: ``(m, P)`` which points were seen.
    """

    poses: Array
    full_poses: Array
    pose_mask: Array
    points: Array
    seen: Array

    @property
    def m(self) -> int:
        return int(self.poses.shape[0])

    @property
    def n_points(self) -> int:
        return int(self.points.shape[1])


def make_observations(
    arm: Arm, q, full_poses: np.ndarray | None, points: np.ndarray | None
) -> Observations:
    """:class:`Observations` from module states ``q (m, dof)``, measured full poses ``(m, 4, 4)``
    (NaN rows where none) and measured points ``(m, P, 3)`` (NaN where not seen)."""
    q = np.asarray(q, dtype=float)
    m = q.shape[0]
    if full_poses is None:
        full_poses = np.full((m, 4, 4), np.nan)
    T = np.asarray(full_poses, dtype=float)
    mask = np.all(np.isfinite(T), axis=(-2, -1))
    T = np.where(mask[:, None, None], T, np.eye(4))
    if points is None:
        points = np.zeros((m, 0, 3))
    P = np.asarray(points, dtype=float)
    seen = np.all(np.isfinite(P), axis=-1)
    P = np.where(seen[..., None], P, 0.0)
    return Observations(
        poses=_module_poses(arm, q),
        full_poses=device_array(T),
        pose_mask=device_array(mask),
        points=device_array(P),
        seen=device_array(seen),
    )


_module_poses = eqx.filter_jit(module_poses)


BUCKETS = (8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256, 384, 512, 768, 1024)
"""Row counts that measurement files are padded up to (beyond: multiples of 512), so that files
of different lengths share compiled programs (and the persistent compilation cache)."""


def bucket(m: int) -> int:
    """The smallest of :data:`BUCKETS` at least ``m`` (beyond them, a multiple of 512)."""
    for b in BUCKETS:
        if m <= b:
            return b
    return -(-m // 512) * 512


def padded(obs: Observations, rows: int) -> Observations:
    """``obs`` with unmeasured rows appended up to ``rows``: they contribute exact zeros to the
    residual and its Jacobian (identity poses, every mask false)."""
    extra = rows - obs.m
    if extra <= 0:
        return obs

    def pad(a, fill):
        a = np.asarray(a)
        block = np.broadcast_to(np.asarray(fill, a.dtype), (extra,) + a.shape[1:])
        return device_array(np.concatenate([a, block]))

    return Observations(
        poses=pad(obs.poses, np.eye(4)),
        full_poses=pad(obs.full_poses, np.eye(4)),
        pose_mask=pad(obs.pose_mask, False),
        points=pad(obs.points, 0.0),
        seen=pad(obs.seen, False),
    )


def marker_table(arm: Arm, point_names: Sequence[str]) -> tuple[np.ndarray, tuple[int, ...]]:
    """``(xyz (P, 3), calibrated)``: the tool-frame position of each point (the origin is
    ``0``) and the indices of the points whose position is calibrated."""
    xyz = np.zeros((len(point_names), 3))
    calibrated = []
    for j, name in enumerate(point_names):
        if name == "origin":
            continue
        mk = arm.marker(name)
        xyz[j] = mk.xyz
        if mk.calibrate:
            calibrated.append(j)
    return xyz, tuple(calibrated)


@eqx.filter_jit
def apply_parameters(
    theta: ArrayLike, frames0: ArrayLike, xyz0: ArrayLike, calibrated: tuple[int, ...]
) -> tuple[Array, Array]:
    """``(frames (K+1, 4, 4), xyz (P, 3))`` at the parameters ``theta = [X; dx]``."""
    theta, frames0, xyz0 = jnp.asarray(theta), jnp.asarray(frames0), jnp.asarray(xyz0)
    n_frames = frames0.shape[0]
    frames = moved_frames(frames0, theta[: 6 * n_frames])
    if calibrated:
        dx = theta[6 * n_frames :].reshape(len(calibrated), 3)
        xyz0 = xyz0.at[jnp.asarray(calibrated)].add(dx)
    return frames, xyz0


@eqx.filter_jit
def predictions(frames: ArrayLike, xyz: ArrayLike, obs: Observations) -> tuple[Array, Array]:
    """Model tool poses ``(m, 4, 4)`` and model points ``(m, P, 3)`` (world frame, mm)."""
    tool, _ = chain(jnp.asarray(frames), obs.poses)
    return tool, tool_points(tool, xyz)


def whitened_residual(
    theta: Array,
    frames0: Array,
    xyz0: Array,
    obs: Observations,
    sigma_pos: Array,
    sigma_rot: Array,
    sigma_pt: Array,
    calibrated: tuple[int, ...],
) -> Array:
    """The stacked whitened residual ``(6 m + 3 m P,)`` at ``theta`` (module docstring).

    Args:
        sigma_pos, sigma_rot: ``(m,)`` standard deviations of the full poses' position (mm)
            and rotation (rad), ``inf`` where a row has no full pose or is weighted out.
        sigma_pt: ``(m, P)`` standard deviations of the points (mm), ``inf`` where not seen.
    """
    frames, xyz = apply_parameters(theta, frames0, xyz0, calibrated)
    tool, _ = chain(frames, obs.poses)
    return stacked_residual(tool, xyz, obs, sigma_pos, sigma_rot, sigma_pt)


class MeasuredRows(Protocol):
    """What :func:`stacked_residual` reads of the measurements: :class:`Observations`, or any
    object with these arrays (masks instead of missing values)."""

    full_poses: Array  # (m, 4, 4) measured tool poses, the identity where pose_mask is false
    pose_mask: Array  # (m,)
    points: Array  # (m, P, 3) measured points (mm), zero where not seen
    seen: Array  # (m, P)


def stacked_residual(
    tool: Array, xyz: Array, obs: MeasuredRows, sigma_pos: Array, sigma_rot: Array, sigma_pt: Array
) -> Array:
    """The stacked whitened residual ``(6 m + 3 m P,)`` of model tool poses ``tool (m, 4, 4)``
    (world frame, mm) and tool-frame points ``xyz (P, 3)`` (mm) against ``obs`` (standard
    deviations as in :func:`whitened_residual`; layout: module docstring, :func:`row_layout`)."""
    G = whitening(obs.full_poses, NoiseModel(sigma_pos, sigma_rot))
    Y = jnp.einsum("mij,mj->mi", G, residual_twist(obs.full_poses, tool))
    Y = jnp.where(obs.pose_mask[:, None], Y, 0.0)
    e = point_residual(obs.points, tool, xyz) / sigma_pt[..., None]
    e = jnp.where(obs.seen[..., None], e, 0.0)
    return jnp.concatenate([Y.reshape(-1), e.reshape(-1)])


ROW_POSITION, ROW_ROTATION, ROW_POINT = 0, 1, 2
"""Kinds of the rows of the stacked residual (:func:`row_layout`)."""


def row_layout(obs: Observations) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(measured, row, kind, point)``, each ``(6 m + 3 m P,)``, for the stacked residual:
    whether the entry is measured (else it is an exact zero), the measurement row it belongs
    to, its kind (:data:`ROW_POSITION` / :data:`ROW_ROTATION` of a full pose, or
    :data:`ROW_POINT`) and the point's index (``-1`` for full-pose entries)."""
    m, P = obs.m, obs.n_points
    pose_mask = np.asarray(obs.pose_mask)
    seen = np.asarray(obs.seen)
    measured = np.concatenate([np.repeat(pose_mask, 6), np.repeat(seen.reshape(-1), 3)])
    row = np.concatenate([np.repeat(np.arange(m), 6), np.repeat(np.arange(m), 3 * P)])
    kind = np.concatenate(
        [
            np.tile([ROW_POSITION] * 3 + [ROW_ROTATION] * 3, m),
            np.full(3 * m * P, ROW_POINT),
        ]
    )
    point = np.concatenate([np.full(6 * m, -1), np.tile(np.repeat(np.arange(P), 3), m)])
    return measured, row, kind, point


residual = eqx.filter_jit(whitened_residual)
"""Compiled :func:`whitened_residual` (the residual alone, no Jacobian)."""


@eqx.filter_jit
def linearise(theta, frames0, xyz0, obs, sigma_pos, sigma_rot, sigma_pt, calibrated):
    """``(r, J)``: :func:`whitened_residual` and its Jacobian in ``theta`` (forward mode)."""

    def f(t):
        return whitened_residual(t, frames0, xyz0, obs, sigma_pos, sigma_rot, sigma_pt, calibrated)

    return f(theta), jax.jacfwd(f)(theta)


@eqx.filter_jit
def raw_errors(frames, xyz, obs: Observations) -> tuple[Array, Array, Array]:
    """Unwhitened errors: ``(position (m, 3) mm, rotation (m,) rad, points (m, P, 3) mm)``.

    Position and rotation errors of the full poses (measured minus model position; the angle
    of ``R_meas^T R_model``), NaN in rows without a full pose; point errors NaN where not seen.
    """
    tool, pts = predictions(frames, xyz, obs)
    dpos = obs.full_poses[:, :3, 3] - tool[:, :3, 3]
    Rrel = jnp.swapaxes(obs.full_poses[:, :3, :3], -1, -2) @ tool[:, :3, :3]
    ang = lie.rotation_angle(Rrel)
    nan = jnp.nan
    dpos = jnp.where(obs.pose_mask[:, None], dpos, nan)
    ang = jnp.where(obs.pose_mask, ang, nan)
    e = jnp.where(obs.seen[..., None], obs.points - pts, nan)
    return dpos, ang, e


@eqx.filter_jit
def raw_errors_at(
    theta: ArrayLike,
    frames0: ArrayLike,
    xyz0: ArrayLike,
    obs: Observations,
    calibrated: tuple[int, ...],
) -> tuple[Array, Array, Array]:
    """:func:`raw_errors` of the model at the parameters ``theta`` (:func:`apply_parameters`),
    as one compiled program (the auto solver records them after every accepted step)."""
    frames, xyz = apply_parameters(theta, frames0, xyz0, calibrated)
    return raw_errors(frames, xyz, obs)


def error_table(frames, xyz, obs: Observations) -> tuple[np.ndarray, np.ndarray]:
    """``(position (m, 1 + P) mm, rotation (m,) rad)``: the norm of each row's full-pose
    position error then of each point's error (NaN where not measured), and the full pose's
    rotation angle (NaN without one), from :func:`raw_errors`."""
    dpos, ang, e = (np.asarray(a, dtype=float) for a in raw_errors(frames, xyz, obs))
    pos = np.concatenate([np.linalg.norm(dpos, axis=-1)[:, None], np.linalg.norm(e, axis=-1)], 1)
    return pos, ang


def row_means(position: np.ndarray) -> np.ndarray:
    """``(m,)`` mean of each row's measured position errors (NaN for a row with none)."""
    seen = np.isfinite(position)
    with np.errstate(invalid="ignore"):
        return np.where(seen, position, 0.0).sum(-1) / np.where(seen.any(-1), seen.sum(-1), np.nan)
