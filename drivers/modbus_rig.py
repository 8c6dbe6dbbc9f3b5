"""Modbus front-end: a :class:`~setmem_hil.drivers.protocols.Rig` on the register map of
``drivers/modbus_wire_format.md`` (pymodbus client, Modbus TCP or RTU framing over TCP).

:class:`ModbusLink` wraps pymodbus's synchronous client with the retry policy of
:mod:`setmem_hil.drivers.transport`: every request is safe to repeat (register writes are
absolute; the one-shot commands WAIT and ACQUIRE carry a request id the device executes once),
so a timeout, a dropped connection, a BUSY/ACKNOWLEDGE exception or a reply that fails to
decode (wrong length, page CRC, stale page) is retried with backoff. After a timeout or a
malformed reply the connection is closed and reopened: that discards any late or partial reply
still in the stream (with RTU framing there is no transaction id to recognise it by). Other
exception codes (illegal address/value, device failure) are device errors, not retried.

:class:`ModbusRig` checks the procedure's limits before any write, commands zero on every
abort path and at exit, and implements the optional rig capabilities of
:mod:`setmem_hil.drivers.protocols` (sample rate, wait, measurement index, reconnect).
The loopback rig with the fake device (a pymodbus server on 127.0.0.1 at a free port) is built
by :func:`setmem_hil.loopback.rigs.open_modbus_loopback_rig` (drivers never import simulation code). The samples feed the sine-dwell estimate of one
frequency-response point (thesis eq. 3.7: ``g = g_0 + n``, ``|n| <= R``).

Example
-------
>>> from setmem_hil.io.procedure import default_procedure
>>> from setmem_hil.loopback.rigs import open_modbus_loopback_rig
>>> with open_modbus_loopback_rig(default_procedure(), seed=1) as rig:
...     rig.sensor.set_sample_rate(20.0)
...     rig.exciter.set_sine(5.0, 0.5)
...     block = rig.sensor.acquire(2.0)
>>> block.response.shape
(40,)
"""

from __future__ import annotations

import logging
import time
from typing import Callable, Sequence

import numpy as np
from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.framer import FramerType

from setmem_hil.drivers import modbus_registers as mr
from setmem_hil.drivers.safety import check_sine_command
from setmem_hil.drivers.transport import ChunkedSensor, Closeable, RetryPolicy, RigLifecycle, SafeShutdown, TransportStats, sleep_s
from setmem_hil.drivers.protocols import RigMetadata, SampleBlock
from setmem_hil.errors import DeviceError, DeviceTimeoutError, FrameError


class _Retry(Exception):
    """Internal: this attempt failed in a way that is safe to retry."""


class ModbusLink:
    """Requests with bounded retries over a pymodbus synchronous TCP client.

    Parameters
    ----------
    host, port : str, int
    framer : str
        ``"socket"`` (Modbus TCP) or ``"rtu"`` (RTU framing over TCP).
    unit : int
        Device id.
    retry : RetryPolicy
    """

    def __init__(self, host: str, port: int, framer: str = "socket", unit: int = 1, retry: RetryPolicy = RetryPolicy()):
        if framer not in ("socket", "rtu"):
            raise ValueError(f"framer: expected 'socket' or 'rtu', found {framer!r}")
        self.host, self.port, self.framer, self.unit, self.retry = host, int(port), framer, int(unit), retry
        self.where = f"Modbus {framer} {host}:{port} unit {unit}"
        self.stats = TransportStats()
        self._client: ModbusTcpClient | None = None
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # it logs every skipped late reply
        self._open()

    def _open(self) -> None:
        self._client = ModbusTcpClient(
            self.host, port=self.port, framer=FramerType.RTU if self.framer == "rtu" else FramerType.SOCKET,
            timeout=self.retry.reply_timeout_s, retries=0,
        )
        self._client.connect()  # a failed connect is retried by the first request

    def reconnect(self) -> None:
        self.stats.add("reconnects")
        self.close()
        self._open()

    def close(self) -> None:
        if self._client is not None:
            try:
                self._client.close()
            finally:
                self._client = None

    def _call(self, what: str, attempt_fn: Callable[[ModbusTcpClient], object]):
        t_start = time.monotonic()
        last = ""
        for attempt, delay in enumerate(self.retry.delays()):
            sleep_s(delay)
            if attempt:
                self.stats.add("retries")
            if self._client is None:
                raise DeviceError(f"{self.where}: link is closed")
            try:
                if not self._client.connected and not self._client.connect():
                    raise ConnectionException("connect failed")
                return attempt_fn(self._client)
            except _Retry as exc:
                last = str(exc)
                continue
            except (ModbusIOException, ConnectionException) as exc:
                self.stats.add("timeouts" if isinstance(exc, ModbusIOException) else "connection_errors")
                last = f"{type(exc).__name__}: {exc}"
                self.reconnect()  # discard late or partial replies
            except FrameError as exc:
                self.stats.add("crc_errors" if "CRC" in str(exc) else "malformed_replies")
                last = str(exc)
                self.reconnect()
            except mr.ModbusExceptionError as exc:
                if not exc.retryable:
                    raise
                self.stats.add("busy_exceptions")
                last = str(exc)
            except ModbusException as exc:  # anything else pymodbus raises on a garbled stream
                self.stats.add("malformed_replies")
                last = f"{type(exc).__name__}: {exc}"
                self.reconnect()
        raise DeviceTimeoutError(
            f"{self.where}: {what} failed after {self.retry.max_attempts} attempts "
            f"({time.monotonic() - t_start:.2f} s); last error: {last}"
        )

    def _check(self, response, what: str):
        if response.isError():
            code = getattr(response, "exception_code", None)
            if code is None:
                raise FrameError(f"{self.where}: {what}: unexpected error reply {response!r}")
            raise mr.ModbusExceptionError(response.function_code & 0x7F, int(code), f"{self.where}: {what}")
        return response

    def read(self, address: int, count: int, what: str, decode: Callable[[list[int]], object] | None = None):
        """Read ``count`` holding registers (and decode them; decoding errors are retried)."""

        def attempt(client):
            response = self._check(client.read_holding_registers(address, count=count, device_id=self.unit), what)
            regs = list(response.registers)
            if len(regs) != count:
                raise FrameError(f"{self.where}: {what}: {len(regs)} registers in the reply, {count} requested")
            return decode(regs) if decode is not None else regs

        return self._call(what, attempt)

    def write(self, address: int, values: list[int], what: str) -> None:
        """Write holding registers with function 16 (safe to repeat: see the module docstring)."""

        def attempt(client):
            self._check(client.write_registers(address, list(values), device_id=self.unit), what)

        self._call(what, attempt)


class ModbusExciter:
    def __init__(self, rig: "ModbusRig"):
        self._rig = rig

    def set_sine(self, omega_rad_s: float, amplitude_n: float) -> None:
        rig = self._rig
        check_sine_command(rig.limits, omega_rad_s, amplitude_n, rig.link.where)
        values = (
            mr.u32_to_registers(mr.scale_unsigned(omega_rad_s, mr.OMEGA_LSB_RAD_S, "omega_rad_s"))
            + mr.u32_to_registers(mr.scale_unsigned(amplitude_n, mr.AMPLITUDE_LSB_N, "amplitude_n"))
            + [1]
        )
        with rig.guard.armed():
            rig.link.write(mr.REG_OMEGA, values, "write omega, amplitude, enable")
            rig.output_on = True

    def stop(self) -> None:
        self._rig.link.write(mr.REG_ENABLE, [0], "write enable = 0")
        self._rig.output_on = False


class ModbusSensor(ChunkedSensor):
    """Sensor over a :class:`ModbusLink`: samples read page by page (every page CRC-checked)."""

    @property
    def max_block_samples(self) -> int:
        return self._rig.max_block_samples

    def _send_rate(self, rate_hz: float) -> None:
        self._rig.link.write(mr.REG_SAMPLE_RATE, mr.float32_to_registers(rate_hz), "write sample rate")

    def _send_wait(self, duration_s: float) -> None:
        rig = self._rig
        rig.next_request_id()
        counts = mr.scale_unsigned(duration_s, mr.WAIT_LSB_S, "duration_s")
        rig.link.write(mr.REG_WAIT, mr.u32_to_registers(counts) + [rig.request_id], "write wait")

    def _read_block(self, n: int) -> SampleBlock:
        return self._rig.acquire_block(n)


class ModbusRig(RigLifecycle):
    """A rig on a :class:`ModbusLink` (see the module docstring).

    Parameters
    ----------
    link : ModbusLink
    limits : SafetyLimits
    owned : sequence of closeables, optional
        Closed last by :meth:`close` (e.g. a loopback fake device the rig owns).
    max_block_samples : int
        Samples per capture (longer acquisitions are split; the device clock runs on).
    """

    def __init__(self, link: ModbusLink, limits, owned: Sequence[Closeable] = (), name: str = "modbus",
                 max_block_samples: int = 4000):
        self.link = link
        self.limits = limits
        self.output_on = False
        self.max_block_samples = min(int(max_block_samples), mr.MAX_SAMPLES)
        self.request_id = int(time.monotonic_ns() & 0x7FFF) or 1  # differs from the device's last id after a host restart
        self.owned = tuple(owned)
        self._closed = False
        self._name = name
        self.guard = SafeShutdown(self._stop_output)
        self.exciter = ModbusExciter(self)
        self.sensor = ModbusSensor(self)
        self.metadata = RigMetadata(sample_rate_hz=1.0, force_range_n=1.0, response_range=1.0, name=name)
        with self.guard.armed():
            self.refresh_metadata()
        self.guard.register_exit(self.close)

    def next_request_id(self) -> int:
        self.request_id = self.request_id % 0xFFFF + 1
        return self.request_id

    def _stop_output(self) -> None:
        if self.link._client is not None:
            self.exciter.stop()

    def read_info(self) -> mr.DeviceInfo:
        return self.link.read(0, mr.N_CONTROL_REGISTERS, "read control registers", mr.decode_control_block)

    def refresh_metadata(self) -> None:
        info = self.read_info()
        self.metadata = RigMetadata(
            sample_rate_hz=info.sample_rate_hz, force_range_n=info.force_range_n, response_range=info.response_range,
            name=self._name,
        )

    def acquire_block(self, n: int) -> SampleBlock:
        """Capture ``n`` samples and read them page by page (every page CRC-checked)."""
        if self.output_on:
            info = self.read_info()
            if not info.output_on:
                raise DeviceError(f"{self.link.where}: exciter output dropped by the device (status 0x{info.status:04X}); dwell aborted")
        acq_id = self.next_request_id()
        self.link.write(mr.REG_ACQ_LENGTH, [n, acq_id], f"write capture of {n} samples")
        info = self.read_info()
        if info.acq_done_id != acq_id or info.acq_count != n:
            raise DeviceError(
                f"{self.link.where}: capture {acq_id} of {n} samples not done (device reports id {info.acq_done_id}, {info.acq_count} samples)"
            )
        dev, force, resp = [], [], []
        for p in range(mr.n_pages(n)):
            k = min(mr.PAGE_SAMPLES, n - p * mr.PAGE_SAMPLES)

            def decode(regs, p=p, k=k):
                page = mr.decode_page(regs, acq_id, p)
                if page.dev_counts.size != k:
                    raise FrameError(f"Modbus page {p}: {page.dev_counts.size} samples, {k} expected")
                return page

            page = self.link.read(mr.page_address(p), mr.PAGE_REGISTERS, f"read sample page {p}", decode)
            dev.append(page.dev_counts)
            force.append(page.force_counts)
            resp.append(page.response_counts)
        dev_c = np.concatenate(dev)
        t = info.acq_t0_counts * mr.T0_LSB_S + np.arange(n) / info.acq_rate_hz + dev_c * mr.DEV_LSB_S
        t[dev_c == mr.INVALID_SAMPLE] = np.nan
        md = self.metadata
        return SampleBlock(t, mr.counts_to_samples(np.concatenate(force), md.force_range_n),
                           mr.counts_to_samples(np.concatenate(resp), md.response_range))

    def begin_measurement(self, index: int, attempt: int = 0) -> None:
        """Mark the start of measurement ``index`` (the fake device reseeds its noise; see docs)."""
        with self.guard.armed():
            self.link.write(mr.REG_MEASUREMENT, mr.u32_to_registers(int(index)) + [int(attempt) & 0xFFFF], "write measurement index")
            self.output_on = False

    def reconnect(self) -> None:
        """Reopen the connection and command zero output (the dwell is then re-run)."""
        self.link.reconnect()
        self.exciter.stop()
