"""Each Modbus fault kind alone (TCP and RTU framing): injected, and survived with samples
identical to a fault-free run."""

import threading

import pytest

from setmem_hil.loopback.fault_survey import MODBUS_KINDS, RTU_KINDS, survey


@pytest.fixture(autouse=True)
def no_server_thread_left():
    yield
    assert not [t for t in threading.enumerate() if t.name.startswith("fake-modbus-")]


@pytest.mark.parametrize("transport, kinds", [("modbus-socket", MODBUS_KINDS), ("modbus-rtu", RTU_KINDS)])
def test_every_modbus_fault_kind_is_injected_and_survived(transport, kinds):
    rows = survey(transport, kinds, rate=0.08, seed=2, omegas=(5.0,), n_samples=200)
    assert [r.kind for r in rows] == list(kinds)
    for r in rows:
        assert r.injected > 0, r
        assert r.survived, r
    by_kind = {r.kind: r for r in rows}
    # detected <= injected (no other source); >= 1 (a reply the client already gave up on under
    # heavy load is discarded unseen)
    assert 1 <= by_kind["exception"].detected.get("busy_exceptions", 0) <= by_kind["exception"].injected
    assert by_kind["disconnect"].detected.get("connection_errors", 0) >= 1
    if transport == "modbus-socket":
        assert 1 <= by_kind["corrupt"].detected.get("crc_errors", 0) <= by_kind["corrupt"].injected
