"""``cdra-jax demo``: regenerate the paper's Table I, Fig. 5 and Fig. 7 on the default CDRA.

Runs the three studies of :mod:`cdra_jax.reproduction` on the embedded default model, prints
their tables next to the paper's numbers and writes the figures (PNG), the printed report and a
JSON summary into an output folder. The default sizes finish in about half a minute on two idle
CPU cores, JIT compilation (most of it) included; ``--full`` runs the sizes of the notebook
(``notebooks/01_paper_reproduction.ipynb``): 1000 trials per pose count, m = 4 ... 40.

The command-line tool wires :func:`register` into its subcommands; :func:`main` runs the demo
with its own parser (``python -m cdra_jax.demo --help``).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import sys
import time
from pathlib import Path

import equinox as eqx
import numpy as np

OUTPUT_FILES: tuple[str, ...] = (
    "report.txt",
    "summary.json",
    "fig5_convergence.png",
    "fig7_noise.png",
    "fig7_parameter_error.png",
)
"""What the demo writes into its output folder."""

DEFAULT_OUT = "cdra_demo_out"


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


def _add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--full",
        action="store_true",
        help="notebook sizes: 1000 trials per pose count, m = 4..40 (several minutes)",
    )
    p.add_argument(
        "--out",
        metavar="DIR",
        default=None,
        help=f"output folder (default: a new ./{DEFAULT_OUT}, or ./{DEFAULT_OUT}-2, ... if taken)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="write into an existing non-empty --out folder, overwriting the demo's own files",
    )
    p.add_argument("--seed", type=int, default=0, help="PRNG seed of all studies (default 0)")


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``demo`` subcommand to an ``argparse`` subparsers object (``func=run``)."""
    p = subparsers.add_parser(
        "demo",
        help="regenerate the paper's Table I, Fig. 5 and Fig. 7 on the default CDRA",
        description=__doc__.split("\n\n")[0] + " " + __doc__.split("\n\n")[1],
    )
    _add_arguments(p)
    p.set_defaults(func=run)
    return p


def _output_folder(out: str | None, force: bool) -> Path:
    """The folder to write into, created; never one whose files would be overwritten silently."""
    if out is None:
        base = Path(DEFAULT_OUT)
        candidates = [base] + [Path(f"{DEFAULT_OUT}-{i}") for i in range(2, 1000)]
        for c in candidates:
            if not c.exists() or (c.is_dir() and not any(c.iterdir())):
                c.mkdir(parents=True, exist_ok=True)
                return c
        raise FileExistsError(f"no free output folder {DEFAULT_OUT}[-N] here; pass --out DIR")
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise FileExistsError(f"--out {out}: exists and is not a folder")
    if path.exists() and any(path.iterdir()) and not force:
        raise FileExistsError(
            f"--out {out}: folder exists and is not empty; pass --force to overwrite the demo's "
            f"files in it ({', '.join(OUTPUT_FILES)})"
        )
    path.mkdir(parents=True, exist_ok=True)
    return path


def _summary(table, conv, noise, sizes: DemoSizes, seed: int, timings: dict) -> dict:
    """JSON-ready numbers of the three studies."""
    from . import __version__

    def band(a, b, c):
        return {"median": a.tolist(), "p10": b.tolist(), "p90": c.tolist()}

    metrics = ("dp_measured", "dR_measured", "dp_true", "dR_true", "param_v", "param_w")
    return {
        "cdra_jax_version": __version__,
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


def run(args: argparse.Namespace) -> int:
    """Run the demo for parsed arguments (``full``, ``out``, ``force``, ``seed``); exit status."""
    import jax

    jax.config.update("jax_enable_x64", True)
    t_start, c_start = time.perf_counter(), time.process_time()
    from .cli_common import check_seed

    try:  # file problems: one error line and exit 1, as every command (before any work)
        check_seed(args.seed)
        out = _output_folder(args.out, args.force)
    except (ValueError, OSError) as e:
        print(f"error: {' '.join(str(e).split())}", file=sys.stderr)
        return 1

    from . import plots, reproduction
    from .io import default_arm, save_figure_atomic, write_text_atomic

    sizes = FULL if args.full else SMALL
    seed = int(args.seed)
    arm = default_arm()
    timings: dict[str, float] = {}
    cpu: dict[str, float] = {}
    report: list[str] = []

    def emit(text: str) -> None:
        print(text, flush=True)
        report.append(text)

    @contextlib.contextmanager
    def timed(name: str):
        """Record the wall and CPU seconds of the ``with`` body under ``name``."""
        t, c = time.perf_counter(), time.process_time()
        yield
        timings[name], cpu[name] = time.perf_counter() - t, time.process_time() - c

    emit(
        f"cdra-jax demo: the paper's evidence regenerated on the default model {arm.name!r} "
        f"({'full' if args.full else 'small'} sizes, seed {seed}); output folder: {out}"
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
            progress=lambda m: print(
                f"  Fig. 7: m = {m} done ({time.perf_counter() - t:.0f} s)", file=sys.stderr
            ),
        )
    emit("")
    emit(reproduction.format_noise_study(noise))

    with timed("figures"):
        figures = {
            "fig5_convergence.png": plots.convergence_figure(conv),
            "fig7_noise.png": plots.noise_figure(noise),
            "fig7_parameter_error.png": plots.parameter_error_figure(noise),
        }
        for name, fig in figures.items():
            save_figure_atomic(fig, out / name, force=args.force, dpi=120)
    timings["total"], cpu["total"] = time.perf_counter() - t_start, time.process_time() - c_start

    emit("")
    emit(
        "time in s, JIT compilation included (wall / CPU of this process): "
        + ", ".join(f"{k} {v:.1f} / {cpu[k]:.1f}" for k, v in timings.items())
    )
    write_text_atomic(out / "report.txt", "\n".join(report) + "\n", force=args.force)
    summary = _summary(table, conv, noise, sizes, seed, {"wall": timings, "cpu": cpu})
    write_text_atomic(
        out / "summary.json",
        json.dumps(summary, indent=1, default=_json_default) + "\n",
        force=args.force,
    )
    print(f"wrote {', '.join(OUTPUT_FILES)} to {out.resolve()}")
    return 0


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def main(argv: list[str] | None = None) -> int:
    """Run the demo with its own parser (``argv`` without the program name)."""
    parser = argparse.ArgumentParser(
        prog="cdra-jax demo",
        description=__doc__.split("\n\n")[0],
    )
    _add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
