"""Points from raw records: the one function per record kind that every dwell uses to compute its
measurements, so that ``setmem-hil reprocess`` recomputes them from ``raw.h5`` by the same code
(issue 39). Pure functions of the record: its datasets and its stored settings.

========================  =============================================================================
kind                      computed by
========================  =============================================================================
``simulated-phasor``      :func:`setmem_hil.estimation.simulated_record.simulated_points`: the simulated phasor is the point; the bound is the
                          noise bound plus ``|W1|`` (section 6.2)
``sine-dwell``            :func:`setmem_hil.estimation.dwell_record.dwell_points` (sampled records:
                          the transient-aware sine fit, the instrument terms)
``lock-in-readings``      :func:`setmem_hil.estimation.phasor_record.lock_in_points` (lock-in X, Y
                          readings with their times)
========================  =============================================================================
"""

from __future__ import annotations

from typing import Callable

from setmem_hil.estimation.dwell_record import SINE_DWELL, dwell_points
from setmem_hil.estimation.phasor_record import LOCK_IN_READINGS, lock_in_points
from setmem_hil.estimation.simulated_record import SIMULATED_PHASOR, simulated_points
from setmem_hil.model.experiment import Measurement, RawRecord

__all__ = ["SIMULATED_PHASOR", "SINE_DWELL", "LOCK_IN_READINGS", "points_from_record", "simulated_points"]

PROCESSORS: dict[str, Callable[[RawRecord], list[Measurement]]] = {
    SIMULATED_PHASOR: simulated_points, SINE_DWELL: dwell_points, LOCK_IN_READINGS: lock_in_points}
"""Each raw-record kind and the function that computes its points (each record module owns its kind's name)."""


def points_from_record(record: RawRecord) -> list[Measurement]:
    """The measurements ``record`` gives (in the order the dwell returned them)."""
    if record.kind not in PROCESSORS:
        raise ValueError(f"raw record of unknown kind {record.kind!r} (known: {', '.join(sorted(PROCESSORS))})")
    return PROCESSORS[record.kind](record)
