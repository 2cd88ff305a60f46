"""Figures of the paper's evidence (Figs. 5 and 7) from the data objects of :mod:`.reproduction`.

Every function takes a study object and returns a :class:`matplotlib.figure.Figure` drawn on
the Agg canvas; saving (``cdra_jax.io.save_figure_atomic(fig, path)``, atomic and no overwrite
without ``force``) or showing it is the caller's job. Nothing here
touches pyplot or matplotlib's global state, so importing this module changes no backend and
opens no window.
"""

from __future__ import annotations

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from ..reproduction import PAPER_FLAT_POSES, ConvergenceStudy, NoiseStudy
from .canvas import new_figure

SOLVER_STYLE: dict[str, dict] = {
    "paper": {"color": "C0", "label": "paper solver (unweighted, Eq. 10)"},
    "weighted": {"color": "C3", "label": "weighted solver (noise-whitened)"},
}
"""Colour and legend label of each solver."""


def _figure(
    ncols: int, width: float = 11.0, height: float = 4.8, bottom: float = 0.12
) -> tuple[Figure, list[Axes]]:
    # A fixed layout (no constrained/tight layout: it doubles the drawing time).
    fig = new_figure(width, height, layout=None)
    fig.subplots_adjust(left=0.07, right=0.98, top=0.86, bottom=bottom, wspace=0.22)
    axes = [fig.add_subplot(1, ncols, i + 1) for i in range(ncols)]
    return fig, axes


def _positive(x: np.ndarray, floor: float = 1e-300) -> np.ndarray:
    """Clip to a positive floor so that exact zeros survive a log axis."""
    return np.maximum(np.asarray(x, dtype=float), floor)


def convergence_figure(study: ConvergenceStudy, traces: int = 20) -> Figure:
    """Fig. 5: dp (a) and dR (b) per iteration, median and 10-90 % band, log scale.

    Args:
        study: from :func:`~cdra_jax.reproduction.convergence_study`.
        traces: number of individual trials drawn as thin grey lines.
    """
    fig, axes = _figure(2)
    k = np.arange(study.delta_p.shape[-1])
    panels = (
        ("delta_p", "(a) position deviation $\\delta p$ (Eq. 20)", "$\\delta p$ [mm]"),
        ("delta_R", "(b) orientation deviation $\\delta R$ (Eq. 21)", "$\\delta R$ [rad]"),
    )
    for ax, (metric, title, ylabel) in zip(axes, panels, strict=True):
        data = getattr(study, metric)
        for row in data[: max(0, traces)]:
            ax.plot(k, _positive(row), color="0.75", lw=0.6, zorder=1)
        med, lo, hi = study.band(metric)
        ax.fill_between(
            k,
            _positive(lo),
            _positive(hi),
            color="C0",
            alpha=0.3,
            lw=0,
            label="10-90 % of trials",
            zorder=2,
        )
        ax.plot(k, _positive(med), "o-", color="C0", label="median", zorder=3)
        ax.axhline(study.tol, color="k", ls=":", lw=1, label=f"{study.tol:g}")
        ax.set_yscale("log")
        ax.set_xlabel("iteration")
        ax.set_ylabel(ylabel)
        ax.set_title(title, fontsize=10)
        ax.set_xticks(k)
        ax.grid(True, which="major", alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    fig.suptitle(
        f"Fig. 5: convergence of the paper solver, {study.trials} random error draws "
        f"($d_v$ = {study.d_v:g} mm, $d_\\omega$ = {study.d_w:g} rad), m = {study.m} "
        "noise-free poses",
        fontsize=10,
    )
    return fig


def _bands(ax: Axes, study: NoiseStudy, metric: str, true_metric: str | None = None) -> None:
    m = study.m_values
    for solver in study.solvers:
        style = SOLVER_STYLE.get(solver, {"color": None, "label": solver})
        med, lo, hi = study.band(solver, metric)
        ax.fill_between(m, _positive(lo), _positive(hi), color=style["color"], alpha=0.2, lw=0)
        ax.plot(m, _positive(med), "o-", ms=3, color=style["color"], label=style["label"])
        if true_metric is not None:
            med_t, _, _ = study.band(solver, true_metric)
            ax.plot(
                m,
                _positive(med_t),
                "--",
                color=style["color"],
                lw=1,
                label=f"{solver}: vs actual poses",
            )
    ax.axvline(PAPER_FLAT_POSES, color="0.4", ls=":", lw=1)
    ax.set_yscale("log")
    ax.set_xlabel("number of calibration poses m")
    ax.grid(True, which="major", alpha=0.3)


def noise_figure(study: NoiseStudy, within: float = 0.10) -> Figure:
    """Fig. 7: held-out dp (a) and dR (b) against the pose count, both solvers.

    Solid lines and bands: median and 10-90 % of Eqs. 20-21 against the noisy held-out
    measurements (the paper's experimental metric); dashed: median against the actual poses;
    dotted horizontal: the noise floor ``sqrt(3) sigma``; dotted vertical: the paper's 15
    poses; triangles: where each solid median flattens (within ``within`` of its last value).
    """
    fig, axes = _figure(2, bottom=0.22)
    floors = study.noise_floor
    panels = (
        ("dp_measured", "dp_true", "(a) held-out $\\delta p$ (Eq. 20)", "$\\delta p$ [mm]"),
        ("dR_measured", "dR_true", "(b) held-out $\\delta R$ (Eq. 21)", "$\\delta R$ [rad]"),
    )
    for ax, floor, (metric, true_metric, title, ylabel) in zip(axes, floors, panels, strict=True):
        _bands(ax, study, metric, true_metric)
        ax.axhline(floor, color="k", ls=":", lw=1, label="noise floor $\\sqrt{3}\\sigma$")
        for solver in study.solvers:
            m_flat = study.flattening(solver, metric, within)
            med, _, _ = study.band(solver, metric)
            y = med[list(study.m_values).index(m_flat)]
            ax.plot(
                [m_flat],
                [y],
                "v",
                ms=9,
                color=SOLVER_STYLE.get(solver, {}).get("color"),
                markeredgecolor="k",
            )
        ax.set_ylabel(ylabel)
        ax.set_title(title, fontsize=10)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=8, frameon=False)
    fig.suptitle(
        f"Fig. 7: held-out accuracy vs number of poses, {study.trials} trials per m, "
        f"$\\sigma_p$ = {float(study.noise.position_mm):g} mm, "
        f"$\\sigma_R$ = {float(study.noise.rotation_rad):.2g} rad "
        f"(dotted vertical: the paper's {PAPER_FLAT_POSES} poses)",
        fontsize=10,
    )
    return fig


def parameter_error_figure(study: NoiseStudy) -> Figure:
    """Error of the identified frames in the identifiable subspace against the pose count.

    (a) the translational components (mm), (b) the rotational ones (rad) of the projected group
    difference ``log(F^c (F^a)^-1)`` (see :class:`~cdra_jax.reproduction.NoiseStudy`); median and
    10-90 % band for both solvers.
    """
    fig, axes = _figure(2, bottom=0.2)
    panels = (
        ("param_v", "(a) translation part of the frame errors", "error [mm]"),
        ("param_w", "(b) rotation part of the frame errors", "error [rad]"),
    )
    for ax, (metric, title, ylabel) in zip(axes, panels, strict=True):
        _bands(ax, study, metric)
        ax.set_ylabel(ylabel)
        ax.set_title(title, fontsize=10)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=2, fontsize=8, frameon=False)
    fig.suptitle(
        "Frame-error estimation error in the identifiable subspace (null-space part removed), "
        f"{study.trials} trials per m",
        fontsize=10,
    )
    return fig
