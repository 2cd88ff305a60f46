"""The calibrate workflow: model + measurements -> identified frame errors, checked and reported.

:func:`calibrate` runs, in order: the plausibility checks of the data (wrong units or
conventions stop with an error naming the column; the rest warns), the solve (the paper's
iterative least squares, Eqs. 9-19, its noise-weighted form, or Levenberg-Marquardt; optionally a
robust loss around it), the identifiability analysis at the nominal model (rank and the named
unidentifiable combinations), the conditioning check, the parameter uncertainty (with a noise
model), the outlier flags, and the implausibly-large-error check. It returns a
:class:`CalibrationRun` whose :meth:`~CalibrationRun.to_dict` is the result file contract of
``shared/design.md`` and whose :meth:`~CalibrationRun.report` is what ``cdra-jax calibrate``
prints. The command line and the notebooks call this same function.

A model with ``[[effects]]`` is calibrated with them: the frame errors and the effects'
parameters are refined jointly (:func:`cdra_jax.physics.refine`, Levenberg-Marquardt on the
whitened residual of full poses and points against the extended model, noise scales given or
estimated); the result holds the refined effects (``effects``, the model file's entries, and
``effect_parameters`` with start values, standard deviations and 95 % intervals) and the
calibrated model (:attr:`CalibrationRun.calibrated_arm`, ``--model-out``) carries them. This
needs the auxiliary columns the effects use, and markers at known positions.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .. import lie
from ..arm import TWIST_COMPONENTS, Arm, error_twists
from ..calibration import (
    NoiseModel,
    RobustSolution,
    calibrate_auto,
    calibrate_lm,
    calibrate_paper,
    calibrate_robust,
    make_observations,
    to_nominal_gauge,
)
from ..calibration.observations import marker_table, row_means
from ..calibration.registration import initial_guess
from ..calibration.robust import OUTLIER_THRESHOLD
from ..compilation import cached_filter_jit, filter_jit
from ..conditioning import conditioning, conditioning_from_jacobian
from ..identifiability import (
    analyze,
    generic_rank,
    pose_set_warnings,
    report_from_jacobian,
)
from ..io import (
    Measurements,
    auto_result_to_dict,
    calibrated_arm_from_result,
    check_plausibility,
    check_pose_count,
    dumps_result,
    result_to_dict,
    save_model,
    save_result,
)
from ..io.model import effects_from_list, effects_to_list
from ..io.results import RESULT_FORMAT, RESULT_FORMAT_VERSION, package_version
from ..physics import (
    check_effect_data,
    data_residual,
    effect_param_names,
    effect_param_units,
    extended_tool_pose,
    model_effects,
    prediction_error_table,
    refine,
)
from ..uncertainty import analyze_uncertainty
from .inputs import Data, Model, check_range, resolve_arm, resolve_measurements

if TYPE_CHECKING:
    from matplotlib.figure import Figure

SOLVERS: tuple[str, ...] = ("auto", "paper", "weighted", "lm")
"""Solver names, the same in every command and function of the package:

* ``auto`` (the default without a noise model): estimates the noise scale of each residual kind
  from the data, weights by it, uses a Huber loss, registers the measuring device's frame and
  fits full poses, points and markers alike (:func:`cdra_jax.calibration.calibrate_auto`);
* ``paper``: the paper's unweighted iterative least squares (Eqs. 9-14, minimum-norm steps);
* ``weighted``: the same iteration on the residual whitened by the noise model (needs one; the
  default with a noise model);
* ``lm``: Levenberg-Marquardt, whitened when a noise model is given.

``paper``, ``weighted`` and ``lm`` fit full tool poses only.
"""
LOSSES: tuple[str, ...] = ("huber", "cauchy", "ls", "none")
"""``huber`` (the default of ``auto``), ``cauchy``: robust; ``ls`` or ``none``: plain (weighted)
least squares, the default of the other solvers."""

FRAME_ERROR_PLAUSIBLE_MM = 50.0
"""Identified frame errors beyond this translation (norm of the twist's v, mm) ..."""
FRAME_ERROR_PLAUSIBLE_RAD = 0.5
"""... or this rotation (norm of w, rad) make :func:`calibrate` warn: a calibration corrects
small errors of a nominal model, so such a result usually comes from gross errors in the data
(a typo, swapped rows, wrong units) or too few poses to outvote them."""


def default_solver(noise: NoiseModel | None, points: bool = False, paper: bool = False) -> str:
    """``auto``; ``weighted`` when a noise model is given and the data are full poses (or
    ``paper`` without one, when ``paper`` asks for the paper's solvers)."""
    if points:
        return "auto"
    if noise is not None:
        return "weighted"
    return "paper" if paper else "auto"


def check_solver(
    solver: str, noise: NoiseModel | None, flag: str = "solver", points: bool = False
) -> str:
    """``solver`` unchanged when it is one of :data:`SOLVERS` usable with ``noise`` (and with
    measured points, when ``points``)."""
    if solver not in SOLVERS:
        raise ValueError(f"{flag} must be one of {', '.join(SOLVERS)}, got {solver!r}")
    if points and solver != "auto":
        raise ValueError(
            f"{flag} {solver} fits full tool poses; these data measure points (the tool origin "
            "without orientation, or markers): use the auto solver (the default)"
        )
    if solver == "weighted" and noise is None:
        raise ValueError(
            f"{flag} weighted whitens the residual by the measuring device's noise: give the "
            "noise model (--noise-pos and --noise-rot)"
        )
    return solver


def trust_check(result: dict) -> dict[str, Any]:
    """Whether a calibration result is better than the model it started from, on its own data.

    Compares the mean measured-position residual ``|p_meas - p_model|`` (mm) of the calibrated
    model with the nominal model's over the fitted poses. A calibration whose model predicts the
    measured points worse than the nominal one (possible when an unweighted fit trades position
    for orientation, or when gross errors pull it away) is not trusted: the command line exits
    with :data:`cdra_jax.cli.EXIT_UNTRUSTED` and the result holds ``"trusted": false``.

    Returns:
        ``{"trusted": bool, "nominal_position_mm": mean, "calibrated_position_mm": mean,
        "reason": text or None}``.
    """
    rows = result["residuals"]
    nominal = [r["nominal_position_mm"] for r in rows if r["nominal_position_mm"] is not None]
    calibrated = [
        r["calibrated_position_mm"] for r in rows if r["calibrated_position_mm"] is not None
    ]
    n_mean = sum(nominal) / len(nominal) if nominal else math.nan
    c_mean = sum(calibrated) / len(calibrated) if len(calibrated) == len(rows) else math.nan
    trusted = bool(c_mean <= n_mean * (1 + 1e-9) + 1e-12)
    reason = None
    if not trusted:
        reason = (
            f"the calibrated model is worse than the nominal one on the measured points: mean "
            f"position residual {c_mean:.4g} mm against {n_mean:.4g} mm nominal; do not use "
            "it. Try weighting by the measuring device's noise (--noise-pos/--noise-rot with "
            "--solver weighted or lm), a robust loss (--loss huber), checking the data for gross "
            "errors (units, swapped rows, registration of the device frame), or more poses"
        )
    return {
        "trusted": trusted,
        "nominal_position_mm": None if math.isnan(n_mean) else n_mean,
        "calibrated_position_mm": None if math.isnan(c_mean) else c_mean,
        "reason": reason,
    }


def implausible_frame_errors_warning(result: dict) -> str | None:
    """The warning for identified frame errors beyond :data:`FRAME_ERROR_PLAUSIBLE_MM` or
    :data:`FRAME_ERROR_PLAUSIBLE_RAD` in a result mapping, or None."""
    large = []
    registered = bool((result.get("registration") or {}).get("registered"))
    for j, (name, frame) in enumerate(result["frames"].items()):
        if j == 0 and registered:
            continue  # the base frame carries the measuring device's registration

        t = frame["error_twist"]
        v = math.sqrt(sum((t[c] or 0.0) ** 2 for c in ("vx", "vy", "vz")))
        w = math.sqrt(sum((t[c] or 0.0) ** 2 for c in ("wx", "wy", "wz")))
        if v > FRAME_ERROR_PLAUSIBLE_MM or w > FRAME_ERROR_PLAUSIBLE_RAD:
            large.append(f"{name} (|v| = {v:.4g} mm, |w| = {w:.3g} rad)")
    if not large:
        return None
    unidentifiable = (result.get("identifiability") or {}).get("unidentifiable") or []
    return (
        f"implausibly large identified frame errors: {', '.join(large)}, above "
        f"{FRAME_ERROR_PLAUSIBLE_MM:g} mm or {FRAME_ERROR_PLAUSIBLE_RAD:g} rad; a calibration "
        "corrects small errors of the nominal model: check the data for gross errors (typos, "
        "swapped rows, wrong units) and measure more poses"
        + (
            " (part of the error may lie along the unidentifiable directions listed in the "
            "summary, which the tool poses do not determine)"
            if unidentifiable
            else ""
        )
    )


@dataclasses.dataclass(frozen=True, eq=False)
class CalibrationRun:
    """One finished calibration and everything reported about it.

    Attributes:
        arm: the nominal model the solve started from.
        measurements: the fitted measurements.
        solution: the solver's :class:`~cdra_jax.calibration.CalibrationSolution` (or
            :class:`~cdra_jax.calibration.RobustSolution` for a robust loss).
        result: the result mapping (the result file contract; :meth:`to_dict`).
        identifiability_summary: the plain-text identifiability (and uncertainty) summary.
        warnings: every warning, in the order the command line prints them on stderr.
        model_label: how the model is named in the report (file name or ``embedded CDRA``).
        data_label: how the measurements are named in the report.
    """

    arm: Arm
    measurements: Measurements
    solution: Any
    result: dict[str, Any]
    identifiability_summary: str
    warnings: tuple[str, ...]
    model_label: str
    data_label: str

    @property
    def converged(self) -> bool:
        """Whether the solver met its tolerance."""
        return bool(self.result["converged"])

    @property
    def trusted(self) -> bool:
        """Whether the calibrated model fits the measured points at least as well as the nominal
        one (:func:`trust_check`); an untrusted result must not be used."""
        return bool(self.result["trusted"])

    @property
    def calibrated_arm(self) -> Arm:
        """The calibrated model (Eq. 19: the identified errors applied to the nominal frames;
        the refined effects where the model has ``[[effects]]``)."""
        return result_arm(self.result, self.arm)

    def to_dict(self) -> dict[str, Any]:
        """The result mapping (what :meth:`save` writes as JSON)."""
        return self.result

    def to_json(self) -> str:
        """The result file's JSON text."""
        return dumps_result(self.result)

    def save(self, path: str | os.PathLike, *, force: bool = False) -> Path:
        """Write the result JSON atomically; an existing file is replaced only with ``force``."""
        return save_result(self.result, path, force=force)

    def save_model(self, path: str | os.PathLike, *, force: bool = False) -> Path:
        """Write the calibrated model as a model TOML file (the model contract, frames as exact
        4x4 matrices), loadable by every command (``--model``)."""
        return save_model(self.calibrated_arm, path, exact=True, force=force)

    def report(self) -> str:
        """The plain-text report ``cdra-jax calibrate`` prints (iterations, Eqs. 20-21, the
        identified frame errors, identifiability, uncertainty and outliers)."""
        return _report(
            self.arm, self.result, self.model_label, self.data_label, self.identifiability_summary
        )

    def plot(self) -> Figure:
        """Per-pose residuals of the nominal and calibrated models and the convergence
        (:func:`cdra_jax.plots.calibration_residuals_figure`)."""
        from ..plots import calibration_residuals_figure

        return calibration_residuals_figure(self.result)


def calibrate(
    model: Model,
    data: Data,
    *,
    solver: str | None = None,
    noise: NoiseModel | None = None,
    loss: Literal["huber", "cauchy", "ls", "none"] | None = None,
    reject_outliers: bool = False,
    max_iterations: int | None = None,
    model_label: str | None = None,
    data_label: str | None = None,
) -> CalibrationRun:
    """Calibrate the fixed frames of a model from measured tool poses (Eqs. 7-21).

    Args:
        model: an :class:`~cdra_jax.arm.Arm`, a model TOML path, or ``None`` (the embedded
            7-DOF CDRA of the paper).
        data: :class:`~cdra_jax.io.Measurements` or a measurement CSV path (module states and
            measured tool poses in the world frame, mm and rad).
        solver: one of :data:`SOLVERS`; default ``weighted`` with a noise model, else
            ``paper``.
        noise: the measuring device's noise (std per pose: position mm, rotation rad); used to
            weight the residual (``weighted``, ``lm``), for the parameter uncertainty and the
            outlier scale.
        loss: ``ls``, or ``huber``/``cauchy`` for robust IRLS around the solver.
        reject_outliers: with a robust loss, finish with a least-squares refit without the
            flagged poses (kept only when it loses no identifiable direction).
        max_iterations: iteration cap (default 20 for paper/weighted, 50 for lm; per round for
            a robust loss).
        model_label, data_label: names for the report (default: file names).

    Raises:
        ValueError: bad arguments, or data that fail the plausibility checks (the message names
            the file, row and column); ``OSError`` for unreadable files.
    """
    if loss is not None and loss not in LOSSES:
        raise ValueError(f"loss must be one of {', '.join(LOSSES)}, got {loss!r}")
    if loss == "none":
        loss = "ls"
    if max_iterations is not None:
        check_range("max_iterations", max_iterations)
    arm, model_label = resolve_arm(model, model_label)
    meas, data_label, sha = resolve_measurements(data, arm, data_label)
    check_pose_count(meas)
    if not meas.has_measurements:
        raise ValueError(
            f"{data_label}: no measured tool poses or points (measured.* columns) to fit"
        )
    if arm.effects:
        return _calibrate_effects(
            arm,
            meas,
            noise,
            solver,
            loss,
            reject_outliers,
            max_iterations,
            model_label,
            data_label,
            sha,
        )
    points = meas.measured is None
    if solver is None:
        # A Cauchy loss and the refit without flagged poses go with the paper's solvers.
        legacy = loss == "cauchy" or reject_outliers
        solver = default_solver(noise, points and not legacy, legacy)
    check_solver(solver, noise, points=points)
    if loss is None:
        loss = "huber" if solver == "auto" else "ls"
    if reject_outliers and loss == "ls":
        raise ValueError(
            "reject_outliers needs a robust loss to flag the outliers: use loss huber or cauchy"
        )
    if solver == "auto":
        if loss == "cauchy" or reject_outliers:
            raise ValueError(
                "the auto solver takes loss huber (default) or ls; a Cauchy loss and "
                "reject_outliers go with the paper, weighted and lm solvers"
            )
        return _calibrate_auto(arm, meas, noise, loss, max_iterations, model_label, data_label, sha)
    assert meas.measured is not None
    # Wrong units or conventions stop here with an error naming the column; the rest warns.
    plausibility = list(check_plausibility(arm, meas))
    solve_noise = None if solver == "paper" else noise
    # The result reports the singular values of the Jacobian at the solution: computed once,
    # after the iteration (the solvers skip them by default).
    kwargs: dict[str, Any] = {"throw": False, "singular_values": True}
    if max_iterations is not None:
        kwargs["max_iterations"] = max_iterations
    sol: Any
    if loss == "ls":
        fn = calibrate_lm if solver == "lm" else calibrate_paper
        sol = cached_filter_jit(fn)(arm, meas.q, meas.measured, solve_noise, **kwargs)
    else:
        kwargs.update(
            loss=loss, solver="lm" if solver == "lm" else "paper", reject_outliers=reject_outliers
        )
        sol = cached_filter_jit(calibrate_robust)(arm, meas.q, meas.measured, noise, **kwargs)
    sol, gauge = _in_nominal_gauge(arm, meas, sol)
    # Unidentifiable directions are reported at the nominal model, where they read simply
    # (e.g. "0.707 upper_arm.vy - 0.707 forearm.vy" for the CDRA).
    ident = analyze(arm, meas.q, meas.measured, noise)
    cond = conditioning(arm, meas.q, meas.measured, noise)
    # A pose set that identifies less than poses spread over the joint ranges would (repeated
    # poses, a module that never moves) is degenerate data. Directions that no pose set
    # identifies (the CDRA's two along the elbow axis) are a property of the model.
    generic = generic_rank(arm, meas.m, noise)
    degenerate = []
    if ident.rank < generic:
        degenerate.append(_degenerate_text(ident, generic))
    stored = [
        *plausibility,
        *degenerate,
        *ident.warnings,
        *([cond.warning] if cond.warning else []),
    ]
    inputs = {"model": model_label, "data": data_label}
    if sha is not None:
        inputs["data_sha256"] = sha
    result = result_to_dict(
        arm,
        sol,
        meas.q,
        meas.measured,
        noise=noise,
        identifiability=ident.to_dict(),
        pose_ids=meas.pose_ids,
        inputs=inputs,
        conditioning=cond.to_dict(),
        warnings=stored,
    )
    shown = _finish(result, _gauge_dict(gauge), plausibility, degenerate, ident, cond)
    summary = ident.summary()
    if noise is not None:
        # Covariance of the identified parameters, Cramer-Rao bound and 95 % intervals at the
        # calibrated model; a robust fit's with its final IRLS weights.
        base = sol.solution if loss != "ls" else sol
        unc = analyze_uncertainty(
            calibrated_arm_from_result(result, arm),
            meas.q,
            noise,
            meas.measured,
            estimate=np.asarray(base.errors),
            weights=None if loss == "ls" else np.asarray(sol.weights),
        )
        result["uncertainty"] = unc.to_dict()
        summary = summary + "\n" + unc.summary()
    return CalibrationRun(
        arm=arm,
        measurements=meas,
        solution=sol,
        result=result,
        identifiability_summary=summary,
        warnings=tuple(shown),
        model_label=model_label,
        data_label=data_label,
    )


def result_arm(result: dict[str, Any] | Any, nominal: Arm, source: str = "<result>") -> Arm:
    """The calibrated model of a result: ``nominal`` with its calibrated frames and markers
    (Eq. 19) and, when the calibration refined the model's effects (``effects``), their
    refined values."""
    arm = calibrated_arm_from_result(result, nominal)
    if result.get("effects"):
        arm = arm.with_effects(effects_from_list(result["effects"], f"{source}: effects"))
        model_effects(arm, source)
    return arm


EFFECTS_GAUGE_TEXT = (
    "the model's frames and effects refined jointly by Levenberg-Marquardt with minimum-norm "
    "steps from the model: the identified correction has (to first order) no component along "
    "the unidentifiable directions of the extended model"
)


def _calibrate_effects(
    arm: Arm,
    meas: Measurements,
    noise: NoiseModel | None,
    solver: str | None,
    loss: str | None,
    reject_outliers: bool,
    max_iterations: int | None,
    model_label: str,
    data_label: str,
    sha: str | None,
) -> CalibrationRun:
    """Calibrate a model with ``[[effects]]``: frames and effect parameters jointly."""
    labels = ", ".join(e.label for e in arm.effects)
    if solver not in (None, "auto", "lm"):
        raise ValueError(
            f"solver {solver}: a model with [[effects]] ({labels}) is calibrated by "
            "Levenberg-Marquardt on the frames and the effects' parameters jointly; use the "
            "default (or lm)"
        )
    if loss not in (None, "ls") or reject_outliers:
        raise ValueError(
            f"a model with [[effects]] ({labels}) is calibrated by least squares; robust losses "
            "and reject_outliers are not available with effects"
        )
    xyz, rough = marker_table(arm, meas.point_names)
    if rough:
        raise ValueError(
            f"the markers {', '.join(meas.point_names[j] for j in rough)} have calibrate = true: "
            f"with [[effects]] ({labels}) the markers' positions are taken as known. Calibrate "
            "them first with the model without its [[effects]] (calibrate --model-out writes "
            "their positions), then refine the effects with that model's markers"
        )
    check_effect_data(arm, meas.aux, data_label)
    # Start: the base frame registered to the measuring device's frame where that lowers the
    # position errors (data in a tracker's own frame), as the auto solver starts.
    obs = make_observations(arm, meas.q, meas.full_poses, meas.points)
    start = initial_guess(np.asarray(arm.frames), xyz, obs, ())
    placed = arm.with_frames(jnp.asarray(start.frames)) if start.registered else arm
    plausibility = list(
        check_plausibility(arm, meas if meas.measured is None else _states_only(meas))
    )
    if meas.measured is not None:
        plausibility = list(check_plausibility(placed, meas))
    fit = refine(
        arm,
        meas.q,
        meas.full_poses,
        meas.aux,
        noise,
        points=meas.points,
        point_xyz=xyz,
        errors0=np.asarray(error_twists(jnp.asarray(start.frames), arm.frames)).reshape(-1),
        max_iterations=50 if max_iterations is None else max_iterations,
    )
    n = arm.n_params
    names = effect_param_names(arm)
    units = effect_param_units(arm)
    J = fit.geometric_jacobian
    ident = report_from_jacobian(
        J, arm.param_names, meas.m, warnings=pose_set_warnings(arm, meas.q)
    )
    cond = conditioning_from_jacobian(J, arm.param_names)
    q = np.asarray(meas.q)
    q = q.astype(jnp.result_type(q.dtype))  # the dtype jnp.asarray gives (float32 without x64)
    aux = {k: np.asarray(v, q.dtype) for k, v in meas.aux.items()}
    y0 = np.concatenate([np.zeros(n), fit.theta_start])
    y1 = np.concatenate([fit.errors.reshape(-1), fit.theta])
    # Standardised residual per row: RMS of its measured whitened entries at the noise scales.
    scales = np.asarray([fit.noise.position_mm, fit.noise.rotation_rad, fit.point_noise_mm])
    tool0, tool1, res = _effect_readouts(
        y0, y1, arm, fit.candidates, q, aux, fit.data, scales.astype(jnp.result_type(scales))
    )
    pos0, r0 = prediction_error_table(tool0, fit.data)
    pos1, r1 = prediction_error_table(tool1, fit.data)
    p0, p1 = row_means(pos0), row_means(pos1)
    res = np.asarray(res, float)
    m, n_pts = meas.m, len(meas.point_names)
    sq = (res[: 6 * m].reshape(m, 6) ** 2).sum(1) + (res[6 * m :].reshape(m, -1) ** 2).sum(1)
    counts = 6 * np.asarray(fit.data.pose_mask) + 3 * np.asarray(fit.data.seen).sum(1)
    n_rows = max(int(counts.sum()), 1)
    z = np.sqrt(sq / np.maximum(counts, 1) * n_rows / max(n_rows - fit.rank, 1))
    flagged = z > OUTLIER_THRESHOLD
    has_poses = bool(np.asarray(fit.data.pose_mask).any())
    del n_pts
    nxyz, nrv = (np.asarray(a, float) for a in lie.to_xyz_rotvec(jnp.asarray(arm.frames)))
    cxyz, crv = (np.asarray(a, float) for a in lie.to_xyz_rotvec(jnp.asarray(fit.frames)))
    frames = {
        name: {
            "nominal": _pose(np.asarray(arm.frames)[j], nxyz[j], nrv[j]),
            "calibrated": _pose(fit.frames[j], cxyz[j], crv[j]),
            "error_twist": {
                c: _float(v) for c, v in zip(TWIST_COMPONENTS, fit.errors[j], strict=True)
            },
        }
        for j, name in enumerate(arm.frame_names)
    }
    # An effect parameter is identified when no unidentifiable direction of the joint problem
    # moves it (theta_std is NaN along those directions).
    params = {}
    for k, name in enumerate(names):
        v, sd = float(fit.theta[k]), float(fit.theta_std[k])
        ok = math.isfinite(sd)
        params[name] = {
            "value": v,
            "unit": units[k],
            "start": float(fit.theta_start[k]),
            "std": sd if ok else None,
            "ci95": [v - 1.96 * sd, v + 1.96 * sd] if ok else None,
            "identifiable": ok,
        }
    unidentified = [nm for nm, p in params.items() if not p["identifiable"]]
    refined = fit.calibrated_arm(arm)
    steps, dps, dRs = fit.step_norm, fit.delta_p, fit.delta_R
    k = fit.iterations
    ids = list(meas.pose_ids)
    stored = [*plausibility, *ident.warnings, *([cond.warning] if cond.warning else [])]
    if unidentified:
        stored.append(
            "effect parameters not identifiable from these poses (kept at the model's values "
            "along the unidentifiable directions): " + ", ".join(unidentified)
        )
    if flagged.any():
        stored.append(
            f"{int(flagged.sum())} pose(s) with a standardised residual above "
            f"{OUTLIER_THRESHOLD:g}: " + ", ".join(ids[i] for i in np.flatnonzero(flagged))
        )
    inputs: dict[str, Any] = {"model": model_label, "data": data_label}
    if sha is not None:
        inputs["data_sha256"] = sha
    result: dict[str, Any] = {
        "format": RESULT_FORMAT,
        "format_version": RESULT_FORMAT_VERSION,
        "cdra_jax_version": package_version(),
        "inputs": inputs,
        "model": arm.name,
        "n_poses": meas.m,
        "solver": "lm",
        "converged": fit.converged,
        "result": "successful" if fit.converged else "max_iterations_reached",
        "message": ""
        if fit.converged
        else "the calibration did not converge within max_iterations; raise it",
        "noise": {
            "position_mm": float(fit.noise.position_mm) if has_poses else None,
            "rotation_rad": float(fit.noise.rotation_rad) if has_poses else None,
            "points_mm": fit.point_noise_mm if meas.point_names else None,
            "source": fit.noise_source,
        },
        "initial": {"delta_p_mm": _float(dps[0]), "delta_R_rad": _float(dRs[0])},
        "iterations": [
            {
                "iteration": i,
                "step_norm": _float(steps[i - 1]),
                "delta_p_mm": _float(dps[i]),
                "delta_R_rad": _float(dRs[i]),
            }
            for i in range(1, k + 1)
        ],
        "final": {
            "delta_p_mm": _float(dps[k]),
            "delta_R_rad": _float(dRs[k]),
            "cost": _float(fit.cost),
            "rank": fit.rank,
            "n_params": fit.n_params,
            "singular_values": [_float(v) for v in fit.singular_values],
        },
        "frames": frames,
        "registration": {
            "registered": bool(start.registered),
            "markers_placed": [],
            "rms_before_mm": _float(start.rms_before_mm),
            "rms_after_mm": _float(start.rms_after_mm),
        },
        "effects": effects_to_list(refined.effects),
        "effect_parameters": params,
        "identifiability": ident.to_dict(),
        "residuals": [
            {
                "pose": ids[i],
                "nominal_position_mm": _float(p0[i]),
                "nominal_rotation_rad": _float(r0[i]),
                "calibrated_position_mm": _float(p1[i]),
                "calibrated_rotation_rad": _float(r1[i]),
                "z": _float(z[i]),
                "weight": 1.0,
                "outlier": bool(flagged[i]),
            }
            for i in range(meas.m)
        ],
        "outliers": {
            "threshold": OUTLIER_THRESHOLD,
            "scale": {
                "position_mm": float(fit.noise.position_mm) if has_poses else None,
                "rotation_rad": float(fit.noise.rotation_rad) if has_poses else None,
                "source": "noise model" if fit.noise_source == "given" else "noise estimate",
            },
            "poses": [ids[i] for i in np.flatnonzero(flagged)],
        },
        "robust": None,
        "conditioning": cond.to_dict(),
        "warnings": stored,
    }
    gauge = {"definition": EFFECTS_GAUGE_TEXT, "reference": "nominal", "residual_to_nominal": None}
    shown = _finish(result, gauge, plausibility, [], ident, cond)
    return CalibrationRun(
        arm=arm,
        measurements=meas,
        solution=fit,
        result=_finite_json(result),
        identifiability_summary=ident.summary(),
        warnings=tuple(shown),
        model_label=model_label,
        data_label=data_label,
    )


@filter_jit
def _effect_readouts(y0, y1, arm, candidates, q, aux, data, scales):
    """Tool poses of the extended model at ``y0`` (start) and ``y1`` (fit), and the stacked
    whitened residual at ``y1`` (one compiled program per problem shape)."""
    tool0 = extended_tool_pose(y0, arm, candidates, q, aux)
    tool1 = extended_tool_pose(y1, arm, candidates, q, aux)
    return tool0, tool1, data_residual(y1, arm, candidates, q, aux, data, scales)


def _float(x: Any) -> float | None:
    v = float(x)
    return v if math.isfinite(v) else None


def _finite_json(obj: Any) -> Any:
    """``obj`` with every non-finite float replaced by ``None`` (JSON has no NaN or inf)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite_json(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite_json(v) for v in obj]
    return obj


def _pose(T: np.ndarray, xyz: np.ndarray, rotvec: np.ndarray) -> dict[str, Any]:
    return {
        "xyz": [float(v) for v in xyz],
        "rotvec": [float(v) for v in rotvec],
        "matrix": np.asarray(T, dtype=float).tolist(),
    }


def _effect_lines(r: dict) -> list[str]:
    """The refined effects of a result with ``effect_parameters``."""
    lines = ["effects refined with the frames (start -> refined, 95 % interval):"]
    for name, p in r["effect_parameters"].items():
        ci = p.get("ci95")
        interval = f" ({ci[0]:.4g} to {ci[1]:.4g})" if ci else " (not identifiable)"
        lines.append(f"  {name} [{p['unit']}]: {p['start']:.6g} -> {p['value']:.6g}{interval}")
    return lines


def _finish(result, gauge, plausibility, degenerate, ident, cond) -> list[str]:
    """Add the gauge, the implausibility warning and the trust verdict to a result mapping;
    return the warnings stderr shows, each once (those of the identifiability analysis only
    with a degenerate pose set: otherwise they are part of the summary)."""
    result["gauge"] = gauge
    implausible = implausible_frame_errors_warning(result)
    if implausible is not None:
        result["warnings"].append(implausible)
    trust = trust_check(result)
    result["trusted"] = trust["trusted"]
    result["trust"] = trust
    shown = [*plausibility, *degenerate]
    if degenerate:
        shown += list(ident.warnings)
    if cond.warning:
        shown.append(cond.warning)
    shown += [w for w in result["warnings"] if w not in shown and w not in ident.warnings]
    return shown


def _calibrate_auto(
    arm: Arm,
    meas: Measurements,
    noise: NoiseModel | None,
    loss: str,
    max_iterations: int | None,
    model_label: str,
    data_label: str,
    sha: str | None,
) -> CalibrationRun:
    """The ``auto`` solver's calibration (:func:`cdra_jax.calibration.calibrate_auto`)."""
    # The state checks first; the measured poses are checked against the nominal model placed
    # in the measuring device's frame by the registration (they may lie anywhere in it).
    plausibility = list(
        check_plausibility(arm, meas if meas.measured is None else _states_only(meas))
    )
    kwargs: dict[str, Any] = {}
    if max_iterations is not None:
        kwargs["max_iterations"] = max_iterations
    sol = calibrate_auto(
        arm,
        meas.q,
        meas.full_poses,
        meas.points,
        meas.point_names,
        noise=noise,
        loss=loss,
        **kwargs,
    )
    if meas.measured is not None:
        plausibility = list(check_plausibility(arm.with_frames(sol.start.frames), meas))
    ident = report_from_jacobian(
        sol.start_jacobian, sol.param_names, meas.m, warnings=pose_set_warnings(arm, meas.q)
    )
    cond = conditioning_from_jacobian(sol.start_jacobian, sol.param_names)
    degenerate = []
    if meas.points is None:
        # Full poses only: the same rank as the paper's problem, compared with generic poses.
        generic = generic_rank(arm, meas.m)
        if ident.rank < generic:
            degenerate.append(_degenerate_text(ident, generic))
    obs = make_observations(arm, meas.q, meas.full_poses, meas.points)
    uncertainty = _auto_uncertainty(sol)
    inputs = {"model": model_label, "data": data_label}
    if sha is not None:
        inputs["data_sha256"] = sha
    stored = [
        *plausibility,
        *degenerate,
        *ident.warnings,
        *([cond.warning] if cond.warning else []),
    ]
    result = auto_result_to_dict(
        arm,
        sol,
        meas.q,
        meas.pose_ids,
        identifiability=ident.to_dict(),
        inputs=inputs,
        conditioning=cond.to_dict(),
        uncertainty=uncertainty,
        warnings=stored,
        observations=obs,
    )
    gauge = _gauge_dict(sol.gauge, sol.gauge_reference)
    shown = _finish(result, gauge, plausibility, degenerate, ident, cond)
    summary = ident.summary() + "\n" + _uncertainty_summary(uncertainty)
    return CalibrationRun(
        arm=arm,
        measurements=meas,
        solution=sol,
        result=result,
        identifiability_summary=summary,
        warnings=tuple(shown),
        model_label=model_label,
        data_label=data_label,
    )


GAUGE_TEXT = (
    "the identified correction (error twists w.r.t. the reference frames, marker corrections) "
    "has no component along the unidentifiable directions of the reference model; along them "
    "the result keeps the reference values. The reference is the nominal model, or, where the "
    "auto solver registered the base to the measuring device and no exact move along the "
    "unidentifiable directions reaches the nominal gauge, that registered start model"
)

"""How every solver's result fixes what the data cannot determine
(:mod:`cdra_jax.calibration.gauge`)."""


def _gauge_dict(g, reference: str = "nominal") -> dict[str, Any]:
    return {
        "definition": GAUGE_TEXT,
        "reference": reference if g.exact or reference == "start" else "solver",
        "residual_to_nominal": float(g.residual),
    }


def _in_nominal_gauge(arm: Arm, meas: Measurements, sol: Any):
    """The solution moved onto the nominal gauge (exact moves only), and the move."""
    robust = isinstance(sol, RobustSolution)
    base = sol.solution if robust else sol
    obs = make_observations(arm, meas.q, meas.measured, None)
    none = np.zeros((0, 3))
    g = to_nominal_gauge(np.asarray(base.frames), none, np.asarray(arm.frames), none, obs)
    if g.moved:
        frames = jnp.asarray(g.frames, dtype=jnp.asarray(base.frames).dtype)
        base = eqx.tree_at(
            lambda s: (s.frames, s.errors), base, (frames, error_twists(frames, arm.frames))
        )
        sol = eqx.tree_at(lambda s: s.solution, sol, base) if robust else base
    return sol, g


def _degenerate_text(ident, generic: int) -> str:
    return (
        f"degenerate pose set: rank {ident.rank} of {ident.n_params} parameters from "
        f"{ident.n_poses} poses, where as many poses spread over the joint ranges give "
        f"{generic}; {generic - ident.rank} more combination(s) are lost to the pose set "
        "(the unidentifiable directions are listed in the summary)"
    )


def _states_only(meas: Measurements) -> Measurements:
    """``meas`` without its measured columns' poses (for the state plausibility checks)."""
    return dataclasses.replace(meas, measured=None, full_poses=None, points=None, point_names=())


def _auto_uncertainty(sol) -> dict[str, Any]:
    """Standard deviations and 95 % intervals of the identified correction (first order, at
    the estimated noise scales), per parameter."""
    std = np.sqrt(np.clip(np.diag(sol.covariance), 0.0, None))
    n_frames = sol.errors.shape[0]
    values = list(np.asarray(sol.errors, dtype=float).reshape(-1))
    for j in sol.calibrated_points:
        values += list(np.asarray(sol.xyz[j]) - np.asarray(sol.start.xyz[j]))
    params = {}
    for k, name in enumerate(sol.param_names):
        v = float(values[k])
        s = float(std[k])
        params[name] = {"value": v, "std": s, "ci95": [v - 1.96 * s, v + 1.96 * s]}
    del n_frames
    return {
        "method": "first-order covariance of the identified correction at the estimated noise "
        "scales and the final robust weights, restricted to the identifiable directions",
        "noise_source": sol.noise_source,
        "parameters": params,
    }


def _uncertainty_summary(unc: dict[str, Any]) -> str:
    """One line per frame: the largest translation (mm) and rotation (rad) std."""
    by_frame: dict[str, list[float]] = {}
    lines = ["uncertainty (1 std of the identified correction, " + unc["noise_source"] + " noise):"]
    for name, p in unc["parameters"].items():
        frame, comp = name.rsplit(".", 1)
        by_frame.setdefault(frame, [0.0, 0.0])
        slot = 1 if comp.startswith("w") else 0
        by_frame[frame][slot] = max(by_frame[frame][slot], p["std"])
    for frame, (t, r) in by_frame.items():
        lines.append(
            f"  {frame}: translation <= {t:.3g} mm" + (f", rotation <= {r:.3g} rad" if r else "")
        )
    return "\n".join(lines)


def _fmt(x: float | None, spec: str = ".4e") -> str:
    return "-" if x is None else format(x, spec)


def frame_table(names: Sequence[str], rows, title: str) -> list[str]:
    """Lines of a table of per-frame twists (``vx ... wz``) under ``title``."""
    width = max(len(n) for n in names)
    lines = [title, "  " + " " * width + "".join(f"{c:>13}" for c in TWIST_COMPONENTS)]
    for name, row in zip(names, rows, strict=True):
        lines.append("  " + f"{name:<{width}}" + "".join(f"{float(v):>13.6g}" for v in row))
    return lines


_SOLVER_TEXT = {
    "paper": "paper (the paper's unweighted iterative least squares, Eqs. 9-14)",
    "weighted": "weighted (the paper's iterative least squares, whitened by the noise model)",
    "lm": "lm (Levenberg-Marquardt)",
}


def _auto_lines(r: dict) -> list[str]:
    """The noise scales, registration and markers of an ``auto`` result."""
    n = r["noise"]
    parts = []
    if n["position_mm"] is not None:
        parts.append(f"pose position {n['position_mm']:.3g} mm")
    if n["rotation_rad"] is not None:
        parts.append(f"pose rotation {n['rotation_rad']:.3g} rad")
    parts += [
        f"{name} {v:.3g} mm" for name, v in (n.get("points_mm") or {}).items() if v is not None
    ]
    lines = [f"noise scales ({n['source']}, 1 std): " + ", ".join(parts)]
    reg = r.get("registration") or {}
    if reg.get("registered"):
        placed = reg.get("markers_placed") or []
        lines.append(
            f"start: base frame registered to the measuring device's frame (point RMS "
            f"{_fmt(reg['rms_before_mm'], '.4g')} -> {_fmt(reg['rms_after_mm'], '.4g')} mm)"
            + (f"; markers placed: {', '.join(placed)}" if placed else "")
        )
    for name, mk in (r.get("markers") or {}).items():
        if mk["calibrate"]:
            xyz = ", ".join(f"{v:.4f}" for v in mk["calibrated"])
            lines.append(f"marker {name}: calibrated position ({xyz}) mm in the tool frame")
    return lines


def _report(arm: Arm, r: dict, model_label: str, data: str, ident: str) -> str:
    rob = r.get("robust")
    out = r.get("outliers") or {}
    scale = out.get("scale") or {}
    if r["solver"] == "auto":
        text = (
            "auto ({} loss, {} noise scales, Levenberg-Marquardt in the identifiable "
            "directions)".format(
                "Huber" if r.get("loss") == "huber" else "least-squares",
                r["noise"]["source"],
            )
        )
    elif r.get("effect_parameters") is not None:
        text = (
            "lm (Levenberg-Marquardt on the frames and the model's [[effects]] jointly, "
            "weighted by the noise scales)"
        )
    elif rob is None:
        text = _SOLVER_TEXT[r["solver"]]
        if r["solver"] == "lm" and r["noise"] is not None:
            text += ", weighted"
    else:
        inner = _SOLVER_TEXT[rob["inner_solver"]].split(" (")[0]
        text = (
            f"{rob['loss']} (robust, c = {rob['tuning_constant']:g}) by iteratively reweighted "
            f"least squares around {inner}; "
            f"{rob['rounds']} reweighting round{'s' if rob['rounds'] != 1 else ''}"
        )
        if rob.get("refit_without_flagged"):
            n_out = len(out.get("poses") or [])
            text += (
                f"; then least squares without the {n_out} flagged pose(s) (--reject-outliers)"
                if n_out
                else "; then least squares on all poses (none flagged, --reject-outliers)"
            )
        elif rob.get("reject_outliers"):
            text += (
                "; the refit without the flagged poses was not kept (fewer than 4 poses left, "
                "an identifiable direction lost, or not converged)"
            )
    lines = [
        f"model: {arm.name} ({model_label}); data: {data} ({r['n_poses']} poses)",
        f"solver: {text}",
    ]
    if r["solver"] == "auto":
        lines += _auto_lines(r)
    elif r["noise"] is not None:
        n = r["noise"]
        what = (
            "noise scales (estimated from the residual)"
            if n.get("source") == "estimated"
            else "noise model"
        )
        parts = []
        if n.get("position_mm") is not None:
            parts.append(f"{n['position_mm']:.3g} mm")
        if n.get("rotation_rad") is not None:
            parts.append(f"{n['rotation_rad']:.3g} rad")
        if n.get("points_mm") is not None:
            parts.append(f"points {n['points_mm']:.3g} mm")
        lines.append(f"{what}: {', '.join(parts)}")
        reg = r.get("registration") or {}
        if reg.get("registered"):
            lines.append(
                f"start: base frame registered to the measuring device's frame (position RMS "
                f"{_fmt(reg['rms_before_mm'], '.4g')} -> {_fmt(reg['rms_after_mm'], '.4g')} mm)"
            )
    lines.append(f"  {'iter':>4}  {'step norm':>11}  {'dp [mm]':>11}  {'dR [rad]':>11}")
    init = r["initial"]
    lines.append(
        f"  {0:>4}  {'-':>11}  {_fmt(init['delta_p_mm']):>11}  {_fmt(init['delta_R_rad']):>11}"
    )
    for it in r["iterations"]:
        lines.append(
            f"  {it['iteration']:>4}  {_fmt(it['step_norm']):>11}  "
            f"{_fmt(it['delta_p_mm']):>11}  {_fmt(it['delta_R_rad']):>11}"
        )
    k = len(r["iterations"])
    status = "converged" if r["converged"] else f"NOT converged ({r['result']})"
    lines.append(
        f"{status} after {k} iteration{'s' if k != 1 else ''}: dp = "
        f"{_fmt(r['final']['delta_p_mm'], '.3g')} mm, dR = "
        f"{_fmt(r['final']['delta_R_rad'], '.3g')} rad (Eqs. 20-21, fitted poses"
        + ("; dp over every measured position" if r["solver"] == "auto" else "")
        + ")"
    )
    names = list(r["frames"])
    nan = float("nan")
    twists = [r["frames"][n]["error_twist"] for n in names]
    rows = [[nan if t[c] is None else t[c] for c in TWIST_COMPONENTS] for t in twists]
    lines += frame_table(
        names, rows, "identified frame errors dt = log(T^c T^-1) (Eqs. 15-18; v mm, w rad):"
    )
    if r.get("effect_parameters"):
        lines += _effect_lines(r)
    lines.append(ident)
    if r["solver"] == "auto":
        units = out.get("units") or []
        lines.append(
            f"outliers (z > {out['threshold']:.3g}, family-wise 1 %, in units of the noise "
            "scales above): " + (", ".join(units) if units else "none")
        )
    elif scale:
        flagged = [x for x in r["residuals"] if x.get("outlier")]
        sp, sr = _fmt(scale["position_mm"], ".3g"), _fmt(scale["rotation_rad"], ".3g")
        lines.append(
            f"outliers (z > {out['threshold']:.3g}; residual scale {sp} mm, {sr} rad from the "
            f"{scale['source']}): " + (str(len(flagged)) if flagged else "none")
        )
        for x in sorted(flagged, key=lambda x: -(x["z"] or 0.0)):
            lines.append(
                f"  {x['pose']}: z = {_fmt(x['z'], '.3g')}, weight {_fmt(x['weight'], '.2g')}, "
                f"calibrated residual {_fmt(x['calibrated_position_mm'], '.3g')} mm, "
                f"{_fmt(x['calibrated_rotation_rad'], '.3g')} rad"
            )
    return "\n".join(lines)
