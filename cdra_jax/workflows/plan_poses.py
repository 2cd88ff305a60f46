"""The plan-poses workflow: which poses to measure (optimal selection from a pool).

:func:`plan_poses` draws a pool of feasible module states (:func:`cdra_jax.simulation.
sample_poses`: uniform within the joint limits, tension-feasible where the model has cables),
selects ``count`` of them by a design criterion (:mod:`cdra_jax.pose_selection`; I-optimal by
default) and predicts the accuracy of a calibration from them against that of as many random
poses. The :class:`PosePlan` writes a measurement-plan CSV in the measurement-file column naming
(``pose`` and the module state columns; no ``measured.*`` columns: it is a plan to be measured).
"""

from __future__ import annotations

import csv
import dataclasses
import io
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax
import numpy as np

from ..arm import Arm
from ..calibration import NoiseModel
from ..io.files import write_text_atomic
from ..physics import needed_aux
from ..pose_selection import (
    CRITERIA,
    DEFAULT_CRITERION,
    DEFAULT_POOL_SIZE,
    marker_prediction_rms,
    select_poses,
)
from ..uncertainty import predicted_pose_covariance
from .inputs import Model, check_range, check_seed, resolve_arm
from .result import JsonResult

if TYPE_CHECKING:
    from matplotlib.figure import Figure

DEFAULT_NOISE = NoiseModel(position_mm=0.08, rotation_rad=1e-3)
"""The measuring device assumed when none is given: the paper's FARO arm (Section VI, 80 um),
orientation from calibration-block points about 80 mm apart (1e-3 rad)."""
RANDOM_DRAWS = 20
"""Random pose sets of the same size whose median accuracy the plan is compared with."""


def plan_csv_text(state_names: Sequence[str], states, comments: Sequence[str] = ()) -> str:
    """The plan CSV: ``#`` comment lines, a header ``pose,<state names>``, one row per pose.

    Pose ids are ``P01``, ``P02``, ... (zero-padded to the count); floats are written with
    ``repr`` (round trip exact).
    """
    buf = io.StringIO()
    for c in comments:
        buf.write(f"# {c}\n")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["pose", *state_names])
    width = max(2, len(str(len(states))))
    for i, row in enumerate(states, start=1):
        w.writerow([f"P{i:0{width}d}", *(repr(float(v)) for v in row)])
    return buf.getvalue()


@dataclasses.dataclass(frozen=True, eq=False)
class PosePlan(JsonResult):
    """A measurement plan and its expected accuracy.

    Attributes:
        arm: the model.
        states: ``(count, dof)`` the selected module states.
        selection: the :class:`~cdra_jax.pose_selection.PoseSelection` (pool, criterion values).
        expected_dp_mm: expected RMS tool-position accuracy after calibrating from the plan.
        expected_dR_rad: likewise for the orientation.
        random_dp_mm: ``(RANDOM_DRAWS,)`` the same for random pose sets of the same size.
        criterion, pool, seed, noise, model_label: how the plan was made.
    """

    arm: Arm
    states: np.ndarray
    selection: Any
    expected_dp_mm: float
    expected_dR_rad: float
    random_dp_mm: np.ndarray
    criterion: str
    pool: int
    seed: int
    noise: NoiseModel
    model_label: str

    def comments(self) -> list[str]:
        """The ``#`` lines of the plan CSV (how it was made, what to measure)."""
        sel = self.selection
        return [
            f"measurement plan: {len(self.states)} poses chosen by cdra-jax plan-poses "
            f"({self.criterion})",
            f"model: {self.model_label}; pool: {self.pool} states, seed {self.seed}",
            f"noise: {float(self.noise.position_mm)} mm, {float(self.noise.rotation_rad)} rad",
            f"log det information (identifiable subspace, rank {sel.rank}): {sel.log_det:.6g}; "
            f"O1: {sel.o1:.6g}",
            f"expected RMS accuracy after calibration: dp {self.expected_dp_mm:.4g} mm, "
            f"dR {self.expected_dR_rad:.4g} rad",
            "measure the tool pose at each row and add measured.x/y/z and measured.rx/ry/rz "
            "columns",
            *effects_note(self.arm),
        ]

    def to_csv_text(self) -> str:
        """The plan CSV text."""
        return plan_csv_text(self.arm.state_names, self.states, self.comments())

    def save(self, path: str | os.PathLike, *, force: bool = False) -> Path:
        """Write the plan CSV atomically (an existing file only with ``force``)."""
        return write_text_atomic(path, self.to_csv_text(), force=force)

    def to_dict(self) -> dict[str, Any]:
        """The plan's numbers: criterion values and expected accuracies."""
        sel = self.selection
        return {
            "count": len(self.states),
            "criterion": self.criterion,
            "pool": self.pool,
            "seed": self.seed,
            "noise": {
                "position_mm": float(self.noise.position_mm),
                "rotation_rad": float(self.noise.rotation_rad),
            },
            "rank": int(sel.rank),
            "log_det": float(sel.log_det),
            "o1": float(sel.o1),
            "expected_dp_mm": self.expected_dp_mm,
            "expected_dR_rad": None if np.isnan(self.expected_dR_rad) else self.expected_dR_rad,
            "random_dp_mm_median": float(np.median(self.random_dp_mm)),
            "states": {n: self.states[:, j].tolist() for j, n in enumerate(self.arm.state_names)},
        }

    def report(self) -> str:
        """The summary ``cdra-jax plan-poses`` prints."""
        sel = self.selection
        n = len(self.states)
        return "\n".join(
            [
                f"selected {n} of {self.pool} poses by {self.criterion}: log det "
                f"{sel.log_det:.6g} (greedy {sel.log_det_greedy:.6g}, {sel.n_exchanges} "
                f"exchanges), rank {sel.rank}, O1 {sel.o1:.4g}",
                f"expected RMS accuracy over the workspace with noise "
                f"{float(self.noise.position_mm)} mm / {float(self.noise.rotation_rad)} rad:",
                (
                    f"  planned poses: dp {self.expected_dp_mm:.4g} mm (marker positions)"
                    if self.arm.markers
                    else f"  planned poses: dp {self.expected_dp_mm:.4g} mm, dR "
                    f"{self.expected_dR_rad:.4g} rad"
                ),
                f"  {n} random poses (median of {len(self.random_dp_mm)} draws): dp "
                f"{np.median(self.random_dp_mm):.4g} mm",
                *effects_note(self.arm),
            ]
        )

    def plot(self) -> Figure:
        """Expected RMS position accuracy of the plan against that of random pose sets."""
        from ..plots import new_figure

        fig = new_figure(6.0, 3.6)
        ax = fig.add_subplot()
        ax.hist(self.random_dp_mm, bins=10, color="0.7", label=f"{len(self.states)} random poses")
        ax.axvline(self.expected_dp_mm, color="C3", lw=2, label=f"plan ({self.criterion})")
        ax.set_xlabel("expected RMS tool-position accuracy after calibration [mm]")
        ax.set_ylabel("random pose sets")
        ax.legend(fontsize="small")
        return fig


def effects_note(arm: Arm) -> list[str]:
    """Lines on a model's ``[[effects]]``: the criterion is the frames'; the columns to record."""
    if not arm.effects:
        return []
    aux = needed_aux(arm, ("time_s", "payload_kg", *(f"approach.{n}" for n in arm.module_names)))
    lines = [
        "the model's effects ("
        + ", ".join(e.label for e in arm.effects)
        + ") are not part of the criterion: the poses are chosen for the fixed frames"
    ]
    if aux:
        lines.append(f"record also the columns the effects need: {', '.join(aux)}")
    return lines


def plan_poses(
    model: Model,
    count: int,
    *,
    noise: NoiseModel | None = None,
    pool: int = DEFAULT_POOL_SIZE,
    seed: int = 0,
    criterion: str = DEFAULT_CRITERION,
    model_label: str | None = None,
) -> PosePlan:
    """Choose ``count`` poses to measure from a pool of ``pool`` random feasible states.

    Args:
        model: an :class:`~cdra_jax.arm.Arm`, a model TOML path, or ``None`` (embedded CDRA).
        count: poses to select (>= 4, the paper's minimum).
        noise: the measuring device's noise (default :data:`DEFAULT_NOISE`).
        pool: candidate states (>= ``count``); also the workspace sample over which the
            I-criterion averages the predicted tool-position variance.
        seed: seed of the pool (and of the random comparison sets).
        criterion: one of :data:`cdra_jax.pose_selection.CRITERIA` (``i-opt`` default).
        model_label: name of the model in the plan's comments.
    """
    check_range("count", count)  # at least 4: the paper's minimum
    check_range("pool", pool)
    if pool < count:
        raise ValueError(f"pool ({pool}) must be at least count ({count})")
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {', '.join(CRITERIA)}, got {criterion!r}")
    check_seed(seed)
    noise = DEFAULT_NOISE if noise is None else noise
    arm, model_label = resolve_arm(model, model_label)
    sel = select_poses(
        arm, count, noise, key=jax.random.PRNGKey(seed), pool_size=pool, criterion=criterion
    )
    # Expected accuracy over the pool (a sample of the workspace), selected vs random poses:
    # of the tool pose, or, for a model measured by markers, of the marker positions.
    rng = np.random.default_rng(seed % 2**64)  # numpy takes no negative seeds

    def expected_dp(states) -> tuple[float, float]:
        if arm.markers:
            return marker_prediction_rms(arm, states, noise, sel.pool), float("nan")
        pred = predicted_pose_covariance(arm, states, noise, sel.pool)
        return float(pred.expected_delta_p), float(pred.expected_delta_R)

    exp_dp, exp_dR = expected_dp(sel.states)
    rand = np.array(
        [
            expected_dp(sel.pool[rng.choice(len(sel.pool), count, replace=False)])[0]
            for _ in range(RANDOM_DRAWS)
        ]
    )
    return PosePlan(
        arm=arm,
        states=np.asarray(sel.states),
        selection=sel,
        expected_dp_mm=exp_dp,
        expected_dR_rad=exp_dR,
        random_dp_mm=rand,
        criterion=criterion,
        pool=pool,
        seed=seed,
        noise=noise,
        model_label=model_label,
    )
