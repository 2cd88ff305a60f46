"""The hand-written baselines of benchmarks/throughput.py are correct (independent oracles).

The NumPy maps of benchmarks/baselines.py (the paper's Eqs. 25-27 written per pose) against
cdra_jax.lie, and the NumPy and SciPy calibrations against the JAX paper solver on the same
simulated trials; then a small end-to-end run of the benchmark script (slow).
"""

from __future__ import annotations

import importlib.util
import json
import pathlib

import equinox as eqx
import jax
import numpy as np
import pytest

from cdra_jax import calibrate_paper, lie, simulation

BENCH = pathlib.Path(__file__).resolve().parent.parent / "benchmarks"


def _load(name):
    spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


baselines = _load("baselines")


def test_numpy_maps_are_the_lie_maps():
    rng = np.random.default_rng(0)
    for scale in (1.0, 0.3, 1e-4, 1e-9, 0.0):
        xi = rng.normal(size=6) * [50, 50, 50, scale, scale, scale]
        T = baselines.se3_exp(xi)
        np.testing.assert_allclose(T, lie.se3_exp(xi), rtol=1e-12, atol=1e-13)
        np.testing.assert_allclose(baselines.se3_log(T), xi, rtol=0, atol=1e-9)
        np.testing.assert_allclose(baselines.adjoint(T), lie.adjoint(T), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(baselines.inverse(T) @ T, np.eye(4), atol=1e-12)
        stack = np.stack([T, baselines.se3_exp(-xi)])
        np.testing.assert_allclose(
            baselines._se3_log_b(stack), lie.se3_log(stack), rtol=0, atol=1e-9
        )


@eqx.filter_jit
def _trial(key, arm):
    return simulation.simulate_trial(key, arm, 15)


@eqx.filter_jit
def _paper(arm, q, T):
    # The baselines stop as the paper does (step norm below tol), without the prediction.
    return calibrate_paper(arm, q, T, throw=False, predictive_stop=False)


def test_baseline_calibrations_agree_with_the_paper_solver(cdra):
    frames0 = np.asarray(cdra.frames)
    kinds = baselines.arm_kinds(cdra)
    for seed in (0, 1):
        q, T, _, _, X = _trial(jax.random.PRNGKey(seed), cdra)
        q, T = np.asarray(q), np.asarray(T)
        ref = jax.tree.map(np.asarray, _paper(cdra, q, T))
        poses = baselines.module_poses(kinds, q)
        for solve in (
            baselines.calibrate_numpy,
            baselines.calibrate_numpy_vectorized,
            baselines.calibrate_scipy,
        ):
            out = solve(frames0, poses, T)
            assert out["converged"], solve.__name__
            # Base and tool errors (the identifiable frames): preset and JAX solver.
            np.testing.assert_allclose(
                out["errors"][[0, 3]], np.asarray(X).reshape(4, 6)[[0, 3]], atol=1e-8
            )
            np.testing.assert_allclose(out["errors"][[0, 3]], ref.errors[[0, 3]], atol=1e-8)
            if solve is not baselines.calibrate_scipy:  # the same iteration as the paper solver
                assert out["iterations"] == int(ref.iterations)
                assert out["rank"] == int(ref.rank) == 22
                np.testing.assert_allclose(out["errors"], ref.errors, atol=1e-8)
                np.testing.assert_allclose(
                    out["delta_p"], ref.delta_p[: out["iterations"] + 1], rtol=1e-6, atol=1e-9
                )


@pytest.mark.slow
def test_throughput_script_runs_and_reports_json(capsys):
    throughput = _load("throughput")
    args = ["--trials", "6", "--baseline-trials", "2", "--repeats", "1", "--json"]
    # LM: its own tests. --xla-defaults: the paper solver also compiled with plain jax.jit.
    throughput.main(args + ["--solvers", "paper", "numpy", "scipy", "--xla-defaults"])
    last = capsys.readouterr().out.strip().splitlines()[-1]
    report = json.loads(last)
    for key in (
        "ratio_paper_vs_numpy",
        "ratio_scipy_vs_numpy",
        "compile_s_paper",
        "ratio_paper_xla_defaults_vs_numpy",
        "compile_s_paper_xla_defaults",
    ):
        assert np.isfinite(report[key]) and report[key] > 0, key
    for name in ("paper", "paper_xla_defaults", "numpy", "scipy"):
        assert report[f"maxdiff_vs_preset_{name}"] < 1e-8, name
        assert report[f"converged_{name}"] == 1.0, name
    assert report["maxdiff_vs_paper_paper_xla_defaults"] < 1e-9
    assert "trials_per_s_lm" not in report


@pytest.mark.slow
def test_throughput_scaling_mode_generates_in_blocks_and_reports(cdra, capsys, monkeypatch):
    """The block-wise problem generator (used for N = 10^6) gives the trials of one big batch,
    and the scaling sweep reports a rate and a compile time per row."""
    throughput = _load("throughput")
    # The shapes of the script test's problems and solver (N = 6, m = 15): the programs come
    # from the compilation cache.
    whole = throughput.make_problems(cdra, 6, 15, None, seed=3)
    monkeypatch.setattr(throughput, "_GEN_BLOCK", 4)  # blocks of 4, the last one padded
    blocks = throughput.make_problems(cdra, 6, 15, None, seed=3)
    for a, b in zip(whole, blocks, strict=True):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    # The sweep asks twice for these very problems (its N row and its m row): handed the ones
    # generated above (make_problems itself is what the lines above test), so that the run
    # traces no simulator again.
    generate = throughput.make_problems
    generated = {(6, 15, None, 3): whole}

    def once(arm, n_trials, m, noise, seed=0):
        key = (n_trials, m, noise, seed)
        if key not in generated:
            generated[key] = generate(arm, n_trials, m, noise, seed)
        return generated[key]

    monkeypatch.setattr(throughput, "make_problems", once)
    args = ["--scaling", "--solvers", "paper", "--repeats", "1", "--json", "--seed", "3"]
    args += ["--scaling-trials", "6", "--scaling-poses", "15", "--scaling-n", "6"]
    throughput.main(args)
    assert list(generated) == [(6, 15, None, 3)]  # the sweep's problems: the ones above
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    (row_n,), (row_m,) = report["by_trials"], report["by_poses"]
    assert (row_n["N"], row_m["m"]) == (6, 15)
    for row in (row_n, row_m):
        assert row["paper"] > 0 and row["paper_compile_s"] > 0 and row["paper_repeats"] == 1
    assert len(report["machine"]["load_average"]) == 3


def test_profile_split_takes_each_thunk_exclusive_of_the_thunks_inside_it(tmp_path):
    """benchmarks/profile_split.py: an event's exclusive time is its duration less that of the
    events nested in it on the same thread, and every thunk falls in one group."""
    import gzip

    split = _load("profile_split")

    def event(name, ts, dur, tid=1):
        return {"ph": "X", "name": name, "ts": ts, "dur": dur, "pid": 1, "tid": tid}

    events = [
        event("cond.3", 0, 100),
        event("ynn_fusion.2", 10, 30),
        event("ThunkExecutor::Execute", 50, 40),
        event("cholesky.9", 55, 20),
        event("copy.5", 0, 70, tid=2),  # another thread: nothing nested
        event("multiply_add_fusion.1", 200, 5),
        {"ph": "M", "name": "thread_name", "pid": 1, "tid": 1},  # metadata: ignored
    ]
    trace = tmp_path / "perfetto_trace.json.gz"
    with gzip.open(trace, "wt") as f:
        json.dump({"traceEvents": events}, f)
    times = split.exclusive_times(trace)
    assert times == {
        "cond.3": 30,
        "ynn_fusion.2": 30,
        "ThunkExecutor::Execute": 20,
        "cholesky.9": 20,
        "copy.5": 70,
        "multiply_add_fusion.1": 5,
    }
    groups = {name: split._group(name) for name in times}
    assert groups == {
        "cond.3": "control flow",
        "ynn_fusion.2": "matrix products",
        "ThunkExecutor::Execute": "dispatch",
        "cholesky.9": "LAPACK",
        "copy.5": "copies",
        "multiply_add_fusion.1": "element-wise",
    }
    assert split._group("$api.py:2479 block_until_ready") is None
    assert split._group("ThunkExecutor::Execute (wait for completion)") is None
    assert set(groups.values()) == set(split.GROUPS)


def test_compile_split_counts_ir_lines_and_finds_the_package_frame(tmp_path):
    """benchmarks/compile_split.py: the lines of each function of an LLVM IR file, and the
    innermost frame inside ``cdra_jax`` of an HLO instruction (frames outside it skipped;
    instructions without a frame left out)."""
    split = _load("compile_split")
    ir = tmp_path / "m.ir-with-opt.ll"
    ir.write_text(
        "; header\ndefine void @fusion.1(ptr %a) {\n  %x = load\n  ret void\n}\n"
        "declare void @ext()\ndefine internal void @dot_kernel() {\n  ret void\n}\n"
    )
    assert split._functions(str(ir)) == {"fusion.1": 2, "dot_kernel": 1}
    hlo = "\n".join(
        [
            "HloModule jit_f",
            "ENTRY %main {",
            '  %fusion.1 = f64[3] fusion(%p), metadata={op_name="x" stack_frame_id=2}',
            "  %dot = f64[3] dot(%p, %q)",
            "}",
            "FileNames",
            '1 "/site-packages/jax/_src/numpy/ufuncs.py"',
            '2 "/repo/cdra_jax/lie.py"',
            "FunctionNames",
            '1 "multiply"',
            '2 "so3_exp"',
            "FileLocations",
            "1 file_name_id=2 function_name_id=2 line=10",
            "2 file_name_id=1 function_name_id=1 line=99",
            "StackFrames",
            "1 file_location_id=1 parent_frame_id=1",
            "2 file_location_id=2 parent_frame_id=1",
        ]
    )
    assert split._sources(hlo) == {"fusion.1": "lie.py:so3_exp"}
    lines, kernels = split._by_source(
        {"fusion.1": 2, "fusion.2": 5, "dot_kernel": 1}, {"fusion.1": "lie.py:so3_exp"}
    )
    assert lines == {"lie.py:so3_exp": 2, "(made by XLA)": 6}
    assert kernels == {"lie.py:so3_exp": 1, "(made by XLA)": 2}


def test_compile_split_reads_valgrinds_instruction_count():
    """benchmarks/compile_split.py --instructions: the count of cachegrind's report (with its
    thousands separators), and a clear error where the report has none."""
    split = _load("compile_split")
    report = "==12== Cachegrind, a cache profiler\n==12== \n==12== I   refs:      22,035,659,986\n"
    assert split._instructions(report) == 22_035_659_986
    with pytest.raises(RuntimeError, match="no instruction count"):
        split._instructions("valgrind: command not found")
