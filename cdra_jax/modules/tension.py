"""Tension closure of CDPM modules: structure matrix, exact closure test, margin, feasible sampler.

Structure matrix. A cable pulling with tension ``t_i >= 0`` along ``u_i`` (from its platform
attachment ``p_i`` towards its base attachment, see :mod:`.cables`) exerts on the platform the
torque ``(p_i x u_i) t_i`` about the module origin. The structure matrix ``A (d, n)`` of a module
maps tensions to the generalised force on the platform, in the module base frame:

* spherical (d = 3): column ``i`` is ``p_i x u_i = (R a_i) x u_i`` (mm, i.e. N mm per N);
* revolute (d = 1): ``axis . (p_i x u_i)``, the torque about the joint axis (mm);
* prismatic (d = 1): ``axis . u_i``, the force along the axis (dimensionless).

The joint itself carries every other force and moment component.

Tension closure. A pose admits strictly positive tensions for *any* load ``w`` (``A t = w``,
``t > 0``) iff the columns of ``A`` positively span ``R^d``: ``A`` has full row rank and no
hyperplane through the origin has all columns on one side (no ``c != 0`` with ``c . A_i >= 0``
for every ``i``). If the columns do not positively span, the cone ``{c : A^T c >= 0}`` is a
pointed polyhedral cone whose extreme rays are orthogonal to ``d - 1`` linearly independent
columns, so for d = 3 the candidate normals ``+-(A_i x A_j)`` of every pair of columns decide
exactly; for d = 2 the perpendiculars ``+-rot90(A_i)``; for d = 1 the columns must take both
signs. This is what :func:`tension_closure` evaluates: a fixed number of dot products, no
iterative solver, jit- and vmap-able.

Margin. :func:`hull_margin` is the signed distance from the origin to the boundary of the convex
hull of the columns (positive inside): the largest ``r`` such that every generalised force of
norm ``r`` is produced by tensions ``t >= 0`` summing to 1 N, i.e. the torque (N mm) available in
the weakest direction per newton of total cable tension. It is positive exactly when the pose
has tension closure and goes to zero at the boundary of the workspace (a cable torque vanishing
or the columns becoming coplanar). It is computed exactly as the minimum, over a finite set of
unit directions ``c``, of the support ``max_i c . A_i``: the facet normals of the hull (triples
of columns for d = 3), the directions to the nearest points of its edges and vertices, and the
normals of planes through the origin (for flat hulls). :func:`closure_margin`
divides it by the module's largest lever arm ``max_i |a_i|`` (the most torque one newton of
tension can give), so that a single threshold fits modules of any size:
:data:`DEFAULT_MIN_MARGIN` = 0.05 rejects poses whose weakest direction gets less than 5 % of
the best possible lever arm.
"""

from __future__ import annotations

import functools
import itertools

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax import Array, lax
from jax.typing import ArrayLike

from ..arm import Arm, Module, sample_states
from ..compilation import batched_like, compiled_when_eager_args
from .cables import cable_vectors, require_cables

DEFAULT_MIN_MARGIN = 0.05
"""Default smallest :func:`closure_margin` of a pose accepted by :func:`sample_feasible_states`."""

_RTOL = 1e-9
_BLOCK = 8  # draws per closure-test block of sample_feasible_states (for small m)


@compiled_when_eager_args("state")
def structure_matrix(module: Module, state: ArrayLike) -> Array:
    """Structure matrix ``A (..., d, n)`` of ``module`` at ``state (..., dof)``, base frame.

    Columns: ``(R a_i) x u_i`` (spherical, mm), ``axis . ((R a_i) x u_i)`` (revolute, mm) or
    ``axis . u_i`` (prismatic, dimensionless); see the module docstring.
    """
    p, u, _ = cable_vectors(module, state)
    axis = jnp.asarray(module.axis, p.dtype)
    if module.kind == "spherical":
        return jnp.swapaxes(jnp.cross(p, u), -1, -2)
    if module.kind == "revolute":
        return jnp.einsum("...ni,i->...n", jnp.cross(p, u), axis)[..., None, :]
    return jnp.einsum("...ni,i->...n", u, axis)[..., None, :]


def _check_d(A: Array) -> int:
    d = A.shape[-2]
    if d not in (1, 2, 3):
        raise ValueError(f"structure matrix must have 1, 2 or 3 rows (d), got shape {A.shape}")
    return d


def _unit(v: Array, eps: Array) -> tuple[Array, Array]:
    """``v / |v|`` and whether ``|v| > eps`` (invalid rows are returned as zeros)."""
    n = jnp.linalg.norm(v, axis=-1)
    ok = n > eps
    return v / jnp.where(ok, n, 1.0)[..., None] * ok[..., None], ok


@compiled_when_eager_args("A", "rtol")
def tension_closure(A: ArrayLike, rtol: float = _RTOL) -> Array:
    """Exact test: do the columns of ``A (..., d, n)`` positively span ``R^d``? ``(...)`` bool.

    True iff every generalised force is balanced by strictly positive tensions (see the module
    docstring for the method). ``rtol`` is the relative tolerance of the rank and sign tests.
    """
    A = jnp.asarray(A)
    d = _check_d(A)
    n = A.shape[-1]
    cols = jnp.swapaxes(A, -1, -2)  # (..., n, d)
    norms = jnp.linalg.norm(cols, axis=-1)
    scale = jnp.max(norms, axis=-1)
    tol = rtol * scale
    if d == 1:
        x = cols[..., 0]
        return jnp.any(x > tol[..., None], axis=-1) & jnp.any(x < -tol[..., None], axis=-1)
    if d == 2:
        normals = jnp.stack([-cols[..., 1], cols[..., 0]], axis=-1)  # (..., n, 2)
        c, valid = _unit(normals, tol[..., None])
        rank_ok = jnp.any(valid, axis=-1)  # rank 1 is caught by the separation test
    else:
        if n < 2:
            return jnp.zeros(A.shape[:-2], bool)
        i, j = np.array(list(itertools.combinations(range(n), 2))).T
        cr = jnp.cross(cols[..., i, :], cols[..., j, :])
        c, valid = _unit(cr, (tol * scale)[..., None])
        # Rank 1 or less leaves no candidate normal; rank 2 puts every column on the plane
        # normal to a candidate, which the separation test below catches.
        rank_ok = jnp.any(valid, axis=-1)
    c = jnp.concatenate([c, -c], axis=-2)
    valid = jnp.concatenate([valid, valid], axis=-1)
    dots = jnp.einsum("...ck,...nk->...cn", c, cols)  # (..., candidates, n)
    separating = valid & jnp.all(dots >= -tol[..., None, None], axis=-1)
    return rank_ok & ~jnp.any(separating, axis=-1)


@compiled_when_eager_args("A")
def hull_margin(A: ArrayLike) -> Array:
    """Signed distance from the origin to the boundary of the hull of the columns of ``A``.

    ``A (..., d, n)`` with d in {1, 2, 3}; returns ``(...)`` in the units of ``A`` (mm for the
    torque rows of spherical and revolute modules): positive iff the pose has tension closure,
    the generalised force available in the weakest direction per newton of total tension.
    Negative values are minus the distance from the origin to the hull.
    """
    A = jnp.asarray(A)
    d = _check_d(A)
    n = A.shape[-1]
    cols = jnp.swapaxes(A, -1, -2)  # (..., n, d)
    if d == 1:
        x = cols[..., 0]
        return jnp.minimum(jnp.max(x, axis=-1), -jnp.min(x, axis=-1))
    scale = jnp.max(jnp.linalg.norm(cols, axis=-1), axis=-1)
    eps = 1e-12 * scale
    cands, valids = [], []
    # Vertices: the direction away from each column.
    v, ok = _unit(-cols, eps[..., None])
    cands.append(v)
    valids.append(ok)
    if n >= 2:
        i, j = np.array(list(itertools.combinations(range(n), 2))).T
        e = cols[..., j, :] - cols[..., i, :]
        if d == 2:
            # Edges are the facets: both normals.
            nrm = jnp.stack([-e[..., 1], e[..., 0]], axis=-1)
            c, ok = _unit(nrm, eps[..., None] * scale[..., None])
            cands += [c, -c]
            valids += [ok, ok]
        else:
            # Nearest point of each edge segment to the origin.
            ee = jnp.sum(e * e, axis=-1)
            t = jnp.clip(-jnp.sum(cols[..., i, :] * e, axis=-1) / jnp.where(ee > 0, ee, 1.0), 0, 1)
            near = cols[..., i, :] + t[..., None] * e
            c, ok = _unit(-near, eps[..., None])
            cands.append(c)
            valids.append(ok)
    if d == 3:
        # Planes through the origin: normals of column pairs, and perpendiculars of each
        # column. They are the facets of a flat hull (columns of rank 2 or 1), whose margin is
        # then 0 (origin inside the flat hull) or negative.
        perp = jnp.cross(cols[..., :, None, :], jnp.eye(3, dtype=cols.dtype)).reshape(
            cols.shape[:-2] + (3 * n, 3)
        )
        if n >= 2:
            i, j = np.array(list(itertools.combinations(range(n), 2))).T
            perp = jnp.concatenate([perp, jnp.cross(cols[..., i, :], cols[..., j, :])], axis=-2)
        c, ok = _unit(perp, eps[..., None] * scale[..., None])
        cands += [c, -c]
        valids += [ok, ok]
    if d == 3 and n >= 3:
        i, j, k = np.array(list(itertools.combinations(range(n), 3))).T
        nrm = jnp.cross(cols[..., j, :] - cols[..., i, :], cols[..., k, :] - cols[..., i, :])
        c, ok = _unit(nrm, eps[..., None] * scale[..., None])
        cands += [c, -c]
        valids += [ok, ok]
    c = jnp.concatenate(cands, axis=-2)
    valid = jnp.concatenate(valids, axis=-1)
    support = jnp.max(jnp.einsum("...ck,...nk->...cn", c, cols), axis=-1)
    margin = jnp.min(jnp.where(valid, support, jnp.inf), axis=-1)
    # No candidate at all: every column is at the origin, the hull is the origin itself, whose
    # distance to it is 0 (not the inf of an empty minimum).
    return jnp.where(jnp.any(valid, axis=-1), margin, 0.0)


def _closure_and_margin_3(A: Array, rtol: float = _RTOL) -> tuple[Array, Array]:
    """:func:`tension_closure` and, where it holds, :func:`hull_margin` of ``A (..., 3, n)``.

    The same verdict (same candidate normals ``+-(A_i x A_j)``, same tolerances) and, at poses
    with tension closure, the same margin: the origin is then inside a full-dimensional hull, so
    the support function is smallest at a facet normal and only the triple normals are needed.
    Where the verdict is false the second output is no hull margin. The arrays are laid out
    ``(candidates, ...)`` per vector component, with the dot products against the ``n`` columns
    unrolled, so that XLA fuses each stage into one pass over the batch instead of materialising
    ``(..., candidates, n, 3)`` products: several times faster, and far smaller, on the large
    batches of :func:`sample_feasible_states` inside the sweeps.
    """
    n = A.shape[-1]
    x, y, z = jnp.moveaxis(A, (-2, -1), (0, 1))  # each (n, ...): batch contiguous
    scale = jnp.sqrt(jnp.max(x * x + y * y + z * z, axis=0))  # (...)
    tol = rtol * scale

    def unit_dots(cx, cy, cz, threshold):
        """Validity ``(C, ...)`` and the ``n`` dots ``(C, ...)`` of the unit normals ``c``."""
        nrm = jnp.sqrt(cx * cx + cy * cy + cz * cz)
        valid = nrm > threshold
        inv = 1.0 / jnp.where(valid, nrm, 1.0)
        return valid, [(cx * x[k] + cy * y[k] + cz * z[k]) * inv for k in range(n)]

    i, j = np.array(list(itertools.combinations(range(n), 2))).T
    valid, dots = unit_dots(
        y[i] * z[j] - z[i] * y[j], z[i] * x[j] - x[i] * z[j], x[i] * y[j] - y[i] * x[j], tol * scale
    )
    ahead = functools.reduce(jnp.logical_and, [d >= -tol for d in dots])
    behind = functools.reduce(jnp.logical_and, [d <= tol for d in dots])
    closed = jnp.any(valid, axis=0) & ~jnp.any(valid & (ahead | behind), axis=0)
    i, j, k = np.array(list(itertools.combinations(range(n), 3))).T
    ax, ay, az = x[j] - x[i], y[j] - y[i], z[j] - z[i]
    bx, by, bz = x[k] - x[i], y[k] - y[i], z[k] - z[i]
    valid, dots = unit_dots(
        ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx, 1e-12 * scale * scale
    )
    support = jnp.minimum(functools.reduce(jnp.maximum, dots), -functools.reduce(jnp.minimum, dots))
    return closed, jnp.min(jnp.where(valid, support, jnp.inf), axis=0)


def lever_scale(module: Module) -> float | Array:
    """Largest generalised force per newton of tension: ``max_i |a_i|`` mm (1 for prismatic)."""
    _, a, _ = require_cables(module)
    if module.kind == "prismatic":
        return 1.0
    return jnp.max(jnp.linalg.norm(a, axis=-1))


@compiled_when_eager_args("state")
def closure_margin(module: Module, state: ArrayLike) -> Array:
    """Dimensionless tension-closure margin ``hull_margin / lever_scale`` at ``state``: ``(...)``.

    Positive iff the pose has tension closure; at most 1.
    """
    return hull_margin(structure_matrix(module, state)) / lever_scale(module)


@compiled_when_eager_args("state")
def has_tension_closure(module: Module, state: ArrayLike) -> Array:
    """Exact tension-closure verdict of ``module`` at ``state (..., dof)``: ``(...)`` bool."""
    return tension_closure(structure_matrix(module, state))


@compiled_when_eager_args("q")
def arm_closure_margins(arm: Arm, q: ArrayLike) -> Array:
    """:func:`closure_margin` of every module at flat states ``q (..., dof)``: ``(..., K)``.

    Modules without cables impose no tension condition and report ``+inf``.
    """
    q = jnp.asarray(q)
    out = []
    for m, qi in zip(arm.modules, arm.split_state(q), strict=True):
        if m.n_cables:
            out.append(closure_margin(m, qi))
        else:
            out.append(jnp.full(q.shape[:-1], jnp.inf, q.dtype))
    return jnp.stack(out, axis=-1)


@compiled_when_eager_args("q", "min_margin")
def arm_tension_closure(arm: Arm, q: ArrayLike, min_margin: float | ArrayLike = 0.0) -> Array:
    """Whether every module has tension closure (and margin above ``min_margin``): ``(...)``.

    With ``min_margin = 0`` this is the exact :func:`tension_closure` verdict of every module
    with cables; with a positive ``min_margin`` it also requires :func:`closure_margin` above it.
    """
    q = jnp.asarray(q)
    ok = jnp.ones(q.shape[:-1], bool)
    for m, qi in zip(arm.modules, arm.split_state(q), strict=True):
        if m.n_cables:
            A = structure_matrix(m, qi)
            if A.shape[-2] == 3 and A.shape[-1] >= 3:
                closed, margin = _closure_and_margin_3(A)  # the same verdicts, fused
            else:
                closed, margin = tension_closure(A), hull_margin(A)
            ok = ok & closed & (margin / lever_scale(m) > min_margin)
    return ok


@compiled_when_eager_args("key", "min_margin")
def sample_feasible_states(
    key: Array,
    arm: Arm,
    m: int,
    dtype=None,
    *,
    min_margin: float | ArrayLike = DEFAULT_MIN_MARGIN,
    oversample: int = 4,
    throw: bool = True,
) -> Array:
    """``m`` module states uniform within the joint limits and with tension closure: ``(m, dof)``.

    Same signature as :func:`cdra_jax.simulation.sample_states` (usable as ``sampler=``): draws
    ``oversample * m + 16`` states with it, rejects those where a module lacks tension closure or
    has :func:`closure_margin` at or below ``min_margin``, and returns the first ``m`` accepted
    ones in draw order (so the result is uniform over the feasible part of the joint box).
    Jit- and vmap-able; raises at run time (``equinox`` runtime error) when fewer than ``m`` of
    the draws are feasible: raise ``oversample`` or lower ``min_margin``. With ``throw=False``
    it returns NaN states instead (per batch element under ``vmap``), so that a solver given
    them ends with a ``nonfinite`` result for that trial alone; the program then holds no host
    callback, which lets several devices run it at the same time (the sweeps do this).

    The draws are tested in draw order, a block of ``max(8, ceil(m / 8))`` at a time (a
    ``lax.while_loop``), until ``m`` are accepted: a model whose joint box is mostly feasible
    pays for about ``m / feasible fraction`` closure tests instead of ``oversample * m + 16``,
    and a vmapped batch (the sweeps: thousands of trials at once) holds the intermediates of
    one small block per trial. The result is the same as testing every draw (the first ``m``
    feasible draws lie in the tested blocks). Under ``vmap`` the loop runs as many blocks as the
    batch element that needs the most.
    """
    if oversample < 1:
        raise ValueError(f"oversample must be a positive integer, got {oversample}")
    n = oversample * m + 16
    cand = sample_states(key, arm, n, dtype)
    block = min(n, max(_BLOCK, -(-m // _BLOCK)))
    blocks = -(-n // block)
    padded = jnp.concatenate([cand, jnp.broadcast_to(cand[:1], (blocks * block - n, arm.dof))])

    def more(carry):
        b, ok = carry
        return (b < blocks) & (jnp.sum(ok) < m)

    def test_block(carry):
        b, ok = carry
        q = lax.dynamic_slice_in_dim(padded, b * block, block)
        ok = lax.dynamic_update_slice_in_dim(
            ok, arm_tension_closure(arm, q, min_margin), b * block, 0
        )
        return b + 1, ok

    # Verdicts batched from the start under vmap (a third less tracing; see batched_like).
    none_yet = batched_like(cand[0, 0], jnp.zeros(blocks * block, bool))
    _, ok = lax.while_loop(more, test_block, (0, none_yet))
    ok = ok[:n]
    out = cand[jnp.flatnonzero(ok, size=m)]  # the first m accepted, in draw order
    if not throw:
        return jnp.where(jnp.sum(ok) < m, jnp.nan, out)
    return eqx.error_if(
        out,
        jnp.sum(ok) < m,
        "sample_feasible_states: fewer than m of the oversample * m + 16 drawn states have tension "
        "closure with the requested margin; raise oversample or lower min_margin",
    )


@compiled_when_eager_args("key", "min_margin")
def feasible_fraction(key: Array, arm: Arm, n: int = 10000, min_margin: float = 0.0) -> Array:
    """Fraction of ``n`` uniform draws in the joint box that :func:`arm_tension_closure` accepts."""
    return jnp.mean(arm_tension_closure(arm, sample_states(key, arm, n), min_margin))


__all__ = [
    "DEFAULT_MIN_MARGIN",
    "arm_closure_margins",
    "arm_tension_closure",
    "closure_margin",
    "feasible_fraction",
    "has_tension_closure",
    "hull_margin",
    "lever_scale",
    "sample_feasible_states",
    "structure_matrix",
    "tension_closure",
]
