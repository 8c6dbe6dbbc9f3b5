"""A synthetic structure with a close pair of modes (issue 47's reference case).

Modes at 10 rad/s and ``10 (1 + separation)``, damping 0.005, residues ``b0`` given (4 and -2.5 by
default: opposite signs), and a third mode at 31 rad/s (residue 3); ``n`` lines from 6 to 40 rad/s
with the bound ``noise (2 % |G| + 1e-4)`` and errors drawn uniformly in each point's disc. The
prior's brackets meet between the pair (``b0`` in [-10, 10], ``b1`` in [-0.1, 0.1], zeta <= 0.05).
Used by the tests and ``benchmarks/close_modes.py``.
"""

from __future__ import annotations

import numpy as np

from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.model.modal_model import ModalParameters
from setmem_hil.model.prior import ModePrior, Prior


def close_pair_case(separation: float, residues=(4.0, -2.5), noise: float = 1.0, n: int = 300, seed: int = 0):
    """``(truth, data, prior)`` of the close-pair structure (module docstring)."""
    w1, w2 = 10.0, 10.0 * (1.0 + separation)
    truth = ModalParameters.from_modal([w1, w2, 31.0], [0.005] * 3, [residues[0], residues[1], 3.0])
    w = np.linspace(6.0, 40.0, n)
    G = truth.frequency_response(w)
    bound = noise * (0.02 * np.abs(G) + 1e-4)
    rng = np.random.default_rng(seed)
    g = G + bound * np.sqrt(rng.uniform(0, 1, n)) * np.exp(2j * np.pi * rng.uniform(0, 1, n))
    mid = np.sqrt(w1 * w2)
    brackets = [(0.95 * w1, mid), (mid, 1.05 * w2), (0.9 * 31.0, 1.1 * 31.0)]
    prior = Prior(tuple(ModePrior(a, b, 0.05, -0.1, 0.1, -10.0, 10.0) for a, b in brackets))
    return truth, FrequencyData(w, g, bound), prior
