"""Plausibility of measurements against the model: wrong units and conventions, odd rows.

A measurement file can be perfectly well-formed and still wrong: tool positions in metres,
rotation vectors or joint angles in degrees, quaternions written scalar-last, a device that
reports the inverse rotation, one row with a typo. :func:`check_plausibility` compares the
file with what the **nominal** model predicts at the same module states and

* raises :class:`~cdra_jax.io.measurements.MeasurementFileError` (naming the file, the column
  and, where it is one row, the line) when another reading of the columns explains the data and
  the given one does not, saying which and what to do ("multiply by 1000?");
* returns warnings (plain text) when something is off but the cause is not clear: states
  outside the model's limits, rotation-vector components beyond pi, large mismatches, single
  rows far from the prediction, repeated module states.

Nothing is changed: the checks only read. The tolerances are generous, since the nominal model
is off by the very frame errors the calibration is to find. For the CDRA with random errors in
the paper's range (1 mm and 0.05 rad per component and frame; 2000 draws of 20 poses) the
median distance between measured and predicted tool positions is 28 mm (at most 71 mm), single
poses are at most 96 mm off, and the median orientation angle is at most 0.2 rad.

* positions: the robust spread of the measured positions (median distance from their median)
  over the model's, outside ``[1/2, 2]`` is an error (:data:`POSITION_SCALE_TOL`); a unit is
  named when the ratio is within 25 % of 1/1000 (metres), 1/10 (centimetres), 1/25.4 (inches)
  or 1000 (micrometres, or a model in metres);
* orientations: a median angle between measured and predicted tool orientations above
  :data:`ORIENTATION_TOL` (0.5 rad) is a warning, and an error when degrees (rotation vectors),
  scalar-last order (quaternions) or the inverse rotation brings it below 0.5 rad and below a
  quarter of the given one;
* joint states in rad (spherical, revolute): values outside the limits (plus 5 % of the range)
  are a warning; an error when most of them are outside (or one is beyond 2 pi) and the values
  divided by 57.3 (degrees to rad) all fit;
* single rows: a pose whose measured position is farther from its prediction than the median
  distance over the poses plus ``max(100 mm, 10 sigma)`` is a warning naming the line and the
  column that is most off (a typo or a mis-seated probe; ``--loss huber`` down-weights such
  rows); ``sigma = 1.4826 MAD`` is the robust standard deviation of the distances, so one bad
  row does not hide itself by raising the threshold (:func:`far_rows`);
* a median position mismatch above 100 mm is a warning (is the measuring device registered to
  the model's world frame? Eqs. 11-14 assume small errors).
"""

from __future__ import annotations

import math

import numpy as np

from .. import lie
from ..arm import Arm, tool_pose
from ..compilation import device_array
from .measurements import (
    POSITION_COLUMNS,
    QUATERNION_COLUMNS,
    ROTVEC_COLUMNS,
    MeasurementFileError,
    Measurements,
)

POSITION_SCALE_TOL = 2.0
"""Measured/model position spread outside ``[1/2, 2]`` is an error."""
ORIENTATION_TOL = 0.5
"""Median measured-vs-model orientation angle (rad) above which the orientation is suspect."""
POSITION_OFFSET_WARN_MM = 100.0
"""Median measured-vs-model position distance (mm) above which a warning is given."""
ROW_OUTLIER_MIN_MM = 100.0
"""A row is named only when its distance exceeds the median distance by more than this (mm)."""
ROW_OUTLIER_Z = 10.0
"""... and by more than this many robust standard deviations (1.4826 MAD) of the distances.

For the CDRA with random errors in the paper's range (4000 draws each of 4 to 100 poses) no
pose exceeds the median by more than 62 mm, and the largest robust z of a pose is 8.6 for 30
poses (15 for 12 poses, where the 100 mm floor decides); a 400 mm typo in one of 30 rows has
z = 23.
"""
LIMIT_MARGIN = 0.05
"""Joint states may exceed the model's limits by this fraction of the range without a word."""
_UNITS = (
    (1000.0, "metres", "multiply by 1000"),
    (10.0, "centimetres", "multiply by 10"),
    (25.4, "inches", "multiply by 25.4"),
    (1e-3, "micrometres (or the model file is in metres)", "divide by 1000"),
)
_MIN_SPREAD_MM = 10.0
_POSITION_COLUMNS_TEXT = "measured.x, measured.y, measured.z"


def check_plausibility(arm: Arm, meas: Measurements) -> tuple[str, ...]:
    """Check ``meas`` against the predictions of the nominal ``arm`` (see the module docstring).

    Args:
        arm: the nominal model the measurements are for.
        meas: the measurements (a pose plan without measured poses gets the state checks only).

    Returns:
        The warnings, as plain-text lines (empty when all is plausible).

    Raises:
        MeasurementFileError: a unit or convention error that another reading of the columns
            explains (the message names the file, the column, the likely cause and the fix).
    """
    warnings: list[str] = []
    warnings += _check_states(arm, meas)
    if meas.measured is not None and meas.m > 0:
        T_model = np.asarray(tool_pose(arm, device_array(meas.q)), dtype=float)
        if not np.all(np.isfinite(T_model)):
            raise MeasurementFileError(
                meas.source, "the model's tool poses at these module states are not finite"
            )
        warnings += _check_positions(meas, T_model)
        warnings += _check_orientations(meas, T_model)
    elif meas.points is not None and meas.m > 0:
        T_model = np.asarray(tool_pose(arm, device_array(meas.q)), dtype=float)
        _check_point_scale(arm, meas, T_model)
    warnings += _check_repeats(meas)
    return tuple(warnings)


def _where(meas: Measurements, i: int) -> str:
    return f"pose {meas.pose_ids[i]!r} (line {meas.lines[i]})"


def _check_states(arm: Arm, meas: Measurements) -> list[str]:
    warnings = []
    j = 0
    for mod in arm.modules:
        for name, (lo, hi) in zip(mod.state_names, mod.limits, strict=True):
            v = meas.q[:, j]
            j += 1
            if v.size == 0:
                continue
            margin = LIMIT_MARGIN * (hi - lo)
            out = np.flatnonzero((v < lo - margin) | (v > hi + margin))
            if not out.size:
                continue
            i = int(out[0])
            if mod.kind != "prismatic" and (
                out.size >= 0.5 * v.size or np.abs(v).max() > 2 * np.pi
            ):
                rad = np.deg2rad(v)
                if np.all((rad >= lo - margin) & (rad <= hi + margin)):
                    raise MeasurementFileError(
                        meas.source,
                        f"looks like degrees: values from {v.min():.4g} to {v.max():.4g}, but "
                        f"the model's limits are [{lo:g}, {hi:g}] rad (the values divided by "
                        "57.3 fit them); multiply by pi/180?",
                        line=meas.lines[i],
                        column=name,
                    )
            unit = "rad" if mod.kind != "prismatic" else "mm"
            warnings.append(
                f"column {name!r}: {out.size} of {meas.m} poses outside the model's limits "
                f"[{lo:g}, {hi:g}] {unit} (first: {_where(meas, i)}, {v[i]:.6g}); used as given"
            )
    return warnings


def _spread(p: np.ndarray) -> float:
    return float(np.median(np.linalg.norm(p - np.median(p, axis=0), axis=-1)))


def _check_point_scale(arm: Arm, meas: Measurements, T_model: np.ndarray) -> None:
    """Measured points (in any device frame) must spread like the model's: the spread is
    independent of where the device stands, so a factor of 1000, 10 or 25.4 is a unit error."""
    assert meas.points is not None
    for j, name in enumerate(meas.point_names):
        seen = np.all(np.isfinite(meas.points[:, j]), axis=-1)
        if seen.sum() < 3:
            continue
        x = np.zeros(3) if name == "origin" else np.asarray(arm.marker(name).xyz)
        p_model = (T_model[seen, :3, :3] @ x) + T_model[seen, :3, 3]
        s_model, s_meas = _spread(p_model), _spread(meas.points[seen, j])
        if s_model < _MIN_SPREAD_MM:
            continue
        ratio = s_meas / s_model
        if 1.0 / POSITION_SCALE_TOL <= ratio <= POSITION_SCALE_TOL:
            continue
        column = "measured.x" if name == "origin" else f"measured.{name}.x"
        raise _unit_error(
            meas.source, column, f"the measured points {name!r}", "median spread", s_meas, s_model
        )


def _unit_error(
    source: str, column: str, what: str, measure: str, s_meas: float, s_model: float
) -> MeasurementFileError:
    """The error for measured positions ``s_meas / s_model`` times the model's: a named unit
    where the factor is one (metres, centimetres, inches, micrometres), else wrong units."""
    ratio = s_meas / s_model
    for factor, unit, fix in _UNITS:
        if ratio > 0 and abs(math.log(ratio * factor)) < math.log(1.25):
            return MeasurementFileError(
                source,
                f"{what} look like {unit}: {measure} {s_meas:.4g} vs {s_model:.4g} mm predicted "
                f"by the model; {fix}?",
                column=column,
            )
    return MeasurementFileError(
        source,
        f"{what}: {measure} {s_meas:.4g} is {ratio:.3g} times the {s_model:.4g} mm predicted by "
        "the model: wrong units (the file must be in mm), or a model of another arm?",
        column=column,
    )


def _check_positions(meas: Measurements, T_model: np.ndarray) -> list[str]:
    assert meas.measured is not None
    p, p_model = meas.measured[:, :3, 3], T_model[:, :3, 3]
    s_model, s_meas = _spread(p_model), _spread(p)
    what = "median spread"
    if meas.m < 3 or s_model < _MIN_SPREAD_MM:
        s_model = float(np.median(np.linalg.norm(p_model, axis=-1)))
        s_meas = float(np.median(np.linalg.norm(p, axis=-1)))
        what = "median |p|"
    if s_model >= _MIN_SPREAD_MM:
        ratio = s_meas / s_model
        if not 1.0 / POSITION_SCALE_TOL <= ratio <= POSITION_SCALE_TOL:
            raise _unit_error(
                meas.source, "measured.x", _POSITION_COLUMNS_TEXT, what, s_meas, s_model
            )
    warnings = []
    dist = np.linalg.norm(p - p_model, axis=-1)
    med = float(np.median(dist))
    if med > POSITION_OFFSET_WARN_MM:
        warnings.append(
            f"measured positions are a median {med:.4g} mm from the model's predictions: frame "
            "errors this large are beyond the small-error model of Eqs. 11-14; is the measuring "
            "device registered to the model's world frame?"
        )
    far, sigma = far_rows(dist)
    for i in far[:5]:
        i = int(i)
        delta = p[i] - p_model[i]
        j = int(np.argmax(np.abs(delta)))
        column = POSITION_COLUMNS[j]
        warnings.append(
            f"{_where(meas, i)}, column {column!r}: measured position {dist[i]:.4g} mm from "
            f"the model's prediction (median over poses {med:.3g} mm, robust spread "
            f"{sigma:.3g} mm); {column} alone is {delta[j]:+.4g} mm off: a typo or a "
            "mis-seated probe? (a robust loss, --loss huber, down-weights such poses)"
        )
    if far.size > 5:
        warnings.append(f"... and {far.size - 5} more poses far from the model's predictions")
    return warnings


def far_rows(dist: np.ndarray) -> tuple[np.ndarray, float]:
    """Rows whose distance to the model's prediction stands out from the others.

    Row ``i`` is named when ``dist[i] - median > max(ROW_OUTLIER_MIN_MM, ROW_OUTLIER_Z sigma)``
    with ``sigma = 1.4826 median(|dist - median|)``, the robust (MAD) standard deviation. Median
    and MAD ignore up to half of the rows, so a gross typo neither raises the threshold nor
    hides other bad rows (a rule relative to the median alone, such as ``10 x median``, misses
    a 400 mm typo whenever the frame errors give a median of 40 mm).

    Args:
        dist: ``(m,)`` distances (mm) between measured and predicted tool positions.

    Returns:
        The indices of the rows named, largest distance first, and ``sigma`` (mm).
    """
    dist = np.asarray(dist, dtype=float)
    if dist.size == 0:
        return np.zeros(0, dtype=int), 0.0
    med = float(np.median(dist))
    sigma = 1.4826 * float(np.median(np.abs(dist - med)))
    limit = max(ROW_OUTLIER_MIN_MM, ROW_OUTLIER_Z * sigma)
    far = np.flatnonzero(dist - med > limit)
    return far[np.argsort(-dist[far], kind="stable")], sigma


def _angles(R: np.ndarray, R_model: np.ndarray) -> np.ndarray:
    rel = np.swapaxes(R, -1, -2) @ R_model
    return np.asarray(lie.rotation_angle(device_array(rel)), dtype=float)


def _check_orientations(meas: Measurements, T_model: np.ndarray) -> list[str]:
    assert meas.measured is not None
    R, R_model = meas.measured[:, :3, :3], T_model[:, :3, :3]
    given = float(np.median(_angles(R, R_model)))
    alternatives: list[tuple[str, str, np.ndarray]] = []
    beyond_pi = False
    cols: tuple[str, ...]
    if meas.orientation == "rotvec":
        cols = ROTVEC_COLUMNS
        rv = np.stack([meas.values[c] for c in cols], axis=-1)
        beyond_pi = bool(np.any(np.abs(rv) > math.pi))
        if given > ORIENTATION_TOL or beyond_pi:
            R_deg = np.asarray(lie.so3_exp(device_array(np.deg2rad(rv))), dtype=float)
            alternatives.append(("look like degrees", "multiply by pi/180", R_deg))
    else:
        cols = QUATERNION_COLUMNS
        if given > ORIENTATION_TOL:
            quat = np.stack([meas.values[c] for c in cols], axis=-1)
            xyzw = quat[:, [3, 0, 1, 2]]  # the columns read as (x, y, z, w)
            xyzw = xyzw / np.linalg.norm(xyzw, axis=-1, keepdims=True)
            R_sl = np.asarray(lie.quaternion_to_rotation(device_array(xyzw)), dtype=float)
            alternatives.append(
                ("look scalar-last (x, y, z, w)", "put the scalar part w first", R_sl)
            )
    if given > ORIENTATION_TOL:
        alternatives.append(
            (
                "look like the inverse rotation (the world's orientation in the tool frame)",
                "invert the rotation (negate the rotation vector / conjugate the quaternion)",
                np.swapaxes(R, -1, -2),
            )
        )
    for what, fix, R_alt in alternatives:
        alt = float(np.median(_angles(R_alt, R_model)))
        if alt < ORIENTATION_TOL and alt < given / 4:
            raise MeasurementFileError(
                meas.source,
                f"{', '.join(cols)} {what}: the measured orientations differ from the model's "
                f"predictions by a median {given:.3g} rad as given, {alt:.3g} rad read that way; "
                f"{fix}?",
                column=cols[0],
            )
    warnings = []
    if beyond_pi:
        i = int(np.flatnonzero(np.any(np.abs(rv) > math.pi, axis=-1))[0])
        warnings.append(
            f"{_where(meas, i)}: a rotation-vector component beyond pi ({', '.join(cols)}); "
            "rotation vectors are in rad, degrees?"
        )
    if given > ORIENTATION_TOL:
        warnings.append(
            f"measured orientations differ from the model's predictions by a median {given:.3g} "
            f"rad (more than {ORIENTATION_TOL:g}): check the orientation convention (tool frame "
            "in the world frame; rotation vector in rad, or unit quaternion w, x, y, z) and the "
            "model"
        )
    return warnings


def _check_repeats(meas: Measurements) -> list[str]:
    if meas.m < 2:
        return []
    _, first, inverse = np.unique(meas.q, axis=0, return_index=True, return_inverse=True)
    inverse = np.asarray(inverse).reshape(-1)
    repeats = [i for i in range(meas.m) if first[inverse[i]] != i]
    if not repeats:
        return []
    examples = ", ".join(
        f"{_where(meas, i)} repeats {meas.pose_ids[first[inverse[i]]]!r}" for i in repeats[:3]
    )
    more = f" and {len(repeats) - 3} more" if len(repeats) > 3 else ""
    return [
        f"{len(repeats)} pose(s) repeat the module state of an earlier pose ({examples}{more}); "
        f"{len(first)} distinct states among {meas.m} poses: repeats average the noise but add "
        "no new geometry"
    ]
