"""Measurement files (CSV): module states and measured tool poses, one row per measured pose.

Format (see the README for a complete example)::

    # comment lines (starting with '#') may precede the header; they are kept
    pose,shoulder.rx,shoulder.ry,shoulder.rz,elbow.q,wrist.rx,wrist.ry,wrist.rz,measured.x,...
    p01,0.1,-0.2,0.3,1.2,0.0,0.1,-0.1,101.5,...

Columns (any order; the order is kept when the file is written back):

* ``pose``: a unique identifier, kept as text (``007`` stays ``007``).
* The state of every module of the arm, either joint coordinates, ``<module>.rx .ry .rz``
  (spherical: rotation vector of the platform in the module base frame, rad) or ``<module>.q``
  (revolute: rad; prismatic: mm), or cable lengths ``<module>.l1 ... <module>.lN`` (mm; recognised
  but not supported yet, see :mod:`.state_sources`).
* The measured tool pose in the world frame: ``measured.x .y .z`` (mm) and either
  ``measured.rx .ry .rz`` (rotation vector, rad) or ``measured.qw .qx .qy .qz`` (unit quaternion,
  scalar first). A quaternion whose norm is within 1e-6 of 1 is normalised for the pose
  matrix (the file values are kept as given); beyond that it is an error.
* Or points only: ``measured.x .y .z`` without orientation columns (or with the orientation cells
  of a row left empty) measure the tool-frame origin, and ``measured.<marker>.x .y .z`` the
  markers declared in the model (``[[markers]]``). An empty cell means the point was not seen in
  that row (occlusion); a point's three cells are all given or all empty; a row needs a full pose
  or at least one seen point. Files may mix full-pose rows and point rows.
* Optional auxiliaries: ``time_s``, ``approach.<module>`` (+1 or -1, the sign of the last motion),
  ``payload_kg``, ``temperature_c``.

Every cell except ``pose`` and the empty cells of measured points must be a finite number in
decimal notation (``1_0`` is not read as 10) of magnitude at most :data:`MAX_MAGNITUDE`; a pose
identifier holds no control characters.
Errors are :class:`MeasurementFileError` (a ``ValueError``) naming the file, the line and the
column. The reader accepts any number of rows; :func:`check_pose_count` enforces the
calibration's minimum of 4 distinct module configurations (Section IV, Eq. 9).

Writing is lossless: numbers are written with ``repr`` (the shortest text that reads back to
the same float64), identifiers and comments as given, columns in their order. Files are written
atomically and an existing file is only replaced with ``force=True``.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import os
import re
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import jax
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from .. import lie
from ..arm import Arm
from ..calibration.validation import MIN_POSES
from ..compilation import device_array, jit
from .files import write_text_atomic
from .rows import MeasurementFileError, RowContext
from .state_sources import STATE_SOURCES, StateSource

POSE_COLUMN = "pose"
POSITION_COLUMNS = ("measured.x", "measured.y", "measured.z")
ROTVEC_COLUMNS = ("measured.rx", "measured.ry", "measured.rz")
QUATERNION_COLUMNS = ("measured.qw", "measured.qx", "measured.qy", "measured.qz")
AUX_COLUMNS = ("time_s", "payload_kg", "temperature_c")
"""Auxiliary columns besides ``approach.<module>``."""
QUATERNION_TOL = 1e-6
ORIGIN = "origin"
"""The name of the tool-frame origin among :attr:`Measurements.point_names` (reserved: no marker
may be called so)."""
#: Largest accepted rotation-vector angle (rad).  Far beyond any rotation vector in radians
#: (even one written in degrees stays below ~312), and small enough that ``sin``/``cos`` of it
#: keep full double precision, so the rotation built from it is orthonormal to 1e-12.
ROTVEC_MAX_ANGLE = 1e3
"""A measured quaternion is accepted (and normalised) when ``| |q| - 1 | <= QUATERNION_TOL``."""
_ORTHO_TOL = 1e-6
MAX_MAGNITUDE = 1e7
"""Largest magnitude of any number in a measurement file: 10 km in mm (positions, cable lengths,
prismatic joints), far beyond any angle in radians or auxiliary value. A larger value is a typo
or a wrong unit, and would overflow the squared residuals of the solvers."""

Orientation = Literal["rotvec", "quaternion"]


@dataclass(frozen=True, eq=False)
class Measurements:
    """The content of a measurement file.

    Attributes:
        pose_ids: the ``pose`` identifiers, as text, ``(m,)``.
        q: module states ``(m, dof)`` in ``state_names`` order (``arm.state_names``).
        measured: measured tool poses ``(m, 4, 4)`` in the world frame (mm), or ``None`` for a
            pose plan without measured columns.
        aux: auxiliary columns (``time_s``, ``approach.<module>``, ``payload_kg``,
            ``temperature_c``) present in the file, name -> ``(m,)`` float array, as given.
        state_names: the column name of each entry of ``q``.
        columns: every column, in file order (``pose`` included); the order of writing.
        values: every numeric column as given in the file, name -> ``(m,)`` float array.
        comments: the ``#`` lines before the header, without the ``#`` (and one space after it).
        source: the file name (for messages).
        lines: 1-based line of each row in ``source`` (for messages), ``(m,)``.
        full_poses: ``(m, 4, 4)`` measured tool poses of the rows that measure one, NaN in the
            other rows, or ``None`` when no row does; equal to ``measured`` for a file of full
            poses only.
        points: ``(m, P, 3)`` measured points in the world frame (mm), NaN where a point was
            not seen (or, for the tool origin, where the row measures a full pose), or ``None``
            for a file of full poses only.
        point_names: the ``P`` point names: :data:`ORIGIN` (``measured.x/y/z`` of the rows
            without orientation) and the markers (``measured.<marker>.x/y/z``).
    """

    pose_ids: tuple[str, ...]
    q: np.ndarray
    measured: np.ndarray | None
    aux: Mapping[str, np.ndarray]
    state_names: tuple[str, ...]
    columns: tuple[str, ...]
    values: Mapping[str, np.ndarray]
    comments: tuple[str, ...] = ()
    source: str = "<measurements>"
    lines: tuple[int, ...] = field(default=())
    full_poses: np.ndarray | None = None
    points: np.ndarray | None = None
    point_names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        m = len(self.pose_ids)
        if self.full_poses is None and self.measured is not None:
            object.__setattr__(self, "full_poses", self.measured)
        if self.points is not None and self.points.shape != (m, len(self.point_names), 3):
            raise ValueError(
                f"Measurements: points must be ({m}, {len(self.point_names)}, 3), "
                f"got {self.points.shape}"
            )
        if self.q.shape != (m, len(self.state_names)):
            raise ValueError(
                f"Measurements: q must be (m, dof) = ({m}, {len(self.state_names)}), "
                f"got {self.q.shape}"
            )
        if self.measured is not None and self.measured.shape != (m, 4, 4):
            raise ValueError(
                f"Measurements: measured must be ({m}, 4, 4), got {self.measured.shape}"
            )
        numeric = [c for c in self.columns if c != POSE_COLUMN]
        if sorted(numeric) != sorted(self.values) or POSE_COLUMN not in self.columns:
            raise ValueError(
                f"Measurements: columns {self.columns} do not match values {tuple(self.values)}"
            )
        if not self.lines:
            object.__setattr__(self, "lines", tuple(range(1, m + 1)))

    def __len__(self) -> int:
        return len(self.pose_ids)

    @property
    def m(self) -> int:
        """Number of poses (rows)."""
        return len(self.pose_ids)

    @property
    def has_measurements(self) -> bool:
        """Whether any row measures a pose or a point (a pose plan does not)."""
        return self.full_poses is not None or self.points is not None

    @property
    def pose_rows(self) -> np.ndarray:
        """``(m,)`` bool: the rows that measure a full tool pose."""
        if self.full_poses is None:
            return np.zeros(self.m, bool)
        return np.all(np.isfinite(self.full_poses), axis=(-2, -1))

    @property
    def orientation(self) -> Orientation | None:
        """How the measured orientation is given: ``"rotvec"``, ``"quaternion"`` or ``None``."""
        if ROTVEC_COLUMNS[0] in self.values:
            return "rotvec"
        if QUATERNION_COLUMNS[0] in self.values:
            return "quaternion"
        return None

    def select(self, rows: Sequence[int] | np.ndarray) -> Measurements:
        """The measurements of the given rows (indices or a boolean mask), in that order."""
        rows = np.asarray(rows)
        if rows.size == 0:
            rows = rows.astype(int)  # [] is a float array, which numpy refuses as an index
        if rows.dtype != bool and not np.issubdtype(rows.dtype, np.integer):
            raise ValueError(
                f"Measurements.select: rows must be integer indices or a boolean mask, got "
                f"dtype {rows.dtype}"
            )
        idx = np.arange(self.m)[rows]
        return dataclasses.replace(
            self,
            pose_ids=tuple(self.pose_ids[i] for i in idx),
            q=self.q[idx],
            measured=None if self.measured is None else self.measured[idx],
            full_poses=None if self.full_poses is None else self.full_poses[idx],
            points=None if self.points is None else self.points[idx],
            aux={k: v[idx] for k, v in self.aux.items()},
            values={k: v[idx] for k, v in self.values.items()},
            lines=tuple(self.lines[i] for i in idx),
        )

    @classmethod
    def from_arrays(
        cls,
        arm: Arm,
        q: ArrayLike,
        measured: ArrayLike | None = None,
        *,
        pose_ids: Sequence[str] | None = None,
        orientation: Orientation = "rotvec",
        aux: Mapping[str, ArrayLike] | None = None,
        comments: Iterable[str] = (),
        cable_lengths: Mapping[str, ArrayLike] | None = None,
        points: Mapping[str, ArrayLike] | None = None,
    ) -> Measurements:
        """Measurements from arrays (joint coordinates; measured orientation as ``orientation``).

        Args:
            arm: the model (gives the state columns and module names).
            q: ``(m, dof)`` module states in ``arm.state_names`` order.
            measured: ``(m, 4, 4)`` measured tool poses, or ``None`` (a pose plan); with
                ``points``, rows all NaN where a row measures no full pose.
            pose_ids: ``m`` unique non-empty identifiers (default ``p01``, ``p02``, ...).
            orientation: write the measured rotation as ``"rotvec"`` or ``"quaternion"``
                (``qw >= 0``).
            aux: auxiliary columns, name -> ``(m,)``.
            comments: comment lines (without ``#``).
            cable_lengths: ``{module: (m, n)}`` measured cable lengths (mm); those modules are
                written as ``<module>.l1 ... <module>.lN`` columns instead of joint coordinates
                (``q`` is kept as the states the lengths were measured at).
            points: ``{name: (m, 3)}`` measured points (mm, world frame), a row all NaN where
                the point was not seen: :data:`ORIGIN` for the tool-frame origin (rows without
                a full pose) and markers declared in ``arm.markers``.
        """
        q = np.asarray(q, dtype=float)
        if q.ndim != 2 or q.shape[1] != arm.dof:
            raise ValueError(
                f"q must have shape (m, {arm.dof}) with columns {arm.state_names}, got {q.shape}"
            )
        m = q.shape[0]
        if pose_ids is None:
            width = max(2, len(str(m)))
            pose_ids = [f"p{i + 1:0{width}d}" for i in range(m)]
        pose_ids = tuple(str(p) for p in pose_ids)
        if len(pose_ids) != m:
            raise ValueError(f"pose_ids: expected {m} identifiers, got {len(pose_ids)}")
        _check_ids(pose_ids, lambda i, what: ValueError(f"pose_ids[{i}]: {what}"))
        if not np.all(np.isfinite(q)):
            raise ValueError("q contains NaN or inf")
        values: dict[str, np.ndarray] = {n: q[:, j].copy() for j, n in enumerate(arm.state_names)}
        columns = [POSE_COLUMN]
        cables = dict(cable_lengths or {})
        for mod in arm.modules:
            if mod.name not in cables:
                columns += mod.state_names
                continue
            L = np.asarray(cables.pop(mod.name), dtype=float)
            if L.shape != (m, mod.n_cables) or mod.n_cables == 0:
                raise ValueError(
                    f"cable_lengths[{mod.name!r}]: expected shape ({m}, {mod.n_cables}) "
                    f"(module cables in the model), got {L.shape}"
                )
            for n in mod.state_names:
                del values[n]
            for j in range(mod.n_cables):
                values[f"{mod.name}.l{j + 1}"] = L[:, j].copy()
                columns.append(f"{mod.name}.l{j + 1}")
        if cables:
            raise ValueError(f"cable_lengths: unknown modules {sorted(cables)}")
        pts = {name: np.asarray(v, dtype=float) for name, v in (points or {}).items()}
        for name, v in pts.items():
            if name != ORIGIN:
                arm.marker(name)
            if v.shape != (m, 3) or np.any(np.isnan(v).any(-1) != np.isnan(v).all(-1)):
                raise ValueError(
                    f"points[{name!r}]: expected ({m}, 3) positions (mm), a row all NaN where "
                    f"the point was not seen, got shape {v.shape}"
                )
            if not np.all(np.isfinite(v) | np.isnan(v)):
                raise ValueError(f"points[{name!r}]: contains inf")
        T = None
        pose_rows = np.zeros(m, bool)
        if measured is not None:
            T = np.asarray(measured, dtype=float)
            _check_poses(T, m, allow_missing=bool(pts))
            pose_rows = np.all(np.isfinite(T), axis=(-2, -1))
        if pts or T is not None:
            origin = pts.get(ORIGIN, np.full((m, 3), np.nan))
            both = pose_rows & np.isfinite(origin[:, 0])
            if np.any(both):
                raise ValueError(
                    f"points[{ORIGIN!r}] and measured both give row {int(np.flatnonzero(both)[0])}"
                    "'s tool position; give one"
                )
        if T is not None or ORIGIN in pts:
            xyz = np.where(pose_rows[:, None], np.full((m, 3), np.nan), origin)
            if T is not None:
                xyz = np.where(pose_rows[:, None], T[:, :3, 3], xyz)
            for j, n in enumerate(POSITION_COLUMNS):
                values[n] = xyz[:, j].copy()
            columns += list(POSITION_COLUMNS)
        if T is not None:
            safe = np.where(pose_rows[:, None, None], T, np.eye(4))
            rv, quat = _float64(_rotvec_quaternion, safe)
            names: tuple[str, ...]
            if orientation == "rotvec":
                rot, names = rv, ROTVEC_COLUMNS
            elif orientation == "quaternion":
                rot = np.where(quat[:, :1] < 0, -quat, quat)
                names = QUATERNION_COLUMNS
            else:
                raise ValueError(
                    f"orientation must be 'rotvec' or 'quaternion', got {orientation!r}"
                )
            rot = np.where(pose_rows[:, None], rot, np.nan)
            for j, n in enumerate(names):
                values[n] = rot[:, j]
            columns += names
        for name, v in pts.items():
            if name == ORIGIN:
                continue
            for j, c in enumerate("xyz"):
                values[f"measured.{name}.{c}"] = v[:, j].copy()
                columns.append(f"measured.{name}.{c}")
        point_names, point_array = _point_table(arm, values, pose_rows)
        if point_names and T is None:
            T = np.full((m, 4, 4), np.nan)
        if point_names:
            seen = np.isfinite(point_array[..., 0]).any(-1) | pose_rows
            if not np.all(seen):
                raise ValueError(
                    f"row {int(np.flatnonzero(~seen)[0])} measures neither a full pose nor a point"
                )
        aux_out: dict[str, np.ndarray] = {}
        for name, column in (aux or {}).items():
            if not _is_aux(name, arm):
                raise ValueError(f"aux: unknown auxiliary column {name!r}; known: {_aux_text(arm)}")
            a = np.asarray(column, dtype=float)
            if a.shape != (m,) or not np.all(np.isfinite(a)):
                raise ValueError(f"aux[{name!r}]: expected {m} finite numbers, got shape {a.shape}")
            if name.startswith("approach.") and not np.all(np.abs(a) == 1.0):
                raise ValueError(f"aux[{name!r}]: approach directions must be +1 or -1")
            aux_out[name] = a.copy()
            values[name] = aux_out[name]
            columns.append(name)
        return cls(
            pose_ids=pose_ids,
            q=q.copy(),
            measured=T if not point_names else None,
            full_poses=None if T is None or not pose_rows.any() else T,
            points=point_array if point_names else None,
            point_names=point_names,
            aux=aux_out,
            state_names=arm.state_names,
            columns=tuple(columns),
            values=values,
            comments=tuple(comments),
            source="<arrays>",
        )


def _float64(fn, *args) -> tuple[np.ndarray, ...]:
    """``fn(*args)`` computed in float64 whatever JAX's global setting (reading and writing
    files is lossless also where ``jax_enable_x64`` is off), as numpy arrays."""
    with jax.enable_x64(True):
        out = fn(*(device_array(np.asarray(a, dtype=np.float64)) for a in args))
        leaves = out if isinstance(out, tuple) else (out,)
        return tuple(np.asarray(a, dtype=np.float64) for a in leaves)


# Compiled once per row count: much faster than dispatching the small ops one by one.
@jit
def _poses_from_quaternion(xyz: Array, quat: Array) -> Array:
    return lie.make_pose(lie.quaternion_to_rotation(quat), xyz)


@jit
def _rotvec_quaternion(T: Array) -> tuple[Array, Array]:
    return lie.so3_log(lie.rotation(T)), lie.rotation_to_quaternion(lie.rotation(T))


def rigid_transform_problem(T: ArrayLike, tol: float = _ORTHO_TOL) -> str | None:
    """What keeps a 4x4 matrix from being a rigid transform ``[[R, p], [0, 1]]``, or ``None``.

    Checks the shape, finiteness, the last row, orthonormality of ``R`` (``max |R^T R - I|``
    up to ``tol``) and handedness (``det R = +1``; a reflection is a left-handed frame).
    """
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        return f"expected a 4x4 matrix, got shape {T.shape}"
    if not np.all(np.isfinite(T)):
        return "contains NaN or inf"
    if np.any(T[3] != np.array([0.0, 0.0, 0.0, 1.0])):
        return f"last row must be [0, 0, 0, 1], got {T[3].tolist()}"
    R = T[:3, :3]
    dev = float(np.abs(R.T @ R - np.eye(3)).max())
    if dev > tol:
        return (
            f"rotation block is not orthonormal (max |R^T R - I| = {dev:.2e}): a scaled or "
            "sheared matrix, or one written with too few digits?"
        )
    if np.linalg.det(R) < 0:
        return (
            "rotation block is a reflection (det R = -1, a left-handed frame): is one axis of "
            "the measuring device or of the exported frame flipped?"
        )
    return None


def _check_poses(T: np.ndarray, m: int, allow_missing: bool = False) -> None:
    if T.shape != (m, 4, 4):
        raise ValueError(f"measured must have shape ({m}, 4, 4), got {T.shape}")
    for i in range(m):
        if allow_missing and np.all(np.isnan(T[i])):
            continue
        problem = rigid_transform_problem(T[i])
        if problem:
            raise ValueError(
                f"measured[{i}]: measured poses must be rigid transforms [[R, p], [0, 1]]; "
                f"{problem}"
            )


def _point_table(
    arm: Arm, values: Mapping[str, np.ndarray], pose_rows: np.ndarray
) -> tuple[tuple[str, ...], np.ndarray]:
    """``(point_names, (m, P, 3))`` from the measured columns in ``values`` (NaN = not seen).

    The tool origin is a point of the rows without a full pose; markers follow in the model's
    order. Empty when the file has full poses only.
    """
    m = pose_rows.shape[0]
    names: list[str] = []
    cols: list[np.ndarray] = []
    if POSITION_COLUMNS[0] in values and not np.all(pose_rows):
        xyz = np.stack([values[c] for c in POSITION_COLUMNS], axis=-1)
        names.append(ORIGIN)
        cols.append(np.where(pose_rows[:, None], np.nan, xyz))
    for mk in arm.markers:
        keys = [f"measured.{mk.name}.{c}" for c in "xyz"]
        if keys[0] in values:
            names.append(mk.name)
            cols.append(np.stack([values[k] for k in keys], axis=-1))
    if not names:
        return (), np.zeros((m, 0, 3))
    return tuple(names), np.stack(cols, axis=1)


def _check_ids(ids: Sequence[str], err) -> None:
    seen: dict[str, int] = {}
    for i, p in enumerate(ids):
        if not p.strip():
            raise err(i, "empty pose identifier")
        if p in seen:
            raise err(i, f"duplicate pose identifier {p!r} (first used in row {seen[p] + 1})")
        seen[p] = i


def _is_aux(name: str, arm: Arm) -> bool:
    if name in AUX_COLUMNS:
        return True
    return name.startswith("approach.") and name[len("approach.") :] in arm.module_names


def aux_columns(arm: Arm) -> tuple[str, ...]:
    """Every auxiliary column a measurement file of ``arm`` may have."""
    return (*AUX_COLUMNS, *(f"approach.{m}" for m in arm.module_names))


def _aux_text(arm: Arm) -> str:
    return ", ".join(aux_columns(arm))


def _columns_text(arm: Arm) -> str:
    parts = [POSE_COLUMN]
    for mod in arm.modules:
        parts.append(" | ".join(s.expected_text(mod) for s in STATE_SOURCES))
    parts += [
        ", ".join(POSITION_COLUMNS),
        ", ".join(ROTVEC_COLUMNS) + " | " + ", ".join(QUATERNION_COLUMNS),
    ]
    parts.append("optional " + _aux_text(arm))
    return "; ".join(parts)


def _checked_records(reader: Iterator[list[str]], feed: _Lines, source: str):
    """The records of ``reader``; a malformed record (``csv.Error``, e.g. a cell beyond the
    csv module's field size limit) becomes a :class:`MeasurementFileError` at its line."""
    while True:
        try:
            row = next(reader)
        except StopIteration:
            return
        except csv.Error as e:
            raise MeasurementFileError(
                source, f"malformed CSV record: {e}", line=feed.record_start
            ) from None
        yield row


class _Lines:
    """Feeds lines to ``csv.reader`` and remembers the first physical line of each record."""

    def __init__(self, lines: Sequence[str], first_line: int):
        self._lines = lines
        self._i = 0
        self.first_line = first_line  # 1-based line number of _lines[0]
        self.record_start = first_line
        self.record_text = ""
        self._in_record = False

    def __iter__(self) -> Iterator[str]:
        return self

    def __next__(self) -> str:
        if self._i >= len(self._lines):
            raise StopIteration
        line = self._lines[self._i]
        if not self._in_record:
            self.record_start = self.first_line + self._i
            self.record_text = line
            self._in_record = True
        self._i += 1
        return line

    def end_record(self) -> None:
        self._in_record = False


def loads_measurements(
    text: str, arm: Arm, *, source: str = "<measurements>", require_measured: bool = True
) -> Measurements:
    """Parse measurement CSV text for the model ``arm`` (see the module docstring).

    Args:
        text: the file content.
        arm: the model; gives the module names, kinds and the order of ``q``.
        source: file name used in error messages.
        require_measured: demand the measured tool pose columns. With ``False`` a file without
            any ``measured.*`` column (a pose plan) gives ``measured = None``.

    Raises:
        MeasurementFileError: malformed content (message names the file, line and column).
    """
    if text.startswith("\ufeff"):
        text = text[1:]  # a UTF-8 byte-order mark, as spreadsheet programs write
    # Split lines the way the csv module does (\n, \r\n or \r), so line numbers agree.
    lines = io.StringIO(text, newline="").readlines()
    comments: list[str] = []
    h = 0
    while h < len(lines) and (not lines[h].strip() or lines[h].lstrip().startswith("#")):
        s = lines[h].strip()
        if s:
            c = s[1:]
            comments.append(c[1:] if c.startswith(" ") else c)
        h += 1
    if h == len(lines):
        raise MeasurementFileError(
            source,
            f"missing header row (the file has no lines besides comments); expected "
            f"columns: {_columns_text(arm)}",
        )
    header_line = h + 1
    feed = _Lines(lines[h:], header_line)
    reader = _checked_records(csv.reader(feed), feed, source)
    header = [c.strip() for c in next(reader)]
    feed.end_record()
    ctx = RowContext(source, header_line, ())
    layout = _parse_header(header, arm, ctx, require_measured)

    ids: list[str] = []
    row_lines: list[int] = []
    cells: list[list[float]] = []
    seen: dict[str, int] = {}
    numeric = [(j, c) for j, c in enumerate(header) if c != POSE_COLUMN]
    pose_j = header.index(POSE_COLUMN)
    for row in reader:
        start, raw = feed.record_start, feed.record_text
        feed.end_record()
        if not row or (len(row) == 1 and not row[0].strip() and len(header) > 1):
            continue  # a blank line
        if raw.lstrip().startswith("#"):
            raise MeasurementFileError(
                source,
                "comment line after the header; '#' lines are only allowed before it",
                line=start,
            )
        if len(row) != len(header):
            raise MeasurementFileError(
                source,
                f"expected {len(header)} fields (one per header column), got {len(row)}",
                line=start,
                column=header[len(row)] if len(row) < len(header) else None,
            )
        pid = row[pose_j]
        if not pid.strip():
            raise MeasurementFileError(
                source, "empty pose identifier", line=start, column=POSE_COLUMN
            )
        if any(ord(c) < 32 or ord(c) == 127 for c in pid):
            raise MeasurementFileError(
                source,
                f"pose identifier {pid!r} contains a control character; use printable text",
                line=start,
                column=POSE_COLUMN,
            )
        if pid in seen:
            raise MeasurementFileError(
                source,
                f"duplicate pose identifier {pid!r} (first used on line {seen[pid]})",
                line=start,
                column=POSE_COLUMN,
            )
        seen[pid] = start
        vals = []
        for j, name in numeric:
            cell = row[j]
            if name in layout.optional and not cell.strip():
                vals.append(math.nan)  # a measured value not given in this row (occlusion)
                continue
            try:
                v = parse_number(cell)
            except ValueError:
                what = "empty cell" if not cell.strip() else f"not a number: {cell!r}"
                raise MeasurementFileError(source, what, line=start, column=name) from None
            if not math.isfinite(v):
                raise MeasurementFileError(
                    source,
                    f"{cell.strip()!r} is not a finite number (NaN and inf are not allowed)",
                    line=start,
                    column=name,
                )
            if abs(v) > MAX_MAGNITUDE:
                raise MeasurementFileError(
                    source,
                    f"{cell.strip()!r} is beyond {MAX_MAGNITUDE:g} in magnitude: not a plausible "
                    "length (mm), angle (rad) or auxiliary value; check for a typo or a wrong unit",
                    line=start,
                    column=name,
                )
            vals.append(v)
        ids.append(pid)
        row_lines.append(start)
        cells.append(vals)

    m = len(ids)
    table = np.asarray(cells, dtype=float).reshape(m, len(numeric))
    values = {name: table[:, k].copy() for k, (_, name) in enumerate(numeric)}
    ctx = RowContext(source, header_line, tuple(row_lines))

    q_parts = []
    for mod, (src, suffixes) in zip(arm.modules, layout.states, strict=True):
        cols = np.stack([values[f"{mod.name}.{s}"] for s in suffixes], axis=-1)
        qm = np.asarray(src.to_state(mod, cols, ctx), dtype=float)
        if qm.shape != (m, mod.dof):
            raise ValueError(
                f"state source {type(src).__name__} returned {qm.shape}, not {(m, mod.dof)}"
            )
        q_parts.append(qm)
    q = np.concatenate(q_parts, axis=-1) if q_parts else np.zeros((m, 0))

    aux = {name: values[name] for name in layout.aux}
    for name in layout.aux:
        if name.startswith("approach."):
            bad = np.flatnonzero(np.abs(values[name]) != 1.0)
            if bad.size:
                raise ctx.error(
                    f"approach direction must be +1 or -1, got {values[name][bad[0]]:g}",
                    column=name,
                    row=int(bad[0]),
                )

    measured = None
    pose_rows = np.zeros(m, bool)
    for group in _measured_groups(layout):
        given = np.isfinite(np.stack([values[c] for c in group], axis=-1))
        partial = np.flatnonzero(given.any(-1) & ~given.all(-1))
        if partial.size:
            k = int(partial[0])
            raise ctx.error(
                f"empty cell: {', '.join(group)} are given together or left empty together "
                "(all empty: the point was not seen in this row)",
                column=group[int(np.argmin(given[k]))],
                row=k,
            )
    if layout.orientation is not None:
        rot_cols = ROTVEC_COLUMNS if layout.orientation == "rotvec" else QUATERNION_COLUMNS
        pose_rows = np.isfinite(values[rot_cols[0]])
        no_position = np.flatnonzero(pose_rows & ~np.isfinite(values[POSITION_COLUMNS[0]]))
        if no_position.size:
            raise ctx.error(
                "a measured orientation needs the measured position (measured.x/y/z) of the "
                "same row; this row leaves it empty",
                column=POSITION_COLUMNS[0],
                row=int(no_position[0]),
            )
    if layout.orientation is not None and pose_rows.any():
        xyz = np.stack([values[c] for c in POSITION_COLUMNS], axis=-1)[pose_rows]
        first = np.flatnonzero(pose_rows)
        if layout.orientation == "rotvec":
            rv = np.stack([values[c] for c in ROTVEC_COLUMNS], axis=-1)[pose_rows]
            angle = np.linalg.norm(rv, axis=-1)
            bad = np.flatnonzero(~(angle <= ROTVEC_MAX_ANGLE))
            if bad.size:
                k = int(bad[0])
                j = int(np.argmax(np.abs(rv[k])))
                raise ctx.error(
                    f"rotation vector (measured.rx, .ry, .rz) = {tuple(rv[k].tolist())} has an "
                    f"angle of {angle[k]:.4g} rad, above the limit {ROTVEC_MAX_ANGLE:g} rad: "
                    "not a rotation vector in radians (a position or a value in another unit "
                    "in this column?)",
                    column=ROTVEC_COLUMNS[j],
                    row=int(first[k]),
                )
            (poses,) = _float64(lie.from_xyz_rotvec, xyz, rv)
        else:
            quat = np.stack([values[c] for c in QUATERNION_COLUMNS], axis=-1)[pose_rows]
            norm = np.linalg.norm(quat, axis=-1)
            bad = np.flatnonzero(np.abs(norm - 1.0) > QUATERNION_TOL)
            if bad.size:
                k = int(bad[0])
                raise ctx.error(
                    f"quaternion (measured.qw, .qx, .qy, .qz) = {tuple(quat[k].tolist())} is not "
                    f"unit: its norm {norm[k]:.7g} differs from 1 by {abs(norm[k] - 1.0):.3g} "
                    f"(tolerance {QUATERNION_TOL:g})",
                    column=QUATERNION_COLUMNS[0],
                    row=int(first[k]),
                )
            (poses,) = _float64(_poses_from_quaternion, xyz, quat / norm[:, None])
        measured = np.full((m, 4, 4), np.nan)
        measured[pose_rows] = poses
    elif layout.orientation is not None:
        measured = np.full((m, 4, 4), np.nan)  # no rows
    point_names, point_array = _point_table(arm, values, pose_rows)
    if point_names:
        empty = np.flatnonzero(~(np.isfinite(point_array[..., 0]).any(-1) | pose_rows))
        if empty.size:
            raise ctx.error(
                "the row measures nothing: every measured cell is empty; a row needs a full pose "
                "or at least one seen point",
                column=_measured_groups(layout)[0][0],
                row=int(empty[0]),
            )
    full_poses = measured if pose_rows.any() or (m == 0 and measured is not None) else None

    return Measurements(
        pose_ids=tuple(ids),
        q=q,
        measured=None if point_names else full_poses,
        full_poses=full_poses,
        points=point_array if point_names else None,
        point_names=point_names,
        aux=aux,
        state_names=arm.state_names,
        columns=tuple(header),
        values=values,
        comments=tuple(comments),
        source=source,
        lines=tuple(row_lines),
    )


@dataclass(frozen=True)
class _Layout:
    states: list[tuple[StateSource, tuple[str, ...]]]
    aux: list[str]
    orientation: Orientation | None
    origin: bool = False
    markers: tuple[str, ...] = ()

    @property
    def optional(self) -> frozenset[str]:
        """The columns whose cells may be empty: the measured ones (a point not seen in a row,
        or a row that measures points but no orientation)."""
        return frozenset(c for g in _measured_groups(self) for c in g)


def _measured_groups(layout: _Layout) -> list[tuple[str, ...]]:
    """The measured columns that are given or left empty together, row by row."""
    groups: list[tuple[str, ...]] = []
    if layout.origin:
        groups.append(POSITION_COLUMNS)
    if layout.orientation == "rotvec":
        groups.append(ROTVEC_COLUMNS)
    elif layout.orientation == "quaternion":
        groups.append(QUATERNION_COLUMNS)
    groups += [tuple(f"measured.{name}.{c}" for c in "xyz") for name in layout.markers]
    return groups


def _parse_header(header: list[str], arm: Arm, ctx: RowContext, require_measured: bool) -> _Layout:
    source = ctx.source

    def err(what: str, column: str | None = None) -> MeasurementFileError:
        return ctx.error(what, column=column)

    for sep, name in ((";", "';'"), ("\t", "tabs")):
        if len(header) == 1 and sep in header[0]:
            raise MeasurementFileError(
                source,
                f"columns must be separated by commas; this header row uses {name}",
                line=ctx.header_line,
            )
    if POSE_COLUMN not in header:
        looks_like_data = any(_is_number(c) for c in header)
        if looks_like_data:
            raise MeasurementFileError(
                source,
                "missing header row: the first line that is not a comment holds data; it must "
                f"name the columns: {_columns_text(arm)}",
                line=ctx.header_line,
            )
        raise err(f"missing column 'pose'; expected columns: {_columns_text(arm)}", POSE_COLUMN)
    seen: set[str] = set()
    for c in header:
        if not c:
            raise err("empty column name in the header row")
        if c in seen:
            raise err("column appears twice in the header row", c)
        seen.add(c)

    per_module: dict[str, list[str]] = {m: [] for m in arm.module_names}
    aux: list[str] = []
    measured: list[str] = []
    known_measured = POSITION_COLUMNS + ROTVEC_COLUMNS + QUATERNION_COLUMNS
    for c in header:
        if c == POSE_COLUMN:
            continue
        if c in AUX_COLUMNS:
            aux.append(c)
        elif c.startswith("measured."):
            if c not in known_measured and not _is_marker_column(c, arm):
                raise err(
                    f"unknown column; measured columns are {', '.join(known_measured)}"
                    + (
                        " and measured.<marker>.x/y/z for the model's markers "
                        + ", ".join(mk.name for mk in arm.markers)
                        if arm.markers
                        else " (marker columns measured.<marker>.x/y/z need the marker "
                        "declared in the model's [[markers]])"
                    ),
                    c,
                )
            measured.append(c)
        elif c.startswith("approach."):
            target = c[len("approach.") :]
            if target not in arm.module_names:
                raise err(
                    f"unknown module {target!r} in an approach column; modules of arm "
                    f"{arm.name!r}: {', '.join(arm.module_names)}",
                    c,
                )
            aux.append(c)
        elif "." in c:
            prefix, suffix = c.split(".", 1)
            if prefix not in per_module:
                raise err(
                    f"unknown module {prefix!r} in the column prefix; modules of arm {arm.name!r}: "
                    f"{', '.join(arm.module_names)}",
                    c,
                )
            per_module[prefix].append(suffix)
        else:
            raise err(f"unknown column; expected columns: {_columns_text(arm)}", c)

    states: list[tuple[StateSource, tuple[str, ...]]] = []
    for mod in arm.modules:
        suffixes = per_module[mod.name]
        options = " or ".join(f"{s.description} {s.expected_text(mod)}" for s in STATE_SOURCES)
        if not suffixes:
            first = STATE_SOURCES[0].expected_text(mod).split(", ")[0]
            raise err(
                f"missing columns for module {mod.name!r} ({mod.kind}): give {options}", first
            )
        claimed: dict[int, list[str]] = {}
        for s in suffixes:
            owners = [i for i, src in enumerate(STATE_SOURCES) if src.claims(mod, s)]
            if not owners:
                raise err(
                    f"unknown column for module {mod.name!r} ({mod.kind}); give {options}",
                    f"{mod.name}.{s}",
                )
            claimed.setdefault(owners[0], []).append(s)
        if len(claimed) > 1:
            kinds = [STATE_SOURCES[i] for i in claimed]
            raise err(
                f"module {mod.name!r} has both {kinds[0].description} and {kinds[1].description} "
                "columns; give one of them",
                f"{mod.name}.{claimed[next(iter(claimed))][0]}",
            )
        src = STATE_SOURCES[next(iter(claimed))]
        states.append((src, src.columns(mod, suffixes, ctx)))

    orientation: Orientation | None = None
    marker_cols = [c for c in measured if c.count(".") == 2]
    markers: list[str] = []
    for c in marker_cols:
        name = c.split(".")[1]
        if name not in markers:
            markers.append(name)
    for name in markers:
        for axis in "xyz":
            if f"measured.{name}.{axis}" not in measured:
                raise err(
                    f"missing column measured.{name}.{axis} (marker {name!r} needs x, y and z, mm)",
                    f"measured.{name}.{axis}",
                )
    markers = [mk.name for mk in arm.markers if mk.name in markers]  # the model's order
    pose_cols = [c for c in measured if c not in marker_cols]
    origin = any(c in POSITION_COLUMNS for c in pose_cols)
    if pose_cols or (require_measured and not markers):
        for c in POSITION_COLUMNS:
            if c not in measured:
                raise err(f"missing column {c} (measured tool position, mm)", c)
        has_rv = [c for c in ROTVEC_COLUMNS if c in measured]
        has_q = [c for c in QUATERNION_COLUMNS if c in measured]
        if has_rv and has_q:
            raise err(
                "both orientation column sets are present (measured.rx/ry/rz and "
                "measured.qw/qx/qy/qz); give exactly one",
                has_q[0],
            )
        if has_rv or has_q:
            need = ROTVEC_COLUMNS if has_rv else QUATERNION_COLUMNS
            for c in need:
                if c not in measured:
                    raise err(f"missing column {c} (the orientation needs {', '.join(need)})", c)
            orientation = "rotvec" if has_rv else "quaternion"
    return _Layout(states, aux, orientation, origin, tuple(markers))


def _is_marker_column(column: str, arm: Arm) -> bool:
    parts = column.split(".")
    return (
        len(parts) == 3
        and parts[2] in ("x", "y", "z")
        and any(mk.name == parts[1] for mk in arm.markers)
    )


_NUMBER = re.compile(
    r"\s*[+-]?(?:(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?|nan|inf|infinity)\s*",
    re.ASCII | re.IGNORECASE,
)


def parse_number(text: str) -> float:
    """A cell as a float: ASCII decimal notation (``-1.5``, ``2e-3``, ``.5``; surrounding spaces
    allowed) or ``nan``/``inf`` (rejected later as not finite). ``ValueError`` for anything
    else, including what Python's ``float`` also accepts: digit groups with ``_`` (``1_0``),
    non-ASCII digits."""
    if not _NUMBER.fullmatch(text):
        raise ValueError(f"not a number: {text!r}")
    return float(text)


def _is_number(text: str) -> bool:
    try:
        parse_number(text)
    except ValueError:
        return False
    return True


def load_measurements(
    path: str | os.PathLike, arm: Arm, *, require_measured: bool = True
) -> Measurements:
    """Read a measurement CSV file (see :func:`loads_measurements`)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as e:
        raise MeasurementFileError(
            str(path), f"cannot read measurement file: {e.strerror}"
        ) from None
    except UnicodeDecodeError as e:
        raise MeasurementFileError(str(path), f"not UTF-8 text: {e.reason}") from None
    return loads_measurements(text, arm, source=str(path), require_measured=require_measured)


def dumps_measurements(meas: Measurements) -> str:
    """CSV text of ``meas``: comments, header, rows (floats as ``repr``, empty where a measured
    value is not given; lossless)."""
    out = io.StringIO()
    for c in meas.comments:
        for part in str(c).splitlines() or [""]:
            out.write(f"# {part}\n" if part else "#\n")
    out.write(_csv_line(meas.columns))
    cols = [None if c == POSE_COLUMN else meas.values[c] for c in meas.columns]
    for i, pid in enumerate(meas.pose_ids):
        out.write(_csv_line([pid if col is None else _cell(float(col[i])) for col in cols]))
    return out.getvalue()


def _cell(v: float) -> str:
    return "" if math.isnan(v) else repr(v)


def _csv_line(cells: Sequence[str]) -> str:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(cells)
    line = buf.getvalue()
    if line.lstrip().startswith("#"):
        # A pose id starting with '#' in the first column would read as a comment: quote it.
        first = str(cells[0])
        rest = line[len(first) :] if line.startswith(first) else line[line.index(",") :]
        line = '"' + first.replace('"', '""') + '"' + rest
    return line


def save_measurements(meas: Measurements, path: str | os.PathLike, *, force: bool = False) -> Path:
    """Write ``meas`` as a measurement CSV file atomically; never over a file unless ``force``."""
    return write_text_atomic(path, dumps_measurements(meas), force=force)


def check_pose_count(meas: Measurements, minimum: int = MIN_POSES) -> None:
    """Raise :class:`MeasurementFileError` when ``meas`` has fewer than ``minimum`` poses or
    fewer than ``minimum`` distinct module configurations (rows with the same module states
    measure the same pose again: they average noise but identify nothing new).

    The calibration needs at least 4 measured poses (Section IV, Eq. 9).
    """
    if meas.m < minimum:
        raise MeasurementFileError(
            meas.source,
            f"{meas.m} measured pose(s); the calibration needs at least {minimum} "
            "(Section IV, Eq. 9)",
        )
    distinct = len(np.unique(np.asarray(meas.q, dtype=float), axis=0)) if meas.m else 0
    if distinct < minimum:
        raise MeasurementFileError(
            meas.source,
            f"{meas.m} rows but only {distinct} distinct module configuration(s); the "
            f"calibration needs at least {minimum} distinct ones (Section IV, Eq. 9): repeated "
            "configurations measure the same pose again",
        )
