"""Statistics of the diagnosis on the linearised, whitened calibration problem (numpy).

Notation: ``r (N,)`` is the whitened residual (unit variance per entry under the stated noise
model) at a fit: 6 entries per measured full pose and 3 per measured point, only the measured
ones. ``A (N, k)`` is the whitened Jacobian of the fitted parameters (the 6 (K+1) frame errors,
24 for the CDRA, calibrated marker positions, plus a candidate's physical parameters).
Cross-validation folds split the measurement rows (poses), never the entries of one row: every
function takes the fold of each entry, ``fold[row]``.

Held-out test. For fold ``f`` the parameters are refitted on the other folds (minimum-norm
least squares), ``x_-f = A_-f^+ r_-f``, and the held-out residual ``e_f = r_f - A_f x_-f`` has,
under the model with unit noise, the predictive covariance ``S_f = I + A_f C_-f A_f^T`` with
``C_-f = (A_-f^T A_-f)^+`` (the parameter uncertainty of the refit). The statistic
``Q = sum_f e_f^T S_f^-1 e_f`` is a quadratic form ``e^T W^T W e`` of the standard normal noise
``e`` (the true parameters cancel: the unidentifiable directions of the frame errors are the
same for every pose), so ``Q ~ sum_k lambda_k chi2_1`` with ``lambda_k`` the squared singular
values of ``W``; its tail is computed exactly by Imhof's integral (:func:`quadratic_form_sf`).
The folds overlap in their training sets, so ``Q`` is *not* ``chi2(N)``; its mean is ``N``.

Candidate tests. A candidate's columns ``J`` are projected on the orthogonal complement of the
geometric ones, ``(I - P_D) J``; directions of ``J`` whose visible fraction
``|(I - P_D) J v|^2 / |J v|^2`` is below 1e-3 (absorbed fraction > 0.999) cannot be seen in
poses and are dropped. On the remaining ``k`` directions (orthonormal basis ``B``) the extra
sum of squares ``T = |B^T r|^2`` gives the F statistic
``F = (T / k) / ((|r|^2 - T) / (N - rank(D) - k))`` (exact for the linear Gaussian model,
independent of the noise scale), corrected over the candidates by Holm's step-down method.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import scipy.integrate
import scipy.linalg
import scipy.optimize
import scipy.stats

_RCOND = 1e-10
VISIBLE_MIN = 1e-3
"""A direction whose visible fraction is below this (absorbed > 0.999) is not identifiable."""


def fold_of_poses(m: int, folds: int, seed: int) -> np.ndarray:
    """Fold index ``(m,)`` of each pose: a seeded random permutation dealt into ``folds``."""
    if folds < 2:
        raise ValueError(f"folds must be at least 2, got {folds}")
    k = min(folds, m)
    perm = np.random.default_rng(seed).permutation(m)
    out = np.empty(m, int)
    out[perm] = np.arange(m) % k
    return out


def _svd(A: np.ndarray, full_matrices: bool = True, compute_uv: bool = True):
    """``numpy.linalg.svd``; where LAPACK's divide-and-conquer driver does not converge (badly
    scaled or nearly repeated singular values), the slower QR-iteration driver (``gesvd``).
    Non-finite input is an error naming what to check."""
    A = np.asarray(A, dtype=float)
    if not np.all(np.isfinite(A)):
        raise ValueError(
            "a non-finite value (NaN or inf) in the linearised model: a candidate effect or the "
            "data produce it (check the auxiliary columns and the model's masses)"
        )
    try:
        if not compute_uv:
            return np.linalg.svd(A, compute_uv=False)
        return np.linalg.svd(A, full_matrices=full_matrices)
    except np.linalg.LinAlgError:
        return scipy.linalg.svd(
            A, full_matrices=full_matrices, compute_uv=compute_uv, lapack_driver="gesvd"
        )


def _cholesky(S: np.ndarray) -> np.ndarray:
    """Cholesky factor of ``S = I + G G^T`` (positive definite); symmetrised and, where
    rounding makes it indefinite, with a relative jitter of 1e-12 on the diagonal."""
    S = 0.5 * (S + S.T)
    try:
        return np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        jitter = 1e-12 * max(float(np.trace(S)) / max(S.shape[0], 1), 1.0)
        return np.linalg.cholesky(S + jitter * np.eye(S.shape[0]))


def _normalise_columns(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = np.linalg.norm(A, axis=0)
    s = np.where(n > 0, 1.0 / np.where(n > 0, n, 1.0), 1.0)
    return A * s, s


def pinv(A: np.ndarray, rcond: float = _RCOND) -> tuple[np.ndarray, int]:
    """Pseudo-inverse with a relative singular-value cut-off, and the numerical rank."""
    if A.shape[1] == 0:
        return np.zeros((0, A.shape[0])), 0
    U, s, Vt = _svd(A, full_matrices=False)
    keep = s > rcond * (s[0] if s.size else 0.0)
    return (Vt[keep].T / s[keep]) @ U[:, keep].T, int(keep.sum())


def orthonormal_basis(A: np.ndarray, rcond: float = _RCOND) -> np.ndarray:
    """Orthonormal basis ``(N, rank)`` of the column space of ``A`` (columns normalised first)."""
    if A.shape[1] == 0:
        return np.zeros((A.shape[0], 0))
    U, s, _ = _svd(_normalise_columns(A)[0], full_matrices=False)
    return U[:, s > rcond * s[0]] if s.size and s[0] > 0 else np.zeros((A.shape[0], 0))


@dataclass
class HeldOut:
    """Cross-validated prediction of a linear model (see the module docstring).

    Attributes:
        residual: ``(N,)`` held-out whitened residual of each entry.
        variance: ``(N,)`` its predictive variance (diagonal of ``S_f``).
        statistic: ``Q``.
        loglik: held-out Gaussian log-likelihood ``-(Q + sum log det S_f + N log 2 pi) / 2``.
        weights: ``lambda_k`` of the null distribution of ``Q`` (when requested), else None.
        ss_weights: those of the plain sum of squares ``|e|^2`` of the held-out residuals (when
            requested), else None.
    """

    residual: np.ndarray
    variance: np.ndarray
    statistic: float
    loglik: float
    weights: np.ndarray | None = None
    ss_weights: np.ndarray | None = None

    @property
    def sum_of_squares(self) -> float:
        """``|e|^2``: the plain sum of squared held-out residuals (what ``delta_p`` reports)."""
        return float(np.sum(self.residual**2))

    @property
    def expected_sum_of_squares(self) -> float:
        """``E|e|^2 = tr S`` under the model."""
        return float(np.sum(self.variance))

    def p_value_sum_of_squares(self, tolerance: float = 1.0) -> float:
        """``P(|e'|^2 >= |e|^2 / tolerance)`` under the model (needs ``ss_weights``): with a
        ``tolerance`` above 1, whether the residual exceeds what a noise variance ``tolerance``
        times the stated one explains. Unlike ``Q``, it is not deflated when a model with many
        parameters predicts with a wide covariance."""
        if self.ss_weights is None:
            raise ValueError("held-out null weights were not computed (with_null=False)")
        return quadratic_form_sf(self.sum_of_squares / tolerance, self.ss_weights)

    def p_value(self, tolerance: float = 1.0) -> float:
        """``P(Q' >= Q / tolerance)`` under the model (needs ``weights``); see
        :meth:`p_value_sum_of_squares` for ``tolerance``."""
        if self.weights is None:
            raise ValueError("held-out null weights were not computed (with_null=False)")
        return quadratic_form_sf(self.statistic / tolerance, self.weights)


def heldout(r: np.ndarray, A: np.ndarray, fold: np.ndarray, *, with_null: bool = False) -> HeldOut:
    """K-fold held-out residuals and statistic of the linear model ``r ~ A x`` (unit noise).

    Args:
        r: ``(N,)`` whitened residual.
        A: ``(N, k)`` whitened Jacobian.
        fold: ``(N,)`` fold of each entry (that of its pose, :func:`fold_of_poses`).
        with_null: also compute the weights of the null distribution of ``Q``.
    """
    N = r.shape[0]
    rows = np.asarray(fold)
    An, _ = _normalise_columns(A)
    res = np.zeros(N)
    var = np.zeros(N)
    Q = 0.0
    logdet = 0.0
    W = np.zeros((N, N)) if with_null else None
    Wss = np.zeros((N, N)) if with_null else None
    for f in np.unique(rows):
        te = rows == f
        tr = ~te
        P, _ = pinv(An[tr])
        At = An[te]
        e = r[te] - At @ (P @ r[tr])
        G = At @ P  # (n_te, n_tr): prediction from the training residual
        S = np.eye(int(te.sum())) + G @ G.T
        L = _cholesky(S)
        z = np.linalg.solve(L, e)
        Q += float(z @ z)
        logdet += 2.0 * float(np.sum(np.log(np.diag(L))))
        res[te] = e
        var[te] = np.diag(S)
        if W is not None and Wss is not None:
            B = np.zeros((int(te.sum()), N))
            B[:, te] = np.eye(int(te.sum()))
            B[:, tr] = -G
            W[te] = np.linalg.solve(L, B)
            Wss[te] = B
    weights = ss_weights = None
    if W is not None and Wss is not None:
        weights = _svd(W, compute_uv=False) ** 2
        ss_weights = _svd(Wss, compute_uv=False) ** 2
    loglik = -0.5 * (Q + logdet + N * np.log(2 * np.pi))
    return HeldOut(res, var, Q, float(loglik), weights, ss_weights)


def quadratic_form_sf(x: float, weights: np.ndarray) -> float:
    """``P(sum_k w_k z_k^2 > x)`` for independent standard normal ``z_k`` (Imhof 1961).

    ``P = 1/2 + (1/pi) int_0^inf sin(th(u)) / (u rho(u)) du`` with
    ``th(u) = sum atan(w_k u) / 2 - x u / 2`` and ``rho(u) = prod (1 + w_k^2 u^2)^(1/4)``.
    The weights may have either sign (an indefinite form: the tail of a ratio of quadratic
    forms, :func:`structure_test`). Accurate to ~1e-10 absolute; beyond that (a Chernoff
    bound below 1e-9) the Chernoff upper bound is returned, and with fewer than 10 non-zero
    weights a seeded Monte Carlo estimate (4e5 draws).
    """
    w = np.asarray(weights, float)
    w = w[np.abs(w) > 1e-12 * max(float(np.abs(w).max(initial=0.0)), 1e-300)]
    if w.size == 0:
        return 1.0 if x < 0 else 0.0
    if x <= 0 and w.min() > 0:
        return 1.0
    if w.max() <= 0:
        return 0.0 if x >= 0 else _flip(x, w)
    bound = _chernoff_sf(x, w)
    if bound < 1e-9:  # far in the tail: the bound is all the precision a p-value needs
        return bound
    if w.size < 10:  # Imhof's integrand decays too slowly; a seeded Monte Carlo is enough here
        z = np.random.default_rng(0).standard_normal((400_000, w.size))
        return float(np.mean((z * z) @ w > x))

    def integrand(u: float) -> float:
        if u == 0.0:
            return 0.5 * (float(w.sum()) - x)
        wu = w * u
        th = 0.5 * float(np.sum(np.arctan(wu))) - 0.5 * x * u
        log_rho = 0.25 * float(np.sum(np.log1p(wu * wu)))
        return float(np.sin(th) * np.exp(-log_rho) / u)

    # The integrand decays like u^(-1 - n/2): integrate piecewise on [0, U] with U where
    # rho(U) > 1e30, on pieces that double in length (each holds a few oscillations at most).
    top = float(np.abs(w).max())
    edges = [0.0, 0.5 / top]
    while 0.25 * float(np.sum(np.log1p((w * edges[-1]) ** 2))) < 70.0 and edges[-1] < 1e12:
        edges.append(2.0 * edges[-1])
    val = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", scipy.integrate.IntegrationWarning)
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            piece, _ = scipy.integrate.quad(integrand, a, b, limit=400, epsabs=1e-13, epsrel=1e-10)
            val += piece
    return float(np.clip(min(0.5 + val / np.pi, bound), 0.0, 1.0))


def _flip(x: float, w: np.ndarray) -> float:
    """``P(sum w z^2 > x)`` for non-positive weights and ``x < 0``: ``1 - P(sum -w z^2 >= -x)``."""
    return 1.0 - quadratic_form_sf(-x, -w)


def _chernoff_sf(x: float, w: np.ndarray) -> float:
    """Chernoff upper bound ``min_t exp(-t x) E[exp(t Q)]`` of ``P(Q > x)`` (``w`` with at least
    one positive entry): far in the tail, where the oscillating Imhof integral loses its
    digits, it is the sharper of the two."""
    if x <= float(w.sum()):
        return 1.0
    t_max = 0.5 / float(w.max())

    def log_bound(t: float) -> float:
        return -t * x - 0.5 * float(np.sum(np.log1p(-2.0 * t * w)))

    res = scipy.optimize.minimize_scalar(
        log_bound, bounds=(0.0, t_max * (1 - 1e-12)), method="bounded"
    )
    return float(np.exp(min(res.fun, 0.0)))


def holm(p: np.ndarray) -> np.ndarray:
    """Holm step-down adjusted p-values (controls the family-wise error rate)."""
    p = np.asarray(p, float)
    n = p.size
    order = np.argsort(p, kind="stable")
    adj = np.empty(n)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (n - rank) * p[i]))
        adj[i] = running
    return adj


@dataclass
class Projection:
    """A candidate's columns with the geometric part projected out.

    Attributes:
        basis: ``(N, k)`` orthonormal basis of the visible projected directions.
        absorbed_fraction: ``1 - max visible fraction`` (1: entirely absorbed by the frames).
        visible: visible fraction of each direction of the candidate's column space.
    """

    basis: np.ndarray
    absorbed_fraction: float
    visible: np.ndarray

    @property
    def df(self) -> int:
        return int(self.basis.shape[1])


def project(J: np.ndarray, UD: np.ndarray) -> Projection:
    """Project ``J (N, p)`` on the complement of the orthonormal geometric basis ``UD (N, r)``."""
    UJ = orthonormal_basis(J)
    if UJ.shape[1] == 0:
        return Projection(np.zeros((J.shape[0], 0)), 1.0, np.zeros(0))
    Pj = UJ - UD @ (UD.T @ UJ)
    U, s, _ = _svd(Pj, full_matrices=False)
    vis = s * s
    keep = vis > VISIBLE_MIN
    return Projection(U[:, keep], float(1.0 - vis.max()), vis)


def f_test(
    r: np.ndarray, basis: np.ndarray, df_resid: int, floor2: float = 0.0
) -> tuple[float, float, int, int]:
    """``(F, p, df1, df2)`` for adding the projected directions ``basis`` to the fit.

    ``floor2``: the mean square of rounding error per entry of ``r`` (:func:`rounding_floor`);
    the residual mean square in the denominator is never taken below it, so that a residual
    at the rounding level (exact data) gives no significant F.
    """
    k = basis.shape[1]
    df2 = df_resid - k
    if k == 0 or df2 <= 0:
        return float("nan"), 1.0, k, df2
    T = float(np.sum((basis.T @ r) ** 2))
    rest = max(float(r @ r) - T, 1e-300)
    F = (T / k) / max(rest / df2, floor2)
    return F, float(scipy.stats.f.sf(F, k, df2)), k, df2


def principal_cosines(Ba: np.ndarray, Bb: np.ndarray) -> np.ndarray:
    """Cosines of the principal angles between two orthonormal bases, decreasing."""
    if Ba.shape[1] == 0 or Bb.shape[1] == 0:
        return np.zeros(0)
    return np.clip(_svd(Ba.T @ Bb, compute_uv=False), 0.0, 1.0)


def indistinguishable(Ba: np.ndarray, Bb: np.ndarray, cos_min: float = 0.98) -> bool:
    """One projected space lies (nearly) inside the other: all ``min(ka, kb)`` cosines > cos_min."""
    c = principal_cosines(Ba, Bb)
    return bool(c.size and c.min() > cos_min)


def repeat_groups(q: np.ndarray, tol: float) -> list[np.ndarray]:
    """Groups (index arrays, size >= 2) of poses whose module states agree within ``tol``."""
    m = q.shape[0]
    seen = np.zeros(m, bool)
    out = []
    for i in range(m):
        if seen[i]:
            continue
        same = np.all(np.abs(q - q[i]) <= tol, axis=1) & ~seen
        idx = np.flatnonzero(same)
        seen[idx] = True
        if idx.size > 1:
            out.append(idx)
    return out


@dataclass
class LackOfFit:
    """Lack-of-fit F test from repeated poses (:func:`lack_of_fit`).

    Attributes:
        F: the statistic (None when not applicable).
        p_value: ``P(F' >= F)`` under the model (None when not applicable).
        df_lack_of_fit, df_pure_error: its degrees of freedom.
        applicable: False when both the lack of fit and the pure error are at the rounding
            level (exact data: there is no scatter to compare the misfit with, and no misfit).
    """

    F: float | None
    p_value: float | None
    df_lack_of_fit: int
    df_pure_error: int
    applicable: bool = True


def lack_of_fit(
    r: np.ndarray,
    groups: list[np.ndarray],
    df_resid: int,
    floor2: float = 0.0,
    *,
    row: np.ndarray | None = None,
    entry: np.ndarray | None = None,
) -> LackOfFit | None:
    """Lack-of-fit F test from repeated poses, or None (no repeats, or no degrees of freedom).

    Pure error: scatter of the whitened residuals within each group of repeats, entry by entry
    (the same entry of each repeat: ``entry`` numbers the entries within a row; an entry seen
    in ``n`` repeats gives ``n - 1`` degrees of freedom); lack of fit: the rest of the residual
    sum of squares. Needs no noise value (only the ratio of the noise of the entries enters
    through the whitening). ``row (N,)`` is the measurement row of each entry; without
    ``row``/``entry``, 6 entries per pose in pose order.

    ``floor2`` is the mean square of rounding error per entry of ``r`` (:func:`rounding_floor`).
    The pure-error mean square is never taken below it: exactly repeated, noise-free poses
    have a pure error of zero (or of rounding), against which any rounding-level misfit would
    look infinitely significant. When both mean squares are at or below the floor the test is
    not applicable (``applicable=False``, no p-value): the data are exact and the model fits
    them to rounding.
    """
    if not groups:
        return None
    if row is None or entry is None:
        row = np.repeat(np.arange(r.size // 6), 6)
        entry = np.tile(np.arange(6), r.size // 6)
    ss_pe = 0.0
    df_pe = 0
    for g in groups:
        sel = np.isin(row, g)
        for e in np.unique(entry[sel]):
            v = r[sel & (entry == e)]
            ss_pe += float(np.sum((v - v.mean()) ** 2))
            df_pe += v.size - 1
    df_lof = df_resid - df_pe
    if df_lof <= 0 or df_pe <= 0:
        return None
    ss_lof = max(float(r @ r) - ss_pe, 0.0)
    ms_lof, ms_pe = ss_lof / df_lof, ss_pe / df_pe
    if floor2 > 0 and max(ms_lof, ms_pe) <= floor2:
        return LackOfFit(None, None, df_lof, df_pe, applicable=False)
    F = ms_lof / max(ms_pe, floor2, 1e-300)
    return LackOfFit(F, float(scipy.stats.f.sf(F, df_lof, df_pe)), df_lof, df_pe)


ROUNDING = 1e3 * float(np.finfo(float).eps)
"""Relative rounding floor of a residual: 1000 float64 ulps of the measured magnitudes (the
residual of an exact fit is about one ulp of the tool position; the margin covers the chain of
products in the kinematics)."""


def rounding_floor(positions_mm: np.ndarray) -> tuple[float, float]:
    """``(position mm, rotation rad)`` below which a residual is rounding, not measurement:
    :data:`ROUNDING` times the largest measured distance from the origin (at least 1 mm), and
    :data:`ROUNDING` rad."""
    size = max(1.0, float(np.max(np.linalg.norm(np.asarray(positions_mm), axis=-1), initial=0.0)))
    return ROUNDING * size, ROUNDING


def variance_components(
    e: np.ndarray,
    D: np.ndarray,
    groups: np.ndarray,
    floors: np.ndarray,
    *,
    iterations: int = 100,
    rtol: float = 1e-10,
) -> np.ndarray:
    """The noise std of each group of residual entries, estimated from a residual.

    ``e (N,)`` is the residual in physical units (e.g. per pose the tool-point position error
    in mm, then the rotation in rad; per point mm) and ``D (N, n)`` the Jacobian of the fitted
    parameters in the same units; ``groups (N,)`` numbers each entry's group ``0 .. G-1`` and
    ``floors (G,)`` the smallest std of each. Each group's variance is its weighted residual
    sum of squares over its share of the residual degrees of freedom (Foerstner's
    variance-component estimation, REML-like): with rows weighted by ``1 / s``, ``H`` the hat
    matrix of the weighted fit,

        ``s_g^2 = sum_{i in g} (s_g res_i)^2 / (n_g - sum_{i in g} H_ii)``,

    iterated to its fixed point (the weighted fit and ``H`` depend on ``s``). Each std is kept
    at or above its floor (:func:`rounding_floor`), so that exact data give the rounding floor
    rather than zero. With one fixed ratio instead (say 1 mm : 1 mrad), the whitened residual
    of a device whose ratio differs is not homoscedastic, and the candidate F tests, which
    assume it is, fire on clean data.

    Returns:
        ``(G,)`` the stds.
    """
    groups = np.asarray(groups, dtype=int)
    floors = np.asarray(floors, dtype=float)
    n_groups = floors.size
    s = np.array(
        [
            max(float(np.sqrt(np.mean(e[groups == g] ** 2))) if np.any(groups == g) else 0.0, f)
            for g, f in enumerate(floors)
        ]
    )
    for _ in range(iterations):
        w = s[groups]
        U = orthonormal_basis(D / w[:, None])
        rw = e / w
        res = rw - U @ (U.T @ rw)
        h = np.sum(U * U, axis=1)
        new = s.copy()
        for g in range(n_groups):
            sel = groups == g
            if not sel.any():
                continue
            dof = max(float(sel.sum() - h[sel].sum()), 1.0)
            new[g] = max(s[g] * float(np.sqrt(np.sum(res[sel] ** 2) / dof)), floors[g])
        done = bool(np.all(np.abs(new - s) <= rtol * s))
        s = new
        if done:
            break
    return s


STRUCTURE_SCALES = (0.4, 1.0)
"""Length scales of the structure test's smoother, in standard deviations of each regressor
(Bonferroni over them)."""

STRUCTURE_RIDGE = 1.0
"""Ridge of the structure test's kernel smoother (whitened units: a prior signal variance equal
to the noise variance)."""


@dataclass
class Structure:
    """Whether the residual is predictable from the rows' regressors (:func:`structure_test`).

    Attributes:
        statistic: ``T`` of the most significant group: the fraction of ``|r|^2`` that its
            leave-one-row-out smoother predicts (negative: worse than predicting zero).
        p_value: ``P(T' >= T)`` under the null of no structure, Bonferroni over the groups of
            regressors and the length scales.
        gain: ``|r|^2 - |r - r_hat|^2`` of that group and scale (whitened units).
        scale: its length scale (standard deviations of the regressors).
        group: the index of that group.
        group_p: ``(G,)`` each group's p-value (Bonferroni over the scales only).
    """

    statistic: float
    p_value: float
    gain: float
    scale: float
    group: int = -1
    group_p: np.ndarray | None = None


def _standardise(X: np.ndarray) -> np.ndarray:
    X = np.asarray(X, float)
    sd = X.std(axis=0)
    sd = np.where(sd > 0, sd, 1.0)
    return (X - X.mean(axis=0)) / sd


def cv_smoother(X: np.ndarray, length_scale: float, ridge: float = STRUCTURE_RIDGE) -> np.ndarray:
    """``H (n, n)``: the leave-one-out kernel-ridge prediction of a value at each of ``n`` rows
    from the other rows, ``y_hat = H y``, over the rows' regressors ``X (n, d)`` (standardised)
    with a Gaussian kernel of ``length_scale``.

    With the smoother ``S = K (K + ridge I)^-1``, the exact leave-one-out prediction of kernel
    ridge regression is ``y_hat_i = ((S y)_i - S_ii y_i) / (1 - S_ii)``.
    """
    d2 = np.sum((X[:, None, :] - X[None, :, :]) ** 2, axis=-1)
    K = np.exp(-0.5 * d2 / length_scale**2)
    S = np.linalg.solve(K + ridge * np.eye(K.shape[0]), K).T  # K (K + ridge I)^-1 (symmetric)
    d = np.diag(S).copy()
    H = (S - np.diag(d)) / (1.0 - d)[:, None]
    return H


def structure_test(
    r: np.ndarray,
    U: np.ndarray,
    X: np.ndarray,
    row: np.ndarray,
    entry: np.ndarray,
    groups: np.ndarray,
    *,
    scales: tuple[float, ...] = STRUCTURE_SCALES,
) -> Structure:
    """Is the residual predictable from the regressors? Needs no noise value.

    ``r (N,)`` is the whitened residual of a least-squares fit whose whitened Jacobian has the
    orthonormal column basis ``U (N, k)``; ``X (m, d)`` the regressors of each measurement row
    (module states, time, ...), ``groups (d,)`` which group each belongs to (a module's state
    entries together); ``row`` and ``entry`` each entry's row and kind. For each group and
    length scale, with ``H`` the leave-one-row-out smoother on that group's regressors
    (:func:`cv_smoother`, applied to each entry kind over the rows that measure it), the
    statistic is the fraction of the residual it predicts,
    ``T = (|r|^2 - |r - H r|^2) / |r|^2 = r^T A r / r^T r`` with ``A = H + H^T - H^T H``: a
    ratio of quadratic forms that does not depend on the noise scale. Under the null (no
    structure: ``r = P e``, ``P = I - U U^T``, ``e`` white noise of any scale) its tail is
    exact: ``P(T' >= T) = P(e^T P (A - T I) P e >= 0) = P(sum_i (mu_i - T) z_i^2 >= 0)``
    with ``mu_i`` the eigenvalues of ``P A P`` on the complement of ``U`` (Imhof's integral
    of an indefinite form, :func:`quadratic_form_sf`). Unlike a chi-square against a noise
    value, it cannot be hidden by a noise estimate that absorbed the misfit. One group at a
    time: an effect usually lives at one module, and the group that predicts the residual is
    where it lives.
    """
    X = np.asarray(X, float)
    groups = np.asarray(groups)
    N = r.size
    names = [g for g in np.unique(groups) if np.any(X[:, groups == g].std(axis=0) > 0)]
    if not names or N == 0 or U.shape[1] >= N:
        return Structure(0.0, 1.0, 0.0, float("nan"))
    Z = _standardise(X)
    rr = float(r @ r)
    # Each entry kind is smoothed over its own rows: the quadratic form is block diagonal, one
    # block per kind (kinds measured in the same rows share the smoother).
    kinds = [np.flatnonzero(entry == e) for e in np.unique(entry)]
    best: Structure | None = None
    group_p = np.ones(int(np.max(groups)) + 1)
    for g in names:
        Zg = Z[:, groups == g]
        for s in scales:
            A = np.zeros((N, N))
            cache: dict[bytes, np.ndarray] = {}
            for idx in kinds:
                rows_k = row[idx]
                key = rows_k.tobytes()
                if key not in cache:
                    H = cv_smoother(Zg[rows_k], s)
                    cache[key] = H + H.T - H.T @ H
                A[np.ix_(idx, idx)] = cache[key]
            gain = float(r @ A @ r)
            T = gain / rr if rr > 0 else 0.0
            # P (A - T I) P with P = I - U U^T: eigenvalues mu_i - T on the complement of U,
            # zero on U (dropped by quadratic_form_sf)
            M = A - T * np.eye(N)
            MU = M @ U
            M = M - MU @ U.T - U @ MU.T + U @ ((U.T @ MU) @ U.T)
            p = min(1.0, len(scales) * quadratic_form_sf(0.0, np.linalg.eigvalsh(M)))
            group_p[g] = min(group_p[g], p)
            if best is None or p < best.p_value:
                best = Structure(T, p, gain, s, int(g))
    assert best is not None
    best.p_value = min(1.0, len(names) * best.p_value)
    best.group_p = group_p
    return best
