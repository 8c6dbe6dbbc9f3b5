"""The host's side of a real-time target that runs the compensator (docs/real-time-target.md).

Written from the protocol's documentation (one ASCII command per line, one reply line each:
the value, ``OK`` or ``ERR <why>``), not from the firmware's code. :class:`RealTimeTarget` adds
what a lab needs on top of the bare commands:

* **read back** every change: a load is confirmed by the checksum the target computes from what
  it parsed (CRC-32 of the coefficients' binary64 bits, :func:`compensator_checksum`), an
  engagement and a bypass by the state the target reports afterwards;
* **refusals are errors** naming the target and the command (:class:`~setmem_hil.errors.DeviceRejectedError`);
  a reply that is not the protocol's, or an identity that is not a setmem-hil target, is a
  :class:`~setmem_hil.errors.DeviceIdentityError`; no reply is a
  :class:`~setmem_hil.errors.DeviceTimeoutError`.

The line itself is a :class:`LineChannel`: :class:`SerialLineChannel` for a board on a serial
port (any pyserial URL); the emulated target brings its own.
"""

from __future__ import annotations

import math
import re
import struct
import time
import zlib
from dataclasses import dataclass
from typing import Protocol, Sequence

import numpy as np

from setmem_hil.estimation.analyser_sums import AnalyserSums
from setmem_hil.errors import DeviceDisconnectedError, DeviceError, DeviceIdentityError, DeviceRejectedError, DeviceTimeoutError

__all__ = ["LineChannel", "SerialLineChannel", "RealTimeTarget", "TargetIdentity", "TargetState", "AnalyserProgress",
           "compensator_checksum",
           "IDENTITY_PREFIX"]

IDENTITY_PREFIX = "SETMEM-HIL,reference-target,"
BYPASS, ENGAGED, TRIPPED = "BYPASS", "ENGAGED", "TRIPPED"

TRIP_MEANINGS = {
    "drive_limit": "the drive reached the board's limit: the loop grew",
    "watchdog": "the host fell silent for longer than the watchdog",
}
"""What the firmware's own trip reasons mean (docs/real-time-target.md). Any other reason is the
board's hardware (an amplifier fault, an over-temperature, an emergency stop): said as such, never
blamed on the loop (issue 63: ``TRIPPED amplifier_fault`` was reported as "the loop grew")."""


def trip_meaning(reason: str) -> str:
    """A trip's reason as a sentence for the operator."""
    if reason in TRIP_MEANINGS:
        return TRIP_MEANINGS[reason]
    return f"a fault the board reports ({reason or 'no reason given'}), not the loop: check the rig before engaging again"


class LineChannel(Protocol):
    """One command line out, its reply line back (no newline in either)."""

    def exchange(self, line: str) -> str: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class TargetIdentity:
    """What ``*IDN?`` says: the firmware's version, its sample rate and its computation delay."""

    text: str
    version: str
    fs_hz: float
    delay_samples: int

    @classmethod
    def parse(cls, reply: str, where: str) -> "TargetIdentity":
        match = re.fullmatch(r"SETMEM-HIL,reference-target,([^,]+),fs=([0-9.eE+-]+),delay=(\d+)", reply.strip())
        if match is None:
            raise DeviceIdentityError(f"{where}: *IDN? answered {reply.strip()[:60]!r}, not a setmem-hil real-time target "
                                      f"({IDENTITY_PREFIX}<version>,fs=<Hz>,delay=<samples>)")
        return cls(reply.strip(), match.group(1), float(match.group(2)), int(match.group(3)))


@dataclass(frozen=True)
class TargetState:
    """``STATE?``: ``mode`` BYPASS, ENGAGED (at ``gain``) or TRIPPED (``reason``)."""

    mode: str
    gain: float = 0.0
    reason: str = ""

    @classmethod
    def parse(cls, reply: str, where: str) -> "TargetState":
        words = reply.split(maxsplit=1)
        if words == [BYPASS]:
            return cls(BYPASS)
        if len(words) == 2 and words[0] == ENGAGED:
            try:
                return cls(ENGAGED, float(words[1]))
            except ValueError:
                pass
        if words and words[0] == TRIPPED:
            return cls(TRIPPED, reason=words[1] if len(words) > 1 else "")
        raise DeviceIdentityError(f"{where}: STATE? answered {reply[:60]!r} (expected BYPASS, ENGAGED <gain> or TRIPPED <reason>)")

    def __str__(self) -> str:
        return {BYPASS: BYPASS, ENGAGED: f"ENGAGED {self.gain:g}", TRIPPED: f"TRIPPED {self.reason}"}[self.mode]


@dataclass(frozen=True)
class AnalyserProgress:
    """``ANALYSIS?``: ``IDLE``, ``SETTLING left``, ``SUMMING done count`` or ``DONE first_n count``,
    each (but IDLE) with the peak drive and sensor since ``ANALYSE``."""

    state: str
    done: int = 0  # samples summed (SUMMING), or settle samples left (SETTLING)
    count: int = 0
    first_n: int = 0
    peak_drive: float = 0.0
    peak_response: float = 0.0

    @classmethod
    def parse(cls, reply: str, where: str) -> "AnalyserProgress":
        fields = reply.split()
        sizes = {"IDLE": 1, "SETTLING": 4, "SUMMING": 5, "DONE": 5}
        try:
            if not fields or sizes.get(fields[0]) != len(fields):
                raise ValueError(reply)
            state, numbers = fields[0], fields[1:]
            if state == "IDLE":
                return cls("IDLE")
            peaks = float(numbers[-2]), float(numbers[-1])
            if state == "SETTLING":
                return cls(state, done=int(numbers[0]), peak_drive=peaks[0], peak_response=peaks[1])
            if state == "SUMMING":
                return cls(state, done=int(numbers[0]), count=int(numbers[1]), peak_drive=peaks[0], peak_response=peaks[1])
            return cls(state, done=int(numbers[1]), count=int(numbers[1]), first_n=int(numbers[0]), peak_drive=peaks[0],
                       peak_response=peaks[1])
        except ValueError:
            raise DeviceIdentityError(f"{where}: ANALYSIS? answered {reply[:60]!r}, not the protocol's") from None


def compensator_checksum(sos: np.ndarray, gain: float) -> int:
    """The protocol's checksum of a compensator: CRC-32 (IEEE) of the section count as a
    little-endian uint32, then b0 b1 b2 a1 a2 of every section and the gain as little-endian
    IEEE-754 binary64 (a0, always 1, is not sent)."""
    sos = np.asarray(sos, dtype=float).reshape(-1, 6)
    payload = struct.pack("<I", sos.shape[0])
    for row in sos:
        payload += struct.pack("<5d", row[0], row[1], row[2], row[4], row[5])
    return zlib.crc32(payload + struct.pack("<d", float(gain))) & 0xFFFFFFFF


class RealTimeTarget:
    """A real-time target on ``channel``; ``where`` names it in every error (e.g. its port)."""

    def __init__(self, channel: LineChannel, where: str):
        self.channel, self.where = channel, where

    # -- the protocol's commands, each checked ----------------------------------------------------
    def ask(self, line: str) -> str:
        """Send one command; its reply, or :class:`DeviceRejectedError` for ``ERR``."""
        reply = self.channel.exchange(line).strip()
        if reply.startswith("ERR"):
            raise DeviceRejectedError("ERR", f"{self.where}: {line.split()[0]} refused: {reply[3:].strip()}")
        return reply

    def _ok(self, line: str) -> None:
        reply = self.ask(line)
        if reply != "OK":
            raise DeviceIdentityError(f"{self.where}: {line.split()[0]} answered {reply[:60]!r}, not OK")

    def identity(self) -> TargetIdentity:
        return TargetIdentity.parse(self.ask("*IDN?"), self.where)

    def state(self) -> TargetState:
        return TargetState.parse(self.ask("STATE?"), self.where)

    def load(self, sos: Sequence[Sequence[float]], gain: float = 1.0) -> int:
        """Load the sections (rows ``b0 b1 b2 1 a1 a2``) and their gain; returns the checksum the
        target read back, which must equal :func:`compensator_checksum` of what was sent."""
        sos = np.asarray(sos, dtype=float).reshape(-1, 6)
        if not np.allclose(sos[:, 3], 1.0, rtol=0, atol=1e-15):
            raise ValueError("each section's a0 must be 1 (normalised sections, as scipy.signal returns them)")
        self._ok(f"LOAD {sos.shape[0]}")
        for i, row in enumerate(sos):
            self._ok(f"SOS {i} " + " ".join(repr(float(v)) for v in (row[0], row[1], row[2], row[4], row[5])))
        self._ok(f"SOSGAIN {float(gain)!r}")
        reply = self.ask("CHECKSUM?")
        match = re.fullmatch(r"CHECKSUM ([0-9A-Fa-f]{8})", reply)
        if match is None:
            raise DeviceIdentityError(f"{self.where}: CHECKSUM? answered {reply[:60]!r}")
        read_back, sent = int(match.group(1), 16), compensator_checksum(sos, gain)
        if read_back != sent:
            raise DeviceRejectedError("checksum", f"{self.where}: the compensator read back with checksum {read_back:08X}, "
                                                  f"sent {sent:08X}: the target holds other coefficients than were sent")
        return read_back

    def engage(self, gain: float) -> TargetState:
        """Engage the loaded compensator at ``gain``; confirmed by the state read back."""
        self._ok(f"ENGAGE {float(gain)!r}")
        state = self.state()
        if state.mode != ENGAGED or not math.isclose(state.gain, gain, rel_tol=1e-12):
            raise DeviceRejectedError("engage", f"{self.where}: engaged at {gain:g} but the target reports {state}")
        return state

    def bypass(self) -> TargetState:
        """Bypass the compensator (clears a trip); confirmed by the state read back."""
        self._ok("BYPASS")
        state = self.state()
        if state.mode != BYPASS:
            raise DeviceRejectedError("bypass", f"{self.where}: bypassed but the target reports {state}")
        return state

    def set_drive_limit(self, limit: float) -> None:
        self._ok(f"LIMIT {float(limit)!r}")

    def inject(self, amplitude: float, omega_rad_s: float) -> None:
        """The target's own sine at the summing junction (``inject(0, 0)``: off)."""
        self._ok(f"INJECT {float(amplitude)!r} {float(omega_rad_s)!r}")

    def set_watchdog(self, seconds: float) -> None:
        self._ok(f"WATCHDOG {float(seconds)!r}")

    # -- the target's own analyser (ANALYSE, ANALYSIS?, SUMS?) -------------------------------------
    def analyse(self, settle_samples: int, count: int) -> None:
        """Start the analyser on the current injection: wait ``settle_samples``, sum ``count``."""
        self._ok(f"ANALYSE {int(settle_samples)} {int(count)}")

    def analysis(self) -> AnalyserProgress:
        return AnalyserProgress.parse(self.ask("ANALYSIS?"), self.where)

    def sums(self, omega_rad_s: float, fs_hz: float, progress: AnalyserProgress) -> AnalyserSums:
        """The finished analysis's sums (``progress``: its ``DONE`` reply)."""
        rows = {}
        for name, size in (("R", 4), ("U", 4), ("Y", 4), ("REF", 5)):
            reply = self.ask(f"SUMS? {name}")
            try:
                values = tuple(float(v) for v in reply.split())
            except ValueError:
                values = ()
            if len(values) != size or not all(math.isfinite(v) for v in values):
                raise DeviceIdentityError(f"{self.where}: SUMS? {name} answered {reply[:60]!r}, not {size} numbers")
            rows[name] = values
        return AnalyserSums(float(omega_rad_s), float(fs_hz), progress.first_n, progress.count, rows["R"], rows["U"], rows["Y"],
                            rows["REF"], progress.peak_drive, progress.peak_response, self._force_sums())

    def _force_sums(self) -> tuple[float, float, float, float] | None:
        """``SUMS? F``: the force channel's sums, None when the board has none (it answers ``ERR``:
        ``no force channel`` from this firmware, an unknown name from an older one)."""
        reply = self.channel.exchange("SUMS? F").strip()  # an ERR here is an answer, not a fault
        if reply.startswith("ERR"):
            return None
        try:
            values = tuple(float(v) for v in reply.split())
        except ValueError:
            values = ()
        if len(values) != 4 or not all(math.isfinite(v) for v in values):
            raise DeviceIdentityError(f"{self.where}: SUMS? F answered {reply[:60]!r}, not 4 numbers")
        return values

    def ping(self) -> None:
        self._ok("PING")

    def close(self) -> None:
        self.channel.close()


class SerialLineChannel:
    """The protocol over a serial port (pyserial URL: ``/dev/ttyACM0``, ``socket://host:port``...)."""

    def __init__(self, url: str, baudrate: int = 115200, timeout_s: float = 1.0):
        import serial

        self.url, self.timeout_s = url, float(timeout_s)
        try:
            self._port = serial.serial_for_url(url, baudrate=baudrate, timeout=self.timeout_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceDisconnectedError(f"real-time target {url}: cannot open: {exc}") from exc
        self._port.reset_input_buffer()

    def exchange(self, line: str) -> str:
        import serial

        try:
            self._port.write(line.encode("ascii") + b"\n")
            deadline, reply = time.monotonic() + self.timeout_s, b""
            while not reply.endswith(b"\n"):
                if time.monotonic() > deadline:
                    raise DeviceTimeoutError(f"real-time target {self.url}: no reply to {line.split()[0]} within {self.timeout_s:g} s")
                reply += self._port.read_until(b"\n")
        except DeviceError:  # our own timeout is an OSError too: it stays a timeout, not "link lost"
            raise
        except (serial.SerialException, OSError) as exc:
            raise DeviceDisconnectedError(f"real-time target {self.url}: link lost: {exc}") from exc
        return reply.decode("ascii", errors="replace").rstrip("\r\n")

    def close(self) -> None:
        self._port.close()
