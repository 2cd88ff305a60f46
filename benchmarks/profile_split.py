"""Where a solver's time goes: XLA's thunk profile of the vmapped paper, weighted or LM solver.

Setup: the paper's problem (default CDRA, ``--poses`` poses, Section V errors +-1 mm / +-0.05
rad, noise-free, ``--trials`` trials, float64, one CPU device), each solver compiled with the
package's options (``cdra_jax.jit``) and called ``--calls`` times under ``jax.profiler`` after a
warm-up call. The trace (Perfetto JSON) is read back, and the time of every XLA:CPU thunk is
taken exclusive of the thunks nested in it, summed per thunk and grouped by kind:

* ``matrix products``: XLA's dot fusions (``ynn_fusion``) and dots, e.g. ``V^T V``;
* ``LAPACK``: the Cholesky factorisations and triangular solves;
* ``element-wise``: every other fusion (the chain, the residual's logarithm, building ``V``,
  the exponential of the step, the selects of the batched loop);
* ``copies``: copies and the layout transposes inside them;
* ``dispatch``: the thunk executor's own time between the thunks it runs (XLA's cost of many
  small kernels, per chunk of trials);
* ``control flow``: the ``while`` and ``cond`` thunks themselves.

The thunks run on XLA's intra-op threads, so the sum is CPU time, not wall time; the profiler
adds overhead of its own. Shares are of the solver's summed thunk time; the largest thunks are
listed too.

Usage::

    python benchmarks/profile_split.py                      # paper and LM, 2,048 trials
    python benchmarks/profile_split.py --solvers paper --json
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
from throughput import make_problems  # noqa: E402

from cdra_jax import NoiseModel, calibrate_lm, calibrate_paper, default_arm  # noqa: E402
from cdra_jax.compilation import jit as package_jit  # noqa: E402

GROUPS = (
    "matrix products",
    "LAPACK",
    "element-wise",
    "copies",
    "dispatch",
    "control flow",
)
"""The kinds of thunk time, in the order of the report."""


def _group(name: str) -> str | None:
    """The kind of an XLA:CPU thunk event (``None``: not a thunk of the program)."""
    if name.startswith("$") or name == "ThunkExecutor::Execute (wait for completion)":
        return None  # Python frames and the caller's wait
    if name == "ThunkExecutor::Execute":
        return "dispatch"
    if name.startswith(("ynn_fusion", "dot", "xnn_fusion")):
        return "matrix products"
    if name.startswith(("cholesky", "triangular_solve", "lapack", "custom-call")):
        return "LAPACK"
    if name.startswith(("copy", "Transpose")):
        return "copies"
    if name.startswith(("while", "cond", "conditional", "call")):
        return "control flow"
    if "fusion" in name or name.startswith(("slice", "concatenate", "dynamic", "select")):
        return "element-wise"
    return None  # runtime events that are not thunks (PjRt, transfers)


def exclusive_times(trace_file: Path) -> dict[str, float]:
    """Exclusive time (us) per event name of a Perfetto trace: each event's duration less that
    of the events nested in it on the same thread."""
    events = json.load(gzip.open(trace_file))
    events = events["traceEvents"] if isinstance(events, dict) else events
    threads: dict = collections.defaultdict(list)
    for e in events:
        if e.get("ph") == "X":
            threads[(e["pid"], e["tid"])].append(e)
    out: collections.Counter = collections.Counter()
    for evs in threads.values():
        evs.sort(key=lambda e: (e["ts"], -e["dur"]))
        stack: list[dict] = []
        for e in evs:
            while stack and stack[-1]["ts"] + stack[-1]["dur"] <= e["ts"]:
                stack.pop()
            if stack:
                out[stack[-1]["name"]] -= e["dur"]
            out[e["name"]] += e["dur"]
            stack.append(e)
    return dict(out)


def profile(solve, q, T, calls: int) -> dict:
    """The thunk split of ``calls`` calls of the compiled batched ``solve``."""
    compiled = package_jit(jax.vmap(solve)).lower(q, T).compile()
    jax.block_until_ready(compiled(q, T))
    with tempfile.TemporaryDirectory() as d:
        with jax.profiler.trace(d, create_perfetto_trace=True):
            for _ in range(calls):
                jax.block_until_ready(compiled(q, T))
        (trace_file,) = Path(d).rglob("perfetto_trace.json.gz")
        times = exclusive_times(trace_file)
    per_trial = {n: t / calls / q.shape[0] for n, t in times.items() if _group(n)}
    total = sum(per_trial.values())
    groups = dict.fromkeys(GROUPS, 0.0)
    for n, t in per_trial.items():
        groups[_group(n)] += t  # type: ignore[index]
    top = sorted(per_trial.items(), key=lambda kv: -kv[1])[:8]
    return {
        "thunk_us_per_trial": total,
        "share": {g: t / total for g, t in groups.items()},
        "largest_us_per_trial": dict(top),
    }


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--trials", type=int, default=2048)
    p.add_argument("--poses", type=int, default=15)
    p.add_argument("--calls", type=int, default=3, help="profiled calls per solver")
    p.add_argument(
        "--solvers", nargs="+", default=["paper", "lm"], choices=("paper", "weighted", "lm")
    )
    p.add_argument("--json", action="store_true", help="print one JSON object on the last line")
    args = p.parse_args(argv)
    arm = default_arm()
    q, T, _ = make_problems(arm, args.trials, args.poses, None)
    q, T = jnp.asarray(q), jnp.asarray(T)
    weights = NoiseModel(0.08, 1e-3)
    solvers = {
        "paper": lambda qq, TT: calibrate_paper(arm, qq, TT, throw=False),
        "weighted": lambda qq, TT: calibrate_paper(arm, qq, TT, weights, throw=False),
        "lm": lambda qq, TT: calibrate_lm(arm, qq, TT, throw=False),
    }
    out = {s: profile(solvers[s], q, T, args.calls) for s in args.solvers}
    for s, r in out.items():
        print(f"{s}: {r['thunk_us_per_trial']:.1f} us of thunk time per trial")
        for g, f in r["share"].items():
            print(f"  {g:16s} {100 * f:5.1f} %")
        largest = r["largest_us_per_trial"].items()
        print("  largest: " + ", ".join(f"{n} {t:.1f}" for n, t in largest))
    if args.json:
        print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
