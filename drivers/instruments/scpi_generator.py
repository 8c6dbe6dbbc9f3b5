"""A function generator driven through its SCPI profile (Keysight 33500B, Rigol DG800, ...)."""

from __future__ import annotations

import math

from setmem_hil.drivers.instruments.source import check_instrument_range
from setmem_hil.drivers.instruments.profile import ScpiGeneratorProfile
from setmem_hil.drivers.instruments.scpi_instrument import ScpiInstrument
from setmem_hil.drivers.instruments.visa_link import VisaLink
from setmem_hil.errors import SafetyLimitError

__all__ = ["ScpiGenerator", "AMPLITUDE_FACTORS"]

# instrument unit per peak volt
AMPLITUDE_FACTORS = {"Vpp": 2.0, "Vpk": 1.0, "Vrms": 1.0 / math.sqrt(2.0)}


class ScpiGenerator(ScpiInstrument):
    """:class:`~setmem_hil.drivers.instruments.source.SignalSource` over a SCPI generator.

    ``channel`` selects the output (``{ch}`` in the templates); ``load_ohms`` the output load
    setting (``{load}``; ``None``: the profile's ``high_z`` word, ``INF`` by default: high
    impedance, right for an amplifier input).
    """

    profile: ScpiGeneratorProfile

    def __init__(self, name: str, profile: ScpiGeneratorProfile, link: VisaLink, channel: int = 1, load_ohms: float | None = None):
        if channel not in profile.channels:
            raise SafetyLimitError(f"{name}: channel {channel} does not exist on a {profile.model} (channels {list(profile.channels)})")
        load = profile.high_z if load_ohms is None else f"{load_ohms:g}"
        super().__init__(name, profile, link, {"ch": channel, "load": load})
        self.frequency_limits_hz = profile.frequency_limits_hz
        self.amplitude_limits_v = profile.amplitude_limits_v
        self.keepalive_interval_s = math.inf  # no watchdog

    def initialise(self) -> None:
        """Output off first (before anything else is touched), then the profile's init sequence."""
        self.set_output(False)
        self.run_init()
        self.set_output(False)

    def set_frequency_hz(self, frequency_hz: float) -> None:
        check_instrument_range(self.where, self.model, frequency_hz, self.frequency_limits_hz, "Hz")
        self.set_checked(self.profile.frequency, frequency_hz, "frequency (Hz)")

    def set_amplitude_v(self, peak_v: float) -> None:
        check_instrument_range(self.where, self.model, peak_v, self.amplitude_limits_v, "V")
        value = float(f"{peak_v * AMPLITUDE_FACTORS[self.profile.amplitude.unit]:.5g}")
        self.set_checked(self.profile.amplitude, value, f"amplitude ({self.profile.amplitude.unit})")

    def set_output(self, on: bool) -> None:
        self.set_checked(self.profile.output_on if on else self.profile.output_off)

    def keepalive(self) -> None:
        """No watchdog on a generator (see the profile's ``dead_man``)."""
