"""What one pass of the paper and LM solvers costs, piece by piece.

Setup: the paper's problem (default CDRA, ``--poses`` poses, Section V errors +-1 mm / +-0.05
rad, noise-free, ``--trials`` trials, float64, one CPU device), evaluated at the nominal frames
(the first pass of both solvers). Each piece of a pass is compiled on its own with the
package's options (``cdra_jax.jit``), vmapped over chunks of 32 trials and mapped over the
chunks, as the solvers run their trials (:mod:`cdra_jax.calibration.batching`):

* ``model``: the chain (Eq. 1) and the residual with the deviation metrics (Eqs. 7, 20-21),
  ``kernels.chain`` and ``kernels.residual_and_metrics``; both solvers, every pass;
* ``paper_normal_equations``: ``D^T D`` and ``D^T Y`` (``kernels.normal_equations``);
* ``lm_normal_equations``: ``J^T J`` and ``J^T r`` of LM's exact Jacobian ``J = -J_r^-1(r) D``
  (``kernels.lm_normal_equations``);
* ``lm_jacobian_inverse``: ``J_r^-1(r)`` per pose alone (``kernels.se3_left_jacobian_inverse``:
  the blocks that the latter computes, as one matrix);
* ``null_space_solve`` and ``null_space_solve_damped``: the step from the normal equations
  knowing the structural null space (``linear.null_space_solve``), without and with LM's
  damping.

The pieces are timed in interleaved rounds (one call of each per round); the report is the
median us per trial. A pass of the paper solver is ``model + paper_normal_equations +
null_space_solve``, one of LM ``model + lm_normal_equations + null_space_solve_damped``, each
plus the bookkeeping of its loop (not timed here). Both solvers take about four passes with a
step and a last evaluation of the model (``benchmarks/README.md``, *Where the time goes*).

Usage::

    python benchmarks/step_split.py                 # 4,096 trials, 15 poses
    python benchmarks/step_split.py --json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from throughput import make_problems  # noqa: E402

from cdra_jax import default_arm  # noqa: E402
from cdra_jax.arm import module_poses  # noqa: E402
from cdra_jax.calibration import kernels  # noqa: E402
from cdra_jax.calibration.batching import chunked_vmap  # noqa: E402
from cdra_jax.calibration.gauss_newton import CHUNK_SIZE  # noqa: E402
from cdra_jax.calibration.levenberg_marquardt import INITIAL_DAMPING  # noqa: E402
from cdra_jax.calibration.linear import null_space_solve  # noqa: E402
from cdra_jax.calibration.nullspace import null_basis, null_generators  # noqa: E402
from cdra_jax.compilation import jit as package_jit  # noqa: E402


def _chunked(fn):
    """``fn`` of one trial, vmapped in chunks of ``CHUNK_SIZE`` trials (as the solvers batch
    theirs, :func:`cdra_jax.calibration.batching.chunked_vmap`) and compiled."""
    return package_jit(jax.vmap(chunked_vmap(fn, CHUNK_SIZE)))


def pieces(arm, q, T):
    """``{name: (compiled function, arguments)}`` of the pieces of a pass (module docstring),
    at the nominal frames of ``arm``."""
    n_trials = q.shape[0]
    frames = arm.frames
    null_modules, generators = null_generators(arm)

    def layout(q, T):
        return jnp.moveaxis(module_poses(arm, q)[..., :3, :], 0, -1), kernels.pose_stack(T)

    def model(P, Tm):
        tool, after = kernels.chain(frames, P)
        r, dp, dR = kernels.residual_and_metrics(Tm, tool)
        return after, r, dp, dR

    evaluate = _chunked(model)
    paper_normal_equations = _chunked(lambda a, r, t: kernels.normal_equations(a, r, t, None))
    P, Tm = _chunked(layout)(q, T)
    after, r, _, _ = evaluate(P, Tm)
    N, g = paper_normal_equations(after, r, Tm)
    Z = _chunked(lambda _: null_basis(frames, null_modules, generators))(jnp.zeros(n_trials))
    return {
        "model": (evaluate, (P, Tm)),
        "paper_normal_equations": (paper_normal_equations, (after, r, Tm)),
        "lm_normal_equations": (
            _chunked(lambda a, r, t: kernels.lm_normal_equations(a, r, t, None)[:2]),
            (after, r, Tm),
        ),
        "lm_jacobian_inverse": (
            _chunked(lambda r: kernels.se3_left_jacobian_inverse(-r)),
            (r,),
        ),
        "null_space_solve": (
            _chunked(lambda N, g, Z: null_space_solve(N, g, Z, check=False)[0]),
            (N, g, Z),
        ),
        "null_space_solve_damped": (
            _chunked(
                lambda N, g, Z: null_space_solve(N, g, Z, check=False, damping=INITIAL_DAMPING * N)[
                    0
                ],
            ),
            (N, g, Z),
        ),
    }


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--trials", type=int, default=4096, help="trials (padded to whole chunks of 32)")
    p.add_argument("--poses", type=int, default=15)
    p.add_argument("--rounds", type=int, default=9, help="interleaved rounds of calls")
    p.add_argument("--json", action="store_true", help="print one JSON object on the last line")
    args = p.parse_args(argv)
    arm = default_arm()
    q, T, _ = make_problems(arm, args.trials, args.poses, None)
    funcs = pieces(arm, jnp.asarray(q), jnp.asarray(T))
    for f, a in funcs.values():
        jax.block_until_ready(f(*a))  # compiled and run once
    times: dict[str, list[float]] = {name: [] for name in funcs}
    for _ in range(args.rounds):
        for name, (f, a) in funcs.items():
            t0 = time.perf_counter()
            jax.block_until_ready(f(*a))
            times[name].append(time.perf_counter() - t0)
    us = {name: float(np.median(t)) / args.trials * 1e6 for name, t in times.items()}
    paper = us["model"] + us["paper_normal_equations"] + us["null_space_solve"]
    lm = us["model"] + us["lm_normal_equations"] + us["null_space_solve_damped"]
    out = {
        "us_per_trial": us,
        "paper_pass_us": paper,
        "lm_pass_us": lm,
        "lm_over_paper_pass": lm / paper,
        "trials": args.trials,
        "poses": args.poses,
        "rounds": args.rounds,
    }
    for name, t in us.items():
        print(f"{name:24s} {t:6.2f} us/trial")
    print(f"pass without bookkeeping: paper {paper:.2f}, LM {lm:.2f} us/trial ({lm / paper:.2f}x)")
    if args.json:
        print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
