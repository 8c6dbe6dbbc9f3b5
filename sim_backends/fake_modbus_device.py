"""Fake shaker + DAQ behind a real pymodbus server on 127.0.0.1 (the Modbus register map).

The server (``pymodbus.server.ModbusTcpServer``, socket or RTU framing over TCP) runs in its own
thread and event loop. Its datastore is a ``pymodbus.simulator.SimDevice`` whose ``action``
callback (pymodbus 3.16, run on every request before the store is read or written) maps the
register map of ``setmem_hil.drivers.modbus_registers`` onto a
:class:`~setmem_hil.sim_backends.fake_device_core.FakeDeviceCore`:

* writes of the command registers call the core (``set_sine``, ``stop``, ``set_sample_rate``,
  ``wait``, ``begin_measurement``, ``capture``); a command outside the device's own range is
  answered with exception 3 (ILLEGAL DATA VALUE), a write to a read-only register with
  exception 2;
* before every read the status registers are refreshed from the core, and the sample pages the
  read touches are filled *on demand* from the core's buffer (so a page corrupted by fault
  injection is fresh again at the next read).

Fault injection (seeded; ``procedure.backend.faults``), per request:

* ``exception``: answered with exception 6 (SERVER DEVICE BUSY), nothing executed;
* ``timeout``: the request is executed at once but answered ``late_s`` later (beyond the
  client's timeout);
* ``disconnect``: every connection is closed and requests are ignored for ``disconnect_s``;
* ``corrupt``: socket framing: one register of a sample page is flipped (the page CRC
  catches it; TCP's own checksum makes corruption of other replies unrealistic); RTU framing:
  one bit of any reply is flipped (the RTU CRC catches it);
* ``truncate``: the reply is cut short (the client times out and reconnects);
* ``duplicate`` and ``reorder`` (socket framing only: RTU has no transaction id, so on an RTU
  line a duplicated or late reply could not be told from the next one): the reply is sent
  twice, or held back and sent after the next reply; the client discards both by transaction id.

Watchdog: with the output on and no request for ``watchdog_s``, the output is zeroed and
``STATUS_WATCHDOG`` latched until the next ``ENABLE = 1``.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import threading
import time

from pymodbus.constants import ExcCodes
from pymodbus.framer import FramerType
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import SimData, SimDevice
from pymodbus.simulator.simdata import DataType

from setmem_hil.drivers import modbus_registers as mr
from setmem_hil.errors import DeviceRejectedError
from setmem_hil.sim_backends.fake_device_core import FakeDeviceCore
from setmem_hil.sim_backends.transport_faults import BackgroundFakeDevice, TransportFaults

N_REGISTERS = mr.BUFFER_BASE + mr.n_pages(mr.MAX_SAMPLES) * mr.PAGE_REGISTERS
WRITABLE = {
    mr.REG_OMEGA, mr.REG_OMEGA + 1, mr.REG_AMPLITUDE, mr.REG_AMPLITUDE + 1, mr.REG_ENABLE,
    mr.REG_SAMPLE_RATE, mr.REG_SAMPLE_RATE + 1, mr.REG_WAIT, mr.REG_WAIT + 1, mr.REG_WAIT + 2,
    mr.REG_MEASUREMENT, mr.REG_MEASUREMENT + 1, mr.REG_MEASUREMENT + 2, mr.REG_ACQ_LENGTH, mr.REG_ACQ_LENGTH + 1,
}
UNIT = 1


def free_tcp_port() -> int:
    """A currently free TCP port on 127.0.0.1 (asked from the OS)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class FakeModbusDevice(BackgroundFakeDevice):
    """The fake device as a pymodbus server on ``127.0.0.1:port``.

    Parameters
    ----------
    core : FakeDeviceCore
    framer : str
        ``"socket"`` (Modbus TCP) or ``"rtu"`` (RTU framing over the TCP loopback).
    transport_faults : TransportFaults, optional
        Modbus-specific kinds (``exception``).
    late_s, disconnect_s, watchdog_s : float
        Wall-clock delay of a late reply, length of a disconnect, host-silence watchdog.
    """

    def __init__(
        self,
        core: FakeDeviceCore,
        framer: str = "socket",
        transport_faults: TransportFaults | None = None,
        *,
        late_s: float = 0.25,
        disconnect_s: float = 0.15,
        watchdog_s: float = 5.0,
    ):
        if framer not in ("socket", "rtu"):
            raise ValueError(f"framer: expected 'socket' or 'rtu', found {framer!r}")
        self.core = core
        self.framer = framer
        self.transport_faults = transport_faults or TransportFaults()
        self.late_s = late_s
        self.disconnect_s = disconnect_s
        self.watchdog_s = watchdog_s
        self.port = 0
        self.requests = 0  # requests that reached the register map (for tests and reports)
        self.internal_errors: list[str] = []
        self._omega_rad_s = 0.0
        self._amplitude_n = 0.0
        self._enabled = False
        self._watchdog = False
        self._last_wait_id: int | None = None
        self._last_acq_id: int | None = None
        self._acq = {"id": 0, "count": 0, "t0": 0, "rate": 0.0}
        self._offline_until = 0.0
        self._last_request = time.monotonic()
        self._held: bytes | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: ModbusTcpServer | None = None
        self._thread: threading.Thread | None = None

    # -- life cycle -----------------------------------------------------------------------------
    def start(self) -> "FakeModbusDevice":
        """Start the server thread on a free port; returns when it listens."""
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # deprecation notices per request
        ready = threading.Event()
        errors: list[BaseException] = []
        self._loop = asyncio.new_event_loop()

        def run() -> None:
            asyncio.set_event_loop(self._loop)
            try:
                self._loop.run_until_complete(self._serve())
            except BaseException as exc:  # reported to start()
                errors.append(exc)
                ready.set()
                return
            ready.set()
            self._loop.run_forever()

        for _ in range(5):  # the free port may be taken between asking and binding
            self.port = free_tcp_port()
            self._thread = threading.Thread(target=run, name=f"fake-modbus-{self.port}", daemon=True)
            self._thread.start()
            ready.wait(10.0)
            if not errors:
                return self
            self._thread.join(1.0)
            errors.clear()
            ready.clear()
        self._loop.close()
        raise RuntimeError("fake Modbus device: could not listen on 127.0.0.1")

    async def _serve(self) -> None:
        device = SimDevice(
            UNIT, simdata=[SimData(0, count=N_REGISTERS, values=0, datatype=DataType.REGISTERS)], action=self._action
        )
        self._server = ModbusTcpServer(
            device,
            address=("127.0.0.1", self.port),
            framer=FramerType.RTU if self.framer == "rtu" else FramerType.SOCKET,
            trace_packet=self._trace_packet,
        )
        await self._server.serve_forever(background=True)
        self._watchdog_task = asyncio.get_running_loop().create_task(self._watchdog_loop())

    def stop(self) -> None:
        """Zero the output, shut the server down and join its thread (idempotent)."""
        if self._loop is None:
            return
        loop, self._loop = self._loop, None

        async def shutdown() -> None:
            self._watchdog_task.cancel()
            await self._server.shutdown()
            # requests still in flight (a late reply sleeping): cancel them before the loop stops
            pending = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
            for task in pending:
                task.cancel()
            await asyncio.gather(*pending, return_exceptions=True)

        try:
            if loop.is_running():
                asyncio.run_coroutine_threadsafe(shutdown(), loop).result(5.0)
                loop.call_soon_threadsafe(loop.stop)
            if self._thread is not None:
                self._thread.join(5.0)
        finally:
            if not loop.is_running():
                loop.close()
            self.core.stop()

    async def _watchdog_loop(self) -> None:
        while True:
            await asyncio.sleep(0.05)
            if self._enabled and time.monotonic() - self._last_request > self.watchdog_s:
                self.core.host_lost()
                self._enabled = False
                self._watchdog = True

    # -- byte-level faults --------------------------------------------------------------------------
    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if not sending:
            return data
        if time.monotonic() < self._offline_until:
            return b""
        f = self.core.faults
        out = data
        if f.draw("truncate"):
            out = out[: int(f.rng.integers(1, max(2, len(out))))]
        if self.framer == "rtu" and f.draw("corrupt"):
            raw = bytearray(out)
            raw[int(f.rng.integers(0, len(raw)))] ^= 1 << int(f.rng.integers(0, 8))
            out = bytes(raw)
        if self.framer == "socket":
            if f.draw("duplicate"):
                out = out + out
            if self._held is None and f.draw("reorder"):
                self._held = out
                return b""
            if self._held is not None:
                out, self._held = out + self._held, None
        return out

    # -- the register map -----------------------------------------------------------------------------
    async def _action(self, function_code, start_address, address, count, registers, set_values):
        self.requests += 1
        now = time.monotonic()
        if self._enabled and now - self._last_request > self.watchdog_s:  # even if the loop was starved
            self.core.host_lost()
            self._enabled, self._watchdog = False, True
        self._last_request = now
        if time.monotonic() < self._offline_until:
            return ExcCodes.DEVICE_FAILURE  # the reply is dropped while offline
        f = self.core.faults
        if f.draw("disconnect"):
            self._offline_until = time.monotonic() + self.disconnect_s
            self._held = None
            for conn in list(self._server.active_connections.values()):
                conn.close()
            return ExcCodes.DEVICE_FAILURE
        if self.transport_faults.draw("exception"):
            return ExcCodes.DEVICE_BUSY
        late = f.draw("timeout")
        try:
            if set_values is not None:
                result = self._write(address, list(set_values), registers)
            else:
                result = self._read(address, count, registers)
        except (ValueError, ArithmeticError) as exc:  # answer, never drop the connection
            self.internal_errors.append(repr(exc))
            result = ExcCodes.DEVICE_FAILURE
        if late:
            # executed now, answered late: a late *execution* could apply a stale command after
            # a newer one (e.g. ENABLE = 1 after the host's ENABLE = 0)
            await asyncio.sleep(self.late_s)
        return result

    def _write(self, address: int, values: list[int], registers: list[int]) -> ExcCodes | None:
        span = range(address, address + len(values))
        if any(a not in WRITABLE for a in span):
            return ExcCodes.ILLEGAL_ADDRESS
        after = {a: v for a, v in zip(span, values)}

        def reg(a: int) -> int:
            return after.get(a, registers[a])

        def touched(first: int, n: int) -> bool:
            return any(a in after for a in range(first, first + n))

        def whole(first: int, n: int) -> bool:
            return all(a in after for a in range(first, first + n))

        try:
            if touched(mr.REG_OMEGA, 2):
                self._omega_rad_s = mr.registers_to_u32([reg(mr.REG_OMEGA), reg(mr.REG_OMEGA + 1)]) * mr.OMEGA_LSB_RAD_S
            if touched(mr.REG_AMPLITUDE, 2):
                amp = mr.registers_to_u32([reg(mr.REG_AMPLITUDE), reg(mr.REG_AMPLITUDE + 1)]) * mr.AMPLITUDE_LSB_N
                if amp > self.core.metadata.force_range_n:
                    return ExcCodes.ILLEGAL_VALUE
                self._amplitude_n = amp
            if touched(mr.REG_ENABLE, 1):
                if reg(mr.REG_ENABLE) == 1:
                    if self._omega_rad_s <= 0:
                        return ExcCodes.ILLEGAL_VALUE
                    self.core.set_sine(self._omega_rad_s, self._amplitude_n)
                    self._enabled, self._watchdog = True, False
                elif reg(mr.REG_ENABLE) == 0:
                    self.core.stop()
                    self._enabled = False
                else:
                    return ExcCodes.ILLEGAL_VALUE
            elif self._enabled and (touched(mr.REG_OMEGA, 2) or touched(mr.REG_AMPLITUDE, 2)):
                self.core.set_sine(self._omega_rad_s, self._amplitude_n)
            if touched(mr.REG_SAMPLE_RATE, 2):
                self.core.set_sample_rate(mr.registers_to_float32([reg(mr.REG_SAMPLE_RATE), reg(mr.REG_SAMPLE_RATE + 1)]))
            if touched(mr.REG_WAIT, 3):
                if not whole(mr.REG_WAIT, 3):
                    return ExcCodes.ILLEGAL_VALUE
                if reg(mr.REG_WAIT + 2) != self._last_wait_id:
                    self.core.wait(mr.registers_to_u32([reg(mr.REG_WAIT), reg(mr.REG_WAIT + 1)]) * mr.WAIT_LSB_S)
                    self._last_wait_id = reg(mr.REG_WAIT + 2)
            if touched(mr.REG_MEASUREMENT, 3):
                if not whole(mr.REG_MEASUREMENT, 3):
                    return ExcCodes.ILLEGAL_VALUE
                index = mr.registers_to_u32([reg(mr.REG_MEASUREMENT), reg(mr.REG_MEASUREMENT + 1)])
                self.core.begin_measurement(index, reg(mr.REG_MEASUREMENT + 2))
                self._enabled = False
            if touched(mr.REG_ACQ_LENGTH, 2):
                if not whole(mr.REG_ACQ_LENGTH, 2):
                    return ExcCodes.ILLEGAL_VALUE
                if self._watchdog:
                    return ExcCodes.DEVICE_FAILURE
                n, acq_id = reg(mr.REG_ACQ_LENGTH), reg(mr.REG_ACQ_LENGTH + 1)
                if not 1 <= n <= min(mr.MAX_SAMPLES, self.core.max_samples):
                    return ExcCodes.ILLEGAL_VALUE
                if acq_id != self._last_acq_id:
                    self.core.capture(n, request_id=("modbus", acq_id))
                    t0 = float(self.core.read_buffer(0, 1).t_s[0])
                    self._acq = {"id": acq_id, "count": n, "t0": int(round(t0 / mr.T0_LSB_S)), "rate": self.core.sample_rate_hz}
                    self._last_acq_id = acq_id
        except DeviceRejectedError:
            return ExcCodes.ILLEGAL_VALUE
        return None

    def _read(self, address: int, count: int, registers: list[int]) -> None:
        if address < mr.N_CONTROL_REGISTERS:
            self._refresh_control(registers)
        last = address + count
        if last > mr.BUFFER_BASE:
            first_page = max(0, (address - mr.BUFFER_BASE) // mr.PAGE_REGISTERS)
            last_page = (last - 1 - mr.BUFFER_BASE) // mr.PAGE_REGISTERS
            for p in range(first_page, last_page + 1):
                base = mr.page_address(p)
                registers[base : base + mr.PAGE_REGISTERS] = self._page(p)
            if self.framer == "socket" and self.core.faults.draw("corrupt"):
                rng = self.core.faults.rng
                k = int(rng.integers(max(address, mr.BUFFER_BASE), last))
                registers[k] ^= 1 << int(rng.integers(0, 16))
        return None

    def _refresh_control(self, registers: list[int]) -> None:
        md = self.core.metadata
        status = (mr.STATUS_OUTPUT_ON if self._enabled else 0) | (mr.STATUS_WATCHDOG if self._watchdog else 0)
        status |= mr.STATUS_DATA_READY if self._acq["count"] else 0
        values = {
            mr.REG_MAGIC: [mr.MAGIC],
            mr.REG_VERSION: [mr.VERSION],
            mr.REG_ENABLE: [1 if self._enabled else 0],
            mr.REG_STATUS: [status],
            mr.REG_SAMPLE_RATE: mr.float32_to_registers(self.core.sample_rate_hz),
            mr.REG_FORCE_RANGE: mr.u32_to_registers(mr.scale_unsigned(md.force_range_n, mr.RANGE_LSB, "force range")),
            mr.REG_RESPONSE_RANGE: mr.u32_to_registers(mr.scale_unsigned(md.response_range, mr.RANGE_LSB, "response range")),
            mr.REG_ACQ_DONE_ID: [self._acq["id"]],
            mr.REG_ACQ_COUNT: [self._acq["count"]],
            mr.REG_ACQ_T0: mr.u64_to_registers(self._acq["t0"] & (2**64 - 1)),
            mr.REG_ACQ_RATE: mr.float32_to_registers(self._acq["rate"]),
        }
        for a, regs in values.items():
            registers[a : a + len(regs)] = regs

    def _page(self, page: int) -> list[int]:
        n = self._acq["count"] if self._acq["count"] == self.core.buffer_length else 0
        first = page * mr.PAGE_SAMPLES
        k = max(0, min(mr.PAGE_SAMPLES, n - first))
        if k == 0:
            return mr.encode_page(self._acq["id"], page, [], [], [])
        block = self.core.read_buffer(first, k)
        md = self.core.metadata
        t0 = self._acq["t0"] * mr.T0_LSB_S
        rate = self._acq["rate"]
        dev = [mr.deviation_to_counts(float(block.t_s[i]) - (t0 + (first + i) / rate)) for i in range(k)]
        force = [mr.sample_to_counts(v, md.force_range_n) for v in block.force]
        resp = [mr.sample_to_counts(v, md.response_range) for v in block.response]
        return mr.encode_page(self._acq["id"], page, dev, force, resp)
