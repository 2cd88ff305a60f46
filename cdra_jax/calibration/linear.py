"""Rank-revealing minimum-norm least squares for the stacked calibration system (Eq. 10).

Eq. 10 writes ``X = (D^T D)^-1 D^T Y``. For the paper's arm ``D~`` has rank 22 of 24 (a rotation
about the elbow axis and a translation along it move freely between ``upper_arm`` and
``forearm``), so ``D^T D`` is singular. We use the pseudo-inverse instead: a thin SVD
``D = U S V^T`` and ``X = V S^+ U^T Y`` with singular values below ``rcond * s_max`` treated as
zero. The step is the minimum-Euclidean-norm solution in the parameter units (mm, rad); its
null-space component is exactly zero, so unidentifiable directions are never moved.

Default ``rcond``: ``eps ** (2/3)`` of the dtype (3.7e-11 in float64, 2.4e-5 in float32). The
structurally null singular values of the CDRA come out at ``~1e-16 s_max`` and the smallest
identifiable ones at ``~1e-3 s_max`` for random pose sets, so the threshold has many decades of
margin on both sides. Pass a larger ``rcond`` to truncate nearly-degenerate directions too.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike


def default_rcond(dtype) -> float:
    """``eps ** (2/3)`` of ``dtype``: the relative singular-value cut-off used by default."""
    return float(jnp.finfo(dtype).eps ** (2.0 / 3.0))


def min_norm_lstsq(
    A: ArrayLike, b: ArrayLike, rcond: float | None = None
) -> tuple[Array, Array, Array]:
    """Minimum-norm least-squares solution of ``A x ~= b`` with a rank-revealing cut-off.

    Args:
        A: ``(..., r, n)``.
        b: ``(..., r)``.
        rcond: relative singular-value cut-off (``None``: :func:`default_rcond`).

    Returns:
        ``(x (..., n), rank (...), s (..., min(r, n)))``: solution, numerical rank and singular
        values in decreasing order.
    """
    A = jnp.asarray(A)
    b = jnp.asarray(b, dtype=A.dtype)
    if rcond is None:
        rcond = default_rcond(A.dtype)
    U, s, Vt = jnp.linalg.svd(A, full_matrices=False)
    keep = s > rcond * s[..., :1]
    s_inv = jnp.where(keep, 1.0 / jnp.where(keep, s, 1.0), 0.0)
    Utb = jnp.einsum("...ri,...r->...i", U, b)
    x = jnp.einsum("...ij,...i->...j", Vt, s_inv * Utb)
    return x, jnp.sum(keep, axis=-1), s
