"""What every subcommand shares: exit codes, common options, and the one-line user errors.

Each subcommand is a module of :mod:`cdra_jax.cli` with ``register(subparsers)`` (adds its parser
and ``set_defaults(func=run)``) and ``run(args) -> int`` (argument checks, then one call of a
workflow of :mod:`cdra_jax.workflows`, then printing its report and writing its files). The
workflows are imported inside ``run``, so that ``--help`` answers without starting JAX.
"""

from __future__ import annotations

import argparse
import os

EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_NOT_CONVERGED = 0, 1, 2, 3
"""Exit codes: success; bad input or a file problem (one ``error: ...`` line on stderr); wrong
usage (argparse); a calibration that did not converge (its result file is still written)."""
EXIT_UNTRUSTED = 4
"""The calibrated model fits the measured points worse than the nominal one: the result is still
written, with ``"trusted": false``, and must not be used."""
EXIT_INTERRUPTED, EXIT_TERMINATED = 130, 143
"""Interrupted by ``SIGINT`` (Ctrl-C) or terminated by ``SIGTERM``; no partial file is left."""


def add_model_option(p: argparse.ArgumentParser) -> None:
    """``--model M``: a model TOML file (default: the embedded 7-DOF CDRA)."""
    p.add_argument(
        "--model",
        metavar="M",
        help="model TOML file (default: the embedded 7-DOF CDRA of the paper)",
    )


def add_noise_options(p: argparse.ArgumentParser, what: str) -> None:
    """``--noise-pos MM`` and ``--noise-rot RAD``: the measuring device's noise (std)."""
    p.add_argument("--noise-pos", metavar="MM", type=float, help=f"position noise std (mm) {what}")
    p.add_argument(
        "--noise-rot", metavar="RAD", type=float, help=f"orientation noise std (rad) {what}"
    )


def add_force_option(p: argparse.ArgumentParser) -> None:
    """``--force``: replace existing output files."""
    p.add_argument("--force", action="store_true", help="overwrite existing output files")


def noise(args: argparse.Namespace):
    """The :class:`~cdra_jax.calibration.NoiseModel` of ``--noise-pos``/``--noise-rot`` (both
    or neither), or None."""
    from ..workflows import noise_model

    return noise_model(args.noise_pos, args.noise_rot, flags=("--noise-pos", "--noise-rot"))


def wrote(path: str | os.PathLike) -> str:
    """The line printed for each file written."""
    return f"wrote {path}"


def runtime_error_text(e: BaseException) -> str:
    """The message of a run-time check inside compiled code (``equinox.EquinoxRuntimeError``)
    without JAX's stack and debugging advice, plus a hint for the CLI user where one is known."""
    text = str(e)
    marker = "EquinoxRuntimeError: "
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    msg = next((ln.split(marker, 1)[1] for ln in lines if marker in ln), None)
    if msg is None:
        msg = next(
            (ln for ln in lines if not ln.startswith(("Above is the stack", "File "))),
            type(e).__name__,
        )
    if "tension closure" in msg:  # the advice (raise oversample ...) is for the Python API
        msg = (
            msg.split(";")[0] + ": the model's cables cannot hold (almost) any module state "
            "within the joint limits; check the cables and limits of each cabled module in the "
            "model file (a module with d degrees of freedom needs at least d + 1 cables)"
        )
    return msg


def user_error_line(e: BaseException) -> str | None:
    """``"error: ..."`` (one line) for the exceptions that are user errors (``ValueError``,
    ``OSError``, a failed run-time check of compiled code), else None."""
    import equinox as eqx

    if isinstance(e, eqx.EquinoxRuntimeError):
        text = runtime_error_text(e)
    elif isinstance(e, OSError) and e.filename is not None and e.strerror:
        text = f"{e.filename}: {e.strerror}"  # not "[Errno 2] No such file ...: 'name'"
    elif isinstance(e, ValueError | OSError):
        text = str(e) or type(e).__name__
    else:
        return None
    return "error: " + " ".join(text.split())
