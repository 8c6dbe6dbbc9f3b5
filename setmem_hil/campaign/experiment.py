"""The experiment protocol: what the campaign loop needs from a rig, real or simulated.

One call applies a unit-amplitude sinusoid at ``omega_rad_s`` and returns the steady-state
complex response ``G(j omega)`` with an absolute bound on its total error (noise, estimation
error and unmodelled dynamics), exactly the four columns of the data CSV. The loop depends on
this protocol only (devices and procedures apart, as in Bluesky/ophyd): the simulated beam,
the sine-dwell measurement over serial/CAN/Modbus and test doubles all implement it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable


@dataclass(frozen=True)
class Measurement:
    """One frequency-response measurement: a row of the data CSV."""

    omega_rad_s: float
    response: complex
    bound: float


@runtime_checkable
class Experiment(Protocol):
    """Anything that can measure the structure's frequency response at one frequency."""

    def measure(self, omega_rad_s: float) -> Measurement:
        """Apply a unit sinusoid at ``omega_rad_s``, wait for steady state, return the response.

        Must leave the actuator at zero output when it returns or raises.
        """
        ...

    def close(self) -> None:
        """Command the actuator to zero and release the device (idempotent)."""
        ...
