"""SO(3)/SE(3) maps (cdra_jax.lie) against scipy, matrix exp/log, group laws and autodiff.

Oracles: ``scipy.spatial.transform.Rotation`` for rotations and quaternions,
``scipy.linalg.expm`` / ``logm`` of the 4x4 se(3) matrix for the SE(3) maps, plain numpy for
inverses and adjoints, and fourth-order central finite differences for the derivatives.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from cdra_jax import lie

PI = np.pi

# One compilation per function and input shape for the whole module.
so3_exp = jax.jit(lie.so3_exp)
so3_log = jax.jit(lie.so3_log)
se3_exp = jax.jit(lie.se3_exp)
se3_log = jax.jit(lie.se3_log)
to_quat = jax.jit(lie.rotation_to_quaternion)
from_quat = jax.jit(lie.quaternion_to_rotation)
quat_log = jax.jit(lie.quaternion_log)
rot_angle = jax.jit(lie.rotation_angle)
inverse = jax.jit(lie.inverse)
adjoint = jax.jit(lie.adjoint)
from_xyz_rotvec = jax.jit(lie.from_xyz_rotvec)
to_xyz_rotvec = jax.jit(lie.to_xyz_rotvec)

N = 12  # rows per regime: every batched call below has the same shape, so compiles once


def _unit_vectors(rng: np.random.Generator, n: int) -> np.ndarray:
    u = rng.normal(size=(n, 3))
    return u / np.linalg.norm(u, axis=-1, keepdims=True)


def _rotvecs(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Rotation vectors by regime: generic, tiny (1e-9 rad) and near or at pi."""
    axes = _unit_vectors(rng, N)
    exact_pi = np.concatenate([np.diag([PI, PI, PI]), PI * axes[3:]])
    # The closed forms switch to Taylor series below 0.1 rad (lie._SMALL_ANGLE_SQ = 1e-2).
    switch = 0.1 + np.array([-1e-9, 1e-9, -1e-6, 1e-6, -1e-3, 1e-3] * 2)[:, None]
    return {
        "generic": _unit_vectors(rng, N) * rng.uniform(1e-3, PI - 1e-3, size=(N, 1)),
        "series": _unit_vectors(rng, N) * np.logspace(-8, -1.001, N)[:, None],
        "switch": _unit_vectors(rng, N) * switch,
        "tiny": 1e-9 * axes,
        "pi-1e-7": (PI - 1e-7) * axes,
        "pi-1e-12": (PI - 1e-12) * axes,
        "pi": exact_pi,
    }


ROTVECS = _rotvecs(np.random.default_rng(20080519))
BELOW_PI = ("generic", "series", "switch", "tiny", "pi-1e-7", "pi-1e-12")


def _hat3(w: np.ndarray) -> np.ndarray:
    x, y, z = w
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _hat6(xi: np.ndarray) -> np.ndarray:
    X = np.zeros((4, 4))
    X[:3, :3] = _hat3(xi[3:])
    X[:3, 3] = xi[:3]
    return X


def _pose(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T


def _adjoint(T: np.ndarray) -> np.ndarray:
    R, p = T[:3, :3], T[:3, 3]
    out = np.zeros((6, 6))
    out[:3, :3] = R
    out[:3, 3:] = _hat3(p) @ R
    out[3:, 3:] = R
    return out


# --------------------------------------------------------------------------- SO(3) vs scipy


@pytest.mark.parametrize("regime", list(ROTVECS))
def test_so3_exp_matches_scipy(regime):
    w = ROTVECS[regime]
    np.testing.assert_allclose(so3_exp(w), Rotation.from_rotvec(w).as_matrix(), rtol=0, atol=2e-15)


@pytest.mark.parametrize("regime", BELOW_PI)
def test_so3_log_recovers_rotvec_below_pi(regime):
    w = ROTVECS[regime]
    R = Rotation.from_rotvec(w).as_matrix()
    got = np.asarray(so3_log(R))
    # Absolute accuracy at machine precision in every regime, relative accuracy for tiny angles.
    np.testing.assert_allclose(got, w, rtol=0, atol=4e-15)
    np.testing.assert_allclose(got, Rotation.from_matrix(R).as_rotvec(), rtol=0, atol=4e-15)
    if regime in ("tiny", "series"):  # small angles: relative accuracy too
        err = np.linalg.norm(got - w, axis=-1) / np.linalg.norm(w, axis=-1)
        assert err.max() < 1e-14


def test_so3_log_at_exactly_pi_up_to_sign():
    w = ROTVECS["pi"]
    R = Rotation.from_rotvec(w).as_matrix()
    got = np.asarray(so3_log(R))
    err = np.minimum(np.abs(got - w).max(-1), np.abs(got + w).max(-1))
    assert err.max() < 4e-15
    np.testing.assert_allclose(np.linalg.norm(got, axis=-1), PI, rtol=0, atol=4e-15)
    # Either sign is the same rotation.
    np.testing.assert_allclose(so3_exp(got), R, rtol=0, atol=2e-15)


@pytest.mark.parametrize("regime", list(ROTVECS))
def test_quaternions_match_scipy(regime):
    w = ROTVECS[regime]
    rot = Rotation.from_rotvec(w)
    R = rot.as_matrix()
    xyzw = rot.as_quat()
    wxyz = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=-1)
    q = np.asarray(to_quat(R))
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, rtol=0, atol=2e-15)
    sign = np.sign(np.sum(q * wxyz, axis=-1, keepdims=True))
    np.testing.assert_allclose(q, sign * wxyz, rtol=0, atol=4e-15)
    np.testing.assert_allclose(from_quat(wxyz), R, rtol=0, atol=2e-15)
    np.testing.assert_allclose(from_quat(-wxyz), R, rtol=0, atol=2e-15)
    # log of a quaternion and of its antipode are the same rotation vector (norm <= pi).
    for qq in (wxyz, -wxyz):
        got = np.asarray(quat_log(qq))
        if regime == "pi":
            err = np.minimum(np.abs(got - w).max(-1), np.abs(got + w).max(-1))
            assert err.max() < 4e-15
        else:
            np.testing.assert_allclose(got, w, rtol=0, atol=4e-15)
    np.testing.assert_allclose(rot_angle(R), rot.magnitude(), rtol=0, atol=4e-15)


# --------------------------------------------------------------------------- SE(3)


def _twists(rng: np.random.Generator, regime: str) -> np.ndarray:
    w = ROTVECS[regime]
    v = rng.uniform(-500.0, 500.0, size=w.shape)
    return np.concatenate([v, w], axis=-1)


@pytest.mark.parametrize("regime", list(ROTVECS))
def test_se3_exp_matches_matrix_exponential(regime):
    xi = _twists(np.random.default_rng(1), regime)
    expected = np.stack([scipy.linalg.expm(_hat6(x)) for x in xi])
    np.testing.assert_allclose(se3_exp(xi), expected, rtol=1e-13, atol=1e-12)


def test_se3_log_matches_matrix_logarithm():
    xi = _twists(np.random.default_rng(2), "generic")
    T = np.asarray(se3_exp(xi))
    expected = np.stack([np.real(scipy.linalg.logm(t)) for t in T])
    np.testing.assert_allclose(se3_log(T), np.stack([_vee6(X) for X in expected]), atol=1e-9)


def _vee6(X: np.ndarray) -> np.ndarray:
    return np.array([X[0, 3], X[1, 3], X[2, 3], X[2, 1], X[0, 2], X[1, 0]])


@pytest.mark.parametrize("regime", list(ROTVECS))
def test_se3_exp_log_round_trips(regime):
    xi = _twists(np.random.default_rng(3), regime)
    T = np.asarray(se3_exp(xi))
    back = np.asarray(se3_log(T))
    if regime == "pi":
        # The rotation vector is only defined up to sign at pi; the pose is what must agree.
        np.testing.assert_allclose(np.linalg.norm(back[:, 3:], axis=-1), PI, atol=4e-15)
    else:
        np.testing.assert_allclose(back[:, 3:], xi[:, 3:], rtol=0, atol=4e-15)
        np.testing.assert_allclose(back[:, :3], xi[:, :3], rtol=0, atol=1e-11)
    np.testing.assert_allclose(se3_exp(back), T, rtol=0, atol=1e-12)


def test_inverse_and_adjoint_against_numpy():
    rng = np.random.default_rng(4)
    T = np.asarray(se3_exp(_twists(rng, "generic")))
    xi = _twists(rng, "generic")
    np.testing.assert_allclose(inverse(T), np.linalg.inv(T), rtol=0, atol=1e-12)
    np.testing.assert_allclose(inverse(T) @ T, np.broadcast_to(np.eye(4), T.shape), atol=1e-12)
    Ad = np.asarray(adjoint(T))
    np.testing.assert_allclose(Ad, np.stack([_adjoint(t) for t in T]), rtol=0, atol=1e-12)
    # Eq. 6: T hat(xi) T^-1 = hat(Ad_T xi), and its integrated form T exp(xi) T^-1 = exp(Ad xi).
    lhs = np.stack([t @ _hat6(x) @ np.linalg.inv(t) for t, x in zip(T, xi, strict=True)])
    rhs = np.stack([_hat6(a @ x) for a, x in zip(Ad, xi, strict=True)])
    np.testing.assert_allclose(lhs, rhs, rtol=0, atol=1e-9)
    conj = T @ np.asarray(se3_exp(xi)) @ np.linalg.inv(T)
    np.testing.assert_allclose(conj, se3_exp(np.einsum("nij,nj->ni", Ad, xi)), atol=1e-9)


def test_from_and_to_xyz_rotvec():
    rng = np.random.default_rng(5)
    w = ROTVECS["generic"]
    p = rng.uniform(-500, 500, size=w.shape)
    T = np.asarray(from_xyz_rotvec(p, w))
    np.testing.assert_allclose(T[:, :3, :3], Rotation.from_rotvec(w).as_matrix(), atol=2e-15)
    np.testing.assert_allclose(T[:, :3, 3], p, rtol=0, atol=0)
    xyz, rv = to_xyz_rotvec(T)
    np.testing.assert_allclose(xyz, p, rtol=0, atol=0)
    np.testing.assert_allclose(rv, w, rtol=0, atol=4e-15)


# --------------------------------------------------------------------------- group laws


def _twist_strategy(regime: str) -> st.SearchStrategy[np.ndarray]:
    comp = st.floats(-1.0, 1.0, allow_nan=False)
    axis = st.tuples(comp, comp, comp).filter(lambda a: np.linalg.norm(a) > 0.1)
    angle = {
        "zero": st.floats(0.0, 1e-6),
        "generic": st.floats(1e-3, 3.0),
        "pi": st.floats(1e-9, 1e-3).map(lambda d: PI - d),
    }[regime]
    v = st.tuples(*[st.floats(-500.0, 500.0, allow_nan=False)] * 3)

    def build(args):
        a, t, vv = args
        a = np.asarray(a) / np.linalg.norm(a)
        return np.concatenate([np.asarray(vv), t * a])

    return st.tuples(axis, angle, v).map(build)


TWISTS = st.sampled_from(["zero", "generic", "pi"]).flatmap(_twist_strategy)
GROUP = settings(max_examples=40, deadline=None)


@jax.jit
def _group_law_errors(a, b, c):
    A, B, C = lie.se3_exp(a), lie.se3_exp(b), lie.se3_exp(c)
    inv = lie.inverse
    eye = jnp.eye(4)
    return {
        "assoc": lie.compose(lie.compose(A, B), C) - lie.compose(A, lie.compose(B, C)),
        "identity": jnp.stack([lie.compose(A, eye) - A, lie.compose(eye, A) - A]),
        "exp0": lie.se3_exp(jnp.zeros(6)) - eye,
        "inverse": jnp.stack([inv(A) @ A - eye, A @ inv(A) - eye, inv(inv(A)) - A]),
        "inverse_of_product": inv(A @ B) - inv(B) @ inv(A),
        "exp_neg": lie.se3_exp(-a) - inv(A),
        "ad_hom": lie.adjoint(A @ B) - lie.adjoint(A) @ lie.adjoint(B),
        "ad_inv": lie.adjoint(inv(A)) @ lie.adjoint(A) - jnp.eye(6),
        "conj": A @ lie.se3_exp(c) @ inv(A) - lie.se3_exp(lie.adjoint(A) @ c),
    }


@GROUP
@given(TWISTS, TWISTS, TWISTS)
def test_group_laws(a, b, c):
    errs = {k: float(jnp.max(jnp.abs(v))) for k, v in _group_law_errors(a, b, c).items()}
    # Translations are up to ~1500 mm after three products: 1e-12 relative is ~2e-9 mm;
    # the 6x6 adjoints carry hat(p) R blocks of the same size, squared in the products.
    tol = {"ad_hom": 1e-8, "ad_inv": 1e-8, "conj": 1e-8}
    for k, e in errs.items():
        assert e < tol.get(k, 2e-9), (k, e, errs)


@jax.jit
def _log_exp(xi):
    T = lie.se3_exp(xi)
    back = lie.se3_log(T)
    return back, lie.se3_exp(back) - T


@GROUP
@given(TWISTS)
def test_log_exp_inverse_within_injectivity_radius(xi):
    back, pose_err = _log_exp(xi)
    # |w| < pi for every strategy, so log(exp(xi)) = xi.
    np.testing.assert_allclose(back[3:], xi[3:], rtol=0, atol=1e-14)
    np.testing.assert_allclose(back[:3], xi[:3], rtol=0, atol=1e-9)
    assert float(jnp.max(jnp.abs(pose_err))) < 1e-11


# --------------------------------------------------------------------------- derivatives


def _fd_jacobian(f, x: np.ndarray, h: float) -> np.ndarray:
    """Fourth-order central differences of a batched ``f`` at ``x``: ``f.shape + x.shape``."""
    x = np.asarray(x, dtype=float)
    n = x.size
    E = np.eye(n).reshape((n,) + x.shape)
    pts = np.concatenate([x + s * h * E for s in (2, 1, -1, -2)])  # one batched evaluation
    vals = np.asarray(f(pts))
    vals = vals.reshape((4, n) + vals.shape[1:])
    d = (-vals[0] + 8 * vals[1] - 8 * vals[2] + vals[3]) / (12 * h)
    return np.moveaxis(d, 0, -1).reshape(vals.shape[2:] + x.shape)


def _branch_margin(R: np.ndarray) -> float:
    """Distance of R from the branch switches of Shepperd's method in rotation_to_quaternion."""
    m00, m11, m22 = R[0, 0], R[1, 1], R[2, 2]
    return min(abs(m22), abs(m00 - m11) if m22 < 0 else abs(m00 + m11))


def _points(regime: str) -> list[np.ndarray]:
    """Twists at zero, at random points and with rotation angle pi - 1e-3."""
    rng = np.random.default_rng({"zero": 0, "random": 1, "near_pi": 2}[regime])
    if regime == "zero":
        return [np.zeros(6)]
    out = []
    while len(out) < 3:
        axis = _unit_vectors(rng, 1)[0]
        angle = PI - 1e-3 if regime == "near_pi" else rng.uniform(0.3, 2.5)
        xi = np.concatenate([rng.uniform(-300, 300, 3), angle * axis])
        if _branch_margin(Rotation.from_rotvec(xi[3:]).as_matrix()) > 1e-2:
            out.append(xi)
    return out


JACOBIAN_CASES = [(r, i) for r in ("zero", "random", "near_pi") for i in range(len(_points(r)))]


def _tangent_log(d, R0):
    """log(exp(d) R0): the SO(3) logarithm along the manifold."""
    return lie.so3_log(lie.so3_exp(d) @ R0)


# Jacobians, forward and reverse mode, compiled once each.
JAC = {
    name: (jax.jit(jax.jacfwd(f)), jax.jit(jax.jacrev(f)))
    for name, f in {
        "so3_exp": lie.so3_exp,
        "se3_exp": lie.se3_exp,
        "so3_log": lie.so3_log,
        "se3_log": lie.se3_log,
        "tangent_log": _tangent_log,
    }.items()
}
PRIMAL = {
    "so3_exp": so3_exp,
    "se3_exp": se3_exp,
    "so3_log": so3_log,
    "se3_log": se3_log,
    "tangent_log": jax.jit(jax.vmap(_tangent_log, (0, None))),
}


def _check_jacobians(name, x, h, atol, *args):
    jfwd, jrev = JAC[name]
    fwd = np.asarray(jfwd(jnp.asarray(x), *args))
    rev = np.asarray(jrev(jnp.asarray(x), *args))
    assert np.all(np.isfinite(fwd)) and np.all(np.isfinite(rev))
    np.testing.assert_allclose(fwd, rev, rtol=0, atol=1e-12 * max(1.0, np.abs(fwd).max()))
    fd = _fd_jacobian(lambda y: PRIMAL[name](y, *args), x, h)
    np.testing.assert_allclose(fwd, fd, rtol=0, atol=atol)
    return fwd


@pytest.mark.parametrize(("regime", "i"), JACOBIAN_CASES)
def test_exp_jacobians(regime, i):
    xi = _points(regime)[i]
    _check_jacobians("so3_exp", xi[3:], 1e-4, 1e-10)
    _check_jacobians("se3_exp", xi, 1e-4, 1e-8)


@pytest.mark.parametrize(("regime", "i"), JACOBIAN_CASES)
def test_log_jacobians(regime, i):
    """d log / d matrix entries (the implementation's extension off the manifold)."""
    xi = _points(regime)[i]
    T = np.asarray(se3_exp(xi))
    # Steps must stay well inside the branch and, near pi, below the distance to pi.
    h = 1e-6 if regime == "near_pi" else 1e-4
    _check_jacobians("so3_log", T[:3, :3], h, 1e-7)
    _check_jacobians("se3_log", T, h, 1e-6)


def _jl_inverse(w: np.ndarray) -> np.ndarray:
    """Inverse left Jacobian of SO(3), the textbook closed form (independent of cdra_jax)."""
    t = np.linalg.norm(w)
    W = _hat3(w)
    if t < 1e-8:
        return np.eye(3) - W / 2
    return np.eye(3) - W / 2 + (1 / t**2 - (1 + np.cos(t)) / (2 * t * np.sin(t))) * W @ W


@pytest.mark.parametrize(("regime", "i"), JACOBIAN_CASES)
def test_log_tangent_jacobian_is_inverse_left_jacobian(regime, i):
    """On the manifold: d/dd log(exp(d) R0) at d = 0 is A^-1 (Eq. 27) of w0 = log(R0)."""
    w0 = _points(regime)[i][3:]
    R0 = jnp.asarray(Rotation.from_rotvec(w0).as_matrix())
    J = _check_jacobians(
        "tangent_log", np.zeros(3), 1e-6 if regime == "near_pi" else 1e-4, 1e-8, R0
    )
    np.testing.assert_allclose(J, _jl_inverse(w0), rtol=0, atol=1e-10)


def test_jacobians_at_identity_are_exact():
    """At exactly zero and at 1e-9 rad: finite, and equal to the generators (no NaN)."""
    gens = np.stack([_hat3(e) for e in np.eye(3)], axis=-1)  # dR/dw_k = hat(e_k)
    gens6 = np.stack([_hat6(e) for e in np.eye(6)], axis=-1)
    # log near the identity: w = vee((R - R^T) / 2), v = p.
    dlog = np.zeros((3, 3, 3))
    for k, (i, j) in enumerate([(2, 1), (0, 2), (1, 0)]):
        dlog[k, i, j], dlog[k, j, i] = 0.5, -0.5
    for scale in (0.0, 1e-9):
        w = scale * _unit_vectors(np.random.default_rng(6), 1)[0]
        xi = np.concatenate([scale * np.ones(3), w])
        R = jnp.asarray(Rotation.from_rotvec(w).as_matrix())
        T = jnp.asarray(_pose(np.asarray(R), np.zeros(3)))
        for mode in (0, 1):  # jacfwd, jacrev
            np.testing.assert_allclose(JAC["so3_exp"][mode](jnp.asarray(w)), gens, atol=1e-8)
            np.testing.assert_allclose(JAC["se3_exp"][mode](jnp.asarray(xi)), gens6, atol=1e-8)
            np.testing.assert_allclose(JAC["so3_log"][mode](R), dlog, atol=1e-8)
            J6 = np.asarray(JAC["se3_log"][mode](T))
            assert np.all(np.isfinite(J6))
            np.testing.assert_allclose(J6[3:, :3, :3], dlog, atol=1e-8)
            np.testing.assert_allclose(J6[:3, :3, 3], np.eye(3), atol=1e-8)


WRONG_SHAPES = [
    (lie.hat3, (2,)),
    (lie.vee3, (3, 2)),
    (lie.hat, (5,)),
    (lie.vee, (3, 4)),
    (lie.so3_exp, (2,)),
    (lie.so3_left_jacobian, (4,)),
    (lie.so3_left_jacobian_inverse, (6,)),
    (lie.rotation_to_quaternion, (4, 4)),
    (lie.quaternion_to_rotation, (3,)),
    (lie.quaternion_log, (3,)),
    (lie.so3_log, (4, 4)),
    (lie.se3_exp, (5,)),
    (lie.se3_log, (3, 4)),
    (lie.inverse, (3, 3)),
    (lie.adjoint, (3, 4)),
    (lie.rotation, (3, 3)),
    (lie.translation, (3,)),
    (lie.rotation_angle, (4, 4)),
]


@pytest.mark.parametrize(("fn", "shape"), WRONG_SHAPES, ids=[f.__name__ for f, _ in WRONG_SHAPES])
def test_wrong_trailing_shapes_raise(fn, shape):
    """A short trailing axis would be clamped silently by indexing under jit (so3_exp of a
    2-vector used w[1] as its z component); the maps name the argument and the shape."""
    with pytest.raises(ValueError, match=rf"lie\.{fn.__name__}: \w+ must have shape \(\.\.\."):
        fn(jnp.zeros(shape))
    with pytest.raises(ValueError, match="must have shape"):
        jax.jit(fn)(jnp.zeros((7, *shape)))
    with pytest.raises(ValueError, match=r"lie\.make_pose: p must have shape \(\.\.\., 3\)"):
        lie.make_pose(jnp.eye(3), jnp.zeros(2))


def test_rotation_angle_gradient_is_finite_at_identity():
    """The angle is a cone at the identity: gradient zero there, not NaN; elsewhere it matches
    jacrev and central differences."""
    g = jax.jit(jax.grad(lie.rotation_angle))(jnp.eye(3))
    np.testing.assert_array_equal(g, np.zeros((3, 3)))
    w = jnp.array([0.1, -0.2, 0.3])
    f = lambda w: lie.rotation_angle(lie.so3_exp(w))  # noqa: E731
    # compiled: one program per derivative instead of each operation compiled on its own
    grad, rev, fwd = (jax.jit(d(f)) for d in (jax.grad, jax.jacrev, jax.jacfwd))
    np.testing.assert_allclose(grad(w), w / jnp.linalg.norm(w), rtol=1e-12)
    np.testing.assert_allclose(rev(w), fwd(w), rtol=1e-12)
    assert np.all(np.isfinite(grad(jnp.zeros(3))))
