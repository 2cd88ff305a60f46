"""Model files (TOML): read and write an :class:`~cdra_jax.arm.Arm`; the embedded default CDRA.

Format (see the README for a complete example)::

    name = "cdra"
    description = "..."              # optional
    gravity = [0.0, 0.0, -9.81]      # optional, m/s^2, world frame

    [[frames]]                       # K+1 fixed transforms in chain order
    name = "base"
    xyz = [0.0, 0.0, 50.0]           # mm
    rotvec = [0.0, 0.0, 0.0]         # rad   (or: matrix = [[...4 rows of 4...]])

    [[modules]]                      # K modules; module i sits between frames[i] and frames[i+1]
    name = "elbow"
    kind = "revolute"                # spherical | revolute | prismatic
    axis = [0.0, 1.0, 0.0]           # revolute / prismatic only
    limits = [[0.0, 2.0]]            # one (low, high) per state entry
    # optional: cables = [{ base = [x, y, z], platform = [x, y, z] }, ...] (mm), each cable
    #           optionally with offset = <mm> (measured length = attachment distance + offset),
    #           mass (kg), com (mm, platform frame), pretension (N), stiffness (N/mm)

    [[markers]]                      # optional: measured points on the tool
    name = "m1"                      # columns measured.m1.x, measured.m1.y, measured.m1.z
    xyz = [0.0, 40.0, 25.0]          # mm, tool frame
    calibrate = true                 # optional: the position is rough, identify it

    [[effects]]                      # optional: non-geometric physics (cdra_jax.physics)
    effect = "periodic_error"        # a name of the physics vocabulary
    location = "elbow"               # the module or frame it sits at
    variant = "k=1"                  # optional: which form (default: the vocabulary's first)
    [effects.parameters]             # every parameter of the effect, with its unit
    q_sin1 = { value = 0.002, unit = "rad" }
    q_cos1 = { value = -0.001, unit = "rad" }

Effect entries are checked here for their structure (names, numbers, unit strings); whether
the effect, location, variant, parameter names and units exist in the vocabulary is checked by
:func:`cdra_jax.physics.model_effects` (every command calls it on loading a model).

Frames are written back as ``xyz`` + ``rotvec`` (floats printed with all 17 significant digits,
reproducing the matrix to ~1e-16), or as ``matrix`` with ``exact=True`` (bit-exact round trip).
"""

from __future__ import annotations

import importlib.resources
import math
import os
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from .. import lie
from ..arm import MODULE_KINDS, Arm, EffectRecord, Marker, Module
from ..compilation import device_array
from .files import write_text_atomic

_ORTHO_TOL = 1e-6


_DEFAULT_MODEL = "cdra.toml"


class ModelFileError(ValueError):
    """A model file is malformed; the message names the file and the entry."""


_ROTVEC_MAX_ANGLE = 1e3  # rad; as io.measurements.ROTVEC_MAX_ANGLE
_NAME_FORBIDDEN = frozenset('.,"')
RESERVED_MODULE_NAMES = ("pose", "measured", "approach", "time_s", "payload_kg", "temperature_c")
"""Names a module cannot have: the measurement file's own columns and column prefixes
(``pose``, ``measured.*``, ``approach.<module>``, the auxiliaries)."""


def _err(source: str, where: str, what: str) -> ModelFileError:
    return ModelFileError(f"{source}: {where}: {what}")


def _is_number(v: Any) -> bool:
    """A TOML integer or float (not a bool, not a string such as ``"250"``)."""
    return isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool)


def _finite(v: Any) -> bool:
    try:
        return math.isfinite(v)
    except OverflowError:  # an int beyond the float range
        return False


def _array(value: Any, shape: tuple[int, ...]) -> np.ndarray | None:
    """``value`` (nested lists of numbers of ``shape``) as floats, or None when it is not one
    (strings are not numbers here, whatever they spell)."""

    def ok(v: Any, dims: tuple[int, ...]) -> bool:
        if not dims:
            return _is_number(v)
        return isinstance(v, list | tuple) and len(v) == dims[0] and all(ok(x, dims[1:]) for x in v)

    if not ok(value, shape):
        return None
    try:
        return np.asarray(value, dtype=float)
    except OverflowError:
        return np.full(shape, np.inf)


_MAX_PHYSICAL = {"mass": 1e6, "pretension": 1e9, "stiffness": 1e9}
"""Upper bounds of the physical module parameters (kg, N, N/mm): beyond them a typo or a unit."""
MAX_LENGTH_MM = 1e7
"""Largest length (mm) a model may give, 10 km: a frame offset, cable attachment point, centre of
mass or prismatic limit beyond it is a typo or a wrong unit, and would overflow the solvers'
squared residuals long before it meant anything physical."""


def _short(v: Any, width: int = 40) -> str:
    """``repr(v)``, cut to ``width`` characters (a 400-digit integer stays readable)."""
    text = repr(v)
    return text if len(text) <= width else text[: width - 3] + "..."


def _vector(source: str, where: str, value: Any, n: int) -> np.ndarray:
    a = _array(value, (n,))
    if a is None:
        raise _err(source, where, f"expected a list of {n} numbers, got {value!r}")
    if not np.all(np.isfinite(a)):
        raise _err(source, where, f"contains a non-finite number: {value!r}")
    if np.max(np.abs(a), initial=0.0) > MAX_LENGTH_MM:
        raise _err(
            source,
            where,
            f"{value!r} has an entry beyond {MAX_LENGTH_MM:g} (mm): not a plausible length; "
            "check for a typo or a wrong unit",
        )
    return a


def _frame_matrix(source: str, i: int, spec: Mapping[str, Any]) -> np.ndarray:
    where = f"frames[{i}] ({spec.get('name', '?')!s})"
    has_matrix = "matrix" in spec
    has_pose = "xyz" in spec or "rotvec" in spec
    if has_matrix and has_pose:
        raise _err(source, where, "give either 'matrix' or 'xyz' + 'rotvec', not both")
    if has_matrix:
        M = _array(spec["matrix"], (4, 4))
        if M is None or not np.all(np.isfinite(M)):
            raise _err(
                source,
                where,
                f"'matrix' must be 4 rows of 4 finite numbers, got {spec['matrix']!r}",
            )
        if np.max(np.abs(M[:3, 3])) > MAX_LENGTH_MM:
            raise _err(
                source,
                where,
                f"translation {M[:3, 3].tolist()} of 'matrix' has an entry beyond "
                f"{MAX_LENGTH_MM:g} (mm): not a plausible length",
            )
        if not np.allclose(M[3], [0, 0, 0, 1], atol=0):
            raise _err(source, where, f"last row of 'matrix' must be [0, 0, 0, 1], got {M[3]}")
        R = M[:3, :3]
        dev = np.abs(R.T @ R - np.eye(3)).max()
        if dev > _ORTHO_TOL:
            raise _err(
                source, where, f"rotation block is not orthonormal (|R^T R - I| = {dev:.2e})"
            )
        if np.linalg.det(R) < 0:
            raise _err(source, where, "rotation block is a reflection (det < 0, left-handed)")
        return M
    if "xyz" not in spec or "rotvec" not in spec:
        raise _err(source, where, "needs 'xyz' (mm) and 'rotvec' (rad), or 'matrix' (4x4)")
    xyz = _vector(source, f"{where}.xyz", spec["xyz"], 3)
    rv = _vector(source, f"{where}.rotvec", spec["rotvec"], 3)
    if not np.linalg.norm(rv) <= _ROTVEC_MAX_ANGLE:
        raise _err(
            source,
            f"{where}.rotvec",
            f"angle {np.linalg.norm(rv):.4g} rad is above {_ROTVEC_MAX_ANGLE:g} rad: "
            "not a rotation vector in radians",
        )
    return np.asarray(lie.from_xyz_rotvec(device_array(xyz), device_array(rv)))


def _module(source: str, i: int, spec: Mapping[str, Any]) -> Module:
    if not isinstance(spec, Mapping):
        raise _err(source, f"modules[{i}]", f"expected a table ([[modules]]), got {spec!r}")
    name = spec.get("name")
    where = f"modules[{i}] ({name!s})"
    if not isinstance(name, str) or not name:
        raise _err(source, f"modules[{i}]", "needs a 'name' (string)")
    bad = sorted({ch for ch in name if ch in _NAME_FORBIDDEN or not ch.isprintable()})
    if bad:
        raise _err(
            source,
            where,
            "a module name makes the measurement file's column names (<module>.q, <module>.l1, "
            f"...), so it cannot contain {' or '.join(map(repr, bad))}",
        )
    if name != name.strip():
        raise _err(source, where, "a module name cannot start or end with a space")
    if name in RESERVED_MODULE_NAMES:
        raise _err(
            source,
            where,
            f"{name!r} is reserved for the measurement file's own columns (pose, measured.*, "
            "approach.*, time_s, payload_kg, temperature_c); rename the module",
        )
    kind = spec.get("kind")
    if kind not in MODULE_KINDS:
        raise _err(source, where, f"'kind' must be one of {MODULE_KINDS}, got {kind!r}")
    dof = 3 if kind == "spherical" else 1
    known = {
        "name",
        "kind",
        "axis",
        "limits",
        "cables",
        "mass",
        "com",
        "pretension",
        "stiffness",
    }
    unknown = sorted(set(spec) - known)
    if unknown:
        raise _err(source, where, f"unknown keys {unknown}; known: {sorted(known)}")
    if kind == "spherical":
        if "axis" in spec:
            raise _err(source, where, "a spherical module takes no 'axis'")
        axis = np.zeros(3)
        default_limits = [[-1.0, 1.0]] * 3
    else:
        if "axis" not in spec:
            raise _err(source, where, f"a {kind} module needs an 'axis'")
        axis = _vector(source, f"{where}.axis", spec["axis"], 3)
        n = np.linalg.norm(axis)
        if n < 1e-12:
            raise _err(source, where, "'axis' must be non-zero")
        axis = axis / n
        default_limits = [[-math.pi, math.pi]] if kind == "revolute" else [[-100.0, 100.0]]
    limits = spec.get("limits", default_limits)
    lim = _array(limits, (dof, 2))
    if lim is None or not np.all(np.isfinite(lim)) or np.any(lim[:, 0] >= lim[:, 1]):
        raise _err(
            source,
            f"{where}.limits",
            f"expected {dof} pairs [low, high] with low < high, got {limits!r}",
        )
    bound = MAX_LENGTH_MM if kind == "prismatic" else _ROTVEC_MAX_ANGLE
    if np.max(np.abs(lim)) > bound:
        unit = "mm" if kind == "prismatic" else "rad"
        raise _err(
            source,
            f"{where}.limits",
            f"{limits!r} has a limit beyond {bound:g} {unit}: not a plausible joint range",
        )
    kwargs: dict[str, Any] = {}
    if "cables" in spec:
        cables = spec["cables"]
        if not isinstance(cables, list) or not cables:
            raise _err(source, f"{where}.cables", "expected a non-empty list of {base, platform}")
        base, plat, offset = [], [], []
        for j, c in enumerate(cables):
            if not isinstance(c, Mapping) or not (
                {"base", "platform"} <= set(c) <= {"base", "platform", "offset"}
            ):
                raise _err(
                    source,
                    f"{where}.cables[{j}]",
                    "expected { base = [x, y, z], platform = [x, y, z] } (optional offset = mm)",
                )
            base.append(_vector(source, f"{where}.cables[{j}].base", c["base"], 3))
            plat.append(_vector(source, f"{where}.cables[{j}].platform", c["platform"], 3))
            if np.array_equal(base[-1], plat[-1]):
                raise _err(
                    source,
                    f"{where}.cables[{j}]",
                    f"base and platform are the same point {c['base']!r}: the cable has zero "
                    "length in the home state and pulls in no direction there; a cable runs "
                    "between two distinct attachment points",
                )
            if "offset" in c:
                v = c["offset"]
                if not _is_number(v) or not _finite(v):
                    raise _err(
                        source, f"{where}.cables[{j}].offset", f"expected a number (mm), got {v!r}"
                    )
                offset.append(float(v))
        if offset and len(offset) != len(cables):
            raise _err(
                source,
                f"{where}.cables",
                f"give 'offset' for every cable or for none "
                f"({len(offset)} of {len(cables)} have one)",
            )
        kwargs["cable_base"] = device_array(np.stack(base))
        kwargs["cable_platform"] = device_array(np.stack(plat))
        if offset:
            kwargs["cable_offset"] = device_array(offset)
    for key, unit in (("mass", "kg"), ("pretension", "N"), ("stiffness", "N/mm")):
        if key in spec:
            v = spec[key]
            if not _is_number(v) or not _finite(v) or not 0 < v <= _MAX_PHYSICAL[key]:
                raise _err(
                    source,
                    f"{where}.{key}",
                    f"expected a positive number of {unit} up to {_MAX_PHYSICAL[key]:g}, got "
                    f"{_short(v)} (leave '{key}' out where it is unknown; zero or a negative value "
                    "has no physical meaning here)",
                )
            kwargs[key] = float(v)
    if "com" in spec:
        kwargs["com"] = device_array(_vector(source, f"{where}.com", spec["com"], 3))
    return Module(
        name=name,
        kind=kind,
        axis=device_array(axis),
        limits=tuple((float(a), float(b)) for a, b in lim),
        **kwargs,
    )


def arm_from_dict(spec: Mapping[str, Any], source: str = "<model>") -> Arm:
    """Build an :class:`Arm` from the parsed TOML mapping (``source`` names it in errors)."""
    if not isinstance(spec.get("name"), str):
        raise _err(source, "top level", "needs a 'name' (string)")
    unknown = sorted(
        set(spec) - {"name", "description", "gravity", "frames", "modules", "markers", "effects"}
    )
    if unknown:
        raise _err(source, "top level", f"unknown keys {unknown}")
    if not isinstance(spec.get("description", ""), str):
        raise _err(source, "description", f"expected a string, got {spec['description']!r}")
    frames = spec.get("frames")
    modules = spec.get("modules")
    if not isinstance(modules, list) or not modules:
        raise _err(source, "top level", "needs at least one [[modules]] entry")
    if not isinstance(frames, list):
        raise _err(source, "top level", "needs [[frames]] entries")
    if len(frames) != len(modules) + 1:
        raise _err(
            source,
            "top level",
            f"{len(modules)} modules need {len(modules) + 1} [[frames]] (one before, between "
            f"and after the modules), got {len(frames)}",
        )
    names = []
    for i, f in enumerate(frames):
        if not isinstance(f, Mapping) or not isinstance(f.get("name"), str) or not f["name"]:
            raise _err(source, f"frames[{i}]", "needs a 'name' (string)")
        extra = sorted(set(f) - {"name", "xyz", "rotvec", "matrix"})
        if extra:
            raise _err(source, f"frames[{i}] ({f['name']})", f"unknown keys {extra}")
        names.append(f["name"])
    mats = np.stack([_frame_matrix(source, i, f) for i, f in enumerate(frames)])
    mods = tuple(_module(source, i, m) for i, m in enumerate(modules))
    all_names = names + [m.name for m in mods]
    dup = sorted({n for n in all_names if all_names.count(n) > 1})
    if dup:
        raise _err(source, "top level", f"frame and module names must be unique, repeated: {dup}")
    gravity = _vector(source, "gravity", spec.get("gravity", [0.0, 0.0, -9.81]), 3)
    markers = _markers(source, spec.get("markers", []))
    effects = effects_from_list(spec.get("effects", []), source)
    return Arm(
        frames=device_array(mats),
        modules=mods,
        frame_names=tuple(names),
        name=spec["name"],
        description=spec.get("description", ""),
        gravity=device_array(gravity),
        markers=markers,
        effects=effects,
    )


EFFECT_KEYS = ("effect", "location", "variant", "parameters")
"""Keys of an ``[[effects]]`` entry."""


def effects_from_list(specs: Any, source: str = "<model>") -> tuple[EffectRecord, ...]:
    """The ``[[effects]]`` tables (or the same list in a result or diagnosis JSON) as
    :class:`~cdra_jax.arm.EffectRecord`: ``effect``, ``location``, optional ``variant`` and a
    ``parameters`` table ``name = { value = <number>, unit = "<unit>" }``. Errors name
    ``source``, the entry and the key."""
    if not isinstance(specs, list):
        raise _err(source, "effects", f"expected [[effects]] tables, got {_short(specs)}")
    out: list[EffectRecord] = []
    for i, spec in enumerate(specs):
        if not isinstance(spec, Mapping):
            raise _err(source, f"effects[{i}]", f"expected a table ([[effects]]), got {spec!r}")
        for key in ("effect", "location"):
            v = spec.get(key)
            if not isinstance(v, str) or not v:
                raise _err(
                    source,
                    f"effects[{i}].{key}",
                    f"needs '{key}' (a string: the "
                    + ("vocabulary name" if key == "effect" else "module or frame name")
                    + f"), got {_short(v)}",
                )
        where = f"effects[{i}] ({spec['effect']}@{spec['location']})"
        unknown = sorted(set(spec) - set(EFFECT_KEYS))
        if unknown:
            raise _err(source, where, f"unknown keys {unknown}; known: {list(EFFECT_KEYS)}")
        variant = spec.get("variant", "")
        if not isinstance(variant, str):
            raise _err(source, f"{where}.variant", f"expected a string, got {_short(variant)}")
        params = spec.get("parameters")
        if not isinstance(params, Mapping) or not params:
            raise _err(
                source,
                f"{where}.parameters",
                "expected a table of the effect's parameters, each "
                'name = { value = <number>, unit = "<unit>" }, got ' + _short(params),
            )
        values = []
        for name, p in params.items():
            at = f"{where}.parameters.{name}"
            if not isinstance(p, Mapping) or set(p) != {"value", "unit"}:
                raise _err(
                    source, at, f'expected {{ value = <number>, unit = "<unit>" }}, got {_short(p)}'
                )
            v, unit = p["value"], p["unit"]
            if not _is_number(v) or not _finite(v):
                raise _err(source, f"{at}.value", f"expected a finite number, got {_short(v)}")
            if not isinstance(unit, str):
                raise _err(source, f"{at}.unit", f"expected a string, got {_short(unit)}")
            values.append((str(name), float(v), unit))
        record = EffectRecord(
            name=spec["effect"],
            location=spec["location"],
            variant=variant,
            parameters=tuple(values),
        )
        if any(
            (e.name, e.location, e.variant) == (record.name, record.location, record.variant)
            for e in out
        ):
            raise _err(source, where, f"effect {record.label} is given twice")
        out.append(record)
    return tuple(out)


def effects_to_list(effects: Any) -> list[dict[str, Any]]:
    """The ``[[effects]]`` tables of effect records (the inverse of :func:`effects_from_list`;
    values as Python floats, which TOML and JSON write with all their digits)."""
    out = []
    for e in effects:
        d: dict[str, Any] = {"effect": e.name, "location": e.location}
        if e.variant:
            d["variant"] = e.variant
        d["parameters"] = {n: {"value": float(v), "unit": u} for n, v, u in e.parameters}
        out.append(d)
    return out


def _markers(source: str, specs: Any) -> tuple[Marker, ...]:
    """The ``[[markers]]`` tables: ``name``, ``xyz`` (mm, tool frame), optional ``calibrate``."""
    if not isinstance(specs, list):
        raise _err(source, "markers", f"expected [[markers]] tables, got {_short(specs)}")
    out: list[Marker] = []
    for i, spec in enumerate(specs):
        if not isinstance(spec, Mapping):
            raise _err(source, f"markers[{i}]", f"expected a table ([[markers]]), got {spec!r}")
        name = spec.get("name")
        if not isinstance(name, str) or not name:
            raise _err(source, f"markers[{i}]", "needs a 'name' (string)")
        where = f"markers[{i}] ({name})"
        bad = sorted({ch for ch in name if ch in _NAME_FORBIDDEN or not ch.isprintable()})
        if bad or name != name.strip():
            raise _err(
                source,
                where,
                "a marker name makes the measurement columns measured.<name>.x/y/z, so it "
                "cannot contain " + " or ".join(map(repr, bad or [" (leading/trailing)"])),
            )
        if name in {"x", "y", "z", "rx", "ry", "rz", "qw", "qx", "qy", "qz", "origin"}:
            raise _err(
                source,
                where,
                f"{name!r} names a measured tool pose column or the tool origin; rename the marker",
            )
        unknown = sorted(set(spec) - {"name", "xyz", "calibrate"})
        if unknown:
            raise _err(
                source, where, f"unknown keys {unknown}; known: ['calibrate', 'name', 'xyz']"
            )
        if "xyz" not in spec:
            raise _err(source, where, "needs 'xyz' (position in the tool frame, mm)")
        xyz = _vector(source, f"{where}.xyz", spec["xyz"], 3)
        calibrate = spec.get("calibrate", False)
        if not isinstance(calibrate, bool):
            raise _err(source, f"{where}.calibrate", f"expected true or false, got {calibrate!r}")
        if any(m.name == name for m in out):
            raise _err(source, where, f"marker name {name!r} is used twice")
        position = (float(xyz[0]), float(xyz[1]), float(xyz[2]))
        out.append(Marker(name=name, xyz=position, calibrate=calibrate))
    return tuple(out)


def load_model(path: str | os.PathLike) -> Arm:
    """Read a model TOML file. Errors name the file and the offending entry."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise ModelFileError(f"{path}: cannot read model file: {e.strerror}") from None
    except UnicodeDecodeError as e:
        raise ModelFileError(f"{path}: not UTF-8 text: {e.reason}") from None
    return loads_model(text, source=str(path))


def loads_model(text: str, source: str = "<model>") -> Arm:
    """Parse model TOML text (a leading UTF-8 byte-order mark is ignored, as in CSV files)."""
    text = text.removeprefix("\ufeff")
    try:
        spec = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ModelFileError(f"{source}: not valid TOML: {e}") from None
    except RecursionError:
        raise ModelFileError(f"{source}: not valid TOML: nested too deeply") from None
    try:
        return arm_from_dict(spec, source)
    except RecursionError:
        raise ModelFileError(f"{source}: a value is nested too deeply") from None


def default_arm() -> Arm:
    """The paper's 7-DOF CDRA, from the model file embedded in the package."""
    ref = importlib.resources.files("cdra_jax.data").joinpath(_DEFAULT_MODEL)
    return loads_model(ref.read_text(encoding="utf-8"), source=f"<cdra_jax>/data/{_DEFAULT_MODEL}")


def default_model_text() -> str:
    """Text of the embedded default model file."""
    ref = importlib.resources.files("cdra_jax.data").joinpath(_DEFAULT_MODEL)
    return ref.read_text(encoding="utf-8")


def _floats(a: Any) -> Any:
    return np.asarray(a, dtype=float).tolist()


def arm_to_dict(arm: Arm, *, exact: bool = False) -> dict[str, Any]:
    """Mapping for :func:`dumps_model` (frames as ``matrix`` when ``exact``)."""
    frames = []
    for name, M in zip(arm.frame_names, np.asarray(arm.frames), strict=True):
        if exact:
            frames.append({"name": name, "matrix": _floats(M)})
        else:
            xyz, rv = lie.to_xyz_rotvec(device_array(M))
            frames.append({"name": name, "xyz": _floats(xyz), "rotvec": _floats(rv)})
    modules = []
    for m in arm.modules:
        d: dict[str, Any] = {"name": m.name, "kind": m.kind}
        if m.kind != "spherical":
            d["axis"] = _floats(m.axis)
        d["limits"] = [list(lim) for lim in m.limits]
        if m.cable_base is not None and m.cable_platform is not None:
            d["cables"] = [
                {"base": _floats(b), "platform": _floats(p)}
                for b, p in zip(np.asarray(m.cable_base), np.asarray(m.cable_platform), strict=True)
            ]
            if m.cable_offset is not None:
                for c, o in zip(d["cables"], np.asarray(m.cable_offset), strict=True):
                    c["offset"] = float(o)
        if m.mass is not None:
            d["mass"] = float(m.mass)
        if m.com is not None:
            d["com"] = _floats(m.com)
        if m.pretension is not None:
            d["pretension"] = float(m.pretension)
        if m.stiffness is not None:
            d["stiffness"] = float(m.stiffness)
        modules.append(d)
    out: dict[str, Any] = {"name": arm.name}
    if arm.description:
        out["description"] = arm.description
    out["gravity"] = _floats(arm.gravity)
    out["frames"] = frames
    out["modules"] = modules
    if arm.markers:
        out["markers"] = [
            {"name": mk.name, "xyz": list(mk.xyz), **({"calibrate": True} if mk.calibrate else {})}
            for mk in arm.markers
        ]
    if arm.effects:
        out["effects"] = effects_to_list(arm.effects)
    return out


def dumps_model(arm: Arm, *, exact: bool = False) -> str:
    """Model TOML text of ``arm``."""
    return tomli_w.dumps(arm_to_dict(arm, exact=exact))


def save_model(
    arm: Arm, path: str | os.PathLike, *, exact: bool = False, force: bool = False
) -> Path:
    """Write ``arm`` as a model TOML file (see :func:`dumps_model`); returns the path.

    Written atomically (a reader or a crash never sees half a file); an existing file is only
    replaced with ``force=True``, otherwise :class:`~cdra_jax.io.OutputExistsError`.
    """
    return write_text_atomic(path, dumps_model(arm, exact=exact), force=force)
