"""Sine-dwell sweep through the Modbus transport (backend ``modbus-loopback``, TCP and RTU framing): truth inside every bound."""

import dataclasses

import numpy as np
import pytest

from setmem_hil.experiment_factory import open_experiment
from setmem_hil.io.procedure import default_procedure
from setmem_hil.sim_backends.beam import beam_parameters

OMEGAS = (0.9, 5.9536, 16.6697, 30.0)


def _procedure(faults=None, framer="socket"):
    proc = default_procedure()
    backend = dataclasses.replace(proc.backend, kind="modbus-loopback", faults=dict(faults or {}), transport={"framer": framer})
    return dataclasses.replace(proc, backend=backend)


@pytest.mark.parametrize(
    "faults, framer",
    [(None, "socket"), ({"rate": 0.01, "seed": 4}, "socket"), (None, "rtu")],
    ids=["tcp-clean", "tcp-faults", "rtu-clean"],
)
def test_dwell_sweep_through_modbus_bounds_the_truth(faults, framer):
    truth = beam_parameters()  # the 8-mode beam the fake device simulates (independent of the dwell)
    with open_experiment(_procedure(faults, framer), seed=3) as exp:
        measurements = [exp.measure(w) for w in OMEGAS]
        injected = exp.rig.owned[0].injected
    for m in measurements:
        g = truth.frequency_response(np.array([m.omega_rad_s]))[0]
        assert abs(m.response - g) <= m.bound, (m, g)
        assert m.bound < 0.5 * abs(g) + 1.0  # informative, not a vacuous bound
    if faults:
        assert sum(injected.values()) > 0
