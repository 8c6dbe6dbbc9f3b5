"""Modbus register values: physical value <-> 16-bit registers, by type, scale and word order.

Physical value = raw x ``scale``. Types ``uint16``, ``int16`` (one register), ``uint32``,
``int32``, ``float32`` (two registers; IEEE 754 for float32). The registers themselves are
pymodbus's (``convert_to_registers`` / ``convert_from_registers``, issue 40: the library's code
where it is the same as ours was): big-endian within a register (the Modbus standard);
``word_order = "big"`` puts the high word first (the common "ABCD" order), ``"little"`` the low
word first ("CDAB", many PLCs). This module adds the scale, the rounding of integer types and an
error that names what does not fit.
"""

from __future__ import annotations

import math
import struct

from pymodbus.client.mixin import ModbusClientMixin

from setmem_hil.drivers.instruments.profile import RegisterSpec

__all__ = ["encode", "decode"]

_TYPES = {"uint16": ModbusClientMixin.DATATYPE.UINT16, "int16": ModbusClientMixin.DATATYPE.INT16,
          "uint32": ModbusClientMixin.DATATYPE.UINT32, "int32": ModbusClientMixin.DATATYPE.INT32,
          "float32": ModbusClientMixin.DATATYPE.FLOAT32}


def encode(value: float, spec: RegisterSpec) -> list[int]:
    """Registers holding ``value`` (ValueError if it does not fit the type)."""
    if not math.isfinite(value):
        raise ValueError(f"cannot write {value!r} to a register")
    raw = value / spec.scale
    raw = float(raw) if spec.type == "float32" else int(round(raw))
    try:
        return list(ModbusClientMixin.convert_to_registers(raw, _TYPES[spec.type], word_order=spec.word_order))
    except (struct.error, OverflowError):
        raise ValueError(f"{value:g} (raw {raw:g}) does not fit a {spec.type} register (scale {spec.scale:g})") from None


def decode(registers: list[int], spec: RegisterSpec) -> float:
    """The physical value of ``registers`` (as read, in wire order)."""
    raw = ModbusClientMixin.convert_from_registers([int(r) for r in registers], _TYPES[spec.type], word_order=spec.word_order)
    return float(raw) * spec.scale
