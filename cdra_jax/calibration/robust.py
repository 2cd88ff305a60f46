"""Robust calibration: Huber and Cauchy M-estimation by iteratively reweighted least squares.

A mis-seated probe, a bumped tracker or a typo in one row spoils a measured pose as a whole:
all six entries of its residual twist at once. So the robust estimator works on **poses as
blocks**: each pose gets one weight, from the size of its whole whitened residual, and the
weight multiplies all six entries. (Entry-wise weights would keep the five "good-looking"
entries of a corrupted pose and fit them, and would make the weights depend on the arbitrary
split of a twist into components.)

Residual and scale. Pose ``i`` has the residual twist ``Y_i`` of Eq. 7. Whitened with the unit
noise model (see :mod:`.model`) it becomes ``e_i = (dp_i, dth_i)`` to first order: the position
error (mm) and the world-frame rotation error (rad) of the measured tool pose. With the residual
scale ``s = (s_pos, s_rot)`` the standardized residual of the pose is

    z_i = || (dp_i / s_pos, dth_i / s_rot) || / sqrt(6),

the root mean square of its six standardized entries: ``sqrt(6) z_i`` is the Mahalanobis norm
of the pose's residual, and a clean pose has ``E[z_i^2] = 1``, like a scalar standard normal
residual, so the usual scalar tuning constants keep their meaning. The scale ``s`` is

* the stated noise, when a :class:`~.model.NoiseModel` is given (``s = (position_mm,
  rotation_rad)``), or
* without one (the paper's unweighted form), a robust estimate: the median absolute deviation
  (about zero) of the 3m position entries and of the 3m rotation entries, times 1.4826 (so that
  it estimates the standard deviation of Gaussian noise) and times ``sqrt(6m / (6m - rank))``
  for the degrees of freedom used by the fit; it is re-estimated in every round. It never goes
  below ``sqrt(eps) (1 + rms |p|)`` mm and ``sqrt(eps)`` rad, so noise-free data give
  ``z ~ 0`` rather than standardized rounding errors.

Losses (``z`` in units of the residual scale; :class:`Huber`, :class:`Cauchy`):

* Huber, ``c = 1.345``: ``rho = z^2/2`` for ``|z| <= c``, ``c |z| - c^2/2`` beyond;
  influence ``psi = clip(z, -c, c)``; weight ``min(1, c/|z|)``. 95 % efficient for Gaussian
  scalar residuals; convex, so the answer does not depend on the start.
* Cauchy (Lorentzian), ``c = 2.385``: ``rho = c^2/2 log(1 + (z/c)^2)``;
  ``psi = z / (1 + (z/c)^2)``; weight ``1 / (1 + (z/c)^2)``. 95 % efficient too; redescending
  (gross outliers get almost no influence) but not convex, so it starts from the least-squares
  answer and relies on the outliers being visible there.

IRLS. Round 0 is the ordinary fit (``calibrate_paper`` or ``calibrate_lm``, with the given
noise model or the paper's unweighted form). Each further round computes ``z_i`` at the current
frames, the weights ``w_i = weight(z_i)``, and re-solves with the per-pose noise model
``(s_pos / sqrt(w_i), s_rot / sqrt(w_i))`` (the weights enter through the whitening), warm
started from the previous frames (``arm.with_frames``). The rounds stop when no weight changes
by more than ``weight_tol``. The identified errors are re-expressed against the nominal frames
(Eqs. 15-18), so the result reads exactly like an ordinary calibration.

Rejection (``reject_outliers=True``). An M-estimate still feels every outlier a little: a
Huber weight ``c / z`` leaves a flagged pose with the influence of a pose about ``c`` noise
standard deviations off, and with few poses and high leverage that bias shows in the held-out
accuracy (measured: 12 poses with 2 gross outliers, Huber's held-out prediction error is within
1.5x of the clean fit's in only 24 of 100 draws). With ``reject_outliers`` the robust fit is
followed by one more solve: least squares (weights 1, the same scale) on the poses that are
*not* flagged, flagged ones with weight 0, warm started from the robust frames. This is the
classical "skipped" or one-step-reweighted estimator (a robust fit to find the outliers, least
squares on the rest; Rousseeuw & Leroy, *Robust Regression and Outlier Detection*, 1987). The
refit is kept only when at least 4 poses remain, its rank equals the robust fit's (rejecting
must not cost an identifiable direction) and it converged; otherwise the robust fit stands and
``refit`` is false. Nothing is deleted: every pose stays in the result with its ``z`` and flag.

Outliers. A pose is flagged when ``z_i > OUTLIER_THRESHOLD = 1.9347``: its squared Mahalanobis
norm ``6 z_i^2`` exceeds the 99.9 % point of the chi-square distribution with 6 degrees of
freedom (22.46), the same 0.1 % false-alarm rate as ``|z| > 3.29`` for a scalar residual. The
flag is about the data; the weight is about the fit (a Huber weight is below 1 already from
``z > 1.345``).

Everything is jit- and vmap-able; use ``throw=False`` under ``vmap`` and read the per-trial
``solution.result``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import ClassVar, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from .. import lie
from ..arm import Arm, chain, error_twists, module_poses
from ..compilation import any_tracer, batched_like, filter_jit
from . import implicit
from .gauss_newton import calibrate_paper
from .levenberg_marquardt import calibrate_lm
from .model import NoiseModel, deviation_metrics, residual_twist, whitening
from .solution import RESULTS, CalibrationSolution, _assemble_solution
from .validation import check_problem

HUBER_C = 1.345
"""Huber tuning constant, in units of the residual scale (95 % Gaussian efficiency)."""
CAUCHY_C = 2.385
"""Cauchy tuning constant, in units of the residual scale (95 % Gaussian efficiency)."""
POSE_DOF = 6
"""Entries of one pose's residual twist (a block)."""
OUTLIER_THRESHOLD = 1.9347
"""``sqrt(chi2_6^-1(0.999) / 6)``: a pose with ``z`` above it is flagged as an outlier."""
_MAD_TO_STD = 1.482602218505602  # 1 / Phi^-1(3/4)

LossName = Literal["huber", "cauchy"]


class RobustLoss(eqx.Module):
    """A robust loss of the standardized residual ``z`` (see the module docstring).

    Attributes:
        c: tuning constant, in units of the residual scale.
    """

    c: float = eqx.field(static=True)
    name: ClassVar[str] = "loss"

    def __check_init__(self) -> None:
        if not (isinstance(self.c, int | float) and math.isfinite(self.c) and self.c > 0):
            raise ValueError(f"{type(self).__name__}: c must be a positive number, got {self.c!r}")

    def rho(self, z: ArrayLike) -> Array:
        """The loss ``rho(z)`` (``z^2/2`` near 0)."""
        raise NotImplementedError

    def influence(self, z: ArrayLike) -> Array:
        """The influence function ``psi(z) = rho'(z)``."""
        raise NotImplementedError

    def weight(self, z: ArrayLike) -> Array:
        """The IRLS weight ``psi(z) / z`` (1 at ``z = 0``), in ``(0, 1]``."""
        raise NotImplementedError


class Huber(RobustLoss):
    """Huber loss: quadratic up to ``c``, linear beyond (``c = 1.345``)."""

    c: float = eqx.field(static=True, default=HUBER_C)
    name: ClassVar[str] = "huber"

    def rho(self, z: ArrayLike) -> Array:
        a = jnp.abs(jnp.asarray(z))
        return jnp.where(a <= self.c, 0.5 * a * a, self.c * (a - 0.5 * self.c))

    def influence(self, z: ArrayLike) -> Array:
        return jnp.clip(jnp.asarray(z), -self.c, self.c)

    def weight(self, z: ArrayLike) -> Array:
        return self.c / jnp.maximum(jnp.abs(jnp.asarray(z)), self.c)


class Cauchy(RobustLoss):
    """Cauchy (Lorentzian) loss ``c^2/2 log(1 + (z/c)^2)`` (``c = 2.385``), redescending."""

    c: float = eqx.field(static=True, default=CAUCHY_C)
    name: ClassVar[str] = "cauchy"

    def rho(self, z: ArrayLike) -> Array:
        a = jnp.abs(jnp.asarray(z)) / self.c
        big = a > 1e100  # (z/c)^2 would overflow: log1p(a^2) = 2 log(a) to double precision
        small = jnp.where(big, 0.0, a)
        return (
            0.5
            * self.c**2
            * jnp.where(big, 2.0 * jnp.log(jnp.where(big, a, 1.0)), jnp.log1p(small * small))
        )

    def influence(self, z: ArrayLike) -> Array:
        z = jnp.asarray(z)
        return z * self.weight(z)

    def weight(self, z: ArrayLike) -> Array:
        u = jnp.asarray(z) / self.c
        return 1.0 / (1.0 + u * u)


LOSSES: dict[str, Callable[[], RobustLoss]] = {"huber": Huber, "cauchy": Cauchy}
"""The robust losses by name (``--loss`` of ``cdra-jax calibrate``)."""


def robust_loss(loss: str | RobustLoss) -> RobustLoss:
    """A :class:`RobustLoss` from its name (``"huber"``, ``"cauchy"``) or as given."""
    if isinstance(loss, RobustLoss):
        return loss
    if loss not in LOSSES:
        raise ValueError(f"unknown robust loss {loss!r}; known: {', '.join(LOSSES)}")
    return LOSSES[loss]()


class RobustSolution(eqx.Module):
    """What :func:`calibrate_robust` returns (batched leading dimensions under ``vmap``).

    Attributes:
        solution: the final fit as a :class:`CalibrationSolution`: ``frames``, ``errors`` (w.r.t.
            the nominal frames, Eqs. 15-18), ``rank``, ``singular_values`` and ``cost`` (the
            weighted sum of squares) of the last round. Its histories count solves: ``delta_p``
            entry 0 is the nominal model, entry 1 the least-squares start (round 0), entry
            ``k + 1`` after round ``k``; ``step_norm[k]`` is the norm of the frame change
            ``log(F_new F_old^-1)`` of that solve; ``iterations = rounds + 1`` (``+ 2`` after a
            rejection refit, the last solve). ``result`` is successful when the weights
            settled (and the last solve converged); ``max_iterations_reached`` when
            ``max_rounds`` ran out first.
        weights: ``(..., m)`` per-pose weights of the final fit, in ``(0, 1]`` (0 for the
            poses left out of a rejection refit).
        z: ``(..., m)`` standardized residual of each pose at the final frames.
        outliers: ``(..., m)`` bool, ``z > threshold`` at the robust fit (with a rejection
            refit: the poses it left out).
        scale: ``(..., 2)`` residual scale ``(s_pos mm, s_rot rad)`` of the final assessment.
        rounds: ``(...)`` number of reweighted solves after the least-squares start.
        refit: ``(...)`` bool, the final fit is the least-squares refit without the flagged
            poses (``reject_outliers=True`` and the refit was kept).
        loss: loss name (``"huber"``, ``"cauchy"``).
        tuning: its tuning constant ``c``.
        threshold: the outlier threshold on ``z``.
        scale_source: ``"noise model"`` or ``"MAD"``.
    """

    solution: CalibrationSolution
    weights: Array
    z: Array
    outliers: Array
    scale: Array
    rounds: Array
    refit: Array
    loss: str = eqx.field(static=True)
    tuning: float = eqx.field(static=True)
    threshold: float = eqx.field(static=True)
    scale_source: str = eqx.field(static=True)

    @property
    def converged(self) -> Array:
        """Boolean ``(...)``: the weights settled and the last solve converged."""
        return self.solution.converged

    @property
    def frames(self) -> Array:
        """Calibrated fixed transforms ``(..., K+1, 4, 4)``."""
        return self.solution.frames

    @property
    def errors(self) -> Array:
        """Identified error twists w.r.t. the nominal frames ``(..., K+1, 6)``."""
        return self.solution.errors

    def calibrated_arm(self, nominal: Arm) -> Arm:
        """The nominal arm with the calibrated frames (Eq. 19); unbatched solutions only."""
        return nominal.with_frames(self.solution.frames)


def unit_residuals(frames: ArrayLike, poses: ArrayLike, measured: ArrayLike) -> Array:
    """Per-pose residual ``e_i = (dp_i, dth_i)`` (mm, rad) to first order: ``(m, 6)``.

    The Eq. 7 twist ``log(T_meas T_model^-1)`` whitened with the unit noise model, i.e. with the
    lever arm of the tool position removed from its translational part (see :mod:`.model`).

    Args:
        frames: ``(K+1, 4, 4)`` fixed transforms of the model.
        poses: ``(m, K, 4, 4)`` module poses (:func:`~cdra_jax.arm.module_poses`).
        measured: ``(m, 4, 4)`` measured tool poses.
    """
    measured = jnp.asarray(measured)
    tool, _ = chain(frames, poses)
    Y = residual_twist(measured, tool)
    G = whitening(measured, NoiseModel(position_mm=1.0, rotation_rad=1.0))
    assert G is not None
    return jnp.einsum("...ij,...j->...i", G, Y)


def mad_scale(e: ArrayLike, measured: ArrayLike, rank: ArrayLike | None = None) -> Array:
    """Robust residual scale ``(s_pos mm, s_rot rad)`` from the unit residuals ``e (m, 6)``.

    ``1.4826 median |e|`` over the 3m position entries and over the 3m rotation entries, times
    ``sqrt(6m / (6m - rank))`` when the fit's ``rank`` is given; floored at
    ``sqrt(eps) (1 + rms |p|)`` mm and ``sqrt(eps)`` rad (``p``: measured tool positions).
    """
    e = jnp.asarray(e)
    measured = jnp.asarray(measured, e.dtype)
    n_obs = POSE_DOF * e.shape[-2]
    med_p = jnp.median(jnp.abs(e[..., :3]).reshape(e.shape[:-2] + (-1,)), axis=-1)
    med_r = jnp.median(jnp.abs(e[..., 3:]).reshape(e.shape[:-2] + (-1,)), axis=-1)
    s = _MAD_TO_STD * jnp.stack([med_p, med_r], axis=-1)
    if rank is not None:
        free = jnp.maximum(n_obs - jnp.asarray(rank), 1)
        # In the dtype of e: the quotient of two integers is float64 with x64 enabled, which
        # would promote a float32 scale (and the IRLS weights carried in the loop) to float64.
        s = s * jnp.sqrt(n_obs / free).astype(e.dtype)[..., None]
    eps = float(jnp.finfo(e.dtype).eps) ** 0.5
    p = lie.translation(measured)
    reach = jnp.sqrt(jnp.mean(jnp.sum(p * p, axis=-1), axis=-1))
    floor = jnp.stack([eps * (1.0 + reach), jnp.full_like(reach, eps)], axis=-1)
    return jnp.maximum(s, floor)


def _z(e: Array, scale: Array) -> Array:
    s = jnp.concatenate([jnp.repeat(scale[..., :1], 3, -1), jnp.repeat(scale[..., 1:], 3, -1)], -1)
    r = e / s[..., None, :]
    return jnp.sqrt(jnp.sum(r * r, axis=-1) / POSE_DOF)


def standardized_residuals(
    arm: Arm,
    q: ArrayLike,
    measured: ArrayLike,
    noise: NoiseModel | None = None,
    *,
    rank: ArrayLike | None = None,
) -> tuple[Array, Array]:
    """Standardized residual ``z (m,)`` of each pose at the model ``arm``, and the scale ``(2,)``.

    ``z_i`` is the RMS of pose ``i``'s six standardized residual entries (see the module
    docstring); the scale ``(s_pos mm, s_rot rad)`` is the noise model's, or without one the
    robust MAD estimate (:func:`mad_scale`, with the fit's ``rank`` if given). Flag outliers
    with ``z > OUTLIER_THRESHOLD``. Works for any fit (e.g. a plain least-squares one).

    Args:
        arm: the (calibrated) model.
        q: ``(m, dof)`` module states.
        measured: ``(m, 4, 4)`` measured tool poses.
        noise: the stated measurement noise (scalar stds), or ``None``.
        rank: rank of the fit (degrees-of-freedom correction of the MAD scale).
    """
    measured = jnp.asarray(measured)
    dtype = jnp.result_type(measured.dtype, jnp.float32)
    measured = measured.astype(dtype)
    frames = jnp.asarray(arm.frames, dtype)
    e = unit_residuals(frames, module_poses(arm, jnp.asarray(q, dtype)), measured)
    scale = _noise_scale(noise, dtype)
    if scale is None:
        scale = mad_scale(e, measured, rank)
    return _z(e, scale), scale


def _check_scalar_noise(noise: NoiseModel | None) -> None:
    """Raise ``ValueError`` unless each std of ``noise`` is a number (shape ``()``)."""
    if noise is None:
        return
    for name in ("position_mm", "rotation_rad"):
        if np.ndim(getattr(noise, name)):
            raise ValueError(
                f"noise.{name} must be a number (shape ()) for robust estimation, got shape "
                f"{np.shape(getattr(noise, name))}: it needs one noise std per quantity (the "
                "robust weights are the per-pose part)"
            )


def _noise_scale(noise: NoiseModel | None, dtype) -> Array | None:
    _check_scalar_noise(noise)
    if noise is None:
        return None
    return jnp.stack(
        [jnp.asarray(noise.position_mm, dtype), jnp.asarray(noise.rotation_rad, dtype)]
    )


_SOLVERS: dict[str, Callable[..., CalibrationSolution]] = {
    "paper": calibrate_paper,
    "lm": calibrate_lm,
}


_NOT_DIFFERENTIABLE = (
    "calibrate_robust is not differentiable: its reweighting rounds and outlier flags are "
    "discrete decisions. Differentiate calibrate_paper or calibrate_lm instead, with the final "
    "round's weights as per-pose noise (NoiseModel(s_pos / sqrt(w), s_rot / sqrt(w))), or "
    "wrap the inputs of calibrate_robust in jax.lax.stop_gradient"
)


def calibrate_robust(
    arm: Arm,
    q: ArrayLike,
    measured: ArrayLike,
    noise: NoiseModel | None = None,
    *,
    loss: LossName | RobustLoss = "huber",
    solver: Literal["paper", "lm"] = "paper",
    max_rounds: int = 30,
    weight_tol: float = 1e-4,
    threshold: float = OUTLIER_THRESHOLD,
    reject_outliers: bool = False,
    max_iterations: int | None = None,
    rcond: float | None = None,
    allow_underdetermined: bool = False,
    throw: bool = True,
    singular_values: bool = False,
) -> RobustSolution:
    """Robust calibration of the fixed transforms of ``arm`` by IRLS (see the module docstring).

    Called on concrete arrays, the fit runs as one compiled program per problem shape and
    static configuration (``loss``, ``solver``, ``max_rounds``, ``weight_tol``, ``threshold``,
    ``reject_outliers``, ``max_iterations``, ``rcond``, ``allow_underdetermined``,
    ``singular_values``; the noise values are traced); inside ``jit`` or ``vmap`` it is traced
    inline.

    Args:
        arm: nominal model (start of round 0 and reference of the identified errors).
        q: ``(m, dof)`` module states.
        measured: ``(m, 4, 4)`` measured tool poses (mm).
        noise: stated measurement noise (scalar stds): gives the residual scale and the round-0
            weighting. ``None``: round 0 is the paper's unweighted fit and the scale is the
            robust MAD estimate, re-estimated every round.
        loss: ``"huber"``, ``"cauchy"`` or a :class:`RobustLoss` (e.g. ``Huber(c=2.0)``).
        solver: inner solver of every round, ``"paper"`` (:func:`calibrate_paper`) or ``"lm"``
            (:func:`calibrate_lm`).
        max_rounds: cap on the reweighted solves after round 0 (static).
        weight_tol: stop when no pose weight changes by more than this in a round.
        threshold: flag poses with ``z > threshold`` as outliers.
        reject_outliers: finish with a least-squares refit without the flagged poses (see the
            module docstring; static).
        max_iterations: iteration cap of each inner solve (default: the solver's). The inner
            solves use their default tolerances, which depend on the dtype (float32 problems:
            :data:`.gauss_newton.TOL_FLOAT32`, :data:`.levenberg_marquardt.ATOL_FLOAT32`).
        rcond: relative singular-value cut-off of the inner solves (see :mod:`.linear`).
        allow_underdetermined: passed to the inner solver (fewer than 4 poses).
        throw: raise when the result is not successful; use ``False`` under ``vmap``.
        singular_values: the inner solves compute the singular values of the Jacobian at
            their solutions (see :func:`calibrate_paper`; static); the result reports those of
            the final solve, NaN without.

    Returns:
        A :class:`RobustSolution`.

    Raises:
        ValueError: unknown loss or solver, wrong shapes, too few poses, per-pose noise arrays.
            Also when differentiated (``jax.grad``, ``jax.jvp``, ...): see the message.
    """
    arm, q, measured, noise = implicit.refuse_derivatives(
        _NOT_DIFFERENTIABLE, (arm, q, measured, noise)
    )
    loss = robust_loss(loss)
    if solver not in _SOLVERS:
        raise ValueError(f"unknown solver {solver!r}; known: {', '.join(_SOLVERS)}")
    if max_rounds < 0:
        raise ValueError(f"max_rounds must be >= 0, got {max_rounds}")
    q, measured = check_problem(arm, q, measured, allow_underdetermined=allow_underdetermined)
    _check_scalar_noise(noise)
    # Called on concrete values, the whole fit runs as one compiled program per static
    # configuration (rather than its set-up and assembly op by op and its loop as a program of
    # its own); traced (inside jit or vmap), it is traced inline.
    irls = _irls if any_tracer((arm, q, measured, noise)) else _irls_compiled
    out, failed = irls(
        arm,
        q,
        measured,
        noise,
        loss=loss,
        solver=solver,
        max_rounds=max_rounds,
        weight_tol=weight_tol,
        threshold=float(threshold),
        reject_outliers=bool(reject_outliers),
        max_iterations=max_iterations,
        rcond=rcond,
        allow_underdetermined=allow_underdetermined,
        singular_values=singular_values,
    )
    if throw:
        out = out.solution.result.error_if(out, failed)
    return out


def _irls(
    arm: Arm,
    q: Array,
    measured: Array,
    noise: NoiseModel | None,
    *,
    loss: RobustLoss,
    solver: str,
    max_rounds: int,
    weight_tol: float,
    threshold: float,
    reject_outliers: bool,
    max_iterations: int | None,
    rcond: float | None,
    allow_underdetermined: bool,
    singular_values: bool,
) -> tuple[RobustSolution, Array]:
    """The IRLS fit of :func:`calibrate_robust` on a checked problem: the solution, and whether
    its result is not successful."""
    dtype = measured.dtype
    m = measured.shape[0]
    sigma = _noise_scale(noise, dtype)
    inner = _SOLVERS[solver]
    kwargs: dict = {
        "rcond": rcond,
        "allow_underdetermined": allow_underdetermined,
        "throw": False,
        "singular_values": singular_values,
    }
    if max_iterations is not None:
        kwargs["max_iterations"] = max_iterations
    nominal = jnp.asarray(arm.frames, dtype)
    poses = module_poses(arm, q)
    nan = jnp.asarray(jnp.nan, dtype)

    def solve(frames: Array, nm: NoiseModel | None) -> CalibrationSolution:
        return inner(arm.with_frames(frames), q, measured, nm, **kwargs)

    def assess(frames: Array, rank: Array) -> tuple[Array, Array]:
        e = unit_residuals(frames, poses, measured)
        scale = mad_scale(e, measured, rank) if sigma is None else sigma
        return _z(e, scale), scale

    def change(new: Array, old: Array) -> Array:
        return jnp.linalg.norm(error_twists(new, old))

    n = arm.n_params
    dp_nom, dR_nom = deviation_metrics(measured, chain(nominal, poses)[0])
    extra = int(bool(reject_outliers))  # history slots for the rejection refit
    steps0 = jnp.full((max_rounds + 1 + extra,), nan)
    dps0 = jnp.full((max_rounds + 2 + extra,), nan).at[0].set(dp_nom)
    dRs0 = jnp.full((max_rounds + 2 + extra,), nan).at[0].set(dR_nom)
    ones = jnp.ones(m, dtype)
    if sigma is None:
        # Round 0 is the paper's unweighted fit; the scale comes from its residuals.
        sol0 = solve(nominal, None)
        ok0 = sol0.result != RESULTS.nonfinite
        frames0 = jnp.where(ok0, sol0.frames, nominal)
        z0, scale0 = assess(frames0, sol0.rank)
        carry0 = (
            jnp.asarray(1),  # solves so far
            frames0,
            loss.weight(z0),  # weights of the next solve
            ones,  # weights of the last solve (round 0: least squares)
            z0,
            scale0,
            sol0.rank,
            sol0.singular_values,
            sol0.cost,
            sol0.result == RESULTS.successful,
            steps0.at[0].set(change(frames0, nominal)),
            dps0.at[1].set(sol0.final_delta_p),
            dRs0.at[1].set(sol0.final_delta_R),
            jnp.asarray(False),
            ok0,
        )
    else:
        # Round 0 (weights 1 with the stated noise: the weighted fit) runs in the loop below;
        # one compiled inner solver serves every round.
        carry0 = (
            jnp.asarray(0),
            nominal,
            ones,
            ones,
            jnp.zeros(m, dtype),
            sigma,
            jnp.asarray(0),
            jnp.zeros(n, dtype),
            nan,
            jnp.asarray(False),
            steps0,
            dps0,
            dRs0,
            jnp.asarray(False),
            jnp.asarray(True),
        )

    # Batched from the start under vmap, so that JAX batches the loop body once (batching.py).
    carry0 = batched_like(jnp.all(jnp.isfinite(measured)), carry0)

    def cond(c):
        k, *_, done, ok = c
        return (k <= max_rounds) & ~done & ok

    def body(c):
        k, frames, w, _, _, scale, _, _, _, _, steps, dps, dRs, _, _ = c
        sw = jnp.sqrt(w)
        sol = solve(frames, NoiseModel(position_mm=scale[0] / sw, rotation_rad=scale[1] / sw))
        ok = sol.result != RESULTS.nonfinite
        new = jnp.where(ok, sol.frames, frames)
        z, scale = assess(new, sol.rank)
        w_next = loss.weight(z)
        return (
            k + 1,
            new,
            w_next,
            w,
            z,
            scale,
            sol.rank,
            sol.singular_values,
            sol.cost,
            sol.result == RESULTS.successful,
            steps.at[k].set(change(new, frames)),
            dps.at[k + 1].set(sol.final_delta_p),
            dRs.at[k + 1].set(sol.final_delta_R),
            jnp.max(jnp.abs(w_next - w)) <= weight_tol,
            ok,
        )

    k, frames, _, w, z, scale, rank, s, cost, inner_ok, steps, dps, dRs, done, ok = (
        jax.lax.while_loop(cond, body, carry0)
    )
    done = done | (max_rounds == 0)  # no reweighting asked for: the least-squares fit is it
    outliers = z > threshold
    refit = jnp.asarray(False)
    if reject_outliers:
        # Least squares on the unflagged poses (flagged: weight 0, i.e. infinite std).
        w_in = jnp.where(outliers, 0.0, 1.0).astype(dtype)
        sw = jnp.sqrt(w_in)
        # A failed trial (not ok) can carry a NaN scale; its refit is discarded below. (This
        # function always runs traced, so NoiseModel's value check does not see the scale.)
        sol_r = solve(frames, NoiseModel(position_mm=scale[0] / sw, rotation_rad=scale[1] / sw))
        refit = (
            ok
            & (jnp.sum(~outliers) >= 4)
            & (sol_r.rank == rank)
            & (sol_r.result == RESULTS.successful)
            & jnp.all(jnp.isfinite(sol_r.frames))
        )
        z_r, scale_r = assess(jnp.where(refit, sol_r.frames, frames), sol_r.rank)

        def take(new, old):
            return jnp.where(refit, new, old)

        steps = take(steps.at[k].set(change(sol_r.frames, frames)), steps)
        dps = take(dps.at[k + 1].set(sol_r.final_delta_p), dps)
        dRs = take(dRs.at[k + 1].set(sol_r.final_delta_R), dRs)
        frames = take(sol_r.frames, frames)
        w, z, scale = take(w_in, w), take(z_r, z), take(scale_r, scale)
        rank, s, cost = (
            take(sol_r.rank, rank),
            take(sol_r.singular_values, s),
            take(sol_r.cost, cost),
        )
        inner_ok = take(jnp.asarray(True), inner_ok)
        k = k + refit
    ok = ok & jnp.all(jnp.isfinite(frames)) & jnp.all(jnp.isfinite(z))
    name = ("lm" if solver == "lm" else "weighted") + "+" + loss.name
    if reject_outliers:
        name += "+reject"
    sol = _assemble_solution(
        frames,
        nominal,
        ok=ok,
        done=done & inner_ok,
        iterations=k,
        step_norm=steps,
        delta_p=dps,
        delta_R=dRs,
        rank=rank,
        singular_values=s,
        cost=cost,
        solver=name,
    )
    out = RobustSolution(
        solution=sol,
        weights=w,
        z=z,
        outliers=outliers,
        scale=scale,
        rounds=k - 1 - refit,
        refit=refit,
        loss=loss.name,
        tuning=float(loss.c),
        threshold=float(threshold),
        scale_source="MAD" if sigma is None else "noise model",
    )
    return out, sol.result != RESULTS.successful


_irls_compiled = filter_jit(_irls)
