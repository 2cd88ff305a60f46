"""``cdra-jax validate``: how well a model predicts held-out measurements.

A thin layer over :func:`cdra_jax.workflows.validate`: predicts every row of a measurement CSV
with a model (or a nominal model with a calibration result applied), prints the pooled position
and rotation errors (and the nominal model's beside them with ``--result``), and optionally
writes the per-row JSON and a figure.
"""

from __future__ import annotations

import argparse

from ..io.files import check_distinct_files, check_output
from . import common


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``validate`` subcommand."""
    p = subparsers.add_parser(
        "validate",
        help="predict held-out measurements with a model or a calibration result",
        description=(
            "Predict the measured tool poses and points (tool origin, markers) of a measurement "
            "CSV with a model (or, with --result, the nominal model with a calibration result "
            "applied: Eq. 19) and report the position error (mm, over every measured position) "
            "and the rotation error (rad, full poses) per row and pooled (mean, rms, max)."
        ),
    )
    common.add_model_option(p)
    p.add_argument("--data", metavar="D", required=True, help="held-out measurement CSV file")
    p.add_argument(
        "--result",
        metavar="R",
        help="calibration result JSON (from cdra-jax calibrate) to apply to the model",
    )
    p.add_argument(
        "--compare",
        metavar="M2",
        help="a second model TOML whose errors are shown beside (e.g. the nominal model next to "
        "a calibrated one from calibrate --model-out); not with --result",
    )
    p.add_argument(
        "--register",
        action="store_true",
        help="place the reference model (--compare, or the nominal model with --result) in the "
        "measuring device's frame first, by a rigid fit of its base frame to these data: a fair "
        "baseline when the data come from a tracker in its own frame",
    )
    p.add_argument("--out", metavar="V", help="write the validation JSON (per-row errors)")
    p.add_argument("--plot", metavar="PNG", help="write the per-row error figure")
    common.add_force_option(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``validate``; returns the exit code (0)."""
    check_distinct_files(
        [("--out", args.out), ("--plot", args.plot)],
        [
            ("--data", args.data),
            ("--model", args.model),
            ("--result", args.result),
            ("--compare", args.compare),
        ],
    )
    if args.result is not None and args.compare is not None:
        raise ValueError("--result and --compare: give one (a result applies to --model)")
    if args.register and args.result is None and args.compare is None:
        raise ValueError("--register places the reference model: give --compare or --result")
    check_output(args.out, args.force, "--out")
    check_output(args.plot, args.force, "--plot")

    from ..io import save_figure_atomic
    from ..workflows import validate

    v = validate(
        args.model,
        args.data,
        result=args.result,
        compare=args.compare,
        register_reference=args.register,
    )
    lines = [v.report()]
    if args.out:
        lines.append(common.wrote(v.save(args.out, force=args.force)))
    if args.plot:
        lines.append(common.wrote(save_figure_atomic(v.plot(), args.plot, force=args.force)))
    print("\n".join(lines))
    return common.EXIT_OK
