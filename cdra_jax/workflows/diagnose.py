"""The diagnose workflow: why does a calibrated model still disagree with the recordings?

:func:`diagnose` loads the model and the measurements (objects or files) and runs the
missing-physics analyser of :mod:`cdra_jax.diagnosis` (detect a mismatch, locate it, attribute
it to an effect of the vocabulary of :mod:`cdra_jax.physics`, refit, and measure the held-out
gain). The returned :class:`DiagnosisRun` is what ``cdra-jax diagnose`` prints and writes.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..arm import Arm
from ..calibration import NoiseModel
from ..io import Measurements, arm_to_dict, save_model
from .inputs import Data, Model, check_range, check_seed, resolve_arm, resolve_measurements
from .result import JsonResult

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from ..diagnosis import Diagnosis


@dataclasses.dataclass(frozen=True, eq=False)
class DiagnosisRun(JsonResult):
    """A diagnosis with the model and measurements it was made on.

    Attributes:
        arm: the nominal model.
        measurements: the recordings.
        diagnosis: the analyser's :class:`~cdra_jax.diagnosis.Diagnosis` (verdict, location,
            effect, parameters, candidate table, held-out errors before and after).
        model_label: the model file (or ``embedded CDRA``).
        data_label: the measurement file.
    """

    arm: Arm
    measurements: Measurements
    diagnosis: Diagnosis
    model_label: str
    data_label: str

    @property
    def refit_arm(self) -> Arm:
        """The model the diagnosis ends with: the geometric fit's frames (and calibrated
        markers) plus the selected effect as ``[[effects]]`` with its refitted parameters (the
        geometric fit alone when the effect is ``none`` or ``unattributed``)."""
        return self.diagnosis.refit_arm

    def to_dict(self) -> dict[str, Any]:
        """The diagnosis mapping with the model and data labels and the refit model in the
        model contract (``refit_model``, what :meth:`save_model` writes): the diagnosis JSON."""
        out = self.diagnosis.to_dict()
        out["model"] = self.model_label
        out["data"] = self.data_label
        out["refit_model"] = arm_to_dict(self.refit_arm, exact=True)
        return out

    def save_model(self, path: str | os.PathLike, *, force: bool = False) -> Path:
        """Write :attr:`refit_arm` as a model TOML file (frames as exact 4x4 matrices, the
        effect under ``[[effects]]``), loadable by every command (``--model``): ``validate``
        predicts with it, ``calibrate`` refines it."""
        return save_model(self.refit_arm, path, exact=True, force=force)

    def report(self) -> str:
        """The plain-words verdict and the candidate table (what ``cdra-jax diagnose`` prints)."""
        return f"{self.diagnosis.report}\n\n{self.diagnosis.table()}"

    def plot(self) -> Figure:
        """Held-out residuals against every regressor, before and after the refit."""
        from ..plots import residual_vs_regressors_figure

        return residual_vs_regressors_figure(self.arm, self.measurements, self.diagnosis)

    def save_plots(self, folder: str | os.PathLike, *, force: bool = False) -> Sequence[Path]:
        """Write the diagnosis figures (PNG) into ``folder``; returns the paths."""
        from ..plots import save_diagnosis_plots

        return save_diagnosis_plots(
            self.arm, self.measurements, self.diagnosis, folder, force=force
        )


def diagnose(
    model: Model,
    data: Data,
    noise: NoiseModel | None = None,
    *,
    seed: int = 0,
    folds: int = 5,
    alpha: float = 0.01,
    model_label: str | None = None,
    data_label: str | None = None,
) -> DiagnosisRun:
    """Find the missing physics a geometric calibration leaves in the recordings.

    Args:
        model: an :class:`~cdra_jax.arm.Arm`, a model TOML path, or ``None`` (embedded CDRA).
        data: :class:`~cdra_jax.io.Measurements` or a measurement CSV path.
        noise: the measuring device's noise, or ``None`` (estimated from the residuals).
        seed: seed of the cross-validation folds.
        folds: number of cross-validation folds (>= 2).
        alpha: significance level of the detection and the candidate tests (0 < alpha < 1).
        model_label, data_label: names for the report.
    """
    check_seed(seed)
    check_range("folds", folds)
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    arm, model_label = resolve_arm(model, model_label)
    meas, data_label, _ = resolve_measurements(data, arm, data_label)
    from ..diagnosis import diagnose as _diagnose  # here: the other commands do not load it

    d = _diagnose(arm, meas, noise, seed=seed, folds=folds, alpha=alpha)
    return DiagnosisRun(arm, meas, d, model_label, data_label)
