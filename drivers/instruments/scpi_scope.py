"""An oscilloscope as a sampling sensor: force and responses as one triggered record (issue 26).

:class:`ScpiScope` interprets a ``kind = "scpi-scope"`` profile
(:class:`~setmem_hil.drivers.instruments.profile.ScopeProfile`). One :meth:`ScpiScope.record`:

1. picks the shortest time scale whose record (``time_divisions`` x s/div) covers the asked
   duration, asks the profile's points for the channels on, and sets it;
2. arms a single acquisition, triggered on the generator's sync output (a channel or the EXT
   input), and polls the done query on the caller's clock; no trigger within the timeout is a
   :class:`~setmem_hil.errors.DeviceRejectedError` ("no trigger") naming the scope and the source;
3. reads each channel: the preamble (``format,type,points,count,xincrement,xorigin,xreference,
   yincrement,yorigin,yreference``), then the data as IEEE 488.2 definite-length blocks through
   PyVISA's ``query_binary_values``, in pieces of ``max_transfer_points`` where the profile has
   a range command; a record shorter than its preamble says, or a block that is not one, is
   refused naming the scope;
4. refuses a record with a code at the ADC's rails (``clip_codes``: clipped, or a hole) naming
   the channel; the caller moves that channel's vertical scale up and records again
   (:class:`ClippedChannel`).

Volts: ``(code - yorigin - yreference) * yincrement`` where the profile's ``y_origin`` is
``"codes"`` (Rigol), ``(code - yreference) * yincrement + yorigin`` where it is ``"volts"``
(Keysight). Times: ``(i - xreference) * xincrement + xorigin`` from the trigger.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass

import numpy as np

from setmem_hil.drivers.clock import Clock
from setmem_hil.drivers.instruments.profile import ScopeProfile
from setmem_hil.drivers.instruments.scpi_commands import parse_number, render
from setmem_hil.drivers.instruments.scpi_instrument import ScpiInstrument
from setmem_hil.drivers.instruments.visa_link import VisaLink
from setmem_hil.errors import DeviceRejectedError

__all__ = ["ScpiScope", "Preamble", "ClippedChannel", "ScopeRecord", "volts_from_codes"]

log = logging.getLogger(__name__)

PREAMBLE_FIELDS = ("format", "type", "points", "count", "xincrement", "xorigin", "xreference", "yincrement", "yorigin", "yreference")


@dataclass(frozen=True)
class Preamble:
    """The waveform preamble (IEEE-style, as the DS1000Z and InfiniiVision guides define it)."""

    points: int
    xincrement: float
    xorigin: float
    xreference: float
    yincrement: float
    yorigin: float
    yreference: float

    @classmethod
    def parse(cls, reply: str) -> "Preamble":
        parts = [p.strip() for p in reply.split(",")]
        if len(parts) != len(PREAMBLE_FIELDS):
            raise ValueError(f"{len(parts)} fields, expected {len(PREAMBLE_FIELDS)}")
        v = dict(zip(PREAMBLE_FIELDS, (float(p) for p in parts)))
        if not (v["points"] >= 1 and v["xincrement"] > 0 and v["yincrement"] > 0):
            raise ValueError("points, xincrement and yincrement must be positive")
        return cls(int(v["points"]), v["xincrement"], v["xorigin"], v["xreference"], v["yincrement"], v["yorigin"], v["yreference"])


def volts_from_codes(codes: np.ndarray, pre: Preamble, y_origin: str) -> np.ndarray:
    """Codes to volts by the profile's convention (module docstring)."""
    codes = np.asarray(codes, dtype=float)
    if y_origin == "codes":
        return (codes - pre.yorigin - pre.yreference) * pre.yincrement
    return (codes - pre.yreference) * pre.yincrement + pre.yorigin


class ClippedChannel(DeviceRejectedError):
    """A channel's record touched the ADC's rails (or has holes); ``channel`` names it."""

    def __init__(self, where: str, channel: int, count: int, scale_v: float):
        self.channel = channel
        super().__init__("overload", f"{where}: channel {channel}: {count} samples at the ADC's rails at {scale_v:g} V/div "
                                     "(clipped): the record is refused")


@dataclass(frozen=True)
class ScopeRecord:
    """One triggered record: sample times from the trigger (s) and each channel's volts."""

    t_s: np.ndarray
    volts: dict[int, np.ndarray]
    scales_v: dict[int, float]  # V/div of each channel when recorded
    sample_interval_s: float
    completed_at_s: float = math.nan  # the clock when the scope said the record was complete (before the transfer)


class ScpiScope(ScpiInstrument):
    """The driver of a ``kind = "scpi-scope"`` profile (module docstring)."""

    DONE_POLLS = 200  # polls of the done query over the wait (the wait itself is the caller's clock)

    def __init__(self, name: str, profile: ScopeProfile, link: VisaLink, channels: tuple[int, ...], trigger_source: str,
                 trigger_level_v: float, clock: Clock):
        super().__init__(name, profile, link)
        self.profile: ScopeProfile = profile
        # "ext", or "chN": the channel the trigger is wired to (switched on even when not read)
        self.trigger_channel = int(trigger_source[2:]) if trigger_source.startswith("ch") else None
        bad = [c for c in (*channels, *([self.trigger_channel] if self.trigger_channel else [])) if c not in profile.channels]
        if bad:
            raise DeviceRejectedError("instrument", f"{self.where}: channel {bad[0]} does not exist on a {profile.model} (channels {list(profile.channels)})")
        self.channels, self.trigger_source, self.trigger_level_v, self.clock = tuple(channels), trigger_source, trigger_level_v, clock
        self._trigger_now: tuple[str, float] | None = None  # what the scope triggers on now (use_trigger)
        self.scales_v = {c: profile.vertical_scales_v[-1] for c in channels}  # every record starts on the largest scale
        self.time_scale_s = 0.0
        self.points = 0
        # fine scales fill the screen; a channel match (issue 26) holds for the listed steps only
        self.fine_scales = profile.vertical_fine

    # -- set-up ---------------------------------------------------------------------------------
    def initialise(self) -> None:
        self.run_init()
        for ch in self.channels:
            self._command("channel_on", ch=ch)
            self.set_vertical_scale(ch, self.scales_v[ch])
        if self.trigger_channel is not None and self.trigger_channel not in self.channels:
            self._command("channel_on", ch=self.trigger_channel)
            self.set_vertical_scale(self.trigger_channel, self._scale_for(abs(self.trigger_level_v) * 4 + 1e-3))
        self._trigger_now = None
        self.use_trigger(self.trigger_source, self.trigger_level_v)
        if "waveform_setup" in self.profile.commands:
            self._command("waveform_setup")

    def use_trigger(self, source: str, level_v: float) -> None:
        """Trigger the next records on ``source`` (``"ext"`` or ``"chN"``) at ``level_v``, rising;
        sent only when it changes (a multisine record on the force channel, a sine on the sync)."""
        if self._trigger_now == (source, level_v):
            return
        command = (self.profile.trigger_sources["ext"] if source == "ext"
                   else render(self.profile.trigger_sources["channel"], ch=int(source[2:])))
        self._command("trigger", source=command, value=level_v)
        self._trigger_now = (source, level_v)

    def reconnect(self) -> None:
        """A fresh session, then the whole setup sent again before the next record: after a
        query timed out the scope's state is unknown (an acquisition running, a command half
        taken, a setting refused), so the channels, their scales, the trigger, the waveform
        format, the time base and the record length are restored from what this driver holds
        (issue 46: a retry that trusted the old state was refused at every ``:SINGle``)."""
        super().reconnect()
        self.time_scale_s, self.points = 0.0, 0  # sent again by the next set_record_length
        self.initialise()  # the profile's init first (it clears the error queue and stops the acquisition)

    def _command(self, role: str, **values) -> None:
        text = render(self.profile.commands[role], **values)
        for part in (p for p in text.split(";") if p.strip()):
            self.link.write(part.strip())
        self.check_errors(text)

    SCREEN_FILL = 0.8  # a ranged signal's peak fills this much of the half screen

    def _scale_for(self, peak_v: float) -> float:
        """The smallest V/div whose screen (``divisions`` x V/div, centred) holds ``peak_v`` with
        room: a listed step, or with fine scales (``vertical_fine``) the need itself rounded up to 3 digits."""
        scales = self.profile.vertical_scales_v
        need = 2.0 * peak_v / (self.SCREEN_FILL * self.profile.divisions)
        if self.fine_scales and scales[0] < need < scales[-1]:
            digits = 10.0 ** (math.floor(math.log10(need)) - 2)
            return math.ceil(need / digits * (1 - 1e-12)) * digits
        return next((s for s in scales if s >= need), scales[-1])

    def set_vertical_scale(self, channel: int, scale_v: float) -> None:
        self._command("vertical_scale", ch=channel, value=scale_v)
        if "vertical_scale_query" in self.profile.commands:
            got = self.query_parsed(render(self.profile.commands["vertical_scale_query"], ch=channel), parse_number, f"channel {channel} scale")
            if not math.isclose(got, scale_v, rel_tol=1e-3):
                raise DeviceRejectedError("instrument", f"{self.where}: channel {channel} set to {scale_v:g} V/div, reads back {got:g}")
        self.scales_v[channel] = scale_v

    def range_up(self, channel: int) -> bool:
        """A larger V/div for ``channel`` (the next step; with fine scales 3 times: a lightly damped
        response may still be growing); False at the largest."""
        scales = self.profile.vertical_scales_v
        if self.scales_v[channel] >= scales[-1] * (1 - 1e-9):
            return False
        if self.fine_scales:
            self.set_vertical_scale(channel, min(scales[-1], self._scale_for(3.0 * self.scales_v[channel] * self.SCREEN_FILL * self.profile.divisions / 2)))
            return True
        self.set_vertical_scale(channel, next(s for s in scales if s > self.scales_v[channel] * (1 + 1e-9)))
        return True

    def range_for(self, channel: int, peak_v: float) -> None:
        """The smallest V/div that holds ``peak_v`` (auto-ranging from a record's peak)."""
        scale = self._scale_for(peak_v)
        if not math.isclose(scale, self.scales_v[channel]):
            self.set_vertical_scale(channel, scale)

    def hold(self, channel: int, peak_v: float) -> None:
        """A larger V/div for ``channel`` if its present one does not hold ``peak_v`` (never a smaller one)."""
        if self._scale_for(peak_v) > self.scales_v[channel] * (1 + 1e-9):
            self.range_for(channel, peak_v)

    def full_scale_v(self, channel: int) -> float:
        return self.profile.divisions * self.scales_v[channel]

    # A record may come out this much shorter than asked: a dwell's window is a whole number of
    # samples (a planned 120 s window asks 120.01 s) and its fit uses whatever length the record
    # has; without the slack a 12-division screen of 10 s/div would become one of 20 s/div, twice
    # the rig time for nothing.
    LENGTH_SLACK = 0.01

    def _time_scale_for(self, duration_s: float) -> float:
        need = duration_s / self.profile.time_divisions
        scale = next((s for s in self.profile.time_scales_s if s >= need * (1 - self.LENGTH_SLACK)), None)
        if scale is None:
            raise DeviceRejectedError("range", f"{self.where}: a {duration_s:.4g} s record is longer than the {self.profile.model}'s "
                                               f"{self.profile.time_scales_s[-1] * self.profile.time_divisions:g} s")
        return scale

    def record_length_for(self, duration_s: float) -> float:
        """The length of the record :meth:`set_record_length` would set for ``duration_s`` (nothing sent)."""
        return self._time_scale_for(duration_s) * self.profile.time_divisions

    def set_record_length(self, duration_s: float, min_rate_hz: float = 0.0) -> float:
        """The shortest time scale whose record covers ``duration_s`` (within ``LENGTH_SLACK``),
        and the smallest memory depth sampling it at ``min_rate_hz`` or faster (else the deepest);
        returns the record's length."""
        scale = self._time_scale_for(duration_s)
        length = scale * self.profile.time_divisions
        n_on = len(set(self.channels) | ({self.trigger_channel} if self.trigger_channel is not None else set()))
        offered = self.profile.record_points[n_on]
        points = next((p for p in offered if p >= min_rate_hz * length), offered[-1])
        if scale != self.time_scale_s:
            self._command("time_scale", value=scale, offset=length / 2.0)
            self.time_scale_s = scale
        if points != self.points and "record_points" in self.profile.commands:
            self._command("record_points", value=points)
        self.points = points
        return length

    # -- one record -----------------------------------------------------------------------------
    def record(self, duration_s: float, min_rate_hz: float = 0.0) -> ScopeRecord:
        """Arm, wait for the trigger and the record, read every channel (module docstring)."""
        length = self.set_record_length(duration_s, min_rate_hz)
        self._command("arm")
        self._wait_done(length)
        completed = self.clock.now()
        volts, t, dt = {}, None, 0.0
        for ch in self.channels:
            pre, codes = self._read_channel(ch)
            clipped = int(np.isin(codes, self.profile.clip_codes).sum())
            if clipped:
                raise ClippedChannel(self.where, ch, clipped, self.scales_v[ch])
            volts[ch] = volts_from_codes(codes, pre, self.profile.y_origin)
            if t is None:
                t = (np.arange(pre.points) - pre.xreference) * pre.xincrement + pre.xorigin
                dt = pre.xincrement
        return ScopeRecord(t, volts, dict(self.scales_v), dt, completed)

    NOISE_RECORD_S = 0.05
    NOISE_POINTS = 2000

    def noise_divisions(self) -> dict[int, float]:
        """Each channel's rms noise, in divisions at its present scale, from a record completed
        without a trigger (``force_trigger``; call it with the output off). Empty when the
        profile has no such command."""
        if "force_trigger" not in self.profile.commands:
            return {}
        length = self.set_record_length(self.NOISE_RECORD_S, self.NOISE_POINTS / self.NOISE_RECORD_S)
        self._command("arm")
        self._command("force_trigger")
        self._wait_done(length)
        out = {}
        for ch in self.channels:
            pre, codes = self._read_channel(ch)
            out[ch] = float(np.std(volts_from_codes(codes, pre, self.profile.y_origin))) / self.scales_v[ch]
        return out

    def noise_floor_divisions(self) -> dict[int, float]:
        """Each channel's noise in divisions with the output off: :meth:`noise_divisions` at the
        smallest and the largest scale, the smaller of the two (the quantization terms count on
        it: :func:`~setmem_hil.estimation.channel_errors.quantization_bias`). The channels are
        left on the largest scale."""
        scales = self.profile.vertical_scales_v
        found: dict[int, float] = {}
        for scale in (scales[0], scales[-1]):
            for ch in self.channels:
                self.set_vertical_scale(ch, scale)
            for ch, div in self.noise_divisions().items():
                found[ch] = min(div, found.get(ch, math.inf))
        return found

    def _wait_done(self, length_s: float) -> None:
        """Poll the done query until the record is complete; no trigger within the wait (the
        record's length, ten trigger periods of 1 s at most, and 2 s of room) is an error."""
        timeout = 1.5 * length_s + 2.0
        poll = max(1e-3, timeout / self.DONE_POLLS)
        start = self.clock.now()
        while True:
            reply = self.link.query(self.profile.commands["done_query"])
            if self._is_done(reply):
                return
            if self.clock.now() - start > timeout:
                now = self._trigger_now[0] if self._trigger_now else self.trigger_source
                source = "its EXT input" if now == "ext" else f"channel {now[2:]}"
                raise DeviceRejectedError("no trigger", f"{self.where}: no trigger on {source} within {timeout:.3g} s "
                                                        f"({self.profile.commands['done_query']!r} answered {reply!r}): is the "
                                                        "generator's sync output wired to it and switched on?")
            self.clock.sleep(poll)

    def _is_done(self, reply: str) -> bool:
        if self.profile.done_expect:
            return re.search(self.profile.done_expect, reply.strip()) is not None
        try:
            return (int(parse_number(reply)) & self.profile.done_clear_mask) == 0
        except ValueError:
            return False

    def _read_channel(self, channel: int) -> tuple[Preamble, np.ndarray]:
        self._command("waveform_source", ch=channel)
        pre = self.query_parsed(self.profile.commands["preamble"], Preamble.parse, f"channel {channel} preamble")
        word = self.profile.data_format == "word"
        pieces = []
        step = self.profile.max_transfer_points if "waveform_range" in self.profile.commands else pre.points
        for start in range(1, pre.points + 1, step):
            if "waveform_range" in self.profile.commands:
                self._command("waveform_range", start=start, stop=min(pre.points, start + step - 1))
            pieces.append(self.link.query_block(self.profile.commands["data"], "H" if word else "B", self.profile.word_msb_first))
        codes = np.concatenate(pieces) if pieces else np.zeros(0)
        if codes.size != pre.points:
            raise DeviceRejectedError("short record", f"{self.where}: channel {channel}: {codes.size} samples read, the preamble "
                                                      f"announced {pre.points}: the record is refused")
        return pre, codes

    def close(self) -> None:
        self.link.close()
