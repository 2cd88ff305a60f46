"""Peak resident memory of a chunked sweep against the number of trials.

Each size runs in a fresh process (``ru_maxrss`` is a lifetime peak): one noise level
(``--noise-pos`` mm / ``--noise-rot`` rad), ``m = --poses``, solver ``--solver``, ``N`` trials in
chunks of ``--chunk``, then the table is written as CSV. Reported per size: peak RSS after
imports, after the first (compiled) chunk, after the sweep, after writing the CSV, the wall
time and the throughput. The driver extrapolates to ``--extrapolate`` trials: the peak after
the first chunk (JAX, XLA's compilation and one chunk of intermediates; independent of ``N``)
plus twice the in-memory table (the per-chunk parts and their concatenation coexist for a
moment; 19 columns, ``table_bytes`` measured).

Usage::

    python benchmarks/sweep_memory.py                       # N = 1e4, 1e5
    python benchmarks/sweep_memory.py --sizes 10000 100000 1000000
    python benchmarks/sweep_memory.py --child 100000        # one size, in this process
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def child(args) -> dict:
    sys.path.insert(0, str(ROOT))
    from cdra_jax.cli.sweep import default_cpu_devices
    from cdra_jax.parallel import use_cpu_devices

    # Before JAX starts; by default as cdra-jax sweep chooses for a cell of this many trials.
    use_cpu_devices(args.cpu_devices or default_cpu_devices(args.child))
    import jax

    jax.config.update("jax_enable_x64", True)
    from cdra_jax import default_arm
    from cdra_jax.sweeps import run_sweep

    out = {"trials": args.child, "after_import_mib": _peak_mib(), "devices": len(jax.devices())}
    arm = default_arm()
    kw = dict(
        noise_levels=[(args.noise_pos, args.noise_rot)],
        pose_counts=[args.poses],
        solvers=[args.solver],
        chunk=args.chunk,
        seed=args.seed,
        progress=False,
    )
    t0 = time.perf_counter()
    run_sweep(arm, trials=args.chunk, **kw)  # compile + one chunk
    out["compile_and_first_chunk_s"] = time.perf_counter() - t0
    out["after_first_chunk_mib"] = _peak_mib()
    t0 = time.perf_counter()
    table = run_sweep(arm, trials=args.child, **kw)
    out["sweep_s"] = time.perf_counter() - t0
    out["trials_per_s"] = args.child / out["sweep_s"]
    out["after_sweep_mib"] = _peak_mib()
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        path = table.save(Path(tmp) / "sweep.csv")
        out["csv_s"] = time.perf_counter() - t0
        out["csv_mib"] = path.stat().st_size / 2**20
    out["after_csv_mib"] = _peak_mib()
    out["table_bytes"] = int(sum(v.nbytes for v in table.columns.values()))
    out["converged"] = float(table["converged"].mean())
    out["median_dp_heldout_mm"] = float(sorted(table["dp_heldout"])[len(table) // 2])
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000])
    ap.add_argument("--extrapolate", type=int, default=1_000_000)
    ap.add_argument("--chunk", type=int, default=4096)
    ap.add_argument("--poses", type=int, default=15)
    ap.add_argument("--solver", default="weighted")
    ap.add_argument("--noise-pos", type=float, default=0.08)
    ap.add_argument("--noise-rot", type=float, default=1e-3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--cpu-devices", type=int, help="XLA:CPU devices (default: as cdra-jax sweep chooses)"
    )
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(args)))
        return 0
    results = []
    for n in args.sizes:
        cmd = [sys.executable, __file__, "--child", str(n)]
        for flag in ("chunk", "poses", "solver", "noise_pos", "noise_rot", "seed", "cpu_devices"):
            if getattr(args, flag) is not None:
                cmd += [f"--{flag.replace('_', '-')}", str(getattr(args, flag))]
        proc = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ))
        if proc.returncode != 0:
            print(proc.stderr[-2000:], file=sys.stderr)
            return 1
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        results.append(r)
        print(
            f"N = {n:>8d}: peak RSS {r['after_import_mib']:.0f} MiB after import, "
            f"{r['after_first_chunk_mib']:.0f} after the first chunk, "
            f"{r['after_sweep_mib']:.0f} after the sweep, {r['after_csv_mib']:.0f} after the CSV "
            f"({r['csv_mib']:.0f} MiB); sweep {r['sweep_s']:.1f} s "
            f"({r['trials_per_s']:.0f} trials/s), compile+first chunk "
            f"{r['compile_and_first_chunk_s']:.1f} s; {r['devices']} device(s)",
            flush=True,
        )
    if results:
        big = max(results, key=lambda r: r["trials"])
        grown = big["after_csv_mib"] - big["after_first_chunk_mib"]
        per_trial = big["table_bytes"] / big["trials"]
        # at the end of a sweep the per-chunk parts and their concatenation coexist: 2 tables
        model = big["after_first_chunk_mib"] + 2 * per_trial * args.extrapolate / 2**20
        rate = max(r["trials_per_s"] for r in results)
        print(
            f"N = {big['trials']}: the peak grew {grown:.0f} MiB past the first chunk; the table "
            f"holds {per_trial:.0f} bytes/trial. Extrapolated peak at N = {args.extrapolate}: "
            f"first-chunk peak + 2 tables = {model:.0f} MiB; time ~"
            f"{args.extrapolate / rate / 60:.0f} min at {rate:.0f} trials/s"
        )
    print(json.dumps(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
