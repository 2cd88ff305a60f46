"""Cable lengths as measurement data: synthetic lengths of a pose set, joint states from lengths.

Measurement files may give a module's state as cable lengths, columns ``<module>.l1 ...
<module>.lN`` (mm, the *measured* lengths of :mod:`.cables`: attachment distance plus the cable's
length offset). This module provides what the readers and writers of those files need:

* :func:`cable_length_columns` and :func:`arm_cable_lengths` / :func:`simulate_cable_lengths`
  (optionally with Gaussian length noise) to write synthetic lengths for a pose set;
* :func:`check_cable_lengths`, per-row diagnostics of a module's length table (wrong count,
  NaN/inf, non-positive lengths, lengths no pose can produce, no convergence), each naming the
  row and the column;
* :func:`module_states_from_cable_lengths` and :func:`arm_states_from_cable_lengths`, which turn
  length tables into joint states (the flat ``(m, dof)`` in ``arm.state_names`` order) and raise
  a ``ValueError`` naming the source, the row and the column for the first bad entry.

The caller passes its own row labels (e.g. ``"line 7 (pose p3)"``) and column names so that the
messages point into the user's file. A row is impossible when the RMS length residual of the
best-fitting pose exceeds ``residual_tol`` (default :data:`~.cables.DEFAULT_RESIDUAL_TOL`,
0.1 mm). With two or more redundant cables (``n - dof >= 2``) the message names the column with
the largest standardised residual ``|r_i| / sqrt(1 - h_ii)`` (``h`` the hat matrix of the
linearised fit), which is where a single bad length shows; with a single redundant cable no
column can be singled out (every standardised residual is the same) and the message names all
of the module's columns.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from ..arm import Arm, Module
from ..compilation import compiled_when_eager_args, jit
from ._linalg import small_inv
from ._results import result_names
from .cables import (
    DEFAULT_RESIDUAL_TOL,
    cable_forward_kinematics,
    cable_length_names,
    cable_lengths,
    length_jacobian,
)


def cable_length_columns(arm: Arm) -> dict[str, tuple[str, ...]]:
    """``{module: ("<module>.l1", ...)}`` for every module of ``arm`` that has cables."""
    return {m.name: cable_length_names(m) for m in arm.modules if m.n_cables}


@compiled_when_eager_args("q")
def arm_cable_lengths(arm: Arm, q: ArrayLike) -> dict[str, Array]:
    """Measured cable lengths of every module with cables at flat states ``q (..., dof)``.

    Returns ``{module: (..., n)}`` mm (:func:`~.cables.cable_lengths`).
    """
    q = jnp.asarray(q)
    return {
        m.name: cable_lengths(m, qi)
        for m, qi in zip(arm.modules, arm.split_state(q), strict=True)
        if m.n_cables
    }


@compiled_when_eager_args("key", "q", "noise_mm")
def simulate_cable_lengths(
    key: Array, arm: Arm, q: ArrayLike, noise_mm: float | ArrayLike = 0.0
) -> dict[str, Array]:
    """Synthetic measured cable lengths ``{module: (..., n)}`` mm, with optional noise.

    Each length gets independent Gaussian noise of standard deviation ``noise_mm`` (0: exact).
    Jit- and vmap-able (``key`` is a PRNG key).
    """
    exact = arm_cable_lengths(arm, q)
    keys = jax.random.split(key, max(len(exact), 1))
    out = {}
    for k, (name, lengths) in zip(keys, exact.items(), strict=False):
        noise = jnp.asarray(noise_mm, lengths.dtype) * jax.random.normal(
            k, lengths.shape, lengths.dtype
        )
        out[name] = lengths + noise
    return out


def cable_length_table(lengths: Mapping[str, ArrayLike], arm: Arm) -> tuple[list[str], np.ndarray]:
    """Flatten ``{module: (m, n)}`` into CSV columns: ``(names, values (m, total))``.

    Columns follow the chain order of the modules, ``<module>.l1 ... <module>.lN`` each.
    """
    cols: list[str] = []
    blocks = []
    for m in arm.modules:
        if m.name in lengths:
            v = np.asarray(lengths[m.name], dtype=float)
            if v.ndim != 2 or v.shape[1] != m.n_cables:
                raise ValueError(
                    f"lengths[{m.name!r}] must be (m, {m.n_cables}), got shape {v.shape}"
                )
            cols.extend(cable_length_names(m))
            blocks.append(v)
    unknown = sorted(set(lengths) - {m.name for m in arm.modules})
    if unknown:
        raise ValueError(f"arm {arm.name!r} has no modules {unknown}; modules: {arm.module_names}")
    if not blocks:
        return cols, np.zeros((0, 0))
    return cols, np.concatenate(blocks, axis=1)


@dataclass(frozen=True)
class CableDataProblem:
    """One bad entry of a cable-length table.

    Attributes:
        row: row index (0-based) in the table.
        column: column index (0-based) among the module's cables, or ``None`` when the problem
            concerns the row's lengths together (no single column can be blamed).
        message: what is wrong, e.g. ``"negative cable length -3.0 mm"``.
    """

    row: int
    column: int | None
    message: str


def check_cable_lengths(
    module: Module,
    lengths: ArrayLike,
    *,
    residual_tol: float = DEFAULT_RESIDUAL_TOL,
) -> tuple[np.ndarray, np.ndarray, list[CableDataProblem]]:
    """Forward kinematics of a length table with per-row diagnostics (not jitted; numpy out).

    Args:
        module: a module with ``n`` cables.
        lengths: ``(m, n)`` measured lengths, mm.
        residual_tol: RMS residual (mm) above which a row is impossible.

    Returns:
        ``(states (m, dof), residual_rms (m,), problems)``: rows with a problem have NaN states.
        A table with the wrong number of columns gives a single problem with ``row = -1``.
    """
    n = module.n_cables
    if n == 0:
        raise ValueError(f"module {module.name!r} has no cables in the model")
    L = np.asarray(lengths, dtype=float)
    if L.ndim == 1:
        L = L[None, :]
    if L.ndim != 2 or L.shape[1] != n:
        got = L.shape[1] if L.ndim == 2 else L.shape
        return (
            np.full((L.shape[0] if L.ndim else 0, module.dof), np.nan),
            np.full(L.shape[0] if L.ndim else 0, np.nan),
            [
                CableDataProblem(
                    -1,
                    None,
                    f"module {module.name!r} has {n} cables, expected columns "
                    f"{', '.join(cable_length_names(module))}; got {got}",
                )
            ],
        )
    m = L.shape[0]
    problems: list[CableDataProblem] = []
    bad = np.zeros(m, bool)
    for i in range(m):
        for j in range(n):
            v = L[i, j]
            if not np.isfinite(v):
                problems.append(
                    CableDataProblem(i, j, f"cable length is {v} (not a finite number)")
                )
                bad[i] = True
                break
            if v <= 0:
                problems.append(
                    CableDataProblem(i, j, f"cable length {float(v):g} mm is not positive")
                )
                bad[i] = True
                break
    states = np.full((m, module.dof), np.nan)
    rms = np.full(m, np.nan)
    good = np.nonzero(~bad)[0]
    if good.size:
        # Solve every row (bad ones filled with a good row's lengths and ignored), so that the
        # compiled solver is reused for tables of the same shape.
        filled = np.where(bad[:, None], L[good[0]], L)
        sol, w = _fk(module, jnp.asarray(filled), residual_tol)
        sol, w = jax.tree_util.tree_map(lambda x: np.asarray(x)[good], (sol, w))
        st = np.asarray(sol.state)
        rr = np.asarray(sol.residual_rms)
        res = np.asarray(sol.residuals)
        w = np.asarray(w)
        codes = result_names(sol.result)
        for k, row in enumerate(good):
            rms[row] = rr[k]
            if codes[k] == "successful":
                states[row] = st[k]
                continue
            if codes[k] == "inconsistent_lengths":
                what = (
                    f"no pose of module {module.name!r} produces these cable lengths: RMS "
                    f"residual {rr[k]:.4g} mm > tolerance {residual_tol:g} mm"
                )
                if n - module.dof >= 2:
                    # The largest standardised residual points at a single bad length.
                    j = int(np.argmax(w[k]))
                    what += (
                        f"; this length is {-res[k, j]:+.4g} mm off the best-fitting pose (the "
                        "largest standardised misfit)"
                    )
                    problems.append(CableDataProblem(int(row), j, what))
                else:
                    what += (
                        f" (with {n} cables for {module.dof} degrees of freedom, one redundant "
                        "length, a misfit cannot be pinned to one column)"
                    )
                    problems.append(CableDataProblem(int(row), None, what))
            else:
                problems.append(
                    CableDataProblem(
                        int(row),
                        None,
                        f"forward kinematics of module {module.name!r} failed ({codes[k]}); "
                        f"RMS residual {rr[k]:.4g} mm",
                    )
                )
    problems.sort(key=lambda p: p.row)
    return states, rms, problems


@jit
def _fk_jit(module: Module, lengths: Array, residual_tol: Array):
    sol = cable_forward_kinematics(module, lengths, residual_tol=residual_tol)
    # Standardised residuals |r_i| / sqrt(1 - h_ii), h the hat matrix of the linearised fit:
    # for a single bad length the largest one is at that length (Baarda's data snooping).
    J = length_jacobian(module, sol.state)
    G = jnp.einsum("...ni,...nj->...ij", J, J)
    h = jnp.einsum("...ni,...ij,...nj->...n", J, small_inv(G), J)
    w = jnp.abs(sol.residuals) / jnp.sqrt(jnp.maximum(1.0 - h, 1e-12))
    return sol, w


def _fk(module: Module, lengths: Array, residual_tol: float):
    return _fk_jit(module, lengths, jnp.asarray(residual_tol, lengths.dtype))


def _where(source: str | None, row: str, column: str) -> str:
    loc = f"{row}, {'columns' if ', ' in column else 'column'} {column}"
    return f"{source}: {loc}" if source else loc


def module_states_from_cable_lengths(
    module: Module,
    lengths: ArrayLike,
    *,
    rows: Sequence[str] | None = None,
    columns: Sequence[str] | None = None,
    source: str | None = None,
    residual_tol: float = DEFAULT_RESIDUAL_TOL,
) -> np.ndarray:
    """Module states ``(m, dof)`` from a length table ``(m, n)``; ``ValueError`` on bad data.

    Args:
        module: the module (with cables).
        lengths: ``(m, n)`` measured lengths, mm.
        rows: label of each row for messages (default ``"row <i+1>"``).
        columns: name of each column (default ``<module>.l1 ...``).
        source: file name (or other origin) prefixed to messages.
        residual_tol: RMS residual (mm) above which a row is impossible.

    Raises:
        ValueError: for the first bad row, e.g. ``"m.csv: line 7, column shoulder.l3:
            cable length -2.0 mm is not positive"``.
    """
    states, _, problems = check_cable_lengths(module, lengths, residual_tol=residual_tol)
    if problems:
        p = problems[0]
        cols = list(columns) if columns is not None else list(cable_length_names(module))
        if p.row < 0:
            where = f"{source}: " if source else ""
            raise ValueError(f"{where}columns {', '.join(cols)}: {p.message}")
        label = rows[p.row] if rows is not None else f"row {p.row + 1}"
        col = ", ".join(cols) if p.column is None else cols[p.column]
        more = f" ({len(problems) - 1} more bad rows)" if len(problems) > 1 else ""
        raise ValueError(f"{_where(source, label, col)}: {p.message}{more}")
    return states


def arm_states_from_cable_lengths(
    arm: Arm,
    lengths: Mapping[str, ArrayLike],
    joint_states: Mapping[str, ArrayLike] | None = None,
    *,
    rows: Sequence[str] | None = None,
    columns: Mapping[str, Sequence[str]] | None = None,
    source: str | None = None,
    residual_tol: float = DEFAULT_RESIDUAL_TOL,
) -> np.ndarray:
    """Flat joint states ``(m, dof)`` in ``arm.state_names`` order from per-module data.

    Args:
        arm: the arm.
        lengths: ``{module: (m, n)}`` cable lengths (mm) of the modules measured by cables.
        joint_states: ``{module: (m, dof_i)}`` joint coordinates of the other modules.
        rows: labels of the ``m`` rows for messages (e.g. file line numbers).
        columns: ``{module: column names}`` of the length columns (default ``<module>.lN``).
        source: file name prefixed to messages.
        residual_tol: RMS residual (mm) above which a row of lengths is impossible.

    Raises:
        ValueError: a module is given twice or not at all, a table has the wrong shape, or a
            row of lengths is bad (the message names source, row and column).
    """
    joint_states = dict(joint_states or {})
    lengths = dict(lengths)
    known = set(arm.module_names)
    for name in list(lengths) + list(joint_states):
        if name not in known:
            raise ValueError(
                f"arm {arm.name!r} has no module {name!r}; modules: {arm.module_names}"
            )
    both = sorted(set(lengths) & set(joint_states))
    if both:
        raise ValueError(f"modules {both} given both as cable lengths and as joint states")
    missing = [n for n in arm.module_names if n not in lengths and n not in joint_states]
    if missing:
        raise ValueError(
            f"no state for modules {missing}: give their joint coordinates or cable lengths"
        )
    m_rows = {np.shape(v)[0] for v in list(lengths.values()) + list(joint_states.values())}
    if len(m_rows) != 1:
        raise ValueError(f"all modules need the same number of rows, got {sorted(m_rows)}")
    blocks = []
    for mod in arm.modules:
        if mod.name in lengths:
            cols = None if columns is None else columns.get(mod.name)
            blocks.append(
                module_states_from_cable_lengths(
                    mod,
                    lengths[mod.name],
                    rows=rows,
                    columns=cols,
                    source=source,
                    residual_tol=residual_tol,
                )
            )
        else:
            v = np.asarray(joint_states[mod.name], dtype=float)
            if v.ndim == 1 and mod.dof == 1:
                v = v[:, None]
            if v.ndim != 2 or v.shape[1] != mod.dof:
                raise ValueError(
                    f"joint_states[{mod.name!r}] must be (m, {mod.dof}) "
                    f"({', '.join(mod.state_names)}), got shape {v.shape}"
                )
            blocks.append(v)
    return np.concatenate(blocks, axis=1)
