"""The model's own physics: the ``[[effects]]`` of a model file as candidates and parameters.

A model (:class:`~cdra_jax.arm.Arm`) carries its non-geometric effects as plain records
(:class:`~cdra_jax.arm.EffectRecord`: effect name, location, variant, named parameters with
values and units). This module turns them into the vocabulary's effects (:mod:`.effects`) and
one parameter vector, and predicts with them:

* :func:`model_effects` ``(arm) -> (candidates, theta)``: the checked candidates and the
  parameter values in their feature-column order; unknown effects, variants, locations,
  parameter names and wrong units are errors that name the entry and list what exists;
* :func:`model_tool_pose` ``(arm, q, aux)``: the tool poses of the extended forward model
  (Eq. 1 with the effects' corrections, :func:`.base.corrected_tool_pose`); without effects,
  Eq. 1 exactly;
* :func:`effect_records` and :func:`with_effect_values`: records from fitted candidates and
  values (what a refit writes back into a model file);
* :func:`check_effect_data`: the auxiliary columns the effects need are in the data.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence

import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from ..arm import Arm, EffectRecord
from ..compilation import filter_jit
from .base import Aux, Candidate, Effect, Features, corrected_tool_pose, stacked_features
from .effects import VOCABULARY, DrumPeriodicError, PeriodicError, ThermalDrift


def _where(i: int, rec: EffectRecord, source: str | None) -> str:
    head = f"{source}: " if source else ""
    return f"{head}effects[{i}] ({rec.name}@{rec.location})"


_VARIANT_FORMS = {
    "periodic_error": "'k=<k>[,<k>...]' (harmonics of the joint angle) or "
    "'drum r=<radius>mm k=<k>[,<k>...]' (of the winch drum angle)",
    "thermal_drift": "'warm-up tau=<seconds>s'",
}
"""Variants beyond the vocabulary's own that a model file may name (other harmonics, drum
radii, warm-up time constants), in the spelling of the effect's ``variant``."""

_MADE: dict[tuple[str, str], Effect] = {}
"""Effects made for such variants, one object per (name, variant): candidates compare by the
identity of their effect, so the same variant must give the same object (one compilation)."""


def _variant_effect(name: str, variant: str) -> Effect | None:
    """The effect of a variant outside the vocabulary's list (see :data:`_VARIANT_FORMS`)."""
    if (name, variant) in _MADE:
        return _MADE[(name, variant)]
    harmonics = r"k=(\d+(?:,\d+)*)"
    number = r"([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)"
    effect: Effect | None = None
    try:
        if name == "periodic_error":
            if m := re.fullmatch(harmonics, variant):
                effect = PeriodicError(tuple(int(k) for k in m.group(1).split(",")))
            elif m := re.fullmatch(rf"drum r={number}mm {harmonics}", variant):
                ks = tuple(int(k) for k in m.group(2).split(","))
                effect = DrumPeriodicError(float(m.group(1)), ks)
        elif name == "thermal_drift" and (m := re.fullmatch(rf"warm-up tau={number}s", variant)):
            effect = ThermalDrift(float(m.group(1)))
    except ValueError:  # k = 0, a zero radius or time constant
        return None
    if effect is None or effect.variant != variant:  # only the canonical spelling
        return None
    _MADE[(name, variant)] = effect
    return effect


def effect_candidate(record: EffectRecord, arm: Arm, *, where: str = "effect") -> Candidate:
    """The vocabulary's candidate for one record (effect, variant and location checked).

    A variant outside the vocabulary's list may be named in the forms of
    :data:`_VARIANT_FORMS` (``periodic_error`` ``"k=1,2"``, ``"drum r=12mm k=1"``;
    ``thermal_drift`` ``"warm-up tau=300s"``)."""
    named = [e for e in VOCABULARY if e.name == record.name]
    if not named:
        known = ", ".join(dict.fromkeys(e.name for e in VOCABULARY))
        raise ValueError(f"{where}: unknown effect {record.name!r}; the vocabulary has: {known}")
    if record.variant:
        chosen = [e for e in named if e.variant == record.variant]
        made = None if chosen else _variant_effect(record.name, record.variant)
        if made is not None:
            chosen = [made]
        if not chosen:
            variants = ", ".join(repr(e.variant) for e in named if e.variant) or "none"
            forms = _VARIANT_FORMS.get(record.name)
            raise ValueError(
                f"{where}.variant: {record.name} has no variant {record.variant!r}; its "
                f"variants: {variants}" + (f"; or any {forms}" if forms else "")
            )
    else:
        chosen = named
    effect = chosen[0]
    locations = effect.locations(arm)
    if record.location not in locations:
        raise ValueError(
            f"{where}.location: {record.name} cannot sit at {record.location!r} of arm "
            f"{arm.name!r}; its locations: {', '.join(locations)}"
        )
    return Candidate(effect, record.location)


def model_effects(arm: Arm, source: str | None = None) -> tuple[tuple[Candidate, ...], np.ndarray]:
    """The model's effects as candidates and their parameter values ``theta (p,)``.

    Every parameter of each effect must be given, with the unit of its
    :class:`~.base.ParameterSpec`; ``theta`` follows the candidates' parameter order (the
    order of their feature columns), whatever the order in the file.

    Args:
        arm: the model.
        source: the model file, named in errors.

    Raises:
        ValueError: an unknown effect, variant, location or parameter, a missing parameter, or
            a unit that differs from the vocabulary's (the message names the entry and the key,
            and lists what exists).
    """
    cands: list[Candidate] = []
    theta: list[float] = []
    for i, rec in enumerate(arm.effects):
        where = _where(i, rec, source)
        c = effect_candidate(rec, arm, where=where)
        specs = c.parameters(arm)
        given = {n: (v, u) for n, v, u in rec.parameters}
        expected = {s.name: s.unit for s in specs}
        unknown = [n for n in given if n not in expected]
        missing = [n for n in expected if n not in given]
        if unknown or missing:
            listing = ", ".join(f"{n} [{u}]" for n, u in expected.items())
            what = []
            if unknown:
                what.append(f"unknown parameter(s) {unknown}")
            if missing:
                what.append(f"missing parameter(s) {missing}")
            raise ValueError(
                f"{where}.parameters: {'; '.join(what)}; {c.label}"
                + (f" ({c.variant})" if c.variant else "")
                + f" takes: {listing}"
            )
        for s in specs:
            value, unit = given[s.name]
            if unit != s.unit:
                raise ValueError(
                    f"{where}.parameters.{s.name}.unit: expected {s.unit!r}, got {unit!r} "
                    "(values are not converted: give the value in the expected unit)"
                )
            theta.append(value)
        cands.append(c)
    return tuple(cands), np.asarray(theta, dtype=float)


def effect_param_names(arm: Arm) -> tuple[str, ...]:
    """``"<effect>@<location>.<parameter>"`` for each entry of the model's ``theta``."""
    cands, _ = model_effects(arm)
    return tuple(f"{c.label}.{s.name}" for c in cands for s in c.parameters(arm))


def effect_param_units(arm: Arm) -> tuple[str, ...]:
    """The unit of each entry of the model's ``theta``."""
    cands, _ = model_effects(arm)
    return tuple(s.unit for c in cands for s in c.parameters(arm))


def effect_records(
    arm: Arm, candidates: Sequence[Candidate], theta: ArrayLike
) -> tuple[EffectRecord, ...]:
    """Effect records (for :meth:`~cdra_jax.arm.Arm.with_effects`) of fitted ``candidates``
    with the values ``theta`` (their parameters concatenated, in feature-column order)."""
    values = np.asarray(theta, dtype=float).reshape(-1)
    out, k = [], 0
    for c in candidates:
        specs = c.parameters(arm)
        if k + len(specs) > values.size:
            raise ValueError(
                f"effect_records: {sum(len(c.parameters(arm)) for c in candidates)} parameters "
                f"for these candidates, got {values.size} values"
            )
        out.append(
            EffectRecord(
                name=c.name,
                location=c.location,
                variant=c.variant,
                parameters=tuple(
                    (s.name, float(values[k + j]), s.unit) for j, s in enumerate(specs)
                ),
            )
        )
        k += len(specs)
    if k != values.size:
        raise ValueError(f"effect_records: {k} parameters for these candidates, got {values.size}")
    return tuple(out)


def with_effects(arm: Arm, candidates: Sequence[Candidate], theta: ArrayLike) -> Arm:
    """``arm`` with the effects ``candidates`` at the values ``theta`` (replacing its own)."""
    return arm.with_effects(effect_records(arm, candidates, theta))


def with_effect_values(arm: Arm, theta: ArrayLike) -> Arm:
    """``arm`` with its own effects at the values ``theta`` (e.g. refined by a calibration)."""
    cands, _ = model_effects(arm)
    return with_effects(arm, cands, theta)


def missing_effect_data(arm: Arm, aux_names: Iterable[str]) -> list[str]:
    """Why each effect of the model cannot be evaluated on data with the auxiliary columns
    ``aux_names`` (empty: all can)."""
    cands, _ = model_effects(arm)
    names = frozenset(aux_names)
    out = []
    for c in cands:
        why = c.missing(arm, names)
        if why:
            out.append(f"{c.label}: {why}")
    return out


def check_effect_data(arm: Arm, aux_names: Iterable[str], data_label: str = "the data") -> None:
    """``ValueError`` when the model's effects need auxiliary columns that the data lack (or
    model content, such as masses, that the model lacks)."""
    why = missing_effect_data(arm, aux_names)
    if why:
        raise ValueError(
            f"the model's [[effects]] cannot be evaluated on {data_label}: " + "; ".join(why)
        )


def needed_aux(arm: Arm, available: Iterable[str]) -> tuple[str, ...]:
    """The auxiliary columns of ``available`` that some effect of the model needs (those
    whose absence makes :meth:`Candidate.missing` give a reason)."""
    cands, _ = model_effects(arm)
    avail = tuple(available)
    full = frozenset(avail)
    out = []
    for name in avail:
        rest = full - {name}
        if any(c.missing(arm, full) is None and c.missing(arm, rest) for c in cands):
            out.append(name)
    return tuple(out)


def model_features(
    arm: Arm, q: ArrayLike, aux: Aux, candidates: Sequence[Candidate] | None = None
) -> Features:
    """Features of the model's effects (or of ``candidates``) at states ``q (m, dof)``,
    concatenated; zero columns without effects."""
    q = jnp.asarray(q)
    if candidates is None:
        candidates, _ = model_effects(arm)
    if not candidates:
        return Features.zeros(arm, q.shape[0], 0, q.dtype)
    return stacked_features(candidates, arm, q, aux)


def model_tool_pose(
    arm: Arm, q: ArrayLike, aux: Aux | None = None, theta: ArrayLike | None = None
) -> Array:
    """Tool poses ``(m, 4, 4)`` of the model with its effects (world frame, mm).

    Args:
        arm: the model (its frames and effect records).
        q: ``(m, dof)`` module states as recorded.
        aux: the auxiliary columns the effects need (``time_s``, ``approach.<module>``,
            ``payload_kg``), name -> ``(m,)``.
        theta: the effects' parameters (default: the values in the model).

    Without effects this is :func:`cdra_jax.arm.tool_pose` (Eq. 1).
    """
    q = jnp.asarray(q)
    cands, values = model_effects(arm)
    if theta is None:
        theta = values
    aux = {k: jnp.asarray(v, q.dtype) for k, v in (aux or {}).items()}
    # The records hold values: strip them from the compiled call's static arguments (the
    # candidates and theta carry them), so that other values reuse the compiled program.
    return _predict(arm.with_effects(()), cands, q, aux, jnp.asarray(theta, q.dtype))


@filter_jit
def _predict(arm: Arm, cands: tuple[Candidate, ...], q: Array, aux: Aux, theta: Array) -> Array:
    return corrected_tool_pose(arm, q, model_features(arm, q, aux, cands), theta)
