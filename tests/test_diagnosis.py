"""The missing-physics analyser on its own simulated recordings, its statistics and its CLI.

The recordings are made with this package's own effect models (tests/_physics_data.py); the
independent check is the benchmark's concealed simulator.
"""

import functools
import json

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats
from _physics_data import NOISE, BrokenEffect, base, find, recordings

from cdra_jax.cli import main
from cdra_jax.diagnosis import diagnose, diagnose_files, model, stats
from cdra_jax.io import Measurements, save_measurements
from cdra_jax.physics import corrected_tool_pose

pytestmark = pytest.mark.keep_programs  # the tests share the candidates' compiled features

CONTRACT_KEYS = {
    "mismatch",
    "p_value",
    "located_in",
    "effect",
    "parameters",
    "candidates",
    "heldout_before",
    "heldout_after",
    "not_identifiable_from_poses",
    "report",
    "noise",
}
ROW_KEYS = {
    "effect",
    "location",
    "n_params",
    "absorbed_fraction",
    "statistic",
    "p_value",
    "heldout_gain",
    "selected",
    "indistinguishable_from",
    "parameters",
}


# ----------------------------------------------------------------------------- statistics


def test_imhof_matches_chi_square_and_monte_carlo():
    for n in (12, 60, 180):
        for x in (0.5 * n, n, 2 * n + 20):
            assert stats.quadratic_form_sf(x, np.ones(n)) == pytest.approx(
                scipy.stats.chi2.sf(x, n), rel=1e-6, abs=1e-12
            )
    rng = np.random.default_rng(0)
    w = rng.uniform(0.3, 3.0, 40)
    z = (rng.standard_normal((100_000, 40)) ** 2) @ w
    for x in np.quantile(z, [0.5, 0.95, 0.99]):
        assert stats.quadratic_form_sf(x, w) == pytest.approx(np.mean(z > x), abs=0.004)
    assert stats.quadratic_form_sf(1e6, w) < 1e-100  # Chernoff tail, no lost digits


def test_heldout_statistic_has_its_stated_null_distribution():
    """Monte Carlo: residuals of a rank-deficient linear fit under unit noise give uniform
    held-out p-values, although Q is not chi2(N) (the folds share training data)."""
    rng = np.random.default_rng(1)
    m, k = 12, 10
    D = rng.standard_normal((6 * m, k))
    D[:, -1] = D[:, 0] - D[:, 1]  # a structural null direction, as the CDRA has two
    fold = np.repeat(stats.fold_of_poses(m, 4, 0), 6)  # the fold of each entry
    UD = stats.orthonormal_basis(D)
    null = stats.heldout(np.zeros(6 * m), D, fold, with_null=True).weights
    assert null.sum() == pytest.approx(6 * m, rel=1e-9)  # E[Q] = N
    ps = []
    for _ in range(300):
        e = rng.standard_normal(6 * m)
        r = e - UD @ (UD.T @ e)
        ho = stats.heldout(r, D, fold)
        ps.append(stats.quadratic_form_sf(ho.statistic, null))
    assert scipy.stats.kstest(ps, "uniform").pvalue > 1e-3


def test_holm_and_subspace_helpers():
    np.testing.assert_allclose(stats.holm(np.array([0.01, 0.04, 0.03])), [0.03, 0.06, 0.06])
    B = np.linalg.qr(np.random.default_rng(2).standard_normal((20, 3)))[0]
    assert stats.indistinguishable(B[:, :1], B)
    assert not stats.indistinguishable(B[:, :1], B[:, 1:])


def test_lack_of_fit_on_exact_repeats_is_not_applicable():
    """Exactly repeated, noise-free poses: pure error and lack of fit both at rounding. Without
    the rounding floor, F = lack of fit / 0 was astronomically significant."""
    rng = np.random.default_rng(3)
    groups = [np.arange(3 * i, 3 * i + 3) for i in range(4)]
    r = 1e-13 * rng.standard_normal(72)  # rounding-level misfit, repeats identical
    R = r.reshape(12, 6)
    for g in groups:
        R[g] = R[g[0]]
    floor2 = 1e-20
    lof = stats.lack_of_fit(r, groups, 50, floor2)
    assert lof is not None and not lof.applicable and lof.p_value is None
    # a real misfit between exactly repeated poses is still found (the floor is the denominator)
    R2 = R.copy()
    R2[::3] += 1e-3 * rng.standard_normal((4, 6))
    for g in groups:
        R2[g] = R2[g[0]]
    lof = stats.lack_of_fit(R2.reshape(-1), groups, 50, floor2)
    assert lof is not None and lof.applicable and lof.p_value < 1e-12
    # noisy repeats: an ordinary F test, unchanged by the floor
    e = rng.standard_normal(72)
    with_floor = stats.lack_of_fit(e, groups, 50, floor2)
    without = stats.lack_of_fit(e, groups, 50)
    assert with_floor is not None and without is not None
    assert with_floor.F == without.F and 0.0 < with_floor.p_value < 1.0
    # an exact residual gives no significant candidate F either
    B = np.linalg.qr(rng.standard_normal((72, 3)))[0]
    assert stats.f_test(1e-13 * B[:, 0], B, 50, floor2)[1] > 0.5


def test_variance_components_estimate_position_and_rotation_noise_separately():
    """Monte Carlo on a linear fit: the estimated variances are unbiased in each group, with the
    degrees of freedom the fit uses accounted for (a noise ratio far from 1 mm : 1 mrad)."""
    rng = np.random.default_rng(4)
    m, sp, sr = 12, 0.05, 5e-3
    s = np.tile([sp] * 3 + [sr] * 3, m)
    D = rng.standard_normal((6 * m, 22)) * np.tile([1.0] * 3 + [1e-3] * 3, m)[:, None]
    U = stats.orthonormal_basis(D / s[:, None])
    groups = np.tile([0, 0, 0, 1, 1, 1], m)
    est = []
    for _ in range(200):
        w = rng.standard_normal(6 * m)
        e = s * (w - U @ (U.T @ w))  # the residual of the fit at the true weights
        est.append(stats.variance_components(e, D, groups, np.array([1e-12, 1e-15])))
    v = np.mean(np.square(est), axis=0)
    assert v[0] == pytest.approx(sp**2, rel=0.06)
    assert v[1] == pytest.approx(sr**2, rel=0.06)
    # exact data: the rounding floor, not zero
    floors = np.array([1e-10, 1e-13])
    assert stats.variance_components(np.zeros(6 * m), D, groups, floors).tolist() == [1e-10, 1e-13]


# ----------------------------------------------------------------------------- diagnosis


@functools.cache
def _diagnosis(effect=None, values=(), noise=NOISE, *, seed=1, fold_seed=0, distortion=None):
    """``diagnose`` of the shared recordings (``recordings(effect, values, seed=seed,
    distortion=distortion)``) of the base arm with ``noise`` and the fold seed ``fold_seed``,
    once per module: several tests check different properties of the same diagnosis. Also
    returns the last ``(y, problem)`` whose full Jacobian the diagnosis formed
    (:func:`cdra_jax.diagnosis.model.residual_and_jacobian`; ``None`` if it formed none)."""
    problems = []
    full = model.residual_and_jacobian

    def spy(y, problem):
        problems.append((y, problem))
        return full(y, problem)

    meas = recordings(effect, list(values), seed=seed, distortion=distortion)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(model, "residual_and_jacobian", spy)
        d = diagnose(base().arm, meas, noise, seed=fold_seed)
    return d, (problems[-1] if problems else None)


@pytest.fixture(scope="module", autouse=True)
def _forget_the_shared_diagnoses():
    """Drop the diagnoses that :func:`_diagnosis` keeps when the module ends."""
    yield
    _diagnosis.cache_clear()


def _check_contract(d):
    out = d.to_dict()
    assert CONTRACT_KEYS <= set(out)
    text = json.dumps(out, allow_nan=False)
    assert json.loads(text)["effect"] == d.effect
    for row in out["candidates"]:
        assert ROW_KEYS <= set(row)
    for k in ("heldout_before", "heldout_after"):
        assert {"delta_p_mm", "delta_R_rad"} <= set(out[k])
    return out


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_clean_recordings_give_none(seed):
    d, _ = _diagnosis(seed=seed, fold_seed=seed)
    out = _check_contract(d)
    assert (d.effect, d.mismatch, d.located_in) == ("none", False, None)
    assert d.p_value >= 0.01
    assert out["parameters"] == {}
    assert any("uniform length scale" in s for s in d.not_identifiable_from_poses)
    assert "No missing physics" in d.report


CASES = [
    ("joint_compliance", "shoulder", None, [4e-7]),
    ("cable_elasticity", "wrist", None, [0.03]),
    ("cable_scale", "elbow", "from_home", [0.01]),
    ("backlash", "wrist", "state", [0.003, 0.0, -0.002]),
    ("periodic_error", "elbow", "k=2", [0.002, 0.001]),
    ("link_bending", "forearm", None, [1e-7, 1e-7]),
    ("thermal_drift", "base", None, [5e-4, -3e-4, 0.0, 0.0, 0.0, 2e-6]),
]


@pytest.mark.parametrize("name, location, variant, values", CASES)
def test_injected_effect_is_found_where_it_is(name, location, variant, values):
    c = find(name, location, variant)
    d, _ = _diagnosis(c, tuple(values))
    out = _check_contract(d)
    assert d.mismatch and d.p_value < 1e-6
    assert (d.effect, d.located_in) == (name, location), d.report + "\n" + d.table()
    assert d.heldout_after.delta_p_mm < d.heldout_before.delta_p_mm
    selected = [r for r in out["candidates"] if r["selected"]]
    assert len(selected) == 1 and selected[0]["effect"] == name
    # The refit's intervals cover the truth: within 1.7 half-widths of the 95 % interval
    # (3.3 sigma, so that the ~15 parameters checked here rarely fail by chance) when the
    # simulated form was selected; a variant of another form (e.g. backlash as a rotation
    # instead of a state offset: equal to first order) gets the values to 20 %.
    same_form = selected[0]["variant"] in (None, c.variant)
    for spec, v in zip(c.parameters(base().arm), values, strict=True):
        est = d.parameters[spec.name]
        half = 0.5 * (est.high - est.low)
        tol = 1.7 * half if same_form else 1.7 * half + 0.2 * max(abs(x) for x in values)
        assert abs(est.value - v) <= tol + 1e-15, (spec.name, v, est, selected[0]["variant"])
        assert est.plausible


def test_a_richer_form_is_refitted_and_reaches_the_noise_floor():
    """A drift that settles (a refinement: never tested alone) is detected by the tested
    drift-rate form and refitted in the settling form, which predicts held-out poses to the
    noise floor; refinements never get a row of the candidate table."""
    c = find("thermal_drift", "base", "warm-up tau=300s")
    d = diagnose(base().arm, recordings(c, [1.0, -0.6, 0.4, 0.0, 1e-3, 0.0]), NOISE)
    assert (d.effect, d.located_in) == ("thermal_drift", "base"), d.report
    forms = [f["variant"] for f in d.details["refit"]["forms"]]
    assert forms[0].startswith("warm-up"), forms
    floor = d.details["noise_floor"]["delta_p_mm"]
    assert d.heldout_before.delta_p_mm > 3 * floor
    assert d.heldout_after.delta_p_mm < 1.2 * floor
    assert not any(v.startswith("warm-up") for row in d.candidates for v in row.variants)


def test_uniform_length_scale_is_absorbed():
    b = base()
    frames = np.array(b.actual.frames)
    frames[:, :3, 3] *= 1.01
    d = diagnose(b.arm, recordings(actual=b.actual.with_frames(frames)), NOISE)
    assert (d.effect, d.mismatch) == ("none", False)


def test_out_of_library_distortion_is_unattributed():
    # a tool translation that grows with the product of two wrist angles: no effect's form
    def distortion(q):
        q = np.asarray(q)
        v = 0.5 * q[:, 4] * q[:, 5]
        z = np.zeros_like(v)
        return np.stack([v, z, z, z, z, z], -1)

    d = diagnose(base().arm, recordings(distortion=distortion), NOISE)
    assert d.mismatch and d.effect == "unattributed", d.report
    assert d.parameters == {}
    assert "not explained by any effect" in d.report


def test_without_noise_values_the_noise_is_estimated():
    c = find("cable_scale", "elbow", "from_home")
    d = diagnose(base().arm, recordings(c, [0.02]), None)
    assert d.noise["source"] == "estimated"
    assert (d.effect, d.located_in) == ("cable_scale", "elbow")
    clean = diagnose(base().arm, recordings(seed=5), None)
    assert clean.effect == "none"


@pytest.mark.parametrize("seed", [6, 7])
def test_without_noise_values_clean_recordings_give_none(seed):
    """No stated noise, a device whose position : rotation noise (0.05 mm : 5e-4 rad) is not the
    1 mm : 1 mrad weighting: the two are estimated separately, near the truth, and clean
    recordings are not flagged (with one fixed ratio the candidate F tests fired on about half
    of them)."""
    d = diagnose(base().arm, recordings(seed=seed), None, seed=seed)
    assert d.noise["source"] == "estimated"
    assert d.noise["position_mm"] == pytest.approx(NOISE.position_mm, rel=0.25)
    assert d.noise["rotation_rad"] == pytest.approx(NOISE.rotation_rad, rel=0.25)
    assert (d.effect, d.mismatch) == ("none", False), d.report
    assert "noisier than stated" not in d.report


@pytest.mark.parametrize("noise", [None, NOISE])
def test_exactly_repeated_exact_poses_give_none(noise):
    """Noise-free recordings of poses each repeated exactly three times: the pure error is zero,
    the misfit is rounding, and nothing is missing."""
    b = base()
    idx = np.repeat(np.arange(10), 3)
    T = corrected_tool_pose(b.actual, b.q, b.F, np.zeros(b.F.n_params))
    aux = {k: np.asarray(v)[idx] for k, v in b.aux.items()}
    meas = Measurements.from_arrays(b.arm, np.asarray(b.q)[idx], np.asarray(T)[idx], aux=aux)
    d = diagnose(b.arm, meas, noise)
    assert (d.effect, d.mismatch) == ("none", False), d.report
    lof = d.tests["lack_of_fit"]
    assert lof["repeated_groups"] == 10 and not lof["applicable"] and lof["p_value"] is None
    assert "lack_of_fit" not in d.tests["combined"]["tests"]
    assert "not applicable" in d.report
    _check_contract(d)


def test_bad_inputs_raise_clear_errors():
    meas = recordings()
    with pytest.raises(ValueError, match="folds"):
        diagnose(base().arm, meas, NOISE, folds=1)
    with pytest.raises(ValueError, match="alpha"):
        diagnose(base().arm, meas, NOISE, alpha=1.5)
    with pytest.raises(ValueError, match="at least 6"):
        diagnose(base().arm, meas.select(np.arange(5)), NOISE)


def test_cli_end_to_end(tmp_path, capsys):
    c = find("joint_compliance", "shoulder")
    data = save_measurements(recordings(c, [4e-7]), tmp_path / "rec.csv")
    out = tmp_path / "diag.json"
    plots = tmp_path / "plots"
    argv = ["diagnose", "--data", str(data), "--noise-pos", "0.05", "--noise-rot", "0.0005"]
    argv += ["--out", str(out), "--plots", str(plots)]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "shoulder module deflects" in text and "candidate" in text and "SELECTED" in text
    res = json.loads(out.read_text())
    assert CONTRACT_KEYS <= set(res)
    assert (res["effect"], res["located_in"]) == ("joint_compliance", "shoulder")
    assert sorted(p.name for p in plots.iterdir()) == [
        "residual_per_pose.png",
        "residual_vs_regressors.png",
    ]
    assert main(argv) == 1  # no overwrite without --force (refused before any work)
    assert "exists" in capsys.readouterr().err
    d = diagnose_files(None, data, 0.05, 0.0005)
    assert d.effect == "joint_compliance"


def test_skipped_effects_are_summarised_per_effect_when_no_location_applies():
    from types import SimpleNamespace

    from cdra_jax.diagnosis.report import _skipped_text

    rows = [
        SimpleNamespace(
            effect="cable_elasticity",
            location=loc,
            label=f"cable_elasticity@{loc}",
            skipped=f"module {loc!r} has no cables in the model",
        )
        for loc in ("j1", "j2", "j3")
    ] + [
        SimpleNamespace(effect="backlash", location="j1", label="backlash@j1", skipped=None),
        SimpleNamespace(
            effect="backlash", location="j2", label="backlash@j2", skipped="no approach.j2"
        ),
    ]
    assert _skipped_text(rows) == [
        "cable_elasticity at every location (no module has cables in the model)",
        "backlash@j2 (no approach.j2)",
    ]


def test_svd_and_cholesky_survive_what_lapack_refuses():
    from cdra_jax.diagnosis import stats

    with pytest.raises(ValueError, match="non-finite value"):
        stats.orthonormal_basis(np.array([[1.0, np.nan], [0.0, 1.0]]))
    S = np.eye(3) + 1e-17 * np.ones((3, 3))
    assert np.all(np.isfinite(stats._cholesky(S)))


# ----------------------------------------------------------------------------- points


MARKERS = (("m1", (40.0, 0.0, 10.0)), ("m2", (0.0, 35.0, 10.0)), ("m3", (-30.0, -25.0, 20.0)))


def _point_recordings(effect=None, values=(), *, seed: int = 11, device=True):
    """The shared poses measured as 3 markers on the tool (0.05 mm per coordinate, about 10 %
    of the markers occluded), in a device frame 400 mm and 30 deg away from the model's base."""
    from cdra_jax.arm import Marker

    b = base()
    arm = b.arm.with_markers([Marker(n, xyz) for n, xyz in MARKERS])
    theta = np.zeros(b.F.n_params)
    if effect is not None:
        theta[b.cols[effect]] = values
    T = np.asarray(corrected_tool_pose(b.actual, b.q, b.F, jnp.asarray(theta)))
    if device:
        c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
        to_device = np.array([[c, -s, 0, 400.0], [s, c, 0, -150.0], [0, 0, 1, 80.0], [0, 0, 0, 1]])
        T = to_device @ T
    rng = np.random.default_rng(seed)
    points = {}
    for name, xyz in MARKERS:
        p = T[:, :3, :3] @ np.asarray(xyz) + T[:, :3, 3]
        p = p + 0.05 * rng.standard_normal(p.shape)
        p[rng.random(p.shape[0]) < 0.1] = np.nan
        points[name] = p
    aux = {k: np.asarray(v) for k, v in b.aux.items()}
    meas = Measurements.from_arrays(arm, np.asarray(b.q), None, aux=aux, points=points)
    return arm, meas


def test_point_data_clean_give_none_and_an_injected_effect_is_found_where_it_is():
    """Markers only (no orientation), occlusions, a device frame far from the base, the noise
    estimated: the geometric fit registers the device frame; a periodic transmission error at
    the elbow is found there and refitted to the noise floor; clean data give none."""
    arm, clean = _point_recordings()
    d = diagnose(arm, clean, None)
    out = _check_contract(d)
    assert (d.effect, d.mismatch) == ("none", False), d.report
    assert list(d.noise["points_mm"]) == ["m1", "m2", "m3"]
    assert all(v == pytest.approx(0.05, rel=0.25) for v in d.noise["points_mm"].values())
    assert d.noise["position_mm"] is None and out["heldout_before"]["delta_R_rad"] is None
    assert "marker coordinates" not in d.report and "(noise estimated: points 0.0" in d.report

    c = find("periodic_error", "elbow", "k=2")
    arm, meas = _point_recordings(c, [0.002, 0.001])
    d = diagnose(arm, meas, None)
    _check_contract(d)
    assert d.mismatch and (d.effect, d.located_in) == ("periodic_error", "elbow"), d.report
    # the noise is estimated from the geometric fit's residual, which the misfit inflates: the
    # floor of the truth (0.05 mm per coordinate) is what the refit must reach
    true_floor = 0.05 * np.sqrt(3)
    assert d.heldout_before.delta_p_mm > 2.5 * true_floor, d.heldout_before
    assert d.heldout_after.delta_p_mm < 1.2 * true_floor, d.heldout_after
    for spec, v in zip(c.parameters(arm), (0.002, 0.001), strict=True):
        est = d.parameters[spec.name]
        assert abs(est.value - v) <= 1.7 * 0.5 * (est.high - est.low), (spec.name, est)
    per_row = d.residuals["after"]
    assert per_row["position_mm"].shape == (meas.m,)
    assert np.all(np.isnan(per_row["rotation_rad"]))


def test_point_data_through_the_cli(tmp_path, capsys):
    from cdra_jax.io import save_model

    c = find("periodic_error", "elbow", "k=2")
    arm, meas = _point_recordings(c, [0.002, 0.001], device=False)
    model = save_model(arm, tmp_path / "model.toml")
    data = save_measurements(meas, tmp_path / "points.csv")
    out = tmp_path / "diag.json"
    argv = ["diagnose", "--model", str(model), "--data", str(data), "--out", str(out)]
    assert main(argv + ["--plots", str(tmp_path / "plots")]) == 0
    res = json.loads(out.read_text())
    assert (res["effect"], res["located_in"]) == ("periodic_error", "elbow")
    assert res["noise"]["source"] == "estimated" and res["noise"]["points_mm"]["m2"] > 0
    assert "points" in capsys.readouterr().out


def test_gravity_turns_with_the_registered_base_frame():
    from cdra_jax import default_arm, lie
    from cdra_jax.diagnosis.core import _gravity_in_fit_frame

    arm = default_arm()
    turn = np.asarray(lie.from_xyz_rotvec(np.array([400.0, 0, 0]), np.array([np.pi / 2, 0, 0])))
    frames = np.asarray(arm.frames).copy()
    frames[0] = turn @ frames[0]
    moved = _gravity_in_fit_frame(arm.with_frames(frames), arm)
    np.testing.assert_allclose(np.asarray(moved.gravity), [0.0, 9.81, 0.0], atol=1e-12)


def test_the_refit_model_predicts_poses_the_diagnosis_never_saw(tmp_path, capsys):
    """diagnose --model-out writes the fitted frames plus the found effect as [[effects]];
    validate predicts new poses with it far better than with the geometric calibration of the
    same recording, close to the noise."""
    import equinox as eqx
    import jax

    from cdra_jax.diagnosis.model import all_features
    from cdra_jax.io import load_model
    from cdra_jax.modules.tension import sample_feasible_states

    c = find("periodic_error", "elbow", "k=2")
    values = [0.002, 0.001]
    b = base()
    fit = save_measurements(recordings(c, values), tmp_path / "fit.csv")
    # 30 other poses of the same arm and effect, made as the shared recordings are (the same
    # programs and shapes: no new compilation)
    q = eqx.filter_jit(sample_feasible_states)(jax.random.PRNGKey(77), b.arm, 30)
    theta = np.zeros(b.F.n_params)
    theta[b.cols[c]] = values
    T = np.array(
        corrected_tool_pose(b.actual, q, all_features(b.everything, b.actual, q, b.aux), theta)
    )
    q = np.asarray(q)
    rng = np.random.default_rng(78)
    T[:, :3, 3] += NOISE.position_mm * rng.standard_normal((30, 3))
    aux = {k: np.asarray(v) for k, v in b.aux.items()}
    test = save_measurements(Measurements.from_arrays(b.arm, q, T, aux=aux), tmp_path / "test.csv")
    out, refit = tmp_path / "diag.json", tmp_path / "refit.toml"
    assert main(["diagnose", "--data", str(fit), "--out", str(out), "--model-out", str(refit)]) == 0
    cal = tmp_path / "cal.toml"
    argv = ["calibrate", "--data", str(fit), "--out", str(tmp_path / "cal.json")]
    assert main(argv + ["--model-out", str(cal)]) == 0
    val = tmp_path / "val.json"
    argv = ["validate", "--model", str(refit), "--compare", str(cal), "--data", str(test)]
    assert main(argv + ["--out", str(val)]) == 0
    capsys.readouterr()
    res = json.loads(val.read_text())
    geometric = res["compare"]["position_error_mm"]["rms"]
    found = res["position_error_mm"]["rms"]
    assert found < 0.5 * geometric, (found, geometric)
    assert found < 2.0 * NOISE.position_mm * np.sqrt(3), found
    model = load_model(refit)
    assert [(e.name, e.location, e.variant) for e in model.effects] == [
        ("periodic_error", "elbow", "k=2")
    ]
    diag = json.loads(out.read_text())
    assert diag["refit_model"]["effects"][0]["effect"] == "periodic_error"


def test_a_model_with_the_found_effect_explains_new_recordings():
    """The refit model carries the effect as [[effects]]; diagnosing new recordings of the same
    arm with it fits the effect with the frames (part of the base model), finds nothing more
    and skips that candidate; the effect's values are refitted."""
    c = find("periodic_error", "elbow", "k=2")
    first, _ = _diagnosis(c, (0.002, 0.001))
    assert (first.effect, first.located_in) == ("periodic_error", "elbow")
    model = first.refit_arm
    assert [(e.name, e.location, e.variant) for e in model.effects] == [
        ("periodic_error", "elbow", "k=2")
    ]
    d = diagnose(model, recordings(c, [0.002, 0.001], seed=4), NOISE)
    assert (d.effect, d.mismatch) == ("none", False), d.report
    assert d.details["geometric_fit"]["model_effects"] == ["periodic_error@elbow"]
    row = next(r for r in d.candidates if r.label == "periodic_error@elbow")
    assert "k=2" not in row.variants  # the model's own form is not a candidate
    (refitted,) = d.refit_arm.effects
    values = [v for _, v, _ in refitted.parameters]
    np.testing.assert_allclose(values, [0.002, 0.001], atol=3e-4)


def test_a_physically_impossible_estimate_is_never_reported():
    """A shoulder that deflects against gravity (a negative compliance): the best candidate fits
    it with an impossible sign, so no effect is named; the report says which and why."""
    c = find("joint_compliance", "shoulder")
    d = diagnose(base().arm, recordings(c, [-4e-7]), NOISE)
    assert d.mismatch and d.effect == "unattributed", d.report
    assert d.parameters == {}
    rejected = d.details["refit"]["rejected"]
    assert rejected["candidate"] == "joint_compliance@shoulder"
    assert "physically implausible" in rejected["reason"] and "not reported" in d.report
    assert not d.refit_arm.effects  # the written model keeps only the geometric fit


def test_a_candidate_that_fails_numerically_is_marked_failed_and_the_diagnosis_goes_on():
    c = find("cable_scale", "elbow", "from_home")
    d = diagnose(base().arm, recordings(c, [0.02]), NOISE, effects=(c.effect, BrokenEffect()))
    assert (d.effect, d.located_in) == ("cable_scale", "elbow"), d.report
    row = next(r for r in d.candidates if r.effect == "broken")
    assert row.skipped == "failed: its features are not finite on these data"
    assert "broken@elbow (failed" in d.report


def _tanh_stretch(q):
    """A saturating transmission stretch at the elbow (no effect of the vocabulary has it)."""
    v = 0.3 * np.tanh(2 * np.asarray(q)[:, 3])
    z = np.zeros_like(v)
    return np.stack([v, v, z, z, z, z], -1)


@pytest.mark.parametrize("case", ["clean", "compliance", "saturating"])
def test_the_verdict_does_not_depend_on_the_noise_values(case):
    """The verdict rests on tests without a noise value: the same effect and place with the
    true noise and with every noise value scaled by 0.7 or 1.3; a stated noise that the
    residuals contradict is said to be so, without changing the verdict (a named effect's refit
    that contradicts the stated noise by more than NOISE_CONTRADICTION: the diagnosis runs
    again with the noise estimated from that refit)."""
    from cdra_jax import NoiseModel

    if case == "clean":  # the recordings and folds of test_clean_recordings_give_none[1]
        kw, expected = {"fold_seed": 1}, ("none", None)
    elif case == "compliance":
        kw = {"effect": find("joint_compliance", "shoulder"), "values": (4e-7,)}
        expected = ("joint_compliance", "shoulder")
    else:
        kw, expected = {"distortion": _tanh_stretch}, ("unattributed", "elbow")
    for k in (0.7, 1.0, 1.3):
        noise = NoiseModel(NOISE.position_mm * k, NOISE.rotation_rad * k)
        d, _ = _diagnosis(noise=noise, **kw)
        assert (d.effect, d.located_in) == expected, (k, d.report)
        if case == "clean":
            text = "noisier than stated" if k == 0.7 else "consistent with the residuals"
            assert text in d.report, (k, d.report)
        if case == "compliance":
            ratio = d.noise.get("stated_contradicted_by")
            if k != 1.3:  # 1/1.3 is near the threshold: either way
                assert (ratio is not None) == (k == 0.7), (k, ratio)
            assert ratio is None or abs(ratio * k - 1.0) < 0.2, (k, ratio)  # the true noise
            said = "The noise values given are contradicted" in d.report
            assert said == (ratio is not None), (k, d.report)


def test_a_shape_the_vocabulary_lacks_is_unattributed_where_it_lives_without_noise_values():
    """A saturating stretch at the elbow, the noise estimated: not absorbed by a flexible
    candidate (a periodic error fits it partly), but reported unattributed and located at the
    elbow, whose states predict the residual's structure."""
    d = diagnose(base().arm, recordings(distortion=_tanh_stretch), None)
    assert d.mismatch and (d.effect, d.located_in) == ("unattributed", "elbow"), d.report
    assert d.details["location_source"] in ("structure", "partial candidate")
    assert d.tests["structure"]["p_value"] < 0.01


def test_a_misfit_that_changes_with_time_is_placed_at_the_frame_whose_time_probe_explains_it():
    """Time probes have the same size at every fixed frame; the most significant one places a
    time-dependent misfit (a link growing as it warms up), the base when none is significant."""
    from cdra_jax.diagnosis.core import _place
    from cdra_jax.physics import TimeProbe

    arm = base().arm
    kind = TimeProbe.summary
    rows = [
        {"location": "base", "kind": kind, "df": 6, "F": 30.0, "p_value": 1e-20},
        {"location": "upper_arm", "kind": kind, "df": 6, "F": 200.0, "p_value": 1e-60},
        {"location": "shoulder", "kind": "a module probe", "df": 36, "F": 900.0, "p_value": 1e-90},
    ]
    assert _place(arm, "time_s", rows, 0.01) == "upper_arm"
    assert _place(arm, "time_s", [{**r, "p_value": 0.5} for r in rows], 0.01) == "base"
    assert _place(arm, "elbow", rows, 0.01) == "elbow"
    f = base().F
    probe = next(c for c in base().everything if isinstance(c.effect, TimeProbe))
    assert len(probe.parameters(arm)) == 6 and f.n_params > 0


def test_refit_columns_are_those_of_the_full_jacobian():
    """The Jacobian's columns (every column through the per-pose corrections; the refit's
    steps take only the free ones) equal those of jax.jacfwd of the whitened residual, for
    all of them and for column sets of a few sizes."""
    import jax

    c = find("periodic_error", "elbow", "k=2")
    _, (y, problem) = _diagnosis(c, (0.002, 0.001))
    # away from the fit, every entry moved
    y = jnp.asarray(np.asarray(y) + 1e-3 * np.sin(np.arange(y.shape[0])))

    def residual_twice(yy):
        r = model.whitened_residual(yy, problem)
        return r, r

    J, r = jax.jit(jax.jacfwd(residual_twice, has_aux=True))(y)  # one program for both
    r, J = np.asarray(r), np.asarray(J)
    r_all, J_all = model.residual_and_jacobian(y, problem)
    np.testing.assert_allclose(r_all, r, rtol=0, atol=1e-12 * float(np.max(np.abs(r))))
    np.testing.assert_allclose(J_all, J, rtol=0, atol=1e-12 * float(np.max(np.abs(J))))
    rng = np.random.default_rng(0)
    for k in (16, 7, 25):
        cols = np.sort(rng.choice(y.shape[0], k, replace=False))
        r_k, J_k = model.residual_and_columns(y, problem, cols)
        np.testing.assert_allclose(r_k, r, rtol=0, atol=1e-12 * float(np.max(np.abs(r))))
        scale = float(np.max(np.abs(J[:, cols])))
        np.testing.assert_allclose(J_k, J[:, cols], rtol=0, atol=1e-12 * scale)


def test_the_shape_check_weights_each_kind_of_entry_by_its_spread():
    """Position entries twice as spread as the rotation entries (as when the noise values were
    estimated from a residual that holds a misfit) are weighted down to the same spread after
    the alternative's columns are fitted; the weights do not depend on the overall scale."""
    from cdra_jax.diagnosis.core import _POINT, _POSITION, _ROTATION, _kind_weights, _Rows

    rng = np.random.default_rng(5)
    kind = np.repeat([_POSITION, _ROTATION, _POINT], 300)
    n = kind.size
    point = np.where(kind == _POINT, 0, -1)
    rows = _Rows(*(np.arange(n),) * 2, kind, *(np.zeros(n, int),) * 2, point, np.ones(n))
    J = rng.standard_normal((n, 4))
    spread = np.select([kind == _POSITION, kind == _ROTATION], [2.0, 1.0], 0.5)
    r = spread * rng.standard_normal(n) + J @ np.array([3.0, -1.0, 0.5, 2.0])
    w = _kind_weights(r, J, rows)
    ratio = [float(w[kind == k][0]) for k in (_POSITION, _ROTATION, _POINT)]
    np.testing.assert_allclose(np.array(ratio) / ratio[1], [0.5, 1.0, 2.0], rtol=0.15)
    assert np.mean(w**2) == pytest.approx(1.0)
    np.testing.assert_allclose(_kind_weights(10 * r, 10 * J, rows), w, rtol=1e-12)
