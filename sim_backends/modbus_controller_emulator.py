"""An emulated Modbus shaker controller: a pymodbus server implementing a profile's register map.

Whatever map the profile describes (identity, ``frequency_hz``, ``amplitude_v``, ``output``,
``watchdog_s``; any table, type, scale and word order), the emulator holds the identity value
and turns writes of the drive registers into the emulated bench's generator (the
:class:`~setmem_hil.sim_backends.instrument_bench.EmulatedBench`). A value outside the
profile's limits is refused with exception 3 (ILLEGAL DATA VALUE); a register outside the map
with exception 2. The watchdog: with the output on, when the watchdog register has not been
rewritten within the seconds it holds (on the bench's clock), the output is switched off.

Simulation only; the driver (:mod:`setmem_hil.drivers.instruments.modbus_generator`) never
imports it.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import threading

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import SimData, SimDevice
from pymodbus.simulator.simdata import DataType

from setmem_hil.drivers.instruments.profile import ModbusProfile, RegisterSpec
from setmem_hil.drivers.instruments.register_codec import decode, encode
from setmem_hil.sim_backends.instrument_bench import EmulatedBench

__all__ = ["ModbusControllerEmulator"]

N_ADDRESSES = 1024
_TABLE_OF_FUNCTION = {1: "coil", 5: "coil", 15: "coil", 2: "discrete", 3: "holding", 6: "holding", 16: "holding", 4: "input"}


class ModbusControllerEmulator:
    """The controller on ``127.0.0.1:port`` (0: a free port) in its own thread and event loop."""

    def __init__(self, bench: EmulatedBench, profile: ModbusProfile, port: int = 0):
        self.bench, self.profile, self.port = bench, profile, port
        self.store = {t: [0] * N_ADDRESSES for t in ("coil", "discrete", "holding", "input")}
        ident = profile.identity
        self._put(ident, ident.expect)
        self.roles = {"frequency_hz": profile.frequency_hz, "amplitude_v": profile.amplitude_v, "output": profile.output}
        if profile.watchdog_s is not None:
            self.roles["watchdog_s"] = profile.watchdog_s
        self.values = {"frequency_hz": 0.0, "amplitude_v": 0.0, "output": 0.0, "watchdog_s": 0.0}
        self.last_keepalive = bench.clock.now()
        self.watchdog_trips = 0
        self.requests = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None

    def _put(self, spec: RegisterSpec, value: float) -> None:
        if spec.table in ("coil", "discrete"):
            self.store[spec.table][spec.address] = int(bool(value))
        else:
            for i, word in enumerate(encode(value, spec)):
                self.store[spec.table][spec.address + i] = word

    def _get(self, spec: RegisterSpec, overlay: dict[int, int] | None = None) -> float:
        table = self.store[spec.table]
        overlay = overlay or {}
        if spec.table in ("coil", "discrete"):
            return float(bool(overlay.get(spec.address, table[spec.address])))
        words = [overlay.get(spec.address + i, table[spec.address + i]) for i in range(spec.n_registers)]
        return decode(words, spec)

    # -- the register map -----------------------------------------------------------------------
    def _check_watchdog(self) -> None:
        limit = self.values["watchdog_s"]
        if self.profile.watchdog_s is not None and self.values["output"] and limit > 0 \
                and self.bench.clock.now() - self.last_keepalive > limit:
            self.watchdog_trips += 1
            self.values["output"] = 0.0
            self._put(self.profile.output, 0.0)
            self.bench.set_generator(output_on=False)

    def apply_write(self, table: str, address: int, values: list[int]) -> ExcCodes | None:
        overlay = {address + i: int(v) for i, v in enumerate(values)}
        touched = {role: spec for role, spec in self.roles.items()
                   if spec.table == table and any(a in overlay for a in range(spec.address, spec.address + max(1, spec.n_registers)))}
        mapped = set()
        for spec in self.roles.values():
            if spec.table == table:
                mapped.update(range(spec.address, spec.address + max(1, spec.n_registers)))
        if not set(overlay) <= mapped:
            return ExcCodes.ILLEGAL_ADDRESS
        new = {role: self._get(spec, overlay) for role, spec in touched.items()}
        limits = {"frequency_hz": self.profile.frequency_limits_hz, "amplitude_v": self.profile.amplitude_limits_v}
        for role, value in new.items():
            lo, hi = limits.get(role, (float("-inf"), float("inf")))
            if not lo <= value <= hi:
                return ExcCodes.ILLEGAL_VALUE
        for role, value in new.items():
            self.values[role] = value
        if "watchdog_s" in new:
            self.last_keepalive = self.bench.clock.now()
        with self.bench.lock:
            self._check_watchdog()
            self.bench.set_generator(frequency_hz=self.values["frequency_hz"] or None,
                                     amplitude_v=self.values["amplitude_v"], output_on=bool(self.values["output"]))
        return None

    async def _action(self, function_code, start_address, address, count, registers, set_values):
        self.requests += 1
        table = _TABLE_OF_FUNCTION.get(function_code)
        if table is None:
            return ExcCodes.ILLEGAL_FUNCTION
        with self.bench.lock:
            self.bench.advance()
            self._check_watchdog()
        if set_values is not None:
            result = self.apply_write(table, address, [int(v) for v in set_values])
            if result is None:
                for i, v in enumerate(set_values):
                    self.store[table][address + i] = int(v)
            return result
        for i in range(count):  # reads serve the emulator's own store
            registers[address + i] = bool(self.store[table][address + i]) if table in ("coil", "discrete") else self.store[table][address + i]
        return None

    # -- life cycle -----------------------------------------------------------------------------
    def start(self) -> "ModbusControllerEmulator":
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
        if self.port == 0:
            with socket.socket() as s:
                s.bind(("127.0.0.1", 0))
                self.port = s.getsockname()[1]
        ready = threading.Event()
        errors: list[BaseException] = []
        self._loop = asyncio.new_event_loop()

        async def serve() -> None:
            bits = lambda: [SimData(0, count=N_ADDRESSES, values=False, datatype=DataType.BITS)]  # noqa: E731
            regs = lambda: [SimData(0, count=N_ADDRESSES, values=0, datatype=DataType.REGISTERS)]  # noqa: E731
            device = SimDevice(self.profile.device_id, simdata=(bits(), bits(), regs(), regs()), action=self._action)
            self._server = ModbusTcpServer(device, address=("127.0.0.1", self.port))
            await self._server.serve_forever(background=True)

        def run() -> None:
            asyncio.set_event_loop(self._loop)
            try:
                self._loop.run_until_complete(serve())
            except BaseException as exc:  # reported to start()
                errors.append(exc)
                ready.set()
                return
            ready.set()
            self._loop.run_forever()

        self._thread = threading.Thread(target=run, name=f"modbus-controller-{self.port}", daemon=True)
        self._thread.start()
        ready.wait(10.0)
        if errors:
            raise RuntimeError(f"emulated Modbus controller: cannot listen on 127.0.0.1:{self.port} ({errors[0]})")
        return self

    def close(self) -> None:
        if self._loop is None:
            return
        loop, self._loop = self._loop, None

        async def shutdown() -> None:
            await self._server.shutdown()

        try:
            if loop.is_running():
                asyncio.run_coroutine_threadsafe(shutdown(), loop).result(5.0)
                loop.call_soon_threadsafe(loop.stop)
            if self._thread is not None:
                self._thread.join(5.0)
        finally:
            if not loop.is_running():
                loop.close()
            self.bench.set_generator(output_on=False)
