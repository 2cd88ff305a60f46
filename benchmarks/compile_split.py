"""What XLA:CPU compiles for the vmapped solvers: LLVM modules, IR lines, and where they come from.

Compile time is noisy on a shared machine; the size of what XLA hands to LLVM is not. This
script compiles the vmapped paper or LM solver (the paper's problem, batches of 4,096 trials of
15 poses, the package's compile options) in a child process that dumps XLA's output
(``XLA_FLAGS=--xla_dump_to``), and reports, deterministically for a given jax version:

* the number of LLVM modules (the fused kernels, split into parts for parallel code generation,
  and every operation that XLA emits as a kernel of its own: small matrix products, reductions
  rewritten as trees, the loops of scatters, broadcasts of loop state);
* the kernels (LLVM functions: each fused kernel and each operation emitted on its own), which
  cost LLVM a few milliseconds each whatever their size;
* the lines of optimised LLVM IR, in total and grouped by the package function that the HLO
  instructions come from (the innermost frame of ``cdra_jax`` in their stack), with the kernels
  of each;
* the child's trace, lowering and XLA compile times (wall and CPU), for orientation only.

With ``--instructions`` it counts instead the machine instructions that the compilation
executes, under valgrind (``cachegrind --cache-sim=no``, about 20x slower, four minutes): a
child that only imports and builds the solver, one that also traces and lowers it, and one
that also compiles it, so that the differences are the instructions of tracing and lowering
and of XLA. The counts repeat to about 0.3 % from run to run, whatever else the machine
runs: the measure to compare two versions of the code by, where compile times on a shared
machine scatter by 10-15 %.

    python benchmarks/compile_split.py [--solver paper|lm] [--top 15] [--json]
    python benchmarks/compile_split.py --instructions [--solver paper|lm] [--json]
"""

from __future__ import annotations

import argparse
import collections
import glob
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile

_SETUP = r"""
import json, sys, time
sys.path.insert(0, {root!r})
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import cdra_jax as cj
arm = cj.default_arm()
q = jax.ShapeDtypeStruct((4096, 15, arm.dof), jnp.float64)
T = jax.ShapeDtypeStruct((4096, 15, 4, 4), jnp.float64)
solve = {{"paper": cj.calibrate_paper, "lm": cj.calibrate_lm}}[{solver!r}]
f = cj.jit(jax.vmap(lambda q, T: solve(arm, q, T, throw=False)))
"""
"""The children's common start: the vmapped solver for the paper's problem (4,096 trials of
15 poses, float64; the compiled program depends only on the shapes, so no data is made)."""

_CHILD = (
    _SETUP
    + r"""
t0, c0 = time.perf_counter(), time.process_time()
traced = f.trace(q, T)
t1 = time.perf_counter()
lowered = traced.lower()
t2, c2 = time.perf_counter(), time.process_time()
lowered.compile()
t3, c3 = time.perf_counter(), time.process_time()
print(json.dumps(dict(trace_s=t1 - t0, lower_s=t2 - t1, xla_s=t3 - t2, trace_lower_cpu_s=c2 - c0,
                      xla_cpu_s=c3 - c2)))
"""
)

_INSTRUCTION_CHILD = (
    _SETUP
    + r"""
stage = {stage!r}
if stage == "lower":
    f.lower(q, T)
elif stage == "compile":
    f.lower(q, T).compile()
"""
)

_STAGES = ("import", "lower", "compile")
"""The children of ``--instructions``: import and build the solver; also trace and lower it;
also compile it."""


def _instructions(valgrind_output: str) -> int:
    """The instruction count (``I refs``) of a cachegrind run's report."""
    m = re.search(r"I\s+refs:\s+([\d,]+)", valgrind_output)
    if m is None:
        raise RuntimeError(f"no instruction count in valgrind's output:\n{valgrind_output[-2000:]}")
    return int(m.group(1).replace(",", ""))


def count_instructions(solver: str) -> dict:
    """Instructions executed to import, to trace and lower, and to compile the vmapped solver
    (``--instructions``; needs valgrind)."""
    valgrind = shutil.which("valgrind")
    if valgrind is None:
        raise SystemExit("--instructions needs valgrind (e.g. apt install valgrind)")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    counts = {}
    for stage in _STAGES:
        code = _INSTRUCTION_CHILD.format(root=root, solver=solver, stage=stage)
        done = subprocess.run(
            [valgrind, "--tool=cachegrind", "--cache-sim=no", "--cachegrind-out-file=/dev/null"]
            + [os.path.realpath(sys.executable), "-c", code],
            env=env,
            capture_output=True,
            text=True,
        )
        if done.returncode:
            raise RuntimeError(f"the {stage} child failed:\n{done.stderr[-2000:]}")
        counts[stage] = _instructions(done.stderr)
    return dict(
        solver=solver,
        instructions=counts,
        trace_and_lower=counts["lower"] - counts["import"],
        xla=counts["compile"] - counts["lower"],
    )


def _functions(path: str) -> dict[str, int]:
    """Lines of each function defined in an LLVM IR file."""
    out: dict[str, int] = collections.Counter()
    current = None
    with open(path) as f:
        for line in f:
            m = re.match(r"define .*@([\w.\-]+)\(", line)
            if m:
                current = m.group(1)
            elif line.startswith("}"):
                current = None
            elif current:
                out[current] += 1
    return out


def _sources(hlo_text: str) -> dict[str, str]:
    """The innermost ``cdra_jax`` frame (``file:function``) of every HLO instruction."""
    files, funcs, locs, frames = {}, {}, {}, {}
    section = None
    body = []
    for line in hlo_text.splitlines():
        if line in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
            section = line
            continue
        if line.startswith(("%", "ENTRY", "HloModule", "  ")):
            section = None
        if section is None:
            body.append(line)
            continue
        m = re.match(r"^(\d+) (.*)$", line)
        if not m:
            continue
        i, rest = int(m.group(1)), m.group(2)
        fields = dict(re.findall(r"(\w+)=(\d+)", rest))
        if section == "FileNames":
            files[i] = rest.strip('"')
        elif section == "FunctionNames":
            funcs[i] = rest.strip('"')
        elif section == "FileLocations":
            locs[i] = (int(fields["file_name_id"]), int(fields["function_name_id"]))
        else:
            frames[i] = (int(fields["file_location_id"]), int(fields["parent_frame_id"]))
    out = {}
    for line in body:
        m = re.match(r"\s+(?:ROOT )?%([\w.\-]+) = .*stack_frame_id=(\d+)", line)
        if not m:
            continue
        frame, seen = int(m.group(2)), set()
        while frame and frame not in seen and frame in frames:
            seen.add(frame)
            loc, parent = frames[frame]
            file, func = locs[loc]
            if "/cdra_jax/" in files[file]:
                out[m.group(1)] = f"{os.path.basename(files[file])}:{funcs[func]}"
                break
            frame = parent
    return out


def _by_source(lines: dict[str, int], sources: dict[str, str]) -> tuple[dict, dict]:
    """Lines of IR and kernels per package function (:func:`_sources`; a kernel named
    ``<instruction>_kernel`` belongs to the instruction, one without a package frame to XLA)."""
    by_source: dict[str, int] = collections.Counter()
    kernels: dict[str, int] = collections.Counter()
    for name, n in lines.items():
        source = sources.get(name.removesuffix("_kernel"), "(made by XLA)")
        by_source[source] += n
        kernels[source] += 1
    return by_source, kernels


def measure(solver: str, top: int) -> dict:
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    with tempfile.TemporaryDirectory() as dump:
        env = dict(
            os.environ, XLA_FLAGS=f"--xla_dump_to={dump} --xla_dump_hlo_module_re=.*lambda.*"
        )
        done = subprocess.run(
            [sys.executable, "-c", _CHILD.format(root=root, solver=solver)],
            env=env,
            capture_output=True,
            text=True,
            check=True,
        )
        times = json.loads(done.stdout.strip().splitlines()[-1])
        hlo = sorted(glob.glob(os.path.join(dump, "*jit__lambda.cpu_after_optimizations.txt")))[-1]
        module = os.path.basename(hlo).split(".")[0]
        ir_files = glob.glob(os.path.join(dump, f"{module}.*.ir-with-opt.ll"))
        lines: dict[str, int] = collections.Counter()
        for path in ir_files:
            lines.update(_functions(path))
        with open(hlo) as f:
            sources = _sources(f.read())
    by_source, kernels_by_source = _by_source(lines, sources)
    total = sum(lines.values())
    return dict(
        solver=solver,
        llvm_modules=len(ir_files),
        modules_outside_parts=sum("part_" not in os.path.basename(p) for p in ir_files),
        kernels=len(lines),
        ir_lines=total,
        by_source=dict(by_source.most_common(top)),
        kernels_by_source={k: kernels_by_source[k] for k, _ in by_source.most_common(top)},
        **times,
    )


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--solver", choices=("paper", "lm"), default="paper")
    parser.add_argument("--top", type=int, default=15, help="package functions listed")
    parser.add_argument("--json", action="store_true", help="print one JSON object last")
    parser.add_argument(
        "--instructions",
        action="store_true",
        help="count the instructions of tracing, lowering and compiling, under valgrind",
    )
    args = parser.parse_args(argv)
    if args.instructions:
        r = count_instructions(args.solver)
        print(
            f"{r['solver']}: {r['trace_and_lower'] / 1e9:.2f} G instructions to trace and "
            f"lower, {r['xla'] / 1e9:.2f} G to compile (XLA); the import and the solver's "
            f"construction {r['instructions']['import'] / 1e9:.2f} G"
        )
        if args.json:
            print(json.dumps(r))
        return r
    r = measure(args.solver, args.top)
    print(
        f"{r['solver']}: {r['llvm_modules']} LLVM modules ({r['modules_outside_parts']} outside "
        f"the parallel-codegen parts), {r['kernels']} kernels, "
        f"{r['ir_lines']} lines of optimised IR"
    )
    print(
        f"trace {r['trace_s']:.2f} s, lowering {r['lower_s']:.2f} s, XLA {r['xla_s']:.2f} s "
        f"({r['xla_cpu_s']:.2f} s CPU)"
    )
    print("  lines  share  kernels  package function")
    for source, n in r["by_source"].items():
        kernels = r["kernels_by_source"][source]
        print(f"{n:7d} {100 * n / r['ir_lines']:5.1f} % {kernels:8d}  {source}")
    if args.json:
        print(json.dumps(r))
    return r


if __name__ == "__main__":
    main()
