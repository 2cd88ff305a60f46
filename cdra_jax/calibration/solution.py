"""Result codes and the solution object shared by the calibration solvers."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax import Array

from ..arm import Arm


class RESULTS(eqx.Enumeration):
    """Per-trial outcome of a calibration solve (one entry per trial under ``vmap``)."""

    successful = ""
    max_iterations_reached = (
        "the calibration did not converge within max_iterations; raise it or loosen tol"
    )
    nonfinite = "a non-finite value (NaN or inf) appeared in the measurements or the iterates"


class CalibrationSolution(eqx.Module):
    """What a calibration solver returns (batched leading dimensions under ``vmap``).

    Attributes:
        frames: calibrated fixed transforms ``(..., K+1, 4, 4)`` (T^c of Eq. 19).
        errors: identified error twists w.r.t. the nominal frames ``(..., K+1, 6)``
            (Eqs. 15-18, ``(v, w)``, mm and rad).
        result: :class:`RESULTS` code.
        iterations: number of steps taken ``(...)``.
        step_norm: ``||X||`` of each step ``(..., max_iterations)``, NaN past the last step.
        delta_p: Eq. 20 on the fitting poses ``(..., max_iterations + 1)``: entry 0 for the
            nominal model, entry k after k steps, NaN past the end (mm).
        delta_R: the same for Eq. 21 (rad).
        rank: numerical rank of the (weighted) stacked Jacobian at the solution ``(...)``.
        singular_values: its singular values ``(..., n_params)``.
        cost: final weighted sum of squared residuals (paper form: unweighted) ``(...)``.
        solver: ``"paper"``, ``"weighted"`` or ``"lm"``.
    """

    frames: Array
    errors: Array
    result: RESULTS
    iterations: Array
    step_norm: Array
    delta_p: Array
    delta_R: Array
    rank: Array
    singular_values: Array
    cost: Array
    solver: str = eqx.field(static=True)

    def calibrated_arm(self, nominal: Arm) -> Arm:
        """The nominal arm with the calibrated frames (Eq. 19); unbatched solutions only."""
        return nominal.with_frames(self.frames)

    @property
    def converged(self) -> Array:
        """Boolean ``(...)``: the solve ended with :attr:`RESULTS.successful`."""
        return self.result == RESULTS.successful

    @property
    def final_delta_p(self) -> Array:
        """Eq. 20 after the last step ``(...)``."""
        return jnp.take_along_axis(self.delta_p, self.iterations[..., None], axis=-1)[..., 0]

    @property
    def final_delta_R(self) -> Array:
        """Eq. 21 after the last step ``(...)``."""
        return jnp.take_along_axis(self.delta_R, self.iterations[..., None], axis=-1)[..., 0]


def result_names(result: RESULTS) -> np.ndarray:
    """Name (``"successful"``, ``"max_iterations_reached"``, ...) of each entry of a code."""
    names = list(RESULTS._name_to_item)
    idx = np.asarray(result._value)
    return np.vectorize(lambda i: names[int(i)], otypes=[object])(idx)


def result_messages(result: RESULTS) -> np.ndarray:
    """Human-readable message of each entry of a (batched) result code."""
    msgs = [m or "successful" for m in RESULTS._index_to_message]
    idx = np.asarray(result._value)
    return np.vectorize(lambda i: msgs[int(i)], otypes=[object])(idx)
