"""Monte-Carlo throughput of the calibration solvers on the paper's problem (Section V).

The problem: the default CDRA (24 parameters), ``m`` = 15 calibration poses, preset frame errors
uniform in +-1 mm / +-0.05 rad per component (``d_v``, ``d_w`` of Section V), noise-free
measurements unless ``--noise`` is given. All problems are generated once with
:func:`cdra_jax.simulation.simulate_trial` under ``vmap`` and every solver gets the same ones:

(a) ``paper``: ``cdra_jax.jit(jax.vmap(calibrate_paper(..., throw=False)))`` over the batch
    (``jax.jit`` with the package's compile options, :mod:`cdra_jax.compilation`;
    ``--xla-defaults`` adds rows compiled with plain ``jax.jit``); ``weighted``: the same with
    the noise model of ``--noise-pos-mm`` / ``--noise-rot-rad`` (whitened residual);
(b) ``lm``: the same with :func:`cdra_jax.calibrate_lm` (Levenberg-Marquardt);
``lm_optimistix``: :func:`cdra_jax.calibrate_lm_optimistix` (the same minimisation through
optimistix, the reference);
    ``--singular-values`` adds rows ``*_sv`` with ``singular_values=True`` (the rank and
    singular values of the Jacobian at the solution, a QR and an SVD per trial, as the command
    line asks for them); the solvers' defaults skip them and, for paper and weighted, stop
    predictively (``predictive_stop=True``);
(c) ``numpy``: a plain NumPy loop over trials (``benchmarks/baselines.py``: Rodrigues exp,
    Eq. 27 log, Eq. 25 adjoint, per-pose stacking, ``np.linalg.lstsq``), the reference of
    the ratios; ``numpy_vec`` is the same algorithm batched over the poses of a trial;
(d) ``scipy``: ``scipy.optimize.least_squares`` per trial on the stacked Eq. 7 residual.

JAX solvers are timed on the whole batch: the first call (trace + compile + run) is reported
apart from the steady state (median of ``--repeats`` calls, the solvers called in turn, round
after round, after all of them have compiled); the compile time alone is measured with
``jit(...).lower(...).compile()``. The baselines are timed on a subset
(``--baseline-trials``, default ``min(N, 200)``) split into 5 chunks; the per-trial time is the
median over chunks. All of this happens in one process, side by side, so that a shared machine
slows all of them alike. The sanity column is the largest difference of the recovered ``base``
and ``tool`` error twists (the identifiable frames) from those of the paper solver, and from the
preset errors.

Usage::

    python benchmarks/throughput.py --trials 10000            # the table
    python benchmarks/throughput.py --trials 10000 --json     # ... and JSON on the last line
    python benchmarks/throughput.py --scaling                 # trials/s against N and m

The script enables float64 (``--dtype float32`` to compare) and runs on whatever
``jax.devices()`` gives (CPU here; a GPU where jax finds one).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import baselines  # noqa: E402

from cdra_jax import (  # noqa: E402
    NoiseModel,
    calibrate_lm,
    calibrate_lm_optimistix,
    calibrate_paper,
    default_arm,
)
from cdra_jax.calibration import levenberg_marquardt  # noqa: E402
from cdra_jax.compilation import jit as package_jit  # noqa: E402
from cdra_jax.parallel import split_over_devices, use_cpu_devices  # noqa: E402
from cdra_jax.simulation import simulate_trial  # noqa: E402

SOLVERS = ("paper", "weighted", "lm", "lm_optimistix", "numpy", "numpy_vec", "scipy")
_JAX_SOLVERS = ("paper", "weighted", "lm", "lm_optimistix")


def _base(name: str) -> str:
    """The solver of a result row (``paper_sv_x2`` -> ``paper``, ``numpy_vec`` -> itself)."""
    return max((s for s in SOLVERS if name == s or name.startswith(s + "_")), key=len)


_N_CHUNKS = 5
_GEN_BLOCK = 100_000


# --------------------------------------------------------------------------- problems
def make_problems(arm, n_trials: int, m: int, noise: NoiseModel | None, seed: int = 0):
    """``(q (N, m, dof), measured (N, m, 4, 4), preset errors (N, K+1, 6))`` as NumPy arrays.

    Generated in blocks of at most ``_GEN_BLOCK`` trials (one compiled simulator), so that the
    simulator's intermediates stay small for N = 10^6.
    """
    keys = jax.random.split(jax.random.PRNGKey(seed), n_trials)
    sim = jax.jit(
        jax.vmap(lambda k: simulate_trial(k, arm, m, d_v=1.0, d_w=0.05, noise=noise, m_verify=1))
    )
    block = min(n_trials, _GEN_BLOCK)
    parts = []
    for a in range(0, n_trials, block):
        kb = keys[a : a + block]
        pad = block - kb.shape[0]
        if pad:  # the last block, padded to the compiled size
            kb = jnp.concatenate([kb, jnp.broadcast_to(kb[:1], (pad,) + kb.shape[1:])])
        q, T, _, _, X = sim(kb)
        parts.append(tuple(np.asarray(x)[: block - pad] for x in (q, T, X)))
    q, T, X = (np.concatenate(p) for p in zip(*parts, strict=True))
    k1 = len(arm.frame_names)
    return q, T, X.reshape(n_trials, k1, 6)


# --------------------------------------------------------------------------- timing
def _block(x):
    return jax.block_until_ready(x)


def time_jax(
    solve: Callable,
    q: np.ndarray,
    T: np.ndarray,
    repeats: int,
    first_call: bool = True,
    jit: Callable = package_jit,
) -> dict:
    """Compile time, first-call time and steady-state median of a jitted batched solver.

    ``first_call=False`` skips the separate first call (trace + compile + run), whose time is
    then reported as NaN: the scaling sweep does so for its large batches. ``jit``: the
    package's (:func:`cdra_jax.compilation.jit`, its compile options) or ``jax.jit`` (XLA's
    defaults, rows ``*_xla_defaults``).
    """
    qj, Tj = jnp.asarray(q), jnp.asarray(T)
    _block((qj, Tj))
    fn = jit(jax.vmap(solve))
    t0 = time.perf_counter()
    compiled = fn.lower(qj, Tj).compile()
    compile_s = time.perf_counter() - t0
    first_s = float("nan")
    if first_call:
        fresh = jit(jax.vmap(solve))  # a separate jit: its first call traces and compiles
        t0 = time.perf_counter()
        _block(fresh(qj, Tj))
        first_s = time.perf_counter() - t0
    return _steady(lambda: _block(compiled(qj, Tj)), q.shape[0], repeats, compile_s, first_s)


def _steady(call: Callable, n: int, repeats: int, compile_s: float, first_s: float) -> dict:
    """Median wall time of ``repeats`` calls of ``call()`` (a batch of ``n`` trials), as the
    result dict of :func:`time_jax` (``solution``: the last call's result). ``repeats=0``: no
    call; the dict holds ``call`` for :func:`steady_interleaved`."""
    prepared = dict(compile_s=compile_s, first_call_s=first_s, call=call)
    if repeats:
        steady_interleaved({"one": prepared}, n, repeats)
    return prepared


def steady_interleaved(prepared: dict[str, dict], n: int, repeats: int) -> None:
    """The steady state of several prepared solvers (:func:`_steady` with ``repeats=0``),
    measured side by side: ``repeats`` rounds, each calling every solver once in turn, so that
    a change of the machine's load during the run touches all of them alike. Each dict gets the
    median wall time of its calls (``steady_s``, ``trials_per_s``), the median CPU time per
    trial and its last ``solution``; ``call`` is removed."""
    times: dict[str, list[float]] = {k: [] for k in prepared}
    cpu: dict[str, list[float]] = {k: [] for k in prepared}
    for _ in range(repeats):
        for name, p in prepared.items():
            t0, c0 = time.perf_counter(), time.process_time()
            p["solution"] = p["call"]()
            times[name].append(time.perf_counter() - t0)
            cpu[name].append(time.process_time() - c0)
    for name, p in prepared.items():
        steady = statistics.median(times[name])
        del p["call"]
        p.update(
            steady_s=steady,
            trials_per_s=n / steady,
            # CPU time of this process (all its threads) per trial: on a machine shared with
            # other jobs a steadier measure of the work than the wall time.
            cpu_us_per_trial=1e6 * statistics.median(cpu[name]) / n,
            all_s=times[name],
        )


def time_jax_split(
    solve: Callable, q: np.ndarray, T: np.ndarray, repeats: int, devices: list
) -> dict:
    """As :func:`time_jax`, with the batch split into one part per device
    (:func:`cdra_jax.parallel.split_over_devices`: the parts run at the same time, each device
    with its own compiled program). ``compile_s`` is the first call (it compiles for every
    device); the steady state includes moving each part to its device and the results back."""
    fn = package_jit(jax.vmap(solve))
    t0 = time.perf_counter()
    split_over_devices(fn, (q, T), devices)
    first_s = time.perf_counter() - t0
    return _steady(
        lambda: split_over_devices(fn, (q, T), devices), q.shape[0], repeats, first_s, first_s
    )


def time_jax_calls(solve: Callable, q: np.ndarray, T: np.ndarray, per_call: int) -> dict:
    """trials/s of a batch too large for one call: calls of ``per_call`` trials in sequence.

    One program is compiled for ``per_call`` trials (the last call is padded to that size with
    copies of its first trial; the padding's work is not counted) and the whole batch runs once,
    call after call, as :mod:`cdra_jax.sweeps` runs large sweeps. The inputs of each call are
    moved to the device before its clock starts, and its outputs are discarded after it.
    """
    n = q.shape[0]
    fn = package_jit(jax.vmap(solve))
    t0 = time.perf_counter()
    compiled = fn.lower(jnp.asarray(q[:per_call]), jnp.asarray(T[:per_call])).compile()
    compile_s = time.perf_counter() - t0
    total = 0.0
    converged = 0
    for a in range(0, n, per_call):
        qa, Ta = q[a : a + per_call], T[a : a + per_call]
        pad = per_call - qa.shape[0]
        if pad:
            qa = np.concatenate([qa, np.repeat(qa[:1], pad, axis=0)])
            Ta = np.concatenate([Ta, np.repeat(Ta[:1], pad, axis=0)])
        qj, Tj = jnp.asarray(qa), jnp.asarray(Ta)
        _block((qj, Tj))
        t0 = time.perf_counter()
        sol = _block(compiled(qj, Tj))
        total += (time.perf_counter() - t0) * (per_call - pad) / per_call
        converged += int(np.sum(np.asarray(sol.converged)[: per_call - pad]))
        del sol, qj, Tj
    return dict(
        compile_s=compile_s,
        steady_s=total,
        trials_per_s=n / total,
        all_s=[total],
        converged=converged / n,
        calls=-(-n // per_call),
    )


def time_per_trial(run_one: Callable[[int], dict], n: int) -> dict:
    """Run ``run_one(i)`` for ``i < n`` in chunks; median per-trial time over the chunks."""
    bounds = np.linspace(0, n, min(_N_CHUNKS, n) + 1).astype(int)
    per_trial, cpu, outs = [], [], []
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        t0, c0 = time.perf_counter(), time.process_time()
        outs.extend(run_one(i) for i in range(a, b))
        per_trial.append((time.perf_counter() - t0) / (b - a))
        cpu.append((time.process_time() - c0) / (b - a))
    med = statistics.median(per_trial)
    return dict(
        per_trial_s=med,
        trials_per_s=1.0 / med,
        cpu_us_per_trial=1e6 * statistics.median(cpu),
        chunks_s=per_trial,
        outputs=outs,
    )


# --------------------------------------------------------------------------- one run
def run(args) -> dict:
    arm = default_arm()
    dtype = jnp.float64 if args.dtype == "float64" else jnp.float32
    arm = arm.with_frames(jnp.asarray(arm.frames, dtype))
    noise = NoiseModel(args.noise_pos_mm, args.noise_rot_rad) if args.noise else None
    q, T, X_true = make_problems(arm, args.trials, args.poses, noise, args.seed)
    q, T = q.astype(dtype), T.astype(dtype)
    n_base = min(args.trials, args.baseline_trials)
    k_last = len(arm.frame_names) - 1
    ident = [0, k_last]  # base and tool: identifiable frames

    res: dict = {}
    print(f"# devices: {jax.devices()}", flush=True)
    print(
        f"# problem: CDRA, m={args.poses} poses, n_params={arm.n_params}, N={args.trials} "
        f"trials, noise={'none' if noise is None else (args.noise_pos_mm, args.noise_rot_rad)}"
        f", {args.dtype}",
        flush=True,
    )
    devices = jax.devices()
    weights = NoiseModel(args.noise_pos_mm, args.noise_rot_rad)
    runs: list[tuple[str, Callable, int, dict]] = [
        ("paper", calibrate_paper, 1, {}),
        ("weighted", calibrate_paper, 1, {"noise": weights}),
        ("lm", calibrate_lm, 1, {}),
        ("lm_optimistix", calibrate_lm_optimistix, 1, {}),
    ]
    if args.singular_values:
        sv = {"singular_values": True}
        runs += [
            ("paper_sv", calibrate_paper, 1, sv),
            ("weighted_sv", calibrate_paper, 1, {**sv, "noise": weights}),
            ("lm_sv", calibrate_lm, 1, sv),
        ]
    if len(devices) > 1:
        runs += [
            (f"{name}_x{len(devices)}", fn, len(devices), kw) for name, fn, _, kw in list(runs)
        ]
    if args.xla_defaults:
        runs += [(f"{name}_xla_defaults", fn, 0, kw) for name, fn, n, kw in list(runs) if n == 1]
    # Compile every JAX solver first, then time their steady state side by side.
    prepared: dict[str, dict] = {}
    for name, fn, n_dev, kw in runs:
        if _base(name) not in args.solvers:
            continue
        solve = lambda qq, TT, fn=fn, kw=kw: fn(arm, qq, TT, throw=False, **kw)  # noqa: E731
        if n_dev == 1:
            r = time_jax(solve, q, T, 0)
        elif n_dev == 0:  # one device, plain jax.jit: XLA's default compile options
            r = time_jax(solve, q, T, 0, jit=jax.jit)
        else:
            r = time_jax_split(solve, q, T, 0, devices)
        prepared[name] = r
        print(
            f"# {name}: compile {r['compile_s']:.2f} s, first call {r['first_call_s']:.2f} s",
            flush=True,
        )
    steady_interleaved(prepared, q.shape[0], args.repeats)
    for name, r in prepared.items():
        sol = r.pop("solution")
        r["errors"] = np.asarray(sol.errors)
        r["converged"] = float(np.mean(np.asarray(sol.converged)))
        r["iterations_mean"] = float(np.mean(np.asarray(sol.iterations)))
        res[name] = r
        print(f"# {name}: steady {r['steady_s']:.3f} s", flush=True)

    frames0 = np.asarray(arm.frames, dtype=float)
    kinds = baselines.arm_kinds(arm)
    base_fns = {
        "numpy": baselines.calibrate_numpy,
        "numpy_vec": baselines.calibrate_numpy_vectorized,
        "scipy": baselines.calibrate_scipy,
    }
    qb, Tb = q[:n_base].astype(float), T[:n_base].astype(float)
    for name, fn in base_fns.items():
        if name not in args.solvers:
            continue

        # The module poses are part of each trial's work, as they are for the JAX solvers.
        def one(i, fn=fn):
            return fn(frames0, baselines.module_poses(kinds, qb[i]), Tb[i])

        r = time_per_trial(one, n_base)
        outs = r.pop("outputs")
        r["errors"] = np.stack([o["errors"] for o in outs])
        r["converged"] = float(np.mean([o["converged"] for o in outs]))
        r["iterations_mean"] = float(np.mean([o["iterations"] for o in outs]))
        res[name] = r
        print(f"# {name}: {r['per_trial_s'] * 1e3:.2f} ms/trial", flush=True)

    ref = res["paper"]["errors"][:n_base] if "paper" in res else None
    for r in res.values():
        e = r["errors"][:n_base]
        r["maxdiff_vs_paper"] = (
            float(np.max(np.abs(e[:, ident] - ref[:, ident]))) if ref is not None else float("nan")
        )
        r["maxdiff_vs_preset"] = float(np.max(np.abs(e[:, ident] - X_true[:n_base][:, ident])))
    return dict(results=res, n_base=n_base, arm=arm)


def print_table(res: dict, n_base: int, n_trials: int) -> None:
    ref = res["numpy"]["trials_per_s"] if "numpy" in res else float("nan")
    w = max([10] + [len(k) for k in res])
    head = (
        f"{'solver':{w}s} {'trials':>7s} {'us/trial':>9s} {'cpu us':>7s} {'trials/s':>10s} "
        f"{'vs numpy':>9s} {'compile s':>10s} "
        f"{'first s':>8s} {'conv':>5s} {'iters':>6s} {'d(base,tool) vs paper':>22s} "
        f"{'vs preset':>10s}"
    )
    print(head)
    print("-" * len(head))
    for name in sorted(res, key=lambda k: (SOLVERS.index(_base(k)), k)):
        r = res[name]
        n = n_trials if _base(name) in _JAX_SOLVERS else n_base
        comp = f"{r['compile_s']:10.2f}" if "compile_s" in r else f"{'-':>10s}"
        first = f"{r['first_call_s']:8.2f}" if "first_call_s" in r else f"{'-':>8s}"
        print(
            f"{name:{w}s} {n:7d} {1e6 / r['trials_per_s']:9.1f} "
            f"{r.get('cpu_us_per_trial', float('nan')):7.1f} {r['trials_per_s']:10.1f} "
            f"{r['trials_per_s'] / ref:9.1f} "
            f"{comp} {first} {r['converged']:5.2f} {r['iterations_mean']:6.2f} "
            f"{r['maxdiff_vs_paper']:22.2e} {r['maxdiff_vs_preset']:10.2e}"
        )


def summary_json(res: dict, args, n_base: int) -> dict:
    out: dict = dict(
        trials=args.trials,
        baseline_trials=n_base,
        poses=args.poses,
        dtype=args.dtype,
        noise=bool(args.noise),
        devices=[str(d) for d in jax.devices()],
        jax_version=jax.__version__,
        lm_chunk_size=levenberg_marquardt.CHUNK_SIZE,
    )
    ref = res.get("numpy", {}).get("trials_per_s", float("nan"))
    for name, r in res.items():
        out[f"trials_per_s_{name}"] = r["trials_per_s"]
        out[f"us_per_trial_{name}"] = 1e6 / r["trials_per_s"]
        if "cpu_us_per_trial" in r:
            out[f"cpu_us_per_trial_{name}"] = r["cpu_us_per_trial"]
        out[f"maxdiff_vs_paper_{name}"] = r["maxdiff_vs_paper"]
        out[f"maxdiff_vs_preset_{name}"] = r["maxdiff_vs_preset"]
        out[f"converged_{name}"] = r["converged"]
        if "compile_s" in r:
            out[f"compile_s_{name}"] = r["compile_s"]
            out[f"first_call_s_{name}"] = r["first_call_s"]
        if name != "numpy":
            out[f"ratio_{name}_vs_numpy"] = r["trials_per_s"] / ref
    return out


# --------------------------------------------------------------------------- scaling
def scaling(args) -> dict:
    """trials/s of the JAX solvers against the batch size N and the pose count m."""
    arm = default_arm()
    out: dict = dict(devices=[str(d) for d in jax.devices()], by_trials=[], by_poses=[])
    solvers = [s for s in ("paper", "lm") if s in args.solvers]
    fns = dict(paper=calibrate_paper, lm=calibrate_lm)
    print(f"# devices: {jax.devices()}")
    print("# trials/s against N (m = 15)")
    print(f"{'N':>9s} " + " ".join(f"{s:>12s} {'compile s':>9s}" for s in solvers))
    for n in args.scaling_trials:
        q, T, _ = make_problems(arm, n, 15, None, args.seed)
        row = dict(N=n)
        for s in solvers:
            if s == "lm" and n > args.lm_max_trials:
                row[s] = None
                continue
            solve = lambda qq, TT, f=fns[s]: f(arm, qq, TT, throw=False)  # noqa: E731
            if n > args.max_call:
                r = time_jax_calls(solve, q, T, args.max_call)
                row[f"{s}_calls"] = r["calls"]
            else:
                r = time_jax(solve, q, T, _scaling_repeats(args.repeats, n), first_call=False)
            row[s] = r["trials_per_s"]
            row[f"{s}_compile_s"] = r["compile_s"]
            row[f"{s}_repeats"] = len(r["all_s"])
        out["by_trials"].append(row)
        print(f"{n:9d} " + " ".join(_fmt(row, s) for s in solvers), flush=True)
        del q, T
    print(f"# trials/s against m (N = {args.scaling_n})")
    print(f"{'m':>9s} " + " ".join(f"{s:>12s} {'compile s':>9s}" for s in solvers))
    for m in args.scaling_poses:
        q, T, _ = make_problems(arm, args.scaling_n, m, None, args.seed)
        row = dict(m=m)
        for s in solvers:
            r = time_jax(
                lambda qq, TT, f=fns[s]: f(arm, qq, TT, throw=False),
                q,
                T,
                _scaling_repeats(args.repeats, args.scaling_n * m // 15),
                first_call=False,
            )
            row[s] = r["trials_per_s"]
            row[f"{s}_compile_s"] = r["compile_s"]
            row[f"{s}_repeats"] = len(r["all_s"])
        out["by_poses"].append(row)
        print(f"{m:9d} " + " ".join(_fmt(row, s) for s in solvers), flush=True)
    return out


def _scaling_repeats(repeats: int, work: int) -> int:
    """Steady-state calls for a batch of ``work`` trial-equivalents (m = 15): ``repeats`` up to
    10^4, then fewer (3 up to 10^5, 1 beyond), so that N = 10^6 runs once."""
    if work <= 10_000:
        return repeats
    return min(repeats, 3) if work <= 100_000 else 1


def _fmt(row: dict, solver: str) -> str:
    """``trials/s compile_s`` of one solver in a scaling row (dashes where it did not run)."""
    if row[solver] is None:
        return f"{'-':>12s} {'-':>9s}"
    return f"{row[solver]:12.1f} {row[f'{solver}_compile_s']:9.2f}"


def machine() -> dict:
    cpu = "unknown"
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if "model name" in line)
    except (OSError, StopIteration):
        pass
    return dict(
        cpu=cpu,
        cores=os.cpu_count(),
        python=platform.python_version(),
        jax=jax.__version__,
        numpy=np.__version__,
        devices=[str(d) for d in jax.devices()],
        load_average=list(os.getloadavg()),
    )


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--trials", type=int, default=10_000, help="batch size N of the JAX solvers")
    p.add_argument("--poses", type=int, default=15, help="calibration poses per trial (m)")
    p.add_argument("--baseline-trials", type=int, default=200, help="subset for numpy/scipy")
    p.add_argument(
        "--repeats", type=int, default=5, help="steady-state rounds (one call of each JAX solver)"
    )
    p.add_argument("--noise", action="store_true", help="add measurement noise")
    p.add_argument("--noise-pos-mm", type=float, default=0.08, help="position noise std (mm)")
    p.add_argument("--noise-rot-rad", type=float, default=1e-3, help="rotation noise std (rad)")
    p.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    p.add_argument("--solvers", nargs="+", default=list(SOLVERS), choices=SOLVERS)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="print one JSON object on the last line")
    p.add_argument(
        "--devices",
        type=int,
        default=1,
        help="CPU devices (cdra_jax.parallel.use_cpu_devices): with N > 1 the JAX solvers are "
        "also timed with the batch split over N devices (rows paper_xN, lm_xN)",
    )
    p.add_argument(
        "--xla-defaults",
        action="store_true",
        help="also time the JAX solvers compiled with plain jax.jit, i.e. XLA's default options "
        "(rows paper_xla_defaults, lm_xla_defaults), side by side with the package's "
        "cdra_jax.compilation.jit",
    )
    p.add_argument(
        "--singular-values",
        action="store_true",
        help="also time the JAX solvers with singular_values=True (rows *_sv), as the command "
        "line runs them",
    )
    p.add_argument("--scaling", action="store_true", help="trials/s against N and m instead")
    p.add_argument(
        "--scaling-trials",
        type=int,
        nargs="+",
        default=[100, 1_000, 10_000, 100_000, 1_000_000],
    )
    p.add_argument("--scaling-poses", type=int, nargs="+", default=[5, 10, 15, 30, 60, 100, 200])
    p.add_argument("--scaling-n", type=int, default=10_000, help="N of the pose-count sweep")
    p.add_argument(
        "--max-call",
        type=int,
        default=100_000,
        help="scaling: a batch above this many trials runs as calls of this size (one compile)",
    )
    p.add_argument(
        "--lm-max-trials", type=int, default=100_000, help="largest N the LM scaling runs"
    )
    p.add_argument(
        "--lm-chunk-size",
        type=int,
        default=None,
        help="trials per chunk of the vmapped LM solver (default: its CHUNK_SIZE, 32); read when "
        "the solver is traced",
    )
    args = p.parse_args(argv)
    if args.lm_chunk_size is not None:
        levenberg_marquardt.CHUNK_SIZE = args.lm_chunk_size
    if args.devices > 1:
        use_cpu_devices(args.devices)  # before JAX starts its CPU backend
    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)

    info = machine()
    print(f"# machine: {info}", flush=True)
    if args.scaling:
        out = scaling(args)
        out["machine"] = info
        if args.json:
            print(json.dumps(out))
        return out
    r = run(args)
    print_table(r["results"], r["n_base"], args.trials)
    out = summary_json(r["results"], args, r["n_base"])
    out["machine"] = info
    if args.json:
        print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
