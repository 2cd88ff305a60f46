"""``cdra-jax simulate`` then ``calibrate`` end to end through ``main([...])``, and its errors."""

from __future__ import annotations

import json
import sys
import tomllib
import types
from pathlib import Path

import equinox as eqx
import numpy as np
import pytest

from cdra_jax import cli, default_arm, tool_pose
from cdra_jax.cli import commands as cli_commands
from cdra_jax.cli import demo as demo_cli
from cdra_jax.io import dumps_model, loads_measurements
from cdra_jax.workflows.calibrate import implausible_frame_errors_warning

COMPONENTS = ("vx", "vy", "vz", "wx", "wy", "wz")
M = 12


def _run(*argv: str) -> int:
    return cli.main([str(a) for a in argv])


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """A noise-free 12-pose simulation of the default arm (no --model) with a truth file."""
    d = tmp_path_factory.mktemp("cli")
    rc = _run(
        "simulate", "--poses", M, "--seed", 5, "--out", d / "poses.csv", "--truth", d / "truth.json"
    )
    assert rc == 0
    return d


def _truth(path) -> dict:
    return json.loads(path.read_text())


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    return lines[0]


def test_simulate_writes_csv_with_preset_errors_in_comments(cdra, sim):
    truth = _truth(sim / "truth.json")
    assert truth["seed"] == 5 and truth["poses"] == M and truth["noise"] is None
    assert truth["inputs"]["model"] == "<cdra_jax>/data/cdra.toml"  # --model omitted
    meas = loads_measurements((sim / "poses.csv").read_text(), cdra)
    assert meas.m == M and meas.orientation == "rotvec"
    assert meas.pose_ids[0] == "p01"
    for name in cdra.frame_names:
        line = next(c for c in meas.comments if c.strip().startswith(f"{name} = ["))
        values = [float(v) for v in line.split("[")[1].rstrip("]").split(",")]
        assert values == [truth["frames"][name][c] for c in COMPONENTS]  # exact (repr)
    # the 'measurements' are the tool poses of the actual frames written in the truth file
    actual = np.stack([truth["actual_frames"][n]["matrix"] for n in cdra.frame_names])
    T = np.asarray(eqx.filter_jit(tool_pose)(cdra.with_frames(actual), meas.q))
    np.testing.assert_allclose(meas.measured, T, rtol=0, atol=1e-12)


@pytest.mark.parametrize("solver", ["paper", pytest.param("lm", marks=pytest.mark.slow)])
def test_simulate_then_calibrate_recovers_the_preset_errors(cdra, sim, solver, capsys):
    out = sim / f"result_{solver}.json"
    assert _run("calibrate", "--data", sim / "poses.csv", "--out", out, "--solver", solver) == 0
    r = json.loads(out.read_text())
    truth = _truth(sim / "truth.json")
    assert r["solver"] == solver and r["converged"] is True and r["noise"] is None
    assert r["inputs"]["model"] == "<cdra_jax>/data/cdra.toml" and r["model"] == "cdra"
    assert r["inputs"]["data"] == str(sim / "poses.csv") and len(r["inputs"]["data_sha256"]) == 64
    assert r["final"]["delta_p_mm"] < 1e-9 and r["final"]["delta_R_rad"] < 1e-11
    for name in ("base", "tool"):  # fully identifiable: recovered exactly (Table I)
        got = r["frames"][name]["error_twist"]
        for c in COMPONENTS:
            assert abs(got[c] - truth["frames"][name][c]) < 1e-8, (name, c)
    # upper_arm/forearm are identified up to the null space; the tool poses they predict at
    # new states agree with the actual arm's
    cal = np.stack([r["frames"][n]["calibrated"]["matrix"] for n in cdra.frame_names])
    act = np.stack([truth["actual_frames"][n]["matrix"] for n in cdra.frame_names])
    q_new = cdra.state_limits[:, 0] + np.linspace(0.1, 0.9, 7) * np.ptp(cdra.state_limits, 1)
    fk = eqx.filter_jit(tool_pose)
    np.testing.assert_allclose(
        np.asarray(fk(cdra.with_frames(cal), q_new)),
        np.asarray(fk(cdra.with_frames(act), q_new)),
        rtol=0,
        atol=1e-8,
    )
    printed = capsys.readouterr().out
    assert "identifiability: rank 22 of 24 parameters from 12 poses" in printed
    assert printed.count("unidentifiable: ") == 2
    assert f"converged after {len(r['iterations'])} iteration" in printed
    for name in cdra.frame_names:
        assert f"\n  {name} " in printed
    assert f"wrote {out}" in printed


@pytest.mark.slow
def test_noise_flags_select_the_weighted_solver(tmp_path, capsys):
    data, truth = tmp_path / "noisy.csv", tmp_path / "truth.json"
    noise = ("--noise-pos", "0.01", "--noise-rot", "0.0001")
    rc = _run("simulate", "--poses", M, "--seed", 2, *noise, "--out", data, "--truth", truth)
    assert rc == 0
    assert _truth(truth)["noise"] == {"position_mm": 0.01, "rotation_rad": 0.0001}
    out = tmp_path / "r.json"
    assert _run("calibrate", "--data", data, "--out", out, *noise) == 0
    r = json.loads(out.read_text())
    assert r["solver"] == "weighted" and r["converged"] is True
    assert r["noise"] == {"position_mm": 0.01, "rotation_rad": 0.0001}
    assert "whitened by the noise model" in capsys.readouterr().out
    # with noise the fit residual is of the noise size, and base/tool are close to the truth
    assert 1e-3 < r["final"]["delta_p_mm"] < 0.05
    preset = _truth(truth)["frames"]
    for name in ("base", "tool"):
        got = r["frames"][name]["error_twist"]
        assert max(abs(got[c] - preset[name][c]) for c in COMPONENTS[:3]) < 0.1
        assert max(abs(got[c] - preset[name][c]) for c in COMPONENTS[3:]) < 1e-3
    # with a noise model the result carries 95 % intervals, and the base/tool ones are finite
    # and contain the estimate; upper_arm.wy is not identifiable on its own (elbow axis)
    unc = r["uncertainty"]
    assert unc["rank"] == 22 and unc["n_params"] == 24
    params = unc["parameters"]
    low, high = params["base.vx"]["interval"]
    assert low < r["frames"]["base"]["error_twist"]["vx"] < high
    assert params["upper_arm.wy"]["identifiable"] is False
    assert params["upper_arm.wy"]["interval"] is None


def test_explicit_model_file_gives_the_same_simulation_as_the_default(sim, tmp_path):
    model = tmp_path / "cdra_copy.toml"
    model.write_text(dumps_model(default_arm(), exact=True))
    out = tmp_path / "poses.csv"
    assert _run("simulate", "--model", model, "--poses", M, "--seed", 5, "--out", out) == 0
    arm = default_arm()
    a = loads_measurements((sim / "poses.csv").read_text(), arm)
    b = loads_measurements(out.read_text(), arm)
    assert a.columns == b.columns
    for c in a.columns[1:]:
        np.testing.assert_array_equal(a.values[c], b.values[c])
    assert str(model) in b.comments[0] and "<cdra_jax>/data/cdra.toml" in a.comments[0]


def test_outputs_are_not_overwritten_without_force(sim, capsys):
    result = sim / "existing.json"
    result.write_text("keep")
    rc = _run("calibrate", "--data", sim / "poses.csv", "--out", result)
    assert rc == 1 and result.read_text() == "keep"
    assert "existing.json: file exists" in _one_error_line(capsys)
    csv_path = sim / "poses.csv"
    before = csv_path.read_text()
    rc = _run("simulate", "--poses", M, "--seed", 9, "--out", csv_path)
    assert rc == 1 and csv_path.read_text() == before
    assert "--force" in _one_error_line(capsys)
    other = sim / "other.csv"
    other.write_text("old")
    assert _run("simulate", "--poses", M, "--seed", 9, "--out", other, "--force") == 0
    assert other.read_text().startswith("# cdra-jax")


def test_not_converged_exits_3_and_still_writes_the_result(sim, capsys):
    out = sim / "short.json"
    out.write_text("old")
    rc = _run(
        "calibrate",
        "--data",
        sim / "poses.csv",
        "--out",
        out,
        "--max-iterations",
        1,
        "--force",
        "--solver",
        "paper",
    )
    assert rc == cli.EXIT_NOT_CONVERGED
    r = json.loads(out.read_text())
    assert r["converged"] is False and r["result"] == "max_iterations_reached"
    assert len(r["iterations"]) == 1
    captured = capsys.readouterr()
    assert "NOT converged (max_iterations_reached)" in captured.out
    assert "warning: not converged" in captured.err


def test_errors_file_sets_the_preset_errors(tmp_path):
    errors = tmp_path / "errors.toml"
    errors.write_text(
        "[frames.base]\nvx = 0.5\nwz = 0.01\n\n[frames.tool]\ntwist = [1, 2, 3, 0, 0, 0.02]\n"
    )
    truth = tmp_path / "t.json"
    rc = _run(
        "simulate", "--poses", M, "--errors", errors, "--out", tmp_path / "p.csv", "--truth", truth
    )
    assert rc == 0
    frames = _truth(truth)["frames"]
    assert frames["base"] == {"vx": 0.5, "vy": 0, "vz": 0, "wx": 0, "wy": 0, "wz": 0.01}
    assert [frames["tool"][c] for c in COMPONENTS] == [1, 2, 3, 0, 0, 0.02]
    assert all(v == 0 for n in ("upper_arm", "forearm") for v in frames[n].values())
    # the truth file is itself a valid --errors file
    truth2 = tmp_path / "t2.json"
    rc = _run(
        "simulate", "--poses", M, "--errors", truth, "--out", tmp_path / "p2.csv", "--truth", truth2
    )
    assert rc == 0 and _truth(truth2)["frames"] == frames


def _few_poses_csv(sim, tmp_path, n):
    lines = (sim / "poses.csv").read_text().splitlines(keepends=True)
    header = next(i for i, line in enumerate(lines) if line.startswith("pose,"))
    path = tmp_path / "few.csv"
    path.write_text("".join(lines[: header + 1 + n]))
    return path, header + 1


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["calibrate", "--data", "{few}", "--out", "{tmp}/r.json"], ["few.csv", "3 measured pose"]),
        (
            ["calibrate", "--data", "{bad}", "--out", "{tmp}/r.json"],
            ["bad.csv, line {line}, column 'elbow.q'", "not a number: 'x'"],
        ),
        (
            [
                "calibrate",
                "--data",
                "{sim}/poses.csv",
                "--out",
                "{tmp}/r.json",
                "--noise-pos",
                "0.1",
            ],
            ["--noise-pos and --noise-rot go together"],
        ),
        (
            ["calibrate", "--data", "{tmp}/missing.csv", "--out", "{tmp}/r.json"],
            ["missing.csv: cannot read measurement file"],
        ),
        (
            ["calibrate", "--model", "{tmp}/none.toml", "--data", "{few}", "--out", "{tmp}/r.json"],
            ["none.toml: cannot read model file"],
        ),
        (
            ["calibrate", "--data", "{few}", "--out", "{tmp}/nofolder/r.json"],
            ["nofolder", "does not exist"],
        ),
        (
            ["simulate", "--poses", "5", "--errors", "zero", "--d-v", "2", "--out", "{tmp}/s.csv"],
            ["--d-v/--d-w", "--errors random"],
        ),
        (
            ["simulate", "--poses", "5", "--errors", "{tmp}/e.json", "--out", "{tmp}/s.csv"],
            ["e.json: frames.elbow: unknown frame 'elbow'", "base, upper_arm, forearm, tool"],
        ),
        (
            ["simulate", "--poses", "0", "--out", "{tmp}/s.csv"],
            ["--poses must be an integer in [1, 1000000], got 0"],
        ),
        (
            ["simulate", "--poses", "5", "--noise-pos", "0.1", "--noise-rot", "-1", "--out", "x"],
            ["--noise-rot must be a number in [1e-12, 3.2]"],
        ),
    ],
    ids=[
        "fewer than 4 poses",
        "bad cell",
        "noise flags alone",
        "missing data",
        "missing model",
        "missing output folder",
        "d-v without random",
        "unknown frame in errors file",
        "zero poses",
        "negative noise",
    ],
)
def test_bad_input_gives_one_error_line(sim, tmp_path, capsys, argv, expected):
    few, _ = _few_poses_csv(sim, tmp_path, 3)
    lines = (sim / "poses.csv").read_text().splitlines(keepends=True)
    header = next(i for i, line in enumerate(lines) if line.startswith("pose,"))
    cells = lines[header + 2].split(",")
    cells[4] = "x"  # elbow.q of the second pose
    lines[header + 2] = ",".join(cells)
    (tmp_path / "bad.csv").write_text("".join(lines))
    (tmp_path / "e.json").write_text('{"frames": {"elbow": [0, 0, 0, 0, 0, 0]}}')
    subs = {
        "few": few,
        "bad": tmp_path / "bad.csv",
        "tmp": tmp_path,
        "sim": sim,
        "line": header + 3,
    }
    assert _run(*(a.format(**subs) for a in argv)) == cli.EXIT_ERROR
    line = _one_error_line(capsys)
    for part in expected:
        assert part.format(**subs) in line, line


def test_help_and_usage_errors(capsys):
    assert cli.main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "calibrate" in out and "simulate" in out
    assert cli.main(["calibrate", "--data", "x.csv"]) == cli.EXIT_USAGE  # --out missing
    assert "--out" in capsys.readouterr().err
    assert cli.main(["calibrate", "--solver", "gn", "--data", "x", "--out", "y"]) == 2


def test_demo_entry_point_dispatches_to_the_demo(tmp_path, monkeypatch, capsys):
    # The installed `cdra-jax` script is cli.main; `cdra-jax demo ...` must reach demo.run.
    pyproject = Path(__file__).resolve().parents[1] / "pyproject.toml"
    scripts = tomllib.loads(pyproject.read_text())["project"]["scripts"]
    assert scripts == {"cdra-jax": "cdra_jax.cli:main"}
    assert cli.main(["demo", "--help"]) == 0
    out = capsys.readouterr().out
    assert "usage: cdra-jax demo" in out and "--full" in out and "Table I" in out
    # The real demo.run, cheaply: a non-empty --out folder is refused before any computation.
    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "keep.txt").write_text("keep")
    assert cli.main(["demo", "--out-dir", str(taken)]) == cli.EXIT_ERROR  # a file problem: exit 1
    assert "--force" in _one_error_line(capsys)
    assert (taken / "keep.txt").read_text() == "keep"
    assert cli.main(["demo", "--out-dir", str(taken / "keep.txt")]) == cli.EXIT_ERROR
    assert "keep.txt: exists and is not a folder" in _one_error_line(capsys)
    # The parsed options arrive at demo.run unchanged.
    seen = []
    monkeypatch.setattr(demo_cli, "run", lambda args: seen.append(args) or 0)
    assert cli.main(["demo", "--full", "--out", str(tmp_path / "o"), "--seed", "3"]) == 0
    (args,) = seen
    assert (args.full, args.out_dir, args.seed, args.force) == (True, str(tmp_path / "o"), 3, False)


def test_external_subcommand_module_plugs_in(monkeypatch, capsys):
    fake = types.ModuleType("cdra_jax._fake_cmd")

    def register(subparsers):
        p = subparsers.add_parser("fake", help="a plugged-in subcommand")
        p.add_argument("--n", type=int, default=1)

    def run(args):
        print(f"fake ran with n={args.n}")
        return 7

    fake.register, fake.run = register, run
    monkeypatch.setitem(sys.modules, "cdra_jax._fake_cmd", fake)
    monkeypatch.setattr(cli_commands, "SUBCOMMANDS", (*cli_commands.SUBCOMMANDS, fake))
    assert cli.main(["fake", "--n", "3"]) == 7
    assert "fake ran with n=3" in capsys.readouterr().out


def test_simulate_cables_then_calibrate(tmp_path, capsys):
    data, truth, out = tmp_path / "cables.csv", tmp_path / "truth.json", tmp_path / "r.json"
    assert (
        _run("simulate", "--poses", M, "--seed", 4, "--cables", "--out", data, "--truth", truth)
        == 0
    )
    header = [ln for ln in data.read_text().splitlines() if not ln.startswith("#")][0]
    assert "shoulder.l6" in header and "wrist.l4" in header and "elbow.l2" in header
    assert "shoulder.rx" not in header
    assert _run("calibrate", "--data", data, "--out", out) == 0
    r = json.loads(out.read_text())
    preset = _truth(truth)["frames"]
    for name in ("base", "tool"):
        got = r["frames"][name]["error_twist"]
        assert max(abs(got[c] - preset[name][c]) for c in COMPONENTS) < 1e-8


# --------------------------------------------------------------------------- QA defects

TINY_MODEL = """name = "one"
[[frames]]
name = "a"
xyz = [0.0, 0.0, 0.0]
rotvec = [0.0, 0.0, 0.0]
[[frames]]
name = "b"
xyz = [0.0, 0.0, 100.0]
rotvec = [0.0, 0.0, 0.0]
[[modules]]
name = "hinge"
kind = "revolute"
axis = [0.0, 1.0, 0.0]
limits = [[-1.0, 1.0]]
cables = [{ base = [30.0, 0.0, -70.0], platform = [15.0, 0.0, 30.0] }]
"""
"""One revolute module held by one cable: no state has tension closure (it needs 2)."""

HUGE = "99999999999999999999999"


@pytest.mark.parametrize(
    "argv",
    [
        ["simulate", "--model", "{model}", "--poses", "4", "--out", "{tmp}/s.csv"],
        ["plan-poses", "--model", "{model}", "--count", "4", "--pool", "8", "--out", "{tmp}/p.csv"],
    ],
    ids=["simulate", "plan-poses"],
)
def test_model_whose_cables_hold_no_pose_gives_one_error_line(tmp_path, capsys, argv):
    model = tmp_path / "one.toml"
    model.write_text(TINY_MODEL)
    assert _run(*(a.format(model=model, tmp=tmp_path) for a in argv)) == cli.EXIT_ERROR
    line = _one_error_line(capsys)
    assert "tension closure" in line and "the model's cables cannot hold" in line, line
    assert "EQX_ON_ERROR" not in line and not list(tmp_path.glob("*.csv"))


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["simulate", "--poses", "4", "--seed", HUGE, "--out", "{tmp}/s.csv"], "--seed must be"),
        (["simulate", "--poses", "4", "--seed", "-" + HUGE, "--out", "{tmp}/s.csv"], "--seed"),
        (["plan-poses", "--count", "4", "--seed", HUGE, "--out", "{tmp}/p.csv"], "--seed must"),
        (["demo", "--seed", HUGE, "--out", "{tmp}/demo"], "--seed must be"),
        (
            ["simulate", "--poses", "4", "--cable-noise", "-1", "--out", "{tmp}/s.csv"],
            "--cable-noise needs --cables",
        ),
        (
            ["simulate", "--poses", "4", "--cable-noise", "0.1", "--out", "{tmp}/s.csv"],
            "--cable-noise needs --cables",
        ),
        (
            ["simulate", "--poses", "4", "--cables", "--cable-noise", "-1", "--out", "{tmp}/s.csv"],
            "--cable-noise must be a number in [0, 1e+06], got -1.0",
        ),
        (
            ["simulate", "--poses", "4", "--cables", "--cable-noise", "nan", "--out", "{tmp}/s"],
            "--cable-noise must be a number in [0, 1e+06], got nan",
        ),
        (
            ["simulate", "--poses", "4", "--errors", "{tmp}/big.json", "--out", "{tmp}/s.csv"],
            "big.json: frames.base.vx: expected a finite number",
        ),
        (["plan-poses", "--count", "5", "--out", "{tmp}"], "is a folder, expected a file name"),
        (
            ["plan-poses", "--count", "5", "--out", "{tmp}", "--force"],
            "is a folder, expected a file name",
        ),
        (["plan-poses", "--count", "5", "--out", "{tmp}/no/p.csv"], "folder {tmp}/no does not"),
    ],
    ids=[
        "simulate huge seed",
        "simulate huge negative seed",
        "plan-poses huge seed",
        "demo huge seed",
        "cable noise without cables",
        "positive cable noise without cables",
        "negative cable noise",
        "nan cable noise",
        "huge integer in errors file",
        "plan-poses out is a folder",
        "plan-poses out is a folder, force",
        "plan-poses missing folder",
    ],
)
def test_bad_arguments_are_refused_before_any_work(tmp_path, capsys, argv, expected):
    (tmp_path / "big.json").write_text('{"frames": {"base": {"vx": 1' + "0" * 400 + "}}}")
    before = sorted(tmp_path.iterdir())
    assert _run(*(a.format(tmp=tmp_path) for a in argv)) == cli.EXIT_ERROR
    assert expected.format(tmp=tmp_path) in _one_error_line(capsys)
    assert sorted(tmp_path.iterdir()) == before  # nothing written


def test_seed_at_the_ends_of_the_accepted_range_works(tmp_path, capsys):
    for seed in (-(2**63), 2**63 - 1):
        assert (
            _run("simulate", "--poses", 4, "--seed", seed, "--out", tmp_path / f"{seed}.csv") == 0
        )
    assert _run("simulate", "--poses", 4, "--seed", 2**63, "--out", tmp_path / "x.csv") == 1
    assert "--seed must be an integer in [-2^63, 2^63), got 9223372036854775808" in (
        _one_error_line(capsys)
    )


def test_an_output_naming_an_input_is_refused(sim, tmp_path, capsys):
    data = tmp_path / "d.csv"
    data.write_bytes((sim / "poses.csv").read_bytes())
    (tmp_path / "link.csv").symlink_to(data)
    errors = tmp_path / "e.json"
    errors.write_text('{"frames": {"base": [0, 0, 0, 0, 0, 0.01]}}')
    model = tmp_path / "m.toml"
    model.write_text(dumps_model(default_arm()))
    cases = [
        (["calibrate", "--data", data, "--out", data], "--out and --data name the same file"),
        (["calibrate", "--data", data, "--out", tmp_path / "link.csv"], "--out and --data"),
        (["calibrate", "--data", data, "--out", f"{tmp_path}/../{tmp_path.name}/d.csv"], "--data"),
        (
            ["calibrate", "--model", model, "--data", data, "--out", model],
            "--out and --model name the same file",
        ),
        (["diagnose", "--data", data, "--out", data], "--out and --data name the same file"),
        (
            [
                "simulate",
                "--poses",
                4,
                "--errors",
                errors,
                "--out",
                "{tmp}/s.csv",
                "--truth",
                errors,
            ],
            "--truth and --errors name the same file",
        ),
        (["simulate", "--poses", 4, "--model", model, "--out", model], "--out and --model"),
        (["plan-poses", "--count", 4, "--model", model, "--out", model], "--out and --model"),
    ]
    saved = {p: p.read_bytes() for p in (data, errors, model)}
    for argv, expected in cases:
        argv = [str(a).format(tmp=tmp_path) for a in argv] + ["--force"]
        assert _run(*argv) == cli.EXIT_ERROR, argv
        assert expected in _one_error_line(capsys), argv
        assert {p: p.read_bytes() for p in saved} == saved, argv


def test_implausibly_large_identified_errors_warn(tmp_path, capsys):
    # A model 100 mm off at the base: the calibration identifies it, and says it is implausible.
    errors = tmp_path / "e.json"
    errors.write_text('{"frames": {"base": {"vx": 100.0}}}')
    data, out = tmp_path / "d.csv", tmp_path / "r.json"
    assert _run("simulate", "--poses", M, "--errors", errors, "--out", data) == 0
    capsys.readouterr()
    # the paper solver: the auto solver registers the base to the device frame instead
    assert _run("calibrate", "--data", data, "--out", out, "--solver", "paper") == 0
    err = capsys.readouterr().err
    r = json.loads(out.read_text())
    assert abs(r["frames"]["base"]["error_twist"]["vx"] - 100.0) < 1e-6
    (w,) = [w for w in r["warnings"] if w.startswith("implausibly large identified frame errors")]
    assert "base (|v| = 100 mm" in w and "above 50 mm or 0.5 rad" in w and "gross errors" in w
    assert f"warning: {w}" in err.splitlines()


def test_plausibility_thresholds_of_identified_errors():
    zero = dict.fromkeys(COMPONENTS, 0.0)
    frames = {"base": {"error_twist": dict(zero, vx=30.0, vy=40.0)}}  # |v| = 50: not above
    assert implausible_frame_errors_warning({"frames": frames}) is None
    frames["tool"] = {"error_twist": dict(zero, wz=-0.51, vx=None)}  # unidentified -> 0
    w = implausible_frame_errors_warning({"frames": frames})
    assert w is not None and "tool (|v| = 0 mm, |w| = 0.51 rad)" in w and "base" not in w
