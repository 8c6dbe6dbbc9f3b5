"""A Modbus shaker controller or PLC as the signal source, through its register-map profile.

The profile (``kind = "modbus"``) maps the roles ``identity``, ``frequency_hz``, ``amplitude_v``
(peak volts), ``output`` and optionally ``watchdog_s`` to registers
(:mod:`setmem_hil.drivers.instruments.register_codec`). Every write is read back. With a
watchdog register, :meth:`initialise` arms the controller's own dead-man (it switches the output
off when the register is not rewritten within ``watchdog_timeout_s``) and every reading of the
dwell rewrites it (:meth:`keepalive`): if this program dies, the shaker stops by itself.

Resources: ``tcp://HOST:PORT`` (Modbus TCP) or ``rtu://PORT?baudrate=19200&parity=E&stopbits=1``
(RTU over a serial port, e.g. ``rtu:///dev/ttyUSB0?baudrate=19200&parity=E``).
"""

from __future__ import annotations

import logging
import math
from urllib.parse import parse_qs

from setmem_hil.drivers.instruments.source import check_instrument_range
from setmem_hil.drivers.instruments.profile import ModbusProfile, RegisterSpec
from setmem_hil.drivers.instruments.register_codec import decode, encode
from setmem_hil.errors import DeviceDisconnectedError, DeviceIdentityError, DeviceRejectedError, DeviceTimeoutError, SafetyLimitError

__all__ = ["ModbusGenerator", "parse_modbus_resource"]

log = logging.getLogger(__name__)

_PARITIES = {"N", "E", "O"}


def parse_modbus_resource(resource: str) -> dict:
    """``tcp://HOST:PORT`` or ``rtu://PORT?baudrate=..`` to client settings (ValueError says why)."""
    if resource.startswith("tcp://"):
        host, sep, port = resource[6:].rpartition(":")
        if not sep or not host or not port.isdigit() or not 0 <= int(port) < 65536:
            raise ValueError(f"expected tcp://HOST:PORT, found {resource!r}")
        return {"kind": "tcp", "host": host, "port": int(port)}
    if resource.startswith("rtu://"):
        port, _, query = resource[6:].partition("?")
        if not port:
            raise ValueError(f"expected rtu://PORT?baudrate=..., e.g. rtu:///dev/ttyUSB0?baudrate=19200&parity=E, found {resource!r}")
        options = {k: v[-1] for k, v in parse_qs(query, keep_blank_values=True).items()}
        unknown = set(options) - {"baudrate", "parity", "stopbits", "bytesize"}
        if unknown:
            raise ValueError(f"unknown RTU option {sorted(unknown)[0]!r} in {resource!r} (baudrate, parity, stopbits, bytesize)")
        try:
            settings = {"kind": "rtu", "port": port, "baudrate": int(options.get("baudrate", 19200)),
                        "parity": options.get("parity", "E").upper(), "stopbits": int(options.get("stopbits", 1)),
                        "bytesize": int(options.get("bytesize", 8))}
        except ValueError:
            raise ValueError(f"RTU options must be integers (baudrate, stopbits, bytesize) in {resource!r}") from None
        if settings["parity"] not in _PARITIES:
            raise ValueError(f"RTU parity must be N, E or O, found {settings['parity']!r} in {resource!r}")
        return settings
    raise ValueError(f"a Modbus resource is tcp://HOST:PORT or rtu://PORT?baudrate=..., found {resource!r}")


class ModbusGenerator:
    """:class:`~setmem_hil.drivers.instruments.source.SignalSource` over a Modbus register map."""

    def __init__(self, name: str, profile: ModbusProfile, resource: str):
        self.name, self.profile, self.resource = name, profile, resource
        self.model = profile.model
        self.frequency_limits_hz = profile.frequency_limits_hz
        self.amplitude_limits_v = profile.amplitude_limits_v
        self.where = f"{name} ({resource})"
        # the dwell refreshes the watchdog at least three times per timeout
        self.keepalive_interval_s = profile.watchdog_timeout_s / 3.0 if profile.watchdog_s is not None else math.inf
        self._client = self._connect(parse_modbus_resource(resource))

    def _connect(self, settings: dict):
        try:
            from pymodbus.client import ModbusSerialClient, ModbusTcpClient
        except ImportError:  # pragma: no cover - pymodbus is a core dependency
            raise DeviceDisconnectedError(f"{self.where}: pymodbus is not installed") from None
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
        timeout = self.profile.timeout_s
        if settings["kind"] == "tcp":
            client = ModbusTcpClient(settings["host"], port=settings["port"], timeout=timeout, retries=1)
        else:
            client = ModbusSerialClient(settings["port"], baudrate=settings["baudrate"], parity=settings["parity"],
                                        stopbits=settings["stopbits"], bytesize=settings["bytesize"], timeout=timeout, retries=1)
        if not client.connect():
            client.close()
            raise DeviceDisconnectedError(f"{self.where}: cannot connect")
        return client

    def reconnect(self) -> None:
        """A fresh client to the same resource (after the link failed)."""
        try:
            self._client.close()
        except Exception as exc:  # noqa: BLE001 - the old client is being dropped
            log.debug("%s: closing the old client: %r", self.where, exc)
        self._client = self._connect(parse_modbus_resource(self.resource))

    # -- registers ------------------------------------------------------------------------------
    def _reply(self, response, what: str):
        if response is None or response.isError():
            code = getattr(response, "exception_code", None)
            raise DeviceRejectedError("instrument", f"{self.where}: {what}: the device answered Modbus exception {code}")
        return response

    def _call(self, what: str, fn):
        from pymodbus.exceptions import ModbusException

        try:
            return self._reply(fn(), what)
        except ModbusException as exc:
            raise DeviceTimeoutError(f"{self.where}: {what}: no valid reply ({' '.join(str(exc).split())})") from None

    def read(self, spec: RegisterSpec, what: str) -> float:
        c, unit = self._client, self.profile.device_id
        if spec.table in ("coil", "discrete"):
            fn = c.read_coils if spec.table == "coil" else c.read_discrete_inputs
            r = self._call(f"reading {what}", lambda: fn(spec.address, count=1, device_id=unit))
            return 1.0 if r.bits[0] else 0.0
        fn = c.read_holding_registers if spec.table == "holding" else c.read_input_registers
        r = self._call(f"reading {what}", lambda: fn(spec.address, count=spec.n_registers, device_id=unit))
        return decode(list(r.registers)[: spec.n_registers], spec)

    def write(self, spec: RegisterSpec, value: float, what: str) -> None:
        """Write and read back (within float32 / the register's resolution)."""
        c, unit = self._client, self.profile.device_id
        if spec.table == "coil":
            self._call(f"writing {what}", lambda: c.write_coil(spec.address, bool(value), device_id=unit))
        else:
            try:
                words = encode(value, spec)
            except ValueError as exc:
                raise SafetyLimitError(f"{self.where}: {what}: {exc}; nothing was sent") from None
            self._call(f"writing {what}", lambda: c.write_registers(spec.address, words, device_id=unit))
        back = self.read(spec, what)
        resolution = abs(spec.scale) if spec.type != "float32" else 1e-6 * abs(value)
        if not math.isclose(back, value, rel_tol=0, abs_tol=max(resolution, 1e-12)):
            raise DeviceRejectedError("instrument", f"{self.where}: {what} written {value:.7g}, read back {back:.7g}")

    # -- SignalSource ---------------------------------------------------------------------------
    def check_identity(self) -> str:
        spec = self.profile.identity
        value = self.read(spec, "the identity register")
        if not math.isclose(value, spec.expect, rel_tol=1e-9, abs_tol=1e-12):
            raise DeviceIdentityError(f"{self.where}: expected a {self.model} (identity register {spec.table} {spec.address} = {spec.expect:.10g}), "
                                      f"it answered {value:.10g}; nothing was switched on")
        return f"{self.model} (identity register {spec.address} = {value:.10g})"

    def initialise(self) -> None:
        self.set_output(False)
        self.write(self.profile.amplitude_v, max(0.0, self.amplitude_limits_v[0]), "amplitude_v")
        self.keepalive()

    def keepalive(self) -> None:
        if self.profile.watchdog_s is not None:
            self.write(self.profile.watchdog_s, self.profile.watchdog_timeout_s, "watchdog_s")

    def set_frequency_hz(self, frequency_hz: float) -> None:
        check_instrument_range(self.where, self.model, frequency_hz, self.frequency_limits_hz, "Hz")
        self.write(self.profile.frequency_hz, frequency_hz, "frequency_hz")

    def set_amplitude_v(self, peak_v: float) -> None:
        check_instrument_range(self.where, self.model, peak_v, self.amplitude_limits_v, "V")
        self.write(self.profile.amplitude_v, peak_v, "amplitude_v")

    def set_output(self, on: bool) -> None:
        self.write(self.profile.output, 1.0 if on else 0.0, "output")

    def close(self) -> None:
        try:
            self._client.close()
        except Exception as exc:  # noqa: BLE001
            log.debug("closing %s: %r", self.where, exc)
