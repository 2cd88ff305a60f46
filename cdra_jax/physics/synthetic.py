"""Synthetic recordings with one effect hidden in them (for tests, notebooks and examples).

:func:`simulate_recordings` follows the paper's Section V procedure (feasible random module
states, preset frame errors, measurement noise) and adds one candidate effect of this package
with given parameters, plus the auxiliary columns every recording carries: ``time_s`` (one
pose every ``dt_s`` seconds), ``approach.<module>`` (random +-1 per module and pose) and
``payload_kg``. Note that the effect is simulated with the very model the diagnosis fits; an
independent check needs an independent simulator.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from .. import lie
from ..arm import Arm, apply_frame_errors
from ..calibration import NoiseModel
from ..compilation import filter_jit
from ..io.measurements import Measurements
from ..modules.tension import sample_feasible_states
from ..simulation import add_measurement_noise, random_frame_errors
from .base import Candidate, Features, corrected_tool_pose


def recording_aux(key: Array, arm: Arm, m: int, *, dt_s: float = 20.0, payload_kg: float = 0.0):
    """The auxiliary columns of ``m`` recordings: ``time_s``, ``approach.*``, ``payload_kg``."""
    dtype = jnp.asarray(arm.frames).dtype
    one = jnp.ones((m, len(arm.modules)), dtype)
    signs = jnp.where(jax.random.bernoulli(key, 0.5, (m, len(arm.modules))), one, -one)
    aux = {
        "time_s": jnp.arange(m, dtype=dtype) * jnp.asarray(dt_s, dtype),
        "payload_kg": jnp.full(m, payload_kg, dtype),
    }
    for i, name in enumerate(arm.module_names):
        aux[f"approach.{name}"] = signs[:, i]
    return aux


@filter_jit
def _simulate(key, arm, m, candidate, params, noise, d_v, d_w, dt_s, payload_kg, distortion):
    k_err, k_q, k_aux, k_noise = jax.random.split(key, 4)
    X = random_frame_errors(k_err, arm, d_v, d_w)
    actual = apply_frame_errors(arm, X)
    q = sample_feasible_states(k_q, arm, m)
    aux = recording_aux(k_aux, arm, m, dt_s=dt_s, payload_kg=payload_kg)
    if candidate is None:
        T = corrected_tool_pose(actual, q, Features.zeros(arm, m, 0), jnp.zeros(0))
    else:
        T = candidate.tool_pose(actual, q, aux, jnp.asarray(params, float))
    if distortion is not None:
        T = lie.se3_exp(distortion(q)) @ T
    return q, add_measurement_noise(k_noise, T, noise), aux, X


def simulate_recordings(
    key: Array,
    arm: Arm,
    m: int,
    *,
    candidate: Candidate | None = None,
    params: ArrayLike | None = None,
    noise: NoiseModel | None = None,
    d_v: float = 1.0,
    d_w: float = 0.01,
    dt_s: float = 20.0,
    payload_kg: float = 0.0,
    distortion=None,
) -> tuple[Measurements, Array]:
    """``m`` measured poses of ``arm`` with random frame errors and one hidden effect.

    Args:
        key: PRNG key.
        arm: nominal model (the recordings' model file).
        m: number of poses.
        candidate, params: the hidden effect and its parameters (``None``: none).
        noise: measurement noise (``None``: exact poses).
        d_v, d_w: preset frame-error ranges (mm, rad).
        dt_s: time between poses (s).
        payload_kg: payload at the tool (kg), constant.
        distortion: optional ``f(q (m, dof)) -> (m, 6)`` extra world twist left-multiplied on
            the tool pose (an effect outside the vocabulary).

    Returns:
        ``(measurements, frame_errors (6 (K+1),))``.
    """
    params = None if params is None else jnp.asarray(params, float)
    q, T, aux, X = _simulate(
        key, arm, m, candidate, params, noise, d_v, d_w, dt_s, payload_kg, distortion
    )
    meas = Measurements.from_arrays(
        arm, np.asarray(q), np.asarray(T), aux={k: np.asarray(v) for k, v in aux.items()}
    )
    return meas, X
