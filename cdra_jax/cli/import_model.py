"""``cdra-jax import``: a model file from a URDF chain or a DH table.

Usage::

    cdra-jax import urdf ROBOT.urdf --base LINK --tip LINK --out model.toml [--name N] [--force]
    cdra-jax import dh TABLE.csv --convention standard|modified --out model.toml [--name N]
        [--force]

A thin layer over :func:`cdra_jax.workflows.import_urdf` and :func:`cdra_jax.workflows.
import_dh`: writes the model TOML (the model file contract) and prints a summary.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..io.files import check_distinct_files, check_output
from . import common

_CONVENTIONS = ("standard", "modified")  # as io.dh.CONVENTIONS (kept here: --help starts no JAX)


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``import`` subcommand with its formats ``urdf`` and ``dh``."""
    p = subparsers.add_parser(
        "import",
        help="make a model file from a URDF chain or a DH table",
        description="Write a model TOML file from the serial chain between two links of a "
        "URDF file, or from a Denavit-Hartenberg table (CSV). Units: mm, rad.",
    )
    formats = p.add_subparsers(dest="format", metavar="FORMAT", required=True)
    u = formats.add_parser(
        "urdf",
        help="the chain between two links of a URDF file",
        description="Fixed joints are folded into the fixed frames; each revolute, continuous "
        "or prismatic joint becomes a module named as the joint. Lengths become mm.",
    )
    u.add_argument("urdf", metavar="ROBOT.urdf", help="URDF file (meshes are not loaded)")
    u.add_argument("--base", metavar="LINK", required=True, help="link the chain starts at")
    u.add_argument("--tip", metavar="LINK", required=True, help="link the chain ends at (tool)")
    d = formats.add_parser(
        "dh",
        help="a Denavit-Hartenberg table (CSV)",
        description="Columns joint,type,a,alpha,d,theta[,lower,upper] (type revolute or "
        "prismatic; a, d in mm; alpha, theta in rad; limits in rad or mm). The joint variable "
        "adds to theta (revolute) or d (prismatic).",
    )
    d.add_argument("table", metavar="TABLE.csv", help="DH table")
    d.add_argument(
        "--convention",
        choices=_CONVENTIONS,
        required=True,
        help="standard (Denavit-Hartenberg) or modified (Craig)",
    )
    for sub in (u, d):
        sub.add_argument("--out", metavar="TOML", required=True, help="model file to write")
        sub.add_argument("--name", metavar="N", help="model name (default: robot or file name)")
        common.add_force_option(sub)
        sub.set_defaults(func=run)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``import urdf`` or ``import dh``; returns the exit code (0)."""
    source = args.urdf if args.format == "urdf" else args.table
    out = Path(args.out)
    check_distinct_files([("--out", out)], [(args.format.upper(), source)])
    check_output(out, args.force, "--out")

    from ..workflows import import_dh, import_urdf

    if args.format == "urdf":
        imported = import_urdf(source, args.base, args.tip, name=args.name)
    else:
        imported = import_dh(source, args.convention, name=args.name)
    path = imported.save(out, force=args.force)
    print(imported.report())
    print(common.wrote(path))
    return common.EXIT_OK
