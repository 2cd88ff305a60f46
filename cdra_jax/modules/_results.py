"""Element-wise result codes for batched solvers (``eqx.Enumeration.where`` is scalar-only)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike


def select(pred: ArrayLike, a, b):
    """Element-wise ``a if pred else b`` for two items of the same ``eqx.Enumeration``."""
    value = jnp.where(jnp.asarray(pred), a._value, b._value)
    return eqx.tree_at(lambda r: r._value, a, value)


def result_names(result) -> np.ndarray:
    """Name of each entry of a (batched) result code, e.g. ``"successful"``."""
    enum = result._enumeration
    keys = list(enum._name_to_item)
    idx = np.asarray(result._value)
    return np.vectorize(lambda i: keys[int(i)], otypes=[object])(idx)


def result_messages(result) -> np.ndarray:
    """Human-readable message of each entry of a (batched) result code."""
    enum = result._enumeration
    msgs = [m or "successful" for m in enum._index_to_message]
    idx = np.asarray(result._value)
    return np.vectorize(lambda i: msgs[int(i)], otypes=[object])(idx)
