"""Modbus register map of the shaker + DAQ front-end and its pure codec (no I/O).

Everything lives in holding registers (function 3 read, 16 write). Multi-register values are
big-endian in both bytes and words (high word first, the Modbus convention). The full map,
with units and access, is in ``drivers/modbus_wire_format.md``; the addresses are the
constants below (0-based wire addresses).

Sample buffers are read in *pages* of :data:`PAGE_REGISTERS` = 124 registers (one read each,
below the 125-register limit of function 3)::

    [acq_id, page_index, n_valid, crc16] + PAGE_SAMPLES x [dev_ns i32, force i32, response i32]

``crc16`` is CRC-16/MODBUS over the other 123 registers (as big-endian bytes), so a page
corrupted anywhere on the way (a gateway, an injected fault, an RTU line) is rejected with
:class:`~setmem_hil.errors.FrameError`, and a stale page (another acquisition or page) is
recognised by its header. Sample instants are ``t0 + k / rate + dev_ns * 1e-9`` with ``t0``
(u64 ns) and ``rate`` (binary32) from the status registers.

Also here: a codec of whole Modbus ADUs for function 3 (request/response/exception) in RTU
framing (CRC-16) and socket/MBAP framing, used by the tests to check byte-exactness against
pymodbus's framers and to fuzz the parser.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from setmem_hil.errors import FrameError, ModbusExceptionError

MAGIC = 0x5348  # "SH"
VERSION = 1

REG_MAGIC = 0
REG_VERSION = 1
REG_OMEGA = 2  # u32, 1e-5 rad/s, RW
REG_AMPLITUDE = 4  # u32, 1e-6 N, RW
REG_ENABLE = 6  # 0/1, RW: writing 1 applies omega and amplitude; 0 zeroes the output
REG_STATUS = 7  # R: bit 0 output on, bit 1 watchdog tripped, bit 2 data ready
REG_SAMPLE_RATE = 8  # binary32 Hz, RW
REG_FORCE_RANGE = 10  # u32, 1e-6 N, R
REG_RESPONSE_RANGE = 12  # u32, 1e-6 response units, R
REG_WAIT = 14  # [u32 duration (0.1 ms), request id] written together: waits once per id
REG_MEASUREMENT = 17  # [u32 index, attempt] written together: begin_measurement (idempotent)
REG_ACQ_LENGTH = 20  # [length, request id] written together: captures once per id
REG_ACQ_DONE_ID = 22  # R: request id of the last completed capture
REG_ACQ_COUNT = 23  # R: samples in the buffer
REG_ACQ_T0 = 24  # R: u64 ns, start of the buffer on the device clock
REG_ACQ_RATE = 28  # R: binary32 Hz, rate of the buffer
N_CONTROL_REGISTERS = 30

BUFFER_BASE = 100
PAGE_HEADER = 4
PAGE_SAMPLES = 20
PAGE_REGISTERS = PAGE_HEADER + 6 * PAGE_SAMPLES  # 124
MAX_PAGES = (0x10000 - BUFFER_BASE) // PAGE_REGISTERS
MAX_SAMPLES = 10000

STATUS_OUTPUT_ON = 0x1
STATUS_WATCHDOG = 0x2
STATUS_DATA_READY = 0x4

OMEGA_LSB_RAD_S = 1e-5
AMPLITUDE_LSB_N = 1e-6
RANGE_LSB = 1e-6
WAIT_LSB_S = 1e-4
T0_LSB_S = 1e-9
DEV_LSB_S = 1e-9
SAMPLE_FULL_SCALE = 2**31 - 1
INVALID_SAMPLE = -(2**31)
U32_MAX = 0xFFFFFFFF


# --- CRC-16/MODBUS -------------------------------------------------------------------------------

def _make_crc16_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC16_TABLE = _make_crc16_table()


def crc16_modbus(data: bytes) -> int:
    """CRC-16/MODBUS (reflected poly 0xA001, init 0xFFFF) of ``data``."""
    crc = 0xFFFF
    for b in data:
        crc = (crc >> 8) ^ _CRC16_TABLE[(crc ^ b) & 0xFF]
    return crc


# --- scalar codecs ---------------------------------------------------------------------------------

def _check_registers(regs, count: int, what: str) -> list[int]:
    regs = list(regs)
    if len(regs) != count:
        raise FrameError(f"Modbus {what}: expected {count} registers, found {len(regs)}")
    for r in regs:
        if not isinstance(r, (int, np.integer)) or not 0 <= int(r) <= 0xFFFF:
            raise FrameError(f"Modbus {what}: register value {r!r} is not a 16-bit word")
    return [int(r) for r in regs]


def u32_to_registers(value: int) -> list[int]:
    if not isinstance(value, (int, np.integer)) or not 0 <= value <= U32_MAX:
        raise ValueError(f"u32 register pair: expected an integer in 0..{U32_MAX}, found {value!r}")
    return [(int(value) >> 16) & 0xFFFF, int(value) & 0xFFFF]


def registers_to_u32(regs, what: str = "u32") -> int:
    hi, lo = _check_registers(regs, 2, what)
    return hi << 16 | lo


def i32_to_registers(value: int) -> list[int]:
    return u32_to_registers(int(value) & U32_MAX)


def registers_to_i32(regs, what: str = "i32") -> int:
    v = registers_to_u32(regs, what)
    return v - (1 << 32) if v & 0x80000000 else v


def u64_to_registers(value: int) -> list[int]:
    if not 0 <= value < 1 << 64:
        raise ValueError(f"u64 registers: expected an integer in 0..2**64-1, found {value!r}")
    return [(int(value) >> s) & 0xFFFF for s in (48, 32, 16, 0)]


def registers_to_u64(regs, what: str = "u64") -> int:
    r = _check_registers(regs, 4, what)
    return r[0] << 48 | r[1] << 32 | r[2] << 16 | r[3]


def float32_to_registers(value: float) -> list[int]:
    return u32_to_registers(struct.unpack(">I", struct.pack(">f", float(value)))[0])


def registers_to_float32(regs, what: str = "float32") -> float:
    return struct.unpack(">f", struct.pack(">I", registers_to_u32(regs, what)))[0]


def wire_sample_rate(rate_hz: float) -> float:
    """The rate both ends use: ``rate_hz`` rounded to binary32."""
    return registers_to_float32(float32_to_registers(rate_hz))


def scale_unsigned(value: float, lsb: float, name: str) -> int:
    """``round(value / lsb)`` as u32; ValueError naming ``name`` when it does not fit."""
    v = float(value)
    if not (v == v) or v < 0:
        raise ValueError(f"{name}: expected a finite value >= 0, found {value!r}")
    counts = round(v / lsb)
    if counts > U32_MAX:
        raise ValueError(f"{name}: {value!r} exceeds the register range {U32_MAX * lsb:g}")
    return int(counts)


def sample_to_counts(value: float, full_range: float) -> int:
    """i32 counts of ``full_range / (2**31 - 1)``: saturating; NaN -> :data:`INVALID_SAMPLE`."""
    v = float(value)
    if v != v:
        return INVALID_SAMPLE
    if v >= full_range:
        return SAMPLE_FULL_SCALE
    if v <= -full_range:
        return -SAMPLE_FULL_SCALE
    return int(max(-SAMPLE_FULL_SCALE, min(SAMPLE_FULL_SCALE, round(v / full_range * SAMPLE_FULL_SCALE))))


def counts_to_samples(counts: np.ndarray, full_range: float) -> np.ndarray:
    c = np.asarray(counts, dtype=np.int64)
    out = c.astype(float) * (full_range / SAMPLE_FULL_SCALE)
    out[c == INVALID_SAMPLE] = np.nan
    return out


def deviation_to_counts(dev_s: float) -> int:
    v = float(dev_s)
    if v != v:
        return INVALID_SAMPLE
    return int(max(-SAMPLE_FULL_SCALE, min(SAMPLE_FULL_SCALE, round(v / DEV_LSB_S))))


# --- status block ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class DeviceInfo:
    """Decoded control registers 0..29."""

    omega_rad_s: float
    amplitude_n: float
    enabled: bool
    status: int
    sample_rate_hz: float
    force_range_n: float
    response_range: float
    acq_done_id: int
    acq_count: int
    acq_t0_s: float
    acq_t0_counts: int
    acq_rate_hz: float

    @property
    def output_on(self) -> bool:
        return bool(self.status & STATUS_OUTPUT_ON)

    @property
    def watchdog_tripped(self) -> bool:
        return bool(self.status & STATUS_WATCHDOG)


def decode_control_block(regs) -> DeviceInfo:
    """Decode registers ``0 .. N_CONTROL_REGISTERS-1``.

    Raises
    ------
    FrameError
        Wrong count, non-16-bit values, wrong magic or version (not this device, or garbled).
    """
    r = _check_registers(regs, N_CONTROL_REGISTERS, "control registers 0..29")
    if r[REG_MAGIC] != MAGIC or r[REG_VERSION] != VERSION:
        raise FrameError(
            f"Modbus control registers: magic/version 0x{r[REG_MAGIC]:04X}/{r[REG_VERSION]} "
            f"(expected 0x{MAGIC:04X}/{VERSION}): not this device or a garbled reply"
        )
    rate = registers_to_float32(r[REG_SAMPLE_RATE : REG_SAMPLE_RATE + 2])
    acq_rate = registers_to_float32(r[REG_ACQ_RATE : REG_ACQ_RATE + 2])
    for name, v in (("sample rate", rate), ("buffer rate", acq_rate)):
        if not (np.isfinite(v) and v >= 0):
            raise FrameError(f"Modbus control registers: {name} {v!r} is not a finite rate")
    t0 = registers_to_u64(r[REG_ACQ_T0 : REG_ACQ_T0 + 4])
    return DeviceInfo(
        omega_rad_s=registers_to_u32(r[REG_OMEGA : REG_OMEGA + 2]) * OMEGA_LSB_RAD_S,
        amplitude_n=registers_to_u32(r[REG_AMPLITUDE : REG_AMPLITUDE + 2]) * AMPLITUDE_LSB_N,
        enabled=bool(r[REG_ENABLE]),
        status=r[REG_STATUS],
        sample_rate_hz=rate,
        force_range_n=registers_to_u32(r[REG_FORCE_RANGE : REG_FORCE_RANGE + 2]) * RANGE_LSB,
        response_range=registers_to_u32(r[REG_RESPONSE_RANGE : REG_RESPONSE_RANGE + 2]) * RANGE_LSB,
        acq_done_id=r[REG_ACQ_DONE_ID],
        acq_count=r[REG_ACQ_COUNT],
        acq_t0_s=t0 * T0_LSB_S,
        acq_t0_counts=t0,
        acq_rate_hz=acq_rate,
    )


# --- sample pages ----------------------------------------------------------------------------------

def page_address(page: int) -> int:
    if not 0 <= page < MAX_PAGES:
        raise ValueError(f"page index: expected 0..{MAX_PAGES - 1}, found {page}")
    return BUFFER_BASE + page * PAGE_REGISTERS


def n_pages(n_samples: int) -> int:
    return -(-int(n_samples) // PAGE_SAMPLES)


def _page_crc(header3: list[int], data: list[int]) -> int:
    return crc16_modbus(struct.pack(f">{3 + len(data)}H", *header3, *data))


def encode_page(acq_id: int, page: int, dev_counts, force_counts, response_counts) -> list[int]:
    """Registers of one page (``len(dev_counts) <= PAGE_SAMPLES`` samples, zero-padded)."""
    n = len(dev_counts)
    if not (n == len(force_counts) == len(response_counts)) or not 0 <= n <= PAGE_SAMPLES:
        raise ValueError(f"page: expected up to {PAGE_SAMPLES} samples per channel, found {n}")
    data: list[int] = []
    for d, f, y in zip(dev_counts, force_counts, response_counts):
        data += i32_to_registers(int(d)) + i32_to_registers(int(f)) + i32_to_registers(int(y))
    data += [0] * (6 * PAGE_SAMPLES - len(data))
    header3 = [acq_id & 0xFFFF, page & 0xFFFF, n]
    return header3 + [_page_crc(header3, data)] + data


@dataclass(frozen=True)
class Page:
    acq_id: int
    page: int
    dev_counts: np.ndarray
    force_counts: np.ndarray
    response_counts: np.ndarray


def decode_page(regs, expected_acq_id: int, expected_page: int) -> Page:
    """Check and decode one page.

    Raises
    ------
    FrameError
        Wrong length, CRC mismatch, a page of another acquisition or index (stale), or a
        sample count above :data:`PAGE_SAMPLES`. The page's data are not used.
    """
    r = _check_registers(regs, PAGE_REGISTERS, f"page {expected_page}")
    header3, crc, data = r[:3], r[3], r[PAGE_HEADER:]
    computed = _page_crc(header3, data)
    if crc != computed:
        raise FrameError(f"Modbus page {expected_page}: CRC-16 mismatch (page 0x{crc:04X}, computed 0x{computed:04X})")
    acq, page, n = header3
    if acq != expected_acq_id & 0xFFFF or page != expected_page:
        raise FrameError(f"Modbus page {expected_page}: stale page (acquisition {acq}, page {page}; expected {expected_acq_id}, {expected_page})")
    if n > PAGE_SAMPLES:
        raise FrameError(f"Modbus page {expected_page}: {n} samples (at most {PAGE_SAMPLES})")
    words = np.asarray(data[: 6 * n], dtype=np.int64).reshape(n, 3, 2)
    values = (words[..., 0] << 16) | words[..., 1]
    values = np.where(values >= 1 << 31, values - (1 << 32), values)
    return Page(acq, page, values[:, 0].copy(), values[:, 1].copy(), values[:, 2].copy())


# --- whole ADUs of function 3 (RTU and socket framing) -------------------------------------------------

def encode_read_request_pdu(address: int, count: int) -> bytes:
    if not 0 <= address <= 0xFFFF or not 1 <= count <= 125:
        raise ValueError(f"read holding registers: address {address} / count {count} out of range (count 1..125)")
    return struct.pack(">BHH", 3, address, count)


def encode_read_response_pdu(registers) -> bytes:
    regs = list(registers)
    return struct.pack(f">BB{len(regs)}H", 3, 2 * len(regs), *regs)


def decode_read_response_pdu(pdu: bytes, expected_count: int) -> list[int]:
    """Registers of a function-3 response PDU.

    Raises
    ------
    ModbusExceptionError
        An exception response (function 0x83).
    FrameError
        Anything else that is not exactly ``expected_count`` registers.
    """
    if len(pdu) < 2:
        raise FrameError(f"Modbus response PDU: {len(pdu)} bytes is too short")
    fc = pdu[0]
    if fc == 0x83:
        if len(pdu) != 2:
            raise FrameError(f"Modbus exception PDU: expected 2 bytes, found {len(pdu)}")
        raise ModbusExceptionError(3, pdu[1])
    if fc != 3:
        raise FrameError(f"Modbus response PDU: function {fc} (expected 3)")
    if pdu[1] != 2 * expected_count or len(pdu) != 2 + 2 * expected_count:
        raise FrameError(
            f"Modbus response PDU: byte count {pdu[1]} and length {len(pdu)} (expected {2 * expected_count} data bytes)"
        )
    return list(struct.unpack(f">{expected_count}H", pdu[2:]))


def rtu_frame(unit: int, pdu: bytes) -> bytes:
    """RTU ADU: ``unit + pdu + CRC-16`` (CRC low byte first)."""
    body = bytes([unit & 0xFF]) + pdu
    return body + struct.pack("<H", crc16_modbus(body))


def rtu_unframe(adu: bytes, unit: int) -> bytes:
    """PDU of an RTU ADU; FrameError for short frames, CRC mismatch or another unit."""
    if len(adu) < 4:
        raise FrameError(f"Modbus RTU frame: {len(adu)} bytes is too short")
    (crc,) = struct.unpack("<H", adu[-2:])
    computed = crc16_modbus(adu[:-2])
    if crc != computed:
        raise FrameError(f"Modbus RTU frame: CRC-16 mismatch (frame 0x{crc:04X}, computed 0x{computed:04X})")
    if adu[0] != unit:
        raise FrameError(f"Modbus RTU frame: unit {adu[0]} (expected {unit})")
    return adu[1:-2]


def mbap_frame(transaction_id: int, unit: int, pdu: bytes) -> bytes:
    """Socket (MBAP) ADU: ``tid, protocol 0, length, unit`` + pdu."""
    return struct.pack(">HHHB", transaction_id & 0xFFFF, 0, len(pdu) + 1, unit & 0xFF) + pdu


def mbap_unframe(adu: bytes, transaction_id: int, unit: int) -> bytes:
    """PDU of an MBAP ADU; FrameError for bad header, length, transaction id or unit."""
    if len(adu) < 8:
        raise FrameError(f"Modbus MBAP frame: {len(adu)} bytes is too short")
    tid, proto, length, u = struct.unpack(">HHHB", adu[:7])
    if proto != 0:
        raise FrameError(f"Modbus MBAP frame: protocol id {proto} (expected 0)")
    if length != len(adu) - 6:
        raise FrameError(f"Modbus MBAP frame: length field {length}, {len(adu) - 6} bytes follow")
    if tid != transaction_id:
        raise FrameError(f"Modbus MBAP frame: transaction id {tid} (expected {transaction_id}): stale or duplicated")
    if u != unit:
        raise FrameError(f"Modbus MBAP frame: unit {u} (expected {unit})")
    return adu[7:]
