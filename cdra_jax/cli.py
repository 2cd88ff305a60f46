"""The ``cdra-jax`` command line: ``calibrate`` a model from a measurement file, ``simulate`` one.

Usage::

    cdra-jax simulate --poses 20 --seed 1 --out poses.csv --truth truth.json
    cdra-jax calibrate --data poses.csv --out result.json [--model arm.toml] [--solver paper|lm]
        [--loss ls|huber|cauchy [--reject-outliers]]

Exit codes: 0 success; 1 bad input or a file problem (one line ``error: ...`` on stderr, no
traceback); 2 wrong usage (argparse); 3 the calibration did not converge (the result file is
still written, with ``"converged": false``). Warnings (implausible data, a degenerate or poorly
conditioned pose set, outliers) do not change the exit code: each is one ``warning: ...`` line on
stderr and an entry of ``warnings`` in the result file.

Adding a subcommand: write a ``_register_<name>(subparsers)`` function that adds its parser and
sets ``func`` (a callable ``args -> int``) with ``set_defaults``, and append it to
:data:`SUBCOMMANDS`; for a module ``cdra_jax.<module>`` that provides ``register(subparsers)``
and ``run(args) -> int``, append ``_external("<module>")``. Import JAX-heavy code inside the run
function, not at the top of this file. ``main`` enables ``jax_enable_x64`` before running any
subcommand and turns ``ValueError``, ``OSError`` and a failed run-time check inside compiled
code (``equinox.EquinoxRuntimeError``, e.g. a model whose cables hold no pose) into the one-line
error.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import importlib
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from . import cli_common

Registrar = Callable[[Any], None]
"""``register(subparsers)``: adds one subcommand parser with ``set_defaults(func=run)``."""

EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_NOT_CONVERGED = 0, 1, 2, 3
_DEFAULT_MODEL_LABEL = "<cdra_jax>/data/cdra.toml"


# --------------------------------------------------------------------------- shared options


def _add_model_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--model",
        metavar="M",
        help="model TOML file (default: the embedded 7-DOF CDRA of the paper)",
    )


def _add_noise_options(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--noise-pos", metavar="MM", type=float, help=f"position noise std (mm) {what}")
    p.add_argument(
        "--noise-rot", metavar="RAD", type=float, help=f"orientation noise std (rad) {what}"
    )


def _add_force_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--force", action="store_true", help="overwrite existing output files")


def _noise(args: argparse.Namespace):
    """The :class:`NoiseModel` of ``--noise-pos``/``--noise-rot`` (both or neither), or None."""
    pos, rot = args.noise_pos, args.noise_rot
    if (pos is None) != (rot is None):
        raise ValueError("--noise-pos and --noise-rot go together: give both or neither")
    if pos is None:
        return None
    for flag, v in (("--noise-pos", pos), ("--noise-rot", rot)):
        if not v > 0 or v == float("inf"):
            raise ValueError(f"{flag} must be a positive number, got {v}")
    from .calibration import NoiseModel

    return NoiseModel(position_mm=pos, rotation_rad=rot)


def _load_arm(model: str | None):
    """``(arm, label)``: the model file, or the embedded default when ``model`` is None."""
    from .io import default_arm, load_model

    if model is None:
        return default_arm(), _DEFAULT_MODEL_LABEL
    return load_model(model), model


def _check_output(path: str | None, force: bool, flag: str) -> None:
    """Fail before any work when an output exists (no ``--force``) or its folder is missing
    (:func:`cdra_jax.cli_common.check_output`)."""
    cli_common.check_output(path, force, flag)


FRAME_ERROR_PLAUSIBLE_MM = 50.0
"""Identified frame errors beyond this translation (norm of the twist's v, mm) ..."""
FRAME_ERROR_PLAUSIBLE_RAD = 0.5
"""... or this rotation (norm of w, rad) make ``calibrate`` warn: a calibration corrects small
errors of a nominal model, so such a result usually comes from gross errors in the data (a typo,
swapped rows, wrong units) or too few poses to outvote them."""


def implausible_frame_errors_warning(result: dict) -> str | None:
    """The warning for identified frame errors beyond :data:`FRAME_ERROR_PLAUSIBLE_MM` or
    :data:`FRAME_ERROR_PLAUSIBLE_RAD` in a result dict, or None."""
    import math

    large = []
    for name, frame in result["frames"].items():
        t = frame["error_twist"]
        v = math.sqrt(sum((t[c] or 0.0) ** 2 for c in ("vx", "vy", "vz")))
        w = math.sqrt(sum((t[c] or 0.0) ** 2 for c in ("wx", "wy", "wz")))
        if v > FRAME_ERROR_PLAUSIBLE_MM or w > FRAME_ERROR_PLAUSIBLE_RAD:
            large.append(f"{name} (|v| = {v:.4g} mm, |w| = {w:.3g} rad)")
    if not large:
        return None
    unidentifiable = (result.get("identifiability") or {}).get("unidentifiable") or []
    return (
        f"implausibly large identified frame errors: {', '.join(large)}, above "
        f"{FRAME_ERROR_PLAUSIBLE_MM:g} mm or {FRAME_ERROR_PLAUSIBLE_RAD:g} rad; a calibration "
        "corrects small errors of the nominal model: check the data for gross errors (typos, "
        "swapped rows, wrong units) and measure more poses"
        + (
            " (part of the error may lie along the unidentifiable directions listed in the "
            "summary, which the tool poses do not determine)"
            if unidentifiable
            else ""
        )
    )


def _sha256(path: str) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _fmt(x: float | None, spec: str = ".4e") -> str:
    return "-" if x is None else format(x, spec)


def _frame_table(names: Sequence[str], rows, title: str) -> list[str]:
    from .arm import TWIST_COMPONENTS

    width = max(len(n) for n in names)
    lines = [title, "  " + " " * width + "".join(f"{c:>13}" for c in TWIST_COMPONENTS)]
    for name, row in zip(names, rows, strict=True):
        lines.append("  " + f"{name:<{width}}" + "".join(f"{float(v):>13.6g}" for v in row))
    return lines


@functools.cache
def _jitted(fn: Callable) -> Callable:
    """:func:`cdra_jax.compilation.filter_jit` of ``fn``, made once per function so repeated
    calls reuse the compile.

    One compiled program per solve starts several times faster than op-by-op dispatch.
    """
    from .compilation import filter_jit

    return filter_jit(fn)


def _simulation(key, arm, X, d_v, d_w, m: int, noise, random_errors: bool):
    """Section V steps 1-3 in one compiled call (see :func:`_run_simulate`).

    Returns the preset errors ``(K+1, 6)`` (random ones when ``random_errors``, else ``X``),
    the module states ``(m, dof)``, the measured tool poses ``(m, 4, 4)`` and the actual frames
    ``(K+1, 4, 4)`` with their translations and rotation vectors.
    """
    import jax

    from . import lie
    from .arm import apply_frame_errors
    from .simulation import measure, random_frame_errors, sample_poses

    k_err, k_states, k_noise = jax.random.split(key, 3)
    if random_errors:
        X = random_frame_errors(k_err, arm, d_v, d_w).reshape(-1, 6)
    actual = apply_frame_errors(arm, X)
    q = sample_poses(k_states, arm, m)
    xyz, rotvec = lie.to_xyz_rotvec(actual.frames)
    return X, q, measure(k_noise, actual, q, noise), actual.frames, xyz, rotvec


# --------------------------------------------------------------------------- calibrate


def _register_calibrate(subparsers) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="identify the fixed-frame errors of a model from a measurement CSV",
        description=(
            "Calibrate the fixed transforms of a modular arm from measured tool poses "
            "(Mustafa et al. 2008, Eqs. 7-21) and write the result as JSON. Without "
            "--noise-pos/--noise-rot the paper solver is the paper's unweighted iterative least "
            "squares; with them both solvers whiten the residual by the noise model."
        ),
    )
    _add_model_option(p)
    p.add_argument("--data", metavar="D", required=True, help="measurement CSV file")
    p.add_argument("--out", metavar="R", required=True, help="result JSON file to write")
    p.add_argument(
        "--solver",
        choices=("paper", "lm"),
        default="paper",
        help="paper: iterative least squares (Eqs. 10-14, default); lm: Levenberg-Marquardt",
    )
    _add_noise_options(p, "of the measured tool poses, to weight the residual")
    p.add_argument(
        "--loss",
        choices=("ls", "huber", "cauchy"),
        default="ls",
        help="ls: plain least squares, as in the paper (default); huber or cauchy: robust "
        "estimation that down-weights outlying poses (iteratively reweighted, around --solver)",
    )
    p.add_argument(
        "--reject-outliers",
        action="store_true",
        help="with --loss huber|cauchy: finish with a least-squares refit that leaves out the "
        "flagged poses (kept only when it loses no identifiable direction; they stay in the "
        "result)",
    )
    p.add_argument(
        "--max-iterations",
        metavar="N",
        type=int,
        help="iteration cap (default: 20 for paper, 50 for lm; per round for a robust loss)",
    )
    _add_force_option(p)
    p.set_defaults(func=_run_calibrate)


def _run_calibrate(args: argparse.Namespace) -> int:
    noise = _noise(args)
    if args.max_iterations is not None and args.max_iterations < 1:
        raise ValueError(f"--max-iterations must be at least 1, got {args.max_iterations}")
    if args.reject_outliers and args.loss == "ls":
        raise ValueError(
            "--reject-outliers needs a robust loss to flag the outliers: add --loss huber or "
            "--loss cauchy"
        )
    cli_common.check_distinct_files(
        [("--out", args.out)], [("--data", args.data), ("--model", args.model)]
    )
    _check_output(args.out, args.force, "--out")

    from .calibration import calibrate_lm, calibrate_paper, calibrate_robust
    from .conditioning import conditioning
    from .identifiability import analyze, generic_rank
    from .io import (
        check_plausibility,
        check_pose_count,
        load_measurements,
        result_to_dict,
        save_result,
    )

    arm, model_label = _load_arm(args.model)
    meas = load_measurements(args.data, arm)
    check_pose_count(meas)
    assert meas.measured is not None  # the reader demands the measured columns by default
    # Wrong units or conventions stop here with an error naming the column; the rest warns.
    warnings = list(check_plausibility(arm, meas))
    kwargs: dict[str, Any] = {"throw": False}
    if args.max_iterations is not None:
        kwargs["max_iterations"] = args.max_iterations
    sol: Any
    if args.loss == "ls":
        solve = calibrate_paper if args.solver == "paper" else calibrate_lm
        sol = _jitted(solve)(arm, meas.q, meas.measured, noise, **kwargs)
    else:
        kwargs.update(loss=args.loss, solver=args.solver, reject_outliers=args.reject_outliers)
        sol = _jitted(calibrate_robust)(arm, meas.q, meas.measured, noise, **kwargs)
    # Unidentifiable directions are reported at the nominal model, where they read simply
    # (e.g. "0.707 upper_arm.vy - 0.707 forearm.vy" for the CDRA).
    report = analyze(arm, meas.q, meas.measured, noise)
    cond = conditioning(arm, meas.q, meas.measured, noise)
    # A pose set that identifies less than poses spread over the joint ranges would (repeated
    # poses, a module that never moves) is degenerate data: say so on stderr. Directions that no
    # pose set identifies (the CDRA's two along the elbow axis) are a property of the model:
    # they stay in the summary and the JSON.
    generic = generic_rank(arm, meas.m, noise)
    degenerate = []
    if report.rank < generic:
        degenerate = [
            f"degenerate pose set: rank {report.rank} of {report.n_params} parameters from "
            f"{report.n_poses} poses, where as many poses spread over the joint ranges give "
            f"{generic}; {generic - report.rank} more combination(s) are lost to the pose set "
            "(the unidentifiable directions are listed in the summary)",
            *report.warnings,
        ]
    shown = list(warnings) + degenerate  # printed on stderr
    if cond.warning:
        shown.append(cond.warning)
    result = result_to_dict(
        arm,
        sol,
        meas.q,
        meas.measured,
        noise=noise,
        identifiability=report.to_dict(),
        pose_ids=meas.pose_ids,
        inputs={"model": model_label, "data": args.data, "data_sha256": _sha256(args.data)},
        conditioning=cond.to_dict(),
        warnings=[
            *warnings,
            *degenerate[:1],
            *report.warnings,
            *([cond.warning] if cond.warning else []),
        ],
    )
    implausible = implausible_frame_errors_warning(result)
    if implausible is not None:
        result["warnings"].append(implausible)
    shown += [w for w in result["warnings"] if w not in shown and w not in report.warnings]
    ident = report.summary()
    if noise is not None:
        # Covariance of the identified parameters, Cramer-Rao bound and 95 % intervals, at the
        # calibrated model (issue: uncertainty with noise weights); a robust fit's with its final
        # IRLS weights, so down-weighted poses carry less information.
        import numpy as np

        from .io import calibrated_arm_from_result
        from .uncertainty import analyze_uncertainty

        unc = analyze_uncertainty(
            calibrated_arm_from_result(result, arm),
            meas.q,
            noise,
            meas.measured,
            estimate=result_errors(result, arm),
            weights=None if args.loss == "ls" else np.asarray(sol.weights),
        )
        result["uncertainty"] = unc.to_dict()
        ident = ident + "\n" + unc.summary()
    print(_calibration_summary(arm, result, model_label, args.data, ident))
    path = save_result(result, args.out, force=args.force)
    print(f"wrote {path}")
    for w in shown:
        print(f"warning: {w}", file=sys.stderr)
    if not result["converged"]:
        print(f"warning: not converged: {result['message']}", file=sys.stderr)
        return EXIT_NOT_CONVERGED
    return EXIT_OK


def result_errors(result: dict, arm) -> Any:
    """Identified error twists ``(K+1, 6)`` (Eqs. 15-18) from a result dict, frame order."""
    import numpy as np

    from .arm import TWIST_COMPONENTS

    return np.array(
        [
            [
                np.nan if (v := result["frames"][f]["error_twist"][c]) is None else v
                for c in TWIST_COMPONENTS
            ]
            for f in arm.frame_names
        ]
    )


def _calibration_summary(arm, r: dict, model_label: str, data: str, ident: str) -> str:
    from .arm import TWIST_COMPONENTS

    solver_text = {
        "paper": "paper (the paper's unweighted iterative least squares, Eqs. 9-14)",
        "weighted": "paper, weighted by the noise model (iterative least squares, Eqs. 9-14)",
        "lm": "lm (Levenberg-Marquardt)" + ("" if r["noise"] is None else ", weighted"),
    }
    rob = r.get("robust")
    out = r.get("outliers") or {}
    scale = out.get("scale") or {}
    if rob is None:
        text = solver_text[r["solver"]]
    else:
        text = (
            f"{rob['loss']} (robust, c = {rob['tuning_constant']:g}) by iteratively reweighted "
            f"least squares around {solver_text[rob['inner_solver']].split(' (')[0]}; "
            f"{rob['rounds']} reweighting round{'s' if rob['rounds'] != 1 else ''}"
        )
        if rob.get("refit_without_flagged"):
            n_out = len(out.get("poses") or [])
            text += (
                f"; then least squares without the {n_out} flagged pose(s) (--reject-outliers)"
                if n_out
                else "; then least squares on all poses (none flagged, --reject-outliers)"
            )
        elif rob.get("reject_outliers"):
            text += (
                "; the refit without the flagged poses was not kept (fewer than 4 poses left, "
                "an identifiable direction lost, or not converged)"
            )
    lines = [
        f"model: {arm.name} ({model_label}); data: {data} ({r['n_poses']} poses)",
        f"solver: {text}",
    ]
    if r["noise"] is not None:
        n = r["noise"]
        lines.append(f"noise model: {n['position_mm']:g} mm, {n['rotation_rad']:g} rad")
    lines.append(f"  {'iter':>4}  {'step norm':>11}  {'dp [mm]':>11}  {'dR [rad]':>11}")
    init = r["initial"]
    lines.append(
        f"  {0:>4}  {'-':>11}  {_fmt(init['delta_p_mm']):>11}  {_fmt(init['delta_R_rad']):>11}"
    )
    for it in r["iterations"]:
        lines.append(
            f"  {it['iteration']:>4}  {_fmt(it['step_norm']):>11}  "
            f"{_fmt(it['delta_p_mm']):>11}  {_fmt(it['delta_R_rad']):>11}"
        )
    k = len(r["iterations"])
    status = "converged" if r["converged"] else f"NOT converged ({r['result']})"
    lines.append(
        f"{status} after {k} iteration{'s' if k != 1 else ''}: dp = "
        f"{_fmt(r['final']['delta_p_mm'], '.3g')} mm, dR = "
        f"{_fmt(r['final']['delta_R_rad'], '.3g')} rad (Eqs. 20-21, fitted poses)"
    )
    names = list(r["frames"])
    nan = float("nan")
    twists = [r["frames"][n]["error_twist"] for n in names]
    rows = [[nan if t[c] is None else t[c] for c in TWIST_COMPONENTS] for t in twists]
    lines += _frame_table(
        names, rows, "identified frame errors dt = log(T^c T^-1) (Eqs. 15-18; v mm, w rad):"
    )
    lines.append(ident)
    if scale:
        flagged = [x for x in r["residuals"] if x.get("outlier")]
        sp, sr = _fmt(scale["position_mm"], ".3g"), _fmt(scale["rotation_rad"], ".3g")
        lines.append(
            f"outliers (z > {out['threshold']:.3g}; residual scale {sp} mm, {sr} rad from the "
            f"{scale['source']}): " + (str(len(flagged)) if flagged else "none")
        )
        for x in sorted(flagged, key=lambda x: -(x["z"] or 0.0)):
            lines.append(
                f"  {x['pose']}: z = {_fmt(x['z'], '.3g')}, weight {_fmt(x['weight'], '.2g')}, "
                f"calibrated residual {_fmt(x['calibrated_position_mm'], '.3g')} mm, "
                f"{_fmt(x['calibrated_rotation_rad'], '.3g')} rad"
            )
    return "\n".join(lines)


# --------------------------------------------------------------------------- simulate


def _register_simulate(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="write a synthetic measurement CSV (Section V of the paper)",
        description=(
            "Simulate measurements as in Section V of the paper: random module states within the "
            "joint limits, preset errors on the fixed frames (T_actual = exp(dt) T_nominal), "
            "tool poses of the erroneous arm, optional measurement noise. The preset errors are "
            "written as '#' comments at the top of the CSV and, with --truth, as JSON."
        ),
    )
    _add_model_option(p)
    p.add_argument("--poses", metavar="N", type=int, required=True, help="number of poses")
    p.add_argument("--seed", metavar="S", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--errors",
        metavar="random|zero|FILE",
        default="random",
        help="preset frame errors: random (uniform in +-d_v, +-d_w; default), zero, or a "
        "JSON/TOML file of per-frame error twists",
    )
    p.add_argument(
        "--d-v",
        metavar="MM",
        type=float,
        help="range of random translation errors, per component (default 1 mm)",
    )
    p.add_argument(
        "--d-w",
        metavar="RAD",
        type=float,
        help="range of random rotation errors, per component (default 0.05 rad)",
    )
    _add_noise_options(p, "added to the measured tool poses (default: noise-free)")
    p.add_argument(
        "--cables",
        action="store_true",
        help="write the states of modules with cables as cable lengths <module>.l1 ... .lN",
    )
    p.add_argument(
        "--cable-noise",
        metavar="MM",
        type=float,
        help="std of Gaussian noise on each cable length; needs --cables (default 0)",
    )
    p.add_argument("--out", metavar="D", required=True, help="measurement CSV file to write")
    p.add_argument("--truth", metavar="T.json", help="also write the preset errors as JSON")
    _add_force_option(p)
    p.set_defaults(func=_run_simulate)


def _run_simulate(args: argparse.Namespace) -> int:
    noise = _noise(args)
    if args.poses < 1:
        raise ValueError(f"--poses must be at least 1, got {args.poses}")
    if args.errors != "random" and (args.d_v is not None or args.d_w is not None):
        raise ValueError("--d-v/--d-w set the range of random errors; they need --errors random")
    d_v = cli_common.check_non_negative("--d-v", 1.0 if args.d_v is None else args.d_v)
    d_w = cli_common.check_non_negative("--d-w", 0.05 if args.d_w is None else args.d_w)
    cli_common.check_seed(args.seed)
    if args.cable_noise is not None and not args.cables:
        raise ValueError("--cable-noise needs --cables (noise on the written cable lengths)")
    cable_noise = cli_common.check_non_negative(
        "--cable-noise", 0.0 if args.cable_noise is None else args.cable_noise
    )
    errors_file = None if args.errors in ("random", "zero") else args.errors
    cli_common.check_distinct_files(
        [("--out", args.out), ("--truth", args.truth)],
        [("--model", args.model), ("--errors", errors_file)],
    )
    _check_output(args.out, args.force, "--out")
    _check_output(args.truth, args.force, "--truth")

    import jax
    import numpy as np

    from .io import Measurements, load_frame_errors, save_frame_errors, save_measurements
    from .io.results import package_version

    arm, model_label = _load_arm(args.model)
    X = np.zeros((len(arm.frame_names), 6))
    if args.errors == "random":
        errors_text = f"random, uniform in +-{d_v:g} mm / +-{d_w:g} rad per component"
    elif args.errors == "zero":
        errors_text = "zero"
    else:
        X = load_frame_errors(args.errors, arm)
        errors_text = f"from {args.errors}"
    out = _jitted(_simulation)(
        jax.random.PRNGKey(args.seed),
        arm,
        X,
        np.asarray(d_v),
        np.asarray(d_w),
        args.poses,
        noise,
        args.errors == "random",
    )
    X, q, measured, actual_frames, actual_xyz, actual_rotvec = (np.asarray(a) for a in out)

    noise_text = (
        "none (noise-free)"
        if noise is None
        else f"position {args.noise_pos!r} mm, rotation {args.noise_rot!r} rad (std, Gaussian)"
    )
    comments = [
        f"cdra-jax {package_version()} simulate: model {arm.name} ({model_label}), "
        f"{args.poses} poses, seed {args.seed}",
        f"measurement noise: {noise_text}",
        f"preset frame errors ({errors_text}); T_actual = exp(dt) T_nominal (Eqs. 11-14),",
        "dt = [vx, vy, vz (mm), wx, wy, wz (rad)]:",
        *(
            f"  {name} = [{', '.join(repr(float(v)) for v in row)}]"
            for name, row in zip(arm.frame_names, X, strict=True)
        ),
    ]
    cable_lengths = None
    if args.cables:
        from .modules.cable_data import simulate_cable_lengths

        cable_lengths = {
            k: np.asarray(v)
            for k, v in simulate_cable_lengths(
                jax.random.fold_in(jax.random.PRNGKey(args.seed), 7), arm, q, cable_noise
            ).items()
        }
        if not cable_lengths:
            raise ValueError(f"--cables: no module of model {arm.name!r} has cables")
        comments.append(
            f"cable lengths (mm) for {', '.join(cable_lengths)}; noise std {cable_noise!r} mm"
        )
    meas = Measurements.from_arrays(
        arm, q, measured, comments=comments, cable_lengths=cable_lengths
    )
    path = save_measurements(meas, args.out, force=args.force)
    lines = [
        f"model: {arm.name} ({model_label}); {args.poses} poses, seed {args.seed}",
        f"measurement noise: {noise_text}",
        *_frame_table(arm.frame_names, X, f"preset frame errors ({errors_text}; v mm, w rad):"),
    ]
    if args.truth is not None:
        meta = {
            "cdra_jax_version": package_version(),
            "model": arm.name,
            "inputs": {"model": model_label, "errors": args.errors},
            "measurements": str(args.out),
            "seed": args.seed,
            "poses": args.poses,
            "d_v_mm": d_v if args.errors == "random" else None,
            "d_w_rad": d_w if args.errors == "random" else None,
            "noise": None
            if noise is None
            else {"position_mm": args.noise_pos, "rotation_rad": args.noise_rot},
            "actual_frames": {
                name: {
                    "xyz": actual_xyz[j].tolist(),
                    "rotvec": actual_rotvec[j].tolist(),
                    "matrix": actual_frames[j].tolist(),
                }
                for j, name in enumerate(arm.frame_names)
            },
        }
        truth = save_frame_errors(args.truth, arm, X, metadata=meta, force=args.force)
        lines.append(f"wrote {truth}")
    lines.append(f"wrote {path}")
    print("\n".join(lines))
    return EXIT_OK


# --------------------------------------------------------------------------- wiring


def _external(module: str) -> Registrar:
    """Registrar for ``cdra_jax.<module>`` providing ``register(subparsers)`` and ``run(args)``."""

    def registrar(subparsers) -> None:
        mod = importlib.import_module(f"{__package__}.{module}")
        before = set(subparsers.choices)
        mod.register(subparsers)
        for name in set(subparsers.choices) - before:
            parser = subparsers.choices[name]
            if parser.get_default("func") is None:
                parser.set_defaults(func=mod.run)

    return registrar


SUBCOMMANDS: list[Registrar] = [
    _external("demo"),
    _register_calibrate,
    _register_simulate,
    _external("cli_plan"),
    _external("cli_sweep"),
    _external("diagnosis"),
]
"""One registrar per subcommand, in the order ``--help`` lists them."""


def build_parser() -> argparse.ArgumentParser:
    """The ``cdra-jax`` argument parser with every subcommand of :data:`SUBCOMMANDS`."""
    parser = argparse.ArgumentParser(
        prog="cdra-jax",
        description="Kinematic calibration of modular (cable-driven) robot arms "
        "(Mustafa et al., ICRA 2008). Units: mm, rad.",
    )
    parser.add_argument("--version", action="version", version=_version_text())
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for register in SUBCOMMANDS:
        register(subparsers)
    return parser


def _version_text() -> str:
    from .io.results import package_version

    return f"cdra-jax {package_version()}"


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``cdra-jax`` with ``argv`` (default ``sys.argv[1:]``); returns the exit code."""
    import jax

    jax.config.update("jax_enable_x64", True)
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help, --version, usage errors
        return int(e.code or 0) if not isinstance(e.code, str) else EXIT_USAGE
    try:
        return int(args.func(args) or 0)
    except Exception as e:  # user errors (cli_common.user_error_line) only; the rest raises
        line = cli_common.user_error_line(e)
        if line is None:
            raise
        print(line, file=sys.stderr)
        return EXIT_ERROR


if __name__ == "__main__":
    sys.exit(main())
