"""The extended forward model shared by every candidate effect: features, parameters, candidates.

Every effect of the vocabulary (:mod:`.effects`) is a small, differentiable extension of the
geometric chain of Eq. 1 that is *linear in its physical parameters at the level of the
corrections* (module-state offsets and small twists), while the tool pose stays the exact,
nonlinear product of exponentials. An effect turns the data (module states, auxiliary columns,
model masses and cables) into :class:`Features`, per pose and per parameter:

* ``state (m, dof, p)``: additive offsets of the flat module state ``q`` (rad or mm);
* ``module_twist (m, K, 6, p)``: left-multiplied twists ``(v, w)`` of each module's platform
  pose, in the module base frame (``M_i -> exp(hat(xi_i)) M_i(q_i + dq_i)``);
* ``frame_deflection (m, K+1, 6, p)``: end deflections ``(delta (mm), theta (rad))`` of each
  fixed transform ``F_j = [R_j, p_j]`` in its start frame, ``F_j -> [exp(hat(theta)) R_j,
  p_j + delta]`` (a bent link, a drifting mount).

With parameters ``theta (p,)`` the corrections are ``features @ theta`` and
:func:`corrected_tool_pose` composes them into Eq. 1. ``theta = 0`` gives the geometric model
exactly (``exp(0) = I``, zero offsets). Features of several candidates concatenate along ``p``,
so that one compiled program evaluates (and ``jax.jacfwd`` differentiates) all of them at once.
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from .. import lie
from ..arm import Arm, chain, module_poses
from ..compilation import compiled_when_eager, eager_program


@dataclass(frozen=True)
class ParameterSpec:
    """One physical parameter of an effect.

    Attributes:
        name: short name, e.g. ``"compliance"`` or ``"half_band_rx"``.
        unit: its unit, e.g. ``"rad/(N*mm)"``.
        low, high: the physically plausible range (a fitted value outside it is flagged).
        description: what it is, in words.
    """

    name: str
    unit: str
    low: float
    high: float
    description: str = ""


class Features(eqx.Module):
    """Per-pose, per-parameter corrections of one or more candidates (see the module docstring).

    Attributes:
        state: ``(m, dof, p)`` module-state offsets per unit parameter.
        module_twist: ``(m, K, 6, p)`` module-platform twists ``(v, w)`` (module base frame).
        frame_deflection: ``(m, K+1, 6, p)`` fixed-frame end deflections ``(delta, theta)``.
    """

    state: Array
    module_twist: Array
    frame_deflection: Array

    @property
    def n_params(self) -> int:
        return int(self.state.shape[-1])

    @staticmethod
    def zeros(arm: Arm, m: int, p: int, dtype=None) -> Features:
        """All-zero features for ``m`` poses and ``p`` parameters."""
        dtype = dtype or jnp.asarray(arm.frames).dtype
        k = len(arm.modules)
        return Features(
            state=jnp.zeros((m, arm.dof, p), dtype),
            module_twist=jnp.zeros((m, k, 6, p), dtype),
            frame_deflection=jnp.zeros((m, k + 1, 6, p), dtype),
        )

    @staticmethod
    def concatenate(parts: Sequence[Features]) -> Features:
        """Stack the parameters of several feature sets (same poses) along ``p``."""
        if not parts:
            raise ValueError("Features.concatenate needs at least one feature set")
        return Features(
            state=jnp.concatenate([f.state for f in parts], axis=-1),
            module_twist=jnp.concatenate([f.module_twist for f in parts], axis=-1),
            frame_deflection=jnp.concatenate([f.frame_deflection for f in parts], axis=-1),
        )


def corrected_tool_pose(arm: Arm, q: ArrayLike, features: Features, theta: ArrayLike) -> Array:
    """Tool poses ``(m, 4, 4)`` of the geometric chain corrected by ``features @ theta``.

    Args:
        arm: the model (its fixed frames are the geometric part).
        q: ``(m, dof)`` module states as recorded.
        features: the candidates' :class:`Features` for these poses.
        theta: ``(p,)`` physical parameters (units of each effect's :class:`ParameterSpec`).

    Returns:
        ``T_OF`` per pose, world frame, mm. ``theta = 0`` is Eq. 1 exactly.
    """
    q = jnp.asarray(q)
    return perturbed_tool_pose(arm, q, *feature_corrections(features, jnp.asarray(theta, q.dtype)))


def feature_corrections(features: Features, theta: ArrayLike) -> tuple[Array, Array, Array]:
    """The per-pose corrections ``features @ theta`` that :func:`corrected_tool_pose` applies:
    module-state offsets ``(m, dof)``, module-platform twists ``(m, K, 6)`` (module base frame)
    and fixed-frame end deflections ``(m, K+1, 6)``; linear in ``theta (p,)``."""
    theta = jnp.asarray(theta)
    if theta.shape != (features.n_params,):
        raise ValueError(
            f"theta must have shape ({features.n_params},) (one entry per feature column), "
            f"got {theta.shape}"
        )
    dq = jnp.einsum("...dp,p->...d", features.state, theta)
    xi = jnp.einsum("...kcp,p->...kc", features.module_twist, theta)
    defl = jnp.einsum("...kcp,p->...kc", features.frame_deflection, theta)
    return dq, xi, defl


def perturbed_tool_pose(arm: Arm, q: Array, dq: Array, xi: Array, defl: Array) -> Array:
    """Tool poses ``(m, 4, 4)`` (world frame, mm) of the chain at states ``q + dq (m, dof)``,
    each module platform moved by the twist ``xi (m, K, 6)`` (on the left, module base frame)
    and each fixed frame's end deflected by ``defl (m, K+1, 6)`` (translation added, rotation
    on the left): the corrections of :func:`feature_corrections`; all zero: Eq. 1."""
    poses = lie.se3_exp(xi) @ module_poses(arm, q + dq)
    frames = jnp.asarray(arm.frames, q.dtype)
    R = lie.so3_exp(defl[..., 3:]) @ frames[..., :3, :3]
    p = frames[..., :3, 3] + defl[..., :3]
    tool, _ = chain(lie.make_pose(R, p), poses)
    return tool


_T = TypeVar("_T")

_SHARED_TERMS: contextvars.ContextVar[dict[tuple, tuple[tuple, Any]] | None] = (
    contextvars.ContextVar("cdra_jax_shared_terms", default=None)
)


@contextlib.contextmanager
def sharing_terms() -> Iterator[None]:
    """Within this block, :func:`shared_term` evaluates each function once per arguments.

    The candidates of one diagnosis need the same intermediate terms (the gravity loads, each
    module's holding tensions, the module base frames) for many forms; evaluating all
    candidates inside this block (as :func:`stacked_features` does, which the diagnosis
    compiles as one program) puts each term into the program once instead of once per form,
    which shortens its compilation. The memo lives only as long as the block.
    """
    token = _SHARED_TERMS.set({})
    try:
        yield
    finally:
        _SHARED_TERMS.reset(token)


def shared_term(fn: Callable[..., _T], *args: Any) -> _T:
    """``fn(*args)``, evaluated once per ``(fn, args)`` inside :func:`sharing_terms`.

    Arguments are matched by identity (arrays, arms, auxiliary mappings) or by value (``int``,
    ``str``); the memo keeps the arguments alive, so an identity is never reused within the
    block. Outside the block this is a plain call.
    """
    memo = _SHARED_TERMS.get()
    if memo is None:
        return fn(*args)
    key = (fn, *(a if isinstance(a, int | str) else id(a) for a in args))
    if key not in memo:
        memo[key] = (args, fn(*args))
    return memo[key][1]


ROUNDING = 1e-12
"""A feature column this many times smaller than its effect's largest is rounding: zero."""

# Auxiliary data handed to the effects: column name -> (m,) array (``time_s``, ``payload_kg``,
# ``approach.<module>``, ...), as in :attr:`cdra_jax.io.Measurements.aux`.
Aux = Mapping[str, ArrayLike]


class Effect:
    """A candidate non-geometric effect (one row of the design's vocabulary).

    Subclasses set :attr:`name`, :attr:`needs` and :attr:`summary`, and implement
    :meth:`locations`, :meth:`parameters`, :meth:`missing` and :meth:`features`.
    """

    name: str = ""
    needs: str = ""
    summary: str = ""
    variant: str = ""
    """Which form of the effect (e.g. ``"k=2"`` for the second harmonic); the variants of one
    effect at one location are alternatives, tried together and Bonferroni-corrected."""
    refinement: bool = False
    """A richer term of an effect (e.g. a load-hardening correction of a compliance) that is not
    tested on its own: the diagnosis adds it to a selected effect at the same location only
    where it pays for itself in held-out likelihood (see :mod:`cdra_jax.diagnosis`)."""
    alone: bool = False
    """For a refinement: whether it is a complete form of the effect by itself (a settling
    drift, a power-law stretch), which may then replace the form it refines in a refit; a
    correction term (a load-hardening term, an overtone) only joins another form."""

    def locations(self, arm: Arm) -> tuple[str, ...]:
        """Module or frame names this effect can sit at."""
        raise NotImplementedError

    def joins(self, other: Effect) -> bool:
        """Whether this form may be refitted together with ``other``, another form of the same
        effect at the same place (the diagnosis adds forms to a selected one where they pay).
        Every form by default; a form that describes one mechanism with one hidden constant
        (a drum's radius, a warm-up's time constant) joins only forms that agree on it."""
        return True

    def parameters(self, arm: Arm, location: str) -> tuple[ParameterSpec, ...]:
        """The physical parameters at ``location``."""
        raise NotImplementedError

    def missing(self, arm: Arm, location: str, aux_names: frozenset[str]) -> str | None:
        """Why this effect cannot be evaluated at ``location`` with these data, or ``None``."""
        return None

    def features(self, arm: Arm, q: Array, aux: Aux, location: str) -> Features:
        """Per-pose features ``(m, ..., p)`` at states ``q (m, dof)`` (see :class:`Features`)."""
        raise NotImplementedError

    def coordinate(self, arm: Arm, q: Array, location: str) -> tuple[Array, np.ndarray] | None:
        """For a form that is a series in a coordinate of its module (harmonics of a joint
        angle or of a drum angle): ``(z (m, n), owner (p,))``, the coordinate each pose has on
        each of ``n`` axes (a state entry, a cable's payout) and the axis whose function each
        parameter's feature is. Such a series fits a smooth shape that is not of its kind
        over a part of one period; the diagnosis checks that its amplitudes are the same over
        both halves of each axis' range (:func:`cdra_jax.diagnosis.core._shape_check`).
        ``None`` (the default): a form whose shape is fixed by its physics."""
        return None

    def describe(self, location: str, values: Mapping[str, tuple[float, float, float]]) -> str:
        """Plain words for a fitted effect; ``values``: name -> (value, low95, high95)."""
        return f"{self.name} at {location}"


@dataclass(frozen=True)
class Candidate:
    """One effect at one location, e.g. ``cable_elasticity`` at ``shoulder``.

    Hashable (effects compare by identity), so a tuple of candidates can be a static argument
    of a compiled function.
    """

    effect: Effect
    location: str

    @property
    def name(self) -> str:
        return self.effect.name

    @property
    def variant(self) -> str:
        return self.effect.variant

    @property
    def label(self) -> str:
        """``"<effect>@<location>"``."""
        return f"{self.effect.name}@{self.location}"

    def parameters(self, arm: Arm) -> tuple[ParameterSpec, ...]:
        return self.effect.parameters(arm, self.location)

    def missing(self, arm: Arm, aux_names: frozenset[str] | Sequence[str]) -> str | None:
        return self.effect.missing(arm, self.location, frozenset(aux_names))

    def coordinate(self, arm: Arm, q: ArrayLike) -> tuple[Array, np.ndarray] | None:
        """:meth:`Effect.coordinate` at this location."""
        return self.effect.coordinate(arm, jnp.asarray(q), self.location)

    def features(self, arm: Arm, q: ArrayLike, aux: Aux) -> Features:
        """The effect's features, with every column at the rounding level of its largest
        (:data:`ROUNDING`) set to exactly zero: a parameter this arm's geometry does not see
        (the travel of a prismatic joint along a revolute axis produces no torque about it),
        which a fit must leave alone rather than scale up from rounding noise."""
        f = self._effect_features(arm, q, aux)
        return _without_rounding_columns(f, np.zeros(f.n_params, int))

    def _effect_features(self, arm: Arm, q: ArrayLike, aux: Aux) -> Features:
        """The effect's features as it computes them (rounding-level columns included)."""
        f = self.effect.features(arm, jnp.asarray(q), aux, self.location)
        p = len(self.parameters(arm))
        if f.n_params != p:  # a bug in an effect, not a user error
            raise AssertionError(f"{self.label}: {f.n_params} feature columns for {p} parameters")
        return f

    def tool_pose(self, arm: Arm, q: ArrayLike, aux: Aux, params: ArrayLike) -> Array:
        """The pure extended forward model: tool poses ``(m, 4, 4)`` with this effect's
        parameters ``params (p,)`` (zero: the geometric model exactly)."""
        return corrected_tool_pose(arm, q, self.features(arm, q, aux), params)


def stacked_features(cands: Sequence[Candidate], arm: Arm, q: ArrayLike, aux: Aux) -> Features:
    """Features of several candidates at states ``q (m, dof)``, concatenated along ``p`` in
    the order given: each candidate's :meth:`Candidate.features`. The terms that several of
    them need are evaluated once (:func:`sharing_terms`), and the rounding-level columns of
    all of them are found in one pass (each against its own candidate's largest column).

    Called on concrete arrays, one compiled program per candidates and shapes; traced inline
    under ``jit``, ``vmap`` and ``grad``."""
    return eager_program(_stacked_features, tuple(cands))(arm, q, aux)


def _stacked_features(cands: tuple[Candidate, ...], arm: Arm, q: ArrayLike, aux: Aux) -> Features:
    with sharing_terms():
        raw = [c._effect_features(arm, q, aux) for c in cands]
    segments = np.repeat(np.arange(len(raw)), [f.n_params for f in raw])
    return _without_rounding_columns(Features.concatenate(raw), segments)


def _without_rounding_columns(f: Features, segments: np.ndarray) -> Features:
    """``f`` with every column at the rounding level (:data:`ROUNDING`) of the largest column
    of its segment set to exactly zero; ``segments (p,)``: each column's candidate (static,
    ``0, 0, 1, ...``). A column that is not finite stays as it is (the diagnosis marks its
    candidate failed)."""
    if f.n_params == 0:
        return f
    member = np.arange(int(segments.max()) + 1)[:, None] == segments[None, :]  # (S, p)
    return _zero_rounding_columns(f, member, segments)


@compiled_when_eager
def _zero_rounding_columns(f: Features, member: ArrayLike, segments: ArrayLike) -> Features:
    """:func:`_without_rounding_columns` given ``member (S, p)``, whether column ``c`` belongs
    to candidate ``s``; one compiled program per shape when called on concrete features (a
    diagnosis outside ``jit``), instead of a dozen small ones."""
    p = f.n_params
    parts = (f.state, f.module_twist, f.frame_deflection)
    columns = [a.reshape(-1, p) for a in parts]  # (entries, p) each
    size = jnp.max(jnp.stack([jnp.abs(c).max(axis=0) for c in columns]), axis=0)
    # Tested apart: XLA:CPU's max reduction does not always carry a NaN through.
    finite = jnp.all(jnp.stack([jnp.isfinite(c).all(axis=0) for c in columns]), axis=0)
    largest = jnp.max(jnp.where(member & finite, size, 0.0), axis=1)[segments]  # (p,)
    seen = ~finite | ~(size <= ROUNDING * largest)
    return Features(*(jnp.where(seen, a, 0.0) for a in parts))
