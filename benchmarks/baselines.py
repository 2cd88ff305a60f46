"""Hand-written NumPy / SciPy baselines of the paper's calibration, for the throughput benchmark.

This is what a user would write by hand from the paper, one trial at a time and without JAX:

* :func:`so3_exp` / :func:`se3_exp`: Rodrigues' formula and the matrix ``A`` of Eq. 26;
* :func:`se3_log`: Eq. 27, ``phi = arccos((tr R - 1) / 2)``, ``hat(w) = phi / (2 sin phi)
  (R - R^T)`` with the paper's small-angle branch ``hat(w) ~ (R - R^T) / 2``, and ``A*``;
* :func:`adjoint`: Eq. 25, ``[[R, hat(p) R], [0, R]]``;
* :func:`calibrate_numpy`: the iteration of Fig. 4: stack ``Y_k``, ``D_k`` of every pose
  (Eqs. 7-9), solve Eq. 10 with ``np.linalg.lstsq`` (SVD-based, minimum norm, the same relative
  cut-off ``rcond`` as :func:`cdra_jax.calibration.min_norm_lstsq`), left-multiply the fixed
  transforms (Eqs. 11-14) until ``||X|| < tol``, recording the deviation metrics (Eqs. 20-21)
  at every iteration as the JAX solvers do; the identified errors are Eqs. 15-18;
* :func:`calibrate_scipy`: ``scipy.optimize.least_squares`` on the stacked Eq. 7 residual as a
  function of ``X`` (``F_j(X) = exp(hat(X_j)) F_j``), with a finite-difference Jacobian.

The per-pose code works on single 3-vectors and 4x4 matrices (a Python loop over the ``m``
poses, as the paper's Eq. 9 is written); :func:`calibrate_numpy_vectorized` is the same
algorithm with every per-pose operation batched over the poses with NumPy (``(m, 4, 4)``
arrays), the stronger of the two NumPy baselines. Nothing here imports :mod:`cdra_jax`, so the
baselines are independent oracles of the JAX solvers as well. Units mm and rad; twists
``(v, w)``.

The module poses only depend on the module states, not on the fixed transforms being
calibrated, so they are computed once per trial, outside the iteration, in every baseline.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.optimize

_EYE3 = np.eye(3)
_SMALL_PHI = 1e-6
"""Below this rotation angle (rad) the paper's small-angle branch of Eq. 27 is used."""


# --------------------------------------------------------------------------- single pose
def hat(w: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix of a 3-vector."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula (Eq. 26): rotation matrix of a rotation vector."""
    th2 = float(w @ w)
    W = hat(w)
    if th2 < 1e-16:
        return _EYE3 + W + 0.5 * (W @ W)
    th = math.sqrt(th2)
    return _EYE3 + (math.sin(th) / th) * W + ((1.0 - math.cos(th)) / th2) * (W @ W)


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Eq. 26: pose of a twist ``(v, w)``."""
    v, w = xi[:3], xi[3:]
    th2 = float(w @ w)
    W = hat(w)
    W2 = W @ W
    if th2 < 1e-16:
        R = _EYE3 + W + 0.5 * W2
        A = _EYE3 + 0.5 * W + W2 / 6.0
    else:
        th = math.sqrt(th2)
        s, c = math.sin(th), math.cos(th)
        R = _EYE3 + (s / th) * W + ((1.0 - c) / th2) * W2
        A = _EYE3 + ((1.0 - c) / th2) * W + ((th - s) / (th2 * th)) * W2
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = A @ v
    return T


def se3_log(T: np.ndarray) -> np.ndarray:
    """Eq. 27: twist ``(v, w)`` of a pose (rotation angle below pi)."""
    R, p = T[:3, :3], T[:3, 3]
    c = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    phi = math.acos(min(1.0, max(-1.0, c)))
    S = R - R.T
    if phi < _SMALL_PHI:
        W = 0.5 * S
        k = 1.0 / 12.0
    else:
        s = math.sin(phi)
        W = (phi / (2.0 * s)) * S
        k = (2.0 * s - phi * (1.0 + math.cos(phi))) / (2.0 * phi * phi * s)
    A_inv = _EYE3 - 0.5 * W + k * (W @ W)
    out = np.empty(6)
    out[:3] = A_inv @ p
    out[3:] = (W[2, 1], W[0, 2], W[1, 0])
    return out


def adjoint(T: np.ndarray) -> np.ndarray:
    """Eq. 25: ``[[R, hat(p) R], [0, R]]``."""
    R, p = T[:3, :3], T[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = R
    Ad[:3, 3:] = hat(p) @ R
    Ad[3:, 3:] = R
    return Ad


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a pose, ``[[R^T, -R^T p], [0, 1]]``."""
    Ti = np.eye(4)
    Rt = T[:3, :3].T
    Ti[:3, :3] = Rt
    Ti[:3, 3] = -Rt @ T[:3, 3]
    return Ti


# --------------------------------------------------------------------------- the arm
def module_poses(kinds: list[tuple[str, np.ndarray | None]], q: np.ndarray) -> np.ndarray:
    """Module platform poses ``(m, K, 4, 4)`` from states ``q (m, dof)``.

    ``kinds`` lists ``(kind, axis)`` per module (``spherical``, ``revolute`` or ``prismatic``).
    """
    m = q.shape[0]
    out = np.tile(np.eye(4), (m, len(kinds), 1, 1))
    for k in range(m):
        i = 0
        for j, (kind, axis) in enumerate(kinds):
            if kind == "spherical":
                out[k, j, :3, :3] = so3_exp(q[k, i : i + 3])
                i += 3
            elif kind == "revolute":
                out[k, j, :3, :3] = so3_exp(q[k, i] * axis)
                i += 1
            else:
                out[k, j, :3, 3] = q[k, i] * axis
                i += 1
    return out


def arm_kinds(arm) -> list[tuple[str, np.ndarray | None]]:
    """``(kind, axis)`` of each module of a :class:`cdra_jax.Arm` (the only use of the Arm)."""
    return [(m.kind, np.asarray(m.axis, dtype=float)) for m in arm.modules]


def _linearise(frames: np.ndarray, poses: np.ndarray, measured: np.ndarray):
    """Stacked ``Y~ (6m,)``, ``D~ (6m, 6(K+1))`` of Eq. 9 and the metrics of Eqs. 20-21."""
    m, K = poses.shape[:2]
    n = 6 * (K + 1)
    Y = np.empty(6 * m)
    D = np.zeros((6 * m, n))
    sq_p = sq_r = 0.0
    for k in range(m):
        T = frames[0]
        for i in range(K):
            T = T @ poses[k, i]
            D[6 * k : 6 * k + 6, 6 * (i + 1) : 6 * (i + 2)] = adjoint(T)
            T = T @ frames[i + 1]
        D[6 * k : 6 * k + 6, :6] = np.eye(6)
        Y[6 * k : 6 * k + 6] = se3_log(measured[k] @ inverse(T))
        dpos = measured[k, :3, 3] - T[:3, 3]
        sq_p += float(dpos @ dpos)
        # |log(R_a^-1 R_c)| of Eq. 21 is the angle of R_a R_c^-1, i.e. |w| of Y_k (conjugate
        # rotations have the same angle): no second logarithm needed.
        w = Y[6 * k + 3 : 6 * k + 6]
        sq_r += float(w @ w)
    return Y, D, math.sqrt(sq_p / m), math.sqrt(sq_r / m)


def calibrate_numpy(
    frames0: np.ndarray,
    poses: np.ndarray,
    measured: np.ndarray,
    *,
    max_iterations: int = 20,
    tol: float = 1e-10,
    rcond: float | None = None,
) -> dict:
    """The paper's iterative least squares (Fig. 4, Eqs. 9-21), one trial, pose-by-pose NumPy.

    Args:
        frames0: nominal fixed transforms ``(K+1, 4, 4)``.
        poses: module poses ``(m, K, 4, 4)`` (:func:`module_poses`).
        measured: measured tool poses ``(m, 4, 4)``.

    Returns:
        ``dict(frames, errors (K+1, 6), iterations, converged, step_norm, delta_p, delta_R,
        rank, singular_values)``.
    """
    rcond = np.finfo(float).eps ** (2.0 / 3.0) if rcond is None else rcond
    return _iterate(_linearise, frames0, poses, measured, max_iterations, tol, rcond)


def _iterate(linearise, frames0, poses, measured, max_iterations, tol, rcond) -> dict:
    frames = frames0.copy()
    K1 = frames.shape[0]
    steps, dps, dRs = [], [], []
    converged = False
    rank, s = 0, np.zeros(6 * K1)
    for _ in range(max_iterations):
        Y, D, dp, dR = linearise(frames, poses, measured)
        dps.append(dp)
        dRs.append(dR)
        X, _, rank, s = np.linalg.lstsq(D, Y, rcond=rcond)
        step = float(np.linalg.norm(X))
        steps.append(step)
        if not np.isfinite(step):
            break
        for j in range(K1):  # Eqs. 11-14
            frames[j] = se3_exp(X[6 * j : 6 * j + 6]) @ frames[j]
        if step < tol:
            converged = True
            break
    _, _, dp, dR = linearise(frames, poses, measured)
    dps.append(dp)
    dRs.append(dR)
    errors = np.stack([se3_log(frames[j] @ inverse(frames0[j])) for j in range(K1)])  # 15-18
    return dict(
        frames=frames,
        errors=errors,
        iterations=len(steps),
        converged=converged,
        step_norm=np.asarray(steps),
        delta_p=np.asarray(dps),
        delta_R=np.asarray(dRs),
        rank=int(rank),
        singular_values=np.asarray(s),
    )


# --------------------------------------------------------------------------- batched over poses
def _hat_b(w: np.ndarray) -> np.ndarray:
    W = np.zeros(w.shape[:-1] + (3, 3))
    W[..., 0, 1], W[..., 0, 2] = -w[..., 2], w[..., 1]
    W[..., 1, 0], W[..., 1, 2] = w[..., 2], -w[..., 0]
    W[..., 2, 0], W[..., 2, 1] = -w[..., 1], w[..., 0]
    return W


def _se3_log_b(T: np.ndarray) -> np.ndarray:
    """Eq. 27 on a stack ``(m, 4, 4) -> (m, 6)``, small-angle branch per pose."""
    R, p = T[:, :3, :3], T[:, :3, 3]
    c = 0.5 * (np.trace(R, axis1=1, axis2=2) - 1.0)
    phi = np.arccos(np.clip(c, -1.0, 1.0))
    small = phi < _SMALL_PHI
    s = np.sin(np.where(small, 1.0, phi))
    f = np.where(small, 0.5, phi / (2.0 * s))
    k = np.where(
        small, 1.0 / 12.0, (2.0 * s - phi * (1.0 + np.cos(phi))) / (2.0 * phi * phi * s + small)
    )
    W = f[:, None, None] * (R - np.swapaxes(R, 1, 2))
    A_inv = _EYE3 - 0.5 * W + k[:, None, None] * (W @ W)
    w = np.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], axis=-1)
    return np.concatenate([np.einsum("mij,mj->mi", A_inv, p), w], axis=-1)


def _linearise_vectorized(frames: np.ndarray, poses: np.ndarray, measured: np.ndarray):
    m, K = poses.shape[:2]
    D = np.zeros((m, 6, 6 * (K + 1)))
    D[:, :, :6] = np.eye(6)
    T = np.broadcast_to(frames[0], (m, 4, 4))
    for i in range(K):
        T = T @ poses[:, i]
        R, p = T[:, :3, :3], T[:, :3, 3]
        c = 6 * (i + 1)
        D[:, :3, c : c + 3] = R
        D[:, :3, c + 3 : c + 6] = _hat_b(p) @ R
        D[:, 3:, c + 3 : c + 6] = R
        T = T @ frames[i + 1]
    R, p = T[:, :3, :3], T[:, :3, 3]
    Rt = np.swapaxes(R, 1, 2)
    T_inv = np.zeros((m, 4, 4))
    T_inv[:, :3, :3] = Rt
    T_inv[:, :3, 3] = -np.einsum("mij,mj->mi", Rt, p)
    T_inv[:, 3, 3] = 1.0
    Y = _se3_log_b(measured @ T_inv)
    dpos = measured[:, :3, 3] - p
    dp = math.sqrt(float(np.mean(np.sum(dpos * dpos, axis=-1))))
    dR = math.sqrt(float(np.mean(np.sum(Y[:, 3:] ** 2, axis=-1))))  # see _linearise
    return Y.reshape(-1), D.reshape(6 * m, -1), dp, dR


def calibrate_numpy_vectorized(
    frames0: np.ndarray,
    poses: np.ndarray,
    measured: np.ndarray,
    *,
    max_iterations: int = 20,
    tol: float = 1e-10,
    rcond: float | None = None,
) -> dict:
    """:func:`calibrate_numpy` with every per-pose operation batched over the ``m`` poses."""
    rcond = np.finfo(float).eps ** (2.0 / 3.0) if rcond is None else rcond
    return _iterate(_linearise_vectorized, frames0, poses, measured, max_iterations, tol, rcond)


# --------------------------------------------------------------------------- scipy
def calibrate_scipy(
    frames0: np.ndarray,
    poses: np.ndarray,
    measured: np.ndarray,
    *,
    method: str = "trf",
    tol: float = 1e-12,
    max_nfev: int | None = None,
) -> dict:
    """``scipy.optimize.least_squares`` on the stacked Eq. 7 residual as a function of ``X``.

    ``F_j(X) = exp(hat(X_j)) F_j`` (Eqs. 11-14 in one step), residual
    ``[log(T_meas,k T_k(X)^-1)^v]_k`` (Eq. 7 stacked, Eq. 9) using the per-pose helpers above;
    the Jacobian by finite differences (scipy's default ``2-point``).
    """
    m, K = poses.shape[:2]
    K1 = K + 1

    def frames_of(X):
        return np.stack([se3_exp(X[6 * j : 6 * j + 6]) @ frames0[j] for j in range(K1)])

    def residual(X):
        F = frames_of(X)
        Y = np.empty(6 * m)
        for k in range(m):
            T = F[0]
            for i in range(K):
                T = T @ poses[k, i] @ F[i + 1]
            Y[6 * k : 6 * k + 6] = se3_log(measured[k] @ inverse(T))
        return Y

    res = scipy.optimize.least_squares(
        residual, np.zeros(6 * K1), method=method, xtol=tol, ftol=tol, gtol=tol, max_nfev=max_nfev
    )
    frames = frames_of(res.x)
    errors = np.stack([se3_log(frames[j] @ inverse(frames0[j])) for j in range(K1)])
    return dict(
        frames=frames,
        errors=errors,
        iterations=int(res.nfev),
        converged=bool(res.success),
        cost=float(2.0 * res.cost),
    )
