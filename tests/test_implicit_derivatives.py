"""Derivatives of the calibration solvers through their optimality conditions
(:mod:`cdra_jax.calibration.implicit`): against central finite differences of the converged
solution, forward against reverse mode, what the data cannot move, and refusals.

Each test compiles a solver with its derivative (5-15 s); the checks are gathered into few
compiled functions for the suite's time."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cdra_jax as cj
from cdra_jax import lie
from cdra_jax.calibration import residual_twist, whitening
from cdra_jax.simulation import simulate_trial

ARM = cj.default_arm()
NOISE = cj.NoiseModel(0.08, 1e-3)
M = 8


@jax.jit
def _simulate(keys):
    """:func:`simulate_trial` (``M`` poses, ``NOISE``) for each key, and the measured poses
    without the noise (the same states): one compiled simulation for the module."""

    def one(k):
        q, T, q_ver, _, X = simulate_trial(k, ARM, M, noise=NOISE)
        return q, T, q_ver[:3], cj.tool_pose(cj.apply_frame_errors(ARM, X), q)

    return jax.vmap(one)(keys)


@pytest.fixture(scope="module")
def trials():
    """Trial 0 (``PRNGKey(3)``): the noisy problem; trials 1-3 (``PRNGKey(7)`` split): the
    noise-free measurements of their own trials, which the calibration fits exactly.
    ``(q, T, q_ver)``, each with the 4 trials along its first axis."""
    keys = jnp.concatenate(
        [jax.random.PRNGKey(3)[None], jax.random.split(jax.random.PRNGKey(7), 3)]
    )
    q, T, q_ver, T_clean = (np.asarray(x) for x in _simulate(keys))
    T = np.concatenate([T[:1], T_clean[1:]])
    return q, T, q_ver


@pytest.fixture(scope="module")
def problem(trials):
    return tuple(x[0] for x in trials)


@jax.jit
def _reverse(q, T, q_ver, u):
    """For each trial, the gradient of ``u . identifiable`` (:func:`_identifiable` of the paper
    solver, ``throw=False``) with respect to ``(q, T)``, by reverse mode under ``vmap``."""

    def one(q, T, q_ver, u):
        def scalar(q, T):
            return u @ _identifiable(cj.calibrate_paper(ARM, q, T, throw=False), q_ver)

        return jax.grad(scalar, argnums=(0, 1))(q, T)

    return jax.vmap(one)(q, T, q_ver, u)


@pytest.fixture(scope="module")
def cotangents():
    """The cotangents of :func:`_reverse`: for the noisy problem random ones (the paper
    solver's reverse-mode check), for the exact fits the selector of ``errors[0, 0] + cost``."""
    u = np.zeros((4, 3 * 3 + 6 + 6 + 1))
    u[0] = np.random.default_rng(1).normal(size=u.shape[1])
    u[1:, 3 * 3] = u[1:, -1] = 1.0  # errors[0, 0] (after 3 tool positions) and the cost
    return u


@pytest.fixture(scope="module")
def reverse(trials, cotangents):
    """:func:`_reverse` of the trials, as numpy arrays."""
    return jax.tree.map(np.asarray, _reverse(*trials, jnp.asarray(cotangents)))


def _tangents(seed, q, T):
    """Random tangents of the module states and of the measured poses; the latter as twists
    ``xi`` (mm, rad), so that the poses stay rigid: ``T(h) = exp(h xi) T``."""
    rng = np.random.default_rng(seed)
    xi = rng.normal(size=T.shape[:-2] + (6,)) * np.array([1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3])
    return rng.normal(size=q.shape) * 1e-2, xi


def _identifiable(sol, q_ver):  # (3 * 3 tool positions, 6, 6, 1)
    """What the data determine: tool positions of the calibrated arm at held-out states, the
    base and tool errors, and the cost."""
    tool = cj.tool_pose(sol.calibrated_arm(ARM), q_ver)[:, :3, 3].ravel()
    return jnp.concatenate([tool, sol.errors[0], sol.errors[-1], sol.cost[None]])


def _along(f, q, T, dq, xi):
    """``h -> f(q + h dq, exp(h xi) T)``."""
    return lambda h: f(q + h * dq, lie.se3_exp(h * jnp.asarray(xi)) @ T)


def _assert_close(actual, desired, rtol=1e-6):
    actual, desired = np.asarray(actual), np.asarray(desired)
    np.testing.assert_allclose(actual, desired, rtol=rtol, atol=rtol * np.abs(desired).max())


def test_paper_solver_derivative(problem, reverse, cotangents):
    """Forward mode against central differences of the converged solver; reverse mode (under
    ``vmap``) against forward mode (``<u, J v>``); the nominal frames move the errors but no
    prediction."""
    q, T, q_ver = problem
    dq, xi = _tangents(0, q, T)

    def f(q, T, frames0=ARM.frames):
        return _identifiable(cj.calibrate_paper(ARM.with_frames(frames0), q, T), q_ver)

    # One compiled forward program for both directions: along the data (h) and along the
    # nominal frames (F), the tangents as arguments.
    @jax.jit
    def at(h, dh, dF):
        return jax.jvp(
            lambda h, F: _along(lambda q, T: f(q, T, F), q, T, dq, xi)(h), (h, ARM.frames), (dh, dF)
        )

    zeros, ones = jnp.zeros_like(ARM.frames), jnp.ones_like(ARM.frames)
    value, forward = at(0.0, 1.0, zeros)  # the value and forward derivative at h
    h = 1e-4
    _assert_close(forward, (at(h, 1.0, zeros)[0] - at(-h, 1.0, zeros)[0]) / (2 * h))
    assert np.abs(forward).max() > 1e-2  # the data do move the solution

    # <u, J v>: the gradient along the tangent (dq, d/dh exp(h xi) T = hat(xi) T)
    (g_q, g_T) = (g[0] for g in reverse)
    dT = np.asarray(lie.hat(jnp.asarray(xi))) @ np.asarray(T)
    reverse_along = np.sum(g_q * dq) + np.sum(g_T * dT)
    d_nominal = at(0.0, 0.0, ones)[1]
    _assert_close(reverse_along, cotangents[0] @ np.asarray(forward), rtol=1e-8)
    n_tool = 3 * q_ver.shape[0]
    assert np.abs(d_nominal[:n_tool]).max() == 0  # predictions: independent of the start
    assert np.abs(d_nominal[n_tool:-1]).max() > 0.5  # errors: measured against it


def test_weighted_solver_derivative(problem):
    """The whitening depends on the measured positions and on the stated noise: forward mode
    against central differences in all three; the cost against the envelope theorem."""
    q, T, q_ver = problem
    dq, xi = _tangents(2, q, T)

    def f(q, T, s=1.0):
        noise = cj.NoiseModel(0.08 * s, 1e-3 * s)
        return _identifiable(cj.calibrate_paper(ARM, q, T, noise), q_ver)

    def g(h):
        return _along(lambda q, T: f(q, T, 1.0 + 0.1 * h), q, T, dq, xi)(h)

    at = jax.jit(lambda h: jax.jvp(g, (h,), (1.0,)))
    h = 1e-4
    _assert_close(at(0.0)[1], (at(h)[0] - at(-h)[0]) / (2 * h))
    # d cost / d s = -2 cost / s for a common scale s of both stds
    c, dc = jax.jit(jax.value_and_grad(lambda s: f(q, T, s)[-1]))(1.0)
    np.testing.assert_allclose(dc, -2 * c, rtol=1e-6)


def _refined(q, T, frames, noise, steps=1):
    """The stationary point of the weighted least-squares cost ``|r|^2 / 2``, by Gauss-Newton
    steps from ``frames`` (close to it: one step converges) on an independent residual ``r``
    (:mod:`cdra_jax.calibration.model`, not the solvers' kernels; its Jacobian by
    ``jax.jacfwd``), and the largest component of the cost's gradient ``J^T r`` there."""

    def residual(d, frames):
        moved = lie.se3_exp(d.reshape(-1, 6)) @ frames
        Y = residual_twist(T, cj.tool_pose(ARM.with_frames(moved), q))
        return jnp.einsum("...ij,...j->...i", whitening(T, noise), Y).ravel()

    def gradient_and_jacobian(frames):
        J = jax.jacfwd(residual)(d0, frames)
        return J.T @ residual(d0, frames), J

    d0 = jnp.zeros(frames.shape[0] * 6, frames.dtype)
    for _ in range(steps):
        g, J = gradient_and_jacobian(frames)
        d = -jnp.linalg.pinv(J.T @ J, rtol=1e-10, hermitian=True) @ g
        frames = lie.se3_exp(d.reshape(-1, 6)) @ frames
    return frames, jnp.abs(gradient_and_jacobian(frames)[0]).max()


def test_lm_derivative_is_that_of_the_least_squares_optimum(problem):
    """LM's damped steps stop a little short of the optimum (finite differences of its output
    agree to ~3e-4 relative only); the implicit derivative is the optimum's, which finite
    differences of the optimum itself (refined by a Gauss-Newton step) confirm."""
    q, T, q_ver = problem
    dq, xi = _tangents(3, q, T)

    def tool(frames):
        return cj.tool_pose(ARM.with_frames(frames), q_ver)[:, :3, 3].ravel()

    def lm_tool(q, T):
        frames = cj.calibrate_lm(ARM, q, T, NOISE).frames
        return tool(frames), frames

    # LM's frames and the forward derivative of its tool positions, at h
    at = jax.jit(lambda h: jax.jvp(_along(lm_tool, q, T, dq, xi), (h,), (1.0,)))

    @jax.jit
    def optimum_tool(h, frames):
        frames, g = _refined(q + h * dq, lie.se3_exp(h * jnp.asarray(xi)) @ T, frames, NOISE)
        return tool(frames), g

    h = 1e-3
    (up, g_up), (down, g_down) = (optimum_tool(s, at(s)[0][1]) for s in (h, -h))
    assert max(g_up, g_down) < 1e-6  # stationary (whitened units; ~1e4 at the nominal model)
    _assert_close(at(0.0)[1][0], (up - down) / (2 * h))


def test_gradients_under_vmap_and_at_an_exact_fit(trials, reverse, cotangents):
    """Gradients of ``errors[0, 0] + cost`` by reverse mode under ``vmap`` at exact fits
    (noise-free trials): finite and nonzero; each trial's gradient is its own (the solver's
    batching is chunked, the rule per trial): the trials reversed give the gradients
    reversed."""
    g_q, g_T = reverse
    assert np.all(np.isfinite(g_T[1:])) and np.abs(g_T[1:]).max() > 1e-3
    assert np.all(np.isfinite(g_q[1:]))
    flipped = _reverse(*(x[::-1] for x in trials), jnp.asarray(cotangents[::-1]))
    np.testing.assert_array_equal(np.asarray(flipped[1]), g_T[::-1])
    np.testing.assert_array_equal(np.asarray(flipped[0]), g_q[::-1])


def test_robust_calibration_refuses_derivatives(problem):
    q, T, _ = problem
    with pytest.raises(ValueError, match="calibrate_robust is not differentiable"):
        jax.grad(lambda T: cj.calibrate_robust(ARM, q, T, NOISE).solution.cost)(T)
    with pytest.raises(ValueError, match="calibrate_robust is not differentiable"):
        jax.jvp(
            lambda s: cj.calibrate_robust(ARM, q, T, cj.NoiseModel(s, 1e-3)).weights,
            (0.08,),
            (1.0,),
        )
