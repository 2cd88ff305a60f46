"""Gravity loads on the links (fixed transforms) of the arm, for the bending model.

The module loads (torques about each module's centre, cable tensions) come from
:mod:`cdra_jax.modules.statics`; this file adds what a link carries. Link ``j`` is the fixed
transform ``F_j = [R_j, p_j]`` from the platform of module ``j - 1`` (its *start* frame) to the
base of module ``j`` (its *tip*); it is modelled as a straight cantilever of length
``L = |p_j|`` along ``e = p_j / L``, clamped at the start. It carries

* at its tip, the weight of every body distal to it (the bodies moved by modules ``j .. K-1``
  and the payload at the tool origin) as a force ``F`` (N) and a moment ``M`` (N mm) about the
  tip;
* along its length, its own body (moved by module ``j - 1``: ``mass`` kg at ``com`` mm in the
  start frame), as a point load ``P`` at ``a = clip(com . e, 0, L)``.

Euler-Bernoulli cantilever formulas (only the components transverse to ``e`` bend the link;
axial force and torsion are ignored), per unit bending compliance ``c = 1 / (E I)``
(1/(N mm^2)), in the start frame::

    delta = F_t L^3 / 3 + (M_t x e) L^2 / 2 + P_t a^2 (3 L - a) / 6       (mm per unit c)
    theta = (e x F_t) L^2 / 2 + M_t L + (e x P_t) a^2 / 2                 (rad per unit c)
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from .. import lie
from ..arm import Arm, chain, module_poses
from ..compilation import compiled_when_eager, eager_program


def _mass_properties(arm: Arm, dtype) -> tuple[Array, Array]:
    mass = jnp.asarray([0.0 if m.mass is None else m.mass for m in arm.modules], dtype)
    com = jnp.stack(
        [jnp.zeros(3, dtype) if m.com is None else jnp.asarray(m.com, dtype) for m in arm.modules]
    )
    return mass, com


def link_tip_loads(arm: Arm, q: ArrayLike, j: int, payload_kg: ArrayLike = 0.0) -> tuple:
    """Loads on link ``j`` (``1 <= j <= K - 1``), in its start frame.

    Args:
        arm: the arm (masses, centres of mass, ``arm.gravity`` m/s^2).
        q: ``(..., dof)`` module states.
        j: index of the fixed transform (``arm.frame_names[j]``).
        payload_kg: payload at the tool origin, kg, scalar or ``(...)``.

    Returns:
        ``(F (..., 3) N, M (..., 3) N mm, P (..., 3) N, a (...) mm)``: tip force and moment of
        the distal weights, own weight and its distance along the link.
    """
    k = len(arm.modules)
    if not 1 <= j <= k - 1:
        raise ValueError(f"link index must be between 1 and {k - 1} (an inner frame), got {j}")
    return eager_program(_link_tip_loads, j)(arm, q, payload_kg)


def _link_tip_loads(j: int, arm: Arm, q: ArrayLike, payload_kg: ArrayLike) -> tuple:
    k = len(arm.modules)
    q = jnp.asarray(q)
    dtype = q.dtype
    tool, after = chain(jnp.asarray(arm.frames, dtype), module_poses(arm, q))
    frames = jnp.asarray(arm.frames, dtype)
    start = after[..., j - 1, :, :]
    tip = (start @ frames[j])[..., :3, 3]
    mass, com = _mass_properties(arm, dtype)
    g = jnp.asarray(arm.gravity, dtype)
    payload = jnp.asarray(payload_kg, dtype)
    F = payload[..., None] * g
    M = jnp.cross(tool[..., :3, 3] - tip, payload[..., None] * g)
    for b in range(j, k):
        x = jnp.einsum("...ij,j->...i", after[..., b, :3, :3], com[b]) + after[..., b, :3, 3]
        F = F + mass[b] * g
        M = M + jnp.cross(x - tip, mass[b] * g)
    Rs = start[..., :3, :3]
    to_start = lambda v: jnp.einsum("...ji,...j->...i", Rs, v)
    P = mass[j - 1] * to_start(jnp.broadcast_to(g, F.shape))
    e = frames[j, :3, 3] / jnp.linalg.norm(frames[j, :3, 3])
    a = jnp.clip(jnp.dot(com[j - 1], e), 0.0, jnp.linalg.norm(frames[j, :3, 3]))
    return to_start(F), to_start(M), P, jnp.broadcast_to(a, P.shape[:-1])


def _link_axis(arm: Arm, j: int, dtype) -> tuple[Array, Array]:
    """``(L, e)``: length (mm) and unit direction (start frame) of link ``j``."""
    p = jnp.asarray(arm.frames, dtype)[j, :3, 3]
    L = jnp.linalg.norm(p)
    return L, p / L


def _tip_moment_deflection(Mt: Array, e: Array, L: Array) -> Array:
    """``(delta, theta) (..., 6)`` of a cantilever of length ``L`` along ``e`` per unit
    compliance under the transverse tip moment ``Mt (..., 3)``: ``(Mt x e) L^2 / 2``,
    ``Mt L``."""
    return jnp.concatenate([jnp.cross(Mt, e) * L**2 / 2.0, Mt * L], axis=-1)


def bending_deflection(
    arm: Arm, q: ArrayLike, j: int, payload_kg: ArrayLike = 0.0, *, split: bool = False
) -> Array:
    """Tip deflection ``(delta, theta) (..., 6)`` of link ``j`` per unit compliance ``1/(EI)``.

    With ``split``, ``(..., 6, 2)``: the part of the transverse forces (distal weights and own
    weight) and the part of the tip moment, whose sum is the deflection.

    See the module docstring; start frame of the link, mm and rad per 1/(N mm^2). The link
    must have a non-zero length (``LinkBending.missing`` reports it otherwise).
    """
    k = len(arm.modules)
    if not 1 <= j <= k - 1:
        raise ValueError(f"link index must be between 1 and {k - 1} (an inner frame), got {j}")
    return eager_program(_bending_deflection, j, split)(arm, q, payload_kg)


def _bending_deflection(j: int, split: bool, arm: Arm, q: ArrayLike, payload_kg: ArrayLike):
    F, M, P, a = _link_tip_loads(j, arm, q, payload_kg)
    L, e = _link_axis(arm, j, F.dtype)
    perp = lambda v: v - jnp.einsum("...i,i->...", v, e)[..., None] * e
    Ft, Mt, Pt = perp(F), perp(M), perp(P)
    a = a[..., None]
    force = jnp.concatenate(
        [
            Ft * L**3 / 3.0 + Pt * a**2 * (3 * L - a) / 6.0,
            jnp.cross(e, Ft) * L**2 / 2.0 + jnp.cross(e, Pt) * a**2 / 2.0,
        ],
        axis=-1,
    )
    moment = _tip_moment_deflection(Mt, e, L)
    if split:
        return jnp.stack([force, moment], axis=-1)
    return force + moment


# ----------------------------------------------------------------- lumped gravity moments

MomentTerm = tuple[int, str]
"""One lumped gravity moment: ``(body, component)``, the module whose body it belongs to and
``"x"``, ``"y"``, ``"z"`` (an axis of that module's platform frame), ``"u"``, ``"v"`` (the two
directions across its joint axis, :func:`across_axis`) or ``"travel"`` (the distal mass carried
along a prismatic module's travel)."""


@compiled_when_eager
def across_axis(axis: ArrayLike) -> Array:
    """``(2, 3)``: the directions ``u``, ``v`` across a unit joint axis ``a``: ``u`` is the
    coordinate axis least aligned with ``a`` (the first of a tie) made perpendicular to it,
    ``v = a x u`` (for ``a = z``: ``u = x``, ``v = y``)."""
    a = jnp.asarray(axis)
    e = jnp.eye(3, dtype=a.dtype)[jnp.argmin(jnp.abs(a))]
    u = e - jnp.dot(e, a) * a
    u = u / jnp.linalg.norm(u)
    return jnp.stack([u, jnp.cross(a, u)])


def moment_terms(
    arm: Arm, first: int, *, axial: bool = False, travel_first: bool = False
) -> tuple[MomentTerm, ...]:
    """The lumped gravity moments of the bodies ``first .. K-1`` that gravity can tell apart.

    The first moment ``sum_b m_b (x_b - o)`` of the distal bodies about a point ``o`` of
    module ``first`` is, with ``w_b = h_b + M_b p_b`` (``h_b = m_b com_b``: the body's own
    moment; ``M_b``: the mass beyond module ``b``; ``p_b``: the next fixed transform's
    translation) constant in the platform frame ``P_b`` of module ``b``,
    ``sum_b R_b w_b + sum_c M_c t_c`` (``R_b``: that frame's orientation; ``t_c``: the travel of
    a prismatic module ``c``). The part of ``w_b`` along a revolute module's axis does not turn
    with it and is one with the moment of the body before; a prismatic module does not turn, so
    its whole ``w_b`` is. What is left, per body (its module's kind):

    * ``first``: ``x, y, z`` (all three), or ``u, v`` with ``axial`` (a torque about the
      module's own axis does not see the part along it);
    * a later revolute module: ``u, v``; spherical: ``x, y, z``; prismatic: ``travel``;
    * with ``travel_first``, a prismatic ``first`` adds its ``travel`` (the point ``o`` is
      then its base origin, not its platform origin);
    * where no module before ``first`` turns (it is the first, or they are prismatic),
      gravity is fixed in its base frame: the part of its moment that does not turn with it
      (all of it for a prismatic module, the part along the axis for a revolute one) has a
      constant torque, a constant rotation of the platform that the frame errors absorb
      exactly; a revolute ``first`` keeps ``u, v`` only, a prismatic one nothing.

    These are the combinations identifiable from a deflection linear in the gravity torque
    on an arm of general geometry (special geometry, e.g. a joint axis along a link, can make
    one of them coincide with another; the fits are rank-revealing).
    """
    out: list[MomentTerm] = []
    kinds = [m.kind for m in arm.modules]
    for b in range(first, len(arm.modules)):
        kind = kinds[b]
        if b == first:
            if travel_first and kind == "prismatic":
                out.append((b, "travel"))
            comps: tuple[str, ...] = ("u", "v") if axial else ("x", "y", "z")
            if not travel_first and set(kinds[:first]) <= {"prismatic"}:
                # gravity is fixed in the module's base frame: what does not turn with the
                # module gives a constant torque, which the frame errors absorb exactly
                comps = {"prismatic": (), "revolute": ("u", "v")}.get(kind, comps)
        elif kind == "revolute":
            comps = ("u", "v")
        elif kind == "spherical":
            comps = ("x", "y", "z")
        else:
            comps = ("travel",)
        out += [(b, c) for c in comps]
    return tuple(out)


def moment_torques(arm: Arm, q: ArrayLike, terms: tuple[MomentTerm, ...]) -> Array:
    """World torques ``(..., 3, n)`` of unit gravity ``g / |g|`` per unit lumped moment.

    A body term ``(b, c)`` is the moment ``R_b d`` (``d`` its direction in the platform frame
    of module ``b``): torque ``R_b d x g / |g|`` per kg mm; a ``travel`` term is the travel
    ``t_b`` of prismatic module ``b`` (world frame): ``t_b x g / |g|`` per kg.
    Multiplied by a compliance and ``|g|`` (N/kg), the lumped values are the products that a
    gravity-driven deflection identifies (see :func:`moment_terms`).
    """
    return eager_program(_moment_torques, tuple(terms))(arm, q)


def _moment_torques(terms: tuple[MomentTerm, ...], arm: Arm, q: ArrayLike) -> Array:
    q = jnp.asarray(q)
    poses = module_poses(arm, q)
    _, after = chain(jnp.asarray(arm.frames, q.dtype), poses)
    g = jnp.asarray(arm.gravity, q.dtype)
    g = g / jnp.linalg.norm(g)
    eye = jnp.eye(3, dtype=q.dtype)
    cols = []
    for b, c in terms:
        R = after[..., b, :3, :3]
        if c == "travel":
            r = jnp.einsum("...ij,...j->...i", R, poses[..., b, :3, 3])
        else:
            d = (
                eye["xyz".index(c)]
                if c in "xyz"
                else across_axis(jnp.asarray(arm.modules[b].axis, q.dtype))["uv".index(c)]
            )
            r = jnp.einsum("...ij,j->...i", R, d)
        cols.append(jnp.cross(r, g))
    return jnp.stack(cols, axis=-1)


def lumped_bending_deflection(
    arm: Arm, q: ArrayLike, j: int, terms: tuple[MomentTerm, ...]
) -> Array:
    """Tip deflection ``(delta, theta) (..., 6, 1 + n)`` of link ``j`` (start frame) per unit
    lumped parameter, without masses.

    Columns: the weights it carries bend it as a tip load along the transverse unit gravity
    ``gt``, ``(2 L gt / 3, e x gt)`` per rad of tip rotation (``c |g| M L^2 / 2``; the link's
    own weight counts as part of it: a uniform link's own weight would give ``3 L / 4`` instead
    of ``2 L / 3``); then per lumped moment of ``terms`` (:func:`moment_torques`, about the tip)
    the tip-moment deflection per unit ``c |g| w L`` (rad; ``c = 1/(E I)``, ``L`` the link
    length). A rigid rotation at the link's start (a compliant joint) has ``delta = L theta``:
    the cantilever's shapes tell the two apart.
    """
    return eager_program(_lumped_bending_deflection, j, tuple(terms))(arm, q)


def _lumped_bending_deflection(
    j: int, terms: tuple[MomentTerm, ...], arm: Arm, q: ArrayLike
) -> Array:
    q = jnp.asarray(q)
    L, e = _link_axis(arm, j, q.dtype)
    g = _world_gravity_direction(j, arm, q)
    gt = g - jnp.einsum("...i,i->...", g, e)[..., None] * e
    weight = jnp.concatenate([2.0 * L * gt / 3.0, jnp.cross(e, gt)], -1)[..., None]
    _, after = chain(jnp.asarray(arm.frames, q.dtype), module_poses(arm, q))
    M = jnp.einsum("...ji,...jn->...in", after[..., j - 1, :3, :3], _moment_torques(terms, arm, q))
    Mt = jnp.moveaxis(M - jnp.einsum("...in,i->...n", M, e)[..., None, :] * e[:, None], -1, -2)
    moment = jnp.moveaxis(_tip_moment_deflection(Mt, e, L) / L, -2, -1)
    return jnp.concatenate([weight, moment], axis=-1)


def world_gravity_direction(arm: Arm, q: ArrayLike, j: int) -> Array:
    """Unit gravity direction in the start frame of fixed frame ``j`` (world for ``j = 0``)."""
    return eager_program(_world_gravity_direction, j)(arm, q)


def _world_gravity_direction(j: int, arm: Arm, q: ArrayLike) -> Array:
    q = jnp.asarray(q)
    g = jnp.asarray(arm.gravity, q.dtype)
    g = g / jnp.linalg.norm(g)
    if j == 0:
        return jnp.broadcast_to(g, q.shape[:-1] + (3,))
    _, after = chain(jnp.asarray(arm.frames, q.dtype), module_poses(arm, q))
    return jnp.einsum("...ji,j->...i", lie.rotation(after[..., j - 1, :, :]), g)
