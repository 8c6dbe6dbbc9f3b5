"""A generator plus an oscilloscope as a sampled :class:`~setmem_hil.drivers.protocols.Rig` (issue 26).

One oscilloscope holds the force and the response roles (``channels = { force = 1, response =
[2, 3] }``): every record samples them together, so their ratio needs no common clock. The
measurement is the sine dwell of :mod:`setmem_hil.drivers.sine_dwell` (the transient-aware sine
fit), with three things the scope adds:

* **closed-loop drive level** (:class:`LevelledExciter`, :class:`ScopeSensor.wait`): the output
  comes on at a quarter of the nominal level (the first dwell; later ones at half, with the gain
  measured before); short records of the force (``LEVEL_PERIODS`` periods) re-estimate the drive
  gain and set the level, until the force is within ``LEVEL_TOLERANCE`` of its target. The
  target leaves room for what the force channel may be off by (its calibration, the scope's gain
  accuracy at the force's range), so the true force stays below ``max_amplitude_n`` even with the
  drive gain wrong by tens of percent; a record whose fitted force exceeds ``1.05 x
  max_amplitude_n`` switches the output off and stops the run;
* **vertical ranging**: every channel starts on the largest V/div; the levelling records set
  each channel to the smallest scale holding its peak with room (the gain accuracy is a fraction
  of *full scale*); a clipped record moves that channel up one scale and is taken again;
* **instrument terms in the bound** (:meth:`ScopeSensor.corrected`,
  :mod:`setmem_hil.estimation.channel_errors`): gain accuracy, quantization, calibration and
  timing for every channel used, then the ratio converted to receptance (velocity and
  acceleration sensors).

The time spent (levelling, the trigger wait, records longer than asked because the time scale
comes in 1-2-5 steps) is counted from the clock: ``last_acquire_s`` is what the last acquisition
cost.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import numpy as np

from setmem_hil.drivers.clock import Clock
from setmem_hil.drivers.instruments.phasor_dwell import to_receptance
from setmem_hil.drivers.instruments.sampled_rig import POINTS_PER_PERIOD
from setmem_hil.drivers.instruments.scpi_scope import ClippedChannel, ScopeRecord, ScpiScope
from setmem_hil.drivers.instruments.source import SignalSource
from setmem_hil.drivers.protocols import RigMetadata, SampleBlock
from setmem_hil.drivers.sine_dwell import SineDwellExperiment
from setmem_hil.errors import DataQualityError, DeviceRejectedError, SafetyLimitError
from setmem_hil.estimation.channel_errors import MAX_CLOCK_PHASE_RAD, ChannelError, ratio_error_bound, scope_channel_error
from setmem_hil.estimation.sine_fit import fit_sine
from setmem_hil.model.experiment import Measurement

__all__ = ["ScopeChannel", "LevelledExciter", "ScopeSensor", "ScopeRig", "ScopeDwellExperiment", "FORCE_TRIP"]

log = logging.getLogger(__name__)

FORCE_TRIP = 1.05  # x max_amplitude_n: a fitted force above it switches the output off
LEVEL_TOLERANCE = 0.03
LEVEL_PERIODS = 1.5  # periods of the drive in a levelling record
MIN_LEVEL_RECORD_S = 0.02
MAX_LEVEL_STEPS = 6
MAX_STEP_UP = 3.0  # the most one levelling step multiplies the drive by
MAX_RANGE_STEPS = 6
RANGE_HEADROOM = 1.15  # a channel is ranged for this much more than the peak it showed (the response still grows)


def level_record_s(omega_rad_s: float) -> float:
    """A levelling record: ``LEVEL_PERIODS`` periods of the (lowest) drive frequency."""
    return max(LEVEL_PERIODS * 2 * math.pi / omega_rad_s, MIN_LEVEL_RECORD_S)


def levelling_allowance_s(lowest_rad_s: float) -> float:
    """How long an arbitrary waveform plays before its record: the levelling records (each may
    come out 2.5 times longer on a 1-2-5 time base) and the trigger waits."""
    return MAX_LEVEL_STEPS * 2.5 * level_record_s(lowest_rad_s) * 1.2 + 10.0


def held_waveform_gain(t_s: np.ndarray, force_n: np.ndarray, points: np.ndarray, rate_hz: float) -> float:
    """Force per unit point of a played arbitrary waveform, from a record of the force that
    starts anywhere in it: the record on the waveform's sample grid, aligned by circular
    cross-correlation, then the least-squares scale."""
    grid = np.arange(t_s[0], t_s[-1], 1.0 / rate_hz)
    r = np.interp(grid, t_s, force_n)
    n = points.size
    if r.size < 8 or r.size > n:
        raise DataQualityError(f"a levelling record of {r.size} points on a waveform of {n}: cannot align them")
    corr = np.fft.irfft(np.conj(np.fft.rfft(r, n)) * np.fft.rfft(points, n), n)
    # normalised by each window's energy: the least-squares fit's quality at every alignment
    energy = np.convolve(np.concatenate([points, points[: r.size - 1]]) ** 2, np.ones(r.size), "valid")
    shift = int(np.argmax(corr * np.abs(corr) / np.maximum(energy, 1e-300)))
    # refine within a hold on the record's own samples: the played value at each sample time
    best = (-math.inf, 0.0)
    for offset in np.linspace(-1.0, 1.0, 41):
        k = np.floor((t_s - t_s[0]) * rate_hz + shift + offset).astype(np.int64) % n
        held = points[k]
        gain = float(np.dot(force_n, held) / np.dot(held, held))
        fit = gain * float(np.dot(force_n, held))
        best = max(best, (fit, gain))
    return best[1]


@dataclass(frozen=True)
class ScopeChannel:
    """One oscilloscope channel and the sensor wired to it."""

    number: int
    volt_per_unit: float
    calibration_uncertainty: float = 0.0
    quantity: str = "displacement"


class LevelledExciter:
    """The :class:`~setmem_hil.drivers.protocols.Exciter` of a generator whose level the force
    channel closes (:meth:`ScopeSensor.wait` finishes each :meth:`set_sine`)."""

    FIRST_FRACTION = 0.25  # of the target, with the nominal gain (the first dwell)
    NEXT_FRACTION = 0.5  # with the gain measured at the last frequency

    def __init__(self, source: SignalSource, newton_per_volt: float, max_drive_v: float = math.inf):
        self.source, self.max_drive_v = source, float(max_drive_v)
        self.newton_per_volt = float(newton_per_volt)
        self.gain_estimate = float(newton_per_volt)  # N/V, measured from the force once the output is on
        self.measured = False
        self.on = False
        self.volts = 0.0
        self.omega_rad_s = 0.0
        self.target_n = 0.0
        self.needs_level = False
        self.arbitrary: tuple[np.ndarray, float] | None = None  # the multisine record playing: (points, Sa/s)
        self.lowest_rad_s = 0.0

    def set_sine(self, omega_rad_s: float, amplitude_n: float) -> None:
        frequency_hz = omega_rad_s / (2 * math.pi)
        self._check_drive(amplitude_n, frequency_hz)
        if self.arbitrary is not None:  # back to the generator's own sine, the output off meanwhile
            if self.on:
                self.stop()
            self.source.play_sine()
            self.arbitrary = None
        self.omega_rad_s, self.target_n = float(omega_rad_s), float(amplitude_n)
        self.source.set_frequency_hz(frequency_hz)
        self._start(amplitude_n)

    # -- multisine records through the generator's arbitrary waveform (issue 26) ---------------
    POINTS_PER_PERIOD = POINTS_PER_PERIOD  # of the highest line; held points: the line's amplitude is 2.6 % low, measured anyway
    MIN_POINTS_PER_PERIOD = 5

    @property
    def plays_multisine(self) -> bool:
        return bool(getattr(self.source, "plays_arbitrary", False))

    def set_multisine_record(self, multisine, duration_s: float) -> None:
        """Upload the record (and room for the levelling) as one arbitrary waveform and play it
        at a quarter (then half) of the target level; the levelling finishes it. Its peak is
        checked against the generator's limits before anything is sent."""
        arb = self.source.profile.arbitrary
        top_hz = max(multisine.omegas_rad_s) / (2 * math.pi)
        # the scope's records may come out longer than asked (1-2-5 time base): room for that too
        length = 1.5 * duration_s + levelling_allowance_s(min(multisine.omegas_rad_s))
        rate = self.POINTS_PER_PERIOD * top_hz
        if length * rate > arb.max_points:
            rate = arb.max_points / length
            if rate < self.MIN_POINTS_PER_PERIOD * top_hz:
                raise DeviceRejectedError("range", f"{self.source.name}: a {length:.0f} s multisine record with lines up to "
                                                   f"{top_hz:.4g} Hz needs {self.MIN_POINTS_PER_PERIOD * top_hz * length:.0f} points; "
                                                   f"the {self.source.model} profile holds {arb.max_points}; nothing was sent")
        force = multisine.force(np.arange(int(math.ceil(length * rate))) / rate)
        peak_n = float(np.max(np.abs(force)))
        self._check_drive(peak_n, top_hz)
        if self.on:
            self.stop()
        self.source.play_arbitrary(force / peak_n, rate)
        self.arbitrary = (force / peak_n, rate)
        self.omega_rad_s, self.target_n, self.lowest_rad_s = 0.0, peak_n, min(multisine.omegas_rad_s)
        self._start(peak_n)

    def _check_drive(self, amplitude_n: float, frequency_hz: float) -> None:
        lo, hi = self.source.frequency_limits_hz
        nominal_v = amplitude_n / self.newton_per_volt
        if nominal_v > self.max_drive_v or nominal_v > self.source.amplitude_limits_v[1] or not lo <= frequency_hz <= hi:
            raise SafetyLimitError(f"{self.source.name}: {amplitude_n:g} N at {frequency_hz:.6g} Hz needs {nominal_v:.4g} V at the "
                                   f"nominal {self.newton_per_volt:g} N/V (max_drive_v {self.max_drive_v:g} V, instrument "
                                   f"{self.source.amplitude_limits_v[1]:g} V, {lo:g}-{hi:g} Hz); nothing was sent")

    def _start(self, amplitude_n: float) -> None:
        fraction = self.NEXT_FRACTION if self.measured else self.FIRST_FRACTION
        self.set_volts(fraction * amplitude_n / self.gain_estimate)
        if not self.on:
            self.source.set_output(True)
            self.on = True
        self.needs_level = True

    def set_volts(self, volts: float) -> None:
        vlo, vhi = self.source.amplitude_limits_v
        self.volts = float(min(max(volts, vlo), vhi, self.max_drive_v))
        self.source.set_amplitude_v(self.volts)

    def stop(self) -> None:
        self.on = False
        self.needs_level = False
        self.source.set_output(False)


class ScopeSensor:
    """Sensor, rate-configurable, waiting: force and response channels of one oscilloscope."""

    def __init__(self, scope: ScpiScope, force: ScopeChannel, responses: tuple[ScopeChannel, ...], exciter: LevelledExciter,
                 clock: Clock, max_force_n: float):
        self.scope, self.force, self.responses = scope, force, tuple(responses)
        self.exciter, self.clock, self.max_force_n = exciter, clock, float(max_force_n)
        self.sample_rate_hz = 1000.0
        self.last_acquire_s = 0.0
        self.last_sample_rate_hz = 0.0
        self.last_scales_v: dict[int, float] = {}
        self.last_length_s = 0.0
        self.counters = {"range_up": 0, "level_steps": 0}
        self.waveform_started = 0.0  # clock time the playing arbitrary waveform started

    @property
    def channels(self) -> tuple[ScopeChannel, ...]:
        return (self.force, *self.responses)

    def set_sample_rate(self, rate_hz: float) -> None:
        self.sample_rate_hz = float(rate_hz)  # the scope's memory depth and time scale decide the rate it gives

    # -- the dwell's settling: level the drive, range the channels, let the rest pass --------------
    def wait(self, duration_s: float) -> None:
        start = self.clock.now()
        if self.exciter.arbitrary is not None and self.exciter.needs_level:
            self.waveform_started = start - 1.0  # the output came on just before (a second's room)
        if self.exciter.needs_level:
            self._level()
        left = duration_s - (self.clock.now() - start)
        if left > 0:
            self.clock.sleep(left)
        self.last_acquire_s = self.clock.now() - start

    def force_target_n(self) -> float:
        """The measured force the level aims at: the asked amplitude less what the force channel
        may be off by (calibration, and the scope's gain accuracy at a tightly ranged scale)."""
        p = self.scope.profile
        room = self.force.calibration_uncertainty + p.gain_accuracy * p.divisions / (0.8 * p.divisions / 2.0) / RANGE_HEADROOM
        return self.exciter.target_n / (1.0 + room)

    def _level(self) -> None:
        """Short records: measure the force, correct the drive, range every channel (module docs)."""
        omega = self.exciter.omega_rad_s or self.exciter.lowest_rad_s
        target = self.force_target_n()
        length = level_record_s(omega)
        if not self.exciter.measured:  # the force channel starts where the largest allowed force fits
            self.scope.range_for(self.force.number, FORCE_TRIP * self.max_force_n * self.force.volt_per_unit)
        for step in range(MAX_LEVEL_STEPS):
            rate = 20 * omega / (2 * math.pi) if self.exciter.arbitrary is None else 4 * self.exciter.arbitrary[1]
            record = self._record(length, rate)
            force_n = self._force_peak(record)
            scale_was = record.scales_v[self.force.number]
            self._range_from(record, target / max(force_n, 1e-12))
            self.counters["level_steps"] += 1
            if self.scope.scales_v[self.force.number] < scale_was / 2.5:
                continue  # the force was a small part of its screen: measure it again before trusting the gain
            if force_n <= 0:
                raise DataQualityError(f"{self.scope.where}: no force on channel {self.force.number} with {self.exciter.volts:.4g} V "
                                       "of drive: is the amplifier on and the force sensor connected?")
            # never more than MAX_STEP_UP times the drive per step, whatever a measurement says
            self.exciter.gain_estimate = max(force_n / self.exciter.volts, self.exciter.gain_estimate / MAX_STEP_UP)
            self.exciter.measured = True
            if abs(force_n / target - 1.0) <= LEVEL_TOLERANCE:
                break
            self.exciter.set_volts(target / self.exciter.gain_estimate)
        else:
            log.warning("%s: force level not within %.0f %% of %.3g N after %d steps", self.scope.where, 100 * LEVEL_TOLERANCE,
                        target, MAX_LEVEL_STEPS)
        self.exciter.needs_level = False

    def _force_peak(self, record: ScopeRecord) -> float:
        """The force's peak (N) as the drive sets it: a sine's fitted amplitude, or the played
        waveform's scale (times its largest point, 1); above the trip level the output goes off first."""
        force = record.volts[self.force.number] / self.force.volt_per_unit
        if self.exciter.arbitrary is None:
            amplitude = abs(fit_sine(record.t_s, force, np.array([self.exciter.omega_rad_s]), t_ref_s=float(record.t_s[0])).line(0).phasor)
        else:
            points, rate = self.exciter.arbitrary
            amplitude = max(held_waveform_gain(record.t_s, force, points, rate), float(np.max(np.abs(force))))
        if amplitude > FORCE_TRIP * self.max_force_n:
            self.exciter.stop()
            raise SafetyLimitError(f"{self.scope.where}: measured force {amplitude:.4g} N exceeds max_amplitude_n "
                                   f"{self.max_force_n:g} N by more than 5 %; output switched off")
        return amplitude

    def _range_from(self, record: ScopeRecord, level_ratio: float) -> None:
        """Every channel ranged for what it will show once the force is on target (the record's
        peaks times ``level_ratio``, the force at most ``1 + LEVEL_TOLERANCE`` of its target)."""
        ratio = min(max(level_ratio, 1.0 / MAX_STEP_UP), MAX_STEP_UP) * (1 + LEVEL_TOLERANCE)
        for ch in self.channels:
            self.scope.range_for(ch.number, RANGE_HEADROOM * ratio * float(np.max(np.abs(record.volts[ch.number]))))

    # -- records -----------------------------------------------------------------------------------
    def _record(self, duration_s: float, min_rate_hz: float = 0.0) -> ScopeRecord:
        """One record; a clipped channel moves up a scale and the record is taken again."""
        for step in range(MAX_RANGE_STEPS + 1):
            try:
                return self.scope.record(duration_s, min_rate_hz)
            except ClippedChannel as exc:
                self.counters["range_up"] += 1
                if step == MAX_RANGE_STEPS or not self.scope.range_up(exc.channel):
                    raise
                log.info("%s: channel %d clipped; now %g V/div", self.scope.where, exc.channel, self.scope.scales_v[exc.channel])
        raise AssertionError("unreachable")  # pragma: no cover (the last step re-raises)

    def acquire(self, duration_s: float) -> SampleBlock:
        start = self.clock.now()
        record = self._record(duration_s, self.sample_rate_hz)
        self.last_acquire_s = self.clock.now() - start
        self.last_scales_v = dict(record.scales_v)
        self.last_sample_rate_hz = 1.0 / record.sample_interval_s
        self.last_length_s = float(record.t_s[-1] - record.t_s[0] + record.sample_interval_s)
        units = [record.volts[ch.number] / ch.volt_per_unit for ch in self.channels]
        if self.exciter.arbitrary is not None:
            points, rate = self.exciter.arbitrary
            if self.clock.now() > self.waveform_started + points.size / rate:
                raise DataQualityError(f"{self.scope.where}: the record ran past the end of the generator's waveform "
                                       f"({points.size / rate:.0f} s); the record is taken again")
        if self.exciter.omega_rad_s or self.exciter.arbitrary is not None:
            self._force_peak(record)  # the trip
            drift = self.exciter.omega_rad_s * self.scope.profile.timebase_ppm * 1e-6 * self.last_length_s
            if drift > MAX_CLOCK_PHASE_RAD:
                raise DataQualityError(f"{self.scope.where}: a {self.last_length_s:.4g} s record at {self.exciter.omega_rad_s:g} rad/s: the "
                                       f"{self.scope.profile.timebase_ppm:g} ppm time base may turn the phasors by {drift:.3g} rad")
        return SampleBlock(t_s=record.t_s, force=units[0], response=units[1], others=tuple(units[2:]))

    # -- the instrument terms ----------------------------------------------------------------------
    def channel_error(self, channel: ScopeChannel, omega_rad_s: float) -> ChannelError:
        p = self.scope.profile
        return scope_channel_error(gain_accuracy=p.gain_accuracy, full_scale_v=p.divisions * self.last_scales_v[channel.number],
                                   adc_bits=p.adc_bits, volt_per_unit=channel.volt_per_unit, calibration=channel.calibration_uncertainty,
                                   omega_rad_s=omega_rad_s, trigger_jitter_s=p.trigger_jitter_s)

    def corrected(self, m: Measurement, force_amplitude_n: float) -> Measurement:
        """``m`` (from the last record) with every output's instrument terms added to its bound,
        then converted to receptance where a sensor measures velocity or acceleration."""
        w = m.omega_rad_s
        force = self.channel_error(self.force, w)

        def one(g: complex, bound: float, channel: ScopeChannel) -> tuple[complex, float]:
            total = bound + ratio_error_bound(g, force_amplitude_n, force, self.channel_error(channel, w))
            if not math.isfinite(total):
                raise DataQualityError(f"{self.scope.where}: the force at {w:g} rad/s ({force_amplitude_n:.3g} N) is not larger than "
                                       f"channel {self.force.number}'s error ({force.absolute:.3g} N)")
            scale = abs(to_receptance(1.0, w, channel.quantity))
            return to_receptance(g, w, channel.quantity), total * scale

        response, bound = one(m.response, m.bound, self.responses[0])
        others = tuple(one(g, b, ch) for (g, b), ch in zip(m.others, self.responses[1:]))
        return dataclasses.replace(m, response=response, bound=bound, others=others)


class ScopeRig:
    """The Rig protocol over a generator and an oscilloscope (closed with both)."""

    def __init__(self, source: SignalSource, scope: ScpiScope, force: ScopeChannel, responses: tuple[ScopeChannel, ...],
                 newton_per_volt: float, max_drive_v: float, max_force_n: float, clock: Clock, owned: tuple = ()):
        self.source, self.scope, self.owned = source, scope, owned
        self.exciter = LevelledExciter(source, newton_per_volt, max_drive_v)
        self.sensor = ScopeSensor(scope, force, responses, self.exciter, clock, max_force_n)
        # the dwell's own clipping check must never fire before the scope's: infinite ranges here
        self.metadata = RigMetadata(1000.0, math.inf, math.inf, name=f"{source.name} + {scope.name}")

    def close(self) -> None:
        try:
            self.exciter.stop()
        finally:
            try:
                self.source.close()
            finally:
                self.scope.close()
                for thing in self.owned:
                    thing.close()


class ScopeDwellExperiment(SineDwellExperiment):
    """The sine dwell on a :class:`ScopeRig`; ``identities`` are journaled with the run."""

    def __init__(self, rig: ScopeRig, limits, settings=None, model=None, extra_bound=None, identities=None):
        super().__init__(rig, limits, settings, model, extra_bound)
        self.identities = dict(identities or {})
