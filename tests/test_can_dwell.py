"""Sine-dwell sweep through the CAN transport (backend ``can-virtual``): truth inside every bound."""

import dataclasses

import can.interfaces.virtual
import numpy as np
import pytest

from setmem_hil.experiment_factory import open_experiment
from setmem_hil.io.procedure import default_procedure
from setmem_hil.sim_backends.beam import beam_parameters

OMEGAS = (0.9, 5.9536, 16.6697, 30.0)


@pytest.fixture(autouse=True)
def no_virtual_channel_left_open():
    yield
    assert not can.interfaces.virtual.channels


def _procedure(faults=None):
    proc = default_procedure()
    return dataclasses.replace(proc, backend=dataclasses.replace(proc.backend, kind="can-virtual", faults=dict(faults or {})))


@pytest.mark.parametrize("faults", [None, {"rate": 0.01, "seed": 4}], ids=["clean", "faults"])
def test_dwell_sweep_through_can_bounds_the_truth(faults):
    truth = beam_parameters()  # the 8-mode beam the fake device simulates (independent of the dwell)
    with open_experiment(_procedure(faults), seed=3) as exp:
        measurements = [exp.measure(w) for w in OMEGAS]
        injected = exp.rig.owned[0].injected
    for m in measurements:
        g = truth.frequency_response(np.array([m.omega_rad_s]))[0]
        assert abs(m.response - g) <= m.bound, (m, g)
        assert m.bound < 0.5 * abs(g) + 1.0  # informative, not a vacuous bound
    if faults:
        assert sum(injected.values()) > 0
