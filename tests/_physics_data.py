"""Shared synthetic recordings for the physics and diagnosis tests (computed once per session).

Every recording uses the same 30 feasible poses and auxiliary columns and the features of every
candidate of the vocabulary evaluated in one compiled call, the very call (same static
candidates, same shapes) the diagnosis makes, so that the whole test session compiles the
extended model once.
"""

from __future__ import annotations

import functools
from types import SimpleNamespace

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from cdra_jax import NoiseModel, lie
from cdra_jax.arm import apply_frame_errors
from cdra_jax.diagnosis.model import all_features
from cdra_jax.io import Measurements, default_arm
from cdra_jax.modules.tension import sample_feasible_states
from cdra_jax.physics import (
    PROBES,
    Effect,
    Features,
    ParameterSpec,
    candidates,
    corrected_tool_pose,
)
from cdra_jax.physics.synthetic import recording_aux
from cdra_jax.simulation import add_measurement_noise, random_frame_errors

M = 30
NOISE = NoiseModel(0.05, 0.0005)


@functools.cache
def base(seed: int = 0) -> SimpleNamespace:
    jax.config.update("jax_enable_x64", True)
    arm = default_arm()
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(seed), 3)
    q = eqx.filter_jit(sample_feasible_states)(k1, arm, M)
    aux = recording_aux(k2, arm, M)
    X = random_frame_errors(k3, arm, 1.0, 0.01)
    actual = apply_frame_errors(arm, X)
    live = [c for c, why in candidates(arm, aux.keys()) if why is None]
    probes = [c for c, why in candidates(arm, aux.keys(), PROBES) if why is None]
    everything = tuple(live + probes)
    F = all_features(everything, actual, q, aux)
    sizes = [len(c.parameters(arm)) for c in everything]
    off = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    cols = {c: slice(int(off[i]), int(off[i + 1])) for i, c in enumerate(everything)}
    return SimpleNamespace(
        arm=arm, q=q, aux=aux, X=X, actual=actual, everything=everything, F=F, cols=cols
    )


def find(name: str, location: str, variant: str | None = None):
    b = base()
    for c in b.everything:
        if c.name == name and c.location == location and (variant is None or c.variant == variant):
            return c
    raise KeyError((name, location, variant))


def recordings(
    effect=None, values=(), *, noise=NOISE, seed: int = 1, distortion=None, actual=None
) -> Measurements:
    """The shared poses measured on the actual arm with ``effect`` (a candidate) at ``values``."""
    b = base()
    theta = np.zeros(b.F.n_params)
    if effect is not None:
        theta[b.cols[effect]] = values
    T = corrected_tool_pose(b.actual if actual is None else actual, b.q, b.F, jnp.asarray(theta))
    if distortion is not None:
        T = lie.se3_exp(distortion(b.q)) @ T
    T = add_measurement_noise(jax.random.PRNGKey(seed), T, noise)
    aux = {k: np.asarray(v) for k, v in b.aux.items()}
    return Measurements.from_arrays(b.arm, np.asarray(b.q), np.asarray(T), aux=aux)


class BrokenEffect(Effect):
    """A candidate at the elbow whose one feature column is not finite (NaN in the first state
    entry of every pose): a numerical failure the diagnosis must survive."""

    name = "broken"
    summary = "a candidate whose features are not finite"

    def locations(self, arm):
        return ("elbow",)

    def parameters(self, arm, location):
        return (ParameterSpec("x", "1", -1.0, 1.0),)

    def features(self, arm, q, aux, location):
        f = Features.zeros(arm, q.shape[0], 1, q.dtype)
        return Features(f.state.at[:, 0, 0].set(jnp.nan), f.module_twist, f.frame_deflection)
