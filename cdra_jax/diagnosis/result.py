"""What a diagnosis returns: :class:`Diagnosis` (JSON via ``to_dict``) and its candidate rows."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any


def _num(x: float | None) -> float | None:
    """JSON-safe float (NaN and inf become None)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


@dataclass
class ParameterEstimate:
    """One physical parameter: value and 95 % interval, unit, physical range and its check.

    ``plausible`` is true when the 95 % interval overlaps the physical range ``[range_low,
    range_high]``.
    """

    value: float
    low: float
    high: float
    unit: str
    range_low: float
    range_high: float
    description: str = ""

    @property
    def plausible(self) -> bool:
        return bool(self.high >= self.range_low and self.low <= self.range_high)

    def to_dict(self) -> dict[str, Any]:
        return {
            "value": _num(self.value),
            "low": _num(self.low),
            "high": _num(self.high),
            "unit": self.unit,
            "plausible": self.plausible,
            "plausible_range": [_num(self.range_low), _num(self.range_high)],
            "description": self.description,
        }


@dataclass
class CandidateRow:
    """One row of the candidate table.

    Attributes:
        effect, location: the candidate.
        n_params: its number of physical parameters.
        skipped: why it was not evaluated (missing data), else None.
        variant: the form of the effect the row reports (e.g. ``"k=2"``: second harmonic),
            chosen among ``variants`` by the smallest p-value (Bonferroni over them).
        absorbed_fraction: fraction of its most visible direction that the frame errors absorb.
        df: number of directions the poses can see (absorbed fraction < 0.999).
        statistic: F statistic of adding it to the geometric fit.
        p_value: Holm-corrected p-value over the evaluated candidates; ``p_value_raw``: single.
        heldout_gain: held-out (cross-validated) log-likelihood gain over the geometric fit.
        selected: the reported effect.
        indistinguishable_from: candidates whose projected spaces this pose set cannot separate
            from this one (all principal cosines > 0.98).
        parameters: linearised estimates (the joint refit for the selected one).
    """

    effect: str
    location: str
    n_params: int
    skipped: str | None = None
    variant: str | None = None
    variants: list[str] = field(default_factory=list)
    absorbed_fraction: float | None = None
    df: int = 0
    statistic: float | None = None
    p_value: float | None = None
    p_value_raw: float | None = None
    heldout_gain: float | None = None
    selected: bool = False
    indistinguishable_from: list[str] = field(default_factory=list)
    parameters: dict[str, ParameterEstimate] = field(default_factory=dict)

    @property
    def label(self) -> str:
        return f"{self.effect}@{self.location}"

    def to_dict(self) -> dict[str, Any]:
        return {
            "effect": self.effect,
            "location": self.location,
            "n_params": self.n_params,
            "skipped": self.skipped,
            "variant": self.variant,
            "variants": list(self.variants),
            "absorbed_fraction": _num(self.absorbed_fraction),
            "df": self.df,
            "statistic": _num(self.statistic),
            "p_value": _num(self.p_value),
            "p_value_raw": _num(self.p_value_raw),
            "heldout_gain": _num(self.heldout_gain),
            "selected": self.selected,
            "indistinguishable_from": list(self.indistinguishable_from),
            "parameters": {k: v.to_dict() for k, v in self.parameters.items()},
        }


@dataclass
class HeldOutErrors:
    """Held-out (cross-validated) RMS errors of predicted tool poses: Eqs. 20-21 on held-out."""

    delta_p_mm: float
    delta_R_rad: float
    statistic: float | None = None
    p_value: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "delta_p_mm": _num(self.delta_p_mm),
            "delta_R_rad": _num(self.delta_R_rad),
            "chi2": _num(self.statistic),
            "p_value": _num(self.p_value),
        }


@dataclass
class Diagnosis:
    """The answer to "why does the calibrated model still disagree with the recordings?".

    Attributes:
        mismatch: the geometric fit is inconsistent with the noise (combined ``p_value < alpha``).
        p_value: combined (Bonferroni) p-value of the detection tests (see ``tests``).
        effect: a vocabulary name, ``"none"`` or ``"unattributed"``.
        located_in: module or frame name, or None.
        parameters: the selected effect's parameters from the joint refit.
        candidates: the candidate table.
        heldout_before, heldout_after: held-out errors of the geometric and the extended fit.
        noise: the noise model used (``source``: ``"given"`` or ``"estimated"``).
        not_identifiable_from_poses: effects a pose-only calibration absorbs exactly.
        report: the plain-words text.
        tests: the detection tests (held-out chi-square, lack of fit, candidate family).
        details: anything else worth keeping (fit, refit, probes, settings).
        residuals: per-pose held-out residuals for plots (not serialised).
    """

    mismatch: bool
    p_value: float
    effect: str
    located_in: str | None
    parameters: dict[str, ParameterEstimate]
    candidates: list[CandidateRow]
    heldout_before: HeldOutErrors
    heldout_after: HeldOutErrors
    noise: dict[str, Any]
    not_identifiable_from_poses: list[str]
    report: str = ""
    tests: dict[str, Any] = field(default_factory=dict)
    details: dict[str, Any] = field(default_factory=dict)
    refit_arm: Any = field(default=None, repr=False)
    """The model the diagnosis ends with (an :class:`~cdra_jax.arm.Arm`, not in this mapping;
    the diagnose workflow writes it): the geometric fit's frames and markers, plus the selected
    effect as ``[[effects]]`` with its refitted parameters (none for ``none`` and
    ``unattributed``)."""
    residuals: dict[str, Any] = field(default_factory=dict, repr=False)
    """Held-out errors per measurement row (not in the JSON): ``"before"`` / ``"after"`` map
    ``"position_mm"`` ``(m,)`` (RMS norm of the row's position errors: the full pose's tool
    point and each seen point) and ``"rotation_rad"`` ``(m,)`` (norm of the full pose's
    rotation error, NaN in rows without one), measured minus predicted; and ``"pose_ids"``."""

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready mapping with every key of the design's diagnosis contract."""
        return {
            "mismatch": bool(self.mismatch),
            "p_value": _num(self.p_value),
            "located_in": self.located_in,
            "effect": self.effect,
            "parameters": {k: v.to_dict() for k, v in self.parameters.items()},
            "candidates": [c.to_dict() for c in self.candidates],
            "heldout_before": self.heldout_before.to_dict(),
            "heldout_after": self.heldout_after.to_dict(),
            "not_identifiable_from_poses": list(self.not_identifiable_from_poses),
            "report": self.report,
            "noise": dict(self.noise),
            "tests": self.tests,
            **self.details,
        }

    def table(self) -> str:
        """The candidate table as fixed-width text."""
        head = (
            f"{'candidate':<28}{'n':>3}{'absorbed':>10}{'F':>10}{'p (Holm)':>11}{'gain':>10}  notes"
        )
        lines = [head, "-" * len(head)]
        for c in self.candidates:
            if c.skipped:
                lines.append(f"{c.label:<28}{c.n_params:>3}  skipped: {c.skipped}")
                continue
            notes = []
            if c.selected:
                notes.append("SELECTED")
            if c.variant:
                notes.append(c.variant)
            if c.absorbed_fraction is not None and c.df == 0:
                notes.append("not identifiable from poses")
            if c.indistinguishable_from:
                notes.append("~ " + ", ".join(c.indistinguishable_from))
            lines.append(
                f"{c.label:<28}{c.n_params:>3}{_f(c.absorbed_fraction, '.4f'):>10}"
                f"{_f(c.statistic, '.3g'):>10}{_f(c.p_value, '.2g'):>11}"
                f"{_f(c.heldout_gain, '.1f'):>10}  {'; '.join(notes)}"
            )
        return "\n".join(lines)


def _f(x: float | None, spec: str) -> str:
    return "-" if x is None or not math.isfinite(x) else format(x, spec)
