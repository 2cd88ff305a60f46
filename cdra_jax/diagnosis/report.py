"""The plain-words report of a :class:`~cdra_jax.diagnosis.result.Diagnosis`."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ..physics import Candidate
    from .result import Diagnosis


def _g(x: float | None, spec: str = ".3g") -> str:
    return "-" if x is None else format(x, spec)


def _p(p: float | None) -> str:
    if p is None:
        return "-"
    return "< 1e-12" if p < 1e-12 else format(p, ".2g")


def _finite(x: float | None) -> bool:
    return x is not None and math.isfinite(x)


def _errors_text(position_mm: float | None, rotation_rad: float | None) -> str:
    """``"position 0.1 mm, rotation 0.002 rad"``; the rotation left out where none is measured."""
    text = f"position {_g(position_mm)} mm"
    return text + (f", rotation {_g(rotation_rad)} rad" if _finite(rotation_rad) else "")


def _noise_text(noise: dict) -> str:
    """The noise values used, one per measured kind (full-pose position and rotation, points)."""
    parts = []
    if _finite(noise.get("position_mm")):
        parts.append(f"{noise['position_mm']:.3g} mm")
    if _finite(noise.get("rotation_rad")):
        parts.append(f"{noise['rotation_rad']:.3g} rad")
    pts = [v for v in (noise.get("points_mm") or {}).values() if _finite(v)]
    if pts:
        lo, hi = min(pts), max(pts)
        parts.append(
            f"points {lo:.3g} mm" if f"{lo:.2g}" == f"{hi:.2g}" else f"points {lo:.3g}-{hi:.3g} mm"
        )
    return ", ".join(parts)


def _noise_check(d: Diagnosis, ho: dict) -> str:
    """The given noise values against the residual: the held-out chi-square and, where it
    contradicts them, the noise the residual suggests."""
    text = (
        f"Stated noise: held-out chi-square {ho['statistic']:.1f} (expected {ho['expected']:.0f}), "
        f"p = {_p(ho['p_value'])}"
    )
    ratio = (ho["statistic"] / ho["expected"]) ** 0.5 if ho["expected"] else 1.0
    alpha = d.details["alpha"]
    if ho["p_value"] < alpha or ratio < 0.7:
        sug = _noise_text(d.details["noise_suggested"])
        cause = (
            "the missing physics above adds to it"
            if d.mismatch
            else "the residuals contradict the stated noise: the measuring device is "
            + ("noisier" if ratio > 1 else "less noisy")
            + " than stated"
        )
        return (
            f"{text}: the held-out residuals are {ratio:.2g} times what the stated noise "
            f"explains ({cause}; the residual suggests {sug})."
        )
    return text + ": consistent with the residuals."


def _skipped_text(candidates, locations: dict[str, int] | None = None) -> list[str]:
    """One entry per skipped effect where every location was skipped for the same reason
    ("backlash at every location (no approach.<module> column in the measurements)"), else
    one per candidate; effects skipped for the same reason at every location share an entry
    ("cable_elasticity, cable_scale at every location (no module has cables in the model)").
    ``locations``: how many locations each effect has (default: its rows here)."""
    by_effect: dict[str, list] = {}
    for c in candidates:
        by_effect.setdefault(c.effect, []).append(c)
    out: list[str] = []
    everywhere: dict[str, list[str]] = {}
    for effect, rows in by_effect.items():
        skipped = [c for c in rows if c.skipped]
        if not skipped:
            continue
        generic = {
            c.skipped.replace(repr(c.location), "<module>").replace(
                f"approach.{c.location}", "approach.<module>"
            )
            for c in skipped
        }
        n = (locations or {}).get(effect, len(rows))
        if len(skipped) == n and n > 1 and len(generic) == 1:
            reason = generic.pop().replace("module <module> has no ", "no module has ")
            everywhere.setdefault(reason, []).append(effect)
        else:
            out += [f"{c.label} ({c.skipped})" for c in skipped]
    return [
        f"{', '.join(effects)} at every location ({reason})"
        for reason, effects in everywhere.items()
    ] + out


def render_report(d: Diagnosis, best: Candidate | None) -> str:
    """Plain-words text: the fit, the test, the answer, the improvement, the caveats."""
    det = d.details
    b, a = d.heldout_before, d.heldout_after
    floor = det["noise_floor"]
    t = d.tests
    fit = det.get("geometric_fit") or {}
    n_frame = det.get("n_frame_params", 0)
    n_marker = int(fit.get("n_marker_coordinates", 0))
    params = f"{n_frame} frame-error parameters" + (
        f" and {n_marker} marker coordinates" if n_marker > 0 else ""
    )
    if fit.get("model_effects"):
        params += ", with the model's effects " + ", ".join(fit["model_effects"])
    lines = [
        f"Geometric calibration ({params}, {fit.get('solver', 'weighted Gauss-Newton')}) of "
        f"{det['n_poses']} poses, {det['folds']}-fold cross-validated: held-out "
        f"{_errors_text(b.delta_p_mm, b.delta_R_rad)}; noise floor "
        f"{_errors_text(floor['delta_p_mm'], floor['delta_R_rad'])} "
        f"(noise {d.noise['source']}: {_noise_text(d.noise)}"
        + (
            " from the refit with the named effect"
            if "refit" in str(d.noise.get("estimated_from", ""))
            else ""
        )
        + ").",
    ]
    ratio = d.noise.get("stated_contradicted_by")
    if ratio is not None:
        lines.append(
            f"The noise values given are contradicted: the residual of the refit with the named "
            f"effect is {ratio:.2g} times them, so the diagnosis ran again with the noise "
            "estimated from that residual, as without noise values."
        )
    parts = []
    st = t.get("structure") or {}
    if st.get("p_value") is not None:
        regs = ", ".join(st.get("regressors", ()))
        parts.append(
            f"residual structure (predictable on left-out poses from: {regs}) "
            f"p = {_p(st['p_value'])}"
        )
    if t["lack_of_fit"] is not None:
        lof = t["lack_of_fit"]
        if lof.get("applicable", True):
            parts.append(
                f"lack of fit on {lof['repeated_groups']} repeated pose(s) F = {lof['F']:.3g}, "
                f"p = {_p(lof['p_value'])}"
            )
        else:
            parts.append(
                f"lack of fit on {lof['repeated_groups']} repeated pose(s) not applicable (the "
                "repeats and the fit agree to rounding: exact data)"
            )
    parts.append(f"best candidate test p = {_p(t['candidates_min_p_holm'])} (Holm)")
    tolerant = t["heldout_chi2"].get("p_value_tolerant")
    if tolerant is not None:
        k = t["heldout_chi2"]["noise_tolerance"]
        parts.append(
            f"held-out chi-square with {k:g}x the stated noise variance p = {_p(tolerant)}"
        )
    verdict = (
        "leaves a misfit that the geometric model cannot explain"
        if d.mismatch
        else "leaves nothing the geometric model cannot explain"
    )
    lines.append(
        f"The fit {verdict}: {'; '.join(parts)}; combined "
        f"p = {_p(d.p_value)} (alpha = {det['alpha']:g})."
    )
    ho = t["heldout_chi2"]
    if ho["p_value"] is not None:
        lines.append(_noise_check(d, ho))
    if d.effect == "none":
        lines.append("No missing physics detected: the geometric model explains the recordings.")
    elif d.effect == "unattributed":
        msg = "The misfit is not explained by any effect of the vocabulary"
        rejected = (det.get("refit") or {}).get("rejected")
        if best is not None and rejected:
            msg += f" (the best candidate, {best.label}, is not reported: {rejected['reason']})"
        elif best is not None and det.get("refit"):
            msg += (
                f" (the best candidate, {best.label}, removes only "
                f"{100 * det['refit']['explained_fraction']:.0f} % of the excess held-out misfit)"
            )
        msg += "."
        if d.located_in and det.get("location_source") == "rival probe":
            msg += f" It belongs to the {d.located_in}, where the probe that outdid it sits."
        elif d.located_in and det.get("location_source") == "probe":
            top = det["probes"][0]
            msg += (
                f" It belongs to the {d.located_in} (generic probe: {top['kind']}, "
                f"p = {_p(top['p_value'])})."
            )
        elif d.located_in:
            msg += (
                f" It belongs to the {d.located_in}, where the best candidate sits: an effect "
                "of that kind but of another form than the vocabulary's."
            )
        elif det.get("location_source") == "structure":
            msg += (
                " No place of the chain explains it: it follows where the tool is in the "
                "workspace (a measuring device's distortion, or a field of the workspace), not "
                "one module's states."
            )
        else:
            msg += (
                " No single location explains it (no module's states, and no pose-dependent "
                "probe, predict it on their own)."
            )
        lines.append(msg)
    else:
        assert best is not None
        values = {k: (v.value, v.low, v.high) for k, v in d.parameters.items() if ":" not in k}
        text = best.effect.describe(best.location, values)
        lines.append(f"Most likely missing physics: {text}.")
        added = (det["refit"] or {}).get("forms", [])[1:]
        if added:
            lines.append(
                "Richer forms of it that pay for themselves on held-out poses, refitted with it: "
                + ", ".join(
                    f"{f['variant']} (+{f['heldout_gain']:.1f} log-likelihood)" for f in added
                )
                + "."
            )
        rot = (
            f", rotation {b.delta_R_rad:.3g} -> {a.delta_R_rad:.3g} rad"
            if _finite(b.delta_R_rad)
            else ""
        )
        lines.append(
            f"Held-out position error {b.delta_p_mm:.3g} -> {a.delta_p_mm:.3g} mm{rot}; noise "
            f"floor {floor['delta_p_mm']:.3g} mm."
        )
        if a.p_value is not None and a.p_value < det["alpha"]:
            lines.append(
                f"A misfit remains after the refit (held-out p = {_p(a.p_value)}); the effect "
                f"removes {100 * det['refit']['explained_fraction']:.0f} % of the excess."
            )
        bad = [k for k, v in d.parameters.items() if not v.plausible]
        if bad:
            lines.append(
                "Outside the physically plausible range: " + ", ".join(bad) + " (check units, "
                "or the effect is a stand-in for another one)."
            )
        row = next(c for c in d.candidates if c.selected)
        tied = (det.get("indistinguishable") or {}).get("candidates") or []
        if tied:
            lines.append(
                "Indistinguishable on these poses: "
                + " or ".join(t["candidate"] for t in tied)
                + " (each refitted, they predict held-out poses equally well: likelihood ratio "
                f"within {det['indistinguishable']['within_nats']:g} nats; the first is "
                "reported): "
                "poses that separate them, or less noise, would tell which."
            )
        rivals = [
            r
            for r in det.get("close_rivals") or []
            if r["candidate"] not in {t["candidate"] for t in tied}
        ]
        if rivals:
            lines.append(
                "Nearly as well supported on held-out poses: "
                + ", ".join(
                    f"{r['candidate']} (gain {r['heldout_gain']:.1f} against "
                    f"{row.heldout_gain:.1f})"
                    for r in rivals
                )
                + ": poses that separate them, or less noise, would tell which."
            )
        if row.indistinguishable_from:
            lines.append(
                "This pose set cannot tell it apart from: "
                + ", ".join(row.indistinguishable_from)
                + " (add poses that separate them)."
            )
    nid = [c.label for c in d.candidates if c.skipped is None and c.df == 0]
    if nid:
        lines.append(
            "Not identifiable from these poses (absorbed by the frames): " + ", ".join(nid)
        )
    skipped = _skipped_text(d.candidates)
    if skipped:
        lines.append("Not tried: " + "; ".join(skipped) + ".")
    inapt = [
        SimpleNamespace(**r, label=f"{r['effect']}@{r['location']}", skipped=r["reason"])
        for r in det.get("not_applicable") or ()
    ]
    if inapt:
        n: dict[str, int] = {}
        for effect in [c.effect for c in d.candidates] + [c.effect for c in inapt]:
            n[effect] = n.get(effect, 0) + 1
        lines.append("Not for this arm: " + "; ".join(_skipped_text(inapt, n)) + ".")
    return "\n".join(lines)
