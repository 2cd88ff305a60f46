"""The diagnosis's full Jacobian: through the per-pose corrections against one tangent per column.

At the geometric fit the missing-physics analyser needs every column of the extended model's
Jacobian, the frames' and every candidate's parameters (hundreds).
:func:`cdra_jax.diagnosis.model.residual_and_jacobian` takes the parameters' columns through the
per-pose corrections that they move (``dof + 12 K + 6`` tangents, 49 for the CDRA, then one
contraction with the features); :func:`cdra_jax.diagnosis.model.residual_and_columns` with every
column asked for is forward mode with one tangent per column. This script captures the problem
of a diagnosis of a synthetic recording (the default arm, ``--poses`` poses with tension closure,
a concealed shoulder compliance, the tests' noise), then times both compiled programs on it,
interleaved, and compares their columns (largest difference relative to the largest entry).

    python benchmarks/diagnosis_jacobian.py [--poses 30] [--repeats 15] [--json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import jax
import numpy as np

from cdra_jax.diagnosis import core, diagnose, model
from cdra_jax.io import default_arm
from cdra_jax.physics import Candidate, effect
from cdra_jax.physics.synthetic import simulate_recordings
from cdra_jax.simulation import NoiseModel


def _problem(poses: int):
    """``(y, problem)`` of the full-Jacobian call of a diagnosis of a synthetic recording."""
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
    return seen[-1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--poses", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--json", action="store_true", help="also print JSON on the last line")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)

    y, problem = _problem(args.poses)
    every = np.arange(y.shape[0])
    methods = {
        "through_corrections": lambda: model.residual_and_jacobian(y, problem),
        "one_tangent_per_column": lambda: model.residual_and_columns(y, problem, every),
    }
    results = {name: jax.block_until_ready(f()) for name, f in methods.items()}  # compiled
    times: dict[str, list[float]] = {name: [] for name in methods}
    for _ in range(args.repeats):
        for name, f in methods.items():
            start = time.perf_counter()
            jax.block_until_ready(f())
            times[name].append(time.perf_counter() - start)
    (_, J_new), (_, J_old) = results["through_corrections"], results["one_tangent_per_column"]
    J_new, J_old = np.asarray(J_new), np.asarray(J_old)
    scale = np.maximum(np.max(np.abs(J_old), axis=0), np.finfo(float).tiny)
    row = {
        "poses": args.poses,
        "residual_rows": int(J_old.shape[0]),
        "columns": int(J_old.shape[1]),
        "ms_through_corrections": 1e3 * statistics.median(times["through_corrections"]),
        "ms_one_tangent_per_column": 1e3 * statistics.median(times["one_tangent_per_column"]),
        "max_rel_difference": float(np.max(np.abs(J_new - J_old) / scale)),
    }
    row["speedup"] = row["ms_one_tangent_per_column"] / row["ms_through_corrections"]
    print(
        f"{row['residual_rows']} rows x {row['columns']} columns ({args.poses} poses): "
        f"through the corrections {row['ms_through_corrections']:.1f} ms, one tangent per "
        f"column {row['ms_one_tangent_per_column']:.1f} ms (medians of {args.repeats}, "
        f"interleaved): {row['speedup']:.1f}x; columns equal to "
        f"{row['max_rel_difference']:.1e} of their largest entry"
    )
    if args.json:
        print(json.dumps(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
