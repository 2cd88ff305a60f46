"""A modular arm: K+1 fixed transforms interleaved with K modules (Eq. 1), and its kinematics.

The tool pose in the world frame is (Eq. 1, for the paper's K = 3)::

    T_OF = F_0 M_1(q_1) F_1 M_2(q_2) F_2 ... M_K(q_K) F_K

with ``F_j`` the fixed transforms (``frames``; for the CDRA ``base`` = T_OBs, ``upper_arm`` =
T_SBe, ``forearm`` = T_EBw, ``tool`` = T_WF) and ``M_i`` the module poses (``shoulder`` =
T_BsS, ``elbow`` = T_BeE, ``wrist`` = T_BwW), each a function of the module state. Nothing here
is specific to K = 3: a 6R industrial arm is the same chain with six revolute modules.

The joint state of the whole arm is one flat vector ``q`` of length ``arm.dof``: the module
states concatenated in chain order, spherical modules contributing their rotation vector
``(rx, ry, rz)`` (rad), revolute modules an angle (rad) and prismatic modules a displacement
(mm). ``arm.state_names`` gives the measurement-file column of each entry.

:func:`module_poses`, :func:`chain` and :func:`forward_kinematics` run as one compiled program
per arm structure and shape when called on concrete arrays (as the maps of :mod:`cdra_jax.lie`),
and are traced inline inside ``jit``, ``vmap`` or ``grad``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from . import lie
from .compilation import compiled_when_eager

ModuleKind = Literal["spherical", "revolute", "prismatic"]
MODULE_KINDS: tuple[str, ...] = ("spherical", "revolute", "prismatic")
_DOF = {"spherical": 3, "revolute": 1, "prismatic": 1}
TWIST_COMPONENTS: tuple[str, ...] = ("vx", "vy", "vz", "wx", "wy", "wz")


class Module(eqx.Module):
    """One module of the chain: a mechanism whose state sets the pose of its moving platform.

    Attributes:
        name: module name, e.g. ``"shoulder"``.
        kind: ``"spherical"`` (3-DOF rotation about the module origin, state = rotation vector),
            ``"revolute"`` (rotation by ``q`` rad about ``axis`` through the origin) or
            ``"prismatic"`` (translation by ``q`` mm along ``axis``).
        axis: unit axis ``(3,)`` in the module base frame (ignored for spherical modules).
        limits: per state entry ``(low, high)``, in rad or mm.
        cable_base: cable attachment points on the module base, ``(n, 3)`` mm, or ``None``.
        cable_platform: matching points on the moving platform, ``(n, 3)`` mm, or ``None``.
        cable_offset: per-cable length offset ``(n,)`` mm, or ``None`` (zero): a measured cable
            length is the straight-line attachment distance plus this offset (encoder zero,
            routing; see :mod:`cdra_jax.modules.cables`).
        mass: mass (kg) of the body the module moves, or ``None``.
        com: its centre of mass ``(3,)`` mm in the platform frame, or ``None``.
        pretension: cable pretension (N), or ``None``.
        stiffness: cable axial stiffness (N/mm), or ``None``.
    """

    name: str = eqx.field(static=True)
    kind: str = eqx.field(static=True)
    axis: Array
    limits: tuple[tuple[float, float], ...] = eqx.field(static=True)
    cable_base: Array | None = None
    cable_platform: Array | None = None
    cable_offset: Array | None = None
    mass: float | None = eqx.field(static=True, default=None)
    com: Array | None = None
    pretension: float | None = eqx.field(static=True, default=None)
    stiffness: float | None = eqx.field(static=True, default=None)

    def __check_init__(self) -> None:
        if self.kind not in MODULE_KINDS:
            raise ValueError(
                f"module {self.name!r}: unknown kind {self.kind!r}, expected one of {MODULE_KINDS}"
            )
        if len(self.limits) != _DOF[self.kind]:
            raise ValueError(
                f"module {self.name!r}: {self.kind} needs {_DOF[self.kind]} (low, high) limits, "
                f"got {len(self.limits)}"
            )
        for lo, hi in self.limits:
            if not (np.isfinite(lo) and np.isfinite(hi)):
                raise ValueError(
                    f"module {self.name!r}: limits must be finite (low, high) pairs, "
                    f"got ({lo}, {hi})"
                )
            if not lo < hi:
                raise ValueError(f"module {self.name!r}: limit low {lo} is not below high {hi}")
        if self.kind != "spherical" and not isinstance(self.axis, jax.core.Tracer):
            a = np.asarray(self.axis, dtype=float)
            if a.shape != (3,) or not np.all(np.isfinite(a)):
                raise ValueError(
                    f"module {self.name!r}: axis must be a finite 3-vector, got {self.axis!r}"
                )
            if abs(np.linalg.norm(a) - 1.0) > 1e-9:
                raise ValueError(
                    f"module {self.name!r}: axis must be a unit vector (norm "
                    f"{np.linalg.norm(a):.6g}); build the module with revolute() or "
                    "prismatic(), which normalise it"
                )
        if (self.cable_base is None) != (self.cable_platform is None):
            raise ValueError(f"module {self.name!r}: cables need both base and platform points")
        if self.cable_base is not None and self.cable_platform is not None:
            if np.shape(self.cable_base) != np.shape(self.cable_platform) or (
                np.ndim(self.cable_base) != 2 or np.shape(self.cable_base)[-1] != 3
            ):
                raise ValueError(
                    f"module {self.name!r}: cable points must both be (n, 3), got "
                    f"{np.shape(self.cable_base)} and {np.shape(self.cable_platform)}"
                )
        if self.cable_offset is not None:
            if self.cable_base is None:
                raise ValueError(f"module {self.name!r}: cable_offset given without cables")
            if np.shape(self.cable_offset) != (self.n_cables,):
                raise ValueError(
                    f"module {self.name!r}: cable_offset must be ({self.n_cables},), one per "
                    f"cable, got {np.shape(self.cable_offset)}"
                )

    @property
    def dof(self) -> int:
        """Number of state entries (3 for spherical, 1 otherwise)."""
        return _DOF[self.kind]

    @property
    def state_names(self) -> tuple[str, ...]:
        """Measurement-file columns of the state: ``<name>.rx/.ry/.rz`` or ``<name>.q``."""
        if self.kind == "spherical":
            return tuple(f"{self.name}.{c}" for c in ("rx", "ry", "rz"))
        return (f"{self.name}.q",)

    @property
    def n_cables(self) -> int:
        """Number of cables (0 when the model gives none)."""
        return 0 if self.cable_base is None else int(np.shape(self.cable_base)[0])

    def pose(self, q: ArrayLike) -> Array:
        """Platform pose in the module base frame: ``(..., dof) -> (..., 4, 4)``."""
        q = jnp.asarray(q)
        if q.shape[-1] != self.dof:
            raise ValueError(
                f"module {self.name!r} ({self.kind}) takes {self.dof} state entries, "
                f"got trailing dimension {q.shape[-1]}"
            )
        rotation, translation = self._motion(q)
        return lie.make_pose(lie.so3_exp(rotation), translation)

    def _motion(self, q: Array, axis: Array | None = None) -> tuple[Array, Array]:
        """The platform's rotation vector and translation (mm) at state ``q (..., dof)``: a
        spherical module turns by ``q``, a revolute one by ``q`` about its axis (``axis``, or
        the module's own), a prismatic one moves by ``q`` along it (its rotation vector zero:
        ``so3_exp`` of zero is exactly the identity)."""
        axis = jnp.asarray(self.axis if axis is None else axis, dtype=q.dtype)
        zeros3 = jnp.zeros(q.shape[:-1] + (3,), dtype=q.dtype)
        if self.kind == "spherical":
            return q, zeros3
        if self.kind == "revolute":
            return q * axis, zeros3
        return zeros3, q * axis


def spherical(
    name: str, limits: Sequence[tuple[float, float]] = ((-1.0, 1.0),) * 3, **kwargs
) -> Module:
    """A 3-DOF spherical module (state: rotation vector, rad)."""
    return Module(name=name, kind="spherical", axis=jnp.zeros(3), limits=_limits(limits), **kwargs)


def revolute(
    name: str, axis: ArrayLike, limits: tuple[float, float] = (-np.pi, np.pi), **kwargs
) -> Module:
    """A 1-DOF revolute module about ``axis`` (state: angle, rad)."""
    return Module(
        name=name, kind="revolute", axis=_unit(axis, name), limits=_limits([limits]), **kwargs
    )


def prismatic(
    name: str, axis: ArrayLike, limits: tuple[float, float] = (-100.0, 100.0), **kwargs
) -> Module:
    """A 1-DOF prismatic module along ``axis`` (state: displacement, mm)."""
    return Module(
        name=name, kind="prismatic", axis=_unit(axis, name), limits=_limits([limits]), **kwargs
    )


def _limits(limits: Sequence[Sequence[float]]) -> tuple[tuple[float, float], ...]:
    return tuple((float(lo), float(hi)) for lo, hi in limits)


def _unit(axis: ArrayLike, name: str) -> Array:
    a = np.asarray(axis, dtype=float)
    n = np.linalg.norm(a)
    if a.shape != (3,) or not np.isfinite(n) or n < 1e-12:
        raise ValueError(f"module {name!r}: axis must be a finite non-zero 3-vector, got {axis!r}")
    return jnp.asarray(a / n)


@dataclasses.dataclass(frozen=True)
class Marker:
    """A measured point on the tool (a laser-tracker reflector, a motion-capture marker).

    Attributes:
        name: the marker's name; its measurement columns are ``measured.<name>.x/y/z``.
        xyz: position in the tool frame (the frame after the last fixed transform), mm.
        calibrate: whether the position is only roughly known and is identified with the
            frames (``True``), or known (``False``, the default).
    """

    name: str
    xyz: tuple[float, float, float]
    calibrate: bool = False

    def __post_init__(self) -> None:
        xyz = tuple(float(v) for v in self.xyz)
        if len(xyz) != 3 or not all(np.isfinite(xyz)):
            raise ValueError(
                f"marker {self.name!r}: xyz must be 3 finite numbers (mm), got {self.xyz!r}"
            )
        object.__setattr__(self, "xyz", xyz)


@dataclasses.dataclass(frozen=True)
class EffectRecord:
    """A non-geometric effect of the model (a ``[[effects]]`` entry of the model file), as plain
    data: which effect of the physics vocabulary (:mod:`cdra_jax.physics`), where, which
    variant, and the values of its named parameters with their units.

    The arm only carries the records; :func:`cdra_jax.physics.model_effects` turns them into
    the vocabulary's effects and a parameter vector, and checks names, locations and units.

    Attributes:
        name: the effect's vocabulary name, e.g. ``"periodic_error"``.
        location: the module or frame it sits at, e.g. ``"elbow"``.
        variant: which form of the effect, e.g. ``"k=1"`` (``""``: the vocabulary's first).
        parameters: ``(name, value, unit)`` per parameter, in the effect's order, e.g.
            ``(("q_sin1", 0.002, "rad"), ("q_cos1", -0.001, "rad"))``.
    """

    name: str
    location: str
    variant: str = ""
    parameters: tuple[tuple[str, float, str], ...] = ()

    def __post_init__(self) -> None:
        params = []
        for p in self.parameters:
            if len(p) != 3:
                raise ValueError(
                    f"effect {self.label}: each parameter must be (name, value, unit), got {p!r}"
                )
            name, value, unit = p
            value = float(value)
            if not np.isfinite(value):
                raise ValueError(f"effect {self.label}: parameter {name!r} is not finite: {value}")
            params.append((str(name), value, str(unit)))
        names = [p[0] for p in params]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"effect {self.label}: parameter names repeated: {dup}")
        object.__setattr__(self, "parameters", tuple(params))

    @property
    def label(self) -> str:
        """``"<effect>@<location>"`` with the variant in brackets when there is one."""
        return f"{self.name}@{self.location}" + (f" ({self.variant})" if self.variant else "")

    @property
    def values(self) -> tuple[float, ...]:
        """The parameter values in order."""
        return tuple(p[1] for p in self.parameters)

    def with_values(self, values: Sequence[float]) -> EffectRecord:
        """The same effect with other parameter values (names and units kept)."""
        values = [float(v) for v in values]
        if len(values) != len(self.parameters):
            raise ValueError(
                f"effect {self.label}: {len(self.parameters)} parameters, got {len(values)} values"
            )
        return dataclasses.replace(
            self,
            parameters=tuple(
                (n, v, u) for (n, _, u), v in zip(self.parameters, values, strict=True)
            ),
        )


class Arm(eqx.Module):
    """A modular arm: ``frames[0] M_1 frames[1] ... M_K frames[K]`` (Eq. 1).

    Attributes:
        frames: the K+1 fixed transforms, ``(K+1, 4, 4)``, mm.
        modules: the K modules, module i sitting between ``frames[i]`` and ``frames[i+1]``.
        frame_names: names of the fixed transforms (``base``, ``upper_arm``, ...).
        name, description: free text.
        gravity: gravity vector in the world frame, m/s^2.
        markers: measured points on the tool (:class:`Marker`), in the order of the model file.
        effects: non-geometric physics of the model (:class:`EffectRecord`, the model file's
            ``[[effects]]``), in file order; evaluated by :mod:`cdra_jax.physics`. The
            geometric chain here (:func:`tool_pose`) ignores them; every command predicts with
            :func:`cdra_jax.physics.model_tool_pose`, which adds them.
    """

    frames: Array
    modules: tuple[Module, ...]
    frame_names: tuple[str, ...] = eqx.field(static=True)
    name: str = eqx.field(static=True, default="arm")
    description: str = eqx.field(static=True, default="")
    gravity: Array = eqx.field(default_factory=lambda: jnp.array([0.0, 0.0, -9.81]))
    markers: tuple[Marker, ...] = eqx.field(static=True, default=())
    effects: tuple[EffectRecord, ...] = eqx.field(static=True, default=())

    def __check_init__(self) -> None:
        k = len(self.modules)
        if k < 1:
            raise ValueError("an arm needs at least one module")
        if tuple(np.shape(self.frames)[-3:]) != (k + 1, 4, 4):
            raise ValueError(
                f"arm {self.name!r}: {k} modules need {k + 1} fixed frames of shape (4, 4), "
                f"got frames of shape {np.shape(self.frames)}"
            )
        if len(self.frame_names) != k + 1:
            raise ValueError(f"arm {self.name!r}: need {k + 1} frame names, got {self.frame_names}")
        names = list(self.frame_names) + [m.name for m in self.modules]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"arm {self.name!r}: frame and module names must be unique: {dup}")
        marker_names = [m.name for m in self.markers]
        dup = sorted({n for n in marker_names if marker_names.count(n) > 1})
        if dup:
            raise ValueError(f"arm {self.name!r}: marker names must be unique: {dup}")
        for e in self.effects:
            if not isinstance(e, EffectRecord):
                raise ValueError(f"arm {self.name!r}: effects must be EffectRecord, got {e!r}")
        keys = [(e.name, e.location, e.variant) for e in self.effects]
        dup = sorted(
            {e.label for e, k in zip(self.effects, keys, strict=True) if keys.count(k) > 1}
        )
        if dup:
            raise ValueError(f"arm {self.name!r}: an effect is given twice: {dup}")

    def marker(self, name: str) -> Marker:
        """The marker called ``name`` (``ValueError`` naming the declared ones otherwise)."""
        for m in self.markers:
            if m.name == name:
                return m
        known = ", ".join(m.name for m in self.markers) or "none"
        raise ValueError(f"arm {self.name!r} has no marker {name!r}; markers: {known}")

    def with_markers(self, markers: Sequence[Marker]) -> Arm:
        """The same arm with other markers (e.g. calibrated positions)."""
        return dataclasses.replace(self, markers=tuple(markers))

    def with_marker_positions(self, positions: Mapping[str, ArrayLike]) -> Arm:
        """The same arm with the named markers at other positions ``{name: (3,)}`` (mm, tool
        frame), e.g. calibrated ones; the other markers and every ``calibrate`` flag unchanged.
        """
        unknown = sorted(set(positions) - {mk.name for mk in self.markers})
        if unknown:
            raise ValueError(f"arm {self.name!r} has no marker(s) {unknown}")
        out = []
        for mk in self.markers:
            if mk.name in positions:
                v = np.asarray(positions[mk.name], dtype=float).reshape(3)
                mk = dataclasses.replace(mk, xyz=(float(v[0]), float(v[1]), float(v[2])))
            out.append(mk)
        return self.with_markers(out)

    def with_effects(self, effects: Sequence[EffectRecord]) -> Arm:
        """The same arm with other effect records (e.g. refitted values, or ``()``: the
        geometric model alone)."""
        return dataclasses.replace(self, effects=tuple(effects))

    @property
    def dof(self) -> int:
        """Total number of state entries (7 for the CDRA)."""
        return sum(m.dof for m in self.modules)

    @property
    def module_names(self) -> tuple[str, ...]:
        return tuple(m.name for m in self.modules)

    @property
    def state_names(self) -> tuple[str, ...]:
        """Column name of each entry of the flat joint state."""
        return tuple(n for m in self.modules for n in m.state_names)

    @property
    def n_params(self) -> int:
        """Number of calibration parameters, ``6 (K + 1)`` (Eq. 8: 24 for the CDRA)."""
        return 6 * len(self.frame_names)

    @property
    def param_names(self) -> tuple[str, ...]:
        """Calibration parameter names ``<frame>.<vx|vy|vz|wx|wy|wz>`` in the order of X (Eq. 8)."""
        return tuple(f"{f}.{c}" for f in self.frame_names for c in TWIST_COMPONENTS)

    @property
    def state_limits(self) -> np.ndarray:
        """``(dof, 2)`` lower and upper bound of each state entry."""
        return np.array([lim for m in self.modules for lim in m.limits], dtype=float)

    def module(self, name: str) -> Module:
        """The module called ``name`` (``ValueError`` naming the known ones otherwise)."""
        for m in self.modules:
            if m.name == name:
                return m
        raise ValueError(f"arm {self.name!r} has no module {name!r}; modules: {self.module_names}")

    def frame_index(self, name: str) -> int:
        """Position of the fixed frame ``name`` in the chain."""
        if name not in self.frame_names:
            raise ValueError(f"arm {self.name!r} has no frame {name!r}; frames: {self.frame_names}")
        return self.frame_names.index(name)

    def split_state(self, q: ArrayLike) -> list[Array]:
        """Split a flat state ``(..., dof)`` into the per-module states."""
        q = jnp.asarray(q)
        if q.shape[-1] != self.dof:
            raise ValueError(
                f"arm {self.name!r} has {self.dof} state entries {self.state_names}, "
                f"got trailing dimension {q.shape[-1]}"
            )
        out, i = [], 0
        for m in self.modules:
            out.append(q[..., i : i + m.dof])
            i += m.dof
        return out

    def with_frames(self, frames: ArrayLike) -> Arm:
        """The same arm with other fixed transforms ``(K+1, 4, 4)``.

        The shape is checked as in the constructor (``eqx.tree_at`` skips ``__check_init__``):
        with too few frames, indexing under ``jit`` would clamp and reuse the last one.
        """
        frames = jnp.asarray(frames)
        k = len(self.modules)
        if tuple(frames.shape[-3:]) != (k + 1, 4, 4):
            raise ValueError(
                f"arm {self.name!r}: with_frames needs {k + 1} fixed frames of shape (4, 4) "
                f"for {k} modules, got frames of shape {frames.shape}"
            )
        return eqx.tree_at(lambda a: a.frames, self, frames)


def module_axes(arm: Arm, dtype=None) -> Array:
    """The modules' axes ``(K, 3)`` (a spherical module's is unused)."""
    return jnp.stack([jnp.asarray(m.axis, dtype) for m in arm.modules])


@compiled_when_eager
def module_poses(arm: Arm, q: ArrayLike, axes: ArrayLike | None = None) -> Array:
    """Module platform poses ``(..., K, 4, 4)`` from the flat state ``q (..., dof)``
    (:meth:`Module.pose` of each module, the exponentials of all modules in one call: traced
    and compiled once, not once per module). ``axes (K, 3)``: the modules' axes as an array of
    the caller's (:func:`module_axes`; the solvers take them as an argument, so that they read
    nothing but the arm's structure), default the arm's own."""
    q = jnp.asarray(q)
    per_module = [None] * len(arm.modules) if axes is None else list(jnp.unstack(jnp.asarray(axes)))
    states = arm.split_state(q)
    motions = [m._motion(qi, a) for m, qi, a in zip(arm.modules, states, per_module, strict=True)]
    rotation = jnp.stack([r for r, _ in motions], -2)
    translation = jnp.stack([p for _, p in motions], -2)
    return lie.make_pose(lie.so3_exp(rotation), translation)


@compiled_when_eager
def chain(frames: ArrayLike, poses: ArrayLike) -> tuple[Array, Array]:
    """Product of Eq. 1 from fixed frames and module poses.

    Args:
        frames: ``(..., K+1, 4, 4)`` fixed transforms.
        poses: ``(..., K, 4, 4)`` module platform poses.

    Returns:
        ``(tool, after)``: the tool pose ``(..., 4, 4)`` in the world frame and the world pose
        after each module ``(..., K, 4, 4)`` (T_OS, T_OE, T_OW of Eq. 4 for the CDRA).
    """
    frames = jnp.asarray(frames)
    poses = jnp.asarray(poses)
    k = poses.shape[-3]
    T = frames[..., 0, :, :]
    after = []
    for i in range(k):
        T = T @ poses[..., i, :, :]
        after.append(T)
        T = T @ frames[..., i + 1, :, :]
    return T, jnp.stack(after, axis=-3)


@compiled_when_eager
def forward_kinematics(arm: Arm, q: ArrayLike) -> tuple[Array, Array]:
    """Tool pose and the pose after each module for states ``q (..., dof)`` (Eqs. 1 and 4).

    Returns:
        ``(tool, after)`` with ``tool (..., 4, 4)`` the world pose of the tool frame (T_OF) and
        ``after (..., K, 4, 4)`` the world pose after each module (T_OS, T_OE, T_OW).
    """
    return chain(arm.frames, module_poses(arm, q))


def tool_pose(arm: Arm, q: ArrayLike) -> Array:
    """World pose of the tool frame, ``(..., 4, 4)`` (Eq. 1)."""
    return forward_kinematics(arm, q)[0]


def apply_frame_errors(arm: Arm, errors: ArrayLike) -> Arm:
    """Left-multiply each fixed frame by the exponential of its error twist (Eqs. 11-14).

    ``errors`` is the flat parameter vector ``X (6 (K+1),)`` of Eq. 8 (ordered as
    ``arm.param_names``) or ``(K+1, 6)``; ``F_j -> exp(hat(X_j)) F_j``.
    """
    X = jnp.asarray(errors)
    # Only the two documented layouts: a (6, K+1) array has the right size but, reshaped,
    # pairs the wrong numbers.
    if X.shape not in ((arm.n_params,), (len(arm.frame_names), 6)):
        raise ValueError(
            f"arm {arm.name!r} has {arm.n_params} error parameters, a (v, w) twist for each "
            f"frame of {arm.frame_names}: pass ({arm.n_params},) or "
            f"({len(arm.frame_names)}, 6), got errors of shape {X.shape}"
        )
    return arm.with_frames(moved_frames(arm.frames, X))


def moved_frames(frames: ArrayLike, errors: ArrayLike) -> Array:
    """The fixed frames moved by their error twists, ``F_j -> exp(hat(X_j)) F_j`` (Eqs. 11-14).

    Args:
        frames: ``(K+1, 4, 4)`` fixed transforms (mm).
        errors: ``(K+1, 6)`` twists ``(v, w)`` (mm, rad), or the flat ``(6 (K+1),)`` of Eq. 8.

    Returns:
        ``(K+1, 4, 4)``, in the promoted dtype of the two. :func:`apply_frame_errors` is the
        same on an :class:`Arm`; :func:`cdra_jax.calibration.kernels.step_frames` the same
        product written for the solvers' batched loops.
    """
    F = jnp.asarray(frames)
    X = jnp.asarray(errors).reshape(F.shape[-3], 6)
    return lie.se3_exp(X) @ F


def frame_errors(calibrated: Arm, nominal: Arm) -> Array:
    """Error twists of the calibrated frames w.r.t. the nominal ones (Eqs. 15-18): ``(K+1, 6)``."""
    return error_twists(calibrated.frames, nominal.frames)


@compiled_when_eager
def error_twists(frames: ArrayLike, reference: ArrayLike) -> Array:
    """The identified error of each frame, ``dt_j = log(F_j F_j,ref^-1)^v`` (Eqs. 15-18): the
    left-multiplied twist that moves the reference frame onto the frame (``F = exp(dt^) F_ref``,
    Eqs. 11-14). ``(..., K+1, 4, 4)`` twice -> ``(..., K+1, 6)``, ``(v [mm], w [rad])``; the one
    implementation of this formula in the package. One compiled program when called on concrete
    arrays (:func:`cdra_jax.compilation.compiled_when_eager`)."""
    return lie.se3_log(jnp.asarray(frames) @ lie.inverse(jnp.asarray(reference)))


def sample_states(key: Array, arm: Arm, m: int, dtype=None) -> Array:
    """``m`` module states drawn uniformly within each state entry's limits: ``(m, dof)``.

    Spherical modules are sampled per rotation-vector component within their box limits.
    """
    lim = jnp.asarray(arm.state_limits, dtype=dtype or jnp.asarray(arm.frames).dtype)
    u = jax.random.uniform(key, (m, arm.dof), dtype=lim.dtype)
    return lim[:, 0] + u * (lim[:, 1] - lim[:, 0])
