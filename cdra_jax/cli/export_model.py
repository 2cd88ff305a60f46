"""``cdra-jax export``: a (calibrated) model written back into its URDF.

Usage::

    cdra-jax export urdf --model cal.toml --urdf ROBOT.urdf --base LINK --tip LINK
        --out cal.urdf [--force]

A thin layer over :func:`cdra_jax.workflows.export_urdf`: writes the URDF with the chain's joint
origins carrying the model's fixed frames, prints what changed, and prints one ``warning: ...``
line on stderr for each thing the URDF cannot hold (cables, masses, effects, ...) or the writer
did not keep (XML comments).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..io.files import check_distinct_files, check_output
from . import common


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``export`` subcommand with its format ``urdf``."""
    p = subparsers.add_parser(
        "export",
        help="write a (calibrated) model back into its URDF",
        description="Write a model's fixed frames into the joint origins of a URDF chain.",
    )
    formats = p.add_subparsers(dest="format", metavar="FORMAT", required=True)
    u = formats.add_parser(
        "urdf",
        help="into the chain between two links of a URDF file",
        description="The chain's movable joints must be the model's modules (as after "
        "'cdra-jax import urdf' of the same chain). In each segment between movable joints the "
        "last joint's origin carries the model's frame; everything else of the file is kept.",
    )
    u.add_argument("--model", metavar="M", required=True, help="(calibrated) model TOML file")
    u.add_argument("--urdf", metavar="ROBOT.urdf", required=True, help="the original URDF")
    u.add_argument("--base", metavar="LINK", required=True, help="link the chain starts at")
    u.add_argument("--tip", metavar="LINK", required=True, help="link the chain ends at (tool)")
    u.add_argument("--out", metavar="URDF", required=True, help="URDF file to write")
    common.add_force_option(u)
    u.set_defaults(func=run)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``export urdf``; returns the exit code (0)."""
    out = Path(args.out)
    check_distinct_files([("--out", out)], [("--model", args.model), ("--urdf", args.urdf)])
    check_output(out, args.force, "--out")

    from ..workflows import export_urdf

    exported = export_urdf(args.model, args.urdf, args.base, args.tip)
    for w in exported.warnings():
        print(f"warning: {w}", file=sys.stderr)
    path = exported.save(out, force=args.force)
    print(exported.report())
    print(common.wrote(path))
    return common.EXIT_OK
