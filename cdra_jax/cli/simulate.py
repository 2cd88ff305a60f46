"""``cdra-jax simulate``: a synthetic measurement CSV (Section V of the paper).

A thin layer over :func:`cdra_jax.workflows.simulate`: prints the preset errors, writes the
measurement CSV (the preset errors as ``#`` comments) and, with ``--truth``, the truth JSON.
"""

from __future__ import annotations

import argparse

from ..io.files import check_distinct_files, check_output
from ..workflows.inputs import check_range
from . import common


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``simulate`` subcommand."""
    p = subparsers.add_parser(
        "simulate",
        help="write a synthetic measurement CSV (Section V of the paper)",
        description=(
            "Simulate measurements as in Section V of the paper: random module states within the "
            "joint limits, preset errors on the fixed frames (T_actual = exp(dt) T_nominal), "
            "tool poses of the erroneous arm, optional measurement noise. The preset errors are "
            "written as '#' comments at the top of the CSV and, with --truth, as JSON."
        ),
    )
    common.add_model_option(p)
    p.add_argument("--poses", metavar="N", type=int, required=True, help="number of poses")
    p.add_argument("--seed", metavar="S", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--errors",
        metavar="random|zero|FILE",
        default="random",
        help="preset frame errors: random (uniform in +-d_v, +-d_w; default), zero, or a "
        "JSON/TOML file of per-frame error twists",
    )
    p.add_argument(
        "--d-v",
        metavar="MM",
        type=float,
        help="range of random translation errors, per component (default 1 mm)",
    )
    p.add_argument(
        "--d-w",
        metavar="RAD",
        type=float,
        help="range of random rotation errors, per component (default 0.05 rad)",
    )
    common.add_noise_options(p, "added to the measured tool poses (default: noise-free)")
    p.add_argument(
        "--cables",
        action="store_true",
        help="write the states of modules with cables as cable lengths <module>.l1 ... .lN",
    )
    p.add_argument(
        "--cable-noise",
        metavar="MM",
        type=float,
        help="std of Gaussian noise on each cable length; needs --cables (default 0)",
    )
    p.add_argument(
        "--points",
        action="store_true",
        help="measure points instead of full tool poses: the model's [[markers]] "
        "(measured.<marker>.x/y/z), or the tool origin (measured.x/y/z) for a model without "
        "markers; --noise-pos is then the std of each point coordinate, and --noise-rot is not "
        "needed",
    )
    p.add_argument(
        "--occlusion",
        metavar="P",
        type=float,
        help="with --points: probability that a point is not seen in a row (default 0)",
    )
    p.add_argument(
        "--marker-error",
        metavar="MM",
        type=float,
        help="with --points: markers with calibrate = true sit off their model position by up "
        "to MM per component (default 0)",
    )
    p.add_argument(
        "--device-frame",
        metavar=("X", "Y", "Z", "RX", "RY", "RZ"),
        type=float,
        nargs=6,
        help="write the measurements in a measuring device's frame: the pose of the robot's "
        "world frame in it (mm, rotation vector in rad)",
    )
    p.add_argument("--out", metavar="D", required=True, help="measurement CSV file to write")
    p.add_argument("--truth", metavar="T.json", help="also write the preset errors as JSON")
    common.add_force_option(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``simulate``; returns the exit code (0)."""
    if args.points and args.noise_pos is not None and args.noise_rot is None:
        # Points carry no orientation: the rotation std is not used; any valid value will do.
        args.noise_rot = 1e-3
    noise = common.noise(args)
    check_range("--poses", args.poses)
    if args.errors != "random" and (args.d_v is not None or args.d_w is not None):
        raise ValueError("--d-v/--d-w set the range of random errors; they need --errors random")
    if args.cable_noise is not None and not args.cables:
        raise ValueError("--cable-noise needs --cables (noise on the written cable lengths)")
    for flag, v in (
        ("--d-v", args.d_v),
        ("--d-w", args.d_w),
        ("--cable-noise", args.cable_noise),
        ("--occlusion", args.occlusion),
        ("--marker-error", args.marker_error),
    ):
        if v is not None:
            check_range(flag, v)
    if (args.occlusion is not None or args.marker_error is not None) and not args.points:
        raise ValueError("--occlusion and --marker-error need --points (measured points)")
    errors_file = None if args.errors in ("random", "zero") else args.errors
    check_distinct_files(
        [("--out", args.out), ("--truth", args.truth)],
        [("--model", args.model), ("--errors", errors_file)],
    )
    check_output(args.out, args.force, "--out")
    check_output(args.truth, args.force, "--truth")

    from ..workflows import simulate

    sim = simulate(
        args.model,
        args.poses,
        seed=_seed(args.seed),
        errors=args.errors,
        d_v=args.d_v,
        d_w=args.d_w,
        noise=noise,
        cables=args.cables,
        cable_noise=args.cable_noise,
        points=args.points,
        occlusion=args.occlusion or 0.0,
        marker_error_mm=args.marker_error or 0.0,
        device_frame=args.device_frame,
    )
    written = sim.save(args.out, args.truth, force=args.force)
    print("\n".join([sim.report(), *(common.wrote(p) for p in written)]))
    return common.EXIT_OK


def _seed(seed: int) -> int:
    from ..workflows.inputs import check_seed

    return check_seed(seed, "--seed")
