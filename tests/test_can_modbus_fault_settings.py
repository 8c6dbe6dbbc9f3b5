"""Splitting a procedure's [backend.faults] between the device core and the CAN/Modbus kinds."""

import dataclasses

import pytest

from setmem_hil.errors import ProcedureError
from setmem_hil.io.procedure import default_procedure
from setmem_hil.sim_backends.fake_device_core import FaultSettings
from setmem_hil.sim_backends.transport_faults import CAN_FAULT_KINDS, MODBUS_FAULT_KINDS, split_faults


def _proc(faults):
    proc = default_procedure()
    return dataclasses.replace(proc, backend=dataclasses.replace(proc.backend, faults=faults))


def test_kinds_and_per_kind_rates_go_where_they_belong():
    faults = {"rate": 0.1, "seed": 4, "kinds": ["corrupt", "bus_off"], "rates": {"bus_off": 0.5, "corrupt": 0.2}}
    core_proc, mine = split_faults(_proc(faults), CAN_FAULT_KINDS)
    core = FaultSettings.from_mapping(core_proc.backend.faults)  # the core accepts its part
    assert core.kinds == ("corrupt",) and core.rate_of("corrupt") == 0.2
    assert mine.kinds == ("bus_off",) and mine.rate_of("bus_off") == 0.5 and mine.seed == 4
    assert not mine.draw("error_frame")  # not enabled


def test_without_kinds_every_kind_is_enabled_and_draws_follow_the_rate():
    _, mine = split_faults(_proc({"rate": 0.25, "seed": 1}), MODBUS_FAULT_KINDS)
    assert mine.kinds == ("exception",)
    hits = sum(mine.draw("exception") for _ in range(4000))
    assert abs(hits / 4000 - 0.25) < 0.03  # binomial: sd 0.007
    assert mine.injected["exception"] == hits


@pytest.mark.parametrize(
    "faults, message",
    [({"kinds": ["bus_off", "nope"]}, "unknown kinds \\['nope'\\]"),
     ({"kinds": "bus_off"}, "expected a list of names"),
     ({"rates": {"bus_off": 2.0}}, "rates\\] key 'bus_off'")],
)
def test_bad_fault_settings_name_the_key(faults, message):
    with pytest.raises(ProcedureError, match=message):
        split_faults(_proc(faults), CAN_FAULT_KINDS)
