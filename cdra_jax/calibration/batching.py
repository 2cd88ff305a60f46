"""Chunked batching of per-trial solvers: ``vmap`` runs the trials in cache-sized chunks.

``jax.vmap`` of an iterative solver turns its ``while_loop`` into one loop over the whole batch:
every iteration touches the state of every trial (megabytes for thousands of trials, far beyond
the CPU caches) and the loop runs until the *slowest* trial of the batch has finished. Wrapping
the per-trial solver with :func:`chunked_vmap` keeps ``vmap`` semantics but evaluates a batch as
a ``jax.lax.map`` over chunks of ``chunk_size`` trials, each chunk vmapped: the working set of a
chunk stays in cache and each chunk stops when its own slowest trial has converged. A batch that
is not a multiple of the chunk size is padded with copies of its first trial (and the padding is
dropped from the result), so that the chunk body is compiled once.

Unbatched calls are untouched, and the results equal those of plain ``vmap`` (the same
per-trial arithmetic). The wrapped function is not differentiable (``jax.custom_batching``
functions are not); the solvers it is used for are iterative and are not differentiated.
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap


def chunked_vmap(fn: Callable, chunk_size: int, batched: Callable | None = None) -> Callable:
    """``fn`` (positional array arguments) whose ``vmap`` is ``lax.map`` over vmapped chunks.

    Args:
        fn: a per-trial function of positional array (pytree) arguments.
        chunk_size: trials per chunk (static); a batch no larger runs as a single chunk.
        batched: the function applied to one chunk (all arguments with a leading chunk axis);
            ``jax.vmap(fn)`` by default. It lets a solver take decisions per chunk, e.g. redo a
            chunk a slower way only when one of its trials needs it.
    """
    wrapped = custom_vmap(fn)
    chunk_fn = jax.vmap(fn) if batched is None else batched

    @wrapped.def_vmap
    def _rule(axis_size, in_batched, *args):
        # Broadcast the unbatched arguments, so that every leaf has the batch axis in front.
        args = jax.tree.map(
            lambda x, b: x if b else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x)),
            list(args),
            list(in_batched),
        )
        if axis_size <= chunk_size:
            out = chunk_fn(*args)
        else:
            n_chunks = -(-axis_size // chunk_size)
            pad = n_chunks * chunk_size - axis_size

            def to_chunks(x):
                if pad:
                    x = jnp.concatenate([x, jnp.broadcast_to(x[:1], (pad,) + x.shape[1:])])
                return x.reshape((n_chunks, chunk_size) + x.shape[1:])

            chunks = jax.tree.map(to_chunks, args)
            out = jax.lax.map(lambda c: chunk_fn(*c), chunks)
            out = jax.tree.map(lambda y: y.reshape((-1,) + y.shape[2:])[:axis_size], out)
        return out, jax.tree.map(lambda _: True, out)

    return wrapped


class Iteration(NamedTuple):
    """A per-trial iterative solver, split so that a batch can be run as a work queue.

    Attributes:
        init: ``init(*args) -> carry``, the loop state of a trial.
        step: ``step(carry, *args) -> carry``, one iteration.
        running: ``running(carry) -> bool``, whether another iteration is due.
        result: ``result(carry) -> small pytree`` kept of a finished trial.
        finish: ``finish(result, *args) -> output``.
    """

    init: Callable
    step: Callable
    running: Callable
    result: Callable
    finish: Callable


def iterate(it: Iteration, *args):
    """One trial: ``while running: step``, then ``finish``."""
    carry = jax.lax.while_loop(it.running, lambda c: it.step(c, *args), it.init(*args))
    return it.finish(it.result(carry), *args)


def queued_vmap(it: Iteration, slots: int, chunk_size: int) -> Callable:
    """:func:`iterate` whose ``vmap`` runs the trials through ``slots`` slots as a work queue.

    ``vmap`` of a ``while_loop`` runs every trial until the slowest of the batch has finished;
    chunking (:func:`chunked_vmap`) bounds that waste by the slowest trial of each chunk. For
    solvers whose iteration count varies a lot between trials (Levenberg-Marquardt: 9 to 30+
    steps for the CDRA), a work queue removes it: ``slots`` trials iterate side by side, and a
    slot whose trial has finished takes the next trial of the batch. Each iteration of the queue
    costs one (vmapped) step of ``slots`` trials, and the batch takes about
    ``sum(iterations) / slots`` of them. The results are those of :func:`iterate` per trial.
    ``finish`` then runs over the batch in chunks of ``chunk_size``.
    """

    def one(*args):
        return iterate(it, *args)

    def batch(*args):
        size = jax.tree.leaves(args)[0].shape[0]
        n_slots = min(slots, size)
        ids = jnp.arange(n_slots)
        take = functools.partial(_take, args)
        slot_args = take(ids)
        carry = jax.vmap(it.init)(*slot_args)
        res_shape = jax.eval_shape(jax.vmap(it.result), carry)
        results = jax.tree.map(lambda s: jnp.zeros((size,) + s.shape[1:], s.dtype), res_shape)
        state = (slot_args, carry, ids, jnp.ones(n_slots, bool), jnp.asarray(n_slots), results)

        def body(state):
            slot_args, carry, ids, active, nxt, results = state
            go = active & jax.vmap(it.running)(carry)
            stepped = jax.vmap(it.step)(carry, *slot_args)
            carry = _where(go, stepped, carry)
            done = active & ~jax.vmap(it.running)(carry)
            # Finished trials: store their results (rows of other slots are dropped).
            rows = jnp.where(done, ids, size)
            res = jax.vmap(it.result)(carry)
            results = jax.tree.map(lambda b, r: b.at[rows].set(r, mode="drop"), results, res)
            # ... and hand their slots the next trials.
            pos = nxt + jnp.cumsum(done) - 1
            refill = done & (pos < size)

            def load(slot_args, carry):
                new_args = take(jnp.minimum(pos, size - 1))
                new_carry = jax.vmap(it.init)(*new_args)
                return _where(refill, new_args, slot_args), _where(refill, new_carry, carry)

            slot_args, carry = jax.lax.cond(
                jnp.any(refill), load, lambda a, c: (a, c), slot_args, carry
            )
            ids = jnp.where(refill, pos, ids)
            active = (active & ~done) | refill
            return slot_args, carry, ids, active, nxt + jnp.sum(refill), results

        results = jax.lax.while_loop(lambda s: jnp.any(s[3]), body, state)[5]
        fin = chunked_vmap(lambda r, *a: it.finish(r, *a), chunk_size)
        return jax.vmap(fin)(results, *args)

    return chunked_vmap(one, sys.maxsize, batch)  # the queue takes the whole batch


def _take(args, idx):
    return jax.tree.map(lambda a: a[idx], args)


def _where(mask, a, b):
    """Per-slot select between two pytrees with a leading slot axis."""
    return jax.tree.map(
        lambda x, y: jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, y), a, b
    )
