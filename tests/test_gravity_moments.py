"""Gravity effects without masses: the lumped gravity moments (compliance x weight x lever
products) of joint compliance and link bending, checked against the statics with masses, and
diagnosed on a mass-less six-joint arm imported from a URDF."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdra_jax import lie
from cdra_jax.arm import Arm, prismatic, revolute, sample_states, spherical
from cdra_jax.modules.statics import gravity_torques
from cdra_jax.physics import Candidate, bending_deflection, candidates, effect

jax.config.update("jax_enable_x64", True)

DATA = Path(__file__).parent / "data" / "urdf"


@pytest.fixture(autouse=True)
def _drop_the_programs_of_each_arm():
    """Every test here compiles programs for its own random or imported arm that no other test
    reuses: drop them after each (the module otherwise reached 3.4 GB)."""
    yield
    jax.clear_caches()


def _random_arm(seed: int, kinds: str) -> Arm:
    """A chain of modules of ``kinds`` (``r``, ``s``, ``p``) with random axes and links."""
    rng = np.random.default_rng(seed)
    mods = []
    for k, c in enumerate(kinds):
        name = f"j{k}"
        if c == "s":
            mods.append(spherical(name))
        else:
            axis = rng.normal(size=3)
            make = revolute if c == "r" else prismatic
            mods.append(make(name, axis / np.linalg.norm(axis)))
    frames = np.stack(
        [
            np.asarray(lie.from_xyz_rotvec(rng.uniform(-300, 300, 3), rng.uniform(-2, 2, 3)))
            for _ in range(len(kinds) + 1)
        ]
    )
    names = tuple(f"f{j}" for j in range(len(kinds) + 1))
    return Arm(frames=jnp.asarray(frames), modules=tuple(mods), frame_names=names)


def _with_mass(arm: Arm, b: int, com) -> Arm:
    """``arm`` with 1 kg at ``com`` on body ``b`` and no other mass."""
    mods = tuple(
        dataclasses.replace(
            m, mass=1.0 if k == b else None, com=jnp.asarray(com, float) if k == b else None
        )
        for k, m in enumerate(arm.modules)
    )
    return eqx.tree_at(lambda a: a.modules, arm, mods, is_leaf=lambda x: x is None)


def _mass_columns(arm: Arm, q, i: int) -> np.ndarray:
    """Gravity torques at module ``i`` (base frame) per unknown mass and first moment of each
    distal body, from the statics with masses: ``(m, 3, 4 (K - i))``."""
    cols = []
    for b in range(i, len(arm.modules)):
        t0 = gravity_torques(_with_mass(arm, b, np.zeros(3)), q)[:, i]
        cols.append(t0)
        for k in range(3):
            cols.append(gravity_torques(_with_mass(arm, b, np.eye(3)[k]), q)[:, i] - t0)
    return np.stack([np.asarray(c) for c in cols], -1)


def _rank(A: np.ndarray, rows: int = 0) -> int:
    """Numerical rank of the columns; with ``rows``, of the columns less their mean over
    poses (``rows`` entries per pose): the span modulo constants, which the frame errors
    absorb exactly."""
    if rows:
        A = A.reshape(-1, rows, A.shape[-1])
        A = (A - A.mean(axis=0)).reshape(-1, A.shape[-1])
    s = np.linalg.svd(A, compute_uv=False)
    return int(np.sum(s > 1e-9 * s[0]))


DH_ARM = """# a six-joint arm with a prismatic joint, standard DH (a, d in mm; alpha, theta in rad)
joint,type,a,alpha,d,theta,lower,upper
waist,revolute,0,1.5707963267948966,320,0,-3,3
shoulder,revolute,400,0,0,0.2,-2,2
extend,prismatic,0,1.5707963267948966,120,0,0,200
roll,revolute,30,-1.5707963267948966,350,0,-3,3
pitch,revolute,0,1.5707963267948966,0,0.1,-2,2
flange,revolute,0,0,90,0,-3,3
"""


def _dh_arm(tmp_path) -> Arm:
    from cdra_jax.workflows import import_dh

    table = tmp_path / "dh.csv"
    table.write_text(DH_ARM)
    return import_dh(table, "standard").arm


@pytest.mark.parametrize(
    "seed, kinds", [(0, "rrrrrr"), (1, "rrsrpr"), (2, "srprrs"), (3, "prrr"), (4, "dh")]
)
def test_lumped_moments_are_the_identifiable_combinations_of_the_statics(seed, kinds, tmp_path):
    """On random arms and a DH-imported one: the lumped columns are independent and span
    exactly what the mass-based statics produce from every distal mass and first moment (up
    to constants, which the frame errors absorb): their number is the rank of the statics'
    columns."""
    arm = _dh_arm(tmp_path) if kinds == "dh" else _random_arm(seed, kinds)
    q = sample_states(jax.random.PRNGKey(seed), arm, 120)
    for i, mod in enumerate(arm.modules):
        variants = ["lumped"] if mod.kind == "spherical" else ["lumped_axial", "lumped_transverse"]
        masses = _mass_columns(arm, q, i)
        for v in variants:
            e = effect("joint_compliance", v)
            if Candidate(e, mod.name).missing(arm, []):  # no torque about a vertical axis
                assert v == "lumped_axial" and np.allclose(np.asarray(mod.axis), [0, 0, 1])
                continue
            c = Candidate(e, mod.name)
            lumped = np.asarray(c.features(arm, q, {}).module_twist)[:, i, 3:]  # (m, 3, n)
            ref = masses
            if v != "lumped":
                a = np.asarray(mod.axis)
                along = np.einsum("mkn,k->mn", masses, a)[:, None] * a[:, None]
                ref = along if v == "lumped_axial" else masses - along
            A, B = ref.reshape(-1, ref.shape[-1]), lumped.reshape(-1, lumped.shape[-1])
            n = len(e.terms(arm, mod.name))
            assert B.shape[1] == n == len(c.parameters(arm))
            # no parameter too many: the columns the geometry sees are independent; special
            # geometry zeroes some exactly (on the DH arm the prismatic joint slides along the
            # shoulder axis, and gravity stays across the horizontal shoulder axis: no torque
            # about it from the one, none across it from the moments across it)
            zero = np.all(B == 0.0, axis=0)
            assert zero.sum() == 0 or kinds == "dh", (kinds, i, v)
            assert _rank(B) == n - zero.sum(), (kinds, i, v)
            span = _rank(B, 3)
            assert _rank(A, 3) == span == _rank(np.hstack([A, B]), 3), (kinds, i, v)


def _with_masses(arm: Arm, seed: int, massless: int = -1) -> Arm:
    """``arm`` with random masses and centres of mass (none on body ``massless``)."""
    rng = np.random.default_rng(seed)
    mods = tuple(
        dataclasses.replace(
            m,
            mass=None if k == massless else float(rng.uniform(0.5, 3)),
            com=jnp.asarray(rng.normal(0, 80, 3)),
        )
        for k, m in enumerate(arm.modules)
    )
    return eqx.tree_at(lambda a: a.modules, arm, mods, is_leaf=lambda x: x is None)


@pytest.mark.parametrize("seed, kinds", [(4, "rrrrr"), (5, "rsrr")])
def test_bending_with_masses_is_a_combination_of_the_lumped_columns(seed, kinds):
    """The cantilever with masses beyond the link (any masses and centres of mass) is
    reproduced exactly by one set of lumped values at every pose, the lumped columns are
    independent, and the weights' term comes out positive."""
    arm = _random_arm(seed, kinds)
    q = sample_states(jax.random.PRNGKey(seed), arm, 80)
    for j in range(1, len(kinds)):
        heavy = _with_masses(arm, seed, massless=j - 1)
        loc = arm.frame_names[j]
        c = Candidate(effect("link_bending", "lumped"), loc)
        B = np.asarray(c.features(arm, q, {}).frame_deflection)[:, j].reshape(
            -1, len(c.parameters(arm))
        )
        y = np.asarray(bending_deflection(heavy, q, j)).reshape(-1)
        x, *_ = np.linalg.lstsq(B, y, rcond=None)
        assert np.linalg.norm(B @ x - y) < 1e-9 * np.linalg.norm(y), (kinds, j)
        assert _rank(B) == B.shape[1], (kinds, j)
        assert x[0] > 0  # the weights' tip rotation: never negative


def _ur5() -> Arm:
    from cdra_jax.workflows import import_urdf

    return import_urdf(DATA / "ur5_robot.urdf", "base_link", "ee_link").arm


def test_every_joint_and_link_of_a_massless_six_joint_arm_has_a_gravity_candidate():
    """A URDF-imported 6R arm without masses: joint compliance at every joint and bending of
    every inner link are tried in their lumped forms; what cannot apply is said once."""
    arm = _ur5()
    assert all(m.mass is None for m in arm.modules)
    table = candidates(arm, [])
    live = {(c.name, c.location, c.variant) for c, why in table if why is None}
    for name in arm.module_names:
        assert ("joint_compliance", name, "lumped_transverse") in live
    # the first joint turns about the vertical: no gravity torque about its axis
    axial = {loc for n, loc, v in live if v == "lumped_axial"}
    assert axial == set(arm.module_names[1:])
    assert {loc for n, loc, v in live if n == "link_bending"} == set(arm.frame_names[1:-1])
    sizes = {c.location: len(c.parameters(arm)) for c, _ in table if c.variant == "lumped_axial"}
    # two combinations across each axis, the joint's own and one per revolute joint beyond
    assert [sizes[n] for n in arm.module_names] == [12, 10, 8, 6, 4, 2]
    assert {v for _, _, v in live if v and "lumped" not in v and v.startswith("k=")}
    assert not any(v in ("isotropic", "per_axis") for _, _, v in live)  # no masses
    # what is checkable: a moment product has no sign; the weights' rotation has
    specs = {s.name: s for c, _ in table if c.variant == "lumped" for s in c.parameters(arm)}
    assert specs["moment_wrist_3_joint_u"].low == -specs["moment_wrist_3_joint_u"].high
    assert specs["weight_rotation"].low == 0.0 < specs["weight_rotation"].high


def _lumped_model(arm: Arm) -> Arm:
    """``arm`` with a lumped joint compliance at the elbow and a lumped bending of the upper
    arm as ``[[effects]]`` (random products, the weights' rotation positive)."""
    from cdra_jax.physics import effect_records

    cands = [
        Candidate(effect("joint_compliance", "lumped_axial"), "elbow_joint"),
        Candidate(effect("link_bending", "lumped"), "upper_arm_link"),
    ]
    n = [len(c.parameters(arm)) for c in cands]
    theta = np.random.default_rng(0).uniform(-3e-4, 3e-4, sum(n))
    theta[n[0]] = 2e-4
    return arm.with_effects(effect_records(arm, cands, theta))


def test_a_lumped_effect_round_trips_through_the_model_file():
    """Stored as [[effects]] (variant, named parameters with units), read back exactly, and
    predicted with: the tool poses differ from the chain's by the effects' deflections."""
    from cdra_jax import tool_pose
    from cdra_jax.io import dumps_model, loads_model
    from cdra_jax.physics import check_effect_data, model_effects, model_tool_pose

    arm = _ur5()
    truth = _lumped_model(arm)
    text = dumps_model(truth)
    assert 'variant = "lumped_axial"' in text and "moment_wrist_1_joint_u" in text
    back = loads_model(text)
    assert back.effects == truth.effects
    got, values = model_effects(back)
    assert [c.variant for c in got] == ["lumped_axial", "lumped"]
    np.testing.assert_array_equal(values, model_effects(truth)[1])
    units = {p[0]: p[2] for e in back.effects for p in e.parameters}
    assert units["weight_rotation"] == "rad" and units["moment_elbow_joint_u"] == "rad"
    check_effect_data(back, [])  # needs no auxiliary column and no mass
    q = sample_states(jax.random.PRNGKey(1), arm, 20)
    moved = np.linalg.norm(model_tool_pose(back, q)[:, :3, 3] - tool_pose(arm, q)[:, :3, 3], axis=1)
    assert 0.01 < moved.max() < 5.0
    bad = back.effects[0]
    with pytest.raises(ValueError, match="missing parameter.*moment_elbow_joint_u"):
        model_effects(back.with_effects([dataclasses.replace(bad, parameters=bad.parameters[1:])]))


@pytest.mark.slow
def test_simulate_calibrate_and_validate_honour_a_lumped_effect(tmp_path):
    """Simulated with the stored effects, refined by calibrate from zero values, predicted by
    validate from the calibrated model file."""
    from cdra_jax.io import load_model, save_model
    from cdra_jax.workflows import calibrate, simulate, validate

    truth = _lumped_model(_ur5())
    run = simulate(truth, 40, seed=2, d_w=0.005)
    start = truth.with_effects([e.with_values([0.0] * len(e.parameters)) for e in truth.effects])
    cal = calibrate(start, run.measurements)
    assert cal.converged and cal.trusted
    # noise-free data: to the gauge's effect on the link geometry the lumped columns use
    assert cal.to_dict()["final"]["delta_p_mm"] < 1e-3
    model = cal.save_model(tmp_path / "cal.toml")
    assert [e.variant for e in load_model(model).effects] == ["lumped_axial", "lumped"]
    assert validate(model, run.measurements).to_dict()["position_error_mm"]["max"] < 2e-3
    bare = validate(save_model(start.with_effects(()), tmp_path / "bare.toml"), run.measurements)
    assert bare.to_dict()["position_error_mm"]["max"] > 0.05


UR5_MASS = (3.7, 8.4, 2.3, 1.2, 1.2, 0.19)
UR5_COM = ((0, 0, 0), (0, 0, 210), (0, 0, 190), (0, 50, 0), (0, 0, 40), (0, 30, 0))


def _tracker_recordings(compliance: float, seed: int):
    """60 poses of a UR5 measured by a laser tracker (full poses, 0.02 mm, 2e-4 rad), the
    real arm with frame errors, masses (hidden from the model) and an elbow whose compliance
    about its axis is ``compliance`` rad/(N mm) (5e-8: 0.7 mrad under its own load)."""
    from cdra_jax import NoiseModel
    from cdra_jax.arm import apply_frame_errors
    from cdra_jax.io import Measurements
    from cdra_jax.physics import corrected_tool_pose
    from cdra_jax.simulation import add_measurement_noise, random_frame_errors

    arm = _ur5()
    mods = tuple(
        dataclasses.replace(m, mass=UR5_MASS[k], com=jnp.asarray(UR5_COM[k], float))
        for k, m in enumerate(arm.modules)
    )
    heavy = eqx.tree_at(lambda a: a.modules, arm, mods, is_leaf=lambda x: x is None)
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(seed), 3)
    q = sample_states(k1, arm, 60)
    actual = apply_frame_errors(heavy, random_frame_errors(k2, arm, 1.0, 0.01))
    c = Candidate(effect("joint_compliance", "isotropic"), "elbow_joint")  # the true physics
    T = corrected_tool_pose(actual, q, c.features(actual, q, {}), jnp.array([compliance, 0.0]))
    noise = NoiseModel(0.02, 2e-4)
    T = add_measurement_noise(k3, T, noise)
    return arm, Measurements.from_arrays(arm, np.asarray(q), np.asarray(T)), noise


@pytest.mark.slow
def test_a_concealed_joint_compliance_is_found_without_masses_and_clean_data_give_none():
    """The model has no masses; the recordings come from an arm with them and a compliant
    elbow. The lumped form finds it at the elbow and refits to near the noise floor; without
    the compliance, nothing is found. Cable effects are not for this arm and are not listed
    as not tried."""
    from cdra_jax.diagnosis import diagnose

    arm, meas, noise = _tracker_recordings(5e-8, seed=0)
    d = diagnose(arm, meas, noise)
    assert (d.effect, d.located_in) == ("joint_compliance", "elbow_joint"), d.report
    row = next(r for r in d.candidates if r.selected)
    assert row.variant == "lumped_axial" and len(d.parameters) == 8
    floor = d.details["noise_floor"]["delta_p_mm"]
    assert d.heldout_before.delta_p_mm > 3 * floor
    assert d.heldout_after.delta_p_mm < 1.3 * floor
    assert all(v.plausible for v in d.parameters.values())
    assert d.details["close_rivals"] == []  # these poses prefer the elbow clearly
    assert "cable" not in d.report.split("Not tried")[1].split("\n")[0]
    assert "Not for this arm: cable_elasticity, cable_scale" in d.report
    names = {(r.effect, r.location) for r in d.candidates}
    assert all(("joint_compliance", m) in names for m in arm.module_names)
    assert all(("link_bending", f) in names for f in arm.frame_names[1:-1])
    assert not any(r.effect.startswith("cable") for r in d.candidates)

    _, clean, _ = _tracker_recordings(0.0, seed=1)
    d0 = diagnose(arm, clean, noise)
    assert (d0.effect, d0.mismatch) == ("none", False), d0.report


def test_what_cannot_apply_to_the_arm_is_named_once():
    """Effects skipped for the same reason everywhere share one entry; a reason that holds at
    some locations only names them (counted against all the effect's locations)."""
    from types import SimpleNamespace

    from cdra_jax.diagnosis.report import _skipped_text

    def row(effect, loc, why):
        return SimpleNamespace(effect=effect, location=loc, label=f"{effect}@{loc}", skipped=why)

    rows = [
        row(e, loc, f"module {loc!r} has no cables in the model")
        for e in ("cable_elasticity", "cable_scale")
        for loc in ("j1", "j2")
    ] + [row("link_bending", "f2", "link 'f2' has zero length")]
    assert _skipped_text(rows, {"cable_elasticity": 2, "cable_scale": 2, "link_bending": 4}) == [
        "cable_elasticity, cable_scale at every location (no module has cables in the model)",
        "link_bending@f2 (link 'f2' has zero length)",
    ]
    two = [row("link_bending", f, f"link {f!r} has zero length") for f in ("f1", "f2")]
    assert _skipped_text(two, {"link_bending": 4}) == [
        "link_bending@f1 (link 'f1' has zero length)",
        "link_bending@f2 (link 'f2' has zero length)",
    ]


@pytest.mark.slow
def test_random_arms_with_random_effects_never_crash_the_diagnosis():
    """A random chain of a revolute, a spherical, a prismatic and a revolute joint, no masses,
    no cables, 12 poses, the noise not given; two random effects of the vocabulary (a random
    evaluable place and form), each at a plausible size and at a size outside its physical
    range (a negative compliance where one is impossible), and clean data: every diagnosis
    ends with a verdict of the contract (no exception), a place of the model or none, and a
    named effect only with plausible estimates."""
    from cdra_jax import NoiseModel
    from cdra_jax.diagnosis import diagnose
    from cdra_jax.physics import VOCABULARY
    from cdra_jax.physics.synthetic import recording_aux, simulate_recordings

    arm = _random_arm(0, "rspr")
    rng = np.random.default_rng(0)
    key = jax.random.PRNGKey(0)
    tried = [
        c
        for c, why in candidates(arm, recording_aux(key, arm, 12), VOCABULARY)
        if why is None and not c.effect.refinement
    ]
    names = sorted({c.name for c in tried})
    places = set(arm.module_names) | set(arm.frame_names)
    cases: list = [(None, None)]
    for name in rng.choice(names, 2, replace=False):
        of_name = [c for c in tried if c.name == name]
        c = of_name[rng.integers(len(of_name))]
        size = [s.low + 0.3 * (min(s.high, 1e3) - s.low) for s in c.parameters(arm)]
        cases += [(c, size), (c, [-abs(v) - 1e-3 for v in size])]
    for c, params in cases:
        meas, _ = simulate_recordings(
            key, arm, 12, candidate=c, params=params, noise=NoiseModel(0.05, 5e-4)
        )
        d = diagnose(arm, meas, None)
        assert d.effect in (*{e.name for e in VOCABULARY}, "none", "unattributed"), d.report
        assert d.located_in is None or d.located_in in places, d.located_in
        assert all(v.plausible for v in d.parameters.values()), (c, params, d.report)
        assert d.to_dict()["effect"] == d.effect
