"""``cdra-jax calibrate``: identify the fixed-frame errors of a model from a measurement CSV.

A thin layer over :func:`cdra_jax.workflows.calibrate`: prints its report, writes the result
JSON (and, with ``--model-out``, the calibrated model TOML), prints each warning as one
``warning: ...`` line on stderr, and exits with 3 when the solver did not converge and with 4 when
the calibrated model fits the measured points worse than the nominal one (the result file is
still written, with ``"converged": false`` or ``"trusted": false``).
"""

from __future__ import annotations

import argparse
import sys

from ..io.files import check_distinct_files, check_output
from ..workflows.calibrate import LOSSES, SOLVERS, check_solver
from ..workflows.inputs import check_range
from . import common

SOLVER_HELP = (
    "auto: noise scales estimated from the data, a Huber loss, the measuring device's frame "
    "registered; full poses, points and markers (the default without --noise-pos/--noise-rot, "
    "and for point data); paper: the paper's unweighted iterative least squares (Eqs. 9-14); "
    "weighted: the same iteration whitened by the noise model (needs --noise-pos/--noise-rot; "
    "the default with them); lm: Levenberg-Marquardt, whitened when a noise model is given. "
    "paper, weighted and lm fit full tool poses only"
)


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``calibrate`` subcommand."""
    p = subparsers.add_parser(
        "calibrate",
        help="identify the fixed-frame errors of a model from a measurement CSV",
        description=(
            "Calibrate the fixed transforms of a serial arm (and the positions of markers marked "
            "calibrate) from measured tool poses, tool positions or markers (Mustafa et al. "
            "2008, Eqs. 7-21) and write the result as JSON. Exit code 3 when "
            "the solver did not converge, 4 when the calibrated model fits the measured points "
            "worse than the nominal one (the result is still written, marked untrusted)."
        ),
    )
    common.add_model_option(p)
    p.add_argument("--data", metavar="D", required=True, help="measurement CSV file")
    p.add_argument("--out", metavar="R", required=True, help="result JSON file to write")
    p.add_argument("--solver", choices=SOLVERS, default=None, help=SOLVER_HELP)
    common.add_noise_options(
        p, "of the measuring device, to weight the residual (default: estimated from the data)"
    )
    p.add_argument(
        "--loss",
        choices=LOSSES,
        default=None,
        help="huber: robust estimation that down-weights outlying measurements (the default of "
        "auto); cauchy: a stronger robust loss (paper/weighted/lm); ls or none: plain "
        "(weighted) least squares, as in the paper (the default of paper/weighted/lm)",
    )
    p.add_argument(
        "--reject-outliers",
        action="store_true",
        help="with --loss huber|cauchy: finish with a least-squares refit that leaves out the "
        "flagged poses (kept only when it loses no identifiable direction; they stay in the "
        "result)",
    )
    p.add_argument(
        "--max-iterations",
        metavar="N",
        type=int,
        help="iteration cap (default: 20 for paper/weighted, 50 for lm; per round for a "
        "robust loss; 100 per round for auto)",
    )
    p.add_argument(
        "--model-out",
        metavar="M",
        help="also write the calibrated model as a model TOML (loadable by every command)",
    )
    p.add_argument("--plot", metavar="PNG", help="also write the residual figure")
    common.add_force_option(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``calibrate``; returns the exit code."""
    noise = common.noise(args)
    if args.max_iterations is not None:
        check_range("--max-iterations", args.max_iterations)
    if args.reject_outliers and args.loss in (None, "ls", "none"):
        raise ValueError(
            "--reject-outliers needs a robust loss to flag the outliers: add --loss huber or "
            "--loss cauchy"
        )
    if args.solver is not None and args.solver != "auto":
        check_solver(args.solver, noise, "--solver")
    check_distinct_files(
        [("--out", args.out), ("--model-out", args.model_out), ("--plot", args.plot)],
        [("--data", args.data), ("--model", args.model)],
    )
    check_output(args.out, args.force, "--out")
    check_output(args.model_out, args.force, "--model-out")
    check_output(args.plot, args.force, "--plot")

    from ..io import save_figure_atomic
    from ..workflows import calibrate

    run_ = calibrate(
        args.model,
        args.data,
        solver=args.solver,
        noise=noise,
        loss=args.loss,
        reject_outliers=args.reject_outliers,
        max_iterations=args.max_iterations,
    )
    print(run_.report())
    print(common.wrote(run_.save(args.out, force=args.force)))
    if args.model_out:
        print(common.wrote(run_.save_model(args.model_out, force=args.force)))
    if args.plot:
        print(common.wrote(save_figure_atomic(run_.plot(), args.plot, force=args.force)))
    for w in run_.warnings:
        print(f"warning: {w}", file=sys.stderr)
    if not run_.converged:
        print(f"warning: not converged: {run_.result['message']}", file=sys.stderr)
    if not run_.trusted:
        print(f"error: untrusted result: {run_.result['trust']['reason']}", file=sys.stderr)
        return common.EXIT_UNTRUSTED
    return common.EXIT_OK if run_.converged else common.EXIT_NOT_CONVERGED
