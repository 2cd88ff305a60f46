"""The environment of the subprocesses the tests start (the command line, scripts on two
devices): the code of this checkout, whatever version of the package is installed."""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
"""The repository root (the checkout under test)."""


def checkout_env(*drop: str, **extra: str) -> dict[str, str]:
    """``os.environ`` with the checkout first on ``PYTHONPATH`` (so that ``python -m
    cdra_jax.cli`` runs this checkout's code, as the tests in this process do), the variables
    ``drop`` removed and ``extra`` set."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    for name in drop:
        env.pop(name, None)
    env.update(extra)
    return env
