"""The concealed-effect generator (benchmarks/concealed_generator.py) and its scoring harness.

Oracles: the package's own forward kinematics for the zero-size limit, an independent world-frame
moment sum and SciPy's SLSQP for the statics, a NumPy re-evaluation of the whitened residual for
the effect size, and the CSV reader for the files.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCH))

import concealed_generator as gen  # noqa: E402
import concealed_physics as harness  # noqa: E402

M = 12  # one pose count for every test: the geometric fit compiles once


@pytest.fixture(scope="module")
def arm(cdra):
    from cdra_jax.io import default_model_text

    return gen.arm_data(cdra, default_model_text())


@pytest.fixture(scope="module")
def scn(arm):
    return gen.draw_scenario(arm, M, gen.spawn(3, 1), noise_pos_mm=0.08, noise_rot_rad=1e-3)


def _effects(arm):
    return [
        gen.draw_effect(arm, e, gen.spawn(3, 2, i), loc)
        for i, (e, loc) in enumerate(gen.effect_table(arm))
    ]


def test_every_effect_at_zero_size_is_the_geometric_model(arm, scn):
    from cdra_jax import apply_frame_errors, tool_pose

    ref = np.asarray(tool_pose(apply_frame_errors(arm.arm, scn.errors.reshape(-1)), scn.q))
    effects = _effects(arm)
    assert {e.name for e in effects} == set(gen.ALL_EFFECTS)
    for eff in effects:
        T = gen.true_poses(scn, eff, 0.0)
        assert np.abs(T - ref).max() < 1e-9, (eff.name, eff.location)
        # ... and a non-zero size changes the poses
        assert np.abs(gen.true_poses(scn, eff, eff.guess) - ref).max() > 1e-6, eff.name


def _se3_log_np(T):
    w = Rotation.from_matrix(T[:, :3, :3]).as_rotvec()
    out = np.empty((len(T), 6))
    for k, (wk, p) in enumerate(zip(w, T[:, :3, 3], strict=True)):
        th = np.linalg.norm(wk)
        W = np.array([[0, -wk[2], wk[1]], [wk[2], 0, -wk[0]], [-wk[1], wk[0], 0]])
        V = np.eye(3) + (1 - np.cos(th)) / th**2 * W + (th - np.sin(th)) / th**3 * W @ W
        out[k] = np.concatenate([np.linalg.solve(V, p), wk])
    return out


def _whitened_rms(arm, scn, frames, T_meas):
    """Independent NumPy re-evaluation of the whitened geometric residual (Eq. 7)."""
    Mods = scn.commanded_module_poses()
    F = np.broadcast_to(frames, (scn.m,) + frames.shape)
    T_model = gen.chain_poses(F, Mods)[0]
    Y = _se3_log_np(T_meas @ np.linalg.inv(T_model))
    p = T_meas[:, :3, 3]
    dth = Y[:, 3:]
    dp = Y[:, :3] - np.cross(p, dth)
    r = np.concatenate([dp / scn.noise_pos_mm, dth / scn.noise_rot_rad], axis=1)
    return float(np.sqrt(np.mean(r**2)))


@pytest.mark.parametrize("size", [2.0])
def test_size_calibration_hits_the_requested_unabsorbed_rms(arm, scn, size):
    rng = np.random.default_rng(0)
    for eff in _effects(arm)[::2]:
        scale, achieved = gen.calibrate_size(scn, eff, size)
        assert abs(achieved / size - 1) <= 0.05, (eff.name, achieved)
        T = gen.true_poses(scn, eff, scale)
        rms, frames = gen.geometric_fit(scn, T)
        assert rms == pytest.approx(achieved, rel=1e-9)
        # The RMS is what NumPy computes from the fitted frames ...
        assert _whitened_rms(arm, scn, frames, T) == pytest.approx(rms, rel=1e-6)
        # ... and the fit is a minimum: perturbed frames leave more.
        for _ in range(3):
            xi = rng.normal(size=(4, 6)) * np.array([1e-3] * 3 + [1e-6] * 3)
            worse = _whitened_rms(arm, scn, gen._se3_exp(xi) @ frames, T)
            assert worse >= rms * (1 - 1e-9)


def test_columns_are_the_same_for_every_effect(arm, scn, tmp_path):
    from cdra_jax.io import load_measurements

    headers = set()
    for i, eff in enumerate([gen.NO_EFFECT, *_effects(arm)]):
        rec = gen.make_recording(scn, eff, scale=0.0 if eff.name == "none" else eff.guess)
        model, data = gen.write_recording(rec, tmp_path / f"r{i}")
        assert model.read_text() == arm.model_text  # the nominal model, unchanged
        text = data.read_text()
        assert not text.startswith("#")  # no comment that could name the effect
        headers.add(text.splitlines()[0])
        back = load_measurements(data, arm.arm)
        np.testing.assert_allclose(back.measured, rec.measured, atol=1e-9)
        np.testing.assert_array_equal(back.q, scn.q)
    assert len(headers) == 1
    assert tuple(headers.pop().split(",")) == gen.measurement_columns(arm)


def test_approach_is_the_sign_of_the_last_motion_and_backlash_follows_it(arm, scn):
    lim = arm.limits
    prev = np.vstack([np.clip(0.0, lim[:, 0], lim[:, 1]), scn.q[:-1]])
    for i, (md, sl) in enumerate(zip(arm.modules, arm.slices, strict=True)):
        motion = (scn.q[:, sl] - prev[:, sl]) @ scn.approach_dirs[i]
        np.testing.assert_array_equal(scn.approach[md.name], np.where(motion >= 0, 1.0, -1.0))
    eff = gen.draw_effect(arm, "backlash", gen.spawn(0), "elbow")
    b = 1e-3
    F, Mods = gen._apply_backlash(scn, eff, b, None, scn.commanded_module_poses())
    i = arm.module_index("elbow")
    q_act = Rotation.from_matrix(Mods[:, i, :3, :3]).as_rotvec() @ arm.modules[i].axis
    lag = q_act - scn.q[:, arm.slices[i]][:, 0]
    moved = np.abs(np.diff(np.concatenate([[0.0], scn.q[:, arm.slices[i]][:, 0]]))) > b
    np.testing.assert_allclose(lag[moved], -0.5 * b * scn.approach["elbow"][moved], atol=1e-12)


def test_tension_distribution_is_in_equilibrium_and_optimal(arm):
    rng = np.random.default_rng(1)
    q = arm.limits[:, 0] + rng.random((6, arm.dof)) * np.ptp(arm.limits, axis=1)
    payload = np.full(6, 0.2)
    F = np.broadcast_to(arm.frames, (6,) + arm.frames.shape)
    Mods = np.stack(
        [gen.module_pose(md, q[:, s]) for md, s in zip(arm.modules, arm.slices, strict=True)], 1
    )
    tau = gen.gravity_moments(arm, F, Mods, payload)
    tool, before, after = gen.chain_poses(F, Mods)
    checked = compared = 0
    for i, md in enumerate(arm.modules):
        t, ok = gen.module_tensions(md, Mods[:, i, :3, :3], tau[:, i])
        for k in np.flatnonzero(ok):
            checked += 1
            assert np.all(t[k] >= md.pretension - 1e-12)
            # world-frame moment about the centre: cables + gravity of everything carried
            o = after[k, i, :3, 3]
            pb = before[k, i, :3, :3] @ md.cable_base.T + before[k, i, :3, 3:4]
            pp = after[k, i, :3, :3] @ md.cable_platform.T + after[k, i, :3, 3:4]
            u = (pb - pp) / np.linalg.norm(pb - pp, axis=0)
            mom = np.cross((pp - o[:, None]).T, (t[k] * u).T).sum(0)
            for j in range(i, arm.n_modules + 1):
                if j < arm.n_modules:
                    c = after[k, j, :3, :3] @ arm.modules[j].com + after[k, j, :3, 3]
                    mass = arm.modules[j].mass
                else:
                    c, mass = tool[k, :3, 3], payload[k]
                mom += np.cross(c - o, mass * arm.gravity)
            if md.kind == "revolute":
                mom = mom @ (before[k, i, :3, :3] @ md.axis)
            assert np.max(np.abs(mom)) < 1e-7 * (1 + np.abs(tau[k, i]).max())
            # optimal: SLSQP (scaled to O(1) variables) finds no feasible smaller 2-norm
            A = gen.cable_moment_matrix(md, Mods[k : k + 1, i, :3, :3])[0]
            rhs = -(tau[k, i] @ md.axis if md.kind == "revolute" else tau[k, i])
            t0, r0 = md.pretension, max(1.0, np.abs(rhs).max())
            res = minimize(
                lambda x: x @ x,
                np.full(md.n_cables, 2.0),
                jac=lambda x: 2 * x,
                bounds=[(1.0, None)] * md.n_cables,
                constraints=[
                    {"type": "eq", "fun": lambda x, A=A, r=rhs, c=t0, d=r0: (c * A @ x - r) / d}
                ],
                method="SLSQP",
                options={"ftol": 1e-15, "maxiter": 1000},
            )
            x = res.x * t0
            if np.abs(A @ x - rhs).max() < 1e-6 * r0 and x.min() >= t0 * (1 - 1e-9):
                assert t[k] @ t[k] <= x @ x * (1 + 1e-6)
                compared += 1
    assert checked >= 8 and compared >= checked // 2


def test_cable_forward_kinematics_recovers_the_pose(arm):
    rng = np.random.default_rng(2)
    md = arm.modules[0]
    R = Rotation.from_rotvec(rng.uniform(-0.8, 0.8, (5, 3))).as_matrix()
    R0 = Rotation.from_rotvec(rng.normal(0, 0.05, (5, 3))).as_matrix() @ R
    R_fk = gen.cable_forward(md, gen.cable_lengths(md, R), R0)
    np.testing.assert_allclose(R_fk, R, atol=1e-12)


def test_out_of_library_effects_are_not_absorbed(arm, scn):
    """A geometric fit leaves a good part of them: they are not a disguised frame error."""
    T0 = gen.true_poses(scn)
    for name in gen.OUT_OF_LIBRARY:
        eff = gen.draw_effect(arm, name, gen.spawn(4))
        T = gen.true_poses(scn, eff, eff.guess)
        raw = _whitened_rms(arm, scn, scn.actual_frames, T)  # before any fit
        left = gen.unabsorbed_rms(scn, eff, eff.guess)
        assert gen.unabsorbed_rms(scn, gen.NO_EFFECT, 0.0) < 1e-6
        assert raw > 0 and np.abs(T - T0).max() > 0
        assert left > 0.25 * raw, (name, left, raw)


def test_twin_shares_poses_errors_and_noise(arm, scn):
    eff = gen.draw_effect(arm, "thermal_drift", gen.spawn(5))
    rec = gen.make_recording(scn, eff, scale=0.5)
    twin = gen.clean_twin(rec)
    assert twin.effect.name == "none" and twin.scale == 0.0
    np.testing.assert_allclose(
        twin.measured[:, :3, 3] - twin.true[:, :3, 3],
        rec.measured[:, :3, 3] - rec.true[:, :3, 3],
        atol=1e-12,
    )
    # the noise-only held-out floor: zero without noise, about the noise with it
    assert gen.geometric_heldout_dp(scn, twin.true) < 1e-8
    floor = gen.geometric_heldout_dp(scn, twin.measured)
    assert np.sqrt(3) * 0.08 * 0.5 < floor < np.sqrt(3) * 0.08 * 4
    # drawing again with the same key gives the same scenario whatever the effect
    again = gen.draw_scenario(arm, M, gen.spawn(3, 1), noise_pos_mm=0.08, noise_rot_rad=1e-3)
    np.testing.assert_array_equal(again.q, scn.q)
    np.testing.assert_array_equal(again.unit_noise, scn.unit_noise)


def _oracle(model, data, sp, sr):
    folder = Path(data).parent
    t = json.loads((folder.parent / harness.TRUTH_FOLDER / f"{folder.name}.json").read_text())
    e = t["expected_effect"]
    return {
        "mismatch": e != "none",
        "effect": e,
        "located_in": t["expected_location"],
        "heldout_before": {"delta_p_mm": 0.20},
        "heldout_after": {"delta_p_mm": 0.15},
    }


def _always_none(model, data, sp, sr):
    return {
        "mismatch": False,
        "effect": "none",
        "located_in": None,
        "heldout_before": {"delta_p_mm": 0.15},
        "heldout_after": {"delta_p_mm": 0.15},
    }


def test_harness_scores_a_perfect_and_a_blind_stand_in(tmp_path):
    cfg = harness.Config(trials=3, sizes=(3.0,), poses=(M,), clean=2, ool=2, out=tmp_path / "a")
    good = harness.run(cfg, _oracle, log=lambda s: None)
    assert good["all_pass"], good["targets"]
    assert good["targets"]["effect_and_location"]["n"] == 3
    assert good["targets"]["false_positive_rate"]["n"] == 2 + 3  # clean + twins
    names = {p.name for p in (tmp_path / "a").iterdir()}
    assert all(n.startswith("rec_") for n in names - {"_truth", "results.json"})
    cfg.out = tmp_path / "b"
    blind = harness.run(cfg, _always_none, log=lambda s: None)
    t = blind["targets"]
    assert t["effect_and_location"]["rate"] == 0.0 and t["unattributed_rate"]["rate"] == 0.0
    assert t["false_positive_rate"]["rate"] == 0.0 and not blind["all_pass"]
    assert blind["heldout"]["median_after_over_floor"] == pytest.approx(1.0)
    assert len(blind["failures"]) == 3 + 2


@pytest.mark.slow
def test_statics_agree_with_the_packages_separate_implementation(arm):
    """Two separate codes (the generator's NumPy statics and cdra_jax.modules.statics) give the
    same gravity moments and the same least-norm tensions on the nominal arm."""
    import equinox as eqx

    from cdra_jax.modules.statics import gravity_torques, holding_tensions

    rng = np.random.default_rng(6)
    q = arm.limits[:, 0] + rng.random((8, arm.dof)) * np.ptp(arm.limits, axis=1)
    payload = rng.choice(gen.PAYLOADS_KG, 8)
    F = np.broadcast_to(arm.frames, (8,) + arm.frames.shape)
    Mods = np.stack(
        [gen.module_pose(md, q[:, s]) for md, s in zip(arm.modules, arm.slices, strict=True)], 1
    )
    tau = gen.gravity_moments(arm, F, Mods, payload)
    theirs_tau = eqx.filter_jit(gravity_torques)(arm.arm, q, payload)
    np.testing.assert_allclose(tau, np.asarray(theirs_tau), atol=1e-8)
    theirs = eqx.filter_jit(holding_tensions)(arm.arm, q, payload)
    for i, md in enumerate(arm.modules):
        t, ok = gen.module_tensions(md, Mods[:, i, :3, :3], tau[:, i])
        sol = theirs[md.name]
        both = ok & np.asarray(sol.successful)
        assert both.sum() >= 4
        np.testing.assert_allclose(t[both], np.asarray(sol.tensions)[both], rtol=1e-7, atol=1e-7)


def test_missing_analyser_stops_with_a_message(monkeypatch):
    monkeypatch.setitem(sys.modules, "cdra_jax.diagnosis", None)
    with pytest.raises(SystemExit, match="cdra_jax.diagnosis.diagnose_files"):
        harness.load_analyser()
