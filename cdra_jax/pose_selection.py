"""Which poses to measure: I-optimal (or D-optimal) selection from a pool of feasible states.

Each candidate state ``q_i`` contributes a 6-row block ``A_i = G_i D_i (6, n)`` to the whitened
stacked Jacobian of Eq. 9 (``D_i`` from Eq. 8 at the nominal model, ``G_i`` the whitening of a
:class:`~cdra_jax.calibration.NoiseModel`), so a pose set ``S`` has the Fisher information
``F(S) = sum_{i in S} A_i^T A_i``. For the CDRA ``F`` is singular for every pose set (rank 22 of
24, :mod:`cdra_jax.identifiability`), so the criteria work on the identifiable subspace: with
``W (n, r)`` an orthonormal basis of the row space of the whole pool's information (the
structural row space), ``M(S) = W^T F(S) W (r, r)`` and ``B_i = A_i W (6, r)``.

Criteria:

* ``"i-opt"`` (default): minimise ``tr(Q M(S)^-1)``, the average over a reference set of
  states ``h`` (where the calibrated arm will be used; default the pool) of the predicted
  variance of the tool *position*, ``Q = W^T mean_h(P_h^T P_h) W`` with
  ``P_h = [I, -hat(p_h)] D_h (3, n)`` the position rows of Eq. 8 (mm per parameter). To first
  order ``tr(Q M^-1) = E[dp^2]``, the expected square of the held-out position error of Eq. 20
  (:func:`cdra_jax.uncertainty.predicted_pose_covariance`), so this is the criterion that
  targets held-out accuracy (I- or V-optimality). It is the default because it is the one that
  minimises what a user of the calibrated arm sees: in ``benchmarks/pose_selection.py`` (200
  trials, common random numbers, 5000-state pool) its median held-out ``dp`` is below that of
  ``"d-opt"`` at every ``m`` from 5 to 15 but m = 10 (equal): 12 % lower at m = 5, 2 % at
  m = 7, 7 % at m = 9 (only the m = 5 confidence intervals separate), and its first-order
  prediction is lower at every ``m``. Unlike D-optimality it does not
  spend poses on parameter directions (e.g. tool orientation offsets seen only through the
  noisy orientation measurements) that barely move the tool position.
* ``"d-opt"``: maximise ``log det M(S)``, the D-optimality of the whitened information on the
  identifiable subspace. It minimises the volume of the confidence ellipsoid of the
  identifiable combinations (:mod:`cdra_jax.uncertainty`) and is invariant to any invertible
  reparametrisation of that subspace; the right choice when the parameters themselves are the
  goal rather than the predicted tool positions.
* ``"o1"``: the observability index ``O1 = (s_1 ... s_r)^(1/r) / sqrt(m)`` of Borm and Menq
  (1991) on the *unweighted* paper Jacobian ``D`` (Eq. 9 without ``G``; the noise model is not
  used). For a fixed ``m``, ``O1 = exp(log det(W^T D^T D W) / (2 r)) / sqrt(m)`` is a monotone
  function of the unweighted D-criterion, so it is maximised by the same algorithm; on the
  whitened Jacobian it would rank pose sets exactly as ``"d-opt"`` does. It is offered for
  comparison with the calibration literature; its ranking depends on the choice of units
  (1 mm weighs as much as 1 rad).

Algorithms. D-criterion: greedy forward selection (each step adds the candidate with the
largest gain ``log det(I_6 + B_i M^-1 B_i^T)``, the matrix determinant lemma for the rank-6
update), then a Fedorov exchange pass (repeatedly make the best swap of a selected pose for an
unselected one while it increases ``log det M``, the gain of each swap again from the
determinant lemma, ``det(C + U M^-1 U^T)`` with ``U = [B_j; B_i]``, ``C = diag(I, -I)``).
I-criterion: the same two passes with the Woodbury identity (adding ``B_j`` lowers
``tr(Q M^-1)`` by ``tr((I + B_j Y_j)^-1 Y_j^T Q Y_j)``, ``Y_j = M^-1 B_j^T``; a swap by
``tr((C + U Y)^-1 Y^T Q Y)``, ``Y = M^-1 U^T``), run from two starts (the I-greedy set and the
D-optimal set) of which the better end point is kept: the exchange ends in a local optimum and
the I-greedy start is poor for small ``m``. While fewer poses than needed for full rank are
selected, ``M + eps I`` with a tiny ``eps`` (1e-9 of the pool's mean per-pose information) is
used, so the greedy passes first raise the rank. The loops are jitted (``lax`` loops, static
``m``); only the rank of the pool is found on the host.

How good can a selection be? :func:`prediction_bound` solves the convex approximate-design
relaxation of the I-criterion over the pool and returns a certified lower bound on the
predicted ``sqrt(E[dp^2])`` of *any* ``m`` poses from it.

Unbounded predictions. The criteria live on ``W``, what the *pool* can identify. Where the
reference states' position rows see a direction outside it (``|P_h (I - W W^T)| > tol |P_h|``,
``tol = IDENTIFIABLE_TOL = 1e-8`` of :mod:`cdra_jax.uncertainty`; e.g. a pool of repeated or
too similar states and a reference elsewhere), no pose set from the pool bounds the error
there: :func:`prediction_bound` returns ``inf``, as does a selection's ``prediction_rms``,
which is :func:`cdra_jax.uncertainty.predicted_pose_covariance` of the selected poses at the
reference states (also ``inf`` when the selected poses identify less than the pool). The
CDRA's two structural directions move no tool pose and never count.

The number of poses ``m`` must be an integer of at least 4 (the paper's lower bound,
:data:`cdra_jax.calibration.MIN_POSES`).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from . import lie
from .arm import Arm, chain, module_poses
from .calibration.linear import cholesky_of_symmetric, default_rcond
from .calibration.model import NoiseModel, calibration_jacobian, tool_points, whitening
from .calibration.validation import MIN_POSES, require_finite_states
from .compilation import compiled_when_eager, filter_jit, jit
from .simulation import StateSampler, sample_poses
from .uncertainty import IDENTIFIABLE_TOL, predicted_pose_covariance

CRITERIA: tuple[str, ...] = ("i-opt", "d-opt", "o1")
DEFAULT_CRITERION = "i-opt"
DEFAULT_POOL_SIZE = 5000
_RIDGE = 1e-9


@dataclass(frozen=True)
class PoseSelection:
    """Result of :func:`select_poses`.

    Attributes:
        states: selected module states ``(m, dof)`` in selection order.
        indices: their rows in ``pool`` ``(m,)``.
        pool: the candidate states ``(N, dof)``.
        criterion: ``"i-opt"``, ``"d-opt"`` or ``"o1"``.
        log_det: ``log det M(S)`` of the selected set (no ridge), whitened for ``"i-opt"`` and
            ``"d-opt"``, unweighted for ``"o1"``.
        log_det_greedy: the same for the criterion's own greedy set, before the exchanges.
        o1: the observability index ``exp(log_det / (2 r)) / sqrt(m)`` of the same matrix.
        prediction_rms: predicted ``sqrt(E[dp^2])`` (mm, first order) of a calibration from the
            selected poses at the reference states
            (:func:`cdra_jax.uncertainty.predicted_pose_covariance`; ``sqrt(tr(Q M^-1))``, the
            I-criterion, when the poses identify the pool's subspace and the reference sees no
            more); ``inf`` when the selected poses leave a direction unidentified that moves
            the tool position at a reference state; ``nan`` without a noise model.
        rank: dimension ``r`` of the identifiable subspace of the pool.
        n_exchanges: swaps made by the exchange pass (for ``"i-opt"``, by the start that won).
    """

    states: np.ndarray
    indices: np.ndarray
    pool: np.ndarray
    criterion: str
    log_det: float
    log_det_greedy: float
    o1: float
    prediction_rms: float
    rank: int
    n_exchanges: int


@filter_jit
def information_blocks(arm: Arm, q: ArrayLike, noise: NoiseModel | None) -> Array:
    """Per-pose (whitened) Jacobian blocks ``A_i = G_i D_i``: ``(N, dof) -> (N, 6, n)``.

    ``noise=None`` gives the unweighted blocks of Eq. 8. Whitening uses the model's tool poses.

    A model with ``[[markers]]`` is measured by its markers: each pose then contributes the
    rows of its ``P`` marker positions, ``[I, -hat(p_j)] D_i / s_pos`` (``p_j`` the marker's
    world position), ``(N, 3 P, n)``: the frame parameters as seen by the points (the marker
    positions themselves are not part of the design).
    """
    dtype = jnp.asarray(arm.frames).dtype
    tool, after = chain(arm.frames, module_poses(arm, jnp.asarray(q, dtype)))
    A = calibration_jacobian(after)
    if arm.markers:
        xyz = jnp.asarray([mk.xyz for mk in arm.markers], dtype)
        p = tool_points(tool, xyz)  # (N, P, 3)
        eye = jnp.broadcast_to(jnp.eye(3, dtype=dtype), p.shape + (3,))
        rows = jnp.concatenate([eye, -lie.hat3(p)], axis=-1)  # (N, P, 3, 6)
        A = jnp.einsum("npij,njk->npik", rows, A).reshape(A.shape[0], -1, A.shape[-1])
        if noise is not None:
            A = A / jnp.asarray(noise.position_mm, dtype)
        return A
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


@compiled_when_eager
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
    eye_k = jnp.eye(B.shape[1], dtype=B.dtype)

    def gains(M):
        Z = _chol_solve_blocks(cholesky_of_symmetric(M), B)  # (N, r, k)
        C = eye_k + jnp.einsum("nri,nrj->nij", Z, Z)
        return 2.0 * jnp.sum(
            jnp.log(jnp.diagonal(cholesky_of_symmetric(C), axis1=-2, axis2=-1)), -1
        )

    return _add_while_best(gains, B, m, eps)


def _add_while_best(gains, B: Array, m: int, eps: Array) -> Array:
    """Greedy forward selection: ``m`` times add the untaken candidate with the largest
    ``gains(M) (N,)``, starting from ``M = eps I``, ``M += B_j^T B_j``. Returns ``(m,)``."""
    N, _, r = B.shape

    def body(t, carry):
        M, taken, idx = carry
        gain = gains(M)
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
        L = cholesky_of_symmetric(M)
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
        return gain.reshape(-1)[flat] - tol, flat // N, flat % N

    return _swap_while_improving(best_swap, idx, max_swaps)


def _swap_while_improving(best_swap, idx: Array, max_swaps: int) -> tuple[Array, Array]:
    """Apply ``best_swap(idx) -> (margin, i, j)`` (put candidate ``j`` in slot ``i``) while its
    margin over the tolerance is positive, at most ``max_swaps`` times: ``(idx, swaps made)``."""

    def cond(carry):
        _, n, go = carry
        return go & (n < max_swaps)

    def body(carry):
        idx, n, _ = carry
        margin, i, j = best_swap(idx)
        go = margin > 0
        idx = jnp.where(go, idx.at[i].set(j.astype(idx.dtype)), idx)
        return idx, n + go.astype(n.dtype), go

    idx, n, _ = jax.lax.while_loop(cond, body, (idx, jnp.asarray(0), jnp.asarray(True)))
    return idx, n


@compiled_when_eager
def _prediction_weight(reference_blocks: Array, basis: Array, position_mm: Array) -> Array:
    """``Q = s_p^2 W^T mean_h(A_h[:3]^T A_h[:3]) W (r, r)``: weight of the I-criterion.

    The whitened position rows of a block are ``[I, -hat(p)] D / s_p`` (Eq. 7 whitening), so
    ``s_p A_h[:3] W`` maps the identifiable coordinates to the tool position error at ``h`` (mm).
    """
    P = jnp.einsum("hai,ir->har", reference_blocks[..., :3, :], basis) * position_mm
    return jnp.einsum("har,has->rs", P, P) / reference_blocks.shape[0]


def _greedy_i(B: Array, Q: Array, m: int, eps: Array) -> Array:
    """Greedy forward selection of ``m`` candidates minimising ``tr(Q (M + eps I)^-1)``.

    Adding ``B_j`` lowers it by ``tr((I + B_j Y_j)^-1 Y_j^T Q Y_j)``, ``Y_j = M^-1 B_j^T``
    (Sherman-Morrison-Woodbury).
    """
    eye_k = jnp.eye(B.shape[1], dtype=B.dtype)

    def gains(M):
        Y = _spd_solve_blocks(M, B)  # (N, r, k)
        S = eye_k + jnp.einsum("nir,nrj->nij", B, Y)
        V = jnp.einsum("nri,rs,nsj->nij", Y, Q, Y)
        return jnp.trace(jnp.linalg.solve(S, V), axis1=-2, axis2=-1)

    return _add_while_best(gains, B, m, eps)


def _spd_solve_blocks(M: Array, B: Array) -> Array:
    """``M^-1 B_j^T`` for every block: ``(r, r) SPD, (N, k, r) -> (N, r, k)``."""
    L = cholesky_of_symmetric(M)
    Z = _chol_solve_blocks(L, B)
    return jax.scipy.linalg.solve_triangular(L.T, Z, lower=False)


def _exchange_i(
    B: Array, Q: Array, idx: Array, eps: Array, max_swaps: int, tol: float
) -> tuple[Array, Array]:
    """Fedorov exchange for the I-criterion: best single swap while it lowers ``tr(Q M^-1)``
    by more than ``tol`` times its value.

    Swapping selected ``i`` for ``j`` is the update ``M + U^T C U`` with ``U = [B_j; B_i]``,
    ``C = diag(I, -I)``; it lowers the criterion by ``tr(K^-1 Y^T Q Y)``, ``Y = M^-1 U^T``,
    ``K = C + U Y``.
    """
    N, k, r = B.shape
    m = idx.shape[0]
    C = jnp.diag(jnp.concatenate([jnp.ones(k), -jnp.ones(k)])).astype(B.dtype)

    def best_swap(idx):
        Bs = B[idx]
        M = eps * jnp.eye(r, dtype=B.dtype) + jnp.einsum("mkr,mks->rs", Bs, Bs)
        Y = _spd_solve_blocks(M, B)  # (N, r, k): M^-1 B_j^T
        QY = jnp.einsum("rs,nsk->nrk", Q, Y)
        Ys = Y[idx]
        Pjj = jnp.einsum("nir,nrj->nij", B, Y)  # B_j M^-1 B_j^T
        Pij = jnp.einsum("mir,nrj->mnij", Bs, Y)  # B_i M^-1 B_j^T
        Pii = Pjj[idx]
        Vjj = jnp.einsum("nri,nrj->nij", Y, QY)  # Y_j^T Q Y_j
        Vij = jnp.einsum("mri,nrj->mnij", Ys, QY)  # Y_i^T Q Y_j
        Vii = Vjj[idx]

        def assemble(jj, ij, ii):  # [[jj, ji], [ij, ii]] over (m, N)
            top = jnp.concatenate([jnp.broadcast_to(jj[None], (m, N, k, k)), _t(ij)], -1)
            bottom = jnp.concatenate([ij, jnp.broadcast_to(ii[:, None], (m, N, k, k))], -1)
            return jnp.concatenate([top, bottom], -2)

        K = C + assemble(Pjj, Pij, Pii)
        V = assemble(Vjj, Vij, Vii)
        gain = jnp.trace(jnp.linalg.solve(K, V), axis1=-2, axis2=-1)
        taken = jnp.zeros(N, bool).at[idx].set(True)
        gain = jnp.where(taken[None, :] | ~jnp.isfinite(gain), -jnp.inf, gain)
        flat = jnp.argmax(gain)
        phi = jnp.trace(jnp.linalg.solve(M, Q))
        return gain.reshape(-1)[flat] - tol * phi, flat // N, flat % N

    return _swap_while_improving(best_swap, idx, max_swaps)


def _t(x: Array) -> Array:
    return jnp.swapaxes(x, -1, -2)


def _select(B: Array, m: int, eps: Array, exchange: bool, max_swaps: int, tol: float):
    """D-criterion: greedy, then (optionally) Fedorov exchange."""
    idx = _greedy(B, m, eps)
    if not exchange:
        return idx, idx, jnp.asarray(0)
    idx2, n = _exchange(B, idx, eps, max_swaps, tol)
    return idx, idx2, n


def _i_value(B: Array, Q: Array, idx: Array, eps: Array | float) -> Array:
    """``tr(Q (M(S) + eps I)^-1)`` of the set ``idx``."""
    Bs = B[idx]
    M = eps * jnp.eye(B.shape[-1], dtype=B.dtype) + jnp.einsum("mkr,mks->rs", Bs, Bs)
    return jnp.trace(jnp.linalg.solve(M, Q))


def _select_i(B: Array, Q: Array, m: int, eps: Array, exchange: bool, max_swaps: int, tol: float):
    """I-criterion: two starts (I-greedy; the D-optimal greedy + exchange set), each improved
    by I-exchanges; the better end point wins. Returns (greedy set, final set, swaps)."""
    idx_g = _greedy_i(B, Q, m, eps)
    if not exchange:
        return idx_g, idx_g, jnp.asarray(0)
    idx_d = _select(B, m, eps, True, max_swaps, 1e-10)[1]
    idx_1, n_1 = _exchange_i(B, Q, idx_g, eps, max_swaps, tol)
    idx_2, n_2 = _exchange_i(B, Q, idx_d, eps, max_swaps, tol)
    first = _i_value(B, Q, idx_1, eps) <= _i_value(B, Q, idx_2, eps)
    return idx_g, jnp.where(first, idx_1, idx_2), jnp.where(first, n_1, n_2)


_select_jit = jit(_select, static_argnums=(1, 3, 4, 5))
_sample_poses_jit = filter_jit(sample_poses)  # one compile instead of many eager ones
_select_i_jit = jit(_select_i, static_argnums=(2, 4, 5, 6))


def _check_count(value, name: str, minimum: int, what: str) -> int:
    """``value`` as an ``int``: an integer (not a bool) of at least ``minimum``."""
    if isinstance(value, bool | np.bool_) or not isinstance(value, int | np.integer):
        raise ValueError(f"{name} must be an integer ({what}), got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be at least {minimum} ({what}), got {value}")
    return int(value)


def _check_m(m) -> int:
    """The number of poses: an integer of at least ``MIN_POSES`` (4, the paper's bound)."""
    return _check_count(
        m, "m", MIN_POSES, f"the number of poses; {MIN_POSES} is the paper's lower bound"
    )


def _require_noise(noise: NoiseModel | None, what: str) -> NoiseModel:
    if noise is None:
        raise ValueError(
            f"{what} weights the poses by the measurement noise: pass "
            "noise=NoiseModel(position_mm, rotation_rad)"
        )
    return noise


def _sees_outside(blocks: Array, basis: np.ndarray, tol: float = IDENTIFIABLE_TOL) -> bool:
    """Whether the position rows of any block ``(K, 6, n)`` have a component outside the span
    of ``basis (n, r)`` larger than ``tol`` times their size (Frobenius norms, per block)."""
    P = np.asarray(blocks)[..., :3, :]
    W = np.asarray(basis)
    outside = P - (P @ W) @ W.T
    num = np.sum(outside**2, axis=(-2, -1))
    return bool(np.any(num > tol**2 * np.sum(P**2, axis=(-2, -1))))


def _check_pool(arm: Arm, pool: ArrayLike, name: str = "pool") -> np.ndarray:
    pool = np.asarray(pool, dtype=float)
    if pool.ndim != 2 or pool.shape[1] != arm.dof:
        raise ValueError(
            f"{name} must have shape (N, {arm.dof}) with columns {arm.state_names}, "
            f"got {pool.shape}"
        )
    require_finite_states(arm, pool, name)
    return pool


def _projected_blocks(
    arm: Arm, pool: np.ndarray, noise: NoiseModel | None, rcond: float | None
) -> tuple[Array, np.ndarray, Array]:
    """``(A (N, 6, n), W (n, r), B = A W (N, 6, r))``: blocks, identifiable basis, projection."""
    A = information_blocks(arm, pool, noise)
    W = identifiable_basis(A, rcond)
    return A, W, _project(A, jnp.asarray(W, A.dtype))


@compiled_when_eager
def _project(A: Array, W: Array) -> Array:
    """``B = A W``: ``(N, k, n), (n, r) -> (N, k, r)``."""
    return jnp.einsum("nai,ir->nar", A, W)


@compiled_when_eager
def _ridge(B: Array) -> Array:
    """``eps``: ``_RIDGE`` times the mean per-pose information ``sum(B * B) / (N r)``."""
    return _RIDGE * jnp.sum(B * B) / (B.shape[0] * B.shape[-1])


def _reference_weight(
    arm: Arm, reference: np.ndarray, noise: NoiseModel, basis: np.ndarray
) -> Array:
    dtype = jnp.asarray(arm.frames).dtype
    blocks = information_blocks(arm, reference, noise)
    pos = jnp.asarray(noise.position_mm, dtype)
    if pos.ndim:
        raise ValueError("criterion 'i-opt' needs a scalar noise.position_mm (one device)")
    if arm.markers:
        return _marker_weight(blocks, jnp.asarray(basis, dtype), pos, len(arm.markers))
    return _prediction_weight(blocks, jnp.asarray(basis, dtype), pos)


@filter_jit
def _marker_weight(blocks: Array, basis: Array, position_mm: Array, n_pts: int) -> Array:
    """The I-criterion weight of a model measured by ``n_pts`` markers: every marker's position
    rows of the blocks ``(H, 3 n_pts, n)``, averaged over the markers (E[dp^2] per point)."""
    P = _project(blocks, basis) * position_mm
    return jnp.einsum("har,has->rs", P, P) / (blocks.shape[0] * n_pts)


def marker_prediction_rms(
    arm: Arm,
    q: ArrayLike,
    noise: NoiseModel,
    reference: ArrayLike,
    rcond: float | None = None,
) -> float:
    """Predicted ``sqrt(E[dp^2])`` (mm, first order) of the marker positions at the reference
    states after a calibration of ``arm``'s frames from its markers measured at ``q``:
    ``sqrt(tr(Q M^-1))`` on the identifiable subspace of ``q``; ``inf`` where a reference
    marker position sees a direction that ``q`` leaves unidentified."""
    A = information_blocks(arm, np.asarray(q, dtype=float), noise)
    W = identifiable_basis(A, rcond)
    ref = information_blocks(arm, np.asarray(reference, dtype=float), noise)
    if _sees_outside(ref, W):
        return float("inf")
    Q = _reference_weight(arm, np.asarray(reference, dtype=float), noise, W)
    return float(_marker_rms(A, jnp.asarray(W, A.dtype), Q))


@compiled_when_eager
def _marker_rms(A: Array, W: Array, Q: Array) -> Array:
    """``sqrt(tr(Q M^-1))`` with ``M = sum_i B_i^T B_i``, ``B_i = A_i W``."""
    B = _project(A, W)
    M = jnp.einsum("nar,nas->rs", B, B)
    return jnp.sqrt(jnp.trace(jnp.linalg.solve(M, Q)))


def select_from_pool(
    arm: Arm,
    pool: ArrayLike,
    m: int,
    noise: NoiseModel | None = None,
    *,
    criterion: str = DEFAULT_CRITERION,
    reference: ArrayLike | None = None,
    exchange: bool = True,
    max_exchanges: int | None = None,
    rcond: float | None = None,
) -> PoseSelection:
    """Choose ``m`` of the candidate states ``pool (N, dof)`` (see the module docstring).

    Args:
        arm: model to linearise at (the nominal arm).
        pool: candidate module states, e.g. from :func:`cdra_jax.simulation.sample_poses`
            (tension-feasible where the model has cables).
        m: number of poses to select, an integer in ``[4, N]`` (4: the paper's lower bound).
        noise: the measuring device's noise; required for ``"i-opt"`` and ``"d-opt"``, unused
            for ``"o1"``.
        criterion: ``"i-opt"`` (default), ``"d-opt"`` or ``"o1"``.
        reference: states ``(K, dof)`` where the calibrated arm will be used (the workspace
            sample the I-criterion averages over and ``prediction_rms`` is evaluated at);
            default: the pool.
        exchange: run the exchange pass after the greedy selection.
        max_exchanges: cap on swaps, a non-negative integer (default ``10 m``).
        rcond: relative singular-value cut-off for the identifiable subspace.

    Raises:
        ValueError: unknown criterion, no noise model for ``"i-opt"`` / ``"d-opt"``, ``m`` not
            an integer in ``[4, N]``, a negative or non-integer ``max_exchanges``, or a pool /
            reference of the wrong shape or with a non-finite state.
    """
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {CRITERIA}, got {criterion!r}")
    if criterion != "o1" and noise is None:
        raise ValueError(
            f"criterion {criterion!r} weights the poses by the measurement noise: pass "
            "noise=NoiseModel(position_mm, rotation_rad) (or use criterion='o1')"
        )
    m = _check_m(m)
    if max_exchanges is not None:
        max_exchanges = _check_count(max_exchanges, "max_exchanges", 0, "a cap on swaps")
    pool = _check_pool(arm, pool)
    reference = pool if reference is None else _check_pool(arm, reference, "reference")
    if m > pool.shape[0]:
        raise ValueError(f"cannot select m = {m} poses from a pool of {pool.shape[0]}")
    A, W, B = _projected_blocks(arm, pool, None if criterion == "o1" else noise, rcond)
    r = W.shape[1]
    eps = _ridge(B)
    max_swaps = 10 * m if max_exchanges is None else max_exchanges
    if criterion == "i-opt":
        assert noise is not None  # checked above
        Q = _reference_weight(arm, reference, noise, W)
        idx_greedy, idx, n_swaps = _select_i_jit(B, Q, m, eps, bool(exchange), max_swaps, 1e-10)
    else:
        idx_greedy, idx, n_swaps = _select_jit(B, m, eps, bool(exchange), max_swaps, 1e-10)
    idx = np.asarray(idx)
    A_host = np.asarray(A)
    log_det = float(log_det_information(A_host[idx], W))
    log_det_greedy = float(log_det_information(A_host[np.asarray(idx_greedy)], W))
    if not np.isfinite(log_det) and np.isfinite(log_det_greedy):
        # The I-exchange may trade away a direction that the reference positions do not see
        # (e.g. a tool orientation offset); a set that identifies the pool's whole subspace is
        # preferred: keep the greedy set.
        idx, log_det, n_swaps = np.asarray(idx_greedy), log_det_greedy, 0
    rms = float("nan")
    if noise is not None and arm.markers:
        rms = marker_prediction_rms(arm, pool[idx], noise, reference, rcond)
    elif noise is not None:
        # The uncertainty module's prediction from the selected set's own Jacobian: equal to
        # sqrt(tr(Q M^-1)) when the set identifies W and the reference sees nothing outside
        # it, inf where the set leaves a direction that moves a reference position unidentified.
        pred = predicted_pose_covariance(arm, pool[idx], noise, reference, rcond=rcond)
        rms = float(pred.expected_delta_p)
    return PoseSelection(
        states=pool[idx],
        indices=idx,
        pool=pool,
        criterion=criterion,
        log_det=log_det,
        log_det_greedy=log_det_greedy,
        o1=float(np.exp(log_det / (2 * r)) / np.sqrt(m)) if r else 0.0,
        prediction_rms=rms,
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
    reference: ArrayLike | None = None,
    exchange: bool = True,
    max_exchanges: int | None = None,
    rcond: float | None = None,
) -> PoseSelection:
    """Draw a pool of ``pool_size`` states with ``sampler(key, arm, pool_size)`` and select
    ``m`` of them (:func:`select_from_pool`).

    The default sampler is :func:`cdra_jax.simulation.sample_poses`: uniform within the joint
    limits, and with tension closure in every module where the model has cables (poses the arm
    can hold).

    Raises:
        ValueError: ``m`` not an integer of at least 4, ``pool_size`` not an integer of at
            least ``m``, and the errors of :func:`select_from_pool`.
    """
    m = _check_m(m)
    pool_size = _check_count(pool_size, "pool_size", m, "the number of candidate states, >= m")
    key = jax.random.PRNGKey(0) if key is None else key
    pool = (sampler or _sample_poses_jit)(key, arm, pool_size)
    return select_from_pool(
        arm,
        np.asarray(pool),
        m,
        noise,
        criterion=criterion,
        reference=reference,
        exchange=exchange,
        max_exchanges=max_exchanges,
        rcond=rcond,
    )


@dataclass(frozen=True)
class PredictionBound:
    """Result of :func:`prediction_bound` (first-order, position error in mm).

    Attributes:
        lower: no ``m`` poses from the pool give a smaller predicted ``sqrt(E[dp^2])`` at the
            reference states than this (mm); ``inf`` when the reference states see a direction
            that no pose of the pool identifies (module docstring).
        approximate: ``sqrt(tr(Q M(w)^-1) / m)`` of the best weighted design found (mm); the
            optimum of the relaxation lies in ``[lower, approximate]``; ``inf`` with ``lower``.
        weights: design weights over the pool ``(N,)``, summing to 1.
        support: number of pool states with weight above ``1e-3``.
        iterations: multiplicative-algorithm steps run.
    """

    lower: float
    approximate: float
    weights: np.ndarray
    support: int
    iterations: int


@filter_jit
def _approximate_i_design(B: Array, Q: Array, iterations: int):
    """Multiplicative algorithm for ``min_w tr(Q M(w)^-1)``, ``M(w) = sum_i w_i F_i``,
    ``F_i = B_i^T B_i``."""
    F = jnp.einsum("nar,nas->nrs", B, B)
    N = F.shape[0]

    def sensitivities(w):
        Mi = jnp.linalg.inv(jnp.einsum("n,nrs->rs", w, F))
        phi = jnp.trace(Q @ Mi)
        return jnp.einsum("nrs,rs->n", F, Mi @ Q @ Mi), phi

    def body(_, w):
        d, phi = sensitivities(w)
        w = w * jnp.sqrt(d / phi)
        return w / jnp.sum(w)

    w = jax.lax.fori_loop(0, iterations, body, jnp.full(N, 1.0 / N, F.dtype))
    d, phi = sensitivities(w)
    return w, phi, jnp.max(d)


def prediction_bound(
    arm: Arm,
    pool: ArrayLike,
    m: int,
    noise: NoiseModel,
    *,
    reference: ArrayLike | None = None,
    iterations: int = 2000,
    rcond: float | None = None,
) -> PredictionBound:
    """Lower bound on the predicted held-out error of *any* ``m`` poses taken from ``pool``.

    The I-criterion ``phi(S) = tr(Q M(S)^-1)`` (module docstring) of an ``m``-pose set equals
    ``phi(w_S) / m`` for the design ``w_S`` that puts weight ``1/m`` on each of its poses, so it
    is at least ``phi* / m`` with ``phi*`` the optimum over all weights on the pool (the
    approximate-design relaxation, a convex problem). The multiplicative algorithm
    (``w_i <- w_i sqrt(d_i / phi)``, ``d_i = tr(F_i M^-1 Q M^-1)``) approaches it, and
    convexity gives the certificate ``phi* >= phi(w)^2 / max_i d_i`` at every ``w`` (the
    tangent plane of the convex ``phi`` at ``t M(w)``, optimised over ``t``). Returned as RMS
    position errors (mm): ``lower = sqrt(phi(w)^2 / max_i d_i / m)``. Both are ``inf`` when a
    reference state's position sees a direction outside the pool's identifiable subspace.

    Args:
        arm: model to linearise at (the nominal arm).
        pool: candidate module states ``(N, dof)``.
        m: number of poses, an integer of at least 4 (repeats allowed: the bound holds for
            multisets too).
        noise: the measuring device's noise (scalar stds).
        reference: states ``(K, dof)`` to predict at; default: the pool.
        iterations: multiplicative-algorithm steps, a non-negative integer (the certificate
            holds after any number; 0: uniform weights).
        rcond: relative singular-value cut-off for the identifiable subspace.

    Raises:
        ValueError: no noise model, ``m`` or ``iterations`` out of range or not integers, or a
            pool / reference of the wrong shape or with a non-finite state.
    """
    noise = _require_noise(noise, "prediction_bound")
    m = _check_m(m)
    iterations = _check_count(iterations, "iterations", 0, "multiplicative-algorithm steps")
    pool = _check_pool(arm, pool)
    reference = pool if reference is None else _check_pool(arm, reference, "reference")
    _, W, B = _projected_blocks(arm, pool, noise, rcond)
    Q = _reference_weight(arm, reference, noise, W)
    w, phi, dmax = _approximate_i_design(B, Q, iterations)
    w = np.asarray(w)
    lower = float(np.sqrt(float(phi) ** 2 / float(dmax) / m))
    approximate = float(np.sqrt(float(phi) / m))
    if _sees_outside(information_blocks(arm, reference, noise), W):
        lower = approximate = float("inf")
    return PredictionBound(
        lower=lower,
        approximate=approximate,
        weights=w,
        support=int(np.sum(w > 1e-3)),
        iterations=iterations,
    )
