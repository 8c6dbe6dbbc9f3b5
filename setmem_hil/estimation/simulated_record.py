"""The simulated beam's raw record: its phasors are the points (kind ``simulated-phasor``)."""

from __future__ import annotations

import numpy as np

from setmem_hil.model.experiment import Measurement, RawRecord

__all__ = ["SIMULATED_PHASOR", "simulated_points"]

SIMULATED_PHASOR = "simulated-phasor"
"""Raw-record kind of the simulated beam (:func:`simulated_points`)."""


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
