"""A bare matplotlib figure on the Agg canvas: no pyplot, no global state, no backend change.

Every figure of :mod:`cdra_jax.plots` starts here, so that importing or calling the plots from a
script, a notebook or the command line never touches matplotlib's global figure manager (a
notebook displays the returned :class:`~matplotlib.figure.Figure` as PNG).
"""

from __future__ import annotations

from typing import Literal

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure


def new_figure(
    width: float,
    height: float,
    *,
    layout: Literal["constrained", "compressed", "tight"] | None = "constrained",
) -> Figure:
    """A ``width`` x ``height`` inch figure with an Agg canvas attached (``layout`` as for
    :class:`~matplotlib.figure.Figure`; ``None`` for a fixed layout, which draws faster)."""
    fig = Figure(figsize=(width, height), layout=layout)
    FigureCanvasAgg(fig)
    return fig
