"""Module self-calibration from redundant cable lengths (first stage of the paper's Fig. 2).

Problem. A module with ``n`` cables is measured at ``m`` unknown states; only the cable lengths
``l_ki`` are known. The parameters are, per cable, the base attachment ``b_i`` (3, mm, base
frame), the platform attachment ``a_i`` (3, mm, platform frame) and the length offset ``o_i``
(mm), ``7 n`` in all, named ``<module>.base<i>.x``, ``<module>.platform<i>.y``,
``<module>.offset<i>``. The model of :mod:`.cables`,
``l_ki = ||b_i - R(q_k) a_i - t(q_k)|| + o_i``, is fitted to all lengths jointly over the
parameters and the ``m`` states (``n m`` equations, ``7 n + dof m`` unknowns).

Solver. Gauss-Newton on the joint unknowns, in the paper's style: the states enter through
left-multiplied exponential updates (spherical) or additive ones, each step is the exact joint
Gauss-Newton step computed by eliminating the states pose by pose (the projection
``P_k = I - J_q (J_q^T J_q)^-1 J_q^T`` of each pose's residual and parameter Jacobian, a Schur
complement), and the parameter step is the minimum-norm least-squares solution of the reduced
system (rank-revealing SVD with the cut-off of :func:`cdra_jax.calibration.default_rcond`, as
in :func:`cdra_jax.calibration.min_norm_lstsq`). Unidentifiable parameter combinations are
therefore never moved (to first order). The iteration starts as plain Gauss-Newton; a step
that does not lower the cost is rejected and the following ones are damped Levenberg-Marquardt
style (``s / (s^2 + lam s_max^2)`` on the singular values, ``lam`` updated from the ratio of
actual to predicted decrease as in Nielsen's rule): the 2-cable elbow is conditioned badly
enough (condition number ~1e4) for plain Gauss-Newton to diverge on noisy lengths. The
initial states come from the forward kinematics of the nominal model.

Identifiability and gauge. The reduced Jacobian ``[P_k J_theta,k]`` (stacked over the poses;
its rank equals the rank of the joint Jacobian minus ``dof m``) tells which parameter
combinations cable lengths can see. Some motions of the parameters are invisible because the
unknown states absorb them (gauge freedoms of the module frames):

* spherical: a rigid rotation of the whole base point set about the module centre
  (``b -> Q b``, ``R_k -> Q R_k``) and one of the platform point set (``a -> P a``,
  ``R_k -> R_k P^T``): 6 directions, the module's zero orientation is not seen by its cables;
* revolute: rotations of the base set and of the platform set about the joint axis (the joint
  angle absorbs them), a rotation of a single cable's two points about the axis, a shift of a
  cable's two points along the axis, and a trade-off between a cable's distances from the axis
  ``r_b, r_a`` and the axial spacing ``h = b_ax - a_ax`` of its points: per cable only
  ``r_b^2 + r_a^2 + h^2``, ``r_b r_a``, the phase difference and the offset are seen (for cables
  in a plane normal to the axis, as in the default elbow, the trade-off is the axial spacing
  itself);
* prismatic: translations of either set along the axis and a rotation of both about it.

:func:`analyze_self_calibration` reports the rank, the singular values, these named symmetries
when they lie in the null space, and any other unidentifiable combination as named parameter
combinations. The gauge is fixed after the solve by re-aligning the estimated point sets with
the nominal ones (a Kabsch rotation of each set about the centre for spherical modules, about
the axis for revolute modules, translations along and a rotation about the axis for prismatic
ones), with the states transformed to match, so that the calibrated module's zero pose is as
close to the nominal as the data allow. Whatever rotation of the module frames remains is a
fixed-transform error that the arm calibration (stage 2, Eqs. 7-19) identifies.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from .. import lie
from ..arm import Arm, Module
from ..calibration.linear import default_rcond
from ..compilation import batched_like, compiled_when_eager_args
from ..identifiability import format_combination, sparse_basis
from ._linalg import small_inv
from ._results import select
from .cables import _length_jacobian, _points, cable_forward_kinematics, require_cables

_COMPONENTS = ("x", "y", "z")


def parameter_names(module: Module) -> tuple[str, ...]:
    """Names of the ``7 n`` self-calibration parameters, cable by cable.

    ``<module>.base<i>.x|y|z``, ``<module>.platform<i>.x|y|z``, ``<module>.offset<i>`` (mm).
    """
    out = []
    for i in range(1, module.n_cables + 1):
        out += [f"{module.name}.base{i}.{c}" for c in _COMPONENTS]
        out += [f"{module.name}.platform{i}.{c}" for c in _COMPONENTS]
        out.append(f"{module.name}.offset{i}")
    return tuple(out)


@compiled_when_eager_args()
def module_parameters(module: Module) -> Array:
    """The ``(7 n,)`` parameter vector of a module (order of :func:`parameter_names`)."""
    b, a, o = require_cables(module)
    return jnp.concatenate([b, a, o[:, None]], axis=-1).reshape(-1)


@compiled_when_eager_args("theta")
def with_parameters(module: Module, theta: ArrayLike) -> Module:
    """``module`` with cable geometry and offsets from a ``(7 n,)`` parameter vector."""
    n = module.n_cables
    P = jnp.asarray(theta).reshape(n, 7)
    return eqx.tree_at(
        lambda m: (m.cable_base, m.cable_platform, m.cable_offset),
        module,
        (P[:, :3], P[:, 3:6], P[:, 6]),
        is_leaf=lambda x: x is None,
    )


def with_module(arm: Arm, module: Module) -> Arm:
    """``arm`` with its module of the same name replaced by ``module``."""
    idx = arm.module_names.index(arm.module(module.name).name)
    return eqx.tree_at(lambda a: a.modules[idx], arm, module)


# --- the model and its Jacobians -------------------------------------------------------------


def _to_var(module: Module, states: Array) -> Array:
    """Solver variable of the states: rotations ``(m, 3, 3)`` or ``(m, 1)``."""
    if module.kind == "spherical":
        return lie.so3_exp(states)
    return states


def _to_state(module: Module, x: Array) -> Array:
    return lie.so3_log(x) if module.kind == "spherical" else x


def _linearise(module: Module, theta: Array, x: Array, lengths: Array):
    """Residuals ``(m, n)``, parameter Jacobian ``(m, n, 7n)`` and state Jacobian ``(m, n, d)``."""
    n = module.n_cables
    P = theta.reshape(n, 7)
    b, a, o = P[:, :3], P[:, 3:6], P[:, 6]
    p = _points(module, a, x)  # (m, n, 3)
    v = b - p
    d = jnp.linalg.norm(v, axis=-1)
    u = v / d[..., None]
    r = d + o - lengths
    if module.kind == "prismatic":
        da = -u
    else:
        R = x if module.kind == "spherical" else lie.so3_exp(x * jnp.asarray(module.axis, x.dtype))
        da = -jnp.einsum("mji,mnj->mni", R, u)  # -R^T u
    ones = jnp.ones(u.shape[:-1] + (1,), u.dtype)
    blocks = jnp.concatenate([u, da, ones], axis=-1)  # (m, n, 7)
    eye = jnp.eye(n, dtype=u.dtype)
    Jp = jnp.einsum("mnk,nc->mnck", blocks, eye).reshape(u.shape[0], n, 7 * n)
    Jq = _length_jacobian(module, p, u)
    return r, Jp, Jq


def _eliminate(Jp: Array, Jq: Array, r: Array):
    """Project out the state directions pose by pose: reduced ``(m n, 7n)``, ``(m n,)``."""
    G = jnp.einsum("mni,mnj->mij", Jq, Jq)
    eye = jnp.eye(G.shape[-1], dtype=G.dtype)
    Ginv = small_inv(G + 1e-12 * jnp.trace(G, axis1=-2, axis2=-1)[:, None, None] * eye)
    Pk = jnp.eye(Jq.shape[1], dtype=Jq.dtype) - jnp.einsum("mni,mij,mkj->mnk", Jq, Ginv, Jq)
    M = jnp.einsum("mnk,mkp->mnp", Pk, Jp)
    y = -jnp.einsum("mnk,mk->mn", Pk, r)
    return M.reshape(-1, Jp.shape[-1]), y.reshape(-1), Ginv


@compiled_when_eager_args("states")
def reduced_jacobian(module: Module, states: ArrayLike) -> Array:
    """Jacobian of the lengths w.r.t. the parameters with the states eliminated: ``(m n, 7n)``.

    Evaluated at ``module``'s parameters and the module states ``(m, dof)``; its null space is
    the set of parameter combinations that cable lengths cannot identify.
    """
    states = jnp.asarray(states, jnp.asarray(module.cable_base).dtype)
    theta = module_parameters(module).astype(states.dtype)
    x = _to_var(module, states)
    lengths = jnp.zeros(states.shape[:1] + (module.n_cables,), states.dtype)
    _, Jp, Jq = _linearise(module, theta, x, lengths)
    M, _, _ = _eliminate(Jp, Jq, jnp.zeros(Jp.shape[:2], Jp.dtype))
    return M


# --- gauge ---------------------------------------------------------------------------------


def _kabsch(src: Array, dst: Array) -> Array:
    """Rotation ``Q`` minimising ``sum |Q src_i - dst_i|^2`` (about the origin): ``(3, 3)``."""
    H = jnp.einsum("ni,nj->ij", dst, src)
    U, _, Vt = jnp.linalg.svd(H)
    s = jnp.sign(jnp.linalg.det(U @ Vt))
    D = jnp.diag(jnp.asarray([1.0, 1.0, 1.0], src.dtype).at[2].set(s))
    return U @ D @ Vt


def _axis_angle(src: Array, dst: Array, axis: Array) -> Array:
    """Angle of the rotation about ``axis`` best aligning ``src`` with ``dst`` (least squares)."""
    cross = jnp.sum(jnp.einsum("i,ni->n", axis, jnp.cross(src, dst)))
    perp = lambda v: v - jnp.einsum("ni,i->n", v, axis)[:, None] * axis
    dot = jnp.sum(perp(src) * perp(dst))
    return jnp.arctan2(cross, dot)


def _fix_gauge(module: Module, nominal: Array, theta: Array, x: Array) -> tuple[Array, Array]:
    """Re-align the estimated point sets with the nominal ones (see the module docstring)."""
    n = module.n_cables
    P = theta.reshape(n, 7)
    N = nominal.reshape(n, 7)
    b, a, o = P[:, :3], P[:, 3:6], P[:, 6:]
    axis = jnp.asarray(module.axis, theta.dtype)
    if module.kind == "spherical":
        Qb = _kabsch(b, N[:, :3])
        Qa = _kabsch(a, N[:, 3:6])
        b, a = b @ Qb.T, a @ Qa.T
        x = Qb @ x @ Qa.T
    elif module.kind == "revolute":
        phi_b = _axis_angle(b, N[:, :3], axis)
        phi_a = _axis_angle(a, N[:, 3:6], axis)
        b = b @ lie.so3_exp(phi_b * axis).T
        a = a @ lie.so3_exp(phi_a * axis).T
        x = x + (phi_b - phi_a)
    else:
        s_b = jnp.mean((N[:, :3] - b) @ axis)
        s_a = jnp.mean((N[:, 3:6] - a) @ axis)
        b = b + s_b * axis
        a = a + s_a * axis
        x = x + (s_b - s_a)
        both = jnp.concatenate([b, a])
        phi = _axis_angle(both, jnp.concatenate([N[:, :3], N[:, 3:6]]), axis)
        Q = lie.so3_exp(phi * axis)
        b, a = b @ Q.T, a @ Q.T
    return jnp.concatenate([b, a, o], axis=-1).reshape(-1), x


# --- solver --------------------------------------------------------------------------------


class SelfCalibrationResult(eqx.Enumeration):
    """Outcome of a module self-calibration."""

    successful = ""
    max_iterations_reached = (
        "the self-calibration did not converge within max_iterations; raise it or check the data"
    )
    nonfinite = "a non-finite value (NaN or inf) appeared in the cable lengths or the iterates"


class SelfCalibrationSolution(eqx.Module):
    """What :func:`self_calibrate` returns.

    Attributes:
        module: the calibrated module (cable attachments and offsets; gauge fixed to the
            nominal, see the module docstring).
        states: ``(m, dof)`` estimated module states of the measured poses (same gauge).
        residual_rms: RMS length residual at the solution, mm.
        rms_history: RMS residual before each iteration and after the last ``(max_it + 1,)``,
            NaN past the end.
        step_norm: norm of each accepted parameter step (mm; 0 for a rejected one)
            ``(max_iterations,)``, NaN past the end.
        iterations: number of steps taken.
        rank: numerical rank of the reduced Jacobian at the solution.
        singular_values: its singular values ``(7 n,)``, decreasing.
        result: :class:`SelfCalibrationResult` code.
    """

    module: Module
    states: Array
    residual_rms: Array
    rms_history: Array
    step_norm: Array
    iterations: Array
    rank: Array
    singular_values: Array
    result: SelfCalibrationResult

    @property
    def parameters(self) -> Array:
        """Calibrated ``(7 n,)`` parameter vector (order of :func:`parameter_names`)."""
        return module_parameters(self.module)


@compiled_when_eager_args("lengths", "initial_states", "tol", "ftol", "rcond")
def self_calibrate(
    module: Module,
    lengths: ArrayLike,
    *,
    initial_states: ArrayLike | None = None,
    max_iterations: int = 200,
    tol: float = 1e-10,
    ftol: float = 1e-10,
    rcond: float | None = None,
    throw: bool = True,
) -> SelfCalibrationSolution:
    """Identify a module's cable attachments and length offsets from cable lengths alone.

    Args:
        module: nominal module (with cables): the starting point and the gauge reference.
        lengths: ``(m, n)`` measured cable lengths of ``m`` poses, mm.
        initial_states: ``(m, dof)`` start states; default the forward kinematics of the
            nominal module from ``lengths``.
        max_iterations: Gauss-Newton iteration cap (static).
        tol: stop once the parameter step (mm) and the state step (rad or mm) are below it.
        ftol: ... or once an accepted step lowers the cost by less than this fraction of it: the
            change of chi^2 is then ~``ftol`` times the residual degrees of freedom, a parameter
            motion far below the estimate's standard deviation (the 2-cable elbow's noisy
            problem otherwise crawls along a flat valley for hundreds of steps).
        rcond: relative singular-value cut-off of the minimum-norm step (default
            :func:`cdra_jax.calibration.default_rcond`).
        throw: raise at run time when the result is not successful (use ``False`` under vmap).

    Returns:
        A :class:`SelfCalibrationSolution`.
    """
    b0, _, _ = require_cables(module)
    lengths = jnp.asarray(lengths)
    if not jnp.issubdtype(lengths.dtype, jnp.floating):
        lengths = lengths.astype(b0.dtype)
    n = module.n_cables
    if lengths.ndim != 2 or lengths.shape[1] != n:
        raise ValueError(
            f"module {module.name!r} has {n} cables: lengths must be (m, {n}), got {lengths.shape}"
        )
    m = lengths.shape[0]
    if m * (n - module.dof) < 7 * n:
        raise ValueError(
            f"module {module.name!r}: {m} poses give {m * (n - module.dof)} redundant lengths, "
            f"fewer than the {7 * n} parameters; measure at least "
            f"{-(-7 * n // max(n - module.dof, 1))} poses"
        )
    dtype = lengths.dtype
    nominal = module_parameters(module).astype(dtype)
    if initial_states is None:
        initial_states = cable_forward_kinematics(module, lengths).state
    states0 = jnp.asarray(initial_states, dtype)
    if states0.shape != (m, module.dof):
        raise ValueError(f"initial_states must be ({m}, {module.dof}), got shape {states0.shape}")
    x0 = _to_var(module, states0)
    spherical = module.kind == "spherical"
    nan = jnp.asarray(jnp.nan, dtype)

    cut = default_rcond(dtype) if rcond is None else rcond

    def rms_of(theta, x):
        r, _, _ = _linearise(module, theta, x, lengths)
        return jnp.sqrt(jnp.mean(r * r))

    def cond(carry):
        k, _, _, _, _, _, _, done, ok = carry
        return (k < max_iterations) & ~done & ok

    def body(carry):
        k, theta, x, lam, nu, steps, rmss, _, _ = carry
        r, Jp, Jq = _linearise(module, theta, x, lengths)
        cost = jnp.mean(r * r)
        M, y, Ginv = _eliminate(Jp, Jq, r)
        U, sv, Vt = jnp.linalg.svd(M, full_matrices=False)
        keep = sv > cut * sv[0]
        # Levenberg-Marquardt damping of the minimum-norm step (lam = 0: Gauss-Newton)
        f = jnp.where(keep, sv / jnp.where(keep, sv * sv + lam * sv[0] ** 2, 1.0), 0.0)
        dtheta = jnp.einsum("ji,j->i", Vt, f * jnp.einsum("rj,r->j", U, y))
        rk = r + jnp.einsum("mnp,p->mn", Jp, dtheta)
        dx = -jnp.einsum("mij,mnj,mn->mi", Ginv, Jq, rk)
        theta_new = theta + dtheta
        x_new = lie.so3_exp(dx) @ x if spherical else x + dx
        cost_new = rms_of(theta_new, x_new) ** 2
        pred = jnp.mean((rk + jnp.einsum("mni,mi->mn", Jq, dx)) ** 2)
        accept = jnp.isfinite(cost_new) & (cost_new <= cost * (1 + 1e-12) + 1e-30)
        theta = jnp.where(accept, theta_new, theta)
        x = jnp.where(accept, x_new, x)
        # Nielsen's update of the damping from the gain ratio actual / predicted decrease
        rho = (cost - cost_new) / jnp.maximum(cost - pred, 1e-300)
        shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * jnp.clip(rho, 0.0, 1.0) - 1.0) ** 3)
        # (plain Gauss-Newton, lam = 0, until a step fails)
        lam = jnp.where(accept, lam * shrink, jnp.maximum(lam * nu, 1e-6))
        lam = jnp.where(lam < 1e-12, 0.0, lam)
        nu = jnp.where(accept, 2.0, 2.0 * nu)
        step = jnp.linalg.norm(dtheta)
        flat = accept & (cost - cost_new <= ftol * cost)
        done = ((step < tol) & (jnp.max(jnp.abs(dx)) < tol)) | flat
        ok = jnp.isfinite(step) & jnp.all(jnp.isfinite(dx)) & (lam < 1e20)
        return (
            k + 1,
            theta,
            x,
            lam,
            nu,
            steps.at[k].set(jnp.where(accept, step, 0.0)),
            rmss.at[k].set(jnp.sqrt(cost)),
            done,
            ok,
        )

    finite_in = jnp.all(jnp.isfinite(lengths)) & jnp.all(jnp.isfinite(x0))
    # The carry batched from the start under vmap: JAX batches the body once less.
    rest = (
        nominal,
        x0,
        jnp.asarray(0.0, dtype),
        jnp.asarray(2.0, dtype),
        jnp.full((max_iterations,), nan),
        jnp.full((max_iterations + 1,), nan),
        jnp.asarray(False),
        finite_in,
    )
    init = (jnp.asarray(0), *batched_like(finite_in, rest))
    k, theta, x, _, _, steps, rmss, done, ok = jax.lax.while_loop(cond, body, init)
    theta, x = _fix_gauge(module, nominal, theta, x)
    rms = rms_of(theta, x)
    rmss = rmss.at[k].set(rms)
    r, Jp, Jq = _linearise(module, theta, x, lengths)
    M, _, _ = _eliminate(Jp, Jq, r)
    s = jnp.linalg.svd(M, compute_uv=False)
    rank = jnp.sum(s > cut * s[0])
    ok = ok & jnp.isfinite(rms)
    result = select(
        ok,
        select(
            done, SelfCalibrationResult.successful, SelfCalibrationResult.max_iterations_reached
        ),
        SelfCalibrationResult.nonfinite,
    )
    sol = SelfCalibrationSolution(
        module=with_parameters(module, theta),
        states=_to_state(module, x),
        residual_rms=rms,
        rms_history=rmss,
        step_norm=steps,
        iterations=k,
        rank=rank,
        singular_values=s,
        result=result,
    )
    if throw:
        sol = result.error_if(sol, result != SelfCalibrationResult.successful)
    return sol


@compiled_when_eager_args()
def gauge_invariants(module: Module) -> dict[str, Array]:
    """Quantities cable lengths determine for any module state, per cable.

    ``distances``: ``(n, n)`` distances between base points and ``(n, n)`` between platform
    points (rotation-invariant; spherical), and for revolute modules ``c = r_b^2 + r_a^2 +
    (b_ax - a_ax)^2``, ``p = r_b r_a`` and the phase difference relative to cable 1; the
    offsets in every case. Used to compare calibrations that differ by a gauge motion.
    """
    b, a, o = require_cables(module)
    out: dict[str, Array] = {"offset": o}
    if module.kind == "spherical":
        out["base_distances"] = jnp.linalg.norm(b[:, None] - b[None], axis=-1)
        out["platform_distances"] = jnp.linalg.norm(a[:, None] - a[None], axis=-1)
        out["base_radius"] = jnp.linalg.norm(b, axis=-1)
        out["platform_radius"] = jnp.linalg.norm(a, axis=-1)
    elif module.kind == "revolute":
        axis = jnp.asarray(module.axis, b.dtype)
        bax, aax = b @ axis, a @ axis
        bp, ap = b - bax[:, None] * axis, a - aax[:, None] * axis
        rb, ra = jnp.linalg.norm(bp, axis=-1), jnp.linalg.norm(ap, axis=-1)
        out["c"] = rb**2 + ra**2 + (bax - aax) ** 2
        out["p"] = rb * ra
        # angle from the platform point to the base point about the axis
        phase = jnp.arctan2(jnp.einsum("i,ni->n", axis, jnp.cross(ap, bp)), jnp.sum(ap * bp, -1))
        dphi = phase - phase[0]
        out["phase"] = jnp.arctan2(jnp.sin(dphi), jnp.cos(dphi))
    return out


# --- identifiability -----------------------------------------------------------------------


@dataclass(frozen=True)
class SelfCalibrationReport:
    """Which module parameters cable lengths can identify from one pose set.

    Attributes:
        module: module name.
        rank: numerical rank of the reduced Jacobian (parameters only; the states add
            ``dof m`` to the rank of the joint Jacobian).
        n_params: ``7 n``.
        n_poses: ``m``.
        singular_values: ``(7 n,)`` decreasing.
        condition_number: over the identifiable directions.
        symmetries: named parameter motions (gauge freedoms) that lie in the null space.
        unidentifiable: the null space in words: the symmetries, and any remaining direction as
            a named parameter combination.
        null_space: ``(7 n - rank, 7 n)`` orthonormal basis (rows).
        param_names: names of the parameters.
        rcond: the relative singular-value cut-off.
    """

    module: str
    rank: int
    n_params: int
    n_poses: int
    singular_values: np.ndarray
    condition_number: float
    symmetries: tuple[str, ...]
    unidentifiable: tuple[str, ...]
    null_space: np.ndarray
    param_names: tuple[str, ...]
    rcond: float
    _row_space: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 0)))

    def covariance(self, noise_mm: float) -> np.ndarray:
        """Covariance ``(7n, 7n)`` mm^2 of the minimum-norm estimate for length noise ``noise_mm``.

        ``s^2 (J^T J)^+`` with the reduced Jacobian ``J`` and the same rank cut-off: the
        covariance in the identifiable subspace (zero along the unidentifiable directions).
        """
        V = self._row_space
        s = self.singular_values[: self.rank]
        return noise_mm**2 * (V.T / s**2) @ V

    def to_dict(self) -> dict:
        """JSON-ready mapping."""
        return {
            "module": self.module,
            "rank": int(self.rank),
            "n_params": int(self.n_params),
            "n_poses": int(self.n_poses),
            "condition_number": float(self.condition_number),
            "rcond": float(self.rcond),
            "singular_values": [float(s) for s in self.singular_values],
            "symmetries": list(self.symmetries),
            "unidentifiable": list(self.unidentifiable),
        }

    def summary(self) -> str:
        lines = [
            f"self-calibration of {self.module}: rank {self.rank} of {self.n_params} parameters "
            f"from {self.n_poses} poses, condition number {self.condition_number:.3g}"
        ]
        lines += [f"  unidentifiable: {u}" for u in self.unidentifiable]
        return "\n".join(lines)


def _symmetry_candidates(module: Module, theta: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Named parameter motions that may be invisible to cable lengths (see the docstring)."""
    n = module.n_cables
    P = theta.reshape(n, 7)
    b, a = P[:, :3], P[:, 3:6]
    name = module.name
    out = []

    def vec(db=None, da=None):
        v = np.zeros((n, 7))
        if db is not None:
            v[:, :3] = db
        if da is not None:
            v[:, 3:6] = da
        return v.reshape(-1)

    if module.kind == "spherical":
        for k, c in enumerate(_COMPONENTS):
            e = np.eye(3)[k]
            out.append(
                (
                    f"rotation of all {name} base points about the module centre ({c})",
                    vec(db=np.cross(e, b)),
                )
            )
        for k, c in enumerate(_COMPONENTS):
            e = np.eye(3)[k]
            out.append(
                (
                    f"rotation of all {name} platform points about the module centre ({c})",
                    vec(da=np.cross(e, a)),
                )
            )
        return out
    axis = np.asarray(module.axis, float)
    if module.kind == "revolute":
        out.append(
            (f"rotation of all {name} base points about the joint axis", vec(db=np.cross(axis, b)))
        )
        out.append(
            (
                f"rotation of all {name} platform points about the joint axis",
                vec(da=np.cross(axis, a)),
            )
        )
        for i in range(n):
            m = np.zeros((n, 1))
            m[i] = 1.0
            out.append(
                (
                    f"rotation of {name} cable {i + 1}'s two points about the joint axis",
                    vec(db=m * np.cross(axis, b), da=m * np.cross(axis, a)),
                )
            )
            out.append(
                (
                    f"shift of {name} cable {i + 1}'s two points along the joint axis",
                    vec(db=m * axis, da=m * axis),
                )
            )
            out.append(
                (
                    f"trade-off of {name} cable {i + 1}'s radii and axial spacing at fixed "
                    "r_b^2 + r_a^2 + (b_ax - a_ax)^2 and r_b r_a",
                    _tradeoff(b, a, axis, i),
                )
            )
        return out
    out.append(
        (
            f"translation of all {name} base points along the axis",
            vec(db=np.broadcast_to(axis, b.shape)),
        )
    )
    out.append(
        (
            f"translation of all {name} platform points along the axis",
            vec(da=np.broadcast_to(axis, a.shape)),
        )
    )
    out.append(
        (
            f"rotation of all {name} points about the axis",
            vec(db=np.cross(axis, b), da=np.cross(axis, a)),
        )
    )
    return out


def _tradeoff(b: np.ndarray, a: np.ndarray, axis: np.ndarray, i: int) -> np.ndarray:
    """Motion of cable ``i`` of a revolute module that keeps both of its length invariants.

    With ``r_b, r_a`` the distances of the points from the axis and ``h = b_ax - a_ax``, the
    lengths see only ``C = r_b^2 + r_a^2 + h^2`` and ``P = r_b r_a``; the motion along
    ``grad C x grad P = (-2 h r_b, 2 h r_a, 2 (r_b^2 - r_a^2))`` in ``(r_b, r_a, h)`` changes
    neither (with ``h`` split equally between the two points).
    """
    n = b.shape[0]
    bax, aax = b[i] @ axis, a[i] @ axis
    bp, ap = b[i] - bax * axis, a[i] - aax * axis
    rb, ra, h = np.linalg.norm(bp), np.linalg.norm(ap), bax - aax
    d_rb, d_ra, d_h = -2 * h * rb, 2 * h * ra, 2 * (rb**2 - ra**2)
    v = np.zeros((n, 7))
    v[i, :3] = d_rb * bp / max(rb, 1e-300) + 0.5 * d_h * axis
    v[i, 3:6] = d_ra * ap / max(ra, 1e-300) - 0.5 * d_h * axis
    return v.reshape(-1)


def analyze_self_calibration(
    module: Module, states: ArrayLike, *, rcond: float | None = None
) -> SelfCalibrationReport:
    """Identifiability of ``module``'s cable parameters from cable lengths at ``states (m, dof)``.

    SVD of :func:`reduced_jacobian`; the null space is described by the named symmetries of the
    module docstring that lie in it (checked numerically) and, for whatever they do not span,
    by readable parameter combinations.
    """
    M = np.asarray(reduced_jacobian(module, states))
    names = parameter_names(module)
    n_params = len(names)
    cut = default_rcond(M.dtype) if rcond is None else rcond
    _, s, Vt = np.linalg.svd(M, full_matrices=True)
    s_full = np.zeros(n_params)
    s_full[: s.size] = s
    rank = int(np.sum(s_full > cut * s_full[0]))
    row = Vt[:rank]
    null = Vt[rank:]
    theta = np.asarray(module_parameters(module), float)
    found: list = []
    vecs: list[np.ndarray] = []
    for label, v in _symmetry_candidates(module, theta):
        nv = np.linalg.norm(v)
        if nv == 0:
            continue
        v = v / nv
        if np.linalg.norm(row @ v) < 1e-6:
            if vecs and np.linalg.matrix_rank(np.stack(vecs + [v]), tol=1e-8) == len(vecs):
                continue  # already spanned by the symmetries found so far
            found.append(label)
            vecs.append(v)
    words = list(found)
    if null.shape[0] > len(vecs):
        # Directions of the null space the symmetries do not explain.
        B = null.T
        if vecs:
            S = np.stack(vecs, axis=1)
            Qs, _ = np.linalg.qr(S)
            B = B - Qs @ (Qs.T @ B)
            U, sv, _ = np.linalg.svd(B, full_matrices=False)
            B = U[:, : null.shape[0] - len(vecs)]
        for row_vec in sparse_basis(B):
            words.append(format_combination(row_vec, names))
    cond = float(s_full[0] / s_full[rank - 1]) if rank else float("inf")
    return SelfCalibrationReport(
        module=module.name,
        rank=rank,
        n_params=n_params,
        n_poses=int(np.shape(states)[0]),
        singular_values=s_full,
        condition_number=cond,
        symmetries=tuple(found),
        unidentifiable=tuple(words),
        null_space=null,
        param_names=names,
        rcond=cut,
        _row_space=row,
    )
