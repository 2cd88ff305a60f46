"""Which poses to measure: D-optimal selection from a pool of feasible states.

Each candidate state ``q_i`` contributes a 6-row block ``A_i = G_i D_i (6, n)`` to the whitened
stacked Jacobian of Eq. 9 (``D_i`` from Eq. 8 at the nominal model, ``G_i`` the whitening of a
:class:`~cdra_jax.calibration.NoiseModel`), so a pose set ``S`` has the Fisher information
``F(S) = sum_{i in S} A_i^T A_i``. For the CDRA ``F`` is singular for every pose set (rank 22 of
24, :mod:`cdra_jax.identifiability`), so the criteria work on the identifiable subspace: with
``W (n, r)`` an orthonormal basis of the row space of the whole pool's information (the
structural row space), ``M(S) = W^T F(S) W (r, r)``.

Criteria:

* ``"d-opt"`` (default): maximise ``log det M(S)``, the D-optimality of the whitened information
  on the identifiable subspace. It minimises the volume of the confidence ellipsoid of the
  identifiable combinations (:mod:`cdra_jax.uncertainty`), it is invariant to any invertible
  reparametrisation of that subspace (so the mixed mm / rad units do not matter), and with the
  noise model it weights position and orientation measurements by what the device delivers.
* ``"o1"``: the observability index ``O1 = (s_1 ... s_r)^(1/r) / sqrt(m)`` of Borm and Menq
  (1991) on the *unweighted* paper Jacobian ``D`` (Eq. 9 without ``G``; the noise model is not
  used). For a fixed ``m``, ``O1 = exp(log det(W^T D^T D W) / (2 r)) / sqrt(m)`` is a monotone
  function of the unweighted D-criterion, so it is maximised by the same algorithm; on the
  whitened Jacobian it would rank pose sets exactly as ``"d-opt"`` does. It is offered for
  comparison with the calibration literature; its ranking depends on the choice of units
  (1 mm weighs as much as 1 rad), which is why it is not the default.

Algorithm: greedy forward selection (each step adds the candidate with the largest gain
``log det(I_6 + B_i M^-1 B_i^T)``, ``B_i = A_i W``, the matrix determinant lemma for the rank-6
update), then a Fedorov exchange pass (repeatedly make the best swap of a selected pose for an
unselected one while it increases ``log det M``, the gain of each swap again from the
determinant lemma, ``det(C + U^T M^-1 U)`` with ``U = [B_j^T, B_i^T]``, ``C = diag(I, -I)``).
While fewer poses than needed for full rank are selected, ``M + eps I`` with a tiny ``eps``
(1e-9 of the pool's mean per-pose information) is used, so the greedy first maximises rank
and then volume. The greedy and exchange loops are jitted (``lax`` loops, static ``m``); only the
rank of the pool is found on the host.
"""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from .arm import Arm, chain, module_poses
from .calibration.linear import default_rcond
from .calibration.model import NoiseModel, calibration_jacobian, whitening
from .simulation import StateSampler, sample_states

CRITERIA: tuple[str, ...] = ("d-opt", "o1")
DEFAULT_CRITERION = "d-opt"
DEFAULT_POOL_SIZE = 2000
_RIDGE = 1e-9


@dataclass(frozen=True)
class PoseSelection:
    """Result of :func:`select_poses`.

    Attributes:
        states: selected module states ``(m, dof)`` in selection order.
        indices: their rows in ``pool`` ``(m,)``.
        pool: the candidate states ``(N, dof)``.
        criterion: ``"d-opt"`` or ``"o1"``.
        log_det: ``log det M(S)`` of the selected set (no ridge), whitened for ``"d-opt"``,
            unweighted for ``"o1"``.
        log_det_greedy: the same after the greedy phase, before the exchanges.
        o1: the observability index ``exp(log_det / (2 r)) / sqrt(m)`` of the same matrix.
        rank: dimension ``r`` of the identifiable subspace of the pool.
        n_exchanges: swaps made by the exchange pass.
    """

    states: np.ndarray
    indices: np.ndarray
    pool: np.ndarray
    criterion: str
    log_det: float
    log_det_greedy: float
    o1: float
    rank: int
    n_exchanges: int


@eqx.filter_jit
def information_blocks(arm: Arm, q: ArrayLike, noise: NoiseModel | None) -> Array:
    """Per-pose (whitened) Jacobian blocks ``A_i = G_i D_i``: ``(N, dof) -> (N, 6, n)``.

    ``noise=None`` gives the unweighted blocks of Eq. 8. Whitening uses the model's tool poses.
    """
    dtype = jnp.asarray(arm.frames).dtype
    tool, after = chain(arm.frames, module_poses(arm, jnp.asarray(q, dtype)))
    A = calibration_jacobian(after)
    G = whitening(tool, noise)
    return A if G is None else G @ A


def identifiable_basis(blocks: ArrayLike, rcond: float | None = None) -> np.ndarray:
    """Orthonormal basis ``W (n, r)`` of the row space of the stacked blocks ``(N, 6, n)``.

    The rank uses the solvers' relative singular-value cut-off (:mod:`.calibration.linear`)
    on the SVD of the stack (a thin SVD of the R factor of its QR, which has the same singular
    values and right singular vectors).
    """
    A = np.asarray(blocks)
    A = A.reshape(-1, A.shape[-1])
    R = np.linalg.qr(A, mode="r") if A.shape[0] > A.shape[1] else A
    _, s, Vt = np.linalg.svd(R, full_matrices=False)
    rcond = default_rcond(A.dtype) if rcond is None else rcond
    keep = s > rcond * s[0] if s.size and s[0] > 0 else np.zeros(s.shape, bool)
    return Vt[keep].T


def log_det_information(blocks: ArrayLike, basis: ArrayLike) -> Array:
    """``log det(W^T F W)`` of a pose set given its blocks ``(m, 6, n)`` and ``W (n, r)``.

    ``-inf`` when the set does not identify the whole subspace.
    """
    B = jnp.einsum("...ai,ir->...ar", jnp.asarray(blocks), jnp.asarray(basis))
    M = jnp.einsum("...kar,...kas->...rs", B, B)
    sign, logdet = jnp.linalg.slogdet(M)
    return jnp.where(sign > 0, logdet, -jnp.inf)


def _chol_solve_blocks(L: Array, B: Array) -> Array:
    """``L^-1 B_i^T`` for every block: ``(r, r), (N, k, r) -> (N, r, k)``."""
    Bt = jnp.swapaxes(B, -1, -2)
    return jax.scipy.linalg.solve_triangular(L, Bt, lower=True)


def _greedy(B: Array, m: int, eps: Array) -> Array:
    """Greedy forward selection of ``m`` distinct candidates maximising ``log det(M + eps I)``."""
    N, k, r = B.shape
    eye_k = jnp.eye(k, dtype=B.dtype)

    def body(t, carry):
        M, taken, idx = carry
        L = jnp.linalg.cholesky(M)
        Z = _chol_solve_blocks(L, B)  # (N, r, k)
        C = eye_k + jnp.einsum("nri,nrj->nij", Z, Z)
        gain = 2.0 * jnp.sum(jnp.log(jnp.diagonal(jnp.linalg.cholesky(C), axis1=-2, axis2=-1)), -1)
        gain = jnp.where(taken | ~jnp.isfinite(gain), -jnp.inf, gain)
        j = jnp.argmax(gain)
        return M + B[j].T @ B[j], taken.at[j].set(True), idx.at[t].set(j.astype(idx.dtype))

    M0 = eps * jnp.eye(r, dtype=B.dtype)
    init = (M0, jnp.zeros(N, bool), jnp.zeros(m, jnp.int32))
    _, _, idx = jax.lax.fori_loop(0, m, body, init)
    return idx


def _exchange(B: Array, idx: Array, eps: Array, max_swaps: int, tol: float) -> tuple[Array, Array]:
    """Fedorov exchange: best single swap while it raises ``log det(M + eps I)`` by > ``tol``."""
    N, k, r = B.shape
    m = idx.shape[0]
    C = jnp.diag(jnp.concatenate([jnp.ones(k), -jnp.ones(k)])).astype(B.dtype)

    def information(idx):
        Bs = B[idx]
        return eps * jnp.eye(r, dtype=B.dtype) + jnp.einsum("mkr,mks->rs", Bs, Bs)

    def best_swap(idx):
        M = information(idx)
        L = jnp.linalg.cholesky(M)
        Z = _chol_solve_blocks(L, B)  # (N, r, k): L^-1 B_j^T
        Zs = Z[idx]  # (m, r, k)
        Pjj = jnp.einsum("nri,nrj->nij", Z, Z)  # (N, k, k)
        Pii = Pjj[idx]  # (m, k, k)
        Pij = jnp.einsum("mri,nrj->mnij", Zs, Z)  # (m, N, k, k): B_i M^-1 B_j^T
        top = jnp.concatenate(
            [jnp.broadcast_to(Pjj[None], (m, N, k, k)), jnp.swapaxes(Pij, -1, -2)], -1
        )
        bottom = jnp.concatenate([Pij, jnp.broadcast_to(Pii[:, None], (m, N, k, k))], -1)
        K = C + jnp.concatenate([top, bottom], -2)  # (m, N, 2k, 2k)
        _, logabs = jnp.linalg.slogdet(K)
        taken = jnp.zeros(N, bool).at[idx].set(True)
        gain = jnp.where(taken[None, :] | ~jnp.isfinite(logabs), -jnp.inf, logabs)
        flat = jnp.argmax(gain)
        return gain.reshape(-1)[flat], flat // N, flat % N

    def cond(carry):
        _, n, go = carry
        return go & (n < max_swaps)

    def body(carry):
        idx, n, _ = carry
        gain, i, j = best_swap(idx)
        go = gain > tol
        idx = jnp.where(go, idx.at[i].set(j.astype(idx.dtype)), idx)
        return idx, n + go.astype(n.dtype), go

    idx, n, _ = jax.lax.while_loop(cond, body, (idx, jnp.asarray(0), jnp.asarray(True)))
    return idx, n


def _select(B: Array, m: int, eps: Array, exchange: bool, max_swaps: int, tol: float):
    idx = _greedy(B, m, eps)
    if not exchange:
        return idx, idx, jnp.asarray(0)
    idx2, n = _exchange(B, idx, eps, max_swaps, tol)
    return idx, idx2, n


_select_jit = jax.jit(_select, static_argnums=(1, 3, 4, 5))


def select_from_pool(
    arm: Arm,
    pool: ArrayLike,
    m: int,
    noise: NoiseModel | None = None,
    *,
    criterion: str = DEFAULT_CRITERION,
    exchange: bool = True,
    max_exchanges: int | None = None,
    rcond: float | None = None,
) -> PoseSelection:
    """Choose ``m`` of the candidate states ``pool (N, dof)`` (see the module docstring).

    Args:
        arm: model to linearise at (the nominal arm).
        pool: candidate module states, e.g. from :func:`cdra_jax.simulation.sample_states` or a
            tension-closure sampler.
        m: number of poses to select (``<= N``).
        noise: the measuring device's noise; required for ``"d-opt"``, unused for ``"o1"``.
        criterion: ``"d-opt"`` (default) or ``"o1"``.
        exchange: run the Fedorov exchange pass after the greedy selection.
        max_exchanges: cap on swaps (default ``10 m``).
        rcond: relative singular-value cut-off for the identifiable subspace.

    Raises:
        ValueError: unknown criterion, no noise model for ``"d-opt"``, ``m`` out of range or a
            pool of the wrong shape.
    """
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {CRITERIA}, got {criterion!r}")
    if criterion == "d-opt" and noise is None:
        raise ValueError(
            "criterion 'd-opt' weights the poses by the measurement noise: pass "
            "noise=NoiseModel(position_mm, rotation_rad) (or use criterion='o1')"
        )
    pool = np.asarray(pool, dtype=float)
    if pool.ndim != 2 or pool.shape[1] != arm.dof:
        raise ValueError(
            f"pool must have shape (N, {arm.dof}) with columns {arm.state_names}, got {pool.shape}"
        )
    if not 1 <= m <= pool.shape[0]:
        raise ValueError(f"cannot select m = {m} poses from a pool of {pool.shape[0]}")
    dtype = jnp.asarray(arm.frames).dtype
    A = information_blocks(arm, pool, noise if criterion == "d-opt" else None)
    W = identifiable_basis(A, rcond)
    r = W.shape[1]
    B = jnp.einsum("nai,ir->nar", A, jnp.asarray(W, dtype))
    eps = _RIDGE * jnp.sum(B * B) / (pool.shape[0] * r)
    max_swaps = 10 * m if max_exchanges is None else int(max_exchanges)
    tol = 1e-10
    idx_greedy, idx, n_swaps = _select_jit(B, int(m), eps, bool(exchange), max_swaps, tol)
    idx = np.asarray(idx)
    log_det = float(log_det_information(A[idx], W))
    log_det_greedy = float(log_det_information(A[np.asarray(idx_greedy)], W))
    return PoseSelection(
        states=pool[idx],
        indices=idx,
        pool=pool,
        criterion=criterion,
        log_det=log_det,
        log_det_greedy=log_det_greedy,
        o1=float(np.exp(log_det / (2 * r)) / np.sqrt(m)) if r else 0.0,
        rank=r,
        n_exchanges=int(n_swaps),
    )


def select_poses(
    arm: Arm,
    m: int,
    noise: NoiseModel | None = None,
    *,
    key: Array | None = None,
    pool_size: int = DEFAULT_POOL_SIZE,
    sampler: StateSampler | None = None,
    criterion: str = DEFAULT_CRITERION,
    exchange: bool = True,
    max_exchanges: int | None = None,
    rcond: float | None = None,
) -> PoseSelection:
    """Draw a pool of ``pool_size`` states with ``sampler(key, arm, pool_size)`` (default
    :func:`cdra_jax.simulation.sample_states`) and select ``m`` of them
    (:func:`select_from_pool`).
    """
    if pool_size < m:
        raise ValueError(f"pool_size ({pool_size}) must be at least m ({m})")
    key = jax.random.PRNGKey(0) if key is None else key
    pool = (sampler or sample_states)(key, arm, int(pool_size))
    return select_from_pool(
        arm,
        np.asarray(pool),
        m,
        noise,
        criterion=criterion,
        exchange=exchange,
        max_exchanges=max_exchanges,
        rcond=rcond,
    )
