"""CAN rig + fake CAN device on python-can's virtual bus: dwell accuracy, safety, faults, shutdown."""

import dataclasses

import can
import can.interfaces.virtual
import numpy as np
import pytest

from setmem_hil.drivers import can_protocol as cp
from setmem_hil.drivers.can_rig import CanLink, CanRig, CanSettings
from setmem_hil.loopback.rigs import open_can_virtual_rig
from setmem_hil.drivers.transport import RetryPolicy
from setmem_hil.errors import DeviceError, DeviceTimeoutError, SafetyLimitError
from setmem_hil.io.procedure import SafetyLimits, SimulationSettings, default_procedure
from setmem_hil.sim_backends.beam import beam_parameters
from setmem_hil.sim_backends.fake_can_device import FakeCanDevice
from setmem_hil.sim_backends.fake_device_core import FakeDeviceCore

FRAME_KINDS = ["timeout", "truncate", "corrupt", "duplicate", "reorder", "disconnect", "error_frame", "bus_off"]


@pytest.fixture(autouse=True)
def no_virtual_channel_left_open():
    """As python-can's own conftest: every test must shut down every virtual bus it opened."""
    yield
    assert not can.interfaces.virtual.channels, f"virtual CAN channels left open: {list(can.interfaces.virtual.channels)}"


def _procedure(faults=None, noise="none", limits=SafetyLimits()):
    proc = default_procedure()
    backend = dataclasses.replace(
        proc.backend, kind="can-virtual", simulation=SimulationSettings(noise_profile=noise), faults=dict(faults or {})
    )
    return dataclasses.replace(proc, backend=backend, safety=limits)


def _lockin(block, omega):
    """Least-squares sine fit (IEEE 1057, frequency known) of both channels: G = R / F."""
    X = np.column_stack([np.sin(omega * block.t_s), np.cos(omega * block.t_s), np.ones_like(block.t_s)])
    cf = np.linalg.lstsq(X, block.force, rcond=None)[0]
    cr = np.linalg.lstsq(X, block.response, rcond=None)[0]
    return complex(cr[0], cr[1]) / complex(cf[0], cf[1])


def _dwell(rig, index, omega, amplitude=0.5, settle=2048, n=1024):
    rig.begin_measurement(index)
    fs = 32 * omega / (2 * np.pi)
    rig.sensor.set_sample_rate(fs)
    rig.exciter.set_sine(omega, amplitude)
    rig.sensor.acquire(settle / fs)
    block = rig.sensor.acquire(n / fs)
    rig.exciter.stop()
    return block


class _Spy:
    """A second bus on the channel recording every frame (an independent observer)."""

    def __init__(self, channel):
        self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)

    def commands(self, node=0x21):
        out = []
        while (msg := self.bus.recv(0)) is not None:
            if msg.arbitration_id == cp.COMMAND_BASE + node:
                out.append(cp.decode_frame(node, msg.arbitration_id, bytes(msg.data)))
        return out

    def close(self):
        self.bus.shutdown()


def test_dwell_through_can_recovers_the_true_frequency_response():
    truth = beam_parameters()
    with open_can_virtual_rig(_procedure(), seed=1) as rig:
        assert rig.metadata.force_range_n == pytest.approx(10.0)
        for i, omega in enumerate([6.0, 17.0]):
            block = _dwell(rig, i, omega)
            assert block.t_s.size == 1024
            assert np.all(np.diff(block.t_s) > 0)
            g_true = truth.frequency_response(np.array([omega]))[0]
            assert abs(_lockin(block, omega) - g_true) < 0.02 * abs(g_true)


def test_samples_through_can_equal_the_device_model_driven_directly_to_one_lsb():
    proc = _procedure(noise="fully_damped")
    with open_can_virtual_rig(proc, seed=4) as rig:
        block = _dwell(rig, 3, 40.0, settle=300, n=700)
        md = rig.metadata
    direct = FakeDeviceCore.from_procedure(proc, 4)
    direct.begin_measurement(3)
    direct.set_sample_rate(cp.wire_sample_rate(32 * 40.0 / (2 * np.pi)))  # the rate as sent (binary32)
    direct.set_sine(40.0, 0.5)
    direct.capture(300)
    direct.capture(700)
    ref = direct.read_buffer(0, 700)
    lsb_f = md.force_range_n / (2**31 - 1)
    lsb_r = md.response_range / (2**31 - 1)
    assert np.max(np.abs(block.force - ref.force)) <= lsb_f
    assert np.max(np.abs(block.response - ref.response)) <= lsb_r
    assert np.max(np.abs(block.t_s - ref.t_s)) <= 2e-9  # ns block start and ns deviations
    # the dwell's timestamp check (1e-6 of a period) holds for these times
    dt = np.diff(block.t_s)
    assert np.max(np.abs(dt * rig.metadata.sample_rate_hz - 1)) < 1e-6


def test_limits_are_enforced_before_anything_is_sent():
    limits = SafetyLimits(max_amplitude_n=0.5, omega_min_rad_s=1.0, omega_max_rad_s=50.0, max_dwell_s=100.0)
    with open_can_virtual_rig(_procedure(limits=limits), seed=1) as rig:
        spy = _Spy(rig.owned[0].channel)
        try:
            with pytest.raises(SafetyLimitError, match="amplitude 0.6 N outside"):
                rig.exciter.set_sine(5.0, 0.6)
            with pytest.raises(SafetyLimitError, match="omega 60.0 rad/s outside"):
                rig.exciter.set_sine(60.0, 0.1)
            with pytest.raises(SafetyLimitError, match="max_dwell_s"):
                rig.sensor.acquire(101.0)
            assert spy.commands() == []
            assert rig.owned[0].core.status().output_on is False
        finally:
            spy.close()


def test_close_commands_zero_releases_the_bus_and_is_idempotent():
    rig = open_can_virtual_rig(_procedure(), seed=1)
    spy = _Spy(rig.owned[0].channel)
    try:
        rig.exciter.set_sine(5.0, 0.3)
        assert rig.owned[0].core.status().output_on
        rig.close()
        rig.close()
        ops = [c.opcode for c in spy.commands()]
        assert ops[-1] == cp.Opcode.STOP
        assert rig.owned[0].core.status().output_on is False
    finally:
        spy.close()


def test_device_rejection_is_a_typed_error_and_the_output_is_zeroed():
    # limits wider than the fake shaker's own range (10 N): the device answers OUT_OF_RANGE
    with open_can_virtual_rig(_procedure(limits=SafetyLimits(max_amplitude_n=50.0)), seed=1) as rig:
        rig.exciter.set_sine(5.0, 0.2)
        with pytest.raises(DeviceError, match="SET_AMPLITUDE.*OUT_OF_RANGE"):
            rig.exciter.set_sine(5.0, 20.0)
        assert rig.owned[0].core.status().output_on is False
        assert rig.output_on is False


def test_silent_device_gives_device_timeout_error_and_close_still_works():
    with open_can_virtual_rig(_procedure(), seed=1) as rig:
        rig.owned[0].stop()  # the device disappears: nobody answers
        rig.link.settings = dataclasses.replace(rig.link.settings, retry=RetryPolicy(0.02, 3, 0.005, 0.01))
        with pytest.raises(DeviceTimeoutError, match="no valid reply to SET_FREQUENCY after 3 attempts"):
            rig.exciter.set_sine(5.0, 0.1)


def test_keyboard_interrupt_mid_acquisition_commands_zero():
    core = FakeDeviceCore(seed=2)
    channel = "setmem-test-kbint"
    device = FakeCanDevice(core, channel).start()
    state = {"armed": False, "n": 0}

    class InterruptingBus:
        def __init__(self):
            self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)

        def send(self, msg, timeout=None):
            self.bus.send(msg, timeout)

        def recv(self, timeout=None):
            if state["armed"]:
                state["n"] += 1
                if state["n"] == 50:
                    raise KeyboardInterrupt
            return self.bus.recv(timeout)

        def shutdown(self):
            self.bus.shutdown()

    try:
        rig = CanRig(CanLink(InterruptingBus, CanSettings()), SafetyLimits())
        rig.sensor.set_sample_rate(50.0)
        rig.exciter.set_sine(5.0, 0.2)
        state["armed"] = True
        with pytest.raises(KeyboardInterrupt):
            rig.sensor.acquire(20.0)
        assert core.status().output_on is False
        rig.close()
    finally:
        device.stop()


def test_bus_operation_error_reopens_the_bus_and_the_command_succeeds():
    core = FakeDeviceCore(seed=2)
    channel = "setmem-test-busoff"
    device = FakeCanDevice(core, channel).start()
    opened = []

    class FlakyBus:
        """First bus raises CanOperationError (as a controller in bus-off) on its first recv."""

        def __init__(self):
            self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
            self.fail = not opened
            opened.append(self)

        def send(self, msg, timeout=None):
            self.bus.send(msg, timeout)

        def recv(self, timeout=None):
            if self.fail:
                self.fail = False
                raise can.CanOperationError("bus-off")
            return self.bus.recv(timeout)

        def shutdown(self):
            self.bus.shutdown()

    try:
        rig = CanRig(CanLink(FlakyBus, CanSettings()), SafetyLimits())
        rig.exciter.set_sine(5.0, 0.2)
        assert core.status().output_on and core.status().omega_rad_s == pytest.approx(5.0)
        assert rig.transport_statistics()["reconnects"] == 1
        assert len(opened) == 2
        rig.close()
    finally:
        device.stop()


def test_injected_faults_are_survived_and_corrupted_data_never_used():
    """Every frame-level fault kind and CAN error/bus-off: the samples equal a fault-free run's."""
    clean_blocks, faulty_blocks = [], []
    with open_can_virtual_rig(_procedure(noise="fully_damped"), seed=5) as rig:
        for i, omega in enumerate([3.0, 9.0]):
            clean_blocks.append(_dwell(rig, i, omega, settle=256, n=512))
    faults = {"rate": 0.03, "kinds": FRAME_KINDS, "seed": 11}
    with open_can_virtual_rig(_procedure(faults, noise="fully_damped"), seed=5) as rig:
        for i, omega in enumerate([3.0, 9.0]):
            faulty_blocks.append(_dwell(rig, i, omega, settle=256, n=512))
        injected = rig.owned[0].injected
        stats = rig.transport_statistics()
    for clean, faulty in zip(clean_blocks, faulty_blocks):
        np.testing.assert_array_equal(clean.t_s, faulty.t_s)
        np.testing.assert_array_equal(clean.force, faulty.force)
        np.testing.assert_array_equal(clean.response, faulty.response)
    for kind in ("timeout", "truncate", "corrupt", "duplicate", "reorder"):
        assert injected.get(kind, 0) > 0, (kind, injected)
    assert stats["crc_errors"] + stats["malformed_frames"] >= injected["corrupt"] * 0.5
    assert stats["duplicate_frames_discarded"] > 0
    assert stats["resend_rounds"] > 0


def test_disconnect_and_bus_off_every_time_are_recovered_then_reported():
    faults = {"rate": 0.15, "kinds": ["disconnect", "bus_off", "error_frame"], "seed": 3}
    with open_can_virtual_rig(_procedure(faults), seed=5) as rig:
        block = _dwell(rig, 0, 6.0, settle=64, n=128)
        injected = rig.owned[0].injected
        stats = rig.transport_statistics()
    assert block.t_s.size == 128
    assert injected.get("disconnect", 0) > 0 and injected.get("bus_off", 0) > 0
    # every reconnect was caused by an injected bus-off (a frame still queued on a bus being
    # reopened may go unread under heavy load, hence <=)
    assert 1 <= stats["reconnects"] <= injected["bus_off"]
    assert stats.get("error_frames", 0) <= injected.get("error_frame", 0)


@pytest.mark.parametrize(
    "transport, faults, message",
    [
        ({"node": 200}, {}, "key 'node': expected an integer in \\[1, 127\\], found 200"),
        ({"reply_timeout_s": "fast"}, {}, "key 'reply_timeout_s': expected a number"),
        ({}, {"rate": 0.1, "kinds": ["bus_of"]}, "unknown kinds \\['bus_of'\\]"),
    ],
)
def test_bad_transport_options_and_fault_kinds_are_procedure_errors(transport, faults, message):
    from setmem_hil.errors import ProcedureError

    proc = _procedure(faults)
    proc = dataclasses.replace(proc, backend=dataclasses.replace(proc.backend, transport=transport))
    with pytest.raises(ProcedureError, match=message):
        open_can_virtual_rig(proc, seed=1)


def test_device_watchdog_zeroes_the_output_and_the_host_aborts_the_dwell():
    import time

    core = FakeDeviceCore(seed=2)
    channel = "setmem-test-watchdog"
    device = FakeCanDevice(core, channel, watchdog_s=0.15).start()
    try:
        rig = CanRig(CanLink(lambda: can.Bus(interface="virtual", channel=channel, receive_own_messages=False)), SafetyLimits())
        rig.sensor.set_sample_rate(50.0)
        rig.exciter.set_sine(5.0, 0.2)
        time.sleep(0.6)  # the host falls silent (e.g. hung): the device drops the output
        assert core.status().output_on is False
        with pytest.raises(DeviceError, match="exciter output dropped by the device"):
            rig.sensor.acquire(1.0)
        rig.close()
    finally:
        device.stop()
