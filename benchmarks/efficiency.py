"""Statistical efficiency: does the weighted estimator reach the Cramer-Rao bound?

Setup: the default CDRA, one fixed set of ``--poses`` random module states, one fixed set of
Section V frame errors (uniform +-1 mm / +-0.05 rad), and ``--trials`` independent draws of
isotropic Gaussian measurement noise (``--noise-pos`` mm, ``--noise-rot`` rad, default the
paper's 80 um FARO arm and 1e-3 rad, the orientation that calibration-block points ~80 mm apart
give at 80 um). Each draw is calibrated (vmapped, in chunks of ``--chunk``) by

* ``weighted``: ``calibrate_paper(..., noise=NoiseModel(...))``, the whitened (maximum-likelihood)
  estimator whose efficiency is claimed, and, for contrast,
* ``paper``: the paper's unweighted Eq. 10 (``noise=None``).

The estimation error of each trial is ``e = log(F_c F_true^-1)`` (Eqs. 15-18 at the truth). The
Fisher information ``F = D~^T D~`` at the truth (:mod:`cdra_jax.uncertainty`) has principal axes
``u_i`` (right singular vectors of ``D~``) with ``F u_i = s_i^2 u_i``; the Cramer-Rao bound on
``u_i^T X`` is ``1 / s_i^2`` (i = 1..22: the identifiable directions; the two null directions have
no bound). The efficiency along ``u_i`` is ``eff_i = (1 / s_i^2) / Var_MC(u_i^T e)``; its 95 %
confidence interval follows from ``(n - 1) s^2 / sigma^2 ~ chi2(n - 1)``:
``[chi2_0.025 / ((n - 1) v), chi2_0.975 / ((n - 1) v)]`` with ``v = s_i^2 Var_MC``. The pooled
efficiency over all 22 axes (``22 (n - 1)`` degrees of freedom) is reported too.

Usage::

    python benchmarks/efficiency.py                     # 20000 trials, m = 10
    python benchmarks/efficiency.py --trials 20000 --poses 15 --json
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
from scipy import stats  # noqa: E402

from cdra_jax import (  # noqa: E402
    NoiseModel,
    apply_frame_errors,
    calibrate_paper,
    default_arm,
    lie,
    tool_pose,
)
from cdra_jax.compilation import jit  # noqa: E402
from cdra_jax.identifiability import format_combination  # noqa: E402
from cdra_jax.simulation import measure, random_frame_errors, sample_states  # noqa: E402
from cdra_jax.uncertainty import parameter_covariance  # noqa: E402


def efficiency_table(y: np.ndarray, confidence: float = 0.95) -> dict:
    """Per-axis and pooled efficiency of standardised errors ``y (n, r)`` (unit variance if
    efficient), with chi-square confidence intervals."""
    n, r = y.shape
    v = y.var(axis=0, ddof=1)
    a = (1 - confidence) / 2
    lo = stats.chi2.ppf(a, n - 1) / ((n - 1) * v)
    hi = stats.chi2.ppf(1 - a, n - 1) / ((n - 1) * v)
    pooled = v.mean()
    dof = r * (n - 1)
    return {
        "eff": 1 / v,
        "lo": lo,
        "hi": hi,
        "bias_over_std": y.mean(axis=0) / np.sqrt(v),
        "pooled": 1 / pooled,
        "pooled_lo": stats.chi2.ppf(a, dof) / (dof * pooled),
        "pooled_hi": stats.chi2.ppf(1 - a, dof) / (dof * pooled),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=20000)
    ap.add_argument("--poses", type=int, default=10)
    ap.add_argument("--noise-pos", type=float, default=0.08)
    ap.add_argument("--noise-rot", type=float, default=1e-3)
    ap.add_argument("--chunk", type=int, default=5000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--solvers", default="weighted,paper")
    ap.add_argument("--json", action="store_true", help="JSON summary on the last line")
    args = ap.parse_args(argv)

    arm = default_arm()
    noise = NoiseModel(args.noise_pos, args.noise_rot)
    k_q, k_x, k_n = jax.random.split(jax.random.PRNGKey(args.seed), 3)
    q = sample_states(k_q, arm, args.poses)
    actual = apply_frame_errors(arm, random_frame_errors(k_x, arm))
    unc = parameter_covariance(actual, q, noise, tool_pose(actual, q))
    r = int(unc.rank)
    s = np.asarray(unc.singular_values)[:r]
    U = np.asarray(unc.basis)[:r]  # principal axes (rows)
    print(
        f"device {jax.devices()[0].platform}, m = {args.poses}, noise {args.noise_pos} mm / "
        f"{args.noise_rot} rad, {args.trials} trials, rank {r} of {arm.n_params}"
    )
    summary: dict = {"trials": args.trials, "m": args.poses, "rank": r}
    for solver in args.solvers.split(","):
        w = noise if solver == "weighted" else None

        def trial(key, w=w):
            sol = calibrate_paper(arm, q, measure(key, actual, q, noise), w, throw=False)
            e = lie.se3_log(sol.frames @ lie.inverse(actual.frames)).reshape(-1)
            return e, sol.result._value

        f = jit(jax.vmap(trial))
        keys = jax.random.split(jax.random.fold_in(k_n, 1), args.trials)
        t0 = time.perf_counter()
        es, codes = [], []
        for start in range(0, args.trials, args.chunk):
            e, c = f(keys[start : start + args.chunk])
            es.append(np.asarray(e))
            codes.append(np.asarray(c))
        e, codes = np.concatenate(es), np.concatenate(codes)
        dt = time.perf_counter() - t0
        ok = codes == 0
        y = (e[ok] @ U.T) * s  # standardised: unit variance at the bound
        tab = efficiency_table(y)
        print(
            f"\n{solver}: {ok.sum()} of {len(ok)} trials converged ({dt:.1f} s incl. compile); "
            "efficiency = CRB / MC variance per principal axis of the Fisher information"
        )
        print(f"  {'axis':>4} {'CRB std':>10} {'MC std':>10} {'eff':>7} {'95% CI':>17} "
              f"{'bias/std':>8}  main parameters")  # fmt: skip
        for i in range(r):
            print(
                f"  {i + 1:4d} {1 / s[i]:10.3g} {np.sqrt(1 / tab['eff'][i]) / s[i]:10.3g} "
                f"{tab['eff'][i]:7.3f} [{tab['lo'][i]:.3f}, {tab['hi'][i]:.3f}] "
                f"{tab['bias_over_std'][i]:8.3f}  "
                f"{format_combination(np.where(np.abs(U[i]) > 0.3, U[i], 0), arm.param_names)}"
            )
        print(
            f"  pooled efficiency {tab['pooled']:.4f} [{tab['pooled_lo']:.4f}, "
            f"{tab['pooled_hi']:.4f}]; min per axis {tab['eff'].min():.3f} (its CI upper end "
            f"{tab['hi'][np.argmin(tab['eff'])]:.3f}); axes whose CI lies wholly below 0.95: "
            f"{int(np.sum(tab['hi'] < 0.95))}"
        )
        summary[solver] = {
            "converged": int(ok.sum()),
            "pooled_efficiency": float(tab["pooled"]),
            "pooled_ci": [float(tab["pooled_lo"]), float(tab["pooled_hi"])],
            "min_efficiency": float(tab["eff"].min()),
            "max_efficiency": float(tab["eff"].max()),
            "axes_significantly_below_0.95": int(np.sum(tab["hi"] < 0.95)),
            "seconds": dt,
        }
    if args.json:
        print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
