"""Closed-form inverses of the tiny (1x1 to 3x3) symmetric systems of the module solvers.

``jnp.linalg.solve`` compiles to a pivoted LU per call site, which dominates the compile time
of the small batched Gauss-Newton and Newton loops here; the adjugate formula is exact
arithmetic of the same accuracy (relative error ~ condition number x eps) for these sizes.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array


def small_inv(H: Array) -> Array:
    """Inverse of ``H (..., d, d)`` for d in {1, 2, 3} by the adjugate formula."""
    d = H.shape[-1]
    if d == 1:
        return 1.0 / H
    if d == 2:
        a, b, c, e = H[..., 0, 0], H[..., 0, 1], H[..., 1, 0], H[..., 1, 1]
        det = a * e - b * c
        adj = jnp.stack([jnp.stack([e, -b], -1), jnp.stack([-c, a], -1)], -2)
        return adj / det[..., None, None]
    if d == 3:
        r0, r1, r2 = H[..., 0, :], H[..., 1, :], H[..., 2, :]
        c0, c1, c2 = jnp.cross(r1, r2), jnp.cross(r2, r0), jnp.cross(r0, r1)
        det = jnp.sum(r0 * c0, axis=-1)
        return jnp.stack([c0, c1, c2], axis=-1) / det[..., None, None]
    return jnp.linalg.inv(H)


def small_solve(H: Array, g: Array) -> Array:
    """Solution ``x (..., d)`` of ``H x = g`` for ``H (..., d, d)``, d in {1, 2, 3}."""
    return jnp.einsum("...ij,...j->...i", small_inv(H), g)
