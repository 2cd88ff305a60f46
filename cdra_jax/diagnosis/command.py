"""``cdra-jax diagnose``: the missing-physics analyser on a model file and a measurement CSV.

Usage::

    cdra-jax diagnose --data D.csv --noise-pos MM --noise-rot RAD --out R.json \
        [--model M.toml] [--plots DIR] [--folds 5] [--seed 0] [--alpha 0.01] [--force]

Prints the plain-words report and the candidate table, writes the diagnosis JSON (and, with
``--plots``, residual-versus-regressor figures before and after the refit).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(subparsers) -> None:
    """Add the ``diagnose`` subcommand (see :mod:`cdra_jax.cli`)."""
    from ..cli import _add_force_option, _add_model_option, _add_noise_options

    p = subparsers.add_parser(
        "diagnose",
        help="find the missing physics a geometric calibration leaves in the recordings",
        description=(
            "Test whether the weighted geometric calibration of a model is consistent with the "
            "measuring device's noise and, if not, which non-geometric effect (joint "
            "compliance, cable elasticity, cable scale, backlash, periodic error, link "
            "bending, thermal drift) and where explains the misfit; refit it and report the "
            "physical parameters and the held-out improvement."
        ),
    )
    _add_model_option(p)
    p.add_argument("--data", metavar="D", required=True, help="measurement CSV file")
    p.add_argument("--out", metavar="R", required=True, help="diagnosis JSON file to write")
    _add_noise_options(p, "of the measuring device (without them the noise is estimated)")
    p.add_argument("--plots", metavar="DIR", help="write residual plots (PNG) into this folder")
    p.add_argument("--folds", type=int, default=5, help="cross-validation folds (default 5)")
    p.add_argument("--seed", type=int, default=0, help="seed of the folds (default 0)")
    p.add_argument("--alpha", type=float, default=0.01, help="significance level (default 0.01)")
    _add_force_option(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``diagnose``; exit code 0 (also when a mismatch is found)."""
    from ..cli import EXIT_OK, _check_output, _load_arm, _noise
    from ..cli_common import check_distinct_files

    noise = _noise(args)
    check_distinct_files([("--out", args.out)], [("--data", args.data), ("--model", args.model)])
    _check_output(args.out, args.force, "--out")
    if args.plots is not None and Path(args.plots).exists() and not Path(args.plots).is_dir():
        raise NotADirectoryError(f"--plots {args.plots}: exists and is not a folder")
    from ..io import load_measurements, write_text_atomic
    from .core import diagnose

    arm, label = _load_arm(args.model)
    meas = load_measurements(args.data, arm)
    d = diagnose(arm, meas, noise, seed=args.seed, folds=args.folds, alpha=args.alpha)
    out = d.to_dict()
    out["model"] = label
    out["data"] = str(args.data)
    write_text_atomic(args.out, json.dumps(out, indent=1) + "\n", force=args.force)
    lines = [d.report, "", d.table(), "", f"wrote {args.out}"]
    if args.plots is not None:
        from ..plots_diagnosis import save_diagnosis_plots

        for path in save_diagnosis_plots(arm, meas, d, args.plots, force=args.force):
            lines.append(f"wrote {path}")
    print("\n".join(lines))
    return EXIT_OK
