"""Modbus register values: physical value <-> 16-bit registers, by type, scale and word order.

Physical value = raw x ``scale``. Types ``uint16``, ``int16`` (one register), ``uint32``,
``int32``, ``float32`` (two registers; IEEE 754 for float32). Within a register the bytes are
big-endian (the Modbus standard); ``word_order = "big"`` puts the high word first (the common
"ABCD" order), ``"little"`` the low word first ("CDAB", many PLCs).
"""

from __future__ import annotations

import math
import struct

from setmem_hil.drivers.instruments.profile import RegisterSpec

__all__ = ["encode", "decode"]

_FORMATS = {"uint16": ">H", "int16": ">h", "uint32": ">I", "int32": ">i", "float32": ">f"}


def encode(value: float, spec: RegisterSpec) -> list[int]:
    """Registers holding ``value`` (ValueError if it does not fit the type)."""
    if not math.isfinite(value):
        raise ValueError(f"cannot write {value!r} to a register")
    raw = value / spec.scale
    if spec.type != "float32":
        raw = round(raw)
    try:
        data = struct.pack(_FORMATS[spec.type], raw)
    except struct.error:
        raise ValueError(f"{value:g} (raw {raw:g}) does not fit a {spec.type} register (scale {spec.scale:g})") from None
    words = [int.from_bytes(data[i:i + 2], "big") for i in range(0, len(data), 2)]
    return words if spec.word_order == "big" else words[::-1]


def decode(registers: list[int], spec: RegisterSpec) -> float:
    """The physical value of ``registers`` (as read, in wire order)."""
    words = list(registers) if spec.word_order == "big" else list(registers)[::-1]
    data = b"".join(int(w).to_bytes(2, "big") for w in words)
    (raw,) = struct.unpack(_FORMATS[spec.type], data)
    return float(raw) * spec.scale
