"""Benchmark: robust calibration under 10 % gross outliers (a mis-seated probe).

Each trial simulates the paper's procedure (Section V, random frame errors of +-1 mm /
+-0.05 rad) with measurement noise, then corrupts 10 % of the calibration poses with a gross
error of 5 mm along a random direction and 0.05 rad about a random axis
(:func:`cdra_jax.simulation.add_outliers`), and fits four ways:

* clean LS: least squares on the uncorrupted poses (the reference),
* clean Huber: the robust fit of the uncorrupted poses (what robustness costs on clean data),
* contaminated LS: least squares on the corrupted poses,
* inliers only LS: least squares on the uncorrupted poses alone (with the stated noise model;
  the best any estimator that finds and drops the outliers can do),
* contaminated Huber / Cauchy: :func:`cdra_jax.calibration.robust.calibrate_robust`,
* contam. Huber / Cauchy + reject: the same with ``reject_outliers=True`` (least-squares refit
  without the flagged poses).

Besides the medians, the table gives per trial the ratio of each fit's held-out dp to the clean
LS fit's on the same draw: its 90th percentile and the share of trials within 1.5x (against the
noisy held-out measurements, and against the true tool poses).

Held-out ``dp`` / ``dR`` (Eqs. 20-21) are measured on separate verification poses, both against
their noisy measurements (what a user can measure) and against the true tool poses of the
simulated arm (the prediction error). The table shows medians over trials and the ratio of the
median to the clean fit's. Two blocks: with the stated noise model (weighted least squares,
scale from the noise) and without (the paper's unweighted least squares; the robust fits then
estimate the scale by MAD and, from their first reweighting on, weight position and rotation by
it, which is why they beat the unweighted clean fit there).

    PYTHONPATH=. python benchmarks/robust.py [--trials 50] [--poses 30] [--seed 0]
"""

from __future__ import annotations

import argparse
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

ROWS = (
    "clean LS",
    "clean Huber",
    "inliers only LS",
    "contaminated LS",
    "contaminated Huber",
    "contaminated Cauchy",
    "contam. Huber+reject",
    "contam. Cauchy+reject",
)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--trials", type=int, default=50)
    p.add_argument("--poses", type=int, default=30, help="calibration poses per trial")
    p.add_argument("--verify", type=int, default=100, help="held-out poses per trial")
    p.add_argument("--fraction", type=float, default=0.1, help="fraction of gross outliers")
    p.add_argument("--outlier-pos", type=float, default=5.0, help="gross position error (mm)")
    p.add_argument("--outlier-rot", type=float, default=0.05, help="gross rotation error (rad)")
    p.add_argument("--noise-pos", type=float, default=0.08, help="noise std (mm)")
    p.add_argument("--noise-rot", type=float, default=0.001, help="noise std (rad)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    jax.config.update("jax_enable_x64", True)

    from cdra_jax import apply_frame_errors, default_arm, tool_pose
    from cdra_jax.calibration import NoiseModel, calibrate_paper, deviation_metrics
    from cdra_jax.calibration.robust import calibrate_robust
    from cdra_jax.simulation import add_outliers, simulate_trial

    arm = default_arm()
    noise = NoiseModel(args.noise_pos, args.noise_rot)
    n_out = int(round(args.fraction * args.poses))

    def trial(key, stated):
        k_sim, k_out = jax.random.split(key)
        q, T, qv, Tv, X = simulate_trial(k_sim, arm, args.poses, noise=noise, m_verify=args.verify)
        T_bad, mask = add_outliers(k_out, T, n_out, args.outlier_pos, args.outlier_rot)
        truth = tool_pose(apply_frame_errors(arm, X), qv)
        nm = noise if stated else None
        fits = {
            "clean LS": calibrate_paper(arm, q, T, nm, throw=False),
            "contaminated LS": calibrate_paper(arm, q, T_bad, nm, throw=False),
        }
        if stated:  # the oracle: least squares on the uncorrupted poses only (weight 0 on the rest)
            sw = jnp.where(mask, 0.0, 1.0)
            oracle = NoiseModel(noise.position_mm / sw, noise.rotation_rad / sw)
            fits["inliers only LS"] = calibrate_paper(arm, q, T_bad, oracle, throw=False)
        robust = {
            f"contaminated {loss.capitalize()}": calibrate_robust(
                arm, q, T_bad, nm, loss=loss, throw=False
            )
            for loss in ("huber", "cauchy")
        }
        robust |= {
            f"contam. {loss.capitalize()}+reject": calibrate_robust(
                arm, q, T_bad, nm, loss=loss, reject_outliers=True, throw=False
            )
            for loss in ("huber", "cauchy")
        }
        robust["clean Huber"] = calibrate_robust(arm, q, T, nm, loss="huber", throw=False)
        clean_mask = jnp.zeros_like(mask)
        out = {}
        for name, sol in [*fits.items(), *((n, r.solution) for n, r in robust.items())]:
            model = tool_pose(arm.with_frames(sol.frames), qv)
            dp_meas, dR_meas = deviation_metrics(Tv, model)
            dp_true, dR_true = deviation_metrics(truth, model)
            out[name] = {
                "dp_meas": dp_meas,
                "dR_meas": dR_meas,
                "dp_true": dp_true,
                "dR_true": dR_true,
                "ok": sol.converged,
            }
        for name, r in robust.items():
            bad = clean_mask if name.startswith("clean") else mask
            out[name]["rounds"] = r.rounds
            out[name]["hit"] = jnp.sum(r.outliers & bad) / max(n_out, 1)
            out[name]["false"] = jnp.sum(r.outliers & ~bad)
        return out

    keys = jax.random.split(jax.random.PRNGKey(args.seed), args.trials)
    print(
        f"{args.trials} trials, {args.poses} calibration poses ({n_out} corrupted by "
        f"{args.outlier_pos:g} mm / {args.outlier_rot:g} rad), {args.verify} held-out poses, "
        f"noise {args.noise_pos:g} mm / {args.noise_rot:g} rad (std); medians over trials"
    )
    for stated in (True, False):
        t0 = time.perf_counter()
        res = jax.tree_util.tree_map(
            np.asarray,
            eqx.filter_jit(jax.vmap(lambda k: trial(k, stated)))(keys),  # noqa: B023
        )
        wall = time.perf_counter() - t0
        title = (
            "with the stated noise model (weighted LS; robust scale = the noise)"
            if stated
            else "paper form, no noise model (unweighted LS; robust scale = MAD)"
        )
        print(f"\n{title}  [{wall:.1f} s incl. compile]")
        head = (
            f"  {'fit':<22}{'held-out dp':>12}{'x clean':>9}{'dR [rad]':>11}"
            f"{'true dp':>12}{'x clean':>9}{'outliers found':>16}{'false flags':>13}"
            f"{'rounds':>8}{'converged':>11}{'per trial: p90 x':>18}{'<= 1.5x':>9}"
            f"{'true <= 1.5x':>14}"
        )
        print(head)
        ref_meas = np.median(res["clean LS"]["dp_meas"])
        ref_true = np.median(res["clean LS"]["dp_true"])
        for name in ROWS:
            if name not in res:
                continue
            r = res[name]
            dpm, dpt = np.median(r["dp_meas"]), np.median(r["dp_true"])
            found = (
                "-"
                if "hit" not in r or name.startswith("clean")
                else f"{100 * np.mean(r['hit']):.0f} %"
            )
            false = f"{np.mean(r['false']):.2f}" if "false" in r else "-"
            rounds = f"{np.median(r['rounds']):.0f}" if "rounds" in r else "-"
            # per trial: this fit's held-out dp over the clean LS fit's on the same draw
            ratio = r["dp_meas"] / res["clean LS"]["dp_meas"]
            ratio_true = r["dp_true"] / res["clean LS"]["dp_true"]
            print(
                f"  {name:<22}{dpm:>9.4f} mm{dpm / ref_meas:>8.2f}x{np.median(r['dR_meas']):>11.2e}"
                f"{dpt:>9.4f} mm{dpt / ref_true:>8.2f}x{found:>16}{false:>13}{rounds:>8}"
                f"{100 * np.mean(r['ok']):>10.0f}%{np.quantile(ratio, 0.9):>17.2f}x"
                f"{100 * np.mean(ratio <= 1.5):>8.0f}%{100 * np.mean(ratio_true <= 1.5):>13.0f}%"
            )


if __name__ == "__main__":
    main()
