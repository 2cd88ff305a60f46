"""Chunked batching (cdra_jax.calibration.batching) equals plain vmap per trial."""

from __future__ import annotations

import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _devices import run_on_two_cpu_devices

from cdra_jax.calibration.batching import (
    _batched_outputs,
    _traced_once,
    chunked_loop,
    chunked_vmap,
    multi_pass,
    set_entry,
    two_pass,
)
from cdra_jax.compilation import batched_like


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
    a = np.logspace(-3, 12, 11)  # 11 trials, chunks of 4: padded
    x0 = np.ones(11)
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


def _flag_multiples_of_three(calls):
    """A chunk function for ``two_pass``: the first pass returns ``x`` and flags multiples of 3,
    the second returns ``10 x``; each call's pass and flags are appended to ``calls``."""

    def batched(second, x):
        out = jnp.where(second, 10 * x, x)
        redo = (x % 3 == 0) & ~second
        jax.debug.callback(lambda s, r: calls.append((bool(s), int(r.sum()))), second, redo)
        return out, redo

    return batched


@pytest.mark.parametrize("size", [1, 3, 4, 11, 20])
def test_two_pass_redoes_the_flagged_trials_in_chunks_of_their_own(size):
    """The flagged trials' outputs are the second pass's, the others the first pass's; the
    second pass runs ceil(flagged / chunk) chunks, not one per chunk that holds a flagged trial;
    padding (copies of the first trial, a multiple of 3) is never redone."""
    x = np.arange(size, dtype=np.float64)  # x[0] = 0 is flagged
    chunk = 4
    calls: list[tuple[bool, int]] = []
    out = jax.jit(lambda x: two_pass(_flag_multiples_of_three(calls), chunk, x))(x)
    flagged = np.asarray(x) % 3 == 0
    np.testing.assert_array_equal(out, np.where(flagged, 10 * np.asarray(x), np.asarray(x)))
    n_chunks = -(-size // min(chunk, size))
    first = [c for c in calls if not c[0]]
    second = [c for c in calls if c[0]]
    assert len(first) == n_chunks
    assert len(second) == -(-int(flagged.sum()) // min(chunk, size))


def test_chunked_vmap_second_pass_under_vmap():
    """``chunked_vmap(..., second_pass=True)``: vmapped (several chunks, padded), nested, and
    unbatched calls give the per-trial result."""

    def one(second, x):
        return jnp.where(second, 10 * x, x), (x % 3 == 0) & ~second

    f = chunked_vmap(one, 4, second_pass=True)
    x = np.arange(11, dtype=np.float64)
    expected = np.where(x % 3 == 0, 10 * x, x)
    np.testing.assert_array_equal(jax.jit(jax.vmap(f))(x), expected)
    np.testing.assert_array_equal(jax.vmap(jax.vmap(f))(x.reshape(1, 11))[0], expected)
    assert f(x[3]) == 30.0 and f(x[4]) == 4.0


def test_multi_pass_keeps_every_output_dtype_and_shape():
    """Outputs of several dtypes and shapes (held in one buffer per dtype while the passes
    run) come back unchanged, each trial's from the last pass that evaluated it; trials of
    mode 2 skip mode 1, and padding is never handed on."""

    def batched(mode, x):
        out = {
            "value": x[:, None, None] * jnp.arange(6.0).reshape(2, 3) + mode,
            "flag": (x > 4) ^ (mode == 1),
            "count": jnp.broadcast_to(mode, x.shape).astype(jnp.int32) * 7,
            "big": (x * 1e6).astype(jnp.int64) + jnp.int64(2**40),
            "mode": jnp.broadcast_to(mode, x.shape).astype(jnp.float32),
        }
        want = jnp.where(mode == 0, (x.astype(jnp.int32) % 3), 0)
        return out, want.astype(jnp.int32)

    x = jnp.arange(11, dtype=jnp.float64)
    out = jax.jit(lambda x: multi_pass(batched, 4, 3, x))(x)
    mode = np.asarray(x).astype(int) % 3  # the last mode that evaluated each trial
    xs = np.asarray(x)
    np.testing.assert_array_equal(
        out["value"], xs[:, None, None] * np.arange(6.0).reshape(2, 3) + mode[:, None, None]
    )
    np.testing.assert_array_equal(out["flag"], (xs > 4) ^ (mode == 1))
    np.testing.assert_array_equal(out["count"], 7 * mode)
    np.testing.assert_array_equal(out["big"], (xs * 1e6).astype(np.int64) + 2**40)
    np.testing.assert_array_equal(out["mode"], mode.astype(np.float32))
    assert out["flag"].dtype == bool and out["count"].dtype == jnp.int32
    assert out["big"].dtype == jnp.int64 and out["mode"].dtype == jnp.float32
    assert out["value"].shape == (11, 2, 3)


def test_set_entry_is_at_set_under_vmap():
    """``set_entry`` equals ``.at[i].set`` (vmapped, per-trial index), leaves the values where
    ``where`` is false and changes nothing for an index out of range."""
    values = jnp.arange(12.0).reshape(3, 4)
    i = jnp.array([0, 3, 1])
    new = jnp.array([-1.0, -2.0, -3.0])
    got = jax.vmap(set_entry)(values, i, new)
    np.testing.assert_array_equal(got, jax.vmap(lambda v, i, x: v.at[i].set(x))(values, i, new))
    where = jnp.array([True, False, True])
    got = jax.vmap(set_entry)(values, i, new, where)
    np.testing.assert_array_equal(got[1], values[1])
    np.testing.assert_array_equal(set_entry(values[0], 4, 9.0), values[0])


def _newton_loop():
    """Newton's iteration for sqrt(a) as a chunked loop whose data hold a value that depends
    only on the (possibly shared) start ``s``."""

    def init(mode, a, s):
        return (jnp.asarray(0), s + 0.0 * mode), (a, 2.0 * s)

    def body(it, mode, step, state, data):
        k, x = state
        a, _ = data
        return jax.lax.cond(step, lambda: (k + 1, 0.5 * (x + a / x)), lambda: state)

    def running(state):
        return state[0] < 60

    def finish(mode, state, data):
        k, x = state
        return (k, x * data[1]), jnp.asarray(0, jnp.int32)

    return chunked_loop(init, body, running, finish, chunk_size=4, passes=1, stragglers=4)


def test_chunked_loop_keeps_shared_arguments_unbatched():
    """An argument that is the same for every trial (the arm's frames) is handed to every chunk
    as it is, and the data that depend only on it stay unbatched: the same results as with the
    argument broadcast to the batch."""
    solve = _newton_loop()
    a = jnp.linspace(1.0, 50.0, 11)
    shared = jax.jit(jax.vmap(solve, in_axes=(0, None)))(a, 3.0)
    batched = jax.jit(jax.vmap(solve))(a, jnp.full_like(a, 3.0))
    for x, y in zip(shared, batched, strict=True):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_allclose(shared[1], 6.0 * np.sqrt(np.asarray(a)), rtol=1e-14)


def test_batched_outputs_follow_the_dependencies():
    """``_batched_outputs``: an output depends on a marked input through any chain of
    equations, literals and unmarked inputs do not make it batched."""

    def fn(a, b, c):
        return a * 2.0, jnp.sin(b) + c, jnp.ones(3), b + 1.0

    f32 = jax.ShapeDtypeStruct((), jnp.float32)
    replay, _ = _traced_once(fn, f32, f32, f32)
    assert _batched_outputs(replay, [True, False, False]) == [True, False, False, False]
    assert _batched_outputs(replay, [False, False, True]) == [False, True, False, False]
    assert _batched_outputs(replay, [False, True, False]) == [False, True, False, True]


def test_empty_batches_give_empty_outputs():
    """Zero trials: empty outputs of the right shapes, no error (a division by the chunk size
    raised ``ZeroDivisionError`` before)."""
    x = jnp.zeros((0, 3))
    out = jax.jit(lambda x: two_pass(_flag_multiples_of_three([]), 4, x))(x)
    assert out.shape == (0, 3) and out.dtype == x.dtype

    def one(second, x):
        return jnp.where(second, 10 * x, x), jnp.any(x < 0) & ~second

    assert jax.vmap(chunked_vmap(one, 4, second_pass=True))(x).shape == (0, 3)
    k, root = jax.vmap(chunked_vmap(_newton_sqrt, 4), in_axes=(0, 0, None))(x[:, 0], x[:, 0], 1e-9)
    assert k.shape == (0,) and root.shape == (0,)


def test_batched_like_changes_no_value():
    """``batched_like`` (the solvers' initial loop carries) is the identity, for either value of
    the reference, batched or not, NaNs included."""
    tree = (jnp.zeros(3), jnp.asarray(False), jnp.full(2, jnp.nan), jnp.asarray(7))
    for ref in (True, False):
        out = batched_like(jnp.asarray(ref), tree)
        for a, b in zip(out, tree, strict=True):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
    out = jax.vmap(lambda x: batched_like(x > 0, tree))(jnp.array([-1.0, 1.0]))
    for a, b in zip(out, tree, strict=True):
        np.testing.assert_array_equal(a, jnp.broadcast_to(b, (2,) + b.shape))

    def newton(a, x0):  # the carry starts batched: the same loop, the same result
        return _newton_sqrt(a, batched_like(a > 0, x0), 1e-12)

    a = jnp.logspace(-3, 12, 5)
    np.testing.assert_array_equal(
        jax.vmap(newton, in_axes=(0, None))(a, 1.0)[1],
        jax.vmap(_newton_sqrt, in_axes=(0, None, None))(a, 1.0, 1e-12)[1],
    )


@pytest.mark.slow
def test_solvers_split_over_two_cpu_devices_finish_and_match():
    """Both chunked solvers on 2 x 128 trials split over 2 CPU devices (``use_cpu_devices``,
    as ``cdra-jax sweep`` and ``benchmarks/throughput.py --devices 2`` run them) finish and give
    the one-device results. With a pool of 2 threads (no ``PJRT_NPROC``) this hung in
    batched LAPACK (``cdra_jax.parallel``); a work queue (a data-dependent gather of trials inside
    a loop) deadlocked there too. In a subprocess, with a timeout."""
    script = textwrap.dedent(
        """
        from cdra_jax.parallel import split_over_devices, use_cpu_devices
        use_cpu_devices(2)
        import jax
        jax.config.update("jax_enable_x64", True)
        import numpy as np
        from cdra_jax import NoiseModel, calibrate_lm, calibrate_paper, default_arm, simulation
        assert len(jax.devices()) == 2, jax.devices()
        arm, noise = default_arm(), NoiseModel(0.05, 1e-3)
        keys = jax.random.split(jax.random.PRNGKey(0), 256)
        sim = jax.vmap(lambda k: simulation.simulate_trial(k, arm, 15, noise=noise))
        q, T, *_ = jax.jit(sim)(keys)
        q, T = np.asarray(q), np.asarray(T)
        for solve in (calibrate_paper, calibrate_lm):
            f = jax.jit(jax.vmap(lambda q, T: solve(arm, q, T, noise, throw=False)))
            sol = split_over_devices(f, (q, T), jax.devices())
            assert np.all(sol.converged), solve
            # the second device's half against the same trials solved on the first device
            ref = split_over_devices(f, (q[128:], T[128:]), jax.devices()[:1])
            np.testing.assert_allclose(sol.errors[128:], ref.errors, rtol=0, atol=1e-9)
            np.testing.assert_array_equal(sol.iterations[128:], ref.iterations)
        """
    )
    run_on_two_cpu_devices(script, timeout=300, forced=False)
