"""A signal source plus a sampling DAQ as a :class:`~setmem_hil.drivers.protocols.Rig`.

With a DAQ instead of lock-ins (``[backend] force`` and ``response`` name ``nidaqmx`` instruments),
the measurement is the sine dwell of :mod:`setmem_hil.drivers.sine_dwell` (transient-aware sine
fit of the sampled force and response). :class:`SourceExciter` makes any
:class:`~setmem_hil.drivers.instruments.source.SignalSource` an
:class:`~setmem_hil.drivers.protocols.Exciter`: newtons to volts through the nominal
``newton_per_volt`` (checked against ``max_drive_v`` and the instrument's limits before anything
is sent), amplitude ramped up from a tenth, output off on ``stop``. :class:`ForceLimitedSensor`
switches the output off and stops the run when a sampled force peak exceeds
``1.05 x max_amplitude_n`` (the level is open loop on this path: the nominal gain sets it, the
measured force bounds it).
"""

from __future__ import annotations

import math

import numpy as np

from setmem_hil.drivers.instruments.source import SignalSource
from setmem_hil.drivers.protocols import RigMetadata, SampleBlock
from setmem_hil.errors import SafetyLimitError

__all__ = ["SourceExciter", "ForceLimitedSensor", "SampledInstrumentRig"]

RAMP_FRACTIONS = (0.1, 0.3, 0.6, 1.0)
# Points per period of a multisine's highest line in the generator's arbitrary waveform. Held
# points add images at m f_arb +- f of relative size about f / (m f_arb); a sampling sensor whose
# rate divides some m f_arb aliases one of them exactly onto its line (the force's phasor, not the
# response's: the structure filters it). Many points, at a rate no sensor rate divides
# (an irrational factor), keep that leak far below the bound.
POINTS_PER_PERIOD = 32 * 1.0618


class SourceExciter:
    def __init__(self, source: SignalSource, newton_per_volt: float, max_drive_v: float = math.inf):
        self.source, self.newton_per_volt, self.max_drive_v = source, float(newton_per_volt), float(max_drive_v)
        self.on = False

    arbitrary = False  # an arbitrary waveform was last played (the next sine switches back first)

    def set_sine(self, omega_rad_s: float, amplitude_n: float) -> None:
        if self.arbitrary:
            if self.on:
                self.stop()
            self.source.play_sine()
            self.arbitrary = False
        frequency_hz = omega_rad_s / (2 * math.pi)
        volts = amplitude_n / self.newton_per_volt
        lo, hi = self.source.frequency_limits_hz
        if volts > self.max_drive_v or volts > self.source.amplitude_limits_v[1] or not lo <= frequency_hz <= hi:
            raise SafetyLimitError(f"{self.source.name}: {amplitude_n:g} N at {frequency_hz:.6g} Hz needs {volts:.4g} V "
                                   f"(max_drive_v {self.max_drive_v:g} V, instrument {self.source.amplitude_limits_v[1]:g} V, "
                                   f"{lo:g}-{hi:g} Hz); nothing was sent")
        self.source.set_frequency_hz(frequency_hz)
        if not self.on:
            self.source.set_amplitude_v(max(RAMP_FRACTIONS[0] * volts, self.source.amplitude_limits_v[0]))
            self.source.set_output(True)
            self.on = True
        for fraction in RAMP_FRACTIONS[1:]:
            self.source.set_amplitude_v(max(fraction * volts, self.source.amplitude_limits_v[0]))

    def set_multisine_record(self, multisine, duration_s: float) -> None:
        """The whole record as the generator's arbitrary waveform (points held one sample
        period, 8 a period of the highest line), at the nominal gain, ramped like a sine."""
        rate = POINTS_PER_PERIOD * max(multisine.omegas_rad_s) / (2 * math.pi)
        force = multisine.force(np.arange(int(math.ceil(duration_s * rate))) / rate)
        peak = float(np.max(np.abs(force)))
        volts = peak / self.newton_per_volt
        if volts > self.max_drive_v or volts > self.source.amplitude_limits_v[1]:
            raise SafetyLimitError(f"{self.source.name}: a multisine of {peak:g} N peak needs {volts:.4g} V (max_drive_v "
                                   f"{self.max_drive_v:g} V, instrument {self.source.amplitude_limits_v[1]:g} V); nothing was sent")
        if self.on:
            self.stop()
        self.source.play_arbitrary(force / peak, rate)
        self.arbitrary = True
        self.source.set_amplitude_v(max(RAMP_FRACTIONS[0] * volts, self.source.amplitude_limits_v[0]))
        self.source.set_output(True)
        self.on = True
        for fraction in RAMP_FRACTIONS[1:]:
            self.source.set_amplitude_v(max(fraction * volts, self.source.amplitude_limits_v[0]))

    def stop(self) -> None:
        self.on = False
        self.source.set_output(False)


class ForceLimitedSensor:
    """Wraps a sampling sensor: a force peak above the limit switches the output off and raises."""

    def __init__(self, sensor, exciter: SourceExciter, max_force_n: float):
        self.inner, self.exciter, self.max_force_n = sensor, exciter, float(max_force_n)

    def set_sample_rate(self, rate_hz: float) -> None:
        self.inner.set_sample_rate(rate_hz)

    def acquire(self, duration_s: float) -> SampleBlock:
        block = self.inner.acquire(duration_s)
        peak = float(np.max(np.abs(block.force))) if block.force.size else 0.0
        if peak > 1.05 * self.max_force_n:
            self.exciter.stop()
            raise SafetyLimitError(f"measured force peak {peak:.4g} N exceeds max_amplitude_n {self.max_force_n:g} N by more than 5 %; "
                                   "output switched off")
        return block


class SampledInstrumentRig:
    """The Rig protocol over a source and a DAQ (closed with the instruments)."""

    def __init__(self, source: SignalSource, sensor, newton_per_volt: float, max_drive_v: float, max_force_n: float,
                 force_range_n: float, response_range: float, sample_rate_hz: float):
        self.exciter = SourceExciter(source, newton_per_volt, max_drive_v)
        self.sensor = ForceLimitedSensor(sensor, self.exciter, max_force_n)
        self.source = source
        self.metadata = RigMetadata(sample_rate_hz, force_range_n, response_range, name=source.name)

    def close(self) -> None:
        try:
            self.exciter.stop()
        finally:
            self.source.close()
