"""Trace-time checks of a calibration problem (shapes and pose counts raise ``ValueError``)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from ..arm import Arm
from .model import NoiseModel

MIN_POSES = 4
"""The paper's lower bound on the number of measured poses for Eq. 9 (Section IV)."""


def check_problem(
    arm: Arm, q: ArrayLike, measured: ArrayLike, *, allow_underdetermined: bool = False
) -> tuple[Array, Array]:
    """Validate shapes of one (unbatched) problem and return ``(q, measured)`` as float arrays.

    Raises:
        ValueError: wrong shapes, or fewer than 4 poses without ``allow_underdetermined``.
    """
    q = jnp.asarray(q)
    measured = jnp.asarray(measured)
    dtype = jnp.result_type(q.dtype, measured.dtype, jnp.float32)
    q = q.astype(dtype)
    measured = measured.astype(dtype)
    if measured.ndim != 3 or measured.shape[-2:] != (4, 4):
        raise ValueError(
            f"measured tool poses must have shape (m, 4, 4), got {measured.shape} "
            "(vmap over trials for batches)"
        )
    m = measured.shape[0]
    if q.shape != (m, arm.dof):
        raise ValueError(
            f"module states must have shape (m, dof) = ({m}, {arm.dof}) with columns "
            f"{arm.state_names}, got {q.shape}"
        )
    if m < MIN_POSES and not allow_underdetermined:
        raise ValueError(
            f"{m} measured poses given; the calibration needs at least {MIN_POSES} "
            "(Section IV, Eq. 9). Pass allow_underdetermined=True to accept a minimum-norm "
            "solve of an underdetermined system."
        )
    if m < 1:
        raise ValueError("no measured poses given")
    return q, measured


def check_noise(noise: NoiseModel | None, m: int) -> None:
    """Trace-time check that each std of ``noise`` is a number or one per pose.

    Raises:
        ValueError: ``noise.position_mm`` or ``noise.rotation_rad`` of a shape other than
            ``()`` or ``(m,)``, naming the field and the expected shape.
    """
    if noise is None:
        return
    for name in ("position_mm", "rotation_rad"):
        shape = np.shape(getattr(noise, name))
        if shape not in ((), (m,)):
            raise ValueError(
                f"noise.{name} must be a number (shape ()) or one std per pose (shape (m,) = "
                f"({m},)), got shape {shape}"
            )


def require_finite_states(arm: Arm, q: np.ndarray, name: str = "module states") -> None:
    """Host-side check that the states ``q (m, dof)`` are finite (the analyses' SVDs would
    otherwise fail with numpy's unnamed "SVD did not converge").

    Raises:
        ValueError: naming the first non-finite entry (row and state name).
    """
    bad = np.argwhere(~np.isfinite(q))
    if bad.size:
        i, j = (int(v) for v in bad[0])
        raise ValueError(
            f"{name} must be finite: row {i}, column {arm.state_names[j]!r} is {float(q[i, j])}"
        )
