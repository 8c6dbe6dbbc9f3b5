"""Fake shaker + DAQ speaking the CAN wire format on a python-can ``virtual`` channel.

A thread owns one virtual bus and translates frames (``setmem_hil.drivers.can_protocol``) into
calls on a :class:`~setmem_hil.sim_backends.fake_device_core.FakeDeviceCore` (the time-domain
beam with sensor noise on an accelerated clock). Samples are computed on demand: a
``START_ACQUISITION`` command simulates the whole block at once (virtual clock), then the device
streams a block header (start time), then one time-stamp, one force and one response frame
per sample and a closing ``ACQUISITION_COMPLETE`` reply. ``RESEND`` repeats the header and any
range of the last block. ``WAIT`` lets virtual time pass with the excitation on.

Fault injection (issue 8), all seeded:

* frame kinds of the core, drawn per outgoing frame: ``timeout`` (frame dropped),
  ``truncate`` (data cut short), ``corrupt`` (one bit flipped: the CRC-8 catches it),
  ``duplicate`` (sent twice), ``reorder`` (held back and sent after the next frame);
* ``disconnect``, drawn per command received: the device goes silent (ignores and sends
  nothing) for ``disconnect_s`` of wall time, then comes back with its state intact;
* CAN kinds (:data:`~setmem_hil.sim_backends.transport_faults.CAN_FAULT_KINDS`), drawn per
  command: ``error_frame`` (a controller error frame before the reply, harmless) and
  ``bus_off`` (an error frame with the bus-off class; the host must reopen its bus);
* data kinds are applied by the core inside ``capture``.

Watchdog: if the output is on and no frame from the host arrives for ``watchdog_s`` (wall
time), the device zeroes the output (``core.host_lost()``) and latches
``FLAG_WATCHDOG_TRIPPED`` in its heartbeat and status until the next ``ENABLE``.
"""

from __future__ import annotations

import threading
import time

import can

from setmem_hil.drivers import can_protocol as cp
from setmem_hil.errors import FrameError
from setmem_hil.errors import DeviceRejectedError
from setmem_hil.sim_backends.fake_device_core import FakeDeviceCore
from setmem_hil.sim_backends.transport_faults import BackgroundFakeDevice, TransportFaults

FLAG_WATCHDOG_TRIPPED = 0x01


class FakeCanDevice(BackgroundFakeDevice):
    """The fake device on ``can.Bus(interface="virtual", channel=channel)``.

    Parameters
    ----------
    core : FakeDeviceCore
        Device model (owns the simulation and the core fault injector).
    channel : str
        Virtual channel name; use a unique name per device (tests run in parallel).
    node : int
        CAN node id (1..127).
    transport_faults : TransportFaults, optional
        CAN-specific fault kinds.
    heartbeat_period_s, watchdog_s, disconnect_s : float
        Wall-clock periods (heartbeat, host-silence watchdog, length of an injected disconnect).
    """

    def __init__(
        self,
        core: FakeDeviceCore,
        channel: str,
        node: int = 0x21,
        transport_faults: TransportFaults | None = None,
        *,
        heartbeat_period_s: float = 0.05,
        watchdog_s: float = 5.0,
        disconnect_s: float = 0.12,
    ):
        self.core = core
        self.channel = channel
        self.node = node
        self.transport_faults = transport_faults or TransportFaults()
        self.heartbeat_period_s = heartbeat_period_s
        self.watchdog_s = watchdog_s
        self.disconnect_s = disconnect_s
        self.frames_rejected = 0  # malformed frames received from the host
        self.internal_errors: list[str] = []
        self._omega_rad_s = 0.0
        self._amplitude_n = 0.0
        self._enabled = False
        self._flags = 0
        self._hb_counter = 0
        self._last_command: cp.Command | None = None
        self._last_reply: cp.Reply | None = None
        self._acq_id: int | None = None
        self._acq_start_counts = 0
        self._acq_rate_hz = 1.0
        self._held: can.Message | None = None
        self._offline_until = 0.0
        self._last_host_frame = time.monotonic()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._bus: can.BusABC | None = None

    # -- life cycle ----------------------------------------------------------------------------
    def start(self) -> "FakeCanDevice":
        self._bus = can.Bus(interface="virtual", channel=self.channel, receive_own_messages=False)
        self._thread = threading.Thread(target=self._run, name=f"fake-can-{self.channel}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Zero the output, stop the thread and shut the bus down (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self.core.stop()
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None

    # -- main loop -----------------------------------------------------------------------------
    def _run(self) -> None:
        next_heartbeat = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_heartbeat:
                self._heartbeat()
                next_heartbeat = now + self.heartbeat_period_s
            msg = self._bus.recv(timeout=min(self.heartbeat_period_s, 0.02))
            now = time.monotonic()
            if self._enabled and now - self._last_host_frame > self.watchdog_s:
                self.core.host_lost()
                self._enabled = False
                self._flags |= FLAG_WATCHDOG_TRIPPED
            if msg is None or now < self._offline_until:
                continue
            try:
                frame = cp.decode_frame(
                    self.node, msg.arbitration_id, bytes(msg.data), is_error_frame=msg.is_error_frame,
                    is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                )
            except FrameError:
                self.frames_rejected += 1
                continue
            if isinstance(frame, (cp.Command, cp.HostHeartbeat)):
                self._last_host_frame = now
            if isinstance(frame, cp.Command):
                self._handle(frame)

    def _heartbeat(self) -> None:
        state = cp.DeviceState.EXCITING if self._enabled else cp.DeviceState.IDLE
        tick = int(self.core.status().time_s * 1e3) & cp.U32_MAX
        self._hb_counter = (self._hb_counter + 1) & 0xFF
        # no fault draws for heartbeats: they follow the wall clock, and drawing for them would
        # make the seeded fault pattern depend on timing
        self._send(*cp.encode_heartbeat(self.node, cp.Heartbeat(int(state), self._flags, self._hb_counter, tick)), faults=False)

    # -- sending with frame faults ----------------------------------------------------------------
    def _send(self, arbitration_id: int, data: bytes, *, faults: bool = True) -> None:
        if time.monotonic() < self._offline_until or self._bus is None:
            return
        msg = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False)
        f = self.core.faults
        if faults:
            if f.draw("timeout"):
                return
            if f.draw("truncate"):
                msg = can.Message(arbitration_id=arbitration_id, data=data[: int(f.rng.integers(0, 8))], is_extended_id=False)
            if f.draw("corrupt"):
                raw = bytearray(msg.data)
                if raw:
                    raw[int(f.rng.integers(0, len(raw)))] ^= 1 << int(f.rng.integers(0, 8))
                msg = can.Message(arbitration_id=arbitration_id, data=bytes(raw), is_extended_id=False)
            if self._held is None and f.draw("reorder"):
                self._held = msg
                return
        self._bus.send(msg)
        if faults and f.draw("duplicate"):
            self._bus.send(msg)
        if self._held is not None and self._held is not msg:
            held, self._held = self._held, None
            self._bus.send(held)

    def _flush_held(self) -> None:
        if self._held is not None:
            held, self._held = self._held, None
            if self._bus is not None and time.monotonic() >= self._offline_until:
                self._bus.send(held)

    def _reply(self, command: cp.Command, status: cp.ReplyStatus, value: int = 0) -> None:
        reply = cp.Reply(command.opcode, command.seq, status, value & cp.U32_MAX)
        self._last_command, self._last_reply = command, reply
        self._send(*cp.encode_reply(self.node, reply))

    # -- command handling -----------------------------------------------------------------------
    def _handle(self, c: cp.Command) -> None:
        if self.core.faults.draw("disconnect"):
            self._offline_until = time.monotonic() + self.disconnect_s
            self._held = None
            return
        if self.transport_faults.draw("bus_off"):
            self._bus.send(can.Message(arbitration_id=cp.CAN_ERR_BUSOFF, is_error_frame=True, data=bytes(8)))
            return  # the command is lost with the bus
        if self.transport_faults.draw("error_frame"):
            self._bus.send(can.Message(arbitration_id=cp.CAN_ERR_CRTL, is_error_frame=True, data=bytes(8)))
        if c == self._last_command and self._last_reply is not None and c.opcode != cp.Opcode.RESEND:
            # a retried command (same seq and arguments): answer again, do not act twice
            self._send(*cp.encode_reply(self.node, self._last_reply))
            self._flush_held()
            return
        try:
            self._execute(c)
        except DeviceRejectedError:
            self._reply(c, cp.ReplyStatus.OUT_OF_RANGE)
        except (ValueError, ArithmeticError) as exc:  # never let the device thread die
            self.internal_errors.append(repr(exc))
            self._reply(c, cp.ReplyStatus.FAULT)
        self._flush_held()

    def _execute(self, c: cp.Command) -> None:
        op = c.opcode
        if op == cp.Opcode.SET_FREQUENCY:
            self._omega_rad_s = c.arg * cp.OMEGA_LSB_RAD_S
            if self._enabled:
                self.core.set_sine(self._omega_rad_s, self._amplitude_n)
            self._reply(c, cp.ReplyStatus.OK, c.arg)
        elif op == cp.Opcode.SET_AMPLITUDE:
            self._amplitude_n = c.arg * cp.AMPLITUDE_LSB_N
            if self._amplitude_n > self.core.metadata.force_range_n:
                raise DeviceRejectedError("range", "amplitude above the shaker's range")
            if self._enabled:
                self.core.set_sine(self._omega_rad_s, self._amplitude_n)
            self._reply(c, cp.ReplyStatus.OK, c.arg)
        elif op == cp.Opcode.ENABLE:
            if c.arg:
                if self._omega_rad_s <= 0:
                    self._reply(c, cp.ReplyStatus.NOT_READY)
                    return
                self.core.set_sine(self._omega_rad_s, self._amplitude_n)
                self._enabled = True
                self._flags &= ~FLAG_WATCHDOG_TRIPPED
            else:
                self.core.stop()
                self._enabled = False
            self._reply(c, cp.ReplyStatus.OK, c.arg)
        elif op == cp.Opcode.STOP:
            self.core.stop()
            self._enabled = False
            self._reply(c, cp.ReplyStatus.OK)
        elif op == cp.Opcode.SET_SAMPLE_RATE:
            self.core.set_sample_rate(cp.u32_to_float(c.arg))
            self._reply(c, cp.ReplyStatus.OK, c.arg)
        elif op == cp.Opcode.WAIT:
            self.core.wait(c.arg * cp.WAIT_LSB_S)
            self._reply(c, cp.ReplyStatus.OK, c.arg)
        elif op == cp.Opcode.BEGIN_MEASUREMENT:
            self.core.begin_measurement(c.arg, c.aux)
            self._enabled = False
            self._reply(c, cp.ReplyStatus.OK, c.arg)
        elif op == cp.Opcode.GET_INFO:
            self._reply(c, cp.ReplyStatus.OK, self._info(c.arg))
        elif op == cp.Opcode.START_ACQUISITION:
            if self._flags & FLAG_WATCHDOG_TRIPPED:
                self._reply(c, cp.ReplyStatus.FAULT, FLAG_WATCHDOG_TRIPPED)
                return
            if not 1 <= c.arg <= min(cp.MAX_BLOCK_SAMPLES, self.core.max_samples):
                self._reply(c, cp.ReplyStatus.OUT_OF_RANGE)
                return
            self.core.capture(c.arg, request_id=("can", c.aux, c.seq))
            self._acq_id = c.aux
            self._acq_start_counts = cp.block_start_to_counts(float(self.core.read_buffer(0, 1).t_s[0]))
            self._acq_rate_hz = self.core.sample_rate_hz
            self._reply(c, cp.ReplyStatus.OK, self.core.buffer_length)
            self._stream(0, self.core.buffer_length)
        elif op == cp.Opcode.RESEND:
            first, count = c.arg & 0xFFFF, c.arg >> 16
            if self._acq_id != c.aux or first + count > self.core.buffer_length:
                self._reply(c, cp.ReplyStatus.OUT_OF_RANGE)
                return
            self._reply(c, cp.ReplyStatus.OK, count)
            self._stream(first, count)
        else:
            self._reply(c, cp.ReplyStatus.BAD_OPCODE)

    def _info(self, item: int) -> int:
        md = self.core.metadata
        if item == cp.InfoItem.SAMPLE_RATE:
            return cp.float_to_u32(self.core.sample_rate_hz)
        if item == cp.InfoItem.FORCE_RANGE:
            return cp.scale_unsigned(md.force_range_n, cp.RANGE_LSB, "force range")
        if item == cp.InfoItem.RESPONSE_RANGE:
            return cp.scale_unsigned(md.response_range, cp.RANGE_LSB, "response range")
        if item == cp.InfoItem.STATUS:
            state = cp.DeviceState.EXCITING if self._enabled else cp.DeviceState.IDLE
            return int(state) | self._flags << 8
        raise DeviceRejectedError("range", f"unknown info item {item}")

    def _stream(self, first: int, count: int) -> None:
        block = self.core.read_buffer(first, count)
        md = self.core.metadata
        acq = self._acq_id
        self._send(*cp.encode_header(self.node, cp.BlockHeader(acq, self._acq_start_counts)))
        t0 = self._acq_start_counts * cp.BLOCK_START_LSB_S
        for k in range(count):
            index = first + k
            deviation = float(block.t_s[k]) - (t0 + index / self._acq_rate_hz)
            self._send(*cp.encode_sample(self.node, cp.SampleFrame("time", acq, index, cp.time_offset_to_counts(deviation))))
            self._send(*cp.encode_sample(self.node, cp.SampleFrame("force", acq, index, cp.sample_to_counts(block.force[k], md.force_range_n))))
            self._send(
                *cp.encode_sample(self.node, cp.SampleFrame("response", acq, index, cp.sample_to_counts(block.response[k], md.response_range)))
            )
        self._flush_held()
        done = cp.Reply(cp.Opcode.ACQUISITION_COMPLETE, acq, cp.ReplyStatus.OK, count)
        self._send(*cp.encode_reply(self.node, done))
        self._flush_held()
