"""A generator plus an oscilloscope as a sampled :class:`~setmem_hil.drivers.protocols.Rig` (issue 26).

One oscilloscope holds the force and the response roles (``channels = { force = 1, response =
[2, 3] }``): every record samples them together, so their ratio needs no common clock. The
measurement is the sine dwell of :mod:`setmem_hil.drivers.sine_dwell` (the transient-aware sine
fit), with three things the scope adds:

* **closed-loop drive level** (:mod:`setmem_hil.drivers.instruments.drive_level`, run by
  :meth:`ScopeSensor.wait`): short records of the force set the generator's level, with room
  for what the force channel may be off by (its calibration, the scope's gain accuracy at the
  force's range), so the true force stays below ``max_amplitude_n`` even with the drive gain
  wrong by tens of percent; a record whose force exceeds ``1.05 x max_amplitude_n`` switches
  the output off and stops the run;
* **vertical ranging**: every channel starts on the largest V/div; the levelling records set
  each channel to the smallest scale holding its peak with room (before the campaign has a
  model, the outputs other than the control output with ``FIRST_RECORD_ROOM``; later, each
  response channel also holds what the model says the response will grow to); a clipped record
  moves that channel up and is taken again;
* **instrument terms in the bound** (:meth:`ScopeSensor.corrected`,
  :mod:`setmem_hil.estimation.channel_errors`): gain accuracy, quantization, calibration and
  timing for every channel used, then the ratio converted to receptance (velocity and
  acceleration sensors). With a channel match (``channel_match``, measured by ``setmem-hil
  calibrate-channels``: :mod:`setmem_hil.estimation.channel_match`) the ratio is divided by its
  channels' measured gain ratio and the match's bound replaces the datasheet's gain accuracy;
  the channels then range on the profile's listed steps only (the match holds there).

The time spent (levelling, the trigger wait, records longer than asked because the time scale
comes in 1-2-5 steps) is counted from the clock: ``last_acquire_s`` is what the last acquisition
cost.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from setmem_hil.drivers.clock import Clock
from setmem_hil.drivers.instruments.drive_level import FORCE_TRIP, LEVEL_TOLERANCE, MAX_STEP_UP, ForceLeveller, LevelledExciter
from setmem_hil.drivers.instruments.scpi_scope import ClippedChannel, ScopeRecord, ScpiScope
from setmem_hil.drivers.instruments.source import SignalSource
from setmem_hil.drivers.protocols import RigMetadata, SampleBlock
from setmem_hil.drivers.instruments.sampled_dwell import SampledDwellExperiment, calibration_scales
from setmem_hil.estimation.instrument_terms import InstrumentTerms, OutputTerms, apply_instrument_terms
from setmem_hil.errors import DataQualityError
from setmem_hil.estimation.channel_errors import GAIN_TEST_SPAN, MAX_CLOCK_PHASE_RAD, ChannelError, adc_code, measured_quantization_bias, scope_channel_error
from setmem_hil.estimation.channel_match import DRIFT_ALLOWANCE
from setmem_hil.estimation.response_growth import predicted_peak
from setmem_hil.model.channel_match import ChannelMatch
from setmem_hil.model.experiment import Measurement

__all__ = ["ScopeChannel", "ScopeSensor", "ScopeRig", "ScopeDwellExperiment"]

log = logging.getLogger(__name__)

MAX_RANGE_STEPS = 6
RANGE_HEADROOM = 1.15  # a channel is ranged for this much more than the peak it showed (the response still grows)
# Before the campaign has a model (the first record), how a mode grows from rest over the record
# is unknown: a line near a lightly damped mode beats with the free response it starts, up to
# twice its steady amplitude, long after the levelling records saw it. The outputs other than the
# control output are ranged for this much more than their levelling peak: their points narrow the
# shared poles, not the residues mu-bar depends on, so a coarser first record costs them little,
# while a clip on any channel costs the whole record again (on the emulated rig the channel at
# 0.7 of the beam, mostly the first mode, clipped half way into every first record). The control
# output stays tightly ranged: ranging it twice as coarse left the design a first record too
# coarse between the second and third modes (4 of 10 tuning campaigns then stalled there).
FIRST_RECORD_ROOM = 2.0
RESOLUTION_SHARE = 0.1  # a multisine line is resolved while the quantization's bias on it is at most this much of it (dynamic_range)


@dataclass(frozen=True)
class ScopeChannel:
    """One oscilloscope channel and the sensor wired to it."""

    number: int
    volt_per_unit: float
    calibration_uncertainty: float = 0.0
    quantity: str = "displacement"


class ScopeSensor:
    """Sensor, rate-configurable, waiting: force and response channels of one oscilloscope."""

    def __init__(self, scope: ScpiScope, force: ScopeChannel, responses: tuple[ScopeChannel, ...], exciter: LevelledExciter,
                 clock: Clock, max_force_n: float, match: ChannelMatch | None = None):
        self.scope, self.force, self.responses = scope, force, tuple(responses)
        self.match = match
        if match is not None:  # the match holds at the scales it measured: the profile's listed steps
            scope.fine_scales = False
        self.exciter, self.clock, self.max_force_n = exciter, clock, float(max_force_n)
        self.sample_rate_hz = 1000.0
        self.last_acquire_s = 0.0
        self.last_sample_rate_hz = 0.0
        self.last_scales_v: dict[int, float] = {}
        self.counters = {"range_up": 0, "level_steps": 0}
        self.leveller = ForceLeveller(exciter, max_force_n, self.force_room, scope.where)
        self.noise_div: dict[int, float] = {}  # each channel's measured noise (divisions rms), see measure_noise
        # each response channel's model (the campaign's midpoints; one for all until the outputs
        # have their own) and what the last record saw: (clock start, end, peak volts per channel)
        self.response_models: tuple = ()
        self._seen: tuple[float, float, dict[int, float]] | None = None

    @property
    def channels(self) -> tuple[ScopeChannel, ...]:
        return (self.force, *self.responses)

    @property
    def dynamic_range(self) -> float:
        """The largest ratio of a multisine record's summed line amplitudes to one line this scope
        still resolves (:class:`~setmem_hil.drivers.protocols.ResolutionLimitedSensor`): a ranged
        channel's sum fills ``SCREEN_FILL / RANGE_HEADROOM`` of the half screen, and a line is
        resolved while the quantization's bias on it (:func:`measured_quantization_bias`, on the least dithered
        of the channels: the one with the least measured noise) is at most ``RESOLUTION_SHARE`` of
        it. Without measured noise the bias is a whole code: an 8-bit screen then resolves lines
        down to about 1/6 of the sum; with the emulated DS1104Z's noise (0.47 of a code rms) about
        1/210. The random part of the quantization averages down like the noise it is, in the
        fit's radius."""
        p = self.scope.profile
        code_div = adc_code(p.divisions, p.adc_bits)
        biases = [measured_quantization_bias(code_div, self.noise_div[ch.number]) if ch.number in self.noise_div else code_div
                  for ch in self.channels]
        return self._ranged_peak_div * RESOLUTION_SHARE / max(biases)

    @property
    def _ranged_peak_div(self) -> float:
        """Where a ranged channel's peak sits, in divisions from the centre (``SCREEN_FILL`` of
        the half screen, less the room ``RANGE_HEADROOM`` leaves)."""
        return self.scope.SCREEN_FILL / RANGE_HEADROOM * self.scope.profile.divisions / 2.0

    def set_sample_rate(self, rate_hz: float) -> None:
        self.sample_rate_hz = float(rate_hz)  # the scope's memory depth and time scale decide the rate it gives

    # -- the dwell's settling: level the drive, range the channels, let the rest pass --------------
    def wait(self, duration_s: float) -> None:
        start = self.clock.now()
        try:
            if self.exciter.needs_level:
                self._level()
            left = duration_s - (self.clock.now() - start)
            if left > 0:
                self.clock.sleep(left)
        finally:  # a levelling that failed took rig time too
            self.last_acquire_s = self.clock.now() - start

    def force_room(self) -> float:
        """What the force channel may be off by, relative, at a tightly ranged scale (its
        calibration, the scope's gain accuracy and, at worst, a whole code of quantization on a
        signal filling ``SCREEN_FILL / RANGE_HEADROOM`` of the half screen): the level's target
        leaves this much room."""
        p = self.scope.profile
        code_div = adc_code(p.divisions, p.adc_bits)
        return self.force.calibration_uncertainty + p.gain_accuracy / GAIN_TEST_SPAN + code_div / self._ranged_peak_div

    def _force_of(self, record: ScopeRecord) -> tuple[np.ndarray, np.ndarray, float]:
        """The record's force and where in the generator's arbitrary waveform it starts, by the
        clock (the record ended when the scope said it was complete; the drive level aligns it
        with the waveform near there, :func:`~setmem_hil.drivers.instruments.drive_level.held_waveform_gain`)."""
        length_s = float(record.t_s[-1] - record.t_s[0] + record.sample_interval_s)
        position_s = record.completed_at_s - length_s - self.exciter.arbitrary_started
        return record.t_s, record.volts[self.force.number] / self.force.volt_per_unit, position_s

    def _level(self) -> None:
        """Short records: measure the force, correct the drive, range every channel (module docs)."""
        if not self.exciter.measured:  # the force channel starts where the largest allowed force fits
            self.scope.range_for(self.force.number, FORCE_TRIP * self.max_force_n * self.force.volt_per_unit)
        last: list[ScopeRecord] = []

        def take(length_s: float, rate_hz: float):
            last[:] = [self._record(length_s, rate_hz)]
            return self._force_of(last[0])

        def after(level_ratio: float) -> bool:
            scale_was = last[0].scales_v[self.force.number]
            self._range_from(last[0], level_ratio)
            # the force was a small part of its screen: measure it again before trusting the gain
            return self.scope.scales_v[self.force.number] < scale_was / 2.5

        steps = self.leveller.steps
        self.leveller.level(take, after)
        self.counters["level_steps"] += self.leveller.steps - steps

    def _range_from(self, record: ScopeRecord, level_ratio: float) -> None:
        """Every channel ranged for what it will show once the force is on target (the record's
        peaks times ``level_ratio``, the force at most ``1 + LEVEL_TOLERANCE`` of its target);
        before any model, the outputs other than the control output with ``FIRST_RECORD_ROOM``."""
        ratio = min(max(level_ratio, 1.0 / MAX_STEP_UP), MAX_STEP_UP) * (1 + LEVEL_TOLERANCE)
        for ch in self.channels:
            room = FIRST_RECORD_ROOM if not self.response_models and ch in self.responses[1:] else 1.0
            self.scope.range_for(ch.number, room * RANGE_HEADROOM * ratio * float(np.max(np.abs(record.volts[ch.number]))))

    # -- records -----------------------------------------------------------------------------------
    def _record(self, duration_s: float, min_rate_hz: float = 0.0) -> ScopeRecord:
        """One record; a clipped channel moves up a scale and the record is taken again."""
        self.scope.use_trigger(*self._trigger_for_record())
        for step in range(MAX_RANGE_STEPS + 1):
            try:
                record = self.scope.record(duration_s, min_rate_hz)
                length_s = float(record.t_s[-1] - record.t_s[0] + record.sample_interval_s)
                self._seen = (record.completed_at_s - length_s, record.completed_at_s,
                              {ch: float(np.max(np.abs(v))) for ch, v in record.volts.items()})
                return record
            except ClippedChannel as exc:
                self.counters["range_up"] += 1
                if step == MAX_RANGE_STEPS or not self.scope.range_up(exc.channel):
                    raise
                log.info("%s: channel %d clipped; now %g V/div", self.scope.where, exc.channel, self.scope.scales_v[exc.channel])
        raise AssertionError("unreachable")  # pragma: no cover (the last step re-raises)

    def _trigger_for_record(self) -> tuple[str, float]:
        """The sync (as wired) for a sine; for an arbitrary waveform whose generator pulses its
        sync once per waveform period (``[arbitrary] sync = "period"``: the 33500B), the force
        channel's rising zero crossing: the sync's next pulse is up to a whole waveform away
        (26 s for an 881,852-point record), far past any record's wait. Where in the waveform
        the record starts is found from the clock either way (:meth:`_force_of`)."""
        arbitrary = getattr(getattr(self.exciter.source, "profile", None), "arbitrary", None)
        if self.exciter.arbitrary is not None and arbitrary is not None and arbitrary.sync == "period":
            return f"ch{self.force.number}", 0.0
        return self.scope.trigger_source, self.scope.trigger_level_v

    def acquire(self, duration_s: float) -> SampleBlock:
        """A record of ``duration_s`` (at most the scope's longest: a window planned longer, at
        a very low frequency, is fitted on what the scope holds)."""
        start = self.clock.now()
        longest = self.scope.profile.time_scales_s[-1] * self.scope.profile.time_divisions
        try:
            self._range_for_growth(min(duration_s, longest))
            record = self._record(min(duration_s, longest), self.sample_rate_hz)
        finally:  # records refused (clipped) took rig time too
            self.last_acquire_s = self.clock.now() - start
        self.last_scales_v = dict(record.scales_v)
        self.last_sample_rate_hz = 1.0 / record.sample_interval_s
        length_s = float(record.t_s[-1] - record.t_s[0] + record.sample_interval_s)
        units = [record.volts[ch.number] / ch.volt_per_unit for ch in self.channels]
        if self.exciter.arbitrary is not None:
            points, rate = self.exciter.arbitrary
            if self.clock.now() > self.exciter.arbitrary_started + points.size / rate:
                self.exciter.waveform_room *= 2.0  # the next attempt uploads a waveform twice as long
                raise DataQualityError(f"{self.scope.where}: the record ran past the end of the generator's waveform "
                                       f"({points.size / rate:.0f} s); the record is taken again on a waveform twice as long")
        if self.exciter.omega_rad_s or self.exciter.arbitrary is not None:
            self.leveller.force_peak(*self._force_of(record))  # the trip
            self.leveller.confirm_level()
            drift = self.exciter.omega_rad_s * self.scope.profile.timebase_ppm * 1e-6 * length_s
            if drift > MAX_CLOCK_PHASE_RAD:
                raise DataQualityError(f"{self.scope.where}: a {length_s:.4g} s record at {self.exciter.omega_rad_s:g} rad/s: the "
                                       f"{self.scope.profile.timebase_ppm:g} ppm time base may turn the phasors by {drift:.3g} rad")
        return SampleBlock(t_s=record.t_s, force=units[0], response=units[1], others=tuple(units[2:]))

    def _range_for_growth(self, duration_s: float) -> None:
        """Each response channel moved up (never down) to hold what it will show over the coming
        record: the drive's response from rest by the model
        (:func:`~setmem_hil.estimation.response_growth.predicted_peak`; a lightly damped mode
        driven near resonance grows for several of its decay times, and a clipped record costs
        the whole record again) plus what the last record showed beyond that drive's response
        then (an earlier dwell's mode still ringing). Without a model, or before any record,
        nothing changes. The model is in displacement: a velocity or acceleration channel is
        left to the clipping check."""
        if (self._seen is None or not self.response_models or not self.exciter.drive_steps or not self.exciter.lines[0]
                or self.exciter.volts <= 0.0):
            return
        origin = self.exciter.drive_origin
        start, end, peaks = self._seen
        now = self.clock.now()
        coming = (now - origin, now - origin + self.scope.record_length_for(duration_s))
        seen = (start - origin, end - origin)
        force_n = self.leveller.target_n()
        omegas, phasors = self.exciter.lines
        phasors = [force_n * p for p in phasors]
        steps = [(t - origin, volts / self.exciter.volts) for t, volts in self.exciter.drive_steps]
        for k, ch in enumerate(self.responses):
            if ch.quantity != "displacement" or ch.number not in peaks:
                continue
            model = self.response_models[min(k, len(self.response_models) - 1)]
            forced_then = predicted_peak(model, omegas, phasors, steps, seen) * ch.volt_per_unit
            forced_next = predicted_peak(model, omegas, phasors, steps, coming) * ch.volt_per_unit
            if not (math.isfinite(forced_then) and math.isfinite(forced_next)):
                continue
            ringing = max(0.0, peaks[ch.number] - forced_then)
            self.scope.hold(ch.number, RANGE_HEADROOM * (forced_next + ringing))

    # -- the instrument terms ----------------------------------------------------------------------
    def measure_noise(self) -> None:
        """Each channel's noise in divisions, with the output off (:meth:`ScpiScope.noise_floor_divisions`)."""
        self.noise_div = self.scope.noise_floor_divisions()

    def matched_gain(self, channel: ScopeChannel) -> tuple[float, float] | None:
        """``(gain, bound)`` of ``channel`` at the scale of the last record from the channel match
        (its bound plus the drift allowance), None without a match or at a scale it did not measure."""
        entry = None if self.match is None else self.match.gain(channel.number, self.last_scales_v[channel.number])
        return None if entry is None else (entry.gain, entry.bound + DRIFT_ALLOWANCE)

    @property
    def calibration_scales(self) -> tuple[tuple[float, float], ...]:
        """Each output's calibration scale (:func:`~setmem_hil.drivers.instruments.sampled_dwell.calibration_scales`)."""
        return calibration_scales(self.force, self.responses)

    def channel_error(self, channel: ScopeChannel, omega_rad_s: float, matched: bool = False) -> ChannelError:
        """The channel's per-point discs (the sensor's calibration is not among them: :attr:`calibration_scales`)."""
        p = self.scope.profile
        scale = self.last_scales_v[channel.number]
        return scope_channel_error(gain_accuracy=p.gain_accuracy, full_scale_v=p.divisions * scale,
                                   adc_bits=p.adc_bits, volt_per_unit=channel.volt_per_unit, calibration=0.0,
                                   omega_rad_s=omega_rad_s, trigger_jitter_s=p.trigger_jitter_s,
                                   noise_v=self.noise_div.get(channel.number, 0.0) * scale,
                                   matched_gain=self.matched_gain(channel) if matched else None)

    def instrument_terms(self, omega_rad_s: float) -> InstrumentTerms:
        """The terms of a point at ``omega_rad_s`` from the last record. Where the channel match
        covers the force channel's and an output's channel's scales, that output's ratio is
        divided by the two channels' gain ratio and its gain terms are the match's; otherwise
        the datasheet's (output by output: one channel ranged off the match's steps costs only
        its own output the match)."""
        force_gain = self.matched_gain(self.force)
        outputs = []
        for ch in self.responses:
            gain = self.matched_gain(ch)
            matched = force_gain is not None and gain is not None
            outputs.append(OutputTerms(self.channel_error(self.force, omega_rad_s, matched), self.channel_error(ch, omega_rad_s, matched),
                                       ch.quantity, gain[0] / force_gain[0] if matched else None, force_gain[0] if matched else None))
        return InstrumentTerms(self.calibration_scales, tuple(outputs), self.scope.where)

    def corrected(self, m: Measurement, force_amplitude_n: float) -> Measurement:
        """``m`` (from the last record) with every output's instrument terms added to its bound
        (:meth:`instrument_terms`), in its calibration scale (the parts of the bound in the
        structure's units, ``|W1|``, scale with it), converted to receptance where a sensor
        measures velocity or acceleration."""
        return apply_instrument_terms(m, force_amplitude_n, self.instrument_terms(m.omega_rad_s))


class ScopeRig:
    """The Rig protocol over a generator and an oscilloscope (closed with both)."""

    def __init__(self, source: SignalSource, scope: ScpiScope, force: ScopeChannel, responses: tuple[ScopeChannel, ...],
                 newton_per_volt: float, max_drive_v: float, max_force_n: float, clock: Clock, owned: tuple = (),
                 match: ChannelMatch | None = None):
        self.source, self.scope, self.owned = source, scope, owned
        self.exciter = LevelledExciter(source, newton_per_volt, max_drive_v, clock)
        self.sensor = ScopeSensor(scope, force, responses, self.exciter, clock, max_force_n, match)
        # the dwell's own clipping check must never fire before the scope's: infinite ranges here
        self.metadata = RigMetadata(1000.0, math.inf, math.inf, name=f"{source.name} + {scope.name}")

    def reconnect(self) -> None:
        """After a device fault (a reply that never came): a fresh session to the scope with its
        whole setup restored (:meth:`ScpiScope.reconnect`); the dwell then runs again
        (:class:`~setmem_hil.drivers.protocols.ReconnectableRig`). The generator is set afresh by
        every dwell's start, and its link reopens itself after a timed-out query."""
        self.scope.reconnect()

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


class ScopeDwellExperiment(SampledDwellExperiment):
    """The sine dwell on a :class:`ScopeRig` (identities journaled, the output confirmed off);
    the campaign's models also range the response channels (:meth:`ScopeSensor._range_for_growth`)."""

    def update_model(self, model) -> None:
        super().update_model(model)
        if not self._output_models:
            with np.errstate(invalid="ignore"):  # the prior's unbounded residues: nan (no prediction)
                self.rig.sensor.response_models = (getattr(model, "midpoint", model),)

    def update_output_models(self, models) -> None:
        """Every output's interval model (control first, issue 25): each response channel's growth
        is predicted with its own residues."""
        self._output_models = tuple(models)
        with np.errstate(invalid="ignore"):
            self.rig.sensor.response_models = tuple(m.midpoint for m in models)

    _output_models: tuple = ()
