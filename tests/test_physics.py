"""The candidate effects: exact geometric model at zero, finite Jacobians, skip reasons, and
independent oracles (cable forward kinematics, the textbook cantilever)."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _physics_data import BrokenEffect, base, find

from cdra_jax import NoiseModel, lie, tool_pose
from cdra_jax.arm import Arm
from cdra_jax.calibration import stacked_system
from cdra_jax.calibration.observations import make_observations
from cdra_jax.diagnosis.model import Extended, residual_and_jacobian
from cdra_jax.modules.cables import cable_forward_kinematics, cable_lengths
from cdra_jax.modules.statics import gravity_torques, holding_tensions
from cdra_jax.physics import (
    EFFECT_NAMES,
    Candidate,
    Features,
    bending_deflection,
    candidates,
    corrected_tool_pose,
    effect,
)
from cdra_jax.physics.base import shared_term, sharing_terms, stacked_features


def test_vocabulary_is_the_design_table():
    assert EFFECT_NAMES == (
        "joint_compliance",
        "cable_elasticity",
        "cable_scale",
        "backlash",
        "periodic_error",
        "link_bending",
        "thermal_drift",
    )
    b = base()
    locs = {(c.name, c.location) for c in b.everything if c.name != "probe"}
    assert ("link_bending", "upper_arm") in locs and ("link_bending", "forearm") in locs
    assert ("thermal_drift", "base") in locs and ("link_bending", "base") not in locs
    for name in ("joint_compliance", "cable_elasticity", "cable_scale", "backlash"):
        assert {loc for n, loc in locs if n == name} == {"shoulder", "elbow", "wrist"}


def test_zero_parameters_give_the_geometric_model_exactly():
    b = base()
    T = corrected_tool_pose(b.actual, b.q, b.F, jnp.zeros(b.F.n_params))
    # identity corrections: equal up to the rounding of a different order of products
    np.testing.assert_allclose(np.asarray(T), np.asarray(tool_pose(b.actual, b.q)), atol=1e-12)


def test_features_shapes_and_jacobians_finite():
    b = base()
    m, k = b.q.shape[0], len(b.arm.modules)
    assert b.F.state.shape == (m, b.arm.dof, b.F.n_params)
    assert b.F.module_twist.shape == (m, k, 6, b.F.n_params)
    assert b.F.frame_deflection.shape == (m, k + 1, 6, b.F.n_params)
    # in numpy: each candidate's column slice is another shape (an XLA program per slice)
    state, twist, deflection = (
        np.asarray(a) for a in (b.F.state, b.F.module_twist, b.F.frame_deflection)
    )
    for c in b.everything:
        sl = b.cols[c]
        assert sl.stop - sl.start == len(c.parameters(b.arm)), c.label
        cols = [state[..., sl], twist[..., sl], deflection[..., sl]]
        assert all(bool(np.all(np.isfinite(x))) for x in cols), c.label
        assert max(float(np.abs(x).max()) for x in cols) > 0, f"{c.label} has no effect"
    # d residual / d (frame errors, theta) through the exact chain (the diagnosis' compiled
    # Jacobian): finite, non-zero for every column, and the frame-error block is Eq. 8's D
    # (minus: the residual is measured minus model).
    T = tool_pose(b.actual, b.q)
    m = b.q.shape[0]
    obs = make_observations(b.actual, b.q, np.asarray(T), None)
    one = jnp.ones(m)
    problem = Extended(b.actual, b.q, obs, one, one, jnp.ones((m, 0)), jnp.zeros((0, 3)), b.F)
    y0 = jnp.zeros(b.arm.n_params + b.F.n_params)
    r, J = (np.asarray(x) for x in residual_and_jacobian(y0, problem))
    assert float(np.abs(r).max()) < 1e-9
    assert bool(np.all(np.isfinite(J)))
    assert bool(np.all(np.abs(J).max(axis=0) > 0))
    # the frame columns are the whitened Eq. 8 Jacobian (1 mm, 1 rad), with the sign of e = -D X
    _, D = stacked_system(b.actual, b.q, T, NoiseModel(1.0, 1.0))
    np.testing.assert_allclose(J[:, : b.arm.n_params], -D, atol=1e-9)


def test_refinements_are_richer_forms_of_a_tested_effect():
    """A refinement (never tested alone) refines an effect that has a tested form at the same
    place; the quadratic joint compliance is the per-axis one scaled by the load."""
    b = base()
    tested = {(c.name, c.location) for c in b.everything if not c.effect.refinement}
    refinements = [c for c in b.everything if c.effect.refinement]
    assert {c.name for c in refinements} == {
        "joint_compliance",
        "cable_elasticity",
        "periodic_error",
        "thermal_drift",
    }
    assert all((c.name, c.location) in tested for c in refinements)
    lin = find("joint_compliance", "wrist", "per_axis").features(b.arm, b.q, b.aux)
    quad = find("joint_compliance", "wrist", "per_axis_quadratic").features(b.arm, b.q, b.aux)
    load = jnp.linalg.norm(gravity_torques(b.arm, b.q, b.aux["payload_kg"])[:, 2], axis=-1)
    assert float(load.min()) > 0
    np.testing.assert_allclose(
        quad.module_twist, lin.module_twist * load[:, None, None, None], rtol=1e-12, atol=1e-18
    )


def test_single_candidate_pure_function_matches_the_stacked_features():
    b = base()
    c = find("joint_compliance", "elbow")
    params = jnp.array([2e-7, -1e-7])
    T = c.tool_pose(b.actual, b.q, b.aux, params)
    theta = jnp.zeros(b.F.n_params).at[b.cols[c]].set(params)
    np.testing.assert_allclose(T, corrected_tool_pose(b.actual, b.q, b.F, theta), atol=1e-9)
    with pytest.raises(ValueError, match="theta must have shape"):
        corrected_tool_pose(b.actual, b.q, b.F, jnp.zeros(3))


def test_shared_terms_are_evaluated_once_per_arguments_and_only_inside_the_block():
    calls = []

    def term(x, i):
        calls.append(i)
        return x * i

    x = np.ones(3)
    shared_term(term, x, 2)
    shared_term(term, x, 2)
    assert calls == [2, 2]  # outside the block: a plain call
    with sharing_terms():
        a = shared_term(term, x, 2)
        assert shared_term(term, x, 2) is a  # same function and arguments: evaluated once
        shared_term(term, x, 3)
        shared_term(term, x.copy(), 2)  # another array (identity, not value)
    assert calls == [2, 2, 2, 3, 2]
    with sharing_terms():
        shared_term(term, x, 2)  # a new block starts empty
    assert calls[-1] == 2 and len(calls) == 6


def test_features_in_one_program_equal_each_candidate_alone():
    """The stacked features (their shared terms evaluated once) equal each candidate's own
    features, for the effects whose forms share terms."""
    b = base()
    for c in (
        find("cable_elasticity", "wrist", "holding"),
        find("cable_elasticity", "shoulder", "per_cable"),
        find("joint_compliance", "elbow"),
    ):
        alone = c.features(b.actual, b.q, b.aux)
        cols = b.cols[c]
        leaves = [np.asarray(a) for a in jax.tree.leaves(alone)]
        scale = max(np.abs(a).max() for a in leaves)
        for got, want in zip(leaves, map(np.asarray, jax.tree.leaves(b.F)), strict=True):
            # the same to rounding (the two programs are fused differently)
            np.testing.assert_allclose(got, want[..., cols], rtol=1e-12, atol=1e-14 * scale)


def test_a_column_that_is_not_finite_stays_among_many_candidates():
    """Rounding-level columns are zeroed per candidate; a non-finite column is kept as it is
    (the diagnosis marks its candidate failed), however many candidates are stacked."""
    b = base()
    broken = Candidate(BrokenEffect(), "elbow")
    others = tuple(c for c in b.everything if c.name in ("cable_scale", "probe"))
    F = stacked_features((*others[:3], broken, *others[3:]), b.arm, b.q, b.aux)
    k = sum(len(c.parameters(b.arm)) for c in others[:3])
    nan_columns = np.where(np.isnan(np.asarray(F.state)).any(axis=(0, 1)))[0]
    assert list(nan_columns) == [k]


def _replace_modules(arm: Arm, **changes) -> Arm:
    mods = tuple(dataclasses.replace(m, **changes) for m in arm.modules)
    return eqx.tree_at(lambda a: a.modules, arm, mods)


def test_skip_reasons_name_what_is_missing():
    b = base()
    reasons = {(c.name, c.location, c.variant): why for c, why in candidates(b.arm, ["time_s"])}
    assert "approach.wrist" in reasons[("backlash", "wrist", "state")]
    assert reasons[("thermal_drift", "base", "")] is None
    reasons = {(c.name, c.location): why for c, why in candidates(b.arm, [])}
    assert "time_s" in reasons[("thermal_drift", "base")]
    massless = _replace_modules(b.arm, mass=None, com=None)
    reasons = {(c.name, c.location, c.variant): why for c, why in candidates(massless, [])}
    assert "mass" in reasons[("joint_compliance", "shoulder", "isotropic")]
    assert "mass" in reasons[("link_bending", "forearm", "")]
    assert reasons[("cable_scale", "elbow", "from_home")] is None
    # without masses, the lumped gravity moments are fitted instead; with them, not tried
    assert reasons[("joint_compliance", "shoulder", "lumped")] is None
    assert reasons[("joint_compliance", "elbow", "lumped_axial")] is None
    assert reasons[("link_bending", "forearm", "lumped")] is None
    heavy = {(c.name, c.location, c.variant): why for c, why in candidates(b.arm, [])}
    assert "masses" in heavy[("joint_compliance", "shoulder", "lumped")]
    assert "masses" in heavy[("link_bending", "forearm", "lumped")]
    # with a payload column the loads exist again
    reasons = {
        (c.name, c.location, c.variant): why for c, why in candidates(massless, ["payload_kg"])
    }
    assert reasons[("joint_compliance", "shoulder", "isotropic")] is None
    cableless = _replace_modules(b.arm, cable_base=None, cable_platform=None, cable_offset=None)
    reasons = {(c.name, c.location, c.variant): why for c, why in candidates(cableless, [])}
    assert "no cables" in reasons[("cable_elasticity", "wrist", "holding")]
    assert "no cables" in reasons[("cable_scale", "shoulder", "from_home")]
    with pytest.raises(ValueError, match="unknown effect"):
        effect("gear_wobble")


def _platform_rotation(c: Candidate, arm, q, aux, value, i):
    """Module i's platform rotation from the candidate's correction alone."""
    f = c.features(arm, q, aux)
    theta = jnp.full(f.n_params, value)
    dq = jnp.einsum("mdp,p->md", f.state, theta)
    xi = jnp.einsum("mkcp,p->mkc", f.module_twist, theta)[:, i]
    qi = arm.split_state(q + dq)[i]
    return lie.se3_exp(xi)[:, :3, :3] @ arm.modules[i].pose(qi)[:, :3, :3]


@eqx.filter_jit
def _cable_fk(mod, lengths, initial):
    """Cable forward kinematics, compiled once for the three effects (same module, shapes)."""
    return cable_forward_kinematics(mod, lengths, initial=initial, residual_tol=1e3)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["cable_elasticity", "cable_scale", "periodic_error"])
def test_cable_effects_agree_with_cable_forward_kinematics(name):
    """Oracle: the module state the stretched/scaled/eccentric-drum cable lengths give by the
    (nonlinear, least-squares) cable forward kinematics of cdra_jax.modules."""
    b = base()
    arm, q, aux = b.arm, b.q[:6], {k: v[:6] for k, v in b.aux.items()}
    mod = arm.modules[0]
    qs = arm.split_state(q)[0]
    if name == "cable_elasticity":
        c, value = find(name, "shoulder"), 0.01  # mm/N: 100 N/mm cables
        tensions = eqx.filter_jit(lambda a, x: holding_tensions(a, x)["shoulder"].tensions)
        lengths = cable_lengths(mod, qs) + value * tensions(arm, q)
    elif name == "cable_scale":
        c, value = find(name, "shoulder", "from_home"), 0.01
        l0 = cable_lengths(mod, jnp.zeros_like(qs))
        lengths = l0 + (1 + value) * (cable_lengths(mod, qs) - l0)
    else:  # an eccentric 10 mm drum per cable, sine and cosine amplitudes 0.2 mm
        c, value = find(name, "shoulder", "drum r=10mm k=1"), 0.2
        paid = cable_lengths(mod, qs) - cable_lengths(mod, jnp.zeros_like(qs))
        phi = paid / 10.0  # drum angle, rad
        wobble = jnp.sin(phi) + jnp.cos(phi)
        lengths = cable_lengths(mod, qs) + value * wobble
    # stretched lengths are not a consistent set: least squares over the 6 cables
    fk = _cable_fk(mod, lengths, qs)
    assert bool(jnp.all(fk.successful))
    R_oracle = lie.so3_exp(fk.state)
    R_model = _platform_rotation(c, arm, q, aux, value, 0)
    R_nominal = mod.pose(qs)[:, :3, :3]
    moved = lie.rotation_angle(jnp.swapaxes(R_nominal, -1, -2) @ R_oracle)
    err = lie.rotation_angle(jnp.swapaxes(R_model, -1, -2) @ R_oracle)
    assert float(moved.min()) > 1e-4  # the effect is visible ...
    assert float((err / moved).max()) < 0.05  # ... and the first-order model gets it right


def test_bending_force_part_is_the_textbook_cantilever():
    """Upper arm horizontal, massless links, payload at the elbow end only through the tip:
    delta = F L^3 / (3 E I), theta = F L^2 / (2 E I) (Euler-Bernoulli)."""
    b = base()
    arm = _replace_modules(b.arm, mass=None, com=None)
    # a payload at the tool with the elbow straight and the wrist at rest puts the load on the
    # link axis line; turn the shoulder by pi/2 about y so that the arm is horizontal
    q = jnp.array([[0.0, np.pi / 2, 0.0, 0.0, 0.0, 0.0, 0.0]])
    payload = 2.0
    d = bending_deflection(arm, q, 1, payload, split=True)[0]
    F = payload * 9.81
    L = 300.0
    force = d[:, 0]
    np.testing.assert_allclose(float(jnp.linalg.norm(force[:3])), F * L**3 / 3, rtol=1e-9)
    np.testing.assert_allclose(float(jnp.linalg.norm(force[3:])), F * L**2 / 2, rtol=1e-9)
    # arm upright: no transverse force; the payload hangs 20 mm beside the link axis (the tool
    # frame's offset), a tip moment M = F * 20 mm: theta = M L, delta = M L^2 / 2
    d_up = bending_deflection(arm, jnp.zeros((1, 7)), 1, payload, split=True)[0]
    assert float(jnp.abs(d_up[:, 0]).max()) < 1e-6
    M = F * 20.0
    np.testing.assert_allclose(float(jnp.linalg.norm(d_up[3:, 1])), M * L, rtol=1e-9)
    np.testing.assert_allclose(float(jnp.linalg.norm(d_up[:3, 1])), M * L**2 / 2, rtol=1e-9)


def test_backlash_and_drift_follow_their_auxiliaries():
    b = base()
    c = find("backlash", "elbow")
    f = c.features(b.arm, b.q, b.aux)
    j = b.arm.state_names.index("elbow.q")
    np.testing.assert_array_equal(f.state[:, j, 0], -b.aux["approach.elbow"])
    d = find("thermal_drift", "base").features(b.arm, b.q, b.aux)
    np.testing.assert_array_equal(d.frame_deflection[:, 0, 2, 2], b.aux["time_s"])
    w = find("thermal_drift", "base", "warm-up tau=600s").features(b.arm, b.q, b.aux)
    settled = 1.0 - np.exp(-np.asarray(b.aux["time_s"]) / 600.0)
    np.testing.assert_allclose(w.frame_deflection[:, 0, 4, 4], settled, rtol=1e-12)
    assert Features.zeros(b.arm, 3, 2).state.shape == (3, b.arm.dof, 2)


def test_only_periodic_series_name_a_coordinate_for_the_shape_check():
    """The harmonic forms (of a joint angle, of a drum angle) are series in a coordinate of
    their module: each parameter's feature follows one axis (a state entry, a cable's payout),
    which the diagnosis' shape check splits at its median. Forms whose shape is fixed by their
    physics name none."""
    b = base()
    arm, q = b.arm, b.q
    for c in b.everything:
        found = c.coordinate(arm, q)
        if c.name != "periodic_error":
            assert found is None, c.label
            continue
        assert found is not None, c.label
        z, owner = np.asarray(found[0]), np.asarray(found[1])
        assert z.shape[0] == q.shape[0] and np.all(np.isfinite(z))
        assert owner.shape == (len(c.parameters(arm)),)
        assert owner.min() == 0 and owner.max() == z.shape[1] - 1
    drum = find("periodic_error", "shoulder", "drum r=10mm k=1")
    z, owner = drum.coordinate(arm, q)
    mod = arm.modules[0]
    qs = arm.split_state(q)[0]
    paid = cable_lengths(mod, qs) - cable_lengths(mod, jnp.zeros_like(qs))
    np.testing.assert_allclose(np.asarray(z), np.asarray(paid))
    assert list(owner) == [j for j in range(mod.n_cables) for _ in range(2)]
