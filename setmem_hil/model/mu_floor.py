"""The floor no compensator can go below: a box that holds an undamped mode with zero residue.

If mode ``i``'s box holds ``a1 = 0`` together with ``b1 = 0`` and ``b0 = 0`` (``a1``'s lower
bound is 0 and 0 lies in the ``b1`` and ``b0`` intervals), it holds a plant whose mode ``i`` has
poles at ``+-j sqrt(a0)`` and no residue: the input does not move it and the output does not see
it. No compensator changes that mode, so for that plant the closed loop of eq. (6.23) has a pole
on the imaginary axis whatever ``K`` is: ``det(I - M(j w) Delta) = 0`` at ``w = sqrt(a0)`` for a
``Delta`` inside the unit ball of the structure, hence ``mu(M(j w)) >= 1`` there and mu-bar >= 1
for **every** compensator (Definition 2.1). Only an experiment that bounds ``a1`` or a residue
away from 0 removes it (issue 38).

Pure function of the box: the journal need not store it to recompute it, and older journals get
it on open.
"""

from __future__ import annotations

import numpy as np

from setmem_hil.model.modal_model import A1, B0, B1, IntervalModel

__all__ = ["floor_mask", "floor_modes", "floor_message", "floor_sentence"]


def floor_mask(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Which modes hold the floor, for bounds of shape ``(..., n_modes, 4)``: bool ``(..., n_modes)``
    (the predicted boxes of every candidate input at once, issue 38)."""
    lower, upper = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
    undamped = lower[..., A1] <= 0.0
    zero_b1 = (lower[..., B1] <= 0.0) & (upper[..., B1] >= 0.0)
    zero_b0 = (lower[..., B0] <= 0.0) & (upper[..., B0] >= 0.0)
    return undamped & zero_b1 & zero_b0


def floor_modes(model: IntervalModel) -> tuple[int, ...]:
    """1-based modes whose box holds an undamped, zero-residue plant (module docstring).

    Examples
    --------
    >>> floor_modes(IntervalModel([[0.0, 1.0, 0.0, -1.0]], [[0.1, 2.0, 0.0, 1.0]]))
    (1,)
    >>> floor_modes(IntervalModel([[0.01, 1.0, 0.0, -1.0]], [[0.1, 2.0, 0.0, 1.0]]))
    ()
    """
    return tuple(int(i) + 1 for i in np.flatnonzero(floor_mask(model.lower, model.upper)))


def floor_sentence(mode: int) -> str:
    """The journal's and the iteration line's words for one floor mode."""
    return (f"mode {mode}: the box holds an undamped mode with zero residue; no compensator can reach "
            "mu-bar < 1 until an experiment bounds a1 or b0 away from 0")


def floor_message(modes: tuple[int, ...] | list[int]) -> str:
    """All floor modes in one message ("" when there are none)."""
    return "; ".join(floor_sentence(m) for m in modes)
