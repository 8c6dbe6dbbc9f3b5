"""A close pair's group problem and a box around its truth (not collected: no ``test_`` prefix),
for tests that contract one box and compare it with the linearised exact feasible set."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from setmem_hil.identification.exact_set import linearised_extent
from setmem_hil.model.modal_model import ModalParameters
from setmem_hil.sim_backends.close_pair import close_pair_case


def pair_box_around_truth(separation: float, residues, noise: float, factor: float = 4.0) -> SimpleNamespace:
    """The pair's data with the far mode subtracted exactly (``w, g, E``), the linearised exact
    set's extent of the pair (``ex_lo, ex_hi``, HiGHS) and the box ``factor`` times that extent
    each side of the truth, clipped to the prior (``lo, hi``); flat ``(8,)`` arrays."""
    truth, data, prior = close_pair_case(separation, residues=residues, noise=noise)
    w, E = data.omega_rad_s, data.bound
    g = data.response - ModalParameters(truth.values[2:]).frequency_response(w)
    box = prior.initial_bounds()
    ex_lo, ex_hi = (v.reshape(-1) for v in linearised_extent(w, g, E, truth.values[:2], box.lower[:2], box.upper[:2]))
    centre, half = truth.values[:2].reshape(-1), factor * (ex_hi - ex_lo)
    lo = np.maximum(centre - half, box.lower[:2].reshape(-1))
    hi = np.minimum(centre + half, box.upper[:2].reshape(-1))
    return SimpleNamespace(w=w, g=g, E=E, ex_lo=ex_lo, ex_hi=ex_hi, lo=lo, hi=hi)
