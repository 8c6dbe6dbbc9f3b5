"""The signal source protocol: what drives the shaker amplifier, in instrument units.

A generator (SCPI), a Modbus shaker controller or a CAN device all offer the same few calls, in
the units the instrument knows (Hz and peak volts). The conversion from the model's rad/s and
newtons and every safety check live in :mod:`setmem_hil.drivers.instruments.phasor_dwell`.
"""

from __future__ import annotations

import logging
from typing import Protocol, runtime_checkable

from setmem_hil.errors import OutputNotConfirmedOffError, SafetyLimitError

__all__ = ["SignalSource", "IdentifiedInstrument", "check_instrument_range", "switch_output_off"]

log = logging.getLogger(__name__)


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


def switch_output_off(source: "SignalSource", label: str | None = None, on_reconnect=lambda: None) -> bool:
    """Switch the output off and read it back; when that fails (the link dropped), open a fresh
    connection (``on_reconnect()`` first) and try once more. Returns whether the fresh connection
    was needed; raises :class:`~setmem_hil.errors.OutputNotConfirmedOffError` when neither is
    confirmed: the output may still be on. ``label`` names the source in messages."""
    label = label or source.name
    try:
        source.set_output(False)
        return False
    except Exception as first:  # noqa: BLE001 - any failure: try a fresh connection
        log.error("%s: switching the output off failed (%s); opening a fresh connection", label, first)
        cause = first
    try:
        on_reconnect()
        source.reconnect()
        source.set_output(False)
        log.warning("%s: output switched off (read back) on a fresh connection", label)
        return True
    except Exception as second:  # noqa: BLE001
        raise OutputNotConfirmedOffError(source.name, f"{label}: the output could not be confirmed off ({short_cause(cause)}; "
                                         f"a fresh connection failed too: {short_cause(second)}): it may still be on: switch "
                                         "it off at the instrument or at the amplifier") from None


def short_cause(exc: BaseException) -> str:
    """An exception as one short line (a message quoting another)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) < 160 else text[:157] + "..."
