"""Points from raw records: the one function per record kind that every dwell uses to compute its
measurements, so that ``setmem-hil reprocess`` recomputes them from ``raw.h5`` by the same code
(issue 39). Pure functions of the record: its datasets and its stored settings.

========================  =============================================================================
kind                      computed by
========================  =============================================================================
``simulated-phasor``      :func:`simulated_points`: the simulated phasor is the point; the bound is the
                          noise bound plus ``|W1|`` (section 6.2)
``sine-dwell``            :func:`setmem_hil.estimation.dwell_record.dwell_points` (sampled records:
                          the transient-aware sine fit, the instrument terms)
``lock-in-readings``      :func:`setmem_hil.estimation.phasor_record.lock_in_points` (lock-in X, Y
                          readings with their times)
========================  =============================================================================
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from setmem_hil.model.experiment import Measurement, RawRecord

__all__ = ["SIMULATED_PHASOR", "SINE_DWELL", "LOCK_IN_READINGS", "points_from_record", "simulated_points"]

SIMULATED_PHASOR = "simulated-phasor"
SINE_DWELL = "sine-dwell"
LOCK_IN_READINGS = "lock-in-readings"


def simulated_points(record: RawRecord) -> list[Measurement]:
    """The simulated beam's points: each sensor's phasor, its bound the noise bound plus the
    unmodelled modes' ``|W1|`` when the truth has them; the control output first."""
    d, control = record.datasets, int(record.attrs["control_output"])
    phasor, noise = np.asarray(d["phasor"]), np.asarray(d["noise_bound"])
    bound = noise + np.asarray(d["unmodelled_bound"]) if record.attrs["unmodelled_dynamics"] else noise
    order = [control] + [k for k in range(phasor.shape[0]) if k != control]
    points = []
    for i, w in enumerate(np.asarray(d["omega_rad_s"], dtype=float)):
        (g, b), *others = [(complex(phasor[k, i]), float(bound[k, i])) for k in order]
        points.append(Measurement(float(w), g, b, others=tuple(others)))
    return points


def _processors() -> dict[str, Callable[[RawRecord], list[Measurement]]]:
    from setmem_hil.estimation.dwell_record import dwell_points
    from setmem_hil.estimation.phasor_record import lock_in_points

    return {SIMULATED_PHASOR: simulated_points, SINE_DWELL: dwell_points, LOCK_IN_READINGS: lock_in_points}


def points_from_record(record: RawRecord) -> list[Measurement]:
    """The measurements ``record`` gives (in the order the dwell returned them)."""
    processors = _processors()
    if record.kind not in processors:
        raise ValueError(f"raw record of unknown kind {record.kind!r} (known: {', '.join(sorted(processors))})")
    return processors[record.kind](record)
