"""Hardware interfaces as ``typing.Protocol`` s (devices apart from procedures, as in ophyd).

An :class:`Exciter` drives the shaker with a sinusoid; a :class:`Sensor` acquires sampled force
and response channels with timestamps; a :class:`Rig` combines them with metadata. The
sine-dwell measurement (``setmem_hil.drivers.sine_dwell``) runs on any Rig and implements the
loop's :class:`setmem_hil.experiment.Experiment` protocol.
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
    """A block of simultaneously sampled channels; ``t_s`` are the sample timestamps."""

    t_s: np.ndarray
    force: np.ndarray
    response: np.ndarray


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
