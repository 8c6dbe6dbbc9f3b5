"""Issue 26: the drive level closed on a sampled force, against a generator whose true gain is
known to the test only."""

import math

import numpy as np
import pytest

from setmem_hil.drivers.instruments.drive_level import FORCE_TRIP, LEVEL_TOLERANCE, ForceLeveller, LevelledExciter, held_waveform_gain
from setmem_hil.errors import SafetyLimitError


class FakeSource:
    """A generator: amplitude (peak V), output state; nothing else matters here."""

    name, model = "fgen", "fake"
    frequency_limits_hz = (1e-3, 1e6)
    amplitude_limits_v = (1e-3, 5.0)

    def __init__(self):
        self.volts, self.output, self.frequency_hz = 0.0, False, 1.0

    def set_frequency_hz(self, f):
        self.frequency_hz = f

    def set_amplitude_v(self, v):
        self.volts = v

    def set_output(self, on):
        self.output = on


def test_the_gain_of_a_held_waveform_is_found_from_a_record_that_starts_anywhere():
    rng = np.random.default_rng(4)
    points = rng.uniform(-1, 1, 5000)
    rate = 200.0
    for start in (0.0, 3.217, 17.9):
        t = start + np.arange(3000) / 1300.0  # a sensor at its own, unrelated rate
        held = points[np.floor(t * rate + 1e-9).astype(int) % points.size]
        force = 0.734 * held + 0.002 * rng.standard_normal(t.size)
        assert held_waveform_gain(t, force, points, rate) == pytest.approx(0.734, rel=2e-3)


@pytest.mark.parametrize("true_gain_ratio", [0.5, 1.1, 1.3, 2.5])
def test_the_level_converges_on_the_measured_force_and_never_trips(true_gain_ratio):
    source = FakeSource()
    exciter = LevelledExciter(source, newton_per_volt=4.0, max_drive_v=5.0)
    leveller = ForceLeveller(exciter, max_force_n=1.0, force_room=lambda: 0.02, where="test")
    peaks = []

    def take(length_s, rate_hz):  # the force the rig really applies: true gain x volts
        t = np.arange(int(max(50, length_s * rate_hz))) / max(rate_hz, 1.0)
        force = 4.0 * true_gain_ratio * source.volts * np.sin(2 * math.pi * t)
        peaks.append(4.0 * true_gain_ratio * source.volts)
        return t, force

    exciter.set_sine(2 * math.pi, 1.0)
    assert source.volts == pytest.approx(0.25 * 1.0 / 4.0)  # a quarter of the nominal level first
    leveller.level(take)
    final = 4.0 * true_gain_ratio * source.volts
    assert final == pytest.approx(1.0 / 1.02, rel=LEVEL_TOLERANCE)
    assert max(peaks) <= FORCE_TRIP * 1.0 and not exciter.needs_level


def test_a_force_above_the_trip_switches_the_output_off_first():
    source = FakeSource()
    exciter = LevelledExciter(source, newton_per_volt=4.0)
    leveller = ForceLeveller(exciter, max_force_n=1.0, force_room=lambda: 0.0, where="test")
    exciter.set_sine(2 * math.pi, 1.0)
    t = np.arange(200) / 100.0
    with pytest.raises(SafetyLimitError, match="exceeds max_amplitude_n"):
        leveller.force_peak(t, 1.2 * np.sin(2 * math.pi * t))
    assert not source.output


def test_an_output_off_that_cannot_be_read_back_is_said_not_confirmed():
    from setmem_hil.errors import DeviceError, OutputNotConfirmedOffError

    class DeadLink(FakeSource):
        def set_output(self, on):
            if not on:
                raise DeviceError("fgen: the instrument closed the connection")
            super().set_output(on)

        def reconnect(self):
            raise DeviceError("fgen: no answer on a fresh connection")

    exciter = LevelledExciter(DeadLink(), newton_per_volt=4.0)
    exciter.set_sine(2 * math.pi, 1.0)
    assert not exciter.confirmed_off
    with pytest.raises(OutputNotConfirmedOffError, match="could not be confirmed off.*switch it off at the instrument"):
        exciter.stop()
    assert not exciter.confirmed_off
