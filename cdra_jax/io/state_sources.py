"""How a module's state is given in a measurement file: one *state source* per set of columns.

Each module of the arm gets its state from exactly one source, chosen by the columns the file
has for it (``<module>.<suffix>``):

* :class:`JointCoordinates`: ``<module>.rx .ry .rz`` (spherical: rotation vector of the platform
  in the module base frame, rad) or ``<module>.q`` (revolute: rad; prismatic: mm). Used as is.
* :class:`CableLengths`: ``<module>.l1 ... <module>.lN`` (mm), turned into the module state by
  the module's cable forward kinematics (:mod:`cdra_jax.modules.cable_data`: Gauss-Newton over
  the redundant cables). Negative, non-finite or inconsistent lengths (RMS misfit above the
  documented tolerance) are errors naming the row and column.

Adding a source (or finishing :class:`CableLengths`) touches only this file: subclass
:class:`StateSource`, implement :meth:`~StateSource.claims`, :meth:`~StateSource.columns` and
:meth:`~StateSource.to_state`, and list it in :data:`STATE_SOURCES`. ``to_state`` receives the
values of its columns for every row and a :class:`~cdra_jax.io.rows.RowContext` whose
``error(what, column=..., row=...)`` builds the error to raise, naming the file, the line (the
row's, or the header's when ``row`` is ``None``) and the column.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from ..arm import Module
from .rows import RowContext

_JOINT_SUFFIXES = {"spherical": ("rx", "ry", "rz"), "revolute": ("q",), "prismatic": ("q",)}
_CABLE_SUFFIX = re.compile(r"l([1-9][0-9]*)")


class StateSource:
    """A way of giving one module's state in a measurement file (a family of columns)."""

    description: ClassVar[str] = "state"

    def claims(self, module: Module, suffix: str) -> bool:
        """Whether the column ``<module>.<suffix>`` belongs to this source."""
        raise NotImplementedError

    def columns(self, module: Module, present: Sequence[str], ctx: RowContext) -> tuple[str, ...]:
        """The ordered suffixes this source reads for ``module``, given the claimed ``present``.

        Raises ``ctx.error(...)`` when a needed column is missing or one is out of range.
        """
        raise NotImplementedError

    def to_state(self, module: Module, values: np.ndarray, ctx: RowContext) -> np.ndarray:
        """Module states ``(m, module.dof)`` from the column values ``(m, len(columns))``."""
        raise NotImplementedError

    def expected_text(self, module: Module) -> str:
        """How to write this source's columns for ``module`` (for error messages)."""
        raise NotImplementedError


class JointCoordinates(StateSource):
    """``<module>.rx .ry .rz`` (spherical, rad) or ``<module>.q`` (revolute rad, prismatic mm)."""

    description = "joint coordinates"

    def claims(self, module: Module, suffix: str) -> bool:
        return suffix in _JOINT_SUFFIXES[module.kind]

    def columns(self, module: Module, present: Sequence[str], ctx: RowContext) -> tuple[str, ...]:
        need = _JOINT_SUFFIXES[module.kind]
        missing = [s for s in need if s not in present]
        if missing:
            raise ctx.error(
                f"missing column {module.name}.{missing[0]}: module {module.name!r} "
                f"({module.kind}) needs {self.expected_text(module)}",
                column=f"{module.name}.{missing[0]}",
            )
        return need

    def to_state(self, module: Module, values: np.ndarray, ctx: RowContext) -> np.ndarray:
        return np.asarray(values, dtype=float)

    def expected_text(self, module: Module) -> str:
        return ", ".join(f"{module.name}.{s}" for s in _JOINT_SUFFIXES[module.kind])


class CableLengths(StateSource):
    """``<module>.l1 ... <module>.lN`` (mm): cable lengths, through the module's forward kinematics.

    The columns must be contiguous ``l1 .. lN`` with ``N`` the module's cable count in the model.
    The file's lengths are kept as given; the state is their least-squares forward kinematics.
    """

    description = "cable lengths"

    def claims(self, module: Module, suffix: str) -> bool:
        return _CABLE_SUFFIX.fullmatch(suffix) is not None

    def columns(self, module: Module, present: Sequence[str], ctx: RowContext) -> tuple[str, ...]:
        idx = sorted(int(_CABLE_SUFFIX.fullmatch(s).group(1)) for s in present)  # type: ignore[union-attr]
        n = module.n_cables or idx[-1]
        extra = [i for i in idx if i > n]
        if extra:
            raise ctx.error(
                f"module {module.name!r} has {n} cables in the model, so {module.name}.l{extra[0]} "
                "does not exist",
                column=f"{module.name}.l{extra[0]}",
            )
        missing = [i for i in range(1, n + 1) if i not in idx]
        if missing:
            raise ctx.error(
                f"missing column {module.name}.l{missing[0]}: cable lengths of module "
                f"{module.name!r} need {module.name}.l1 ... {module.name}.l{n}",
                column=f"{module.name}.l{missing[0]}",
            )
        return tuple(f"l{i}" for i in range(1, n + 1))

    def to_state(self, module: Module, values: np.ndarray, ctx: RowContext) -> np.ndarray:
        from ..modules.cable_data import check_cable_lengths

        if module.n_cables == 0:
            raise ctx.error(
                f"module {module.name!r} has no cables in the model, so its state cannot be "
                f"computed from cable lengths; give {JointCoordinates().expected_text(module)}",
                column=f"{module.name}.l1",
            )
        states, _, problems = check_cable_lengths(module, values)
        if problems:
            p = problems[0]
            n = values.shape[-1]
            col = (
                f"{module.name}.l1 ... {module.name}.l{n}"
                if p.column is None
                else f"{module.name}.l{p.column + 1}"
            )
            more = f" ({len(problems) - 1} more bad rows)" if len(problems) > 1 else ""
            raise ctx.error(p.message + more, column=col, row=None if p.row < 0 else p.row)
        return states

    def expected_text(self, module: Module) -> str:
        n = module.n_cables
        return f"{module.name}.l1 ... {module.name}.l{n if n else 'N'}"


STATE_SOURCES: tuple[StateSource, ...] = (JointCoordinates(), CableLengths())
"""The sources the reader tries, in order; each module's columns must all belong to one."""
