"""Calibration from markers: held-out accuracy of the default estimator against its bound.

Setup, per trial: the UR5 imported from ``tests/data/urdf/ur5_robot.urdf`` (``base_link`` to
``tool0``: 6 revolute modules, 7 fixed frames) with three markers on the tool, at (0, 60, 30),
(50, -40, 30) and (-50, -40, 30) mm in the tool frame, all ``calibrate = true``.
:func:`cdra_jax.workflows.simulate` draws the truth and the fit data: random frame errors
(uniform +-1 mm / +-0.05 rad per component), the true markers up to ``--marker-error`` mm off
their model position per component, ``--poses`` random joint states, the robot's base
``--device-frame`` away from the measuring device (default 403 mm and 90 deg about z), the
three markers measured with isotropic Gaussian noise ``sigma`` per coordinate, each point
hidden with probability ``--occlusion``. The seed changes every trial, so the truth, the poses
and the noise all change. The fit is the default estimator,
:func:`cdra_jax.calibration.calibrate_auto` as ``cdra-jax calibrate`` calls it (noise scales
estimated from the data, Huber loss, units beyond the outlier bound left out, base registered by
Kabsch, markers identified with the frames). The test set is ``--test-poses`` other random
states, all three markers seen.

The bound: the parameters are those of the estimator (error twists of the 7 frames and the
three marker corrections, 51, of which 33 are identifiable: 2 per joint axis and the 6 of the
tool frame against the markers are not). ``J`` is the unwhitened Jacobian of the seen fit points
at the truth, ``J_t`` that of the test points. For unit-variance noise the Fisher information is
``J^T J / sigma^2``; the unidentifiable directions do not move a prediction (checked: the
largest test-point change along them is reported), so the bound on the covariance of the
predicted test points of any unbiased estimator is ``J_t C J_t^T`` with
``C = sigma^2 (J^T J)^+``. Per coordinate, the bound on the mean squared prediction error is
``b = trace(J_t C J_t^T) / (3 n_test)``.

Reported per noise level, over the trials (first table):

* ``prediction RMS``: the RMS (per coordinate) of the predicted test points against the true
  ones; ``bound``: ``sqrt(mean b)``;
* ``efficiency``: ``mean b / mean(squared prediction error)`` (1: the bound), with a bootstrap
  95 % interval over the trials;
* ``first-order efficient, same noise``: the RMS of ``J_t J^+ eps``, the prediction error of the
  efficient estimator linearised at the truth, from the same noise ``eps`` as the fit (its mean
  square estimates ``b``); ``efficiency vs it``: its mean square over the estimator's, paired
  trial by trial, so the noise of the draws largely cancels (a much narrower interval; 1: the
  estimator does as well as the efficient one on the same data);
* ``held-out RMS``: the RMS per coordinate against the test points measured with fresh noise of
  the same ``sigma`` (what ``cdra-jax validate`` measures), and its bound
  ``sqrt(sigma^2 + mean b)``;

and about the estimator (second table):

* the estimated noise scale (mean of the three markers' scales) over the true one, median and
  5-95 % range;
* median accepted Levenberg-Marquardt steps and reweighting rounds, the fraction converged,
  the fraction of trials with any unit flagged as an outlier (clean data: about 1 %, the flags'
  family-wise false-alarm rate), the mean share of units the Huber loss down-weights, and the
  median wall time of one calibration (after compilation).

``--loss ls`` (plain least squares) and ``--given-noise`` (the true ``sigma`` given, no scale
estimated) run the same trials with those parts of the estimator switched off.

Usage::

    python benchmarks/markers.py                          # 50 trials per noise level
    python benchmarks/markers.py --trials 100 --json      # the measured tables
    python benchmarks/markers.py --trials 100 --loss ls --given-noise
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from cdra_jax.arm import Marker, sample_states  # noqa: E402
from cdra_jax.calibration import NoiseModel, calibrate_auto, default_rcond  # noqa: E402
from cdra_jax.calibration.observations import (  # noqa: E402
    linearise,
    make_observations,
    predictions,
)
from cdra_jax.workflows import import_urdf, simulate  # noqa: E402

URDF = ROOT / "tests" / "data" / "urdf" / "ur5_robot.urdf"
MARKERS = (
    ("m1", (0.0, 60.0, 30.0)),
    ("m2", (50.0, -40.0, 30.0)),
    ("m3", (-50.0, -40.0, 30.0)),
)
DEVICE_FRAME = (300.0, -250.0, 100.0, 0.0, 0.0, 1.5708)
ROTATION_NOISE_RAD = 1e-3
"""Required by ``NoiseModel``; unused (points carry no orientation)."""


def ur5_with_markers():
    """The UR5 model (base_link -> tool0) with the three calibrated markers."""
    arm = import_urdf(URDF, "base_link", "tool0").arm
    return arm.with_markers([Marker(n, xyz, calibrate=True) for n, xyz in MARKERS])


def point_jacobian(frames, xyz, obs, calibrated):
    """Unwhitened Jacobian ``(3 m P, n)`` of the seen points (zero rows where not seen) with
    respect to the estimator's parameters at ``frames``, ``xyz``."""
    m, n_pts = obs.m, obs.n_points
    n = 6 * frames.shape[0] + 3 * len(calibrated)
    inf = np.full(m, np.inf)
    s_pt = np.where(np.asarray(obs.seen), 1.0, np.inf)
    _, J = linearise(np.zeros(n), frames, xyz, obs, inf, inf, s_pt, calibrated)
    return np.asarray(J)[6 * m :].reshape(m * n_pts * 3, n)


def trial(arm, sigma, seed, args):
    """One simulated calibration; returns its numbers (mean squared errors per coordinate)."""
    run = simulate(
        arm,
        args.poses,
        seed=seed,
        noise=NoiseModel(sigma, ROTATION_NOISE_RAD),
        points=True,
        occlusion=args.occlusion,
        marker_error_mm=args.marker_error,
        device_frame=list(args.device_frame),
    )
    meas = run.measurements
    names = tuple(meas.point_names)
    t0 = time.perf_counter()
    given = NoiseModel(sigma, ROTATION_NOISE_RAD) if args.given_noise else None
    sol = calibrate_auto(
        arm, meas.q, meas.full_poses, meas.points, names, noise=given, loss=args.loss
    )
    wall = time.perf_counter() - t0

    # The truth in the device frame: the device pose folded into the base frame.
    device = np.asarray(run.truth["device_frame"])
    frames_true = np.array(run.actual_frames)
    frames_true[0] = device @ frames_true[0]
    xyz_true = np.array([run.truth["markers"][n] for n in names])
    calibrated = tuple(range(len(names)))

    # Test states and their true, noise-free points (every marker seen).
    key = jax.random.fold_in(jax.random.PRNGKey(seed), 1_000_003)
    q_test = np.asarray(sample_states(key, arm, args.test_poses))
    no_points = np.zeros((args.test_poses, len(names), 3))
    obs_test = make_observations(arm, q_test, None, no_points)
    _, true_pts = predictions(frames_true, xyz_true, obs_test)
    true_pts = np.asarray(true_pts)
    obs_test = make_observations(arm, q_test, None, true_pts)
    _, pred = predictions(sol.frames, sol.xyz, obs_test)
    pred = np.asarray(pred)
    n_coord = true_pts.size
    mse_pred = float(np.sum((pred - true_pts) ** 2) / n_coord)
    rng = np.random.default_rng([seed, 23])
    measured = true_pts + sigma * rng.standard_normal(true_pts.shape)
    mse_held = float(np.sum((pred - measured) ** 2) / n_coord)

    # Cramer-Rao bound on the predicted test points (module docstring).
    obs_fit = make_observations(arm, meas.q, None, meas.points)
    J = point_jacobian(frames_true, xyz_true, obs_fit, calibrated)
    Jt = point_jacobian(frames_true, xyz_true, obs_test, calibrated)
    _, s, Vt = np.linalg.svd(J, full_matrices=True)
    rank = int(np.sum(s > default_rcond(J.dtype) * s[0]))
    A = Jt @ (Vt[:rank].T / s[:rank])
    bound = sigma**2 * float(np.sum(A * A)) / n_coord
    # The first-order efficient estimate from the same noise: e = J_t J^+ eps.
    _, fit_true = predictions(frames_true, xyz_true, obs_fit)
    eps = np.where(np.isfinite(meas.points), meas.points - np.asarray(fit_true), 0.0)
    e_lin = A @ ((Vt[:rank] @ (J.T @ eps.reshape(-1))) / s[:rank])
    mse_lin = float(np.sum(e_lin**2) / n_coord)
    null_leak = float(np.max(np.abs(Jt @ Vt[rank:].T), initial=0.0))

    seen = np.isfinite(sol.z_points)
    flagged = bool(np.any(sol.z_points[seen] > sol.outlier_threshold))
    down = float(np.mean(sol.weights_points[seen] < 1.0))
    return {
        "mse_pred": mse_pred,
        "mse_held": mse_held,
        "mse_lin": mse_lin,
        "bound": bound,
        "rank": rank,
        "estimator_rank": int(sol.rank),
        "null_leak": null_leak,
        "sigma_ratio": float(np.nanmean(sol.sigma_points_mm) / sigma),
        "iterations": int(sol.iterations),
        "rounds": int(sol.rounds),
        "converged": bool(sol.converged),
        "flagged": flagged,
        "downweighted": down,
        "wall_s": wall,
    }


def summarise(sigma, rows, n_boot=2000, seed=0):
    """The per-noise-level summary of a list of :func:`trial` results."""

    def col(k):
        return np.array([r[k] for r in rows], dtype=float)

    mse, bnd, held, lin = col("mse_pred"), col("bound"), col("mse_held"), col("mse_lin")
    idx = np.random.default_rng(seed).integers(0, len(rows), (n_boot, len(rows)))
    boot = bnd[idx].mean(1) / mse[idx].mean(1)
    boot_lin = lin[idx].mean(1) / mse[idx].mean(1)

    def ci(b):
        return [float(np.quantile(b, 0.025)), float(np.quantile(b, 0.975))]

    ratio = col("sigma_ratio")
    return {
        "sigma_mm": sigma,
        "trials": len(rows),
        "rms_pred_mm": float(np.sqrt(mse.mean())),
        "rms_bound_mm": float(np.sqrt(bnd.mean())),
        "efficiency": float(bnd.mean() / mse.mean()),
        "efficiency_ci95": ci(boot),
        "rms_first_order_mm": float(np.sqrt(lin.mean())),
        "efficiency_paired": float(lin.mean() / mse.mean()),
        "efficiency_paired_ci95": ci(boot_lin),
        "held_out_rms_mm": float(np.sqrt(held.mean())),
        "held_out_bound_mm": float(np.sqrt(sigma**2 + bnd.mean())),
        "sigma_ratio_median": float(np.median(ratio)),
        "sigma_ratio_p5_p95": [float(np.quantile(ratio, 0.05)), float(np.quantile(ratio, 0.95))],
        "iterations_median": float(np.median(col("iterations"))),
        "rounds_median": float(np.median(col("rounds"))),
        "converged": float(col("converged").mean()),
        "flagged": float(col("flagged").mean()),
        "downweighted": float(col("downweighted").mean()),
        "rank": sorted({int(r["rank"]) for r in rows}),
        "estimator_rank": sorted({int(r["estimator_rank"]) for r in rows}),
        "null_leak_max_mm": float(col("null_leak").max()),
        "calibration_s_median": float(np.median(col("wall_s"))),
    }


def print_table(head, rows) -> None:
    """A Markdown table."""
    print("| " + " | ".join(head) + " |")
    print("|" + " --- |" * len(head))
    for r in rows:
        print("| " + " | ".join(r) + " |")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="\n\n".join(__doc__.split("\n\n")[1:]),
    )
    ap.add_argument("--trials", type=int, default=50, help="trials per noise level (50)")
    ap.add_argument(
        "--noise",
        type=float,
        nargs="+",
        default=[0.01, 0.05, 0.2],
        help="marker noise std per coordinate, mm (0.01 0.05 0.2)",
    )
    ap.add_argument("--poses", type=int, default=36, help="fit poses per trial (36)")
    ap.add_argument("--test-poses", type=int, default=40, help="held-out poses per trial (40)")
    ap.add_argument("--occlusion", type=float, default=0.2, help="point occlusion rate (0.2)")
    ap.add_argument(
        "--marker-error", type=float, default=20.0, help="true markers off by up to (mm, 20)"
    )
    ap.add_argument(
        "--device-frame",
        type=float,
        nargs=6,
        default=list(DEVICE_FRAME),
        metavar=("X", "Y", "Z", "RX", "RY", "RZ"),
        help="robot base in the device frame, mm and rad (300 -250 100 0 0 1.5708)",
    )
    ap.add_argument(
        "--loss",
        choices=("huber", "ls"),
        default="huber",
        help="the estimator's loss: huber (the default estimator) or ls (plain least squares)",
    )
    ap.add_argument(
        "--given-noise",
        action="store_true",
        help="give the estimator the true sigma instead of estimating the scales from the data",
    )
    ap.add_argument("--seed", type=int, default=0, help="first seed (0)")
    ap.add_argument("--json", action="store_true", help="JSON summary on the last line")
    args = ap.parse_args(argv)

    arm = ur5_with_markers()
    t_start = time.perf_counter()
    levels = []
    for i, sigma in enumerate(args.noise):
        rows = [trial(arm, sigma, args.seed + 100_000 * i + k, args) for k in range(args.trials)]
        levels.append(summarise(sigma, rows))
        print(
            f"sigma {sigma:g} mm: {args.trials} trials, {time.perf_counter() - t_start:.0f} s",
            file=sys.stderr,
        )
    total = time.perf_counter() - t_start

    print(
        f"UR5, 3 calibrated markers, {args.poses} fit poses ({args.occlusion:g} occlusion), "
        f"{args.test_poses} test poses, {args.trials} trials per noise level, loss "
        f"{args.loss}, noise {'given' if args.given_noise else 'estimated'}; RMS per "
        "coordinate, mm"
    )
    print_table(
        (
            "sigma (mm)",
            "prediction RMS",
            "bound",
            "efficiency [95 %]",
            "first-order efficient, same noise",
            "efficiency vs it [95 %]",
            "held-out RMS",
            "held-out bound",
        ),
        [
            (
                f"{s['sigma_mm']:g}",
                f"{s['rms_pred_mm']:.4g}",
                f"{s['rms_bound_mm']:.4g}",
                "{:.3f} [{:.3f}, {:.3f}]".format(s["efficiency"], *s["efficiency_ci95"]),
                f"{s['rms_first_order_mm']:.4g}",
                "{:.3f} [{:.3f}, {:.3f}]".format(
                    s["efficiency_paired"], *s["efficiency_paired_ci95"]
                ),
                f"{s['held_out_rms_mm']:.4g}",
                f"{s['held_out_bound_mm']:.4g}",
            )
            for s in levels
        ],
    )
    print()
    print_table(
        (
            "sigma (mm)",
            "estimated / true sigma, median [5-95 %]",
            "LM steps (rounds), median",
            "converged",
            "trials with a flag",
            "units down-weighted",
            "calibration s, median",
        ),
        [
            (
                f"{s['sigma_mm']:g}",
                "{:.3f} [{:.3f}, {:.3f}]".format(s["sigma_ratio_median"], *s["sigma_ratio_p5_p95"]),
                f"{s['iterations_median']:g} ({s['rounds_median']:g})",
                f"{s['converged']:.2f}",
                f"{s['flagged']:.3f}",
                f"{100 * s['downweighted']:.1f} %",
                f"{s['calibration_s_median']:.2f}",
            )
            for s in levels
        ],
    )
    ranks = sorted({r for s in levels for r in s["rank"]})
    est_ranks = sorted({r for s in levels for r in s["estimator_rank"]})
    leak = max(s["null_leak_max_mm"] for s in levels)
    print(
        f"identifiable parameters at the truth: {ranks} (estimator: {est_ranks}); largest "
        f"test-point change along an unidentifiable direction: {leak:.1e} mm per unit; "
        f"total {total:.0f} s"
    )
    out = {
        "model": "ur5 base_link->tool0, 3 calibrated markers",
        "poses": args.poses,
        "test_poses": args.test_poses,
        "occlusion": args.occlusion,
        "marker_error_mm": args.marker_error,
        "device_frame": list(args.device_frame),
        "trials": args.trials,
        "loss": args.loss,
        "given_noise": args.given_noise,
        "seed": args.seed,
        "levels": levels,
        "total_s": total,
    }
    if args.json:
        print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
