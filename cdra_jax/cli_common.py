"""Helpers shared by the stand-alone subcommand modules (:mod:`.cli_plan`, :mod:`.cli_sweep`).

Each such module provides ``register(subparsers)`` and ``run(args)`` for :mod:`cdra_jax.cli`,
and a ``main(argv)`` entry point (``python -m cdra_jax.cli_<name> ...``) built from
:func:`standalone_main`.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from typing import Any

EMBEDDED_MODEL_LABEL = "embedded CDRA"


def load_arm(model: str | None) -> tuple[Any, str]:
    """``(arm, label)`` for ``--model``: the model file, or the embedded default arm when
    ``model`` is None (label ``"embedded CDRA"``). Raises what :func:`cdra_jax.io.load_model`
    raises (``ModelFileError``, a ``ValueError``, or ``OSError``)."""
    from .io import default_arm, load_model

    if model is None:
        return default_arm(), EMBEDDED_MODEL_LABEL
    return load_model(model), str(model)


def standalone_main(
    command: str, register: Callable[[Any], argparse.ArgumentParser], argv: Sequence[str] | None
) -> int:
    """Parse ``argv`` (default ``sys.argv[1:]``) as ``cdra-jax <command> ...`` and run it.

    Returns the subcommand's exit code, or 1 after printing ``error: <message>`` to stderr for
    a ``ValueError`` or ``OSError`` (bad values, existing or unreadable files).
    """
    parser = argparse.ArgumentParser(prog="cdra-jax")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args([command, *(sys.argv[1:] if argv is None else argv)])
    try:
        return args.func(args)
    except (ValueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
