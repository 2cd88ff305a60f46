"""Calibration result files (JSON): what was identified, how the solve went, what is identifiable.

Structure (see the README for a complete example; ``...`` marks repetition)::

    {
      "format": "cdra_jax.calibration_result", "format_version": 1,
      "cdra_jax_version": "0.1.0",
      "inputs": {"model": "arm.toml" | "<cdra_jax>/data/cdra.toml", "data": "poses.csv",
                 "data_sha256": "..."},
      "model": "cdra", "n_poses": 20,
      "solver": "paper" | "weighted" | "lm",
      "converged": true, "result": "successful", "message": "",
      "noise": null | {"position_mm": 0.08, "rotation_rad": 0.001},
      "initial": {"delta_p_mm": ..., "delta_R_rad": ...},            # nominal model (Eqs. 20-21)
      "iterations": [{"iteration": 1, "step_norm": ..., "delta_p_mm": ..., "delta_R_rad": ...},
                     ...],                                          # after each step
      "final": {"delta_p_mm": ..., "delta_R_rad": ..., "cost": ..., "rank": 22,
                "singular_values": [...]},
      "frames": {"base": {"nominal": {"xyz": [3], "rotvec": [3], "matrix": [[4] x 4]},
                          "calibrated": {...same...},
                          "error_twist": {"vx": ..., "vy": ..., "vz": ...,     # mm
                                          "wx": ..., "wy": ..., "wz": ...}},   # rad (Eqs. 15-18)
                 ...},
      "identifiability": {"rank": 22, "n_params": 24, "unidentifiable": ["..."], ...},
      "residuals": [{"pose": "p01", "nominal_position_mm": ..., "nominal_rotation_rad": ...,
                     "calibrated_position_mm": ..., "calibrated_rotation_rad": ...,
                     "z": 0.8, "weight": 1.0, "outlier": false}, ...],
      "outliers": {"threshold": 1.9347, "scale": {"position_mm": ..., "rotation_rad": ...,
                   "source": "noise model" | "MAD"}, "poses": ["p07"]},
      "robust": null | {"loss": "huber", "tuning_constant": 1.345, "rounds": 6,
                        "inner_solver": "paper" | "lm", "reject_outliers": false,
                        "refit_without_flagged": false},
      "conditioning": null | {"condition_number": ..., "ill_conditioned": false, ...},
      "warnings": ["..."]
    }

Per pose, ``z`` is the standardized residual of the pose at the calibrated model (the RMS of its
six residual entries in units of the residual scale, see :mod:`cdra_jax.calibration.robust`),
``weight`` the weight the fit gave it (1 for least squares) and ``outlier`` whether
``z > threshold``; ``outliers.poses`` lists the flagged poses. For least squares the scale is the
noise model's or a robust MAD estimate of the fit's residuals, so a gross outlier is flagged
even when the fit did not down-weight it.

``iterations[k-1]`` holds the norm of step ``k`` (the paper solver: ``||X||`` of Eq. 10; LM:
``||X_k - X_{k-1}||``, 0 for a rejected step) and the deviation metrics after it. Non-finite
numbers are written as ``null``. ``matrix`` entries reproduce the frames bit for bit; ``xyz`` and
``rotvec`` are for reading. Files are written atomically and never over an existing file unless
``force=True``.
"""

from __future__ import annotations

import importlib.metadata
import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from .. import lie
from ..arm import TWIST_COMPONENTS, Arm, tool_pose
from ..calibration.auto import AutoSolution
from ..calibration.model import NoiseModel, pose_errors
from ..calibration.observations import Observations, error_table, row_means
from ..calibration.robust import OUTLIER_THRESHOLD, RobustSolution, standardized_residuals
from ..calibration.solution import CalibrationSolution, result_messages, result_names
from ..compilation import device_array, filter_jit
from .files import json_text, write_text_atomic
from .measurements import rigid_transform_problem

RESULT_FORMAT = "cdra_jax.calibration_result"
RESULT_FORMAT_VERSION = 1
_REQUIRED = ("solver", "converged", "result", "initial", "iterations", "frames", "identifiability")


class ResultFileError(ValueError):
    """A result file is malformed; the message names the file and the entry."""


def package_version() -> str:
    """The installed ``cdra_jax`` version (``"unknown"`` when not installed)."""
    try:
        return importlib.metadata.version("cdra_jax")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def _num(x: Any) -> float | None:
    v = float(x)
    return v if math.isfinite(v) else None


def _finite(obj: Any) -> Any:
    """``obj`` with every non-finite float replaced by ``None`` (JSON has no NaN or inf)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Mapping):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    return obj


def _pose_dict(T: np.ndarray, xyz: np.ndarray, rotvec: np.ndarray) -> dict[str, Any]:
    return {
        "xyz": [float(v) for v in xyz],
        "rotvec": [float(v) for v in rotvec],
        "matrix": np.asarray(T, dtype=float).tolist(),
    }


@filter_jit
def _readouts(arm: Arm, frames: Array, q: Array, measured: Array):
    """xyz/rotvec of the nominal and calibrated frames; per-pose errors of both models."""
    calibrated = arm.with_frames(frames)
    return (
        lie.to_xyz_rotvec(jnp.asarray(arm.frames)),
        lie.to_xyz_rotvec(jnp.asarray(frames)),
        pose_errors(measured, tool_pose(arm, q)),
        pose_errors(measured, tool_pose(calibrated, q)),
    )


_standardized = filter_jit(standardized_residuals)


def result_to_dict(
    arm: Arm,
    solution: CalibrationSolution | RobustSolution,
    q: ArrayLike,
    measured: ArrayLike,
    *,
    noise: NoiseModel | None = None,
    identifiability: Mapping[str, Any] | None = None,
    pose_ids: Sequence[str] | None = None,
    inputs: Mapping[str, Any] | None = None,
    conditioning: Mapping[str, Any] | None = None,
    warnings: Sequence[str] = (),
) -> dict[str, Any]:
    """JSON-ready mapping of one (unbatched) calibration (see the module docstring).

    Args:
        arm: the nominal model the solver started from.
        solution: its :class:`~cdra_jax.calibration.CalibrationSolution`, or the
            :class:`~cdra_jax.calibration.RobustSolution` of a robust fit (its weights, flags
            and settings are written too).
        q: ``(m, dof)`` module states of the fitted poses.
        measured: ``(m, 4, 4)`` measured tool poses.
        noise: the noise model used for weighting (scalar stds), or ``None``.
        identifiability: ``identifiability.analyze(...).to_dict()``; computed at the
            nominal model (with ``measured`` and ``noise``) when ``None``.
        pose_ids: identifiers of the poses (default ``"1"``, ``"2"``, ...).
        inputs: file names and the like, stored under ``inputs`` as given.
        conditioning: ``conditioning.conditioning(...).to_dict()``, stored as given.
        warnings: plain-text warnings to store (plausibility, identifiability, ...); the
            outlier warning is added here.
    """
    robust = solution if isinstance(solution, RobustSolution) else None
    if robust is not None:
        solution = robust.solution
    assert isinstance(solution, CalibrationSolution)
    if np.ndim(solution.iterations) != 0:
        raise ValueError(
            "result_to_dict takes one calibration; index a batched (vmapped) solution first, "
            f"got iterations of shape {np.shape(solution.iterations)}"
        )
    q = np.asarray(q, dtype=float)
    measured = np.asarray(measured, dtype=float)
    m = measured.shape[0]
    ids = [str(i + 1) for i in range(m)] if pose_ids is None else [str(p) for p in pose_ids]
    if len(ids) != m:
        raise ValueError(f"pose_ids: expected {m} identifiers, got {len(ids)}")
    if identifiability is None:
        from ..identifiability import analyze

        identifiability = analyze(arm, q, measured, noise, allow_underdetermined=True).to_dict()

    k = int(solution.iterations)
    steps = np.asarray(solution.step_norm, dtype=float)
    dps = np.asarray(solution.delta_p, dtype=float)
    dRs = np.asarray(solution.delta_R, dtype=float)
    nominal_frames = np.asarray(arm.frames, dtype=float)
    cal_frames = np.asarray(solution.frames, dtype=float)
    errors = np.asarray(solution.errors, dtype=float)
    (nxyz, nrv), (cxyz, crv), (p0, r0), (p1, r1) = jax.tree_util.tree_map(
        np.asarray,
        _readouts(arm, device_array(cal_frames), device_array(q), device_array(measured)),
    )
    frames = {
        name: {
            "nominal": _pose_dict(nominal_frames[j], nxyz[j], nrv[j]),
            "calibrated": _pose_dict(cal_frames[j], cxyz[j], crv[j]),
            "error_twist": {c: _num(v) for c, v in zip(TWIST_COMPONENTS, errors[j], strict=True)},
        }
        for j, name in enumerate(arm.frame_names)
    }
    if robust is not None:
        z, scale = np.asarray(robust.z, dtype=float), np.asarray(robust.scale, dtype=float)
        weights, threshold = np.asarray(robust.weights, dtype=float), robust.threshold
    else:
        z, scale = (
            np.asarray(a, dtype=float)
            for a in _standardized(
                arm.with_frames(device_array(cal_frames)),
                device_array(q),
                device_array(measured),
                noise,
                rank=solution.rank,
            )
        )
        weights, threshold = np.ones(m), OUTLIER_THRESHOLD
    flagged = z > threshold
    residuals = [
        {
            "pose": ids[i],
            "nominal_position_mm": _num(p0[i]),
            "nominal_rotation_rad": _num(r0[i]),
            "calibrated_position_mm": _num(p1[i]),
            "calibrated_rotation_rad": _num(r1[i]),
            "z": _num(z[i]),
            "weight": _num(weights[i]),
            "outlier": bool(flagged[i]),
        }
        for i in range(m)
    ]
    outlier_ids = [ids[i] for i in np.flatnonzero(flagged)]
    warnings = list(warnings)
    if outlier_ids:
        warnings.append(outlier_warning(ids, z, weights, flagged, threshold, robust is not None))
    return {
        **_header(arm, inputs, m, solution.solver),
        "converged": bool(solution.converged),
        "result": str(result_names(solution.result)),
        "message": "" if bool(solution.converged) else str(result_messages(solution.result)),
        "noise": None
        if noise is None
        else {"position_mm": float(noise.position_mm), "rotation_rad": float(noise.rotation_rad)},
        "initial": {"delta_p_mm": _num(dps[0]), "delta_R_rad": _num(dRs[0])},
        "iterations": [
            {
                "iteration": i,
                "step_norm": _num(steps[i - 1]),
                "delta_p_mm": _num(dps[i]),
                "delta_R_rad": _num(dRs[i]),
            }
            for i in range(1, k + 1)
        ],
        "final": {
            "delta_p_mm": _num(dps[k]),
            "delta_R_rad": _num(dRs[k]),
            "cost": _num(solution.cost),
            "rank": int(solution.rank),
            "singular_values": [_num(s) for s in np.asarray(solution.singular_values)],
        },
        "frames": frames,
        "identifiability": _finite(dict(identifiability)),
        "residuals": residuals,
        "outliers": {
            "threshold": float(threshold),
            "scale": {
                "position_mm": _num(scale[0]),
                "rotation_rad": _num(scale[1]),
                "source": "noise model" if noise is not None else "MAD",
            },
            "poses": outlier_ids,
        },
        "robust": None
        if robust is None
        else {
            "loss": robust.loss,
            "tuning_constant": float(robust.tuning),
            "rounds": int(robust.rounds),
            "reject_outliers": robust.solution.solver.endswith("+reject"),
            "refit_without_flagged": bool(robust.refit),
            "inner_solver": "lm" if solution.solver.startswith("lm") else "paper",
        },
        "conditioning": None if conditioning is None else _finite(dict(conditioning)),
        "warnings": warnings,
    }


def _header(arm: Arm, inputs, m: int, solver: str) -> dict[str, Any]:
    """The first keys of every result mapping."""
    return {
        "format": RESULT_FORMAT,
        "format_version": RESULT_FORMAT_VERSION,
        "cdra_jax_version": package_version(),
        "inputs": dict(inputs or {}),
        "model": arm.name,
        "n_poses": m,
        "solver": solver,
    }


def outlier_warning(
    ids: Sequence[str],
    z: np.ndarray,
    weights: np.ndarray,
    flagged: np.ndarray,
    threshold: float,
    robust: bool,
    shown: int = 5,
) -> str:
    """The one-line warning naming the flagged poses (largest ``z`` first).

    When more than a quarter of the poses are flagged the text says so: that is more than a
    few bad measurements explain (a noise model that is too optimistic, an effect the model
    lacks, or gross outliers that least squares has spread over every residual).
    """
    order = [int(i) for i in np.argsort(-z) if flagged[i]]
    parts = [
        f"{ids[i]} (z = {z[i]:.3g}" + (f", weight {weights[i]:.2g})" if robust else ")")
        for i in order[:shown]
    ]
    listed = ", ".join(parts) + (f" and {len(order) - shown} more" if len(order) > shown else "")
    if len(order) > max(2, len(ids) // 4):
        return (
            f"{len(order)} of {len(ids)} poses have standardized residuals above "
            f"{threshold:.3g} ({listed}): more than a few bad measurements explain; the noise "
            "model may be too optimistic, the model may lack an effect, or "
            + (
                "the data may not fit it at all"
                if robust
                else "least squares has spread a few gross outliers over every residual (a "
                "robust loss, --loss huber, tells these apart)"
            )
        )
    left_out = bool(order) and all(weights[i] == 0 for i in order)
    tail = (
        "; the final fit left them out (least-squares refit, --reject-outliers)"
        if robust and left_out
        else "; the robust fit down-weighted them"
        if robust
        else "; least squares gives them full weight: check them, or use a robust loss "
        "(--loss huber)"
    )
    return f"{len(order)} pose(s) look like outliers (z > {threshold:.3g}): {listed}{tail}"


def dumps_result(result: Mapping[str, Any]) -> str:
    """JSON text of a result mapping (2-space indent; floats exact; no NaN)."""
    return json_text(_finite(result))


def save_result(result: Mapping[str, Any], path: str | os.PathLike, *, force: bool = False) -> Path:
    """Write a result mapping as JSON, atomically; refuses to overwrite unless ``force``."""
    return write_text_atomic(path, dumps_result(result), force=force)


def loads_result(text: str, source: str = "<result>") -> dict[str, Any]:
    """Parse result JSON text and check its structure (errors name the source and the key)."""
    try:
        d = json.loads(text)
    except json.JSONDecodeError as e:
        raise ResultFileError(
            f"{source}: not valid JSON (line {e.lineno}, column {e.colno}): {e.msg}"
        ) from None
    except (ValueError, RecursionError) as e:  # a 5000-digit integer, nesting 100000 deep
        raise ResultFileError(f"{source}: not a result file: {type(e).__name__}") from None
    if not isinstance(d, dict):
        raise ResultFileError(f"{source}: top level: expected a JSON object")
    if d.get("format", RESULT_FORMAT) != RESULT_FORMAT:
        raise ResultFileError(
            f"{source}: format: expected {RESULT_FORMAT!r}, got {d.get('format')!r}"
        )
    for key in _REQUIRED:
        if key not in d:
            raise ResultFileError(f"{source}: missing key {key!r}")
    if not isinstance(d["iterations"], list):
        raise ResultFileError(f"{source}: iterations: expected a list")
    for i, it in enumerate(d["iterations"]):
        for key in ("step_norm", "delta_p_mm", "delta_R_rad"):
            if not isinstance(it, dict) or key not in it:
                raise ResultFileError(f"{source}: iterations[{i}]: missing key {key!r}")
    if not isinstance(d["frames"], dict) or not d["frames"]:
        raise ResultFileError(f"{source}: frames: expected an object of frame names")
    for name, f in d["frames"].items():
        for key in ("nominal", "calibrated", "error_twist"):
            if not isinstance(f, dict) or key not in f:
                raise ResultFileError(f"{source}: frames.{name}: missing key {key!r}")
        for key in ("nominal", "calibrated"):
            try:
                M = np.asarray(
                    f[key].get("matrix") if isinstance(f[key], dict) else None, dtype=float
                )
            except (TypeError, ValueError):
                M = np.zeros(0)
            if M.shape != (4, 4) or not np.all(np.isfinite(M)):
                raise ResultFileError(
                    f"{source}: frames.{name}.{key}.matrix: expected 4 rows of 4 finite numbers"
                )
            problem = rigid_transform_problem(M)
            if problem:
                raise ResultFileError(f"{source}: frames.{name}.{key}.matrix: {problem}")
    if not isinstance(d["identifiability"], dict):
        raise ResultFileError(f"{source}: identifiability: expected an object")
    for key in ("rank", "n_params"):
        if key not in d["identifiability"]:
            raise ResultFileError(f"{source}: identifiability: missing key {key!r}")
    return d


def load_result(path: str | os.PathLike) -> dict[str, Any]:
    """Read and check a result JSON file (see :func:`loads_result`)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise ResultFileError(f"{path}: cannot read result file: {e.strerror}") from None
    except UnicodeDecodeError as e:
        raise ResultFileError(f"{path}: not UTF-8 text: {e.reason}") from None
    return loads_result(text, str(path))


def result_frames(result: Mapping[str, Any], which: str = "calibrated") -> dict[str, np.ndarray]:
    """``{frame: (4, 4)}`` of the ``"calibrated"`` or ``"nominal"`` frames of a result mapping."""
    if which not in ("calibrated", "nominal"):
        raise ValueError(f"which must be 'calibrated' or 'nominal', got {which!r}")
    return {
        name: np.asarray(f[which]["matrix"], dtype=float) for name, f in result["frames"].items()
    }


def calibrated_arm_from_result(result: Mapping[str, Any], nominal: Arm) -> Arm:
    """``nominal`` with the calibrated frames (Eq. 19) and marker positions of a result; frame
    names must match."""
    frames = result_frames(result, "calibrated")
    if tuple(frames) != nominal.frame_names:
        raise ValueError(
            f"the result's frames {tuple(frames)} do not match the model's {nominal.frame_names}"
        )
    arm = nominal.with_frames(device_array(np.stack([frames[n] for n in nominal.frame_names])))
    markers = result.get("markers") or {}
    known = {mk.name for mk in nominal.markers}
    return arm.with_marker_positions(
        {name: v["calibrated"] for name, v in markers.items() if name in known}
    )


def auto_result_to_dict(
    arm: Arm,
    solution: AutoSolution,
    meas_q: ArrayLike,
    pose_ids: Sequence[str],
    *,
    identifiability: Mapping[str, Any],
    inputs: Mapping[str, Any] | None = None,
    conditioning: Mapping[str, Any] | None = None,
    uncertainty: Mapping[str, Any] | None = None,
    warnings: Sequence[str] = (),
    observations: Observations,
) -> dict[str, Any]:
    """JSON-ready mapping of one :func:`~cdra_jax.calibration.calibrate_auto` result, in the
    same contract as :func:`result_to_dict` plus ``registration``, ``markers`` and per-point
    residuals.

    Per row, ``nominal_*`` is the start model (the nominal frames with the base registered to
    the device frame and rough markers placed, see :mod:`cdra_jax.calibration.registration`)
    and ``calibrated_*`` the result; ``*_position_mm`` is the mean error of the row's measured
    positions (a full pose's origin and every seen point), ``*_rotation_rad`` the full pose's
    rotation error (``null`` without one); ``z`` the largest standardised residual of the
    row's units, ``weight`` the smallest robust weight, ``points`` the per-point numbers.
    """
    sol = solution
    obs = observations
    ids = [str(p) for p in pose_ids]
    m = len(ids)
    pose_mask = np.asarray(obs.pose_mask)
    seen = np.asarray(obs.seen)
    start_frames, start_xyz = sol.start.frames, sol.start.xyz
    pos0, rot0 = error_table(start_frames, start_xyz, obs)
    pos1, rot1 = error_table(sol.frames, sol.xyz, obs)
    mean0, mean1 = row_means(pos0), row_means(pos1)
    threshold = sol.outlier_threshold

    residuals = []
    flagged_units: list[str] = []
    for i in range(m):
        p0, r0, p1, r1 = mean0[i], rot0[i], mean1[i], rot1[i]
        zs = [sol.z_position[i], sol.z_rotation[i], *sol.z_points[i]]
        ws = [sol.weights_position[i], sol.weights_rotation[i], *sol.weights_points[i]]
        zs = [float(z) for z in zs if np.isfinite(z)]
        ws = [float(w) for w in ws if np.isfinite(w)]
        units = []
        if pose_mask[i]:
            units += [("position", sol.z_position[i]), ("rotation", sol.z_rotation[i])]
        units += [
            (sol.point_names[j], sol.z_points[i, j]) for j in range(seen.shape[1]) if seen[i, j]
        ]
        out = [name for name, z in units if z > threshold]
        flagged_units += [f"{ids[i]}:{name}" for name in out]
        row: dict[str, Any] = {
            "pose": ids[i],
            "nominal_position_mm": _num(p0),
            "nominal_rotation_rad": _num(r0),
            "calibrated_position_mm": _num(p1),
            "calibrated_rotation_rad": _num(r1),
            "z": _num(max(zs)) if zs else None,
            "weight": _num(min(ws)) if ws else None,
            "outlier": bool(out),
        }
        if seen.shape[1]:
            row["points"] = {
                sol.point_names[j]: {
                    "nominal_mm": _num(pos0[i, j + 1]),
                    "calibrated_mm": _num(pos1[i, j + 1]),
                    "z": _num(sol.z_points[i, j]),
                    "weight": _num(sol.weights_points[i, j]),
                }
                for j in range(seen.shape[1])
                if seen[i, j]
            }
        residuals.append(row)
    nominal_frames = np.asarray(arm.frames, dtype=float)
    nxyz, nrv = (np.asarray(a) for a in lie.to_xyz_rotvec(device_array(nominal_frames)))
    cxyz, crv = (np.asarray(a) for a in lie.to_xyz_rotvec(device_array(sol.frames)))
    frames = {
        name: {
            "nominal": _pose_dict(nominal_frames[j], nxyz[j], nrv[j]),
            "calibrated": _pose_dict(sol.frames[j], cxyz[j], crv[j]),
            "error_twist": {
                c: _num(v) for c, v in zip(TWIST_COMPONENTS, sol.errors[j], strict=True)
            },
        }
        for j, name in enumerate(arm.frame_names)
    }
    markers = {}
    for j, name in enumerate(sol.point_names):
        if name == "origin":
            continue
        mk = arm.marker(name)
        markers[name] = {
            "nominal": list(mk.xyz),
            "calibrated": [float(v) for v in sol.xyz[j]],
            "calibrate": mk.calibrate,
        }
    hist = sol.history
    warnings = list(warnings)
    if flagged_units:
        shown = ", ".join(flagged_units[:5]) + (
            f" and {len(flagged_units) - 5} more" if len(flagged_units) > 5 else ""
        )
        warnings.append(
            f"{len(flagged_units)} measured unit(s) beyond the outlier bound z > {threshold:.3g} "
            f"(family-wise 1 %): {shown}; the robust fit down-weighted them"
            if sol.loss == "huber"
            else f"{len(flagged_units)} measured unit(s) beyond the outlier bound z > "
            f"{threshold:.3g} (family-wise 1 %): {shown}"
        )
    scales = {
        "position_mm": _num(sol.sigma_position_mm),
        "rotation_rad": _num(sol.sigma_rotation_rad),
        "points_mm": {
            name: _num(s) for name, s in zip(sol.point_names, sol.sigma_points_mm, strict=True)
        },
        "source": sol.noise_source,
    }
    return _finite(
        {
            **_header(arm, inputs, m, "auto"),
            "converged": bool(sol.converged),
            "result": sol.result,
            "message": ""
            if sol.converged
            else "the calibration did not settle within the iteration limits",
            "noise": scales,
            "loss": sol.loss,
            "registration": {
                "registered": bool(sol.start.registered),
                "markers_placed": [sol.point_names[j] for j in sol.start.placed],
                "rms_before_mm": _num(sol.start.rms_before_mm),
                "rms_after_mm": _num(sol.start.rms_after_mm),
            },
            "initial": {
                "delta_p_mm": _num(hist[0]["position_rms_mm"]),
                "delta_R_rad": _num(hist[0]["rotation_rms_rad"]),
            },
            "iterations": [
                {
                    "iteration": k,
                    "step_norm": _num(h["step_norm"]),
                    "delta_p_mm": _num(h["position_rms_mm"]),
                    "delta_R_rad": _num(h["rotation_rms_rad"]),
                }
                for k, h in enumerate(hist[1:], start=1)
            ],
            "final": {
                "delta_p_mm": _num(hist[-1]["position_rms_mm"]),
                "delta_R_rad": _num(hist[-1]["rotation_rms_rad"]),
                "rank": int(sol.rank),
                "rounds": int(sol.rounds),
            },
            "frames": frames,
            "markers": markers,
            "identifiability": dict(identifiability),
            "uncertainty": None if uncertainty is None else dict(uncertainty),
            "residuals": residuals,
            "outliers": {
                "threshold": float(threshold),
                "scale": {
                    "position_mm": _num(sol.sigma_position_mm),
                    "rotation_rad": _num(sol.sigma_rotation_rad),
                    "source": sol.noise_source,
                },
                "poses": [r["pose"] for r in residuals if r["outlier"]],
                "units": flagged_units,
            },
            "robust": None,
            "conditioning": None if conditioning is None else dict(conditioning),
            "warnings": warnings,
        }
    )
