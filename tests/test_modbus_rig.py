"""Modbus rig + fake Modbus device (pymodbus server on 127.0.0.1): accuracy, RTU framing,
safety, shutdown and seeded fault injection."""

import dataclasses
import socket
import threading

import numpy as np
import pytest

from setmem_hil.drivers import modbus_registers as mr
from setmem_hil.drivers.transport import RetryPolicy
from setmem_hil.loopback.rigs import open_modbus_loopback_rig
from setmem_hil.errors import DeviceError, DeviceTimeoutError, SafetyLimitError
from setmem_hil.io.procedure import SafetyLimits, SimulationSettings, default_procedure
from setmem_hil.sim_backends.beam import beam_parameters
from setmem_hil.sim_backends.fake_device_core import FakeDeviceCore

ALL_KINDS = ["timeout", "truncate", "corrupt", "duplicate", "reorder", "disconnect", "exception"]


@pytest.fixture(autouse=True)
def no_server_thread_left():
    yield
    alive = [t.name for t in threading.enumerate() if t.name.startswith("fake-modbus-")]
    assert not alive, f"fake Modbus servers left running: {alive}"


def _procedure(faults=None, noise="none", limits=SafetyLimits(), framer="socket"):
    proc = default_procedure()
    backend = dataclasses.replace(
        proc.backend, kind="modbus-loopback", simulation=SimulationSettings(noise_profile=noise),
        faults=dict(faults or {}), transport={"framer": framer},
    )
    return dataclasses.replace(proc, backend=backend, safety=limits)


def _lockin(block, omega):
    """Least-squares sine fit (IEEE 1057, frequency known) of both channels: G = R / F."""
    X = np.column_stack([np.sin(omega * block.t_s), np.cos(omega * block.t_s), np.ones_like(block.t_s)])
    cf = np.linalg.lstsq(X, block.force, rcond=None)[0]
    cr = np.linalg.lstsq(X, block.response, rcond=None)[0]
    return complex(cr[0], cr[1]) / complex(cf[0], cf[1])


def _dwell(rig, index, omega, amplitude=0.5, settle_s=None, n=1024):
    rig.begin_measurement(index)
    fs = 32 * omega / (2 * np.pi)
    rig.sensor.set_sample_rate(fs)
    rig.exciter.set_sine(omega, amplitude)
    rig.sensor.wait(settle_s if settle_s is not None else 2048 / fs)
    block = rig.sensor.acquire(n / fs)
    rig.exciter.stop()
    return block


def test_dwell_through_modbus_tcp_recovers_the_true_frequency_response():
    truth = beam_parameters()
    with open_modbus_loopback_rig(_procedure(), seed=1) as rig:
        assert rig.metadata.response_range == pytest.approx(1000.0)
        for i, omega in enumerate([6.0, 17.0]):
            block = _dwell(rig, i, omega)
            assert block.t_s.size == 1024
            g_true = truth.frequency_response(np.array([omega]))[0]
            assert abs(_lockin(block, omega) - g_true) < 0.02 * abs(g_true)


@pytest.mark.parametrize("framer", ["socket", "rtu"])
def test_samples_equal_the_device_model_driven_directly_to_one_lsb(framer):
    proc = _procedure(noise="fully_damped", framer=framer)
    with open_modbus_loopback_rig(proc, seed=4) as rig:
        block = _dwell(rig, 3, 40.0, settle_s=7.5, n=700)
        md = rig.metadata
    direct = FakeDeviceCore.from_procedure(proc, 4)
    direct.begin_measurement(3)
    direct.set_sample_rate(mr.wire_sample_rate(32 * 40.0 / (2 * np.pi)))
    direct.set_sine(40.0, 0.5)
    direct.wait(7.5)
    direct.capture(700)
    ref = direct.read_buffer(0, 700)
    assert np.max(np.abs(block.force - ref.force)) <= md.force_range_n / (2**31 - 1)
    assert np.max(np.abs(block.response - ref.response)) <= md.response_range / (2**31 - 1)
    assert np.max(np.abs(block.t_s - ref.t_s)) <= 2e-9
    assert np.max(np.abs(np.diff(block.t_s) * md.sample_rate_hz - 1)) < 1e-6  # the dwell's check


def test_limits_are_enforced_before_anything_is_sent():
    limits = SafetyLimits(max_amplitude_n=0.5, omega_min_rad_s=1.0, omega_max_rad_s=50.0, max_dwell_s=100.0)
    with open_modbus_loopback_rig(_procedure(limits=limits), seed=1) as rig:
        before = rig.owned[0].requests
        with pytest.raises(SafetyLimitError, match="amplitude 0.6 N outside"):
            rig.exciter.set_sine(5.0, 0.6)
        with pytest.raises(SafetyLimitError, match="omega 0.5 rad/s outside"):
            rig.exciter.set_sine(0.5, 0.1)
        with pytest.raises(SafetyLimitError, match="max_dwell_s"):
            rig.sensor.wait(150.0)
        assert rig.owned[0].requests == before
        assert rig.owned[0].core.status().output_on is False


def test_close_commands_zero_stops_the_server_and_is_idempotent():
    rig = open_modbus_loopback_rig(_procedure(), seed=1)
    port = rig.owned[0].port
    rig.exciter.set_sine(5.0, 0.3)
    assert rig.owned[0].core.status().output_on
    rig.close()
    rig.close()
    assert rig.owned[0].core.status().output_on is False
    with socket.socket() as s:
        assert s.connect_ex(("127.0.0.1", port)) != 0  # nobody listens any more


def test_device_exception_is_a_typed_error_and_the_output_is_zeroed():
    with open_modbus_loopback_rig(_procedure(limits=SafetyLimits(max_amplitude_n=50.0)), seed=1) as rig:
        rig.exciter.set_sine(5.0, 0.2)
        with pytest.raises(mr.ModbusExceptionError, match="exception response to function 16 with code 3") as info:
            rig.exciter.set_sine(5.0, 20.0)  # above the fake shaker's 10 N range
        assert isinstance(info.value, DeviceError)
        assert rig.owned[0].core.status().output_on is False
        with pytest.raises(mr.ModbusExceptionError, match="code 2"):
            rig.link.write(mr.REG_STATUS, [1], "write to a read-only register")


def test_vanished_server_gives_device_timeout_error():
    with open_modbus_loopback_rig(_procedure(), seed=1) as rig:
        rig.owned[0].stop()
        rig.link.retry = RetryPolicy(0.05, 3, 0.005, 0.01)
        with pytest.raises(DeviceTimeoutError, match="failed after 3 attempts"):
            rig.exciter.set_sine(5.0, 0.1)


@pytest.mark.parametrize(
    "framer, kinds",
    [("socket", ALL_KINDS), ("rtu", ["timeout", "truncate", "corrupt", "disconnect", "exception"])],
)
def test_injected_faults_are_survived_and_corrupted_data_never_used(framer, kinds):
    """Same seed with and without faults: the samples are identical (nothing corrupted was used)."""
    blocks = {}
    for label, faults in (("clean", {}), ("faulty", {"rate": 0.04, "kinds": kinds, "seed": 9})):
        with open_modbus_loopback_rig(_procedure(faults, noise="fully_damped", framer=framer), seed=5) as rig:
            blocks[label] = [_dwell(rig, i, w, settle_s=20.0, n=400) for i, w in enumerate([3.0, 9.0])]
            if label == "faulty":
                injected, stats = rig.owned[0].injected, rig.transport_statistics()
    for clean, faulty in zip(blocks["clean"], blocks["faulty"]):
        np.testing.assert_array_equal(clean.t_s, faulty.t_s)
        np.testing.assert_array_equal(clean.force, faulty.force)
        np.testing.assert_array_equal(clean.response, faulty.response)
    assert sum(injected.values()) >= 5, injected
    assert stats["retries"] >= sum(injected.get(k, 0) for k in ("exception", "timeout")), (stats, injected)
    if framer == "socket" and injected.get("corrupt"):
        # corrupted pages are caught by their CRC (a reply the client already gave up on is
        # discarded unseen, hence <=)
        assert 1 <= stats.get("crc_errors", 0) <= injected["corrupt"]


@pytest.mark.parametrize(
    "transport, message",
    [({"framer": "ascii"}, "key 'framer': expected one of \\['socket', 'rtu'\\], found 'ascii'"),
     ({"unit": 0}, "key 'unit': expected an integer in \\[1, 247\\]")],
)
def test_bad_transport_options_are_procedure_errors(transport, message):
    from setmem_hil.errors import ProcedureError

    proc = _procedure()
    proc = dataclasses.replace(proc, backend=dataclasses.replace(proc.backend, transport=transport))
    with pytest.raises(ProcedureError, match=message):
        open_modbus_loopback_rig(proc, seed=1)


def test_device_watchdog_zeroes_the_output_and_the_host_aborts_the_dwell():
    import time

    with open_modbus_loopback_rig(_procedure(), seed=1) as rig:
        rig.owned[0].watchdog_s = 0.15
        rig.sensor.set_sample_rate(50.0)
        rig.exciter.set_sine(5.0, 0.2)
        time.sleep(0.6)
        assert rig.owned[0].core.status().output_on is False
        with pytest.raises(DeviceError, match="exciter output dropped by the device"):
            rig.sensor.acquire(1.0)
