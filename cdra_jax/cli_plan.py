"""``cdra-jax plan-poses``: choose which poses to measure (I-optimal selection from a pool).

Usage::

    cdra-jax plan-poses --count 10 --out plan.csv [--model M] [--pool 5000] [--seed 0]
        [--noise-pos 0.08 --noise-rot 0.001] [--criterion i-opt|d-opt|o1] [--force]

The pool is drawn by :func:`cdra_jax.simulation.sample_poses` (uniform within the joint limits,
tension-feasible where the model has cables) and is also the workspace sample over which the
I-criterion averages the predicted tool-position variance (:mod:`cdra_jax.pose_selection`).

Writes a measurement-plan CSV in the measurement-file column naming (``pose`` and the module
state columns ``arm.state_names``; no ``measured.*`` columns: it is a plan to be measured), with
``#`` comment lines that record how it was made, and prints the expected accuracy of a
calibration from the planned poses against that of as many random ones. Provides
``register(subparsers)`` and ``run(args)`` for :mod:`cdra_jax.cli`, and ``main(argv)``.
"""

from __future__ import annotations

import argparse
import csv
import io
import sys
from collections.abc import Sequence
from pathlib import Path

from .cli_common import (
    check_distinct_files,
    check_output,
    check_seed,
    load_arm,
    standalone_main,
)
from .io.files import write_text_atomic
from .pose_selection import CRITERIA, DEFAULT_CRITERION, DEFAULT_POOL_SIZE

DEFAULT_NOISE_POS_MM = 0.08
"""The paper's FARO arm (Section VI)."""
DEFAULT_NOISE_ROT_RAD = 1e-3
"""An orientation from calibration-block points ~80 mm apart measured to 80 um."""


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``plan-poses`` subcommand (``func`` = :func:`run`)."""
    p = subparsers.add_parser(
        "plan-poses",
        help="choose the poses to measure (I-optimal selection from a pool)",
        description="Select the module states to measure from a pool of random feasible "
        "states so that the calibration is as informative as possible, and write them as a "
        "measurement plan CSV (pose + module state columns).",
    )
    p.add_argument("--model", metavar="M", help="model TOML file (default: the embedded CDRA)")
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
        help=f"position noise std of the measuring device, mm (default {DEFAULT_NOISE_POS_MM})",
    )
    p.add_argument(
        "--noise-rot",
        metavar="RAD",
        type=float,
        help=f"orientation noise std, rad (default {DEFAULT_NOISE_ROT_RAD})",
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
    p.add_argument("--force", action="store_true", help="overwrite an existing output file")
    p.set_defaults(func=run)
    return p


def _noise(args: argparse.Namespace):
    from .calibration import NoiseModel

    pos, rot = args.noise_pos, args.noise_rot
    if (pos is None) != (rot is None):
        raise ValueError("--noise-pos and --noise-rot go together: give both or neither")
    if pos is None:
        pos, rot = DEFAULT_NOISE_POS_MM, DEFAULT_NOISE_ROT_RAD
    for flag, v in (("--noise-pos", pos), ("--noise-rot", rot)):
        if not (v > 0 and v != float("inf")):
            raise ValueError(f"{flag} must be a positive number, got {v}")
    return NoiseModel(position_mm=pos, rotation_rad=rot)


def plan_csv_text(state_names: Sequence[str], states, comments: Sequence[str] = ()) -> str:
    """The plan CSV: ``#`` comment lines, a header ``pose,<state names>``, one row per pose.

    Pose ids are ``P01``, ``P02``, ... (zero-padded to the count); floats are written with
    ``repr`` (round trip exact).
    """
    buf = io.StringIO()
    for c in comments:
        buf.write(f"# {c}\n")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["pose", *state_names])
    width = max(2, len(str(len(states))))
    for i, row in enumerate(states, start=1):
        w.writerow([f"P{i:0{width}d}", *(repr(float(v)) for v in row)])
    return buf.getvalue()


def run(args: argparse.Namespace) -> int:
    """Run ``plan-poses``; returns the exit code (0)."""
    import jax
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    from .pose_selection import select_poses
    from .uncertainty import predicted_pose_covariance

    noise = _noise(args)
    if args.count < 4:
        raise ValueError(f"--count must be at least 4 (the paper's minimum), got {args.count}")
    if args.pool < args.count:
        raise ValueError(f"--pool ({args.pool}) must be at least --count ({args.count})")
    check_seed(args.seed)
    out = Path(args.out)
    check_distinct_files([("--out", out)], [("--model", args.model)])
    check_output(out, args.force, "--out")
    arm, label = load_arm(args.model)
    sel = select_poses(
        arm,
        args.count,
        noise,
        key=jax.random.PRNGKey(args.seed),
        pool_size=args.pool,
        criterion=args.criterion,
    )
    # Expected accuracy over the pool (a sample of the workspace), selected vs random poses.
    eval_q = sel.pool
    exp_sel = predicted_pose_covariance(arm, sel.states, noise, eval_q)
    rng = np.random.default_rng(args.seed % 2**64)  # numpy takes no negative seeds
    rand = [
        float(
            predicted_pose_covariance(
                arm, sel.pool[rng.choice(len(sel.pool), args.count, replace=False)], noise, eval_q
            ).expected_delta_p
        )
        for _ in range(20)
    ]
    comments = [
        f"measurement plan: {args.count} poses chosen by cdra-jax plan-poses ({args.criterion})",
        f"model: {label}; pool: {args.pool} states, seed {args.seed}",
        f"noise: {float(noise.position_mm)} mm, {float(noise.rotation_rad)} rad",
        f"log det information (identifiable subspace, rank {sel.rank}): {sel.log_det:.6g}; "
        f"O1: {sel.o1:.6g}",
        f"expected RMS accuracy after calibration: dp {float(exp_sel.expected_delta_p):.4g} mm, "
        f"dR {float(exp_sel.expected_delta_R):.4g} rad",
        "measure the tool pose at each row and add measured.x/y/z and measured.rx/ry/rz columns",
    ]
    write_text_atomic(out, plan_csv_text(arm.state_names, sel.states, comments), force=args.force)
    print(
        f"selected {args.count} of {args.pool} poses by {args.criterion}: log det "
        f"{sel.log_det:.6g} (greedy {sel.log_det_greedy:.6g}, {sel.n_exchanges} exchanges), "
        f"rank {sel.rank}, O1 {sel.o1:.4g}"
    )
    print(
        f"expected RMS accuracy over the workspace with noise {float(noise.position_mm)} mm / "
        f"{float(noise.rotation_rad)} rad:"
    )
    print(
        f"  planned poses: dp {float(exp_sel.expected_delta_p):.4g} mm, "
        f"dR {float(exp_sel.expected_delta_R):.4g} rad"
    )
    print(f"  {args.count} random poses (median of 20 draws): dp {np.median(rand):.4g} mm")
    print(f"wrote {out}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Stand-alone entry point (``python -m cdra_jax.cli_plan ...``), as ``cdra-jax plan-poses``."""
    return standalone_main("plan-poses", register, argv)


if __name__ == "__main__":
    sys.exit(main())
