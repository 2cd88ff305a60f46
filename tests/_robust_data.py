"""Shared simulated problems for the robustness tests (one compiled generator, cached data).

Twelve calibration poses as in ``test_cli.py`` (so compiled solvers are shared), noise of the
paper's measuring device (0.08 mm) and 0.001 rad, random frame errors in the paper's range, and
gross outliers of 5 mm / 0.05 rad on chosen poses (a mis-seated probe). The module states are
drawn uniformly within the joint limits (``sampler=sample_states``), as when these tests were
written: the tests judge the estimators on one fixed draw, whatever the arm can hold, and
``simulate_trial``'s default (the tension-closure sampler) draws other states.
"""

from __future__ import annotations

import functools
import types

import equinox as eqx
import jax
import numpy as np

from cdra_jax import apply_frame_errors, default_arm, tool_pose
from cdra_jax.calibration import NoiseModel, deviation_metrics
from cdra_jax.simulation import add_outliers, sample_states, simulate_trial

M = 12
M_VERIFY = 30
N_OUTLIERS = 2
NOISE = NoiseModel(position_mm=0.08, rotation_rad=0.001)


@eqx.filter_jit
def _generate(key, arm):
    k_sim, k_out = jax.random.split(key)
    q, T, q_ver, _, X = simulate_trial(
        k_sim, arm, M, noise=NOISE, m_verify=M_VERIFY, sampler=sample_states
    )
    T_bad, mask = add_outliers(k_out, T, N_OUTLIERS)
    actual = apply_frame_errors(arm, X)
    exact = tool_pose(actual, q)  # noise-free
    nominal = tool_pose(arm, q)
    return q, T, T_bad, mask, X, actual.frames, q_ver, tool_pose(actual, q_ver), exact, nominal


@eqx.filter_jit
def held_out_dp(arm, frames, q_ver, T_ver):
    """Eq. 20 at the held-out poses for each of a batch of frame sets ``(n, K+1, 4, 4)``."""
    model = jax.vmap(lambda f: tool_pose(arm.with_frames(f), q_ver))(frames)
    return jax.vmap(lambda T: deviation_metrics(T_ver, T)[0])(model)


@functools.cache
def problem(seed: int = 0) -> types.SimpleNamespace:
    """``q, T`` (noisy), ``T_bad`` (outliers), ``mask, X, actual_frames, q_ver, T_ver, exact``.

    ``T_ver`` are the true (noise-free) tool poses at the held-out states ``q_ver``; ``exact``
    the noise-free tool poses at the calibration states ``q``; ``nominal`` the nominal model's.
    """
    jax.config.update("jax_enable_x64", True)
    arm = default_arm()
    out = [np.asarray(a) for a in _generate(jax.random.PRNGKey(seed), arm)]
    names = ("q", "T", "T_bad", "mask", "X", "actual_frames", "q_ver", "T_ver", "exact", "nominal")
    return types.SimpleNamespace(arm=arm, **dict(zip(names, out, strict=True)))
