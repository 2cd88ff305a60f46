"""Compile time of the missing-physics analyser's features program.

The diagnosis evaluates the features of every candidate of the vocabulary (and the probes) in
one compiled program, :func:`cdra_jax.diagnosis.model.all_features`, once per diagnosis (and
once per test module that diagnoses). It builds them with
:func:`cdra_jax.physics.base.stacked_features`: the terms that several forms need (the gravity
loads, each module's holding tensions, the cable-length Jacobians, the module base frames) enter
the program once, and the rounding-level columns of all candidates are found in one pass. This
script times the trace and compilation of that program (``stacked``) against the same features
with each candidate evaluated on its own (``per_candidate``: :meth:`Candidate.features`, its own
terms and rounding pass, concatenated), interleaved, with the in-memory and on-disk caches
cleared before each, and compares the features (bitwise, and the largest difference
relative to the largest entry of its column: XLA fuses the two programs differently, so an
entry that is zero to rounding can come out as rounding in one of them).

    python benchmarks/diagnosis_compile.py [--poses 30] [--repeats 3] [--json]

The default arm, ``--poses`` states with tension closure, the auxiliary columns of the
synthetic recordings (time, payload, approach directions), ``fast_compile`` as in the package.
"""

from __future__ import annotations

import argparse
import functools
import json
import statistics
import time

import equinox as eqx
import jax
import numpy as np

from cdra_jax.compilation import filter_jit
from cdra_jax.diagnosis.model import all_features
from cdra_jax.io import default_arm
from cdra_jax.modules.tension import sample_feasible_states
from cdra_jax.physics import PROBES, Features, candidates
from cdra_jax.physics.synthetic import recording_aux


@functools.partial(filter_jit, fast_compile=True)
def _per_candidate(cands, arm, q, aux) -> Features:
    """Each candidate's :meth:`Candidate.features` on its own, concatenated."""
    return Features.concatenate([c.features(arm, q, aux) for c in cands])


def _timed(fn, *args) -> tuple[float, Features]:
    jax.clear_caches()
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return time.perf_counter() - t0, out


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--poses", type=int, default=30, help="recorded poses (default 30)")
    p.add_argument("--repeats", type=int, default=3, help="interleaved rounds (default 3)")
    p.add_argument("--json", action="store_true", help="print one JSON object last")
    args = p.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_enable_compilation_cache", False)
    arm = default_arm()
    k1, k2 = jax.random.split(jax.random.PRNGKey(0))
    q = eqx.filter_jit(sample_feasible_states)(k1, arm, args.poses)
    aux = recording_aux(k2, arm, args.poses)
    live = [c for c, why in candidates(arm, aux.keys()) if why is None]
    probes = [c for c, why in candidates(arm, aux.keys(), PROBES) if why is None]
    cands = tuple(live + probes)
    times: dict[str, list[float]] = {"stacked": [], "per_candidate": []}
    outs = {}
    for _ in range(args.repeats):
        for name, fn in (("stacked", all_features), ("per_candidate", _per_candidate)):
            t, outs[name] = _timed(fn, cands, arm, q, aux)
            times[name].append(t)
    pairs = list(
        zip(jax.tree.leaves(outs["stacked"]), jax.tree.leaves(outs["per_candidate"]), strict=True)
    )
    equal = all(np.array_equal(np.asarray(a), np.asarray(b)) for a, b in pairs)
    # the largest difference of an entry, relative to the largest entry of its column
    p = outs["stacked"].n_params
    scale = np.max([np.abs(np.asarray(b)).reshape(-1, p).max(axis=0) for _, b in pairs], axis=0)
    diff = np.max(
        [np.abs(np.asarray(a) - np.asarray(b)).reshape(-1, p).max(axis=0) for a, b in pairs], axis=0
    )
    relative = float(np.max(diff / np.where(scale > 0, scale, 1.0)))
    med = {k: statistics.median(v) for k, v in times.items()}
    res = {
        "poses": args.poses,
        "candidates": len(cands),
        "parameters": outs["stacked"].n_params,
        "stacked_s": med["stacked"],
        "per_candidate_s": med["per_candidate"],
        "ratio": med["per_candidate"] / med["stacked"],
        "bitwise_equal": equal,
        "largest_relative_difference": relative,
        "times": times,
    }
    print(
        f"{len(cands)} candidates, {res['parameters']} parameters, {args.poses} poses: "
        f"trace + compile + run {med['stacked']:.2f} s stacked, "
        f"{med['per_candidate']:.2f} s per candidate ({res['ratio']:.2f}x; medians of "
        f"{args.repeats}); "
        f"features bitwise equal: {equal}, largest difference {relative:.1e} of its column's "
        "largest entry"
    )
    if args.json:
        print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
