"""The sweep workflow: Monte-Carlo noise sensitivity (noise level x pose count x solver).

:func:`sweep` runs :func:`cdra_jax.sweeps.run_sweep` (the Section V/VI procedure per trial:
module states within the joint limits, tension-feasible where the model has cables; random
preset errors; noisy measured poses; calibration; held-out accuracy) on a model, and returns a
:class:`SweepRun`: the tidy per-trial table, the median table ``cdra-jax sweep`` prints, and the
figure (medians with 10-90 % bands against the pose count).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..distributed import DEFAULT_TIMEOUT, check_group, start_group
from ..sweeps import SweepTable, parse_noise_levels, run_sweep
from .inputs import Model, check_range, check_seed, resolve_arm
from .result import JsonResult

if TYPE_CHECKING:
    from matplotlib.figure import Figure


@dataclasses.dataclass(frozen=True, eq=False)
class SweepRun(JsonResult):
    """A finished sweep.

    Attributes:
        table: one row per trial (:class:`~cdra_jax.sweeps.SweepTable`).
        model_label: the model file (or ``embedded CDRA``).
    """

    table: SweepTable
    model_label: str

    def summary_rows(self) -> list[dict[str, Any]]:
        """Per cell (noise level, solver, pose count): median held-out ``dp`` (mm) and ``dR``
        (rad) and the converged fraction."""
        dp = self.table.summary("dp_heldout")
        dR = self.table.summary("dR_heldout")
        return [
            {
                "noise_pos": a["noise_pos"],
                "noise_rot": a["noise_rot"],
                "solver": a["solver"],
                "m": a["m"],
                "dp_heldout_median_mm": a["q50"],
                "dR_heldout_median_rad": b["q50"],
                "converged_fraction": a["converged"],
            }
            for a, b in zip(dp, dR, strict=True)
        ]

    def to_dict(self) -> dict[str, Any]:
        """The sweep's settings (``meta``) and the median table (:meth:`summary_rows`)."""
        return {"meta": dict(self.table.meta), "summary": self.summary_rows()}

    def save(self, path: str | os.PathLike, *, force: bool = False) -> Path:
        """Write the per-trial table (``.csv``, or ``.parquet`` where pyarrow is installed)."""
        return self.table.save(path, force=force)

    def report(self) -> str:
        """The median table ``cdra-jax sweep`` prints."""
        meta = self.table.meta
        lines = [
            f"{len(self.table)} trials in {float(meta['seconds']):.1f} s on {meta['devices']}; "
            "median held-out dp (mm) / dR (rad), converged fraction:",
            f"  {'noise mm':>9} {'noise rad':>9} {'solver':>8} {'m':>4} {'dp':>10} {'dR':>10} conv",
        ]
        for r in self.summary_rows():
            lines.append(
                f"  {r['noise_pos']:9g} {r['noise_rot']:9g} {r['solver']:>8} {r['m']:4d} "
                f"{r['dp_heldout_median_mm']:10.4g} {r['dR_heldout_median_rad']:10.4g} "
                f"{r['converged_fraction']:.3f}"
            )
        return "\n".join(lines)

    def plot(self) -> Figure:
        """Median held-out ``dp`` and ``dR`` against ``m`` with 10-90 % bands."""
        from ..plots import plot_sweep_figure

        return plot_sweep_figure(self.table)


def sweep(
    model: Model,
    noise_pos: Sequence[float],
    noise_rot: Sequence[float],
    poses: Sequence[int],
    *,
    solvers: Sequence[str] = ("paper", "weighted", "lm"),
    trials: int = 100,
    seed: int = 0,
    chunk: int = 4096,
    d_v: float = 1.0,
    d_w: float = 0.05,
    verify: int = 50,
    progress: bool = True,
    checkpoint: str | os.PathLike | None = None,
    model_label: str | None = None,
    predictive_stop: bool = True,
    processes: int = 1,
    process_id: int | None = None,
    coordinator: str | None = None,
    worker_command: Callable[[int, str], Sequence[str]] | None = None,
    timeout: float = DEFAULT_TIMEOUT,
) -> SweepRun | None:
    """Monte-Carlo sweep of the calibration's accuracy over noise levels, pose counts, solvers.

    Args:
        model: an :class:`~cdra_jax.arm.Arm`, a model TOML path, or ``None`` (embedded CDRA).
        noise_pos: position noise std(s), mm (``0`` with rotation ``0``: noise-free).
        noise_rot: rotation noise std(s), rad: one for all position levels or one per level.
        poses: pose counts ``m`` (each >= 4).
        solvers: any of ``paper``, ``weighted``, ``lm`` (the names of :func:`calibrate`).
        trials: trials per cell.
        seed: base seed.
        chunk: trials per vmapped batch (memory grows with it, not with ``trials``).
        d_v, d_w: preset error ranges (mm, rad; the paper's 1 mm and 0.05 rad).
        verify: held-out poses per trial.
        progress: a progress bar on a terminal, progress lines on stderr otherwise.
        checkpoint: a folder keeping the finished chunks, so that the same call after an
            interruption resumes where it stopped (same table; see
            :func:`cdra_jax.sweeps.run_sweep`).
        model_label: name of the model in the table's metadata.
        predictive_stop: the solvers stop once the remaining steps are predicted below
            their tolerances (the default; ``False``: the plain stop, see
            :func:`cdra_jax.sweeps.run_sweep`).
        processes: processes sharing the chunks (1: this one alone). More need
            ``checkpoint`` (the folder they all write to) and must start before JAX runs
            anything in this process (:func:`cdra_jax.distributed.start_group`): either each
            is started by hand with the same ``coordinator`` (``HOST:PORT`` of process 0) and
            its ``process_id``, or neither is given and this process starts the others on this
            machine, running ``worker_command(k, coordinator)``. The table is the same as one
            process's.
        process_id, coordinator, worker_command: see ``processes``.
        timeout: seconds to wait for the other processes to connect, and on process 0 for
            their next finished chunk, before giving up
            (:class:`cdra_jax.distributed.GroupError` naming the missing chunks).

    Returns:
        The finished sweep; ``None`` on a process other than process 0 of a group (its
        chunks are in ``checkpoint``).
    """
    check_range("processes", processes)
    check_range("timeout", timeout)
    check_group(processes, process_id, coordinator)
    if processes > 1 and checkpoint is None:
        raise ValueError("processes > 1 needs checkpoint: the folder all processes write to")
    for flag, n in (("trials", trials), ("verify", verify), ("chunk", chunk)):
        check_range(flag, n)
    check_range("d_v", d_v)
    check_range("d_w", d_w)
    check_seed(seed)
    levels = parse_noise_levels(noise_pos, noise_rot)
    kwargs: dict[str, Any] = dict(
        seed=seed,
        chunk=chunk,
        d_v=d_v,
        d_w=d_w,
        m_verify=verify,
        progress=progress,
        checkpoint=checkpoint,
        predictive_stop=predictive_stop,
    )
    if processes == 1:
        return _sweep(model, model_label, levels, poses, solvers, trials, kwargs)
    group = start_group(
        processes, process_id, coordinator, worker_command=worker_command, timeout=timeout
    )
    ok = False
    try:
        run = _sweep(model, model_label, levels, poses, solvers, trials, kwargs | {"group": group})
        ok = True
        return run
    except BaseException as e:
        if group.process_id != 0:  # process 0 names this process and its error
            group.finish(error=str(e).splitlines()[0] if str(e) else type(e).__name__)
        raise
    finally:
        group.close(ok=ok)


def _sweep(model, model_label, levels, poses, solvers, trials, kwargs) -> SweepRun | None:
    """:func:`run_sweep` on the resolved model (``kwargs``: its keyword arguments)."""
    arm, model_label = resolve_arm(model, model_label)
    if arm.effects:
        raise ValueError(
            f"model {model_label}: the sweep simulates and calibrates the fixed frames alone; "
            "the model's [[effects]] ("
            + ", ".join(e.label for e in arm.effects)
            + ") are not part of it. Sweep the geometric model (the same file without "
            "[[effects]]), or study the effects with simulate + calibrate"
        )
    table = run_sweep(arm, levels, poses, solvers, trials, **kwargs)
    if table is None:
        return None
    table.meta["model"] = model_label
    return SweepRun(table, model_label)
