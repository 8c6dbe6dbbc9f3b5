"""A function generator driven through its SCPI profile (Keysight 33500B, Rigol DG800, ...)."""

from __future__ import annotations

import math
import re

import numpy as np

from setmem_hil.drivers.instruments.source import check_instrument_range
from setmem_hil.drivers.instruments.profile import ArbitraryWaveform, ScpiGeneratorProfile
from setmem_hil.drivers.instruments.scpi_commands import fill_fields, render
from setmem_hil.drivers.instruments.scpi_instrument import ScpiInstrument
from setmem_hil.drivers.instruments.visa_link import VisaLink
from setmem_hil.errors import DeviceRejectedError, SafetyLimitError

__all__ = ["ScpiGenerator", "AMPLITUDE_FACTORS", "dac_codes", "points_of_codes"]

# instrument unit per peak volt
AMPLITUDE_FACTORS = {"Vpp": 2.0, "Vpk": 1.0, "Vrms": 1.0 / math.sqrt(2.0)}


def dac_codes(points: np.ndarray, codes: tuple[int, int]) -> np.ndarray:
    """Points in [-1, 1] as the DAC codes ``codes`` gives for -1 and +1 (linear, rounded)."""
    low, high = codes
    return np.clip(np.rint(low + (np.asarray(points, dtype=float) + 1.0) * 0.5 * (high - low)), low, high).astype(np.int64)


def points_of_codes(dac: np.ndarray, codes: tuple[int, int]) -> np.ndarray:
    """What DAC codes play, as points in [-1, 1] (the inverse of :func:`dac_codes`)."""
    low, high = codes
    return np.clip(2.0 * (np.asarray(dac, dtype=float) - low) / (high - low) - 1.0, -1.0, 1.0)


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

    def play_arbitrary(self, points, rate_hz: float) -> np.ndarray:
        """Upload ``points`` (in [-1, 1]; each held one sample period) and play them at ``rate_hz``
        Sa/s, then read back the function and the rate (issue 26). The amplitude (``set_amplitude_v``)
        scales them: the waveform's peak is the amplitude times the largest ``|point|``. Call with
        the output off; the caller checks the peak before anything is sent.

        Returns the points the generator plays: the ones sent, as the instrument reads them (a
        binary upload's DAC codes decoded; an ASCII upload's six decimals), never above 1."""
        arb = self.profile.arbitrary
        if arb is None:
            raise DeviceRejectedError("instrument", f"{self.where}: the {self.model} profile has no [arbitrary] table")
        values = np.asarray(points, dtype=float)
        largest = float(np.max(np.abs(values))) if values.size else 0.0
        if not 8 <= values.size <= arb.max_points or not largest <= 1.0:
            raise DeviceRejectedError("range", f"{self.where}: an arbitrary waveform needs 8-{arb.max_points} points within +-1, "
                                               f"found {values.size} (largest {largest:.3g}); nothing was sent")
        check_instrument_range(self.where, self.model, rate_hz, arb.sample_rate_limits, "Sa/s")
        if arb.clear:
            self.send(arb.clear)
            self.check_errors(arb.clear)
        played = self._upload_binary(arb, values) if arb.data == "binary" else self._upload_ascii(arb, values)
        for part in (p for p in render(arb.select, **self.fields, name=arb.name).split(";") if p.strip()):
            self.link.write(part.strip())
            self.check_errors(part.strip())
        # after the selection: some generators take the rate of the waveform they select
        self.set_checked(arb.sample_rate, rate_hz, "arbitrary sample rate (Sa/s)")
        reply = self.ask(arb.function_query)
        if not re.search(fill_fields(arb.function_expect, **self.fields), reply.strip(), re.IGNORECASE):
            raise DeviceRejectedError("instrument", f"{self.where}: after selecting the arbitrary waveform, {arb.function_query!r} "
                                                    f"answers {reply!r}")
        return played

    def _upload_ascii(self, arb: ArbitraryWaveform, values: np.ndarray) -> np.ndarray:
        text = [f"{v:.6f}" for v in values]
        command = render(arb.upload, **self.fields, name=arb.name, values=",".join(text))
        self.link.write(command)
        self._await_upload(arb, len(command))
        self.check_errors(f"{arb.upload.split(' ')[0]} ({values.size} points)")
        return np.array([float(t) for t in text])

    def _upload_binary(self, arb: ArbitraryWaveform, values: np.ndarray) -> np.ndarray:
        """The points as DAC codes, in packages of at most ``package_points`` (each at least 8:
        the sizes spread evenly), each package's error queue read before the next is sent."""
        codes = dac_codes(values, arb.codes)
        datatype = "h" if arb.codes[0] < 0 else "H"
        header = "ieee" if arb.block == "ieee" else "empty"
        count = math.ceil(codes.size / arb.package_points)
        packages = np.array_split(codes, count)
        if arb.byte_order_command:
            self.send(arb.byte_order_command)
        for i, package in enumerate(packages):
            flag = arb.package_flags[1] if i == count - 1 else arb.package_flags[0]
            command = render(arb.upload, **self.fields, name=arb.name, flag=flag, points=package.size, bytes=2 * package.size)
            self.link.write_binary(command, package.tolist(), datatype, big_endian=arb.byte_order == "msb", header=header)
            self._await_upload(arb, 2 * package.size)
            self.check_errors(f"{command.split(' ')[0]} (package {i + 1} of {count}, {package.size} points)")
        return points_of_codes(codes, arb.codes)

    def _await_upload(self, arb: ArbitraryWaveform, size_bytes: int) -> None:
        """Ask ``complete_query`` (``*OPC?``) and wait for its answer as long as the upload may
        take at ``upload_bytes_per_s``: an instrument still parsing answers nothing meanwhile,
        and a query with the link's short timeout would give up and leave a late reply behind."""
        if arb.complete_query:
            timeout_s = self.link.timeout_s + size_bytes / arb.upload_bytes_per_s
            self.link.query(render(arb.complete_query, **self.fields), timeout_s=timeout_s)

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
