"""A signal source plus a sampling DAQ as a :class:`~setmem_hil.drivers.protocols.Rig`.

With a DAQ instead of lock-ins (``[backend] force`` and ``response`` name ``nidaqmx`` instruments),
the measurement is the sine dwell of :mod:`setmem_hil.drivers.sine_dwell` (transient-aware sine
fit of the sampled force and response). The drive level is closed on the sampled force
(:mod:`setmem_hil.drivers.instruments.drive_level`, issue 26): :class:`LevelledDaqSensor` runs
the levelling records at the start of each dwell's settling, and any acquisition whose force
exceeds ``1.05 x max_amplitude_n`` switches the output off and stops the run. Multisine records
play as the generator's arbitrary waveform where its profile has an ``[arbitrary]`` table.

The points' bounds gain each sensor's calibration uncertainty, and a velocity or acceleration
sensor's ratio is converted to receptance (:meth:`LevelledDaqSensor.corrected`).
"""

from __future__ import annotations

import dataclasses
import math

from setmem_hil.drivers.instruments.drive_level import ForceLeveller, LevelledExciter
from setmem_hil.drivers.instruments.nidaq_sensor import ac_coupling_error
from setmem_hil.drivers.instruments.sampled_dwell import calibration_scales
from setmem_hil.estimation.instrument_terms import InstrumentTerms, OutputTerms, apply_instrument_terms
from setmem_hil.drivers.instruments.source import SignalSource
from setmem_hil.drivers.protocols import RigMetadata, SampleBlock
from setmem_hil.estimation.channel_errors import ChannelError
from setmem_hil.model.experiment import Measurement

__all__ = ["LevelledDaqSensor", "SampledInstrumentRig", "DaqChannel"]


@dataclasses.dataclass(frozen=True)
class DaqChannel:
    """What a DAQ input's sensor adds to a point: its calibration, its quantity and its input's
    AC-coupling corner (0: DC coupled)."""

    calibration_uncertainty: float = 0.0
    quantity: str = "displacement"
    ac_corner_hz: float = 0.0

    def error_at(self, omega_rad_s: float) -> ChannelError:
        """The AC coupling's high-pass as a relative disc on the reading (none when DC coupled)."""
        return ChannelError(relative=ac_coupling_error(omega_rad_s, self.ac_corner_hz) if self.ac_corner_hz else 0.0)

    def shortfall_at(self, omega_rad_s: float) -> float:
        """How much larger the true amplitude may be than the AC-coupled reading (``1/|H| - 1``)."""
        if not self.ac_corner_hz:
            return 0.0
        if omega_rad_s <= 0:
            return math.inf
        return math.hypot(1.0, 2 * math.pi * self.ac_corner_hz / omega_rad_s) - 1.0


class LevelledDaqSensor:
    """Wraps a DAQ sensor: levels the drive on its force during the settling, trips on too much force."""

    def __init__(self, sensor, exciter: LevelledExciter, max_force_n: float, force: DaqChannel, responses: tuple[DaqChannel, ...]):
        self.inner, self.exciter = sensor, exciter
        self.force, self.responses = force, tuple(responses)
        # the force trip's margin: the calibration, and what an AC-coupled force input reads short
        self.leveller = ForceLeveller(exciter, max_force_n,
                                      lambda: force.calibration_uncertainty + force.shortfall_at(exciter.omega_rad_s or exciter.lowest_rad_s),
                                      getattr(sensor, "where", "DAQ"))
        self.last_acquire_s = 0.0
        self.last_sample_rate_hz = 0.0

    def set_sample_rate(self, rate_hz: float) -> None:
        self.inner.set_sample_rate(rate_hz)

    def wait(self, duration_s: float) -> None:
        """The settling: the levelling acquisitions (the rate the dwell asked for is restored
        after), then the rest of it acquired and dropped (a DAQ has no other clock)."""
        spent = 0.0
        if self.exciter.needs_level:
            rate = self.inner.sample_rate_hz

            def take(length_s: float, min_rate_hz: float):
                nonlocal spent
                self.inner.set_sample_rate(max(rate, min_rate_hz))
                block = self.inner.acquire(length_s)
                spent += length_s
                return block.t_s, block.force

            try:
                self.leveller.level(take)
            finally:
                self.inner.set_sample_rate(rate)
                self.last_acquire_s = spent  # a levelling that failed took rig time too
        if duration_s > spent:
            self.inner.acquire(duration_s - spent)
        self.last_acquire_s = max(duration_s, spent)

    def acquire(self, duration_s: float) -> SampleBlock:
        self.last_acquire_s = duration_s  # also when the acquisition fails
        block = self.inner.acquire(duration_s)
        self.last_sample_rate_hz = self.inner.sample_rate_hz
        if block.force.size and (self.exciter.omega_rad_s or self.exciter.arbitrary is not None):
            self.leveller.force_peak(block.t_s, block.force)  # the trip
            self.leveller.confirm_level()
        return block

    @property
    def calibration_scales(self) -> tuple[tuple[float, float], ...]:
        """Each output's calibration scale (:func:`~setmem_hil.drivers.instruments.sampled_dwell.calibration_scales`)."""
        return calibration_scales(self.force, self.responses)

    def instrument_terms(self, omega_rad_s: float) -> InstrumentTerms:
        """The terms of a point at ``omega_rad_s``: each output's calibration scale
        (:attr:`calibration_scales`), its channel's error and the force channel's, its quantity."""
        w = omega_rad_s
        outputs = tuple(OutputTerms(self.force.error_at(w), ch.error_at(w), ch.quantity) for ch in self.responses)
        return InstrumentTerms(self.calibration_scales, outputs, self.leveller.where)

    def corrected(self, m: Measurement, force_amplitude_n: float) -> Measurement:
        """``m`` in its calibration scale (:attr:`calibration_scales`), converted to receptance."""
        return apply_instrument_terms(m, force_amplitude_n, self.instrument_terms(m.omega_rad_s))


class SampledInstrumentRig:
    """The Rig protocol over a source and a DAQ (closed with the instruments)."""

    def __init__(self, source: SignalSource, sensor, newton_per_volt: float, max_drive_v: float, max_force_n: float,
                 force_range_n: float, response_range: float, sample_rate_hz: float,
                 force: DaqChannel = DaqChannel(quantity="force"), responses: tuple[DaqChannel, ...] = (DaqChannel(),)):
        self.exciter = LevelledExciter(source, newton_per_volt, max_drive_v)
        self.sensor = LevelledDaqSensor(sensor, self.exciter, max_force_n, force, responses)
        self.source = source
        self.metadata = RigMetadata(sample_rate_hz, force_range_n, response_range, name=source.name)

    def close(self) -> None:
        try:
            self.exciter.stop()
        finally:
            self.source.close()
