"""CAN front-end: a :class:`~setmem_hil.drivers.protocols.Rig` speaking ``can_wire_format.md``.

The link (commands, retries, sample assembly, resend, bus-off recovery) is
:class:`setmem_hil.drivers.can_link.CanLink`. :class:`CanRig` adds the exciter (limits checked
before sending, via :func:`~setmem_hil.drivers.safety.check_sine_command`) and the
sensor, commands zero on every abort path and at exit, and implements the optional rig
capabilities of :mod:`setmem_hil.drivers.protocols` (sample rate, wait, measurement index,
reconnect). The loopback rig on a python-can ``virtual`` channel with the fake device is built
by :func:`setmem_hil.loopback.rigs.open_can_virtual_rig` (drivers never import simulation code).

The measured samples feed the sine-dwell estimate of one frequency-response point (thesis
eq. 3.7: ``g = g_0 + n``, ``|n| <= R``); nothing here depends on the identification.

Example
-------
>>> from setmem_hil.io.procedure import default_procedure
>>> from setmem_hil.loopback.rigs import open_can_virtual_rig
>>> with open_can_virtual_rig(default_procedure(), seed=1) as rig:
...     rig.sensor.set_sample_rate(20.0)
...     rig.exciter.set_sine(5.0, 0.5)
...     block = rig.sensor.acquire(2.0)
...     rig.exciter.stop()
>>> block.force.shape
(40,)
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from setmem_hil.drivers import can_protocol as cp
from setmem_hil.drivers.can_link import CanLink, CanSettings
from setmem_hil.drivers.safety import check_sine_command
from setmem_hil.drivers.transport import ChunkedSensor, Closeable, RigLifecycle, SafeShutdown
from setmem_hil.drivers.protocols import RigMetadata, SampleBlock
from setmem_hil.errors import DeviceError

__all__ = ["CanExciter", "CanLink", "CanRig", "CanSensor", "CanSettings"]


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


class CanSensor(ChunkedSensor):
    """Sensor over a :class:`CanLink`: timestamps, force and response of every sample."""

    @property
    def max_block_samples(self) -> int:
        return self._rig.link.settings.max_block_samples

    def _send_rate(self, rate_hz: float) -> None:
        self._rig.link.request(cp.Opcode.SET_SAMPLE_RATE, cp.float_to_u32(rate_hz), what="SET_SAMPLE_RATE")

    def _send_wait(self, duration_s: float) -> None:
        self._rig.link.request(cp.Opcode.WAIT, cp.scale_unsigned(duration_s, cp.WAIT_LSB_S, "duration_s"), what="WAIT")

    def _before_acquire(self) -> None:
        self._rig.check_output()

    def _read_block(self, n: int) -> SampleBlock:
        md = self._rig.metadata
        start_s, counts = self._rig.link.acquire_block(n)
        t = start_s + np.arange(n) / md.sample_rate_hz + counts["time"] * cp.TIME_OFFSET_LSB_S
        t[counts["time"] == cp.INVALID_SAMPLE] = np.nan
        return SampleBlock(t, _to_units(counts["force"], md.force_range_n), _to_units(counts["response"], md.response_range))


def _to_units(counts: np.ndarray, full_range: float) -> np.ndarray:
    values = counts.astype(float) * (full_range / cp.SAMPLE_FULL_SCALE)
    values[counts == cp.INVALID_SAMPLE] = np.nan
    return values


class CanRig(RigLifecycle):
    """A rig on a CAN link (see the module docstring).

    Parameters
    ----------
    link : CanLink
    limits : SafetyLimits
        The procedure's limits, checked before any command is sent.
    owned : sequence of closeables, optional
        Closed last by :meth:`close` (e.g. a loopback fake device the rig owns).
    """

    def __init__(self, link: CanLink, limits, owned: Sequence[Closeable] = (), name: str = "can"):
        self.link = link
        self.limits = limits
        self.output_on = False
        self.owned = tuple(owned)
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
