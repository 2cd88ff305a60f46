"""The simulate workflow: synthetic measurements as in Section V of the paper.

:func:`simulate` draws module states within the joint limits (tension-feasible where the model
has cables; step 1), applies preset errors to the fixed frames, ``T_actual = exp(dt^) T_nominal``
(Eqs. 11-14; step 2), and measures the tool poses of the erroneous arm with optional Gaussian
noise (step 3). The returned :class:`SimulationRun` holds the measurements (a measurement file
with the preset errors as ``#`` comments) and the truth (the preset errors and actual frames).

A model with ``[[effects]]`` is simulated with them (:func:`cdra_jax.physics.model_tool_pose`
at the actual frames): the measurement file then also carries the auxiliary columns that the
effects need (``time_s``: one pose every :data:`DT_S` seconds; ``approach.<module>``: +1 or -1
at random; ``payload_kg``: uniform in 0 to :data:`PAYLOAD_MAX_KG`), and the truth records the
effects.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax
import numpy as np
from jax.typing import ArrayLike

from .. import lie
from ..arm import Arm, apply_frame_errors, tool_pose
from ..calibration import NoiseModel
from ..compilation import cached_filter_jit
from ..io import (
    Measurements,
    load_frame_errors,
    load_marker_truth,
    save_frame_errors,
    save_measurements,
)
from ..io.files import json_text
from ..io.frame_errors import frame_errors_to_dict
from ..io.model import effects_to_list
from ..io.results import package_version
from ..modules.cable_data import simulate_cable_lengths
from ..physics import corrected_tool_pose, model_effects, model_features, needed_aux
from ..simulation import add_measurement_noise, random_frame_errors, sample_poses
from .calibrate import frame_table
from .inputs import Model, check_range, check_seed, resolve_arm

if TYPE_CHECKING:
    from matplotlib.figure import Figure

_FILE_KEYS = ("format", "format_version", "frames")
DEFAULT_D_V_MM = 1.0
"""Range of random translation errors per component (the paper's Section V)."""
DEFAULT_D_W_RAD = 0.05
"""Range of random rotation errors per component (the paper's Section V)."""
DT_S = 20.0
"""Time between simulated poses (s), for the ``time_s`` column of a model with effects."""
PAYLOAD_MAX_KG = 1.0
"""Largest simulated payload (kg), for the ``payload_kg`` column of a model with effects."""


def _effect_aux(arm: Arm, m: int, seed: int) -> dict[str, np.ndarray]:
    """The auxiliary columns the model's effects need, simulated (see the module docstring)."""
    if not arm.effects:
        return {}
    names = ("time_s", "payload_kg", *(f"approach.{n}" for n in arm.module_names))
    rng = np.random.default_rng([seed, 13])
    out = {}
    for name in needed_aux(arm, names):
        if name == "time_s":
            out[name] = np.arange(m, dtype=float) * DT_S
        elif name == "payload_kg":
            out[name] = rng.uniform(0.0, PAYLOAD_MAX_KG, m)
        else:
            out[name] = np.where(rng.uniform(size=m) < 0.5, -1.0, 1.0)
    return out


def _tool_poses(actual: Arm, q, aux):
    """Noise-free tool poses of the actual arm, with the model's effects."""
    cands, theta = model_effects(actual)
    if not cands:
        return tool_pose(actual, q)
    features = model_features(actual, q, aux, cands)
    return corrected_tool_pose(actual, q, features, jax.numpy.asarray(theta, q.dtype))


def _simulation(key, arm, X, d_v, d_w, m: int, noise, random_errors: bool, aux):
    """Section V steps 1-3 in one compiled call: the preset errors ``(K+1, 6)``, the module
    states ``(m, dof)``, the measured tool poses ``(m, 4, 4)`` (with the model's effects) and
    the actual frames ``(K+1, 4, 4)`` with their translations and rotation vectors."""
    k_err, k_states, k_noise = jax.random.split(key, 3)
    if random_errors:
        X = random_frame_errors(k_err, arm, d_v, d_w).reshape(-1, 6)
    actual = apply_frame_errors(arm, X)
    q = sample_poses(k_states, arm, m)
    xyz, rotvec = lie.to_xyz_rotvec(actual.frames)
    measured = add_measurement_noise(k_noise, _tool_poses(actual, q, aux), noise)
    return X, q, measured, actual.frames, xyz, rotvec


@dataclasses.dataclass(frozen=True, eq=False)
class SimulationRun:
    """Synthetic measurements and the truth behind them.

    Attributes:
        arm: the nominal model.
        measurements: the simulated measurement file's content.
        errors: ``(K+1, 6)`` preset error twists ``[vx, vy, vz (mm), wx, wy, wz (rad)]``.
        actual_frames: ``(K+1, 4, 4)`` the frames of the erroneous ("actual") arm.
        truth: the truth mapping (:meth:`to_dict`, the ``--truth`` JSON).
        summary_lines: the report's lines.
    """

    arm: Arm
    measurements: Measurements
    errors: np.ndarray
    actual_frames: np.ndarray
    truth: dict[str, Any]
    summary_lines: tuple[str, ...]

    def to_dict(self) -> dict[str, Any]:
        """The truth: preset errors per frame, actual frames, seed, noise and sizes."""
        return self.truth

    def to_json(self) -> str:
        """The truth as JSON text (the frame-error file format)."""
        return json_text(self.truth)

    def save(
        self,
        path: str | os.PathLike,
        truth: str | os.PathLike | None = None,
        *,
        force: bool = False,
    ) -> list[Path]:
        """Write the measurement CSV (and, with ``truth``, the truth JSON); returns the paths
        written (truth first)."""
        out = []
        if truth is not None:
            meta = {k: v for k, v in self.truth.items() if k not in _FILE_KEYS}
            meta["measurements"] = str(path)
            out.append(save_frame_errors(truth, self.arm, self.errors, metadata=meta, force=force))
        out.append(save_measurements(self.measurements, path, force=force))
        return out

    def report(self) -> str:
        """The plain-text summary ``cdra-jax simulate`` prints (before the written files)."""
        return "\n".join(self.summary_lines)

    def plot(self) -> Figure:
        """The preset error twist of each frame: translation (mm) and rotation (rad) bars."""
        from ..plots import new_figure

        fig = new_figure(10.0, 3.6)
        names = list(self.arm.frame_names)
        x = np.arange(len(names))
        for i, (sl, unit, labels) in enumerate(
            ((slice(0, 3), "mm", "v"), (slice(3, 6), "rad", "w"))
        ):
            ax = fig.add_subplot(1, 2, i + 1)
            for j, c in enumerate("xyz"):
                ax.bar(x + (j - 1) * 0.25, self.errors[:, sl][:, j], 0.25, label=f"{labels}{c}")
            ax.set_xticks(x, names)
            ax.set_ylabel(f"preset error [{unit}]")
            ax.axhline(0.0, color="0.5", lw=0.6)
            ax.legend(fontsize="small")
        return fig


def simulate(
    model: Model,
    poses: int,
    *,
    seed: int = 0,
    errors: str | ArrayLike | os.PathLike = "random",
    d_v: float | None = None,
    d_w: float | None = None,
    noise: NoiseModel | None = None,
    cables: bool = False,
    cable_noise: float | None = None,
    points: bool = False,
    occlusion: float = 0.0,
    marker_error_mm: float = 0.0,
    device_frame: ArrayLike | None = None,
    model_label: str | None = None,
) -> SimulationRun:
    """Simulate ``poses`` measured tool poses of a model with preset frame errors (Section V).

    Args:
        model: an :class:`~cdra_jax.arm.Arm`, a model TOML path, or ``None`` (embedded CDRA).
        poses: number of poses (>= 1).
        seed: PRNG seed of the errors, the states and the noise.
        errors: ``"random"`` (uniform in ``+-d_v`` mm / ``+-d_w`` rad per component),
            ``"zero"``, a ``(K+1, 6)`` array, or the path of a frame-error JSON/TOML file
            (``--truth`` of an earlier simulation: its ``markers`` table, when present, gives
            the true marker positions too, so that a second data set shares the first's truth).
        d_v, d_w: ranges of the random errors (default 1 mm and 0.05 rad, the paper's).
        noise: Gaussian noise on the measured poses (std), or ``None`` for noise-free data;
            with ``points`` only its position std is used (per point coordinate).
        cables: write the states of modules with cables as cable lengths.
        cable_noise: std (mm) of Gaussian noise on each cable length (needs ``cables``).
        points: measure points instead of full poses: the model's markers
            (``measured.<marker>.x/y/z``), or the tool-frame origin (``measured.x/y/z``) for a
            model without markers; the position noise std applies to each point.
        occlusion: probability that a point is not seen in a row (an empty cell; every row
            keeps at least one point).
        marker_error_mm: markers with ``calibrate = true`` sit off their model position by a
            uniform error in ``+-marker_error_mm`` per component (the truth records where).
        device_frame: ``(6,)`` ``[x, y, z (mm), rx, ry, rz (rad)]``: the pose of the robot's
            world frame in the measuring device's frame; measurements are written in the device
            frame (default: the same frame).
        model_label: name of the model in the report.
    """
    check_range("poses", poses)
    is_random = isinstance(errors, str) and errors == "random"
    is_zero = isinstance(errors, str) and errors == "zero"
    if not is_random and (d_v is not None or d_w is not None):
        raise ValueError("d_v/d_w set the range of random errors; they need errors='random'")
    d_v = check_range("d_v", DEFAULT_D_V_MM if d_v is None else d_v)
    d_w = check_range("d_w", DEFAULT_D_W_RAD if d_w is None else d_w)
    check_seed(seed)
    if cable_noise is not None and not cables:
        raise ValueError("cable_noise needs cables=True (noise on the written cable lengths)")
    cable_noise = check_range("cable_noise", 0.0 if cable_noise is None else cable_noise)
    arm, model_label = resolve_arm(model, model_label)
    X = np.zeros((len(arm.frame_names), 6))
    given_markers: dict = {}
    if is_random:
        errors_text = f"random, uniform in +-{d_v:g} mm / +-{d_w:g} rad per component"
        errors_label = "random"
    elif is_zero:
        errors_text = errors_label = "zero"
    elif isinstance(errors, str | os.PathLike):
        X = load_frame_errors(errors, arm)
        given_markers = load_marker_truth(errors, arm)
        errors_text = f"from {errors}"
        errors_label = str(errors)
    else:
        X = np.asarray(errors, dtype=float).reshape(len(arm.frame_names), 6)
        errors_text = errors_label = "given"
    aux = _effect_aux(arm, poses, seed)
    out = cached_filter_jit(_simulation)(
        jax.random.PRNGKey(seed),
        arm,
        X,
        np.asarray(d_v),
        np.asarray(d_w),
        poses,
        noise,
        is_random,
        aux,
    )
    X, q, measured, actual_frames, actual_xyz, actual_rotvec = (np.asarray(a) for a in out)
    if noise is None:
        noise_text = "none (noise-free)"
    elif points:
        noise_text = f"{float(noise.position_mm)!r} mm per point coordinate (std, Gaussian)"
    else:
        noise_text = (
            f"position {float(noise.position_mm)!r} mm, rotation "
            f"{float(noise.rotation_rad)!r} rad (std, Gaussian)"
        )
    comments = [
        f"cdra-jax {package_version()} simulate: model {arm.name} ({model_label}), "
        f"{poses} poses, seed {seed}",
        f"measurement noise: {noise_text}",
        f"preset frame errors ({errors_text}); T_actual = exp(dt) T_nominal (Eqs. 11-14),",
        "dt = [vx, vy, vz (mm), wx, wy, wz (rad)]:",
        *(
            f"  {name} = [{', '.join(repr(float(v)) for v in row)}]"
            for name, row in zip(arm.frame_names, X, strict=True)
        ),
    ]
    if arm.effects:
        comments.append(
            "simulated with the model's effects: "
            + "; ".join(
                e.label + " " + ", ".join(f"{n} = {v!r} {u}" for n, v, u in e.parameters)
                for e in arm.effects
            )
        )
    cable_lengths = None
    if cables:
        cable_lengths = {
            k: np.asarray(v)
            for k, v in simulate_cable_lengths(
                jax.random.fold_in(jax.random.PRNGKey(seed), 7), arm, q, cable_noise
            ).items()
        }
        if not cable_lengths:
            raise ValueError(f"cables: no module of model {arm.name!r} has cables")
        comments.append(
            f"cable lengths (mm) for {', '.join(cable_lengths)}; noise std {cable_noise!r} mm"
        )
    device = np.eye(4)
    if device_frame is not None:
        d = np.asarray(device_frame, dtype=float)
        if d.shape != (6,) or not np.all(np.isfinite(d)):
            raise ValueError(
                f"device_frame: expected 6 finite numbers [x, y, z (mm), rx, ry, rz (rad)], "
                f"got {device_frame!r}"
            )
        device = np.asarray(lie.from_xyz_rotvec(d[:3], d[3:]))
        comments.append(
            "measured in the device frame; robot world frame in it: "
            f"xyz {d[:3].tolist()} mm, rotvec {d[3:].tolist()} rad"
        )
    check_range("occlusion", occlusion)
    check_range("marker_error_mm", marker_error_mm, "marker_error")
    if (occlusion or marker_error_mm) and not points:
        raise ValueError("occlusion and marker_error_mm need points=True (measured points)")
    measured = np.einsum("ij,mjk->mik", device, measured)
    true_markers = {}
    point_data = None
    if points:
        rng = np.random.default_rng([seed, 11])
        names = [mk.name for mk in arm.markers] or ["origin"]
        xyz = np.array([mk.xyz for mk in arm.markers]) if arm.markers else np.zeros((1, 3))
        if given_markers and marker_error_mm:
            raise ValueError(
                "marker_error_mm draws the true marker positions; the errors file already "
                "gives them (its markers table): leave one out"
            )
        for j, mk in enumerate(arm.markers):
            if mk.name in given_markers:
                xyz[j] = given_markers[mk.name]
            elif mk.calibrate and marker_error_mm:
                xyz[j] = xyz[j] + rng.uniform(-marker_error_mm, marker_error_mm, 3)
            true_markers[mk.name] = xyz[j].tolist()
        # Noise-free tool poses in the device frame, then isotropic noise on every point.
        clean = device @ np.asarray(
            cached_filter_jit(_tool_poses)(arm.with_frames(actual_frames), q, aux)
        )
        pts = np.einsum("mij,pj->mpi", clean[:, :3, :3], xyz) + clean[:, None, :3, 3]
        if noise is not None:
            pts = pts + float(noise.position_mm) * rng.standard_normal(pts.shape)
        hidden = rng.uniform(size=pts.shape[:2]) < occlusion
        all_hidden = hidden.all(axis=1)
        hidden[all_hidden, rng.integers(0, pts.shape[1], int(all_hidden.sum()))] = False
        pts[hidden] = np.nan
        point_data = {name: pts[:, j] for j, name in enumerate(names)}
        comments.append(
            f"points measured: {', '.join(names)}; occlusion probability {occlusion!r}"
            + (
                f"; calibrate markers off by up to {marker_error_mm!r} mm"
                if marker_error_mm
                else ""
            )
        )
    meas = Measurements.from_arrays(
        arm,
        q,
        None if points else measured,
        comments=comments,
        cable_lengths=cable_lengths,
        points=point_data,
        aux=aux or None,
    )
    truth = {
        "format": "cdra_jax.frame_errors",
        "format_version": 1,
        "cdra_jax_version": package_version(),
        "model": arm.name,
        "inputs": {"model": model_label, "errors": errors_label},
        "seed": seed,
        "poses": poses,
        "d_v_mm": d_v if is_random else None,
        "d_w_rad": d_w if is_random else None,
        "noise": None
        if noise is None
        else {
            "position_mm": float(noise.position_mm),
            "rotation_rad": None if points else float(noise.rotation_rad),
        },
        "actual_frames": {
            name: {
                "xyz": actual_xyz[j].tolist(),
                "rotvec": actual_rotvec[j].tolist(),
                "matrix": actual_frames[j].tolist(),
            }
            for j, name in enumerate(arm.frame_names)
        },
        "frames": frame_errors_to_dict(arm, X),
    }
    if arm.effects:
        truth["effects"] = effects_to_list(arm.effects)
    if device_frame is not None:
        truth["device_frame"] = device.tolist()
    if true_markers:
        truth["markers"] = true_markers
    lines = (
        f"model: {arm.name} ({model_label}); {poses} poses, seed {seed}",
        f"measurement noise: {noise_text}",
        *(
            [f"effects of the model simulated: {', '.join(e.label for e in arm.effects)}"]
            if arm.effects
            else []
        ),
        *frame_table(arm.frame_names, X, f"preset frame errors ({errors_text}; v mm, w rad):"),
    )
    return SimulationRun(
        arm=arm,
        measurements=meas,
        errors=X,
        actual_frames=actual_frames,
        truth=truth,
        summary_lines=lines,
    )
