"""The signal source protocol: what drives the shaker amplifier, in instrument units.

A generator (SCPI), a Modbus shaker controller or a CAN device all offer the same few calls, in
the units the instrument knows (Hz and peak volts). The conversion from the model's rad/s and
newtons and every safety check live in :mod:`setmem_hil.drivers.instruments.phasor_dwell`.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from setmem_hil.errors import SafetyLimitError

__all__ = ["SignalSource", "IdentifiedInstrument", "check_instrument_range"]


def check_instrument_range(where: str, model: str, value: float, limits: tuple[float, float], unit: str) -> None:
    """The instrument's own limit (from its profile), checked before anything is sent."""
    lo, hi = limits
    if not lo <= value <= hi:
        raise SafetyLimitError(f"{where}: {value:g} {unit} outside the {model}'s range [{lo:g}, {hi:g}] {unit}; nothing was sent")


@runtime_checkable
class IdentifiedInstrument(Protocol):
    name: str
    model: str

    def check_identity(self) -> str:
        """Ask the instrument who it is; raise DeviceIdentityError naming what it answered."""
        ...

    def close(self) -> None: ...


@runtime_checkable
class SignalSource(IdentifiedInstrument, Protocol):
    frequency_limits_hz: tuple[float, float]
    amplitude_limits_v: tuple[float, float]  # peak volts
    keepalive_interval_s: float  # longest wait between keepalive() calls (inf: no dead-man)

    def initialise(self) -> None:
        """Output forced off, then the signal set-up (sine, no offset, load...)."""
        ...

    def set_frequency_hz(self, frequency_hz: float) -> None:
        """Set and read back; raise on a mismatch or an instrument error."""
        ...

    def set_amplitude_v(self, peak_v: float) -> None:
        """Set and read back the peak drive voltage."""
        ...

    def set_output(self, on: bool) -> None:
        """Switch the output relay (read back)."""
        ...

    def keepalive(self) -> None:
        """Refresh the instrument's dead-man (watchdog), if it has one."""
        ...

    def reconnect(self) -> None:
        """Drop the present connection and open a fresh one (a dropped link: the output may
        still be on, and the switch-off must reach the instrument)."""
        ...
