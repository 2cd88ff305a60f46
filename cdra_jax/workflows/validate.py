"""The validate workflow: how well does a model predict measurements it was not fitted to?

:func:`validate` predicts every measured row of a measurement file with a model (a model
file, or a nominal model with a calibration result applied: Eq. 19) and compares: the position
error ``|p_meas - p_model|`` (mm) of every measured position (a full pose's tool origin, each
seen marker or tool-origin point), and the rotation error of full poses, the angle of
``R_meas^T R_model`` (rad). Pooled (``mean``, ``rms``, ``max``, ``n``) over every measured
position and every measured rotation; per row, the mean over the row's positions.
With a calibration result the nominal model's errors are reported beside, so the gain of the
calibration on held-out data reads off directly. A model with ``[[effects]]`` predicts with them
(:func:`cdra_jax.physics.model_tool_pose`, from the module states and the auxiliary columns
``time_s``, ``approach.<module>``, ``payload_kg`` of the measurements); a calibration result
that refined them (``effects``) applies its values. The returned :class:`ValidationRun` is what
``cdra-jax validate`` prints and writes.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from ..arm import Arm
from ..calibration.observations import (
    error_table,
    make_observations,
    marker_table,
    row_means,
)
from ..calibration.registration import initial_guess
from ..io import Measurements, load_result
from ..physics import RefitData, check_effect_data, model_tool_pose, prediction_error_table
from .calibrate import result_arm
from .inputs import Data, Model, resolve_arm, resolve_measurements
from .result import JsonResult

if TYPE_CHECKING:
    from matplotlib.figure import Figure


class PredictionErrors(NamedTuple):
    """A model's errors on measured rows.

    Attributes:
        position_mm: ``(m, 1 + P)``: the full pose's position error (NaN without one), then
            each point's (NaN where not seen).
        rotation_rad: ``(m,)`` the full pose's rotation error (NaN without one).
        names: the columns of ``position_mm``: ``pose`` then the point names.
    """

    position_mm: np.ndarray
    rotation_rad: np.ndarray
    names: tuple[str, ...]

    @property
    def per_row_position_mm(self) -> np.ndarray:
        """``(m,)`` mean position error over each row's measured positions."""
        return row_means(self.position_mm)


def prediction_errors(arm: Arm, meas: Measurements) -> PredictionErrors:
    """The errors of ``arm``'s predictions on every measured position and rotation of ``meas``."""
    obs = make_observations(arm, meas.q, meas.full_poses, meas.points)
    xyz, _ = marker_table(arm, meas.point_names)
    if arm.effects:
        check_effect_data(arm, meas.aux)
        pos, ang = _effect_error_table(arm, meas, xyz)
    else:
        pos, ang = error_table(arm.frames, xyz, obs)
    return PredictionErrors(pos, ang, ("pose", *meas.point_names))


def _effect_error_table(
    arm: Arm, meas: Measurements, xyz: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`~cdra_jax.calibration.observations.error_table` of the model with its effects."""
    tool = model_tool_pose(arm, meas.q, meas.aux)
    data = RefitData.make(meas.m, meas.full_poses, meas.points, xyz)
    return prediction_error_table(tool, data)


def _num(x: float) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


def pooled(errors: np.ndarray) -> dict[str, float | int]:
    """``mean``, ``rms``, ``max`` and ``n`` of errors (the finite entries, any shape)."""
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
    """Prediction errors of a model on measured poses and points.

    Attributes:
        arm: the model that predicted (calibrated when a result was given).
        measurements: the held-out measurements.
        errors: the model's :class:`PredictionErrors`.
        reference_errors: the reference model's (the nominal model when a result was applied,
            the ``compare`` model otherwise), or ``None``.
        model_label: the model file (or ``embedded CDRA``).
        data_label: the measurement file.
        result_label: the calibration result applied, or ``None``.
        reference: ``"nominal"`` (a result was applied) or ``"compare"`` (a second model was
            given): the key of the reference's block and the prefix of its per-row columns.
        reference_label: the reference model's label.
    """

    arm: Arm
    measurements: Measurements
    errors: PredictionErrors
    reference_errors: PredictionErrors | None
    model_label: str
    data_label: str
    result_label: str | None = None
    reference: str = "nominal"
    reference_label: str | None = None

    @property
    def position_error_mm(self) -> np.ndarray:
        """``(m,)`` per-row position error: the mean over the row's measured positions (mm)."""
        return self.errors.per_row_position_mm

    @property
    def rotation_error_rad(self) -> np.ndarray:
        """``(m,)`` per-row rotation error (rad; NaN in rows without a full pose)."""
        return self.errors.rotation_rad

    def to_dict(self) -> dict[str, Any]:
        """The validation mapping: ``position_error_mm`` pooled over every measured position
        (tool origins and points) and ``rotation_error_rad`` over every measured rotation
        (``mean``, ``rms``, ``max``, ``n``), the reference model's beside them, and ``rows``,
        one entry per measured row (with ``points`` where the file measures points)."""
        ref = self.reference_errors
        names = self.errors.names
        rows = []
        for i, pose in enumerate(self.measurements.pose_ids):
            row: dict[str, Any] = {
                "pose": pose,
                "position_mm": _num(self.errors.per_row_position_mm[i]),
                "rotation_rad": _num(self.errors.rotation_rad[i]),
            }
            if ref is not None:
                row[f"{self.reference}_position_mm"] = _num(ref.per_row_position_mm[i])
                row[f"{self.reference}_rotation_rad"] = _num(ref.rotation_rad[i])
            if len(names) > 1:
                row["points"] = {
                    name: _num(self.errors.position_mm[i, j])
                    for j, name in enumerate(names)
                    if j > 0 and np.isfinite(self.errors.position_mm[i, j])
                }
            rows.append(row)
        out: dict[str, Any] = {
            "format": "cdra_jax.validation",
            "inputs": {"model": self.model_label, "data": self.data_label},
            "model": self.arm.name,
            "position_error_mm": pooled(self.errors.position_mm),
            "rotation_error_rad": pooled(self.errors.rotation_rad),
        }
        if self.arm.effects:
            out["effects"] = [e.label for e in self.arm.effects]
        if self.result_label is not None:
            out["inputs"]["result"] = self.result_label
        if ref is not None:
            out[self.reference] = {
                "model": self.reference_label,
                "position_error_mm": pooled(ref.position_mm),
                "rotation_error_rad": pooled(ref.rotation_rad),
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
        if self.arm.effects:
            lines.insert(
                1, "predicted with the model's effects: " + ", ".join(d.get("effects", []))
            )

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
        from ..plots import validation_figure

        return validation_figure(self.to_dict(), reference=self.reference)


def validate(
    model: Model,
    data: Data,
    *,
    result: Mapping[str, Any] | str | os.PathLike | None = None,
    compare: Arm | str | os.PathLike | None = None,
    register_reference: bool = False,
    model_label: str | None = None,
    data_label: str | None = None,
) -> ValidationRun:
    """Predict the measured tool poses and points of ``data`` with a model; report the errors.

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
        register_reference: place the reference model (the nominal or ``compare`` model, in
            the robot's frame) in the measuring device's frame first: its base frame moved by
            the rigid transform that best maps its predicted points onto these measurements
            (:func:`cdra_jax.calibration.registration.initial_guess`; markers with
            ``calibrate = true`` placed likewise). A fair "before calibration" baseline when
            the data are in a tracker's frame; the validated model is used as given.
        model_label, data_label: names for the report.

    Raises:
        ValueError: measurements without measured tool poses, or a result of another model.
    """
    nominal, model_label = resolve_arm(model, model_label)
    meas, data_label, _ = resolve_measurements(data, nominal, data_label)
    if not meas.has_measurements:
        raise ValueError(f"{data_label}: no measured tool poses or points (measured.* columns)")
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
        arm = result_arm(result, nominal, result_label)
    errors = prediction_errors(arm, meas)
    ref = None
    reference, reference_label = "nominal", None
    if result is not None:
        ref = prediction_errors(_registered(nominal, meas, register_reference), meas)
        reference_label = model_label
    elif compare is not None:
        other, reference_label = resolve_arm(compare)
        if other.state_names != nominal.state_names:
            raise ValueError(
                f"compare {reference_label}: its module states {other.state_names} differ from "
                f"the model's {nominal.state_names}"
            )
        other = _with_markers_of(other, nominal, meas)
        ref = prediction_errors(_registered(other, meas, register_reference), meas)
        reference = "compare"
    if register_reference and reference_label is not None:
        reference_label += " (registered to the measuring device's frame on these data)"
    return ValidationRun(
        arm=arm,
        measurements=meas,
        errors=errors,
        reference_errors=ref,
        model_label=model_label,
        data_label=data_label,
        result_label=result_label,
        reference=reference,
        reference_label=reference_label,
    )


def _registered(arm: Arm, meas: Measurements, register: bool) -> Arm:
    """``arm`` with its base frame (and rough markers) registered to ``meas`` when asked."""
    if not register:
        return arm
    obs = make_observations(arm, meas.q, meas.full_poses, meas.points)
    xyz, calibrated = marker_table(arm, meas.point_names)
    start = initial_guess(np.asarray(arm.frames), xyz, obs, calibrated)
    placed = {meas.point_names[j]: start.xyz[j] for j in calibrated}
    return arm.with_frames(start.frames).with_marker_positions(placed)


def _with_markers_of(other: Arm, model: Arm, meas: Measurements) -> Arm:
    """``other`` with ``model``'s markers for those it does not declare (a nominal model
    compared with a calibrated one that carries the markers)."""
    have = {mk.name for mk in other.markers}
    missing = [mk for mk in model.markers if mk.name not in have and mk.name in meas.point_names]
    return other.with_markers([*other.markers, *missing]) if missing else other
