"""Cable kinematics of the CDPM modules: inverse and forward kinematics, offsets in model files."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cdra_jax import lie
from cdra_jax.arm import prismatic, spherical
from cdra_jax.io import dumps_model, loads_model
from cdra_jax.io.model import ModelFileError
from cdra_jax.modules import (
    cable_forward_kinematics,
    cable_length_names,
    cable_lengths,
    length_jacobian,
    result_names,
    structure_matrix,
)

_fk = jax.jit(cable_forward_kinematics)
N = 2000  # one batch size everywhere, so that each module's solver compiles once


def _uniform(key, module, m):
    lim = np.asarray(module.limits)
    u = np.asarray(jax.random.uniform(key, (m, module.dof), dtype=jnp.float64))
    return lim[:, 0] + u * (lim[:, 1] - lim[:, 0])


def _angle_between(rotvec_a, rotvec_b):
    """Rotation angle of ``exp(a) exp(b)^T`` for rotation vectors ``(m, 3)``."""
    Ra, Rb = np.asarray(lie.so3_exp(rotvec_a)), np.asarray(lie.so3_exp(rotvec_b))
    return np.asarray(lie.rotation_angle(Ra @ np.swapaxes(Rb, -1, -2)))


def test_lengths_match_independent_geometry(cdra):
    sh, el, _ = cdra.modules
    q = np.array([[0.3, -0.7, 0.9], [-1.0, 1.0, -1.0], [0.0, 0.0, 0.0]])
    R = Rotation.from_rotvec(q).as_matrix()
    b, a = np.asarray(sh.cable_base), np.asarray(sh.cable_platform)
    expect = np.linalg.norm(b[None] - np.einsum("mij,nj->mni", R, a), axis=-1)
    np.testing.assert_allclose(cable_lengths(sh, q), expect, rtol=0, atol=1e-12)
    # Revolute elbow about y, by hand.
    t = 1.3
    Ry = np.array([[np.cos(t), 0, np.sin(t)], [0, 1, 0], [-np.sin(t), 0, np.cos(t)]])
    b, a = np.asarray(el.cable_base), np.asarray(el.cable_platform)
    expect = np.linalg.norm(b - a @ Ry.T, axis=-1)
    np.testing.assert_allclose(cable_lengths(el, [t]), expect, rtol=0, atol=1e-12)
    assert cable_length_names(sh) == tuple(f"shoulder.l{i}" for i in range(1, 7))


def test_length_jacobian_is_the_left_derivative(cdra):
    sh, el, _ = cdra.modules

    @jax.jit
    def check(q, t):
        R = lie.so3_exp(q)

        def lengths(d):
            return jnp.linalg.norm(
                sh.cable_base - (lie.so3_exp(d) @ R @ sh.cable_platform.T).T, axis=-1
            )

        return (
            length_jacobian(sh, q),
            jax.jacfwd(lengths)(jnp.zeros(3)),
            -structure_matrix(sh, q).T,
            length_jacobian(el, t),
            jax.jacfwd(lambda t: cable_lengths(el, t))(t),
        )

    J, J_ad, A_T, Je, Je_ad = check(jnp.asarray([0.4, -0.2, 0.7]), jnp.asarray([0.8]))
    np.testing.assert_allclose(J, J_ad, rtol=0, atol=1e-10)
    # ... and minus the transposed structure matrix (the statics/kinematics duality)
    np.testing.assert_allclose(J, A_T, atol=1e-12)
    np.testing.assert_allclose(Je, Je_ad, atol=1e-10)


@pytest.mark.parametrize("index", [0, 1, 2])
def test_forward_kinematics_round_trip_over_the_workspace(cdra, index):
    """IK then FK from the default starts, over uniform states in the whole joint box."""
    module = cdra.modules[index]
    q = _uniform(jax.random.PRNGKey(index), module, N)
    lengths = cable_lengths(module, q)
    sol = _fk(module, lengths)
    assert np.all(result_names(sol.result) == "successful")
    # the recovered state reproduces the lengths and is the state we started from
    np.testing.assert_allclose(cable_lengths(module, sol.state), lengths, rtol=0, atol=1e-9)
    if module.kind == "spherical":
        assert np.max(_angle_between(sol.state, q)) < 1e-9
    else:
        assert np.max(np.abs(np.asarray(sol.state) - q)) < 1e-9
    assert np.max(np.asarray(sol.residual_rms)) < 1e-9


def test_forward_kinematics_from_noisy_lengths_reports_the_residual(cdra):
    """E[rms^2] = s^2 (n - dof) / n for least squares over n cables with dof unknowns."""
    sigma = 0.02
    for module in (cdra.modules[0], cdra.modules[2]):
        q = _uniform(jax.random.PRNGKey(7), module, N)
        noisy = np.asarray(cable_lengths(module, q)) + sigma * np.asarray(
            jax.random.normal(jax.random.PRNGKey(8), (N, module.n_cables))
        )
        sol = _fk(module, noisy)
        assert np.all(result_names(sol.result) == "successful")
        n, d = module.n_cables, module.dof
        ratio = float(np.mean(np.asarray(sol.residual_rms) ** 2)) / (sigma**2 * (n - d) / n)
        # mean of N chi^2_{n-d} / (n-d) variables: standard error sqrt(2 / ((n-d) N)) <= 0.032
        assert abs(ratio - 1) < 0.15, ratio
        # the state error is of the size the noise implies (a fraction of a milliradian)
        assert 1e-6 < float(np.median(_angle_between(sol.state, q))) < 5e-3


@pytest.mark.parametrize("index", [0, 1, 2])
def test_forward_kinematics_under_vmap_equals_a_loop(cdra, index):
    """jax.vmap over poses gives, pose by pose, what one unbatched call per pose gives: the
    state, residuals, iterations and result code, for exact, noisy, inconsistent and NaN rows."""
    module = cdra.modules[index]
    k = 8
    q = _uniform(jax.random.PRNGKey(20 + index), module, k)
    lengths = np.array(cable_lengths(module, q))
    noise = 0.02 * np.asarray(jax.random.normal(jax.random.PRNGKey(30 + index), lengths.shape))
    lengths[1:4] += noise[1:4]
    lengths[4, 0] += 5.0
    lengths[5, -1] = np.nan
    one = jax.jit(lambda L: cable_forward_kinematics(module, L))
    batched = jax.jit(jax.vmap(lambda L: cable_forward_kinematics(module, L)))(lengths)
    batched = jax.tree_util.tree_map(np.asarray, batched)
    looped = [one(lengths[i]) for i in range(k)]
    codes = result_names(batched.result)
    assert list(codes[:6]) == ["successful"] * 4 + ["inconsistent_lengths", "nonfinite"]
    for i, sol in enumerate(looped):
        assert result_names(sol.result) == codes[i]
        assert int(sol.iterations) == int(batched.iterations[i])
        for name in ("state", "residual_rms", "residuals"):
            np.testing.assert_allclose(
                getattr(sol, name), getattr(batched, name)[i], rtol=0, atol=1e-12, err_msg=name
            )


def test_inconsistent_and_bad_lengths_get_result_codes(cdra):
    sh = cdra.modules[0]
    good = np.asarray(cable_lengths(sh, _uniform(jax.random.PRNGKey(3), sh, N)))
    bad = good.copy()
    bad[1, 2] += 5.0
    bad[2, 0] = np.nan
    sol = _fk(sh, bad)
    codes = result_names(sol.result)
    assert list(codes[:3]) == ["successful", "inconsistent_lengths", "nonfinite"]
    assert np.all(codes[3:] == "successful")
    assert float(np.asarray(sol.residual_rms)[1]) > 1.0
    # the largest misfit is in the corrupted column
    assert int(np.argmax(np.abs(np.asarray(sol.residuals)[1]))) == 2
    successful = np.asarray(sol.successful)
    assert bool(successful[0]) and not bool(successful[1])
    with pytest.raises(ValueError, match="shoulder.l1, shoulder.l2"):
        _fk(sh, good[:, :5])


def test_initial_guess_and_offsets():
    b = np.array([[60.0, 0, 0], [-30, 52, 0], [-30, -52, 0], [0, 0, -40]])
    a = np.array([[10.0, 0, 40], [-5, 8.66, 40], [-5, -8.66, 40], [0, 10, 20]])
    off = jnp.asarray([1.5, -2.0, 0.25, 3.0])
    m = spherical("s", cable_base=jnp.asarray(b), cable_platform=jnp.asarray(a), cable_offset=off)
    q = jnp.asarray([0.3, -0.2, 0.1])
    plain = np.linalg.norm(b - a @ np.asarray(lie.so3_exp(q)).T, axis=-1)
    np.testing.assert_allclose(cable_lengths(m, q), plain + np.asarray(off), atol=1e-12)
    sol = cable_forward_kinematics(m, cable_lengths(m, q), initial=jnp.asarray([0.25, -0.1, 0.0]))
    np.testing.assert_allclose(sol.state, q, atol=1e-10)


def test_prismatic_module_round_trip():
    b = np.array([[50.0, 0, 0], [-50, 0, 0], [0, 50, 100], [0, -50, 100]])
    a = np.array([[10.0, 0, 0], [-10, 0, 0], [0, 10, 0], [0, -10, 0]])
    m = prismatic(
        "slide", [0, 0, 1], (0.0, 80.0), cable_base=jnp.asarray(b), cable_platform=jnp.asarray(a)
    )
    q = np.linspace(1.0, 79.0, 40)[:, None]
    sol = cable_forward_kinematics(m, cable_lengths(m, q))
    np.testing.assert_allclose(sol.state, q, atol=1e-9)
    # force along the axis per newton: cables 1-2 pull down, 3-4 up
    A = np.asarray(structure_matrix(m, np.asarray([40.0])))
    assert A.shape == (1, 4) and float(A[0, 0]) < 0 < float(A[0, 2])


def test_cable_offsets_round_trip_through_model_files(cdra):
    sh = cdra.modules[0]
    off = jnp.asarray([0.5, -1.25, 0.0, 2.0, 0.125, -0.75])
    arm = eqx.tree_at(lambda a: a.modules[0].cable_offset, cdra, off, is_leaf=lambda x: x is None)
    text = dumps_model(arm)
    assert "offset = 0.5" in text
    back = loads_model(text)
    np.testing.assert_array_equal(back.modules[0].cable_offset, off)
    np.testing.assert_array_equal(back.modules[0].cable_base, sh.cable_base)
    assert back.modules[1].cable_offset is None
    # the default model survives a round trip unchanged
    again = loads_model(dumps_model(cdra))
    for m0, m1 in zip(cdra.modules, again.modules, strict=True):
        np.testing.assert_array_equal(m0.cable_platform, m1.cable_platform)
        assert (m0.mass, m0.pretension, m0.stiffness) == (m1.mass, m1.pretension, m1.stiffness)
    partial = text.replace("offset = 0.5\n", "", 1)
    with pytest.raises(ModelFileError, match=r"modules\[0\] \(shoulder\)\.cables: .*\(5 of 6"):
        loads_model(partial)
    with pytest.raises(ModelFileError, match=r"cables\[0\]\.offset: expected a number"):
        loads_model(text.replace("offset = 0.5\n", 'offset = "x"\n', 1))


def test_forward_kinematics_of_no_rows_gives_no_rows(cdra):
    """An empty batch of cable lengths gives an empty batch of states (no row to index)."""
    module = cdra.modules[0]
    sol = cable_forward_kinematics(module, np.zeros((0, module.n_cables)))
    assert sol.state.shape == (0, 3) and sol.iterations.shape == (0,)
