"""Find the missing physics: detect, locate, attribute and refit (design.md, 'diagnose').

1. **Fit** the 6 (K+1) frame errors (24 for the CDRA) by the weighted Gauss-Newton of the paper
   (:func:`cdra_jax.calibration.calibrate_paper` with the noise model; for points, the
   ``auto`` solver's least squares).
2. **Detect** with tests that need no noise value: whether the residual is predictable from the
   rows' regressors on left-out poses (:func:`stats.structure_test`: module states, time,
   payload, the tool's place in the workspace), the family of candidate F tests
   (Holm-corrected) and, where poses are repeated, a lack-of-fit F test; given noise values add
   the K-fold held-out chi-square ``Q`` (predictive covariance ``I + D_f C D_f^T``, exact null,
   :mod:`.stats`) tolerating :data:`NOISE_TOLERANCE` times the stated variance. The reported
   ``p_value`` is the Bonferroni combination of the tests used (``min(1, n_tests * min p)``),
   so that ``mismatch = p_value < alpha`` keeps the false-positive rate at ``alpha`` or below.
3. **Attribute**: each candidate of :mod:`cdra_jax.physics` is linearised at the geometric fit
   (``jax.jacfwd`` of the extended model, all candidates in one compiled program); what the
   frame errors absorb is projected out; the absorbed fraction, the F test, the held-out
   log-likelihood gain and the candidates this pose set cannot tell apart are tabulated.
4. **Select and refit**: the significant candidates whose held-out merit comes close to the
   best one's (:data:`MAX_CONTENDERS`) are each refitted jointly with the frame errors
   (Levenberg-Marquardt on the whitened residual, :mod:`cdra_jax.calibration.damped`), in
   chains of their forms (:func:`_chains`, :func:`_fit_effect`); the held-out sum of squares
   decides between refits, a refit with more parameters paying for them
   (:func:`_predicts_better`); refits that predict equally well are reported as
   indistinguishable. 95 % intervals come from the joint covariance; a physically
   implausible estimate is never reported.
5. **Specific, or unattributed**: a generic probe of no more parameters at another place that
   predicts held-out poses better (:func:`_outdone`), a refit that leaves a misfit it does not
   explain (:data:`EXPLAINED_MIN`), or no significant candidate: the effect is
   ``unattributed``, located where its structure lives (:func:`_locate_unattributed`).
6. **Noise not given**: a diagnosis that names an effect runs again with the noise estimated
   from that effect's refit (:data:`NOISE_PASSES`).
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import scipy.stats

from ..arm import Arm
from ..calibration import NoiseModel
from ..calibration.auto import calibrate_auto
from ..calibration.model import stacked_system
from ..calibration.observations import (
    ROW_POINT,
    ROW_POSITION,
    ROW_ROTATION,
    Observations,
    apply_parameters,
    make_observations,
    marker_table,
    row_layout,
)
from ..calibration.validation import MIN_POSES
from ..io.measurements import Measurements, aux_columns
from ..physics import (
    PROBES,
    VOCABULARY,
    Candidate,
    Effect,
    Features,
    TimeProbe,
    candidates,
    check_effect_data,
    model_effects,
    with_effects,
)
from . import stats
from .model import (
    Extended,
    all_features,
    geometric_fit,
    joint_refit,
    residual_and_columns,
    residual_and_jacobian,
)
from .report import render_report
from .result import CandidateRow, Diagnosis, HeldOutErrors, ParameterEstimate, _num

EXPLAINED_MIN = 0.9
"""A significant candidate whose refit leaves a significant held-out misfit is still reported
when it removes at least this fraction of the excess held-out chi-square ``Q - E[Q]``."""

LOCATE_MIN = 0.5
"""An unattributed misfit is placed where the best (rejected) candidate sits when that
candidate removes at least this fraction of the excess and no generic probe at another place
explains the residual more significantly; otherwise the structure test and the probes place it."""

SHAPE_SPLIT = 0.5
"""The shape check of a series form (:func:`_shape_check`) compares its amplitudes on the poses
below and above this quantile (the median) of each of its axes' coordinate."""

REFINE_GAIN_PER_PARAM = 2.0
"""A further form of the selected effect at the selected place (another variant, or a
refinement such as a load-hardening term) joins the refit only when it raises the held-out
log-likelihood by more than this many nats per added parameter (about the 2.5 % tail of the
chance gain; see :func:`_chains`)."""

MAX_REFINEMENTS = 3
"""At most this many further forms join the selected one."""

NOISE_TOLERANCE = 2.5
"""Given noise values enter the verdict only through a held-out chi-square that tolerates a
noise variance this many times the stated one (a standard deviation 1.58 times): a stated
noise 0.7 to 1.3 times the truth never changes the verdict, while a misfit several times the
noise is still seen where no structure test sees it. The plain chi-square (tolerance 1) checks
the stated values and is reported."""

COS_INDISTINGUISHABLE = 0.98
RIVAL_NATS = 3.0
"""A significant candidate whose held-out log-likelihood gain comes within this many nats of
the selected one's (a likelihood ratio under about 20) is named as nearly as well supported:
these poses do not clearly prefer the selection over it."""
REPEAT_TOL = 1e-6
"""Module states that agree within this (rad or mm, per entry) count as a repeated pose."""

NOISE_PASSES = 2
"""Without noise values, a diagnosis that names an effect is run once more with the noise
re-estimated from that effect's refit (at most this many passes in all); with noise values,
only where that refit's residual contradicts them (:data:`NOISE_CONTRADICTION`)."""

NOISE_CONTRADICTION = 1.25
"""Given noise values are contradicted where the noise estimated from the named effect's refit
(position, rotation or a point) differs from them by more than this factor either way. The
diagnosis is then run again with the estimated noise, as without noise values: a stated noise
30 % too small inflates every candidate's held-out gain and lets a more flexible one pay for
its parameters (the verdict would depend on the value given). On the default CDRA, 30 poses,
the estimate from the refit scatters by about 8 % (1 std) at the true noise."""

REFIT_RTOL = 1e-8
"""A candidate's joint refit has converged when a step lowers the whitened cost by less than
this fraction (about 1e-3 of a parameter's standard deviation on a few hundred entries; a
tighter tolerance creeps along the ill-conditioned directions of many lumped products)."""

REFIT_STEPS = 15
"""At most this many accepted Levenberg-Marquardt steps per refit: a well-posed refit
converges in a few; one that creeps along ill-conditioned combinations (many lumped products
together) has by then reached the held-out error it will have."""

MAX_CHAINS = 3
"""The chains of forms of a selected effect that are refitted: the tested form's and the best
others' (:func:`_fit_effect`)."""

MAX_CONTENDERS = 3
"""The significant candidates whose linearised held-out merit comes within :data:`RIVAL_NATS`
or :data:`CONTENDER_FRACTION` of the best one's are refitted (at most this many); the refit
that predicts held-out poses best is selected (a linearisation at the geometric fit
misjudges a large effect by a share of its size)."""

CONTENDER_FRACTION = 0.1


ABSORBED_EXACTLY = (
    "a uniform length scale of the arm (every fixed translation scaled alike): the frame "
    "errors absorb it exactly",
    "constant joint offsets (encoder zeros) of revolute and prismatic modules and constant "
    "rotations of a module's platform: the neighbouring frame errors absorb them exactly",
    "a constant measurement-device bias (a fixed transform between the measuring device and "
    "the world frame): the base frame error absorbs it exactly",
    "a constant tool or calibration-block offset: the tool frame error absorbs it exactly",
)

_NOISE_RATIO_DEFAULT = (1.0, 1e-3)  # mm, rad: the first fit's weighting when no noise is given

_POSITION, _ROTATION, _POINT = ROW_POSITION, ROW_ROTATION, ROW_POINT


@dataclasses.dataclass(frozen=True)
class _Rows:
    """The measured entries of the stacked residual (:func:`.observations.row_layout`).

    Attributes:
        take: ``(N,)`` their indices in the stacked vector.
        row: ``(N,)`` the measurement row (pose) of each.
        kind: ``(N,)`` full-pose position, full-pose rotation or point.
        entry: ``(N,)`` the entry's number within its row (the same entry of two repeated
            rows has the same number).
        unit: ``(N,)`` the 3-vector (a full pose's position or rotation, a point) it belongs to.
        point: ``(N,)`` the point's index (``-1`` for full-pose entries).
        scale: ``(N,)`` its standard deviation (mm or rad): whitened times scale is physical.
    """

    take: np.ndarray
    row: np.ndarray
    kind: np.ndarray
    entry: np.ndarray
    unit: np.ndarray
    point: np.ndarray
    scale: np.ndarray

    @property
    def size(self) -> int:
        return int(self.take.size)

    @property
    def noise_group(self) -> np.ndarray:
        """``(N,)`` the noise each entry has: 0 full-pose position, 1 rotation, ``2 + j``
        point ``j``."""
        return np.where(self.kind == _POINT, 2 + self.point, self.kind)


def _rows(problem: Extended) -> _Rows:
    obs = problem.obs
    measured, row, kind, point = row_layout(obs)
    n_pose = 6 * obs.m
    idx = np.arange(measured.size)
    entry = np.where(idx < n_pose, idx % 6, 6 + 3 * point + (idx - n_pose) % 3)
    sp = np.broadcast_to(np.asarray(problem.sigma_pos, float), (obs.m,))
    sr = np.broadcast_to(np.asarray(problem.sigma_rot, float), (obs.m,))
    spt = np.broadcast_to(np.asarray(problem.sigma_pt, float), (obs.m, obs.n_points))
    scale = np.concatenate(
        [np.stack([sp] * 3 + [sr] * 3, axis=1).reshape(-1), np.repeat(spt.reshape(-1), 3)]
    )
    take = np.flatnonzero(measured)
    return _Rows(take, row[take], kind[take], entry[take], idx[take] // 3, point[take], scale[take])


def _sigmas(obs: Observations, position_mm, rotation_rad, points_mm, dtype):
    """Per-row standard deviations ``(m,), (m,), (m, P)``: one value for the full poses'
    position and one for their rotation, one per point (``points_mm`` scalar or ``(P,)``)."""
    m, P = obs.m, obs.n_points
    return (
        jnp.full((m,), position_mm, dtype),
        jnp.full((m,), rotation_rad, dtype),
        jnp.broadcast_to(jnp.asarray(points_mm, dtype), (m, P)),
    )


def _estimate_noise(arm: Arm, q, T, floor: tuple[float, float]) -> NoiseModel:
    """Position and rotation noise estimated separately from a geometric fit of full poses
    (no noise given).

    A first fit weighted 1 mm : 1 mrad; then :func:`stats.variance_components` on its residual
    in mm and rad (the tool-point position error and the rotation of each pose), which
    reweights the linearised fit until each group's residual sum of squares matches its share
    of the residual degrees of freedom."""
    sol = geometric_fit(arm, q, T, NoiseModel(*_NOISE_RATIO_DEFAULT))
    # whitening by (1 mm, 1 rad): rows in mm (tool point) and rad, the Jacobian alike
    e, D = stacked_system(arm.with_frames(sol.frames), q, T, NoiseModel(1.0, 1.0))
    groups = np.tile([0, 0, 0, 1, 1, 1], int(np.shape(q)[0]))
    sp, sr = stats.variance_components(
        np.asarray(e, float), np.asarray(D, float), groups, np.asarray(floor)
    )
    # arrays, not Python floats: the compiled fit treats floats as static (one compile each)
    return NoiseModel(jnp.asarray(sp, q.dtype), jnp.asarray(sr, q.dtype))


def _point_noise(
    problem: Extended,
    floor: tuple[float, float],
    y: np.ndarray | None = None,
    free: np.ndarray | None = None,
) -> tuple[float, float, np.ndarray]:
    """``(position mm, rotation rad, points (P,) mm)`` estimated by variance components on the
    model's residual at ``y`` (default: zero) in physical units (every standard deviation 1),
    with the degrees of freedom of the parameters ``free`` (indices into ``y``; default: the
    base model's, frames, markers and the model's own effects): one group for the full poses'
    positions, one for their rotations, one per point (NaN for a group without measurements)."""
    dtype = problem.q.dtype
    P = problem.obs.n_points
    one = _sigmas(problem.obs, 1.0, 1.0, 1.0, dtype)
    unit = eqx.tree_at(lambda p: (p.sigma_pos, p.sigma_rot, p.sigma_pt), problem, one)
    if y is None:
        y = np.zeros(unit.n_frames_markers + unit.features.n_params)
    if free is None:
        free = np.arange(unit.n_geometric)
    e, D = residual_and_columns(jnp.asarray(y, dtype), unit, free)
    rows = _rows(unit)
    e = np.asarray(e, float)[rows.take]
    D = np.asarray(D, float)[rows.take]
    groups = rows.noise_group
    floors = np.array([floor[0], floor[1]] + [floor[0]] * P)
    s = stats.variance_components(e, D, groups, floors)
    present = np.array([np.any(groups == g) for g in range(2 + P)])
    s = np.where(present, s, np.nan)
    return float(s[0]), float(s[1]), s[2:]


def _with_estimated_noise(
    problem: Extended,
    floor: tuple[float, float],
    y: np.ndarray | None = None,
    free: np.ndarray | None = None,
) -> Extended:
    """``problem`` weighted by the noise :func:`_point_noise` estimates (1 for a kind that is
    not measured)."""
    sp, sr, spt = _point_noise(problem, floor, y, free)
    est = (
        sp if math.isfinite(sp) else 1.0,
        sr if math.isfinite(sr) else 1.0,
        np.where(np.isfinite(spt), spt, 1.0),
    )
    return eqx.tree_at(
        lambda p: (p.sigma_pos, p.sigma_rot, p.sigma_pt),
        problem,
        _sigmas(problem.obs, *est, problem.q.dtype),
    )


def _gravity_in_fit_frame(fit_arm: Arm, nominal: Arm) -> Arm:
    """``fit_arm`` with the nominal model's gravity turned with its base frame: the fit may
    place the world frame in a measuring device's frame (a registration), while the nominal
    model's gravity is given in the robot's world frame, fixed to the nominal base."""
    R_fit = jnp.asarray(fit_arm.frames)[0, :3, :3]
    R_nom = jnp.asarray(nominal.frames, R_fit.dtype)[0, :3, :3]
    g = R_fit @ R_nom.T @ jnp.asarray(nominal.gravity, R_fit.dtype)
    return eqx.tree_at(lambda a: a.gravity, fit_arm, g)


def _measured_positions(meas: Measurements) -> np.ndarray:
    """``(n, 3)`` every measured position (full-pose origins and seen points, mm)."""
    parts = []
    if meas.full_poses is not None:
        parts.append(np.asarray(meas.full_poses)[:, :3, 3])
    if meas.points is not None:
        parts.append(np.asarray(meas.points).reshape(-1, 3))
    pts = np.concatenate(parts) if parts else np.zeros((0, 3))
    return pts[np.all(np.isfinite(pts), axis=1)]


def _as_arrays(arm: Arm, meas: Measurements):
    dtype = jnp.asarray(arm.frames).dtype
    q = jnp.asarray(meas.q, dtype)
    aux = {k: jnp.asarray(v, dtype) for k, v in meas.aux.items()}
    return q, aux


def _check(arm: Arm, meas: Measurements, folds: int, alpha: float) -> None:
    if not isinstance(meas, Measurements):
        raise ValueError(
            "measurements must be a cdra_jax.io.Measurements (from load_measurements or "
            f"Measurements.from_arrays), got {type(meas).__name__}"
        )
    if not meas.has_measurements:
        raise ValueError(
            f"{meas.source}: no measured tool poses or points (measured.x ... columns); a "
            "diagnosis needs them"
        )
    if tuple(meas.state_names) != tuple(arm.state_names):
        raise ValueError(
            f"{meas.source}: module states {meas.state_names} do not match the model's "
            f"{arm.state_names}"
        )
    if meas.m < MIN_POSES + 2:
        raise ValueError(
            f"{meas.source}: {meas.m} poses; a diagnosis needs at least {MIN_POSES + 2} (a "
            "calibration on every cross-validation training set)"
        )
    if not (isinstance(folds, int) and folds >= 2):
        raise ValueError(f"folds must be an integer >= 2, got {folds!r}")
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha!r}")


def _estimates(
    theta: np.ndarray, sigma: np.ndarray, cand: Candidate, arm: Arm
) -> dict[str, ParameterEstimate]:
    out = {}
    for spec, v, s in zip(cand.parameters(arm), theta, sigma, strict=True):
        half = 1.959963984540054 * float(s)
        out[spec.name] = ParameterEstimate(
            value=float(v),
            low=float(v) - half,
            high=float(v) + half,
            unit=spec.unit,
            range_low=float(spec.low),
            range_high=float(spec.high),
            description=spec.description,
        )
    return out


def _linear_fit(r: np.ndarray, A: np.ndarray, scale_var: float) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-norm ``y`` minimising ``|r + A y|`` and the standard deviation of each entry."""
    An, s = stats._normalise_columns(A)
    P, _ = stats.pinv(An)
    y = -(P @ r) * s
    sd = np.sqrt(np.maximum(np.sum(P * P, axis=1), 0.0) * scale_var) * s
    return y, sd


def _per_row(values: np.ndarray, rows: _Rows, m: int) -> dict[str, np.ndarray]:
    """Per measurement row: ``position_mm`` (m,) the RMS norm of the row's position errors (the
    full pose's tool point and each seen point) and ``rotation_rad`` (m,) the norm of its
    rotation error (NaN where the row has none), from physical entry values ``(N,)``."""
    out = {}
    for name, kinds in (("position_mm", (_POSITION, _POINT)), ("rotation_rad", (_ROTATION,))):
        sel = np.isin(rows.kind, kinds)
        units, inverse = np.unique(rows.unit[sel], return_inverse=True)
        sq = np.bincount(inverse, weights=values[sel] ** 2, minlength=units.size)
        owner = rows.row[sel][np.unique(inverse, return_index=True)[1]]
        total = np.bincount(owner, weights=sq, minlength=m)
        count = np.bincount(owner, minlength=m)
        with np.errstate(invalid="ignore", divide="ignore"):
            out[name] = np.where(count > 0, np.sqrt(total / np.maximum(count, 1)), np.nan)
    return out


def _rms(values: np.ndarray, rows: _Rows, kinds: tuple[int, ...]) -> float:
    """RMS over the 3-vectors of ``kinds`` of their norm (NaN where there is none)."""
    sel = np.isin(rows.kind, kinds)
    n_units = np.unique(rows.unit[sel]).size
    return float(np.sqrt(np.sum(values[sel] ** 2) / n_units)) if n_units else math.nan


def _suggested_noise(
    r: np.ndarray, df_resid: int, rows: _Rows, point_names: Sequence[str]
) -> dict[str, Any]:
    """The noise (std) the geometric fit's residual would imply if nothing were missing: the
    used one scaled by the RMS of the whitened residual of each kind (each point), corrected
    for the degrees of freedom the fit uses (``None`` for a kind not measured)."""
    dof = df_resid / r.size

    def implied(sel):
        if not sel.any():
            return None
        return float(np.sqrt(np.mean(r[sel] ** 2) / dof)) * float(np.median(rows.scale[sel]))

    out: dict[str, Any] = {
        "position_mm": implied(rows.kind == _POSITION),
        "rotation_rad": implied(rows.kind == _ROTATION),
    }
    if point_names:
        out["points_mm"] = {n: implied(rows.point == j) for j, n in enumerate(point_names)}
    return out


def _errors(ho: stats.HeldOut, rows: _Rows, p_value: float | None) -> HeldOutErrors:
    phys = ho.residual * rows.scale
    return HeldOutErrors(
        _rms(phys, rows, (_POSITION, _POINT)),
        _rms(phys, rows, (_ROTATION,)),
        float(ho.statistic),
        p_value,
    )


def _noise_floor(ho: stats.HeldOut, rows: _Rows) -> tuple[float, float]:
    """RMS held-out prediction error expected from the noise alone (position mm, rotation rad)."""
    sd = np.sqrt(ho.variance) * rows.scale
    return _rms(sd, rows, (_POSITION, _POINT)), _rms(sd, rows, (_ROTATION,))


def _geometric_start(arm: Arm, meas: Measurements, q, aux, noise: NoiseModel | None, floor):
    """The geometric fit the diagnosis starts from, as an :class:`Extended` problem (without
    features yet) and the fit's summary.

    Full poses in every row: the weighted Gauss-Newton of the paper from the nominal frames
    (noise estimated first where none is given, :func:`_estimate_noise`). Points (markers, the
    tool origin) or rows without a full pose: the ``auto`` solver's plain least squares
    (:func:`cdra_jax.calibration.calibrate_auto`: the device frame registered, markers with
    ``calibrate = true`` placed), then the noise of each kind estimated on its residual."""
    dtype = q.dtype
    xyz_nom, calibrated = marker_table(arm, meas.point_names)
    obs = make_observations(arm, meas.q, meas.full_poses, meas.points)
    none = Features.zeros(arm, meas.m, 0, dtype)
    if meas.measured is not None:
        T = jnp.asarray(meas.measured, dtype)
        wn = noise if noise is not None else _estimate_noise(arm, q, T, floor)
        sol = geometric_fit(arm, q, T, wn)
        sp, sr, spt = _sigmas(obs, wn.position_mm, wn.rotation_rad, wn.position_mm, dtype)
        problem = Extended(
            arm=arm.with_frames(sol.frames),
            q=q,
            obs=obs,
            sigma_pos=sp,
            sigma_rot=sr,
            sigma_pt=spt,
            xyz=jnp.asarray(xyz_nom, dtype),
            features=none,
        )
        fit = {
            "solver": "weighted Gauss-Newton",
            "converged": bool(sol.converged),
            "iterations": int(sol.iterations),
        }
        return problem, fit
    auto = calibrate_auto(
        arm, meas.q, meas.full_poses, meas.points, meas.point_names, noise=noise, loss="ls"
    )
    s = (
        (float(noise.position_mm), float(noise.rotation_rad), float(noise.position_mm))
        if noise is not None
        else (1.0, 1.0, 1.0)
    )
    sp, sr, spt = _sigmas(obs, *s, dtype)
    problem = Extended(
        arm=arm.with_frames(jnp.asarray(auto.frames, dtype)),
        q=q,
        obs=obs,
        sigma_pos=sp,
        sigma_rot=sr,
        sigma_pt=spt,
        xyz=jnp.asarray(auto.xyz, dtype),
        features=none,
        calibrated=auto.calibrated_points,
    )
    if noise is None:
        problem = _with_estimated_noise(problem, floor)
    fit = {
        "solver": "auto solver, least squares",
        "converged": bool(auto.converged),
        "iterations": int(auto.iterations),
    }
    return problem, fit


def diagnose(
    arm: Arm,
    measurements: Measurements,
    noise: NoiseModel | None,
    *,
    seed: int = 0,
    folds: int = 5,
    alpha: float = 0.01,
    effects: Sequence[Effect] = VOCABULARY,
) -> Diagnosis:
    """Diagnose what a geometric calibration of ``arm`` leaves unexplained in ``measurements``.

    Args:
        arm: the nominal model (frames are the calibration's starting point; masses, cables,
            pretension and stiffness feed the physics).
        measurements: what :func:`cdra_jax.io.load_measurements` returns (module states,
            measured tool poses, auxiliary columns ``time_s``, ``approach.<module>``,
            ``payload_kg``).
        noise: the measuring device's noise (position mm, rotation rad std). ``None``: the
            position and rotation noise are estimated separately from the geometric fit's
            residual (variance components, with the degrees of freedom the fit uses; see
            :func:`stats.variance_components`), and only the tests that need no noise value
            (residual structure, lack of fit on repeated poses, candidate F tests) detect a
            mismatch. When an effect is named, its refit's residual gives the noise of the
            data (the geometric fit's residual holds the effect too), and the diagnosis is run
            again with that noise (:data:`NOISE_PASSES`).
        seed: seed of the cross-validation folds.
        folds: number of cross-validation folds (poses are dealt at random).
        alpha: significance level of the detection and of the (Holm-corrected) candidate tests.
        effects: the candidate vocabulary (default: all seven effects of the design).

    Returns:
        A :class:`Diagnosis` (``to_dict()`` for JSON, ``report`` for the plain words).
    """
    _check(arm, measurements, folds, alpha)
    meas = measurements
    q, aux = _as_arrays(arm, meas)
    given = noise is not None
    # below this a residual is rounding (exact data), not measurement noise
    floor_phys = stats.rounding_floor(_measured_positions(meas))

    # the model's own [[effects]] are part of the base model: fitted with the frames
    own, theta_own = model_effects(arm, meas.source)
    check_effect_data(arm, aux.keys(), str(meas.source))

    # 1. geometric fit (frames and markers; the model's effects joined below)
    base, fit_info = _geometric_start(arm.with_effects(()), meas, q, aux, noise, floor_phys)

    # 2. features of the model's effects, then of every evaluable candidate and probe, one
    # Jacobian for all
    table = _not_in_model(candidates(arm, aux.keys(), effects), own)
    live = [c for c, why in table if why is None]
    table = [(c, why) for c, why in table if not c.effect.refinement]
    probes = [c for c, why in candidates(arm, aux.keys(), PROBES) if why is None]
    everything = tuple(live + probes)
    sizes = [len(c.parameters(arm)) for c in everything]
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    cols = {c: slice(int(offsets[i]), int(offsets[i + 1])) for i, c in enumerate(everything)}
    F_all, finite = _finite_columns(
        all_features(own + everything, _gravity_in_fit_frame(base.arm, arm), q, aux)
    )
    if not np.all(finite[: theta_own.size]):
        raise ValueError(
            f"{meas.source}: the model's [[effects]] are not finite on these data (check the "
            "auxiliary columns and the model's masses)"
        )
    problem = dataclasses.replace(base, features=F_all, n_model_effects=int(theta_own.size))
    n_geo = problem.n_geometric
    y_base = np.zeros(problem.n_frames_markers + F_all.n_params)
    if own:
        y_base[problem.n_frames_markers : n_geo] = theta_own
        y_base = joint_refit(y_base, np.arange(n_geo), problem)[0]
        fit_info["model_effects"] = [c.label for c in own]
        if not given:  # the noise of the data, not of the effects the geometric fit missed
            problem = _with_estimated_noise(problem, floor_phys, y_base)
    setup = _Setup(
        arm=arm,
        meas=meas,
        given=given,
        alpha=alpha,
        fold=stats.fold_of_poses(meas.m, folds, seed),
        seed=seed,
        floor_phys=floor_phys,
        own=tuple(own),
        table=table,
        live=live,
        probes=probes,
        cols=cols,
        finite=finite[theta_own.size :],
        fit_info=fit_info,
        regressors=_regressors(arm, meas),
        repeats=stats.repeat_groups(np.asarray(meas.q), REPEAT_TOL),
    )
    verdict = _judge(setup, problem, y_base)
    for _ in range(NOISE_PASSES - 1):
        if verdict.free is None:
            break
        # an effect is named: the noise of the data is what its refit leaves, not what the
        # geometric fit left (that holds the effect too, and its share of position and
        # rotation); the diagnosis runs again weighted by that noise
        estimated = _with_estimated_noise(problem, floor_phys, verdict.y, verdict.free)
        only = verdict.contenders
        if setup.given:
            ratio = _noise_ratio(problem, estimated)
            if 1.0 / NOISE_CONTRADICTION <= ratio <= NOISE_CONTRADICTION:
                break
            # the refit contradicts the stated noise: from here on as without noise values,
            # every significant candidate selected again
            setup = dataclasses.replace(setup, given=False, contradicted=ratio)
            only = frozenset()
        problem = estimated
        y_base = joint_refit(y_base, np.arange(n_geo), problem)[0]
        verdict = _judge(setup, problem, y_base, passes=verdict.passes + 1, only=only)
    return verdict.diagnosis


def _noise_ratio(stated: Extended, estimated: Extended) -> float:
    """The factor by which the ``estimated`` noise departs most from the ``stated`` one, over
    the measured kinds (position, rotation, each point; the median over the rows): the ratio
    estimated / stated farthest from 1."""
    worst = 1.0
    for a_in, b_in in (
        (stated.sigma_pos, estimated.sigma_pos),
        (stated.sigma_rot, estimated.sigma_rot),
        (stated.sigma_pt, estimated.sigma_pt),
    ):
        a, b = np.asarray(a_in, float), np.asarray(b_in, float)
        ok = np.isfinite(a) & np.isfinite(b) & (a > 0) & (b > 0)
        if a.ndim == 2:  # points: one ratio per point
            ratios = [np.median(b[:, j][ok[:, j]] / a[:, j][ok[:, j]]) for j in range(a.shape[1])]
            ratios = [r for r in ratios if np.isfinite(r)]
        else:
            ratios = [float(np.median(b[ok] / a[ok]))] if ok.any() else []
        for r in ratios:
            if abs(math.log(r)) > abs(math.log(worst)):
                worst = float(r)
    return worst


@dataclasses.dataclass(frozen=True)
class _Setup:
    """What every pass of one diagnosis shares (:func:`diagnose`).

    Attributes:
        arm: the nominal model; meas: the measurements; given: whether noise values were given.
        alpha: the significance level; fold: ``(m,)`` cross-validation fold of each row; seed:
            the folds' seed.
        floor_phys: the rounding floor (position mm, rotation rad).
        own: the model's own effects (part of the base model).
        table: every tested (effect, location, variant) with why it is skipped (``None``:
            evaluated); refinements are not in it.
        live: every evaluable form (refinements included); probes: the generic probes.
        cols: each form's and probe's columns among the feature columns.
        finite: ``(p,)`` whether each feature column is finite.
        fit_info: the geometric fit's summary.
        regressors: ``(X, groups, names)`` of the structure test (:func:`_regressors`).
        repeats: groups of repeated poses (lack-of-fit test).
        contradicted: where the named effect's refit contradicted the given noise values, the
            ratio of the estimated noise to them (the pass then runs as without noise values).
    """

    arm: Arm
    meas: Measurements
    given: bool
    alpha: float
    fold: np.ndarray
    seed: int
    floor_phys: tuple[float, float]
    own: tuple[Candidate, ...]
    table: list[tuple[Candidate, str | None]]
    live: list[Candidate]
    probes: list[Candidate]
    cols: dict[Candidate, slice]
    finite: np.ndarray
    fit_info: dict
    regressors: tuple[np.ndarray, np.ndarray, list[str]]
    repeats: list[np.ndarray]
    contradicted: float | None = None


@dataclasses.dataclass(frozen=True)
class _Verdict:
    """One pass's :class:`Diagnosis`, with ``y`` the written model's parameters, ``free`` the
    indices of the parameters fitted with the named effect (``None`` when none is named), the
    number of ``passes`` so far, and the ``(effect, place)`` of the named effect and of those
    its refit could not be told from (what a further pass refits)."""

    diagnosis: Diagnosis
    y: np.ndarray
    free: np.ndarray | None
    passes: int
    contenders: frozenset[tuple[str, str]] = frozenset()


@dataclasses.dataclass
class _Fit:
    """A candidate's joint refit with the frames (:func:`_fit_effect`).

    Attributes:
        forms: the refitted forms (the leading one first, then the forms added to it).
        gains: the held-out log-likelihood gain each form added.
        info: the refit's summary (``details.refit``).
        parameters: the estimates (added forms' named ``<variant>:<name>``).
        heldout: the refit's cross-validated prediction; p_after: its tolerant p-value (given
            noise only).
        y: all entries of ``y`` at the refit; r: its whitened residual; J: the Jacobian of
            every column there.
    """

    forms: list[Candidate]
    gains: list[float]
    info: dict
    parameters: dict[str, ParameterEstimate]
    heldout: stats.HeldOut
    p_after: float | None
    y: np.ndarray
    r: np.ndarray
    J: np.ndarray

    @property
    def lead(self) -> Candidate:
        return self.forms[0]


def _judge(
    s: _Setup,
    problem: Extended,
    y_base: np.ndarray,
    passes: int = 1,
    only: frozenset[tuple[str, str]] = frozenset(),
) -> _Verdict:
    """One pass of the diagnosis on ``problem`` (its noise weighting) from the base model's
    fit ``y_base``: detection, the candidate table, selection and refit, attribution, place.
    ``only``: refit no other significant candidates than these ``(effect, place)`` (a
    further pass re-weights the contenders of the first)."""
    arm, meas, given, alpha, cols = s.arm, s.meas, s.given, s.alpha, s.cols
    m = meas.m
    q = problem.q
    n_geo = problem.n_geometric
    layout = _rows(problem)
    r_j, J_j = residual_and_jacobian(jnp.asarray(y_base, q.dtype), problem)
    r = np.asarray(r_j, float)[layout.take]
    Jfull = np.asarray(J_j, float)[layout.take]
    N = r.size
    D, J = Jfull[:, :n_geo], Jfull[:, n_geo:]
    UD = stats.orthonormal_basis(D)
    rank = UD.shape[1]
    df_resid = N - rank
    # mean square of the rounding floor per whitened entry
    floor_of_kind = np.where(layout.kind == _ROTATION, s.floor_phys[1], s.floor_phys[0])
    floor2 = float(np.mean((floor_of_kind / layout.scale) ** 2))
    fold = s.fold[layout.row]

    # 3. detection
    ho0 = stats.heldout(r, D, fold, with_null=given)
    p_heldout = ho0.p_value() if given else None
    p_tolerant = ho0.p_value(NOISE_TOLERANCE) if given else None
    chi2_in = float(r @ r)
    p_in = float(scipy.stats.chi2.sf(chi2_in, df_resid)) if given else None
    lof = stats.lack_of_fit(r, s.repeats, df_resid, floor2, row=layout.row, entry=layout.entry)
    X_reg, reg_groups, group_names = s.regressors

    def structure(res, basis):
        """The structure test on a residual; not applicable (p = 1) to a residual at the
        rounding level (exact data, an exact fit)."""
        if float(np.mean(res * res)) <= floor2:
            return stats.Structure(0.0, 1.0, 0.0, math.nan)
        return stats.structure_test(res, basis, X_reg, layout.row, layout.entry, reg_groups)

    struct0 = structure(r, UD)

    # 4. candidate table: one row per (effect, location); its variants are alternatives
    evals: dict[Candidate, dict] = {}
    failed: dict[Candidate, str] = {}
    for c, why in s.table:
        if why is not None:
            continue
        if not np.all(s.finite[cols[c]]):
            failed[c] = "failed: its features are not finite on these data"
            continue
        try:
            evals[c] = _evaluate(c, J[:, cols[c]], r, D, UD, df_resid, floor2, fold, ho0)
        except (np.linalg.LinAlgError, ValueError, FloatingPointError) as err:
            # a numerical failure of one candidate (non-finite features, a singular or
            # indefinite matrix): that candidate is marked failed, the diagnosis goes on
            failed[c] = f"failed: {err}"
    table = [(c, failed.get(c, why)) for c, why in s.table]
    by_place: dict[tuple[str, str], list[tuple[Candidate, str | None]]] = {}
    for c, why in table:
        by_place.setdefault((c.name, c.location), []).append((c, why))
    rows: list[CandidateRow] = []
    not_applicable: list[CandidateRow] = []  # skipped whatever the data: not for this arm
    every_column = frozenset(aux_columns(arm))
    chosen: dict[tuple[str, str], Candidate] = {}
    group_p: dict[tuple[str, str], float] = {}
    for key, members in by_place.items():
        ok = [c for c, why in members if why is None]
        if not ok:
            c0, why0 = members[0]
            row = CandidateRow(key[0], key[1], len(c0.parameters(arm)), skipped=why0)
            inapt = all(c.missing(arm, every_column) for c, _ in members)
            (not_applicable if inapt else rows).append(row)
            continue
        seen = [c for c in ok if evals[c]["df"] > 0] or ok
        # The variant with the smallest p (ties: the largest gain), Bonferroni over the variants.
        c = min(seen, key=lambda c: (evals[c]["p"], -(evals[c]["gain"] or -np.inf)))
        chosen[key] = c
        e = evals[c]
        row = CandidateRow(key[0], key[1], len(c.parameters(arm)), variant=c.variant or None)
        row.variants = [o.variant for o in ok] if len(ok) > 1 else []
        row.absorbed_fraction = e["proj"].absorbed_fraction
        row.df = e["df"]
        row.statistic = e["F"] if e["df"] else None
        row.heldout_gain = e["gain"]
        row.p_value_raw = min(1.0, len(seen) * e["p"]) if e["df"] else 1.0
        y_lin, sd_lin = _linear_fit(r, e["A"], 1.0)
        row.parameters = _estimates(y_lin[n_geo:], sd_lin[n_geo:], c, arm)
        rows.append(row)
        if e["df"]:
            group_p[key] = row.p_value_raw
    keys = list(group_p)
    adj = dict(zip(keys, stats.holm(np.array([group_p[k] for k in keys])), strict=True))
    by_key = {(row.effect, row.location): row for row in rows}
    for key, c in chosen.items():
        row = by_key[key]
        row.p_value = adj.get(key, 1.0)
        row.indistinguishable_from = [
            f"{o[0]}@{o[1]}"
            for o in keys
            if o != key
            and key in group_p
            and stats.indistinguishable(
                evals[c]["proj"].basis, evals[chosen[o]]["proj"].basis, COS_INDISTINGUISHABLE
            )
        ]
    p_family = min(adj.values(), default=1.0)

    # The verdict rests on tests that need no noise value (their statistics do not change when
    # every noise value is scaled): the candidates' F tests, the residual's structure, the
    # lack of fit between repeats. A chi-square against given noise values checks those values.
    probe_rows, probe_place = _locate(s.probes, cols, r, J, UD, df_resid, alpha, floor2)
    tests_used = {"candidates": p_family, "structure": struct0.p_value}
    if p_tolerant is not None:
        tests_used["heldout_chi2_tolerant"] = p_tolerant
    if lof is not None and lof.p_value is not None:
        tests_used["lack_of_fit"] = lof.p_value
    p_value = min(1.0, len(tests_used) * min(tests_used.values()))
    mismatch = p_value < alpha

    # 5. selection, refit
    effect_name = "none"
    located_in: str | None = None
    parameters: dict[str, ParameterEstimate] = {}
    before = _errors(ho0, layout, p_heldout)
    after = before
    refit_info: dict = {}
    fit: _Fit | None = None
    ties: list[_Fit] = []  # other effects whose refits predict held-out poses as well
    y_model = y_base  # the written model: the base model's fit ...
    free: np.ndarray | None = None  # ... and the parameters fitted with the named effect
    rival: dict | None = None
    explained = 0.0
    significant = [
        chosen[k] for k in keys if adj[k] < alpha and (evals[chosen[k]]["merit"] or -1.0) > 0
    ]
    lin = _Linearised(problem, layout, arm, r, D, J, fold, given, y_base, cols)
    if mismatch and significant:
        narrowed = [c for c in significant if (c.name, c.location) in only]
        fit, ties = _select(narrowed or significant, evals, lin, s.live)
        best = fit.lead
        refit_info = fit.info
        parameters = fit.parameters
        ho1 = fit.heldout
        after = _errors(ho1, layout, fit.p_after)
        explained = min(
            _explained(ho0.statistic - N, ho1.statistic - N),
            _explained(
                ho0.sum_of_squares - ho0.expected_sum_of_squares,
                ho1.sum_of_squares - ho1.expected_sum_of_squares,
            ),
        )
        refit_info["explained_fraction_heldout"] = float(explained)
        fitted = np.concatenate([np.arange(n_geo), n_geo + _columns(fit.forms, cols)])
        U1 = stats.orthonormal_basis(fit.J[:, fitted])
        struct1 = structure(fit.r, U1)
        after_rows, _ = _locate(
            s.probes, cols, fit.r, fit.J[:, n_geo:], U1, N - U1.shape[1], alpha, floor2
        )
        refit_info["probes_after"] = after_rows[:3]
        explained = _explained(struct0.gain, struct1.gain)
        refit_info["explained_fraction_structure"] = float(explained)
        refit_info["explained_fraction"] = float(
            refit_info["explained_fraction_heldout"] if given else explained
        )
        refit_info["structure_after"] = {
            "statistic": struct1.statistic,
            "p_value": struct1.p_value,
            "scale": _num(struct1.scale),
        }
        tested = chosen[(best.name, best.location)]
        rival = _outdone(tested, evals[tested]["gain"], s.probes, probe_rows, lin, ho0, alpha)
        shape = _shape_check(fit, lin, s.live, floor2)
        if shape is not None:
            refit_info["shape_check"] = shape
        implausible = _implausible(parameters)
        if implausible:
            # never report an effect whose estimate is physically impossible (a negative
            # compliance): it stands in for something else
            refit_info["rejected"] = {
                "candidate": best.label,
                "reason": "its estimate is physically implausible: " + "; ".join(implausible),
            }
            effect_name = "unattributed"
        elif rival is not None:
            # a generic probe of no more parameters elsewhere predicts held-out poses better:
            # the effect's form is not what the data single out
            refit_info["rejected"] = {
                "candidate": best.label,
                "reason": (
                    f"it is not specific: a generic {rival['kind']} at the {rival['location']} "
                    f"({rival['n_params']} parameters, no more than its {rival['against']}) "
                    f"predicts held-out poses better (log-likelihood gain "
                    f"{rival['heldout_gain']:.1f} against {rival['candidate_gain']:.1f})"
                ),
            }
            effect_name = "unattributed"
        elif shape is not None and shape["p_value"] < alpha:
            # a series in a coordinate (harmonics) that fits a shape of another kind over part
            # of a period: its amplitudes differ between the two halves of the range
            refit_info["rejected"] = {
                "candidate": best.label,
                "reason": (
                    "its shape is not the same over the range of the angle it is periodic in: "
                    "its amplitudes differ between the poses below and above the median angle "
                    f"(F = {shape['F']:.2f}, p = {shape['p_value']:.2g}), as those of a "
                    "series that fits another shape over part of one period do"
                ),
            }
            effect_name = "unattributed"
        elif (
            given
            and fit.p_after is not None
            and fit.p_after < alpha
            and refit_info["explained_fraction_heldout"] < EXPLAINED_MIN
        ) or (not given and struct1.p_value < alpha and explained < EXPLAINED_MIN):
            # a misfit remains that the effect does not explain: a shape the vocabulary lacks
            # (given noise: beyond what NOISE_TOLERANCE times its variance explains; without:
            # structure that the joint states still predict)
            effect_name = "unattributed"
        else:
            y_model = fit.y
            free = fitted
            effect_name = best.name
            located_in = best.location
            row = by_key[(best.name, best.location)]
            row.selected = True
            row.parameters = parameters
            row.variant = best.variant or None  # the refit's leading form
    elif mismatch:
        effect_name = "unattributed"

    indistinguishable: dict | None = None
    if located_in is not None and fit is not None and ties:
        indistinguishable = {
            "within_nats": RIVAL_NATS,
            "candidates": [
                {
                    "candidate": f.lead.label,
                    "variant": f.lead.variant or None,
                    "heldout_sum_of_squares": float(f.heldout.sum_of_squares),
                }
                for f in [fit, *ties]
            ],
        }
    close_rivals = []
    if located_in is not None and fit is not None:
        top = by_key[(fit.lead.name, fit.lead.location)].heldout_gain or 0.0
        close_rivals = [
            {"candidate": row.label, "heldout_gain": row.heldout_gain}
            for row in rows
            if not row.selected
            and row.heldout_gain is not None
            and row.heldout_gain >= top - RIVAL_NATS
            and (row.p_value if row.p_value is not None else 1.0) < alpha
        ]

    location_source = None if located_in is None else "candidate"
    structure_rows: list[dict] = []
    if effect_name == "unattributed":
        parameters = {}
        best_p = None if fit is None else by_key[(fit.lead.name, fit.lead.location)].p_value
        located_in, location_source, structure_rows = _locate_unattributed(
            arm,
            struct0,
            group_names,
            probe_rows,
            probe_place,
            alpha,
            None if fit is None else (fit.lead.location, best_p, refit_info["explained_fraction"]),
            rival,
        )

    not_ident = list(ABSORBED_EXACTLY) + [
        f"{row.label}: the frame errors absorb it for this pose set (absorbed fraction "
        f"{row.absorbed_fraction:.4f})"
        for row in rows
        if row.skipped is None and row.df == 0
    ]
    floor = _noise_floor(ho0, layout)
    used: dict[str, Any] = {
        "position_mm": float(np.asarray(problem.sigma_pos)[0])
        if meas.full_poses is not None
        else None,
        "rotation_rad": float(np.asarray(problem.sigma_rot)[0])
        if meas.full_poses is not None
        else None,
    }
    if meas.points is not None:
        sigma_pt = np.asarray(problem.sigma_pt)[0]
        used["points_mm"] = {n: float(v) for n, v in zip(meas.point_names, sigma_pt, strict=True)}
    source = "given" if given else "estimated"
    if not given:
        used["estimated_from"] = (
            "the residual of the refit with the named effect"
            if passes > 1
            else "the residual of the geometric fit"
        )
    if s.contradicted is not None:
        used["stated_contradicted_by"] = float(s.contradicted)
    diag = Diagnosis(
        mismatch=bool(mismatch),
        p_value=float(p_value),
        effect=effect_name,
        located_in=located_in,
        parameters=parameters,
        candidates=rows,
        heldout_before=before,
        heldout_after=after,
        noise={**used, "source": source},
        not_identifiable_from_poses=not_ident,
        tests={
            "heldout_chi2": {
                "statistic": ho0.statistic,
                "expected": float(N),
                "p_value_tolerant": p_tolerant,
                "noise_tolerance": NOISE_TOLERANCE,
                "entries": int(N),
                "p_value": p_heldout,
            },
            "in_sample_chi2": {"statistic": chi2_in, "df": int(df_resid), "p_value": p_in},
            "lack_of_fit": None
            if lof is None
            else {
                "F": lof.F,
                "p_value": lof.p_value,
                "df_lack_of_fit": lof.df_lack_of_fit,
                "df_pure_error": lof.df_pure_error,
                "repeated_groups": len(s.repeats),
                "applicable": lof.applicable,
            },
            "structure": {
                "statistic": struct0.statistic,
                "p_value": struct0.p_value,
                "scale": _num(struct0.scale),
                "regressors": list(group_names),
            },
            "candidates_min_p_holm": p_family,
            "combined": {"p_value": p_value, "tests": sorted(tests_used), "rule": "Bonferroni"},
        },
        details={
            "alpha": alpha,
            "folds": int(fold.max() + 1),
            "seed": s.seed,
            "n_poses": m,
            "n_frame_params": arm.n_params,
            "noise_floor": {"delta_p_mm": floor[0], "delta_R_rad": _num(floor[1])},
            "rounding_floor": {"position_mm": s.floor_phys[0], "rotation_rad": s.floor_phys[1]},
            "noise_suggested": _suggested_noise(r, df_resid, layout, meas.point_names),
            "noise_passes": passes,
            "geometric_fit": {
                **s.fit_info,
                "rank": int(rank),
                "n_params": n_geo,
                "n_marker_coordinates": 3 * len(problem.calibrated),
                "n_model_effect_params": problem.n_model_effects,
            },
            "refit": refit_info or None,
            "probes": probe_rows,
            "not_applicable": [
                {"effect": row.effect, "location": row.location, "reason": row.skipped}
                for row in not_applicable
            ],
            "structure_by_location": structure_rows,
            "best_candidate": None if fit is None else fit.lead.label,
            "close_rivals": close_rivals,
            "indistinguishable": indistinguishable,
            "location_source": location_source,
        },
    )
    diag.residuals = {
        "pose_ids": list(meas.pose_ids),
        "before": _per_row(ho0.residual * layout.scale, layout, m),
        "after": _per_row(
            (fit.heldout if fit is not None else ho0).residual * layout.scale, layout, m
        ),
    }
    model_forms = list(fit.forms) if free is not None and fit is not None else []
    diag.refit_arm = _refit_model(
        problem, y_model, list(s.own) + model_forms, cols, arm, meas.point_names
    )
    diag.report = render_report(diag, None if fit is None else fit.lead)
    named = frozenset(
        (f.lead.name, f.lead.location) for f in ([fit, *ties] if fit and free is not None else [])
    )
    return _Verdict(diag, y_model, free, passes, named)


@dataclasses.dataclass(frozen=True)
class _Linearised:
    """The problem linearised at the base model's fit, which every candidate's refit starts
    from: ``r (N,)`` the whitened residual, ``D (N, n_geo)`` and ``J (N, p)`` the Jacobians of
    the base model's and of the feature columns, ``fold (N,)`` each entry's fold."""

    problem: Extended
    rows: _Rows
    arm: Arm
    r: np.ndarray
    D: np.ndarray
    J: np.ndarray
    fold: np.ndarray
    given: bool
    y_base: np.ndarray
    cols: dict[Candidate, slice]


def _select(
    significant: Sequence[Candidate], evals: dict, lin: _Linearised, live: Sequence[Candidate]
) -> tuple[_Fit, list[_Fit]]:
    """The refits of the significant candidates whose merit is within :data:`RIVAL_NATS` or
    :data:`CONTENDER_FRACTION` of the best one's (at most :data:`MAX_CONTENDERS`): the
    selected one, and the other plausible ones whose held-out sum of squares is within
    ``2 RIVAL_NATS`` of it (a log-likelihood ratio within :data:`RIVAL_NATS`) or that predict
    better without paying for their extra parameters: these poses cannot tell them apart.

    The plausible refit of the highest merit is selected unless another predicts held-out
    poses better by more than its extra parameters cost (:func:`_predicts_better`, one
    parameter at least); an implausible refit only where every contender's is."""
    top = max(evals[c]["merit"] for c in significant)
    margin = max(RIVAL_NATS, CONTENDER_FRACTION * top)
    contenders = sorted(
        (c for c in significant if evals[c]["merit"] >= top - margin),
        key=lambda c: -evals[c]["merit"],
    )[:MAX_CONTENDERS]
    fits = [_fit_effect(c, lin, live) for c in contenders]
    plausible = [f for f in fits if not _implausible(f.parameters)]
    if not plausible:
        return fits[0], []
    best = plausible[0]
    for f in plausible[1:]:
        extra = max(1, _size(f, lin.cols) - _size(best, lin.cols))
        if _predicts_better(f, best, extra):
            best = f
    ties = [
        f
        for f in plausible
        if f is not best
        and f.heldout.sum_of_squares <= best.heldout.sum_of_squares + 2.0 * RIVAL_NATS
    ]
    return best, ties


def _fit_effect(tested: Candidate, lin: _Linearised, live: Sequence[Candidate]) -> _Fit:
    """The joint refit of the frames and a candidate's effect at its place.

    The chains of forms (:func:`_chains`) of the tested form and of the :data:`MAX_CHAINS`
    - 1 best others are refitted, each growing further forms on the model linearised at its
    refit while they pay (up to :data:`MAX_REFINEMENTS`; a large effect moves the solution
    far from the geometric fit, where the first linearisation was made). Of these refits, the
    one with the fewest parameters (ties: the tested form's) is kept unless another predicts
    held-out poses better by more than the parameters of its forms that the kept one lacks
    cost (:func:`_predicts_better`, :func:`_extra`); a physically
    implausible refit only where every one is, after the forms added last are dropped one by
    one (:func:`_plausible_prefix`) and the plainest forms of the effect at the place are
    tried (a richer or more flexible form that comes out impossible, such as
    a negative per-cable compliance, stands in for noise or for another shape)."""
    r, D, J, fold, cols = lin.r, lin.D, lin.J, lin.fold, lin.cols
    place = [c for c in live if (c.name, c.location) == (tested.name, tested.location)]
    chains = _chains(tested, place, cols, r, D, J, fold, lin.arm)
    fits = [_plausible_prefix(_grow(_refit(f, g, lin), place, lin), lin) for f, g in chains]
    kept: _Fit | None = None
    # the fewest parameters first (ties: the tested form's chain): a larger one replaces it
    # only where it pays for what it adds
    for fit in sorted(fits, key=lambda f: _size(f, cols)):
        if _implausible(fit.parameters):
            continue
        if kept is None or _predicts_better(fit, kept, _extra(fit, kept, cols)):
            kept = fit
    if kept is None:
        geometric = stats.heldout(r, D, fold).loglik
        kept = fits[0]
        for c in sorted(
            (c for c in place if c is not kept.lead and not c.effect.refinement),
            key=lambda c: -_score(r, np.hstack([D, J[:, cols[c]]]), fold)[0],
        ):
            trial = _refit([c], [0.0], lin)
            if not _implausible(trial.parameters):
                trial.gains[0] = float(trial.heldout.loglik - geometric)
                kept = trial
                break
    kept.info["forms"] = [
        {"variant": c.variant or None, "heldout_gain": g, "n_params": len(c.parameters(lin.arm))}
        for c, g in zip(kept.forms, kept.gains, strict=True)
    ]
    return kept


def _plausible_prefix(history: Sequence[_Fit], lin: _Linearised) -> _Fit:
    """The last physically plausible refit of ``history`` (a chain's refit, then each with one
    form added, :func:`_grow`); where none is, the refit of the longest plausible prefix of
    the first one's forms (the forms added last dropped one by one); the last refit where no
    prefix is plausible either."""
    for fit in reversed(history):
        if not _implausible(fit.parameters):
            return fit
    first = history[0]
    for k in range(len(first.forms) - 1, 0, -1):
        trial = _refit(first.forms[:k], first.gains[:k], lin)
        if not _implausible(trial.parameters):
            return trial
    return history[-1]


def _fit_score(fit: _Fit) -> tuple[float, float]:
    return fit.heldout.loglik, fit.heldout.sum_of_squares


def _predicts_better(fit: _Fit, than: _Fit, k: int = 0) -> bool:
    """Whether refit ``fit`` predicts held-out poses better than ``than`` by more than ``k``
    parameters cost: its plain held-out sum of squares (whitened; what ``delta_p`` reports) is
    lower by more than ``2 REFINE_GAIN_PER_PARAM k``. The sum of squares, not the
    log-likelihood: a refit whose parameters are poorly determined predicts with a wide
    covariance, which hides its prediction errors from the likelihood."""
    return fit.heldout.sum_of_squares < than.heldout.sum_of_squares - 2.0 * (
        REFINE_GAIN_PER_PARAM * k
    )


def _size(fit: _Fit, cols: dict) -> int:
    """The number of effect parameters of a refit."""
    return int(_columns(fit.forms, cols).size)


def _extra(fit: _Fit, than: _Fit, cols: dict) -> int:
    """The parameters of ``fit``'s forms that ``than`` does not have (at least one): what a
    switch from ``than`` to ``fit`` must pay for."""
    new = [c for c in fit.forms if c not in than.forms]
    return max(1, int(_columns(new, cols).size)) if new else 1


def _grow(fit: _Fit, place: Sequence[Candidate], lin: _Linearised) -> list[_Fit]:
    """``fit``, then its refits with further forms of ``place`` that join it added one at a
    time, judged on the model linearised at the last refit, while they pay
    (:func:`_best_addition`), up to :data:`MAX_REFINEMENTS` added forms."""
    n_geo = lin.D.shape[1]
    history = [fit]
    while len(fit.forms) <= MAX_REFINEMENTS:
        free = np.concatenate([np.arange(n_geo), n_geo + _columns(fit.forms, lin.cols)])
        blocks = {
            c: fit.J[:, n_geo + _columns([c], lin.cols)] for c in place if _joins(c, fit.forms)
        }
        base = _fit_score(fit)
        found = _best_addition(fit.r, fit.J[:, free], blocks, lin.fold, base)
        if found is None:
            break
        fit = _refit(
            [*fit.forms, found[0]], [*fit.gains, float(found[1][0] - base[0])], lin, y_start=fit.y
        )
        history.append(fit)
    return history


def _refit_model(
    problem: Extended,
    y: np.ndarray,
    effects: Sequence[Candidate],
    cols: dict,
    nominal: Arm,
    point_names: Sequence[str],
) -> Arm:
    """The model the diagnosis ends with, in the model contract: the frames (and calibrated
    marker positions) at ``y``, the ``effects`` (the model's own, then the selected effect's
    forms) with their parameters from ``y`` as ``[[effects]]``, gravity in the fitted world
    frame (:func:`_gravity_in_fit_frame`)."""
    n = problem.n_frames_markers
    frames, xyz = apply_parameters(
        jnp.asarray(y[:n]), jnp.asarray(problem.arm.frames), problem.xyz, problem.calibrated
    )
    out = _gravity_in_fit_frame(problem.arm.with_frames(frames), nominal)
    at = np.asarray(xyz, float)
    out = out.with_marker_positions({point_names[j]: at[j] for j in problem.calibrated})
    if effects:
        own = y[n : problem.n_geometric]
        n_geo = problem.n_geometric
        found = [y[n_geo + cols[c].start : n_geo + cols[c].stop] for c in effects if c in cols]
        out = with_effects(out, effects, np.concatenate([own, *found]))
    return out


def _not_in_model(
    table: list[tuple[Candidate, str | None]], own: Sequence[Candidate]
) -> list[tuple[Candidate, str | None]]:
    """The candidate table with the model's own effects (same effect, location and variant)
    marked skipped: they are part of the base model, fitted with the frames."""
    mine = {(c.name, c.location, c.variant) for c in own}
    return [
        (c, "in the model already (its [[effects]], fitted with the frames)")
        if (c.name, c.location, c.variant) in mine
        else (c, why)
        for c, why in table
    ]


WORKSPACE = "workspace"
"""The structure test's regressor group of where the tool is (its measured position): a misfit
that follows it and no single module's states (a measuring device's distortion, a field in
the workspace) lives at no place of the chain."""


def _place(
    arm: Arm, regressor: str, probe_rows: Sequence[Mapping] = (), alpha: float = 1.0
) -> str | None:
    """Where a misfit predictable from ``regressor`` lives: the module itself; for ``time_s``
    the fixed frame whose time probe (:class:`cdra_jax.physics.probes.TimeProbe`, the same
    parameter count at every frame) explains it best, when one is significant: a link that
    grows as it warms up, or the base (a drift of the mount, also where none is); the tool for
    ``payload_kg``; nowhere in the chain (``None``) for the :data:`WORKSPACE`."""
    if regressor == "time_s":
        timed = [row for row in probe_rows if row["kind"] == TimeProbe.summary]
        best = min(timed, key=lambda row: (row["p_value"], -(row["F"] or 0.0)), default=None)
        if best is not None and best["p_value"] < alpha:
            return str(best["location"])
        return arm.frame_names[0]
    if regressor == "payload_kg":
        return arm.frame_names[-1]
    if regressor == WORKSPACE:
        return None
    return regressor


def _regressors(arm: Arm, meas: Measurements) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """``(X (m, d), groups (d,), names)``: what a missing effect may depend on, per row: the
    module states (one group per module: its entries together), each auxiliary column that
    varies (``time_s``, ``payload_kg``), and the :data:`WORKSPACE` (the measured tool
    position, or the mean of a row's seen points), with the group names (module names, the
    column's name, ``"workspace"``)."""
    cols = [np.asarray(meas.q, float)]
    groups = [int(g) for g in np.repeat(np.arange(len(arm.modules)), [m.dof for m in arm.modules])]
    names = list(arm.module_names)
    for k in sorted(meas.aux):
        v = np.asarray(meas.aux[k], float)
        if np.ptp(v) > 0 and not k.startswith("approach."):  # (backlash: its own candidates)
            cols.append(v[:, None])
            groups.append(len(names))
            names.append(k)
    where = _row_positions(meas)
    if np.all(np.isfinite(where)):
        cols.append(where)
        groups += [len(names)] * 3
        names.append(WORKSPACE)
    return np.concatenate(cols, axis=1), np.asarray(groups), names


def _row_positions(meas: Measurements) -> np.ndarray:
    """``(m, 3)`` where the tool is in each row (mm): the measured full pose's origin, else the
    mean of the row's seen points (NaN where a row has neither)."""
    out = np.full((meas.m, 3), np.nan)
    if meas.points is not None:
        pts = np.asarray(meas.points, float)
        seen = np.isfinite(pts).all(axis=-1)
        total = np.where(seen[..., None], pts, 0.0).sum(axis=1)
        n = seen.sum(axis=1)[:, None]
        out = np.where(n > 0, total / np.maximum(n, 1), np.nan)
    if meas.full_poses is not None:
        pos = np.asarray(meas.full_poses, float)[:, :3, 3]
        out = np.where(np.isfinite(pos), pos, out)
    return out


def _finite_columns(F: Features) -> tuple[Features, np.ndarray]:
    """``F`` with every parameter column that has a non-finite entry set to zero (it would
    poison the residual: ``nan * 0`` is ``nan``), and which columns ``(p,)`` were finite."""
    parts = (F.state, F.module_twist, F.frame_deflection)
    finite = np.ones(F.n_params, bool)
    for part in parts:
        a = np.asarray(part)
        finite &= np.all(np.isfinite(a.reshape(-1, a.shape[-1])), axis=0)
    if finite.all():
        return F, finite
    keep = jnp.asarray(finite)
    clean = [jnp.where(keep, jnp.nan_to_num(a), 0.0) for a in parts]
    return Features(state=clean[0], module_twist=clean[1], frame_deflection=clean[2]), finite


def _evaluate(c, Jc, r, D, UD, df_resid, floor2, fold, ho0) -> dict:
    """One candidate's test on the linearised model: the projection of its columns ``Jc`` off
    the frames' (absorbed fraction), its F test, and its held-out log-likelihood gain and
    selection merit over the geometric fit."""
    if not np.all(np.isfinite(Jc)):
        raise ValueError("its features are not finite on these data")
    proj = stats.project(Jc, UD)
    Fv, p, df1, _ = stats.f_test(r, proj.basis, df_resid, floor2)
    A = np.hstack([D, Jc])
    gain = merit = None
    if proj.df:
        ho = stats.heldout(r, A, fold)
        gain = ho.loglik - ho0.loglik
        # what selection ranks: the held-out log-likelihood gain, but no more than half the
        # drop of the plain held-out sum of squares (a flexible candidate that predicts with a
        # wide covariance gains likelihood without predicting better)
        merit = min(gain, 0.5 * (ho0.sum_of_squares - ho.sum_of_squares))
    return {"proj": proj, "F": Fv, "p": p, "df": df1, "gain": gain, "A": A, "merit": merit}


def _implausible(parameters: dict[str, ParameterEstimate]) -> list[str]:
    """The estimates whose 95 % interval lies outside the physical range, in words."""
    return [
        f"{k} = {v.value:.3g} {v.unit} (physical range {v.range_low:g} to {v.range_high:g})"
        for k, v in parameters.items()
        if not v.plausible
    ]


def _explained(excess_before: float, excess_after: float) -> float:
    """The fraction of the excess held-out misfit (over its expectation) a refit removes."""
    return 1.0 - excess_after / excess_before if excess_before > 0 else 1.0


def _joins(c: Candidate, forms: Sequence[Candidate]) -> bool:
    """Whether form ``c`` may join a refit of ``forms`` (one effect at one place): it is not
    one of them, and it and each of them accept one another (:meth:`Effect.joins`: one
    mechanism with one hidden constant, such as a drum's radius)."""
    return c not in forms and all(
        c.effect.joins(f.effect) and f.effect.joins(c.effect) for f in forms
    )


def _columns(forms: Sequence[Candidate], cols: dict) -> np.ndarray:
    return np.concatenate([np.arange(cols[c].start, cols[c].stop) for c in forms])


def _score(r: np.ndarray, A: np.ndarray, fold: np.ndarray) -> tuple[float, float]:
    """Held-out ``(log-likelihood, plain sum of squares)`` of the linear model ``r ~ A x``."""
    ho = stats.heldout(r, A, fold)
    return ho.loglik, ho.sum_of_squares


def _pays(before: tuple[float, float], after: tuple[float, float], k: int) -> bool:
    """Whether ``k`` more parameters pay for themselves: the held-out log-likelihood rises by
    more than :data:`REFINE_GAIN_PER_PARAM` per parameter *and* the plain held-out sum of
    squares falls by twice that (it is twice a log-likelihood), so that a model that merely
    predicts with a wider covariance never pays."""
    return (
        after[0] - before[0] > REFINE_GAIN_PER_PARAM * k
        and before[1] - after[1] > 2.0 * REFINE_GAIN_PER_PARAM * k
    )


def _best_addition(r, A, blocks, fold, base):
    """Of the column blocks ``{form: (6m, k)}`` that pay when added to ``A``, the one with the
    largest held-out gain per parameter: ``(form, score)``, or ``None``."""
    trials = []
    for c, B in blocks.items():
        sc = _score(r, np.hstack([A, B]), fold)
        if _pays(base, sc, B.shape[1]):
            trials.append(((sc[0] - base[0]) / B.shape[1], sc, c))
    if not trials:
        return None
    _, sc, c = max(trials, key=lambda t: t[0])
    return c, sc


def _chains(best, place, cols, r, D, J, fold, arm):
    """Chains of forms of ``best``'s effect at its location to start refits with, chosen on
    the model linearised at the geometric fit: ``[(forms, gains)]``, the chain from the
    tested form ``best`` first, then those from the other forms at the place (``place``:
    its variants and refinements), the best held-out prediction first, as long as it comes
    within :data:`RIVAL_NATS` or :data:`CONTENDER_FRACTION` of the best chain's held-out
    gain (at most :data:`MAX_CHAINS` in all).

    From each start (a tested form, or a refinement that is a complete form by itself,
    :attr:`~cdra_jax.physics.Effect.alone`), forward selection adds the forms that join it
    (:func:`_joins`, :func:`_best_addition`): a drum radius or a harmonic that the F test
    ranked second may, with its overtone, describe the data better; a refinement such as a
    settling drift may replace the form it refines. A form joins only where the linearised
    estimates of the chain with it stay physically plausible (a power law that joins a
    linear stretch by turning its compliances negative describes another shape). ``gains``:
    the held-out log-likelihood gain each form added (the first: over the geometric fit).
    """
    geometric = stats.heldout(r, D, fold).loglik

    def plausible(forms):
        y, sd = _linear_fit(r, np.hstack([D, J[:, _columns(forms, cols)]]), 1.0)
        at = D.shape[1]
        for c in forms:
            k = cols[c].stop - cols[c].start
            if _implausible(_estimates(y[at : at + k], sd[at : at + k], c, arm)):
                return False
            at += k
        return True

    def chain(start):
        forms = [start]
        base = _score(r, np.hstack([D, J[:, cols[start]]]), fold)
        gains = [float(base[0] - geometric)]
        for _ in range(MAX_REFINEMENTS):
            A = np.hstack([D, J[:, _columns(forms, cols)]])
            blocks = {
                c: J[:, cols[c]] for c in place if _joins(c, forms) and plausible([*forms, c])
            }
            found = _best_addition(r, A, blocks, fold, base)
            if found is None:
                break
            c, sc = found
            gains.append(float(sc[0] - base[0]))
            forms.append(c)
            base = sc
        return forms, gains, base[0]

    starts = [c for c in place if c is not best and (not c.effect.refinement or c.effect.alone)]
    first = chain(best)
    others = sorted((chain(c) for c in starts), key=lambda t: -t[2])
    top = max([first[2]] + [t[2] for t in others])
    margin = max(RIVAL_NATS, CONTENDER_FRACTION * (top - geometric))
    out, seen = [], set()
    for forms, gains, score in [first, *others]:
        if len(out) == MAX_CHAINS:
            break
        if frozenset(forms) in seen:  # the same forms reached from another start
            continue
        if out and score < top - margin:  # not close enough to be worth a refit
            continue
        seen.add(frozenset(forms))
        out.append((forms, gains))
    return out


def _refit(
    forms: Sequence[Candidate],
    gains: Sequence[float],
    lin: _Linearised,
    y_start: np.ndarray | None = None,
) -> _Fit:
    """Joint LM refit of the frame errors and the parameters of ``forms`` (the leading form
    first, then the forms added to it, with the held-out ``gains`` each added), from
    ``y_start`` (all entries of ``y``) or from the linearised fit at the base model's fit.
    Parameters of added forms are named ``<variant>:<name>``."""
    problem, rows, arm, cols = lin.problem, lin.rows, lin.arm, lin.cols
    n_geo = lin.D.shape[1]
    sel = _columns(forms, cols)
    free = np.concatenate([np.arange(n_geo), n_geo + sel])
    if y_start is None:
        y_lin, _ = _linear_fit(lin.r, np.hstack([lin.D, lin.J[:, sel]]), 1.0)
        y0 = np.array(lin.y_base, float)
        y0[free] += y_lin
    else:
        y0 = np.array(y_start, float)
    y_all, ok, steps, (r1, J1_all) = joint_refit(
        y0, free, problem, max_steps=REFIT_STEPS, rtol=REFIT_RTOL
    )
    r1 = r1[rows.take]
    J1_all = J1_all[rows.take]
    J1 = J1_all[:, free]
    U1 = stats.orthonormal_basis(J1)
    dof = r1.size - U1.shape[1]
    chi2 = float(r1 @ r1)
    inflate = max(1.0, chi2 / max(dof, 1))
    _, sd = _linear_fit(r1, J1, inflate)
    y = np.asarray(y_all, float)[free]
    params: dict[str, ParameterEstimate] = {}
    at = n_geo
    for i, c in enumerate(forms):
        k = cols[c].stop - cols[c].start
        est = _estimates(y[at : at + k], sd[at : at + k], c, arm)
        at += k
        params.update(est if i == 0 else {f"{c.variant}:{n}": v for n, v in est.items()})
    ho1 = stats.heldout(r1, J1, lin.fold, with_null=lin.given)
    # Q and the plain sum of squares, Bonferroni: a refit with many parameters widens its
    # predictive covariance, which deflates Q but not |e|^2
    p_after = None
    if lin.given:
        p_after = min(
            1.0,
            2.0 * min(ho1.p_value(NOISE_TOLERANCE), ho1.p_value_sum_of_squares(NOISE_TOLERANCE)),
        )
    info = {
        "candidate": forms[0].label,
        "converged": bool(ok),
        "steps": int(steps),
        "chi2": chi2,
        "dof": int(dof),
        "interval_inflation": float(np.sqrt(inflate)),
        "frame_errors_change": {
            name: [float(v) for v in (y_all - lin.y_base)[6 * j : 6 * j + 6]]
            for j, name in enumerate(arm.frame_names)
        },
    }
    return _Fit(
        list(forms), list(gains), info, params, ho1, p_after, np.asarray(y_all, float), r1, J1_all
    )


def _outdone(
    tested: Candidate,
    gain: float | None,
    probes: Sequence[Candidate],
    probe_rows: Sequence[Mapping],
    lin: _Linearised,
    ho0: stats.HeldOut,
    alpha: float,
) -> dict | None:
    """The generic probe (:mod:`cdra_jax.physics.probes`) at another place, with no more
    parameters than the tested form of the selected effect and significant on its own, that
    predicts held-out poses better than that form by more than :data:`RIVAL_NATS` (the
    largest such gain), or ``None``. Its form is then not what the data single out: a mount
    drift that a link growing with time only partly mimics is outdone by the time probe at
    that link (the same six parameters)."""
    if gain is None:
        return None
    k = len(tested.parameters(lin.arm))
    significant = {(row["location"], row["kind"]) for row in probe_rows if row["p_value"] < alpha}
    best: dict | None = None
    for c in probes:
        size = lin.cols[c].stop - lin.cols[c].start
        if c.location == tested.location or size > k:
            continue
        if (c.location, c.effect.summary) not in significant:
            continue
        g = _score(lin.r, np.hstack([lin.D, lin.J[:, lin.cols[c]]]), lin.fold)[0] - ho0.loglik
        if g > gain + RIVAL_NATS and (best is None or g > best["heldout_gain"]):
            best = {
                "location": c.location,
                "kind": c.effect.summary,
                "n_params": size,
                "heldout_gain": float(g),
                "candidate_gain": float(gain),
                "against": f"{k} of {tested.label}",
            }
    return best


def _shape_check(
    fit: _Fit, lin: _Linearised, live: Sequence[Candidate], floor2: float
) -> dict | None:
    """Whether a refitted series form (:meth:`cdra_jax.physics.Effect.coordinate`: harmonics of
    a joint or drum angle) has the same amplitudes over the whole range of its coordinate:
    ``None`` where no form of ``fit`` is a series, else its F test (``F``, ``p_value``,
    ``df``).

    The alternative lets every amplitude take another value on the poses above the
    :data:`SHAPE_SPLIT` quantile of its axis (each feature column times that indicator,
    linearised at the refit). The null model is the refit with every other form at the place
    that may join it (:func:`_joins`: the overtones at the same drum radius, the other
    harmonics of the joint angle), so that a true periodic error whose refit lacks an overtone
    is not mistaken for another shape. A periodic error has the same amplitudes throughout;
    a saturating or monotone shape that a few harmonics fit over less than one period does
    not (the fitted harmonic follows the steep part on one side and the flat part on the
    other).

    No noise value is needed: an F ratio, with each kind of entry (positions, rotations, each
    point) weighted by its spread under the alternative. Weighted by a noise estimated from a
    residual that still holds the misfit (as without noise values: the position noise comes
    out inflated), the positions, where a misfit of a transmission mostly shows, would count
    for less than with the true noise, and the verdict would depend on the noise values."""
    series = [c for c in fit.forms if c.coordinate(lin.arm, lin.problem.q) is not None]
    if not series:
        return None
    n_geo = lin.D.shape[1]
    lead = fit.lead
    place = [c for c in live if (c.name, c.location) == (lead.name, lead.location)]
    null = list(fit.forms) + [c for c in place if _joins(c, fit.forms)]
    J_null = fit.J[:, np.concatenate([np.arange(n_geo), n_geo + _columns(null, lin.cols)])]
    blocks = []
    for c in series:
        found = c.coordinate(lin.arm, lin.problem.q)
        assert found is not None
        z, owner = np.asarray(found[0], float), np.asarray(found[1])
        above = (z > np.quantile(z, SHAPE_SPLIT, axis=0)).astype(float)
        Jc = fit.J[:, n_geo + _columns([c], lin.cols)]
        blocks.append(Jc * above[lin.rows.row][:, owner])
    split = np.hstack(blocks)
    w = _kind_weights(fit.r, np.hstack([J_null, split]), lin.rows)
    U = stats.orthonormal_basis(w[:, None] * J_null)
    r = w * fit.r
    r = r - U @ (U.T @ r)
    proj = stats.project(w[:, None] * split, U)
    Fv, p, df1, _ = stats.f_test(r, proj.basis, r.size - U.shape[1], floor2 * float(np.max(w**2)))
    return {"F": _num(Fv), "p_value": float(p), "df": int(df1)}


def _kind_weights(r: np.ndarray, J: np.ndarray, rows: _Rows) -> np.ndarray:
    """``(N,)`` weights of the entries of the whitened residual ``r``: one per kind of entry
    (full-pose position, rotation, each point), the inverse of that kind's root mean square
    after fitting the columns ``J``, normalised to a mean square of 1."""
    U = stats.orthonormal_basis(J)
    e = r - U @ (U.T @ r)
    groups = rows.noise_group
    w = np.ones(r.size)
    for g in np.unique(groups):
        sel = groups == g
        ms = float(np.mean(e[sel] ** 2))
        if ms > 0.0 and np.isfinite(ms):
            w[sel] = 1.0 / np.sqrt(ms)
    return w / np.sqrt(np.mean(w**2))


def _locate_unattributed(
    arm: Arm,
    struct0: stats.Structure,
    group_names: Sequence[str],
    probe_rows: Sequence[Mapping],
    probe_place: str | None,
    alpha: float,
    partial: tuple[str, float | None, float] | None,
    rival: dict | None,
) -> tuple[str | None, str | None, list[dict]]:
    """Where an ``unattributed`` misfit lives: ``(location, source, structure rows)``.

    In order: the generic probe that outdid the selected candidate (:func:`_outdone`); else
    the module (or column) whose regressors alone predict the residual best when the
    structure test is significant there (:func:`_place`); else the most significant probe.
    Then the partial candidate ``(location, its Holm p, explained fraction)`` places it when
    it removes at least :data:`LOCATE_MIN` of the misfit and no probe at another place is
    more significant than it (a link growing with time that the mount's drift only partly
    mimics is not placed at the mount)."""
    gp = struct0.group_p if struct0.group_p is not None else np.ones(0)
    by_group: list[tuple[float, str]] = sorted(
        (min(1.0, len(group_names) * float(gp[g])), name)
        for g, name in enumerate(group_names)
        if g < gp.size
    )
    structure_rows = [{"location": name, "p_value": p_g} for p_g, name in by_group]
    if rival is not None:
        return rival["location"], "rival probe", structure_rows
    located_in, source = probe_place, (None if probe_place is None else "probe")
    if by_group and by_group[0][0] < alpha:
        located_in, source = _place(arm, by_group[0][1], probe_rows, alpha), "structure"
    if partial is not None:
        place, p_candidate, explained = partial
        p_candidate = 1.0 if p_candidate is None else p_candidate
        elsewhere = [
            row for row in probe_rows if row["location"] != place and row["p_value"] < p_candidate
        ]
        if explained >= LOCATE_MIN and not elsewhere:
            located_in, source = place, "partial candidate"
    return located_in, source, structure_rows


def _locate(probes, cols, r, J, UD, df_resid, alpha, floor2=0.0):
    """Generic probes: which location explains most of the residual (min Bonferroni p)."""
    rows = []
    for c in probes:
        proj = stats.project(J[:, cols[c]], UD)
        Fv, p, df1, _ = stats.f_test(r, proj.basis, df_resid, floor2)
        rows.append({"location": c.location, "kind": c.effect.summary, "df": df1, "F": Fv, "p": p})
    n = max(len(rows), 1)
    for row in rows:
        row["p_value"] = min(1.0, n * row.pop("p"))
        row["F"] = None if not np.isfinite(row["F"]) else float(row["F"])
    rows.sort(key=lambda row: (row["p_value"], -(row["F"] or 0.0)))
    loc = rows[0]["location"] if rows and rows[0]["p_value"] < alpha else None
    return rows, loc


def diagnose_files(
    model_path: str | os.PathLike | None,
    data_path: str | os.PathLike,
    noise_pos_mm: float | None,
    noise_rot_rad: float | None,
    **kw,
) -> Diagnosis:
    """:func:`diagnose` on a model TOML (``None``: the embedded CDRA) and a measurement CSV.

    ``noise_pos_mm`` and ``noise_rot_rad`` go together (both ``None``: estimated, see
    :func:`diagnose`); keywords are passed on.
    """
    from ..io import default_arm, load_measurements, load_model

    if (noise_pos_mm is None) != (noise_rot_rad is None):
        raise ValueError("noise_pos_mm and noise_rot_rad go together: give both or neither")
    arm = default_arm() if model_path is None else load_model(model_path)
    meas = load_measurements(data_path, arm)
    noise = None
    if noise_pos_mm is not None and noise_rot_rad is not None:
        noise = NoiseModel(float(noise_pos_mm), float(noise_rot_rad))
    return diagnose(arm, meas, noise, **kw)
