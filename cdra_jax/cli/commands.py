"""The ``cdra-jax`` command line: one subcommand per workflow of :mod:`cdra_jax.workflows`.

Exit codes (:mod:`.common`): 0 success; 1 bad input or a file problem (one line ``error: ...`` on
stderr, no traceback); 2 wrong usage (argparse); 3 a calibration that did not converge (the
result file is still written, with ``"converged": false``); 130 interrupted (``SIGINT``) and 143
terminated (``SIGTERM``), with no partial output file left behind. Warnings (implausible data, a
degenerate or poorly conditioned pose set, outliers) do not change the exit code: each is one
``warning: ...`` line on stderr and an entry of ``warnings`` in the result file.

Adding a subcommand: a module of this package with ``register(subparsers)`` and ``run(args)``,
appended to :data:`SUBCOMMANDS`.
"""

from __future__ import annotations

import os
import sys
import warnings
from collections.abc import Sequence
from types import ModuleType

from . import (
    calibrate,
    common,
    demo,
    diagnose,
    export_model,
    import_model,
    plan_poses,
    simulate,
    sweep,
    validate,
)

SUBCOMMANDS: tuple[ModuleType, ...] = (
    demo,
    simulate,
    calibrate,
    validate,
    diagnose,
    sweep,
    plan_poses,
    import_model,
    export_model,
)
"""The subcommand modules, in the order ``--help`` lists them."""


def build_parser():
    """The ``cdra-jax`` argument parser with every subcommand of :data:`SUBCOMMANDS`."""
    import argparse

    from ..io.results import package_version

    parser = argparse.ArgumentParser(
        prog="cdra-jax",
        description="Kinematic calibration of serial and modular (cable-driven) robot arms "
        "(Mustafa et al., ICRA 2008). Units: mm, rad.",
    )
    parser.add_argument("--version", action="version", version=f"cdra-jax {package_version()}")
    parser.add_argument(
        "--no-cache",
        action="store_true",
        default=bool(os.environ.get("CDRA_JAX_NO_CACHE")),
        help="do not keep compiled programs between runs (default: kept in "
        "$CDRA_JAX_CACHE_DIR, else ~/.cache/cdra_jax/xla, so that a second run with the same "
        "shapes starts in a fraction of the time; CDRA_JAX_NO_CACHE=1 has the same effect)",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module in SUBCOMMANDS:
        before = set(subparsers.choices)
        module.register(subparsers)
        for name in set(subparsers.choices) - before:  # func defaults to the module's run
            if subparsers.choices[name].get_default("func") is None:
                subparsers.choices[name].set_defaults(func=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``cdra-jax`` with ``argv`` (default ``sys.argv[1:]``); returns the exit code.

    Enables ``jax_enable_x64`` before running any subcommand and turns ``ValueError``,
    ``OSError`` and a failed run-time check inside compiled code into one ``error: ...`` line.
    Run as the program (``argv`` not given), it also makes Python's cycle collector run less
    often (:data:`cdra_jax.compilation.GC_THRESHOLDS`): tracing and lowering the programs a
    command runs creates millions of short-lived objects.
    """
    import gc
    import threading

    import jax
    import numpy as np

    from ..compilation import GC_THRESHOLDS, enable_persistent_cache
    from ..io.files import remove_temporary_files_on_sigterm

    jax.config.update("jax_enable_x64", True)
    if argv is None:
        gc.set_threshold(*GC_THRESHOLDS)
    if threading.current_thread() is threading.main_thread():
        remove_temporary_files_on_sigterm()  # SIGTERM: temporary files removed, exit 143
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help, --version, usage errors
        return int(e.code or 0) if not isinstance(e.code, str) else common.EXIT_USAGE
    args.argv = list(sys.argv[1:] if argv is None else argv)  # e.g. to start the same command
    if not args.no_cache:
        try:
            enable_persistent_cache()
        except OSError as e:  # an unwritable cache folder costs speed, never the run
            print(f"warning: compilation cache off: {e}", file=sys.stderr)
    try:
        # numpy's floating-point warnings are never shown: every bad value is caught by the
        # readers and the checks, which name the file, row and column instead.
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            return int(args.func(args) or 0)
    except KeyboardInterrupt:  # SIGINT: what was being written is removed
        print("error: interrupted; no partial output file was left", file=sys.stderr)
        return common.EXIT_INTERRUPTED
    except Exception as e:  # user errors (common.user_error_line) only; the rest raises
        line = common.user_error_line(e)
        if line is None:
            raise
        print(line, file=sys.stderr)
        return common.EXIT_ERROR


if __name__ == "__main__":
    sys.exit(main())
