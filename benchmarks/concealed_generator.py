"""Concealed-effect recordings: an independent, richer simulation of the CDRA's non-geometric
physics.

This is the *generator* half of the proof on concealed effects: it writes
recordings of a simulated arm that carries one hidden physical effect besides the random
geometric assembly errors of Section V, in exactly the files a user with a real arm has (the
NOMINAL model TOML and a measurement CSV), so that an analyser can be scored on finding the
effect from those files alone. The scorer is ``benchmarks/concealed_physics.py``.

Independence. Everything physical here is written from first principles in NumPy/SciPy: the
gravity loads of the bodies, the cable tension distribution (feasibility by
``scipy.optimize.nnls``, the least-norm tensions by a semismooth Newton iteration on the QP's
dual), the cable forward kinematics (a batched Gauss-Newton on the cable lengths), the joint
stiffness law, the Euler-Bernoulli beam, the warm-up drift and the SE(3) exponential. Only the
file readers/writers (``cdra_jax.io``) and, for the effect size, the paper's geometric
calibration (``cdra_jax.calibrate_paper``) come from the package; no code of
``cdra_jax.physics``, ``cdra_jax.diagnosis`` or ``cdra_jax.modules`` is used, and every effect
has a form richer than a linear candidate model (see each ``_apply_*`` function).

The simulated arm (units mm, rad, kg, N, s; gravity from the model file)::

    T_OF = exp(d_0(t)) F_0^a  M_1^a  F_1^a  M_2^a ... M_K^a  F_K^a        (Eq. 1 with errors)

``F_j^a = exp(hat(X_j)) F_j`` with ``X`` uniform in +-1 mm / +-0.05 rad (Section V), ``M_i^a``
the actual module poses (the commanded ones unless the effect acts on the module) and ``d_0(t)``
the mount drift (``thermal_drift`` only). A measured pose is ``T_OF`` with isotropic Gaussian
noise: ``p + N(0, s_p^2 I)`` and ``R -> exp(hat(N(0, s_r^2 I))) R`` (world frame).

Effect size. The *unabsorbed RMS* of an effect is the RMS, over the ``6 m`` entries, of the
noise-whitened residual left by a geometry-only fit (``calibrate_paper(..., noise=...)``) of the
noise-free recording; it is in units of the noise. :func:`calibrate_size` scales the effect's
physical parameter (secant on log-log, bisection fallback) until that RMS hits the request.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import nnls
from scipy.spatial.transform import Rotation

EFFECTS: tuple[str, ...] = (
    "joint_compliance",
    "cable_elasticity",
    "cable_scale",
    "backlash",
    "periodic_error",
    "link_bending",
    "thermal_drift",
)
"""Effects of the analyser's vocabulary (design.md, 'Candidate physics vocabulary')."""

OUT_OF_LIBRARY: tuple[str, ...] = (
    "cable_coupling",
    "device_distortion",
    "saturating_stretch",
    "link_growth",
    "nonspherical_joint",
)
"""Effects with no candidate in the vocabulary: the expected verdict is ``unattributed``."""

OOL_HOME: dict[str, str] = {
    "saturating_stretch": "module",
    "link_growth": "link",
    "nonspherical_joint": "module",
}
"""Out-of-library effects with one place in the chain where they live (the module or link they
act on): an analyser should locate its ``unattributed`` verdict there. ``cable_coupling`` (its
path runs through two modules) and ``device_distortion`` (outside the arm) have none."""

ALL_EFFECTS = EFFECTS + OUT_OF_LIBRARY

SECTION_V_DV = 1.0
"""Geometric error range per translation component (mm), Section V."""
SECTION_V_DW = 0.05
"""Geometric error range per rotation component (rad), Section V."""

DRUM_RADIUS_MM = 10.0
"""Winch drum radius: a 1 mm cable on a 20 mm drum (cable payout -> drum angle)."""
CABLE_T_REF_N = 50.0
"""Cable stiffening tension: ``k(t) = k0 (1 + t / t_ref)`` (braided fibre cables stiffen)."""
PAYLOADS_KG = (0.0, 0.1, 0.2, 0.5)
"""Payloads at the tool frame origin drawn for the recordings."""


class SizeError(RuntimeError):
    """The requested unabsorbed RMS could not be reached by scaling the effect's parameter."""


# ----------------------------------------------------------------------------------------------
# The model file, as plain NumPy arrays
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ModuleData:
    """One module of the model file (units mm, kg, N, N/mm).

    Attributes:
        name, kind: as in the model file (``spherical``, ``revolute``, ``prismatic``).
        axis: ``(3,)`` unit axis (revolute/prismatic), module base frame.
        limits: ``(dof, 2)`` state limits.
        cable_base, cable_platform: ``(n, 3)`` attachment points (base / platform frame) or None.
        cable_offset: ``(n,)`` length offsets (zeros when the model gives none).
        mass: mass of the body the module moves (kg, 0 when not given).
        com: its centre of mass ``(3,)`` in the platform frame (mm).
        pretension: tension floor (N) or None; stiffness: cable stiffness (N/mm) or None.
    """

    name: str
    kind: str
    axis: np.ndarray
    limits: np.ndarray
    cable_base: np.ndarray | None
    cable_platform: np.ndarray | None
    cable_offset: np.ndarray
    mass: float
    com: np.ndarray
    pretension: float | None
    stiffness: float | None

    @property
    def dof(self) -> int:
        return 3 if self.kind == "spherical" else 1

    @property
    def n_cables(self) -> int:
        return 0 if self.cable_base is None else self.cable_base.shape[0]

    @property
    def rotational(self) -> bool:
        return self.kind in ("spherical", "revolute")


@dataclass(frozen=True, eq=False)
class ArmData:
    """The model file read once: geometry, cables and masses as NumPy arrays.

    Attributes:
        arm: the :class:`cdra_jax.Arm` (used only for the geometric fit and the CSV writer).
        model_text: the file's text, written unchanged next to each recording.
        frames: ``(K+1, 4, 4)`` nominal fixed transforms; frame_names their names.
        modules: the K modules; gravity: ``(3,)`` m/s^2 in the world frame.
    """

    arm: Any
    model_text: str
    frames: np.ndarray
    frame_names: tuple[str, ...]
    modules: tuple[ModuleData, ...]
    gravity: np.ndarray

    @property
    def n_modules(self) -> int:
        return len(self.modules)

    @property
    def dof(self) -> int:
        return sum(md.dof for md in self.modules)

    @property
    def slices(self) -> list[slice]:
        out, i = [], 0
        for md in self.modules:
            out.append(slice(i, i + md.dof))
            i += md.dof
        return out

    @property
    def limits(self) -> np.ndarray:
        return np.concatenate([md.limits for md in self.modules])

    def module_index(self, name: str) -> int:
        for i, md in enumerate(self.modules):
            if md.name == name:
                return i
        raise ValueError(f"no module {name!r}; modules: {[md.name for md in self.modules]}")

    def locations(self, effect: str) -> tuple[str, ...]:
        """Where ``effect`` can act on this arm (module, link or base names; () if nowhere)."""
        mods = self.modules
        has_mass = any(md.mass > 0 for md in mods)
        if effect == "joint_compliance":
            return tuple(md.name for md in mods if md.rotational and has_mass)
        if effect in ("cable_scale", "periodic_error"):
            return tuple(md.name for md in mods if md.rotational and md.n_cables)
        if effect == "cable_elasticity":
            return tuple(
                md.name
                for md in mods
                if md.rotational and md.n_cables and md.stiffness and md.pretension is not None
            )
        if effect == "backlash":
            return tuple(md.name for md in mods if md.rotational)
        if effect == "link_bending":
            return self.frame_names[1:-1] if has_mass else ()
        if effect == "thermal_drift":
            return (self.frame_names[0],)
        if effect == "cable_coupling":
            cabled = [md.name for md in mods if md.rotational and md.n_cables]
            return (cabled[-1],) if len(cabled) >= 2 else ()
        if effect == "device_distortion":
            return ("measurement",)
        if effect == "saturating_stretch":
            return tuple(md.name for md in mods if md.rotational and md.n_cables)
        if effect == "link_growth":
            return self.frame_names[1:-1]
        if effect == "nonspherical_joint":
            return tuple(md.name for md in mods if md.kind == "spherical")
        raise ValueError(f"unknown effect {effect!r}; known: {ALL_EFFECTS}")


def load_arm_data(model_path: str | Path) -> ArmData:
    """Read a model TOML (through ``cdra_jax.io``) into :class:`ArmData`."""
    from cdra_jax.io import loads_model

    path = Path(model_path)
    text = path.read_text(encoding="utf-8")
    return arm_data(loads_model(text, source=str(path)), text)


def arm_data(arm: Any, model_text: str) -> ArmData:
    """:class:`ArmData` of a :class:`cdra_jax.Arm` whose model file text is ``model_text``."""
    mods = []
    for m in arm.modules:
        n = m.n_cables
        mods.append(
            ModuleData(
                name=m.name,
                kind=m.kind,
                axis=np.asarray(m.axis, dtype=float),
                limits=np.asarray(m.limits, dtype=float),
                cable_base=None if m.cable_base is None else np.asarray(m.cable_base, float),
                cable_platform=None
                if m.cable_platform is None
                else np.asarray(m.cable_platform, float),
                cable_offset=np.zeros(n)
                if m.cable_offset is None
                else np.asarray(m.cable_offset, float),
                mass=float(m.mass or 0.0),
                com=np.zeros(3) if m.com is None else np.asarray(m.com, float),
                pretension=None if m.pretension is None else float(m.pretension),
                stiffness=None if m.stiffness is None else float(m.stiffness),
            )
        )
    return ArmData(
        arm=arm,
        model_text=model_text,
        frames=np.asarray(arm.frames, dtype=float),
        frame_names=tuple(arm.frame_names),
        modules=tuple(mods),
        gravity=np.asarray(arm.gravity, dtype=float),
    )


# ----------------------------------------------------------------------------------------------
# Rigid-body helpers (NumPy; batched over a leading pose axis)
# ----------------------------------------------------------------------------------------------


def _rot(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrices of rotation vectors ``(..., 3) -> (..., 3, 3)``."""
    rv = np.asarray(rotvec, dtype=float)
    return Rotation.from_rotvec(rv.reshape(-1, 3)).as_matrix().reshape(rv.shape[:-1] + (3, 3))


def _pose(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    T = np.zeros(np.broadcast_shapes(R.shape[:-2], p.shape[:-1]) + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = p
    T[..., 3, 3] = 1.0
    return T


def _se3_exp(xi: np.ndarray) -> np.ndarray:
    """Pose of twists ``(v, w)`` (Eq. 26): ``(..., 6) -> (..., 4, 4)``, ``[[exp(w^), V v]]``."""
    xi = np.asarray(xi, dtype=float)
    v, w = xi[..., :3], xi[..., 3:]
    th2 = np.sum(w * w, axis=-1)[..., None, None]
    small = th2 < 1e-4
    t2 = np.where(small, 1.0, th2)
    th = np.sqrt(t2)
    b = np.where(small, 0.5 - th2 / 24 + th2**2 / 720, (1 - np.cos(th)) / t2)
    c = np.where(small, 1 / 6 - th2 / 120 + th2**2 / 5040, (th - np.sin(th)) / (t2 * th))
    W = np.zeros(w.shape[:-1] + (3, 3))
    W[..., 0, 1], W[..., 0, 2], W[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    W = W - np.swapaxes(W, -1, -2)
    V = np.eye(3) + b * W + c * (W @ W)
    return _pose(_rot(w), np.einsum("...ij,...j->...i", V, v))


def _apply(T: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Points ``x (..., 3)`` mapped by poses ``T (..., 4, 4)``."""
    return np.einsum("...ij,...j->...i", T[..., :3, :3], x) + T[..., :3, 3]


def module_pose(md: ModuleData, qi: np.ndarray) -> np.ndarray:
    """Platform pose in the module base frame for states ``qi (m, dof)``: ``(m, 4, 4)``."""
    qi = np.asarray(qi, dtype=float)
    zero = np.zeros(qi.shape[:-1] + (3,))
    if md.kind == "spherical":
        return _pose(_rot(qi), zero)
    if md.kind == "revolute":
        return _pose(_rot(qi * md.axis), zero)
    return _pose(np.broadcast_to(np.eye(3), qi.shape[:-1] + (3, 3)), qi * md.axis)


def chain_poses(F: np.ndarray, M: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 1 product. ``F (m, K+1, 4, 4)``, ``M (m, K, 4, 4)`` -> ``(tool, before, after)``.

    ``before[:, i]`` is the world pose of module i's base frame, ``after[:, i]`` that of its
    platform (``before @ M``).
    """
    T = F[:, 0]
    before, after = [], []
    for i in range(M.shape[1]):
        before.append(T)
        T = T @ M[:, i]
        after.append(T)
        T = T @ F[:, i + 1]
    return T, np.stack(before, 1), np.stack(after, 1)


# ----------------------------------------------------------------------------------------------
# Statics: gravity loads and the cable tension distribution
# ----------------------------------------------------------------------------------------------


def _gravity_forces(arm: ArmData, after: np.ndarray, tool: np.ndarray, payload: np.ndarray):
    """World points (mm) and gravity forces (N) of the bodies and the payload.

    Returns ``(points (m, K+1, 3), forces (m, K+1, 3))``: entry i < K is the body module i
    moves (at its centre of mass), entry K the payload at the tool frame origin.
    """
    m, K = after.shape[0], after.shape[1]
    com = np.stack([md.com for md in arm.modules])  # (K, 3)
    mass = np.array([md.mass for md in arm.modules])
    pts = np.concatenate([_apply(after, com[None]), tool[:, None, :3, 3]], axis=1)
    masses = np.concatenate([np.broadcast_to(mass, (m, K)), payload[:, None]], axis=1)
    return pts, masses[..., None] * arm.gravity


def gravity_moments(arm: ArmData, F: np.ndarray, M: np.ndarray, payload: np.ndarray) -> np.ndarray:
    """Moment (N mm) of gravity on everything each module carries, about its centre.

    For module i: the bodies moved by modules i..K-1 and the payload, about the module's centre
    of rotation (the origin of its base frame), expressed in its base frame: ``(m, K, 3)``.
    A rod's moment equals that of its mass at its centre of mass, so the model's ``com`` is exact
    here (the distribution matters for bending, see :func:`_apply_link_bending`).
    """
    tool, before, after = chain_poses(F, M)
    pts, forces = _gravity_forces(arm, after, tool, payload)
    K = M.shape[1]
    out = np.empty((M.shape[0], K, 3))
    for i in range(K):
        o = after[:, i, :3, 3]
        tau_w = np.sum(np.cross(pts[:, i:] - o[:, None], forces[:, i:]), axis=1)
        out[:, i] = np.einsum("mji,mj->mi", before[:, i, :3, :3], tau_w)
    return out


def cable_moment_matrix(md: ModuleData, R: np.ndarray) -> np.ndarray:
    """Moment about the module centre per newton of each cable: ``(m, r, n)``, base frame.

    Cable k pulls platform point ``P_k = R p_k`` towards its base point ``b_k``; its moment is
    ``P_k x u_k`` with ``u_k = (b_k - P_k) / |b_k - P_k|``. For a revolute module only the
    moment about the axis is balanced by the cables (``r = 1``); the hinge takes the rest. A
    spherical joint takes forces only (``r = 3``).
    """
    P = np.einsum("mij,nj->mni", R, md.cable_platform)
    d = md.cable_base[None] - P
    u = d / np.linalg.norm(d, axis=-1, keepdims=True)
    mom = np.cross(P, u)  # (m, n, 3)
    if md.kind == "revolute":
        return np.einsum("i,mni->mn", md.axis, mom)[:, None, :]
    return np.swapaxes(mom, 1, 2)


def distribute_tensions(
    A: np.ndarray, tau: np.ndarray, t_min: float, *, tol: float = 1e-11
) -> tuple[np.ndarray, bool]:
    """Cable tensions of least 2-norm above a floor that balance an external moment.

    Solves ``min |t|^2 / 2`` s.t. ``A t + tau = 0``, ``t >= t_min`` (one pose; ``A (r, n)``,
    ``tau (r,)`` N mm). Feasibility comes from ``scipy.optimize.nnls`` on ``t = t_min + s``;
    the optimum from the dual: ``t(lam) = max(t_min, A^T lam)`` satisfies every KKT condition
    but the equilibrium, and the convex, once-differentiable dual objective
    ``h(lam) = sum_j phi(a_j . lam) - lam . w`` (``w = -tau``, ``phi(x) = x^2 / 2`` above the
    floor and ``t_min x - t_min^2 / 2`` below) has gradient ``A t(lam) - w``: a damped
    semismooth Newton iteration on the ``r <= 3`` multipliers drives it to zero.

    Returns:
        ``(t (n,), feasible)``: ``feasible`` is False when no tensions above the floor balance
        the moment (the pose is outside the module's tension-closure workspace).
    """
    n = A.shape[1]
    w = -np.asarray(tau, dtype=float)
    tmin = np.full(n, float(t_min))
    ref = 1.0 + np.linalg.norm(w) + np.linalg.norm(A @ tmin)
    s, res = nnls(A, w - A @ tmin)
    if res > 1e-8 * ref:
        return tmin + s, False

    def parts(lam):
        x = A.T @ lam
        t = np.maximum(tmin, x)
        h = np.sum(np.where(x > tmin, 0.5 * x * x, tmin * x - 0.5 * tmin * tmin)) - lam @ w
        return x, t, h

    lam = np.linalg.lstsq(A @ A.T, w, rcond=None)[0]
    eps = 1e-13 * max(1.0, np.linalg.norm(A) ** 2)
    x, t, h = parts(lam)
    for _ in range(200):
        grad = A @ t - w
        if np.linalg.norm(grad) <= tol * ref:
            return t, True
        F = x > tmin
        H = A[:, F] @ A[:, F].T + eps * np.eye(A.shape[0])
        step = -np.linalg.solve(H, grad)
        a = 1.0
        while True:
            x1, t1, h1 = parts(lam + a * step)
            if h1 <= h + 1e-4 * a * (grad @ step) or a < 1e-14:
                break
            a *= 0.5
        lam, x, t, h = lam + a * step, x1, t1, h1
    return t, bool(np.linalg.norm(A @ t - w) <= 1e-8 * ref)


def module_tensions(
    md: ModuleData, R: np.ndarray, tau: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Tensions ``(m, n)`` and feasibility ``(m,)`` of one module at orientations ``R (m,3,3)``.

    ``tau (m, 3)`` is the gravity moment about the centre in the base frame (see
    :func:`gravity_moments`); the cables must cancel its free components.
    """
    A = cable_moment_matrix(md, R)
    tau_r = np.einsum("i,mi->m", md.axis, tau)[:, None] if md.kind == "revolute" else tau
    t_min = md.pretension or 0.0
    out = np.empty((R.shape[0], md.n_cables))
    ok = np.empty(R.shape[0], dtype=bool)
    for k in range(R.shape[0]):
        out[k], ok[k] = distribute_tensions(A[k], tau_r[k], t_min)
    return out, ok


# ----------------------------------------------------------------------------------------------
# Cable kinematics
# ----------------------------------------------------------------------------------------------


def cable_lengths(md: ModuleData, R: np.ndarray) -> np.ndarray:
    """Cable lengths ``(m, n)`` (mm, offsets included) at platform orientations ``R (m,3,3)``."""
    P = np.einsum("mij,nj->mni", R, md.cable_platform)
    return np.linalg.norm(P - md.cable_base[None], axis=-1) + md.cable_offset


def cable_forward(
    md: ModuleData, lengths: np.ndarray, R0: np.ndarray, *, iterations: int = 40
) -> np.ndarray:
    """Platform orientations ``(m, 3, 3)`` whose cable lengths best match ``lengths (m, n)``.

    Batched Gauss-Newton on ``sum_k (|R p_k - b_k| + o_k - l_k)^2`` (least squares for a
    redundant cable set), started at ``R0`` and updated as ``R <- exp(hat(d)) R``: the length
    of cable k moves by ``(P_k x u_k) . d`` for a rotation ``d`` (base frame), with
    ``u_k = (P_k - b_k) / |P_k - b_k|``. A revolute module rotates about its axis only.
    """
    R = np.array(R0, dtype=float)
    for _ in range(iterations):
        P = np.einsum("mij,nj->mni", R, md.cable_platform)
        d = P - md.cable_base[None]
        dist = np.linalg.norm(d, axis=-1)
        res = dist + md.cable_offset - lengths
        J = np.cross(P, d / dist[..., None])  # (m, n, 3)
        if md.kind == "revolute":
            Ja = J @ md.axis  # (m, n)
            step = -np.sum(Ja * res, -1) / np.sum(Ja * Ja, -1)
            delta = step[:, None] * md.axis
        else:
            JtJ = np.einsum("mni,mnj->mij", J, J)
            delta = -np.linalg.solve(JtJ, np.einsum("mni,mn->mi", J, res)[..., None])[..., 0]
        R = _rot(delta) @ R
        if np.max(np.abs(delta)) < 1e-15:
            break
    return R


# ----------------------------------------------------------------------------------------------
# Scenario: everything about a recording except the effect and its size
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Scenario:
    """One recording's poses, auxiliaries, geometric errors and noise draws (no effect).

    Attributes:
        arm: the model.
        q: ``(m, dof)`` commanded module states in visiting order (the CSV's state columns).
        time_s: ``(m,)`` time of each measurement (s since the arm was powered up).
        payload_kg: ``(m,)`` payload at the tool frame origin.
        approach_dirs: per module, the ``(dof,)`` unit direction of its drive along which the
            approach sign is taken (spherical: drawn at random; revolute: ``[1]``).
        approach: module name -> ``(m,)`` sign of the last motion along ``approach_dirs``.
        errors: ``(K+1, 6)`` geometric frame errors (Section V).
        noise_pos_mm, noise_rot_rad: measurement noise standard deviations.
        unit_noise: ``(m, 6)`` standard-normal draws (position, rotation) for the noise.
    """

    arm: ArmData
    q: np.ndarray
    time_s: np.ndarray
    payload_kg: np.ndarray
    approach_dirs: tuple[np.ndarray, ...]
    approach: Mapping[str, np.ndarray]
    errors: np.ndarray
    noise_pos_mm: float
    noise_rot_rad: float
    unit_noise: np.ndarray

    @property
    def m(self) -> int:
        return self.q.shape[0]

    @property
    def actual_frames(self) -> np.ndarray:
        """``(K+1, 4, 4)`` fixed transforms with the geometric errors (Eqs. 11-14 form)."""
        return _se3_exp(self.errors) @ self.arm.frames

    def commanded_module_poses(self) -> np.ndarray:
        """``(m, K, 4, 4)`` module poses at the commanded states."""
        return np.stack(
            [
                module_pose(md, self.q[:, s])
                for md, s in zip(self.arm.modules, self.arm.slices, strict=True)
            ],
            axis=1,
        )


def _closure_ok(arm: ArmData, q: np.ndarray, payload: np.ndarray) -> np.ndarray:
    """Whether every cabled module can hold the nominal arm at ``q`` with tensions >= floor."""
    F = np.broadcast_to(arm.frames, (q.shape[0],) + arm.frames.shape)
    M = np.stack(
        [module_pose(md, q[:, s]) for md, s in zip(arm.modules, arm.slices, strict=True)], 1
    )
    tau = gravity_moments(arm, F, M, payload)
    ok = np.ones(q.shape[0], dtype=bool)
    for i, md in enumerate(arm.modules):
        if md.n_cables and md.rotational:
            ok &= module_tensions(md, M[:, i, :3, :3], tau[:, i])[1]
    return ok


def _visit_order(q: np.ndarray, home: np.ndarray, span: np.ndarray) -> np.ndarray:
    """Greedy nearest-neighbour tour from ``home`` (joint distances scaled by the ranges)."""
    left = list(range(q.shape[0]))
    order, cur = [], home
    while left:
        d = np.linalg.norm((q[left] - cur) / span, axis=1)
        j = left.pop(int(np.argmin(d)))
        order.append(j)
        cur = q[j]
    return np.array(order)


def draw_scenario(
    arm: ArmData,
    m: int,
    rng: np.random.Generator,
    *,
    noise_pos_mm: float,
    noise_rot_rad: float,
    d_v: float = SECTION_V_DV,
    d_w: float = SECTION_V_DW,
) -> Scenario:
    """Draw a recording's poses, order, times, payloads, geometric errors and noise.

    Poses: uniform within the joint limits, kept when every cabled module reaches tension
    closure (pretension floor) holding the nominal arm and payload (Section V, step 1), visited
    as a nearest-neighbour tour from home (q = 0 clipped to the limits), 20-40 s apart from a
    start 0-120 s after power-up. The payload is either constant for the whole recording or
    changed at random between poses (half of the recordings each). Every random stream is
    separate, so the same ``rng`` state gives the same scenario whatever effect follows.
    """
    r_pose, r_pay, r_err, r_noise, r_dir, r_time = rng.spawn(6)
    lim = arm.limits
    varied = r_pay.random() < 0.5
    if varied:
        payload = r_pay.choice(PAYLOADS_KG, size=m)
    else:
        payload = np.full(m, r_pay.choice(PAYLOADS_KG))
    qs: list[np.ndarray] = []
    tries = 0
    while sum(len(x) for x in qs) < m:
        tries += 1
        if tries > 200:
            raise RuntimeError("could not draw poses inside the tension-closure workspace")
        need = m - sum(len(x) for x in qs)
        cand = lim[:, 0] + r_pose.random((2 * need + 4, arm.dof)) * (lim[:, 1] - lim[:, 0])
        pay = payload[sum(len(x) for x in qs) :][: len(cand)]
        pay = np.resize(pay, len(cand))
        qs.append(cand[_closure_ok(arm, cand, pay)][:need])
    q = np.concatenate(qs)[:m]
    home = np.clip(0.0, lim[:, 0], lim[:, 1])
    order = _visit_order(q, home, lim[:, 1] - lim[:, 0])
    q = q[order]
    if varied:
        payload = payload[order]
    dirs = []
    approach = {}
    prev = np.vstack([home, q[:-1]])
    for md, s in zip(arm.modules, arm.slices, strict=True):
        d = np.ones(1) if md.dof == 1 else r_dir.normal(size=3)
        d = d / np.linalg.norm(d)
        dirs.append(d)
        motion = (q[:, s] - prev[:, s]) @ d
        approach[md.name] = np.where(motion >= 0.0, 1.0, -1.0)
    time_s = r_time.uniform(0.0, 120.0) + np.cumsum(r_time.uniform(20.0, 40.0, m))
    scale = np.array([d_v] * 3 + [d_w] * 3)
    errors = r_err.uniform(-1.0, 1.0, (len(arm.frame_names), 6)) * scale
    return Scenario(
        arm=arm,
        q=q,
        time_s=time_s,
        payload_kg=payload.astype(float),
        approach_dirs=tuple(dirs),
        approach=approach,
        errors=errors,
        noise_pos_mm=float(noise_pos_mm),
        noise_rot_rad=float(noise_rot_rad),
        unit_noise=r_noise.normal(size=(m, 6)),
    )


# ----------------------------------------------------------------------------------------------
# Effects
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Effect:
    """A hidden effect: its name, where it acts, and the random details of its shape.

    Attributes:
        name: one of :data:`ALL_EFFECTS` (or ``"none"``).
        location: module / link / frame name it acts on, or ``"measurement"``; None for none.
        shape: the effect's fixed random details (phases, directions, time constants ...).
        parameter: name and unit of the physical parameter the size scales.
        guess: a physically typical value of that parameter (start of the size search).
    """

    name: str
    location: str | None
    shape: Mapping[str, Any] = field(default_factory=dict)
    parameter: str = ""
    guess: float = 1.0

    @property
    def expected_effect(self) -> str:
        """The verdict a perfect analyser gives: the name, or ``unattributed`` / ``none``."""
        return "unattributed" if self.name in OUT_OF_LIBRARY else self.name

    @property
    def expected_location(self) -> str | None:
        """Where a perfect analyser places it: the location of an in-library effect, and of an
        out-of-library one that lives at one place of the chain (:data:`OOL_HOME`)."""
        return self.location if self.name in EFFECTS or self.name in OOL_HOME else None


NO_EFFECT = Effect(name="none", location=None)

_PARAMETERS = {
    "joint_compliance": ("compliance at zero load, rad / (N mm)", 1e-7),
    "cable_elasticity": ("cable compliance / (1 / stiffness in the model file), 1", 1e-2),
    "cable_scale": ("mean relative drum-radius error, 1", 1e-3),
    "backlash": ("backlash band width, rad", 1e-3),
    "periodic_error": ("drum eccentricity (first-harmonic payout error), mm", 2e-2),
    "link_bending": ("bending compliance 1 / EI, 1 / (N mm^2)", 5e-9),
    "thermal_drift": ("steady-state mount drift, mm", 0.3),
    "cable_coupling": ("guide-pulley radius of the routed cables, mm/rad", 0.1),
    "device_distortion": ("distortion at 500 mm from the device centre, mm", 0.1),
    "saturating_stretch": ("saturated payout error of the module's cables, mm", 0.05),
    "link_growth": ("steady-state growth of the link's length, mm", 0.2),
    "nonspherical_joint": ("platform centre shift at a 0.5 rad rotation, mm", 0.1),
}


def draw_effect(
    arm: ArmData, name: str, rng: np.random.Generator, location: str | None = None
) -> Effect:
    """An effect ``name`` at ``location`` (drawn among :meth:`ArmData.locations` if None)."""
    if name == "none":
        return NO_EFFECT
    locs = arm.locations(name)
    if not locs:
        raise ValueError(f"effect {name!r} has no possible location on this arm")
    if location is None:
        location = str(rng.choice(locs))
    elif location not in locs:
        raise ValueError(f"effect {name!r} cannot act on {location!r}; possible: {locs}")
    shape: dict[str, Any] = {}
    if name in ("cable_scale", "periodic_error", "cable_coupling"):
        n = arm.modules[arm.module_index(location)].n_cables
        if name == "cable_scale":
            shape["spread"] = np.clip(rng.normal(0.0, 0.25, n), -0.5, 0.5).tolist()
        elif name == "periodic_error":
            shape["phase1"] = rng.uniform(0, 2 * np.pi, n).tolist()
            shape["phase2"] = rng.uniform(0, 2 * np.pi, n).tolist()
            shape["harmonic2"] = float(rng.uniform(0.2, 0.5))
            shape["drum_radius_mm"] = DRUM_RADIUS_MM
        else:
            g = rng.normal(size=(n, 3))
            shape["guide_axes"] = (g / np.linalg.norm(g, axis=1, keepdims=True)).tolist()
            shape["source"] = next(md.name for md in arm.modules if md.n_cables)
    elif name == "joint_compliance":
        shape["twist_softness"] = float(rng.uniform(1.5, 3.0))
    elif name == "cable_elasticity":
        shape["t_ref_n"] = CABLE_T_REF_N
    elif name == "backlash":
        shape["n_play"] = 5
    elif name == "thermal_drift":
        v = rng.normal(size=3)
        w = rng.normal(size=3)
        shape["direction"] = (v / np.linalg.norm(v)).tolist()
        shape["tilt_axis"] = (w / np.linalg.norm(w)).tolist()
        shape["tilt_per_mm"] = float(rng.uniform(1e-4, 4e-4))
        shape["tau_s"] = float(rng.uniform(300.0, 1200.0))
    elif name == "saturating_stretch":
        n = arm.modules[arm.module_index(location)].n_cables
        shape["gains"] = rng.uniform(0.5, 1.5, n).tolist()
        shape["signs"] = rng.choice([-1.0, 1.0], n).tolist()
        shape["l_sat_mm"] = float(rng.uniform(2.0, 5.0))
    elif name == "link_growth":
        shape["tau_s"] = float(rng.uniform(300.0, 1200.0))
    elif name == "nonspherical_joint":
        S = rng.normal(size=(3, 3, 3))
        S = 0.5 * (S + np.swapaxes(S, 1, 2))
        shape["quadratic"] = (S / np.linalg.norm(S)).tolist()
        shape["theta_ref_rad"] = 0.5
    elif name == "device_distortion":
        S = rng.normal(size=(3, 3, 3))
        S = 0.5 * (S + np.swapaxes(S, 1, 2))
        shape["quadratic"] = (S / np.linalg.norm(S)).tolist()
        shape["centre_mm"] = [0.0, 0.0, 350.0]
        shape["radius_mm"] = 500.0
    param, guess = _PARAMETERS[name]
    return Effect(name=name, location=location, shape=shape, parameter=param, guess=guess)


def _module_torque_ref(md: ModuleData) -> float:
    """Load (N mm) at which a cable module's stiffness has doubled.

    The cables' pretension times their lever arms: the moment the pretension alone could
    resist. Modules without cables stiffen at 1000 N mm.
    """
    if not md.n_cables or not md.pretension:
        return 1000.0
    return float(md.pretension * np.linalg.norm(md.cable_platform, axis=1).sum())


def _apply_joint_compliance(scn, eff, c0, F, M):
    """Load-hardening rotational compliance of one module under its full gravity moment.

    ``d = C tau / (1 + |tau| / tau_ref)`` (rad, base frame): ``C = c0 diag(1, 1, s)`` in the
    platform axes (twist about the link axis ``s`` times softer), stiffness rising linearly with
    the load as the cable tensions rise (``tau_ref``: :func:`_module_torque_ref`). ``tau`` is
    the moment of all bodies the module carries and the payload; it is recomputed on the
    deflected arm (3 fixed-point passes). A revolute module deflects about its axis only.
    """
    i = scn.arm.module_index(eff.location)
    md = scn.arm.modules[i]
    M0 = M[:, i].copy()
    tref = _module_torque_ref(md)
    soft = np.diag([1.0, 1.0, eff.shape["twist_softness"]])
    for _ in range(3):
        tau = gravity_moments(scn.arm, F, M, scn.payload_kg)[:, i]
        gain = c0 / (1.0 + np.linalg.norm(tau, axis=-1) / tref)
        if md.kind == "revolute":
            d = (gain * (tau @ md.axis))[:, None] * md.axis
        else:
            Rp = M0[:, :3, :3]
            C = np.einsum("mij,jk,mlk->mil", Rp, soft, Rp)
            d = gain[:, None] * np.einsum("mij,mj->mi", C, tau)
        M = M.copy()
        M[:, i] = _pose(_rot(d), np.zeros(3)) @ M0
    return F, M


def _apply_cable_elasticity(scn, eff, c, F, M):
    """Nonlinear cable stretch under the tensions of our own statics solve.

    Cable stiffness ``k(t) = k0 (1 + t / t_ref)`` with ``1 / k0 = c / k_model``; the stretch is
    its integral ``e(t) = (t_ref / k0) ln(1 + t / t_ref)``. The tensions are the least-norm
    distribution above the pretension floor that holds the gravity moment
    (:func:`distribute_tensions`); the module pose follows from the stretched lengths by the
    cable forward kinematics (:func:`cable_forward`); loads and tensions are recomputed on the
    deflected arm (3 passes).
    """
    i = scn.arm.module_index(eff.location)
    md = scn.arm.modules[i]
    R0 = M[:, i, :3, :3]
    l_cmd = cable_lengths(md, R0)
    tref = eff.shape["t_ref_n"]
    R = R0
    for _ in range(3):
        tau = gravity_moments(scn.arm, F, M, scn.payload_kg)[:, i]
        t, _ = module_tensions(md, R, tau)
        stretch = (c / md.stiffness) * tref * np.log1p(t / tref)
        R = cable_forward(md, l_cmd + stretch, R)
        M = M.copy()
        M[:, i] = _pose(R, np.zeros(3))
    return F, M


def _cable_module_update(scn, eff, M, lengths_fn):
    i = scn.arm.module_index(eff.location)
    md = scn.arm.modules[i]
    R0 = M[:, i, :3, :3]
    l_cmd = cable_lengths(md, R0)
    home = cable_lengths(md, module_pose(md, np.clip(0.0, *md.limits.T)[None])[:, :3, :3])
    R = cable_forward(md, lengths_fn(md, l_cmd, home), R0)
    M = M.copy()
    M[:, i] = _pose(R, np.zeros(3))
    return M


def _apply_cable_scale(scn, eff, s, F, M):
    """Winch drum radii off by ``s (1 + spread_k)``: payout from home scaled per cable.

    ``l_k = l_home,k + (1 + s_k) (l_cmd,k - l_home,k)`` (home: q = 0), then cable forward
    kinematics. The per-cable spread makes it more than a uniform joint-angle scale.
    """
    spread = np.asarray(eff.shape["spread"])

    def lengths(md, l_cmd, home):
        return home + (1.0 + s * (1.0 + spread)) * (l_cmd - home)

    return F, _cable_module_update(scn, eff, M, lengths)


def _apply_periodic_error(scn, eff, a, F, M):
    """Drum transmission error periodic in each drum's angle, two harmonics.

    Drum angle ``phi_k = (l_cmd,k - l_home,k) / r_drum``; payout error
    ``a (sin(phi_k + psi_k) + h2 sin(2 phi_k + chi_k))`` (``a``: drum eccentricity), then cable
    forward kinematics. Periodic in the drum angles, which are nonlinear in the module angles.
    """
    p1, p2 = np.asarray(eff.shape["phase1"]), np.asarray(eff.shape["phase2"])
    h2, rd = eff.shape["harmonic2"], eff.shape["drum_radius_mm"]

    def lengths(md, l_cmd, home):
        phi = (l_cmd - home) / rd
        return l_cmd + a * (np.sin(phi + p1) + h2 * np.sin(2 * phi + p2))

    return F, _cable_module_update(scn, eff, M, lengths)


def _apply_cable_coupling(scn, eff, r_g, F, M):
    """(Out of library) routed cables: each cable of this module runs over guide pulleys in an
    upstream module, whose rotation changes its path length by ``r_g (g_k . rotvec_source)``.
    """
    src = scn.arm.module_index(eff.shape["source"])
    g = np.asarray(eff.shape["guide_axes"])
    q_src = scn.q[:, scn.arm.slices[src]]
    if q_src.shape[1] == 1:
        q_src = q_src * scn.arm.modules[src].axis

    def lengths(md, l_cmd, home):
        return l_cmd + r_g * q_src @ g.T

    return F, _cable_module_update(scn, eff, M, lengths)


def _apply_saturating_stretch(scn, eff, a, F, M):
    """(Out of library) a payout error that saturates: each cable of the module is off by
    ``a g_k s_k tanh((l_cmd,k - l_home,k) / l_sat)`` (a slipping or settling cable sheath),
    then cable forward kinematics. Monotone in the payout, neither periodic nor linear."""
    g = np.asarray(eff.shape["gains"]) * np.asarray(eff.shape["signs"])
    l_sat = eff.shape["l_sat_mm"]

    def lengths(md, l_cmd, home):
        return l_cmd + a * g * np.tanh((l_cmd - home) / l_sat)

    return F, _cable_module_update(scn, eff, M, lengths)


def _apply_link_growth(scn, eff, a, F, M):
    """(Out of library) one link lengthens as it warms up: its fixed transform's translation
    grows by ``a (1 - exp(-t / tau))`` along itself (``t``: ``time_s``). Unlike
    ``thermal_drift`` the mount stays; unlike ``link_bending`` nothing depends on the pose."""
    j = scn.arm.frame_names.index(eff.location)
    grow = a * (1.0 - np.exp(-scn.time_s / eff.shape["tau_s"]))
    p = F[:, j, :3, 3]
    e = p / np.linalg.norm(p, axis=-1, keepdims=True)
    F = F.copy()
    F[:, j, :3, 3] = p + grow[:, None] * e
    return F, M


def _apply_nonspherical_joint(scn, eff, a, F, M):
    """(Out of library) a ball joint that is not a perfect sphere: the platform centre moves by
    ``a x^T S_k x`` (``x``: the module's rotation vector over ``theta_ref``, ``S_k`` a fixed
    random symmetric tensor), in the module base frame. Quadratic in the rotation, so no frame
    error absorbs it, and no vocabulary effect translates a spherical module's platform."""
    i = scn.arm.module_index(eff.location)
    S = np.asarray(eff.shape["quadratic"])
    x = scn.q[:, scn.arm.slices[i]] / eff.shape["theta_ref_rad"]
    d = a * np.einsum("mj,ijk,mk->mi", x, S, x)
    M = M.copy()
    M[:, i, :3, 3] = M[:, i, :3, 3] + d
    return F, M


def _play(s: np.ndarray, start: float, r: float) -> np.ndarray:
    """Play (backlash) operator of half-width ``r`` along the input sequence ``s``."""
    y = np.empty_like(s)
    cur = start
    for k, x in enumerate(s):
        cur = min(max(cur, x - r), x + r)
        y[k] = cur
    return y


def _apply_backlash(scn, eff, b, F, M):
    """Hysteresis band of width ``b`` along the module's drive direction (Prandtl-Ishlinskii).

    The output lags the commanded drive coordinate ``s = d . q`` through ``N`` play operators
    of half-widths ``b i / (N + 1)`` (equal weights): after a move longer than ``b`` the lag is
    ``-b/2`` times the approach sign, after a shorter one it is partial. The sequence starts at
    home with no lag; poses are visited in the recording's order.
    """
    i = scn.arm.module_index(eff.location)
    md = scn.arm.modules[i]
    d = scn.approach_dirs[i]
    qi = scn.q[:, scn.arm.slices[i]]
    home = float(np.clip(0.0, *md.limits.T) @ d) if md.dof == 1 else 0.0
    s = qi @ d
    n = eff.shape["n_play"]
    lag = sum(_play(s, home, b * (k + 1) / (n + 1)) - s for k in range(n)) / n
    M = M.copy()
    M[:, i] = module_pose(md, qi + lag[:, None] * d)
    return F, M


def _apply_link_bending(scn, eff, c, F, M):
    """Euler-Bernoulli cantilever bending of a link (``c = 1 / EI``).

    The link runs from the upstream module's centre to the downstream module's base along its
    fixed-transform translation ``p`` (length ``L``, unit ``e``). Transverse loads: the link's
    own body as a uniform rod (``w = m_rod g_perp / L``) plus, when its centre of mass lies past
    mid-span, a point mass at the tip; the distal bodies and payload as a tip force ``P`` and a
    tip moment ``M_t``. Tip deflection ``u = c (w L^4 / 8 + P L^3 / 3 + (M_t x e) L^2 / 2)``
    and slope ``s = c (w L^3 / 6 + P L^2 / 2 + (M_t x e) L)``; the tip frame is moved by ``u``
    and turned by ``e x s`` about the tip. Loads are recomputed on the bent arm (2 passes).
    """
    arm = scn.arm
    j = arm.frame_names.index(eff.location)
    i_root = j - 1  # the module whose platform carries the link
    body = arm.modules[i_root]
    F0 = F[:, j].copy()
    p = F0[:, :3, 3]
    L = np.linalg.norm(p, axis=-1)
    e = p / L[:, None]
    zc = e @ body.com
    frac_tip = np.clip((zc / L - 0.5) / 0.5, 0.0, 1.0)
    m_tip = body.mass * frac_tip
    m_rod = body.mass - m_tip

    def perp(v):
        return v - np.sum(v * e, -1, keepdims=True) * e

    for _ in range(2):
        tool, before, after = chain_poses(F, M)
        pts, forces = _gravity_forces(arm, after, tool, scn.payload_kg)
        Rr = after[:, i_root, :3, :3]
        g_r = np.einsum("mji,j->mi", Rr, arm.gravity)  # N/kg in the root frame
        tip_w = _apply(after[:, i_root], p)
        distal_mass = m_tip + scn.payload_kg + sum(md.mass for md in arm.modules[j:])
        P = distal_mass[:, None] * perp(g_r)
        Mw = np.sum(np.cross(pts[:, j:] - tip_w[:, None], forces[:, j:]), axis=1)
        Mt = perp(np.einsum("mji,mj->mi", Rr, Mw))
        w = (m_rod / L)[:, None] * perp(g_r)
        Mxe = np.cross(Mt, e)
        Lc = L[:, None]
        u = c * (w * Lc**4 / 8 + P * Lc**3 / 3 + Mxe * Lc**2 / 2)
        s = c * (w * Lc**3 / 6 + P * Lc**2 / 2 + Mxe * Lc)
        Rb = _rot(np.cross(e, s))
        D = _pose(Rb, u + p - np.einsum("mij,mj->mi", Rb, p))
        F = F.copy()
        F[:, j] = D @ F0
    return F, M


def _apply_thermal_drift(scn, eff, a, F, M):
    """Warm-up drift of the mount: ``d(t) = (1 - exp(-t / tau)) (a n_v, a k n_w)`` left-multiplied
    on the base frame (world frame), ``t`` the time since power-up (``time_s``)."""
    sh = eff.shape
    grow = 1.0 - np.exp(-scn.time_s / sh["tau_s"])
    xi = np.concatenate(
        [
            np.asarray(sh["direction"]) * a,
            np.asarray(sh["tilt_axis"]) * a * sh["tilt_per_mm"],
        ]
    )
    F = F.copy()
    F[:, 0] = _se3_exp(grow[:, None] * xi) @ F[:, 0]
    return F, M


_APPLY: dict[str, Callable] = {
    "joint_compliance": _apply_joint_compliance,
    "cable_elasticity": _apply_cable_elasticity,
    "cable_scale": _apply_cable_scale,
    "backlash": _apply_backlash,
    "periodic_error": _apply_periodic_error,
    "link_bending": _apply_link_bending,
    "thermal_drift": _apply_thermal_drift,
    "cable_coupling": _apply_cable_coupling,
    "saturating_stretch": _apply_saturating_stretch,
    "link_growth": _apply_link_growth,
    "nonspherical_joint": _apply_nonspherical_joint,
}


def _distort(eff: Effect, a: float, T: np.ndarray) -> np.ndarray:
    """(Out of library) measuring-device nonlinearity: a quadratic position distortion field
    ``dp_i = a x^T S_i x`` with ``x = (p - c) / radius`` (device frame = world frame)."""
    S = np.asarray(eff.shape["quadratic"])
    x = (T[:, :3, 3] - np.asarray(eff.shape["centre_mm"])) / eff.shape["radius_mm"]
    T = T.copy()
    T[:, :3, 3] += a * np.einsum("mj,ijk,mk->mi", x, S, x)
    return T


def true_poses(scn: Scenario, eff: Effect = NO_EFFECT, scale: float = 0.0) -> np.ndarray:
    """Noise-free tool poses ``(m, 4, 4)`` of the simulated arm with ``eff`` at ``scale``."""
    m = scn.m
    F = np.array(np.broadcast_to(scn.actual_frames, (m,) + scn.arm.frames.shape))
    M = scn.commanded_module_poses()
    if eff.name in _APPLY:
        F, M = _APPLY[eff.name](scn, eff, float(scale), F, M)
    elif eff.name not in ("none", "device_distortion"):
        raise ValueError(f"unknown effect {eff.name!r}")
    T = chain_poses(F, M)[0]
    if eff.name == "device_distortion":
        T = _distort(eff, float(scale), T)
    return T


def add_noise(scn: Scenario, T: np.ndarray) -> np.ndarray:
    """Measured poses: ``p + s_p n_p``, ``R -> exp(hat(s_r n_r)) R`` (world frame)."""
    z = scn.unit_noise
    out = T.copy()
    out[:, :3, 3] += scn.noise_pos_mm * z[:, :3]
    out[:, :3, :3] = _rot(scn.noise_rot_rad * z[:, 3:]) @ T[:, :3, :3]
    return out


# ----------------------------------------------------------------------------------------------
# Effect size: what a geometric calibration cannot absorb
# ----------------------------------------------------------------------------------------------

_GEOMETRIC_FIT: dict[int, Callable] = {}


def _geometric_fit():
    import equinox as eqx

    from cdra_jax import NoiseModel, calibrate_paper

    if 0 not in _GEOMETRIC_FIT:

        @eqx.filter_jit
        def fit(arm, q, T, sp, sr):
            sol = calibrate_paper(
                arm, q, T, NoiseModel(sp, sr), max_iterations=30, tol=1e-12, throw=False
            )
            return sol.cost, sol.frames, sol.result

        _GEOMETRIC_FIT[0] = fit
    return _GEOMETRIC_FIT[0]


def geometric_fit(
    scn: Scenario, T: np.ndarray, rows: np.ndarray | None = None
) -> tuple[float, np.ndarray]:
    """Geometry-only weighted fit (``calibrate_paper`` with the noise model) of poses ``T``.

    Args:
        scn: the scenario (states, noise level, model).
        T: ``(m, 4, 4)`` poses to fit.
        rows: fit only these poses (default all).

    Returns ``(unabsorbed_rms, calibrated_frames)``: the RMS over the ``6 m`` entries of the
    whitened residual (units of the noise) and the calibrated ``(K+1, 4, 4)`` frames.
    """
    import jax

    if not jax.config.jax_enable_x64:
        raise RuntimeError("enable float64 first: jax.config.update('jax_enable_x64', True)")
    rows = np.arange(scn.m) if rows is None else np.asarray(rows)
    cost, frames, _ = _geometric_fit()(
        scn.arm.arm, scn.q[rows], np.asarray(T)[rows], scn.noise_pos_mm, scn.noise_rot_rad
    )
    return float(np.sqrt(float(cost) / (6 * len(rows)))), np.asarray(frames)


def model_poses(scn: Scenario, frames: np.ndarray) -> np.ndarray:
    """Tool poses ``(m, 4, 4)`` of the geometric model with fixed transforms ``frames``."""
    F = np.broadcast_to(frames, (scn.m,) + frames.shape)
    return chain_poses(F, scn.commanded_module_poses())[0]


def geometric_heldout_dp(scn: Scenario, T: np.ndarray, folds: int = 2) -> float:
    """Cross-validated position deviation (Eq. 20, mm) of a geometry-only calibration.

    Poses are dealt to ``folds`` interleaved folds; each fold is predicted by the calibration
    on the others, and the RMS position error over all predictions is returned. On a clean
    recording this is the noise-only floor of the held-out ``delta_p``.
    """
    sq = np.empty(scn.m)
    idx = np.arange(scn.m)
    for f in range(folds):
        test = idx % folds == f
        _, frames = geometric_fit(scn, T, idx[~test])
        d = T[test, :3, 3] - model_poses(scn, frames)[test, :3, 3]
        sq[test] = np.sum(d * d, axis=-1)
    return float(np.sqrt(np.mean(sq)))


def unabsorbed_rms(scn: Scenario, eff: Effect, scale: float) -> float:
    """Unabsorbed RMS (units of the noise) of ``eff`` at ``scale`` on the noise-free recording."""
    return geometric_fit(scn, true_poses(scn, eff, scale))[0]


def calibrate_size(
    scn: Scenario, eff: Effect, size: float, *, rtol: float = 5e-3, max_evals: int = 30
) -> tuple[float, float]:
    """The parameter value at which ``eff`` leaves an unabsorbed RMS of ``size`` (noise units).

    Secant steps on ``log rms`` against ``log scale`` (the RMS is close to a power of the
    parameter), with bracketing bisection whenever a step leaves the bracket.

    Returns:
        ``(scale, achieved_rms)`` with ``|achieved / size - 1| <= rtol``.

    Raises:
        SizeError: the size is not reached within ``1e6`` times the typical parameter value.
    """
    if size <= 0:
        return 0.0, unabsorbed_rms(scn, eff, 0.0)
    pts: list[tuple[float, float]] = []
    lo: tuple[float, float] | None = None
    hi: tuple[float, float] | None = None
    x = math.log(eff.guess)
    target = math.log(size)
    for _ in range(max_evals):
        r = unabsorbed_rms(scn, eff, math.exp(x))
        if abs(r / size - 1.0) <= rtol:
            return math.exp(x), r
        lr = math.log(max(r, 1e-300))
        pts.append((x, lr))
        if lr < target and (lo is None or x > lo[0]):
            lo = (x, lr)
        if lr > target and (hi is None or x < hi[0]):
            hi = (x, lr)
        if len(pts) >= 2 and abs(pts[-1][0] - pts[-2][0]) > 1e-12:
            (x0, y0), (x1, y1) = pts[-2], pts[-1]
            slope = (y1 - y0) / (x1 - x0)
        else:
            slope = 1.0
        slope = slope if slope > 0.05 else 1.0
        nx = x + (target - lr) / slope
        if lo is not None and hi is not None and not (lo[0] < nx < hi[0]):
            nx = 0.5 * (lo[0] + hi[0])
        if nx > math.log(eff.guess) + math.log(1e6):
            raise SizeError(
                f"{eff.name} at {eff.location}: unabsorbed RMS {r:.3g} at {math.exp(x):.3g} "
                f"({eff.parameter}); size {size} not reachable"
            )
        x = nx
    raise SizeError(f"{eff.name} at {eff.location}: size search did not converge (last {r:.4g})")


# ----------------------------------------------------------------------------------------------
# Recordings and files
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Recording:
    """A generated recording: the scenario, the hidden truth and the measured poses.

    Attributes:
        scenario: poses, auxiliaries, geometric errors, noise draws.
        effect: the hidden effect (``NO_EFFECT`` for a clean recording).
        scale: its physical parameter (see ``effect.parameter``).
        size: the requested unabsorbed RMS (noise units); achieved_size: the one reached.
        true: ``(m, 4, 4)`` noise-free poses; measured: with noise.
    """

    scenario: Scenario
    effect: Effect
    scale: float
    size: float
    achieved_size: float
    true: np.ndarray
    measured: np.ndarray

    def truth(self) -> dict[str, Any]:
        """JSON-able ground truth (kept apart from the files given to the analyser)."""
        scn = self.scenario
        return {
            "effect": self.effect.name,
            "location": self.effect.location,
            "expected_effect": self.effect.expected_effect,
            "expected_location": self.effect.expected_location,
            "parameter": self.effect.parameter,
            "scale": self.scale,
            "size_requested": self.size,
            "size_achieved": self.achieved_size,
            "shape": dict(self.effect.shape),
            "m": scn.m,
            "noise_pos_mm": scn.noise_pos_mm,
            "noise_rot_rad": scn.noise_rot_rad,
            "geometric_errors": dict(
                zip(scn.arm.frame_names, np.asarray(scn.errors).tolist(), strict=True)
            ),
            "approach_dirs": [d.tolist() for d in scn.approach_dirs],
        }


def make_recording(
    scn: Scenario, eff: Effect = NO_EFFECT, size: float = 0.0, *, scale: float | None = None
) -> Recording:
    """Generate a recording of ``eff`` whose unabsorbed RMS is ``size`` x noise.

    Give ``scale`` instead to set the physical parameter directly.
    """
    if eff.name == "none":
        scale, achieved = 0.0, 0.0
    elif scale is None:
        scale, achieved = calibrate_size(scn, eff, size)
    else:
        achieved = unabsorbed_rms(scn, eff, scale)
    T = true_poses(scn, eff, scale)
    if eff.name == "none":
        achieved = geometric_fit(scn, T)[0]
    return Recording(
        scenario=scn,
        effect=eff,
        scale=float(scale),
        size=float(size),
        achieved_size=float(achieved),
        true=T,
        measured=add_noise(scn, T),
    )


def clean_twin(rec: Recording) -> Recording:
    """The same recording (poses, errors, noise draws) without the effect: the noise floor."""
    return make_recording(rec.scenario)


AUX_ORDER = ("time_s", "payload_kg")


def measurement_columns(arm: ArmData) -> tuple[str, ...]:
    """The CSV columns every recording carries, whatever its effect."""
    states = tuple(arm.arm.state_names)
    meas = ("measured.x", "measured.y", "measured.z", "measured.rx", "measured.ry", "measured.rz")
    approach = tuple(f"approach.{md.name}" for md in arm.modules)
    return ("pose", *states, *meas, *AUX_ORDER, *approach)


def write_recording(rec: Recording, folder: str | Path) -> tuple[Path, Path]:
    """Write the analyser's inputs: ``folder/model.toml`` (the nominal model, unchanged) and
    ``folder/measurements.csv`` (states, measured poses, ``time_s``, ``payload_kg``,
    ``approach.*``; no comments, nothing that names the effect). Returns both paths.
    """
    from cdra_jax.io import Measurements, save_measurements

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    scn = rec.scenario
    model = folder / "model.toml"
    model.write_text(scn.arm.model_text, encoding="utf-8")
    aux = {"time_s": scn.time_s, "payload_kg": scn.payload_kg}
    aux.update({f"approach.{k}": v for k, v in scn.approach.items()})
    meas = Measurements.from_arrays(scn.arm.arm, scn.q, rec.measured, aux=aux)
    data = folder / "measurements.csv"
    save_measurements(meas, data, force=True)
    return model, data


def effect_table(arm: ArmData) -> list[tuple[str, str]]:
    """Every (effect, location) pair the arm allows, in-library then out-of-library."""
    return [(e, loc) for e in ALL_EFFECTS for loc in arm.locations(e)]


def dataclass_replace(obj, **kw):
    """``dataclasses.replace`` (re-exported for the harness and tests)."""
    return dataclasses.replace(obj, **kw)


def spawn(seed: int | Sequence[int], *key: int) -> np.random.Generator:
    """A generator for the recording keyed by ``(seed, *key)`` (independent streams)."""
    base = [seed] if isinstance(seed, int) else list(seed)
    return np.random.default_rng(np.random.SeedSequence([*base, *key]))


# ----------------------------------------------------------------------------------------------
# Command line: one recording by hand, or the table of physical parameters per size
# ----------------------------------------------------------------------------------------------


def parameter_table(
    arm: ArmData,
    sizes: Sequence[float],
    m: int,
    *,
    noise_pos_mm: float = 0.08,
    noise_rot_rad: float = 1e-3,
    scenarios: int = 3,
    seed: int = 0,
) -> list[dict[str, Any]]:
    """Median physical parameter that gives each unabsorbed RMS, per effect and location."""
    rows = []
    for name, loc in effect_table(arm):
        eff = draw_effect(arm, name, spawn(seed, 1), loc)
        row: dict[str, Any] = {"effect": name, "location": loc, "parameter": eff.parameter}
        for size in sizes:
            vals = []
            for k in range(scenarios):
                scn = draw_scenario(
                    arm,
                    m,
                    spawn(seed, 2, k),
                    noise_pos_mm=noise_pos_mm,
                    noise_rot_rad=noise_rot_rad,
                )
                try:
                    vals.append(calibrate_size(scn, eff, size)[0])
                except SizeError:
                    vals.append(float("nan"))
            row[f"{size:g}"] = float(np.median(vals))
        rows.append(row)
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    import argparse
    import json
    import sys

    root = Path(__file__).resolve().parents[1]
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    import jax

    jax.config.update("jax_enable_x64", True)
    p = argparse.ArgumentParser(
        description="Write one concealed-effect recording, or the table "
        "of physical parameters per effect size."
    )
    p.add_argument("--model", type=Path, help="model TOML (default: the packaged CDRA)")
    p.add_argument("--effect", default="none", choices=("none", *ALL_EFFECTS))
    p.add_argument("--location", help="module / link / base (default: drawn at random)")
    p.add_argument("--size", type=float, default=3.0, help="unabsorbed RMS, units of the noise")
    p.add_argument("--poses", type=int, default=30)
    p.add_argument("--noise-pos", type=float, default=0.08)
    p.add_argument("--noise-rot", type=float, default=1e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, help="folder for model.toml, measurements.csv, truth.json")
    p.add_argument("--table", help="print the parameter table for these sizes, e.g. 1,3,5")
    a = p.parse_args(argv)
    if a.model is None:
        from cdra_jax.io import default_arm, default_model_text

        arm = arm_data(default_arm(), default_model_text())
    else:
        arm = load_arm_data(a.model)
    if a.table:
        sizes = [float(x) for x in a.table.split(",")]
        rows = parameter_table(
            arm, sizes, a.poses, noise_pos_mm=a.noise_pos, noise_rot_rad=a.noise_rot, seed=a.seed
        )
        print(f"| effect | location | parameter | {' | '.join(f'{s:g} x noise' for s in sizes)} |")
        print("|" + " --- |" * (3 + len(sizes)))
        for r in rows:
            vals = " | ".join(f"{r[f'{s:g}']:.3g}" for s in sizes)
            print(f"| {r['effect']} | {r['location']} | {r['parameter']} | {vals} |")
        return 0
    if a.out is None:
        p.error("--out is required to write a recording")
    rng = spawn(a.seed)
    scn = draw_scenario(arm, a.poses, rng, noise_pos_mm=a.noise_pos, noise_rot_rad=a.noise_rot)
    eff = draw_effect(arm, a.effect, spawn(a.seed, 7), a.location)
    rec = make_recording(scn, eff, a.size)
    model, data = write_recording(rec, a.out)
    (a.out / "truth.json").write_text(json.dumps(rec.truth(), indent=1) + "\n")
    print(
        f"{model}\n{data}\n{a.out / 'truth.json'}: {eff.name} at {eff.location}, "
        f"{eff.parameter} = {rec.scale:.4g}, unabsorbed RMS {rec.achieved_size:.3f} x noise"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
