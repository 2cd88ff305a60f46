"""Chunked and queued batching (cdra_jax.calibration.batching) equal plain vmap per trial."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from cdra_jax.calibration.batching import Iteration, chunked_vmap, iterate, queued_vmap


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


def test_queued_vmap_equals_iterate_per_trial():
    tol = 1e-12

    def init(a, x0):
        return jnp.asarray(0), x0, a

    def step(c, a, x0):
        k, x, _ = c
        return k + 1, 0.5 * (x + a / x), a

    def running(c):
        k, x, a = c
        return (jnp.abs(x * x - a) > tol * a) & (k < 100)

    def result(c):
        return c[0], c[1]

    def finish(r, a, x0):
        k, x = r
        return {"k": k, "x": x, "err": x * x - a}

    it = Iteration(init=init, step=step, running=running, result=result, finish=finish)
    a = jnp.concatenate([jnp.logspace(-3, 12, 13), jnp.asarray([4.0])])
    x0 = jnp.ones_like(a).at[-1].set(2.0)  # the last trial needs no step at all
    ref = jax.jit(jax.vmap(lambda aa, xx: iterate(it, aa, xx)))(a, x0)
    for slots in (1, 4, 64):
        got = jax.jit(jax.vmap(queued_vmap(it, slots, chunk_size=5)))(a, x0)
        for key in ("k", "x"):
            np.testing.assert_array_equal(got[key], ref[key], err_msg=f"{key}, {slots} slots")
        np.testing.assert_array_less(
            np.abs(got["err"] - ref["err"]), 1e-15 * np.asarray(a) + 1e-300
        )
    assert int(ref["k"][-1]) == 0 and len(set(np.asarray(ref["k"]).tolist())) > 4
    one = queued_vmap(it, 4, chunk_size=5)(a[2], x0[2])
    assert one["x"] == ref["x"][2]
