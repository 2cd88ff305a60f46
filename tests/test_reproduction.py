"""The paper's evidence (Table I, Figs. 5 and 7) regenerated, and the demo command.

The studies run at the demo's small sizes (``demo.SMALL``), so that the demo test at the end
reuses their compiled programs within the test session.
"""

import json
import math
import re

import jax
import numpy as np
import pytest

from cdra_jax import (
    apply_frame_errors,
    lie,
    reproduction,
    tool_pose,
)
from cdra_jax.cli import demo as demo_cli
from cdra_jax.cli import main
from cdra_jax.identifiability import format_combination
from cdra_jax.workflows.demo import SMALL


@pytest.fixture(scope="module")
def table(cdra):
    return reproduction.table_one(
        cdra, m=SMALL.table_m, m_verify=SMALL.table_m_verify, seed=0, fast_compile=True
    )


@pytest.fixture(scope="module")
def convergence(cdra):
    return reproduction.convergence_study(
        cdra, trials=SMALL.convergence_trials, m=SMALL.convergence_m, fast_compile=True
    )


@pytest.fixture(scope="module")
def noise(cdra):
    return reproduction.noise_study(
        cdra,
        m_values=SMALL.noise_m_values,
        trials=SMALL.noise_trials,
        m_verify=SMALL.noise_m_verify,
        pad_to=SMALL.noise_pad_to,
        fast_compile=True,
    )


def test_table_one_presets_are_the_papers():
    # Spot checks against the paper's Table I (OBs first row, WF last, SBe identified).
    assert reproduction.TABLE_I_PRESET.shape == (4, 6)
    np.testing.assert_array_equal(
        reproduction.TABLE_I_PRESET[0], [-6.5597, 3.8277, 8.9030, 0.1207, 0.1538, -0.0910]
    )
    np.testing.assert_array_equal(
        reproduction.TABLE_I_PAPER[1], [1.5354, 6.1907, 6.0510, -0.1290, 0.0223, -0.0011]
    )
    np.testing.assert_array_equal(
        reproduction.TABLE_I_PAPER[[0, 3]], reproduction.TABLE_I_PRESET[[0, 3]]
    )


def test_table_one_base_and_tool_exact(table):
    assert table.result == "successful"
    assert table.fit_delta_p < 1e-9 and table.fit_delta_R < 1e-12
    err = dict(zip(table.frame_names, table.recovery_error, strict=True))
    assert err["base"] < 1e-8 and err["tool"] < 1e-8
    assert table.exact_frames == ("base", "tool")
    # The middle frames are *not* the presets: the null space is really at play.
    assert err["upper_arm"] > 1e-3 and err["forearm"] > 1e-3


def test_table_one_differences_lie_in_the_null_space(cdra, table):
    assert table.null_space.shape == (2, 24)
    assert table.identifiable_part < 1e-8
    # Independent oracle: F_forearm^c = E^-1 F_forearm^a and F_upper^c = F_upper^a E with E a
    # screw along the elbow axis through the elbow centre: the forearm difference is -zeta with
    # both parts of zeta = (v, w) parallel to the axis, the upper-arm one Ad(F_upper^a) zeta.
    d_up, d_fore = table.group_difference[1], table.group_difference[2]
    axis = np.asarray(cdra.module("elbow").axis)
    assert np.linalg.norm(np.cross(d_fore[:3], axis)) < 1e-9
    assert np.linalg.norm(np.cross(d_fore[3:], axis)) < 1e-9
    assert abs(d_fore[4]) > 1e-4  # a real rotation about the axis, not a zero difference
    zeta = -d_fore
    F_up = np.asarray(lie.se3_exp(table.preset[1])) @ np.asarray(cdra.frames)[1]
    np.testing.assert_allclose(d_up, np.asarray(lie.adjoint(F_up)) @ zeta, atol=1e-9)
    np.testing.assert_allclose(table.group_difference[[0, 3]], 0.0, atol=1e-9)


def _parse_combination(text, names):
    """A vector over ``names`` from ``format_combination`` text
    ("0.707 rad a.wy - 217 mm a.vx ...")."""
    v = np.zeros(len(names))
    for term in text.replace(" - ", " + -").split(" + "):
        coef, unit, name = term.split()
        assert unit == ("rad" if name.rsplit(".", 1)[1].startswith("w") else "mm")
        v[names.index(name)] += float(coef)
    return v


def test_table_one_null_coordinates_are_in_the_printed_basis(table):
    # Data: the coordinates are those of the readable directions that are printed as n1, n2.
    names = table.param_names
    B = table.directions
    assert B.shape == table.null_space.shape == (2, 24)
    assert table.unidentifiable == tuple(format_combination(b, names) for b in B)
    for d, c, part in (
        (table.group_difference, table.null_coordinates, table.identifiable_part),
        (table.paper_group_difference, table.paper_null_coordinates, table.paper_identifiable_part),
    ):
        outside = np.linalg.norm(d.reshape(-1) - B.T @ c)
        assert outside == pytest.approx(part, rel=1e-6, abs=1e-12)
    assert table.identifiable_part < 1e-8
    # Text: the printed coefficients times the printed directions give the printed difference,
    # to the printing precision (3 significant digits for vectors, 4 for coefficients).
    text = reproduction.format_table_one(table).splitlines()
    printed_dirs = [
        _parse_combination(line.split(" = ", 1)[1], names)
        for line in text
        if re.match(r"^  n\d+ = ", line)
    ]
    assert len(printed_dirs) == 2
    np.testing.assert_allclose(printed_dirs, B, rtol=5e-3, atol=1e-8)
    checked = 0
    for who, part in (("ours", table.identifiable_part), ("paper", table.paper_identifiable_part)):
        i = next(k for k, line in enumerate(text) if line.strip().startswith(f"{who}: log("))
        coords = re.findall(r"([+-]\d[\d.]*(?:e[+-]\d+)?) n(\d+)", text[i])
        assert [int(k) for _, k in coords] == [1, 2], text[i]
        c = np.array([float(v) for v, _ in coords])
        diff = _parse_combination(text[i + 1].strip()[1:-1], names)
        recon = c @ np.array(printed_dirs)
        scale = np.abs(c) @ np.abs(np.array(printed_dirs))
        bound = 6e-3 * scale + 6e-3 * np.abs(diff) + 1.1 * part + 2e-6
        assert np.all(np.abs(recon - diff) <= bound), (who, recon - diff, bound)
        # ... and the reconstruction is the exact difference up to its identifiable part
        exact = table.group_difference if who == "ours" else table.paper_group_difference
        np.testing.assert_allclose(recon, exact.reshape(-1), atol=float(np.max(bound)))
        checked += 1
    assert checked == 2


def test_table_one_papers_values_fit_to_their_rounding(table):
    # The paper's identified values are, in our model, a null-space move of the presets up to
    # their rounding: each of the 24 printed values is off by <= 0.5e-4, so the identifiable
    # part of their group difference is at most |r| <= 0.5e-4 sqrt(24) (projection does not
    # expand; the exp/log Jacobians at |w| <= 0.2 rad add < 10 %).
    assert table.paper_identifiable_part < 1.1 * 0.5e-4 * math.sqrt(24)
    v = table.verification
    assert v["ours"][0] < 1e-9 and v["ours"][1] < 1e-12
    # ... and reproduce the actual tool poses to within the first-order worst case of rounding
    # (rounding_bound), as does our own answer rounded to 4 decimals.
    for who, bound in (("paper", "paper"), ("ours_rounded", "ours")):
        dp, dR = v[who]
        bp, bR = table.rounding_bound[bound]
        assert 0 < dp <= bp and 0 < dR <= bR, (who, dp, dR, bp, bR)
    assert table.rounding_bound["paper"][0] < 0.5  # mm: rounding, not a model mismatch
    assert v["nominal"][0] > 1000 * v["paper"][0]
    text = reproduction.format_table_one(table)
    for needed in ("Table I", "recovered exactly", "unidentifiable", "elbow", "rounding"):
        assert needed in text


def test_rounding_bound_holds_for_random_roundings(cdra, table):
    # The bound is a worst case over all roundings: perturb our exact answer by random
    # +-0.5e-4 offsets and check that the tool-pose error stays below it.
    q = reproduction.DEFAULT_SAMPLER(reproduction._keys(3, 1)[0], cdra, 30)
    bp, bR = reproduction.rounding_bound(cdra, table.identified, q)
    r = np.random.default_rng(1).uniform(-0.5e-4, 0.5e-4, size=(3, 24))
    X = table.identified.reshape(1, -1) + np.concatenate([np.zeros((1, 24)), r])
    T = np.asarray(jax.jit(jax.vmap(lambda x: tool_pose(apply_frame_errors(cdra, x), q)))(X))
    for Ti in T[1:]:
        dpos = np.linalg.norm(Ti[:, :3, 3] - T[0][:, :3, 3], axis=-1)
        Rrel = np.swapaxes(T[0][:, :3, :3], -1, -2) @ Ti[:, :3, :3]
        skew = 0.5 * (Rrel - np.swapaxes(Rrel, -1, -2))
        angle = np.arcsin(np.linalg.norm(skew[:, [2, 0, 1], [1, 2, 0]], axis=-1))
        assert np.sqrt(np.mean(dpos**2)) <= bp
        assert np.sqrt(np.mean(angle**2)) <= bR
        assert np.sqrt(np.mean(dpos**2)) > 1e-3 * bp  # the perturbation did something


def test_convergence_within_six_iterations(convergence):
    c = convergence
    assert c.delta_p.shape == (SMALL.convergence_trials, 9)
    assert np.all(c.results == "successful")
    assert np.all((c.iterations_to_tol >= 1) & (c.iterations_to_tol <= 6))
    assert np.all(c.delta_p[:, 6] < 1e-9) and np.all(c.delta_R[:, 6] < 1e-9)
    # Nominal model is far off: the errors really were injected.
    assert np.all(c.delta_p[:, 0] > 1.0)
    med, lo, hi = c.band("delta_p")
    assert np.all(lo <= med) and np.all(med <= hi)
    assert sum(c.iteration_histogram().values()) == c.trials
    assert "Fig. 5" in reproduction.format_convergence(c)


def test_noise_study_monotone_ish(noise):
    s = noise
    i5, i40 = list(s.m_values).index(5), list(s.m_values).index(40)
    fp, fr = s.noise_floor
    for solver in reproduction.SOLVERS:
        for metric in ("dp_true", "dR_true", "param_v", "param_w", "dp_measured"):
            med, _, _ = s.band(solver, metric)
            assert med[i40] < med[i5], (solver, metric)
        # cannot beat the measurement noise against measured poses
        assert np.nanmedian(s.metrics[solver]["dp_measured"][i40]) > 0.9 * fp
        assert np.nanmedian(s.metrics[solver]["dR_measured"][i40]) > 0.9 * fr
        assert s.converged[solver][i40].mean() > 0.95
    # Weighting by the noise model beats the unweighted form at m = 40.
    assert np.median(s.metrics["weighted"]["dp_true"][i40]) < np.median(
        s.metrics["paper"]["dp_true"][i40]
    )
    text = reproduction.format_noise_study(s)
    assert "flatten" in text and "weighted" in text


def test_pose_repetition_gives_the_same_calibration(cdra, noise):
    # Repeating every pose r times is the same least-squares problem: the padded study (the
    # fixture, pad_to=40) equals an unpadded one on the same trials (same seed, same 40 drawn
    # poses, m = 8 solved on 8 rather than 40 rows).
    idx = reproduction.pose_repetition(8, 40)
    assert idx.shape == (40,) and np.all(np.bincount(idx) == 5)
    assert list(reproduction.pose_repetition(3, None)) == [0, 1, 2]
    plain = reproduction.noise_study(
        cdra,
        m_values=(8, 40),
        trials=SMALL.noise_trials,
        m_verify=SMALL.noise_m_verify,
        pad_to=None,
        fast_compile=True,
    )
    i8 = list(noise.m_values).index(8)
    for solver in reproduction.SOLVERS:
        for metric in reproduction.NOISE_METRICS:
            np.testing.assert_allclose(
                plain.metrics[solver][metric][0],
                noise.metrics[solver][metric][i8],
                rtol=1e-6,
                atol=1e-9,
                err_msg=f"{solver} {metric}",
            )
        np.testing.assert_array_equal(plain.converged[solver][0], noise.converged[solver][i8])


def test_flattening_point():
    m = np.array([4, 5, 10, 20, 40])
    assert reproduction.flattening_point(m, [9.0, 3.0, 1.2, 1.05, 1.0]) == 20
    assert reproduction.flattening_point(m, [1.0, 1.0, 1.0, 1.0, 1.0]) == 4
    # a later excursion outside the band moves the point past it
    assert reproduction.flattening_point(m, [9.0, 1.0, 1.5, 1.0, 1.0]) == 20
    with pytest.raises(ValueError, match="matching"):
        reproduction.flattening_point(m, [1.0, 2.0])


def test_cmm_noise():
    n = reproduction.cmm_noise()
    assert n.position_mm == 0.08
    assert n.rotation_rad == pytest.approx(math.sqrt(2) * 0.08 / 100.0)
    with pytest.raises(ValueError, match="positive"):
        reproduction.cmm_noise(feature_spacing_mm=0.0)


def test_bad_arguments(cdra):
    with pytest.raises(ValueError, match="m_values"):
        reproduction.noise_study(cdra, m_values=(3, 10), trials=2)
    with pytest.raises(ValueError, match="at least 4"):
        reproduction.convergence_study(cdra, m=3, trials=2)
    other = cdra.__class__(
        frames=cdra.frames, modules=cdra.modules, frame_names=("a", "b", "c", "d")
    )
    with pytest.raises(ValueError, match="Table I needs"):
        reproduction.table_one(other)


def test_demo_output_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    first = demo_cli.output_folder(None, False)
    assert first.name.startswith("cdra-demo-") and first.is_dir()  # a new folder, never "."
    (first / "x.txt").write_text("keep")
    second = demo_cli.output_folder(None, False)
    assert second != first and second.name.startswith(first.name[:18])
    with pytest.raises(FileExistsError, match="--force"):
        demo_cli.output_folder(str(first), False)
    assert demo_cli.output_folder(str(first), True) == first
    assert main(["demo", "--out-dir", str(first)]) == 1  # refuses before computing anything
    assert (first / "x.txt").read_text() == "keep"


def test_demo_writes_tables_and_figures(tmp_path, capsys, table, convergence):
    # Runs after the studies above, whose compiled programs it reuses (Fig. 7's, those of the
    # noise fixture, only in a run with --extended: the default run computes that study once,
    # here).
    out = tmp_path / "demo"
    assert main(["demo", "--out-dir", str(out), "--seed", "0"]) == 0
    printed = capsys.readouterr().out
    for name in demo_cli.OUTPUT_FILES:
        assert (out / name).stat().st_size > 0, name
    for name in demo_cli.OUTPUT_FILES:
        if name.endswith(".png"):
            assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "Table I" in printed and "Fig. 5" in printed and "Fig. 7" in printed
    assert str(out.resolve()) in printed
    summary = json.loads((out / "summary.json").read_text())
    assert summary["table_1"]["exact_frames"] == ["base", "tool"]
    assert summary["fig_7"]["m_values"] == list(SMALL.noise_m_values)
    # the demo's numbers are the studies' numbers (same seed and sizes)
    np.testing.assert_allclose(summary["table_1"]["identified"], table.identified)
    assert (out / "report.txt").read_text().startswith("cdra-jax demo")
