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
    with pytest.raises(SafetyLimitError, match="exceeds max_amplitude_n") as caught:
        leveller.force_peak(t, 1.2 * np.sin(2 * math.pi * t))
    assert not source.output
    # a measurement stopped the run with the output on: a rig fault, exit 4, not malformed input's 2 (issue 63)
    from setmem_hil.cli.main import EXIT_BAD_INPUT, EXIT_DEVICE, exit_code_and_message
    from setmem_hil.errors import MeasuredLimitError

    assert isinstance(caught.value, MeasuredLimitError)
    code, message = exit_code_and_message(caught.value)
    assert code == EXIT_DEVICE and message.startswith("safety stop: test: measured force")
    assert exit_code_and_message(SafetyLimitError("2 N outside the limit; nothing was sent"))[0] == EXIT_BAD_INPUT


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


def test_a_waveform_longer_than_its_record_is_levelled_to_the_designed_peak():
    """The multisine's peak is designed over the record's duration; the uploaded waveform is
    longer (levelling room, doubled after an overrun) and reaches higher there. Its largest point
    must be levelled to the designed peak, so the force stays within the limit everywhere (a bug
    this caught: the longer waveform's peak became the target, 1.13 N for a 1 N limit)."""
    from setmem_hil.estimation.multisine import design_multisine

    class ArbitrarySource(FakeSource):
        class profile:
            class arbitrary:
                max_points = 1_000_000

        def play_arbitrary(self, points, rate):
            self.points, self.rate = np.asarray(points), rate
            return self.points  # what it plays (a generator returns its decoded codes)

    lines = [0.996458, 1.0107, 5.95715, 6.3051]
    duration = 240.0
    signal = design_multisine(lines, 1.0, duration)
    source = ArbitrarySource()
    exciter = LevelledExciter(source, newton_per_volt=4.0, max_drive_v=5.0)
    exciter.waveform_room = 2.0
    exciter.set_multisine_record(signal, duration)
    whole = signal.force(np.arange(source.points.size) / source.rate)
    assert np.max(np.abs(whole)) > 1.0  # the longer waveform does reach past the designed peak
    assert exciter.target_n <= signal.peak_bound(duration) <= 1.0 + 1e-9
    assert np.max(np.abs(source.points)) == pytest.approx(1.0)  # its largest point plays at the target


def test_a_short_record_of_close_lines_is_aligned_where_the_clock_puts_it():
    """Five lines within 0.3 rad/s at 17 rad/s, a 0.6 s record: the waveform looks alike at many
    places. Told where the record starts (to 10 ms, as the rig's clock knows it), the gain is
    right at every place tried, with the sensor's noise and an 8-bit scope's quantization."""
    from setmem_hil.estimation.multisine import design_multisine

    rng = np.random.default_rng(7)
    lines = list(np.linspace(16.65, 16.93, 5))
    rate = 91.62636647118308
    points = design_multisine(lines, 1.0, 100.0).force(np.arange(19766) / rate)
    points /= np.max(np.abs(points))
    code = 1.0 / 25 * 0.005 / 0.0225  # a DS1000Z code at 5 mV/div, in newtons of a 22.5 mV/N sensor
    for start in rng.uniform(0.0, 200.0, 12):
        t = start + np.arange(3000) * 2e-4
        force = 0.4961 * points[np.floor(t * rate + 1e-9).astype(int) % points.size]
        force = np.round((force + 0.2 * code * rng.standard_normal(t.size)) / code) * code
        assert held_waveform_gain(t, force, points, rate, near_s=start + rng.uniform(-0.01, 0.01)) == pytest.approx(0.4961, rel=0.01)


def _dwell_at_half_level(leveller, exciter, source, force_of_volts):
    """A later dwell (gain measured before): level, then the dwell's own record of the force."""
    records = []

    def take(length_s, rate_hz):
        t = np.arange(400) / 100.0
        records.append(force_of_volts(source.volts))
        return t, force_of_volts(source.volts) * np.sin(2 * math.pi * t)

    exciter.set_sine(2 * math.pi, 1.0)
    leveller.level(take)
    levelling = len(records)
    t, force = take(120.0, 100.0)  # the dwell's record
    leveller.force_peak(t, force)
    leveller.confirm_level()
    return levelling, records[-1]


def test_a_later_dwell_levels_with_one_record_and_its_own_record_confirms_the_level():
    source = FakeSource()
    exciter = LevelledExciter(source, newton_per_volt=4.0, max_drive_v=5.0)
    leveller = ForceLeveller(exciter, max_force_n=1.0, force_room=lambda: 0.02, where="test")
    linear = lambda volts: 4.4 * volts  # noqa: E731 - the true gain, 10 % above the nominal
    first, _ = _dwell_at_half_level(leveller, exciter, source, linear)
    assert first >= 2  # from a quarter of the level at the nominal gain: measured again
    later, force = _dwell_at_half_level(leveller, exciter, source, linear)
    assert later == 1  # from half the level at the measured gain: the dwell's record confirms it
    assert force == pytest.approx(1.0 / 1.02, rel=LEVEL_TOLERANCE)


def test_a_level_that_comes_out_high_discards_the_record_and_every_later_level_is_measured():
    from setmem_hil.errors import DataQualityError

    source = FakeSource()
    exciter = LevelledExciter(source, newton_per_volt=4.0, max_drive_v=5.0)
    leveller = ForceLeveller(exciter, max_force_n=1.0, force_room=lambda: 0.06, where="test")
    # an amplifier whose gain grows with the level: 8 % more at twice the drive
    growing = lambda volts: 4.0 * volts * (1.0 + 0.08 * volts / 0.125)  # noqa: E731
    _dwell_at_half_level(leveller, exciter, source, growing)
    with pytest.raises(DataQualityError, match="above its level"):
        _dwell_at_half_level(leveller, exciter, source, growing)
    levelling, force = _dwell_at_half_level(leveller, exciter, source, growing)
    assert levelling >= 2 and force <= (1 + LEVEL_TOLERANCE) / 1.06
