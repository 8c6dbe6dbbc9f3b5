"""CAN wire format of the shaker + DAQ front-end: a pure frame codec (no bus, no I/O).

The format (documented for technicians in ``drivers/can_wire_format.md``) uses classic CAN
(11-bit identifiers, 8 data bytes, little-endian integers as in CANopen). Every frame ends
with an application CRC-8 over the identifier and the first seven data bytes, so a frame
corrupted above the bus CRC (a faulty gateway, a fault-injecting fake device) is rejected
with :class:`~setmem_hil.errors.FrameError` and its data are never used.

Identifiers (``node`` = device node id, 1..127):

=================  ==================  =========================================
``0x200 + node``   host -> device      command ``[op][seq][arg u32][aux][crc]``
``0x280 + node``   device -> host      reply ``[op][seq][status][value u32][crc]``
``0x300 + node``   device -> host      force sample ``[acq][index u16][value i32][crc]``
``0x380 + node``   device -> host      response sample (same layout)
``0x400 + node``   device -> host      time stamp (same layout, value = ns off the nominal grid)
``0x480 + node``   device -> host      block header ``[acq][t0 u48 ns][crc]``
``0x700 + node``   device -> host      heartbeat ``[state][flags][counter][tick u32][crc]``
``0x77F``          host -> device      host heartbeat ``[counter][0 * 6][crc]``
=================  ==================  =========================================

Scaled integers: frequency in units of 1e-5 rad/s (u32), amplitude in micronewtons (u32),
samples as i32 with least significant bit ``range / (2**31 - 1)`` (ranges read once with
``GET_INFO``), wait durations in 0.1 ms (u32). The sample rate is the one float on the wire
(IEEE-754 binary32 bits in the u32 argument): sample instants are ``t0 + k / rate`` exactly, and
a scaled integer would shift them by more than a dwell's timestamp check tolerates (1e-6 of a
sample period). Sample instants: block start ``t0`` (header frame, ns) plus ``k / rate`` plus
the per-sample deviation from that grid (time-stamp frame, ns; 0 for a healthy clock).

The thesis's measurements ``g(j omega) = g_0(j omega) + n(j omega)``, ``|n| <= R`` (eq. 3.7)
are estimated from these samples by the sine-dwell measurement, not here; the transport's job
is that no corrupted sample ever reaches that estimate (a corrupted sample would be an error
outside any bound ``R``).
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

from setmem_hil.errors import FrameError

COMMAND_BASE = 0x200
REPLY_BASE = 0x280
FORCE_DATA_BASE = 0x300
RESPONSE_DATA_BASE = 0x380
TIME_DATA_BASE = 0x400
HEADER_BASE = 0x480
HEARTBEAT_BASE = 0x700
HOST_HEARTBEAT_ID = 0x77F
MAX_NODE = 0x7F

OMEGA_LSB_RAD_S = 1e-5
AMPLITUDE_LSB_N = 1e-6
RANGE_LSB = 1e-6  # force range (N) and response range (response unit) in GET_INFO
SAMPLE_FULL_SCALE = 2**31 - 1
INVALID_SAMPLE = -(2**31)  # a sample the DAQ marks invalid (NaN); decodes to NaN
BLOCK_START_LSB_S = 1e-9  # header frame: block start on the device clock (u48 ns)
TIME_OFFSET_LSB_S = 1e-9  # time-stamp frames: deviation from the nominal grid (i32 ns)
WAIT_LSB_S = 1e-4
MAX_BLOCK_SAMPLES = 0xFFFF
U32_MAX = 0xFFFFFFFF


class Opcode(enum.IntEnum):
    """Command opcodes (byte 0 of a command and of its reply)."""

    SET_FREQUENCY = 0x01  # arg: omega, 1e-5 rad/s
    SET_AMPLITUDE = 0x02  # arg: amplitude, uN
    ENABLE = 0x03  # arg: 0 = off, 1 = on
    START_ACQUISITION = 0x04  # arg: number of samples; aux: acquisition id; reply value: start tick
    RESEND = 0x05  # arg: first index (low u16) | count << 16; aux: acquisition id
    GET_INFO = 0x06  # arg: InfoItem; reply value: the item
    STOP = 0x07  # zero output now and disable (emergency stop, always accepted)
    ACQUISITION_COMPLETE = 0x08  # unsolicited reply: seq = acquisition id, value = samples sent
    SET_SAMPLE_RATE = 0x09  # arg: sample rate, IEEE-754 binary32 bits (Hz)
    BEGIN_MEASUREMENT = 0x0A  # arg: measurement index; aux: attempt (simulation control, see docs)
    WAIT = 0x0B  # arg: duration, 0.1 ms; excitation runs on, nothing is sampled


class InfoItem(enum.IntEnum):
    """Items readable with ``GET_INFO`` (arg) and their units."""

    SAMPLE_RATE = 0  # IEEE-754 binary32 bits (Hz)
    FORCE_RANGE = 1  # uN
    RESPONSE_RANGE = 2  # 1e-6 response units
    STATUS = 3  # DeviceState in the low byte, flags in the next


class ReplyStatus(enum.IntEnum):
    """Byte 2 of a reply."""

    OK = 0
    BAD_OPCODE = 1
    OUT_OF_RANGE = 2
    BUSY = 3
    NOT_READY = 4
    FAULT = 5


class DeviceState(enum.IntEnum):
    """Byte 0 of a heartbeat."""

    IDLE = 0
    EXCITING = 1
    FAULT = 3


# --- CRC-8 (polynomial 0x07, init 0, no reflection: CRC-8/SMBUS) -------------------------------

def _make_crc8_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


_CRC8_TABLE = _make_crc8_table()


def crc8(data: bytes) -> int:
    """CRC-8/SMBUS (poly 0x07, init 0x00, no reflection, no final xor) of ``data``."""
    crc = 0
    for b in data:
        crc = _CRC8_TABLE[crc ^ b]
    return crc


def _seal(arbitration_id: int, body7: bytes) -> bytes:
    """Append the CRC-8 over ``id (2 bytes, big-endian) + body`` to a 7-byte body."""
    return body7 + bytes([crc8(arbitration_id.to_bytes(2, "big") + body7)])


def _check_frame(arbitration_id: int, data: bytes, what: str) -> None:
    if len(data) != 8:
        raise FrameError(f"CAN {what} frame 0x{arbitration_id:03X}: expected 8 data bytes, found {len(data)}")
    expected = crc8(arbitration_id.to_bytes(2, "big") + bytes(data[:7]))
    if data[7] != expected:
        raise FrameError(
            f"CAN {what} frame 0x{arbitration_id:03X}: CRC-8 mismatch (frame 0x{data[7]:02X}, computed 0x{expected:02X})"
        )


def _check_node(node: int) -> None:
    if not isinstance(node, int) or not 1 <= node <= MAX_NODE:
        raise ValueError(f"CAN node id: expected an integer in 1..{MAX_NODE}, found {node!r}")


def _u8(name: str, value: int) -> int:
    if not isinstance(value, int) or not 0 <= value <= 0xFF:
        raise ValueError(f"{name}: expected an integer in 0..255, found {value!r}")
    return value


def _u32(name: str, value: int) -> int:
    if not isinstance(value, int) or not 0 <= value <= U32_MAX:
        raise ValueError(f"{name}: expected an integer in 0..{U32_MAX}, found {value!r}")
    return value


# --- scaled integers -------------------------------------------------------------------------

def scale_unsigned(value: float, lsb: float, name: str) -> int:
    """``round(value / lsb)`` as u32; raises ValueError naming ``name`` when out of range."""
    if not (value == value) or value < 0:  # NaN or negative
        raise ValueError(f"{name}: expected a finite value >= 0, found {value!r}")
    counts = round(value / lsb)
    if counts > U32_MAX:
        raise ValueError(f"{name}: {value!r} exceeds the wire range {U32_MAX * lsb:g}")
    return int(counts)


def sample_to_counts(value: float, full_range: float) -> int:
    """Quantise a sample to i32 counts of ``full_range / (2**31 - 1)``.

    Values beyond the range (and infinities) saturate at full scale, as a clipping ADC does;
    NaN becomes :data:`INVALID_SAMPLE`.
    """
    value = float(value)
    if value != value:
        return INVALID_SAMPLE
    if value >= full_range:
        return SAMPLE_FULL_SCALE
    if value <= -full_range:
        return -SAMPLE_FULL_SCALE
    return int(max(-SAMPLE_FULL_SCALE, min(SAMPLE_FULL_SCALE, round(value / full_range * SAMPLE_FULL_SCALE))))


def counts_to_sample(counts: int, full_range: float) -> float:
    """Inverse of :func:`sample_to_counts` (to one least significant bit); invalid -> NaN."""
    if counts == INVALID_SAMPLE:
        return float("nan")
    return counts * full_range / SAMPLE_FULL_SCALE


def float_to_u32(value: float) -> int:
    """IEEE-754 binary32 bits of ``value`` (the sample rate's wire form)."""
    return struct.unpack("<I", struct.pack("<f", float(value)))[0]


def u32_to_float(bits: int) -> float:
    """The binary32 value of ``bits`` (inverse of :func:`float_to_u32`)."""
    return struct.unpack("<f", struct.pack("<I", _u32("float bits", bits)))[0]


def wire_sample_rate(rate_hz: float) -> float:
    """The sample rate both ends use: ``rate_hz`` rounded to binary32."""
    return u32_to_float(float_to_u32(rate_hz))


def time_offset_to_counts(dt_s: float) -> int:
    """Deviation of a sample instant from the nominal grid as i32 nanoseconds (saturating)."""
    dt = float(dt_s)
    if dt != dt:
        return INVALID_SAMPLE
    return int(max(-SAMPLE_FULL_SCALE, min(SAMPLE_FULL_SCALE, round(dt / TIME_OFFSET_LSB_S))))


def block_start_to_counts(t_s: float) -> int:
    """Block start (device clock, s) as u48 nanoseconds (wraps after 78 h)."""
    return int(round(float(t_s) / BLOCK_START_LSB_S)) & 0xFFFFFFFFFFFF


# --- frames ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Command:
    """A host -> device command frame."""

    opcode: int
    seq: int
    arg: int = 0
    aux: int = 0


@dataclass(frozen=True)
class Reply:
    """A device -> host reply (or the unsolicited ACQUISITION_COMPLETE)."""

    opcode: int
    seq: int
    status: int
    value: int = 0


@dataclass(frozen=True)
class SampleFrame:
    """One sample of one channel (``"force"``, ``"response"`` or ``"time"``)."""

    channel: str
    acquisition_id: int
    index: int
    counts: int


@dataclass(frozen=True)
class BlockHeader:
    """Start of acquisition block ``acquisition_id`` on the device clock (u48 ns)."""

    acquisition_id: int
    start_counts: int


@dataclass(frozen=True)
class Heartbeat:
    """Device heartbeat: state, flag bits, wrapping counter and device clock tick."""

    state: int
    flags: int
    counter: int
    tick: int


@dataclass(frozen=True)
class HostHeartbeat:
    counter: int


@dataclass(frozen=True)
class ErrorFrame:
    """A CAN error frame (``error_class`` = SocketCAN error class bits of the identifier)."""

    error_class: int

    @property
    def bus_off(self) -> bool:
        return bool(self.error_class & CAN_ERR_BUSOFF)


CAN_ERR_BUSOFF = 0x40  # SocketCAN linux/can/error.h
CAN_ERR_CRTL = 0x04


def encode_command(node: int, command: Command) -> tuple[int, bytes]:
    """Return ``(arbitration_id, data)`` of a command frame.

    Raises
    ------
    ValueError
        When a field does not fit its wire width (a programming error, never a device fault).
    """
    _check_node(node)
    body = struct.pack(
        "<BBIB", _u8("opcode", int(command.opcode)), _u8("seq", command.seq), _u32("arg", command.arg), _u8("aux", command.aux)
    )
    return COMMAND_BASE + node, _seal(COMMAND_BASE + node, body)


def encode_reply(node: int, reply: Reply) -> tuple[int, bytes]:
    """``(arbitration_id, data)`` of a reply frame (device side); ValueError if a field does not fit."""
    _check_node(node)
    body = struct.pack(
        "<BBBI", _u8("opcode", int(reply.opcode)), _u8("seq", reply.seq), _u8("status", int(reply.status)), _u32("value", reply.value)
    )
    return REPLY_BASE + node, _seal(REPLY_BASE + node, body)


def encode_sample(node: int, sample: SampleFrame) -> tuple[int, bytes]:
    """``(arbitration_id, data)`` of a force, response or time-stamp frame (device side)."""
    _check_node(node)
    base = {"force": FORCE_DATA_BASE, "response": RESPONSE_DATA_BASE, "time": TIME_DATA_BASE}.get(sample.channel)
    if base is None:
        raise ValueError(f"sample channel: expected 'force', 'response' or 'time', found {sample.channel!r}")
    if not 0 <= sample.index <= 0xFFFF:
        raise ValueError(f"sample index: expected 0..65535, found {sample.index}")
    if not INVALID_SAMPLE <= sample.counts <= SAMPLE_FULL_SCALE:
        raise ValueError(f"sample counts: expected an i32, found {sample.counts}")
    body = struct.pack("<BHi", _u8("acquisition id", sample.acquisition_id), sample.index, sample.counts)
    return base + node, _seal(base + node, body)


def encode_header(node: int, header: BlockHeader) -> tuple[int, bytes]:
    """``(arbitration_id, data)`` of a block header frame (device side)."""
    _check_node(node)
    if not 0 <= header.start_counts <= 0xFFFFFFFFFFFF:
        raise ValueError(f"block start: expected a u48, found {header.start_counts}")
    body = bytes([_u8("acquisition id", header.acquisition_id)]) + header.start_counts.to_bytes(6, "little")
    return HEADER_BASE + node, _seal(HEADER_BASE + node, body)


def encode_heartbeat(node: int, heartbeat: Heartbeat) -> tuple[int, bytes]:
    """``(arbitration_id, data)`` of a device heartbeat frame."""
    _check_node(node)
    body = struct.pack(
        "<BBBI", _u8("state", heartbeat.state), _u8("flags", heartbeat.flags), _u8("counter", heartbeat.counter), _u32("tick", heartbeat.tick)
    )
    return HEARTBEAT_BASE + node, _seal(HEARTBEAT_BASE + node, body)


def encode_host_heartbeat(counter: int) -> tuple[int, bytes]:
    """``(0x77F, data)`` of the host heartbeat (the device's watchdog input)."""
    body = bytes([_u8("counter", counter)]) + bytes(6)
    return HOST_HEARTBEAT_ID, _seal(HOST_HEARTBEAT_ID, body)


Frame = Command | Reply | SampleFrame | BlockHeader | Heartbeat | HostHeartbeat | ErrorFrame


def decode_frame(
    node: int, arbitration_id: int, data: bytes, *, is_error_frame: bool = False, is_extended_id: bool = False,
    is_remote_frame: bool = False,
) -> Frame | None:
    """Decode one received frame for ``node``.

    Parameters
    ----------
    node : int
        Node id of the device the caller talks to (frames of other nodes return ``None``).
    arbitration_id, data : int, bytes
        Identifier and data bytes as received.
    is_error_frame, is_extended_id, is_remote_frame : bool
        Flags of the received frame.

    Returns
    -------
    Command, Reply, SampleFrame, BlockHeader, Heartbeat, HostHeartbeat, ErrorFrame or None
        ``None`` for frames that are not part of this protocol or not for ``node``
        (other traffic on a shared bus is not an error).

    Raises
    ------
    FrameError
        A frame with this protocol's identifier but a wrong length, a CRC mismatch, an
        unknown opcode or a remote request: never used, the caller discards it.
    """
    if is_error_frame:
        return ErrorFrame(int(arbitration_id) & 0x1FFFFFFF)
    if is_extended_id:
        return None
    data = bytes(data)
    kinds = {
        COMMAND_BASE + node: "command",
        REPLY_BASE + node: "reply",
        FORCE_DATA_BASE + node: "force sample",
        RESPONSE_DATA_BASE + node: "response sample",
        TIME_DATA_BASE + node: "time sample",
        HEADER_BASE + node: "block header",
        HEARTBEAT_BASE + node: "heartbeat",
        HOST_HEARTBEAT_ID: "host heartbeat",
    }
    what = kinds.get(arbitration_id)
    if what is None:
        return None
    if is_remote_frame:
        raise FrameError(f"CAN {what} frame 0x{arbitration_id:03X}: unexpected remote request")
    _check_frame(arbitration_id, data, what)
    if what == "command":
        opcode, seq, arg, aux = struct.unpack("<BBIB", data[:7])
        if opcode not in Opcode._value2member_map_:
            raise FrameError(f"CAN command frame 0x{arbitration_id:03X}: unknown opcode 0x{opcode:02X}")
        return Command(Opcode(opcode), seq, arg, aux)
    if what == "reply":
        opcode, seq, status, value = struct.unpack("<BBBI", data[:7])
        if opcode not in Opcode._value2member_map_:
            raise FrameError(f"CAN reply frame 0x{arbitration_id:03X}: unknown opcode 0x{opcode:02X}")
        if status not in ReplyStatus._value2member_map_:
            raise FrameError(f"CAN reply frame 0x{arbitration_id:03X}: unknown status {status}")
        return Reply(Opcode(opcode), seq, ReplyStatus(status), value)
    if what in ("force sample", "response sample", "time sample"):
        acq, index, counts = struct.unpack("<BHi", data[:7])
        return SampleFrame(what.split()[0], acq, index, counts)
    if what == "block header":
        return BlockHeader(data[0], int.from_bytes(data[1:7], "little"))
    if what == "heartbeat":
        state, flags, counter, tick = struct.unpack("<BBBI", data[:7])
        return Heartbeat(state, flags, counter, tick)
    if any(data[1:7]):
        raise FrameError(f"CAN host heartbeat frame 0x{arbitration_id:03X}: reserved bytes not zero")
    return HostHeartbeat(data[0])
