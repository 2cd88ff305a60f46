"""The package's compile options (cdra_jax.compilation) and its jit wrappers."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cdra_jax
from cdra_jax import compilation, simulation


@pytest.fixture(scope="module", autouse=True)
def _xla_flags_read_before_the_tests_remove_them():
    """XLA reads ``XLA_FLAGS`` once, at the first compilation in the process. Some tests here
    remove it (``monkeypatch.delenv``) and compile: were that the process's first compilation
    (this module run on its own), every later one would be without the suite's flags, at XLA's
    default optimisation level and emitters, twice the CPU time, and the solver test below
    would compare the default emitters with themselves. Compile once with the flags first."""
    jax.jit(lambda x: x + 1.0).lower(1.0).compile()


def test_preferred_options_are_accepted_here(monkeypatch):
    # jaxlib of this project's pin knows the options; the probe compiles a trivial program.
    # (The suite's conftest sets an XLA_FLAGS option, which compiler_options would leave out.)
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    opts = compilation.compiler_options()
    assert opts == compilation.PREFERRED_OPTIONS
    fast = compilation.compiler_options(fast_compile=True)
    assert fast == {**compilation.PREFERRED_OPTIONS, **compilation.FAST_COMPILE_OPTIONS}
    assert compilation.compiler_options() is not compilation.compiler_options()  # a copy


def test_unknown_option_is_left_out(monkeypatch):
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    assert not compilation._accepted(("xla_no_such_option_for_cdra_jax", True))
    monkeypatch.setattr(compilation, "PREFERRED_OPTIONS", {"xla_no_such_option_for_cdra_jax": True})
    assert compilation.compiler_options() == {}
    # Probed together first, then one by one: the known option is kept.
    known = {"xla_cpu_use_fusion_emitters": False}
    monkeypatch.setattr(
        compilation, "PREFERRED_OPTIONS", {"xla_no_such_option_for_cdra_jax": True, **known}
    )
    assert compilation.compiler_options() == known


def test_environment_switches(monkeypatch):
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    monkeypatch.setenv(compilation.DEFAULTS_ENV, "1")
    assert compilation.compiler_options() == {}
    assert compilation.compiler_options(fast_compile=True) == compilation.FAST_COMPILE_OPTIONS
    monkeypatch.delenv(compilation.DEFAULTS_ENV)
    # An option the user sets in XLA_FLAGS is theirs: not overridden per compilation.
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=true")
    assert "xla_cpu_use_fusion_emitters" not in compilation.compiler_options()


def test_jit_wrappers_work_top_level_and_nested():
    f = compilation.jit(lambda x: jnp.sin(x) * x)
    g = compilation.filter_jit(lambda x, n: x**n)  # n: a static Python int for filter_jit
    x = jnp.linspace(0.1, 1.0, 4)
    np.testing.assert_allclose(f(x), np.sin(x) * x, rtol=1e-15)
    np.testing.assert_allclose(g(x, 3), x**3, rtol=1e-15)
    # Nested: inside jit, vmap and grad JAX refuses compiler_options; the wrappers fall back.
    np.testing.assert_allclose(jax.jit(lambda y: f(y) + g(y, 2))(x), np.sin(x) * x + x**2)
    np.testing.assert_allclose(jax.vmap(f)(x), np.sin(x) * x, rtol=1e-15)
    np.testing.assert_allclose(jax.grad(lambda y: g(y, 3))(2.0), 12.0)
    assert f.lower(x).compile()(x).shape == (4,)
    assert f.__name__ == "<lambda>"

    def raises(y):
        raise ValueError("the function's own error")

    with pytest.raises(ValueError, match="own error"):
        compilation.jit(raises)(x)


def test_nested_call_traces_the_function_once():
    traces = []

    def fn(y):
        traces.append(1)
        return 2 * y

    f = compilation.jit(fn)
    np.testing.assert_allclose(jax.jit(lambda y: f(y) - 1)(jnp.arange(3.0)), [-1.0, 1.0, 3.0])
    assert len(traces) == 1  # straight to the plain jit: no refused attempt with the options


def test_filter_jit_traces_the_numbers_of_a_module_not_those_passed_alone():
    """A NoiseModel of floats is data: one program for every noise value, with the promotion
    of a Python number (a float32 input stays float32); a float passed as an argument itself
    (a tolerance) stays static, and so do a module's static fields."""
    traces = []

    def scaled(noise, x, k):
        traces.append(k)
        return k * x / noise.position_mm + noise.rotation_rad

    f = compilation.filter_jit(scaled)
    x = jnp.ones(3, jnp.float32)
    a = f(cdra_jax.NoiseModel(0.5, 1e-3), x, 2.0)
    b = f(cdra_jax.NoiseModel(0.25, 2e-3), x, 2.0)
    assert traces == [2.0]
    assert a.dtype == b.dtype == jnp.float32
    np.testing.assert_allclose(b, 8.002, rtol=1e-6)
    f(cdra_jax.NoiseModel(0.25, 2e-3), x, 3.0)
    assert traces == [2.0, 3.0]
    noise = cdra_jax.NoiseModel(0.5, 1e-3)
    f(noise, x, 2.0)
    assert type(noise.position_mm) is float  # the caller's module is not changed

    arm = cdra_jax.default_arm()
    names = compilation.filter_jit(lambda arm, x: (arm.name, x * arm.gravity[2]))
    assert names(arm, 2.0)[0] == arm.name


def test_probe_runs_when_first_used_inside_another_jit(monkeypatch):
    # The options' probe compiles its own small program while the outer jit traces. (A call
    # with a traced argument goes to the plain jit without probing; one with constants only
    # tries the options first.)
    monkeypatch.delenv("XLA_FLAGS", raising=False)  # the suite's flags would skip the probe
    compilation._accepted.cache_clear()
    h = compilation.jit(lambda y: 3 * y)
    x = np.arange(3.0)
    np.testing.assert_allclose(jax.jit(lambda y: h(x) + y)(1.0), 3 * x + 1, rtol=1e-15)
    assert compilation._accepted.cache_info().misses == 1  # all the options in one probe


def test_options_change_no_result_of_the_solvers():
    """The paper and LM solvers compiled with the package's options and with every HLO pass
    are bitwise equal; with XLA's default (MLIR) emitters they agree to rounding (bitwise at
    XLA's default optimisation level on 10^4 trials, benchmarks/README.md; this suite compiles
    without LLVM's optimisations, where the two emitters round differently in the last
    digits). The suite's XLA_FLAGS select the older
    emitters, so the default ones are asked for explicitly."""
    arm = cdra_jax.default_arm()
    keys = jax.random.split(jax.random.key(3), 6)
    q, T, *_ = jax.jit(jax.vmap(lambda k: simulation.simulate_trial(k, arm, 8)))(keys)

    def solve(qq, TT):
        return (
            cdra_jax.calibrate_paper(arm, qq, TT, throw=False),
            cdra_jax.calibrate_lm(arm, qq, TT, throw=False),
        )

    # One trace and lowering, compiled twice: with the package's options (cdra_jax.jit), and
    # with the default emitters added at compilation (the compile-time options come last and
    # win, as jax.jit's compiler_options would).
    lowered = cdra_jax.jit(jax.vmap(solve)).lower(q, T)
    ours = lowered.compile()(q, T)
    mlir = {"xla_cpu_use_fusion_emitters": True}
    plain = lowered.compile(mlir)(q, T)
    # With every HLO pass (the package leaves out the verifier and the while-loop simplifier):
    # the same program, bitwise.
    every_pass = lowered.compile({"xla_disable_hlo_passes": ""})(q, T)
    for a, b in zip(ours, every_pass, strict=True):
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
            np.testing.assert_array_equal(x, y)
    for a, b in zip(ours, plain, strict=True):
        assert bool(jnp.all(a.converged)) and bool(jnp.all(b.converged))
        np.testing.assert_array_equal(a.iterations, b.iterations)
        np.testing.assert_array_equal(a.rank, b.rank)
        np.testing.assert_allclose(a.frames, b.frames, rtol=0, atol=1e-9)
        np.testing.assert_allclose(a.errors, b.errors, rtol=0, atol=1e-9)
        np.testing.assert_allclose(a.singular_values, b.singular_values, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(a.delta_p, b.delta_p, rtol=0, atol=1e-9)


def test_collection_is_paused_while_tracing_and_restored_after():
    """The package's jit turns Python's garbage collector off while it traces, lowers or calls
    (compiles) and restores its state after: on stays on, off stays off, also after an error."""
    import gc

    seen = []

    def f(x):
        seen.append(gc.isenabled())
        return x + 1

    assert gc.isenabled()
    fn = compilation.jit(f)
    fn.lower(1.0)
    fn(jnp.ones(3))  # another shape: traced and compiled by the call
    assert seen == [False, False] and gc.isenabled()

    def broken(x):
        raise RuntimeError("in the trace")

    with pytest.raises(RuntimeError):
        compilation.jit(broken)(1.0)
    assert gc.isenabled()
    gc.disable()
    try:
        with compilation.collection_paused():
            pass
        assert not gc.isenabled()
    finally:
        gc.enable()
