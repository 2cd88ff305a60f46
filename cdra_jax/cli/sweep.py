"""``cdra-jax sweep``: Monte-Carlo noise-sensitivity sweep (noise level x pose count x solver).

Usage::

    cdra-jax sweep --noise-pos 0.02,0.08,0.2 --noise-rot 0.001 --poses 5,10,15,30
        --solvers paper,weighted,lm --trials 1000 --out results.csv [--chunk 4096]
        [--plot fig.png] [--seed 0] [--model M] [--d-v 1 --d-w 0.05] [--verify 50]
        [--no-progress] [--force] [--processes N [--coordinator HOST:PORT --process-id K]]

A thin layer over :func:`cdra_jax.workflows.sweep`. Finished chunks are kept in a hidden folder
beside the output (``.<out>.chunks``) until the table is written: after an interruption (Ctrl-C,
``SIGTERM``, a crash) the same command resumes where it stopped and writes the same table.
``--noise-rot`` takes one value for all position levels or one per level; ``0`` and ``0`` is the
noise-free level. Writes the tidy per-trial table (``.csv``, or ``.parquet`` where pyarrow is
installed) and prints the median held-out accuracy per cell. Progress: a bar on a terminal, plain
lines on stderr otherwise. ``--processes N`` shares the chunks out over N processes
(:func:`cdra_jax.distributed.start_group`): alone, it starts N - 1 more processes on this
machine; with ``--coordinator`` and ``--process-id``, each process is started by hand (one per
machine), all writing to the same chunk folder. The table is the same as one process's.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..distributed import DEFAULT_TIMEOUT, check_group
from ..io.files import check_distinct_files, check_output
from ..workflows.inputs import check_range
from . import common


def _floats(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers, got {text!r}"
        ) from None


def _ints(text: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers, got {text!r}"
        ) from None


def _names(text: str) -> list[str]:
    return [v.strip() for v in text.split(",") if v.strip()]


TRIALS_PER_EXTRA_DEVICE = 50_000
"""Trials of a cell (one pose count and solver) that pay for one more CPU device.

Every device compiles each cell once more (about 8 s for the weighted solver on this project's
2-core machine), and the second core gives 1920 -> 2608 trials/s (m = 15, weighted): the extra
compilation is paid back after about 60,000 trials (``docs``: README, sweeps, "Both cores")."""


def default_cpu_devices(trials_per_cell: int, processes: int = 1) -> int:
    """CPU devices for a sweep: one per :data:`TRIALS_PER_EXTRA_DEVICE` trials of a cell (at
    least 1), at most one per core of the ``processes`` sharing this machine."""
    from ..parallel import schedulable_cores

    cores = max(1, schedulable_cores() // processes)
    return max(1, min(cores, trials_per_cell // TRIALS_PER_EXTRA_DEVICE))


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``sweep`` subcommand (``func`` = :func:`run`)."""
    p = subparsers.add_parser(
        "sweep",
        help="Monte-Carlo noise-sensitivity sweep (noise x poses x solvers x trials)",
        description="Simulate and calibrate many trials (Section V/VI procedure: module states "
        "within the joint limits and, where the model has cables, with tension closure) for every "
        "combination of noise level, pose count and solver; write one row per trial. Finished "
        "chunks are kept in the hidden folder .<out>.chunks beside --out until the table is "
        "written: after an interruption the same command resumes where it stopped.",
    )
    common.add_model_option(p)
    p.add_argument(
        "--noise-pos", metavar="MM,...", type=_floats, required=True, help="position noise std(s)"
    )
    p.add_argument(
        "--noise-rot",
        metavar="RAD,...",
        type=_floats,
        required=True,
        help="orientation noise std(s): one for all, or one per --noise-pos value",
    )
    p.add_argument("--poses", metavar="m,...", type=_ints, required=True, help="pose counts")
    p.add_argument(
        "--solvers",
        metavar="S,...",
        type=_names,
        default=["paper", "weighted", "lm"],
        help="any of paper, weighted, lm, the solver names of calibrate (default: all three)",
    )
    p.add_argument("--trials", metavar="N", type=int, required=True, help="trials per cell")
    p.add_argument("--chunk", metavar="C", type=int, default=4096, help="trials per batch (4096)")
    p.add_argument("--out", metavar="FILE", required=True, help="results table (.csv/.parquet)")
    p.add_argument("--plot", metavar="PNG", help="also write a figure (medians, 10-90 %% bands)")
    p.add_argument("--seed", metavar="S", type=int, default=0, help="base seed (0)")
    p.add_argument("--d-v", metavar="MM", type=float, default=1.0, help="preset error range, mm")
    p.add_argument("--d-w", metavar="RAD", type=float, default=0.05, help="preset error, rad")
    p.add_argument("--verify", metavar="K", type=int, default=50, help="held-out states (50)")
    p.add_argument(
        "--cpu-devices",
        metavar="N",
        type=int,
        help="on a CPU, run as N XLA devices, one part of every chunk each (default: one per "
        f"{TRIALS_PER_EXTRA_DEVICE} trials of a cell, at most one per core: each device costs "
        "one more compilation)",
    )
    p.add_argument(
        "--no-progress",
        action="store_true",
        help="no progress (default: a bar on a terminal, plain lines on stderr otherwise)",
    )
    p.add_argument(
        "--processes",
        metavar="N",
        type=int,
        default=1,
        help="share the chunks out over N processes (default 1); alone, it starts N - 1 more "
        "on this machine; with --coordinator and --process-id, start each process yourself",
    )
    p.add_argument(
        "--coordinator",
        metavar="HOST:PORT",
        help="address of process 0 and a free port on it, the same for every process of a "
        "group started by hand (several machines: the output folder must be shared)",
    )
    p.add_argument(
        "--process-id",
        metavar="K",
        type=int,
        help="this process's number in a group started by hand, 0 .. N-1 (0 writes the table)",
    )
    p.add_argument(
        "--timeout",
        metavar="S",
        type=float,
        default=DEFAULT_TIMEOUT,
        help="with --processes: seconds to wait for all processes to connect, and for the next "
        f"finished chunk of another process, before giving up ({DEFAULT_TIMEOUT:g})",
    )
    common.add_force_option(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``sweep``; returns the exit code (0)."""
    # Every check of the arguments and the output files before any work.
    for flag, n in (("--trials", args.trials), ("--verify", args.verify), ("--chunk", args.chunk)):
        check_range(flag, n)
    if args.cpu_devices is not None:
        check_range("--cpu-devices", args.cpu_devices)
    for flag, v in (("--d-v", args.d_v), ("--d-w", args.d_w), ("--timeout", args.timeout)):
        check_range(flag, v)
    check_range("--processes", args.processes)
    flags = {"num_processes": "--processes", "process_id": "--process-id"}
    check_group(
        args.processes, args.process_id, args.coordinator, flags | {"coordinator": "--coordinator"}
    )
    out = Path(args.out)
    if out.suffix.lower() not in (".csv", ".parquet"):
        raise ValueError(f"{out}: --out must end in .csv or .parquet")
    check_distinct_files([("--out", out), ("--plot", args.plot)], [("--model", args.model)])
    check_output(out, args.force, "--out")
    check_output(args.plot, args.force, "--plot")

    import jax

    from ..parallel import use_cpu_devices

    # Before JAX starts: every core as a CPU device (no effect on a GPU host's devices). Called
    # from a process where JAX already runs (e.g. a notebook), the default keeps its devices.
    # A group on this machine (--processes alone) shares its cores among the processes.
    local = args.processes if args.coordinator is None else 1
    devices = args.cpu_devices or default_cpu_devices(args.trials * len(args.noise_pos), local)
    try:
        use_cpu_devices(devices)
    except RuntimeError:
        if args.cpu_devices is not None:
            raise
    jax.config.update("jax_enable_x64", True)
    from ..io import save_figure_atomic
    from ..sweeps import remove_checkpoint
    from ..workflows import sweep
    from ..workflows.inputs import check_seed

    checkpoint = out.parent / f".{out.name}.chunks"
    argv = getattr(args, "argv", None)  # the command line, set by cdra_jax.cli.main

    def worker_command(k: int, coordinator: str) -> list[str]:
        """The same command as process ``k`` of the group on this machine."""
        assert argv is not None
        group = ["--process-id", str(k), "--coordinator", coordinator]
        cpu = ["--cpu-devices", str(devices), "--no-progress"]
        return [sys.executable, "-m", "cdra_jax.cli", *argv, *group, *cpu]

    if checkpoint.is_dir() and not args.process_id:
        done = len(list(checkpoint.glob("*.npz")))
        print(f"sweep: resuming from {done} finished chunk(s) in {checkpoint}", file=sys.stderr)
    result = sweep(
        args.model,
        args.noise_pos,
        args.noise_rot,
        args.poses,
        solvers=args.solvers,
        trials=args.trials,
        seed=check_seed(args.seed, "--seed"),
        chunk=args.chunk,
        d_v=args.d_v,
        d_w=args.d_w,
        verify=args.verify,
        progress=not args.no_progress,
        checkpoint=checkpoint,
        processes=args.processes,
        process_id=args.process_id,
        coordinator=args.coordinator,
        worker_command=worker_command if argv is not None else None,
        timeout=args.timeout,
    )
    if result is None:  # another process than 0 of a group: its chunks are in the folder
        print(f"sweep: process {args.process_id} of {args.processes} wrote its chunks")
        return common.EXIT_OK
    result.save(out, force=args.force)
    remove_checkpoint(checkpoint)
    lines = [result.report(), common.wrote(out)]
    if args.plot:
        lines.append(common.wrote(save_figure_atomic(result.plot(), args.plot, force=args.force)))
    print("\n".join(lines))
    return common.EXIT_OK
