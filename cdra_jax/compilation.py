"""XLA compile options for the package's compiled programs, and ``jit`` wrappers that apply them.

The calibration solvers are long element-wise programs (the pose-last kernels of
:mod:`cdra_jax.calibration.kernels`) inside ``while`` loops. XLA:CPU (jaxlib 0.10) emits its
fused element-wise kernels with the MLIR "fusion emitters" by default; for these programs its
older LLVM-IR emitters (``xla_cpu_use_fusion_emitters=False``) compile 1.2-1.5x faster and the
code runs a few per cent faster, with bitwise equal results at XLA's default optimisation level
(``benchmarks/README.md``; 10^4 trials, medians of 5 fresh processes: LM 5.24 ->
4.43 s, paper solver 4.13 -> 2.72 s to trace and compile; interleaved calls: paper 1.09x, LM
1.04x the throughput). Two of XLA's HLO passes are left out (``xla_disable_hlo_passes``): the
HLO verifier, which checks XLA's own invariants after every pass (a debugging aid), and the
while-loop simplifier, which works out the trip counts of the solvers' nested loops by copying
their computations again at every round of the simplification: of the vmapped paper solver's
compilation, XLA's HLO passes then take about 0.13 s instead of 0.24 s; the code runs as fast
and the results are bitwise equal (``benchmarks/README.md``, *What XLA compiles*).

Every place where the package compiles a program (the sweeps, the Section V/VI reproduction,
the command line, the analyses) uses :func:`jit` or :func:`filter_jit`, which pass
:func:`compiler_options` to :func:`jax.jit`. When you compile
the solvers yourself, pass them too::

    solve = cdra_jax.jit(jax.vmap(lambda q, T: cdra_jax.calibrate_paper(arm, q, T, throw=False)))
    # or: jax.jit(..., compiler_options=cdra_jax.compiler_options())

The options are resolved at the first compilation, not at import: an option that the installed
XLA does not know, or that the user sets in ``XLA_FLAGS`` (which then wins), is left out, and
``CDRA_JAX_XLA_DEFAULTS=1`` in the environment turns all of them off (XLA's own defaults, e.g.
to compare). The probe compiles on the default backend, so on a GPU an option is kept only
if that backend accepts it (the emitters are a CPU code-generation option; none of the options
was measured on a GPU: this project's machine has none).
"""

from __future__ import annotations

import contextlib
import functools
import gc
import os
from collections.abc import Callable
from typing import Any, TypeVar, cast

import jax
import numpy as np

PREFERRED_OPTIONS: dict[str, Any] = {
    "xla_cpu_use_fusion_emitters": False,
    "xla_disable_hlo_passes": "hlo-verifier,simplify-while-loops",
}
"""XLA debug options the package compiles with (see the module docstring)."""

FAST_COMPILE_OPTIONS: dict[str, Any] = {"xla_backend_optimization_level": 0}
"""Added by ``fast_compile=True``: no LLVM optimisation passes. Several times quicker to
compile and up to ~2x slower to run: the right trade for one-off runs of a few hundred trials."""

DEFAULTS_ENV = "CDRA_JAX_XLA_DEFAULTS"
"""Environment variable: ``1`` compiles with XLA's defaults (:func:`compiler_options` is empty)."""


def compiler_options(fast_compile: bool = False) -> dict[str, Any]:
    """The options for :func:`jax.jit`'s ``compiler_options`` (a new dict each call).

    Args:
        fast_compile: also add :data:`FAST_COMPILE_OPTIONS`.

    Returns:
        The options of :data:`PREFERRED_OPTIONS` (and :data:`FAST_COMPILE_OPTIONS`) that the
        installed XLA accepts and that ``XLA_FLAGS`` does not set; empty when
        ``CDRA_JAX_XLA_DEFAULTS=1``. ``fast_compile`` options are kept even then (they are an
        explicit request of the caller).
    """
    wanted = {} if os.environ.get(DEFAULTS_ENV, "") == "1" else dict(PREFERRED_OPTIONS)
    if fast_compile:
        wanted.update(FAST_COMPILE_OPTIONS)
    flags = os.environ.get("XLA_FLAGS", "")
    candidates = {k: v for k, v in wanted.items() if f"--{k}" not in flags}
    if not candidates or _accepted(*candidates.items()):
        return candidates
    return {k: v for k, v in candidates.items() if _accepted((k, v))}


@functools.cache
def _accepted(*options: tuple[str, Any]) -> bool:
    """Whether XLA accepts the compile options ``(name, value)`` together: one trivial
    compilation, cached (all the options at once first, one by one only where that fails)."""
    try:
        jax.jit(lambda x: x, compiler_options=dict(options)).lower(0.0).compile()
    except jax.errors.JaxRuntimeError as e:
        if "compile option" in str(e):
            return False
        raise
    return True


def any_tracer(tree: Any) -> bool:
    """Whether any leaf of ``tree`` is a tracer (the call is inside ``jit``, ``vmap``, ``grad``)."""
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(tree))


_NESTED = "can only be passed to top-level"
"""JAX's error for ``compiler_options`` on a ``jit`` traced inside another transformation."""


class _LazyJit:
    """A jitted function whose compile options are resolved at its first use (not at import,
    so that e.g. :func:`cdra_jax.parallel.use_cpu_devices` can still configure the backend).

    JAX accepts ``compiler_options`` only on a top-level ``jit``; called inside another ``jit``,
    ``vmap`` or ``grad`` the function runs as a plain ``jit`` (the enclosing program's options
    apply to it).
    """

    def __init__(
        self,
        make: Callable[[dict[str, Any]], Callable],
        fun: Callable,
        fast: bool,
        prepare: Callable[[Any], Any] | None = None,
    ):
        self._make = make
        self._fast = fast
        self._prepare = prepare
        self._jitted: Callable | None = None
        self._plain: Callable | None = None
        functools.update_wrapper(self, fun)

    @property
    def jitted(self) -> Any:
        """The underlying jitted function (built at the first access)."""
        if self._jitted is None:
            self._jitted = self._make(compiler_options(self._fast))
        return self._jitted

    @property
    def plain(self) -> Any:
        """The same function jitted without compile options (for nested calls)."""
        if self._plain is None:
            self._plain = self._make({})
        return self._plain

    def __call__(self, *args, **kwargs):
        if self._prepare is not None:
            args, kwargs = self._prepare((args, kwargs))
        # A traced argument means a nested call: go to the plain jit directly rather than
        # tracing the function once for JAX to refuse the options and once more without them.
        if any_tracer((args, kwargs)):
            return self.plain(*args, **kwargs)
        try:  # nested without a traced argument (e.g. constants inside an outer jit)
            with collection_paused():
                return self.jitted(*args, **kwargs)
        except ValueError as e:
            if _NESTED not in str(e):
                raise
        return self.plain(*args, **kwargs)

    def lower(self, *args, **kwargs):
        """As ``jax.jit(...).lower``."""
        with collection_paused():
            return self.jitted.lower(*args, **kwargs)

    def trace(self, *args, **kwargs):
        """As ``jax.jit(...).trace``."""
        with collection_paused():
            return self.jitted.trace(*args, **kwargs)


@contextlib.contextmanager
def collection_paused():
    """Python's cyclic garbage collector off for the block (restored after; nested blocks
    leave it to the outermost).

    Tracing a solver creates tens of thousands of Python objects (tracers, equations), and the
    collector's full collections, which this triggers, traverse every object the process holds
    (after a simulation, its cached programs too): about a fifth of the paper solver's trace
    time (0.38-0.45 s instead of 0.48-0.59 s after generating the problems,
    ``benchmarks/README.md``). The garbage of the block is collected after it, as usual. Around
    a call that does not compile, the block costs two calls of :mod:`gc`.
    """
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def jit(fun: Callable, *, fast_compile: bool = False, **jit_kwargs) -> Any:
    """:func:`jax.jit` with :func:`compiler_options` (merged under any ``compiler_options`` given).

    Args:
        fun: the function.
        fast_compile: add :data:`FAST_COMPILE_OPTIONS`.
        **jit_kwargs: passed to :func:`jax.jit` (``static_argnames``, ...).

    Returns:
        A callable with ``lower`` and ``trace`` as a :func:`jax.jit` function has.
    """
    own = jit_kwargs.pop("compiler_options", None) or {}

    def make(options):
        return jax.jit(fun, compiler_options={**options, **own}, **jit_kwargs)

    return _LazyJit(make, fun, fast_compile)


def filter_jit(fun: Callable, *, fast_compile: bool = False, **jit_kwargs) -> Any:
    """:func:`equinox.filter_jit` with :func:`compiler_options` (see :func:`jit`).

    Unlike plain :func:`equinox.filter_jit`, the Python numbers held in the data fields of an
    ``equinox.Module`` argument (a :class:`~cdra_jax.calibration.NoiseModel` of floats, say)
    are traced, as weakly typed scalars (the promotion rules of a Python number), not compiled
    in as constants: one program serves every noise value, where each value would otherwise
    compile its own (1.5 s for the geometric fit of a diagnosis, whose noise is estimated
    afresh for every recording). A module's static fields (``equinox.field(static=True)``)
    and the numbers passed as arguments themselves (tolerances, counts) stay static.
    """
    import equinox as eqx

    own = jit_kwargs.pop("compiler_options", None) or {}

    def make(options):
        return eqx.filter_jit(fun, compiler_options={**options, **own}, **jit_kwargs)

    return _LazyJit(make, fun, fast_compile, prepare=_module_numbers_traced)


def _module_numbers_traced(tree: Any) -> Any:
    """``tree`` with every Python ``float`` inside an ``equinox.Module``'s data fields made a
    weakly typed JAX scalar (``jnp.asarray``), so that :func:`filter_jit` traces it."""
    import equinox as eqx
    import jax.numpy as jnp

    def numbers(module: Any) -> Any:
        if not isinstance(module, eqx.Module):
            return module
        return jax.tree.map(lambda x: jnp.asarray(x) if type(x) is float else x, module)

    return jax.tree.map(numbers, tree, is_leaf=lambda x: isinstance(x, eqx.Module))


_F = TypeVar("_F", bound=Callable[..., object])

_ARRAY_LIKE = (int, float, complex, list, tuple, np.ndarray, np.generic)


def compiled_when_eager(fn: _F) -> _F:
    """``fn`` run as one compiled program (one per shape, dtype and static part) when it is
    called on concrete values, and traced inline, as written, when any argument is a tracer
    (inside ``jit``, ``vmap``, ``grad``).

    For the small maps that are called both ways (:mod:`cdra_jax.lie`, the chain of
    :mod:`cdra_jax.arm`): called eagerly, they would otherwise dispatch their 20-100 operations
    one by one, each compiled at its first use for every new shape (loading a model, forward
    kinematics of a few poses, a report); one program per shape is cheaper to compile and to
    run. Traced, nothing changes (no nested program in the caller's). The values are those of
    the traced function. Array-likes (numbers, lists, numpy arrays) are made arrays first;
    other arguments are pytrees (:func:`equinox.filter_jit`: their arrays traced, everything
    else static).
    """
    import equinox as eqx

    compiled = eqx.filter_jit(fn)

    @functools.wraps(fn)
    def call(*args):
        if any_tracer(args):
            return fn(*args)
        return compiled(*(_as_array(a) if isinstance(a, _ARRAY_LIKE) else a for a in args))

    return cast(_F, call)


def compiled_when_eager_args(*array_args: str) -> Callable[[_F], _F]:
    """:func:`compiled_when_eager` for functions with keyword and static arguments.

    Called on concrete values, ``fn`` runs as one compiled program (:func:`equinox.filter_jit`)
    per shape and static part; traced inline, as written, when any argument is a tracer. The
    arguments named in ``array_args`` are made arrays when they are array-likes (numbers,
    lists, numpy arrays; not ``bool``), so that they are traced (each tolerance value does not
    compile a program of its own); every other argument is a pytree whose arrays are traced and
    whose other values (iteration caps, counts, flags, strings, ``None``) are static.
    """

    def wrap(fn: _F) -> _F:
        import inspect

        import equinox as eqx

        signature = inspect.signature(fn)
        compiled = eqx.filter_jit(fn)

        @functools.wraps(fn)
        def call(*args, **kwargs):
            if any_tracer((args, kwargs)):
                return fn(*args, **kwargs)
            bound = signature.bind(*args, **kwargs)
            for name in array_args:
                value = bound.arguments.get(name)
                if isinstance(value, _ARRAY_LIKE) and not isinstance(value, bool):
                    bound.arguments[name] = _as_array(value)
            return compiled(*bound.args, **bound.kwargs)

        return cast(_F, call)

    return wrap


def eager_program(fn: Callable[..., Any], *static: Any) -> Callable[..., Any]:
    """``fn`` with its leading arguments ``static`` (hashable: indices, names, flags, objects)
    bound as static: one compiled program per value of ``static`` and shapes when called on
    concrete arrays, traced inline under ``jit``, ``vmap`` and ``grad``
    (:func:`compiled_when_eager`, which would make numbers and tuples arrays). Made once per
    ``(fn, static)``."""
    return _bound_program(fn, static)


@functools.cache
def _bound_program(fn: Callable[..., Any], static: tuple) -> Callable[..., Any]:
    return compiled_when_eager(functools.partial(fn, *static))


def device_array(a: Any) -> jax.Array:
    """``a`` (a numpy array, a list of numbers) as a JAX array with the values and dtype of
    ``jnp.asarray(a)``, without compiling anything: ``jnp.asarray`` of a numpy array compiles
    a copy program for every new shape and dtype (jaxlib 0.10), ``jax.device_put`` does not.
    The array put is a private copy (on the CPU the JAX array may share its memory), so the
    caller's array can change freely afterwards."""
    return jax.device_put(np.array(a))


def _as_array(a: Any) -> Any:
    """An array-like argument of a compiled call as a JAX array: numpy arrays and lists through
    :func:`device_array`, Python numbers by ``jnp.asarray`` (weakly typed, as when traced)."""
    if isinstance(a, np.ndarray | np.generic | list | tuple):
        return device_array(a)
    return jax.numpy.asarray(a)


@functools.cache
def cached_filter_jit(fun: Callable) -> Any:
    """:func:`filter_jit` of ``fun``, made once per function, so that repeated calls with the
    same shapes reuse the compiled program (the workflows compile each solve this way: one
    compiled program starts several times faster than op-by-op dispatch)."""
    return filter_jit(fun)


def default_cache_dir() -> str:
    """Where the command line keeps compiled programs between runs:
    ``$CDRA_JAX_CACHE_DIR``, else JAX's own ``$JAX_COMPILATION_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/cdra_jax/xla``, else ``~/.cache/cdra_jax/xla``."""
    explicit = os.environ.get("CDRA_JAX_CACHE_DIR") or os.environ.get("JAX_COMPILATION_CACHE_DIR")
    if explicit:
        return explicit
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "cdra_jax", "xla")


def enable_persistent_cache(path: str | None = None) -> str:
    """Keep compiled programs on disk (JAX's persistent compilation cache) so that a second run
    with the same shapes skips XLA compilation; returns the folder (created if missing).

    Every program is cached, however fast it compiled (the command line's solves compile in
    seconds and run in milliseconds). The folder grows with every new shape (a few MB per
    program); delete it at any time to reclaim the space. Changes JAX's global configuration:
    call it from an
    application (the ``cdra-jax`` command does, unless ``--no-cache``), not from library code.
    """
    import jax

    folder = path or default_cache_dir()
    os.makedirs(folder, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return folder


def batched_like(ref: jax.Array, tree):
    """``tree`` unchanged, every leaf made to depend on ``ref`` (a scalar computed from a trial's
    inputs), so that under ``vmap`` the leaves are batched from the start.

    For the initial carry of a ``while_loop`` whose body makes these leaves batched: JAX batches
    a loop body again whenever the batched-ness of the carry changes in the body (a fixed point),
    so a carry that starts unbatched (zeros, NaN histories, a ``False`` flag) costs a second
    batching pass over the whole body at trace time. ``where(ref, x, x)`` is ``x`` (XLA folds
    it away), so the compiled program and the results are unchanged.
    """
    return jax.tree.map(lambda x: jax.numpy.where(ref, x, x), tree)


GC_THRESHOLDS = (20_000, 50, 100)
"""Thresholds of Python's cycle collector (``gc.set_threshold``) for a process that traces many
programs: the ``cdra-jax`` command and the test processes (CPython's default: 700, 10, 10).
Tracing and lowering create millions of short-lived objects, and the default runs a collection
every few hundred of them. A warm ``cdra-jax calibrate`` of 15 poses: 1.97 s against 2.10 s
(medians of 5, alternated). The package's library functions never change them (its
:func:`jit` turns the collector off while it traces and compiles: :func:`collection_paused`)."""
