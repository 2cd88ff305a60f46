"""The structural null space of the calibration Jacobian ``D`` (Eq. 8), in closed form.

With left-multiplied frame errors (Eqs. 11-14) a twist ``dt_j`` on the fixed frame ``F_j``
moves the tool by the world twist ``Ad(P_j) dt_j``, ``P_j`` the world pose before ``F_j``
(``P_0 = I``), so that ``D = [Ad(P_0), ..., Ad(P_K)]`` (Eq. 8, one block row per pose). Module
``i`` sits between ``F_i`` and ``F_{i+1}`` (``P_{i+1} = P_i F_i M_i(q_i)``). Let ``xi`` be a
twist, in the module's base frame, that every motion of the module leaves unchanged:
``Ad(M_i(q)) xi = xi`` for all ``q``. Then

    X = (dt_i = -Ad(F_i) xi,  dt_{i+1} = xi,  every other dt_j = 0)

moves nothing at any pose: ``Ad(P_{i+1}) xi = Ad(P_i) Ad(F_i) Ad(M_i) xi = Ad(P_i) Ad(F_i) xi``
cancels the first block (exactly, not only to first order: ``M exp(xi) = exp(xi) M`` and
``F exp(xi) = exp(Ad(F) xi) F``). The invariant twists of each module kind, with ``Ad(M) =
[[R, hat(p) R], [0, R]]`` (twists ``(v, w)``):

* revolute about the unit axis ``a`` through the module origin (``R = exp(q hat(a))``,
  ``p = 0``): ``R v = v`` and ``R w = w`` for all ``q``, so ``xi`` in span ``{(a, 0), (0, a)}``:
  translation along and rotation about the joint axis (2 directions). (For an axis through a
  point ``c`` other than the origin, which the model's modules do not have, the rotation would
  be the twist ``(c x a, a)``: conjugate by the translation to ``c``.);
* prismatic along ``a`` (``R = I``, ``p = q a``): ``(v + q a x w, w) = (v, w)`` for all ``q``, so
  ``w`` parallel to ``a`` and ``v`` free: ``{(e_1, 0), (e_2, 0), (e_3, 0), (0, a)}`` (4);
* spherical about the module origin (``p = 0``, every ``R``): ``v = w = 0`` (none).

The directions of different modules are linearly independent (the last module's block
``dt_{i+1} = xi`` appears in no earlier module's direction), so the structural nullity is
``2 R + 4 P`` (``R`` revolute, ``P`` prismatic modules) and the generic rank of the
calibration ``6 (K+1) - 2 R - 4 P = 6 + 4 R + 2 P + 6 S``, the count of identifiable
parameters of a product-of-exponentials model (Chen, Yang, Tang and Yeo, 2001). For the paper's
arm (two spherical modules and a revolute elbow) that is rank 22 of 24, the two elbow-axis
directions of :mod:`cdra_jax.identifiability`. Pose sets that see less (too few or degenerate
poses) add null directions of their own; this module only gives the structural ones, which
hold for every pose set and every noise model (whitening ``G D`` keeps ``null(D)``).

The basis depends on the current frames through ``Ad(F_i)``: the solvers rebuild it at every
iterate (:func:`null_basis`, a few 6x6 products and the QR of an ``(n, k)`` matrix).
"""

from __future__ import annotations

import functools
import operator

import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from .. import lie
from ..arm import Arm


def null_generators(arm: Arm, dtype=None) -> tuple[tuple[int, ...], Array]:
    """The invariant twists of the arm's modules: ``(modules, xi)``.

    Returns:
        ``modules``: a static tuple, for each generator the index ``i`` of its module (between
        ``frames[i]`` and ``frames[i+1]``); ``xi (k, 6)``: the generators ``(v, w)`` in the
        module base frames (unit vectors; see the module docstring). ``k`` is ``2 R + 4 P``;
        for an arm of spherical modules only, ``k = 0``.
    """
    dtype = dtype or jnp.asarray(arm.frames).dtype
    modules: list[int] = []
    rows = []
    z3 = jnp.zeros(3, dtype)
    for i, mod in enumerate(arm.modules):
        a = jnp.asarray(mod.axis, dtype)
        if mod.kind == "revolute":
            new = [jnp.concatenate([a, z3]), jnp.concatenate([z3, a])]
        elif mod.kind == "prismatic":
            eye = jnp.eye(3, dtype=dtype)
            new = [jnp.concatenate([eye[j], z3]) for j in range(3)]
            new.append(jnp.concatenate([z3, a]))
        else:  # spherical: no invariant twist
            new = []
        rows += new
        modules += [i] * len(new)
    xi = jnp.stack(rows) if rows else jnp.zeros((0, 6), dtype)
    return tuple(modules), xi


def null_directions(frames: ArrayLike, modules: tuple[int, ...], xi: ArrayLike) -> Array:
    """The structural null directions ``A (n, k)`` of ``D`` at ``frames (K+1, 4, 4)``, not
    orthonormalised: column ``c`` has ``-Ad(F_i) xi_c`` in block ``i`` and ``xi_c`` in block
    ``i + 1`` (``i = modules[c]``). Linearly independent (module docstring)."""
    frames = jnp.asarray(frames)
    xi = jnp.asarray(xi, frames.dtype)
    k1 = frames.shape[-3]
    n = 6 * k1
    k = len(modules)
    if k == 0:
        return jnp.zeros((n, 0), frames.dtype)
    idx = np.asarray(modules)
    # -Ad(F_i) xi_c (k, 6): the adjoints' columns times the generators' components, summed
    # element-wise (under ``vmap`` a matrix product is a call of its own)
    columns = jnp.unstack(lie.adjoint(frames[idx]), axis=-1)
    components = jnp.unstack(xi[:, :, None], axis=1)
    products = [c * x for c, x in zip(columns, components, strict=True)]
    moved = -functools.reduce(operator.add, products)
    # Placed by selects on fixed masks: under ``vmap`` a scatter is a loop of its own.
    block = np.arange(k1)[None, :, None]
    at_module, after_module = block == idx[:, None, None], block == idx[:, None, None] + 1
    A = jnp.where(at_module, moved[:, None], jnp.where(after_module, xi[:, None], 0.0))
    return A.reshape(k, n).T


def null_basis(frames: ArrayLike, modules: tuple[int, ...], xi: ArrayLike) -> Array:
    """Orthonormal basis ``Z (n, k)`` of the structural null space of ``D`` at ``frames``
    (:func:`null_directions`, orthonormalised by :func:`orthonormalise`)."""
    return orthonormalise(null_directions(frames, modules, xi))


UNROLLED_COLUMNS = 6
"""Up to this many null columns ``k``, the products with a null basis are written column by
column (sums of ``k`` outer or dot products, which XLA fuses into the surrounding element-wise
code: under ``vmap`` each matrix product or LAPACK call is a call of its own, costly for such
small operands). Above it (four or more revolute modules: ``k = 2 R + 4 P``), the unrolled
code, which grows as ``k^2``, costs more than it saves, so the products are matrix products
and the orthonormalisation is a Householder QR. Vmapped paper solves ran 12-14 % faster column
by column at ``k = 4`` and ``k = 6``, and 15 % slower at ``k = 8``; on the UR5 (``k = 12``) the
matrix form compiled 3.8x faster and ran 1.5x faster (``benchmarks/null_space_compile.py``,
``benchmarks/README.md``). The default arm has ``k = 2``."""


def unrolled(k: int) -> bool:
    """Whether the products with ``k`` null columns are written column by column
    (:data:`UNROLLED_COLUMNS`)."""
    return k <= UNROLLED_COLUMNS


def orthonormalise(A: ArrayLike) -> Array:
    """Orthonormal basis of the span of the ``k`` (few, linearly independent) columns of
    ``A (n, k)``, the columns orthonormalised in order (column ``c`` of the result lies in the
    span of the first ``c + 1`` columns of ``A``, with a positive component along column ``c``).

    For ``k <= UNROLLED_COLUMNS``: Cholesky QR, written out element by element: the Gram
    matrix ``A^T A = R^T R`` (``k (k + 1) / 2`` sums of products), its Cholesky factor unrolled
    on scalars, and ``Q = A R^-1`` by substitution over the columns. Every step is element-wise
    work that XLA fuses, with one reduction per Gram entry (Gram-Schmidt chains a reduction per
    projection, each waiting for the previous one): fewer kernels and a third less IR than
    Gram-Schmidt twice (``benchmarks/README.md``, *What XLA compiles*).
    The loss of orthogonality grows as the square of the condition number of ``A`` with its
    columns equilibrated (the Cholesky factorisation's error does not depend on their scales):
    for the null bases it is below 40 (the columns are nearly orthogonal), and ``Q^T Q``
    differs from the identity by at most ``3e-14`` on random arms, also scaled as
    :func:`~cdra_jax.calibration.linear.null_space_solve` scales them
    (``tests/test_nullspace.py``). Above ``UNROLLED_COLUMNS``: a Householder QR, its columns
    signed as Cholesky QR's (the same basis to rounding)."""
    A = jnp.asarray(A)
    k = A.shape[-1]
    if not unrolled(k):
        Q, upper = jnp.linalg.qr(A)
        return Q * jnp.where(jnp.diagonal(upper) < 0, -1.0, 1.0).astype(A.dtype)
    if not k:
        return A
    a = jnp.unstack(A, axis=-1)
    gram = {(i, j): jnp.sum(a[i] * a[j]) for j in range(k) for i in range(j + 1)}
    # R (upper triangular, positive diagonal) with R^T R = A^T A, row by row
    R: dict[tuple[int, int], Array] = {}
    for i in range(k):
        for j in range(i, k):
            t = gram[(i, j)]
            for p in range(i):
                t = t - R[(p, i)] * R[(p, j)]
            R[(i, j)] = jnp.sqrt(t) if i == j else t / R[(i, i)]
    cols: list[Array] = []
    for j in range(k):
        v = a[j]
        for i in range(j):
            v = v - R[(i, j)] * cols[i]
        cols.append(v / R[(j, j)])
    return jnp.stack(cols, axis=-1)


def structural_null_space(arm: Arm, frames: ArrayLike | None = None) -> Array:
    """Orthonormal basis ``Z (6 (K+1), k)`` of the structural null space of the calibration
    Jacobian of ``arm`` at ``frames`` (default: the arm's own), rows ordered as
    ``arm.param_names``: ``D Z = 0`` for every pose set (module docstring)."""
    frames = jnp.asarray(arm.frames if frames is None else frames)
    modules, xi = null_generators(arm, frames.dtype)
    return null_basis(frames, modules, xi)


def structural_nullity(arm: Arm) -> int:
    """``k = 2 R + 4 P``: the number of structural null directions (module docstring)."""
    return sum({"revolute": 2, "prismatic": 4}.get(m.kind, 0) for m in arm.modules)
