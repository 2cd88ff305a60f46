"""Denavit-Hartenberg tables (CSV): a serial chain as an :class:`~cdra_jax.arm.Arm`.

File format: a header row (lines starting with ``#`` before it are comments, as in the
measurement file), then one row per joint, base to tip::

    # UR5, standard DH
    joint,type,a,alpha,d,theta,lower,upper
    shoulder_pan,revolute,0,1.5707963267948966,89.159,0,-3.14159,3.14159
    ...

Columns (any order; the names are fixed):

* ``joint``: the module name (unique; it makes the measurement-file column ``<joint>.q``);
* ``type``: ``revolute`` or ``prismatic``;
* ``a`` (mm), ``alpha`` (rad), ``d`` (mm), ``theta`` (rad): the link parameters. The joint
  variable adds to ``theta`` (revolute) or ``d`` (prismatic): the table's value is the joint's
  offset at ``q = 0``;
* optional ``lower``, ``upper``: joint limits (rad, or mm for prismatic); both columns or
  neither, and a row may leave both cells empty (default ``[-pi, pi]`` or ``[-100, 100]`` mm).

Conventions (``q`` the joint variable; ``Rz``, ``Tz``, ``Tx``, ``Rx`` elementary transforms):

* ``standard`` (Denavit-Hartenberg; row i holds ``a_i, alpha_i, d_i, theta_i``): link
  ``A_i = Rz(theta_i + q) Tz(d_i) Tx(a_i) Rx(alpha_i)`` (revolute). The model is
  ``F_0 = I``, module i rotating (or sliding) about ``z_{i-1}``, ``F_i = Rz(theta_i) Tz(d_i)
  Tx(a_i) Rx(alpha_i)``; the tool frame is DH frame K (the last row's ``x_K, z_K``).
* ``modified`` (Craig; row i holds ``a_{i-1}, alpha_{i-1}, d_i, theta_i``): link
  ``A_i = Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(theta_i + q) Tz(d_i)``. The model is
  ``F_{i-1} = Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(theta_i) Tz(d_i)``, module i about ``z_i``, and
  ``F_K = I``: the tool frame is DH frame K (the last joint's frame).

Frames are named ``base`` (``F_0``) and ``link1`` ... ``linkK`` (``F_i``, the body joint i
moves), made unique against the joint names. Edit the last frame of the model to add a tool.
"""

from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..arm import Arm, prismatic, revolute
from ..compilation import device_array
from .model import MAX_LENGTH_MM, RESERVED_MODULE_NAMES

CONVENTIONS = ("standard", "modified")
"""DH conventions: ``standard`` (Denavit-Hartenberg) and ``modified`` (Craig)."""
REQUIRED_COLUMNS = ("joint", "type", "a", "alpha", "d", "theta")
OPTIONAL_COLUMNS = ("lower", "upper")
_NAME_FORBIDDEN = frozenset('.,"')
_MAX_ANGLE = 1e3  # rad, as io.model


class DHFileError(ValueError):
    """A DH table is malformed; the message names the file, line and column."""


@dataclass(frozen=True)
class DHRow:
    """One joint of a DH table: ``a`` and ``d`` in mm, ``alpha`` and ``theta`` in rad, ``limits``
    ``(low, high)`` in rad or mm (``None``: the default)."""

    joint: str
    kind: str
    a: float
    alpha: float
    d: float
    theta: float
    limits: tuple[float, float] | None = None


def _rz(t: float) -> np.ndarray:
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=float)


def _rx(t: float) -> np.ndarray:
    c, s = math.cos(t), math.sin(t)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1]], dtype=float)


def _tz(d: float) -> np.ndarray:
    T = np.eye(4)
    T[2, 3] = d
    return T


def _tx(a: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = a
    return T


def dh_standard(a: float, alpha: float, d: float, theta: float) -> np.ndarray:
    """Standard DH link transform ``Rz(theta) Tz(d) Tx(a) Rx(alpha)``, ``(4, 4)``, mm."""
    return _rz(theta) @ _tz(d) @ _tx(a) @ _rx(alpha)


def dh_modified(a: float, alpha: float, d: float, theta: float) -> np.ndarray:
    """Modified (Craig) DH link transform ``Rx(alpha) Tx(a) Rz(theta) Tz(d)``, ``(4, 4)``, mm
    (``a``, ``alpha`` are the previous link's ``a_{i-1}``, ``alpha_{i-1}``)."""
    return _rx(alpha) @ _tx(a) @ _rz(theta) @ _tz(d)


def loads_dh(text: str, source: str = "<dh>") -> list[DHRow]:
    """Parse a DH table CSV text; errors name ``source``, the line and the column."""
    text = text.removeprefix("\ufeff")
    lines = text.splitlines()
    start = 0
    while start < len(lines) and (
        lines[start].lstrip().startswith("#") or not lines[start].strip()
    ):
        start += 1
    if start == len(lines):
        raise DHFileError(
            f"{source}: no header row (expected columns {','.join(REQUIRED_COLUMNS)})"
        )
    reader = csv.reader(io.StringIO("\n".join(lines[start:])))
    header = [h.strip() for h in next(reader)]
    hline = start + 1
    unknown = [h for h in header if h not in (*REQUIRED_COLUMNS, *OPTIONAL_COLUMNS)]
    if unknown:
        raise DHFileError(
            f"{source}: line {hline}: unknown column {unknown[0]!r}; columns are "
            f"{', '.join(REQUIRED_COLUMNS)} and optional {', '.join(OPTIONAL_COLUMNS)}"
        )
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise DHFileError(f"{source}: line {hline}: column {dup[0]!r} appears twice")
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise DHFileError(f"{source}: line {hline}: missing column {missing[0]!r}")
    if ("lower" in header) != ("upper" in header):
        raise DHFileError(f"{source}: line {hline}: give both 'lower' and 'upper' or neither")
    col = {h: i for i, h in enumerate(header)}
    rows: list[DHRow] = []
    for k, cells in enumerate(reader):
        line = hline + 1 + k
        if not cells or all(not c.strip() for c in cells) or cells[0].lstrip().startswith("#"):
            continue
        if len(cells) != len(header):
            raise DHFileError(
                f"{source}: line {line}: {len(cells)} cells, the header has {len(header)}"
            )
        cell = {h: cells[i].strip() for h, i in col.items()}
        name = cell["joint"]
        where = f"{source}: line {line}, column"
        bad = sorted({ch for ch in name if ch in _NAME_FORBIDDEN or not ch.isprintable()})
        if not name or bad or name in RESERVED_MODULE_NAMES:
            why = (
                "is empty"
                if not name
                else f"contains {' or '.join(map(repr, bad))}"
                if bad
                else "is reserved by the measurement file"
            )
            raise DHFileError(f"{where} 'joint': the joint name {name!r} {why}")
        if any(r.joint == name for r in rows):
            raise DHFileError(f"{where} 'joint': joint {name!r} appears twice")
        kind = cell["type"].lower()
        if kind not in ("revolute", "prismatic"):
            raise DHFileError(
                f"{where} 'type': expected revolute or prismatic, got {cell['type']!r}"
            )

        def number(
            c: str, bound: float, unit: str, *, line: int = line, cell: dict = cell
        ) -> float:
            try:
                v = float(cell[c])
            except ValueError:
                raise DHFileError(
                    f"{source}: line {line}, column {c!r}: expected a number ({unit}), "
                    f"got {cell[c]!r}"
                ) from None
            if not math.isfinite(v) or abs(v) > bound:
                raise DHFileError(
                    f"{source}: line {line}, column {c!r}: {cell[c]!r} is not a plausible value "
                    f"in {unit} (finite, at most {bound:g} in magnitude)"
                )
            return v

        a = number("a", MAX_LENGTH_MM, "mm")
        alpha = number("alpha", _MAX_ANGLE, "rad")
        d = number("d", MAX_LENGTH_MM, "mm")
        theta = number("theta", _MAX_ANGLE, "rad")
        limits = None
        if "lower" in cell and (cell["lower"] or cell["upper"]):
            unit, bound = ("mm", MAX_LENGTH_MM) if kind == "prismatic" else ("rad", _MAX_ANGLE)
            lo, hi = number("lower", bound, unit), number("upper", bound, unit)
            if not lo < hi:
                raise DHFileError(
                    f"{source}: line {line}, column 'upper': {hi} is not above lower {lo}"
                )
            limits = (lo, hi)
        rows.append(DHRow(name, kind, a, alpha, d, theta, limits))
    if not rows:
        raise DHFileError(f"{source}: no joint rows after the header (line {hline})")
    return rows


def load_dh(path: str | os.PathLike) -> list[DHRow]:
    """Read a DH table CSV file (see the module docstring for the columns)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise DHFileError(f"{path}: not a UTF-8 text file") from None
    return loads_dh(text, source=str(path))


def dh_chain(rows: list[DHRow], convention: str) -> np.ndarray:
    """The model's K+1 fixed frames ``(K+1, 4, 4)`` (mm) of a DH table (module docstring)."""
    if convention not in CONVENTIONS:
        raise ValueError(f"convention must be one of {', '.join(CONVENTIONS)}, got {convention!r}")
    if convention == "standard":
        frames = [np.eye(4)] + [dh_standard(r.a, r.alpha, r.d, r.theta) for r in rows]
    else:
        frames = [dh_modified(r.a, r.alpha, r.d, r.theta) for r in rows] + [np.eye(4)]
    return np.stack(frames)


def arm_from_dh(
    rows: list[DHRow], convention: str, name: str = "dh_arm", description: str = ""
) -> Arm:
    """The model of a DH table: modules about (or along) ``z`` named after the joints; the
    offsets ``theta`` (revolute) and ``d`` (prismatic) are in the fixed frames."""
    frames = dh_chain(rows, convention)
    mods = []
    for r in rows:
        kw = {} if r.limits is None else {"limits": r.limits}
        make = revolute if r.kind == "revolute" else prismatic
        mods.append(make(r.joint, np.array([0.0, 0.0, 1.0]), **kw))
    taken = {r.joint for r in rows}
    names = []
    for i in range(len(rows) + 1):
        n = "base" if i == 0 else f"link{i}"
        cand, k = n, 2
        while cand in taken:
            cand, k = f"{n}_{k}", k + 1
        taken.add(cand)
        names.append(cand)
    return Arm(
        frames=device_array(frames),
        modules=tuple(mods),
        frame_names=tuple(names),
        name=name,
        description=description,
    )
