"""How well a pose set pins the frame errors down: covariance, Cramer-Rao bound, intervals.

Model. With a :class:`~cdra_jax.calibration.NoiseModel` the stacked residual is whitened
(Eq. 9 with ``G``, see :mod:`cdra_jax.calibration.model`), ``r~ = D~ X + n`` with
``n ~ N(0, I)`` to first order, ``D~ (6m, n)`` the whitened calibration Jacobian (Eq. 8) at the
model and ``X`` the frame-error twists (Eq. 8, mm and rad). The Fisher information is
``F = D~^T D~``. For the CDRA it is singular (rank 22 of 24, see :mod:`cdra_jax.identifiability`),
so:

* the covariance of the solvers' minimum-norm estimate (Eq. 10 with the rank-revealing
  pseudo-inverse of :mod:`cdra_jax.calibration.linear`) is ``F^+ = V_r S_r^-2 V_r^T``, with the
  same relative singular-value cut-off ``rcond`` as the solvers (``eps ** (2/3)`` by default);
* the Cramer-Rao bound on an identifiable linear combination ``c^T X`` (``c`` in the row space of
  ``D~``) is ``c^T F^+ c``; for any ``c`` with a component in the null space no unbiased
  estimator exists and the bound is reported as ``inf``;
* the tool pose predicted at a state ``q`` moves by the world-frame twist
  ``dT = D(q) X`` (``T -> exp(hat(dT)) T``, Eqs. 5-8), so its twist covariance is
  ``D(q) F^+ D(q)^T``; the position error is ``[I, -hat(p)] dT`` (mm) and the world-frame
  orientation error is the rotational part ``w`` (rad). That is only the covariance when every
  direction that moves the tool at ``q`` is identified by the calibration poses: where the
  position (orientation) rows of ``D(q)`` have a component in the null space ``N`` of ``D~``,
  ``|rows N| > tol |rows|`` (Frobenius norms, ``tol = IDENTIFIABLE_TOL = 1e-8``), the error
  there is not bounded by the noise at all (the minimum-norm estimate leaves that component of
  the true errors uncorrected) and the predicted covariance is ``inf``. Directions that move no
  tool pose (the CDRA's two, a screw along the elbow axis moved between ``upper_arm`` and
  ``forearm``) are in every ``N`` and give ``|rows N| < 1e-15 |rows|``: they never make a
  prediction infinite. Pose sets of rank below the structural one (22 for the CDRA: too few or
  repeated poses) and empty ones do, at every state they do not pin down. The threshold is far
  from both: rounding contaminates a computed null vector by about ``eps s_max / s_r``
  (``s_r``: the smallest kept singular value), which reaches ``1e-8`` only for sets within a
  factor ``~1e8 eps`` of the rank cut-off, whose predictions are meaningless anyway.

Gradients. The covariance is built from the pseudo-inverse ``D~^+`` with its constant-rank
derivative (Golub and Pereyra), not by differentiating an SVD or eigendecomposition (whose
derivatives are undefined at the CDRA's repeated zero singular values): the covariances and
predicted accuracies are differentiable w.r.t. the states, the model and the noise wherever the
numerical rank does not change.

Robust fits. After :func:`~cdra_jax.calibration.calibrate_robust` pass its final IRLS weights
``w_i`` (``weights=``). The covariance is then the weighted (IRLS) form
``(D~^T W D~)^+``, ``W = diag(w_i I_6)``: pose ``i`` counts as measured with the noise
``(s_pos / sqrt(w_i), s_rot / sqrt(w_i))``, the noise model of the last reweighted solve, so a
down-weighted outlier carries (almost) no information and the intervals widen by what it no
longer contributes (a pose left out by a rejection refit, weight 0, none at all). With all
weights 1 it is the least-squares covariance. (This treats the
weights as known; it is the sandwich ``A^+ B A^+`` of M-estimation with
``A = B = D~^T W D~``, exact when the kept poses follow the stated noise.)

The estimate's units are mixed (mm for ``v``, rad for ``w``), as in the paper; covariances are in
mm^2, mm rad and rad^2 accordingly. Linearise at the calibrated model (``solution.frames``) with
the measured tool poses for whitening to describe a finished calibration, or at the nominal model
to plan one (nothing needs to have been measured: the model's tool poses are used for whitening).

Everything up to :func:`predicted_pose_covariance` is pure JAX, jitted (``equinox.filter_jit``:
one compile per shape instead of many small eager ones) and vmap-able;
:func:`analyze_uncertainty` and :func:`uncertainty_dict` build a JSON-ready report on the host.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from . import lie
from .arm import Arm, chain, module_poses
from .calibration.linear import default_rcond
from .calibration.model import NoiseModel, calibration_jacobian, whitening
from .calibration.validation import require_finite_states
from .compilation import compiled_when_eager, filter_jit
from .identifiability import analyze as analyze_identifiability

DEFAULT_CONFIDENCE = 0.95
IDENTIFIABLE_TOL = 1e-8
"""A direction ``c`` counts as identifiable when ``|P_null c| <= IDENTIFIABLE_TOL |c|``; the
tool pose at a state is predicted with a finite covariance when its Jacobian rows ``R`` satisfy
``|R N| <= IDENTIFIABLE_TOL |R|`` (``N``: the calibration set's null space)."""


def _check_states(arm: Arm, q: Array, name: str) -> None:
    """Trace-time shape check of module states ``(..., m, dof)``."""
    if q.ndim < 2 or q.shape[-1] != arm.dof:
        raise ValueError(
            f"{name} must have shape (m, {arm.dof}) with columns {arm.state_names}, got {q.shape}"
        )


def _check_noise_and_measured(
    noise: NoiseModel | None, measured: ArrayLike | None, poses: tuple[int, ...]
) -> None:
    """Trace-time checks: noise stds are numbers or one per pose, measured poses one per state."""
    if noise is not None:
        for name in ("position_mm", "rotation_rad"):
            shape = np.shape(getattr(noise, name))
            try:
                ok = np.broadcast_shapes(shape, poses) == poses
            except ValueError:
                ok = False
            if not ok:
                raise ValueError(
                    f"noise.{name} must be a number or one std per pose, shape (m,) = "
                    f"({poses[-1]},), got shape {shape}"
                )
    if measured is not None and np.shape(measured) != poses + (4, 4):
        raise ValueError(
            f"measured must hold one tool pose per state of q, shape (m, 4, 4) = "
            f"{poses + (4, 4)}, got {np.shape(measured)}"
        )


def _check_directions(c: Array, n: int) -> None:
    if c.ndim < 1 or c.shape[-1] != n:
        raise ValueError(
            f"directions must have shape (k, n_params) = (k, {n}) (one combination of the "
            f"parameters per row) or ({n},) for a single one, got {c.shape}"
        )


def _pinv_factor_value(A: Array, rcond: float) -> tuple[Array, Array, Array, Array]:
    """``(L, s, U, Vt)``: thin SVD ``A = U diag(s) Vt`` of ``A (M, n)``, ``M >= n``, and the
    square-root factor ``L = V_r S_r^-1 (n, n)`` of ``(A^T A)^+`` (zero columns past the rank
    ``r``: singular values at most ``rcond * s_max``).

    Derivative (custom JVP): ``dL = dA^+ U`` with the constant-rank derivative of the
    pseudo-inverse, ``dA^+ = -A^+ dA A^+ + A^+ A^+T dA^T (I - A A^+) + (I - A^+ A) dA^T A^+T A^+``,
    so that ``d(L L^T) = d(A^+ A^+T)`` exactly (``L L^T = A^+ A^+T`` and ``U U^T A^+T = A^+T``);
    ``ds_k = u_k^T dA v_k``. ``U`` and ``Vt`` get zero tangents: use them only with stopped
    gradients (their derivative is undefined where singular values repeat, as at the CDRA's two
    zeros).
    """
    U, s, Vt = jnp.linalg.svd(A, full_matrices=False)
    keep = s > rcond * s[..., :1]
    inv_s = jnp.where(keep, 1.0 / jnp.where(keep, s, 1.0), 0.0)
    L = jnp.swapaxes(Vt, -1, -2) * inv_s[..., None, :]
    return L, s, U, Vt


def _pinv_factor_jvp(rcond, primals, tangents):
    (A,), (dA,) = primals, tangents
    L, s, U, Vt = _pinv_factor_value(A, rcond)
    t = _t
    P = L @ t(U)  # A^+ (n, M)
    dAt = t(dA)
    dP = (
        -(P @ dA) @ P
        + (P @ t(P)) @ (dAt - (dAt @ A) @ P)
        + ((dAt @ t(P)) - P @ (A @ (dAt @ t(P)))) @ P
    )
    ds = jnp.einsum("...ik,...ij,...kj->...k", U, dA, Vt)
    return (L, s, U, Vt), (dP @ U, ds, jnp.zeros_like(U), jnp.zeros_like(Vt))


def _t(x: Array) -> Array:
    return jnp.swapaxes(x, -1, -2)


_pinv_factor = jax.custom_jvp(_pinv_factor_value, nondiff_argnums=(1,))
_pinv_factor.defjvp(_pinv_factor_jvp)


@filter_jit
def whitened_jacobian(
    arm: Arm, q: ArrayLike, noise: NoiseModel | None, measured: ArrayLike | None = None
) -> Array:
    """Whitened stacked Jacobian ``D~ (6m, n)`` of Eq. 9 at ``arm`` for states ``q (m, dof)``.

    Whitening uses the tool positions of ``measured (m, 4, 4)`` when given (as the solvers do),
    the model's otherwise. ``noise=None`` gives the paper's unweighted ``D``; its stds are
    numbers or one per pose (``(m,)``).

    Raises:
        ValueError: (at trace time) ``q`` not ``(m, dof)``, ``measured`` not ``(m, 4, 4)``, or
            noise stds that are neither numbers nor ``(m,)``.
    """
    dtype = jnp.asarray(arm.frames).dtype
    q = jnp.asarray(q, dtype)
    _check_states(arm, q, "q")
    _check_noise_and_measured(noise, measured, q.shape[:-1])
    tool, after = chain(arm.frames, module_poses(arm, q))
    D = calibration_jacobian(after)
    G = whitening(tool if measured is None else jnp.asarray(measured, dtype), noise)
    if G is not None:
        D = G @ D
    return D.reshape(D.shape[:-3] + (-1, D.shape[-1]))


class ParameterUncertainty(eqx.Module):
    """Covariance of the minimum-norm frame-error estimate from one pose set (first order).

    Attributes:
        covariance: ``F^+ = (D~^T D~)^+`` with the solvers' rank cut-off, ``(n, n)`` (mm^2,
            mm rad, rad^2; ordered as ``arm.param_names``).
        singular_values: singular values of ``D~`` in decreasing order, ``(n,)`` (zero-padded).
        basis: right singular vectors as rows, ``(n, n)``; the first ``rank`` rows span the
            identifiable subspace (the row space of ``D~``), the rest the null space. Carries no
            gradient (it is not differentiable where singular values repeat).
        rank: numerical rank ``()``.
        factor: square-root factor ``L = V_r S_r^-1 (n, n)``, ``covariance = L L^T`` (zero
            columns past the rank); its derivative is that of ``L L^T`` (use it through Gram
            products such as ``(D L)(D L)^T``, as :func:`pose_covariance` does).
    """

    covariance: Array
    singular_values: Array
    basis: Array
    rank: Array
    factor: Array

    @property
    def null_space(self) -> Array:
        """Rows spanning the null space of ``D~`` (what the poses do not identify), ``(n, n)``:
        the rows of ``basis`` past ``rank``, the first ``rank`` rows zero."""
        return _null_rows(self.basis, self.rank)

    @property
    def row_space_projector(self) -> Array:
        """Orthogonal projector onto the identifiable subspace, ``(n, n)``."""
        return _row_space_projector(self.basis, self.rank)

    def _directions(self, directions: ArrayLike) -> tuple[Array, bool]:
        c = jnp.asarray(directions, self.covariance.dtype)
        _check_directions(c, self.covariance.shape[-1])
        return (c[None, :], True) if c.ndim == 1 else (c, False)

    def null_fraction(self, directions: ArrayLike) -> Array:
        """``|P_null c| / |c|`` for each row ``c`` of ``directions (..., k, n)``: ``(..., k)``
        (a single direction ``(n,)``: ``(...)``)."""
        c, single = self._directions(directions)
        frac = _null_fraction(self.basis, self.rank, c)
        return frac[..., 0] if single else frac

    def identifiable(self, directions: ArrayLike, tol: float = IDENTIFIABLE_TOL) -> Array:
        """Whether each row of ``directions (..., k, n)`` (or the one ``(n,)``) lies in the
        identifiable subspace."""
        return self.null_fraction(directions) <= tol

    def bound(self, directions: ArrayLike, tol: float = IDENTIFIABLE_TOL) -> Array:
        """Cramer-Rao bound ``c^T F^+ c`` on ``c^T X`` per row ``c``; ``inf`` if not identifiable.

        Args:
            directions: ``(..., k, n)`` linear combinations of the parameters, one per row, or
                a single one ``(n,)``.

        Returns:
            ``(..., k)`` variances (squared units of ``c^T X``); ``(...)`` for a single
            direction.

        Raises:
            ValueError: ``directions`` whose last axis is not ``n`` (or a scalar).
        """
        c, single = self._directions(directions)
        out = _bound(self.basis, self.rank, self.covariance, c, tol)
        return out[..., 0] if single else out


# The computations of the properties and methods above (and of PoseCovariance's below), each
# one compiled program per shape when called on concrete values (a report, a script) rather
# than a dozen operations dispatched one by one; traced inline under jit, vmap and grad.
@compiled_when_eager
def _null_rows(basis: Array, rank: Array) -> Array:
    """The rows of ``basis (..., n, n)`` past ``rank (...)``, the first ``rank`` rows zero."""
    n = basis.shape[-1]
    null = jnp.arange(n) >= rank[..., None]
    return jnp.where(null[..., :, None], basis, 0.0)


@compiled_when_eager
def _row_space_projector(basis: Array, rank: Array) -> Array:
    """``V_r^T V_r`` with ``V_r`` the first ``rank`` rows of ``basis``: ``(..., n, n)``."""
    n = basis.shape[-1]
    keep = jnp.arange(n) < rank[..., None]
    Vr = jnp.where(keep[..., :, None], basis, 0.0)
    return jnp.einsum("...ki,...kj->...ij", Vr, Vr)


@compiled_when_eager
def _null_fraction(basis: Array, rank: Array, c: Array) -> Array:
    """``|P_null c| / |c|`` per row of ``c (..., k, n)``: ``(..., k)``."""
    Pc = jnp.einsum("...ij,...kj->...ki", _row_space_projector(basis, rank), c)
    norm = jnp.linalg.norm(c, axis=-1)
    return jnp.linalg.norm(c - Pc, axis=-1) / jnp.where(norm > 0, norm, 1.0)


@compiled_when_eager
def _bound(basis: Array, rank: Array, covariance: Array, c: Array, tol: ArrayLike) -> Array:
    """``c^T C c`` per row of ``c (..., k, n)``, ``inf`` where the row's null fraction is above
    ``tol``: ``(..., k)``."""
    var = jnp.einsum("...ki,...ij,...kj->...k", c, covariance, c)
    return jnp.where(_null_fraction(basis, rank, c) <= tol, var, jnp.inf)


def parameter_covariance(
    arm: Arm,
    q: ArrayLike,
    noise: NoiseModel,
    measured: ArrayLike | None = None,
    *,
    rcond: float | None = None,
) -> ParameterUncertainty:
    """Covariance of the identified frame errors for the pose set ``q (m, dof)``.

    ``F^+ = (D~^T D~)^+`` (see the module docstring), with ``D~`` whitened by ``noise`` (stds
    numbers or ``(m,)``) and the singular values below ``rcond * s_max`` dropped, as in the
    solvers' Eq. 10 step. An empty pose set (``m = 0``) has rank 0: nothing is identified.
    jit/vmap-able (batch over ``q`` with ``vmap``); differentiable at constant rank (module
    docstring).

    Raises:
        ValueError: no noise model, or the shape errors of :func:`whitened_jacobian`.
    """
    if noise is None:
        raise ValueError(
            "parameter_covariance needs a NoiseModel (position_mm, rotation_rad): the covariance "
            "of the estimate is in units of the measurement noise"
        )
    # One call form for the compiled function, whichever way the arguments were passed (a
    # direct call and analyze_uncertainty's share one program per shape).
    return _parameter_covariance(arm, q, noise, measured, rcond)


@filter_jit
def _parameter_covariance(
    arm: Arm, q: ArrayLike, noise: NoiseModel, measured: ArrayLike | None, rcond: float | None
) -> ParameterUncertainty:
    """:func:`parameter_covariance`, compiled (``rcond`` static)."""
    D = whitened_jacobian(arm, q, noise, measured)
    n = D.shape[-1]
    if D.shape[-2] < n:  # fewer rows than parameters: pad so that the SVD gives all n directions
        D = jnp.concatenate([D, jnp.zeros(D.shape[:-2] + (n - D.shape[-2], n), D.dtype)], -2)
    rcond = default_rcond(D.dtype) if rcond is None else float(rcond)
    L, s, _, Vt = _pinv_factor(D, rcond)
    keep = jax.lax.stop_gradient(s > rcond * s[..., :1])
    return ParameterUncertainty(
        covariance=L @ _t(L),
        singular_values=s,
        basis=jax.lax.stop_gradient(Vt),
        rank=jnp.sum(keep, axis=-1),
        factor=L,
    )


@filter_jit
def cramer_rao_bound(
    arm: Arm,
    q: ArrayLike,
    noise: NoiseModel,
    directions: ArrayLike,
    *,
    measured: ArrayLike | None = None,
    rcond: float | None = None,
    tol: float = IDENTIFIABLE_TOL,
) -> Array:
    """Cramer-Rao bound on ``c^T X`` for each row ``c`` of ``directions (k, n)``: ``(k,)``.

    For Gaussian measurement noise the whitened model is linear-Gaussian to first order and the
    bound on an identifiable combination is ``c^T (D~^T D~)^+ c``; combinations with a
    null-space component (relative size above ``tol``) get ``inf``. A single direction ``(n,)``
    gives a scalar ``()``. ``n = arm.n_params``, ordered as ``arm.param_names``.

    Raises:
        ValueError: ``directions`` not ``(k, n)`` or ``(n,)``, or the errors of
            :func:`parameter_covariance`.
    """
    _check_directions(jnp.asarray(directions), arm.n_params)
    return parameter_covariance(arm, q, noise, measured, rcond=rcond).bound(directions, tol)


class PoseCovariance(eqx.Module):
    """First-order covariance of predicted tool poses at ``k`` states.

    A pose whose position (orientation) error the calibration does not bound, because a
    direction the poses left unidentified moves it (module docstring), has its whole position
    (orientation) block, and its whole twist block, set to ``inf``: its variances are unbounded
    (the off-diagonal ``inf`` only marks the block). The RMS values and the expected ``dp``
    (``dR``) over poses with such a block are then ``inf`` too; :attr:`bounded` says which.

    Attributes:
        twist: covariance of the world-frame pose-error twist ``(v, w)``, ``(k, 6, 6)``.
        position: covariance of the tool position error, ``(k, 3, 3)`` mm^2.
        rotation: covariance of the world-frame orientation error, ``(k, 3, 3)`` rad^2.
    """

    twist: Array
    position: Array
    rotation: Array

    @property
    def bounded(self) -> Array:
        """Per pose, whether both the position and the orientation covariance are finite:
        ``(k,)`` bool."""
        return _both_finite(self.position, self.rotation)

    @property
    def position_rms(self) -> Array:
        """Expected RMS position error per pose, ``sqrt(trace)`` (mm): ``(k,)``; ``inf`` where
        unbounded."""
        return _rms(self.position)

    @property
    def rotation_rms(self) -> Array:
        """Expected RMS orientation error angle per pose (rad): ``(k,)``; ``inf`` where
        unbounded."""
        return _rms(self.rotation)

    @property
    def expected_delta_p(self) -> Array:
        """``sqrt(E[dp^2])`` of Eq. 20 over these poses, model against the true arm (mm);
        ``inf`` when any pose's position error is unbounded."""
        return _rms_over_poses(self.position)

    @property
    def expected_delta_R(self) -> Array:
        """``sqrt(E[dR^2])`` of Eq. 21 over these poses, model against the true arm (rad);
        ``inf`` when any pose's orientation error is unbounded."""
        return _rms_over_poses(self.rotation)


def _trace(C: Array) -> Array:
    return jnp.trace(C, axis1=-2, axis2=-1)


@compiled_when_eager
def _both_finite(position: Array, rotation: Array) -> Array:
    """Per pose, whether both ``(..., k, 3, 3)`` covariances have a finite trace: ``(..., k)``."""
    return jnp.isfinite(_trace(position)) & jnp.isfinite(_trace(rotation))


@compiled_when_eager
def _rms(C: Array) -> Array:
    """``sqrt(trace)`` per pose of ``C (..., k, 3, 3)``: ``(..., k)``."""
    return _sqrt(_trace(C))


@compiled_when_eager
def _rms_over_poses(C: Array) -> Array:
    """``sqrt`` of the mean trace over the poses of ``C (..., k, 3, 3)``: ``(...)``."""
    return _sqrt(jnp.mean(_trace(C), axis=-1))


def _sqrt(x: Array) -> Array:
    """``sqrt`` of variances (>= 0) with a finite gradient at 0 (double where); a NaN stays
    NaN (``x * 0``)."""
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), x * 0.0)


def _unbounded(rows: Array, null: Array, tol: float) -> Array:
    """``|rows N^T|_F > tol |rows|_F`` per pose: ``rows (..., k, a, n)``, ``null (..., n, n)``
    (null-space rows, zero padded, already broadcast as ``(..., 1, n, n)`` if batched)."""
    num = jnp.sum(jnp.square(rows @ _t(null)), axis=(-2, -1))
    den = jnp.sum(jnp.square(rows), axis=(-2, -1))
    return num > tol**2 * den


@filter_jit
def pose_covariance(
    arm: Arm,
    q_eval: ArrayLike,
    covariance: ArrayLike | ParameterUncertainty,
    *,
    tol: float = IDENTIFIABLE_TOL,
) -> PoseCovariance:
    """Propagate a parameter covariance to the tool poses at ``q_eval (k, dof)``.

    Uses the unwhitened Jacobian ``D(q)`` of Eq. 8 at ``arm``: twist covariance
    ``D C D^T``; position error ``[I, -hat(p)] dT`` with ``p`` the model tool position.
    Computed from a square-root factor ``C = L L^T`` as Gram matrices ``(D L)(D L)^T``, so
    variances are never negative: for a nearly singular ``C`` (poses nearly the same)
    ``D C D^T`` formed directly can cancel to a negative trace and a NaN RMS.

    Args:
        arm: model to linearise at.
        q_eval: states ``(k, dof)`` at which to predict.
        covariance: the :class:`ParameterUncertainty` of a calibration
            (:func:`parameter_covariance`): its null space is unidentified, so a pose whose
            position (orientation) rows ``R`` of ``D(q)`` see it, ``|R N| > tol |R|``, gets an
            ``inf`` block (:class:`PoseCovariance`); its factor ``L`` is used, so the result is
            differentiable (module docstring). Or a plain covariance matrix ``(n, n)`` (mm^2,
            mm rad, rad^2), taken at face value: zero variance means known exactly, never
            ``inf``; factored by a symmetric eigendecomposition (rounding negatives clipped),
            whose derivative is undefined where eigenvalues repeat (e.g. two zeros): to
            differentiate, pass the :class:`ParameterUncertainty`.
        tol: relative size of a null-space component that counts as seen (default
            :data:`IDENTIFIABLE_TOL`, ``1e-8``; the CDRA's structural directions give
            below ``1e-15``).

    Raises:
        ValueError: (at trace time) ``q_eval`` not ``(k, dof)``.
    """
    dtype = jnp.asarray(arm.frames).dtype
    q_eval = jnp.asarray(q_eval, dtype)
    _check_states(arm, q_eval, "q_eval")
    tool, after = chain(arm.frames, module_poses(arm, q_eval))
    D = calibration_jacobian(after)  # (k, 6, n)
    null = None
    if isinstance(covariance, ParameterUncertainty):
        L = covariance.factor.astype(dtype)
        null = jax.lax.stop_gradient(covariance.null_space).astype(dtype)
    else:
        C = jnp.asarray(covariance, dtype)
        lam, U = jnp.linalg.eigh(0.5 * (C + _t(C)))
        L = U * _sqrt(lam)[..., None, :]  # C = L L^T
    if L.ndim > 2:  # a batch of covariances: broadcast against the k poses
        L = L[..., None, :, :]
        null = None if null is None else null[..., None, :, :]
    DL = D @ L  # (k, 6, n)
    twist = DL @ _t(DL)
    p = lie.translation(tool)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=dtype), p.shape[:-1] + (3, 3))
    H = jnp.concatenate([eye, -lie.hat3(p)], axis=-1)  # (k, 3, 6)
    HDL = H @ DL
    position = HDL @ _t(HDL)
    rotation = twist[..., 3:, 3:]
    if null is not None:
        bad_p = _unbounded(H @ D, null, tol)[..., None, None]
        bad_r = _unbounded(D[..., 3:, :], null, tol)[..., None, None]
        position = jnp.where(bad_p, jnp.inf, position)
        rotation = jnp.where(bad_r, jnp.inf, rotation)
        twist = jnp.where(bad_p | bad_r, jnp.inf, twist)
    return PoseCovariance(twist=twist, position=position, rotation=rotation)


@filter_jit
def predicted_pose_covariance(
    arm: Arm,
    q: ArrayLike,
    noise: NoiseModel,
    q_eval: ArrayLike | None = None,
    measured: ArrayLike | None = None,
    *,
    rcond: float | None = None,
    tol: float = IDENTIFIABLE_TOL,
) -> PoseCovariance:
    """Covariance of the calibrated model's tool poses at ``q_eval`` (default: at ``q``).

    ``q (m, dof)`` are the calibration states, ``noise`` the measuring device's noise (stds
    numbers or ``(m,)``), ``q_eval (k, dof)``. The expected held-out accuracy of a calibration
    from ``q`` is ``predicted_pose_covariance(arm, q, noise, q_heldout).expected_delta_p`` (mm).
    It is ``inf`` when ``q`` leaves a direction unidentified that moves the tool at a state of
    ``q_eval`` (rank-deficient sets: too few, repeated or empty; see :func:`pose_covariance`
    and ``tol``), finite and differentiable otherwise.
    """
    unc = parameter_covariance(arm, q, noise, measured, rcond=rcond)
    return pose_covariance(arm, q if q_eval is None else q_eval, unc, tol=tol)


def normal_quantile(confidence: float) -> float:
    """Two-sided standard-normal quantile: 1.96 for 0.95 (``scipy.special.ndtri``: importing
    ``scipy.stats`` would add half a second to every command that reports an uncertainty)."""
    from scipy.special import ndtri

    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}")
    return float(ndtri(0.5 + 0.5 * confidence))


@dataclass(frozen=True)
class UncertaintyReport:
    """Host-side report of :func:`analyze_uncertainty` (numpy arrays, JSON-ready via
    :meth:`to_dict`).

    Attributes:
        param_names: parameter names (``arm.param_names``).
        estimate: identified errors ``(n,)`` or ``None`` when none were given.
        std: standard deviation of each parameter's minimum-norm estimate ``(n,)``.
        identifiable: per parameter, whether it is identifiable on its own ``(n,)``.
        covariance: ``(n, n)`` parameter covariance ``F^+``.
        rank, n_poses: rank of ``D~`` and the number of poses.
        confidence, z: the interval level and its normal quantile.
        noise: ``(position_mm, rotation_rad)``, each a float or, for per-pose stds, an ``(m,)``
            array.
        pose_position_rms, pose_rotation_rms: per evaluation pose, expected RMS errors (mm, rad);
            ``inf`` where the calibration poses leave a direction unidentified that moves the
            tool there (:func:`pose_covariance`): the error is not bounded by the noise.
        expected_delta_p, expected_delta_R: ``sqrt(E[dp^2])``, ``sqrt(E[dR^2])`` over them
            (``inf`` when any pose's is).
        unidentifiable: the unidentifiable directions as text (from :mod:`.identifiability`).
        involved_in: per parameter, the unidentifiable directions it enters.
        weights: per-pose IRLS weights of a robust fit the covariance uses, or ``None``.
    """

    param_names: tuple[str, ...]
    estimate: np.ndarray | None
    std: np.ndarray
    identifiable: np.ndarray
    covariance: np.ndarray
    rank: int
    n_poses: int
    confidence: float
    z: float
    noise: tuple[float | np.ndarray, float | np.ndarray]
    pose_position_rms: np.ndarray
    pose_rotation_rms: np.ndarray
    expected_delta_p: float
    expected_delta_R: float
    eval_states: str
    unidentifiable: tuple[str, ...] = field(default=())
    involved_in: tuple[tuple[str, ...], ...] = field(default=())
    weights: np.ndarray | None = None

    def interval(self, i: int) -> tuple[float, float] | None:
        """Confidence interval of parameter ``i`` (estimate +- z std; about 0 without an
        estimate), or ``None`` when it is not identifiable on its own."""
        if not self.identifiable[i]:
            return None
        c = 0.0 if self.estimate is None else float(self.estimate[i])
        h = self.z * float(self.std[i])
        return (c - h, c + h)

    @property
    def unbounded_poses(self) -> np.ndarray:
        """Indices of the evaluation poses whose predicted error is unbounded (``inf``)."""
        return np.flatnonzero(
            ~(np.isfinite(self.pose_position_rms) & np.isfinite(self.pose_rotation_rms))
        )

    def to_dict(self) -> dict:
        """JSON-ready mapping; see the README fragment for the layout.

        Unbounded (``inf``) predicted errors are written as ``null`` (JSON has no infinity),
        with ``predicted_pose.bounded`` false and a ``note``.
        """
        params = {}
        for i, name in enumerate(self.param_names):
            entry: dict = {
                "identifiable": bool(self.identifiable[i]),
                "estimate": None if self.estimate is None else float(self.estimate[i]),
                "std": float(self.std[i]) if self.identifiable[i] else None,
                "interval": None,
            }
            iv = self.interval(i)
            if iv is not None:
                entry["interval"] = [iv[0], iv[1]]
                entry["half_width"] = self.z * float(self.std[i])
            else:
                entry["note"] = (
                    "not identifiable on its own from tool poses; only combinations orthogonal "
                    "to " + "; ".join(f"({d})" for d in self.involved_in[i]) + " are"
                )
            params[name] = entry
        unbounded = self.unbounded_poses
        return {
            "method": "first-order covariance of the minimum-norm estimate, (D~^T D~)^+ "
            "(= Cramer-Rao bound on identifiable combinations)"
            if self.weights is None
            else "first-order covariance of the robust estimate with its final IRLS weights, "
            "(D~^T W D~)^+, W = diag(w_i I_6): pose i weighs as if measured with noise "
            "s / sqrt(w_i)",
            "weights": None if self.weights is None else [float(w) for w in self.weights],
            "units": "mm for v components, rad for w components",
            "noise": {
                "position_mm": _json_std(self.noise[0]),
                "rotation_rad": _json_std(self.noise[1]),
            },
            "confidence": self.confidence,
            "rank": int(self.rank),
            "n_params": len(self.param_names),
            "n_poses": int(self.n_poses),
            "parameters": params,
            "unidentifiable": list(self.unidentifiable),
            "predicted_pose": {
                "at": self.eval_states,
                "bounded": not unbounded.size,
                **({"note": self._unbounded_note()} if unbounded.size else {}),
                "expected_delta_p_mm": _json_float(self.expected_delta_p),
                "expected_delta_R_rad": _json_float(self.expected_delta_R),
                "position_rms_mm": [_json_float(v) for v in self.pose_position_rms],
                "rotation_rms_rad": [_json_float(v) for v in self.pose_rotation_rms],
            },
            "covariance": {
                "param_names": list(self.param_names),
                "matrix": [[float(v) for v in row] for row in self.covariance],
            },
        }

    def summary(self) -> str:
        """Plain-text table: one row per parameter with estimate, std and the interval."""
        pct = f"{100 * self.confidence:g}%"
        head = f"{'parameter':<16} {'estimate':>12} {'std':>11}  {pct} interval"
        lines = [
            f"uncertainty: rank {self.rank} of {len(self.param_names)} from {self.n_poses} poses, "
            f"noise {_text_std(self.noise[0])} mm / {_text_std(self.noise[1])} rad"
            + ("" if self.weights is None else ", with the robust fit's final weights"),
            head,
            "-" * len(head) + "-" * 14,
        ]
        for i, name in enumerate(self.param_names):
            est = "" if self.estimate is None else f"{self.estimate[i]:12.5g}"
            iv = self.interval(i)
            if iv is None:
                lines.append(f"{name:<16} {est:>12} {'':>11}  not identifiable on its own")
            else:
                lines.append(
                    f"{name:<16} {est:>12} {self.std[i]:11.3g}  [{iv[0]:.5g}, {iv[1]:.5g}]"
                )
        lines.append(
            f"expected accuracy at {self.eval_states}: dp {self.expected_delta_p:.4g} mm, "
            f"dR {self.expected_delta_R:.4g} rad (RMS, model vs true arm)"
        )
        if self.unbounded_poses.size:
            lines.append(self._unbounded_note())
        return "\n".join(lines)

    def _unbounded_note(self) -> str:
        k = self.unbounded_poses.size
        return (
            f"unbounded (inf) at {k} of {self.pose_position_rms.size} evaluation poses: the "
            f"calibration poses (rank {self.rank} of {len(self.param_names)}) leave parameter "
            "combinations unidentified (or below the rank cut-off) that move the tool there, so "
            "the error is not bounded by the noise; add poses that move those combinations"
        )


def _json_float(v) -> float | None:
    """``float(v)``, or ``None`` (JSON ``null``) for an unbounded (infinite) value."""
    v = float(v)
    return v if np.isfinite(v) else None


def _json_std(v) -> float | list[float]:
    return [float(x) for x in v] if np.ndim(v) else float(v)


def _text_std(v) -> str:
    if not np.ndim(v):
        return f"{float(v):g}"
    lo, hi = float(np.min(v)), float(np.max(v))
    return f"{lo:g}" if lo == hi else f"{lo:g}-{hi:g} (per pose)"


def analyze_uncertainty(
    arm: Arm,
    q: ArrayLike,
    noise: NoiseModel,
    measured: ArrayLike | None = None,
    *,
    estimate: ArrayLike | None = None,
    q_eval: ArrayLike | None = None,
    confidence: float = DEFAULT_CONFIDENCE,
    rcond: float | None = None,
    weights: ArrayLike | None = None,
) -> UncertaintyReport:
    """Parameter intervals and predicted-pose accuracy of a calibration from ``q (m, dof)``.

    Args:
        arm: model to linearise at (the calibrated arm for a finished calibration).
        q: calibration states ``(m, dof)``.
        noise: the measuring device's noise; each std a number or one per pose ``(m,)``.
        measured: measured tool poses ``(m, 4, 4)`` (whitening; model poses otherwise).
        estimate: identified errors (``solution.errors``, ``(K+1, 6)`` or flat), centre of the
            intervals; without it the intervals are centred on 0 (half-widths).
        q_eval: states ``(k, dof)`` at which to predict the tool-pose accuracy (default:
            ``q``). The prediction is ``inf`` at states where ``q`` leaves a direction
            unidentified that moves the tool (:func:`pose_covariance`).
        confidence: interval level (0.95: +-1.96 std).
        rcond: singular-value cut-off (default: the solvers').
        weights: ``(m,)`` final IRLS weights of a robust fit (``RobustSolution.weights``):
            the covariance is then ``(D~^T W D~)^+`` (module docstring); ``None`` or all ones:
            least squares.

    Raises:
        ValueError: no noise model, noise stds that are not positive finite numbers or ``(m,)``
            arrays of them, a bad confidence, states (``q``, ``q_eval``) of the wrong shape or
            not finite, ``measured`` not ``(m, 4, 4)``, or weights that are not ``m`` finite
            non-negative numbers with one positive.
    """
    if noise is None:
        raise ValueError("analyze_uncertainty needs a NoiseModel (position_mm, rotation_rad)")
    z = normal_quantile(confidence)
    q = np.asarray(q, dtype=float)
    if q.ndim != 2 or q.shape[1] != arm.dof:
        raise ValueError(
            f"module states must have shape (m, {arm.dof}) with columns {arm.state_names}, "
            f"got {q.shape}"
        )
    require_finite_states(arm, q)
    stds = []
    for name in ("position_mm", "rotation_rad"):
        v = np.asarray(getattr(noise, name), dtype=float)
        if v.shape not in ((), (q.shape[0],)):
            raise ValueError(
                f"noise.{name} must be a number or one std per pose, shape (m,) = "
                f"({q.shape[0]},), got shape {v.shape}"
            )
        bad = np.flatnonzero(~(np.isfinite(v) & (v > 0)).reshape(-1))
        if bad.size:
            raise ValueError(
                f"noise.{name} must be positive and finite, got {v.reshape(-1)[bad[0]]!r}"
                + (f" for pose {bad[0]}" if v.ndim else "")
            )
        stds.append(float(v) if v.ndim == 0 else v)
    if measured is not None and np.shape(measured) != (q.shape[0], 4, 4):
        raise ValueError(
            f"measured must hold one tool pose per state of q, shape (m, 4, 4) = "
            f"({q.shape[0]}, 4, 4), got {np.shape(measured)}"
        )
    if q_eval is not None:
        q_eval = np.asarray(q_eval, dtype=float)
        if q_eval.ndim != 2 or q_eval.shape[1] != arm.dof:
            raise ValueError(
                f"q_eval must have shape (k, {arm.dof}) with columns {arm.state_names}, "
                f"got {q_eval.shape}"
            )
        require_finite_states(arm, q_eval, "q_eval")
    n = arm.n_params
    est = None
    if estimate is not None:
        est = np.asarray(estimate, dtype=float).reshape(-1)
        if est.shape != (n,):
            raise ValueError(f"estimate must hold {n} values ({arm.param_names}), got {est.size}")
    w = None
    cov_noise = noise
    if weights is not None:
        w = np.asarray(weights, dtype=float).reshape(-1)
        if w.shape != (q.shape[0],):
            raise ValueError(f"weights: expected one per pose ({q.shape[0]}), got {w.size}")
        bad = np.flatnonzero(~(np.isfinite(w) & (w >= 0)))
        if bad.size:
            raise ValueError(
                f"weights must be finite and non-negative, got {w[bad[0]]:g} for pose {bad[0]}"
            )
        if not np.any(w > 0):
            raise ValueError("weights: at least one pose needs a positive weight, all are 0")
        # The robust fit's last solve: pose i with the noise (s_pos, s_rot) / sqrt(w_i); a pose
        # with weight 0 (left out by a rejection refit) has infinite noise: no information.
        sw = np.sqrt(w)
        with np.errstate(divide="ignore"):
            cov_noise = NoiseModel(
                position_mm=np.asarray(noise.position_mm, dtype=float) / sw,
                rotation_rad=np.asarray(noise.rotation_rad, dtype=float) / sw,
            )
    unc = parameter_covariance(arm, q, cov_noise, measured, rcond=rcond)
    cov = np.asarray(unc.covariance)
    ident = np.asarray(unc.identifiable(np.eye(n)))
    ident_report = analyze_identifiability(
        arm, q, measured, noise, rcond=rcond, allow_underdetermined=True
    )
    involved = tuple(
        tuple(
            text
            for text, row in zip(ident_report.unidentifiable, ident_report.null_space, strict=True)
            if row[i] != 0.0
        )
        for i in range(n)
    )
    pc = pose_covariance(arm, q if q_eval is None else q_eval, unc)
    return UncertaintyReport(
        param_names=arm.param_names,
        estimate=est,
        std=np.sqrt(np.clip(np.diag(cov), 0.0, None)),
        identifiable=ident,
        covariance=cov,
        rank=int(unc.rank),
        n_poses=q.shape[0],
        confidence=float(confidence),
        z=z,
        noise=(stds[0], stds[1]),
        pose_position_rms=np.asarray(pc.position_rms),
        pose_rotation_rms=np.asarray(pc.rotation_rms),
        expected_delta_p=float(pc.expected_delta_p),
        expected_delta_R=float(pc.expected_delta_R),
        eval_states="the calibration states"
        if q_eval is None
        else f"{q_eval.shape[0]} given states",
        unidentifiable=ident_report.unidentifiable,
        involved_in=involved,
        weights=w,
    )


def uncertainty_dict(
    arm: Arm, q: ArrayLike, noise: NoiseModel, measured: ArrayLike | None = None, **options
) -> dict:
    """The ``uncertainty`` entry of a result JSON (see :meth:`UncertaintyReport.to_dict`).

    The arguments and keyword ``options`` (``estimate``, ``q_eval``, ``confidence``, ``rcond``)
    are those of :func:`analyze_uncertainty`. For a finished calibration call it with the
    calibrated arm, the measured states and poses, the noise model used and
    ``estimate=solution.errors``.
    """
    return analyze_uncertainty(arm, q, noise, measured, **options).to_dict()
