"""Each CAN fault kind alone: injected, and survived with samples identical to a fault-free run."""

import can.interfaces.virtual
import pytest

from setmem_hil.sim_backends.fault_survey import CAN_KINDS, survey


@pytest.fixture(autouse=True)
def no_virtual_channel_left_open():
    yield
    assert not can.interfaces.virtual.channels


def test_every_can_fault_kind_is_injected_and_survived():
    rows = survey("can", CAN_KINDS, rate=0.08, seed=2, omegas=(5.0,), n_samples=200)
    assert [r.kind for r in rows] == list(CAN_KINDS)
    for r in rows:
        assert r.injected > 0, r
        assert r.survived, r
    by_kind = {r.kind: r for r in rows}
    # what the host saw matches what was injected, kind by kind
    assert by_kind["corrupt"].detected["crc_errors"] == by_kind["corrupt"].injected
    assert by_kind["truncate"].detected["malformed_frames"] == by_kind["truncate"].injected
    assert by_kind["bus_off"].detected["reconnects"] == by_kind["bus_off"].injected
    assert by_kind["error_frame"].detected["error_frames"] == by_kind["error_frame"].injected
    assert by_kind["duplicate"].detected.get("duplicate_frames_discarded", 0) > 0
