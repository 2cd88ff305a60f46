"""The validate workflow: how well does a model predict measurements it was not fitted to?

:func:`validate` predicts the tool pose of every row of a measurement file with a model (a
model file, or a nominal model with a calibration result applied: Eq. 19) and compares it with
the measured pose: the position error ``|p_meas - p_model|`` (mm) and the rotation error, the
angle of ``R_meas^T R_model`` (rad), per row and pooled (``mean``, ``rms``, ``max``, ``n``).
With a calibration result the nominal model's errors are reported beside, so the gain of the
calibration on held-out data reads off directly. The returned :class:`ValidationRun` is what
``cdra-jax validate`` prints and writes.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from ..arm import Arm, tool_pose
from ..calibration import pose_errors
from ..compilation import cached_filter_jit
from ..io import Measurements, calibrated_arm_from_result, load_result
from ..plots import validation_figure
from .inputs import Data, Model, resolve_arm, resolve_measurements
from .result import JsonResult


def _errors(arm: Arm, q, measured) -> tuple[np.ndarray, np.ndarray]:
    dp, dR = cached_filter_jit(_predicted_errors)(arm, q, measured)
    return np.asarray(dp, dtype=float), np.asarray(dR, dtype=float)


def _predicted_errors(arm: Arm, q, measured):
    return pose_errors(measured, tool_pose(arm, q))


def pooled(errors: np.ndarray) -> dict[str, float | int]:
    """``mean``, ``rms``, ``max`` and ``n`` of per-row errors (finite entries)."""
    e = np.asarray(errors, dtype=float)
    e = e[np.isfinite(e)]
    if e.size == 0:
        return {"mean": None, "rms": None, "max": None, "n": 0}  # type: ignore[dict-item]
    return {
        "mean": float(np.mean(e)),
        "rms": float(np.sqrt(np.mean(e * e))),
        "max": float(np.max(e)),
        "n": int(e.size),
    }


@dataclasses.dataclass(frozen=True, eq=False)
class ValidationRun(JsonResult):
    """Prediction errors of a model on measured poses.

    Attributes:
        arm: the model that predicted (calibrated when a result was given).
        measurements: the held-out measurements.
        position_error_mm: ``(m,)`` per-row position error (mm).
        rotation_error_rad: ``(m,)`` per-row rotation error (rad).
        nominal_position_error_mm: ``(m,)`` the nominal model's, when a result was applied.
        nominal_rotation_error_rad: likewise for the rotation, or ``None``.
        model_label: the model file (or ``embedded CDRA``).
        data_label: the measurement file.
        result_label: the calibration result applied, or ``None``.
    """

    arm: Arm
    measurements: Measurements
    position_error_mm: np.ndarray
    rotation_error_rad: np.ndarray
    nominal_position_error_mm: np.ndarray | None
    nominal_rotation_error_rad: np.ndarray | None
    model_label: str
    data_label: str
    result_label: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """The validation mapping: ``position_error_mm`` and ``rotation_error_rad`` pooled
        (``mean``, ``rms``, ``max``, ``n``), the nominal model's beside them when a result was
        applied, and ``rows``, one entry per measured pose."""
        nominal = self.nominal_position_error_mm is not None
        rows = []
        for i, pose in enumerate(self.measurements.pose_ids):
            row: dict[str, Any] = {
                "pose": pose,
                "position_mm": float(self.position_error_mm[i]),
                "rotation_rad": float(self.rotation_error_rad[i]),
            }
            if nominal:
                assert self.nominal_rotation_error_rad is not None
                assert self.nominal_position_error_mm is not None
                row["nominal_position_mm"] = float(self.nominal_position_error_mm[i])
                row["nominal_rotation_rad"] = float(self.nominal_rotation_error_rad[i])
            rows.append(row)
        out: dict[str, Any] = {
            "format": "cdra_jax.validation",
            "inputs": {"model": self.model_label, "data": self.data_label},
            "model": self.arm.name,
            "position_error_mm": pooled(self.position_error_mm),
            "rotation_error_rad": pooled(self.rotation_error_rad),
        }
        if self.result_label is not None:
            out["inputs"]["result"] = self.result_label
        if nominal:
            assert self.nominal_position_error_mm is not None
            assert self.nominal_rotation_error_rad is not None
            out["nominal"] = {
                "position_error_mm": pooled(self.nominal_position_error_mm),
                "rotation_error_rad": pooled(self.nominal_rotation_error_rad),
            }
        out["rows"] = rows
        return out

    def report(self) -> str:
        """The plain-text summary ``cdra-jax validate`` prints."""
        d = self.to_dict()
        what = self.model_label + (
            f" with the calibration {self.result_label}" if self.result_label else ""
        )
        lines = [
            f"model: {self.arm.name} ({what}); data: {self.data_label} "
            f"({self.measurements.m} poses)",
            f"  {'':<22}{'mean':>11}{'rms':>11}{'max':>11}",
        ]

        def row(label: str, stats: Mapping[str, Any], unit: str) -> str:
            vals = "".join(
                f"{'-' if stats[k] is None else format(stats[k], '.4g'):>11}"
                for k in ("mean", "rms", "max")
            )
            return f"  {label + ' [' + unit + ']':<22}{vals}"

        if "nominal" in d:
            lines.append(row("nominal position", d["nominal"]["position_error_mm"], "mm"))
            lines.append(row("nominal rotation", d["nominal"]["rotation_error_rad"], "rad"))
        lines.append(row("position", d["position_error_mm"], "mm"))
        lines.append(row("rotation", d["rotation_error_rad"], "rad"))
        return "\n".join(lines)

    def plot(self) -> Figure:
        """Per-row errors (:func:`cdra_jax.plots.validation_figure`)."""
        return validation_figure(self.to_dict())


def validate(
    model: Model,
    data: Data,
    *,
    result: Mapping[str, Any] | str | os.PathLike | None = None,
    model_label: str | None = None,
    data_label: str | None = None,
) -> ValidationRun:
    """Predict the measured tool poses of ``data`` with a model and report the errors.

    Args:
        model: an :class:`~cdra_jax.arm.Arm`, a model TOML path, or ``None`` (the embedded
            CDRA). With ``result`` it is the nominal model the calibration started from.
        data: held-out :class:`~cdra_jax.io.Measurements` or a measurement CSV path.
        result: a calibration result (mapping or result JSON path) to apply to ``model``
            (Eq. 19); the nominal model's errors are then reported beside.
        model_label, data_label: names for the report.

    Raises:
        ValueError: measurements without measured tool poses, or a result of another model.
    """
    nominal, model_label = resolve_arm(model, model_label)
    meas, data_label, _ = resolve_measurements(data, nominal, data_label)
    if meas.measured is None:
        raise ValueError(f"{data_label}: no measured tool poses (measured.* columns) to compare")
    result_label = None
    arm = nominal
    if result is not None:
        if isinstance(result, Mapping):
            result_label = "<result>"
        else:
            result_label = str(result)
            result = load_result(result)
        arm = calibrated_arm_from_result(result, nominal)
    dp, dR = _errors(arm, meas.q, meas.measured)
    ndp = ndR = None
    if result is not None:
        ndp, ndR = _errors(nominal, meas.q, meas.measured)
    return ValidationRun(
        arm=arm,
        measurements=meas,
        position_error_mm=dp,
        rotation_error_rad=dR,
        nominal_position_error_mm=ndp,
        nominal_rotation_error_rad=ndR,
        model_label=model_label,
        data_label=data_label,
        result_label=result_label,
    )
