"""Few poses: how often do the solvers fail to converge on random pose sets near the minimum?

Setup: the default CDRA, ``--trials`` noise-free trials per pose count (``--poses``, default
4, 5, 6: the paper's lower bound of Eq. 9 and just above), each with its own random
tension-feasible module states and Section V frame errors (uniform +-1 mm / +-0.05 rad), as
:func:`cdra_jax.simulation.simulate_trial` draws them. Both solvers run on the same trials
(vmapped, ``throw=False``) with their default settings (paper: ``max_iterations=20``, LM: 50
steps). For the trials where either fails the script prints the result codes, the iteration
counts and the conditioning ``s_22 / s_1`` of the stacked Jacobian at the paper solver's
solution, and runs LM again on them with ``--lm-retry`` steps to see whether it converges.

Usage::

    python benchmarks/few_poses.py                       # 1000 trials each of m = 4, 5, 6
    python benchmarks/few_poses.py --poses 4 --trials 2000 --json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from cdra_jax import calibrate_lm, calibrate_paper, default_arm  # noqa: E402
from cdra_jax.calibration import result_names  # noqa: E402
from cdra_jax.compilation import jit  # noqa: E402
from cdra_jax.simulation import simulate_trial  # noqa: E402


def _solve(solver, arm, q, T, **options):
    return jit(jax.vmap(lambda q, T: solver(arm, q, T, throw=False, **options)))(q, T)


def study(arm, m: int, trials: int, seed: int, lm_retry: list[int]) -> dict:
    """Failures of both solvers on ``trials`` random noise-free ``m``-pose problems."""
    keys = jax.random.split(jax.random.PRNGKey(seed), trials)
    q, T, *_ = jit(jax.vmap(lambda k: simulate_trial(k, arm, m)))(keys)
    t0 = time.perf_counter()
    # the singular values of D~ at the solution (not computed by default)
    paper = jax.device_get(_solve(calibrate_paper, arm, q, T, singular_values=True))
    lm = jax.device_get(_solve(calibrate_lm, arm, q, T))
    names_p, names_l = result_names(paper.result), result_names(lm.result)
    bad = np.nonzero((names_p != "successful") | (names_l != "successful"))[0]
    s = paper.singular_values
    rank = paper.rank
    ratio = np.array([s[i, rank[i] - 1] / s[i, 0] for i in range(trials)])
    rows = [
        {
            "trial": int(i),
            "paper": str(names_p[i]),
            "paper_iterations": int(paper.iterations[i]),
            "lm": str(names_l[i]),
            "lm_iterations": int(lm.iterations[i]),
            "rank": int(rank[i]),
            "s_r_over_s_1": float(ratio[i]),
        }
        for i in bad
    ]
    retries = {}
    if len(bad):
        for steps in lm_retry:
            again = jax.device_get(_solve(calibrate_lm, arm, q[bad], T[bad], max_iterations=steps))
            names = result_names(again.result)
            retries[str(steps)] = {
                "converged": int(np.sum(names == "successful")),
                "iterations": [int(k) for k in again.iterations],
            }
    return {
        "m": m,
        "trials": trials,
        "paper_failures": int(np.sum(names_p != "successful")),
        "lm_failures": int(np.sum(names_l != "successful")),
        "median_s_r_over_s_1": float(np.median(ratio)),
        "trials_below_1e-7": int(np.sum(ratio < 1e-7)),
        "failed": rows,
        "lm_retry": retries,
        "seconds": time.perf_counter() - t0,
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--poses", type=int, nargs="+", default=[4, 5, 6])
    ap.add_argument("--trials", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lm-retry", type=int, nargs="*", default=[200, 1000])
    ap.add_argument("--json", action="store_true", help="JSON summary on the last line")
    args = ap.parse_args(argv)
    if args.trials < 1 or any(m < 4 for m in args.poses):
        ap.error("--trials must be >= 1 and every --poses value >= 4")
    arm = default_arm()
    out = {"results": [study(arm, m, args.trials, args.seed, args.lm_retry) for m in args.poses]}
    for r in out["results"]:
        print(
            f"m = {r['m']}: {r['trials']} trials, failures paper {r['paper_failures']}, "
            f"LM {r['lm_failures']}; s_r / s_1 median {r['median_s_r_over_s_1']:.2g}, "
            f"{r['trials_below_1e-7']} below 1e-7 ({r['seconds']:.1f} s)"
        )
        for row in r["failed"]:
            print(
                f"  trial {row['trial']}: paper {row['paper']} in {row['paper_iterations']}, "
                f"LM {row['lm']} in {row['lm_iterations']}, rank {row['rank']}, "
                f"s_r / s_1 = {row['s_r_over_s_1']:.2g}"
            )
        for steps, retry in r["lm_retry"].items():
            print(
                f"  LM with {steps} steps: {retry['converged']} of {len(r['failed'])} converge, "
                f"steps {retry['iterations']}"
            )
    if args.json:
        print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
