"""Calibrating a model with effects: the frame errors and the effects' parameters jointly.

The unknowns are ``y = (X, theta)``: the error twists ``X (6 (K+1),)`` left-multiplied on the
model's fixed frames (Eqs. 11-14, ordered as ``arm.param_names``) and the parameters ``theta``
of the model's ``[[effects]]`` (:func:`.model.model_effects`, in their order). The tool poses
are those of the extended forward model (:func:`extended_tool_pose`); the residual stacks, as
the calibration's (:mod:`cdra_jax.calibration.observations`), the whitened Eq. 7 twist of every
measured full pose and the error ``p_meas - T x`` of every seen point (the tool origin or a
marker at its model position ``x``) divided by its standard deviation.

The effects' features are evaluated at the moved frames, so that the refitted model predicts
exactly as :func:`.model.model_tool_pose` does with the calibrated frames; their (small)
dependence on the frames is left out of the Jacobian (``stop_gradient``), which changes the
path of the iteration, not its fixed point.

:func:`refine` is a Levenberg-Marquardt with column scaling and rank-revealing least-squares
steps, restricted to the gauge: the frames of an arm have directions that the measurements do
not determine (the CDRA's two along the elbow axis; the tool frame's rotation with the tool
origin alone); the steps have no component along them (:func:`geometric_gauge`), even where
an effect's features (a gravity torque, a bent link) depend on them slightly. Along them the
refit keeps the start. Without a noise model the noise scales (full poses' position and
rotation, points) are estimated from the residual of a first solve and the problem is solved
again with them.

:func:`extended_residual` is the residual of full poses alone (one whitening matrix per pose);
the diagnosis can reuse it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .. import lie
from ..arm import Arm, apply_frame_errors, moved_frames
from ..calibration.damped import levenberg_marquardt
from ..calibration.model import NoiseModel, residual_twist, tool_points
from ..calibration.observations import stacked_residual
from ..compilation import filter_jit
from .base import Aux, Candidate, corrected_tool_pose
from .model import model_effects, model_features, with_effects


def extended_tool_pose(
    y: Array, arm: Arm, candidates: tuple[Candidate, ...], q: Array, aux: Aux
) -> Array:
    """Tool poses ``(m, 4, 4)`` at ``y = (X, theta)``: frames moved by ``X``, effects
    ``candidates`` at ``theta``, their features at the moved frames (without derivative)."""
    n = arm.n_params
    X = y[:n].reshape(-1, 6)
    theta = y[n:]
    moved = arm.with_frames(moved_frames(jnp.asarray(arm.frames, y.dtype), X))
    frozen = moved.with_frames(jax.lax.stop_gradient(moved.frames))
    features = model_features(frozen, q, aux, candidates)
    return corrected_tool_pose(moved, q, features, theta)


def extended_residual(
    y: Array,
    arm: Arm,
    candidates: tuple[Candidate, ...],
    q: Array,
    aux: Aux,
    measured: Array,
    G: Array,
) -> Array:
    """``(6 m,)`` whitened residual ``G log(T_meas T(y)^-1)^v`` of full poses against the
    extended model (:func:`extended_tool_pose`); ``G (m, 6, 6)`` from
    :func:`cdra_jax.calibration.whitening`."""
    tool = extended_tool_pose(y, arm, candidates, q, aux)
    Y = residual_twist(measured, tool)
    return jnp.einsum("mij,mj->mi", G, Y).reshape(-1)


class RefitData(eqx.Module):
    """Measured full poses and points of a refit, without missing values (masks instead).

    Attributes:
        full_poses: ``(m, 4, 4)`` measured tool poses; the identity where ``pose_mask`` is
            false.
        pose_mask: ``(m,)`` rows with a measured full pose.
        points: ``(m, P, 3)`` measured points (mm); zero where not seen.
        seen: ``(m, P)`` which points were seen.
        xyz: ``(P, 3)`` the points' positions in the tool frame (mm; the origin is zero).
    """

    full_poses: Array
    pose_mask: Array
    points: Array
    seen: Array
    xyz: Array

    @staticmethod
    def make(m: int, full_poses=None, points=None, xyz=None) -> RefitData:
        """From full poses ``(m, 4, 4)`` (NaN rows where none) and points ``(m, P, 3)`` (NaN
        where not seen) at tool-frame positions ``xyz (P, 3)``."""
        T = np.full((m, 4, 4), np.nan) if full_poses is None else np.asarray(full_poses, float)
        mask = np.all(np.isfinite(T), axis=(-2, -1))
        T = np.where(mask[:, None, None], T, np.eye(4))
        P = np.zeros((m, 0, 3)) if points is None else np.asarray(points, float)
        seen = np.all(np.isfinite(P), axis=-1)
        P = np.where(seen[..., None], P, 0.0)
        x = np.zeros((P.shape[1], 3)) if xyz is None else np.asarray(xyz, float)
        if x.shape != (P.shape[1], 3):
            raise ValueError(f"xyz: expected ({P.shape[1]}, 3) point positions, got {x.shape}")
        return RefitData(
            jnp.asarray(T), jnp.asarray(mask), jnp.asarray(P), jnp.asarray(seen), jnp.asarray(x)
        )


def data_residual(
    y: Array,
    arm: Arm,
    candidates: tuple[Candidate, ...],
    q: Array,
    aux: Aux,
    data: RefitData,
    scales: Array,
) -> Array:
    """The stacked whitened residual ``(6 m + 3 m P,)`` of full poses and points against the
    extended model; ``scales = (s_pos mm, s_rot rad, s_pt mm)`` (module docstring)."""
    tool = extended_tool_pose(y, arm, candidates, q, aux)
    return stacked_residual(tool, data.xyz, data, scales[0], scales[1], scales[2])


@filter_jit
def _linearise(y, arm, candidates, q, aux, data, scales):
    fn = lambda yy: data_residual(yy, arm, candidates, q, aux, data, scales)
    return fn(y), jax.jacfwd(fn)(y)


@filter_jit
def _tool(y, arm, candidates, q, aux):
    return extended_tool_pose(y, arm, candidates, q, aux)


def raw_errors(tool, data: RefitData) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unwhitened errors of model tool poses ``(m, 4, 4)``: full-pose position ``(m, 3)`` mm,
    rotation ``(m, 3)`` rad (the rotation vector of ``R_meas^T R_model``), points
    ``(m, P, 3)`` mm; NaN where not measured."""
    tool = np.asarray(tool, float)
    full = np.asarray(data.full_poses, float)
    mask = np.asarray(data.pose_mask)
    dpos = np.where(mask[:, None], full[:, :3, 3] - tool[:, :3, 3], np.nan)
    Rrel = np.swapaxes(full[:, :3, :3], -1, -2) @ tool[:, :3, :3]
    w = np.where(mask[:, None], np.asarray(lie.so3_log(jnp.asarray(Rrel))), np.nan)
    pts = np.asarray(tool_points(jnp.asarray(tool), data.xyz), float)
    e = np.where(np.asarray(data.seen)[..., None], np.asarray(data.points) - pts, np.nan)
    return dpos, w, e


def prediction_error_table(tool, data: RefitData) -> tuple[np.ndarray, np.ndarray]:
    """``(position (m, 1 + P) mm, rotation (m,) rad)``: each row's full-pose position error
    then each point's (norms, NaN where not measured), and the full pose's rotation angle, of
    model tool poses ``tool (m, 4, 4)`` (as :func:`cdra_jax.calibration.observations.
    error_table` for the geometric chain)."""
    dpos, w, e = raw_errors(tool, data)
    pos = np.concatenate([np.linalg.norm(dpos, axis=-1)[:, None], np.linalg.norm(e, axis=-1)], 1)
    return pos, np.linalg.norm(w, axis=-1)


def _deviation(tool, data: RefitData) -> tuple[float, float]:
    """Eqs. 20-21 over every measured position (full poses and points) and rotation."""
    dpos, w, e = raw_errors(tool, data)
    pos = np.concatenate([dpos.reshape(-1, 3), e.reshape(-1, 3)])
    pos = pos[np.all(np.isfinite(pos), axis=-1)]
    w = w[np.all(np.isfinite(w), axis=-1)]
    dp = float(np.sqrt(np.mean(np.sum(pos**2, -1)))) if len(pos) else float("nan")
    dR = float(np.sqrt(np.mean(np.sum(w**2, -1)))) if len(w) else float("nan")
    return dp, dR


@dataclasses.dataclass(frozen=True)
class EffectRefit:
    """The outcome of :func:`refine`.

    Attributes:
        errors: ``(K+1, 6)`` identified error twists w.r.t. the model's frames (mm, rad).
        frames: ``(K+1, 4, 4)`` calibrated frames.
        theta: ``(p,)`` refined effect parameters (the model's order and units).
        theta_start: ``(p,)`` the model's values.
        theta_std: ``(p,)`` first-order standard deviations of ``theta`` at the noise scales
            (NaN along unidentifiable directions).
        candidates: the model's effects.
        converged: whether the last solve met its tolerance.
        iterations: steps taken (over both solves when the noise is estimated).
        step_norm, delta_p, delta_R: per step: the norm of the step in ``y`` and Eqs. 20-21 of
            the extended model after it, over every measured position and rotation
            (``delta_p[0]``, ``delta_R[0]``: at the start).
        rank, singular_values: of the whitened, column-scaled Jacobian at the solution, in the
            gauge (without the unidentifiable directions of the frame errors).
        n_params: ``6 (K+1) + p``.
        noise: the full poses' noise scales used (given, or estimated from the residual).
        point_noise_mm: the points' noise scale used (mm per coordinate).
        noise_source: ``"given"`` or ``"estimated"``.
        jacobian: the whitened Jacobian at the solution ``(rows, n_params)``, projected on the
            gauge (zero along the unidentifiable directions).
        cost: the final whitened sum of squares.
        geometric_jacobian: the whitened Jacobian of the frame errors alone (the effects at
            zero) at the solution ``(rows, 6 (K+1))``: the frames' identifiability.
        data: the measurements as fitted.
    """

    errors: np.ndarray
    frames: np.ndarray
    theta: np.ndarray
    theta_start: np.ndarray
    theta_std: np.ndarray
    candidates: tuple[Candidate, ...]
    converged: bool
    iterations: int
    step_norm: np.ndarray
    delta_p: np.ndarray
    delta_R: np.ndarray
    rank: int
    singular_values: np.ndarray
    n_params: int
    noise: NoiseModel
    point_noise_mm: float
    noise_source: str
    jacobian: np.ndarray
    cost: float
    geometric_jacobian: np.ndarray
    data: RefitData

    def calibrated_arm(self, arm: Arm) -> Arm:
        """``arm`` with the calibrated frames and the refined effect values."""
        return with_effects(arm.with_frames(jnp.asarray(self.frames)), self.candidates, self.theta)


def _lm(y0, P, arm, cands, q, aux, data, scales, max_steps, rtol):
    """Levenberg-Marquardt (:func:`cdra_jax.calibration.damped.levenberg_marquardt`) on
    ``y = y0 + P z``; returns ``(y, converged, (step norms, dp, dR per step), r, J P)``."""
    dtype = jnp.asarray(arm.frames).dtype
    y0 = np.array(y0, float)
    sc = jnp.asarray(scales, dtype)

    def evaluate(z):
        r, J = _linearise(jnp.asarray(y0 + P @ z, dtype), arm, cands, q, aux, data, sc)
        return np.asarray(r, float), np.asarray(J, float) @ P

    def metrics(yy):
        return _deviation(_tool(jnp.asarray(yy, dtype), arm, cands, q, aux), data)

    steps: list[float] = []
    dp0, dR0 = metrics(y0)
    dps, dRs = [dp0], [dR0]

    def accepted(z, step_norm):
        dp, dR = metrics(y0 + P @ z)
        steps.append(step_norm)  # P has orthonormal columns: the same norm in y
        dps.append(dp)
        dRs.append(dR)

    sol = levenberg_marquardt(
        evaluate, np.zeros(P.shape[1]), max_steps=max_steps, rtol=rtol, on_accept=accepted
    )
    y = y0 + P @ sol.u
    return y, sol.converged, (np.asarray(steps), np.asarray(dps), np.asarray(dRs)), sol.r, sol.J


def _scaled_svd(J: np.ndarray, rcond: float):
    """``(scale, singular values, Vt, keep)`` of the column-scaled ``J``."""
    norms = np.linalg.norm(J, axis=0)
    scale = np.where(norms > 0, 1.0 / np.where(norms > 0, norms, 1.0), 0.0)
    _, sv, Vt = np.linalg.svd(J * scale, full_matrices=False)
    keep = sv > (sv[0] * rcond if sv.size else 0.0)
    return scale, sv, Vt, keep


GAUGE_RCOND = 1e-10
"""Relative singular value (column-scaled) below which a direction of the frame errors is
unidentifiable from the measurements (the CDRA's two sit at ~1e-16)."""


def geometric_gauge(J_frames: np.ndarray, rcond: float = GAUGE_RCOND) -> tuple[np.ndarray, int]:
    """``(P, k)``: an orthonormal basis ``P (n, n - k)`` (Euclidean, mixed units) of the frame
    errors orthogonal to the ``k`` directions that the geometric Jacobian ``J_frames (rows, n)``
    does not see. Steps restricted to ``P`` leave the unidentifiable directions as they are (the
    package's gauge: no component along them)."""
    n = J_frames.shape[1]
    norms = np.linalg.norm(J_frames, axis=0)
    scale = np.where(norms > 0, 1.0 / np.where(norms > 0, norms, 1.0), 1.0)
    _, sv, Vt = np.linalg.svd(J_frames * scale, full_matrices=True)
    keep = np.zeros(n, bool)
    keep[: sv.size] = sv > (sv[0] * rcond if sv.size else np.inf)
    null = scale[:, None] * Vt[~keep].T  # back to the parameters' own units
    k = null.shape[1]
    if not k:
        return np.eye(n), 0
    Q, _ = np.linalg.qr(null)
    U, _, _ = np.linalg.svd(np.eye(n) - Q @ Q.T)
    return U[:, : n - k], k


def _rms(a: np.ndarray, dof: float, floor: float) -> float:
    """Noise scale from the finite entries of ``a``, corrected for the fitted parameters."""
    a = a[np.isfinite(a)]
    return max(float(np.sqrt(np.mean(a**2) / dof)), floor) if a.size else 1.0


def refine(
    arm: Arm,
    q,
    measured,
    aux: Aux,
    noise: NoiseModel | None = None,
    *,
    points=None,
    point_xyz: Sequence[Sequence[float]] | np.ndarray | None = None,
    errors0: np.ndarray | None = None,
    max_iterations: int = 50,
    rtol: float = 1e-12,
) -> EffectRefit:
    """Calibrate the frames of ``arm`` and refine its effects' parameters jointly.

    Args:
        arm: the model with its ``[[effects]]`` (their values are the start).
        q: ``(m, dof)`` module states.
        measured: ``(m, 4, 4)`` measured tool poses (NaN rows where a row has none), or
            ``None`` (points only).
        aux: the auxiliary columns the effects need.
        noise: the measuring device's noise (stds; points take its position std), or
            ``None``: estimated from the residual (full poses' position and rotation, points)
            after a first solve with 0.1 mm and 1 mrad, then solved again.
        points: ``(m, P, 3)`` measured points (NaN where not seen), or ``None``.
        point_xyz: ``(P, 3)`` their positions in the tool frame (mm; known, not refined).
        errors0: start of the frame errors ``(6 (K+1),)`` (default zero: the model's frames),
            e.g. the base frame registered to the measuring device's frame.
        max_iterations: Levenberg-Marquardt steps per solve.
        rtol: relative decrease of the cost below which a solve has converged.
    """
    q = jnp.asarray(q)
    m = int(q.shape[0])
    data = RefitData.make(m, measured, points, point_xyz)
    aux = {k: jnp.asarray(v, q.dtype) for k, v in aux.items()}
    cands, theta0 = model_effects(arm)
    # The values travel in theta; without the records in the compiled calls' static arguments,
    # other start values reuse the compiled programs.
    arm = arm.with_effects(())
    n, p = arm.n_params, theta0.size
    X0 = np.zeros(n) if errors0 is None else np.asarray(errors0, float).reshape(n)
    y = np.concatenate([X0, theta0])
    rounds: list[tuple[float, float, float] | None]
    if noise is not None:
        s_pos, s_rot = float(noise.position_mm), float(noise.rotation_rad)
        rounds = [(s_pos, s_rot, s_pos)]
    else:
        rounds = [(0.1, 1e-3, 0.1), None]
    source = "given" if noise is not None else "estimated"
    n_rows = 6 * int(np.sum(np.asarray(data.pose_mask))) + 3 * int(np.sum(np.asarray(data.seen)))

    def geometric_jacobian(yy, scales):
        geo = np.concatenate([yy[:n], np.zeros(p)])
        J = _linearise(
            jnp.asarray(geo, q.dtype), arm, cands, q, aux, data, jnp.asarray(scales, q.dtype)
        )[1]
        return np.asarray(J, float)[:, :n]

    converged, steps, dps, dRs = False, np.zeros(0), np.zeros(1), np.zeros(1)
    r = J = np.zeros((0, 0))
    P = np.eye(n + p)
    used = (1.0, 1.0, 1.0)
    for i_round, sc in enumerate(rounds):
        if sc is None:  # the scales estimated from the first solve's residual
            dpos, w, e = raw_errors(_tool(jnp.asarray(y, q.dtype), arm, cands, q, aux), data)
            dof = max(n_rows - (P.shape[1]), 1) / max(n_rows, 1)
            sc = (_rms(dpos, dof, 1e-9), _rms(w, dof, 1e-12), _rms(e, dof, 1e-9))
        used = sc
        if i_round == 0:
            # The gauge: no step along the directions of the frame errors that the geometric
            # chain does not see (the effects' features depend on the frames only weakly and
            # must not make them "identifiable").
            PX, _ = geometric_gauge(geometric_jacobian(y, sc))
            P = np.zeros((n + p, PX.shape[1] + p))
            P[:n, : PX.shape[1]] = PX
            P[n:, PX.shape[1] :] = np.eye(p)
        y, converged, (st, dp, dR), r, J = _lm(
            y, P, arm, cands, q, aux, data, sc, max_iterations, rtol
        )
        if i_round == 0:
            steps, dps, dRs = st, dp, dR
        else:  # the history of every solve, one after the other
            steps = np.concatenate([steps, st])
            dps = np.concatenate([dps, dp[1:]])
            dRs = np.concatenate([dRs, dR[1:]])
    # Rank and first-order covariance in the gauge (column-scaled J P: frame errors in mm and
    # rad, effect parameters in their own units), pseudo-inverse.
    scale, sv, Vt, keep = _scaled_svd(J, 1e-12 * max(J.shape))
    rank = int(np.sum(keep))
    cov_z = scale[:, None] * ((Vt[keep].T / sv[keep] ** 2) @ Vt[keep]) * scale[None, :]
    cov = P @ cov_z @ P.T
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))[n:]
    null = Vt[~keep]
    if null.size and p:  # an effect parameter along a null direction has no meaningful std
        std = np.where(np.abs(null[:, -p:]).max(axis=0) > 1e-6, np.nan, std)
    if p:
        std = np.where(np.linalg.norm(J[:, -p:], axis=0) > 0, std, np.nan)
    X = y[:n].reshape(-1, 6)
    frames = np.asarray(apply_frame_errors(arm, X).frames)
    return EffectRefit(
        errors=X,
        frames=frames,
        theta=y[n:],
        theta_start=theta0,
        theta_std=std,
        candidates=cands,
        converged=bool(converged),
        iterations=len(steps),
        step_norm=steps,
        delta_p=dps,
        delta_R=dRs,
        rank=rank,
        singular_values=sv,
        n_params=len(y),
        noise=NoiseModel(used[0], used[1]),
        point_noise_mm=float(used[2]),
        noise_source=source,
        jacobian=J @ P.T,
        cost=float(r @ r),
        geometric_jacobian=geometric_jacobian(y, used),
        data=data,
    )
