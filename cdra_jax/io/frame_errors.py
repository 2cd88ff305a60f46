"""Frame-error files (JSON or TOML): one error twist per fixed frame, by name.

The error of a fixed frame is the twist ``dt = (vx, vy, vz, wx, wy, wz)`` (mm, rad; the
paper's order, translation first) with ``T_actual = exp(hat(dt)) T_nominal`` (Eqs. 11-14). A
file gives them under ``frames``; each frame is a table of named components (missing ones are
0) or a list of the 6 numbers; frames left out have no error. Other top-level keys are free
metadata and ignored. TOML::

    [frames.base]
    vx = 0.5        # mm
    wz = 0.01       # rad

    [frames.tool]
    twist = [0.1, -0.2, 0.3, 0.0, 0.0, 0.02]   # vx vy vz (mm) wx wy wz (rad)

JSON::

    {"frames": {"base": {"vx": 0.5, "wz": 0.01},
                "tool": [0.1, -0.2, 0.3, 0.0, 0.0, 0.02]}}

``cdra-jax simulate --errors FILE`` reads this format; ``--truth T.json`` writes it (named
components of every frame, plus metadata), so a truth file can be fed back with ``--errors``.
"""

from __future__ import annotations

import json
import math
import os
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from jax.typing import ArrayLike

from ..arm import TWIST_COMPONENTS, Arm
from .files import json_text, write_text_atomic


class FrameErrorFileError(ValueError):
    """A frame-error file is malformed; the message names the file and the entry."""


def frame_errors_to_dict(arm: Arm, errors: ArrayLike) -> dict[str, dict[str, float]]:
    """``{frame: {vx: .., ..., wz: ..}}`` from ``errors`` ``(6 (K+1),)`` or ``(K+1, 6)``."""
    X = np.asarray(errors, dtype=float).reshape(len(arm.frame_names), 6)
    return {
        name: {c: float(v) for c, v in zip(TWIST_COMPONENTS, row, strict=True)}
        for name, row in zip(arm.frame_names, X, strict=True)
    }


def frame_errors_from_mapping(
    spec: Mapping[str, Any], arm: Arm, source: str = "<frame errors>"
) -> np.ndarray:
    """Error twists ``(K+1, 6)`` in ``arm.frame_names`` order from a parsed file (see above)."""
    if not isinstance(spec, Mapping) or "frames" not in spec:
        raise FrameErrorFileError(
            f"{source}: top level: needs a 'frames' table mapping frame names to error twists"
        )
    frames = spec["frames"]
    if not isinstance(frames, Mapping):
        raise FrameErrorFileError(f"{source}: frames: expected a table of frame names")
    X = np.zeros((len(arm.frame_names), 6))
    for name, entry in frames.items():
        where = f"{source}: frames.{name}"
        if name not in arm.frame_names:
            raise FrameErrorFileError(
                f"{where}: unknown frame {name!r}; frames of arm {arm.name!r}: "
                f"{', '.join(arm.frame_names)}"
            )
        i = arm.frame_names.index(name)
        if isinstance(entry, Mapping) and set(entry) == {"twist"}:
            entry = entry["twist"]
        if isinstance(entry, Mapping):
            unknown = sorted(set(entry) - set(TWIST_COMPONENTS))
            if unknown:
                raise FrameErrorFileError(
                    f"{where}: unknown components {unknown}; components are "
                    f"{', '.join(TWIST_COMPONENTS)} (or 'twist' = [6 numbers])"
                )
            for c, v in entry.items():
                X[i, TWIST_COMPONENTS.index(c)] = _number(f"{where}.{c}", v)
        elif isinstance(entry, list):
            if len(entry) != 6:
                raise FrameErrorFileError(
                    f"{where}: expected 6 numbers (vx, vy, vz, wx, wy, wz), got {len(entry)}"
                )
            X[i] = [_number(f"{where}[{j}]", v) for j, v in enumerate(entry)]
        else:
            raise FrameErrorFileError(
                f"{where}: expected a table of components or a list of 6 numbers, got {entry!r}"
            )
    return X


def _number(where: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise FrameErrorFileError(f"{where}: expected a finite number, got {v!r}")
    try:
        x = float(v)
    except OverflowError:  # an integer beyond the float range
        x = math.inf
    if not math.isfinite(x):
        shown = (
            f"an integer of about {int(v.bit_length() * math.log10(2)) + 1} digits"
            if isinstance(v, int)
            else repr(v)
        )
        raise FrameErrorFileError(f"{where}: expected a finite number, got {shown}")
    return x


def load_frame_errors(path: str | os.PathLike, arm: Arm) -> np.ndarray:
    """Read a frame-error file (``.toml``, otherwise JSON): error twists ``(K+1, 6)``."""
    return frame_errors_from_mapping(_read_spec(Path(path)), arm, str(path))


def load_marker_truth(path: str | os.PathLike, arm: Arm) -> dict[str, tuple[float, ...]]:
    """The optional ``markers`` table of a frame-error file (``simulate --truth`` writes it):
    marker name -> true position in the tool frame (mm). Empty when the file has none."""
    spec = _read_spec(Path(path))
    table = (spec.get("markers") if isinstance(spec, dict) else None) or {}
    if not isinstance(table, dict):
        raise FrameErrorFileError(f"{path}: markers: expected a table of name = [x, y, z]")
    out = {}
    known = {mk.name for mk in arm.markers}
    for name, xyz in table.items():
        if name not in known:
            raise FrameErrorFileError(
                f"{path}: markers.{name}: the model declares no marker {name!r}; markers: "
                + (", ".join(sorted(known)) or "none")
            )
        ok = isinstance(xyz, list) and len(xyz) == 3
        ok = ok and all(isinstance(v, int | float) and not isinstance(v, bool) for v in xyz)
        if not ok or not all(math.isfinite(v) for v in xyz):
            raise FrameErrorFileError(
                f"{path}: markers.{name}: expected 3 finite numbers (mm), got {xyz!r}"
            )
        out[name] = tuple(float(v) for v in xyz)
    return out


def _read_spec(path: Path) -> Any:
    """The parsed content of a frame-error file (``.toml``, otherwise JSON)."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise FrameErrorFileError(f"{path}: cannot read frame-error file: {e.strerror}") from None
    except UnicodeDecodeError as e:
        raise FrameErrorFileError(f"{path}: not UTF-8 text: {e.reason}") from None
    if path.suffix.lower() == ".toml":
        try:
            spec = tomllib.loads(text)
        except tomllib.TOMLDecodeError as e:
            raise FrameErrorFileError(f"{path}: not valid TOML: {e}") from None
        except RecursionError:
            raise FrameErrorFileError(f"{path}: not valid TOML: nested too deeply") from None
    else:
        try:
            spec = json.loads(text)
        except json.JSONDecodeError as e:
            raise FrameErrorFileError(
                f"{path}: not valid JSON (line {e.lineno}, column {e.colno}): {e.msg}; "
                "use a .toml suffix for TOML"
            ) from None
        except ValueError as e:  # e.g. an integer of more than 4300 digits
            raise FrameErrorFileError(f"{path}: not valid JSON: {e}") from None
        except RecursionError:
            raise FrameErrorFileError(f"{path}: not valid JSON: nested too deeply") from None
    return spec


def save_frame_errors(
    path: str | os.PathLike,
    arm: Arm,
    errors: ArrayLike,
    *,
    metadata: Mapping[str, Any] | None = None,
    force: bool = False,
) -> Path:
    """Write a frame-error JSON file (``metadata`` first, then ``frames``), atomically."""
    doc: dict[str, Any] = {"format": "cdra_jax.frame_errors", "format_version": 1}
    doc.update(metadata or {})
    doc["frames"] = frame_errors_to_dict(arm, errors)
    return write_text_atomic(path, json_text(doc), force=force)
