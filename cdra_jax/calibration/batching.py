"""Chunked batching of per-trial solvers: ``vmap`` runs the trials in cache-sized chunks.

``jax.vmap`` of an iterative solver turns its ``while_loop`` into one loop over the whole batch:
every iteration touches the state of every trial (megabytes for thousands of trials, far beyond
the CPU caches) and the loop runs until the *slowest* trial of the batch has finished. Wrapping
the per-trial solver with :func:`chunked_vmap` keeps ``vmap`` semantics but evaluates a batch as
a ``jax.lax.map`` over chunks of ``chunk_size`` trials, each chunk vmapped: the working set of a
chunk stays in cache and each chunk stops when its own slowest trial has converged. A batch that
is not a multiple of the chunk size is padded with copies of its first trial (and the padding is
dropped from the result), so that the chunk body is compiled once.

A solver that checks its own result can ask for a second pass (``second_pass=True``,
:func:`two_pass`): the trials it flags in the first pass are gathered from all chunks into
chunks of their own and evaluated again another way (the paper solver: fast normal-equation
steps first, SVD steps for the trials that the normal equations cannot resolve), so that the
second pass costs in proportion to the flagged trials rather than to the chunks that hold one.

Unbatched calls are untouched, and the results equal those of plain ``vmap`` (the same
per-trial arithmetic). The wrapped function is not differentiable (``jax.custom_batching``
functions are not): the solvers call it on inputs without derivatives and take their
derivatives from the optimality condition instead (:mod:`.implicit`).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap


def chunked_vmap(fn: Callable, chunk_size: int, *, second_pass: bool = False) -> Callable:
    """``fn`` (positional array arguments) whose ``vmap`` is ``lax.map`` over vmapped chunks.

    Args:
        fn: a per-trial function of positional array (pytree) arguments.
        chunk_size: trials per chunk (static); a batch no larger runs as a single chunk.
        second_pass: ``fn`` is then ``fn(second, *args) -> (out, redo)``, with ``second`` a
            boolean scalar, the same for a whole chunk (unbatched under ``vmap``, so that a
            ``lax.cond`` on it stays a real branch), and ``redo`` a boolean: the returned
            function takes ``*args`` and returns ``out``, evaluated by :func:`two_pass` (the
            trials flagged with ``second=False`` are evaluated again with ``second=True``,
            gathered into chunks of their own); for an unbatched call the second pass is a
            ``lax.cond`` on the flag.

    ``fn`` is traced once per call, to a jaxpr: ``custom_vmap`` needs the unbatched function
    and the batching rule vmaps the same jaxpr, so that the Python code of ``fn`` (for an
    optimistix solver, most of the lowering time) is not traced twice.
    """

    def call(*args):
        head = (jax.ShapeDtypeStruct((), bool),) if second_pass else ()
        replay, _ = _traced_once(fn, *head, *args)

        if second_pass:
            chunk_fn = jax.vmap(replay, in_axes=(None,) + (0,) * len(args))

            def unbatched(*a):
                # One trial: the second pass is a branch (replaying the jaxpr, not batching it).
                out, redo = replay(jnp.asarray(False), *a)
                return jax.lax.cond(redo, lambda: replay(jnp.asarray(True), *a)[0], lambda: out)

            wrapped = custom_vmap(unbatched)
        else:
            chunk_fn = jax.vmap(replay)
            wrapped = custom_vmap(replay)

        @wrapped.def_vmap
        def _rule(axis_size, in_batched, *args):
            # Broadcast the unbatched arguments, so that every leaf has the batch axis in front.
            args = jax.tree.map(
                lambda x, b: x if b else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x)),
                list(args),
                list(in_batched),
            )
            if second_pass:
                out = two_pass(chunk_fn, chunk_size, *args)
            elif axis_size <= chunk_size:
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


def two_pass(batched: Callable, chunk_size: int, *args):
    """A batch in chunks, with a second pass over the trials the first pass flags.

    ``batched(second, *chunk) -> (out, redo)`` evaluates one chunk of trials (every leaf of
    ``args`` and of ``out`` has the batch on its leading axis); ``second`` is an unbatched
    boolean scalar. The first pass evaluates every chunk with ``second=False``; the trials whose
    ``redo`` flag is set are then gathered, in order, into chunks of ``chunk_size`` (the last one
    part-filled, its spare lanes recomputing a flagged trial and dropped) and evaluated with
    ``second=True``, and their outputs replace the first ones. The second pass therefore costs
    in proportion to the flagged trials, not to the chunks that hold one. Both passes are
    iterations of one ``while_loop`` around one call of ``batched``, so that it is traced and
    compiled once; ``second`` is a real branch (``lax.cond``) wherever ``batched`` uses it.

    A batch that is not a multiple of the chunk size is padded with copies of its first trial
    (never flagged for the second pass, and dropped from the result). An empty batch gives
    empty outputs.

    Returns:
        ``out`` of the whole batch.
    """
    size = jax.tree.leaves(args)[0].shape[0]
    if size == 0:
        # No trials: outputs with no trials (the chunk function's shapes, traced for one).
        one = jax.tree.map(lambda x: jax.ShapeDtypeStruct((1,) + x.shape[1:], x.dtype), args)
        out_shape, _ = jax.eval_shape(batched, jax.ShapeDtypeStruct((), bool), *one)
        return jax.tree.map(lambda s: jnp.zeros((0,) + s.shape[1:], s.dtype), out_shape)
    chunk = min(chunk_size, size)
    n_chunks = -(-size // chunk)
    padded = n_chunks * chunk
    pad = padded - size

    def padding(x):
        if not pad:
            return x
        return jnp.concatenate([x, jnp.broadcast_to(x[:1], (pad,) + x.shape[1:])])

    args = jax.tree.map(padding, args)
    index = jnp.asarray(0).dtype
    lanes = jnp.arange(chunk, dtype=index)
    # ``batched`` traced once, to a jaxpr that the loop body replays.
    chunk_args = jax.tree.map(lambda x: jax.ShapeDtypeStruct((chunk,) + x.shape[1:], x.dtype), args)
    call, (out_shape, _) = _traced_once(batched, jax.ShapeDtypeStruct((), bool), *chunk_args)
    out0 = jax.tree.map(lambda s: jnp.zeros((padded,) + s.shape[1:], s.dtype), out_shape)

    def flagged(redo):
        """The flagged trials' indices in order, padded to whole chunks; and their count."""
        redo = redo & (jnp.arange(padded) < size)
        (idx,) = jnp.nonzero(redo, size=padded + chunk, fill_value=0)
        return idx.astype(index), jnp.sum(redo, dtype=index)

    def body(state):
        item, out, redo, idx, count = state
        second = item >= n_chunks
        start = jnp.where(second, item - n_chunks, item) * chunk
        ids = jnp.where(second, jax.lax.dynamic_slice(idx, (start,), (chunk,)), start + lanes)
        valid = ~second | (start + lanes < count)
        new, new_redo = call(second, *jax.tree.map(lambda x: x[ids], args))
        dest = jnp.where(valid, ids, padded)  # spare lanes of the last chunk: dropped
        out = jax.tree.map(lambda o, n: o.at[dest].set(n, mode="drop"), out, new)
        redo = jnp.where(second, redo, redo.at[dest].set(new_redo, mode="drop"))
        idx, count = jax.lax.cond(item == n_chunks - 1, flagged, lambda _: (idx, count), redo)
        return item + 1, out, redo, idx, count

    def running(state):
        item, _, _, _, count = state
        return item < n_chunks + (count + chunk - 1) // chunk

    init = (
        jnp.asarray(0),
        out0,
        jnp.zeros(padded, bool),
        jnp.zeros(padded + chunk, index),
        jnp.asarray(0, index),
    )
    _, out, _, _, _ = jax.lax.while_loop(running, body, init)
    return jax.tree.map(lambda y: y[:size], out)


def _traced_once(fn: Callable, *args):
    """``fn`` traced once, at ``args`` (arrays, tracers or ``ShapeDtypeStruct``s), to a jaxpr:
    ``(replay, out_shape)``, ``replay(*args)`` evaluating the jaxpr without tracing ``fn``'s
    Python again."""
    closed, out_shape = jax.make_jaxpr(fn, return_shape=True)(*args)
    out_tree = jax.tree.structure(out_shape)

    def replay(*a):
        flat = jax.core.eval_jaxpr(closed.jaxpr, closed.consts, *jax.tree.leaves(a))
        return jax.tree.unflatten(out_tree, flat)

    return replay, out_shape


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
