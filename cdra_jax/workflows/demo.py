"""The demo workflow: the paper's Table I, Fig. 5 and Fig. 7 regenerated on the default CDRA.

:func:`demo` runs the three studies of :mod:`cdra_jax.reproduction` on the embedded default
model and returns a :class:`DemoRun`: their tables next to the paper's numbers (:meth:`DemoRun.
report`), a JSON summary, and the figures. The default sizes finish in about half a minute on
two CPU cores, JIT compilation (most of it) included; ``full=True`` runs the sizes of
``notebooks/01_paper_reproduction.ipynb``: 1000 trials per pose count, m = 4 ... 40.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import equinox as eqx
import numpy as np

from .. import reproduction
from ..io import default_arm, save_figure_atomic, write_text_atomic
from ..io.results import package_version
from .inputs import check_seed

if TYPE_CHECKING:
    from matplotlib.figure import Figure


class DemoSizes(eqx.Module):
    """Sizes of the three studies (see :mod:`cdra_jax.reproduction` for their meaning)."""

    table_m: int = eqx.field(static=True, default=5)
    table_m_verify: int = eqx.field(static=True, default=100)
    convergence_m: int = eqx.field(static=True, default=5)
    convergence_trials: int = eqx.field(static=True, default=100)
    noise_trials: int = eqx.field(static=True, default=32)
    noise_m_values: tuple[int, ...] = eqx.field(static=True, default=(4, 5, 8, 10, 20, 40))
    noise_m_verify: int = eqx.field(static=True, default=20)
    noise_pad_to: int | None = eqx.field(static=True, default=40)
    fast_compile: bool = eqx.field(static=True, default=True)


SMALL = DemoSizes()
"""The default demo: a coarse Fig. 7 (the divisors of 40 from 4 on, 32 trials each with 20
held-out poses: one compiled solver for all of them, see
:func:`cdra_jax.reproduction.pose_repetition`), compiled for speed. Most of its time is JIT
compilation; of the rest, Fig. 7's trials are the bulk (the noisy m = 4 and 5 solves run to the
iteration cap), so their count is what keeps the demo at about half a minute on two cores."""

FULL = DemoSizes(
    convergence_trials=1000,
    noise_trials=1000,
    noise_m_values=tuple(range(4, 41)),
    noise_m_verify=40,
    noise_pad_to=None,
    fast_compile=False,
)
"""``--full``: the notebook's sizes (1000 trials per pose count, m = 4 ... 40, 40 held out)."""


def _summary(table, conv, noise, sizes: DemoSizes, seed: int, timings: dict) -> dict:
    """JSON-ready numbers of the three studies."""

    def band(a, b, c):
        return {"median": a.tolist(), "p10": b.tolist(), "p90": c.tolist()}

    metrics = ("dp_measured", "dR_measured", "dp_true", "dR_true", "param_v", "param_w")
    return {
        "cdra_jax_version": package_version(),
        "seed": seed,
        "sizes": {f.name: getattr(sizes, f.name) for f in dataclasses.fields(sizes)},
        "time_s": timings,
        "table_1": {
            "frames": list(table.frame_names),
            "m": table.m,
            "preset": table.preset.tolist(),
            "identified": table.identified.tolist(),
            "paper": table.paper.tolist(),
            "recovery_error": table.recovery_error.tolist(),
            "exact_frames": list(table.exact_frames),
            "identifiable_part": table.identifiable_part,
            "paper_identifiable_part": table.paper_identifiable_part,
            "unidentifiable": list(table.unidentifiable),
            "verification": {k: list(v) for k, v in table.verification.items()},
            "rounding_bound": {k: list(v) for k, v in table.rounding_bound.items()},
            "rounding_rms": {k: list(v) for k, v in table.rounding_rms.items()},
        },
        "fig_5": {
            "m": conv.m,
            "trials": conv.trials,
            "delta_p": band(*conv.band("delta_p")),
            "delta_R": band(*conv.band("delta_R")),
            "iterations_to_tol": {str(k): v for k, v in conv.iteration_histogram().items()},
            "tol": conv.tol,
        },
        "fig_7": {
            "m_values": noise.m_values.tolist(),
            "trials": noise.trials,
            "noise": {
                "position_mm": float(noise.noise.position_mm),
                "rotation_rad": float(noise.noise.rotation_rad),
            },
            "noise_floor": list(noise.noise_floor),
            "solvers": {
                s: {
                    **{k: band(*noise.band(s, k)) for k in metrics},
                    "converged_fraction": noise.converged[s].mean(axis=-1).tolist(),
                    "flattening_m": {k: noise.flattening(s, k) for k in metrics[:4]},
                }
                for s in noise.solvers
            },
        },
    }


@dataclasses.dataclass(frozen=True, eq=False)
class DemoRun:
    """The three studies of the demo and their report.

    Attributes:
        table: Table I (:class:`~cdra_jax.reproduction.TableOne`).
        convergence: Fig. 5 (:class:`~cdra_jax.reproduction.ConvergenceStudy`).
        noise: Fig. 7 (:class:`~cdra_jax.reproduction.NoiseStudy`).
        sizes: the study sizes used.
        seed: the PRNG seed of all studies.
        timings: wall and CPU seconds per study (JIT compilation included).
        report_lines: the report's sections, in order.
    """

    table: Any
    convergence: Any
    noise: Any
    sizes: DemoSizes
    seed: int
    timings: dict[str, dict[str, float]]
    report_lines: tuple[str, ...]

    def report(self) -> str:
        """The tables next to the paper's numbers and the timings (what ``demo`` prints)."""
        return "\n".join(self.report_lines)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready numbers of the three studies (``summary.json``)."""
        return _summary(
            self.table, self.convergence, self.noise, self.sizes, self.seed, self.timings
        )

    def to_json(self) -> str:
        """:meth:`to_dict` as JSON text."""
        return json.dumps(self.to_dict(), indent=1, default=_json_default) + "\n"

    def figures(self) -> dict[str, Figure]:
        """Fig. 5 and the two panels of Fig. 7, by output file name."""
        from .. import plots

        return {
            "fig5_convergence.png": plots.convergence_figure(self.convergence),
            "fig7_noise.png": plots.noise_figure(self.noise),
            "fig7_parameter_error.png": plots.parameter_error_figure(self.noise),
        }

    def plot(self) -> Figure:
        """Fig. 7: held-out accuracy against the number of calibration poses."""
        from .. import plots

        return plots.noise_figure(self.noise)

    def save(self, folder: str | os.PathLike, *, force: bool = False) -> list[Path]:
        """Write ``report.txt``, ``summary.json`` and the three figures (PNG) into an existing
        ``folder``; returns the paths."""
        folder = Path(folder)
        out = [
            write_text_atomic(folder / "report.txt", self.report() + "\n", force=force),
            write_text_atomic(folder / "summary.json", self.to_json(), force=force),
        ]
        for name, fig in self.figures().items():
            out.append(save_figure_atomic(fig, folder / name, force=force, dpi=120))
        return out


def demo(
    *,
    full: bool = False,
    seed: int = 0,
    log: Callable[[str], None] | None = None,
    progress: Callable[[str], None] | None = None,
) -> DemoRun:
    """Regenerate the paper's Table I, Fig. 5 and Fig. 7 on the embedded default arm.

    Args:
        full: the notebook's sizes (:data:`FULL`, several minutes) instead of :data:`SMALL`.
        seed: PRNG seed of all studies.
        log: called with each section of the report as soon as it is computed (the command
            line prints them as they come).
        progress: called with a short line after each pose count of Fig. 7.
    """
    check_seed(seed)
    t_start, c_start = time.perf_counter(), time.process_time()
    sizes = FULL if full else SMALL
    arm = default_arm()
    timings: dict[str, float] = {}
    cpu: dict[str, float] = {}
    report: list[str] = []

    def emit(text: str) -> None:
        report.append(text)
        if log is not None:
            log(text)

    @contextlib.contextmanager
    def timed(name: str):
        t, c = time.perf_counter(), time.process_time()
        yield
        timings[name], cpu[name] = time.perf_counter() - t, time.process_time() - c

    emit(
        f"cdra-jax demo: the paper's evidence regenerated on the default model {arm.name!r} "
        f"({'full' if full else 'small'} sizes, seed {seed})"
    )
    with timed("table_1"):
        table = reproduction.table_one(
            arm,
            m=sizes.table_m,
            m_verify=sizes.table_m_verify,
            seed=seed,
            fast_compile=sizes.fast_compile,
        )
    emit("")
    emit(reproduction.format_table_one(table))
    with timed("fig_5"):
        conv = reproduction.convergence_study(
            arm,
            trials=sizes.convergence_trials,
            m=sizes.convergence_m,
            seed=seed,
            fast_compile=sizes.fast_compile,
        )
    emit("")
    emit(reproduction.format_convergence(conv))
    with timed("fig_7"):
        t = time.perf_counter()
        noise = reproduction.noise_study(
            arm,
            m_values=sizes.noise_m_values,
            trials=sizes.noise_trials,
            m_verify=sizes.noise_m_verify,
            pad_to=sizes.noise_pad_to,
            seed=seed,
            fast_compile=sizes.fast_compile,
            progress=None
            if progress is None
            else lambda m: progress(f"  Fig. 7: m = {m} done ({time.perf_counter() - t:.0f} s)"),
        )
    emit("")
    emit(reproduction.format_noise_study(noise))
    timings["total"], cpu["total"] = time.perf_counter() - t_start, time.process_time() - c_start
    emit("")
    emit(
        "time in s, JIT compilation included (wall / CPU of this process): "
        + ", ".join(f"{k} {v:.1f} / {cpu[k]:.1f}" for k, v in timings.items())
    )
    return DemoRun(
        table=table,
        convergence=conv,
        noise=noise,
        sizes=sizes,
        seed=seed,
        timings={"wall": timings, "cpu": cpu},
        report_lines=tuple(report),
    )


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
