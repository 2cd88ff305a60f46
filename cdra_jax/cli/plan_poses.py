"""``cdra-jax plan-poses``: choose which poses to measure (optimal selection from a pool).

Usage::

    cdra-jax plan-poses --count 10 --out plan.csv [--model M] [--pool 5000] [--seed 0]
        [--noise-pos 0.08 --noise-rot 0.001] [--criterion i-opt|d-opt|o1] [--force]

A thin layer over :func:`cdra_jax.workflows.plan_poses`: writes the measurement-plan CSV
(``pose`` and the module state columns, ``#`` lines that record how it was made) and prints the
expected accuracy of a calibration from the planned poses against that of as many random ones.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..io.files import check_distinct_files, check_output
from ..pose_selection import CRITERIA, DEFAULT_CRITERION, DEFAULT_POOL_SIZE
from ..workflows.inputs import check_range
from ..workflows.plan_poses import DEFAULT_NOISE
from . import common


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``plan-poses`` subcommand (``func`` = :func:`run`)."""
    p = subparsers.add_parser(
        "plan-poses",
        help="choose the poses to measure (I-optimal selection from a pool)",
        description="Select the module states to measure from a pool of random feasible "
        "states so that the calibration is as informative as possible, and write them as a "
        "measurement plan CSV (pose + module state columns).",
    )
    common.add_model_option(p)
    p.add_argument("--count", metavar="m", type=int, required=True, help="poses to select")
    p.add_argument("--out", metavar="CSV", required=True, help="measurement plan to write")
    p.add_argument(
        "--pool",
        metavar="N",
        type=int,
        default=DEFAULT_POOL_SIZE,
        help=f"candidate states ({DEFAULT_POOL_SIZE})",
    )
    p.add_argument("--seed", metavar="S", type=int, default=0, help="seed of the pool (0)")
    p.add_argument(
        "--noise-pos",
        metavar="MM",
        type=float,
        help="position noise std of the measuring device, mm (default "
        f"{float(DEFAULT_NOISE.position_mm)})",
    )
    p.add_argument(
        "--noise-rot",
        metavar="RAD",
        type=float,
        help=f"orientation noise std, rad (default {float(DEFAULT_NOISE.rotation_rad)})",
    )
    p.add_argument(
        "--criterion",
        choices=CRITERIA,
        default=DEFAULT_CRITERION,
        help="i-opt (default): smallest average predicted tool-position variance over the "
        "pool (what the held-out accuracy measures); d-opt: largest log det of the "
        "noise-weighted information on the identifiable subspace; o1: Borm & Menq's "
        "observability index of the unweighted Jacobian",
    )
    common.add_force_option(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``plan-poses``; returns the exit code (0)."""
    noise = common.noise(args)
    check_range("--count", args.count)  # at least 4: the paper's minimum
    check_range("--pool", args.pool)
    if args.pool < args.count:
        raise ValueError(f"--pool ({args.pool}) must be at least --count ({args.count})")
    out = Path(args.out)
    check_distinct_files([("--out", out)], [("--model", args.model)])
    check_output(out, args.force, "--out")

    from ..workflows import plan_poses
    from ..workflows.inputs import check_seed

    plan = plan_poses(
        args.model,
        args.count,
        noise=noise,
        pool=args.pool,
        seed=check_seed(args.seed, "--seed"),
        criterion=args.criterion,
    )
    path = plan.save(out, force=args.force)
    print(plan.report())
    print(common.wrote(path))
    return common.EXIT_OK
