"""Where LM stops: its answers against the exact least-squares minimum.

Setup: the paper's problem (default CDRA, ``--poses`` poses, Section V errors +-1 mm / +-0.05
rad, ``--trials`` trials, float64), three cases: noise-free; 80 um / 1e-3 rad whitened (solver
with the noise model); the same noise unweighted. For each case two solves of the same trials:
LM with its defaults and the exact minimum (the same solver with ``rtol = atol = 1e-15`` and
100 steps). The distance of the tool position at ``--heldout`` held-out states from that of the
exact minimum, per trial (largest over the states), is reported as its maximum and 99.9th
percentile, with LM's mean step count.

Usage::

    python benchmarks/lm_stop.py                   # 4,096 trials
    python benchmarks/lm_stop.py --trials 1024 --json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from throughput import make_problems  # noqa: E402

from cdra_jax import NoiseModel, calibrate_lm, default_arm, tool_pose  # noqa: E402
from cdra_jax.arm import sample_states  # noqa: E402
from cdra_jax.compilation import jit  # noqa: E402

_NOISE = NoiseModel(0.08, 1e-3)


def _compiled(arm, q, T, noise, **options):
    """The vmapped LM solve of the batch, compiled."""
    fn = jit(jax.vmap(lambda q, T: calibrate_lm(arm, q, T, noise, throw=False, **options)))
    return fn.lower(q, T).compile()


def run(args) -> dict:
    arm = default_arm()
    q_heldout = sample_states(jax.random.PRNGKey(args.seed + 1), arm, args.heldout)

    def positions(frames):
        return jax.vmap(lambda f: tool_pose(arm.with_frames(f), q_heldout)[:, :3, 3])(frames)

    out: dict = {}
    for case, noise, weights in (
        ("noise-free", None, None),
        ("noisy, whitened", _NOISE, _NOISE),
        ("noisy, unweighted", _NOISE, None),
    ):
        q, T, _ = make_problems(arm, args.trials, args.poses, noise, args.seed)
        q, T = jnp.asarray(q), jnp.asarray(T)
        exact = _compiled(arm, q, T, weights, rtol=1e-15, atol=1e-15, max_iterations=100)(q, T)
        reference = positions(exact.frames)
        sol = _compiled(arm, q, T, weights)(q, T)
        dist = np.asarray(
            jnp.max(jnp.linalg.norm(positions(sol.frames) - reference, axis=-1), axis=-1)
        )
        row = dict(
            max_mm=float(dist.max()),
            p999_mm=float(np.quantile(dist, 0.999)),
            iterations=float(np.mean(np.asarray(sol.iterations))),
        )
        out[case] = row
    return out


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--trials", type=int, default=4096)
    p.add_argument("--poses", type=int, default=15)
    p.add_argument("--heldout", type=int, default=20, help="held-out states per trial")
    p.add_argument("--seed", type=int, default=11)
    p.add_argument("--json", action="store_true", help="print one JSON object on the last line")
    args = p.parse_args(argv)
    res = run(args)
    print("{:20s} {:>10s} {:>10s} {:>6s}".format("case", "max mm", "p99.9 mm", "steps"))
    for case, r in res.items():
        print(f"{case:20s} {r['max_mm']:10.2e} {r['p999_mm']:10.2e} {r['iterations']:6.3f}")
    if args.json:
        print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
