"""The import workflow: a model file from a URDF chain or a DH table.

:func:`import_urdf` reads the serial chain between two links of a URDF file
(:mod:`cdra_jax.io.urdf`: yourdfpy, no meshes); :func:`import_dh` reads a Denavit-Hartenberg
table CSV (:mod:`cdra_jax.io.dh`, standard or modified convention). Both return an
:class:`ImportedModel` whose ``save`` writes the model TOML (the model file contract: frames in
mm and rad, modules named after the joints). The model's tool pose ``tool_pose(arm, q)``, ``q``
in the joints' order (rad, mm), equals the URDF's tip link pose in the base link frame (in mm),
or the DH chain's last frame.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..arm import Arm, forward_kinematics
from ..io.dh import CONVENTIONS, arm_from_dh, load_dh
from ..io.files import write_text_atomic
from ..io.model import arm_to_dict, dumps_model
from ..io.urdf import load_urdf_chain
from .result import JsonResult

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def chain_points(arm: Arm) -> np.ndarray:
    """World positions (mm) of the chain at ``q = 0``: the base origin, each module's origin and
    the tool frame origin, ``(K+2, 3)``."""
    tool, after = forward_kinematics(arm, np.zeros(arm.dof))
    pts = [np.zeros(3), *np.asarray(after)[:, :3, 3], np.asarray(tool)[:3, 3]]
    return np.stack(pts)


def plot_chain(arm: Arm, title: str = "") -> Figure:
    """A 3D sketch of the chain at ``q = 0``: joint (module) origins joined by lines, mm."""
    from ..plots import new_figure

    fig = new_figure(5.5, 5.0)
    ax: Any = fig.add_subplot(projection="3d")
    pts = chain_points(arm)
    ax.plot(pts[:, 0], pts[:, 1], pts[:, 2], "-", color="0.5")
    ax.scatter(*pts[0], color="k", marker="s", label="base")
    ax.scatter(pts[1:-1, 0], pts[1:-1, 1], pts[1:-1, 2], color="C0", label="joints")
    ax.scatter(*pts[-1], color="C3", marker="^", label="tool")
    for m, p in zip(arm.modules, pts[1:-1], strict=True):
        ax.text(p[0], p[1], p[2], f" {m.name}", fontsize="x-small")
    span = max(float(np.ptp(pts, axis=0).max()), 1.0)
    mid = (pts.max(0) + pts.min(0)) / 2
    ax.set_xlim(mid[0] - span / 2, mid[0] + span / 2)
    ax.set_ylim(mid[1] - span / 2, mid[1] + span / 2)
    ax.set_zlim(mid[2] - span / 2, mid[2] + span / 2)
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_zlabel("z [mm]")
    ax.set_title(title or f"{arm.name} at q = 0", fontsize="small")
    ax.legend(fontsize="small")
    return fig


@dataclasses.dataclass(frozen=True, eq=False)
class ImportedModel(JsonResult):
    """A model read from a URDF chain or a DH table.

    Attributes:
        arm: the model (frames ``(K+1, 4, 4)`` mm; modules named as the joints).
        source: the file read.
        format: ``"urdf"`` or ``"dh"``.
        details: how: ``base``, ``tip``, ``joints`` (every joint of the chain, fixed ones
            included), ``joint_types`` (URDF); ``convention`` (DH).
    """

    arm: Arm
    source: str
    format: str
    details: dict[str, Any]

    def header(self) -> list[str]:
        """Comment lines at the top of the model file (where it came from)."""
        if self.format == "urdf":
            how = f"URDF {self.source}, chain {self.details['base']} -> {self.details['tip']}"
        else:
            how = f"DH table {self.source} ({self.details['convention']} convention)"
        return [f"model imported by cdra-jax import {self.format} from {how}", "units: mm, rad"]

    def to_toml(self) -> str:
        """The model TOML text (:func:`cdra_jax.io.dumps_model`, after the header comments)."""
        return "".join(f"# {c}\n" for c in self.header()) + dumps_model(self.arm)

    def save(self, path: str | os.PathLike, *, force: bool = False) -> Path:
        """Write the model TOML atomically (an existing file only with ``force``)."""
        return write_text_atomic(path, self.to_toml(), force=force)

    def to_dict(self) -> dict[str, Any]:
        """Provenance and the model (as :func:`cdra_jax.io.arm_to_dict`)."""
        return {
            "format": self.format,
            "source": self.source,
            **self.details,
            "model": arm_to_dict(self.arm),
        }

    def report(self) -> str:
        """The summary ``cdra-jax import`` prints."""
        arm = self.arm
        kinds = ", ".join(f"{m.name} ({m.kind})" for m in arm.modules)
        tool = chain_points(arm)[-1]
        lines = [self.header()[0]]
        if self.format == "urdf":
            fixed = len(self.details["joints"]) - len(arm.modules)
            lines.append(f"{len(arm.modules)} modules: {kinds}; {fixed} fixed joints folded")
        else:
            lines.append(f"{len(arm.modules)} modules: {kinds}")
        lines.append(f"{len(arm.frame_names)} fixed frames: {', '.join(arm.frame_names)}")
        lines.append("tool frame origin at q = 0: [" + ", ".join(f"{v:.4f}" for v in tool) + "] mm")
        return "\n".join(lines)

    def plot(self) -> Figure:
        """The chain's joint positions at ``q = 0`` in 3D (mm)."""
        return plot_chain(self.arm)


def import_urdf(
    path: str | os.PathLike, base: str, tip: str, *, name: str | None = None
) -> ImportedModel:
    """The serial chain from link ``base`` to link ``tip`` of a URDF file as a model.

    Fixed joints fold into the fixed frames; revolute, continuous and prismatic joints become
    modules named as the joints (see :mod:`cdra_jax.io.urdf`). ``name`` names the model
    (default: the URDF's robot name). Raises :class:`~cdra_jax.io.urdf.UrdfFileError` (a
    ``ValueError`` naming the file and element) for an unknown link, no chain, a floating,
    planar or mimic joint in the chain, or a malformed file.
    """
    chain = load_urdf_chain(path, base, tip, name)
    return ImportedModel(
        arm=chain.arm,
        source=str(path),
        format="urdf",
        details={
            "base": base,
            "tip": tip,
            "joints": list(chain.joints),
            "joint_types": list(chain.joint_types),
        },
    )


def import_dh(
    path: str | os.PathLike, convention: str, *, name: str | None = None
) -> ImportedModel:
    """A DH table CSV (:mod:`cdra_jax.io.dh`) as a model; ``convention`` is ``"standard"``
    (Denavit-Hartenberg) or ``"modified"`` (Craig). ``name`` names the model (default: the
    file's stem)."""
    if convention not in CONVENTIONS:
        raise ValueError(f"convention must be one of {', '.join(CONVENTIONS)}, got {convention!r}")
    rows = load_dh(path)
    arm = arm_from_dh(
        rows,
        convention,
        name=name or Path(path).stem or "dh_arm",
        description=f"imported from DH table {Path(path).name} ({convention} convention)",
    )
    return ImportedModel(arm=arm, source=str(path), format="dh", details={"convention": convention})
