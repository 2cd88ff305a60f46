"""``cdra-jax demo``: regenerate the paper's Table I, Fig. 5 and Fig. 7 on the default CDRA.

A thin layer over :func:`cdra_jax.workflows.demo`: prints each table next to the paper's
numbers as soon as it is computed, then writes the report, a JSON summary and the figures into
an output folder: ``--out-dir DIR``, or by default a new folder ``cdra-demo-<date>-<time>`` in
the current directory (never files loose in the current directory, never over existing files
without ``--force``).
"""

from __future__ import annotations

import argparse
import datetime
import sys
from pathlib import Path

from ..io.files import check_output
from . import common

OUTPUT_FILES: tuple[str, ...] = (
    "report.txt",
    "summary.json",
    "fig5_convergence.png",
    "fig7_noise.png",
    "fig7_parameter_error.png",
)
"""What the demo writes into its output folder."""


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``demo`` subcommand."""
    p = subparsers.add_parser(
        "demo",
        help="regenerate the paper's Table I, Fig. 5 and Fig. 7 on the default CDRA",
        description="Regenerate the paper's Table I, Fig. 5 and Fig. 7 on the embedded default "
        "arm: print the tables next to the paper's numbers and write the figures, the report "
        "and a JSON summary into an output folder (about half a minute on two CPU cores).",
    )
    p.add_argument(
        "--full",
        action="store_true",
        help="notebook sizes: 1000 trials per pose count, m = 4..40 (several minutes)",
    )
    p.add_argument(
        "--out-dir",
        metavar="DIR",
        default=None,
        help="output folder (default: a new folder ./cdra-demo-YYYYMMDD-HHMMSS)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="write into an existing non-empty --out-dir, overwriting the demo's own files",
    )
    p.add_argument("--seed", type=int, default=0, help="PRNG seed of all studies (default 0)")
    p.set_defaults(func=run)
    return p


def output_folder(out: str | None, force: bool) -> Path:
    """The folder to write into, created; never one whose files would be overwritten silently.

    ``None``: a new folder named after the current time in the current directory (with
    ``-2``, ``-3``, ... when that name is taken)."""
    if out is None:
        base = "cdra-demo-" + datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
        for name in [base] + [f"{base}-{i}" for i in range(2, 1000)]:
            c = Path(name)
            try:
                c.mkdir()
            except FileExistsError:
                continue
            return c
        raise FileExistsError(f"no free output folder {base}[-N] here; pass --out-dir DIR")
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise FileExistsError(f"--out-dir {out}: exists and is not a folder")
    if path.exists() and any(path.iterdir()) and not force:
        raise FileExistsError(
            f"--out-dir {out}: folder exists and is not empty; pass --force to overwrite the "
            f"demo's files in it ({', '.join(OUTPUT_FILES)})"
        )
    if path.is_dir():  # before any work: never a folder, FIFO or device in the way
        for name in OUTPUT_FILES:
            check_output(path / name, force, "--out-dir")
    path.mkdir(parents=True, exist_ok=True)
    return path


def run(args: argparse.Namespace) -> int:
    """Run the demo; returns the exit code (0)."""
    from ..workflows import demo
    from ..workflows.inputs import check_seed

    check_seed(args.seed, "--seed")
    out = output_folder(args.out_dir, args.force)
    print(f"output folder: {out}", flush=True)
    result = demo(
        full=args.full,
        seed=args.seed,
        log=lambda text: print(text, flush=True),
        progress=lambda line: print(line, file=sys.stderr, flush=True),
    )
    result.save(out, force=args.force)
    print(f"wrote {', '.join(OUTPUT_FILES)} to {out.resolve()}")
    return common.EXIT_OK
