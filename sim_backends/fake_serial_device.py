"""Fake serial shaker/DAQ: the line protocol of ``drivers/serial_wire_format.md`` on a TCP socket.

The device listens on ``127.0.0.1`` at a free port; the host opens it with pyserial's
``socket://127.0.0.1:<port>`` URL (``serial.serial_for_url``), so the host code is the same as
for a real serial port (a loopback socket makes disconnect and reconnect easy to simulate,
which a pty pair does not). A background thread serves one connection at a time and forwards
each decoded request to a :class:`~setmem_hil.sim_backends.fake_device_core.FakeDeviceCore`.

Duplicate requests (same ``seq`` and bytes as the previous one) are answered from a one-entry
cache without executing them again, so every request is safe to retry.

Frame-level faults (``core.faults``, one draw per kind per frame): ``timeout`` (no answer),
``truncate`` (the answer cut short), ``corrupt`` (one character of the request or of the answer
changed, so the CRC fails; a garbled request is answered ``ERR frame`` and not executed),
``duplicate`` (the answer sent twice), ``reorder`` (a stale copy of the previous answer sent
first), ``disconnect`` (the device drops the connection instead of answering and its watchdog
sets the output to zero; the host may reconnect).

Example
-------
>>> dev = FakeSerialDevice(FakeDeviceCore(seed=1))
>>> dev.url.startswith("socket://127.0.0.1:")
True
>>> dev.close()
"""

from __future__ import annotations

import logging
import socket
import threading

from setmem_hil.drivers import serial_protocol as sp
from setmem_hil.errors import DeviceError, FrameError
from setmem_hil.errors import DeviceRejectedError
from setmem_hil.sim_backends.fake_device_core import FakeDeviceCore
from setmem_hil.sim_backends.transport_faults import injected_counts

log = logging.getLogger(__name__)


class FakeSerialDevice:
    """Serve the serial line protocol for a fake device core on a loopback TCP port.

    Parameters
    ----------
    core : FakeDeviceCore
    port : int
        0 picks a free port.
    """

    def __init__(self, core: FakeDeviceCore, port: int = 0):
        self.core = core
        self._server = socket.create_server(("127.0.0.1", port))
        self._server.settimeout(0.05)
        self.port = self._server.getsockname()[1]
        self.url = f"socket://127.0.0.1:{self.port}"
        self._stop = threading.Event()
        self._conn: socket.socket | None = None
        self._last: tuple[bytes, bytes] | None = None  # (request line, response frame)
        self._previous_response: bytes | None = None
        self.requests_served = 0
        self.malformed_requests = 0
        self.connections = 0
        self._thread = threading.Thread(target=self._serve, name=f"fake-serial-{self.port}", daemon=True)
        self._thread.start()

    # -- server loop -----------------------------------------------------------------------
    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._server.accept()
            except socket.timeout:
                continue
            except OSError:
                break
            self.connections += 1
            self._last = None  # a new connection: no retry can refer to the old one
            self._previous_response = None
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # no Nagle delay per answer
            conn.settimeout(0.05)
            self._conn = conn
            try:
                self._serve_connection(conn)
            finally:
                self._conn = None
                try:
                    conn.close()
                except OSError:
                    pass
                self.core.host_lost()  # watchdog: no host, no output

    def _serve_connection(self, conn: socket.socket) -> None:
        buf = b""
        while not self._stop.is_set():
            try:
                data = conn.recv(65536)
            except socket.timeout:
                continue
            except OSError:
                return
            if not data:
                return
            buf += data
            if len(buf) > sp.MAX_LINE_BYTES and b"\n" not in buf:
                buf = b""  # garbage without terminator: drop it
                self.malformed_requests += 1
                continue
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                if not self._answer(conn, line + b"\n"):
                    return

    def _answer(self, conn: socket.socket, line: bytes) -> bool:
        """Handle one request line; False when the connection is to be dropped."""
        if self.core.faults.draw("corrupt"):
            # the request was garbled on its way in: the device cannot parse it and says so;
            # nothing is executed or cached, so the host's retry (same bytes) goes through
            k = int(self.core.faults.rng.integers(1, max(2, len(line) - 1)))
            garbled = line[:k] + (b"0" if line[k : k + 1] != b"0" else b"1") + line[k + 1 :]
            try:
                sp.decode_request(garbled)
                response = self._execute(line)  # the change happened to be harmless
            except FrameError as exc:
                self.malformed_requests += 1
                response = sp.encode_error(_guess_seq(line), "frame", str(exc))
            self.requests_served += 1
            return self._send_with_faults(conn, response)
        if self._last is not None and self._last[0] == line:
            response = self._last[1]  # a retry: answer from the cache, do not execute again
        else:
            response = self._execute(line)
            self._last = (line, response)
        self.requests_served += 1
        return self._send_with_faults(conn, response)

    def _execute(self, line: bytes) -> bytes:
        try:
            req = sp.decode_request(line)
        except FrameError as exc:
            self.malformed_requests += 1
            seq = _guess_seq(line)
            return sp.encode_error(seq, "frame", str(exc))
        try:
            values = self._dispatch(req)
        except DeviceRejectedError as exc:
            return sp.encode_error(req.seq, exc.code, str(exc))
        except DeviceError as exc:  # pragma: no cover - the core raises DeviceRejectedError only
            return sp.encode_error(req.seq, "device", str(exc))
        return sp.encode_response(req.seq, *values)

    def _dispatch(self, req: sp.Request) -> tuple:
        core, a = self.core, req.args
        cmd = req.command
        if cmd == "IDN?":
            return ("setmem-hil-fake-shaker", "1")
        if cmd == "META?":
            md = core.metadata
            return (md.force_range_n, md.response_range, md.force_unit, md.response_unit, core.max_samples)
        if cmd == "STAT?":
            st = core.status()
            return (st.omega_rad_s, st.amplitude_n, int(st.output_on), st.sample_rate_hz, st.time_s, st.buffer_length)
        if cmd == "SINE":
            core.set_sine(a[0], a[1])
            return ()
        if cmd == "STOP":
            core.stop()
            return ()
        if cmd == "RATE":
            core.set_sample_rate(a[0])
            return ()
        if cmd == "BEGIN":
            core.begin_measurement(a[0], a[1])
            return ()
        if cmd == "WAIT":
            core.wait(a[0])
            return ()
        if cmd == "CAPTURE":
            return (core.capture(a[0]),)
        if cmd == "READ":
            off, cnt = a
            if cnt > sp.MAX_READ_SAMPLES:
                raise DeviceRejectedError("range", f"READ of {cnt} samples exceeds {sp.MAX_READ_SAMPLES}")
            block = core.read_buffer(off, cnt)
            out: list = [off, cnt]
            for t, f, y in zip(block.t_s.tolist(), block.force.tolist(), block.response.tolist()):
                out += [t, f, y]
            return tuple(out)
        raise DeviceRejectedError("command", f"unsupported command {cmd}")  # pragma: no cover

    def _send_with_faults(self, conn: socket.socket, frame: bytes) -> bool:
        faults = self.core.faults
        try:
            if faults.draw("disconnect"):
                return False
            if faults.draw("timeout"):
                return True
            out = frame
            if faults.draw("truncate"):
                cut = int(faults.rng.integers(1, max(2, len(frame) - 1)))
                out = frame[:cut] + (b"\n" if faults.rng.random() < 0.5 else b"")
            elif faults.draw("corrupt"):
                k = int(faults.rng.integers(1, max(2, len(frame) - 6)))
                ch = frame[k : k + 1]
                new = b"0" if ch != b"0" else b"1"
                out = frame[:k] + new + frame[k + 1 :]
            if faults.draw("reorder") and self._previous_response is not None:
                conn.sendall(self._previous_response)
            conn.sendall(out)
            if faults.draw("duplicate"):
                conn.sendall(out)
            self._previous_response = frame
            return True
        except OSError:
            return False

    # -- control ---------------------------------------------------------------------------
    def drop_connection(self) -> None:
        """Close the current host connection (the watchdog zeroes the output)."""
        conn = self._conn
        if conn is not None:
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def close(self) -> None:
        """Stop serving, close the sockets and zero the output (idempotent)."""
        self._stop.set()
        self.drop_connection()
        try:
            self._server.close()
        except OSError:  # pragma: no cover
            pass
        self._thread.join(timeout=2.0)
        self.core.stop()

    def __enter__(self) -> "FakeSerialDevice":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def injected(self) -> dict[str, int]:
        """Faults injected so far, per kind (the serial fake has only the core's kinds)."""
        return injected_counts(self.core.faults)


def _guess_seq(line: bytes) -> int:
    try:
        return int(line[1:3].decode("ascii"), 16) & 0xFF
    except (UnicodeDecodeError, ValueError):
        return 0
