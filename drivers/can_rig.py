"""CAN front-end: a :class:`~setmem_hil.drivers.protocols.Rig` speaking ``can_wire_format.md``.

The link (commands, retries, sample assembly, resend, bus-off recovery) is
:class:`setmem_hil.drivers.can_link.CanLink`. :class:`CanRig` adds the exciter (limits checked
before sending, via :func:`~setmem_hil.drivers.fieldbus_common.check_sine_command`) and the
sensor, commands zero on every abort path and at exit, and implements the optional rig
capabilities of :mod:`setmem_hil.drivers.protocols` (sample rate, wait, measurement index,
reconnect). :func:`open_can_virtual_rig` starts the fake device on a uniquely named
python-can ``virtual`` channel and returns a rig that owns it.

The measured samples feed the sine-dwell estimate of one frequency-response point (thesis
eq. 3.7: ``g = g_0 + n``, ``|n| <= R``); nothing here depends on the identification.

Example
-------
>>> from setmem_hil.io.procedure import default_procedure
>>> with open_can_virtual_rig(default_procedure(), seed=1) as rig:
...     rig.sensor.set_sample_rate(20.0)
...     rig.exciter.set_sine(5.0, 0.5)
...     block = rig.sensor.acquire(2.0)
...     rig.exciter.stop()
>>> block.force.shape
(40,)
"""

from __future__ import annotations

import uuid
from typing import Callable

import can
import numpy as np

from setmem_hil.drivers import can_protocol as cp
from setmem_hil.drivers.can_link import CanLink, CanSettings
from setmem_hil.drivers.fieldbus_common import (
    FieldbusRigLifecycle,
    RetryPolicy,
    SafeShutdown,
    check_duration,
    check_sine_command,
    transport_option,
)
from setmem_hil.drivers.protocols import RigMetadata, SampleBlock
from setmem_hil.errors import DeviceError

__all__ = ["CanExciter", "CanLink", "CanRig", "CanSensor", "CanSettings", "open_can_virtual_rig"]


class CanExciter:
    """Exciter over a :class:`CanLink`: limits checked before anything is sent."""

    def __init__(self, rig: "CanRig"):
        self._rig = rig

    def set_sine(self, omega_rad_s: float, amplitude_n: float) -> None:
        rig = self._rig
        check_sine_command(rig.limits, omega_rad_s, amplitude_n, rig.link.where)
        with rig.guard.armed():
            link = rig.link
            link.request(cp.Opcode.SET_FREQUENCY, cp.scale_unsigned(omega_rad_s, cp.OMEGA_LSB_RAD_S, "omega_rad_s"), what="SET_FREQUENCY")
            link.request(cp.Opcode.SET_AMPLITUDE, cp.scale_unsigned(amplitude_n, cp.AMPLITUDE_LSB_N, "amplitude_n"), what="SET_AMPLITUDE")
            link.request(cp.Opcode.ENABLE, 1, what="ENABLE")
            rig.output_on = True

    def stop(self) -> None:
        self._rig.link.request(cp.Opcode.STOP, what="STOP")
        self._rig.output_on = False


class CanSensor:
    """Sensor over a :class:`CanLink`: timestamps, force and response of every sample."""

    def __init__(self, rig: "CanRig"):
        self._rig = rig

    def set_sample_rate(self, rate_hz: float) -> None:
        rig = self._rig
        with rig.guard.armed():
            rate = float(rate_hz)
            if not (np.isfinite(rate) and rate > 0):
                raise ValueError(f"rate_hz: expected a finite positive rate, found {rate_hz!r}")
            rig.link.request(cp.Opcode.SET_SAMPLE_RATE, cp.float_to_u32(rate), what="SET_SAMPLE_RATE")
            rig.refresh_metadata()

    def wait(self, duration_s: float) -> None:
        """Let ``duration_s`` pass on the device with the excitation on (settling), no samples."""
        rig = self._rig
        if duration_s == 0:
            return
        check_duration(rig.limits, duration_s, rig.link.where)
        with rig.guard.armed():
            rig.link.request(cp.Opcode.WAIT, cp.scale_unsigned(duration_s, cp.WAIT_LSB_S, "duration_s"), what="WAIT")

    def acquire(self, duration_s: float) -> SampleBlock:
        rig = self._rig
        check_duration(rig.limits, duration_s, rig.link.where)
        with rig.guard.armed():
            rig.check_output()
            md = rig.metadata
            n_total = max(1, int(round(duration_s * md.sample_rate_hz)))
            t_parts, f_parts, r_parts = [], [], []
            done = 0
            while done < n_total:
                n = min(rig.link.settings.max_block_samples, n_total - done)
                start_s, counts = rig.link.acquire_block(n)
                t = start_s + np.arange(n) / md.sample_rate_hz + counts["time"] * cp.TIME_OFFSET_LSB_S
                t[counts["time"] == cp.INVALID_SAMPLE] = np.nan
                t_parts.append(t)
                f_parts.append(_to_units(counts["force"], md.force_range_n))
                r_parts.append(_to_units(counts["response"], md.response_range))
                done += n
            return SampleBlock(np.concatenate(t_parts), np.concatenate(f_parts), np.concatenate(r_parts))


def _to_units(counts: np.ndarray, full_range: float) -> np.ndarray:
    values = counts.astype(float) * (full_range / cp.SAMPLE_FULL_SCALE)
    values[counts == cp.INVALID_SAMPLE] = np.nan
    return values


class CanRig(FieldbusRigLifecycle):
    """A rig on a CAN link (see the module docstring).

    Parameters
    ----------
    link : CanLink
    limits : SafetyLimits
        The procedure's limits, checked before any command is sent.
    on_close : callable, optional
        Called last by :meth:`close` (stops an owned fake device).
    """

    def __init__(self, link: CanLink, limits, on_close: Callable[[], None] | None = None, name: str = "can"):
        self.link = link
        self.limits = limits
        self.output_on = False
        self._on_close = on_close
        self._closed = False
        self.guard = SafeShutdown(self._stop_output)
        self.exciter = CanExciter(self)
        self.sensor = CanSensor(self)
        self._name = name
        self.metadata = RigMetadata(sample_rate_hz=1.0, force_range_n=1.0, response_range=1.0, name=name)
        with self.guard.armed():
            self.refresh_metadata()
        self.guard.register_exit(self.close)

    def _stop_output(self) -> None:
        if self.link._bus is not None:
            self.exciter.stop()

    def refresh_metadata(self) -> None:
        """Read sample rate and channel ranges with ``GET_INFO``."""
        def info(item):
            return self.link.request(cp.Opcode.GET_INFO, int(item), what=f"GET_INFO {item.name}").value

        self.metadata = RigMetadata(
            sample_rate_hz=cp.u32_to_float(info(cp.InfoItem.SAMPLE_RATE)),
            force_range_n=info(cp.InfoItem.FORCE_RANGE) * cp.RANGE_LSB,
            response_range=info(cp.InfoItem.RESPONSE_RANGE) * cp.RANGE_LSB,
            name=self._name,
        )

    def check_output(self) -> None:
        """Raise DeviceError if the device dropped an output the rig turned on (watchdog)."""
        if not self.output_on:
            return
        status = self.link.request(cp.Opcode.GET_INFO, int(cp.InfoItem.STATUS), what="GET_INFO STATUS").value
        if status & 0xFF != cp.DeviceState.EXCITING:
            raise DeviceError(f"{self.link.where}: exciter output dropped by the device (status 0x{status:04X}); dwell aborted")

    def begin_measurement(self, index: int, attempt: int = 0) -> None:
        """Mark the start of measurement ``index`` (the fake device reseeds its noise; see docs)."""
        with self.guard.armed():
            self.link.request(cp.Opcode.BEGIN_MEASUREMENT, int(index), int(attempt) & 0xFF, what="BEGIN_MEASUREMENT")
            self.output_on = False

    def reconnect(self) -> None:
        """Reopen the bus and command zero output (the dwell is then re-run)."""
        self.link._reconnect()
        self.exciter.stop()


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
    from setmem_hil.sim_backends.fake_can_device import FakeCanDevice
    from setmem_hil.sim_backends.fake_device_core import FakeDeviceCore
    from setmem_hil.sim_backends.transport_faults import CAN_FAULT_KINDS, split_faults

    core_procedure, transport_faults = split_faults(procedure, CAN_FAULT_KINDS)
    channel = transport_option(procedure, "channel", str, f"setmem-can-{uuid.uuid4().hex[:12]}")
    node = transport_option(procedure, "node", int, 0x21, lo=1, hi=cp.MAX_NODE)
    settings = CanSettings(
        node=node,
        retry=RetryPolicy(
            reply_timeout_s=transport_option(procedure, "reply_timeout_s", float, 0.1, lo=1e-3, hi=60.0),
            max_attempts=transport_option(procedure, "max_attempts", int, 7, lo=1, hi=100),
            backoff_s=transport_option(procedure, "backoff_s", float, 0.01, lo=0.0, hi=10.0),
            backoff_max_s=transport_option(procedure, "backoff_max_s", float, 0.32, lo=0.0, hi=60.0),
        ),
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
        rig = CanRig(link, procedure.safety, on_close=device.stop, name=f"can-virtual:{channel}")
    except BaseException:
        link.close()
        device.stop()
        raise
    rig.fake_device = device
    return rig
