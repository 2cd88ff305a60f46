"""Compile time and steady-state speed of the solvers under process-wide XLA:CPU options.

Some XLA:CPU code-generation options exist only as process-wide flags (``XLA_FLAGS``, read when
the backend starts), not as per-program compile options: the CPU backend's extra options
(``--xla_backend_extra_options=xla_cpu_disable_loop_unrolling``, ``..._disable_slp_vectorizer``,
``..._optimize_for_size``) are refused by ``jax.jit(..., compiler_options=...)``. The package
cannot set them for its own programs without changing every program of the user's process, so
this script measures what they would trade: each variant runs in a fresh process (the variants
alternate, round after round, so that a shared machine slows all of them alike), compiles the
vmapped solvers with the package's options (:func:`cdra_jax.jit`, trace and lowering included,
no persistent cache) and times the steady state on the same problems (the paper's: default
CDRA, ``--poses`` poses, +-1 mm / +-0.05 rad preset errors, noise-free, float64).

Usage::

    python benchmarks/xla_options.py                       # the default variants, paper and LM
    python benchmarks/xla_options.py --variant= \\
        --variant=--xla_backend_extra_options=xla_cpu_disable_loop_unrolling --rounds 3 --json

Columns: median compile seconds over the rounds, median us/trial (each process: the median of
``--repeats`` calls), and the largest difference of the frames from those of the first variant
(the default, ``""``): 0 where the variant changes the speed but not one bit of the answers.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile

import numpy as np

_HERE = os.path.dirname(os.path.abspath(__file__))

DEFAULT_VARIANTS = (
    "",
    "--xla_backend_extra_options=xla_cpu_disable_loop_unrolling",
    "--xla_backend_extra_options=xla_cpu_disable_slp_vectorizer",
    "--xla_backend_extra_options=xla_cpu_optimize_for_size",
)
"""The variants measured by default: XLA's defaults (the package's own options on top), and
each of the CPU backend's code-size options alone."""


def _child(problems: str, solvers: list[str], repeats: int, frames_out: str) -> None:
    """Compile and time the solvers in this process (its ``XLA_FLAGS`` are the variant's) with
    ``benchmarks/throughput.py``'s timer; print one JSON line and save the frames to
    ``frames_out``."""
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, _HERE)
    import throughput

    from cdra_jax import calibrate_lm, calibrate_paper, default_arm

    arm = default_arm()
    with np.load(problems) as data:
        q, T = data["q"], data["T"]
    fns = {"paper": calibrate_paper, "lm": calibrate_lm}
    out: dict[str, dict[str, float]] = {}
    frames = {}
    for name in solvers:
        f = fns[name]
        r = throughput.time_jax(
            lambda q, T, f=f: f(arm, q, T, throw=False), q, T, repeats, first_call=False
        )
        sol = r["solution"]
        out[name] = {
            "compile_s": r["compile_s"],
            "us_per_trial": 1e6 / r["trials_per_s"],
            "converged": float(jnp.mean(sol.result._value == 0)),
        }
        frames[name] = np.asarray(sol.frames)
    np.savez(frames_out, **frames)
    print(json.dumps(out))


def _problems(path: str, trials: int, poses: int) -> None:
    """Write the paper's problems (``benchmarks/throughput.py``'s generator) to ``path``."""
    import jax

    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, _HERE)
    import throughput

    from cdra_jax import default_arm

    q, T, _ = throughput.make_problems(default_arm(), trials, poses, None)
    np.savez(path, q=q, T=T)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=4096)
    parser.add_argument("--poses", type=int, default=15)
    parser.add_argument("--solvers", nargs="+", choices=("paper", "lm"), default=["paper", "lm"])
    parser.add_argument(
        "--variant",
        action="append",
        dest="variants",
        metavar="XLA_FLAGS",
        help="the XLA_FLAGS of a variant, written --variant=FLAGS (repeat it; --variant= is "
        "XLA's defaults); the first is the reference of the frames column. Default: "
        "XLA's defaults and each of the CPU backend's code-size options alone",
    )
    parser.add_argument("--rounds", type=int, default=2, help="fresh processes per variant")
    parser.add_argument("--repeats", type=int, default=7, help="steady-state calls per process")
    parser.add_argument("--json", action="store_true", help="also print JSON on the last line")
    parser.add_argument(
        "--child", nargs=2, metavar=("PROBLEMS", "FRAMES_OUT"), help=argparse.SUPPRESS
    )
    args = parser.parse_args(argv)
    args.variants = args.variants or list(DEFAULT_VARIANTS)
    if args.child:
        _child(args.child[0], args.solvers, args.repeats, args.child[1])
        return 0

    with tempfile.TemporaryDirectory(prefix="cdra-xla-options-") as tmp:
        problems = os.path.join(tmp, "problems.npz")
        _problems(problems, args.trials, args.poses)
        runs: dict[tuple[int, str], list[dict[str, float]]] = {}
        frames: dict[int, dict[str, np.ndarray]] = {}
        for r in range(args.rounds):
            for v, flags in enumerate(args.variants):
                frames_out = os.path.join(tmp, f"frames_{v}.npz")
                env = dict(os.environ, XLA_FLAGS=flags, JAX_ENABLE_COMPILATION_CACHE="false")
                cmd = [sys.executable, os.path.abspath(__file__), "--child", problems, frames_out]
                cmd += ["--solvers", *args.solvers, "--repeats", str(args.repeats)]
                done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
                if done.returncode != 0:
                    print(f"variant {flags!r} failed:\n{done.stderr[-2000:]}", file=sys.stderr)
                    return 1
                result = json.loads(done.stdout.strip().splitlines()[-1])
                for name, row in result.items():
                    runs.setdefault((v, name), []).append(row)
                if r == 0:
                    with np.load(frames_out) as f:
                        frames[v] = {k: f[k] for k in f.files}
                print(f"# round {r + 1}, variant {v}: {json.dumps(result)}", flush=True)

    rows = []
    for v, flags in enumerate(args.variants):
        for name in args.solvers:
            rs = runs[(v, name)]
            rows.append(
                {
                    "variant": flags or "(defaults)",
                    "solver": name,
                    "compile_s": statistics.median(x["compile_s"] for x in rs),
                    "us_per_trial": statistics.median(x["us_per_trial"] for x in rs),
                    "frames_vs_first": float(np.max(np.abs(frames[v][name] - frames[0][name]))),
                    "converged": min(x["converged"] for x in rs),
                }
            )
    head = f"{'variant':62s} {'solver':6s} {'compile s':>9s} {'us/trial':>9s}"
    print(f"{head} {'frames vs 1st':>13s}")
    for row in rows:
        print(
            f"{row['variant']:62s} {row['solver']:6s} {row['compile_s']:9.2f} "
            f"{row['us_per_trial']:9.1f} {row['frames_vs_first']:13.1e}"
        )
    if args.json:
        print(json.dumps({"trials": args.trials, "poses": args.poses, "rows": rows}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
