"""Fake device core: commands, virtual clock, noise determinism per (seed, n), fault injection."""

import numpy as np
import pytest

from setmem_hil.errors import DeviceError, ProcedureError
from setmem_hil.errors import DeviceRejectedError as DeviceCommandError
from setmem_hil.sim_backends.fake_device_core import (
    FAULT_KINDS,
    FakeDeviceCore,
    FaultSettings,
)


def _capture(core, index, omega=2.0, n=256, attempt=0):
    core.begin_measurement(index, attempt)
    core.set_sample_rate(32 * omega / (2 * np.pi))
    core.set_sine(omega, 1.0)
    core.capture(n)
    return core.read_buffer(0, n)


def test_noise_depends_only_on_seed_and_measurement_index():
    a, b = FakeDeviceCore(seed=5), FakeDeviceCore(seed=5)
    _capture(a, 0)
    _capture(a, 1)
    x = _capture(a, 2)
    y = _capture(b, 2)  # fresh device, straight to measurement 2 (a resumed campaign)
    assert np.array_equal(x.response - x.response.mean(), y.response - y.response.mean())
    assert np.array_equal(x.force, y.force)
    z = _capture(FakeDeviceCore(seed=6), 2)
    assert not np.array_equal(x.force, z.force)


def test_virtual_clock_and_timestamps():
    core = FakeDeviceCore(seed=1)
    core.begin_measurement(0)
    core.set_sample_rate(10.0)
    core.set_sine(1.0, 0.5)
    t0 = core.time_s
    core.capture(100)
    block = core.read_buffer(0, 100)
    assert np.allclose(np.diff(block.t_s), 0.1)
    assert core.time_s == pytest.approx(t0 + 10.0)
    core.wait(300.0)
    assert core.time_s == pytest.approx(t0 + 310.0)
    st = core.status()
    assert st.output_on and st.omega_rad_s == 1.0 and st.amplitude_n == 0.5 and st.buffer_length == 100


def test_force_channel_is_the_commanded_sine_plus_small_noise():
    core = FakeDeviceCore(seed=2, force_noise_n=1e-3)
    b = _capture(core, 0, omega=3.0, n=320)
    t = b.t_s - b.t_s[0]
    assert np.std(b.force - np.sin(3.0 * t)) == pytest.approx(1e-3, rel=0.2)


def test_capture_with_same_request_id_is_idempotent():
    core = FakeDeviceCore(seed=2)
    core.begin_measurement(0)
    core.set_sine(1.0, 1.0)
    core.capture(50, request_id=7)
    t_after = core.time_s
    first = core.read_buffer(0, 50)
    core.capture(50, request_id=7)
    assert core.time_s == t_after
    assert np.array_equal(core.read_buffer(0, 50).response, first.response)
    core.capture(50, request_id=8)
    assert core.time_s > t_after


def test_device_limits_raise_typed_errors():
    core = FakeDeviceCore()
    with pytest.raises(DeviceCommandError, match="amplitude"):
        core.set_sine(1.0, 100.0)
    with pytest.raises(DeviceError, match="omega"):
        core.set_sine(float("nan"), 1.0)
    with pytest.raises(DeviceCommandError, match="outside buffer"):
        core.read_buffer(0, 1)
    with pytest.raises(DeviceCommandError, match="capture"):
        core.capture(0)


def test_fault_settings_validation_names_the_key():
    assert FaultSettings.from_mapping({"rate": 0.1, "kinds": ["nan"], "seed": 3}) == FaultSettings(0.1, ("nan",), 3)
    with pytest.raises(ProcedureError, match="'rate'"):
        FaultSettings.from_mapping({"rate": 2})
    with pytest.raises(ProcedureError, match="unknown kinds"):
        FaultSettings.from_mapping({"kinds": ["gremlins"]})


@pytest.mark.parametrize("kind", ["saturation", "nan", "inf", "timestamp_jump"])
def test_data_faults_are_injected_counted_and_detectable(kind):
    core = FakeDeviceCore(seed=1, faults=FaultSettings(rate=1.0, kinds=(kind,), seed=4))
    b = _capture(core, 0)
    assert core.faults.injected[kind] == 1
    if kind == "saturation":
        assert np.any(np.abs(b.response) >= core.metadata.response_range)
    elif kind == "nan":
        assert np.isnan(b.response).any()
    elif kind == "inf":
        assert np.isinf(b.force).any()
    else:
        d = np.diff(b.t_s)
        assert d.max() > 1.4 * np.median(d)


def test_fault_rate_is_honoured_statistically():
    inj = FakeDeviceCore(faults=FaultSettings(rate=0.2, kinds=FAULT_KINDS, seed=9)).faults
    hits = sum(inj.draw("corrupt") for _ in range(5000))
    assert abs(hits / 5000 - 0.2) < 0.03
    assert inj.injected["corrupt"] == hits
