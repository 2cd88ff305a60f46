"""Figures of noise-sensitivity sweeps (:mod:`cdra_jax.sweeps`): medians with 10-90 % bands.

Drawn on bare figures (:mod:`.canvas`): no pyplot, no global state.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from ..io.files import save_figure_atomic
from ..sweeps import METRIC_UNITS, SweepTable
from .canvas import new_figure

_LINESTYLES = {"paper": "-", "weighted": "--", "lm": ":"}


def _label(noise_pos: float, noise_rot: float, solver: str) -> str:
    if noise_pos == 0 and noise_rot == 0:
        return f"noise-free, {solver}"
    return f"{1000 * noise_pos:g} um / {noise_rot:g} rad, {solver}"


def plot_sweep(
    table: SweepTable,
    metric: str = "dp_heldout",
    *,
    ax=None,
    band: tuple[float, float] = (0.1, 0.9),
    converged_only: bool = False,
    logy: bool = True,
):
    """Median of ``metric`` against the pose count ``m``, one line per (noise level, solver),
    with a shaded ``band`` (default 10-90 %) of the trials.

    Args:
        table: sweep results.
        metric: a metric column (``dp_heldout``, ``dR_heldout``, ``dp_fit``, ``param_err``...).
        ax: matplotlib axes (default: a new figure).
        band: lower and upper quantile of the band.
        converged_only: leave out trials that did not converge.
        logy: logarithmic y axis.

    Returns:
        The axes.
    """
    if ax is None:
        ax = new_figure(6, 4).add_subplot()
    lo, hi = band
    rows = table.summary(metric, (lo, 0.5, hi), converged_only=converged_only)
    colours: dict[tuple[float, float], str] = {}
    cycle = [f"C{i}" for i in range(10)]
    for sp, sr, solver in table.groups():
        mine = [
            r for r in rows if (r["noise_pos"], r["noise_rot"], r["solver"]) == (sp, sr, solver)
        ]
        if not mine:
            continue
        colour = colours.setdefault((sp, sr), cycle[len(colours) % len(cycle)])
        m = np.array([r["m"] for r in mine])
        med = np.array([r["q50"] for r in mine])
        ax.plot(
            m,
            med,
            marker="o",
            ms=3,
            color=colour,
            ls=_LINESTYLES.get(solver, "-."),
            label=_label(sp, sr, solver),
        )
        ax.fill_between(
            m,
            [r[f"q{100 * lo:g}"] for r in mine],
            [r[f"q{100 * hi:g}"] for r in mine],
            color=colour,
            alpha=0.15,
            lw=0,
        )
    ax.set_xlabel("calibration poses m")
    ax.set_ylabel(f"{metric} ({METRIC_UNITS.get(metric, '')})")
    if logy:
        ax.set_yscale("log")
    ax.set_title(f"{metric}: median and {100 * lo:g}-{100 * hi:g} % of trials")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")
    return ax


def plot_sweep_figure(
    table: SweepTable,
    metrics: Sequence[str] = ("dp_heldout", "dR_heldout"),
    path: str | os.PathLike | None = None,
    *,
    force: bool = False,
    **kwargs,
):
    """One panel per metric (:func:`plot_sweep`); saved to ``path`` when given.

    The file is written atomically and an existing one is only replaced with ``force``
    (:func:`cdra_jax.io.files.save_figure_atomic`).

    Returns:
        The figure.
    """
    fig = new_figure(6 * len(metrics), 4.2)
    for i, metric in enumerate(metrics):
        plot_sweep(table, metric, ax=fig.add_subplot(1, len(metrics), i + 1), **kwargs)
    if path is not None:
        save_figure_atomic(fig, path, force=force, dpi=120)
    return fig
