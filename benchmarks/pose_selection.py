"""Selected against random poses: held-out accuracy against the number of calibration poses.

For each ``m`` in ``--m-min..--m-max`` and each of ``--trials`` trials (random Section V frame
errors, +-1 mm / +-0.05 rad; Gaussian measurement noise ``--noise-pos`` mm / ``--noise-rot``
rad), the weighted solver (``calibrate_paper(..., noise)``) calibrates from

* ``random``: ``m`` states drawn uniformly within the joint limits, new ones every trial, or
* one column per criterion of ``--criteria`` (default ``i-opt,d-opt``): the ``m`` states chosen
  once by :func:`cdra_jax.pose_selection.select_from_pool` from ``--pool`` tension-feasible
  states (:func:`cdra_jax.simulation.sample_poses`) on the nominal model (the errors are
  unknown when one plans), with 1000 uniform states as the workspace reference of ``i-opt``,

and is scored by ``dp`` (Eq. 20) against the true (noise-free) tool poses at ``--verify`` fresh
random states. All columns share the trials' errors and noise (common random numbers). Printed:
median ``dp`` (mm) with a distribution-free 95 % confidence interval of the median (order
statistics), the selected sets' predicted ``sqrt(E[dp^2])`` (first order,
:mod:`cdra_jax.uncertainty`), the first ``m`` whose selected median is at or below the random
median at ``--target`` poses, and, with ``--bound M ...``, the certified lower bound of
:func:`cdra_jax.pose_selection.prediction_bound` on the predicted ``sqrt(E[dp^2])`` of any
``M`` poses, from the pool and from the ``3^dof`` grid of joint-limit extremes and mid-points
plus 5000 uniform states, next to the prediction for random ``--target``-pose sets.

Usage::

    python benchmarks/pose_selection.py                     # m = 5..15, 200 trials
    python benchmarks/pose_selection.py --bound 7 --json    # as in the README (~10 min)
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402

from cdra_jax import (  # noqa: E402
    NoiseModel,
    apply_frame_errors,
    calibrate_paper,
    default_arm,
    deviation_metrics,
    tool_pose,
)
from cdra_jax.pose_selection import (  # noqa: E402
    CRITERIA,
    prediction_bound,
    select_from_pool,
)
from cdra_jax.simulation import (  # noqa: E402
    measure,
    random_frame_errors,
    sample_poses,
    sample_states,
)
from cdra_jax.uncertainty import predicted_pose_covariance  # noqa: E402


def median_ci(x: np.ndarray, confidence: float = 0.95) -> tuple[float, float, float]:
    """Median and its distribution-free confidence interval (binomial order statistics)."""
    x = np.sort(x)
    n = len(x)
    lo = int(stats.binom.ppf((1 - confidence) / 2, n, 0.5))
    hi = int(stats.binom.isf((1 - confidence) / 2, n, 0.5))
    return float(np.median(x)), float(x[max(lo - 1, 0)]), float(x[min(hi, n - 1)])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--m-min", type=int, default=5)
    ap.add_argument("--m-max", type=int, default=15)
    ap.add_argument("--target", type=int, default=15, help="random pose count to match")
    ap.add_argument("--pool", type=int, default=5000)
    ap.add_argument("--verify", type=int, default=100)
    ap.add_argument("--noise-pos", type=float, default=0.08)
    ap.add_argument("--noise-rot", type=float, default=1e-3)
    ap.add_argument(
        "--criteria", default="i-opt,d-opt", help="comma-separated, of " + ",".join(CRITERIA)
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--bound", type=int, nargs="*", default=[], metavar="M",
                    help="also compute the approximate-design lower bound at these m")  # fmt: skip
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    criteria = [c.strip() for c in args.criteria.split(",") if c.strip()]
    for c in criteria:
        if c not in CRITERIA:
            ap.error(f"--criteria: unknown criterion {c!r} (choose from {CRITERIA})")

    arm = default_arm()
    noise = NoiseModel(args.noise_pos, args.noise_rot)
    keys = jax.random.split(jax.random.PRNGKey(args.seed + 1), args.trials)
    # where the arm will be used: the held-out distribution (uniform in the joint box), drawn
    # independently of every trial's held-out states
    reference = np.asarray(sample_states(jax.random.PRNGKey(12345), arm, 1000))
    pool = np.asarray(sample_poses(jax.random.PRNGKey(args.seed), arm, args.pool))

    def trial(key, q_cal):
        k_err, k_noise, k_ver = jax.random.split(key, 3)
        actual = apply_frame_errors(arm, random_frame_errors(k_err, arm))
        sol = calibrate_paper(
            arm, q_cal, measure(k_noise, actual, q_cal, noise), noise, throw=False
        )
        q_ver = sample_states(k_ver, arm, args.verify)
        dp, _ = deviation_metrics(
            tool_pose(actual, q_ver), tool_pose(arm.with_frames(sol.frames), q_ver)
        )
        return dp, sol.result._value

    batched = jax.jit(jax.vmap(trial))  # one compile per m, shared by all pose choices
    random_states = jax.jit(jax.vmap(sample_states, in_axes=(0, None, None)), static_argnums=2)

    def predicted(q):
        return float(predicted_pose_covariance(arm, q, noise, reference).expected_delta_p)

    print(
        f"held-out dp (mm, Eq. 20 vs the true arm at {args.verify} random states): median and "
        f"95% CI over {args.trials} trials; noise {args.noise_pos} mm / {args.noise_rot} rad; "
        f"selected from {args.pool} tension-feasible pool states; pred = predicted "
        "sqrt(E dp^2) (mm, first order)"
    )
    head = f"{'m':>3} {'random':>8} {'95% CI':>17}"
    for c in criteria:
        head += f" {c:>8} {'95% CI':>17} {'pred':>6} {'exch':>4}"
    print(head)
    rows = []
    t0 = time.perf_counter()
    for m in range(args.m_min, args.m_max + 1):
        q_rand = random_states(jax.vmap(lambda k: jax.random.fold_in(k, 99))(keys), arm, m)
        dp_r, c_r = batched(keys, q_rand)
        row = {"m": m, "random": median_ci(np.asarray(dp_r)), "failed": int(np.sum(c_r != 0))}
        line = f"{m:3d} {row['random'][0]:8.4f} [{row['random'][1]:.4f}, {row['random'][2]:.4f}]"
        for c in criteria:
            sel = select_from_pool(arm, pool, m, noise, criterion=c, reference=reference)
            q_sel = jnp.asarray(sel.states)
            dp_s, c_s = batched(keys, jnp.broadcast_to(q_sel, (args.trials, *q_sel.shape)))
            s = median_ci(np.asarray(dp_s))
            row[c] = {
                "median_ci": s,
                "predicted": predicted(sel.states),
                "n_exchanges": sel.n_exchanges,
            }
            row["failed"] += int(np.sum(c_s != 0))
            line += f" {s[0]:8.4f} [{s[1]:.4f}, {s[2]:.4f}] {row[c]['predicted']:6.4f} "
            line += f"{sel.n_exchanges:4d}"
        rows.append(row)
        print(line, flush=True)
    summary = {"rows": rows, "criteria": criteria, "seconds": time.perf_counter() - t0}
    target = next((row for row in rows if row["m"] == args.target), None)
    if target is not None:
        goal = target["random"][0]
        summary["random_target_median"] = goal
        for c in criteria:
            reach = next((row["m"] for row in rows if row[c]["median_ci"][0] <= goal), None)
            summary.setdefault("selected_m_reaching_it", {})[c] = reach
            print(
                f"random {args.target} poses: median {goal:.4f} mm; reached by {c} poses at "
                f"m = {reach}"
            )
    if args.bound:
        rand = [
            predicted(sample_states(jax.random.PRNGKey(500 + i), arm, args.target))
            for i in range(50)
        ]
        lim = np.asarray(arm.state_limits)
        levels = [(lo, 0.5 * (lo + hi), hi) for lo, hi in lim]
        grid = np.array(list(itertools.product(*levels)))  # 3^dof: the joint-limit extremes
        box = np.vstack([grid, np.asarray(sample_states(jax.random.PRNGKey(7), arm, 5000))])
        summary["random_target_predicted_median"] = float(np.median(rand))
        print(
            f"predicted sqrt(E dp^2) of {args.target} random poses (median of 50 sets): "
            f"{np.median(rand):.4f} mm"
        )
        for m in args.bound:
            b_pool = prediction_bound(arm, pool, m, noise, reference=reference)
            b_box = prediction_bound(arm, box, m, noise, reference=reference)
            summary.setdefault("bound", {})[m] = {
                "pool_lower": b_pool.lower,
                "pool_approximate": b_pool.approximate,
                "box_lower": b_box.lower,
                "box_approximate": b_box.approximate,
                "box_states": len(box),
            }
            print(
                f"no {m} poses can give a predicted sqrt(E dp^2) below {b_pool.lower:.4f} mm "
                f"from the pool, below {b_box.lower:.4f} mm from {len(box)} box states "
                f"(3^{arm.dof} grid of the joint limits + 5000 uniform, feasibility ignored)"
            )
    if args.json:
        print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
