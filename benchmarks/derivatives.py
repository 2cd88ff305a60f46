"""What a derivative of a calibration costs, against the calibration alone.

Setup: the default CDRA, ``--trials`` trials of ``--poses`` poses with noise (80 um / 1e-3 rad,
Section V errors), weighted solves (``throw=False``). For each solver, two programs on the same
problems, compiled in the same process and timed side by side (calls interleaved, median of
``--repeats`` steady-state calls):

- ``solve``: ``jit(vmap(f))`` with ``f`` one predicted tool coordinate (x of the calibrated
  arm's tool at a held-out state);
- ``solve + gradient``: ``jit(vmap(grad(f)))``, the gradient with respect to the measured
  poses (``cdra_jax.calibration.implicit``: through the optimality condition).

The first call of each (trace, compile and run) is reported apart, and the gradient is checked
against a central difference of ``f`` along one random direction for the first trial.

Usage::

    python benchmarks/derivatives.py                      # 1000 trials, m = 15
    python benchmarks/derivatives.py --trials 4000 --poses 30 --json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from cdra_jax import NoiseModel, calibrate_lm, calibrate_paper, default_arm, lie, tool_pose  # noqa: E402
from cdra_jax.compilation import jit  # noqa: E402
from cdra_jax.simulation import simulate_trial  # noqa: E402

NOISE = NoiseModel(0.08, 1e-3)
SOLVERS = {"paper": calibrate_paper, "lm": calibrate_lm}


def _timed(fn, *args) -> float:
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - t0


def study(name: str, arm, q, T, q_ver, repeats: int) -> dict:
    """Steady-state and first-call times of the solve and of solve + gradient."""
    solver = SOLVERS[name]

    def predicted_x(T, q, q_ver):
        sol = solver(arm, q, T, NOISE, throw=False)
        return tool_pose(sol.calibrated_arm(arm), q_ver[0])[0, 3]

    programs = {
        "solve": jax.jit(jax.vmap(predicted_x)),
        "gradient": jax.jit(jax.vmap(jax.grad(predicted_x))),
    }
    first = {k: _timed(f, T, q, q_ver) for k, f in programs.items()}
    steady: dict[str, list[float]] = {k: [] for k in programs}
    for _ in range(repeats):  # interleaved, so that the host's load hits both alike
        for k, f in programs.items():
            steady[k].append(_timed(f, T, q, q_ver))
    median = {k: float(np.median(v)) for k, v in steady.items()}

    # The gradient of trial 0 against a central difference along a random rigid perturbation.
    grad0 = programs["gradient"](T[:1], q[:1], q_ver[:1])[0]
    xi = jnp.asarray(np.random.default_rng(0).normal(size=(T.shape[1], 6)) * 1e-3)
    f0 = jit(lambda h: predicted_x(lie.se3_exp(h * xi) @ T[0], q[0], q_ver[0]))
    h = 1e-3
    fd = float((f0(h) - f0(-h)) / (2 * h))
    analytic = float(jnp.sum(grad0 * (lie.hat(xi) @ T[0])))  # d/dh exp(h xi) T = hat(xi) T
    return {
        "solver": name,
        "solve_s": median["solve"],
        "gradient_s": median["gradient"],
        "ratio": median["gradient"] / median["solve"],
        "first_call_solve_s": first["solve"],
        "first_call_gradient_s": first["gradient"],
        "check_directional": analytic,
        "check_central_difference": fd,
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trials", type=int, default=1000)
    parser.add_argument("--poses", type=int, default=15)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--solvers", default="paper,lm")
    parser.add_argument("--json", action="store_true", help="print one JSON object last")
    args = parser.parse_args(argv)
    arm = default_arm()
    keys = jax.random.split(jax.random.PRNGKey(0), args.trials)
    q, T, q_ver, _, _ = jit(jax.vmap(lambda k: simulate_trial(k, arm, args.poses, noise=NOISE)))(
        keys
    )
    rows = [study(s, arm, q, T, q_ver, args.repeats) for s in args.solvers.split(",")]
    load = os.getloadavg()[0]
    print(
        f"# {args.trials} trials, m = {args.poses}, weighted (80 um / 1e-3 rad), medians of "
        f"{args.repeats} interleaved calls; load {load:.1f}"
    )
    print(
        "solver  solve s  solve+gradient s  ratio  first call s (solve / gradient)  "
        "check: gradient . v  central difference"
    )
    for r in rows:
        print(
            f"{r['solver']:6s}  {r['solve_s']:7.3f}  {r['gradient_s']:16.3f}  {r['ratio']:5.1f}  "
            f"{r['first_call_solve_s']:.1f} / {r['first_call_gradient_s']:.1f}"
            f"{'':22s}{r['check_directional']:.9g}  {r['check_central_difference']:.9g}"
        )
    out = {"trials": args.trials, "poses": args.poses, "load_average": load, "rows": rows}
    if args.json:
        print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
