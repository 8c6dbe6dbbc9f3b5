"""A function generator driven through its SCPI profile (Keysight 33500B, Rigol DG800, ...)."""

from __future__ import annotations

import math
import re

from setmem_hil.drivers.instruments.source import check_instrument_range
from setmem_hil.drivers.instruments.profile import ScpiGeneratorProfile
from setmem_hil.drivers.instruments.scpi_commands import render
from setmem_hil.drivers.instruments.scpi_instrument import ScpiInstrument
from setmem_hil.drivers.instruments.visa_link import VisaLink
from setmem_hil.errors import DeviceRejectedError, SafetyLimitError

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

    def play_arbitrary(self, points, rate_hz: float) -> None:
        """Upload ``points`` (in [-1, 1]; each held one sample period) and play them at ``rate_hz``
        Sa/s, then read back the function and the rate (issue 26). The amplitude (``set_amplitude_v``)
        scales them: the waveform's peak is the amplitude times the largest ``|point|``. Call with
        the output off; the caller checks the peak before anything is sent."""
        arb = self.profile.arbitrary
        if arb is None:
            raise DeviceRejectedError("instrument", f"{self.where}: the {self.model} profile has no [arbitrary] table")
        values = [float(v) for v in points]
        if not 8 <= len(values) <= arb.max_points or max(abs(v) for v in values) > 1.0:
            raise DeviceRejectedError("range", f"{self.where}: an arbitrary waveform needs 8-{arb.max_points} points within +-1, "
                                               f"found {len(values)} (largest {max(abs(v) for v in values):.3g}); nothing was sent")
        check_instrument_range(self.where, self.model, rate_hz, arb.sample_rate_limits, "Sa/s")
        self.send(arb.clear)
        self.check_errors(arb.clear)
        upload = render(arb.upload, **self.fields, name=arb.name, values=",".join(f"{v:.6f}" for v in values))
        self.link.write(upload)
        self.check_errors(f"{arb.upload.split(' ')[0]} ({len(values)} points)")
        self.set_checked(arb.sample_rate, rate_hz, "arbitrary sample rate (Sa/s)")
        for part in (p for p in render(arb.select, **self.fields, name=arb.name).split(";") if p.strip()):
            self.link.write(part.strip())
            self.check_errors(part.strip())
        reply = self.ask(arb.function_query)
        if not re.search(arb.function_expect, reply.strip(), re.IGNORECASE):
            raise DeviceRejectedError("instrument", f"{self.where}: after selecting the arbitrary waveform, {arb.function_query!r} "
                                                    f"answers {reply!r}")

    def play_sine(self) -> None:
        """Back to the generator's own sine (after an arbitrary waveform)."""
        if self.profile.arbitrary is not None:
            self.send(self.profile.arbitrary.sine)
            self.check_errors(self.profile.arbitrary.sine)

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
