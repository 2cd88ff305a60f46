"""The candidate physics vocabulary (design.md): seven effects, each a few physical parameters.

Each effect maps the recorded data to per-pose corrections linear in its parameters (see
:mod:`.base`); the tool pose is then the exact product of exponentials. Conventions: module
states as in :mod:`cdra_jax.arm`; a module-platform rotation is left-multiplied in the module
base frame, the frame of :mod:`cdra_jax.modules` (torques, structure matrix, length Jacobian).

==================  ==============  ====================================================  ======
effect              location        correction                                            params
==================  ==============  ====================================================  ======
joint_compliance    module          platform rotation ``c tau`` (spherical), about the    1 / 2
                                    axis ``c_a (a.tau)`` and across it ``c_t tau_perp``
                                    (revolute, prismatic); ``tau``: gravity torque
cable_elasticity    module          state change ``c J^+ t``: stretch ``c t`` of each     1
                                    cable (``t``: holding tensions), least squares over
                                    the cables (``J``: length Jacobian)
cable_scale         module          ``s J^+ (l(q) - l(0))``: lengths paid out from home   1
                                    off by the factor ``1 + s`` (drum radius error)
backlash            module          ``q - approach * b``: lag of ``b`` per state entry    dof
                                    against the last motion
periodic_error      module          ``sum_k a_k sin(k q) + b_k cos(k q)`` per state       2 H dof
                                    entry, harmonics ``k = 1 .. H``
link_bending        inner frame     cantilever tip deflection under gravity,              1
                                    ``c = 1/(EI)`` (:mod:`.loads`)
thermal_drift       base            mount moved by ``v t`` and turned by ``w t``          6
==================  ==============  ====================================================  ======
"""

from __future__ import annotations

from collections.abc import Mapping

import jax.numpy as jnp
from jax import Array

from ..arm import Arm, Module
from ..modules.cables import cable_lengths, length_jacobian
from ..modules.statics import distribute_tensions, gravity_loads, gravity_torques, module_floor
from ..modules.tension import structure_matrix
from .base import Aux, Effect, Features, ParameterSpec
from .loads import bending_deflection

PAYLOAD = "payload_kg"
TIME = "time_s"


def _module_index(arm: Arm, name: str) -> int:
    if name not in arm.module_names:
        raise ValueError(f"arm {arm.name!r} has no module {name!r}; modules: {arm.module_names}")
    return arm.module_names.index(name)


def _state_slice(arm: Arm, i: int) -> slice:
    start = sum(m.dof for m in arm.modules[:i])
    return slice(start, start + arm.modules[i].dof)


def _payload(aux: Aux, q: Array) -> Array:
    if PAYLOAD in aux:
        return jnp.asarray(aux[PAYLOAD], q.dtype)
    return jnp.zeros(q.shape[:-1], q.dtype)


def _distal_mass(arm: Arm, i: int) -> float:
    return float(sum(m.mass or 0.0 for m in arm.modules[i:]))


def _rotation_twist(w: Array) -> Array:
    """``(..., 3, p)`` rotation columns -> ``(..., 6, p)`` twists with zero translation."""
    return jnp.concatenate([jnp.zeros_like(w), w], axis=-2)


def _module_step_features(
    arm: Arm, q: Array, i: int, step: Array, *, spherical_as_twist: bool = True
) -> Features:
    """Features of one module-state increment ``step (m, dof_i, p)``.

    For spherical modules the increment is a left-multiplied rotation of the platform (the
    convention of the length Jacobian and the torques); for the others it adds to the state.
    """
    m, p = q.shape[0], step.shape[-1]
    f = Features.zeros(arm, m, p, q.dtype)
    if arm.modules[i].kind == "spherical" and spherical_as_twist:
        tw = f.module_twist.at[:, i].set(_rotation_twist(step))
        return Features(f.state, tw, f.frame_deflection)
    st = f.state.at[:, _state_slice(arm, i)].set(step)
    return Features(st, f.module_twist, f.frame_deflection)


def _fmt(v: float) -> str:
    return f"{v:.3g}"


def _interval(values: Mapping[str, tuple[float, float, float]], name: str, unit: str) -> str:
    v, lo, hi = values[name]
    return f"{_fmt(v)} {unit} ({_fmt(lo)} to {_fmt(hi)})"


class ModuleEffect(Effect):
    """An effect located at a module (``shoulder``, ``elbow``, ``wrist`` for the CDRA)."""

    def locations(self, arm: Arm) -> tuple[str, ...]:
        return arm.module_names

    def module(self, arm: Arm, location: str) -> tuple[int, Module]:
        i = _module_index(arm, location)
        return i, arm.modules[i]


class JointCompliance(ModuleEffect):
    """Rotational deflection of a module's platform proportional to the gravity torque."""

    name = "joint_compliance"
    needs = "masses (mass, com of the modules' bodies)"
    summary = "rotational deflection of a module proportional to the gravity load it carries"
    MAX = 1e-5  # rad/(N mm): 33 mrad under the ~3.3 N m the CDRA shoulder carries

    def parameters(self, arm, location):
        _, mod = self.module(arm, location)
        if mod.kind == "spherical":
            return (
                ParameterSpec(
                    "compliance",
                    "rad/(N*mm)",
                    0.0,
                    self.MAX,
                    "platform rotation per unit gravity torque (isotropic)",
                ),
            )
        return (
            ParameterSpec(
                "compliance_axial", "rad/(N*mm)", 0.0, self.MAX, "rotation about the joint axis"
            ),
            ParameterSpec(
                "compliance_transverse",
                "rad/(N*mm)",
                0.0,
                self.MAX,
                "rotation across the joint axis (hinge bending)",
            ),
        )

    def missing(self, arm, location, aux_names):
        i, _ = self.module(arm, location)
        if _distal_mass(arm, i) <= 0.0 and PAYLOAD not in aux_names:
            return f"no mass distal to module {location!r} in the model and no payload_kg column"
        return None

    def features(self, arm, q, aux, location):
        i, mod = self.module(arm, location)
        tau = gravity_torques(arm, q, _payload(aux, q))[:, i, :]  # (m, 3) N mm, base frame
        if mod.kind == "spherical":
            cols = tau[..., None]
        else:
            a = jnp.asarray(mod.axis, q.dtype)
            along = jnp.einsum("mi,i->m", tau, a)[:, None] * a
            cols = jnp.stack([along, tau - along], axis=-1)
        f = Features.zeros(arm, q.shape[0], cols.shape[-1], q.dtype)
        tw = f.module_twist.at[:, i].set(_rotation_twist(cols))
        return Features(f.state, tw, f.frame_deflection)

    def describe(self, location, values):
        parts = [f"{n.replace('_', ' ')} {_interval(values, n, 'rad/(N*mm)')}" for n in values]
        return f"the {location} module deflects under the gravity load it carries: " + "; ".join(
            parts
        )


class _CableEffect(ModuleEffect):
    def missing(self, arm, location, aux_names):
        _, mod = self.module(arm, location)
        if not mod.n_cables:
            return f"module {location!r} has no cables in the model"
        return None


class CableElasticity(_CableEffect):
    """Cable stretch ``c t`` (``t``: tensions holding the arm) mapped to a module-state change."""

    name = "cable_elasticity"
    needs = "cables, masses (tensions from the statics), pretension"
    summary = "cable stretch proportional to tension (pretension plus gravity load)"

    def parameters(self, arm, location):
        _, mod = self.module(arm, location)
        high = 10.0 / mod.stiffness if mod.stiffness else 1.0
        return (
            ParameterSpec(
                "axial_compliance",
                "mm/N",
                0.0,
                high,
                "cable stretch per newton of tension (1/stiffness); plausible up to 10x the "
                "model's 1/stiffness",
            ),
        )

    def missing(self, arm, location, aux_names):
        reason = super().missing(arm, location, aux_names)
        if reason:
            return reason
        i, mod = self.module(arm, location)
        if _distal_mass(arm, i) <= 0.0 and not mod.pretension and PAYLOAD not in aux_names:
            return f"module {location!r}: no masses, payload or pretension, so no cable tension"
        return None

    def features(self, arm, q, aux, location):
        i, mod = self.module(arm, location)
        qi = arm.split_state(q)[i]
        # The tensions holding the arm (cdra_jax.modules.statics.holding_tensions), for this
        # module only: min-norm tensions above the pretension floor balancing its gravity load.
        load = arm.split_state(gravity_loads(arm, q, _payload(aux, q)))[i]
        t = distribute_tensions(structure_matrix(mod, qi), -load, module_floor(mod)).tensions
        J = length_jacobian(mod, qi)  # (m, n, dof)
        step = _lstsq(J, t)
        return _module_step_features(arm, q, i, step[..., None])

    def describe(self, location, values):
        v, lo, hi = values["axial_compliance"]
        stiff = f"; stiffness {_fmt(1 / v)} N/mm" if v > 0 else ""
        return (
            f"the {location} module's cables stretch under load: axial compliance "
            f"{_interval(values, 'axial_compliance', 'mm/N')}{stiff}"
        )


def _lstsq(J: Array, b: Array) -> Array:
    """Least-squares state increment ``J^+ b``: ``J (m, n, d)``, ``b (m, n)`` -> ``(m, d)``."""
    JtJ = jnp.einsum("mni,mnj->mij", J, J)
    Jtb = jnp.einsum("mni,mn->mi", J, b)
    return jnp.linalg.solve(JtJ, Jtb[..., None])[..., 0]


class CableScale(_CableEffect):
    """Winch drum radius error: cable lengths off by a factor ``1 + s``.

    Variants: ``"from_home"`` (default), the length paid out from the home state (zero state)
    is off, ``l(q) -> l(q) + s (l(q) - l(0))``, as for a winch zeroed at home; ``"absolute"``,
    the whole length is off, ``l(q) -> (1 + s) l(q)``, as for lengths counted from the drum's
    zero.
    """

    name = "cable_scale"
    needs = "cables"
    summary = "winch/drum radius error: cable lengths off by a factor from home"

    def __init__(self, form: str = "from_home"):
        if form not in ("from_home", "absolute"):
            raise ValueError(f"cable_scale form must be 'from_home' or 'absolute', got {form!r}")
        self.form = form
        self.variant = form

    def parameters(self, arm, location):
        return (
            ParameterSpec(
                "scale_error",
                "1",
                -0.05,
                0.05,
                "relative error of the length paid out from home (drum radius error)",
            ),
        )

    def features(self, arm, q, aux, location):
        i, mod = self.module(arm, location)
        qi = arm.split_state(q)[i]
        dl = cable_lengths(mod, qi)  # (m, n) mm
        if self.form == "from_home":
            dl = dl - cable_lengths(mod, jnp.zeros_like(qi))
        step = _lstsq(length_jacobian(mod, qi), dl)
        return _module_step_features(arm, q, i, step[..., None])

    def describe(self, location, values):
        v = values["scale_error"][0]
        return (
            f"the {location} module's cable lengths are off by a factor (winch drum radius): "
            f"scale error {_interval(values, 'scale_error', '')} ({100 * v:+.2f} %)"
        )


class Backlash(ModuleEffect):
    """A lag ``b`` against the approach direction.

    Two forms (variants) for spherical modules, which differ by the left Jacobian of SO(3) at
    large rotations: ``"state"``, an offset of the recorded state entries, ``q - approach * b``
    (rotation-vector components); ``"rotation"``, a rotation ``exp(-approach * hat(b))`` of the
    platform about the module base axes. For revolute and prismatic modules they coincide and
    only ``"state"`` is used.
    """

    name = "backlash"
    needs = "approach.<module> column"
    summary = "offset whose sign follows the approach direction"

    def __init__(self, form: str = "state"):
        if form not in ("state", "rotation"):
            raise ValueError(f"backlash form must be 'state' or 'rotation', got {form!r}")
        self.form = form
        self.variant = form

    def parameters(self, arm, location):
        _, mod = self.module(arm, location)
        unit = "mm" if mod.kind == "prismatic" else "rad"
        high = 1.0 if mod.kind == "prismatic" else 0.02
        return tuple(
            ParameterSpec(
                f"half_band_{s.split('.')[-1]}",
                unit,
                -high,
                high,
                f"lag of {s} behind the command against the last motion (half the dead band)",
            )
            for s in mod.state_names
        )

    def missing(self, arm, location, aux_names):
        _, mod = self.module(arm, location)
        if self.form == "rotation" and mod.kind != "spherical":
            return f"the rotation form is the state form for a {mod.kind} module"
        if f"approach.{location}" not in aux_names:
            return f"no approach.{location} column in the measurements"
        return None

    def features(self, arm, q, aux, location):
        i, mod = self.module(arm, location)
        s = -jnp.asarray(aux[f"approach.{location}"], q.dtype)  # (m,)
        step = s[:, None, None] * jnp.eye(mod.dof, dtype=q.dtype)
        return _module_step_features(arm, q, i, step, spherical_as_twist=self.form == "rotation")

    def describe(self, location, values):
        unit = "rad"
        parts = [f"{n.removeprefix('half_band_')} {_interval(values, n, unit)}" for n in values]
        return f"the {location} module has backlash (half band per state entry): " + "; ".join(
            parts
        )


class PeriodicError(ModuleEffect):
    """A transmission error periodic in each module angle: ``a sin(k q) + b cos(k q)``.

    The periods are those of the joint angle itself (``2 pi / k``): a once-per-revolution error
    (eccentric drum, pulley or encoder, ``k = 1``) and its overtones (ellipticity ``k = 2``,
    a 3- to 6-lobed bearing or gear). The vocabulary tries each ``k = 1 .. 6`` as a variant
    (one harmonic at a time keeps the model from absorbing any smooth joint error; the
    variants are Bonferroni-corrected). Over the CDRA's 2 rad joint ranges higher orders put
    too few of a few dozen poses into each period to be told from noise.
    """

    name = "periodic_error"
    needs = "joint coordinates"
    summary = "transmission error periodic in a module angle"

    def __init__(self, harmonics: tuple[int, ...] = (1,)):
        self.harmonics = tuple(int(h) for h in harmonics)
        if not self.harmonics or min(self.harmonics) < 1:
            raise ValueError(f"harmonics must be positive integers, got {harmonics!r}")
        self.variant = "k=" + ",".join(map(str, self.harmonics))

    def parameters(self, arm, location):
        _, mod = self.module(arm, location)
        unit = "mm" if mod.kind == "prismatic" else "rad"
        out = []
        for s in mod.state_names:
            c = s.split(".")[-1]
            for k in self.harmonics:
                for fn in ("sin", "cos"):
                    out.append(
                        ParameterSpec(
                            f"{c}_{fn}{k}",
                            unit,
                            -0.01,
                            0.01,
                            f"amplitude of {fn}({k} {s}) in the state error of {s}",
                        )
                    )
        return tuple(out)

    def features(self, arm, q, aux, location):
        i, mod = self.module(arm, location)
        qi = arm.split_state(q)[i]
        m, d = qi.shape
        cols = []
        for j in range(d):
            for k in self.harmonics:
                for fn in (jnp.sin, jnp.cos):
                    cols.append(jnp.zeros((m, d), q.dtype).at[:, j].set(fn(k * qi[:, j])))
        step = jnp.stack(cols, axis=-1)
        return _module_step_features(arm, q, i, step, spherical_as_twist=False)

    def describe(self, location, values):
        amp: dict[str, float] = {}
        for n, (v, _, _) in values.items():
            c = n.split("_")[0]
            amp[c] = amp.get(c, 0.0) + v * v
        parts = ", ".join(f"{c} {_fmt(a**0.5)} rad" for c, a in amp.items())
        return (
            f"the {location} module has a periodic transmission error (harmonics "
            f"{', '.join(map(str, self.harmonics))} of the joint angle): amplitude {parts}"
        )


class LinkBending(Effect):
    """Transverse bending of an inner link under gravity (a cantilever, :mod:`.loads`)."""

    name = "link_bending"
    needs = "masses (mass, com of the modules' bodies)"
    summary = "transverse bending of the upper arm or forearm under gravity"

    def locations(self, arm):
        return arm.frame_names[1:-1]

    def parameters(self, arm, location):
        return (
            ParameterSpec(
                "compliance",
                "1/(N*mm^2)",
                0.0,
                1e-5,
                "bending compliance 1/(E I) under the transverse forces (distal weights at the "
                "tip, own weight); plausible: E I above 1e5 N mm^2",
            ),
            ParameterSpec(
                "compliance_moment",
                "1/(N*mm^2)",
                0.0,
                1e-5,
                "bending compliance 1/(E I) under the tip moment of the distal weights (equal "
                "to 'compliance' for a uniform beam; fitted apart so that a simpler or richer "
                "loading of the real link is not mistaken for another effect)",
            ),
        )

    def _index(self, arm, location):
        j = arm.frame_index(location)
        if not 1 <= j <= len(arm.modules) - 1:
            raise ValueError(f"link_bending sits at an inner frame {self.locations(arm)}")
        return j

    def missing(self, arm, location, aux_names):
        j = self._index(arm, location)
        if _distal_mass(arm, j - 1) <= 0.0 and PAYLOAD not in aux_names:
            return f"no mass on or beyond link {location!r} in the model and no payload_kg column"
        if float(jnp.linalg.norm(jnp.asarray(arm.frames)[j, :3, 3])) == 0.0:
            return f"link {location!r} has zero length"
        return None

    def features(self, arm, q, aux, location):
        j = self._index(arm, location)
        d = bending_deflection(arm, q, j, _payload(aux, q), split=True)  # (m, 6, 2)
        f = Features.zeros(arm, q.shape[0], 2, q.dtype)
        fd = f.frame_deflection.at[:, j].set(d)
        return Features(f.state, f.module_twist, fd)

    def describe(self, location, values):
        v = values["compliance"][0]
        ei = f" (E I {_fmt(1 / v)} N*mm^2)" if v > 0 else ""
        return (
            f"the {location} link bends under gravity: compliance 1/(EI) "
            f"{_interval(values, 'compliance', '1/(N*mm^2)')}{ei}; under the tip moment "
            f"{_interval(values, 'compliance_moment', '1/(N*mm^2)')}"
        )


class ThermalDrift(Effect):
    """The mount moving slowly against the measuring device: translation and rotation ~ time."""

    name = "thermal_drift"
    needs = "time_s column"
    summary = "slow drift with time"
    _COMP = ("vx", "vy", "vz", "wx", "wy", "wz")

    def locations(self, arm):
        return arm.frame_names[:1]

    def parameters(self, arm, location):
        return tuple(
            ParameterSpec(
                f"rate_{c}",
                "mm/s" if c[0] == "v" else "rad/s",
                -1e-2 if c[0] == "v" else -1e-4,
                1e-2 if c[0] == "v" else 1e-4,
                f"drift rate of the mount, {'translation' if c[0] == 'v' else 'rotation'} "
                f"along {c[1]} (world frame; rotation about the mount origin)",
            )
            for c in self._COMP
        )

    def missing(self, arm, location, aux_names):
        if TIME not in aux_names:
            return "no time_s column in the measurements"
        return None

    def features(self, arm, q, aux, location):
        t = jnp.asarray(aux[TIME], q.dtype)
        f = Features.zeros(arm, q.shape[0], 6, q.dtype)
        fd = f.frame_deflection.at[:, 0].set(t[:, None, None] * jnp.eye(6, dtype=q.dtype))
        return Features(f.state, f.module_twist, fd)

    def describe(self, location, values):
        v = [values[f"rate_{c}"][0] for c in self._COMP]
        trans = sum(x * x for x in v[:3]) ** 0.5
        rot = sum(x * x for x in v[3:]) ** 0.5
        return (
            f"the arm's {location} drifts with time: {_fmt(trans)} mm/s "
            f"({_fmt(3600 * trans)} mm per hour) and {_fmt(rot)} rad/s"
        )


VOCABULARY: tuple[Effect, ...] = (
    JointCompliance(),
    CableElasticity(),
    CableScale("from_home"),
    CableScale("absolute"),
    Backlash("state"),
    Backlash("rotation"),
    PeriodicError((1,)),
    PeriodicError((2,)),
    PeriodicError((3,)),
    PeriodicError((4,)),
    PeriodicError((5,)),
    PeriodicError((6,)),
    LinkBending(),
    ThermalDrift(),
)
"""The seven effects of design.md (with their variants), in the order of its table."""

EFFECT_NAMES: tuple[str, ...] = tuple(dict.fromkeys(e.name for e in VOCABULARY))


def effect(name: str, variant: str | None = None) -> Effect:
    """The vocabulary entry called ``name`` (its first variant unless ``variant`` is given).

    ``ValueError`` naming the known effects and variants otherwise.
    """
    for e in VOCABULARY:
        if e.name == name and (variant is None or e.variant == variant):
            return e
    known = ", ".join(f"{e.name}" + (f" ({e.variant})" if e.variant else "") for e in VOCABULARY)
    raise ValueError(f"unknown effect {name!r} (variant {variant!r}); known: {known}")
