"""Chunked batching (cdra_jax.calibration.batching) equals plain vmap per trial."""

from __future__ import annotations

import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _devices import run_on_two_cpu_devices

from cdra_jax.calibration.batching import chunked_vmap


def _newton_sqrt(a, x0, tol):
    """Newton's iteration for sqrt(a): a while_loop whose step count depends on the data."""

    def body(c):
        k, x = c
        return k + 1, 0.5 * (x + a / x)

    def running(c):
        k, x = c
        return (jnp.abs(x * x - a) > tol * a) & (k < 100)

    return jax.lax.while_loop(running, body, (jnp.asarray(0), x0))


def test_chunked_vmap_equals_vmap():
    a = jnp.logspace(-3, 12, 11)  # 11 trials, chunks of 4: padded
    x0 = jnp.ones(11)
    f = chunked_vmap(_newton_sqrt, 4)
    k, x = jax.jit(jax.vmap(f, in_axes=(0, 0, None)))(a, x0, 1e-12)
    k_ref, x_ref = jax.vmap(_newton_sqrt, in_axes=(0, 0, None))(a, x0, 1e-12)
    np.testing.assert_array_equal(k, k_ref)
    np.testing.assert_array_equal(x, x_ref)
    assert len(set(np.asarray(k).tolist())) > 3  # the trials take different step counts
    # Unbatched, a small batch (one chunk), and nested vmap.
    assert f(a[3], x0[3], 1e-12)[1] == x_ref[3]
    np.testing.assert_array_equal(
        jax.vmap(f, in_axes=(0, 0, None))(a[:3], x0[:3], 1e-12)[1], x_ref[:3]
    )
    xx = jax.jit(jax.vmap(jax.vmap(f, in_axes=(0, 0, None)), in_axes=(0, 0, None)))(
        a.reshape(1, 11), x0.reshape(1, 11), 1e-12
    )[1]
    np.testing.assert_array_equal(xx[0], x_ref)


@pytest.mark.slow
def test_lm_runs_with_the_batch_sharded_over_two_cpu_devices():
    """The chunked LM solver, jitted with the trial axis sharded over 2 (forced host) devices as
    the sweeps do (weighted, with noise), finishes and gives the unsharded results. A work queue
    (a data-dependent gather of trials inside a loop) deadlocked there. The paper solver is
    checked the same way by tests/test_sweeps.py. In a subprocess, with a timeout."""
    script = textwrap.dedent(
        """
        import jax
        jax.config.update("jax_enable_x64", True)
        import numpy as np
        from jax.sharding import Mesh, NamedSharding, PartitionSpec
        from cdra_jax import NoiseModel, calibrate_lm, default_arm, simulation
        assert len(jax.devices()) == 2, jax.devices()
        arm, noise = default_arm(), NoiseModel(0.05, 1e-3)
        keys = jax.random.split(jax.random.PRNGKey(0), 4)
        q, T, *_ = jax.vmap(lambda k: simulation.simulate_trial(k, arm, 5, noise=noise))(keys)
        sh = NamedSharding(Mesh(np.asarray(jax.devices()), ("t",)), PartitionSpec("t"))
        f = jax.vmap(lambda q, T: calibrate_lm(arm, q, T, noise, throw=False))
        sol = jax.jit(f, in_shardings=(sh, sh), out_shardings=sh)(
            jax.device_put(q, sh), jax.device_put(T, sh)
        )
        assert len(sol.errors.sharding.device_set) == 2
        assert np.all(np.asarray(sol.converged))
        ref = jax.jit(f)(q, T)
        np.testing.assert_allclose(sol.errors, ref.errors, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(sol.iterations, ref.iterations)
        """
    )
    run_on_two_cpu_devices(script, timeout=240)
