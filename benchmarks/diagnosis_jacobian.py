"""The diagnosis's Jacobian: through the per-pose corrections against one tangent per column.

The missing-physics analyser needs the extended model's Jacobian in two places: every column
(the frames' and every candidate's parameters, hundreds) at the geometric fit and at each
refit's solution, and the free columns (the frames and one candidate's parameters, a few dozen)
at every step of a refit. :func:`cdra_jax.diagnosis.model.residual_and_jacobian` takes the
parameters' columns through the per-pose corrections that they move (``dof + 12 K + 6``
tangents, 49 for the CDRA, then one contraction with the features);
:func:`cdra_jax.diagnosis.model.residual_and_columns` slices the free columns out of it, so
that a problem's refits share that one compiled program. The reference is forward mode with one
tangent per column (``jax.linearize`` of the whitened residual, a ``vmap`` over unit tangents;
the refit's lanes padded to a multiple of 16, so that refits of different sizes share a few
programs): every column, and the free columns of the refit of the concealed effect.

This script captures the problem of a diagnosis of a synthetic recording (the default arm,
``--poses`` poses with tension closure, a concealed shoulder compliance, the tests' noise), then
times both ways on it, compiled with the package's options, interleaved (medians of
``--repeats``), compares their columns (largest difference relative to the largest entry of
each column) and reports the compile time (trace, lowering and XLA, no persistent cache) of the
one-tangent-per-column program of the refit, which ``residual_and_columns`` does not need.

    python benchmarks/diagnosis_jacobian.py [--poses 30] [--repeats 15] [--json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from cdra_jax.compilation import filter_jit
from cdra_jax.diagnosis import core, diagnose, model
from cdra_jax.io import default_arm
from cdra_jax.physics import Candidate, effect
from cdra_jax.physics.synthetic import simulate_recordings
from cdra_jax.simulation import NoiseModel

_LANE_BLOCK = 16
"""The reference's refit lanes come in multiples of this many (unused lanes: zero columns)."""


def _problem(poses: int):
    """``(y, problem, hidden)`` of the full-Jacobian call of a diagnosis of a synthetic
    recording, and the concealed candidate."""
    arm = default_arm()
    noise = NoiseModel(0.05, 5e-4)
    hidden = Candidate(effect("joint_compliance"), "shoulder")
    recording, _ = simulate_recordings(
        jax.random.PRNGKey(3), arm, poses, candidate=hidden, params=[4e-7], noise=noise
    )
    seen = []
    full = core.residual_and_jacobian

    def spy(y, problem):
        seen.append((y, problem))
        return full(y, problem)

    core.residual_and_jacobian = spy
    try:
        diagnose(arm, recording, noise)
    finally:
        core.residual_and_jacobian = full
    return (*seen[-1], hidden)


@filter_jit
def _tangent_columns(y, problem, lanes):
    """Residual and the Jacobian's columns ``lanes`` (``len(y)``: a zero column), ``(N, k)``,
    by forward mode with one tangent per column."""
    r, tangent = jax.linearize(lambda yy: model.whitened_residual(yy, problem), y)
    unit = jax.nn.one_hot(lanes, y.shape[0], dtype=y.dtype)
    return r, jax.vmap(tangent)(unit).T


def _one_tangent_per_column(y, problem, columns):
    """:func:`_tangent_columns` of ``columns``, padded to a multiple of :data:`_LANE_BLOCK`."""
    k = len(columns)
    lanes = np.full(-(-max(k, 1) // _LANE_BLOCK) * _LANE_BLOCK, y.shape[0], int)
    lanes[:k] = columns
    r, J = _tangent_columns(y, problem, jnp.asarray(lanes))
    return np.asarray(r), np.asarray(J)[:, :k]


def _refit_columns(problem, hidden) -> np.ndarray:
    """As many entries of ``y`` as the refit of ``hidden`` frees: the base model's (frames,
    markers, the model's own effects), then as many candidate parameters as ``hidden`` has
    (the time of a column set depends on its size only)."""
    n = problem.n_geometric
    return np.arange(n + len(hidden.parameters(problem.arm)))


def _max_rel_difference(J_new, J_old) -> float:
    J_new, J_old = np.asarray(J_new), np.asarray(J_old)
    scale = np.maximum(np.max(np.abs(J_old), axis=0), np.finfo(float).tiny)
    return float(np.max(np.abs(J_new - J_old) / scale))


def _interleaved(methods: dict, repeats: int) -> tuple[dict, dict]:
    """Results of each method (compiled by the first call) and the median of its times (ms)."""
    results = {name: jax.block_until_ready(f()) for name, f in methods.items()}
    times: dict[str, list[float]] = {name: [] for name in methods}
    for _ in range(repeats):
        for name, f in methods.items():
            start = time.perf_counter()
            jax.block_until_ready(f())
            times[name].append(time.perf_counter() - start)
    return results, {name: 1e3 * statistics.median(t) for name, t in times.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--poses", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--json", action="store_true", help="also print JSON on the last line")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_enable_compilation_cache", False)

    y, problem, hidden = _problem(args.poses)
    every = np.arange(y.shape[0])
    free = _refit_columns(problem, hidden)
    start = time.perf_counter()
    jax.block_until_ready(_one_tangent_per_column(y, problem, free))
    compile_s = time.perf_counter() - start  # the refit's own program (the full one is warm)
    results, ms = _interleaved(
        {
            "through_corrections": lambda: model.residual_and_jacobian(y, problem),
            "one_tangent_per_column": lambda: _one_tangent_per_column(y, problem, every),
            "refit_sliced": lambda: model.residual_and_columns(y, problem, free),
            "refit_one_tangent_per_column": lambda: _one_tangent_per_column(y, problem, free),
        },
        args.repeats,
    )
    row = {
        "poses": args.poses,
        "residual_rows": int(np.asarray(results["through_corrections"][1]).shape[0]),
        "columns": int(y.shape[0]),
        "refit_columns": int(free.size),
        "ms_through_corrections": ms["through_corrections"],
        "ms_one_tangent_per_column": ms["one_tangent_per_column"],
        "ms_refit_sliced": ms["refit_sliced"],
        "ms_refit_one_tangent_per_column": ms["refit_one_tangent_per_column"],
        "refit_tangent_program_compile_s": compile_s,
        "max_rel_difference": _max_rel_difference(
            results["through_corrections"][1], results["one_tangent_per_column"][1]
        ),
        "refit_max_rel_difference": _max_rel_difference(
            results["refit_sliced"][1], results["refit_one_tangent_per_column"][1]
        ),
    }
    row["speedup"] = row["ms_one_tangent_per_column"] / row["ms_through_corrections"]
    print(
        f"{row['residual_rows']} rows x {row['columns']} columns ({args.poses} poses, medians of "
        f"{args.repeats}, interleaved): every column through the corrections "
        f"{row['ms_through_corrections']:.1f} ms, one tangent per column "
        f"{row['ms_one_tangent_per_column']:.1f} ms ({row['speedup']:.1f}x), equal to "
        f"{row['max_rel_difference']:.1e} of each column's largest entry"
    )
    print(
        f"the refit's {row['refit_columns']} free columns: sliced from every column "
        f"{row['ms_refit_sliced']:.1f} ms, one tangent per column "
        f"{row['ms_refit_one_tangent_per_column']:.1f} ms (its own program: "
        f"{row['refit_tangent_program_compile_s']:.2f} s to compile), equal to "
        f"{row['refit_max_rel_difference']:.1e}"
    )
    if args.json:
        print(json.dumps(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
