"""Compile time of the missing-physics analyser's features program.

The diagnosis evaluates the features of every candidate of the vocabulary (and the probes) in
one compiled program, :func:`cdra_jax.diagnosis.model.all_features`, once per diagnosis (and
once per test module that diagnoses). Several forms of an effect need the same terms (the
gravity loads, each module's holding tensions, the cable-length Jacobians), which
:func:`cdra_jax.physics.base.sharing_terms` puts into the program once. This script times the
trace and compilation of the program as the package builds it (``shared``) against each form
computing its own terms (``per_form``), interleaved, with the in-memory and on-disk caches
cleared before each, and checks that both give the same features bitwise.

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
def _per_form(cands, arm, q, aux) -> Features:
    """``all_features`` without :func:`sharing_terms`: every form computes its own terms."""
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
    times: dict[str, list[float]] = {"shared": [], "per_form": []}
    outs = {}
    for _ in range(args.repeats):
        for name, fn in (("shared", all_features), ("per_form", _per_form)):
            t, outs[name] = _timed(fn, cands, arm, q, aux)
            times[name].append(t)
    equal = all(
        np.array_equal(np.asarray(a), np.asarray(b))
        for a, b in zip(
            jax.tree.leaves(outs["shared"]), jax.tree.leaves(outs["per_form"]), strict=True
        )
    )
    med = {k: statistics.median(v) for k, v in times.items()}
    res = {
        "poses": args.poses,
        "candidates": len(cands),
        "parameters": outs["shared"].n_params,
        "shared_s": med["shared"],
        "per_form_s": med["per_form"],
        "ratio": med["per_form"] / med["shared"],
        "bitwise_equal": equal,
        "times": times,
    }
    print(
        f"{len(cands)} candidates, {res['parameters']} parameters, {args.poses} poses: "
        f"trace + compile + run {med['shared']:.2f} s with shared terms, "
        f"{med['per_form']:.2f} s per form ({res['ratio']:.2f}x; medians of {args.repeats}); "
        f"features bitwise equal: {equal}"
    )
    if args.json:
        print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
