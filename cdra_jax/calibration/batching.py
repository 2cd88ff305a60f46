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

from collections.abc import Callable

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

    ``fn`` is traced once per call, to a jaxpr: ``custom_vmap`` needs the unbatched function
    and the default batching rule vmaps the same jaxpr, so that the Python code of ``fn`` (for
    an optimistix solver, most of the lowering time) is not traced twice.
    """

    def call(*args):
        closed, out_shape = jax.make_jaxpr(fn, return_shape=True)(*args)
        out_tree = jax.tree.structure(out_shape)

        def replay(*a):
            flat = jax.core.eval_jaxpr(closed.jaxpr, closed.consts, *jax.tree.leaves(a))
            return jax.tree.unflatten(out_tree, flat)

        wrapped = custom_vmap(replay)
        chunk_fn = jax.vmap(replay) if batched is None else batched

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

        return wrapped(*args)

    return call


def batched_like(ref: jax.Array, tree):
    """``tree`` unchanged, every leaf made to depend on ``ref`` (a value computed from a trial's
    inputs), so that under ``vmap`` the leaves are batched from the start.

    For the initial carry of a ``while_loop`` whose body makes these leaves batched: JAX batches
    a loop body again whenever the batched-ness of the carry changes in the body (a fixed point),
    so a carry that starts unbatched (zeros, NaN histories, a ``False`` flag) costs a second
    batching pass over the whole body at trace time. ``where(ref, x, x)`` is ``x`` (XLA folds
    it away), so the compiled program and the results are unchanged.
    """
    return jax.tree.map(lambda x: jnp.where(ref, x, x), tree)
