"""The export workflow: a (calibrated) model written back into its URDF.

:func:`export_urdf` loads the original URDF with yourdfpy, puts the model's fixed frames into
the joint origins of the chain from ``base`` to ``tip`` (:func:`cdra_jax.io.urdf.
apply_arm_to_urdf`: in each segment between movable joints the last joint carries the frame,
the other fixed joints keep theirs) and writes the file with yourdfpy, everything else kept.
The exported file is read back and its chain compared with the model (``check``). What a URDF
cannot hold (cables, masses, cable properties, a non-default gravity, markers, effects) is
listed in :attr:`ExportedURDF.not_held`, printed on stderr by the command line and written as an
XML comment at the top of the file.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..arm import Arm
from ..io.files import write_text_atomic
from ..io.model import load_model
from ..io.results import package_version
from ..io.urdf import apply_arm_to_urdf, chain_arm, not_held, read_urdf, urdf_text
from .import_model import plot_chain

if TYPE_CHECKING:
    from matplotlib.figure import Figure


@dataclasses.dataclass(frozen=True, eq=False)
class ExportedURDF:
    """A URDF with a model's (calibrated) chain.

    Attributes:
        text: the URDF XML text.
        arm: the model written.
        model_label, urdf: where the model and the original URDF came from.
        base, tip: the chain's links; ``tool_link`` is ``tip`` or the link added to carry the
            tool frame (``<tip>_calibrated``).
        changes: what was changed or added in the URDF, one line each.
        not_held: what of the model the URDF cannot hold, one line each.
        lost: elements of the original that the written file lacks (e.g. XML comments).
        check_mm, check_rad: largest difference between the model's fixed frames and those of
            the exported file read back (translation mm, rotation-matrix entries).
    """

    text: str
    arm: Arm
    model_label: str
    urdf: str
    base: str
    tip: str
    tool_link: str
    changes: tuple[str, ...]
    not_held: tuple[str, ...]
    lost: tuple[str, ...]
    check_mm: float
    check_rad: float

    def save(self, path: str | os.PathLike, *, force: bool = False) -> Path:
        """Write the URDF atomically (an existing file only with ``force``)."""
        return write_text_atomic(path, self.text, force=force)

    def to_dict(self) -> dict[str, Any]:
        """What was exported and what was not."""
        return {
            "model": self.model_label,
            "urdf": self.urdf,
            "base": self.base,
            "tip": self.tip,
            "tool_link": self.tool_link,
            "changes": list(self.changes),
            "not_held": list(self.not_held),
            "lost": list(self.lost),
            "check_mm": self.check_mm,
            "check_rad": self.check_rad,
        }

    def warnings(self) -> list[str]:
        """One line per thing of the model or the original file that the output lacks."""
        out = [f"the URDF cannot hold {w}; it is not exported" for w in self.not_held]
        out += [f"{w} of {self.urdf} not kept by the URDF writer" for w in self.lost]
        return out

    def report(self) -> str:
        """The summary ``cdra-jax export urdf`` prints."""
        lines = [
            f"exported model {self.model_label} into {self.urdf}: chain {self.base} -> "
            f"{self.tool_link}, {len(self.arm.modules)} movable joints",
            *(f"  {c}" for c in self.changes),
            f"read back: the file's chain equals the model's frames to {self.check_mm:.2g} mm, "
            f"{self.check_rad:.2g} rad",
        ]
        if not self.changes:
            lines.insert(1, "  no joint origin changed (the model equals the URDF's chain)")
        return "\n".join(lines)

    def plot(self) -> Figure:
        """The exported chain's joint positions at ``q = 0`` in 3D (mm)."""
        return plot_chain(self.arm, f"{self.arm.name} exported to {Path(self.urdf).name}")


def export_urdf(
    model: Arm | str | os.PathLike,
    urdf: str | os.PathLike,
    base: str,
    tip: str,
    *,
    model_label: str | None = None,
) -> ExportedURDF:
    """The URDF file ``urdf`` with the chain ``base`` -> ``tip`` carrying ``model``'s frames.

    Args:
        model: the (calibrated) model, an :class:`~cdra_jax.arm.Arm` or a model TOML path; its
            modules must be the chain's movable joints (names, order, kinds), as a model from
            :func:`~cdra_jax.workflows.import_urdf` of the same chain is.
        urdf: the original URDF file.
        base, tip: the chain's links.
        model_label: name of the model in the report (default: the path or the arm's name).

    Raises:
        UrdfFileError: (a ``ValueError``) the URDF is malformed, has no such chain, or the chain
            does not match the model.
    """
    if isinstance(model, Arm):
        arm, label = model, model_label or model.name
    else:
        arm, label = load_model(model), model_label or str(model)
    source = str(urdf)
    original = Path(urdf).read_bytes()
    doc = read_urdf(original, label=source)
    changes = apply_arm_to_urdf(doc, arm, base, tip, source)
    held_not = not_held(arm)
    tool_link = tip
    if any(c.startswith("added fixed joint") for c in changes):
        tool_link = f"{tip}_calibrated"
    comment = [
        f"cdra-jax {package_version()} export: the chain {base} -> {tool_link} carries the "
        f"fixed frames of model {label}",
        "(joint origins in metres and radians; each segment's last joint carries the frame)",
        *(f"not held by a URDF, not exported: {w}" for w in held_not),
    ]
    text, lost = urdf_text(doc, original, comment)
    back = chain_arm(
        read_urdf(text.encode("utf-8"), label=f"{source} (exported)"), base, tool_link, source
    )
    F_back = np.asarray(back.arm.frames, dtype=float)
    F = np.asarray(arm.frames, dtype=float)
    check_mm = float(np.max(np.abs(F_back[:, :3, 3] - F[:, :3, 3])))
    check_rad = float(np.max(np.abs(F_back[:, :3, :3] - F[:, :3, :3])))
    return ExportedURDF(
        text=text,
        arm=arm,
        model_label=label,
        urdf=source,
        base=base,
        tip=tip,
        tool_link=tool_link,
        changes=tuple(changes),
        not_held=tuple(held_not),
        lost=tuple(lost),
        check_mm=check_mm,
        check_rad=check_rad,
    )
