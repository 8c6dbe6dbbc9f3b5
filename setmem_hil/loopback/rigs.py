"""Loopback rigs: the drivers' host side wired to the simulation's fake devices.

This is the one place that imports both :mod:`setmem_hil.drivers` (hardware code, which never
imports simulation code) and :mod:`setmem_hil.sim_backends` (the fake devices). Every loopback
rig owns its fake device the same way: the rig's ``owned`` tuple, closed after the link by
``rig.close()`` (:class:`setmem_hil.drivers.transport.RigLifecycle`); ``rig.owned[0]`` is the
fake device (tests read its injected-fault counters through it).

Transport options come from ``[backend.transport]`` (validated by the procedure schema,
:mod:`setmem_hil.io.procedure_file`; :func:`transport_option` re-checks the value it uses and
names the key), the defaults of each transport are the data in
:mod:`setmem_hil.drivers.transport`.
"""

from __future__ import annotations

import dataclasses
import math
import uuid

import can

from setmem_hil.drivers import can_protocol as cp
from setmem_hil.drivers.can_link import CanLink, CanSettings
from setmem_hil.drivers.can_rig import CanRig
from setmem_hil.drivers.modbus_rig import ModbusLink, ModbusRig
from setmem_hil.drivers.serial_rig import SerialRig
from setmem_hil.drivers.transport import FIELDBUS_RETRY, SERIAL_RETRY, RetryPolicy
from setmem_hil.errors import ProcedureError
from setmem_hil.io.procedure import Procedure
from setmem_hil.sim_backends.fake_can_device import FakeCanDevice
from setmem_hil.sim_backends.fake_device_core import FakeDeviceCore
from setmem_hil.sim_backends.fake_modbus_device import FakeModbusDevice
from setmem_hil.sim_backends.fake_serial_device import FakeSerialDevice
from setmem_hil.sim_backends.transport_faults import CAN_FAULT_KINDS, MODBUS_FAULT_KINDS, split_faults

__all__ = ["open_serial_loopback_rig", "open_can_virtual_rig", "open_modbus_loopback_rig", "retry_policy", "transport_option"]

RETRY_LIMITS = {
    # key: (type, lo, hi) -- one rule for every transport (backoff 0 = retry at once)
    "reply_timeout_s": (float, 1e-3, 60.0),
    "max_attempts": (int, 1, 100),
    "backoff_s": (float, 0.0, 10.0),
    "backoff_max_s": (float, 0.0, 60.0),
}


def transport_option(procedure: Procedure, key: str, kind: type, default, *, choices=None, lo=None, hi=None):
    """``procedure.backend.transport[key]`` checked; ProcedureError naming the key otherwise."""
    opts = procedure.backend.transport or {}
    if key not in opts:
        return default
    value = opts[key]
    source = procedure.source_path or procedure.name
    where = f"[backend.transport] key '{key}'"
    if kind is str:
        if not isinstance(value, str) or (choices is not None and value not in choices):
            expected = f"one of {list(choices)}" if choices is not None else "a string"
            raise ProcedureError(source, where, f"expected {expected}, found {value!r}")
        return value
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok and kind is int:
        ok = value == int(value)
    if ok and ((lo is not None and value < lo) or (hi is not None and value > hi)):
        ok = False
    if not ok:
        bounds = f" in [{lo}, {hi}]" if lo is not None or hi is not None else ""
        raise ProcedureError(source, where, f"expected {'an integer' if kind is int else 'a number'}{bounds}, found {value!r}")
    return kind(value)


def retry_policy(procedure: Procedure, defaults: RetryPolicy) -> RetryPolicy:
    """The transport's retry defaults overridden by ``[backend.transport]`` (same limits everywhere)."""
    given = {key: transport_option(procedure, key, kind, getattr(defaults, key), lo=lo, hi=hi)
             for key, (kind, lo, hi) in RETRY_LIMITS.items()}
    return dataclasses.replace(defaults, **given)


def open_serial_loopback_rig(procedure: Procedure, seed: int) -> SerialRig:
    """Start a fake serial device (``socket://127.0.0.1:<free port>``) and return a rig that owns it."""
    policy = retry_policy(procedure, SERIAL_RETRY)
    device = FakeSerialDevice(FakeDeviceCore.from_procedure(procedure, seed))
    try:
        return SerialRig(device.url, policy, owned=(device,))
    except BaseException:
        device.close()
        raise


def open_can_virtual_rig(procedure, seed: int) -> CanRig:
    """Start a fake CAN device on a unique ``virtual`` channel and return a rig that owns it.

    Parameters
    ----------
    procedure : setmem_hil.io.procedure.Procedure
        ``backend.simulation`` configures the simulated beam, ``backend.faults`` the fault
        injection (core kinds plus ``error_frame``, ``bus_off``), ``backend.transport`` may set
        ``channel``, ``node``, ``reply_timeout_s``, ``max_attempts``, ``backoff_s``,
        ``backoff_max_s``, ``gap_timeout_s`` (other keys are ignored).
        ``safety`` limits every command.
    seed : int
        Seed of the sensor noise.

    Returns
    -------
    CanRig
        ``close()`` commands zero, shuts the host bus down and stops the fake device.

    Raises
    ------
    ProcedureError
        A transport option or fault setting that does not validate (names the key).
    """

    core_procedure, transport_faults = split_faults(procedure, CAN_FAULT_KINDS)
    channel = transport_option(procedure, "channel", str, f"setmem-can-{uuid.uuid4().hex[:12]}")
    node = transport_option(procedure, "node", int, 0x21, lo=1, hi=cp.MAX_NODE)
    settings = CanSettings(
        node=node,
        retry=retry_policy(procedure, FIELDBUS_RETRY),
        gap_timeout_s=transport_option(procedure, "gap_timeout_s", float, 0.2, lo=1e-3, hi=60.0),
    )
    core = FakeDeviceCore.from_procedure(core_procedure, seed)
    device = FakeCanDevice(core, channel, node, transport_faults).start()

    def factory() -> can.BusABC:
        return can.Bus(interface="virtual", channel=channel, receive_own_messages=False)

    try:
        link = CanLink(factory, settings, where=f"CAN channel {channel!r} node 0x{node:02X}")
    except BaseException:
        device.stop()
        raise
    try:
        rig = CanRig(link, procedure.safety, owned=(device,), name=f"can-virtual:{channel}")
    except BaseException:
        link.close()
        device.stop()
        raise
    return rig


def open_modbus_loopback_rig(procedure, seed: int) -> ModbusRig:
    """Start a fake Modbus device (pymodbus server on 127.0.0.1, free port) and return a rig owning it.

    Parameters
    ----------
    procedure : setmem_hil.io.procedure.Procedure
        ``backend.simulation`` configures the simulated beam, ``backend.faults`` the faults
        (core kinds plus ``exception``), ``backend.transport`` may set ``framer``
        (``"socket"`` default, or ``"rtu"``), ``unit``, ``reply_timeout_s``, ``max_attempts``,
        ``backoff_s``, ``backoff_max_s``; ``safety`` limits every command.
    seed : int
        Seed of the sensor noise.

    Returns
    -------
    ModbusRig
        ``close()`` commands zero, closes the client and stops the server.

    Raises
    ------
    ProcedureError
        A transport option or fault setting that does not validate (names the key).
    """

    framer = transport_option(procedure, "framer", str, "socket", choices=("socket", "rtu"))
    unit = transport_option(procedure, "unit", int, 1, lo=1, hi=247)
    retry = retry_policy(procedure, FIELDBUS_RETRY)
    core_procedure, transport_faults = split_faults(procedure, MODBUS_FAULT_KINDS)
    core = FakeDeviceCore.from_procedure(core_procedure, seed)
    device = FakeModbusDevice(core, framer, transport_faults).start()
    link = None
    try:
        link = ModbusLink("127.0.0.1", device.port, framer, unit, retry)
        rig = ModbusRig(link, procedure.safety, owned=(device,), name=f"modbus-loopback:{framer}:{device.port}")
    except BaseException:
        if link is not None:
            link.close()
        device.stop()
        raise
    return rig
