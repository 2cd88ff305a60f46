"""Figures of one calibration: per-pose tool residuals of the nominal and calibrated models and
the convergence of Eqs. 20-21 over the iterations, drawn from a result mapping
(:func:`cdra_jax.io.result_to_dict`, the content of a result JSON file)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from .canvas import new_figure


def _values(rows: list[Mapping[str, Any]], key: str) -> np.ndarray:
    return np.array([np.nan if r.get(key) is None else float(r[key]) for r in rows])


def calibration_residuals_figure(result: Mapping[str, Any]) -> Figure:
    """Three panels from a calibration result mapping: (a) per-pose position residual
    ``|p_meas - p_model|`` (mm) of the nominal and the calibrated model, (b) the same for the
    rotation (rad, where measured), (c) ``delta_p`` and ``delta_R`` (Eqs. 20-21) per iteration.
    Poses flagged as outliers are marked with a red ring."""
    rows = list(result["residuals"])
    x = np.arange(len(rows))
    kinds = [("position", "mm")]
    if any(r.get("calibrated_rotation_rad") is not None for r in rows):
        kinds.append(("rotation", "rad"))  # points only: no rotation panel
    n = len(kinds) + 1
    fig = new_figure(4.35 * n, 3.8)
    axes = [fig.add_subplot(1, n, i + 1) for i in range(n)]
    for ax, (what, unit) in zip(axes, kinds, strict=False):
        before = _values(rows, f"nominal_{what}_{unit}")
        after = _values(rows, f"calibrated_{what}_{unit}")
        ax.semilogy(x, np.maximum(before, 1e-300), "o", ms=4, color="0.55", label="nominal")
        ax.semilogy(x, np.maximum(after, 1e-300), "o", ms=4, color="C0", label="calibrated")
        flagged = np.array([bool(r.get("outlier")) for r in rows])
        if flagged.any():
            ax.semilogy(
                x[flagged],
                np.maximum(after[flagged], 1e-300),
                "o",
                ms=9,
                mfc="none",
                color="C3",
                label="outlier",
            )
        ax.set_xlabel("pose (file order)")
        ax.set_ylabel(f"{what} residual [{unit}]")
        ax.set_title(f"({'ab'[what == 'rotation']}) {what} residual per pose")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize="small")
    its = [result["initial"], *result["iterations"]]
    k = np.arange(len(its))
    ax = axes[-1]
    dp = _values(its, "delta_p_mm")
    dR = _values(its, "delta_R_rad")
    ax.semilogy(k, np.maximum(dp, 1e-300), "o-", color="C0", label="$\\delta p$ [mm] (Eq. 20)")
    if np.any(np.isfinite(dR)):
        ax.semilogy(
            k, np.maximum(dR, 1e-300), "s--", color="C1", label="$\\delta R$ [rad] (Eq. 21)"
        )
    ax.set_xlabel("iteration")
    ax.set_title(f"({'abc'[n - 1]}) deviation of the fitted poses")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")
    return fig
