"""Emulators of the shipped instrument models on 127.0.0.1 sockets, backed by the emulated bench.

Each emulator speaks its model's published command set over a raw TCP socket (newline
terminated, what PyVISA opens as ``TCPIP::127.0.0.1::<port>::SOCKET``), so a campaign runs end to
end through the real-instrument drivers in CI:

* :class:`GeneratorEmulator`: Keysight/Agilent 33500B series (``SOURce<n>:FREQuency``,
  ``SOURce<n>:VOLTage`` in Vpp, ``OUTPut<n>``, ``OUTPut<n>:LOAD``, ``SYSTem:ERRor?``, arbitrary
  waveforms as ASCII ``SOURce<n>:DATA:ARBitrary``) and Rigol DG800 (the same tree, commands with a
  leading colon, ``OUTPut<n>:IMPedance``, ``OUTPut<n>?`` answering ON/OFF, arbitrary waveforms as
  binary ``:DATA:DAC16`` packages);
* :class:`SiglentGeneratorEmulator`: Siglent SDG1000X/2000X (``C<n>:BSWV``, ``C<n>:OUTP``,
  ``*ESR?``; TrueArb waveforms: ``WVDT`` with raw 16-bit data, ``ARWV``, ``SRATE``);
* :class:`LockInEmulator`: Stanford Research SR830 (``FMOD``, ``OFLT``, ``OFSL``, ``SENS``,
  ``SNAP? 1,2``, ``LIAS?``, ``ERRS?``) and SR860 (``RSRC``, ``OFLT``, ``OFSL``, ``SCAL``,
  ``SNAP? 0,1``, ``CUROVLDSTAT?``, ``*ESR?``).

Binary data (an IEEE 488.2 definite-length block, or Siglent's bare ``WAVEDATA`` bytes) is read
by its length, as the instruments' parsers do: its bytes may hold the terminator.

SCPI headers are matched in their canonical short form (long and short forms, any case), as the
instruments do. An unknown command or a value out of the instrument's range is not executed and
goes to the error queue (SCPI -113 "Undefined header", -222 "Data out of range"); an unknown
query gets no reply, so the driver times out, as with the real instrument.

Simulation only: the real-instrument drivers (:mod:`setmem_hil.drivers.instruments`) never
import this module; :mod:`setmem_hil.loopback.instrument_rigs` starts the emulators.
"""

from __future__ import annotations

import logging
import math
import re
import socket
import socketserver
import threading
import time
from typing import Callable

import numpy as np

from setmem_hil.drivers.instruments.scpi_commands import canonical_header
from setmem_hil.sim_backends.instrument_bench import EmulatedBench

__all__ = ["GeneratorEmulator", "SiglentGeneratorEmulator", "LockInEmulator", "InstrumentServer", "SR830_TIME_CONSTANTS", "SR860_TIME_CONSTANTS"]

log = logging.getLogger(__name__)

SR830_TIME_CONSTANTS = [10e-6, 30e-6, 100e-6, 300e-6, 1e-3, 3e-3, 10e-3, 30e-3, 100e-3, 300e-3, 1, 3, 10, 30, 100, 300, 1e3, 3e3, 10e3, 30e3]
SR860_TIME_CONSTANTS = [1e-6, 3e-6] + SR830_TIME_CONSTANTS
SR830_SENSITIVITIES = [2e-9, 5e-9, 10e-9, 20e-9, 50e-9, 100e-9, 200e-9, 500e-9, 1e-6, 2e-6, 5e-6, 10e-6, 20e-6, 50e-6,
                       100e-6, 200e-6, 500e-6, 1e-3, 2e-3, 5e-3, 10e-3, 20e-3, 50e-3, 100e-3, 200e-3, 500e-3, 1.0]
SR860_SENSITIVITIES = list(reversed(SR830_SENSITIVITIES)) + [1e-9]  # SCAL 0 = 1 V ... 27 = 1 nV

UNDEFINED_HEADER = '-113,"Undefined header"'
OUT_OF_RANGE = '-222,"Data out of range"'
SETTINGS_CONFLICT = '-221,"Settings conflict"'


class SettingsConflict(Exception):
    """A command valid in itself but refused in the instrument's present state (SCPI -221)."""


class _Emulator:
    """Common part: the error queue and ``;``-separated command lines."""

    idn = ""

    def __init__(self, bench: EmulatedBench):
        self.bench = bench
        self.esr = 0  # IEEE 488.2 standard event status register
        self.errors: list[str] = []
        self.commands: list[str] = []  # every command received (tests read the transcript)

    # binary data without a block header follows this text (None: the command set has none)
    raw_payload_marker: bytes | None = None

    def parse_seconds(self, line: str, payload: bytes | None) -> float:
        """Wall-clock seconds the instrument spends taking in this message before it reads the
        next one (a long upload); replies to later queries wait that long. 0: at once."""
        return 0.0

    def raw_payload_length(self, head: bytes) -> int | None:
        """Bytes of binary data after ``head`` (the message up to ``raw_payload_marker``); None:
        it does not say, the data runs to the message's terminator."""
        return None

    def handle_line(self, line: str, payload: bytes | None = None) -> str | bytes | None:
        if payload is not None:  # a command carrying binary data is the whole message
            self.commands.append(line)
            try:
                return self.handle_upload(line, payload)
            except ValueError:
                return self._execution_error()
        replies = []
        for command in (c.strip() for c in line.split(";")):
            if not command:
                continue
            self.commands.append(command)
            try:
                reply = self.handle(command)
            except ValueError:
                reply = self._execution_error()
            except SettingsConflict:
                reply = self._execution_error(SETTINGS_CONFLICT)
            if isinstance(reply, bytes):  # a binary block ends the answer (an IEEE 488.2 definite-length block)
                return reply
            if reply is not None:
                replies.append(reply)
        return ";".join(replies) if replies else None

    def handle(self, command: str) -> str | None:  # pragma: no cover - overridden
        raise NotImplementedError

    def handle_upload(self, command: str, payload: bytes) -> None:
        """A command followed by binary data; instruments without one answer a command error."""
        return self._command_error()

    def _execution_error(self, error: str = OUT_OF_RANGE) -> None:
        """Not executed: a value out of range (SCPI -222) or a setting the present state refuses
        (-221); the execution-error bit of ``*ESR?``."""
        self.errors.append(error)
        self.esr |= 1 << 4
        return None

    def _command_error(self) -> None:
        """An unknown header: SCPI -113 and the command-error bit of ``*ESR?``."""
        self.errors.append(UNDEFINED_HEADER)
        self.esr |= 1 << 5
        return None


def read_message(rfile, emulator: "_Emulator") -> tuple[str, bytes | None] | None:
    """One message from the client: its text and the binary data it carries (None: none), or
    None at the end of the connection. Binary data comes as an IEEE 488.2 definite-length block
    (``#<n><length><bytes>``: the instruments' parsers read exactly ``length`` bytes, whatever
    they hold) or, after the emulator's ``raw_payload_marker``, as bare bytes (as many as the
    text before says, else to the terminator). The message's terminator follows the data."""
    raw = rfile.readline()
    if not raw:
        return None
    block = re.search(rb"#([1-9])", raw)
    if block is not None:
        digits = int(block.group(1))
        length = raw[block.end(): block.end() + digits]
        if len(length) == digits and length.isdigit():  # else not a block: text the parser refuses
            return _with_payload(rfile, raw, block.start(), block.end() + digits, int(length))
    marker = emulator.raw_payload_marker
    if marker is not None and marker in raw:
        start = raw.index(marker) + len(marker)
        length = emulator.raw_payload_length(raw[:start])
        if length is None:  # to the terminator: what a parser without a length can do
            length = len(raw.rstrip(b"\n")) - start
        return _with_payload(rfile, raw, start, start, length)
    return raw.decode("ascii", errors="replace").strip(), None


def _with_payload(rfile, raw: bytes, text_end: int, start: int, length: int) -> tuple[str, bytes]:
    """Read the rest of a ``length``-byte payload starting at ``start`` and the terminator after it."""
    missing = start + length - len(raw)
    if missing > 0:
        raw += rfile.read(missing)
    rest = raw[start + length:]
    if not rest.endswith(b"\n"):
        raw += rfile.readline()  # the terminator (and anything else in the message)
    return raw[:text_end].decode("ascii", errors="replace").strip(), raw[start: start + length]


def _split(command: str) -> tuple[str, str]:
    head, _, args = command.strip().partition(" ")
    return head, args.strip()


def _number(text: str) -> float:
    x = float(text)
    if not math.isfinite(x):
        raise ValueError(text)
    return x


class GeneratorEmulator(_Emulator):
    """A 33500B (``model = "33500B"``) or DG800 (``model = "DG800"``) two-channel generator.

    Only the channel wired to the amplifier (``channel``) drives the bench; the other channel's
    settings are kept but go nowhere. Arbitrary waveforms: the 33500B's named volatile waveforms
    (``SOURce:DATA:ARBitrary <name>,<floats>``, ASCII, or ``SOURce:DATA:ARBitrary:DAC
    <name>,<block>``, 16-bit codes -32767..+32767 in the ``FORMat:BORDer`` order, NORMal: most
    significant byte first) and the DG800's one volatile waveform (``:DATA:DAC16``, binary); both
    play each point held one sample period (``FUNCtion:ARBitrary:SRATe``).

    Timing (issue 40): the 33500B takes in an upload at ``ascii_parse_s_per_byte`` (text: about
    1 MB/s, so the 7 MB of an 881,852-point record take seconds, as an instrument parsing floats
    does) or ``binary_s_per_byte``; it reads nothing else meanwhile, so a query sent after an
    upload is answered only when the upload is taken in (``*OPC?`` included).
    """

    ascii_parse_s_per_byte = 1e-6
    binary_s_per_byte = 1e-8

    def __init__(self, bench: EmulatedBench, model: str = "33500B", channel: int = 1):
        super().__init__(bench)
        if model not in ("33500B", "DG800"):
            raise ValueError(f"unknown generator model {model!r}")
        self.model, self.channel = model, channel
        self.idn = ("Keysight Technologies,33522B,MY57800001,5.02-1.19-2.00-58-00" if model == "33500B"
                    else "Rigol Technologies,DG812,DG8A224201234,00.01.14")
        self.settings = {ch: {"FUNC": "SIN", "FREQ": 1000.0, "VOLT": 0.1, "OFFS": 0.0, "OUTP": False, "LOAD": math.inf, "UNIT": "VPP",
                              "ARB": "", "SRAT": 40e3, "FILT": "STEP"} for ch in (1, 2)}
        self.volatile: dict[int, dict[str, np.ndarray]] = {1: {}, 2: {}}  # arbitrary waveforms downloaded (33500B)
        self.uploads, self.generation = 0, {}  # which download each (channel, name) holds
        self.playing: tuple | None = None  # what the bench plays: (points id, rate)
        self.pending: dict[int, list[np.ndarray]] = {}  # DG800: packages received before END
        self.byte_order = "NORM"  # 33500B FORMat:BORDer: NORMal (most significant byte first) | SWAPped

    def parse_seconds(self, line: str, payload: bytes | None) -> float:
        if self.model != "33500B":
            return 0.0
        if payload is not None:
            return len(payload) * self.binary_s_per_byte
        return len(line) * self.ascii_parse_s_per_byte if "DATA:ARB" in line.upper() else 0.0

    def handle(self, command: str) -> str | None:
        head, args = _split(command)
        query = head.endswith("?")
        nodes = canonical_header(head.rstrip("?"))
        if nodes in (("*IDN",), ("*RST",), ("*CLS",), ("*OPC",), ("SYST", "ERR")):
            return self._common(nodes, query)
        if self.model == "33500B" and nodes == ("FORM", "BORD"):
            return self._byte_order(args, query)
        m = re.fullmatch(r"(SOUR|OUTP)(\d?)", nodes[0]) if nodes else None
        if not m:
            return self._undefined(query)
        ch = int(m.group(2) or 1)
        if ch not in (1, 2):
            return self._undefined(query)
        if self.model == "33500B" and m.group(1) == "SOUR" and nodes[1:2] == ("DATA",):
            return self._data(ch, nodes[2:], args, query)
        key = self._key(m.group(1), nodes[1:])
        if key is None:
            return self._undefined(query)
        self._addressed = ch
        s = self.settings[ch]
        if query:
            return self._format(key, s[key])
        s[key] = self._parse(key, args)
        self._drive()
        return None

    @staticmethod
    def _key(root: str, rest: tuple[str, ...]) -> str | None:
        table = {
            ("SOUR", ("FREQ",)): "FREQ", ("SOUR", ("VOLT",)): "VOLT", ("SOUR", ("VOLT", "OFFS")): "OFFS",
            ("SOUR", ("VOLT", "UNIT")): "UNIT", ("SOUR", ("FUNC",)): "FUNC", ("OUTP", ()): "OUTP",
            ("OUTP", ("LOAD",)): "LOAD", ("OUTP", ("IMP",)): "LOAD",
            ("SOUR", ("FUNC", "ARB")): "ARB", ("SOUR", ("FUNC", "ARB", "SRAT")): "SRAT", ("SOUR", ("FUNC", "ARB", "FILT")): "FILT",
        }
        return table.get((root, rest))

    MAX_ARB_POINTS = 1_000_000  # the standard 1 MSa a channel (33500B)
    DG800_PACKAGE_BYTES = (16, 32768)  # 8 pts .. 16 kpts a package (DG800 guide, :DATA:DAC16)
    DG800_MAX_POINTS = 2_000_000  # the DG800's arbitrary waveform memory (2 Mpts)

    def handle_upload(self, command: str, payload: bytes) -> None:
        """The DG800's ``[:SOURce[<n>]][:TRACe]:DATA:DAC16 VOLATILE,<flag>,<block>`` (DG800
        programming guide): 14-bit DAC codes 0000-3FFF (0000 the waveform's minimum, 3FFF its
        maximum), two bytes a point, 8 pts to 16 kpts a package; ``CON``: more packages follow,
        ``END``: the last, after which the channel plays the waveform (arbitrary function) on its
        own. The guide does not state the byte order: little-endian, as public code driving
        DG800/DG900/DG1000Z hardware packs it."""
        head, args = _split(command)
        nodes = canonical_header(head)
        m = re.fullmatch(r"SOUR(\d?)", nodes[0]) if nodes else None
        ch = int(m.group(1) or 1) if m else 1
        rest = nodes[1:] if m else nodes
        rest = rest[1:] if rest[:1] == ("TRAC",) else rest
        if self.model == "33500B" and rest == ("DATA", "ARB", "DAC") and ch in (1, 2):
            return self._dac_upload(ch, args, payload)
        if self.model != "DG800" or rest != ("DATA", "DAC16") or ch not in (1, 2):
            return self._undefined(False)
        parts = [a.strip().upper() for a in args.split(",")]
        lo, hi = self.DG800_PACKAGE_BYTES
        if len(parts) != 3 or parts[0] != "VOLATILE" or parts[1] not in ("CON", "END") or parts[2] \
                or not lo <= len(payload) <= hi or len(payload) % 2:
            raise ValueError(args)
        codes = np.frombuffer(payload, dtype="<u2")
        pending = self.pending.setdefault(ch, [])
        if np.any(codes > 0x3FFF) or sum(c.size for c in pending) + codes.size > self.DG800_MAX_POINTS:
            pending.clear()
            raise ValueError(args)
        pending.append(codes)
        if parts[1] == "END":
            points = np.concatenate(pending) / 0x3FFF * 2.0 - 1.0
            pending.clear()
            self._store(ch, "VOLATILE", points)
            self.settings[ch].update(FUNC="ARB", ARB="VOLATILE")
            self._drive()
        return None

    def _byte_order(self, args: str, query: bool) -> str | None:
        """``FORMat:BORDer {NORMal|SWAPped}`` (33500B): the byte order of binary blocks."""
        if query:
            return self.byte_order
        word = canonical_header(args)[0] if args else ""
        if word not in ("NORM", "SWAP"):
            raise ValueError(args)
        self.byte_order = word
        return None

    def _dac_upload(self, ch: int, args: str, payload: bytes) -> None:
        """``SOURce<n>:DATA:ARBitrary:DAC <name>,<block>`` (33500B guide): 16-bit integers from
        -32767 to +32767 (the waveform's -1 and +1), two bytes a point in the ``FORMat:BORDer``
        order; 8 points to the memory's size; the name up to 12 characters."""
        name, comma, rest = args.partition(",")
        dtype = ">i2" if self.byte_order == "NORM" else "<i2"
        if not comma or rest.strip() or len(payload) % 2 or not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]{0,11}", name.strip()):
            raise ValueError(args)
        codes = np.frombuffer(payload, dtype=dtype).astype(np.int32)
        if not 8 <= codes.size <= self.MAX_ARB_POINTS or np.any(np.abs(codes) > 32767):
            raise ValueError(args)
        self._store(ch, name.strip().upper(), codes / 32767.0)
        return None

    def _store(self, ch: int, name: str, points: np.ndarray) -> None:
        self.volatile[ch][name] = points
        self.uploads += 1  # each download is a new waveform, even one equal to the last
        self.generation[(ch, name)] = self.uploads

    def _data(self, ch: int, rest: tuple[str, ...], args: str, query: bool) -> None:
        """``SOURce:DATA:VOLatile:CLEar`` and ``SOURce:DATA:ARBitrary <name>, <value>, ...`` (the
        33500B guide: 8 to 1 M values (the standard memory) from -1 to +1; the name up to 12 characters)."""
        if query:
            return self._undefined(query)
        if rest == ("VOL", "CLE"):
            self.volatile[ch].clear()
            return None
        if rest == ("ARB",):
            name, _, values = args.partition(",")
            points = np.array([_number(v) for v in values.split(",")]) if values.strip() else np.zeros(0)
            if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]{0,11}", name.strip()) or not 8 <= points.size <= self.MAX_ARB_POINTS \
                    or np.max(np.abs(points)) > 1.0:
                raise ValueError(args[:40])
            self._store(ch, name.strip().upper(), points)
            return None
        return self._undefined(query)

    def _parse(self, key: str, args: str):
        a = args.upper()
        if key == "OUTP":
            if a in ("ON", "1"):
                return True
            if a in ("OFF", "0"):
                return False
            raise ValueError(args)
        if key == "LOAD":
            if a in ("INF", "INFINITY", "MAX"):
                return math.inf
            value = _number(args)
            if not 1.0 <= value <= 10e3:
                raise ValueError(args)
            return value
        if key == "FUNC":
            if a not in ("SIN", "SINUSOID", "SQU", "RAMP", "DC", "NOIS", "ARB"):
                raise ValueError(args)
            return a[:3]
        if key == "ARB":
            name = args.strip().strip('"').upper()
            if name not in self.volatile[self._addressed]:  # "Specified arb waveform does not exist"
                raise ValueError(args)
            return name
        if key == "FILT":
            if a not in ("OFF", "STEP", "NORM", "NORMAL"):
                raise ValueError(args)
            return a[:4]
        if key == "UNIT":
            if a not in ("VPP", "VRMS"):
                raise ValueError(args)
            return a
        value = _number(args)
        limits = {"FREQ": (1e-6, 20e6), "VOLT": (1e-3, 10.0), "OFFS": (-5.0, 5.0), "SRAT": (1e-6, 160e6)}[key]
        if not limits[0] <= value <= limits[1]:
            raise ValueError(args)
        return value

    def _format(self, key: str, value) -> str:
        if key == "OUTP":  # the 33500B answers 1/0, the DG800 ON/OFF (its guide's :OUTPut<n>[:STATe]?)
            return ("ON" if value else "OFF") if self.model == "DG800" else ("1" if value else "0")
        if key in ("FUNC", "UNIT", "FILT"):
            return str(value)
        if key == "ARB":
            return f'"{value}"'
        if key == "LOAD" and math.isinf(value):
            return "+9.9E+37"
        return f"{value:+.15E}"

    def _drive(self) -> None:
        s = self.settings[self.channel]
        arb = s["FUNC"] == "ARB" and s["ARB"] in self.volatile[self.channel]
        on = s["OUTP"] and (s["FUNC"] == "SIN" or arb) and s["OFFS"] == 0.0
        volt = s["VOLT"]
        peak = volt / 2.0 if s["UNIT"] == "VPP" else volt * math.sqrt(2.0)
        # an arbitrary waveform's points are held one sample period each with the filter off
        # (STEP and NORMal interpolate; emulated as held too: the drivers switch the filter off)
        playing = (self.generation[(self.channel, s["ARB"])], s["SRAT"]) if arb else None
        if playing != self.playing:
            self.bench.set_arbitrary(self.volatile[self.channel][s["ARB"]] if arb else None, s["SRAT"])
            self.playing = playing
        self.bench.set_generator(frequency_hz=s["FREQ"], amplitude_v=peak, output_on=on)

    def _common(self, nodes: tuple[str, ...], query: bool) -> str | None:
        if nodes == ("*IDN",) and query:
            return self.idn
        if nodes == ("*OPC",) and query:
            return "1"
        if nodes == ("SYST", "ERR") and query:
            return self.errors.pop(0) if self.errors else ('+0,"No error"' if self.model == "33500B" else '0,"No error"')
        if nodes == ("*RST",) and not query:
            for ch in (1, 2):
                self.settings[ch].update(FUNC="SIN", FREQ=1000.0, VOLT=0.1, OFFS=0.0, OUTP=False, UNIT="VPP")
            self._drive()
            return None
        if nodes == ("*CLS",) and not query:
            self.errors.clear()
            return None
        return self._undefined(query)

    def _undefined(self, query: bool) -> None:
        self.errors.append(UNDEFINED_HEADER)
        return None


class SiglentGeneratorEmulator(_Emulator):
    """A Siglent SDG1000X/SDG2000X two-channel generator, in Siglent's own syntax.

    Written from Siglent's SDG series programming guide: parameters are comma-separated
    name/value pairs after a ``C<n>:`` channel header (``C1:BSWV FRQ,100``), and queries answer
    with the header and every parameter of the group, with units (``C1:BSWV
    WVTP,SINE,FRQ,100HZ,PERI,0.01S,AMP,0.5V,...``, ``C1:OUTP ON,LOAD,HZ,PLRT,NOR``). Values out of
    the instrument's range set the execution-error bit of ``*ESR?``; unknown headers the
    command-error bit. Only the channel wired to the amplifier (``channel``) drives the bench.
    """

    IDN = {"SDG2000X": "Siglent Technologies,SDG2042X,SDG2XCAQ1R1234,2.01.01.35R3B2",
           "SDG1000X": "Siglent Technologies,SDG1032X,SDG1XCAD2R3456,1.01.01.33R1B6"}
    FREQUENCY_HZ = {"SDG2000X": (1e-6, 40e6), "SDG1000X": (1e-6, 30e6)}

    MAX_POINTS = {"SDG2000X": 8_000_000, "SDG1000X": 16_384}  # TrueArb waveform length
    SAMPLE_RATE = {"SDG2000X": (1e-6, 300e6), "SDG1000X": (1e-6, 30e6)}  # TrueArb, Sa/s
    raw_payload_marker = b"WAVEDATA,"

    def __init__(self, bench: EmulatedBench, model: str = "SDG2000X", channel: int = 1):
        super().__init__(bench)
        if model not in self.IDN:
            raise ValueError(f"unknown Siglent model {model!r}")
        self.model, self.channel, self.idn = model, channel, self.IDN[model]
        self.channels = {ch: {"WVTP": "SINE", "FRQ": 1000.0, "AMP": 4.0, "OFST": 0.0, "PHSE": 0.0,
                              "OUTP": False, "LOAD": "HZ", "PLRT": "NOR", "SYNC": False,
                              "ARWV": "", "SRATE": ("DDS", 1e6, "LINE")} for ch in (1, 2)}
        self.user_waves: dict[str, np.ndarray] = {}  # WVDT uploads, by name
        self.uploads, self.playing = 0, None

    def raw_payload_length(self, head: bytes) -> int | None:
        """``WVDT``'s ``LENGTH,<n>B`` (bytes of wave data), when the header gives it."""
        m = re.search(rb"LENGTH,(\d+)B?,", head, re.IGNORECASE)
        return int(m.group(1)) if m else None

    def handle_upload(self, command: str, payload: bytes) -> None:
        """``C<n>:WVDT WVNM,<name>[,LENGTH,<n>B][,FREQ,..][,AMPL,..][,OFST,..][,PHASE,..],WAVEDATA,<data>``
        (SDG programming guide): stores user waveform ``<name>``; the data are 16-bit two's
        complement points, little-endian, full scale +-32767. The channel header is required but
        does not choose a channel (``ARWV`` does)."""
        head, args = _split(command)
        if not re.fullmatch(r"C[12]:(WVDT|WAVEDATA)", head.upper()):
            return self._command_error()
        parts = [p.strip() for p in args.split(",")]
        if parts[-1:] != [""] or len(parts) % 2 or parts[-2].upper() != "WAVEDATA":  # pairs, then WAVEDATA,
            return self._command_error()
        fields = {k.upper(): v for k, v in zip(parts[:-2:2], parts[1:-2:2])}
        name = fields.get("WVNM", "")
        length = fields.get("LENGTH", "").upper().rstrip("B")
        points = len(payload) // 2
        if not re.fullmatch(r"[A-Za-z0-9_]{1,20}", name) or len(payload) % 2 or not 8 <= points <= self.MAX_POINTS[self.model] \
                or (length and int(length) != len(payload)):
            raise ValueError(args)
        self.user_waves[name] = np.clip(np.frombuffer(payload, dtype="<i2") / 32767.0, -1.0, 1.0)
        self.uploads += 1
        return None

    def handle(self, command: str) -> str | None:
        head, args = _split(command)
        up = head.upper()
        query = up.endswith("?")
        name = up.rstrip("?")
        if name in ("*IDN", "*OPC", "*ESR", "*CLS", "*RST", "SYST:ERR", "SYSTEM:ERROR"):
            return self._common(name, query)
        m = re.fullmatch(r"C([12]):(BSWV|BASIC_WAVE|OUTP|OUTPUT|SYNC|ARWV|ARBWAVE|SRATE|SAMPLERATE)", name)
        if not m:
            return self._command_error()
        ch = int(m.group(1))
        group = {"BASIC_WAVE": "BSWV", "OUTPUT": "OUTP", "ARBWAVE": "ARWV", "SAMPLERATE": "SRATE"}.get(m.group(2), m.group(2))
        s = self.channels[ch]
        if query:
            return self._describe(ch, group)
        parts = [p.strip() for p in args.split(",") if p.strip()]
        if group == "ARWV":
            self._select_wave(s, parts)
        elif group == "SRATE":
            self._set_sample_rate(s, parts)
        elif group == "BSWV":
            if len(parts) % 2:
                return self._command_error()
            for key, value in zip(parts[::2], parts[1::2]):
                self._set_wave(s, key.upper(), value)
        elif group == "OUTP":
            self._set_output(s, parts)
        else:
            if [p.upper() for p in parts] not in (["ON"], ["OFF"]):
                raise ValueError(args)
            s["SYNC"] = parts[0].upper() == "ON"
        self._drive()
        return None

    def _set_wave(self, s: dict, key: str, value: str) -> None:
        if key == "WVTP":
            if value.upper() not in ("SINE", "SQUARE", "RAMP", "PULSE", "NOISE", "ARB", "DC", "PRBS"):
                raise ValueError(value)
            s["WVTP"] = value.upper()
            return
        units = {"FRQ": "HZ", "AMP": "V", "OFST": "V", "PHSE": ""}
        if key not in units:
            raise ValueError(key)
        number = _number(re.sub(f"{units[key]}$", "", value.strip().upper()) if units[key] else value)
        lo, hi = {"FRQ": self.FREQUENCY_HZ[self.model], "AMP": (0.002, 20.0), "OFST": (-10.0, 10.0), "PHSE": (0.0, 360.0)}[key]
        if not lo <= number <= hi:
            raise ValueError(value)
        s[key] = round(number, 6) if key == "FRQ" else number  # 1 uHz frequency resolution

    def _select_wave(self, s: dict, parts: list[str]) -> None:
        """``C<n>:ARWV NAME,<name>``: the user waveform the arbitrary function plays."""
        if len(parts) != 2 or parts[0].upper() != "NAME" or parts[1] not in self.user_waves:
            raise ValueError(",".join(parts))
        s["ARWV"] = parts[1]

    def _set_sample_rate(self, s: dict, parts: list[str]) -> None:
        """``C<n>:SRATE MODE,<DDS|TARB>[,VALUE,<Sa/s>][,INTER,<HOLD|LINE>]``: TrueArb plays each
        point at the sample rate, held (HOLD) or joined by lines (LINE)."""
        mode, value, inter = s["SRATE"]
        for key, word in zip(parts[::2], parts[1::2]):
            key, word = key.upper(), word.upper()
            if key == "MODE" and word in ("DDS", "TARB"):
                mode = word
            elif key == "VALUE":
                value = _number(re.sub(r"SA/S$", "", word))
                lo, hi = self.SAMPLE_RATE[self.model]
                if not lo <= value <= hi:
                    raise ValueError(word)
            elif key == "INTER" and word in ("HOLD", "LINE"):
                inter = word
            else:
                raise ValueError(key)
        if len(parts) % 2:
            raise ValueError(",".join(parts))
        s["SRATE"] = (mode, value, inter)

    @staticmethod
    def _set_output(s: dict, parts: list[str]) -> None:
        i = 0
        while i < len(parts):
            word = parts[i].upper()
            if word in ("ON", "OFF"):
                s["OUTP"] = word == "ON"
                i += 1
            elif word == "LOAD" and i + 1 < len(parts):
                load = parts[i + 1].upper()
                if load != "HZ" and not (load.replace(".", "", 1).isdigit() and 50 <= float(load) <= 100000):
                    raise ValueError(load)
                s["LOAD"] = load
                i += 2
            elif word == "PLRT" and i + 1 < len(parts) and parts[i + 1].upper() in ("NOR", "INVT"):
                s["PLRT"] = parts[i + 1].upper()
                i += 2
            else:
                raise ValueError(word)

    def _describe(self, ch: int, group: str) -> str:
        s = self.channels[ch]
        if group == "OUTP":
            return f"C{ch}:OUTP {'ON' if s['OUTP'] else 'OFF'},LOAD,{s['LOAD']},PLRT,{s['PLRT']}"
        if group == "SYNC":
            return f"C{ch}:SYNC {'ON' if s['SYNC'] else 'OFF'}"
        if group == "ARWV":
            return f"C{ch}:ARWV NAME,{s['ARWV']}"
        if group == "SRATE":
            mode, value, inter = s["SRATE"]
            return f"C{ch}:SRATE MODE,{mode},VALUE,{value:.10g}Sa/s,INTER,{inter}"
        f, amp, off = s["FRQ"], s["AMP"], s["OFST"]
        return (f"C{ch}:BSWV WVTP,{s['WVTP']},FRQ,{f:.12g}HZ,PERI,{1.0 / f:.6g}S,AMP,{amp:.5g}V,"
                f"AMPVRMS,{amp / (2 * math.sqrt(2.0)):.4g}V,OFST,{off:.5g}V,HLEV,{off + amp / 2:.5g}V,"
                f"LLEV,{off - amp / 2:.5g}V,PHSE,{s['PHSE']:.4g}")

    def _drive(self) -> None:
        """The wired channel's output on the bench: its sine, or its TrueArb waveform held at the
        sample rate (LINE interpolation and DDS arbitrary output are not emulated: silent)."""
        s = self.channels[self.channel]
        mode, rate, inter = s["SRATE"]
        arb = s["WVTP"] == "ARB" and s["ARWV"] in self.user_waves and mode == "TARB" and inter == "HOLD"
        on = s["OUTP"] and (s["WVTP"] == "SINE" or arb) and s["OFST"] == 0.0
        playing = (self.uploads, s["ARWV"], rate) if arb else None
        if playing != self.playing:
            self.bench.set_arbitrary(self.user_waves[s["ARWV"]] if arb else None, rate)
            self.playing = playing
        self.bench.set_generator(frequency_hz=s["FRQ"], amplitude_v=s["AMP"] / 2.0, output_on=on)

    def _common(self, name: str, query: bool) -> str | None:
        if name == "*IDN" and query:
            return self.idn
        if name == "*OPC" and query:
            return "1"
        if name == "*ESR" and query:
            value, self.esr = self.esr, 0
            return str(value)
        if name in ("SYST:ERR", "SYSTEM:ERROR") and query:
            return self.errors.pop(0) if self.errors else '0,"No error"'
        if name == "*CLS" and not query:
            self.errors.clear()
            self.esr = 0
            return None
        if name == "*RST" and not query:
            for ch in (1, 2):
                self.channels[ch].update(WVTP="SINE", FRQ=1000.0, AMP=4.0, OFST=0.0, OUTP=False, LOAD="HZ")
            self._drive()
            return None
        return self._command_error()


class LockInEmulator(_Emulator):
    """An SR830 (``model = "SR830"``) or SR860 (``model = "SR860"``) reading one bench signal.

    ``signal`` is ``"force"`` or ``"response"`` (which sensor is wired to its input). The
    reference is locked to the generator when the instrument is set to its external reference;
    on the internal reference the reading is meaningless and the emulator reports "unlocked".
    """

    def __init__(self, bench: EmulatedBench, signal: str, model: str = "SR830"):
        super().__init__(bench)
        if model not in ("SR830", "SR860", "SR865A"):
            raise ValueError(f"unknown lock-in model {model!r}")
        # the SR865A (4 MHz) has the SR860's command set (SR865A manual, chapter 4): it answers
        # as the SR860 does, except for its identity
        self.idn = {"SR830": "Stanford_Research_Systems,SR830,s/n86021,ver1.07",
                    "SR860": "Stanford_Research_Systems,SR860,004512,v1.51",
                    "SR865A": "Stanford_Research_Systems,SR865A,003245,v1.47"}[model]
        model = "SR830" if model == "SR830" else "SR860"
        self.model, self.signal = model, signal
        self.taus = SR830_TIME_CONSTANTS if model == "SR830" else SR860_TIME_CONSTANTS
        self.sens = SR830_SENSITIVITIES if model == "SR830" else SR860_SENSITIVITIES
        self.external = False
        self.tau_index = self.taus.index(0.1)
        self.slope_index = 1
        self.sens_index = self.sens.index(1.0)
        # input and reference set-up: accepted and read back, no effect on the emulated signal
        self.config = ({"ISRC": 0, "ICPL": 0, "IGND": 0, "RSLP": 0, "SYNC": 0, "RMOD": 1, "ILIN": 0, "HARM": 1} if model == "SR830"
                       else {"IVMD": 0, "ISRC": 0, "ICPL": 0, "IGND": 0, "RTRG": 0, "SYNC": 0, "HARM": 1})
        self._apply_filter()

    @property
    def state(self):
        return self.bench.lockins[self.signal]

    def _apply_filter(self) -> None:
        with self.bench.lock:
            self.bench.advance()
            self.state.set_filter(self.taus[self.tau_index], self.slope_index + 1)
            self.state.sensitivity_v = self.sens[self.sens_index]

    @property
    def locked(self) -> bool:
        """On the external reference and not relocking after a frequency step."""
        return self.external and self.bench.reference_locked()

    def _reading(self) -> complex:
        if not self.external:
            return complex(0.0, 0.0)
        z = self.bench.read_lockin(self.signal)
        # while the PLL relocks the reference phase slips: the output is meaningless
        return z if self.bench.reference_locked() else z * complex(0.0, -0.5)

    def _overloaded(self) -> bool:
        z = self._reading()
        return max(abs(z.real), abs(z.imag)) > self.state.sensitivity_v

    def handle(self, command: str) -> str | None:
        head, args = _split(command)
        if " " not in command.strip() and "?" in head and not head.endswith("?"):
            head, args = head[:head.index("?") + 1], head[head.index("?") + 1:]
        up = head.upper()
        query = up.endswith("?")
        name = up.rstrip("?")
        if name == "*IDN" and query:
            return self.idn
        if name == "*CLS" and not query:
            self.errors.clear()
            self.esr = 0
            return None
        if name == "*ESR" and query:
            value, self.esr = self.esr, 0
            return str(value)
        ref_key = "FMOD" if self.model == "SR830" else "RSRC"
        ext_code = 0 if self.model == "SR830" else 1
        if name == ref_key:
            if query:
                return str(ext_code if self.external else 1 - ext_code)
            code = int(_number(args))
            if code not in (0, 1, 2, 3) or (self.model == "SR830" and code > 1):
                raise ValueError(args)
            self.external = code == ext_code
            return None
        if name in ("OFLT", "OFSL", "SENS", "SCAL"):
            attr = {"OFLT": "tau_index", "OFSL": "slope_index", "SENS": "sens_index", "SCAL": "sens_index"}[name]
            if (name == "SENS") != (self.model == "SR830") and name in ("SENS", "SCAL"):
                return self._command_error()
            if query:
                return str(getattr(self, attr))
            index = int(_number(args))
            size = {"tau_index": len(self.taus), "slope_index": 4, "sens_index": len(self.sens)}[attr]
            if not 0 <= index < size:
                raise ValueError(args)
            setattr(self, attr, index)
            self._apply_filter()
            return None
        if name in self.config:
            if query:
                return str(self.config[name])
            value = int(_number(args))
            if not 0 <= value <= (19999 if name == "HARM" else 4):
                raise ValueError(args)
            self.config[name] = value
            return None
        if name == "SNAP" and query:
            wanted = [p.strip().upper() for p in args.split(",")]
            x_code, y_code = ("1", "2") if self.model == "SR830" else ("0", "1")
            z = self._reading()
            values = {x_code: z.real, y_code: z.imag, "X": z.real, "Y": z.imag}
            if self.model == "SR830" and "9" in wanted:
                values["9"] = self.bench.frequency_hz
            if any(w not in values for w in wanted):
                raise ValueError(args)
            return ",".join(f"{values[w]:.7e}" for w in wanted)
        if name in ("FREQ", "FREQEXT") and query:
            return f"{self.bench.frequency_hz:.7e}" if self.external else f"{1000.0:.7e}"
        if name == "LIAS" and query and self.model == "SR830":
            status = (1 if self._overloaded() else 0) | (0 if self.locked else 8)
            return str(status)
        if name == "ERRS" and query and self.model == "SR830":
            return "0"
        if name == "CUROVLDSTAT" and query and self.model == "SR860":
            status = (1 << 4 if self._overloaded() else 0) | (0 if self.locked else 1 << 3)
            return str(status)
        return self._command_error()

class InstrumentServer:
    """A newline-terminated text instrument on ``127.0.0.1:port`` (0: a free port), in a thread.

    ``close()`` stops it; a client then sees the connection refused, as with an instrument
    switched off. Link faults, for tests (the instrument itself keeps its state, output
    included, as a real one does when its LAN cable is pulled):

    * :meth:`drop_link` closes the connection after ``after`` more commands, and with
      ``reconnectable = False`` every later connection too (the link stays down);
    * :meth:`garble_replies` sends the next ``count`` replies as line noise;
    * :meth:`delay_replies` sends the next ``count`` replies to queries matching a pattern
      ``seconds`` late (wall clock: a reply the driver's timeout gives up on).
    """

    GARBLE = "#\x15?~\x7f"

    def __init__(self, emulator: _Emulator, port: int = 0, host: str = "127.0.0.1",
                 on_disconnect: Callable[[], None] | None = None):
        self.emulator = emulator
        lock = emulator.bench.lock
        emu = emulator
        server = self
        self._drop_in: int | None = None
        self._link_down = False
        self._garble = 0
        self._delay: tuple[float, int, str] | None = None  # (seconds, replies left, pattern)

        class Handler(socketserver.StreamRequestHandler):
            def handle(self):  # noqa: D401 - socketserver API
                try:
                    self.connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                    if server._link_down:
                        return
                    while (message := read_message(self.rfile, emu)) is not None:
                        line, payload = message
                        if not line:
                            continue
                        if server._dropping_now():
                            return  # the command is lost with the link
                        time.sleep(emu.parse_seconds(line, payload))  # outside the bench's lock: other instruments go on
                        with lock:
                            reply = emu.handle_line(line, payload)
                        if reply is not None:
                            time.sleep(server._delay_for(line))  # outside the lock: the instrument goes on
                            if server._garble > 0:
                                server._garble -= 1
                                reply = server.GARBLE
                            self.wfile.write(reply + b"\n" if isinstance(reply, bytes) else (reply + "\n").encode("ascii"))
                except (ConnectionError, OSError):
                    pass
                finally:
                    if on_disconnect is not None:
                        on_disconnect()

        class Server(socketserver.ThreadingTCPServer):
            allow_reuse_address = True
            daemon_threads = True

        self._server = Server((host, port), Handler)
        self.host, self.port = self._server.server_address[:2]
        self._thread = threading.Thread(target=self._server.serve_forever, name=f"emulator-{self.port}", daemon=True)
        self._thread.start()

    def drop_link(self, after: int = 0, reconnectable: bool = True) -> None:
        """Close the connection when ``after`` more commands have been received."""
        self._drop_in = after
        self._reconnectable = reconnectable

    def garble_replies(self, count: int = 1) -> None:
        self._garble = count

    def delay_replies(self, seconds: float, count: int = 1, matching: str = "") -> None:
        """Send the next ``count`` replies to commands matching the regular expression
        ``matching`` (any: ``""``) ``seconds`` late."""
        self._delay = (float(seconds), int(count), matching)

    def _delay_for(self, line) -> float:
        if self._delay is None:
            return 0.0
        seconds, left, pattern = self._delay
        text = line.decode("ascii", "replace") if isinstance(line, bytes) else str(line)
        if not re.search(pattern, text):
            return 0.0
        self._delay = (seconds, left - 1, pattern) if left > 1 else None
        return seconds

    def _dropping_now(self) -> bool:
        if self._drop_in is None:
            return False
        if self._drop_in > 0:
            self._drop_in -= 1
            return False
        self._drop_in = None
        self._link_down = not self._reconnectable
        return True

    @property
    def resource(self) -> str:
        return f"TCPIP::{self.host}::{self.port}::SOCKET"

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
