"""CDPM modules of the default CDRA: workspace coverage, cable FK, statics, self-calibration.

Prints the numbers quoted in ``benchmarks/README.md`` and the model file's comments::

    PYTHONPATH=. python benchmarks/cdpm_study.py [--draws 100000] [--trials 20] [--poses 80]

1. Tension-closure coverage of the joint box (uniform draws): fraction with closure, with
   ``closure_margin > 0.05`` (the sampler's default), median margin; for the whole arm too.
2. Cable forward kinematics from the default starts over uniform states: worst round-trip
   error; with 0.02 mm length noise, mean squared residual over its expectation
   ``s^2 (n - dof) / n``.
3. Statics over feasible poses: holding tensions without and with a 0.5 kg payload.
4. Module self-calibration, per module, over ``--trials`` random preset errors (+-s mm on every
   attachment coordinate, +-2s mm length offsets, s = 1 and 0.5) at ``--poses`` feasible poses:
   how many noise-free fits recover the truth (gauge-aligned parameters for spherical modules,
   the gauge invariants for the elbow; a fit caught in another basin is visible by its residual),
   their worst error, and with 0.02 mm length noise the Mahalanobis distance of the error in
   the identifiable subspace against its chi^2(rank) distribution and the largest error in
   predicted standard deviations.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import chi2

jax.config.update("jax_enable_x64", True)

from cdra_jax import lie  # noqa: E402
from cdra_jax.io import default_arm  # noqa: E402
from cdra_jax.modules import (  # noqa: E402
    analyze_self_calibration,
    arm_closure_margins,
    cable_forward_kinematics,
    cable_lengths,
    closure_margin,
    gauge_invariants,
    holding_tensions,
    module_parameters,
    result_names,
    sample_feasible_states,
    self_calibrate,
    with_parameters,
)
from cdra_jax.modules.self_calibration import _fix_gauge, _to_var  # noqa: E402
from cdra_jax.simulation import sample_states  # noqa: E402

SIGMA = 0.02


def coverage(arm, draws):
    q = sample_states(jax.random.PRNGKey(0), arm, draws)
    m = np.asarray(jax.jit(arm_closure_margins)(arm, q))
    print(f"1. tension-closure coverage of the joint box ({draws} uniform draws)")
    for k, mod in enumerate(arm.modules):
        print(
            f"   {mod.name:9s} {mod.n_cables} cables: closure {100 * np.mean(m[:, k] > 0):6.2f} %"
            f"  margin > 0.05 {100 * np.mean(m[:, k] > 0.05):6.2f} %"
            f"  median margin {np.median(m[:, k]):.3f}"
        )
    print(
        f"   whole arm: closure {100 * np.mean(np.all(m > 0, -1)):.2f} %, margin > 0.05 "
        f"{100 * np.mean(np.all(m > 0.05, -1)):.2f} %"
    )
    el = arm.module("elbow")
    t = jnp.linspace(*el.limits[0], 2001)[:, None]
    print(f"   elbow over 0..2 rad: smallest margin {float(jnp.min(closure_margin(el, t))):.3f}")


def forward_kinematics(arm, draws):
    print(f"2. cable forward kinematics from the default starts ({draws} uniform states each)")
    fk = jax.jit(cable_forward_kinematics)
    for k, mod in enumerate(arm.modules):
        lim = np.asarray(mod.limits)
        u = jax.random.uniform(jax.random.PRNGKey(k), (draws, mod.dof))
        q = lim[:, 0] + u * (lim[:, 1] - lim[:, 0])
        L = cable_lengths(mod, q)
        sol = jax.block_until_ready(fk(mod, L))  # compile
        t0 = time.perf_counter()
        sol = jax.block_until_ready(fk(mod, L))
        dt = time.perf_counter() - t0
        if mod.kind == "spherical":
            err = lie.rotation_angle(lie.so3_exp(sol.state) @ jnp.swapaxes(lie.so3_exp(q), -1, -2))
        else:
            err = jnp.abs(sol.state - q)[:, 0]
        ok = np.mean(result_names(sol.result) == "successful")
        noisy = L + SIGMA * jax.random.normal(jax.random.PRNGKey(9), L.shape)
        sn = fk(mod, noisy)
        n, d = mod.n_cables, mod.dof
        ratio = float(jnp.mean(sn.residual_rms**2)) / (SIGMA**2 * (n - d) / n)
        worst_l = float(jnp.max(jnp.abs(cable_lengths(mod, sol.state) - L)))
        worst_q = float(err.max())
        print(
            f"   {mod.name:9s} successful {100 * ok:.2f} %, worst state error {worst_q:.1e}"
            f", worst length error {worst_l:.1e} mm, max iterations {int(sol.iterations.max())},"
            f" {1e6 * dt / draws:.1f} us/pose; noisy: mean rms^2 / expected {ratio:.3f}"
        )


def statics(arm, m):
    print(f"3. holding tensions over {m} feasible poses (floor = pretension 10 N)")
    q = sample_feasible_states(jax.random.PRNGKey(5), arm, m)
    f = jax.jit(holding_tensions)
    for payload in (0.0, 0.5):
        sol = f(arm, q, payload)
        parts = []
        for name, s in sol.items():
            ok = np.mean(result_names(s.result) == "successful")
            t = np.asarray(s.tensions)
            parts.append(
                f"{name} median max {np.median(t.max(-1)):.0f} N, worst {t.max():.0f} N"
                f" ({100 * ok:.0f} % solved)"
            )
        print(f"   payload {payload} kg: " + "; ".join(parts))


def self_calibration(arm, trials, poses, scales=(1.0, 0.5)):
    print(
        f"4. module self-calibration: {trials} trials per row, {poses} feasible poses, preset "
        "errors +-s mm on every attachment coordinate and +-2s mm on the length offsets, "
        f"length noise {SIGMA} mm for the noisy fits"
    )
    sampler = jax.jit(sample_feasible_states, static_argnums=2)
    for k, nominal in enumerate(arm.modules):
        n = nominal.n_cables
        theta0 = module_parameters(nominal)

        @jax.jit
        def trial(key, scale, nominal=nominal, k=k, n=n, theta0=theta0):
            k1, k2, k3 = jax.random.split(key, 3)
            states = arm.split_state(sampler(k1, arm, poses))[k]
            err = jax.random.uniform(k2, (n, 7), minval=-1, maxval=1)
            err = scale * err * jnp.asarray([1.0] * 6 + [2.0])
            truth = with_parameters(nominal, theta0 + err.reshape(-1))
            lengths = cable_lengths(truth, states)
            clean = self_calibrate(nominal, lengths, throw=False)
            noisy = self_calibrate(
                nominal, lengths + SIGMA * jax.random.normal(k3, lengths.shape), throw=False
            )
            canon, _ = _fix_gauge(
                nominal, theta0, module_parameters(truth), _to_var(nominal, states)
            )
            return states, truth, canon, clean, noisy

        for scale in scales:
            keys = jax.random.split(jax.random.PRNGKey(100 + k), trials)
            jax.block_until_ready(trial(keys[0], scale))  # compile
            t0 = time.perf_counter()
            out = [trial(key, scale) for key in keys]
            dt = (time.perf_counter() - t0) / trials
            _report(nominal, scale, out, dt)


def _report(nominal, scale, out, dt):
    n = nominal.n_cables
    good, worst, its, its_n, stats, zmax, inv_n, rms_n, bad_rms = 0, 0.0, [], [], [], [], [], [], []
    for states, truth, canon, clean, noisy in out:
        if nominal.kind == "spherical":
            e = float(jnp.max(jnp.abs(clean.parameters - canon)))
        else:
            gt, ge = gauge_invariants(truth), gauge_invariants(clean.module)
            e = max(float(jnp.max(jnp.abs(gt[key] - ge[key]))) for key in gt)
        if not (e < 1e-7 and result_names(clean.result) == "successful"):
            bad_rms.append(float(clean.residual_rms))
            continue
        good += 1
        worst = max(worst, e)
        its.append(int(clean.iterations))
        its_n.append(int(noisy.iterations))
        rms_n.append(float(noisy.residual_rms))
        rep = analyze_self_calibration(truth, states)
        if nominal.kind == "spherical":
            cov = rep.covariance(SIGMA)
            err = np.asarray(noisy.parameters - canon)
            stats.append(err @ np.linalg.pinv(cov, rcond=1e-12, hermitian=True) @ err)
            zmax.append(np.max(np.abs(err) / np.sqrt(np.maximum(np.diag(cov), 1e-300))))
        else:
            gn = gauge_invariants(noisy.module)
            inv_n.append({key: float(jnp.max(jnp.abs(gt[key] - gn[key]))) for key in gt})
    m_rows = out[0][0].shape[0]
    line = f"   {nominal.name:9s} s = {scale}: recovered {good}/{len(out)}"
    if bad_rms:
        line += f" (the others stop at residual rms {min(bad_rms):.3g}-{max(bad_rms):.3g} mm)"
    if good:
        rank = rep.rank
        expect = SIGMA * np.sqrt((m_rows * (n - nominal.dof) - rank) / (m_rows * n))
        line += (
            f", rank {rank}/{7 * n}, condition {rep.condition_number:.3g}, worst error "
            f"{worst:.1e}, iterations {min(its)}-{max(its)}, {dt:.2f} s/trial\n"
            f"             noisy: iterations {min(its_n)}-{max(its_n)}, residual rms "
            f"{np.mean(rms_n):.4f} mm (expected {expect:.4f})"
        )
        if inv_n:
            line += ", worst invariant errors " + ", ".join(
                f"{key} {max(d[key] for d in inv_n):.2g}" for key in inv_n[0]
            )
        if stats:
            st = np.asarray(stats)
            lo, hi = chi2.ppf([0.05, 0.95], rank)
            line += (
                f"\n             Mahalanobis mean {st.mean():.1f} (chi2({rank}): mean {rank},"
                f" 90 % range {lo:.1f}-{hi:.1f}), largest |error|/std {max(zmax):.2f}"
            )
    print(line)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--draws", type=int, default=100000)
    p.add_argument("--trials", type=int, default=20)
    p.add_argument("--poses", type=int, default=80)
    args = p.parse_args(argv)
    arm = default_arm()
    coverage(arm, args.draws)
    forward_kinematics(arm, args.draws)
    statics(arm, 2000)
    self_calibration(arm, args.trials, args.poses)


if __name__ == "__main__":
    main()
