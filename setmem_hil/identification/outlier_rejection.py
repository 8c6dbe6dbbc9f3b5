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


def _try(data: FrequencyData, drop: tuple[int, ...], prior: Prior, previous, settings):
    keep = np.setdiff1d(np.arange(len(data)), drop)
    try:
        return identify(data.subset(keep), prior, previous, settings), None
    except InconsistentDataError as exc:
        return None, exc


def _indices(data: FrequencyData, omegas) -> list[int]:
    return [int(np.argmin(np.abs(data.omega_rad_s - w))) for w in omegas]


def identify_rejecting_outliers(data: FrequencyData, prior: Prior, previous: IntervalModel | None = None,
                                settings: IdentifySettings = IdentifySettings(),
                                max_rejected: int = MAX_REJECTED) -> tuple[IdentificationResult, list[float]]:
    """Identify, dropping the fewest points (at most ``max_rejected``) that restore consistency.

    Returns the result and the frequencies of the rejected points (empty when none were needed).
    Raises the last :class:`InconsistentDataError` when more than ``max_rejected`` would be needed.
    """
    dropped: tuple[int, ...] = ()
    result, error = _try(data, dropped, prior, previous, settings)
    while result is None:
        if len(dropped) >= max_rejected:
            raise error
        remaining = np.setdiff1d(np.arange(len(data)), dropped)
        involved = [int(remaining[i]) for i in _indices(data.subset(remaining), error.omegas_rad_s)]
        suspects = [int(remaining[i]) for i in _indices(data.subset(remaining), error.suspects_rad_s)]
        order = suspects + [i for i in involved if i not in suspects]
        restoring = []
        for j in order:
            candidate, _ = _try(data, dropped + (j,), prior, previous, settings)
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
                result, _ = _try(data, dropped + pair, prior, previous, settings)
                if result is not None:
                    dropped += pair
                    break
            else:
                dropped += (order[0],)  # greedy step: the strongest suspect
                result, error = _try(data, dropped, prior, previous, settings)
    return result, sorted(float(data.omega_rad_s[j]) for j in dropped)
