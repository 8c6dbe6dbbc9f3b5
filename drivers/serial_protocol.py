"""Serial line protocol of the shaker/DAQ front-end: framing, checksums, parsing (pure, no I/O).

The wire format is documented in ``drivers/serial_wire_format.md``. In short, every frame is one
ASCII line::

    request:   @<seq> <COMMAND> [<arg> ...]*<crc>\\n
    response:  !<seq> OK [<value> ...]*<crc>\\n
               !<seq> ERR <code> <message words ...>*<crc>\\n

``seq`` is two hex digits (00-ff) chosen by the host; a response carries its request's
``seq``. ``crc`` is four upper-case hex digits of CRC-16/CCITT-FALSE (polynomial 0x1021, initial
value 0xFFFF; ``binascii.crc_hqx(payload, 0xFFFF)``) over the bytes *between* the start
character and ``*``. Fields are separated by single spaces; numbers are decimal (floats in
Python's shortest round-trip ``repr``, ``nan``/``inf`` allowed only in sample data).

Every parser error is a :class:`setmem_hil.errors.FrameError` subclass that says what was wrong:
:class:`TruncatedFrameError`, :class:`ChecksumError`, :class:`MalformedFrameError`. A device's
``ERR`` answer is decoded into :class:`DeviceRejectedError` by :func:`raise_for_error`.
"""

from __future__ import annotations

import binascii
import math
import numbers
from dataclasses import dataclass

from setmem_hil.errors import DeviceRejectedError, FrameError

MAX_LINE_BYTES = 16384
MAX_READ_SAMPLES = 64
COMMANDS = {
    # name: (number of arguments, argument kinds)  f = finite float, i = integer >= 0
    "IDN?": "",
    "META?": "",
    "STAT?": "",
    "SINE": "ff",
    "STOP": "",
    "RATE": "f",
    "BEGIN": "ii",
    "WAIT": "f",
    "CAPTURE": "i",
    "READ": "ii",
}


class TruncatedFrameError(FrameError):
    """A frame without its terminator, checksum or start character (cut short on the wire)."""


class ChecksumError(FrameError):
    """A frame whose CRC does not match its payload (corrupted on the wire)."""


class MalformedFrameError(FrameError):
    """A frame with a valid checksum but unparsable content (unknown command, bad fields)."""


@dataclass(frozen=True)
class Request:
    """A decoded request frame."""

    seq: int
    command: str
    args: tuple


@dataclass(frozen=True)
class Response:
    """A decoded response frame: ``ok`` with ``values`` (strings), or an error ``code``."""

    seq: int
    ok: bool
    values: tuple[str, ...]
    code: str = ""
    message: str = ""


def crc16(payload: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor)."""
    return binascii.crc_hqx(payload, 0xFFFF)


def format_number(x: float | int) -> str:
    """Integers as decimal, floats as the shortest round-trip ``repr`` (``nan``, ``inf`` kept)."""
    if isinstance(x, numbers.Integral) and not isinstance(x, bool):
        return str(int(x))
    return repr(float(x))


def _frame(start: str, seq: int, fields: list[str]) -> bytes:
    if not 0 <= seq <= 0xFF:
        raise ValueError(f"seq: expected 0..255, found {seq}")
    for f in fields:
        if not f or any(c in f for c in " *@!\r\n") or not f.isascii():
            raise ValueError(f"field {f!r}: must be non-empty printable ASCII without spaces, '*', '@', '!'")
    payload = (f"{seq:02x} " + " ".join(fields)).encode("ascii")
    return start.encode() + payload + b"*" + f"{crc16(payload):04X}".encode() + b"\n"


def encode_request(seq: int, command: str, *args: float | int) -> bytes:
    """Frame a request; raises ValueError for an unknown command or wrong argument count."""
    kinds = COMMANDS.get(command)
    if kinds is None:
        raise ValueError(f"command {command!r}: expected one of {sorted(COMMANDS)}")
    if len(args) != len(kinds):
        raise ValueError(f"command {command}: expected {len(kinds)} arguments, found {len(args)}")
    return _frame("@", seq, [command] + [format_number(a) for a in args])


def encode_response(seq: int, *values: float | int | str) -> bytes:
    """Frame an ``OK`` response with values."""
    return _frame("!", seq, ["OK"] + [v if isinstance(v, str) else format_number(v) for v in values])


def encode_error(seq: int, code: str, message: str) -> bytes:
    """Frame an ``ERR`` response; the message's words are kept, unsafe characters replaced."""
    words = ["".join(c if (c.isascii() and c.isprintable() and c not in "*@!") else "?" for c in w) for w in message.split()]
    return _frame("!", seq, ["ERR", code] + [w for w in words if w][:40])


def _split_frame(line: bytes, start: bytes) -> tuple[int, list[str]]:
    if not isinstance(line, (bytes, bytearray)):
        raise MalformedFrameError(f"frame: expected bytes, found {type(line).__name__}")
    if len(line) > MAX_LINE_BYTES:
        raise MalformedFrameError(f"frame: {len(line)} bytes exceeds the {MAX_LINE_BYTES}-byte line limit")
    if not line.endswith(b"\n"):
        raise TruncatedFrameError(f"frame {bytes(line[:40])!r}: no line terminator (truncated or timed out)")
    body = bytes(line[:-1])
    if body.endswith(b"\r"):
        body = body[:-1]
    if not body.startswith(start):
        raise TruncatedFrameError(f"frame {body[:40]!r}: expected start character {start!r}")
    star = body.rfind(b"*")
    if star < 0 or len(body) - star - 1 != 4:
        raise TruncatedFrameError(f"frame {body[:40]!r}: missing or short checksum after '*'")
    payload, crc_text = body[1:star], body[star + 1 :]
    try:
        crc = int(crc_text.decode("ascii"), 16)
    except (UnicodeDecodeError, ValueError):
        raise ChecksumError(f"frame: checksum field {crc_text!r} is not 4 hex digits") from None
    if crc16(payload) != crc:
        raise ChecksumError(f"frame: checksum {crc:04X} does not match payload (computed {crc16(payload):04X})")
    try:
        text = payload.decode("ascii")
    except UnicodeDecodeError:
        raise MalformedFrameError("frame: payload is not ASCII") from None
    fields = text.split(" ")
    if len(fields) < 2 or any(f == "" for f in fields):
        raise MalformedFrameError(f"frame {text[:40]!r}: expected '<seq> <field> ...' separated by single spaces")
    seq_text = fields[0]
    if len(seq_text) != 2 or any(c not in "0123456789abcdef" for c in seq_text):
        raise MalformedFrameError(f"frame {text[:40]!r}: sequence number {seq_text!r} is not two lower-case hex digits")
    return int(seq_text, 16), fields[1:]


def _number(text: str, kind: str, where: str) -> float | int:
    if kind == "i":
        if not text.isdigit() or len(text) > 12:
            raise MalformedFrameError(f"{where}: expected a non-negative integer, found {text!r}")
        return int(text)
    try:
        value = float(text)
    except ValueError:
        raise MalformedFrameError(f"{where}: expected a number, found {text!r}") from None
    if kind == "f" and not math.isfinite(value):
        raise MalformedFrameError(f"{where}: expected a finite number, found {text!r}")
    return value


def decode_request(line: bytes) -> Request:
    """Parse a request line (device side); raises a FrameError subclass."""
    seq, fields = _split_frame(line, b"@")
    command, raw = fields[0], fields[1:]
    kinds = COMMANDS.get(command)
    if kinds is None:
        raise MalformedFrameError(f"request {seq:02x}: unknown command {command[:20]!r}")
    if len(raw) != len(kinds):
        raise MalformedFrameError(f"request {seq:02x} {command}: expected {len(kinds)} arguments, found {len(raw)}")
    args = tuple(_number(a, k, f"request {seq:02x} {command} argument {i + 1}") for i, (a, k) in enumerate(zip(raw, kinds)))
    return Request(seq, command, args)


def decode_response(line: bytes) -> Response:
    """Parse a response line (host side); raises a FrameError subclass."""
    seq, fields = _split_frame(line, b"!")
    status = fields[0]
    if status == "OK":
        return Response(seq, True, tuple(fields[1:]))
    if status == "ERR":
        if len(fields) < 2:
            raise MalformedFrameError(f"response {seq:02x}: ERR without an error code")
        return Response(seq, False, (), fields[1], " ".join(fields[2:]))
    raise MalformedFrameError(f"response {seq:02x}: status {status[:20]!r} is neither OK nor ERR")


def raise_for_error(response: Response) -> Response:
    """Return an OK response; raise DeviceRejectedError for an ERR response."""
    if not response.ok:
        raise DeviceRejectedError(response.code, f"device rejected the request ({response.code}): {response.message}", seq=response.seq)
    return response


def parse_floats(values: tuple[str, ...], count: int | None, where: str, finite: bool = True) -> list[float]:
    """Values of a response as floats (``count`` of them if given); FrameError otherwise."""
    if count is not None and len(values) != count:
        raise MalformedFrameError(f"{where}: expected {count} values, found {len(values)}")
    kind = "f" if finite else "x"
    return [float(_number(v, kind, f"{where} value {i + 1}")) for i, v in enumerate(values)]


def parse_samples(values: tuple[str, ...], offset: int, count: int, where: str) -> tuple[list[float], list[float], list[float]]:
    """Decode a ``READ`` answer ``<offset> <count> (t f y){count}``; non-finite samples allowed."""
    if len(values) < 2:
        raise MalformedFrameError(f"{where}: expected '<offset> <count> samples...', found {len(values)} values")
    off = _number(values[0], "i", f"{where} offset")
    cnt = _number(values[1], "i", f"{where} count")
    if off != offset or cnt != count:
        raise MalformedFrameError(f"{where}: answer for samples [{off}, {off + cnt}) but [{offset}, {offset + count}) was requested")
    nums = parse_floats(values[2:], 3 * count, where, finite=False)
    return nums[0::3], nums[1::3], nums[2::3]
