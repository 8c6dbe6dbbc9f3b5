"""Hardware interfaces as ``typing.Protocol`` s (devices apart from procedures, as in ophyd).

An :class:`Exciter` drives the shaker with a sinusoid; a :class:`Sensor` acquires sampled force
and response channels with timestamps; a :class:`Rig` combines them with metadata. The
sine-dwell measurement (``setmem_hil.drivers.sine_dwell``) runs on any Rig and implements the
loop's :class:`setmem_hil.model.experiment.Experiment` protocol.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class RigMetadata:
    """What a measurement needs to know about a rig."""

    sample_rate_hz: float
    force_range_n: float
    response_range: float
    force_unit: str = "N"
    response_unit: str = "m"
    name: str = "rig"


@dataclass(frozen=True)
class SampleBlock:
    """A block of simultaneously sampled channels; ``t_s`` are the sample timestamps.

    ``response`` is the control output's channel; ``others`` the other response channels of a
    rig with several sensors (issue 25), in the procedure's output order, each as long as ``t_s``.
    """

    t_s: np.ndarray
    force: np.ndarray
    response: np.ndarray
    others: tuple[np.ndarray, ...] = ()


@runtime_checkable
class Exciter(Protocol):
    def set_sine(self, omega_rad_s: float, amplitude_n: float) -> None:
        """Start (or change) a sinusoidal excitation. Limits are checked before sending."""
        ...

    def stop(self) -> None:
        """Command zero output. Must be safe to call at any time, repeatedly."""
        ...


@runtime_checkable
class Sensor(Protocol):
    def acquire(self, duration_s: float) -> SampleBlock:
        """Acquire ``duration_s`` seconds of force and response samples."""
        ...


@runtime_checkable
class Rig(Protocol):
    metadata: RigMetadata
    exciter: Exciter
    sensor: Sensor

    def close(self) -> None:
        """Command the exciter to zero and release the device (idempotent)."""
        ...


# --- Optional capabilities (checked with isinstance; a rig need not have them) -----------------


@runtime_checkable
class MultisineExciter(Protocol):
    """An exciter that can play a sum of sinusoids (a multisine record, several points at once)."""

    def set_multisine(self, omegas_rad_s, amplitudes_n, phases_rad) -> None:
        """Start ``sum_k a_k sin(omega_k t + phi_k)`` (t from this command). Limits checked before sending."""
        ...


@runtime_checkable
class RecordedMultisineExciter(Protocol):
    """An exciter that plays a whole multisine record as one waveform (a generator's arbitrary
    waveform, issue 26): it needs the record's longest duration before anything is sent."""

    def set_multisine_record(self, multisine, duration_s: float) -> None:
        ...


@runtime_checkable
class RateConfigurableSensor(Protocol):
    """A sensor whose sample rate may be set per acquisition (coherent stepped-sine sampling)."""

    def set_sample_rate(self, rate_hz: float) -> None:
        ...


@runtime_checkable
class WaitingSensor(Protocol):
    """A sensor that can let time pass without returning samples (settling)."""

    def wait(self, duration_s: float) -> None:
        ...


@runtime_checkable
class MeasurementIndexedRig(Protocol):
    """A (simulated) rig told which measurement and attempt starts, so it can seed its noise.

    Fake devices reseed their sensor noise with ``(seed, index, attempt)``; a campaign resumed
    from its journal then measures exactly what an uninterrupted one would.
    """

    def begin_measurement(self, index: int, attempt: int = 0) -> None:
        ...


@runtime_checkable
class ReconnectableRig(Protocol):
    """A rig that can reopen its transport after a disconnect (the dwell is then re-run)."""

    def reconnect(self) -> None:
        ...


@runtime_checkable
class InstrumentTermsSensor(Protocol):
    """A sampled sensor whose instruments add terms no averaging removes (gain accuracy,
    quantization, calibration: an oscilloscope, issue 26), and whose sensors may measure velocity
    or acceleration: it adds them to a measurement of its last record and converts the point to
    receptance. ``last_acquire_s`` is the clock time its last ``wait`` or ``acquire`` cost;
    ``last_sample_rate_hz`` the rate its last block was sampled at (the instrument's choice)."""

    last_acquire_s: float
    last_sample_rate_hz: float

    def corrected(self, measurement, force_amplitude: float):
        ...


@runtime_checkable
class TermsReportingSensor(Protocol):
    """An :class:`InstrumentTermsSensor` that states its terms as data: ``instrument_terms(w)``
    is what ``corrected`` applies to a point at ``w`` of the last record
    (:class:`~setmem_hil.estimation.instrument_terms.InstrumentTerms`), kept in the raw record so
    ``reprocess`` applies the same."""

    def corrected(self, measurement, force_amplitude: float):
        ...

    def instrument_terms(self, omega_rad_s: float):
        ...


@runtime_checkable
class ResolutionLimitedSensor(Protocol):
    """A sampled sensor of few bits (an 8-bit oscilloscope): ``dynamic_range`` is the largest
    ratio between a record's summed line amplitudes and one line it still resolves well; a
    multisine record's lines are split into records that respect it
    (:func:`~setmem_hil.estimation.multisine.resolvable_groups`)."""

    dynamic_range: float
