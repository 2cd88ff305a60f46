"""The workflow layer: the same functions behind the CLI and the notebooks, their result
objects (``to_dict``/``to_json``/``report``/``plot``/``save``), ``validate``, and the package's
layering (no import cycles)."""

from __future__ import annotations

import ast
import io
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from _subprocess import checkout_env
from matplotlib.figure import Figure

import cdra_jax
from cdra_jax import cli, sweeps, workflows
from cdra_jax.io import load_result

NOISE = workflows.noise_model(0.05, 5e-4)
PACKAGE = Path(cdra_jax.__file__).parent


@pytest.fixture(scope="module")
def truth_sim():
    """8 noisy poses of one simulated arm to fit, and 10 more of the same arm held out."""
    fit = workflows.simulate(None, 8, seed=1, noise=NOISE)
    held_out = workflows.simulate(None, 10, seed=2, errors=fit.errors, noise=NOISE)
    return fit, held_out


@pytest.fixture(scope="module")
def calibration(truth_sim):
    fit, _ = truth_sim
    return workflows.calibrate(None, fit.measurements, noise=NOISE)


def test_simulate_result_object(truth_sim, tmp_path):
    fit, held_out = truth_sim
    np.testing.assert_array_equal(held_out.errors, fit.errors)  # same arm, other poses
    assert fit.measurements.m == 8 and "preset frame errors" in fit.report()
    truth = json.loads(fit.to_json())
    assert set(truth["frames"]) == set(fit.arm.frame_names)
    assert isinstance(fit.plot(), Figure)
    paths = fit.save(tmp_path / "m.csv", tmp_path / "t.json")
    assert [p.name for p in paths] == ["t.json", "m.csv"]
    assert json.loads((tmp_path / "t.json").read_text())["measurements"] == str(tmp_path / "m.csv")


def test_calibrate_result_object(calibration, tmp_path):
    r = calibration
    assert r.converged and r.result["solver"] == "weighted"
    assert r.result["identifiability"]["rank"] == 22
    assert "uncertainty" in r.result and "identified frame errors" in r.report()
    assert json.loads(r.to_json())["n_poses"] == 8
    assert load_result(r.save(tmp_path / "r.json"))["frames"] == r.result["frames"]
    assert isinstance(r.plot(), Figure)
    # the calibrated arm is the nominal one with the identified errors applied (Eq. 19)
    assert r.calibrated_arm.frame_names == r.arm.frame_names


def test_calibrate_solver_names_are_those_of_sweep(truth_sim):
    fit, _ = truth_sim
    assert workflows.SOLVERS == ("auto", "paper", "weighted", "lm")
    # the batched sweeps run the paper's solvers, by the same names
    assert set(sweeps.SOLVERS) == set(workflows.SOLVERS) - {"auto"}
    assert workflows.calibrate(None, fit.measurements).result["solver"] == "auto"
    # explicit "paper" with a noise model: the unweighted solve, the noise for the uncertainty
    r = workflows.calibrate(None, fit.measurements, solver="paper", noise=NOISE)
    assert r.result["solver"] == "paper" and "uncertainty" in r.result
    with pytest.raises(ValueError, match="weighted whitens"):
        workflows.calibrate(None, fit.measurements, solver="weighted")
    with pytest.raises(ValueError, match="paper, weighted, lm"):
        workflows.calibrate(None, fit.measurements, solver="gauss")


def test_validate_reports_the_gain_on_held_out_poses(truth_sim, calibration, tmp_path):
    _, held_out = truth_sim
    v = workflows.validate(None, held_out.measurements, result=calibration.to_dict())
    d = v.to_dict()
    assert d["position_error_mm"]["n"] == 10 and len(d["rows"]) == 10
    # the calibrated model predicts held-out poses near the noise; the nominal one is far off
    assert d["position_error_mm"]["mean"] < 0.5 < 10 < d["nominal"]["position_error_mm"]["mean"]
    assert d["rotation_error_rad"]["max"] < 0.01
    row = d["rows"][0]
    assert set(row) == {
        "pose",
        "position_mm",
        "rotation_rad",
        "nominal_position_mm",
        "nominal_rotation_rad",
    }
    e = v.position_error_mm
    assert d["position_error_mm"]["rms"] == pytest.approx(float(np.sqrt(np.mean(e * e))))
    assert "nominal position" in v.report() and isinstance(v.plot(), Figure)
    assert json.loads(v.save(tmp_path / "v.json").read_text()) == json.loads(v.to_json())
    # without a result: the model itself, no nominal block
    plain = workflows.validate(None, held_out.measurements).to_dict()
    assert "nominal" not in plain
    assert plain["position_error_mm"] == d["nominal"]["position_error_mm"]


def test_validate_cli_matches_the_function(truth_sim, calibration, tmp_path, capsys):
    _, held_out = truth_sim
    data, result = tmp_path / "held_out.csv", tmp_path / "r.json"
    held_out.save(data)
    calibration.save(result)
    out, png = tmp_path / "v.json", tmp_path / "v.png"
    argv = ["validate", "--data", data, "--result", result, "--out", out, "--plot", png]
    assert cli.main([str(a) for a in argv]) == 0
    printed = capsys.readouterr().out
    assert "position [mm]" in printed and f"wrote {out}" in printed
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    from_cli = json.loads(out.read_text())
    direct = workflows.validate(None, data, result=result).to_dict()
    assert from_cli["position_error_mm"] == direct["position_error_mm"]
    # an existing output is refused before any work, and the file is untouched
    before = out.read_text()
    assert cli.main([str(a) for a in argv]) == cli.EXIT_ERROR
    assert "exists" in capsys.readouterr().err and out.read_text() == before


def test_validate_refuses_a_plan_without_measured_poses(tmp_path):
    plan = workflows.plan_poses(None, 4, pool=40, seed=0)
    plan.save(tmp_path / "plan.csv")
    with pytest.raises(ValueError, match="plan.csv, line 7 .* missing column measured.x"):
        workflows.validate(None, tmp_path / "plan.csv")
    assert "selected 4 of 40" in plan.report() and json.loads(plan.to_json())["count"] == 4
    assert isinstance(plan.plot(), Figure)


def test_calibrate_cli_writes_the_figure(truth_sim, tmp_path, capsys):
    fit, _ = truth_sim
    fit.save(tmp_path / "m.csv")
    argv = ["calibrate", "--data", tmp_path / "m.csv", "--out", tmp_path / "r.json"]
    argv += ["--solver", "lm", "--plot", tmp_path / "r.png"]
    assert cli.main([str(a) for a in argv]) == 0
    assert "solver: lm (Levenberg-Marquardt)" in capsys.readouterr().out
    assert (tmp_path / "r.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_sweep_prints_progress_lines_when_stderr_is_not_a_terminal(monkeypatch):
    err = io.StringIO()
    monkeypatch.setattr(sys, "stderr", err)
    run = workflows.sweep(
        None, [0.05], [5e-4], [5], solvers=["weighted"], trials=2, chunk=2, verify=4
    )
    lines = err.getvalue().strip().splitlines()
    assert lines and lines[-1].startswith("sweep: 2/2 trials (100 %)")
    assert "weighted" in run.report() and run.to_dict()["summary"][0]["m"] == 5
    assert isinstance(run.plot(), Figure)


def test_every_subcommand_is_a_module_with_register_and_run():
    names = [m.__name__.rsplit(".", 1)[-1] for m in cli.SUBCOMMANDS]
    assert names[:7] == [
        "demo",
        "simulate",
        "calibrate",
        "validate",
        "diagnose",
        "sweep",
        "plan_poses",
    ]
    assert {"import_model", "export_model"} <= set(names)
    for m in cli.SUBCOMMANDS:
        assert callable(m.register) and callable(m.run)
    help_text = cli.build_parser().format_help()
    for command in ("demo", "calibrate", "validate", "diagnose", "sweep", "plan-poses"):
        assert command in help_text


def _imports(path: Path, module: str, modules: set[str]) -> set[str]:
    """Modules of the package that ``module`` imports anywhere (functions included)."""
    is_pkg = path.name == "__init__.py"
    base = module.split(".") if is_pkg else module.split(".")[:-1]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name in modules}
        elif isinstance(node, ast.ImportFrom):
            prefix = base[: len(base) - node.level + 1] if node.level else []
            target = ".".join(prefix + ([node.module] if node.module else []))
            for a in node.names:
                sub = f"{target}.{a.name}"
                out.add(sub if sub in modules else target)
    return (out & modules) - {module}


def test_no_import_cycles_in_the_package():
    """Imports only go down: the module graph (function-level imports included; ``from . import
    x`` counts as importing the submodule x) has no cycle."""
    files = {}
    for p in PACKAGE.rglob("*.py"):
        parts = list(p.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        files[".".join(parts)] = p
    modules = set(files)
    graph = {m: _imports(p, m, modules) for m, p in files.items()}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                cycle = stack[stack.index(n) :] + [n]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if n not in state:
                visit(n)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)
    assert "cdra_jax.workflows.calibrate" in graph  # the walk saw the package


def test_layers_only_import_downwards():
    """The lower layers never import the workflows, the plots' callers or the CLI."""
    upper = ("cdra_jax.cli", "cdra_jax.workflows")
    for p in PACKAGE.rglob("*.py"):
        rel = ".".join(p.relative_to(PACKAGE.parent).with_suffix("").parts)
        if rel.startswith(upper) or rel == "cdra_jax.__init__":
            continue
        text = p.read_text()
        for u in ("cli", "workflows"):
            assert f"from ..{u}" not in text and f"from .{u} " not in text, (rel, u)
            assert f"cdra_jax.{u} import" not in text, (rel, u)


def test_an_interrupted_sweep_resumes_from_its_finished_chunks(tmp_path, monkeypatch):
    from cdra_jax import sweeps

    kwargs = dict(solvers=["paper"], trials=6, chunk=2, verify=3, progress=False)
    whole = workflows.sweep(None, [0.05], [5e-4], [5], **kwargs).table
    ck = tmp_path / "ck"
    calls = []
    real = sweeps.split_over_devices

    per_chunk = 2  # a chunk is simulated, then calibrated: two calls

    def interrupted(*args, **kw):
        if len(calls) == 2 * per_chunk:
            raise KeyboardInterrupt  # Ctrl-C after two finished chunks
        calls.append(1)
        return real(*args, **kw)

    monkeypatch.setattr(sweeps, "split_over_devices", interrupted)
    with pytest.raises(KeyboardInterrupt):
        workflows.sweep(None, [0.05], [5e-4], [5], checkpoint=ck, **kwargs)
    assert len(list(ck.glob("*.npz"))) == 2 and not list(ck.glob(".*.tmp"))
    calls.clear()
    monkeypatch.setattr(
        sweeps, "split_over_devices", lambda *a, **k: calls.append(1) or real(*a, **k)
    )
    resumed = workflows.sweep(None, [0.05], [5e-4], [5], checkpoint=ck, **kwargs).table
    assert len(calls) == per_chunk  # only the third chunk is computed again
    for c in whole.columns:
        np.testing.assert_array_equal(resumed[c], whole[c], err_msg=c)
    with pytest.raises(ValueError, match="other arguments"):
        workflows.sweep(None, [0.05], [5e-4], [5], checkpoint=ck, **{**kwargs, "trials": 8})
    sweeps.remove_checkpoint(ck)
    assert not ck.exists()


def test_a_fit_worse_than_nominal_is_marked_untrusted(tmp_path, capsys):
    # The nominal model is the true arm and the positions are exact; the orientations carry
    # 0.2 rad of noise. The unweighted fit (mm and rad summed as they come) trades position for
    # orientation: its model predicts the measured points worse than the nominal one.
    sim = workflows.simulate(None, 8, seed=3, errors="zero", noise=workflows.noise_model(1e-9, 0.2))
    run = workflows.calibrate(None, sim.measurements, solver="paper")
    trust = run.result["trust"]
    assert run.trusted is False and run.result["trusted"] is False
    assert trust["calibrated_position_mm"] > trust["nominal_position_mm"]
    assert "worse than the nominal" in trust["reason"]
    data, out = tmp_path / "d.csv", tmp_path / "r.json"
    sim.save(data)
    argv = ["calibrate", "--data", data, "--out", out, "--solver", "paper"]
    assert cli.main([str(a) for a in argv]) == cli.EXIT_UNTRUSTED
    err = capsys.readouterr().err
    assert "error: untrusted result: the calibrated model is worse than the nominal one" in err
    assert json.loads(out.read_text())["trusted"] is False  # still written, marked


def test_model_out_and_compare(truth_sim, calibration, tmp_path, capsys):
    _, held_out = truth_sim
    cal = calibration.save_model(tmp_path / "cal.toml")
    assert calibration.trusted and calibration.result["trusted"] is True
    from_model = workflows.validate(cal, held_out.measurements).to_dict()
    from_result = workflows.validate(None, held_out.measurements, result=calibration.to_dict())
    # the written model predicts exactly what the result applied to the nominal model does
    assert from_model["position_error_mm"] == from_result.to_dict()["position_error_mm"]
    both = workflows.validate(cal, held_out.measurements, compare=cdra_jax.default_arm())
    d = both.to_dict()
    assert (
        d["compare"]["position_error_mm"] == from_result.to_dict()["nominal"]["position_error_mm"]
    )
    assert "compare_position_mm" in d["rows"][0] and "compare position" in both.report()
    with pytest.raises(ValueError, match="either result"):
        workflows.validate(cal, held_out.measurements, result=calibration.to_dict(), compare=cal)
    data = tmp_path / "h.csv"
    held_out.save(data)
    argv = ["validate", "--model", cal, "--data", data, "--compare", cal]
    assert cli.main([str(a) for a in argv]) == 0
    assert "compared with:" in capsys.readouterr().out


def test_the_cli_keeps_compiled_programs_between_runs(tmp_path):
    import subprocess

    cache = tmp_path / "xla"
    env = checkout_env("CDRA_JAX_NO_CACHE", CDRA_JAX_CACHE_DIR=str(cache))
    argv = [sys.executable, "-m", "cdra_jax.cli", "simulate", "--poses", "4", "--out"]
    subprocess.run([*argv, str(tmp_path / "a.csv")], env=env, check=True, capture_output=True)
    entries = sorted(p.name for p in cache.iterdir())
    assert entries  # the compiled simulation is on disk
    off = [sys.executable, "-m", "cdra_jax.cli", "--no-cache", *argv[3:]]
    subprocess.run([*off, str(tmp_path / "b.csv")], env=env, check=True, capture_output=True)
    assert sorted(p.name for p in cache.iterdir()) == entries  # --no-cache: nothing added
    assert (tmp_path / "a.csv").read_text() == (tmp_path / "b.csv").read_text()
