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

import jax
import jax.numpy as jnp
import jax.scipy.linalg  # noqa: F401  (cho_solve)
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from .nullspace import orthonormalise, unrolled


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


# --------------------------------------------------------------------------- normal equations
def normal_cutoff(dtype, rcond: float | None = None) -> float:
    """Pivot cut-off of :func:`min_norm_solve_normal`, relative to ``max(diag(N))``.

    A singular-value cut-off ``rcond`` on ``D`` is a cut-off ``rcond ** 2`` on the eigenvalues of
    ``N = D^T D``. But ``N`` is only known to about ``n eps max(diag(N))`` (the rounding of its
    sums of products), so eigenvalue cut-offs below that cannot be resolved: the cut-off is
    ``max(rcond ** 2, eps ** (2/3))``, i.e. by default ``3.7e-11`` in float64 (singular values
    below ``6e-6 s_max`` are dropped). For the CDRA the structurally null pivots come out at
    ``~1e-15`` and the smallest identifiable ones at ``~1e-6`` (``s_min / s_max ~ 1e-3``), so the
    default sits four decades from each. In float32 the floor (``2.4e-5``) is above the CDRA's
    smallest identifiable eigenvalues: the solvers use the SVD path (:func:`min_norm_lstsq`) there.
    """
    floor = float(jnp.finfo(dtype).eps ** (2.0 / 3.0))
    return floor if rcond is None else max(float(rcond) ** 2, floor)


RESOLVED_PIVOT = 1e-9
"""Smallest kept pivot (relative to ``max(diag(N))``) for which the fast step is trusted
(the paper solver's steps, LM's steps; the same policy for both solvers, with
:func:`normal_equations_apply`).

The normal equations lose ``cond(D)^2 eps`` relative accuracy: with a pivot of ``1e-9`` the
fast step agrees with the SVD step to ``~1e-7`` of its size in the weakest direction and the
calibrated frames to ``~1e-9`` (measured over 1000 trials of 5 to 15 CDRA poses); pose sets with
a smaller pivot (some of 5 to 8 poses; none of 1000 with 15) are solved with SVD steps.
"""


def normal_equations_apply(dtype, rcond, rows: int, n: int) -> bool:
    """Whether the fast (normal-equation) step applies: float64, the default ``rcond``, and a
    stacked system (Eq. 9) of more than ``1.5 n`` rows for ``n`` parameters.

    An explicit ``rcond`` truncates by singular values, which a pivoted Cholesky factorisation
    of the normal equations does not reproduce (it drops pivots, not singular directions); in
    float32 the normal equations cannot resolve the CDRA's smallest singular values. The row
    count is a matter of speed only (results equal to rounding either way): with few rows the
    weakest identifiable direction is too weak for the normal equations and the trial is solved
    again with SVD steps. For the CDRA (n = 24) that was the case for 98 % of the pose sets of
    m = 5 poses (30 rows), 73 % of m = 6 (36 rows), 5.5 % of m = 7 and 0.4 % of m = 8 (4096
    random sets each), so up to ``1.5 n`` rows the SVD steps are taken from the start.
    """
    return rcond is None and bool(jnp.finfo(dtype).eps < 1e-12) and 2 * rows > 3 * n


def pivoted_cholesky(N: ArrayLike, cutoff: float) -> tuple[Array, Array]:
    """Cholesky factor of a symmetric positive semi-definite ``N ~= L L^T`` with diagonal pivoting.

    The outer-product (left-looking) algorithm with the largest remaining diagonal entry as the
    pivot of each step, as LAPACK's ``pstrf``; a step whose pivot is not above
    ``cutoff * max(diag(N))`` is dropped (its column of ``L`` is zero), and since the remaining
    diagonal can only shrink, every later step is dropped too. Fixed shapes, no branches on
    values: jit- and vmap-able.

    Args:
        N: ``(n, n)`` symmetric positive semi-definite.
        cutoff: relative pivot cut-off (see :func:`normal_cutoff`).

    Returns:
        ``(L (n, n), rank)``: column ``j`` of ``L`` is step ``j`` (rows in the original order,
        so ``L`` is a row permutation of a lower-trapezoidal factor); ``rank`` is the number of
        kept steps, the leading columns.
    """
    N = jnp.asarray(N)
    n = N.shape[-1]
    d0 = jnp.diagonal(N)
    threshold = cutoff * jnp.max(d0)

    def step(j, carry):
        L, d, free = carry
        d_free = jnp.where(free, d, -jnp.inf)
        pivot = jnp.max(d_free)
        e = (d_free == pivot) & free
        e = e & (jnp.cumsum(e) == 1)  # the first of equal pivots
        keep = pivot > threshold
        ef = e.astype(N.dtype)
        # Column of the Schur complement at the pivot: N[:, p] - L L[p, :]^T.
        col = N @ ef - L @ (ef @ L)
        col = jnp.where(keep, col * jax.lax.rsqrt(jnp.where(keep, pivot, 1.0)), 0.0)
        L = L.at[:, j].set(col)
        return L, d - col * col, free & ~e

    init = (jnp.zeros_like(N), d0, jnp.ones(n, bool))
    L, _, _ = jax.lax.fori_loop(0, n, step, init)
    rank = jnp.sum(jnp.any(L != 0, axis=0))
    return L, rank


def min_norm_solve_normal(
    N: ArrayLike, g: ArrayLike, cutoff: float | None = None
) -> tuple[Array, Array, Array]:
    """Minimum-norm solution of the normal equations ``N x = g`` (``N = D^T D``, ``g = D^T Y``).

    The least-squares step of Eq. 10 for float64 without an SVD of the ``(6m, n)`` matrix:
    ``N`` is factorised by :func:`pivoted_cholesky`, which reveals its rank, and with ``L`` the
    ``(n, r)`` factor (``N ~= L L^T``, ``range(L) = range(N)``) the minimum-norm solution is
    ``x = N^+ g = L (L^T L)^-2 L^T g``: it lies in the range of ``N``, so its component along the
    dropped (unidentifiable) directions is zero, as with :func:`min_norm_lstsq`. ``L^T L`` is
    factorised by an ordinary Cholesky (the dropped columns get a unit diagonal).

    Accuracy: the normal equations square the condition number, so the relative error of
    ``x`` is about ``cond(D)^2 eps`` (``~1e-10`` for the CDRA with 15 poses) rather than
    ``cond(D) eps``; the Gauss-Newton iteration converges to the same fixed point either way.

    Args:
        N: ``(n, n)``. g: ``(n,)``.
        cutoff: relative pivot cut-off (default :func:`normal_cutoff` of the dtype).

    Returns:
        ``(x (n,), rank, smallest_pivot)``: the solution, the number of kept pivots and the
        smallest kept pivot relative to ``max(diag(N))`` (``inf`` for rank 0), a measure of how
        well the normal equations resolve the kept directions.
    """
    N = jnp.asarray(N)
    g = jnp.asarray(g, N.dtype)
    if cutoff is None:
        cutoff = normal_cutoff(N.dtype)
    L, C, rank, smallest = _range_factor(N, cutoff)
    z = jax.scipy.linalg.cho_solve((C, True), L.T @ g)
    z = jax.scipy.linalg.cho_solve((C, True), z)
    return L @ z, rank, smallest


def _range_factor(N: Array, cutoff: float) -> tuple[Array, Array, Array, Array]:
    """``(L, C, rank, smallest_pivot)``: :func:`pivoted_cholesky` of ``N``, the Cholesky factor
    ``C`` of ``L^T L`` (the dropped columns given a unit diagonal), and the smallest kept pivot
    relative to ``max(diag(N))`` (``inf`` for rank 0)."""
    L, rank = pivoted_cholesky(N, cutoff)
    kept = jnp.arange(N.shape[-1]) < rank
    G = L.T @ L + jnp.diag(jnp.where(kept, 0.0, 1.0).astype(N.dtype))
    C = cholesky_of_symmetric(G)
    # Column j of L peaks at the pivot row with sqrt(pivot_j) (|S_ij| <= sqrt(S_ii S_jj)).
    pivots = jnp.max(L * L, axis=0) / jnp.max(jnp.diagonal(N))
    smallest = jnp.min(jnp.where(kept, pivots, jnp.inf))
    return L, C, rank, smallest


def svd_rank(D, rcond: float | None = None):
    """Host-side SVD of a stacked Jacobian ``D (rows, n)`` with the solvers' rank cut-off:
    ``(s (n,), Vt (n, n), rank)``: singular values zero-padded to ``n``, the full right singular
    basis (its rows from ``rank`` on span the null space) and the number of singular values
    above ``rcond * s_max`` (default :func:`default_rcond`)."""
    D = np.asarray(D, dtype=float)
    n = D.shape[1]
    _, s, Vt = np.linalg.svd(D, full_matrices=True)
    s_full = np.zeros(n)
    s_full[: s.size] = s
    rc = default_rcond(D.dtype) if rcond is None else float(rcond)
    rank = int(np.sum(s_full > rc * s_full[0])) if s_full[0] > 0 else 0
    return s_full, Vt, rank


# ------------------------------------------------------------- normal equations, null space known
STRUCTURAL_TOL = 1e-12
"""Largest ``max |N_s Z_s|`` (the scaled normal equations of :func:`null_space_solve`, unit
diagonal) for which the analytic null basis is taken as the null space of ``N``. Where the
module poses are the modules' own motions, the structural directions give ``~n eps``
(``1e-16`` to ``1e-14`` on random arms); ``1e-12`` is well below the pivot cut-off of
:func:`normal_cutoff` (``3.7e-11``), so a basis that passes spans directions that the pivoted
factorisation would drop too."""


def cholesky_of_symmetric(A: Array) -> Array:
    """The lower Cholesky factor of a symmetric ``A (..., n, n)`` from one of its triangles.

    ``jnp.linalg.cholesky`` first averages ``A`` with its transpose, which under XLA:CPU costs
    two layout-changing copies of every matrix (LAPACK's factorisation takes column-major
    input, the program's arrays are row-major). The transpose of a row-major matrix is its
    column-major layout, a free relabelling, and of a symmetric matrix the same matrix: the
    factor of ``A^T``, unsymmetrised, reads the other triangle of ``A`` without a copy. ``A``
    here is symmetric to rounding (a Gram matrix plus symmetric terms), so the factor differs
    from that of the average by rounding.
    """
    return jax.lax.linalg.cholesky(jnp.swapaxes(A, -1, -2), symmetrize_input=False)


def null_space_solve(
    N: ArrayLike,
    g: ArrayLike,
    Z: ArrayLike,
    *,
    check: bool | Array = True,
    damping: ArrayLike | None = None,
) -> tuple[Array, Array, Array]:
    """``N^+ g`` for ``g`` in the range of ``N`` when the null space of ``N`` is known.

    With ``B (n, k)`` a basis of ``null(N)`` and ``A = N + B B^T`` (positive definite), the
    solution of ``A x = g`` for ``g`` in ``range(N) = null(N)^perp`` splits into ``N x_r = g``
    on ``null(N)^perp`` and ``B^T x = 0``, so ``x = N^+ g``: the minimum-norm step of
    :func:`min_norm_solve_normal` and :func:`min_norm_lstsq`, from one plain Cholesky
    factorisation (no pivoting, no rank decision).

    The system is solved with the symmetric diagonal (Jacobi) scaling ``S = diag(N)^-1/2``:
    ``N_s = S N S`` has a unit diagonal, its null space is spanned by the columns of ``S^-1 Z``,
    normalised to ``Z_s``, so that ``A_s = N_s + Z_s Z_s^T`` has eigenvalues near 1 there, the
    mean eigenvalue of ``N_s`` (those of ``Z_s^T Z_s``: 1 for orthogonal columns, 0.002 to 3
    for the null bases of random arms, far above the smallest identifiable eigenvalues of
    ``N_s``; any basis of the null space gives the same ``x``, so the columns are not
    orthogonalised; above :data:`~cdra_jax.calibration.nullspace.UNROLLED_COLUMNS` columns
    they are, by a QR), and ``x = S A_s^-1 S g``, then the component along ``Z`` is projected
    out (it is null for ``N``: only the scaled metric made it non-zero). Unscaled, the
    millimetre and radian columns of the CDRA's ``N`` differ by ``|p|^2 ~ 1e6`` and an
    unpivoted factorisation lost up to ``1e-8`` relative accuracy where the scaled one keeps
    ``1e-11`` (7-pose sets).

    Whether this step can be trusted is returned with it, cheaply: ``lambda_min(A_s)`` by two
    steps of inverse iteration from a fixed vector ``u`` with components along every direction
    (``y = A_s^-1 u``, ``lambda ~ |y| / |A_s^-1 y|``, two more solves with ``L``; an estimate
    from above, within a few per cent of ``lambda_min`` once it is well below the other
    eigenvalues: the relative accuracy of ``x`` is about ``eps / lambda_min(A_s)``), to be
    tested against :data:`RESOLVED_PIVOT`; and ``max |N_s Z_s|``, to be below
    :data:`STRUCTURAL_TOL` (``Z`` really is null). A pose set that loses more directions than
    the structural ones (too few or degenerate poses) fails the first test (``A_s`` is then
    singular or nearly so: a tiny estimate, or NaN where its Cholesky factorisation breaks
    down).

    Both tests are properties of the data rather than of the model: the structural one holds
    or fails for every model (the null directions are null when the module poses are the
    modules' own motions, whatever the frames), and ``lambda_min`` changes little from one
    Gauss-Newton iterate to the next. ``check=False`` skips them: the paper solver tests its
    first step and takes the others unchecked.

    The products with the ``k`` (few) columns of ``Z`` are written as sums of ``k`` outer
    products or dot products, which XLA fuses, rather than as matrix products (each a call of
    its own, costly for such small operands under ``vmap``); above
    :data:`~cdra_jax.calibration.nullspace.UNROLLED_COLUMNS` columns, where that code's growth
    as ``k^2`` costs more than it saves, as matrix products. The structural test's ``A_s Z_s``
    is a matrix product for every ``k``: it runs once per problem, and written column by
    column XLA fused the ``k`` sums into the maximum over them (900 more lines of IR in the
    paper solver, ``benchmarks/compile_split.py``).

    ``damping`` ``M (n, n)`` (positive semi-definite) solves ``(N + M) x = g`` instead, the
    component along ``Z`` projected out as above (the damped Levenberg-Marquardt step of
    :mod:`.levenberg_marquardt`, ``M = lambda N_0``); the tests are then those of the damped
    system, so that a caller who needs them checks without ``damping``.

    Args:
        N: ``(n, n)`` ``D~^T D~``. g: ``(n,)`` ``D~^T Y~``. Z: ``(n, k)`` orthonormal basis of
            the null space of ``N`` (:mod:`.nullspace`); ``k = 0`` for none.
        check: compute the two tests: a bool, or a boolean scalar (a ``lax.cond``).
        damping: ``M (n, n)``, or ``None``.

    Returns:
        ``(x (n,), smallest, structural)``: the step, the estimate of ``lambda_min(A_s)`` (NaN
        when the factorisation broke down) and ``max |N_s Z_s|``; without ``check``, ``inf``
        and 0.
    """
    N = jnp.asarray(N)
    g = jnp.asarray(g, N.dtype)
    Z = jnp.asarray(Z, N.dtype)
    n, k = N.shape[-1], Z.shape[-1]
    d = jnp.sqrt(jnp.diagonal(N))
    s = 1.0 / d
    A = N * s[:, None] * s[None, :]
    if unrolled(k):
        Zs = Z * d[:, None]
        Zs = Zs * jax.lax.rsqrt(jnp.sum(Zs * Zs, axis=0))
    else:
        Zs = orthonormalise(Z * d[:, None])
    if not k:
        A_aug = A
    elif unrolled(k):
        A_aug = A + sum(Zs[:, None, c] * Zs[None, :, c] for c in range(k))
    else:
        A_aug = A + Zs @ Zs.T
    if damping is not None:
        A_aug = A_aug + jnp.asarray(damping, N.dtype) * s[:, None] * s[None, :]
    L = cholesky_of_symmetric(A_aug)

    def solve(b):
        return jax.scipy.linalg.cho_solve((L, True), b)

    x = s * solve(s * g)
    if k:
        x = off_null_space(x, Z)

    def tests():
        y = solve(jnp.asarray(_probe(n), N.dtype))
        smallest = jnp.linalg.norm(y) / jnp.linalg.norm(solve(y))
        # max |A_s Z_s|
        if not k:
            structural = jnp.zeros((), N.dtype)
        else:
            structural = jnp.max(jnp.abs(A @ Zs))
        return smallest, structural

    def skipped():
        return jnp.asarray(jnp.inf, N.dtype), jnp.zeros((), N.dtype)

    if isinstance(check, bool):
        smallest, structural = tests() if check else skipped()
    else:  # a traced scalar: a branch (real where it is unbatched, as the paper solver's)
        smallest, structural = jax.lax.cond(check, tests, skipped)
    return x, smallest, structural


def off_null_space(x: Array, Z: Array) -> Array:
    """``x`` less its components along the orthonormal columns of ``Z (n, k)``, ``x - Z Z^T x``
    (as sums of ``k`` products, which XLA fuses, for few columns:
    :data:`~cdra_jax.calibration.nullspace.UNROLLED_COLUMNS`)."""
    if not unrolled(Z.shape[-1]):
        return x - Z @ (Z.T @ x)
    return x - sum(Z[:, c] * jnp.dot(Z[:, c], x) for c in range(Z.shape[-1]))


def _probe(n: int) -> np.ndarray:
    """The start of the inverse iteration of :func:`null_space_solve`: fixed, with components
    of similar size in every direction (not a structured vector that a pose set could miss)."""
    return np.cos(1.0 + 2.3 * np.arange(n))
