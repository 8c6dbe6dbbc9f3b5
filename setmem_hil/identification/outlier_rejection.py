"""Optional outlier rejection (thesis section 7.2): drop the fewest points needed to regain
consistency with the prior, and say which.

Exact minimisation is combinatorial; we search in increasing size. First every single point
named in the infeasibility certificate: when several single removals restore consistency, we
drop the point that disagrees most (normalised residual) with the model identified without it;
then pairs among them; beyond that, greedily remove the strongest suspect and repeat. The result is the minimum whenever one or
two points are at fault (the common case of a glitched dwell) and a small set otherwise.
"""

from __future__ import annotations

from itertools import combinations

import numpy as np

from setmem_hil.errors import InconsistentDataError
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.identification.algorithm import IdentificationResult, IdentifySettings, identify
from setmem_hil.model.modal_model import IntervalModel
from setmem_hil.model.prior import Prior

MAX_REJECTED = 5
"""Most points ``--reject-outliers`` drops; needing more means the prior does not fit the data."""
MAX_TRIALS = 40
"""Most trial identifications of the search (each one is a full identification: on 384 points
about a second). A prior proposed from another sensor once kept it busy for minutes."""
MAX_CANDIDATES = 12
"""Points tried per round: the certificate's suspects first, then the rest of its points."""


class _Budget:
    """Counts the trial identifications and reports each one."""

    def __init__(self, max_trials: int, progress):
        self.max_trials, self.progress, self.used = max_trials, progress, 0

    def spend(self, dropped: tuple[int, ...], data: FrequencyData) -> None:
        if self.used >= self.max_trials:
            raise InconsistentDataError(
                f"--reject-outliers: no consistent subset within {self.max_trials} trial identifications "
                f"({len(dropped)} point(s) set aside so far): the prior does not fit these data; check it against the "
                "data (setmem-hil prior --data ... proposes one) rather than rejecting more points")
        self.used += 1
        if self.progress is not None:
            what = ", ".join(f"{data.omega_rad_s[j]:.6g}" for j in dropped) or "none"
            self.progress(f"reject-outliers: trial {self.used}/{self.max_trials}, without the point(s) at {what} rad/s")


def _try(data: FrequencyData, drop: tuple[int, ...], prior: Prior, previous, settings, budget: _Budget | None = None):
    if budget is not None:
        budget.spend(drop, data)
    keep = np.setdiff1d(np.arange(len(data)), drop)
    try:
        return identify(data.subset(keep), prior, previous, settings), None
    except InconsistentDataError as exc:
        return None, exc


def _indices(data: FrequencyData, omegas) -> list[int]:
    return [int(np.argmin(np.abs(data.omega_rad_s - w))) for w in omegas]


def identify_rejecting_outliers(data: FrequencyData, prior: Prior, previous: IntervalModel | None = None,
                                settings: IdentifySettings = IdentifySettings(),
                                max_rejected: int = MAX_REJECTED, max_trials: int = MAX_TRIALS,
                                progress=None) -> tuple[IdentificationResult, list[float]]:
    """Identify, dropping the fewest points (at most ``max_rejected``) that restore consistency.

    Returns the result and the frequencies of the rejected points (empty when none were needed).
    Raises :class:`InconsistentDataError` saying the prior does not fit the data when more than
    ``max_rejected`` points would be needed or ``max_trials`` trial identifications did not find
    a consistent subset. ``progress(text)`` is called before every trial.
    """
    budget = _Budget(max_trials, progress)
    dropped: tuple[int, ...] = ()
    result, error = _try(data, dropped, prior, previous, settings)
    while result is None:
        if len(dropped) >= max_rejected:
            raise InconsistentDataError(
                f"--reject-outliers: more than {max_rejected} points would have to be set aside, so the prior does not fit "
                f"these data (last conflict: {error})", omegas_rad_s=error.omegas_rad_s, mode_index=error.mode_index)
        remaining = np.setdiff1d(np.arange(len(data)), dropped)
        involved = [int(remaining[i]) for i in _indices(data.subset(remaining), error.omegas_rad_s)]
        suspects = [int(remaining[i]) for i in _indices(data.subset(remaining), error.suspects_rad_s)]
        order = (suspects + [i for i in involved if i not in suspects])[:MAX_CANDIDATES]
        restoring = []
        for j in order:
            candidate, _ = _try(data, dropped + (j,), prior, previous, settings, budget)
            if candidate is not None:
                g_model = candidate.model.midpoint.frequency_response([data.omega_rad_s[j]])[0]
                misfit = abs(data.response[j] - g_model) / max(data.bound[j], 1e-300)
                restoring.append((misfit, j, candidate))
        if restoring:
            _, j, result = max(restoring, key=lambda t: t[0])
            dropped += (j,)
        else:
            for pair in combinations(order[:8], 2):
                if len(dropped) + 2 > max_rejected:
                    break
                result, _ = _try(data, dropped + pair, prior, previous, settings, budget)
                if result is not None:
                    dropped += pair
                    break
            else:
                dropped += (order[0],)  # greedy step: the strongest suspect
                result, error = _try(data, dropped, prior, previous, settings, budget)
    return result, sorted(float(data.omega_rad_s[j]) for j in dropped)
