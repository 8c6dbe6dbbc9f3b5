"""Host side of the serial front-end: a Rig over the line protocol (pyserial).

:class:`SerialLink` sends a request and waits for the response with the same sequence number:
responses with another ``seq`` (duplicates, stale or reordered frames) are discarded; a
garbled frame (:class:`~setmem_hil.errors.FrameError`) or a missing answer
(:class:`~setmem_hil.errors.DeviceTimeoutError`) is retried with the *same* ``seq`` and bytes
under a bounded :class:`~setmem_hil.drivers.transport.RetryPolicy`; the device answers a repeated
request from its cache without executing it again, so retrying is safe for every command.
A closed connection raises :class:`DeviceDisconnectedError` at once (not retried on the same
link); :meth:`SerialRig.reconnect` opens a new one.

:class:`SerialRig` implements :class:`setmem_hil.drivers.protocols.Rig` plus the optional
capabilities (sample rate per acquisition, wait, measurement index, reconnect). Safety limits
are checked in :class:`setmem_hil.drivers.sine_dwell.SineDwellExperiment` (through
:class:`setmem_hil.drivers.safety.SafeExciter`) before anything reaches this layer; ``close``
commands zero output (best effort) and releases the port.

Example
-------
>>> from setmem_hil.io.procedure import default_procedure
>>> from setmem_hil.loopback.rigs import open_serial_loopback_rig
>>> with open_serial_loopback_rig(default_procedure(), seed=1) as rig:
...     rig.exciter.set_sine(2.0, 0.5)
...     rig.exciter.stop()
"""

from __future__ import annotations

import logging
import time
from typing import Sequence

import numpy as np
import serial

from setmem_hil.drivers import serial_protocol as sp
from setmem_hil.drivers.protocols import RigMetadata, SampleBlock
from setmem_hil.drivers.transport import SERIAL_RETRY, Closeable, RetryPolicy, RigLifecycle, SafeShutdown, TransportStats, call_with_retries
from setmem_hil.errors import DeviceDisconnectedError, DeviceError, DeviceTimeoutError, FrameError

log = logging.getLogger(__name__)


class SerialLink:
    """Request/response over a pyserial port (any URL ``serial.serial_for_url`` accepts).

    Parameters
    ----------
    url : str
        ``socket://127.0.0.1:PORT`` for the fake device, ``/dev/ttyUSB0`` for hardware.
    policy : RetryPolicy
    baudrate : int
        Used by real ports only.

    Attributes
    ----------
    stats : TransportStats
        ``requests``, ``retries``, ``timeouts``, ``frame_errors``, ``stale_discarded``.
    """

    def __init__(self, url: str, policy: RetryPolicy | None = None, baudrate: int = 115200):
        self.url = url
        self.policy = policy or SERIAL_RETRY
        self.baudrate = baudrate
        self.stats = TransportStats()
        self._seq = 0
        self._buf = b""
        self._port = None
        self.open()

    def open(self) -> None:
        """Open (or reopen) the port."""
        self.close()
        try:
            self._port = serial.serial_for_url(self.url, timeout=self.policy.reply_timeout_s, baudrate=self.baudrate)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceDisconnectedError(f"serial link {self.url}: cannot open: {exc}") from exc
        self._buf = b""

    def close(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError):  # pragma: no cover
                pass

    @property
    def is_open(self) -> bool:
        return self._port is not None

    def _readline(self, deadline: float) -> bytes:
        """One line; the deadline is for the first byte and is extended while bytes arrive."""
        port = self._port
        hard_deadline = deadline + 20 * self.policy.reply_timeout_s
        while True:
            nl = self._buf.find(b"\n")
            if nl >= 0:
                line, self._buf = self._buf[: nl + 1], self._buf[nl + 1 :]
                return line
            if len(self._buf) > sp.MAX_LINE_BYTES:
                junk, self._buf = self._buf, b""
                raise sp.MalformedFrameError(f"serial link {self.url}: {len(junk)} bytes without a line terminator")
            now = time.monotonic()
            if now >= deadline or now >= hard_deadline:
                partial, self._buf = self._buf, b""
                if partial:
                    raise sp.TruncatedFrameError(f"serial link {self.url}: frame {partial[:40]!r} cut short (no terminator before the timeout)")
                raise DeviceTimeoutError(f"serial link {self.url}: no answer within {self.policy.reply_timeout_s:g} s")
            try:
                data = port.read(1)  # blocks up to the port timeout for the first byte
                if data:
                    # then drain what has arrived without blocking (in_waiting of pyserial's
                    # socket handler is only 0 or 1, so reading it byte by byte is slow)
                    port.timeout = 0
                    try:
                        data += port.read(65536)
                    finally:
                        port.timeout = self.policy.reply_timeout_s
            except (serial.SerialException, OSError) as exc:
                raise DeviceDisconnectedError(f"serial link {self.url}: connection lost ({exc})") from exc
            if data:
                self._buf += data
                deadline = time.monotonic() + self.policy.reply_timeout_s

    def request(self, command: str, *args) -> sp.Response:
        """Send ``command`` and return its OK response (retried; see the class docstring).

        Raises
        ------
        DeviceRejectedError
            The device answered ERR (not retried, except ``frame``: our request was garbled).
        DeviceTimeoutError, FrameError
            The retries are spent.
        DeviceDisconnectedError
            The connection is closed.
        """
        if self._port is None:
            raise DeviceDisconnectedError(f"serial link {self.url}: not connected")
        self._seq = (self._seq + 1) & 0xFF
        seq = self._seq
        frame = sp.encode_request(seq, command, *args)
        self.stats.add("requests")

        def attempt(k: int) -> sp.Response:
            try:
                self._port.write(frame)
            except (serial.SerialException, OSError) as exc:
                raise DeviceDisconnectedError(f"serial link {self.url}: write failed ({exc})") from exc
            deadline = time.monotonic() + self.policy.reply_timeout_s
            while True:
                line = self._readline(deadline)
                if not line.startswith(b"!"):
                    # the tail of a frame cut short earlier, or line noise: resynchronise
                    self.stats.add("garbage_discarded")
                    continue
                resp = sp.decode_response(line)
                if resp.seq != seq:
                    self.stats.add("stale_discarded")
                    continue
                if not resp.ok and resp.code == "frame":
                    raise sp.MalformedFrameError(f"device could not parse request {seq:02x} {command}: {resp.message}")
                return sp.raise_for_error(resp)

        def on_retry(k: int, exc: BaseException) -> None:
            self.stats.add("retries")
            self.stats.add("timeouts" if isinstance(exc, DeviceTimeoutError) else "frame_errors")
            log.debug("serial %s: retry %d of %s after %r", self.url, k, command, exc)

        try:
            return call_with_retries(attempt, self.policy, (FrameError, DeviceTimeoutError), on_retry)
        except DeviceDisconnectedError:
            self.close()  # the link is dead: later requests fail at once until open()
            raise
        except DeviceTimeoutError as exc:
            self.stats.add("timeouts")
            raise DeviceTimeoutError(f"{exc} (request {command}, {self.policy.max_attempts} attempts)") from exc
        except FrameError as exc:
            self.stats.add("frame_errors")
            raise


class _SerialExciter:
    def __init__(self, rig: "SerialRig"):
        self._rig = rig

    def set_sine(self, omega_rad_s: float, amplitude_n: float) -> None:
        self._rig.link.request("SINE", float(omega_rad_s), float(amplitude_n))

    def stop(self) -> None:
        self._rig.link.request("STOP")


class _SerialSensor:
    def __init__(self, rig: "SerialRig"):
        self._rig = rig

    def set_sample_rate(self, rate_hz: float) -> None:
        self._rig.link.request("RATE", float(rate_hz))
        self._rig.sample_rate_hz = float(rate_hz)

    def wait(self, duration_s: float) -> None:
        self._rig.link.request("WAIT", float(duration_s))

    def acquire(self, duration_s: float) -> SampleBlock:
        rig = self._rig
        n = max(1, int(round(float(duration_s) * rig.sample_rate_hz)))
        if n > rig.max_samples:
            raise DeviceError(f"serial rig: acquisition of {n} samples exceeds the device buffer of {rig.max_samples}")
        got = int(sp.parse_floats(rig.link.request("CAPTURE", n).values, 1, "CAPTURE answer")[0])
        if got != n:
            raise sp.MalformedFrameError(f"CAPTURE answer: {got} samples captured, {n} requested")
        t, f, y = [], [], []
        for off in range(0, n, sp.MAX_READ_SAMPLES):
            cnt = min(sp.MAX_READ_SAMPLES, n - off)
            resp = rig.link.request("READ", off, cnt)
            ti, fi, yi = sp.parse_samples(resp.values, off, cnt, f"READ answer [{off}, {off + cnt})")
            t += ti
            f += fi
            y += yi
        return SampleBlock(np.array(t), np.array(f), np.array(y))


class SerialRig(RigLifecycle):
    """A :class:`~setmem_hil.drivers.protocols.Rig` over the serial line protocol.

    Parameters
    ----------
    url : str
        pyserial URL or device path.
    policy : RetryPolicy, optional
        Default :data:`~setmem_hil.drivers.transport.SERIAL_RETRY`.
    owned : sequence of closeables, optional
        Closed last by :meth:`close` (e.g. a loopback fake device the rig owns).
    """

    def __init__(self, url: str, policy: RetryPolicy | None = None, owned: Sequence[Closeable] = ()):
        self.link = SerialLink(url, policy)
        self.owned = tuple(owned)
        self.exciter = _SerialExciter(self)
        self.sensor = _SerialSensor(self)
        self.reconnects = 0
        self._closed = False
        self.guard = SafeShutdown(self._stop_output)
        self._read_metadata()
        self.guard.register_exit(self.close)

    def _stop_output(self) -> None:
        if self.link.is_open:
            self.link.request("STOP")

    def _read_metadata(self) -> None:
        meta = self.link.request("META?").values
        if len(meta) != 5:
            raise sp.MalformedFrameError(f"META? answer: expected 5 values, found {len(meta)}")
        force_range, response_range = sp.parse_floats(meta[:2], 2, "META? answer")
        self.max_samples = int(sp.parse_floats(meta[4:], 1, "META? answer")[0])
        stat = sp.parse_floats(self.link.request("STAT?").values, 6, "STAT? answer")
        self.sample_rate_hz = stat[3]
        self._meta = RigMetadata(self.sample_rate_hz, force_range, response_range, meta[2], meta[3], f"serial {self.link.url}")

    @property
    def metadata(self) -> RigMetadata:
        m = self._meta
        return RigMetadata(self.sample_rate_hz, m.force_range_n, m.response_range, m.force_unit, m.response_unit, m.name)

    def begin_measurement(self, index: int, attempt: int = 0) -> None:
        self.link.request("BEGIN", int(index), int(attempt))

    def status(self) -> dict:
        v = sp.parse_floats(self.link.request("STAT?").values, 6, "STAT? answer")
        keys = ("omega_rad_s", "amplitude_n", "output_on", "sample_rate_hz", "time_s", "buffer_length")
        return dict(zip(keys, v))

    def reconnect(self) -> None:
        """Reopen the link after a disconnect and command zero output."""
        self.link.open()
        self.reconnects += 1
        self.link.request("STOP")

