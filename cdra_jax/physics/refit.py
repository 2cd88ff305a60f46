"""Calibrating a model with effects: the frame errors and the effects' parameters jointly.

The unknowns are ``y = (X, theta)``: the error twists ``X (6 (K+1),)`` left-multiplied on the
model's fixed frames (Eqs. 11-14, ordered as ``arm.param_names``) and the parameters ``theta``
of the model's ``[[effects]]`` (:func:`.model.model_effects`, in their order). The residual is
the whitened Eq. 7 twist of every measured tool pose against the extended forward model
(:func:`.base.corrected_tool_pose`), stacked ``(6 m,)`` (:func:`extended_residual`).

The effects' features are evaluated at the moved frames, so that the refitted model predicts
exactly as :func:`.model.model_tool_pose` does with the calibrated frames; their (small)
dependence on the frames is left out of the Jacobian (``stop_gradient``), which changes the
path of the iteration, not its fixed point.

:func:`refine` is a Levenberg-Marquardt with column scaling and rank-revealing least-squares
steps, restricted to the gauge: the frames of an arm have directions that tool poses do not
determine (the CDRA's two along the elbow axis); the steps have no component along them
(:func:`geometric_gauge`), even where an effect's features (a gravity torque, a bent link)
depend on them slightly. Along them the refit keeps the start. Without a noise model the
position and rotation noise scales are estimated from the residual of a first solve and the
problem is solved again with them.

:func:`extended_residual` is the one residual of the extended model with moved frames;
the diagnosis can reuse it.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .. import lie
from ..arm import Arm
from ..calibration.model import NoiseModel, deviation_metrics, residual_twist, whitening
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
    moved = arm.with_frames(lie.se3_exp(X) @ jnp.asarray(arm.frames, y.dtype))
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
    """``(6 m,)`` whitened residual ``G log(T_meas T(y)^-1)^v`` of the extended model
    (:func:`extended_tool_pose`); ``G (m, 6, 6)`` from :func:`cdra_jax.calibration.whitening`."""
    tool = extended_tool_pose(y, arm, candidates, q, aux)
    Y = residual_twist(measured, tool)
    return jnp.einsum("mij,mj->mi", G, Y).reshape(-1)


@filter_jit
def _linearise(y, arm, candidates, q, aux, measured, G):
    fn = lambda yy: extended_residual(yy, arm, candidates, q, aux, measured, G)
    return fn(y), jax.jacfwd(fn)(y)


@filter_jit
def _metrics(y, arm, candidates, q, aux, measured):
    tool = extended_tool_pose(y, arm, candidates, q, aux)
    dp, dR = deviation_metrics(measured, tool)
    return dp, dR, lie.translation(measured) - lie.translation(tool), tool


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
            the extended model after it (``delta_p[0]``, ``delta_R[0]``: the model as given).
        rank, singular_values: of the whitened, column-scaled Jacobian at the solution, in the
            gauge (without the unidentifiable directions of the frame errors).
        n_params: ``6 (K+1) + p``.
        noise: the noise scales used (given, or estimated from the residual).
        noise_source: ``"given"`` or ``"estimated"``.
        jacobian: the whitened Jacobian at the solution ``(6 m, n_params)``, projected on the
            gauge (zero along the unidentifiable directions).
        geometric_jacobian: the whitened Jacobian of the frame errors alone (the effects at
            zero) at the solution ``(6 m, 6 (K+1))``: the frames' identifiability.
        cost: the final whitened sum of squares.
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
    noise_source: str
    jacobian: np.ndarray
    cost: float
    geometric_jacobian: np.ndarray

    def calibrated_arm(self, arm: Arm) -> Arm:
        """``arm`` with the calibrated frames and the refined effect values."""
        return with_effects(arm.with_frames(jnp.asarray(self.frames)), self.candidates, self.theta)


def _lm(y0, P, arm, cands, q, aux, measured, G, max_steps, rtol):
    """Levenberg-Marquardt on ``y = y0 + P z``; returns ``(y, converged, history, r, J P)``."""
    dtype = jnp.asarray(arm.frames).dtype
    y = np.array(y0, float)

    def evaluate(yy):
        r, J = _linearise(jnp.asarray(yy, dtype), arm, cands, q, aux, measured, G)
        return np.asarray(r, float), np.asarray(J, float) @ P

    def metrics(yy):
        dp, dR, _, _ = _metrics(jnp.asarray(yy, dtype), arm, cands, q, aux, measured)
        return float(dp), float(dR)

    r, J = evaluate(y)
    cost = float(r @ r)
    norms = np.linalg.norm(J, axis=0)
    scale = np.where(norms > 0, 1.0 / np.where(norms > 0, norms, 1.0), 1.0)
    lam = 1e-6
    converged = False
    steps: list[float] = []
    dp0, dR0 = metrics(y)
    dps, dRs = [dp0], [dR0]
    tries = 0
    while len(steps) < max_steps and tries < 10 * max_steps:
        tries += 1
        Js = J * scale
        A = np.vstack([Js, np.sqrt(lam) * np.eye(Js.shape[1])])
        b = np.concatenate([-r, np.zeros(Js.shape[1])])
        dz = np.linalg.lstsq(A, b, rcond=1e-12)[0]
        step = P @ (scale * dz)
        trial = y + step
        r_t, J_t = evaluate(trial)
        cost_t = float(r_t @ r_t)
        if np.isfinite(cost_t) and cost_t <= cost:
            small = cost - cost_t <= rtol * max(cost, 1e-300) or np.linalg.norm(dz) < 1e-12
            y, r, J, cost = trial, r_t, J_t, cost_t
            steps.append(float(np.linalg.norm(step)))
            dp, dR = metrics(y)
            dps.append(dp)
            dRs.append(dR)
            lam = max(lam / 10.0, 1e-12)
            if small or cost == 0.0:
                converged = True
                break
        else:
            lam *= 10.0
            if lam > 1e12:  # no step decreases the cost: at the minimum to rounding
                converged = True
                break
    return y, converged, (np.asarray(steps), np.asarray(dps), np.asarray(dRs)), r, J


def _scaled_svd(J: np.ndarray, rcond: float):
    """``(scale, singular values, Vt, keep)`` of the column-scaled ``J``."""
    norms = np.linalg.norm(J, axis=0)
    scale = np.where(norms > 0, 1.0 / np.where(norms > 0, norms, 1.0), 0.0)
    _, sv, Vt = np.linalg.svd(J * scale, full_matrices=False)
    keep = sv > (sv[0] * rcond if sv.size else 0.0)
    return scale, sv, Vt, keep


GAUGE_RCOND = 1e-10
"""Relative singular value (column-scaled) below which a direction of the frame errors is
unidentifiable from tool poses (the CDRA's two sit at ~1e-16)."""


def geometric_gauge(J_frames: np.ndarray, rcond: float = GAUGE_RCOND) -> tuple[np.ndarray, int]:
    """``(P, k)``: an orthonormal basis ``P (n, n - k)`` (Euclidean, mixed units) of the frame
    errors orthogonal to the ``k`` directions that the geometric Jacobian ``J_frames (rows, n)``
    does not see. Steps restricted to ``P`` leave the unidentifiable directions as they are (the
    package's gauge: no component along them)."""
    n = J_frames.shape[1]
    scale, _, Vt, keep = _scaled_svd(J_frames, rcond)
    null = (scale[:, None] * Vt[~keep].T) if (~keep).any() else np.zeros((n, 0))
    k = null.shape[1]
    if not k:
        return np.eye(n), 0
    Q, _ = np.linalg.qr(null)
    U, _, _ = np.linalg.svd(np.eye(n) - Q @ Q.T)
    return U[:, : n - k], k


def refine(
    arm: Arm,
    q,
    measured,
    aux: Aux,
    noise: NoiseModel | None = None,
    *,
    errors0: np.ndarray | None = None,
    max_iterations: int = 50,
    rtol: float = 1e-12,
) -> EffectRefit:
    """Calibrate the frames of ``arm`` and refine its effects' parameters jointly.

    Args:
        arm: the model with its ``[[effects]]`` (their values are the start).
        q: ``(m, dof)`` module states; measured: ``(m, 4, 4)`` measured tool poses.
        aux: the auxiliary columns the effects need.
        noise: the measuring device's noise (stds), or ``None``: estimated from the residual
            (position from the position errors, rotation from the rotation errors) after a
            first solve with 0.1 mm and 1 mrad, then solved again.
        errors0: start of the frame errors ``(6 (K+1),)`` (default zero: the model's frames),
            e.g. the base frame registered to the measuring device's frame.
        max_iterations: Levenberg-Marquardt steps per solve.
        rtol: relative decrease of the cost below which a solve has converged.
    """
    q = jnp.asarray(q)
    measured = jnp.asarray(measured, q.dtype)
    aux = {k: jnp.asarray(v, q.dtype) for k, v in aux.items()}
    cands, theta0 = model_effects(arm)
    n, p = arm.n_params, theta0.size
    X0 = np.zeros(n) if errors0 is None else np.asarray(errors0, float).reshape(n)
    y = np.concatenate([X0, theta0])
    rounds: list[NoiseModel | None] = (
        [noise] if noise is not None else [NoiseModel(0.1, 1e-3), None]
    )
    source = "given" if noise is not None else "estimated"
    m = int(q.shape[0])

    def geometric_jacobian(yy, G):
        geo = np.concatenate([yy[:n], np.zeros(p)])
        J = _linearise(jnp.asarray(geo, q.dtype), arm, cands, q, aux, measured, G)[1]
        return np.asarray(J, float)[:, :n]

    used = noise
    converged, steps, dps, dRs = False, np.zeros(0), np.zeros(1), np.zeros(1)
    r = J = np.zeros((0, 0))
    P = np.eye(n + p)
    for i_round, nm in enumerate(rounds):
        if nm is None:  # the scales estimated from the first solve's residual
            _, _, dpos, tool = _metrics(jnp.asarray(y, q.dtype), arm, cands, q, aux, measured)
            Rrel = jnp.swapaxes(lie.rotation(measured), -1, -2) @ lie.rotation(tool)
            w = np.asarray(lie.so3_log(Rrel))
            dof = max(6 * m - len(y), 1) / (6 * m)
            s_pos = float(np.sqrt(np.mean(np.asarray(dpos) ** 2) / dof))
            s_rot = float(np.sqrt(np.mean(w**2) / dof))
            nm = NoiseModel(max(s_pos, 1e-9), max(s_rot, 1e-12))
        used = nm
        G = whitening(measured, nm)
        if i_round == 0:
            # The gauge: no step along the directions of the frame errors that the geometric
            # chain does not see (the effects' features depend on the frames only weakly and
            # must not make them "identifiable").
            PX, _ = geometric_gauge(geometric_jacobian(y, G))
            P = np.zeros((n + p, PX.shape[1] + p))
            P[:n, : PX.shape[1]] = PX
            P[n:, PX.shape[1] :] = np.eye(p)
        y, converged, (st, dp, dR), r, J = _lm(
            y, P, arm, cands, q, aux, measured, G, max_iterations, rtol
        )
        if i_round == 0:
            steps, dps, dRs = st, dp, dR
        else:  # the history of every solve, one after the other
            steps = np.concatenate([steps, st])
            dps = np.concatenate([dps, dp[1:]])
            dRs = np.concatenate([dRs, dR[1:]])
    assert used is not None
    # Rank and first-order covariance in the gauge (column-scaled J P: frame errors in mm and
    # rad, effect parameters in their own units), pseudo-inverse.
    scale, sv, Vt, keep = _scaled_svd(J, 1e-12 * max(J.shape))
    rank = int(np.sum(keep))
    cov_z = scale[:, None] * ((Vt[keep].T / sv[keep] ** 2) @ Vt[keep]) * scale[None, :]
    cov = P @ cov_z @ P.T
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))[n:]
    null = Vt[~keep]
    if null.size:  # an effect parameter along a null direction has no meaningful std
        std = np.where(np.abs(null[:, -p:]).max(axis=0) > 1e-6, np.nan, std) if p else std
    std = np.where(np.linalg.norm(J[:, J.shape[1] - p :], axis=0) > 0, std, np.nan)
    X = y[:n].reshape(-1, 6)
    frames = np.asarray(lie.se3_exp(jnp.asarray(X)) @ jnp.asarray(arm.frames))
    geo = geometric_jacobian(y, whitening(measured, used))
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
        noise=used,
        noise_source=source,
        jacobian=J @ P.T,
        geometric_jacobian=geo,
        cost=float(r @ r),
    )
