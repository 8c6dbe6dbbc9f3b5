"""A CAN device described by a DBC file as the signal source (cantools + python-can).

The profile (``kind = "dbc"``) names the command message and its signals for the roles
``frequency_hz``, ``amplitude_v`` (peak volts) and ``output``; the status message the device sends
back (every set is read back from it within ``timeout_s``); and the identity message (optionally
requested by sending ``request``), checked before any output, plus optionally the CANopen
identity object 0x1018 of the node (:mod:`.canopen_identity`).

**Dead-man.** While the output is on the command message is sent *cyclically* (python-can's
``send_periodic``, every ``period_s``); a device that switches off when the cyclic command stops
(the usual CAN drive convention) stops by itself if this program dies. Switching off sends the
command with the output signal at 0 (the cyclic frames too), stops the cyclic task, and sends it
once more so no late cyclic frame is the last word.

Resources: ``can://<interface>/<channel>?bitrate=500000``, e.g. ``can://socketcan/can0``,
``can://pcan/PCAN_USBBUS1?bitrate=500000``, ``can://virtual/bench`` (python-can's virtual bus).
"""

from __future__ import annotations

import logging
import math
import time
from urllib.parse import parse_qs

from setmem_hil.drivers.instruments.source import check_instrument_range
from setmem_hil.drivers.instruments.profile import DbcProfile
from setmem_hil.errors import DeviceDisconnectedError, DeviceIdentityError, DeviceRejectedError, DeviceTimeoutError

__all__ = ["DbcGenerator", "parse_can_resource"]

log = logging.getLogger(__name__)


def parse_can_resource(resource: str) -> dict:
    """``can://<interface>/<channel>?bitrate=N`` to python-can bus arguments (ValueError says why)."""
    if not resource.startswith("can://"):
        raise ValueError(f"a CAN resource is can://<interface>/<channel>[?bitrate=N], e.g. can://socketcan/can0, found {resource!r}")
    path, _, query = resource[6:].partition("?")
    interface, sep, channel = path.partition("/")
    if not interface or not sep or not channel:
        raise ValueError(f"expected can://<interface>/<channel>, e.g. can://socketcan/can0, found {resource!r}")
    args = {"interface": interface, "channel": channel}
    for key, values in parse_qs(query).items():
        if key != "bitrate":
            raise ValueError(f"unknown CAN option {key!r} in {resource!r} (bitrate)")
        if not values[-1].isdigit():
            raise ValueError(f"bitrate must be an integer in {resource!r}")
        args["bitrate"] = int(values[-1])
    return args


class DbcGenerator:
    """:class:`~setmem_hil.drivers.instruments.source.SignalSource` over a DBC-described CAN device."""

    def __init__(self, name: str, profile: DbcProfile, resource: str, *, bus=None):
        import can
        import cantools

        self.name, self.profile, self.resource = name, profile, resource
        self.model = profile.model
        self.where = f"{name} ({resource})"
        self.frequency_limits_hz = profile.frequency_limits_hz
        self.amplitude_limits_v = profile.amplitude_limits_v
        self.keepalive_interval_s = math.inf  # the cyclic task is the keepalive
        self.db = cantools.database.load_file(profile.dbc_path)
        self.command = self.db.get_message_by_name(profile.command_message)
        self.status = self.db.get_message_by_name(profile.status_message)
        self.values = {"frequency_hz": 0.0, "amplitude_v": 0.0, "output": 0.0}
        self._task = None
        self._can = can
        self._bus_args = parse_can_resource(resource)
        try:
            self.bus = bus or can.Bus(**self._bus_args)
        except Exception as exc:  # noqa: BLE001 - python-can raises CanError, OSError, ValueError...
            raise DeviceDisconnectedError(f"{self.where}: cannot open the CAN bus ({' '.join(str(exc).split())})") from None

    # -- frames ----------------------------------------------------------------------------------
    def _frame(self):
        data = {sig.name: 0 for sig in self.command.signals}
        for role, sig in self.profile.command_signals.items():
            data[sig] = self.values[role]
        return self._can.Message(arbitration_id=self.command.frame_id, data=self.command.encode(data),
                                 is_extended_id=self.command.is_extended_frame)

    def _send(self) -> None:
        msg = self._frame()
        try:
            if self._task is not None:
                self._task.modify_data(msg)
            self.bus.send(msg)
        except self._can.CanError as exc:
            raise DeviceDisconnectedError(f"{self.where}: sending {self.command.name} failed ({exc})") from None

    def _receive(self, message, timeout_s: float) -> dict:
        end = time.monotonic() + timeout_s
        while (left := end - time.monotonic()) > 0:
            frame = self.bus.recv(timeout=left)
            if frame is not None and frame.arbitration_id == message.frame_id:
                return message.decode(frame.data)
        raise DeviceTimeoutError(f"{self.where}: no {message.name} frame within {timeout_s:g} s")

    def _set(self, role: str, value: float) -> None:
        self.values[role] = float(value)
        self._send()
        self._read_back()

    def _read_back(self) -> None:
        """Wait for a status frame reporting what was set; a device that keeps reporting other
        values is named with the first difference."""
        deadline = time.monotonic() + self.profile.status_timeout_s
        wrong: dict = {}
        while True:
            left = deadline - time.monotonic()
            try:
                status = self._receive(self.status, max(left, 1e-3))
            except DeviceTimeoutError:
                if not wrong:
                    raise
                role, got = next(iter(wrong.items()))
                raise DeviceRejectedError("instrument", f"{self.where}: {role} set to {self.values[role]:.6g}, the device reports {float(got):.6g}") from None
            wrong = {role: status[sig] for role, sig in self.profile.status_signals.items()
                     if not math.isclose(float(status[sig]), self.values[role], rel_tol=1e-3, abs_tol=self._resolution(sig))}
            if not wrong:
                return

    def _resolution(self, signal_name: str) -> float:
        return 0.5 * abs(float(self.status.get_signal_by_name(signal_name).scale)) or 1e-12  # half a step of the signal

    # -- SignalSource ---------------------------------------------------------------------------
    def check_identity(self) -> str:
        p = self.profile
        if p.identity_request:
            req = self.db.get_message_by_name(p.identity_request)
            self.bus.send(self._can.Message(arbitration_id=req.frame_id, data=req.encode({s.name: 0 for s in req.signals}),
                                            is_extended_id=req.is_extended_frame))
        ident = self.db.get_message_by_name(p.identity_message)
        try:
            value = float(self._receive(ident, max(p.status_timeout_s, 1.0))[p.identity_signal])
        except DeviceTimeoutError as exc:
            raise DeviceIdentityError(f"{exc}; is this a {self.model}? nothing was switched on") from None
        if not math.isclose(value, p.identity_expect, rel_tol=1e-9, abs_tol=1e-9):
            raise DeviceIdentityError(f"{self.where}: expected a {self.model} ({p.identity_message}.{p.identity_signal} = "
                                      f"{p.identity_expect:.10g}), it answered {value:.10g}; nothing was switched on")
        answer = f"{self.model} ({p.identity_message}.{p.identity_signal} = {value:.10g})"
        if p.canopen_identity is not None:
            from setmem_hil.drivers.instruments.canopen_identity import check_canopen_identity

            answer += "; " + check_canopen_identity(self._bus_args, p.canopen_identity, self.where)
        return answer

    def initialise(self) -> None:
        self.values.update(output=0.0, amplitude_v=max(0.0, self.amplitude_limits_v[0]))
        self._send()
        self._read_back()

    def keepalive(self) -> None:
        """The cyclic command is the keepalive (see the module docs)."""

    def set_frequency_hz(self, frequency_hz: float) -> None:
        check_instrument_range(self.where, self.model, frequency_hz, self.frequency_limits_hz, "Hz")
        self._set("frequency_hz", frequency_hz)

    def set_amplitude_v(self, peak_v: float) -> None:
        check_instrument_range(self.where, self.model, peak_v, self.amplitude_limits_v, "V")
        self._set("amplitude_v", peak_v)

    def set_output(self, on: bool) -> None:
        if on:
            self.values["output"] = 1.0
            if self._task is None:
                self._task = self.bus.send_periodic(self._frame(), self.profile.period_s)
            self._send()
            self._read_back()
            return
        self.values["output"] = 0.0
        try:
            if self._task is not None:
                self._task.modify_data(self._frame())  # the cyclic frames say "off" too, until stopped
        finally:
            self._stop_task()
        self._send()
        self._read_back()

    def reconnect(self) -> None:
        """A CAN bus has no connection to re-open: the next frames go out on the same bus."""

    def _stop_task(self) -> None:
        if self._task is not None:
            task, self._task = self._task, None
            task.stop()

    def close(self) -> None:
        try:
            if self._task is not None:
                self.values["output"] = 0.0
                self._send()
        except Exception as exc:  # noqa: BLE001 - closing must go on
            log.error("%s: output off on close failed: %r", self.where, exc)
        finally:
            self._stop_task()
            self.bus.shutdown()
