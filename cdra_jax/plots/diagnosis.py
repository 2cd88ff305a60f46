"""Residual plots of a diagnosis: held-out residuals versus the regressors of the physics.

Each figure is drawn on a bare :class:`matplotlib.figure.Figure` with the Agg canvas (no pyplot
state, no display needed):

* ``residual_vs_regressors.png``: the held-out position error of every pose (norm, mm) and its
  rotation error (rad), before (grey) and after (colour) the refit with the reported effect,
  against each module state entry, ``time_s``, ``payload_kg`` and the magnitude of the gravity
  torque each module carries; a missing effect shows as structure in the grey points that the
  coloured ones no longer have;
* ``residual_per_pose.png``: the same errors in pose order (the order of the file: the time
  order for a drift), with the noise floor.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from ..arm import Arm
from ..io.files import OutputExistsError, save_figure_atomic
from ..io.measurements import Measurements
from .canvas import new_figure


def regressors(arm: Arm, meas: Measurements) -> dict[str, np.ndarray]:
    """Named per-pose regressors ``(m,)``: state entries, auxiliaries that vary (``time_s``,
    ``payload_kg``, ...), the norm of the gravity torque each module carries."""
    import jax.numpy as jnp

    from ..modules.statics import gravity_torques

    out = {name: np.asarray(meas.q[:, j]) for j, name in enumerate(arm.state_names)}
    for k, v in meas.aux.items():
        if not k.startswith("approach.") and np.ptp(np.asarray(v)) > 0:  # constant: no axis
            out[k] = np.asarray(v)
    payload = meas.aux.get("payload_kg", np.zeros(meas.m))
    if any(m.mass for m in arm.modules) or np.any(payload):
        tau = np.asarray(gravity_torques(arm, jnp.asarray(meas.q), jnp.asarray(payload)))
        for i, name in enumerate(arm.module_names):
            out[f"|tau| {name} (N*mm)"] = np.linalg.norm(tau[:, i], axis=-1)
    return out


def _figure(w: float, h: float) -> Figure:
    return new_figure(w, h)


def residual_vs_regressors_figure(arm: Arm, meas: Measurements, diagnosis) -> Figure:
    """Held-out position and rotation errors versus every regressor, before and after."""
    regs = regressors(arm, meas)
    before, after = diagnosis.residuals["before"], diagnosis.residuals["after"]
    kinds = _kinds(before)
    n = len(regs)
    ncol = min(4, n)
    per = len(kinds)
    nrow = per * int(np.ceil(n / ncol))
    fig = _figure(3.2 * ncol, 2.2 * nrow)
    axes = fig.subplots(nrow, ncol, squeeze=False)
    label = diagnosis.effect if diagnosis.effect not in ("none", "unattributed") else "geometric"
    for idx, (name, x) in enumerate(regs.items()):
        r0, c = per * (idx // ncol), idx % ncol
        for row, (key, unit) in enumerate(kinds):
            ax = axes[r0 + row][c]
            ax.scatter(x, before[key], s=8, c="0.6", label="geometric")
            ax.scatter(x, after[key], s=8, c="C1", label=f"+ {label}")
            ax.set_xlabel(name, fontsize=8)
            ax.set_ylabel(f"held-out error ({unit})", fontsize=8)
            ax.tick_params(labelsize=7)
    for idx in range(n, (nrow // per) * ncol):
        for row in range(per):
            axes[per * (idx // ncol) + row][idx % ncol].set_visible(False)
    axes[0][0].legend(fontsize=7)
    fig.suptitle(
        f"held-out residuals: {diagnosis.effect}"
        + (f" at {diagnosis.located_in}" if diagnosis.located_in else ""),
        fontsize=10,
    )
    return fig


def residual_per_pose_figure(diagnosis) -> Figure:
    """Held-out errors in pose order, before and after, with the noise floor."""
    before, after = diagnosis.residuals["before"], diagnosis.residuals["after"]
    floor = diagnosis.details["noise_floor"]
    kinds = _kinds(before)
    fig = _figure(8, 2.25 * len(kinds))
    axes = fig.subplots(len(kinds), 1, sharex=True, squeeze=False)[:, 0]
    i = np.arange(np.asarray(before["position_mm"]).shape[0])
    floors = {"position_mm": floor["delta_p_mm"], "rotation_rad": floor["delta_R_rad"]}
    for ax, (key, unit) in zip(axes, kinds, strict=True):
        ax.plot(i, before[key], "o-", c="0.6", ms=3, label="geometric")
        ax.plot(i, after[key], "o-", c="C1", ms=3, label="refit")
        if floors[key] is not None and np.isfinite(floors[key]):
            ax.axhline(floors[key], c="k", ls=":", lw=1, label="noise floor (RMS)")
        ax.set_ylabel(f"held-out error ({unit})")
    axes[0].legend(fontsize=8)
    axes[-1].set_xlabel("pose (file order)")
    return fig


def _kinds(per_row: dict) -> list[tuple[str, str]]:
    """The error kinds a diagnosis has per row: position (always), rotation (full poses)."""
    kinds = [("position_mm", "mm")]
    if np.any(np.isfinite(np.asarray(per_row["rotation_rad"], dtype=float))):
        kinds.append(("rotation_rad", "rad"))
    return kinds


def save_diagnosis_plots(
    arm: Arm,
    meas: Measurements,
    diagnosis,
    folder: str | os.PathLike,
    *,
    force: bool = False,
) -> Sequence[Path]:
    """Write the diagnosis figures (PNG) into ``folder`` (created if missing); returns paths.

    Each file is written atomically (:func:`cdra_jax.io.files.save_figure_atomic`); existing
    files are only replaced with ``force``, and without it none is written when one exists.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    figures = {
        "residual_vs_regressors.png": residual_vs_regressors_figure(arm, meas, diagnosis),
        "residual_per_pose.png": residual_per_pose_figure(diagnosis),
    }
    paths = [folder / name for name in figures]
    for path in paths:  # all or none: check before writing the first
        if path.exists() and not force:
            raise OutputExistsError(f"{path}: file exists; refusing to overwrite it (pass --force)")
    return [
        save_figure_atomic(fig, path, force=force, dpi=110)
        for path, fig in zip(paths, figures.values(), strict=True)
    ]
