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


def bending_deflection(
    arm: Arm, q: ArrayLike, j: int, payload_kg: ArrayLike = 0.0, *, split: bool = False
) -> Array:
    """Tip deflection ``(delta, theta) (..., 6)`` of link ``j`` per unit compliance ``1/(EI)``.

    With ``split``, ``(..., 6, 2)``: the part of the transverse forces (distal weights and own
    weight) and the part of the tip moment, whose sum is the deflection.

    See the module docstring; start frame of the link, mm and rad per 1/(N mm^2). The link
    must have a non-zero length (``LinkBending.missing`` reports it otherwise).
    """
    frames = jnp.asarray(arm.frames)
    L = jnp.linalg.norm(frames[j, :3, 3])
    F, M, P, a = link_tip_loads(arm, q, j, payload_kg)
    e = frames[j, :3, 3] / L
    e = e.astype(F.dtype)
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
    moment = jnp.concatenate([jnp.cross(Mt, e) * L**2 / 2.0, Mt * L], axis=-1)
    if split:
        return jnp.stack([force, moment], axis=-1)
    return force + moment


def world_gravity_direction(arm: Arm, q: ArrayLike, j: int) -> Array:
    """Unit gravity direction in the start frame of fixed frame ``j`` (world for ``j = 0``)."""
    q = jnp.asarray(q)
    g = jnp.asarray(arm.gravity, q.dtype)
    g = g / jnp.linalg.norm(g)
    if j == 0:
        return jnp.broadcast_to(g, q.shape[:-1] + (3,))
    _, after = chain(jnp.asarray(arm.frames, q.dtype), module_poses(arm, q))
    return jnp.einsum("...ji,j->...i", lie.rotation(after[..., j - 1, :, :]), g)
