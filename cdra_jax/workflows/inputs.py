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
from ..physics import model_effects

DEFAULT_MODEL_LABEL = "<cdra_jax>/data/cdra.toml"
"""Label of the embedded default model (the paper's 7-DOF CDRA) in reports and results."""

SEED_MIN, SEED_MAX = -(2**63), 2**63
"""Seeds accepted: ``SEED_MIN <= seed < SEED_MAX`` (what ``jax.random.PRNGKey`` takes with
64-bit integers)."""

BOUNDS: dict[str, tuple[float, float]] = {
    "max_iterations": (1, 10_000),
    "poses": (1, 1_000_000),
    "trials": (1, 10**9),
    "chunk": (1, 65_536),
    "verify": (1, 100_000),
    "count": (4, 100_000),
    "pool": (4, 1_000_000),
    "folds": (2, 100),
    "cpu_devices": (1, 1024),
    "processes": (1, 1024),
    "timeout": (1.0, 1e6),
    "noise_pos": (1e-9, 1e6),
    "noise_rot": (1e-12, 3.2),
    "d_v": (0.0, 1e6),
    "d_w": (0.0, 3.2),
    "cable_noise": (0.0, 1e6),
    "occlusion": (0.0, 0.95),
    "marker_error": (0.0, 1e4),
}
"""Allowed range (inclusive) of every numeric argument of the workflows and the command line,
by argument name (``--max-iterations`` is ``max_iterations``). The bounds keep memory and time
finite (iteration histories and chunks are allocated up front) and the arithmetic meaningful:
a noise std of 1e-300 mm would whiten residuals to overflow, a rotation beyond pi rad is no
rotation error. Counts are integers, scales are in mm and rad."""

Model = Arm | str | os.PathLike | None
"""A model argument: an arm, the path of a model TOML file, or ``None`` for the default arm."""
Data = Measurements | str | os.PathLike
"""A measurement argument: loaded measurements or the path of a measurement CSV."""


def resolve_arm(model: Model, label: str | None = None) -> tuple[Arm, str]:
    """``(arm, label)`` for a model argument; ``label`` overrides the derived one (the file
    name, ``"embedded CDRA"`` for ``None``, the arm's name for an :class:`Arm`).

    The model's ``[[effects]]`` are checked against the physics vocabulary here
    (:func:`cdra_jax.physics.model_effects`: effect, variant, location, parameter names and
    units), so that every command rejects a wrong entry with a message naming the file."""
    if isinstance(model, Arm):
        arm, label = model, label or model.name
    elif model is None:
        return default_arm(), label or DEFAULT_MODEL_LABEL
    else:
        arm, label = load_model(model), label or str(model)
    if arm.effects:
        model_effects(arm, label)
    return arm, label


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
    check_range(f_pos, position_mm, "noise_pos")
    check_range(f_rot, rotation_rad, "noise_rot")
    return NoiseModel(position_mm=position_mm, rotation_rad=rotation_rad)


def check_seed(seed: int, flag: str = "seed") -> int:
    """``seed`` unchanged when ``jax.random.PRNGKey`` accepts it, else a ``ValueError``."""
    if isinstance(seed, bool) or not isinstance(seed, int) or not SEED_MIN <= seed < SEED_MAX:
        raise ValueError(f"{flag} must be an integer in [-2^63, 2^63), got {seed}")
    return seed


def check_range(flag: str, value, name: str | None = None):
    """``value`` unchanged when it lies in ``BOUNDS[name]`` (``name`` defaults to ``flag`` without
    leading dashes, dashes as underscores), else a ``ValueError`` naming ``flag`` and the range.
    Integer bounds demand an integer."""
    key = name or flag.lstrip("-").replace("-", "_")
    low, high = BOUNDS[key]
    integral = isinstance(low, int) and isinstance(high, int)
    kind = "an integer" if integral else "a number"
    ok = (
        isinstance(value, int) and not isinstance(value, bool)
        if integral
        else isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    )
    if not ok or not low <= value <= high:
        span = f"[{low}, {high}]" if integral else f"[{low:g}, {high:g}]"
        raise ValueError(f"{flag} must be {kind} in {span}, got {value!r}")
    return value
