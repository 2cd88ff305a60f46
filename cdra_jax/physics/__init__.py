"""Candidate non-geometric effects: small, differentiable extensions of the forward model.

:mod:`.base` holds the extended forward model (:class:`Features`, :func:`corrected_tool_pose`,
:class:`Candidate`), :mod:`.effects` the vocabulary of design.md, :mod:`.loads` the gravity
loads on the links, :mod:`.probes` the generic location probes used by the diagnosis,
:mod:`.model` the model file's own ``[[effects]]`` (checked, predicted with), :mod:`.refit`
the joint calibration of frames and effect parameters.
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
from .effects import DrumPeriodicError as DrumPeriodicError
from .effects import JointCompliance as JointCompliance
from .effects import LinkBending as LinkBending
from .effects import PeriodicError as PeriodicError
from .effects import ThermalDrift as ThermalDrift
from .effects import effect as effect
from .loads import bending_deflection as bending_deflection
from .loads import link_tip_loads as link_tip_loads
from .model import check_effect_data as check_effect_data
from .model import effect_candidate as effect_candidate
from .model import effect_param_names as effect_param_names
from .model import effect_param_units as effect_param_units
from .model import effect_records as effect_records
from .model import missing_effect_data as missing_effect_data
from .model import model_effects as model_effects
from .model import model_features as model_features
from .model import model_tool_pose as model_tool_pose
from .model import needed_aux as needed_aux
from .model import with_effect_values as with_effect_values
from .model import with_effects as with_effects
from .probes import PROBES as PROBES
from .probes import TimeProbe as TimeProbe
from .refit import EffectRefit as EffectRefit
from .refit import RefitData as RefitData
from .refit import data_residual as data_residual
from .refit import extended_residual as extended_residual
from .refit import extended_tool_pose as extended_tool_pose
from .refit import prediction_error_table as prediction_error_table
from .refit import refine as refine


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
