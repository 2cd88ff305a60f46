"""Candidate non-geometric effects: small, differentiable extensions of the forward model.

:mod:`.base` holds the extended forward model (:class:`Features`, :func:`corrected_tool_pose`,
:class:`Candidate`), :mod:`.effects` the vocabulary of design.md, :mod:`.loads` the gravity
loads on the links, :mod:`.probes` the generic location probes used by the diagnosis.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from ..arm import Arm
from .base import Aux as Aux
from .base import Candidate as Candidate
from .base import Effect as Effect
from .base import Features as Features
from .base import ParameterSpec as ParameterSpec
from .base import corrected_tool_pose as corrected_tool_pose
from .effects import EFFECT_NAMES as EFFECT_NAMES
from .effects import VOCABULARY as VOCABULARY
from .effects import Backlash as Backlash
from .effects import CableElasticity as CableElasticity
from .effects import CableScale as CableScale
from .effects import JointCompliance as JointCompliance
from .effects import LinkBending as LinkBending
from .effects import PeriodicError as PeriodicError
from .effects import ThermalDrift as ThermalDrift
from .effects import effect as effect
from .loads import bending_deflection as bending_deflection
from .loads import link_tip_loads as link_tip_loads
from .probes import PROBES as PROBES


def candidates(
    arm: Arm, aux_names: Iterable[str], effects: Sequence[Effect] = VOCABULARY
) -> list[tuple[Candidate, str | None]]:
    """Every (effect, location) pair of ``effects`` for ``arm``, with the reason it must be
    skipped for data with the auxiliary columns ``aux_names`` (``None``: it can be evaluated)."""
    names = frozenset(aux_names)
    out = []
    for e in effects:
        for loc in e.locations(arm):
            c = Candidate(e, loc)
            out.append((c, c.missing(arm, names)))
    return out
