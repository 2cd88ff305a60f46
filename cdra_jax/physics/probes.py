"""Generic location probes: where does a misfit that no named effect explains belong?

A probe is a deliberately flexible correction at one place of the chain, not a physical model:

* module ``i``: a platform twist (6 components, module base frame) linear and quadratic in the
  module's own state entries (``q_i`` and ``q_i^2``): ``6 * 2 dof`` parameters;
* inner frame (link) ``j``: an end deflection ``(delta, theta)`` of the link linear in the
  gravity direction seen in its start frame: ``18`` parameters;
* ``base``: a mount deflection linear in ``time_s`` (when present) and in the arm's first
  module state (a base that moves with the shoulder): ``6 (1 + dof_0)`` parameters;
* any fixed frame but the tool, when the data have ``time_s``: an end deflection linear in
  time alone (``6`` parameters, the same at every frame), which says where a misfit that
  changes with time lives: at the mount, or along one link (a link that grows as it warms up).

The probe that explains the largest significant part of the residual left by the geometric
fit names the location of an ``unattributed`` misfit.
"""

from __future__ import annotations

import jax.numpy as jnp

from ..arm import Arm
from .base import Aux, Effect, Features, ParameterSpec
from .effects import TIME, _module_index, _state_slice
from .loads import world_gravity_direction

_TWIST = ("vx", "vy", "vz", "wx", "wy", "wz")


class ModuleProbe(Effect):
    name = "probe"
    summary = "state-dependent platform twist of a module (linear and quadratic in its state)"

    def locations(self, arm: Arm) -> tuple[str, ...]:
        return arm.module_names

    def parameters(self, arm, location):
        mod = arm.modules[_module_index(arm, location)]
        return tuple(
            ParameterSpec(f"{c}_{s}{p}", "-", -float("inf"), float("inf"))
            for c in _TWIST
            for s in mod.state_names
            for p in ("", "^2")
        )

    def features(self, arm, q, aux: Aux, location):
        i = _module_index(arm, location)
        qi = q[:, _state_slice(arm, i)]
        phi = jnp.stack([qi, qi * qi], axis=-1).reshape(q.shape[0], -1)  # (m, 2 dof)
        n = phi.shape[-1]
        f = Features.zeros(arm, q.shape[0], 6 * n, q.dtype)
        cols = jnp.einsum("ca,mb->mcab", jnp.eye(6, dtype=q.dtype), phi).reshape(-1, 6, 6 * n)
        return Features(f.state, f.module_twist.at[:, i].set(cols), f.frame_deflection)


class FrameProbe(Effect):
    name = "probe"
    summary = "end deflection of a fixed frame linear in gravity direction (links) or time (base)"

    def locations(self, arm: Arm) -> tuple[str, ...]:
        return arm.frame_names[:-1]

    def _phi(self, arm, q, aux, location):
        j = arm.frame_index(location)
        if j == 0:
            cols = [q[:, _state_slice(arm, 0)]]
            if TIME in aux:
                cols.insert(0, jnp.asarray(aux[TIME], q.dtype)[:, None])
            return jnp.concatenate(cols, axis=-1)
        return world_gravity_direction(arm, q, j)

    def parameters(self, arm, location):
        j = arm.frame_index(location)
        n = 3 if j > 0 else arm.modules[0].dof + 1
        return tuple(
            ParameterSpec(f"{c}_{b}", "-", -float("inf"), float("inf"))
            for c in _TWIST
            for b in range(n)
        )

    def features(self, arm, q, aux, location):
        j = arm.frame_index(location)
        phi = self._phi(arm, q, aux, location)
        if j == 0 and TIME not in aux:  # keep the column count of parameters(): a zero time
            phi = jnp.concatenate([jnp.zeros((q.shape[0], 1), q.dtype), phi], axis=-1)
        n = phi.shape[-1]
        f = Features.zeros(arm, q.shape[0], 6 * n, q.dtype)
        cols = jnp.einsum("ca,mb->mcab", jnp.eye(6, dtype=q.dtype), phi).reshape(-1, 6, 6 * n)
        return Features(f.state, f.module_twist, f.frame_deflection.at[:, j].set(cols))


class TimeProbe(Effect):
    name = "probe"
    summary = "end deflection of a fixed frame linear in time"

    def locations(self, arm: Arm) -> tuple[str, ...]:
        return arm.frame_names[:-1]

    def parameters(self, arm, location):
        return tuple(ParameterSpec(f"{c}_t", "-", -float("inf"), float("inf")) for c in _TWIST)

    def missing(self, arm, location, aux_names):
        return None if TIME in aux_names else f"no {TIME} column"

    def features(self, arm, q, aux, location):
        j = arm.frame_index(location)
        t = jnp.asarray(aux[TIME], q.dtype)
        f = Features.zeros(arm, q.shape[0], 6, q.dtype)
        cols = jnp.einsum("ca,m->mca", jnp.eye(6, dtype=q.dtype), t)
        return Features(f.state, f.module_twist, f.frame_deflection.at[:, j].set(cols))


PROBES: tuple[Effect, ...] = (ModuleProbe(), FrameProbe(), TimeProbe())
