"""Sweeps: chunking and sharding never change a trial, the table, the CLI and the plot.

All sweeps here share one cell shape (m = 5, solver "weighted", chunk 4, 10 held-out states),
so the vmapped trial function is compiled once per process.
"""

import functools
import importlib.util
import textwrap

import jax
import matplotlib
import numpy as np
import pytest
from _devices import run_on_two_cpu_devices

from cdra_jax import (
    NoiseModel,
    apply_frame_errors,
    calibrate_paper,
    deviation_metrics,
    sweeps,
    tool_pose,
)
from cdra_jax.cli import main as cli_main
from cdra_jax.modules import DEFAULT_MIN_MARGIN, arm_tension_closure
from cdra_jax.simulation import simulate_trial
from cdra_jax.sweeps import (
    COLUMNS,
    parse_noise_levels,
    read_sweep,
    run_sweep,
    trial_key,
)

matplotlib.use("Agg")

LEVELS = [(0.08, 1e-3), (0.2, 2e-3)]
CELL = dict(solvers=["weighted"], seed=7, chunk=4, m_verify=10, progress=False)
FLOATS = [c for c in COLUMNS if c not in ("solver", "result", "converged")]


@pytest.fixture(scope="module")
def table(cdra):
    return run_sweep(cdra, LEVELS, [5], trials=3, **CELL)


def _rows(table):
    """(noise_pos, trial) -> row index."""
    return {
        (float(p), int(t)): i
        for i, (p, t) in enumerate(zip(table["noise_pos"], table["trial"], strict=True))
    }


def _assert_same_trials(a, b):
    ra, rb = _rows(a), _rows(b)
    common = sorted(set(ra) & set(rb))
    assert common
    ia = [ra[k] for k in common]
    ib = [rb[k] for k in common]
    for c in COLUMNS:
        x, y = a[c][ia], b[c][ib]
        if c in FLOATS and x.dtype.kind == "f":
            np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-12, err_msg=c)
        else:
            np.testing.assert_array_equal(x, y, err_msg=c)


def test_table_layout(table):
    assert len(table) == 6
    assert list(table.columns) == list(COLUMNS)
    assert set(table["result"]) == {"successful"} and table["converged"].all()
    assert set(zip(table["noise_pos"], table["noise_rot"], strict=True)) == set(LEVELS)
    assert sorted(table["trial"].tolist()) == [0, 0, 1, 1, 2, 2]
    assert (table["m"] == 5).all() and (table["rank"] == 22).all()
    assert (table["solver"] == "weighted").all() and (table["seed"] == 7).all()
    # held-out against the truth excludes the measurement noise that dp_verify includes
    assert np.all(table["dp_heldout"] < table["dp_verify"] + 1.0)
    assert np.all(table["param_err"] >= table["param_err_v"])
    summary = table.summary("dp_heldout")
    assert [(s["noise_pos"], s["m"], s["n"]) for s in summary] == [(0.08, 5, 3), (0.2, 5, 3)]
    assert summary[0]["q10"] <= summary[0]["q50"] <= summary[0]["q90"]


def test_chunking_does_not_change_trials(cdra, table):
    # trials=2 puts (level 2, trial 0) at another place of the first chunk and (level 2,
    # trial 1) into the first chunk instead of the second; reversing the levels moves every
    # trial again, and the last chunk is padded differently.
    _assert_same_trials(table, run_sweep(cdra, LEVELS, [5], trials=2, **CELL))
    _assert_same_trials(table, run_sweep(cdra, LEVELS[::-1], [5], trials=3, **CELL))


@pytest.mark.slow
def test_trial_matches_direct_computation(cdra, table):
    """One row against simulate_trial + calibrate_paper run directly with trial_key."""
    noise = NoiseModel(*LEVELS[1])
    i = _rows(table)[(LEVELS[1][0], 2)]

    @jax.jit  # one compiled program, not one per eager primitive
    def direct(key):
        q, T, qv, Tv, X = simulate_trial(key, cdra, 5, noise=noise, m_verify=10)
        sol = calibrate_paper(cdra, q, T, noise, throw=False)
        model = tool_pose(cdra.with_frames(sol.frames), qv)
        dp_h, dR_h = deviation_metrics(tool_pose(apply_frame_errors(cdra, X), qv), model)
        dp_v, _ = deviation_metrics(Tv, model)
        return sol, dp_h, dR_h, dp_v

    sol, dp_h, dR_h, dp_v = direct(trial_key(7, 5, 2))
    assert int(sol.iterations) == table["iterations"][i]
    np.testing.assert_allclose(
        [sol.final_delta_p, sol.final_delta_R, dp_h, dR_h, dp_v],
        [table[c][i] for c in ("dp_fit", "dR_fit", "dp_heldout", "dR_heldout", "dp_verify")],
        rtol=1e-9,
    )


def test_every_pose_a_sweep_draws_has_tension_closure(cdra, table, monkeypatch):
    """The module states of every trial (calibration and held-out), recorded from inside the
    compiled, vmapped cell: all of them are poses with tension closure (the default sampler is
    simulation.sample_poses, not plain uniform states), and recording changes no result."""
    drawn = []

    def recording(key, arm, m, **kw):
        out = simulate_trial(key, arm, m, **kw)
        jax.debug.callback(lambda *q: drawn.extend(np.asarray(x) for x in q), out[0], out[2])
        return out

    monkeypatch.setattr(sweeps, "simulate_trial", recording)
    # trace the simulation again, with the recording, in a cache of its own: the original cache
    # (without the recording, traced for the fixture) comes back with monkeypatch's undo
    fresh = functools.lru_cache(maxsize=32)(sweeps._batched_simulation.__wrapped__)
    monkeypatch.setattr(sweeps, "_batched_simulation", fresh)
    recorded = run_sweep(cdra, LEVELS, [5], trials=3, **CELL)
    _assert_same_trials(table, recorded)
    q = np.concatenate([x.reshape(-1, cdra.dof) for x in drawn])
    # 2 levels x 3 trials (padded to 2 chunks of 4) x (5 calibration + 10 held-out) states
    assert len(q) >= 6 * 15
    closure = jax.jit(lambda q: arm_tension_closure(cdra, q, DEFAULT_MIN_MARGIN))  # one program
    assert np.asarray(closure(q)).all()


@pytest.mark.slow
def test_split_over_two_cpu_devices_matches(tmp_path):
    """A sweep of the paper solver split over 2 CPU devices, started by
    ``use_cpu_devices(2)`` in a fresh process, gives the rows of the same sweep on its first
    device alone (which reuses that device's compiled cells)."""
    out1, out2 = tmp_path / "one.csv", tmp_path / "two.csv"
    script = textwrap.dedent(
        f"""
        from cdra_jax.parallel import cpu_pool_threads, use_cpu_devices
        use_cpu_devices(2)  # before JAX starts
        import jax
        jax.config.update("jax_enable_x64", True)
        from cdra_jax import default_arm
        from cdra_jax.sweeps import run_sweep
        assert len(jax.devices()) == 2, jax.devices()
        assert cpu_pool_threads() > 2, cpu_pool_threads()
        kw = dict(trials=3, solvers=["paper"], seed=7, m_verify=10, progress=False)
        t = run_sweep(default_arm(), {LEVELS!r}, [5], chunk=4, **kw)
        assert t.meta["devices"].count("cpu") == 2, t.meta["devices"]
        t.save({str(out2)!r})
        # chunks of 2 on one device: the parts' shape, so device 0's programs are reused
        one = run_sweep(default_arm(), {LEVELS!r}, [5], chunk=2, devices=jax.devices()[:1], **kw)
        one.save({str(out1)!r})
        """
    )
    run_on_two_cpu_devices(script, forced=False)
    one, two = read_sweep(out1), read_sweep(out2)
    assert len(one) == len(two) == 2 * 3
    assert one.meta["devices"].count("cpu") == 1
    _assert_same_rows(one, two)


def _assert_same_rows(a, b):
    """Row by row (same order: m, solver, level, trial), floats to 1e-9."""
    assert len(a) == len(b)
    for c in COLUMNS:
        x, y = a[c], b[c]
        if c in FLOATS and x.dtype.kind == "f":
            np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-12, err_msg=c)
        else:
            np.testing.assert_array_equal(x, y, err_msg=c)


@pytest.mark.slow
def test_two_cpu_devices_with_a_small_pool_are_refused(tmp_path):
    """Two CPU devices and a pool of 2 threads would hang in batched LAPACK: a clear error."""
    script = textwrap.dedent(
        r"""
        import os
        os.environ["PJRT_NPROC"] = "2"
        import jax
        assert len(jax.devices()) == 2
        import pytest
        from cdra_jax import default_arm
        from cdra_jax.sweeps import run_sweep
        msg = "2 CPU devices with a thread pool of 2: .* would hang"
        with pytest.raises(ValueError, match=msg):
            run_sweep(default_arm(), [(0.08, 1e-3)], [5], trials=2, progress=False)
        from cdra_jax.parallel import use_cpu_devices
        with pytest.raises(RuntimeError, match=r"use_cpu_devices\(3\) must run before JAX starts"):
            use_cpu_devices(3)
        """
    )
    run_on_two_cpu_devices(script)


def test_csv_round_trip_and_errors(table, tmp_path):
    path = table.save(tmp_path / "t.csv")
    back = read_sweep(path)
    for c in COLUMNS:
        np.testing.assert_array_equal(back[c], table[c], err_msg=c)
    assert back.meta["seed"] == "7" and back.meta["arm"] == "cdra"
    with pytest.raises(FileExistsError, match="force"):
        table.save(path)
    table.save(path, force=True)
    lines = path.read_text().splitlines()
    header_at = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    cells = lines[header_at + 2].split(",")
    cells[COLUMNS.index("dp_fit")] = "abc"
    lines[header_at + 2] = ",".join(cells)
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=rf"line {header_at + 3}: column 'dp_fit'"):
        read_sweep(bad)
    for column, cell in (("dp_fit", "1_0"), ("m", "1_0"), ("m", "5.0")):  # float()/int() take 1_0
        cells[COLUMNS.index("dp_fit")] = "0.5"
        cells[COLUMNS.index(column)] = cell
        lines[header_at + 2] = ",".join(cells)
        bad.write_text("\n".join(lines) + "\n")
        with pytest.raises(ValueError, match=rf"line {header_at + 3}: column '{column}'"):
            read_sweep(bad)
    with pytest.raises(FileNotFoundError, match="folder .*nodir does not exist"):
        table.save(tmp_path / "nodir" / "t.csv")  # the API creates no folders either
    assert not (tmp_path / "nodir").exists()
    with pytest.raises(ValueError, match="unknown table format"):
        table.save(tmp_path / "t.xlsx")
    if importlib.util.find_spec("pyarrow") is None:
        with pytest.raises(ValueError, match="pyarrow"):
            table.save(tmp_path / "t.parquet")
    else:
        back = read_sweep(table.save(tmp_path / "t.parquet"))
        for c in COLUMNS:
            np.testing.assert_array_equal(back[c], table[c], err_msg=c)


def test_cli_and_plot(table, tmp_path, capsys):
    out, png = tmp_path / "r.csv", tmp_path / "r.png"
    argv = [
        "--noise-pos", "0.08,0.2", "--noise-rot", "0.001,0.002", "--poses", "5",
        "--solvers", "weighted", "--trials", "3", "--chunk", "4", "--seed", "7",
        "--verify", "10", "--out", str(out), "--plot", str(png), "--no-progress",
    ]  # fmt: skip
    assert cli_main(["sweep", *argv]) == 0
    printed = capsys.readouterr().out
    assert "6 trials" in printed and "weighted" in printed
    _assert_same_trials(table, read_sweep(out))
    assert png.stat().st_size > 1000
    assert cli_main(["sweep", *argv]) == 1
    assert "exists" in capsys.readouterr().err
    bad = [*argv[:2], "--noise-rot", "0.001,0.002,0.003", *argv[4:], "--force"]
    assert cli_main(["sweep", *bad]) == 1
    assert "rotation levels" in capsys.readouterr().err

    from cdra_jax.plots import plot_sweep

    ax = plot_sweep(table, "param_err")
    assert len(ax.get_lines()) == 2  # one line per noise level for the one solver
    assert "param_err" in ax.get_ylabel()


def test_bad_sweeps(cdra):
    with pytest.raises(ValueError, match="both are zero"):
        parse_noise_levels([0.0], [1e-3])
    with pytest.raises(ValueError, match="one rotation level for all"):
        parse_noise_levels([0.1, 0.2], [1e-3, 2e-3, 3e-3])
    assert parse_noise_levels([0.1, 0.2], [1e-3]) == [(0.1, 1e-3), (0.2, 1e-3)]
    with pytest.raises(ValueError, match="weighted"):
        run_sweep(cdra, [(0, 0)], [5], ["weighted"], trials=1)
    with pytest.raises(ValueError, match="minimum of 4"):
        run_sweep(cdra, LEVELS, [3], ["paper"], trials=1)
    with pytest.raises(ValueError, match="unknown solver"):
        run_sweep(cdra, LEVELS, [5], ["newton"], trials=1)


PAIRS = "noise_levels must be a non-empty list of \\(position_mm, rotation_rad\\) pairs"


@pytest.mark.parametrize(
    ("args", "kwargs", "expected"),
    [
        (([], [5], ["paper"], 2), {}, PAIRS),
        (([(0.08, 1e-3, 1)], [5], ["paper"], 2), {}, PAIRS + ".*entry 0 is \\(0.08, 0.001, 1\\)"),
        (([0.08], [5], ["paper"], 2), {}, PAIRS + ".*entry 0 is 0.08"),
        ((0.08, [5], ["paper"], 2), {}, PAIRS),
        (([(0.08, "1e-3")], [5], ["paper"], 2), {}, PAIRS),
        ((LEVELS, [5], ["paper"], 2.5), {}, "trials must be an integer, got 2.5"),
        ((LEVELS, [5], ["paper"], True), {}, "trials must be an integer, got True"),
        ((LEVELS, [4.7], ["paper"], 2), {}, "pose_counts must be integers, got 4.7"),
        ((LEVELS, [True], ["paper"], 2), {}, "pose_counts must be integers, got True"),
        ((LEVELS, [5], "paper", 2), {}, "solvers must be a list"),
        ((LEVELS, [5], ["paper"], 2), {"m_verify": 10.0}, "m_verify must be an integer"),
        ((LEVELS, [5], ["paper"], 2), {"chunk": 0}, "chunk must be >= 1, got 0"),
        ((LEVELS, [5], ["paper"], 2), {"seed": 2**64}, "seed must be an integer in"),
        ((LEVELS, [5], ["paper"], 2), {"d_v": float("nan")}, "d_v must be a non-negative number"),
        ((LEVELS, [5], ["paper"], 2), {"d_w": -0.1}, "d_w must be a non-negative number"),
    ],
)
def test_run_sweep_argument_errors_name_the_argument(cdra, args, kwargs, expected):
    with pytest.raises(ValueError, match=expected):
        run_sweep(cdra, *args, progress=False, **kwargs)


def test_run_sweep_accepts_numpy_integers_and_noise_models(cdra, table):
    levels = [NoiseModel(*LEVELS[0]), np.array(LEVELS[1])]
    kw = dict(CELL, seed=np.int64(7), chunk=np.int64(4))
    t = run_sweep(cdra, levels, np.array([5]), trials=np.int64(1), **kw)
    assert len(t) == 2 and t.meta["trials"] == "1" and t.meta["seed"] == "7"
    first = table.select(table["trial"] == 0)  # the same trials as the fixture's trial 0
    for c in ("noise_pos", "m", "dp_heldout", "param_err"):
        np.testing.assert_array_equal(t[c], first[c], err_msg=c)


SWEEP = ["sweep", "--noise-pos", "0.08", "--noise-rot", "0.001", "--poses", "5", "--no-progress"]


@pytest.mark.parametrize(
    ("extra", "expected"),
    [
        (["--trials", "1", "--out", "{tmp}/nodir/x.csv"], "--out {tmp}/nodir/x.csv: folder"),
        (["--trials", "1", "--out", "{tmp}/x.csv", "--plot", "{tmp}/nodir/p.png"], "--plot"),
        (["--trials", "1", "--out", "{tmp}/d.csv"], "d.csv: is a folder, expected a file"),
        (
            ["--trials", "1", "--out", "{tmp}/x.csv", "--d-v", "nan"],
            "--d-v must be a number in [0, 1e+06]",
        ),
        (
            ["--trials", "1", "--out", "{tmp}/x.csv", "--d-v", "-1"],
            "--d-v must be a number in [0, 1e+06]",
        ),
        (
            ["--trials", "1", "--out", "{tmp}/x.csv", "--d-w", "-0.1"],
            "--d-w must be a number in [0, 3.2]",
        ),
        (
            ["--trials", "1", "--out", "{tmp}/x.csv", "--d-w", "inf"],
            "--d-w must be a number in [0, 3.2]",
        ),
        (
            ["--trials", "0", "--out", "{tmp}/x.csv"],
            "--trials must be an integer in [1, 1000000000], got 0",
        ),
        (
            ["--trials", "1", "--verify", "0", "--out", "{tmp}/x.csv"],
            "--verify must be an integer in [1, 100000]",
        ),
        (
            ["--trials", "1", "--chunk", "0", "--out", "{tmp}/x.csv"],
            "--chunk must be an integer in [1, 65536]",
        ),
        (["--trials", "1", "--seed", "9" * 23, "--out", "{tmp}/x.csv"], "--seed must be an int"),
        (["--trials", "1", "--out", "{tmp}/x.csv", "--plot", "{tmp}/x.csv"], "--plot and --out"),
    ],
    ids=[
        "missing out folder",
        "missing plot folder",
        "out is a folder",
        "nan d-v",
        "negative d-v",
        "negative d-w",
        "infinite d-w",
        "zero trials",
        "zero verify",
        "zero chunk",
        "huge seed",
        "plot is out",
    ],
)
def test_sweep_cli_refuses_bad_arguments_before_any_work(tmp_path, capsys, extra, expected):
    from cdra_jax import cli

    (tmp_path / "d.csv").mkdir()
    argv = [*SWEEP, *(a.format(tmp=tmp_path) for a in extra)]
    assert cli.main(argv) == cli.EXIT_ERROR
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    assert expected.format(tmp=tmp_path) in err[0], err
    assert list(tmp_path.iterdir()) == [tmp_path / "d.csv"]  # no folder made, nothing written


def test_default_cpu_devices_pay_for_their_compilation():
    from cdra_jax.cli.sweep import TRIALS_PER_EXTRA_DEVICE, default_cpu_devices
    from cdra_jax.parallel import schedulable_cores

    assert default_cpu_devices(0) == default_cpu_devices(TRIALS_PER_EXTRA_DEVICE - 1) == 1
    assert default_cpu_devices(2 * TRIALS_PER_EXTRA_DEVICE) == min(2, schedulable_cores())
    assert default_cpu_devices(10**12) == schedulable_cores()


@pytest.mark.slow
def test_predictive_stop_keeps_the_heldout_errors(cdra, table):
    """The predictive stop (the default): one step fewer per trial at most a few, the held-out
    errors and the parameter errors within 1e-8 of the plain stop's."""
    fast = table
    plain = run_sweep(cdra, LEVELS, [5], trials=3, predictive_stop=False, **CELL)
    assert np.all(fast["iterations"] <= plain["iterations"])
    assert np.all(fast["converged"])
    for c in ("dp_heldout", "dR_heldout", "dp_verify", "param_err"):
        np.testing.assert_allclose(fast[c], plain[c], rtol=0, atol=1e-8, err_msg=c)
    np.testing.assert_array_equal(fast["rank"], plain["rank"])


def test_identifiable_projection_analytic_and_svd(cdra):
    """The parameter error's projection on the identifiable subspace: analytic (generic pose
    sets) and by SVD (sets that lose more: repeated poses), mixed in one batch, both equal to
    the SVD projection."""
    from cdra_jax.arm import chain, module_poses
    from cdra_jax.calibration import calibration_jacobian
    from cdra_jax.calibration.nullspace import structural_null_space

    def jac(qq):
        _, after = chain(cdra.frames, module_poses(cdra, qq))
        D = calibration_jacobian(after)
        return D.reshape(-1, D.shape[-1])

    @jax.jit  # one program each, not one per eager primitive
    def states(keys):
        return jax.vmap(lambda k: simulate_trial(k, cdra, 8)[0])(keys)

    @jax.jit
    def project(q, e):
        D = jax.vmap(jac)(q)
        Z = structural_null_space(cdra)
        return D, jax.vmap(sweeps._project_identifiable, (0, 0, None))(D, e, Z)

    drawn = np.asarray(states(jax.random.split(jax.random.PRNGKey(0), 4)))
    q = np.stack([np.tile(x[:2], (4, 1)) if i % 2 else x for i, x in enumerate(drawn)])
    e = np.random.default_rng(0).normal(size=(4, cdra.n_params)) * 0.01
    D, got = (np.asarray(a) for a in project(q, e))
    for i in range(4):
        _, s, Vt = np.linalg.svd(D[i])
        V = Vt[: int(np.sum(s > 1e-10 * s[0]))].T
        np.testing.assert_allclose(got[i], V @ (V.T @ e[i]), atol=1e-12)
    # the degenerate sets really lose more than the structural directions
    assert np.linalg.matrix_rank(D[1], tol=1e-8) < 22
