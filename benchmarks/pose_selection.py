"""Selected against random poses: held-out accuracy against the number of calibration poses.

For each ``m`` in ``--m-min..--m-max`` and each of ``--trials`` trials (random Section V frame
errors, +-1 mm / +-0.05 rad; Gaussian measurement noise ``--noise-pos`` mm / ``--noise-rot``
rad), the weighted solver (``calibrate_paper(..., noise)``) calibrates from

* ``random``: ``m`` states drawn uniformly within the joint limits, new ones every trial, or
* ``selected``: the ``m`` states chosen once by :func:`cdra_jax.pose_selection.select_poses`
  (``--criterion``, default D-optimal) from a pool of ``--pool`` uniform states, on the nominal
  model (the errors are unknown when one plans),

and is scored by ``dp`` (Eq. 20) against the true (noise-free) tool poses at ``--verify`` fresh
random states. Both curves share the trials' errors and noise (common random numbers). Printed:
median ``dp`` (mm) with a distribution-free 95 % confidence interval of the median (order
statistics), the first ``m`` whose selected median is at or below the random median at
``--target`` poses, and, with ``--bound``, a lower bound on what any ``m``-pose set within the
joint limits can achieve for the expected held-out error (gradient descent on the states of
the predicted ``E[dp^2]`` from :mod:`cdra_jax.uncertainty`, several starts).

Usage::

    python benchmarks/pose_selection.py                     # m = 5..15, 200 trials
    python benchmarks/pose_selection.py --bound 7 --json
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
from cdra_jax.pose_selection import select_poses  # noqa: E402
from cdra_jax.simulation import measure, random_frame_errors, sample_states  # noqa: E402
from cdra_jax.uncertainty import predicted_pose_covariance  # noqa: E402


def median_ci(x: np.ndarray, confidence: float = 0.95) -> tuple[float, float, float]:
    """Median and its distribution-free confidence interval (binomial order statistics)."""
    x = np.sort(x)
    n = len(x)
    lo = int(stats.binom.ppf((1 - confidence) / 2, n, 0.5))
    hi = int(stats.binom.isf((1 - confidence) / 2, n, 0.5))
    return float(np.median(x)), float(x[max(lo - 1, 0)]), float(x[min(hi, n - 1)])


def design_bound(arm, noise, m, q_eval, starts, steps=1500, seed=0):
    """Smallest predicted sqrt(E[dp^2]) found by Adam on m states (box-constrained through a
    sigmoid) from ``starts`` D-optimal starting sets."""
    lim = jnp.asarray(arm.state_limits)

    def loss(z):
        q = lim[:, 0] + jax.nn.sigmoid(z) * (lim[:, 1] - lim[:, 0])
        return predicted_pose_covariance(arm, q, noise, q_eval).expected_delta_p ** 2

    grad = jax.jit(jax.value_and_grad(loss))
    best = np.inf
    for s in range(starts):
        q0 = select_poses(arm, m, noise, key=jax.random.PRNGKey(seed + s), pool_size=2000).states
        u = np.clip(
            (q0 - np.asarray(lim[:, 0])) / np.asarray(lim[:, 1] - lim[:, 0]), 1e-3, 1 - 1e-3
        )
        z = jnp.asarray(np.log(u / (1 - u)))
        mom, var = jnp.zeros_like(z), jnp.zeros_like(z)
        for k in range(1, steps + 1):
            val, g = grad(z)
            mom = 0.9 * mom + 0.1 * g
            var = 0.999 * var + 0.001 * g * g
            z = z - 0.05 * (mom / (1 - 0.9**k)) / (jnp.sqrt(var / (1 - 0.999**k)) + 1e-12)
        best = min(best, float(jnp.sqrt(loss(z))))
    return best


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--m-min", type=int, default=5)
    ap.add_argument("--m-max", type=int, default=15)
    ap.add_argument("--target", type=int, default=15, help="random pose count to match")
    ap.add_argument("--pool", type=int, default=2000)
    ap.add_argument("--verify", type=int, default=100)
    ap.add_argument("--noise-pos", type=float, default=0.08)
    ap.add_argument("--noise-rot", type=float, default=1e-3)
    ap.add_argument("--criterion", default="d-opt", choices=("d-opt", "o1"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--bound", type=int, nargs="*", default=[], metavar="M",
                    help="also compute the design bound at these m")  # fmt: skip
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)

    arm = default_arm()
    noise = NoiseModel(args.noise_pos, args.noise_rot)
    keys = jax.random.split(jax.random.PRNGKey(args.seed + 1), args.trials)

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

    batched = jax.jit(jax.vmap(trial))  # one compile per m, shared by both pose choices
    random_states = jax.jit(jax.vmap(sample_states, in_axes=(0, None, None)), static_argnums=2)

    print(
        f"held-out dp (mm, Eq. 20 vs the true arm at {args.verify} random states): median and "
        f"95% CI over {args.trials} trials; noise {args.noise_pos} mm / {args.noise_rot} rad; "
        f"selection: {args.criterion} from {args.pool} pool states"
    )
    print(f"{'m':>3} {'random':>8} {'95% CI':>17} {'selected':>9} {'95% CI':>17} {'exch':>4}")
    rows = []
    t0 = time.perf_counter()
    for m in range(args.m_min, args.m_max + 1):
        sel = select_poses(
            arm, m, noise, key=jax.random.PRNGKey(args.seed), pool_size=args.pool,
            criterion=args.criterion,
        )  # fmt: skip
        q_sel = jnp.asarray(sel.states)
        dp_s, c_s = batched(keys, jnp.broadcast_to(q_sel, (args.trials, *q_sel.shape)))
        q_rand = random_states(jax.vmap(lambda k: jax.random.fold_in(k, 99))(keys), arm, m)
        dp_r, c_r = batched(keys, q_rand)
        r = median_ci(np.asarray(dp_r))
        s = median_ci(np.asarray(dp_s))
        failed = int(np.sum(np.asarray(c_r) != 0) + np.sum(np.asarray(c_s) != 0))
        rows.append(
            {"m": m, "random": r, "selected": s, "n_exchanges": sel.n_exchanges, "failed": failed}
        )
        print(
            f"{m:3d} {r[0]:8.4f} [{r[1]:.4f}, {r[2]:.4f}] {s[0]:9.4f} [{s[1]:.4f}, {s[2]:.4f}] "
            f"{sel.n_exchanges:4d}",
            flush=True,
        )
    target = next((row for row in rows if row["m"] == args.target), None)
    summary = {"rows": rows, "seconds": time.perf_counter() - t0}
    if target is not None:
        goal = target["random"][0]
        reach = next((row["m"] for row in rows if row["selected"][0] <= goal), None)
        summary.update({"random_target_median": goal, "selected_m_reaching_it": reach})
        print(
            f"random {args.target} poses: median {goal:.4f} mm; reached by selected poses at "
            f"m = {reach}"
        )
    q_eval = sample_states(jax.random.PRNGKey(12345), arm, 1000)
    for m in args.bound:
        b = design_bound(arm, noise, m, q_eval, starts=3)
        rand = np.median(
            [
                float(
                    predicted_pose_covariance(
                        arm, sample_states(jax.random.PRNGKey(500 + i), arm, args.target),
                        noise, q_eval,
                    ).expected_delta_p
                )
                for i in range(50)
            ]
        )  # fmt: skip
        sel = select_poses(arm, m, noise, key=jax.random.PRNGKey(args.seed), pool_size=args.pool)
        pred_sel = float(predicted_pose_covariance(arm, sel.states, noise, q_eval).expected_delta_p)
        summary.setdefault("bound", {})[m] = {
            "best_any_states": b,
            "selected": pred_sel,
            "random_target": float(rand),
        }
        print(
            f"predicted sqrt(E dp^2) (mm): best {m} states found by gradient descent {b:.4f}; "
            f"selected {m} {pred_sel:.4f}; random {args.target} (median of 50 sets) {rand:.4f}"
        )
    if args.json:
        print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
