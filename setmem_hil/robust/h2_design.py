"""H2 compensator for the augmented plant (thesis section 6.3.1).

The compensator minimises the H2 norm from ``w`` to ``z`` of the augmented plant of
eq. (6.16)-(6.22) built at the interval midpoints, with the parametric uncertainty treated as
noise entering the system ("the compensator is sensitized to this uncertainty"). It has the
order of the augmented plant. ``W_2`` gets the extra pole (``D_2 = 0``) so the problem is well
posed.

Sign convention: positive feedback ``u = K y``, as in the thesis (footnote 3 of 6.3.2) and as
returned by ``control.h2syn`` (SLICOT SB10HD).
"""

from __future__ import annotations

import numpy as np
import control

from setmem_hil.robust.augmented_plant import AugmentedPlant, StateSpaceMatrices, augmented_plant
from setmem_hil.errors import SolverError
from setmem_hil.model.modal_model import IntervalModel
from setmem_hil.robust.uncertain_plant import uncertain_plant
from setmem_hil.model.weights import THESIS_WEIGHTS, Weights


def h2_controller_for_plant(plant: AugmentedPlant):
    """H2-optimal ``K`` (``u = K y``) for an augmented plant.

    Raises
    ------
    SolverError
        If SB10HD fails (e.g. ``D_11 != 0`` because ``W_2`` has no extra pole).
    """
    if np.any(plant.Dzw != 0.0):
        raise SolverError("H2 design: D11 of the augmented plant is nonzero; give W2 an extra pole (w2_extra_pole_rad_s)")
    try:
        return control.h2syn(plant.to_statespace(), 1, 1)
    except Exception as exc:  # slycot raises its own arithmetic/value errors
        raise SolverError(f"H2 design (slycot SB10HD) failed: {exc}") from exc


def design_h2_controller(model: IntervalModel, weights: Weights = THESIS_WEIGHTS):
    """Design the H2 compensator for the model's midpoint (section 6.3.1).

    Parameters
    ----------
    model : IntervalModel
        Identified parameter intervals; uncertain parameters enter as noise channels.
    weights : Weights
        ``W_1`` and ``W_2`` (``W_2`` with its extra roll-off pole).

    Returns
    -------
    control.StateSpace
        ``K`` for positive feedback ``u = K y``.

    Examples
    --------
    >>> from setmem_hil.model.modal_model import IntervalModel
    >>> from setmem_hil.sim_backends.beam import beam_parameters
    >>> K = design_h2_controller(IntervalModel.point(beam_parameters().truncated(3)))
    >>> K.nstates
    15
    """
    return h2_controller_for_plant(augmented_plant(uncertain_plant(model), weights, design_w2=True))


def h2_norm(system: StateSpaceMatrices) -> float:
    """H2 norm: python-control's ``norm(sys, 2)`` (the controllability Gramian's
    ``sqrt(trace(C P C^T))``, ``A P + P A^T + B B^T = 0``).

    Returns ``inf`` for an unstable system or a nonzero feedthrough.
    """
    if np.any(system.D != 0.0) or np.any(np.linalg.eigvals(system.A).real >= 0.0):
        return float("inf")
    return float(control.norm(system.to_statespace(), 2, print_warning=False))
