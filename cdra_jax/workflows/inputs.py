"""What every workflow takes: a model, measurements, a noise model, seeds and counts.

A workflow accepts an :class:`~cdra_jax.arm.Arm` or the path of a model TOML file (``None``: the
embedded default arm of the paper), and :class:`~cdra_jax.io.Measurements` or the path of a
measurement CSV; these helpers turn either into the object and a label for reports. The
argument checks raise a ``ValueError`` naming the argument (the command line passes its option
name, e.g. ``--seed``), so that Python and CLI users get the same message.
"""

from __future__ import annotations

import hashlib
import math
import os
from pathlib import Path

from ..arm import Arm
from ..calibration import NoiseModel
from ..io import Measurements, default_arm, load_measurements, load_model

DEFAULT_MODEL_LABEL = "<cdra_jax>/data/cdra.toml"
"""Label of the embedded default model (the paper's 7-DOF CDRA) in reports and results."""

SEED_MIN, SEED_MAX = -(2**63), 2**63
"""Seeds accepted: ``SEED_MIN <= seed < SEED_MAX`` (what ``jax.random.PRNGKey`` takes with
64-bit integers)."""

Model = Arm | str | os.PathLike | None
"""A model argument: an arm, the path of a model TOML file, or ``None`` for the default arm."""
Data = Measurements | str | os.PathLike
"""A measurement argument: loaded measurements or the path of a measurement CSV."""


def resolve_arm(model: Model, label: str | None = None) -> tuple[Arm, str]:
    """``(arm, label)`` for a model argument; ``label`` overrides the derived one (the file
    name, ``"embedded CDRA"`` for ``None``, the arm's name for an :class:`Arm`)."""
    if isinstance(model, Arm):
        return model, label or model.name
    if model is None:
        return default_arm(), label or DEFAULT_MODEL_LABEL
    return load_model(model), label or str(model)


def resolve_measurements(
    data: Data, arm: Arm, label: str | None = None
) -> tuple[Measurements, str, str | None]:
    """``(measurements, label, sha256)`` for a measurement argument: a CSV path is read
    against ``arm`` (its SHA-256 is recorded in results), loaded measurements pass through
    (``sha256`` is ``None``)."""
    if isinstance(data, Measurements):
        return data, label or "<measurements>", None
    path = Path(data)
    meas = load_measurements(path, arm)
    return meas, label or str(data), hashlib.sha256(path.read_bytes()).hexdigest()


def noise_model(position_mm: float | None, rotation_rad: float | None, *, flags=None):
    """The :class:`~cdra_jax.calibration.NoiseModel` of two stds (both or neither), or None.

    ``flags`` names the two arguments in messages (default ``("noise_pos", "noise_rot")``).
    """
    f_pos, f_rot = flags or ("noise_pos", "noise_rot")
    if (position_mm is None) != (rotation_rad is None):
        raise ValueError(f"{f_pos} and {f_rot} go together: give both or neither")
    if position_mm is None or rotation_rad is None:
        return None
    for flag, v in ((f_pos, position_mm), (f_rot, rotation_rad)):
        if not v > 0 or v == math.inf:
            raise ValueError(f"{flag} must be a positive number, got {v}")
    return NoiseModel(position_mm=position_mm, rotation_rad=rotation_rad)


def check_seed(seed: int, flag: str = "seed") -> int:
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
