"""``cdra-jax diagnose``: the missing-physics analyser on a model file and a measurement CSV.

A thin layer over :func:`cdra_jax.workflows.diagnose`: prints the plain-words report and the
candidate table, writes the diagnosis JSON, with ``--model-out`` the refit model (frames plus
the found effect under ``[[effects]]``) and, with ``--plots``, residual figures before and after
the refit. Exit code 0, also when a mismatch is found.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..io.files import check_distinct_files, check_output
from ..workflows.inputs import check_range, check_seed
from . import common


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``diagnose`` subcommand."""
    p = subparsers.add_parser(
        "diagnose",
        help="find the missing physics a geometric calibration leaves in the recordings",
        description=(
            "Test whether a geometric calibration of a model leaves a misfit in the recordings "
            "(full poses or points; the noise values are optional: the verdict rests on tests "
            "that need none) and, if so, which non-geometric effect (joint compliance, cable "
            "elasticity, cable scale, backlash, periodic error, link bending, thermal drift) "
            "and where explains it; refit it, report the physical parameters and the held-out "
            "improvement, and with --model-out write the model with the effect."
        ),
    )
    common.add_model_option(p)
    p.add_argument("--data", metavar="D", required=True, help="measurement CSV file")
    p.add_argument("--out", metavar="R", required=True, help="diagnosis JSON file to write")
    common.add_noise_options(p, "of the measuring device (without them the noise is estimated)")
    p.add_argument(
        "--model-out",
        metavar="M",
        help="also write the refit model as a model TOML: the fitted frames plus the selected "
        "effect under [[effects]] (validate predicts with it, calibrate refines it)",
    )
    p.add_argument("--plots", metavar="DIR", help="write residual plots (PNG) into this folder")
    p.add_argument("--folds", type=int, default=5, help="cross-validation folds (default 5)")
    p.add_argument("--seed", type=int, default=0, help="seed of the folds (default 0)")
    p.add_argument("--alpha", type=float, default=0.01, help="significance level (default 0.01)")
    common.add_force_option(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``diagnose``; exit code 0 (also when a mismatch is found)."""
    noise = common.noise(args)
    check_range("--folds", args.folds)
    check_seed(args.seed, "--seed")
    if not 0 < args.alpha < 1:
        raise ValueError(f"--alpha must be a number in (0, 1), got {args.alpha}")
    check_distinct_files(
        [("--out", args.out), ("--model-out", args.model_out)],
        [("--data", args.data), ("--model", args.model)],
    )
    check_output(args.out, args.force, "--out")
    check_output(args.model_out, args.force, "--model-out")
    if args.plots is not None and Path(args.plots).exists() and not Path(args.plots).is_dir():
        raise NotADirectoryError(f"--plots {args.plots}: exists and is not a folder")

    from ..workflows import diagnose

    d = diagnose(args.model, args.data, noise, seed=args.seed, folds=args.folds, alpha=args.alpha)
    lines = [d.report(), "", common.wrote(d.save(args.out, force=args.force))]
    if args.model_out:
        lines.append(common.wrote(d.save_model(args.model_out, force=args.force)))
    if args.plots is not None:
        lines += [common.wrote(p) for p in d.save_plots(args.plots, force=args.force)]
    print("\n".join(lines))
    return common.EXIT_OK
