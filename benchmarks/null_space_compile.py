"""Compile time of the solvers on an arm with many structural null directions.

The solvers' null-space step (:func:`cdra_jax.calibration.linear.null_space_solve`) and the
null basis (:func:`cdra_jax.calibration.nullspace.orthonormalise`) write their products with
the ``k`` null directions column by column for ``k <= UNROLLED_COLUMNS`` (fused element-wise
code, the fastest form under ``vmap`` for the default arm's ``k = 2``) and as matrix products
and a Householder QR above it (the column-by-column code grows as ``k^2``). This script times
the trace + lowering and the compilation of the paper and LM solvers on the UR5 of
``examples/ur5`` (six revolute modules, ``k = 12``) in both forms, interleaved in one process
with the in-memory caches cleared before each, and compares their frames. Unbatched by
default; ``--trials N`` compiles them ``vmap``ped over N simulated trials instead and also
times the compiled programs (median of ``--calls`` calls each, interleaved, us per trial).

    python benchmarks/null_space_compile.py [--poses 15] [--repeats 3] [--suite-options]
        [--trials N [--calls 5]] [--revolute R] [--json]

``--revolute R`` replaces the UR5 by a chain of ``R`` revolute modules and a spherical one, with
random axes and fixed frames (seeded; ``k = 2 R``), to place the crossover of the two forms.

``--suite-options`` compiles with the test suite's XLA options (``tests/conftest.py``: no LLVM
optimisation passes, one code-generation part per program), set before JAX starts.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SUITE_XLA_FLAGS = (
    "--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false "
    "--xla_cpu_parallel_codegen_split_count=1"
)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--poses", type=int, default=15, help="poses per calibration (default 15)")
    p.add_argument("--repeats", type=int, default=3, help="interleaved rounds (default 3)")
    p.add_argument("--suite-options", action="store_true", help="the test suite's XLA options")
    p.add_argument("--trials", type=int, default=0, help="vmap over this many trials (default 0)")
    p.add_argument("--calls", type=int, default=5, help="timed calls per program (with --trials)")
    p.add_argument("--revolute", type=int, default=0, help="a random chain of R revolute modules")
    p.add_argument("--json", action="store_true", help="print one JSON object on the last line")
    args = p.parse_args(argv)
    if args.suite_options:
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + SUITE_XLA_FLAGS).strip()

    import jax
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    import cdra_jax as cj
    from cdra_jax.calibration import nullspace
    from cdra_jax.compilation import jit
    from cdra_jax.io import load_model
    from cdra_jax.simulation import simulate_trial

    if args.revolute:
        arm = _random_chain(args.revolute)
        label = f"{args.revolute} revolute modules and a spherical one (random, seed 5)"
    else:
        arm = load_model(ROOT / "examples" / "ur5" / "ur5_markers.toml")
        label = "examples/ur5/ur5_markers.toml"
    k = nullspace.structural_nullity(arm)

    def simulate(key):
        return simulate_trial(key, arm, args.poses)[:2]

    if args.trials:
        keys = jax.random.split(jax.random.PRNGKey(0), args.trials)
        q, T = jax.jit(jax.vmap(simulate))(keys)
    else:
        q, T = jax.jit(simulate)(jax.random.PRNGKey(0))
    solvers = {"paper": cj.calibrate_paper, "lm": cj.calibrate_lm}
    forms = {"columns": 10**6, "matrices": 0}
    default_limit = nullspace.UNROLLED_COLUMNS
    times: dict[str, dict[str, list[tuple[float, float]]]] = {
        s: {f: [] for f in forms} for s in solvers
    }
    frames: dict[tuple[str, str], np.ndarray] = {}
    programs: dict[tuple[str, str], object] = {}
    for _ in range(args.repeats):
        for form, limit in forms.items():
            nullspace.UNROLLED_COLUMNS = limit
            for name, solve in solvers.items():
                jax.clear_caches()

                def one(q, T, solve=solve):
                    return solve(arm, q, T, throw=False)

                fn = jit(jax.vmap(one) if args.trials else one)
                t0 = time.perf_counter()
                lowered = fn.jitted.lower(q, T)
                t1 = time.perf_counter()
                compiled = lowered.compile()
                t2 = time.perf_counter()
                times[name][form].append((t1 - t0, t2 - t1))
                frames[(name, form)] = np.asarray(compiled(q, T).frames)
                programs[(name, form)] = compiled
    nullspace.UNROLLED_COLUMNS = default_limit
    run: dict[tuple[str, str], list[float]] = {key: [] for key in programs}
    for _ in range(args.calls if args.trials else 0):
        for key, compiled in programs.items():
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(q, T))  # type: ignore[operator]
            run[key].append(time.perf_counter() - t0)
    out: dict = {"arm": label, "null_directions": k, "poses": args.poses}
    out["trials"] = args.trials
    batch = f"vmapped over {args.trials} trials" if args.trials else "unbatched"
    print(f"{k} structural null directions, {batch}; median of {args.repeats} rounds (s)")
    print(f"{'solver':8s} {'form':9s} {'trace+lower':>12s} {'compile':>8s} {'us/trial':>9s}")
    for name in solvers:
        for form in forms:
            lower = statistics.median(t[0] for t in times[name][form])
            comp = statistics.median(t[1] for t in times[name][form])
            us = statistics.median(run[(name, form)]) / args.trials * 1e6 if args.trials else None
            rate = f"{us:9.1f}" if us is not None else f"{'-':>9s}"
            print(f"{name:8s} {form:9s} {lower:12.2f} {comp:8.2f} {rate}")
            out[f"{name}_{form}_us_per_trial"] = None if us is None else round(us, 1)
            out[f"{name}_{form}_lower_s"] = round(lower, 3)
            out[f"{name}_{form}_compile_s"] = round(comp, 3)
            out[f"{name}_{form}_compile_all_s"] = [round(t[1], 3) for t in times[name][form]]
        diff = float(np.abs(frames[(name, "columns")] - frames[(name, "matrices")]).max())
        print(f"{name}: largest frame difference between the forms {diff:.1e}")
        out[f"{name}_frame_difference"] = diff
    if args.json:
        print(json.dumps(out))
    return out


def _random_chain(revolute: int):
    """``revolute`` revolute modules (random axes) and a spherical one between random fixed
    frames (rotations from random rotation vectors, translations ~200 mm), seed 5."""
    import jax.numpy as jnp
    import numpy as np
    from scipy.spatial.transform import Rotation

    from cdra_jax import arm as arm_lib

    rng = np.random.default_rng(5)
    modules = [arm_lib.revolute(f"r{i}", rng.normal(size=3)) for i in range(revolute)]
    modules.append(arm_lib.spherical("s"))
    k1 = len(modules) + 1
    frames = np.broadcast_to(np.eye(4), (k1, 4, 4)).copy()
    frames[:, :3, :3] = Rotation.from_rotvec(rng.normal(size=(k1, 3))).as_matrix()
    frames[:, :3, 3] = rng.normal(size=(k1, 3)) * 200.0
    return arm_lib.Arm(
        frames=jnp.asarray(frames),
        modules=tuple(modules),
        frame_names=tuple(f"f{j}" for j in range(k1)),
    )


if __name__ == "__main__":
    main(sys.argv[1:])
