"""Does the data's feasible set hold the floor plant, or only the box? (issue 62)

A mode's box holds the floor (:mod:`setmem_hil.model.mu_floor`) when it holds ``a1 = 0`` with
zero residue: an undamped mode the input does not move and the output does not see, which keeps
mu-bar >= 1 for every compensator. The box is an outer bound of the set of parameters that fit the
data: it may hold that plant although no parameter that fits does. Then no experiment is needed to
remove the floor (a tighter box would), and telling the lab "an experiment must bound a1 or b0 away
from 0" is wrong.

A mode with zero residue contributes nothing to the response, whatever its poles. So the floor
plant of mode ``i`` fits the data exactly when the model *without* mode ``i`` (the other modes in
their boxes, the residual terms in theirs) fits every point within its bound:

* ``held``: a point of that reduced box was found that fits (:func:`~setmem_hil.identification.witness.find_witness`;
  a fact, checked on the model);
* ``excluded``: the reduced box is proved empty (the joint relaxation's certificates,
  :func:`~setmem_hil.identification.shaving.proved_empty`; with no other mode and no residual
  term, by the points themselves: some ``|g| > E``);
* ``unchecked``: neither (one other mode, which the joint search cannot prove empty, or no proof
  in its budget).

Only the first two are claims. Our choice where the thesis is silent: the campaign names a floor
as before (it holds the box's mu-bar at or above 1, and the input design ranks its removal first)
and adds this verdict to the sentence, so a floor the data exclude is said to be the box's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from setmem_hil.identification.residual_terms import residual_midpoint_response, residual_mismatch
from setmem_hil.identification.shaving import proved_empty
from setmem_hil.identification.witness import find_witness
from setmem_hil.model.mu_floor import floor_sentence

__all__ = ["FloorEvidence", "HELD", "EXCLUDED", "UNCHECKED", "floor_evidence"]

HELD, EXCLUDED, UNCHECKED = "held", "excluded", "unchecked"


@dataclass(frozen=True)
class FloorEvidence:
    """The verdict for one mode (1-based) and, when ``held``, the misfit of the point that fits."""

    mode: int
    verdict: str
    misfit: float | None = None

    def sentence(self) -> str:
        """The floor's sentence for the journal, with the data's verdict: a floor the data exclude
        is named the box's, not one an experiment must remove."""
        if self.verdict == EXCLUDED:
            return (f"mode {self.mode}: the box holds an undamped mode with zero residue, but the data exclude it "
                    f"(proved: without mode {self.mode} no parameter of the other modes' boxes fits every point); "
                    "a tighter box, not an experiment, removes it")
        if self.verdict == HELD:
            return f"{floor_sentence(self.mode)} (the data hold it: without mode {self.mode} the model fits, misfit {self.misfit:.3g})"
        return f"{floor_sentence(self.mode)} (not settled against the data)"


def floor_evidence(omega_rad_s, g, E, lo, hi, mode: int, residual_bounds: dict | None = None) -> FloorEvidence:
    """The verdict (module docstring) for ``mode`` (1-based) of the box ``[lo, hi]``
    (``(n_modes, 4)``) on the data ``g`` with bounds ``E``; ``residual_bounds`` the residual
    terms' intervals (``{name: (lo, hi)}``) as identified."""
    omega = np.asarray(omega_rad_s, dtype=float)
    g, E = np.asarray(g, dtype=complex), np.asarray(E, dtype=float)
    keep = [i for i in range(np.shape(lo)[0]) if i != mode - 1]
    r_lo, r_hi = np.asarray(lo, dtype=float)[keep], np.asarray(hi, dtype=float)[keep]
    res = dict(residual_bounds or {})
    if not keep:
        if not res:  # the floor plant is G = 0: the points say it directly
            worst = float(np.max(np.abs(g) / np.where(E > 0, E, np.finfo(float).tiny)))
            return FloorEvidence(mode, HELD, worst) if worst <= 1.0 else FloorEvidence(mode, EXCLUDED)
        return FloorEvidence(mode, UNCHECKED)
    witness = find_witness(omega, g, E, r_lo, r_hi, res)
    if witness.fits:
        return FloorEvidence(mode, HELD, float(witness.misfit))
    g_all, E_all = g - residual_midpoint_response(res, omega), E + residual_mismatch(res, omega)
    if proved_empty(omega, g_all, E_all, r_lo, r_hi):
        return FloorEvidence(mode, EXCLUDED)
    return FloorEvidence(mode, UNCHECKED)
