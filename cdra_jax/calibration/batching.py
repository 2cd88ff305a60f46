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

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_batching import custom_vmap
from jax.extend.core import Literal


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
    and the batching rule vmaps the same jaxpr, so that the Python code of ``fn`` is not traced
    twice.
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
            args = _batched_args(axis_size, in_batched, args)
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


def chunked_loop(
    init: Callable,
    body: Callable,
    running: Callable,
    finish: Callable,
    *,
    chunk_size: int,
    passes: int,
    stragglers: int,
) -> Callable:
    """An iterative per-trial solver whose ``vmap`` runs the iteration chunk by chunk, with the
    loop written at the level of the chunk.

    The solver is given as four per-trial functions:

    * ``init(mode, *args) -> (state, data)``: the start of a trial (``data``: what stays
      constant; ``mode``, int32, see below);
    * ``body(it, mode, step, state, data) -> state``: one pass of the loop; ``it`` (int32, the
      chunk's pass counter), ``mode`` (int32, see below) and ``step`` (bool) are the same for
      the whole chunk (unbatched: a ``lax.cond`` on them is a real branch). The loop ends with
      a pass with ``step`` false, in which the body is to evaluate the final state only;
    * ``running(state) -> bool``: the trial still steps;
    * ``finish(mode, state, data) -> (out, want)``: the result and the later mode (int32; 0:
      none) that must solve the trial again.

    The returned function takes ``*args`` (positional array pytrees) of one trial and returns
    ``out``. A chunk runs its loop while more than ``limit`` of its trials are running: in mode
    0 ``limit = chunk // stragglers``, so that a few slow trials do not hold the whole chunk
    for their last steps; they are handed to mode 1 (solved again from the start, gathered
    into chunks of their own, without the limit). Modes ``2 .. passes - 1`` are the solver's
    own (:func:`multi_pass`). ``vmap`` of the function evaluates the batch by :func:`multi_pass`
    in chunks of ``chunk_size``; an unbatched call is a chunk of one trial.

    Each per-trial function is traced once, to a jaxpr, and the chunk's loop ``vmap``s its
    replay, so that the solver's Python runs once per trace of the caller. Arguments that are
    the same for every trial under ``vmap`` (the arm's frames) stay unbatched, and so do the
    parts of ``data`` that depend on nothing else (:func:`_batched_outputs`): neither is
    broadcast to the batch nor gathered chunk by chunk. Not differentiable (as
    :func:`chunked_vmap`).
    """

    def call(*args):
        scalar = jax.ShapeDtypeStruct((), jnp.int32)
        init_r, (state_s, data_s) = _traced_once(init, scalar, *args)
        flag = jax.ShapeDtypeStruct((), bool)
        body_r, _ = _traced_once(body, scalar, scalar, flag, state_s, data_s)
        running_r, _ = _traced_once(running, state_s)
        finish_r, (out_s, _) = _traced_once(finish, scalar, state_s, data_s)

        def chunk_fn(batched, mode, *chunk):
            """The loop over one chunk; ``batched``: per leaf of the arguments, whether it has
            the chunk's axis (others are the same for every trial)."""
            flat, tree = jax.tree.flatten(chunk)
            axes = jax.tree.unflatten(tree, [0 if b else None for b in batched])
            # The state has the chunk's axis; the constant data only where it depends on a
            # batched argument (the arm's frames stay as they are, not broadcast).
            n_state = len(jax.tree.leaves(state_s))
            per_trial = _batched_outputs(init_r, [False, *batched])[n_state:]
            data_axes = jax.tree.unflatten(
                jax.tree.structure(data_s), [0 if b else None for b in per_trial]
            )
            state, data = jax.vmap(init_r, in_axes=(None, *axes), out_axes=(0, data_axes))(
                mode, *chunk
            )
            size = flat[batched.index(True)].shape[0]
            limit = jnp.where(mode == 0, size // stragglers, 0)
            step_all = jax.vmap(body_r, in_axes=(None, None, None, 0, data_axes))

            def loop(c):
                it, state, _ = c
                step = jnp.sum(jax.vmap(running_r)(state)) > limit
                return it + 1, step_all(it, mode, step, state, data), step

            start = (jnp.asarray(0, jnp.int32), state, jnp.asarray(True))
            _, state, _ = jax.lax.while_loop(lambda c: c[2], loop, start)
            out, want = jax.vmap(finish_r, in_axes=(None, 0, data_axes))(mode, state, data)
            handed_on = jax.vmap(running_r)(state)
            return out, jnp.where(handed_on, 1, want).astype(jnp.int32)

        def solve(mode, *a):
            """One trial in ``mode``: the loop of ``chunk_fn`` on the replays, unbatched."""
            state, data = init_r(mode, *a)

            def loop(c):
                it, state, _ = c
                step = running_r(state)
                return it + 1, body_r(it, mode, step, state, data), step

            start = (jnp.asarray(0, jnp.int32), state, jnp.asarray(True))
            _, state, _ = jax.lax.while_loop(lambda c: c[2], loop, start)
            return finish_r(mode, state, data)

        def unbatched(*a):
            # Mode after mode while the trial wants another (a chunk of one has no stragglers):
            # the replays, not a batch of one, so that nothing is batched twice when traced.
            zeros = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), out_s)

            def again(c):
                mode, _ = c
                out, want = solve(mode, *a)
                return want.astype(jnp.int32), out

            start = (jnp.asarray(0, jnp.int32), zeros)
            _, out = jax.lax.while_loop(
                lambda c: (c[0] >= 0) & (c[0] < passes),
                lambda c: _next_mode(again(c), c[0]),
                start,
            )
            return out

        wrapped = custom_vmap(unbatched)

        @wrapped.def_vmap
        def _rule(axis_size, in_batched, *args):
            # Arguments the same for every trial (the arm's frames) stay unbatched: neither
            # broadcast to the batch nor gathered chunk by chunk.
            batched = [bool(b) for b in jax.tree.leaves(list(in_batched))]
            chunk = functools.partial(chunk_fn, batched)
            out = multi_pass(chunk, chunk_size, passes, *args, batched_leaves=batched)
            return out, jax.tree.map(lambda _: True, out)

        return wrapped(*args)

    return call


def _held_exactly(dtype, integer) -> bool:
    """Whether every value of ``dtype`` (bool or an integer type) is one of ``integer``."""
    if dtype == jnp.dtype(bool):
        return True
    if not jnp.issubdtype(dtype, jnp.integer):
        return False
    info, into = jnp.iinfo(dtype), jnp.iinfo(integer)
    return bool(into.min <= info.min and info.max <= into.max)


def set_entry(values, i, value, where=True):
    """``values`` (1-D) with entry ``i`` set to ``value`` where ``where`` holds (else unchanged;
    an ``i`` out of range changes nothing), as a select over the positions: under ``vmap``,
    where ``i`` differs between trials, ``values.at[i].set(value)`` is a scatter, which XLA:CPU
    compiles into a loop of its own per use (a kernel to compile and a call per chunk); the
    select fuses with its neighbours."""
    hit = (jnp.arange(values.shape[0]) == i) & where
    return jnp.where(hit, value, values)


def _batched_args(axis_size: int, in_batched, args) -> list:
    """The arguments of a ``custom_vmap`` rule with the unbatched ones broadcast, so that every
    leaf has the batch axis in front."""
    return jax.tree.map(
        lambda x, b: x if b else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x)),
        list(args),
        list(in_batched),
    )


def _next_mode(result, mode):
    """``(next mode, out)`` of an unbatched trial after ``mode``: the mode it wants, or -1 when
    it wants none (the loop of :func:`chunked_loop`'s unbatched path then ends)."""
    want, out = result
    return jnp.where(want > mode, want, -1).astype(jnp.int32), out


def two_pass(batched: Callable, chunk_size: int, *args):
    """:func:`multi_pass` with two passes and a boolean mode: ``batched(second, *chunk) ->
    (out, redo)``, ``second`` an unbatched boolean scalar and ``redo`` a boolean per trial; the
    flagged trials of the first pass are evaluated again with ``second=True``."""

    def modes(mode, *chunk):
        out, redo = batched(mode == 1, *chunk)
        return out, redo.astype(jnp.int32) * (mode == 0)

    return multi_pass(modes, chunk_size, 2, *args)


def multi_pass(batched: Callable, chunk_size: int, passes: int, *args, batched_leaves=None):
    """A batch in chunks, with later passes over the trials that a pass hands on.

    ``batched(mode, *chunk) -> (out, want)`` evaluates one chunk of trials (every leaf of
    ``args`` and of ``out`` has the batch on its leading axis); ``mode`` is an unbatched int32
    scalar, ``want`` an int32 per trial: 0 for a finished trial, else a mode above ``mode``
    that must evaluate it again. The first pass evaluates every chunk in mode 0; then, mode by
    mode, the trials that want it are gathered, in order, into chunks of ``chunk_size`` (the
    last one part-filled, its spare lanes recomputing one of its trials and dropped) and
    evaluated in that mode, and their outputs replace the earlier ones. A later pass therefore
    costs in proportion to the trials it holds, not to the chunks that held one. All passes are
    iterations of one ``while_loop`` around one call of ``batched``, so that it is traced and
    compiled once; ``mode`` is a real branch (``lax.cond``) wherever ``batched`` uses it.

    A batch that is not a multiple of the chunk size is padded with copies of its first trial
    (never evaluated again, and dropped from the result). An empty batch gives empty outputs.

    ``batched_leaves`` (a bool per leaf of ``args``, in their flattened order; default all):
    the leaves without it are the same for every trial, have no batch axis, and are handed to
    every chunk as they are.

    Returns:
        ``out`` of the whole batch.
    """
    flat_args, args_tree = jax.tree.flatten(args)
    flags = [True] * len(flat_args) if batched_leaves is None else list(batched_leaves)

    def per_trial(fn, tree):
        """``fn`` applied to the batched leaves of ``tree`` (the structure of ``args``)."""
        flat = jax.tree.leaves(tree)
        return jax.tree.unflatten(
            args_tree, [fn(x) if b else x for x, b in zip(flat, flags, strict=True)]
        )

    size = flat_args[flags.index(True)].shape[0]
    mode_type = jax.ShapeDtypeStruct((), jnp.int32)
    if size == 0:
        # No trials: outputs with no trials (the chunk function's shapes, traced for one).
        one = per_trial(lambda x: jax.ShapeDtypeStruct((1,) + x.shape[1:], x.dtype), args)
        out_shape, _ = jax.eval_shape(batched, mode_type, *one)
        return jax.tree.map(lambda s: jnp.zeros((0,) + s.shape[1:], s.dtype), out_shape)
    chunk = min(chunk_size, size)
    n_chunks = -(-size // chunk)
    padded = n_chunks * chunk
    pad = padded - size

    def padding(x):
        if not pad:
            return x
        return jnp.concatenate([x, jnp.broadcast_to(x[:1], (pad,) + x.shape[1:])])

    args = per_trial(padding, args)
    index = jnp.asarray(0).dtype
    # Index constants as NumPy arrays, embedded in the program: each jnp.arange would be a
    # kernel of its own to compile.
    lanes = np.arange(chunk, dtype=index)
    real = np.arange(padded) < size
    # ``batched`` traced once, to a jaxpr that the loop body replays.
    specs = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), args)
    chunk_args = per_trial(lambda x: jax.ShapeDtypeStruct((chunk,) + x.shape[1:], x.dtype), specs)
    call, (out_shape, _) = _traced_once(batched, mode_type, *chunk_args)
    # The outputs and ``want`` are held in one buffer per dtype (``_Packing``), so that each
    # chunk is written back by one scatter per dtype rather than one per output.
    leaves, out_tree = jax.tree.flatten(out_shape)
    packing = _Packing([*leaves, jax.ShapeDtypeStruct((chunk,), jnp.dtype(jnp.int32))])
    buffers0 = packing.zeros(padded)
    rank = np.arange(passes)
    slots = np.arange(padded + chunk, dtype=index)
    order = np.arange(padded, dtype=index)

    def advance(mode, want, counts):
        """The next mode that some trial wants (``passes`` when none), its trials' indices in
        order (padded to whole chunks) and their count."""
        want = jnp.where(real, want, 0)
        later = (rank > mode) & (counts > 0)
        nxt = jnp.where(jnp.any(later), jnp.argmax(later), passes).astype(jnp.int32)
        # The trials that want ``nxt`` first, in order: a stable sort on "does not want it"
        # (a single sort, where ``jnp.nonzero`` compiles two cumulative sums and a scatter).
        # Spare lanes repeat the first of them (a trial of this mode, not one of another).
        keys = (want != nxt, jnp.asarray(order))
        _, idx = jax.lax.sort(keys, num_keys=1, is_stable=True)
        count = jnp.where(nxt < passes, counts[nxt % passes], 0)
        idx = jnp.where(slots < count, jnp.concatenate([idx, jnp.zeros(chunk, index)]), idx[0])
        return nxt, idx, count

    def body(state):
        mode, c, count, idx, buffers, counts = state
        start = c * chunk
        first = mode == 0
        ids = jnp.where(first, start + lanes, jax.lax.dynamic_slice(idx, (start,), (chunk,)))
        valid = first | (start + lanes < count)
        new, new_want = call(mode, *per_trial(lambda x: x[ids], args))
        rows = packing.pack([*jax.tree.leaves(new), new_want.astype(jnp.int32)])
        dest = jnp.where(valid, ids, padded)  # spare lanes of a part-filled chunk: dropped
        buffers = tuple(b.at[dest].set(r, mode="drop") for b, r in zip(buffers, rows, strict=True))
        # The trials that want each mode, counted as the chunks hand them on (over the chunk's
        # lanes: a sum over the whole batch is a tree of reductions that XLA compiles apart).
        # A trial's want changes only when its own mode evaluates it, so the counts of the
        # modes after the current one are exact. The wants are read back from the buffer just
        # written: counted from ``new_want`` itself, XLA recomputed the chunk's whole
        # ``finish`` inside the count (1.3 % more instructions in XLA for the paper solver).
        want = packing.unpack(buffers, -1)
        handed = (want[ids][:, None] == rank) & (valid & (ids < size))[:, None]
        counts = counts + jnp.sum(handed, axis=0, dtype=index)
        c = c + 1
        done = c * chunk >= count
        mode, idx, count = jax.lax.cond(
            done, advance, lambda m, *_: (m, idx, count), mode, want, counts
        )
        return mode, jnp.where(done, 0, c), count, idx, buffers, counts

    init = (
        jnp.asarray(0, jnp.int32),
        jnp.asarray(0, index),
        jnp.asarray(padded, index),
        jnp.zeros(padded + chunk, index),
        buffers0,
        jnp.zeros(passes, index),
    )
    _, _, _, _, buffers, _ = jax.lax.while_loop(lambda s: s[0] < passes, body, init)
    out = [packing.unpack(buffers, i)[:size] for i in range(len(leaves))]
    return jax.tree.unflatten(out_tree, out)


class _Packing:
    """Where each of a list of arrays (batch axis first) lies in one 2-D buffer per dtype,
    ``(batch, columns)``: the arrays of one dtype side by side, and booleans and the integers
    that it holds exactly in one buffer of the default integer type. The buffers are a tuple
    (dtypes are no pytree keys)."""

    def __init__(self, specs):
        self.dtypes: list[jnp.dtype] = []
        self.widths: list[int] = []
        self.layout: list[tuple[int, int, int, tuple, jnp.dtype]] = []
        integer = jnp.asarray(0).dtype
        for spec in specs:
            dtype = jnp.dtype(spec.dtype)
            held = integer if _held_exactly(dtype, integer) else dtype
            if held not in self.dtypes:
                self.dtypes.append(held)
                self.widths.append(0)
            b = self.dtypes.index(held)
            width = int(np.prod(spec.shape[1:], dtype=int))
            self.layout.append((b, self.widths[b], width, tuple(spec.shape[1:]), dtype))
            self.widths[b] += width

    def zeros(self, rows: int) -> tuple:
        """Empty buffers of ``rows`` rows."""
        return tuple(jnp.zeros((rows, w), k) for k, w in zip(self.dtypes, self.widths, strict=True))

    def pack(self, arrays: list) -> tuple:
        """The buffers' rows holding ``arrays`` (each ``(rows, ...)``, in the order of the
        specs)."""
        parts: list[list] = [[] for _ in self.dtypes]
        for x, (b, _, width, _, _) in zip(arrays, self.layout, strict=True):
            parts[b].append(x.reshape(x.shape[0], width).astype(self.dtypes[b]))
        return tuple(jnp.concatenate(v, axis=1) if len(v) > 1 else v[0] for v in parts)

    def unpack(self, buffers: tuple, i: int):
        """Array ``i`` of the specs, read from the buffers."""
        b, offset, width, shape, dtype = self.layout[i]
        column = buffers[b][:, offset : offset + width]
        return column.reshape((column.shape[0],) + shape).astype(dtype)


def _traced_once(fn: Callable, *args):
    """``fn`` traced once, at ``args`` (arrays, tracers or ``ShapeDtypeStruct``s), to a jaxpr:
    ``(replay, out_shape)``, ``replay(*args)`` evaluating the jaxpr without tracing ``fn``'s
    Python again."""
    closed, out_shape = jax.make_jaxpr(fn, return_shape=True)(*args)
    out_tree = jax.tree.structure(out_shape)

    def replay(*a):
        flat = jax.core.eval_jaxpr(closed.jaxpr, closed.consts, *jax.tree.leaves(a))
        return jax.tree.unflatten(out_tree, [jnp.asarray(x) for x in flat])

    replay.jaxpr = closed  # type: ignore[attr-defined]
    return replay, out_shape


def _batched_outputs(replay: Callable, batched_inputs: list[bool]) -> list[bool]:
    """Per output leaf of a replay of :func:`_traced_once`, whether it depends on one of the
    input leaves marked in ``batched_inputs`` (a forward walk over the jaxpr's equations, each
    output of an equation depending on all of its inputs: an output marked ``False`` is the
    same for every trial)."""
    jaxpr = replay.jaxpr.jaxpr  # type: ignore[attr-defined]
    marked = {v for v, b in zip(jaxpr.invars, batched_inputs, strict=True) if b}

    def depends(v) -> bool:
        return not isinstance(v, Literal) and v in marked

    for eqn in jaxpr.eqns:
        if any(depends(v) for v in eqn.invars):
            marked.update(eqn.outvars)
    return [depends(v) for v in jaxpr.outvars]
