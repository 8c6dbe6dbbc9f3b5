"""Serial rig over the fake serial device (socket:// URL): end to end, faults, safety."""

import socket
import threading

import numpy as np
import pytest

from setmem_hil.drivers import serial_protocol as sp
from setmem_hil.drivers.transport import RetryPolicy
from setmem_hil.drivers.serial_rig import SerialLink, SerialRig
from setmem_hil.drivers.sine_dwell import DwellSettings, SineDwellExperiment
from setmem_hil.errors import DeviceTimeoutError, SafetyLimitError
from setmem_hil.io.procedure import SafetyLimits, default_procedure, thesis_beam_prior
from setmem_hil.sim_backends.beam import beam_parameters
from setmem_hil.sim_backends.core_rig import CoreRig
from setmem_hil.sim_backends.fake_device_core import FRAME_FAULT_KINDS, FakeDeviceCore, FaultSettings
from setmem_hil.sim_backends.fake_serial_device import FakeSerialDevice

TRUTH = beam_parameters()
POLICY = RetryPolicy(reply_timeout_s=0.1, max_attempts=6, backoff_s=0.001)
SCRIPTED = RetryPolicy(reply_timeout_s=1.0, max_attempts=3, backoff_s=0.001)  # no spurious timeouts


class ScriptedDevice:
    """Answers a fixed list of (expected request, reply) pairs; records unexpected requests."""

    def __init__(self, pairs):
        self.pairs = list(pairs)
        self.unexpected = []
        self.server = socket.create_server(("127.0.0.1", 0))
        self.url = f"socket://127.0.0.1:{self.server.getsockname()[1]}"
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        conn, _ = self.server.accept()
        buf = b""
        with conn:
            while self.pairs:
                data = conn.recv(4096)
                if not data:
                    return
                buf += data
                while b"\n" in buf and self.pairs:
                    line, buf = buf.split(b"\n", 1)
                    expected, reply = self.pairs.pop(0)
                    if line + b"\n" != expected:
                        self.unexpected.append(line)
                    conn.sendall(reply)
            self.done.wait(2.0)  # keep the connection open until the test is over

    def close(self):
        self.done.set()
        self.server.close()
        self.thread.join(1.0)


def test_link_exchanges_exact_bytes_and_skips_stale_answers():
    ok = lambda seq, *v: sp.encode_response(seq, *v)  # noqa: E731
    dev = ScriptedDevice([
        (sp.encode_request(1, "SINE", 2.0, 0.5), ok(0) + ok(1)),  # a stale answer first
        (sp.encode_request(2, "STOP"), ok(2) + ok(2)),  # duplicated answer
        (sp.encode_request(3, "RATE", 10.0), ok(3)),
    ])
    link = SerialLink(dev.url, SCRIPTED)
    try:
        link.request("SINE", 2.0, 0.5)
        link.request("STOP")
        link.request("RATE", 10.0)
    finally:
        link.close()
        dev.close()
    assert dev.pairs == [] and dev.unexpected == []
    assert link.stats["stale_discarded"] == 2


def test_link_retries_a_corrupted_answer_with_the_same_bytes():
    good = sp.encode_response(1)
    bad = good.replace(b"OK", b"OJ")
    req = sp.encode_request(1, "STOP")
    dev = ScriptedDevice([(req, bad), (req, good)])
    link = SerialLink(dev.url, SCRIPTED)
    try:
        link.request("STOP")
    finally:
        link.close()
        dev.close()
    assert dev.unexpected == [] and link.stats["retries"] == 1


def test_link_times_out_with_a_typed_error():
    dev = ScriptedDevice([(sp.encode_request(1, "STOP"), b"")] * 2)
    link = SerialLink(dev.url, RetryPolicy(reply_timeout_s=0.02, max_attempts=2, backoff_s=0.001))
    try:
        with pytest.raises(DeviceTimeoutError, match="no answer within 0.02 s.*2 attempts"):
            link.request("STOP")
    finally:
        link.close()
        dev.close()


def _serial_experiment(seed, faults=None, settings=None):
    core = FakeDeviceCore.from_procedure(default_procedure(), seed, faults=faults or FaultSettings())
    dev = FakeSerialDevice(core)
    rig = SerialRig(dev.url, POLICY)
    exp = SineDwellExperiment(rig, SafetyLimits(), settings, model=thesis_beam_prior().initial_bounds())
    return core, dev, rig, exp


def test_serial_dwell_equals_the_direct_dwell_bit_for_bit():
    core, dev, rig, exp = _serial_experiment(seed=21)
    direct_core = FakeDeviceCore.from_procedure(default_procedure(), 21)
    direct = SineDwellExperiment(CoreRig(direct_core), SafetyLimits(), model=thesis_beam_prior().initial_bounds())
    try:
        for w in (0.9, 4.0):
            m = exp.measure(w)
            assert m == direct.measure(w)  # floats travel as exact round-trip reprs
            assert abs(m.response - TRUTH.frequency_response(w)[0]) <= m.bound
        assert rig.status()["output_on"] == 0.0
    finally:
        exp.close()
        dev.close()
    assert core.status().output_on is False


@pytest.mark.parametrize("kind", FRAME_FAULT_KINDS)
def test_each_frame_fault_is_survived(kind):
    # a disconnect ends the dwell, so it is rarer per frame than the other kinds
    rate = 0.04 if kind == "disconnect" else 0.08
    fault_seed = 7 if kind == "disconnect" else 2
    core, dev, rig, exp = _serial_experiment(seed=5, faults=FaultSettings(rate=rate, kinds=(kind,), seed=fault_seed))
    try:
        for w in (1.1, 7.5):
            m = exp.measure(w)
            assert abs(m.response - TRUTH.frequency_response(w)[0]) <= m.bound
    finally:
        exp.close()
        dev.close()
    if kind != "disconnect":  # disconnects are rare per frame; see the deterministic test below
        assert core.faults.injected[kind] >= 1
    dropped = core.faults.injected["disconnect"]
    assert rig.reconnects <= dropped and (dropped == 0 or rig.reconnects >= 1)
    assert core.status().output_on is False


def test_disconnect_in_the_middle_of_a_dwell_reconnects_and_measures_again():
    core, dev, rig, exp = _serial_experiment(seed=6)
    acquire = rig.sensor.acquire
    calls = []

    def acquire_then_unplug(duration_s):
        calls.append(duration_s)
        if len(calls) == 1:
            dev.drop_connection()  # the cable is pulled while the sine is on
        return acquire(duration_s)

    rig.sensor.acquire = acquire_then_unplug
    try:
        m = exp.measure(2.2)
    finally:
        exp.close()
        dev.close()
    assert abs(m.response - TRUTH.frequency_response(2.2)[0]) <= m.bound
    assert rig.reconnects == 1 and exp.counters["device_error"] == 1
    assert exp.last_result.attempts == 2 and dev.connections == 2
    assert core.status().output_on is False


def test_safety_limit_is_enforced_before_the_wire():
    core, dev, rig, exp = _serial_experiment(seed=1)
    before = dev.requests_served
    try:
        with pytest.raises(SafetyLimitError):
            exp.measure(5000.0)
        assert dev.requests_served == before
    finally:
        exp.close()
        dev.close()


def test_malformed_request_gets_a_frame_error_answer_not_a_crash():
    core = FakeDeviceCore(seed=1)
    with FakeSerialDevice(core) as dev:
        link = SerialLink(dev.url, POLICY)
        try:
            link._port.write(b"@zz garbage*0000\n")
            link._port.write(b"\xff\xfe\n")
            link.request("STOP")  # still answers
        finally:
            link.close()
        assert dev.malformed_requests == 2


def test_device_gone_raises_device_error_and_close_still_releases():
    core, dev, rig, exp = _serial_experiment(seed=1, settings=DwellSettings(max_attempts=2))
    dev.close()
    from setmem_hil.errors import DeviceError

    with pytest.raises(DeviceError, match="after 2 attempts"):
        exp.measure(2.0)
    exp.close()
    assert not rig.link.is_open


def test_fuzz_device_answers_every_line_with_a_decodable_frame():
    from hypothesis import given, settings
    from hypothesis import strategies as st

    core = FakeDeviceCore(seed=1)
    dev = FakeSerialDevice(core)
    valid = [sp.encode_request(k, c, *a) for k, (c, a) in enumerate(
        [("SINE", (2.0, 0.5)), ("RATE", (10.0,)), ("CAPTURE", (8,)), ("READ", (0, 4)), ("STAT?", ()), ("WAIT", (1.0,))])]

    @settings(max_examples=300, deadline=None)
    @given(st.one_of(st.binary(max_size=120), st.sampled_from(valid)), st.integers(0, 200), st.integers(0, 255))
    def check(data, pos, byte):
        if data and pos < len(data) - 1:
            data = data[:pos] + bytes([byte]) + data[pos + 1 :]
        line = data.split(b"\n")[0] + b"\n"
        resp = sp.decode_response(dev._execute(line))  # never raises from the device side
        assert resp.ok or resp.code in ("frame", "range", "command")

    try:
        check()
    finally:
        dev.close()
