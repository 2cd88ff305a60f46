"""Figure of a validation: per-row prediction errors of held-out poses, from a validation
mapping (:meth:`cdra_jax.workflows.ValidationRun.to_dict`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from .canvas import new_figure


def validation_figure(validation: Mapping[str, Any], reference: str = "nominal") -> Figure:
    """Per-row position error (mm) and, where measured, rotation error (rad) of the validated
    model, with a reference model's errors beside when the validation holds them (``reference``:
    ``"nominal"`` or ``"compare"``, the prefix of its per-row columns)."""
    rows = list(validation["rows"])
    x = np.arange(len(rows))
    has_rot = bool((validation.get("rotation_error_rad") or {}).get("n"))
    fig = new_figure(6.5 * (1 + has_rot), 3.8)
    panels = [("position_mm", "position error [mm]")]
    if has_rot:
        panels.append(("rotation_rad", "rotation error [rad]"))
    for i, (key, label) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), i + 1)
        for prefix, style, name in ((f"{reference}_", "o", reference), ("", "o", "model")):
            vals = [r.get(prefix + key) for r in rows]
            if all(v is None for v in vals):
                continue
            y = np.array([np.nan if v is None else float(v) for v in vals])
            ax.semilogy(
                x, np.maximum(y, 1e-300), style, ms=4, color="0.55" if prefix else "C0", label=name
            )
        ax.set_xlabel("row (file order)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize="small")
    return fig
