"""Fault kinds a procedure's ``[backend.faults]`` may enable (the loopback fake devices inject them).

Part of the procedure schema, so they live here rather than in the simulation: the fake
devices (:mod:`setmem_hil.sim_backends`) import them, the procedure validation does too, and
neither depends on the other.
"""

FRAME_FAULT_KINDS = ("timeout", "truncate", "corrupt", "duplicate", "reorder", "disconnect")
"""Frame-level faults every fake device injects on its transport."""

DATA_FAULT_KINDS = ("saturation", "nan", "inf", "timestamp_jump")
"""Data-level faults the fake device core applies to captured samples."""

FAULT_KINDS = FRAME_FAULT_KINDS + DATA_FAULT_KINDS
"""Every core fault kind (frame and data)."""

CAN_FAULT_KINDS = ("error_frame", "bus_off")
"""Extra kinds of the CAN fake device."""

MODBUS_FAULT_KINDS = ("exception",)
"""Extra kinds of the Modbus fake device."""

TRANSPORT_FAULT_KINDS = {"serial-loopback": (), "can-virtual": CAN_FAULT_KINDS, "modbus-loopback": MODBUS_FAULT_KINDS}
"""Extra kinds per loopback backend kind."""
