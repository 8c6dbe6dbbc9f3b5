"""Host side of the CAN wire format (``drivers/can_wire_format.md``) over any python-can bus.

:class:`CanLink` sends commands with a sequence number and waits for the matching reply with
bounded retries and backoff (every command is safe to repeat: arguments are absolute and the
device answers a repeated sequence number without acting twice); discards frames that fail to
decode (CRC, length, opcode: counted, never used), duplicates and stale frames (by acquisition
id and sample index); assembles sample blocks in any arrival order; asks for ``RESEND`` of
missing samples; and reopens the bus after bus-off or a ``can.CanOperationError``.
The rig on top is :mod:`setmem_hil.drivers.can_rig`.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable

import can
import numpy as np

from setmem_hil.drivers import can_protocol as cp
from setmem_hil.drivers.transport import RetryPolicy, TransportStats, sleep_s
from setmem_hil.errors import DeviceDisconnectedError, DeviceError, DeviceTimeoutError, FrameError

HOST_HEARTBEAT_PERIOD_S = 0.5


@dataclasses.dataclass(frozen=True)
class CanSettings:
    """Host-side settings of the CAN link (``procedure.backend.transport`` keys of the same names).

    Parameters
    ----------
    node : int
        Device node id.
    retry : RetryPolicy
        Command retries.
    gap_timeout_s : float
        Silence during a block after which missing samples are requested again.
    max_resend_rounds : int
        Rounds of ``RESEND`` before a block is given up (DeviceError).
    max_block_samples : int
        Samples per ``START_ACQUISITION`` (longer acquisitions are split; the device clock
        runs on, so consecutive blocks are contiguous).
    max_reconnects : int
        Bus reopenings per request before giving up.
    """

    node: int = 0x21
    retry: RetryPolicy = RetryPolicy()
    gap_timeout_s: float = 0.2
    max_resend_rounds: int = 12
    max_block_samples: int = 8192
    max_reconnects: int = 5


class _Assembly:
    """Samples of one block by index and channel; duplicates and other blocks are dropped."""

    CHANNELS = ("time", "force", "response")

    def __init__(self, acq_id: int, n: int):
        self.acq_id = acq_id
        self.n = n
        self.values = {ch: np.zeros(n, dtype=np.int64) for ch in self.CHANNELS}
        self.have = {ch: np.zeros(n, dtype=bool) for ch in self.CHANNELS}
        self.complete_seen = False
        self.start_counts: int | None = None

    def add_header(self, header: cp.BlockHeader, stats: TransportStats) -> None:
        if header.acquisition_id != self.acq_id:
            stats.add("stale_frames_discarded")
        elif self.start_counts is None:
            self.start_counts = header.start_counts
        elif self.start_counts != header.start_counts:
            stats.add("conflicting_headers")

    def add(self, frame: cp.SampleFrame, stats: TransportStats) -> None:
        if frame.acquisition_id != self.acq_id or frame.index >= self.n:
            stats.add("stale_frames_discarded")
            return
        if self.have[frame.channel][frame.index]:
            stats.add("duplicate_frames_discarded")
            return
        self.values[frame.channel][frame.index] = frame.counts
        self.have[frame.channel][frame.index] = True

    def missing(self) -> np.ndarray:
        ok = self.have["time"] & self.have["force"] & self.have["response"]
        return np.flatnonzero(~ok)


def _runs(indices: np.ndarray, merge_gap: int = 16) -> list[tuple[int, int]]:
    """Contiguous ``(first, count)`` runs covering ``indices`` (gaps up to merge_gap merged)."""
    runs: list[tuple[int, int]] = []
    for i in indices.tolist():
        if runs and i - (runs[-1][0] + runs[-1][1]) <= merge_gap:
            first, _ = runs[-1]
            runs[-1] = (first, i - first + 1)
        else:
            runs.append((i, 1))
    return [(f, min(c, 0xFFFF)) for f, c in runs]


class CanLink:
    """Host side of the CAN wire format over any python-can bus.

    Parameters
    ----------
    bus_factory : callable
        Returns a new open bus; called at start and after bus-off.
    settings : CanSettings
    where : str
        Names the link in error messages (channel and node).
    """

    def __init__(self, bus_factory: Callable[[], can.BusABC], settings: CanSettings = CanSettings(), where: str = "CAN"):
        self._bus_factory = bus_factory
        self.settings = settings
        self.where = where
        self.stats = TransportStats()
        self._seq = 0
        self._acq_id = 0
        self._assembly: _Assembly | None = None
        self._bus_downs_in_block = 0
        self.last_heartbeat: cp.Heartbeat | None = None
        self._last_host_heartbeat = time.monotonic()
        self._hb_counter = 0
        self._bus: can.BusABC | None = bus_factory()

    # -- bus ---------------------------------------------------------------------------------------
    def close(self) -> None:
        if self._bus is not None:
            try:
                self._bus.shutdown()
            finally:
                self._bus = None

    def _reconnect(self) -> None:
        self.stats.add("reconnects")
        if self._bus is not None:
            try:
                self._bus.shutdown()
            except Exception:  # a bus that failed may fail to shut down too
                pass
            self._bus = None
        self._bus = self._bus_factory()

    def _reconnect_bounded(self, what: str) -> None:
        self._bus_downs_in_block += 1
        if self._bus_downs_in_block > self.settings.max_reconnects:
            raise DeviceError(f"{self.where}: bus down {self._bus_downs_in_block} times while {what}; giving up")
        self._reconnect()

    def _send(self, arbitration_id: int, data: bytes) -> None:
        if self._bus is None:
            raise DeviceError(f"{self.where}: link is closed")
        try:
            self._bus.send(can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False))
        except can.CanError as exc:
            raise DeviceDisconnectedError(str(exc)) from exc

    def _recv(self, timeout_s: float):
        """One decoded frame or None on timeout; bad frames are counted and skipped.

        Also sends the host heartbeat (``0x77F``) every ``HOST_HEARTBEAT_PERIOD_S`` while the
        host is listening, so the device's watchdog sees a live host during long blocks.
        """
        if self._bus is None:
            raise DeviceError(f"{self.where}: link is closed")
        now = time.monotonic()
        if now - self._last_host_heartbeat > HOST_HEARTBEAT_PERIOD_S:
            self._last_host_heartbeat = now
            self._hb_counter = (self._hb_counter + 1) & 0xFF
            self._send(*cp.encode_host_heartbeat(self._hb_counter))
        try:
            msg = self._bus.recv(timeout=max(timeout_s, 0.0))
        except can.CanError as exc:  # CanOperationError: controller fault, bus-off
            self.stats.add("bus_errors")
            raise DeviceDisconnectedError(str(exc)) from exc
        if msg is None:
            return None
        try:
            frame = cp.decode_frame(
                self.settings.node, msg.arbitration_id, bytes(msg.data), is_error_frame=msg.is_error_frame,
                is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
            )
        except FrameError as exc:
            self.stats.add("crc_errors" if "CRC" in str(exc) else "malformed_frames")
            return False
        if isinstance(frame, cp.ErrorFrame):
            if frame.bus_off:
                self.stats.add("bus_off")
                raise DeviceDisconnectedError("bus-off error frame")
            self.stats.add("error_frames")
            return False
        if isinstance(frame, cp.Heartbeat):
            self.last_heartbeat = frame
            return False
        if isinstance(frame, (cp.SampleFrame, cp.BlockHeader)):
            if self._assembly is None:
                self.stats.add("stale_frames_discarded")
            elif isinstance(frame, cp.BlockHeader):
                self._assembly.add_header(frame, self.stats)
            else:
                self._assembly.add(frame, self.stats)
            return frame
        return frame

    # -- commands ----------------------------------------------------------------------------------
    def request(self, opcode: cp.Opcode, arg: int = 0, aux: int = 0, *, what: str) -> cp.Reply:
        """Send a command and return its OK reply.

        Raises
        ------
        DeviceError
            The device rejected the command (status names why) or the bus could not be reopened.
        DeviceTimeoutError
            No valid reply after every retry.
        """
        self._seq = (self._seq + 1) & 0xFF
        command = cp.Command(opcode, self._seq, arg, aux)
        arb, data = cp.encode_command(self.settings.node, command)
        policy = self.settings.retry
        reconnects = 0
        t_start = time.monotonic()
        for attempt, delay in enumerate(policy.delays()):
            sleep_s(delay)
            if attempt:
                self.stats.add("retries")
            try:
                self._send(arb, data)
                reply = self._wait_reply(command, policy.reply_timeout_s)
            except DeviceDisconnectedError:
                reconnects += 1
                if reconnects > self.settings.max_reconnects:
                    raise DeviceError(f"{self.where}: bus down {reconnects} times during {what}; giving up") from None
                self._reconnect()
                continue
            if reply is None:
                self.stats.add("timeouts")
                continue
            if reply.status == cp.ReplyStatus.BUSY:
                self.stats.add("busy_replies")
                continue
            if reply.status != cp.ReplyStatus.OK:
                raise DeviceError(
                    f"{self.where}: device rejected {what} (opcode 0x{int(opcode):02X}, arg {arg}) with status "
                    f"{cp.ReplyStatus(reply.status).name} (value {reply.value})"
                )
            return reply
        raise DeviceTimeoutError(
            f"{self.where}: no valid reply to {what} after {policy.max_attempts} attempts "
            f"({time.monotonic() - t_start:.2f} s, reply timeout {policy.reply_timeout_s:g} s)"
        )

    def _wait_reply(self, command: cp.Command, timeout_s: float) -> cp.Reply | None:
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            frame = self._recv(left)
            if frame is None:
                return None
            if isinstance(frame, cp.Reply):
                if frame.opcode == cp.Opcode.ACQUISITION_COMPLETE:
                    self._note_complete(frame)
                elif frame.opcode == command.opcode and frame.seq == command.seq:
                    return frame
                else:
                    self.stats.add("stale_replies_discarded")

    def _note_complete(self, frame: cp.Reply) -> None:
        if self._assembly is not None and frame.seq == self._assembly.acq_id:
            self._assembly.complete_seen = True
        else:
            self.stats.add("stale_replies_discarded")

    def _collect(self) -> None:
        """Read frames until the block's ACQUISITION_COMPLETE or ``gap_timeout_s`` of silence."""
        asm = self._assembly
        gap = self.settings.gap_timeout_s
        last_progress = time.monotonic()
        while not asm.complete_seen:
            left = last_progress + gap - time.monotonic()
            try:
                frame = self._recv(left) if left > 0 else None
            except DeviceDisconnectedError:
                self._reconnect_bounded("collecting samples")
                return  # what is missing is requested again
            if frame is None:  # silence (heartbeats do not count as progress)
                self.stats.add("gap_timeouts")
                return
            if isinstance(frame, (cp.SampleFrame, cp.BlockHeader)):
                last_progress = time.monotonic()
            elif isinstance(frame, cp.Reply):
                if frame.opcode == cp.Opcode.ACQUISITION_COMPLETE:
                    self._note_complete(frame)
                else:
                    self.stats.add("stale_replies_discarded")

    # -- acquisition -------------------------------------------------------------------------------
    def acquire_block(self, n_samples: int) -> tuple[float, dict[str, np.ndarray]]:
        """Acquire one block; return ``(start_s, counts per channel)`` with every sample verified.

        Raises
        ------
        DeviceError
            Samples (or the header) still missing after ``max_resend_rounds``.
        """
        self._acq_id = (self._acq_id + 1) & 0xFF
        self._assembly = asm = _Assembly(self._acq_id, n_samples)
        self._bus_downs_in_block = 0
        try:
            reply = self._request_collect(
                cp.Opcode.START_ACQUISITION, n_samples, asm.acq_id, what=f"START_ACQUISITION of {n_samples} samples"
            )
            if reply.value != n_samples:
                raise DeviceError(f"{self.where}: device captured {reply.value} samples, {n_samples} requested")
            for _ in range(self.settings.max_resend_rounds):
                missing = asm.missing()
                if missing.size == 0 and asm.start_counts is not None:
                    break
                self.stats.add("resend_rounds")
                self.stats.add("samples_requested_again", int(missing.size))
                for first, count in _runs(missing) or [(0, 0)]:
                    self._request_collect(
                        cp.Opcode.RESEND, first | count << 16, asm.acq_id, what=f"RESEND of {count} samples from {first}"
                    )
            missing = asm.missing()
            if missing.size or asm.start_counts is None:
                raise DeviceError(
                    f"{self.where}: {missing.size} of {n_samples} samples (header {'missing' if asm.start_counts is None else 'ok'}) "
                    f"of block {asm.acq_id} still missing after {self.settings.max_resend_rounds} resend rounds"
                )
            return asm.start_counts * cp.BLOCK_START_LSB_S, asm.values
        finally:
            self._assembly = None

    def _request_collect(self, opcode, arg, aux, *, what: str) -> cp.Reply:
        self._assembly.complete_seen = False
        reply = self.request(opcode, arg, aux, what=what)
        self._collect()
        return reply
