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
        reference_position_error_mm: ``(m,)`` the reference model's (the nominal model when a
            result was applied, the ``compare`` model otherwise), or ``None``.
        reference_rotation_error_rad: likewise for the rotation, or ``None``.
        model_label: the model file (or ``embedded CDRA``).
        data_label: the measurement file.
        result_label: the calibration result applied, or ``None``.
        reference: ``"nominal"`` (a result was applied) or ``"compare"`` (a second model was
            given): the key of the reference's block and the prefix of its per-row columns.
        reference_label: the reference model's label.
    """

    arm: Arm
    measurements: Measurements
    position_error_mm: np.ndarray
    rotation_error_rad: np.ndarray
    reference_position_error_mm: np.ndarray | None
    reference_rotation_error_rad: np.ndarray | None
    model_label: str
    data_label: str
    result_label: str | None = None
    reference: str = "nominal"
    reference_label: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """The validation mapping: ``position_error_mm`` and ``rotation_error_rad`` pooled
        (``mean``, ``rms``, ``max``, ``n``), the nominal model's beside them when a result was
        applied, and ``rows``, one entry per measured pose."""
        ref = self.reference_position_error_mm
        ref_rot = self.reference_rotation_error_rad
        rows = []
        for i, pose in enumerate(self.measurements.pose_ids):
            row: dict[str, Any] = {
                "pose": pose,
                "position_mm": float(self.position_error_mm[i]),
                "rotation_rad": float(self.rotation_error_rad[i]),
            }
            if ref is not None and ref_rot is not None:
                row[f"{self.reference}_position_mm"] = float(ref[i])
                row[f"{self.reference}_rotation_rad"] = float(ref_rot[i])
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
        if ref is not None and ref_rot is not None:
            out[self.reference] = {
                "model": self.reference_label,
                "position_error_mm": pooled(ref),
                "rotation_error_rad": pooled(ref_rot),
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

        if self.reference in d:
            block, name = d[self.reference], self.reference
            if self.reference == "compare":
                lines.insert(1, f"compared with: {self.reference_label}")
            lines.append(row(f"{name} position", block["position_error_mm"], "mm"))
            lines.append(row(f"{name} rotation", block["rotation_error_rad"], "rad"))
        lines.append(row("position", d["position_error_mm"], "mm"))
        lines.append(row("rotation", d["rotation_error_rad"], "rad"))
        return "\n".join(lines)

    def plot(self) -> Figure:
        """Per-row errors of the model and the reference, side by side
        (:func:`cdra_jax.plots.validation_figure`)."""
        return validation_figure(self.to_dict(), reference=self.reference)


def validate(
    model: Model,
    data: Data,
    *,
    result: Mapping[str, Any] | str | os.PathLike | None = None,
    compare: Arm | str | os.PathLike | None = None,
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
        compare: a second model (an :class:`~cdra_jax.arm.Arm` or model TOML path) whose
            errors are reported beside (for example the nominal model next to a calibrated one
            from ``calibrate --model-out``; ``default_arm()`` for the embedded one); not together
            with ``result``.
        model_label, data_label: names for the report.

    Raises:
        ValueError: measurements without measured tool poses, or a result of another model.
    """
    nominal, model_label = resolve_arm(model, model_label)
    meas, data_label, _ = resolve_measurements(data, nominal, data_label)
    if meas.measured is None:
        raise ValueError(f"{data_label}: no measured tool poses (measured.* columns) to compare")
    if result is not None and compare is not None:
        raise ValueError("give either result (applied to the model) or compare, not both")
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
    reference, reference_label = "nominal", None
    if result is not None:
        ndp, ndR = _errors(nominal, meas.q, meas.measured)
        reference_label = model_label
    elif compare is not None:
        other, reference_label = resolve_arm(compare)
        if other.state_names != nominal.state_names:
            raise ValueError(
                f"compare {reference_label}: its module states {other.state_names} differ from "
                f"the model's {nominal.state_names}"
            )
        ndp, ndR = _errors(other, meas.q, meas.measured)
        reference = "compare"
    return ValidationRun(
        arm=arm,
        measurements=meas,
        position_error_mm=dp,
        rotation_error_rad=dR,
        reference_position_error_mm=ndp,
        reference_rotation_error_rad=ndR,
        model_label=model_label,
        data_label=data_label,
        result_label=result_label,
        reference=reference,
        reference_label=reference_label,
    )
