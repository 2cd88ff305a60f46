"""Helpers shared by the stand-alone subcommand modules (:mod:`.cli_plan`, :mod:`.cli_sweep`).

Each such module provides ``register(subparsers)`` and ``run(args)`` for :mod:`cdra_jax.cli`,
and a ``main(argv)`` entry point (``python -m cdra_jax.cli_<name> ...``) built from
:func:`standalone_main`.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

EMBEDDED_MODEL_LABEL = "embedded CDRA"
SEED_MIN, SEED_MAX = -(2**63), 2**63
"""Seeds ``--seed`` accepts: ``SEED_MIN <= seed < SEED_MAX`` (what ``jax.random.PRNGKey`` takes
with 64-bit integers, which the command line enables)."""


def load_arm(model: str | None) -> tuple[Any, str]:
    """``(arm, label)`` for ``--model``: the model file, or the embedded default arm when
    ``model`` is None (label ``"embedded CDRA"``). Raises what :func:`cdra_jax.io.load_model`
    raises (``ModelFileError``, a ``ValueError``, or ``OSError``)."""
    from .io import default_arm, load_model

    if model is None:
        return default_arm(), EMBEDDED_MODEL_LABEL
    return load_model(model), str(model)


def check_seed(seed: int, flag: str = "--seed") -> int:
    """``seed`` unchanged when ``jax.random.PRNGKey`` accepts it, else a ``ValueError``."""
    if isinstance(seed, bool) or not isinstance(seed, int) or not SEED_MIN <= seed < SEED_MAX:
        raise ValueError(f"{flag} must be an integer in [-2^63, 2^63), got {seed}")
    return seed


def check_non_negative(flag: str, value: float) -> float:
    """``value`` unchanged when it is a finite number >= 0, else a ``ValueError`` naming
    ``flag``."""
    if not 0 <= value < math.inf:
        raise ValueError(f"{flag} must be a non-negative number, got {value}")
    return value


def check_at_least(flag: str, value: int, low: int = 1) -> int:
    """``value`` unchanged when it is at least ``low``, else ``"<flag> must be >= <low>"``."""
    if value < low:
        raise ValueError(f"{flag} must be >= {low}, got {value}")
    return value


def check_output(path: str | os.PathLike | None, force: bool, flag: str) -> None:
    """Fail before any work when an output file exists (no ``--force``), is a folder, or its
    folder is missing (outputs never create folders)."""
    if path is None:
        return
    p = Path(path)
    if p.is_dir():
        raise IsADirectoryError(f"{flag} {p}: is a folder, expected a file name")
    if p.exists() and not force:
        raise FileExistsError(f"{p}: file exists; refusing to overwrite it (pass --force)")
    if not (p.parent if str(p.parent) else Path(".")).is_dir():
        raise FileNotFoundError(f"{flag} {p}: folder {p.parent} does not exist")


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether paths ``a`` and ``b`` name the same file (``os.path.samefile`` when both exist,
    so links and hard links count; else the resolved paths)."""
    pa, pb = Path(a), Path(b)
    try:
        if pa.exists() and pb.exists():
            return os.path.samefile(pa, pb)
    except OSError:
        pass
    return pa.resolve() == pb.resolve()


def check_distinct_files(
    outputs: Iterable[tuple[str, str | os.PathLike | None]],
    inputs: Iterable[tuple[str, str | os.PathLike | None]] = (),
) -> None:
    """Refuse an output that names the same file as an input or as another output, before any
    work: ``ValueError("--out and --data name the same file")``. Pairs are ``(flag, path)``;
    a ``None`` path is skipped."""
    outs = [(f, p) for f, p in outputs if p is not None]
    ins = [(f, p) for f, p in inputs if p is not None]
    for i, (flag, path) in enumerate(outs):
        for other, q in [*ins, *outs[:i]]:
            if same_file(path, q):
                raise ValueError(f"{flag} and {other} name the same file")


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


def standalone_main(
    command: str, register: Callable[[Any], argparse.ArgumentParser], argv: Sequence[str] | None
) -> int:
    """Parse ``argv`` (default ``sys.argv[1:]``) as ``cdra-jax <command> ...`` and run it.

    Returns the subcommand's exit code, or 1 after printing ``error: <message>`` to stderr for
    a ``ValueError``, ``OSError`` or failed run-time check (:func:`user_error_line`).
    """
    parser = argparse.ArgumentParser(prog="cdra-jax")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args([command, *(sys.argv[1:] if argv is None else argv)])
    try:
        return args.func(args)
    except Exception as e:
        line = user_error_line(e)
        if line is None:
            raise
        print(line, file=sys.stderr)
        return 1
