"""The candidate physics vocabulary (design.md): seven effects, each a few physical parameters.

Each effect maps the recorded data to per-pose corrections linear in its parameters (see
:mod:`.base`); the tool pose is then the exact product of exponentials. The gravity effects
have forms with the model's masses and, for arms whose model has none, forms in the lumped
gravity moments that the data identify (:func:`.loads.moment_terms`: ``n`` is two per revolute
joint beyond the location, three per spherical one, one per prismatic one, plus the location's
own). Conventions: module
states as in :mod:`cdra_jax.arm`; a module-platform rotation is left-multiplied in the module
base frame, the frame of :mod:`cdra_jax.modules` (torques, structure matrix, length Jacobian).

==================  ==============  ====================================================  ======
effect              location        correction                                            params
==================  ==============  ====================================================  ======
joint_compliance    module          platform rotation ``c tau`` (spherical), about the    1 / 2
                                    axis ``c_a (a.tau)`` and across it ``c_t tau_perp``
                                    (revolute, prismatic); ``tau``: gravity torque.
                                    Without masses: ``c tau`` linear in the lumped        n
                                    moments (compliance x weight x lever, rad each)
cable_elasticity    module          state change ``c J^+ t``: stretch ``c t`` of each     1
                                    cable (``t``: holding tensions), least squares over
                                    the cables (``J``: length Jacobian)
cable_scale         module          ``s J^+ (l(q) - l(0))``: lengths paid out from home   1
                                    off by the factor ``1 + s`` (drum radius error)
backlash            module          ``q - approach * b``: lag of ``b`` per state entry    dof
                                    against the last motion
periodic_error      module          ``sum_k a_k sin(k q) + b_k cos(k q)`` per state       2 H dof
                                    entry, harmonics ``k = 1 .. H``
link_bending        inner frame     cantilever tip deflection under gravity,              2
                                    ``c = 1/(EI)`` (:mod:`.loads`); without masses: the
                                    weights' tip rotation and the lumped moments          1 + n
thermal_drift       base            mount moved by ``v t`` and turned by ``w t``          6
==================  ==============  ====================================================  ======
"""

from __future__ import annotations

from collections.abc import Mapping

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax import Array

from ..arm import Arm, Module
from ..modules.cables import cable_lengths, length_jacobian
from ..modules.statics import (
    distribute_tensions,
    gravity_loads,
    gravity_torques,
    module_floor,
    world_frames,
)
from ..modules.tension import structure_matrix
from .base import Aux, Effect, Features, ParameterSpec, shared_term
from .loads import (
    MomentTerm,
    bending_deflection,
    lumped_bending_deflection,
    moment_terms,
    moment_torques,
)

PAYLOAD = "payload_kg"
TIME = "time_s"


@eqx.filter_jit
def _payout(mod: Module, qi: Array) -> Array:
    """Each cable's payout from home, ``(m, n_cables)`` mm: its length at the module states
    ``qi (m, dof)`` less its length at the home state (compiled: the diagnosis asks for it per
    candidate outside its compiled programs)."""
    return cable_lengths(mod, qi) - cable_lengths(mod, jnp.zeros_like(qi))


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


def _gravity_loads(arm: Arm, q: Array, aux: Aux) -> Array:
    """Gravity loads ``(m, dof)`` of every module at the recorded payload (shared by the
    candidates of one diagnosis, :func:`.base.shared_term`)."""
    return gravity_loads(arm, q, _payload(aux, q))


def _gravity_torques(arm: Arm, q: Array, aux: Aux) -> Array:
    """Gravity torques ``(m, K, 3)`` N mm about each module centre, base frame (shared)."""
    return gravity_torques(arm, q, _payload(aux, q))


def _holding_tensions(arm: Arm, q: Array, aux: Aux, i: int) -> Array:
    """Tensions ``(m, n)`` N holding module ``i`` against its gravity load, minimum norm above
    the pretension floor (:func:`cdra_jax.modules.statics.holding_tensions` for this module
    only; shared by the forms that use them)."""
    mod = arm.modules[i]
    load = arm.split_state(shared_term(_gravity_loads, arm, q, aux))[i]
    A = structure_matrix(mod, arm.split_state(q)[i])  # (m, d, n)
    return distribute_tensions(A, -load, module_floor(mod)).tensions


def _length_jacobian(arm: Arm, q: Array, i: int) -> Array:
    """Module ``i``'s cable-length Jacobian ``(m, n, dof_i)`` at the states (shared)."""
    return length_jacobian(arm.modules[i], arm.split_state(q)[i])


def _distal_mass(arm: Arm, i: int) -> float:
    return float(sum(m.mass or 0.0 for m in arm.modules[i:]))


LUMPED_MAX_RAD = 0.05
"""Largest plausible rotation (rad) a lumped gravity moment causes: a deflection of ~3 degrees
under the arm's own weight is not an elastic one."""


def _moment_specs(arm: Arm, terms: tuple[MomentTerm, ...], what: str) -> tuple[ParameterSpec, ...]:
    """Parameters of lumped gravity moments (:func:`.loads.moment_terms`): ``what`` deflects.

    A body term's product has no checkable sign (a first moment points anywhere); a travel
    term's is a compliance times a mass: never negative."""
    out = []
    for b, c in terms:
        body = arm.modules[b].name
        if c == "travel":
            out.append(
                ParameterSpec(
                    f"travel_{body}",
                    "rad/mm",
                    0.0,
                    LUMPED_MAX_RAD / 100.0,
                    f"{what} per mm of travel of the prismatic module {body!r}: compliance x "
                    f"weight of the bodies it carries (never negative)",
                )
            )
            continue
        axis = (
            f"the {c} axis of the {body} platform"
            if c in "xyz"
            else f"direction {c} across the {body} joint axis"
        )
        out.append(
            ParameterSpec(
                f"moment_{body}_{c}",
                "rad",
                -LUMPED_MAX_RAD,
                LUMPED_MAX_RAD,
                f"{what} from the gravity moment (mass x lever) of the bodies from {body} on "
                f"along {axis}, lever horizontal: compliance x weight x lever (a product; its "
                "sign is not checkable)",
            )
        )
    return tuple(out)


def _lumped_words(values: Mapping[str, tuple[float, float, float]], unit: str) -> str:
    """The three largest lumped products, in words."""
    big = sorted(values, key=lambda n: -abs(values[n][0]))[:3]
    more = len(values) - len(big)
    units = {n: f"{unit}/mm" if n.startswith("travel_") else unit for n in big}
    return "; ".join(f"{n} {_interval(values, n, units[n])}" for n in big) + (
        f" (and {more} more)" if more > 0 else ""
    )


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


def _harmonics(harmonics) -> tuple[int, ...]:
    out = tuple(int(h) for h in harmonics)
    if not out or min(out) < 1:
        raise ValueError(f"harmonics must be positive integers, got {harmonics!r}")
    return out


class ModuleEffect(Effect):
    """An effect located at a module (``shoulder``, ``elbow``, ``wrist`` for the CDRA).

    Effects with named forms list them in ``FORMS`` (those in ``REFINEMENTS`` are refinements,
    see :attr:`Effect.refinement`) and call :meth:`_set_form`.
    """

    FORMS: tuple[str, ...] = ()
    REFINEMENTS: tuple[str, ...] = ()

    def _set_form(self, form: str) -> None:
        if form not in self.FORMS:
            raise ValueError(f"{self.name} form must be one of {self.FORMS}, got {form!r}")
        self.form = form
        self.variant = form
        self.refinement = form in self.REFINEMENTS

    def locations(self, arm: Arm) -> tuple[str, ...]:
        return arm.module_names

    def module(self, arm: Arm, location: str) -> tuple[int, Module]:
        i = _module_index(arm, location)
        return i, arm.modules[i]


class JointCompliance(ModuleEffect):
    """Rotational deflection of a module's platform proportional to the gravity torque ``tau``
    it carries (about the module centre, :func:`cdra_jax.modules.statics.gravity_torques`).

    Variants with the model's masses: ``"isotropic"``, the rotation ``c tau`` (spherical
    modules; 1 parameter), and for revolute and prismatic modules
    ``c_a (a.tau) a + c_t (tau - (a.tau) a)`` about and across the joint axis ``a``
    (2 parameters); ``"per_axis"``, a diagonal compliance along the platform's own axes (the
    moving link's principal axes: bending about x and y, torsion about z), ``R diag(c) R^T tau``
    with ``R`` the platform orientation (3 parameters); ``"per_axis_quadratic"`` (a refinement,
    never tested alone), the second-order term of a load-dependent stiffness,
    ``R diag(c2) R^T tau |tau|`` (rad/(N mm)^2; negative for a joint that stiffens under load).

    Variants without masses (tried where no body distal to the module has a mass): the torque
    is linear in the distal bodies' unknown first moments, so the deflection is linear in the
    products compliance x weight x moment, lumped to the combinations gravity can tell apart
    (:func:`.loads.moment_terms`; rad each): ``"lumped"`` (spherical modules) the rotation
    ``c tau``; ``"lumped_axial"`` (revolute, prismatic) the rotation about the joint axis
    ``c (a.tau) a``; ``"lumped_transverse"`` the rotation across it ``c (tau - (a.tau) a)``.
    """

    name = "joint_compliance"
    needs = "masses (mass, com of the modules' bodies), or none: lumped gravity moments"
    summary = "rotational deflection of a module proportional to the gravity load it carries"
    MAX = 1e-5  # rad/(N mm): 33 mrad under the ~3.3 N m the CDRA shoulder carries
    TAU_SCALE = 1e3  # N mm: the load over which a plausible stiffness may double

    FORMS = (
        "isotropic",
        "per_axis",
        "per_axis_quadratic",
        "lumped",
        "lumped_axial",
        "lumped_transverse",
    )
    REFINEMENTS = ("per_axis_quadratic",)

    def __init__(self, form: str = "isotropic"):
        self._set_form(form)

    @property
    def lumped(self) -> bool:
        return self.form.startswith("lumped")

    def terms(self, arm: Arm, location: str) -> tuple[MomentTerm, ...]:
        """The lumped gravity moments of a ``lumped*`` form at ``location``."""
        i, _ = self.module(arm, location)
        return moment_terms(arm, i, axial=self.form == "lumped_axial")

    def parameters(self, arm, location):
        _, mod = self.module(arm, location)
        if self.lumped:
            how = {"lumped_axial": " about its axis", "lumped_transverse": " across its axis"}
            what = f"rotation of the {location} platform{how.get(self.form, '')}"
            return _moment_specs(arm, self.terms(arm, location), what)
        spec = lambda n, d: ParameterSpec(n, "rad/(N*mm)", 0.0, self.MAX, d)
        if self.form == "per_axis_quadratic":
            return tuple(
                ParameterSpec(
                    f"compliance_{c}_quadratic",
                    "rad/(N*mm)^2",
                    -self.MAX / self.TAU_SCALE,
                    self.MAX / self.TAU_SCALE,
                    f"change of the compliance about the platform's {c} axis per N*mm of load",
                )
                for c in "xyz"
            )
        if self.form == "per_axis":
            return tuple(
                spec(f"compliance_{c}", f"rotation about the platform's {c} axis per N*mm")
                for c in "xyz"
            )
        if mod.kind == "spherical":
            return (spec("compliance", "platform rotation per unit gravity torque (isotropic)"),)
        return (
            spec("compliance_axial", "rotation about the joint axis"),
            spec("compliance_transverse", "rotation across the joint axis (hinge bending)"),
        )

    def missing(self, arm, location, aux_names):
        i, mod = self.module(arm, location)
        if not self.lumped:
            if _distal_mass(arm, i) <= 0.0 and PAYLOAD not in aux_names:
                return (
                    f"no mass distal to module {location!r} in the model and no payload_kg "
                    "column (its lumped forms are tried instead)"
                )
            return None
        if _distal_mass(arm, i) > 0.0:
            return "the model has the masses: the forms with them are tried (more power)"
        if (self.form == "lumped") != (mod.kind == "spherical"):
            return f"not a form of a {mod.kind} module"
        if self.form == "lumped_axial" and _axis_along_gravity(arm, i):
            return (
                f"the {location} joint axis stays parallel to gravity: gravity puts no torque "
                "about it"
            )
        return None

    def features(self, arm, q, aux, location):
        i, mod = self.module(arm, location)
        if self.lumped:
            before = shared_term(_module_bases, arm, q)[:, i, :3, :3]
            cols = jnp.einsum(
                "mji,mjn->min", before, moment_torques(arm, q, self.terms(arm, location))
            )
            if self.form != "lumped":
                a = jnp.asarray(mod.axis, q.dtype)
                along = jnp.einsum("min,i->mn", cols, a)[:, None, :] * a[:, None]
                cols = along if self.form == "lumped_axial" else cols - along
        else:
            tau = shared_term(_gravity_torques, arm, q, aux)[:, i, :]  # (m, 3) N mm, base frame
            if self.form in ("per_axis", "per_axis_quadratic"):
                R = mod.pose(arm.split_state(q)[i])[:, :3, :3]
                local = jnp.einsum("mji,mj->mi", R, tau)  # torque in the platform frame
                cols = R * local[:, None, :]  # column c: R e_c (e_c . R^T tau)
                if self.form == "per_axis_quadratic":
                    cols = cols * jnp.linalg.norm(tau, axis=-1)[:, None, None]
            elif mod.kind == "spherical":
                cols = tau[..., None]
            else:
                a = jnp.asarray(mod.axis, q.dtype)
                along = jnp.einsum("mi,i->m", tau, a)[:, None] * a
                cols = jnp.stack([along, tau - along], axis=-1)
        f = Features.zeros(arm, q.shape[0], cols.shape[-1], q.dtype)
        tw = f.module_twist.at[:, i].set(_rotation_twist(cols))
        return Features(f.state, tw, f.frame_deflection)

    def describe(self, location, values):
        if self.lumped:
            how = {"lumped_axial": " about its axis", "lumped_transverse": " across its axis"}
            return (
                f"the {location} module deflects{how.get(self.form, '')} under the gravity load "
                f"it carries (masses unknown: {len(values)} compliance x gravity moment "
                "products fitted): " + _lumped_words(values, "rad")
            )
        parts = [f"{n.replace('_', ' ')} {_interval(values, n, 'rad/(N*mm)')}" for n in values]
        return f"the {location} module deflects under the gravity load it carries: " + "; ".join(
            parts
        )


def _module_bases(arm: Arm, q: Array) -> Array:
    """World poses ``(m, K, 4, 4)`` of the module base frames."""
    return world_frames(arm, q)[2]


def _axis_along_gravity(arm: Arm, i: int, tol: float = 1e-6) -> bool:
    """Whether module ``i``'s axis is parallel to gravity in every pose: it is at the zero
    state and every module before it only translates or turns about the vertical."""
    q0 = jnp.asarray(np.zeros((1, arm.dof), np.asarray(arm.frames).dtype))
    bases = np.asarray(_module_bases(arm, q0)[0])  # the rest in numpy: a check, not traced
    g = np.asarray(arm.gravity, q0.dtype)
    g = g / np.linalg.norm(g)

    def vertical(k: int) -> bool:
        a = bases[k, :3, :3] @ np.asarray(arm.modules[k].axis, q0.dtype)
        return float(np.linalg.norm(np.cross(a, g))) < tol

    before_ok = all(
        m.kind == "prismatic" or (m.kind == "revolute" and vertical(k))
        for k, m in enumerate(arm.modules[:i])
    )
    return arm.modules[i].kind != "spherical" and before_ok and vertical(i)


class _CableEffect(ModuleEffect):
    def missing(self, arm, location, aux_names):
        _, mod = self.module(arm, location)
        if not mod.n_cables:
            return f"module {location!r} has no cables in the model"
        return None

    def _length_step_features(self, arm: Arm, q: Array, i: int, dl: Array) -> Features:
        """Features of the cable length errors ``dl (m, n)`` (mm per unit parameter) of module
        ``i``, mapped to its state by least squares ``J^+ dl``: one column, or one per cable
        for the ``"per_cable"`` form."""
        mod = arm.modules[i]
        J = shared_term(_length_jacobian, arm, q, i)  # (m, n, dof)
        if getattr(self, "form", None) == "per_cable":
            step = _lstsq_columns(J, dl[..., None] * jnp.eye(mod.n_cables, dtype=q.dtype))
        else:
            step = _lstsq(J, dl)[..., None]
        return _module_step_features(arm, q, i, step)


def _per_cable_words(values: Mapping[str, tuple[float, float, float]], unit: str) -> str:
    """``"l1 <value> (<low> to <high>); l2 ..."`` for parameters named ``..._l<k>``."""
    return "; ".join(f"{n.split('_')[-1]} {_interval(values, n, unit)}" for n in values)


POWER_TENSION_N = 100.0
"""Reference tension (N) of the power-law cable stretch refinements."""


class CableElasticity(_CableEffect):
    """Cable stretch ``c_i t_i`` (``t``: tensions holding the arm) mapped to a module-state
    change by least squares over the cables, ``J^+ (c t)``.

    Variants (the tension model and how many compliances):

    * ``"holding"``: one compliance for all cables, tensions of
      :func:`cdra_jax.modules.statics.holding_tensions` (minimum norm above the pretension floor);
    * ``"pretension_share"``: one compliance, tensions ``f + A^+ (-g)``: the pretension ``f`` in
      every cable plus the minimum-norm share of the gravity load ``g`` (no floor);
    * ``"per_cable"``: one compliance per cable (cables routed over different lengths have
      different stiffnesses), holding tensions;
    * ``"quadratic"`` (a refinement, never tested alone): the second-order term ``c2 t_i^2`` of
      a tension-dependent stiffness (negative for a cable that stiffens as it is loaded);
    * ``"power0.5"``, ``"power0.75"`` (refinements that may also replace the form they refine,
      :attr:`Effect.alone`): a power-law stretch ``c t_ref (t_i / t_ref)^p`` (``t_ref`` =
      :data:`POWER_TENSION_N`), the usual empirical law of a rope or braided cable that
      stiffens as its strands bed in.
    """

    name = "cable_elasticity"
    needs = "cables, masses (tensions from the statics), pretension"
    summary = "cable stretch proportional to tension (pretension plus gravity load)"

    FORMS = ("holding", "pretension_share", "per_cable", "quadratic", "power0.5", "power0.75")
    REFINEMENTS = ("quadratic", "power0.5", "power0.75")

    def __init__(self, form: str = "holding"):
        self._set_form(form)
        self.alone = form.startswith("power")  # a complete stretch law of its own

    def parameters(self, arm, location):
        _, mod = self.module(arm, location)
        high = 10.0 / mod.stiffness if mod.stiffness else 1.0
        desc = (
            "cable stretch per newton of tension (1/stiffness); plausible up to 10x the model's "
            "1/stiffness"
        )
        if self.form == "per_cable":
            return tuple(
                ParameterSpec(f"axial_compliance_l{k + 1}", "mm/N", 0.0, high, desc)
                for k in range(mod.n_cables)
            )
        if self.form == "quadratic":
            t0 = max(float(mod.pretension or 0.0), 1.0)
            return (
                ParameterSpec(
                    "axial_compliance_quadratic",
                    "mm/N^2",
                    -high / t0,
                    high / t0,
                    "change of the cable compliance per newton of tension",
                ),
            )
        if self.form.startswith("power"):
            return (
                ParameterSpec(
                    f"axial_compliance_{self.form}",
                    "mm/N",
                    0.0,
                    high,
                    f"stretch per newton at {POWER_TENSION_N:g} N of a power-law cable",
                ),
            )
        return (ParameterSpec("axial_compliance", "mm/N", 0.0, high, desc),)

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
        if self.form == "pretension_share":
            # f + A^+ (-load): every cable at the pretension plus the min-norm load share
            load = arm.split_state(shared_term(_gravity_loads, arm, q, aux))[i]
            A = structure_matrix(mod, arm.split_state(q)[i])  # (m, d, n)
            AAt = jnp.einsum("mdn,men->mde", A, A)
            share = jnp.einsum("mdn,md->mn", A, jnp.linalg.solve(AAt, -load[..., None])[..., 0])
            t = module_floor(mod) + share
        else:
            t = shared_term(_holding_tensions, arm, q, aux, i)  # (m, n) N
        if self.form == "quadratic":
            t = t * t
        elif self.form.startswith("power"):
            p = float(self.form.removeprefix("power"))
            t = POWER_TENSION_N * (jnp.maximum(t, 0.0) / POWER_TENSION_N) ** p
        return self._length_step_features(arm, q, i, t)

    def describe(self, location, values):
        power = [n for n in values if n.startswith("axial_compliance_power")]
        if power:
            return (
                f"the {location} module's cables stretch under load, stiffening as they are "
                f"loaded (stretch ~ tension^{power[0].removeprefix('axial_compliance_power')}): "
                f"compliance at {POWER_TENSION_N:g} N {_interval(values, power[0], 'mm/N')}"
            )
        if "axial_compliance" not in values:
            return (
                f"the {location} module's cables stretch under load (each its own compliance): "
                + _per_cable_words(values, "mm/N")
            )
        v, lo, hi = values["axial_compliance"]
        stiff = f"; stiffness {_fmt(1 / v)} N/mm" if v > 0 else ""
        return (
            f"the {location} module's cables stretch under load: axial compliance "
            f"{_interval(values, 'axial_compliance', 'mm/N')}{stiff}"
        )


def _lstsq_columns(J: Array, B: Array) -> Array:
    """``J^+ B``: ``J (m, n, d)``, ``B (m, n, p)`` -> ``(m, d, p)``."""
    JtJ = jnp.einsum("mni,mnj->mij", J, J)
    return jnp.linalg.solve(JtJ, jnp.einsum("mni,mnp->mip", J, B))


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
    zero; ``"per_cable"``, from home with one factor per cable (every winch its own drum).
    """

    name = "cable_scale"
    needs = "cables"
    summary = "winch/drum radius error: cable lengths off by a factor from home"

    FORMS = ("from_home", "absolute", "per_cable")

    def __init__(self, form: str = "from_home"):
        self._set_form(form)

    def parameters(self, arm, location):
        _, mod = self.module(arm, location)
        desc = "relative error of the length paid out from home (drum radius error)"
        if self.form == "per_cable":
            return tuple(
                ParameterSpec(f"scale_error_l{k + 1}", "1", -0.05, 0.05, desc)
                for k in range(mod.n_cables)
            )
        return (ParameterSpec("scale_error", "1", -0.05, 0.05, desc),)

    def features(self, arm, q, aux, location):
        i, mod = self.module(arm, location)
        qi = arm.split_state(q)[i]
        dl = cable_lengths(mod, qi) if self.form == "absolute" else _payout(mod, qi)  # (m, n) mm
        return self._length_step_features(arm, q, i, dl)  # per_cable: each winch its drum

    def describe(self, location, values):
        if "scale_error" not in values:
            return (
                f"the {location} module's cable lengths are off by a factor per winch (drum "
                "radius errors): " + _per_cable_words(values, "")
            )
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

    FORMS = ("state", "rotation")

    def __init__(self, form: str = "state"):
        self._set_form(form)

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
    (eccentric pulley or encoder, ``k = 1``) and its overtones (ellipticity ``k = 2``, a 3- to
    6-lobed bearing or gear). The vocabulary tries each ``k = 1 .. 6`` as a variant (one
    harmonic at a time keeps the model from absorbing any smooth joint error; the variants are
    Bonferroni-corrected). Over the CDRA's 2 rad joint ranges higher orders put too few of a
    few dozen poses into each period to be told from noise. Errors periodic in a winch drum's
    angle are :class:`DrumPeriodicError`.
    """

    name = "periodic_error"
    needs = "joint coordinates"
    summary = "transmission error periodic in a module angle"

    def __init__(self, harmonics: tuple[int, ...] = (1,)):
        self.harmonics = _harmonics(harmonics)
        self.variant = "k=" + ",".join(map(str, self.harmonics))

    def joins(self, other):
        """Harmonics of the joint angle join one another, not a drum's."""
        return isinstance(other, PeriodicError)

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

    def coordinate(self, arm, q, location):
        """Each state entry's angle; parameters ``(entry, harmonic, sin|cos)``."""
        i, mod = self.module(arm, location)
        n = 2 * len(self.harmonics)
        return arm.split_state(q)[i], np.arange(mod.dof * n) // n

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


class DrumPeriodicError(_CableEffect):
    """A transmission error periodic in the winch drum angles of a cable-driven module.

    A drum of radius ``r`` turns by ``phi_i = (l_i(q) - l_i(0)) / r`` when cable ``i`` is paid
    out from home (lengths of the model's cable geometry, :func:`cable_lengths`); an eccentric
    or out-of-round drum (or a once-per-turn encoder error) makes the length actually paid out
    err by a Fourier series ``sum_k a_ik sin(k phi_i) + b_ik cos(k phi_i)`` over the harmonics
    ``k`` (1: eccentricity, tested; 2: ovality, a refinement that joins the refit where it
    pays), with its own phases on every drum. The
    module state then moves by the least-squares ``J^+ e`` over the cables (``J`` the length
    Jacobian). The drum radius is not in the model file: the vocabulary tries the radii of
    :data:`DRUM_RADII_MM` as variants (``"drum r=<mm>"``), each with ``2 n_harmonics n``
    amplitudes (mm).
    """

    name = "periodic_error"
    needs = "cables"
    summary = "transmission error periodic in a module angle (winch drum angle)"

    def __init__(self, radius_mm: float = 10.0, harmonics: tuple[int, ...] = (1,)):
        if not radius_mm > 0:
            raise ValueError(f"drum radius must be positive, got {radius_mm!r}")
        self.harmonics = _harmonics(harmonics)
        self.radius_mm = float(radius_mm)
        self.variant = f"drum r={self.radius_mm:g}mm k=" + ",".join(map(str, self.harmonics))
        self.refinement = 1 not in self.harmonics  # overtones alone refine the fundamental

    def joins(self, other):
        """A drum has one radius: only its own harmonics join."""
        return isinstance(other, DrumPeriodicError) and other.radius_mm == self.radius_mm

    def parameters(self, arm, location):
        _, mod = self.module(arm, location)
        return tuple(
            ParameterSpec(
                f"l{j + 1}_{fn}{k}",
                "mm",
                -0.5,
                0.5,
                f"amplitude of {fn}({k} x drum angle) in the length error of cable {j + 1}",
            )
            for j in range(mod.n_cables)
            for k in self.harmonics
            for fn in ("sin", "cos")
        )

    def features(self, arm, q, aux, location):
        i, mod = self.module(arm, location)
        qi = arm.split_state(q)[i]
        phi = _payout(mod, qi) / self.radius_mm
        k = jnp.asarray(self.harmonics, q.dtype)
        kphi = phi[..., None] * k  # (m, n, h)
        waves = jnp.stack([jnp.sin(kphi), jnp.cos(kphi)], axis=-1)  # (m, n, h, 2)
        n, h = mod.n_cables, len(self.harmonics)
        # column (j, k, fn): the wave on cable j only
        e = jnp.einsum("mjkf,jl->mljkf", waves, jnp.eye(n, dtype=q.dtype))
        e = e.reshape(q.shape[0], n, n * h * 2)
        step = _lstsq_columns(shared_term(_length_jacobian, arm, q, i), e)
        return _module_step_features(arm, q, i, step)

    def coordinate(self, arm, q, location):
        """Each cable's payout from home (mm); parameters ``(cable, harmonic, sin|cos)``."""
        i, mod = self.module(arm, location)
        qi = arm.split_state(q)[i]
        n = 2 * len(self.harmonics)
        return _payout(mod, qi), np.arange(mod.n_cables * n) // n

    def describe(self, location, values):
        amp: dict[str, float] = {}
        for name, (v, _, _) in values.items():
            cable = name.split("_")[0]
            amp[cable] = amp.get(cable, 0.0) + v * v
        worst = max(amp.values(), default=0.0) ** 0.5
        return (
            f"the {location} module has a transmission error periodic in its winch drum angles "
            f"(harmonics {', '.join(map(str, self.harmonics))}; drum radius "
            f"{self.radius_mm:g} mm assumed): largest cable length error amplitude "
            f"{_fmt(worst)} mm"
        )


class LinkBending(Effect):
    """Transverse bending of an inner link under gravity (a cantilever, :mod:`.loads`).

    With the model's masses (variant ``""``): the compliances ``1/(E I)`` under the transverse
    forces and under the tip moment. Without masses (variant ``"lumped"``, tried where the link
    and the bodies beyond it have no mass): the tip rotation under the weights as a tip load
    (rad, never negative) and the tip-moment deflection per lumped gravity moment of the
    bodies beyond the link (:func:`.loads.lumped_bending_deflection`,
    :func:`.loads.moment_terms`; rad each).
    """

    name = "link_bending"
    needs = "masses (mass, com of the modules' bodies), or none: lumped gravity moments"
    summary = "transverse bending of the upper arm or forearm under gravity"

    def __init__(self, form: str = ""):
        if form not in ("", "lumped"):
            raise ValueError(f"link_bending form must be '' or 'lumped', got {form!r}")
        self.variant = form

    @property
    def lumped(self) -> bool:
        return self.variant == "lumped"

    def locations(self, arm):
        return arm.frame_names[1:-1]

    def terms(self, arm: Arm, location: str) -> tuple[MomentTerm, ...]:
        """The lumped gravity moments about the tip of link ``location``."""
        return moment_terms(arm, self._index(arm, location), travel_first=True)

    def parameters(self, arm, location):
        if self.lumped:
            weights = (
                ParameterSpec(
                    "weight_rotation",
                    "rad",
                    0.0,
                    LUMPED_MAX_RAD,
                    "tip rotation under the weights it carries (the bodies beyond it and its "
                    "own, as a tip load) with the link horizontal: compliance x weight x "
                    "length^2 / 2 (never negative)",
                ),
            )
            what = f"rotation of the {location} link's tip under the moment"
            return weights + _moment_specs(arm, self.terms(arm, location), what)
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
        if float(jnp.linalg.norm(jnp.asarray(arm.frames)[j, :3, 3])) == 0.0:
            return f"link {location!r} has zero length"
        massless = _distal_mass(arm, j - 1) <= 0.0
        if self.lumped and not massless:
            return "the model has the masses: the form with them is tried (more power)"
        if not self.lumped and massless and PAYLOAD not in aux_names:
            return (
                f"no mass on or beyond link {location!r} in the model and no payload_kg column "
                "(its lumped form is tried instead)"
            )
        return None

    def features(self, arm, q, aux, location):
        j = self._index(arm, location)
        if self.lumped:
            d = lumped_bending_deflection(arm, q, j, self.terms(arm, location))
        else:
            d = bending_deflection(arm, q, j, _payload(aux, q), split=True)  # (m, 6, 2)
        f = Features.zeros(arm, q.shape[0], d.shape[-1], q.dtype)
        fd = f.frame_deflection.at[:, j].set(d)
        return Features(f.state, f.module_twist, fd)

    def describe(self, location, values):
        if self.lumped:
            return (
                f"the {location} link bends under gravity (masses unknown: {len(values)} "
                "products fitted): tip rotation under the weights "
                f"{_interval(values, 'weight_rotation', 'rad')}; under the moments "
                + _lumped_words(
                    {k: v for k, v in values.items() if not k.startswith("weight_")}, "rad"
                )
            )
        v = values["compliance"][0]
        ei = f" (E I {_fmt(1 / v)} N*mm^2)" if v > 0 else ""
        return (
            f"the {location} link bends under gravity: compliance 1/(EI) "
            f"{_interval(values, 'compliance', '1/(N*mm^2)')}{ei}; under the tip moment "
            f"{_interval(values, 'compliance_moment', '1/(N*mm^2)')}"
        )


class ThermalDrift(Effect):
    """The mount moving slowly against the measuring device: translation and rotation ~ time.

    ``tau=None`` (the tested form): drift rates, ``v t`` and ``w t``. With a time constant
    ``tau`` (s; a refinement, never tested alone), a warm-up that settles,
    ``(1 - exp(-t / tau))`` times a translation and a rotation of the mount (mm, rad).
    """

    name = "thermal_drift"
    needs = "time_s column"
    summary = "slow drift with time"
    _COMP = ("vx", "vy", "vz", "wx", "wy", "wz")

    def __init__(self, tau_s: float | None = None):
        if tau_s is not None and not tau_s > 0:
            raise ValueError(f"thermal drift time constant must be positive, got {tau_s!r}")
        self.tau_s = None if tau_s is None else float(tau_s)
        self.refinement = tau_s is not None
        self.alone = True  # a settling drift is a complete drift of its own
        self.variant = "" if tau_s is None else f"warm-up tau={self.tau_s:g}s"

    def joins(self, other):
        """A warm-up has one time constant: the drift rate joins any, two warm-ups do not."""
        return not (
            isinstance(other, ThermalDrift)
            and None not in (self.tau_s, other.tau_s)
            and self.tau_s != other.tau_s
        )

    def locations(self, arm):
        return arm.frame_names[:1]

    def parameters(self, arm, location):
        if self.tau_s is not None:
            return tuple(
                ParameterSpec(
                    f"settled_{c}_tau{self.tau_s:g}",
                    "mm" if c[0] == "v" else "rad",
                    -10.0 if c[0] == "v" else -0.01,
                    10.0 if c[0] == "v" else 0.01,
                    f"settled warm-up {'translation' if c[0] == 'v' else 'rotation'} of the "
                    f"mount along {c[1]} (time constant {self.tau_s:g} s)",
                )
                for c in self._COMP
            )
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
        if self.tau_s is not None:
            t = -jnp.expm1(-t / self.tau_s)
        f = Features.zeros(arm, q.shape[0], 6, q.dtype)
        fd = f.frame_deflection.at[:, 0].set(t[:, None, None] * jnp.eye(6, dtype=q.dtype))
        return Features(f.state, f.module_twist, fd)

    def describe(self, location, values):
        if self.tau_s is not None:
            v = [values[f"settled_{c}_tau{self.tau_s:g}"][0] for c in self._COMP]
            return (
                f"the arm's {location} drifts as it warms up (time constant {self.tau_s:g} s): "
                f"settling {_fmt(sum(x * x for x in v[:3]) ** 0.5)} mm and "
                f"{_fmt(sum(x * x for x in v[3:]) ** 0.5)} rad away"
            )
        v = [values[f"rate_{c}"][0] for c in self._COMP]
        trans = sum(x * x for x in v[:3]) ** 0.5
        rot = sum(x * x for x in v[3:]) ** 0.5
        return (
            f"the arm's {location} drifts with time: {_fmt(trans)} mm/s "
            f"({_fmt(3600 * trans)} mm per hour) and {_fmt(rot)} rad/s"
        )


DRUM_RADII_MM: tuple[float, ...] = (5.0, 7.0, 10.0, 14.0, 20.0)
"""Winch drum radii (mm) the drum-angle periodic-error variants try (a factor ~1.4 apart)."""

WARMUP_TAUS_S: tuple[float, ...] = tuple(round(150.0 * 2 ** (i / 2)) for i in range(9))
"""Time constants (s) of the thermal warm-up refinements: 150 s to 2400 s, a factor 1.41 apart."""

VOCABULARY: tuple[Effect, ...] = (
    JointCompliance("isotropic"),
    JointCompliance("per_axis"),
    JointCompliance("per_axis_quadratic"),
    JointCompliance("lumped"),
    JointCompliance("lumped_axial"),
    JointCompliance("lumped_transverse"),
    CableElasticity("holding"),
    CableElasticity("pretension_share"),
    CableElasticity("per_cable"),
    CableElasticity("quadratic"),
    CableElasticity("power0.5"),
    CableElasticity("power0.75"),
    CableScale("from_home"),
    CableScale("absolute"),
    CableScale("per_cable"),
    Backlash("state"),
    Backlash("rotation"),
    *(PeriodicError((k,)) for k in range(1, 7)),
    *(DrumPeriodicError(r, (1,)) for r in DRUM_RADII_MM),
    *(DrumPeriodicError(r, (2,)) for r in DRUM_RADII_MM),
    LinkBending(),
    LinkBending("lumped"),
    ThermalDrift(),
    *(ThermalDrift(tau) for tau in WARMUP_TAUS_S),
)
"""The seven effects of design.md (with their variants and refinements), in the order of its
table."""

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
