"""Shared pieces of the CAN and Modbus rigs: retry backoff, safe shutdown, limit checks."""

import pytest

from setmem_hil.drivers.safety import check_dwell as check_duration, check_sine_command
from setmem_hil.drivers.transport import RetryPolicy, SafeShutdown
from setmem_hil.errors import DeviceError, SafetyLimitError
from setmem_hil.io.procedure import SafetyLimits


def test_backoff_doubles_and_is_capped():
    delays = list(RetryPolicy(reply_timeout_s=0.1, max_attempts=6, backoff_s=0.01, backoff_max_s=0.05).delays())
    assert delays == pytest.approx([0.0, 0.01, 0.02, 0.04, 0.05, 0.05])


@pytest.mark.parametrize("exc", [DeviceError("link lost"), KeyboardInterrupt()])
def test_armed_block_stops_on_any_abort_and_keeps_the_original_error(exc):
    calls = []

    def failing_stop():
        calls.append("stop")
        raise DeviceError("stop failed too")

    guard = SafeShutdown(failing_stop)
    with pytest.raises(type(exc)) as info:
        with guard.armed():
            raise exc
    assert info.value is exc and calls == ["stop"]


def test_armed_block_does_not_stop_on_success():
    calls = []
    with SafeShutdown(lambda: calls.append("stop")).armed():
        pass
    assert calls == []


def test_limit_checks_name_the_transport_and_the_limit():
    limits = SafetyLimits(max_amplitude_n=0.5, omega_min_rad_s=1.0, omega_max_rad_s=10.0, max_dwell_s=60.0)
    check_sine_command(limits, 1.0, 0.5, "CAN x")  # on the limits is allowed
    with pytest.raises(SafetyLimitError, match="^CAN x: .*omega 10.5 rad/s"):
        check_sine_command(limits, 10.5, 0.1, "CAN x")
    with pytest.raises(SafetyLimitError, match="amplitude nan N"):
        check_sine_command(limits, 5.0, float("nan"), "Modbus y")
    with pytest.raises(SafetyLimitError, match="max_dwell_s"):
        check_duration(limits, 61.0, "Modbus y")
