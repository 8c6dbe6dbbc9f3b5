"""A frequency region the design keeps choosing although it delivers little (thesis section 6.3.4).

The effect estimate (eq. 5.3) assumes the point measured at a candidate will carry the bound
expected there and cut the intervals the way the certainty-equivalent point does. Where that
is wrong the loop can be "caught in a trap of continuing to try the same frequency region when
there is little information available" (section 6.3.4: the model mismatch dominated the noise
the analysis assumed). The thesis diagnoses the trap and leaves it. On the emulated
oscilloscope rig, with the first record's control output ranged twice as coarse as shipped, it
spent four of ten campaigns' budgets on single sines a few percent apart (13.5-13.9 or near
16 rad/s), where mu-bar stopped improving; the rule below freed one of them. Where the exact
re-solve's own prediction is already tiny and is met, the rule rightly waits.

This project's choice (not the thesis's): after ``RUN`` consecutive iterations that each
measured one frequency, all within ``REGION`` (relative) of one another, each lowering mu-bar
by less than ``SHORTFALL`` of the improvement predicted for it, the region they span (widened
by ``REGION`` on each side) is left out of the candidates for the rest of the campaign. A campaign
whose predictions come true, or that moves on by itself, never meets the rule. Pure functions,
no I/O.

Example
-------
>>> history = [Outcome(13.87, 0.011, 0.0017), Outcome(13.70, 0.010, 0.0), Outcome(13.76, 0.012, 0.0001)]
>>> lo, hi = unproductive_region(history)
>>> bool(lo < 13.70 and hi > 13.87)
True
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

__all__ = ["Outcome", "unproductive_region", "outside_regions", "predicted_improvement", "describe", "RUN", "SHORTFALL", "REGION"]

RUN = 3  # consecutive disappointing experiments in one region
SHORTFALL = 0.25  # an experiment disappoints when it delivers less than this share of its prediction
REGION = 0.05  # relative: how close the experiments lie, and how far the region is widened


@dataclass(frozen=True)
class Outcome:
    """One iteration's experiment: its frequency (None when it measured several), the mu-bar
    improvement predicted for it, and the improvement the next iteration found."""

    omega_rad_s: float | None
    predicted: float
    realized: float

    @property
    def disappointing(self) -> bool:
        return (self.omega_rad_s is not None and math.isfinite(self.predicted) and self.predicted > 0.0
                and self.realized < SHORTFALL * self.predicted)


def unproductive_region(history: Sequence[Outcome]) -> tuple[float, float] | None:
    """``(low, high)`` rad/s to leave out when the last ``RUN`` outcomes meet the rule of the
    module docstring, else None."""
    last = list(history)[-RUN:]
    if len(last) < RUN or not all(o.disappointing for o in last):
        return None
    omegas = [float(o.omega_rad_s) for o in last]
    if max(omegas) > min(omegas) * (1.0 + REGION) ** 2:  # not one region
        return None
    return min(omegas) / (1.0 + REGION), max(omegas) * (1.0 + REGION)


def outside_regions(omega_rad_s: np.ndarray, regions: Sequence[tuple[float, float]]) -> np.ndarray:
    """The mask of candidates outside every region (all True when that would leave none)."""
    w = np.asarray(omega_rad_s, dtype=float)
    keep = np.ones(w.shape, dtype=bool)
    for lo, hi in regions:
        keep &= ~((w >= lo) & (w <= hi))
    return keep if keep.any() else np.ones(w.shape, dtype=bool)


def predicted_improvement(choice) -> float:
    """The mu-bar improvement an :class:`~setmem_hil.design.input_design.InputChoice` expected
    of its choice: the exact re-solve's where it re-solved that candidate, else the estimate's;
    nan when it did not predict one (a fallback ranking, a data-blind strategy)."""
    w = choice.next_omega_rad_s
    if choice.basis != "estimate":
        return math.nan
    for candidates, improvements in ((choice.resolved_omega_rad_s, choice.resolved_improvement),
                                     (choice.candidate_omega_rad_s, choice.estimated_improvement)):
        c, v = np.asarray(candidates, dtype=float), np.asarray(improvements, dtype=float)
        hit = np.flatnonzero(np.isclose(c, w, rtol=1e-12, atol=0.0)) if c.size == v.size else []
        if len(hit) and math.isfinite(v[hit[0]]):
            return float(v[hit[0]])
    return math.nan


def describe(region: tuple[float, float], outcomes: Sequence[Outcome]) -> str:
    """One line for the journal and the log: the region and what its experiments did."""
    done = ", ".join(f"{o.omega_rad_s:.4g} rad/s: {o.realized:.2g} of {o.predicted:.2g}" for o in outcomes)
    return (f"{region[0]:.4g}-{region[1]:.4g} rad/s left out of the candidates: {len(outcomes)} experiments there lowered "
            f"mu-bar by less than {SHORTFALL:.0%} of the predicted improvement ({done}; thesis section 6.3.4)")
