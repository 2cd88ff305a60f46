"""Every CPU core at work: the host as several XLA:CPU devices, one part of a batch per device.

XLA:CPU runs one compiled program on one thread: a vmapped solver on a two-core machine keeps
1.2 cores busy (measured, ``benchmarks/README.md``). JAX can present the host as ``n`` CPU
devices (``jax_num_cpu_devices``); programs on different devices run at the same time, so a
batch split into one part per device uses ``n`` cores (:func:`split_over_devices`).

One trap, found with ``gdb`` (jax/jaxlib 0.10.2): a batched LAPACK call (``jnp.linalg.cholesky``,
``qr``, ``svd`` under ``vmap``) splits its batch into tasks on jaxlib's intra-op thread pool and
waits for them, from a thread of that same pool. Devices that execute at once each hold a pool
thread, so when the pool has no more threads than devices, every thread waits and the program
hangs at 0 % CPU. The pool's size is read once, when the CPU client starts: from the environment
variable ``PJRT_NPROC`` (or ``NPROC``), else the number of schedulable cores, two on a two-core
machine. :func:`use_cpu_devices` therefore sets ``PJRT_NPROC`` to cores + devices along with the
device count, and :func:`check_devices` refuses (``ValueError``, not a hang) a set of CPU devices
that the pool cannot serve. GPUs do not use this pool.

Both settings act only before JAX starts its CPU backend (the first computation or
``jax.devices()``): call :func:`use_cpu_devices` first thing, as ``cdra-jax sweep`` and
``benchmarks/throughput.py --devices`` do, or set ``JAX_NUM_CPU_DEVICES`` and ``PJRT_NPROC`` in
the environment.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np

_POOL_VARIABLES = ("PJRT_NPROC", "NPROC")  # read in this order by XLA's CPU client


def schedulable_cores() -> int:
    """Cores this process may run on (its CPU affinity; ``os.cpu_count()`` where unknown)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        return os.cpu_count() or 1


def cpu_pool_threads() -> int:
    """Threads of jaxlib's intra-op pool, as XLA's CPU client sizes it at start-up.

    The first of ``PJRT_NPROC``, ``NPROC`` that holds an integer, else
    :func:`schedulable_cores`.
    """
    for name in _POOL_VARIABLES:
        value = os.environ.get(name, "").strip()
        try:
            return max(0, int(value))
        except ValueError:
            continue
    return schedulable_cores()


def _backends_started() -> bool:
    from jax._src import xla_bridge

    return bool(xla_bridge.backends_are_initialized())


def use_cpu_devices(n: int | None = None) -> int:
    """Present the host as ``n`` XLA:CPU devices, with a thread pool that serves them all.

    Sets ``jax_num_cpu_devices = n`` and, for ``n > 1`` when the pool would have no more
    threads than devices, ``PJRT_NPROC`` = cores + ``n`` (see the module docstring). Call it
    before JAX starts its CPU backend. If the backend has already started with ``n`` CPU
    devices and a large enough pool, this is a no-op.

    Args:
        n: number of CPU devices (default: :func:`schedulable_cores`).

    Returns:
        ``n``.

    Raises:
        ValueError: ``n < 1``.
        RuntimeError: the CPU backend has already started with another device count or too
            small a pool.
    """
    n = schedulable_cores() if n is None else int(n)
    if n < 1:
        raise ValueError(f"use_cpu_devices: n must be at least 1, got {n}")
    if _backends_started():
        have = len(jax.devices("cpu"))
        if have == n and (n == 1 or cpu_pool_threads() > n):
            return n
        raise RuntimeError(
            f"use_cpu_devices({n}) must run before JAX starts its CPU backend, which has already "
            f"started with {have} CPU device(s) and a pool of {cpu_pool_threads()} thread(s); "
            f"call it first thing, or start Python with JAX_NUM_CPU_DEVICES={n} "
            f"PJRT_NPROC={schedulable_cores() + n} in the environment"
        )
    jax.config.update("jax_num_cpu_devices", n)
    if n > 1 and cpu_pool_threads() <= n:
        os.environ["PJRT_NPROC"] = str(schedulable_cores() + n)
    return n


def check_devices(devices: Sequence[jax.Device]) -> None:
    """Raise ``ValueError`` when running on all of ``devices`` at once could hang.

    That is the case for more than one CPU device with a pool of no more threads than CPU
    devices (module docstring). One device, or GPUs, always pass.
    """
    n_cpu = sum(d.platform == "cpu" for d in devices)
    if n_cpu > 1 and cpu_pool_threads() <= n_cpu:
        raise ValueError(
            f"{n_cpu} CPU devices with a thread pool of {cpu_pool_threads()}: jaxlib's batched "
            "LAPACK calls would wait on each other and the computation would hang. Start with "
            f"cdra_jax.parallel.use_cpu_devices({n_cpu}) before JAX runs anything, or set "
            f"PJRT_NPROC={schedulable_cores() + n_cpu} in the environment (or pass one device)"
        )


def split_over_devices(
    fn: Callable[..., Any],
    batched: Sequence[Any],
    devices: Sequence[jax.Device],
    *shared: Any,
) -> Any:
    """``fn(*shared, *batched)`` computed in one part per device, at the same time.

    Every leaf of ``batched`` has the batch on its leading axis, of a size divisible by
    ``len(devices)``; part ``i`` goes to ``devices[i]`` and ``fn`` (a jitted function) runs
    there; JAX dispatches the parts asynchronously, so the devices work concurrently. The
    results are fetched to the host (NumPy) and concatenated along the leading axis, in order.
    ``shared`` arguments go to every part as they are. With one device this is ``fn`` on the
    whole batch. JAX compiles ``fn`` once per device, one after the other. (Dispatching the
    parts from one thread each did not overlap those compilations and made the steady state
    slower: 4427-4576 vs 5090-5207 trials/s for 4000 paper-solver trials, side by side.)

    This is explicit data parallelism rather than a sharded ``jit``: the trials are
    independent, so no communication is needed, and it was measured faster than the SPMD
    partitioning of the chunked solvers (``benchmarks/README.md``).
    """
    check_devices(devices)
    n = len(devices)
    size = jax.tree.leaves(batched)[0].shape[0]
    if size % n:
        raise ValueError(f"split_over_devices: batch of {size} does not split over {n} devices")
    per = size // n
    outs = []
    for i, device in enumerate(devices):
        part = jax.tree.map(
            lambda x, i=i, d=device: jax.device_put(x[i * per : (i + 1) * per], d), batched
        )
        outs.append(fn(*shared, *part))
    host = jax.device_get(outs)
    return jax.tree.map(lambda *xs: np.concatenate([np.asarray(x) for x in xs]), *host)
