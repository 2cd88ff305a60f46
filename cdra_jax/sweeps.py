"""Batched Monte-Carlo noise-sensitivity sweeps: noise level x pose count x solver x trial.

Every trial is the paper's Section V/VI procedure (:func:`cdra_jax.simulation.simulate_trial`:
random module states within the joint limits and, for modules with cables, with tension closure
(:func:`cdra_jax.simulation.sample_poses`, for the calibration and the held-out states alike),
preset frame errors uniform in ``+-d_v`` mm / ``+-d_w`` rad, simulated measurements with
isotropic Gaussian noise) followed by one calibration and its evaluation:

* ``dp_fit``, ``dR_fit``: Eqs. 20-21 between the calibrated model and the measured calibration
  poses;
* ``dp_heldout``, ``dR_heldout``: Eqs. 20-21 between the calibrated model and the *true*
  (noise-free) tool poses of the actual arm at ``m_verify`` fresh states: the accuracy a user
  gets;
* ``dp_verify``, ``dR_verify``: the paper's Step 5, against the *measured* (noisy) verification
  poses (what one can observe on a real arm; it includes the measurement noise);
* ``param_err``: norm of the error of the identified frames w.r.t. the true ones,
  ``e = log(F_c F_true^-1)`` (Eqs. 15-18 at the truth), projected onto the identifiable subspace
  (row space of the Jacobian at the truth for the calibration states; the unidentifiable
  directions are not the solvers' fault); ``param_err_v`` (mm) and ``param_err_w`` (rad) split
  it into translation and rotation components. The norm mixes mm and rad as the paper's step
  norm does.

Solvers: ``"paper"`` (:func:`~cdra_jax.calibration.calibrate_paper` unweighted, the paper's
Eq. 10), ``"weighted"`` (the same with the level's :class:`~cdra_jax.calibration.NoiseModel`,
whitened residual) and ``"lm"`` (:func:`~cdra_jax.calibration.calibrate_lm` on the whitened
residual when the level has noise, unweighted at the noise-free level ``(0, 0)``), all with
``throw=False``: a failed trial keeps its result code and never stops the sweep.

Random numbers: trial ``t`` with ``m`` poses uses the key
``fold_in(fold_in(PRNGKey(seed), m), t)`` (:func:`trial_key`), the same for every noise level
and solver (common random numbers: solvers and noise levels are compared on identical poses,
errors and standardised noise). Chunking and sharding therefore never change a result.

Execution: for each (pose count, solver) one function ``vmap``-ed over trials is jitted and
applied chunk by chunk (``chunk`` trials at a time, the last chunk padded), so memory stays
bounded by the chunk whatever the number of trials. Each chunk is split into one part per
device of ``jax.local_devices()`` (:func:`cdra_jax.parallel.split_over_devices`), and the parts
run at the same time, so a multi-GPU host, or a CPU presented as several devices
(:func:`cdra_jax.parallel.use_cpu_devices`, which ``cdra-jax sweep`` calls), uses all of them
with the same code. The cells of one pose count and noise group hold the same trials whatever
their solver: a chunk of their trials is simulated once (one compiled program) and calibrated
by each solver (one compiled program per solver). The chunks can also be shared out over several
processes, on this machine or several (:mod:`cdra_jax.distributed`; ``cdra-jax sweep
--processes N``): the chunks simulated together, numbered ``k`` in table order, go to process
``k mod N``, each process writes its chunks to the checkpoint folder, and process 0 gathers them
into the same table as one process's. Results are a tidy table, one row per trial
(:class:`SweepTable`), saved as CSV or, where pyarrow is installed, Parquet.
"""

from __future__ import annotations

import contextlib
import csv
import functools
import importlib.util
import json
import math
import numbers
import os
import re
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .arm import Arm, apply_frame_errors, chain, error_twists, module_poses, tool_pose
from .calibration import (
    RESULTS,
    NoiseModel,
    calibrate_lm,
    calibrate_paper,
    calibration_jacobian,
    deviation_metrics,
)
from .calibration.batching import chunked_vmap
from .calibration.linear import (
    RESOLVED_PIVOT,
    STRUCTURAL_TOL,
    default_rcond,
    null_space_solve,
)
from .calibration.nullspace import null_basis, null_generators
from .calibration.validation import MIN_POSES
from .compilation import jit
from .distributed import Group, GroupError
from .io.files import write_file_atomic, write_text_atomic
from .parallel import check_devices, split_over_devices
from .simulation import StateSampler, sample_poses, simulate_trial

SOLVERS: tuple[str, ...] = ("paper", "weighted", "lm")
DEFAULT_CHUNK = 4096
_CSV_BLOCK = 8192
COLUMNS: tuple[str, ...] = (
    "noise_pos",
    "noise_rot",
    "m",
    "solver",
    "trial",
    "seed",
    "converged",
    "result",
    "iterations",
    "dp_fit",
    "dR_fit",
    "dp_heldout",
    "dR_heldout",
    "dp_verify",
    "dR_verify",
    "param_err",
    "param_err_v",
    "param_err_w",
    "rank",
)
_INT_COLUMNS = ("m", "trial", "seed", "iterations", "rank")
_STR_COLUMNS = ("solver", "result")
_BOOL_COLUMNS = ("converged",)
_METRICS = tuple(c for c in COLUMNS[9:] if c != "rank")
METRIC_UNITS = {
    "dp_fit": "mm",
    "dR_fit": "rad",
    "dp_heldout": "mm",
    "dR_heldout": "rad",
    "dp_verify": "mm",
    "dR_verify": "rad",
    "param_err": "mm & rad",
    "param_err_v": "mm",
    "param_err_w": "rad",
}


def trial_key(seed: int, m: int, trial: int | jax.Array) -> jax.Array:
    """PRNG key of trial ``trial`` with ``m`` calibration poses in a sweep seeded ``seed``."""
    return jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(seed), m), trial)


def parse_noise_levels(
    positions: Sequence[float], rotations: Sequence[float]
) -> list[tuple[float, float]]:
    """Pair position (mm) and rotation (rad) noise levels; one rotation value broadcasts.

    Raises:
        ValueError: mismatched lengths, negative values, or a level with only one of the two
            equal to zero (``(0, 0)`` is the noise-free level).
    """
    positions = [float(v) for v in positions]
    rotations = [float(v) for v in rotations]
    if not positions:
        raise ValueError("at least one noise level is needed")
    if len(rotations) == 1:
        rotations = rotations * len(positions)
    if len(rotations) != len(positions):
        raise ValueError(
            f"{len(positions)} position noise levels but {len(rotations)} rotation levels: give "
            "one rotation level for all, or one per position level"
        )
    levels = list(zip(positions, rotations, strict=True))
    for sp, sr in levels:
        if not (math.isfinite(sp) and math.isfinite(sr)) or sp < 0 or sr < 0:
            raise ValueError(f"noise level ({sp} mm, {sr} rad) must be finite and non-negative")
        if (sp == 0) != (sr == 0):
            raise ValueError(
                f"noise level ({sp} mm, {sr} rad): either both are zero (noise-free) or both "
                "positive (the whitened residual needs both standard deviations)"
            )
    return levels


@dataclass
class SweepTable:
    """Tidy sweep results: one row per trial; ``columns`` maps :data:`COLUMNS` to arrays.

    ``meta`` holds the sweep settings (written as ``#`` comment lines in CSV and as Parquet
    metadata).
    """

    columns: dict[str, np.ndarray]
    meta: dict[str, str] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.columns["trial"])

    def __getitem__(self, name: str) -> np.ndarray:
        return self.columns[name]

    def select(self, mask: np.ndarray) -> SweepTable:
        """The rows where ``mask`` is true."""
        return SweepTable({k: v[mask] for k, v in self.columns.items()}, dict(self.meta))

    def groups(self) -> list[tuple[float, float, str]]:
        """The distinct ``(noise_pos, noise_rot, solver)`` lines, in first-seen order."""
        seen: dict[tuple[float, float, str], None] = {}
        for key in zip(self["noise_pos"], self["noise_rot"], self["solver"], strict=True):
            seen.setdefault((float(key[0]), float(key[1]), str(key[2])), None)
        return list(seen)

    def summary(
        self,
        metric: str = "dp_heldout",
        quantiles: Sequence[float] = (0.1, 0.5, 0.9),
        converged_only: bool = False,
    ) -> list[dict]:
        """Quantiles of ``metric`` per (noise level, solver, m), one dict per group.

        Each dict has ``noise_pos``, ``noise_rot``, ``solver``, ``m``, ``n`` (trials),
        ``converged`` (fraction), ``rms`` and ``q<percent>`` entries (``q50`` the median).
        Non-finite values (failed trials) are left out of the quantiles.
        """
        if metric not in _METRICS:
            raise ValueError(f"unknown metric {metric!r}; metrics: {_METRICS}")
        out = []
        for sp, sr, solver in self.groups():
            line = (
                (self["noise_pos"] == sp) & (self["noise_rot"] == sr) & (self["solver"] == solver)
            )
            for m in sorted(set(self["m"][line].tolist())):
                rows = line & (self["m"] == m)
                v = self[metric][rows]
                if converged_only:
                    v = v[self["converged"][rows]]
                v = v[np.isfinite(v)]
                entry = {
                    "noise_pos": sp,
                    "noise_rot": sr,
                    "solver": solver,
                    "m": int(m),
                    "n": int(rows.sum()),
                    "converged": float(np.mean(self["converged"][rows])),
                    "rms": float(np.sqrt(np.mean(v * v))) if v.size else float("nan"),
                }
                for qq in quantiles:
                    entry[f"q{100 * qq:g}"] = float(np.quantile(v, qq)) if v.size else float("nan")
                out.append(entry)
        return out

    def to_csv(self, path: str | os.PathLike, *, force: bool = False) -> Path:
        """Write a CSV (``#`` comment lines with :attr:`meta`, then a header row)."""
        path = Path(path)

        def write(f):
            for k, v in self.meta.items():
                f.write(f"# {k}: {v}\n")
            w = csv.writer(f, lineterminator="\n")
            w.writerow(COLUMNS)
            for start in range(0, len(self), _CSV_BLOCK):  # bounded memory for 10^6 rows
                block = slice(start, start + _CSV_BLOCK)
                cols = [_format_column(c, self.columns[c][block]) for c in COLUMNS]
                w.writerows(zip(*cols, strict=True))

        write_file_atomic(path, write, force=force)
        return path

    def to_parquet(self, path: str | os.PathLike, *, force: bool = False) -> Path:
        """Write Parquet (needs pyarrow; :attr:`meta` goes into the schema metadata)."""
        if importlib.util.find_spec("pyarrow") is None:
            raise ValueError(
                f"{path}: writing Parquet needs pyarrow, which is not installed; write a .csv "
                "file instead (or install pyarrow)"
            )
        import pyarrow as pa
        import pyarrow.parquet as pq

        table = pa.table({c: self.columns[c] for c in COLUMNS})
        table = table.replace_schema_metadata({k: str(v) for k, v in self.meta.items()})
        path = Path(path)
        write_file_atomic(path, lambda f: pq.write_table(table, f), force=force, binary=True)
        return path

    def save(self, path: str | os.PathLike, *, force: bool = False) -> Path:
        """Write CSV or Parquet, by the suffix of ``path`` (``.csv`` / ``.parquet``)."""
        suffix = Path(path).suffix.lower()
        if suffix == ".parquet":
            return self.to_parquet(path, force=force)
        if suffix == ".csv":
            return self.to_csv(path, force=force)
        raise ValueError(f"{path}: unknown table format {suffix!r}; use .csv or .parquet")


def _format_column(name: str, values: np.ndarray) -> list[str]:
    if name in _STR_COLUMNS:
        return [str(v) for v in values]
    if name in _BOOL_COLUMNS:
        return ["true" if v else "false" for v in values]
    if name in _INT_COLUMNS:
        return [str(int(v)) for v in values]
    return [repr(float(v)) for v in values]


def read_sweep(path: str | os.PathLike) -> SweepTable:
    """Read a table written by :meth:`SweepTable.save` (CSV, or Parquet with pyarrow).

    Raises:
        ValueError: a missing column (naming the file and the column) or a bad cell (naming the
            line).
    """
    path = Path(path)
    if path.suffix.lower() == ".parquet":
        import pyarrow.parquet as pq

        t = pq.read_table(path)
        pmeta = {k.decode(): v.decode() for k, v in (t.schema.metadata or {}).items()}
        missing = [c for c in COLUMNS if c not in t.column_names]
        if missing:
            raise ValueError(f"{path}: missing column(s) {missing}")
        return SweepTable({c: t.column(c).to_numpy(zero_copy_only=False) for c in COLUMNS}, pmeta)
    meta: dict[str, str] = {}
    with open(path, newline="") as f:
        line_no = 0
        pos = f.tell()
        line = f.readline()
        while line.startswith("#"):
            line_no += 1
            k, _, v = line[1:].strip().partition(":")
            meta[k.strip()] = v.strip()
            pos = f.tell()
            line = f.readline()
        f.seek(pos)
        reader = csv.reader(f)
        header = next(reader, None)
        if header is None:
            raise ValueError(f"{path}: no header row")
        missing = [c for c in COLUMNS if c not in header]
        if missing:
            raise ValueError(f"{path}: line {line_no + 1}: missing column(s) {missing}")
        idx = {c: header.index(c) for c in COLUMNS}
        blocks: list[dict[str, np.ndarray]] = []
        rows: list[list[str]] = []
        first = line_no + 2
        for i, row in enumerate(reader, start=first):
            if len(row) != len(header):
                raise ValueError(f"{path}: line {i}: {len(row)} cells, header has {len(header)}")
            rows.append(row)
            if len(rows) == _CSV_BLOCK:
                blocks.append(_typed_block(path, first, rows, idx))
                first, rows = i + 1, []
        blocks.append(_typed_block(path, first, rows, idx))
    cols = {c: np.concatenate([b[c] for b in blocks]) for c in COLUMNS}
    return SweepTable(cols, meta)


_DECIMAL = re.compile(
    r"\s*[+-]?(?:(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?|nan|inf|infinity)\s*",
    re.ASCII | re.IGNORECASE,
)


def _read_float(v: str) -> float:
    """A decimal number (or nan/inf, as written for failed trials); not Python's other float
    spellings such as ``1_0``."""
    if not _DECIMAL.fullmatch(v):
        raise ValueError(v)
    return float(v)


def _read_int(v: str) -> int:
    if not re.fullmatch(r"\s*[+-]?\d+\s*", v, re.ASCII):
        raise ValueError(v)
    return int(v)


def _read_bool(v: str) -> bool:
    if v not in ("true", "false"):
        raise ValueError(v)
    return v == "true"


def _typed_block(path, first_line: int, rows: list[list[str]], idx: dict[str, int]) -> dict:
    """Convert a block of CSV rows to typed columns; errors name the line and the column."""
    out: dict[str, np.ndarray] = {}
    conv: Callable[[str], object]
    for c in COLUMNS:
        if c in _STR_COLUMNS:
            conv, dtype, kind = str, object, "text"
        elif c in _BOOL_COLUMNS:
            conv, dtype, kind = _read_bool, bool, "true/false"
        elif c in _INT_COLUMNS:
            conv, dtype, kind = _read_int, np.int64, "an integer"
        else:
            conv, dtype, kind = _read_float, float, "a number"
        values = []
        for j, r in enumerate(rows):
            try:
                values.append(conv(r[idx[c]]))
            except ValueError:
                raise ValueError(
                    f"{path}: line {first_line + j}: column {c!r}: expected {kind}, "
                    f"got {r[idx[c]]!r}"
                ) from None
        out[c] = np.asarray(values, dtype=dtype)
    return out


def _identifiable_error(arm_true: Arm, q: jax.Array, frames: jax.Array) -> tuple:
    """Identified-minus-true frame errors projected on the identifiable subspace at the truth.

    The identifiable subspace is the row space of the Jacobian ``D`` at the truth for the
    calibration states. Where the pose set loses only the structural directions (the generic
    case) it is the complement of the analytic null space (:mod:`.calibration.nullspace`), and
    the projection ``e - Z Z^T e`` needs no factorisation of ``D``; pose sets that lose more
    (detected from the Cholesky factor of ``D^T D``, :func:`.calibration.linear.null_space_solve`)
    are projected with the SVD of ``D``, as before, gathered into chunks of their own under
    ``vmap`` (:func:`.calibration.batching.chunked_vmap`)."""
    e = error_twists(frames, arm_true.frames)  # (K+1, 6)
    _, after = chain(arm_true.frames, module_poses(arm_true, q))
    D = calibration_jacobian(after)
    D = D.reshape(-1, D.shape[-1])
    modules, xi = null_generators(arm_true, D.dtype)
    Z = null_basis(arm_true.frames, modules, xi)
    pe = _project_identifiable(D, e.reshape(-1), Z).reshape(e.shape)
    return jnp.linalg.norm(pe), jnp.linalg.norm(pe[:, :3]), jnp.linalg.norm(pe[:, 3:])


def _projection(use_svd, D, e, Z):
    """``(projection of e on the row space of D, redo)``: analytic (``Z`` null) unless
    ``use_svd`` (unbatched: a real branch), flagged for a redo where ``Z`` is not the whole
    null space of ``D``."""

    def svd(D, e, Z):
        # The right singular vectors and singular values of D are those of the triangular
        # factor of its QR (D = Q R): an SVD of the n x n R instead of the 6m x n D.
        R = jnp.linalg.qr(D, mode="r")
        _, s, Vt = jnp.linalg.svd(R, full_matrices=False)
        keep = s > default_rcond(D.dtype) * s[0]
        coef = jnp.where(keep, Vt @ e, 0.0)
        return Vt.T @ coef, jnp.asarray(False)

    def analytic(D, e, Z):
        N = D.T @ D
        _, smallest, structural = null_space_solve(N, jnp.zeros_like(e), Z)
        generic = (smallest >= RESOLVED_PIVOT) & (structural <= STRUCTURAL_TOL)
        return e - Z @ (Z.T @ e), ~generic

    if not bool(jnp.finfo(D.dtype).eps < 1e-12):  # float32: the rank decision of the SVD
        return svd(D, e, Z)
    return jax.lax.cond(use_svd, svd, analytic, D, e, Z)


_project_identifiable = chunked_vmap(_projection, 128, second_pass=True)


def _simulation_function(
    m: int,
    noisy: bool,
    d_v: float,
    d_w: float,
    m_verify: int,
    sampler: StateSampler | None,
) -> Callable:
    """``f(arm, base_key, trial, noise_pos, noise_rot) -> (q_cal, T_cal, q_ver, T_ver, X)``:
    one trial's simulated data (:func:`~cdra_jax.simulation.simulate_trial`), the same for
    every solver (the key depends on the seed, ``m`` and the trial only).

    The default sampler runs with ``throw=False``: a trial whose draws hold too few feasible
    states gets NaN states and ends ``nonfinite`` instead of stopping the sweep, and the
    program holds no host callback (with one, XLA:CPU ran the devices' parts one after the
    other: measured 2.08 s for two halves of 1.01 s each).
    """
    draw = sampler if sampler is not None else functools.partial(sample_poses, throw=False)

    def f(arm, base, trial, sp, sr):
        dtype = jnp.asarray(arm.frames).dtype
        key = jax.random.fold_in(jax.random.fold_in(base, m), trial)
        noise = NoiseModel(sp.astype(dtype), sr.astype(dtype)) if noisy else None
        return simulate_trial(
            key, arm, m, d_v=d_v, d_w=d_w, noise=noise, m_verify=m_verify, sampler=draw
        )

    return f


def _solve_function(
    solver: str, noisy: bool, max_iterations: int | None, predictive_stop: bool = True
) -> Callable:
    """``f(arm, q_cal, T_cal, q_ver, T_ver, X, noise_pos, noise_rot) -> dict`` of one trial's
    outputs: the calibration by ``solver`` of simulated data and its held-out errors."""

    def f(arm, q_cal, T_cal, q_ver, T_ver, X, sp, sr):
        dtype = jnp.asarray(arm.frames).dtype
        noise = NoiseModel(sp.astype(dtype), sr.astype(dtype)) if noisy else None
        # The table has no singular values: the solvers skip their final QR + SVD (the rank
        # they report is then the solve's own, the same number wherever it is generic).
        kw: dict = {}
        if max_iterations is not None:
            kw["max_iterations"] = max_iterations
        gn = {"predictive_stop": predictive_stop}
        if solver == "paper":
            sol = calibrate_paper(arm, q_cal, T_cal, None, throw=False, **kw, **gn)
        elif solver == "weighted":
            sol = calibrate_paper(arm, q_cal, T_cal, noise, throw=False, **kw, **gn)
        else:
            sol = calibrate_lm(arm, q_cal, T_cal, noise, throw=False, **kw, **gn)
        actual = apply_frame_errors(arm, X)
        T_model = tool_pose(arm.with_frames(sol.frames), q_ver)
        # held-out: against the true (noise-free) poses and the measured ones, in one call
        dp, dR = deviation_metrics(jnp.stack([tool_pose(actual, q_ver), T_ver]), T_model)
        (dp_h, dp_v), (dR_h, dR_v) = dp, dR
        pe, pe_v, pe_w = _identifiable_error(actual, q_cal, sol.frames)
        return {
            "result": sol.result._value,
            "iterations": sol.iterations,
            "dp_fit": sol.final_delta_p,
            "dR_fit": sol.final_delta_R,
            "dp_heldout": dp_h,
            "dR_heldout": dR_h,
            "dp_verify": dp_v,
            "dR_verify": dR_v,
            "param_err": pe,
            "param_err_v": pe_v,
            "param_err_w": pe_w,
            "rank": sol.rank,
        }

    return f


@functools.lru_cache(maxsize=32)
def _batched_simulation(
    m: int,
    noisy: bool,
    d_v: float,
    d_w: float,
    m_verify: int,
    sampler: StateSampler | None,
) -> Callable:
    """The jitted and vmapped simulation of a chunk of trials (cached across sweeps, so a
    repeated sweep with the same settings and chunk size does not compile again; JAX compiles
    it once per device it runs on)."""
    f = _simulation_function(m, noisy, d_v, d_w, m_verify, sampler)
    return jit(jax.vmap(f, in_axes=(None, None, 0, 0, 0)))


@functools.lru_cache(maxsize=32)
def _batched_solve(
    solver: str, noisy: bool, max_iterations: int | None, predictive_stop: bool = True
) -> Callable:
    """The jitted and vmapped calibration of a chunk of simulated trials by one solver (cached
    as :func:`_batched_simulation`)."""
    f = _solve_function(solver, noisy, max_iterations, predictive_stop)
    return jit(jax.vmap(f, in_axes=(None, 0, 0, 0, 0, 0, 0, 0)))


@dataclass(frozen=True)
class _Cell:
    m: int
    solver: str
    noisy: bool
    trials: np.ndarray  # (n,) trial indices
    levels: np.ndarray  # (n, 2) noise level per row


def _cells(levels, pose_counts, solvers, trials) -> list[_Cell]:
    cells = []
    for m in pose_counts:
        for solver in solvers:
            for noisy in (False, True):
                group = [lv for lv in levels if (lv[0] > 0) == noisy]
                if not group:
                    continue
                if solver == "weighted" and not noisy:
                    raise ValueError(
                        "solver 'weighted' needs a noise model; the noise-free level (0, 0) "
                        "can only be run with 'paper' or 'lm'"
                    )
                lv = np.repeat(np.asarray(group, dtype=float), trials, axis=0)
                tr = np.tile(np.arange(trials), len(group))
                cells.append(_Cell(int(m), solver, noisy, tr, lv))
    return cells


def _list(name: str, values) -> list:
    if isinstance(values, str) or not isinstance(values, Iterable):
        raise ValueError(f"{name} must be a list, got {values!r}")
    return list(values)


def _integer(name: str, v, what: str = "an integer") -> int:
    """``v`` as an int when it is an integer (not a bool, not a float), else a ValueError."""
    if isinstance(v, bool) or not isinstance(v, numbers.Integral):
        raise ValueError(f"{name} must be {what}, got {v!r}")
    return int(v)


def _level_pairs(noise_levels) -> list[tuple[float, float]]:
    """``(position_mm, rotation_rad)`` of each noise level; a ValueError naming the argument
    for anything else."""
    what = "noise_levels must be a non-empty list of (position_mm, rotation_rad) pairs"
    if isinstance(noise_levels, str | NoiseModel) or not isinstance(noise_levels, Iterable):
        raise ValueError(f"{what}, got {noise_levels!r}")
    pairs = []
    for i, lv in enumerate(noise_levels):
        if isinstance(lv, NoiseModel):
            pairs.append((float(lv.position_mm), float(lv.rotation_rad)))
            continue
        ok = isinstance(lv, Sequence | np.ndarray) and not isinstance(lv, str) and len(lv) == 2
        if ok and all(isinstance(v, numbers.Real) and not isinstance(v, bool) for v in lv):
            pairs.append((float(lv[0]), float(lv[1])))
        else:
            raise ValueError(f"{what} (or NoiseModels); entry {i} is {lv!r}")
    if not pairs:
        raise ValueError(f"{what}, got none")
    return pairs


def run_sweep(
    arm: Arm,
    noise_levels: Iterable[tuple[float, float] | NoiseModel],
    pose_counts: Iterable[int],
    solvers: Iterable[str] = ("paper", "weighted", "lm"),
    trials: int = 100,
    *,
    seed: int = 0,
    chunk: int = DEFAULT_CHUNK,
    d_v: float = 1.0,
    d_w: float = 0.05,
    m_verify: int = 50,
    sampler: StateSampler | None = None,
    max_iterations: int | None = None,
    predictive_stop: bool = True,
    devices: Sequence[jax.Device] | None = None,
    progress: bool = True,
    checkpoint: str | os.PathLike | None = None,
    group: Group | None = None,
) -> SweepTable | None:
    """Monte-Carlo sweep over noise levels x pose counts x solvers x trials.

    Args:
        arm: nominal arm.
        noise_levels: ``(position_mm, rotation_rad)`` pairs or :class:`NoiseModel` s; ``(0, 0)``
            is noise-free (not with ``"weighted"``).
        pose_counts: numbers of calibration poses ``m`` (each >= 4).
        solvers: any of ``"paper"``, ``"weighted"``, ``"lm"``.
        trials: trials per (noise level, m, solver).
        seed: base seed (see :func:`trial_key`).
        chunk: trials per vmapped batch (rounded up to a multiple of the device count); memory
            grows with it, not with ``trials``.
        d_v, d_w: preset error ranges (Section V: 1 mm, 0.05 rad).
        m_verify: held-out states per trial.
        sampler: module-state sampler ``sampler(key, arm, m)``, traced inside the vmapped trial
            (default :func:`cdra_jax.simulation.sample_poses`: uniform within the joint limits
            and, for modules with cables, with tension closure at the default margin of
            :func:`cdra_jax.modules.sample_feasible_states`; modules without cables stay
            uniform). Pass :func:`cdra_jax.simulation.sample_states` for plain uniform states.
        max_iterations: solver iteration cap (default: each solver's own).
        predictive_stop: the solvers stop once the remaining steps are predicted below their
            tolerances (their default, :func:`~cdra_jax.calibration.calibrate_paper`,
            :func:`~cdra_jax.calibration.calibrate_lm`): about one pass fewer per trial,
            frames and held-out errors within 1e-8 mm of the plain stop (``False``), whose
            noise-free fit metrics end near 1e-13 mm rather than 1e-10.
        devices: devices to split every chunk over (default ``jax.local_devices()``, those of
            this process); several CPU devices need a large enough thread pool
            (:func:`cdra_jax.parallel.check_devices`, ``ValueError`` otherwise).
        progress: a tqdm progress bar on a terminal, plain progress lines on stderr otherwise.
        checkpoint: a folder that keeps every finished chunk (created if missing). A sweep
            interrupted at any point and run again with the same arguments and the same
            checkpoint loads the finished chunks and computes only the rest: the table is the
            same as an uninterrupted run's (each trial depends only on its key). A checkpoint
            of a sweep with other arguments is refused (``ValueError``); remove the folder once
            the table is saved (:func:`remove_checkpoint`).
        group: run over the processes of a started :class:`cdra_jax.distributed.Group` (needs
            ``checkpoint``, a folder all of them see). The chunks simulated together (the same
            rows of every solver's cell; numbered ``k`` in table order) are computed by process
            ``k mod N`` unless they are already in the checkpoint;
            process 0 waits for the others' chunks and returns the table, the same as one
            process's (every trial depends on its key alone); the other processes return
            ``None`` once their chunks are written. :class:`cdra_jax.distributed.GroupError`
            names the missing chunks when a process fails, dies or hangs.

    Returns:
        A :class:`SweepTable` with ``len(levels) * len(pose_counts) * len(solvers) * trials``
        rows, ordered by m, solver, noise level, trial; ``None`` on the processes of a
        ``group`` other than process 0.

    Raises:
        ValueError: naming the argument: ``noise_levels`` not a non-empty list of pairs, a
            pose count, ``trials``, ``chunk``, ``m_verify`` or ``seed`` not an integer (a float
            or a bool is refused, never truncated) or out of range, ``d_v``/``d_w`` not a
            non-negative number, an unknown solver.
    """
    levels = parse_noise_levels(*zip(*_level_pairs(noise_levels), strict=True))
    pose_counts = [
        _integer("pose_counts", m, "integers") for m in _list("pose_counts", pose_counts)
    ]
    solvers = _list("solvers", solvers)
    for s in solvers:
        if s not in SOLVERS:
            raise ValueError(f"unknown solver {s!r}; solvers: {SOLVERS}")
    if not pose_counts or not solvers:
        raise ValueError("run_sweep needs at least one pose count and one solver")
    for m in pose_counts:
        if m < MIN_POSES:
            raise ValueError(f"pose count {m} is below the paper's minimum of {MIN_POSES}")
    for name, v in (("trials", trials), ("chunk", chunk), ("m_verify", m_verify)):
        if _integer(name, v) < 1:
            raise ValueError(f"{name} must be >= 1, got {v}")
    if not -(2**63) <= _integer("seed", seed) < 2**63:
        raise ValueError(f"seed must be an integer in [-2^63, 2^63), got {seed}")
    for name, x in (("d_v", d_v), ("d_w", d_w)):
        if not isinstance(x, numbers.Real) or isinstance(x, bool) or not 0 <= x < math.inf:
            raise ValueError(f"{name} must be a non-negative number, got {x!r}")
    n_proc, me = (1, 0) if group is None else (group.num_processes, group.process_id)
    if n_proc > 1 and checkpoint is None:
        raise ValueError(
            "a sweep over several processes needs checkpoint: the folder they all write to"
        )
    devices = list(jax.local_devices() if devices is None else devices)
    check_devices(devices)
    n_dev = len(devices)
    chunk = -(-int(chunk) // n_dev) * n_dev
    dtype = jnp.asarray(arm.frames).dtype
    base = jax.random.PRNGKey(seed)
    cells = _cells(levels, pose_counts, solvers, int(trials))
    total = sum(len(c.trials) for c in cells)
    t0 = time.perf_counter()
    store = None
    if checkpoint is not None:
        settings = {
            "arm": arm.name,
            "frames": np.asarray(arm.frames, dtype=float).tolist(),
            "levels": [list(map(float, lv)) for lv in levels],
            "pose_counts": pose_counts,
            "solvers": solvers,
            "trials": int(trials),
            "seed": int(seed),
            "chunk": int(chunk),
            "d_v": float(d_v),
            "d_w": float(d_w),
            "m_verify": int(m_verify),
            "max_iterations": max_iterations,
            "sampler": None if sampler is None else getattr(sampler, "__qualname__", "?"),
            "devices": n_dev,
            "dtype": str(dtype),
        }
        # Always recorded: a checkpoint of the other stop (or from before the predictive stop
        # was the default, without the key) is refused rather than mixed with this one.
        settings["predictive_stop"] = bool(predictive_stop)
        if me != 0:
            assert group is not None
            group.wait_ready()  # process 0 has made the folder: mismatches are refused here
        store = _Checkpoint(Path(checkpoint), settings)
        if group is not None and me == 0:
            group.announce_ready()
    plan = [
        (ci, start, min(start + chunk, len(cell.trials)))
        for ci, cell in enumerate(cells)
        for start in range(0, len(cell.trials), chunk)
    ]
    # The cells of one pose count and noise group hold the same trials at the same noise
    # levels, whatever their solver: a chunk of them is simulated once, for all its solvers.
    # Chunks are assigned to processes by that shared simulation (group k: process k mod N).
    shared = {key: k for k, key in enumerate(dict.fromkeys((c.m, c.noisy) for c in cells))}
    starts = sorted({start for _, start, _ in plan})
    sim_group = {
        g: shared[(cells[ci].m, cells[ci].noisy)] * len(starts) + starts.index(start)
        for g, (ci, start, _) in enumerate(plan)
    }
    mine = [g for g in range(len(plan)) if sim_group[g] % n_proc == me]
    done: dict[int, dict[str, np.ndarray]] = {}
    bar = _progress(total if me == 0 else sum(plan[g][2] - plan[g][1] for g in mine), progress)
    try:
        todo: dict[int, list[int]] = {}  # simulation group -> its chunks still to compute
        for g in mine:
            ci, start, stop = plan[g]
            if store is not None and store.has(ci, start):
                done[g] = store.load(ci, start)
                bar.update(stop - start)
            else:
                todo.setdefault(sim_group[g], []).append(g)
        for chunks in todo.values():  # nothing left to compute: no compilation
            ci0, start, stop = plan[chunks[0]]
            first = cells[ci0]
            pad = chunk - (stop - start)
            tr = np.pad(first.trials[start:stop], (0, pad), mode="edge")
            lv = np.pad(first.levels[start:stop], ((0, pad), (0, 0)), mode="edge")
            levels_arg = (lv[:, 0].astype(dtype), lv[:, 1].astype(dtype))
            simulate = _batched_simulation(
                first.m, first.noisy, float(d_v), float(d_w), int(m_verify), sampler
            )
            data = split_over_devices(
                simulate, (tr.astype(np.int32), *levels_arg), devices, arm, base
            )
            for g in chunks:
                ci, _, _ = plan[g]
                cell = cells[ci]
                solve = _batched_solve(
                    cell.solver, cell.noisy, max_iterations, bool(predictive_stop)
                )
                out = split_over_devices(solve, (*data, *levels_arg), devices, arm)
                out = {k: np.asarray(v)[: stop - start] for k, v in out.items()}
                out["trial"] = cell.trials[start:stop]
                out["noise_pos"] = cell.levels[start:stop, 0]
                out["noise_rot"] = cell.levels[start:stop, 1]
                out["m"] = np.full(stop - start, cell.m)
                out["solver"] = np.full(stop - start, cell.solver, dtype=object)
                if store is not None:
                    store.save(ci, start, out)
                done[g] = out
                bar.update(stop - start)
            del data
        if group is not None and me != 0:
            group.finish()
            return None
        if n_proc > 1:
            assert group is not None and store is not None
            owner = {g: k % n_proc for g, k in sim_group.items()}
            _gather(group, store, plan, cells, done, bar, owner)
    finally:
        bar.close()
    parts = [done[g] for g in range(len(plan))]
    cols = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    codes = cols.pop("result").astype(np.int32)
    cols["result"] = _result_names(codes)
    cols["converged"] = codes == 0
    cols["seed"] = np.full(len(codes), int(seed), dtype=np.int64)
    columns = {c: cols[c] for c in COLUMNS}
    meta = {
        "arm": arm.name,
        "seed": str(seed),
        "d_v_mm": repr(float(d_v)),
        "d_w_rad": repr(float(d_w)),
        "m_verify": str(m_verify),
        "trials": str(trials),
        "chunk": str(chunk),
        "devices": ", ".join(str(d) for d in devices),
        "seconds": f"{time.perf_counter() - t0:.3f}",
        "key": "fold_in(fold_in(PRNGKey(seed), m), trial)",
    }
    if n_proc > 1:
        meta["processes"] = str(n_proc)
    return SweepTable(columns, meta)


class _Checkpoint:
    """Finished chunks of a sweep, one ``.npz`` file each, in a folder with the sweep's
    arguments (``settings.json``): a chunk file is written atomically (temporary name, then
    rename), so an interruption leaves whole chunks only."""

    def __init__(self, folder: Path, settings: dict):
        self.folder = folder
        text = json.dumps(settings, sort_keys=True)
        marker = folder / "settings.json"
        if folder.exists():
            if not folder.is_dir():
                raise ValueError(f"checkpoint {folder}: exists and is not a folder")
            if marker.exists() and marker.read_text() != text:
                raise ValueError(
                    f"checkpoint {folder}: holds chunks of a sweep with other arguments; "
                    "run the same command to resume it, or remove the folder to start afresh"
                )
        folder.mkdir(exist_ok=True)
        if not marker.exists():
            write_text_atomic(marker, text)

    def _path(self, cell: int, start: int) -> Path:
        return self.folder / f"cell{cell:04d}-start{start:010d}.npz"

    def has(self, cell: int, start: int) -> bool:
        return self._path(cell, start).exists()

    def load(self, cell: int, start: int) -> dict[str, np.ndarray]:
        with np.load(self._path(cell, start), allow_pickle=False) as z:
            out = {k: z[k] for k in z.files}
        out["solver"] = out["solver"].astype(object)
        return out

    def save(self, cell: int, start: int, out: dict[str, np.ndarray]) -> None:
        arrays: dict[str, Any] = {
            k: np.asarray(v, dtype=str) if k == "solver" else v for k, v in out.items()
        }

        def write(f) -> None:
            np.savez(f, **arrays)

        write_file_atomic(self._path(cell, start), write, binary=True)


def _gather(
    group: Group, store: _Checkpoint, plan, cells, done: dict, bar, owner: dict[int, int]
) -> None:
    """Process 0: load the other processes' chunks (``plan[g]`` = ``(cell, start, stop)``,
    computed by process ``owner[g]``) into ``done`` as they appear in ``store``, advancing
    ``bar``; :class:`GroupError` naming the missing chunks and their processes if a process
    fails, dies or hangs."""
    others = [g for g in range(len(plan)) if g not in done]
    seen: set[int] = set()

    def count() -> int:
        for g in others:
            ci, start, stop = plan[g]
            if g not in seen and store.has(ci, start):
                seen.add(g)
                bar.update(stop - start)
        return len(seen)

    def missing() -> str:
        gone = [g for g in others if not store.has(*plan[g][:2])]
        text = [
            f"cell {plan[g][0]} (m={cells[plan[g][0]].m}, {cells[plan[g][0]].solver}) rows "
            f"{plan[g][1]}-{plan[g][2] - 1} of process {owner[g]}"
            for g in gone[:8]
        ]
        more = f" and {len(gone) - 8} more" if len(gone) > 8 else ""
        return f"{len(gone)} chunk(s) missing: " + "; ".join(text) + more

    try:
        group.wait_for_others(count)
    except GroupError as e:
        raise GroupError(
            f"sweep over {group.num_processes} processes: {e}; {missing()}. The finished "
            f"chunks are kept in {store.folder}: the same command resumes from them"
        ) from None
    count()
    if len(seen) < len(others):
        raise GroupError(
            f"sweep over {group.num_processes} processes: every process reported done but "
            f"{missing()} from {store.folder}: all processes must write to the same folder "
            "(on several machines, a shared file system)"
        )
    for g in others:
        done[g] = store.load(*plan[g][:2])


def remove_checkpoint(folder: str | os.PathLike) -> None:
    """Remove a sweep checkpoint folder (:func:`run_sweep`'s ``checkpoint``) and its chunks."""
    folder = Path(folder)
    if not folder.is_dir():
        return
    for p in folder.iterdir():
        if p.suffix == ".npz" or p.name == "settings.json":
            p.unlink()
    with contextlib.suppress(OSError):
        folder.rmdir()


def _result_names(codes: np.ndarray) -> np.ndarray:
    names = np.asarray(list(RESULTS._name_to_item), dtype=object)
    return names[codes]


class _NoBar:
    def update(self, n: int) -> None:
        pass

    def close(self) -> None:
        pass


class _LogLines:
    """Progress as plain lines on stderr, for a log file or a pipe (no terminal to redraw a
    bar on): one line per finished chunk, at most one every ``every`` seconds, and the last."""

    def __init__(self, total: int, every: float = 5.0):
        self.total, self.done, self.every = total, 0, every
        self.t0 = self.last = time.perf_counter()

    def update(self, n: int) -> None:
        self.done += n
        now = time.perf_counter()
        if now - self.last >= self.every or self.done >= self.total:
            self.last = now
            print(
                f"sweep: {self.done}/{self.total} trials ({100 * self.done / self.total:.0f} %), "
                f"{now - self.t0:.1f} s",
                file=sys.stderr,
                flush=True,
            )

    def close(self) -> None:
        pass


def _progress(total: int, enabled: bool):
    """A tqdm bar on a terminal, log lines otherwise (``enabled=False``: nothing)."""
    if not enabled:
        return _NoBar()
    if not sys.stderr.isatty():
        return _LogLines(total)
    from tqdm.auto import tqdm

    return tqdm(total=total, unit="trial", desc="sweep", file=sys.stderr)
