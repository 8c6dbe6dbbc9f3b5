"""A PyVISA session to one instrument, with one-line errors naming the instrument and resource.

The resource string is anything PyVISA opens (``TCPIP::192.168.1.20::INSTR``,
``TCPIP::10.0.0.5::5025::SOCKET``, ``USB0::0x0957::0x2C07::MY57800001::INSTR``,
``ASRL/dev/ttyUSB0::INSTR``); the VISA library defaults to ``"@py"`` (pyvisa-py, pure Python:
nothing to install from the vendor). Tests pass ``"<file>.yaml@sim"`` (pyvisa-sim).

PyVISA is an optional extra (``pip install 'setmem-hil[instruments]'``); without it, opening a
link raises a :class:`~setmem_hil.errors.DeviceError` that says so.
"""

from __future__ import annotations

import contextlib
import logging
import select
import socket
import time

from setmem_hil.errors import DeviceDisconnectedError, DeviceError, DeviceRejectedError, DeviceTimeoutError

__all__ = ["VisaLink"]

log = logging.getLogger(__name__)


class VisaLink:
    """``write`` / ``query`` to one instrument; every failure is a DeviceError naming it."""

    def __init__(self, name: str, resource: str, *, visa_library: str = "@py", termination: str = "\n", timeout_s: float = 2.0):
        self.name, self.resource, self.timeout_s = name, resource, timeout_s
        self.visa_library, self.termination = visa_library, termination
        self.transcript: list[str] = []  # commands sent (for the run log and tests)
        try:
            import pyvisa
        except ImportError:  # pragma: no cover - the [instruments] extra is in [test]
            raise DeviceError(f"{name}: PyVISA is not installed; install it with pip install 'setmem-hil[instruments]'") from None
        self._pyvisa = pyvisa
        self.answered = False  # has this session ever exchanged a message? (a lost link vs. never reached)
        self._sock: socket.socket | None = None  # pyvisa-py's TCP socket of the open session, if any
        self._reply_owed = False  # a query timed out: its reply may still arrive, and must never answer another
        self.stale_replies = 0  # replies dropped as stale (logged; tests read it)
        self._open()

    def _open(self) -> None:
        try:
            self._rm = self._pyvisa.ResourceManager(self.visa_library)
            self._inst = self._rm.open_resource(self.resource, read_termination=self.termination, write_termination=self.termination,
                                                timeout=int(self.timeout_s * 1000))
        except Exception as exc:  # noqa: BLE001 - pyvisa raises VisaIOError, ValueError, OSError, LibraryError...
            raise DeviceDisconnectedError(f"{self.name}: cannot open {self.resource!r} ({_reason(exc)})") from None
        self._sock = self._socket()  # the session keeps its socket until closed: looked up once
        self._no_delay()

    def _no_delay(self) -> None:
        """Short commands go out at once (Nagle would hold a write behind the last one's ACK):
        the VISA attribute ``VI_ATTR_TCPIP_NODELAY`` first (a vendor VISA honours it; pyvisa-py
        0.8.1 only on raw SOCKET sessions, not on its VXI-11 or HiSLIP INSTR sessions); where it is
        not honoured (refused, or read back off) and we reach the session's socket, the socket
        option itself."""
        constants = self._pyvisa.constants
        try:
            self._inst.set_visa_attribute(constants.VI_ATTR_TCPIP_NODELAY, constants.VI_TRUE)
            if self._inst.get_visa_attribute(constants.VI_ATTR_TCPIP_NODELAY) == constants.VI_TRUE:
                return
        except Exception:  # noqa: BLE001 - not a TCP/IP session, or the library does not support the attribute
            pass
        if self._sock is not None:
            try:
                self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            except OSError:
                pass

    def reopen(self) -> None:
        """Drop this session and open a fresh one to the same resource (after a dropped link)."""
        self.close()
        self.answered = False
        self._reply_owed = False  # a late reply goes to the closed session
        self._open()

    def write(self, command: str) -> None:
        self.transcript.append(command)
        self._refuse_if_closed(command)
        try:
            self._inst.write(command)
        except Exception as exc:  # noqa: BLE001
            raise self._error(command, exc) from None
        self.answered = True

    def query(self, command: str, timeout_s: float | None = None) -> str:
        """Send ``command`` and read its one-line reply within ``timeout_s`` (the link's own by
        default). A reply never answers another query: bytes waiting before the query are
        dropped as stale, and after a query timed out the session is opened afresh first (the
        late reply, still on its way, goes to the old one)."""
        self.transcript.append(command)
        self._refuse_if_closed(command)
        self._drop_stale(command)
        wait_s = self.timeout_s if timeout_s is None else float(timeout_s)
        try:
            with self._timeout(wait_s):
                if self._sock is None:
                    reply = str(self._inst.query(command)).strip()
                else:
                    self._inst.write(command)
                    self._await_reply(self._sock, command, wait_s)
                    reply = str(self._inst.read()).strip()
        except DeviceTimeoutError:
            self._reply_owed = True
            raise
        except DeviceError:
            raise
        except Exception as exc:  # noqa: BLE001
            error = self._error(command, exc, wait_s)
            self._reply_owed = isinstance(error, DeviceTimeoutError)
            raise error from None
        self.answered = True
        return reply

    @contextlib.contextmanager
    def _timeout(self, seconds: float):
        """The session's timeout set to ``seconds`` for one exchange (pyvisa counts milliseconds)."""
        if seconds == self.timeout_s:
            yield
            return
        old = self._inst.timeout
        self._inst.timeout = int(seconds * 1000)
        try:
            yield
        finally:
            self._inst.timeout = old

    def _drop_stale(self, command: str) -> None:
        """Before a query: a session owing a timed-out query's reply is opened afresh (that
        reply, late, must not answer this query), and bytes already waiting are dropped."""
        if self._reply_owed:
            log.warning("%s: a reply was owed to a query that timed out; opening a fresh session before %r", self.name, command)
            self.stale_replies += 1
            self.reopen()
            return
        if not self.answered:  # nothing can be stale before the first exchange (and pyvisa-py connects on first use)
            return
        stale = self._take_waiting_bytes()
        if stale:
            self.stale_replies += 1
            log.warning("%s: dropped %d stale bytes before %r (%r)", self.name, len(stale), command, stale[:40])

    def _take_waiting_bytes(self) -> bytes:
        """What pyvisa-py holds or the socket has ready now (without waiting)."""
        taken = b""
        try:
            buffer = self._inst.visalib.sessions[self._inst.session]._pending_buffer
            taken, buffer[:] = bytes(buffer), b""
        except Exception:  # noqa: BLE001 - another backend, or a session without a buffer
            pass
        while self._sock is not None and _readable_now(self._sock):
            try:
                chunk = self._sock.recv(65536)
            except OSError:  # would block after all, or the link failed: the query reports the latter
                break
            if not chunk:  # the peer closed: reported by the query itself
                break
            taken += chunk
        return taken

    def write_binary(self, command: str, values, datatype: str, *, big_endian: bool, header: str = "ieee") -> None:
        """``command`` followed by ``values`` packed as ``datatype`` (``"H"``, ``"h"``, ...) in one
        message: after an IEEE 488.2 definite-length block header (``header = "ieee"``) or none
        (``"empty"``: the bytes alone, for instruments that take a length in the command text)."""
        self.transcript.append(f"{command}<{len(values)} x {datatype}>")
        self._refuse_if_closed(command)
        try:
            self._inst.write_binary_values(command, values, datatype=datatype, is_big_endian=big_endian, header_fmt=header)
        except Exception as exc:  # noqa: BLE001
            raise self._error(command, exc) from None
        self.answered = True

    def query_block(self, command: str, datatype: str = "B", big_endian: bool = True):
        """An IEEE 488.2 definite-length block (``#<n><length><data>``) as a numpy array of
        ``datatype`` (``"B"`` bytes, ``"H"`` 16-bit words); a reply that is not such a block is a
        :class:`~setmem_hil.errors.DeviceRejectedError` naming the instrument and the query."""
        import numpy as np

        self.transcript.append(command)
        self._refuse_if_closed(command)
        self._drop_stale(command)  # a block query is a query too: no late reply may answer it
        try:
            values = self._inst.query_binary_values(command, datatype=datatype, is_big_endian=big_endian, header_fmt="ieee",
                                                    container=np.array, expect_termination=True)
        except DeviceError:
            raise
        except (ValueError, TypeError) as exc:  # pyvisa: "Could not find start of IEEE block", a length that does not match...
            self._drain()
            raise DeviceRejectedError("garbled", f"{self.name} ({self.resource}): {command!r} did not answer an IEEE 488.2 "
                                                 f"definite-length block ({_reason(exc)})") from None
        except Exception as exc:  # noqa: BLE001
            error = self._error(command, exc)
            self._reply_owed = isinstance(error, DeviceTimeoutError)
            raise error from None
        self.answered = True
        return values

    def _drain(self) -> None:
        """Read and drop whatever is left of a malformed reply (the next query must not see it)."""
        try:
            self._inst.clear()
        except Exception:  # noqa: BLE001 - a raw socket may not support clear: read until silence instead
            old = self._inst.timeout
            try:
                self._inst.timeout = 200
                while True:
                    self._inst.read_raw()
            except Exception:  # noqa: BLE001
                pass
            finally:
                self._inst.timeout = old

    def _socket(self) -> socket.socket | None:
        """The TCP socket under a pyvisa-py session (raw SOCKET resources), else None."""
        try:
            sock = self._inst.visalib.sessions[self._inst.session].interface
        except Exception:  # noqa: BLE001 - another backend, or a session without a socket
            return None
        return sock if isinstance(sock, socket.socket) else None

    def peer_closed(self) -> bool:
        """Has the instrument closed the connection? pyvisa-py reads an orderly close as silence
        and reports a timeout after ``timeout_s``; a peek at a socket ``select`` finds readable
        tells at once. (Not ``MSG_DONTWAIT``: Windows has no such flag.)"""
        if self._sock is None:
            return False
        try:
            return _readable_now(self._sock) and self._sock.recv(1, socket.MSG_PEEK) == b""
        except (ConnectionResetError, ConnectionAbortedError, BrokenPipeError):
            return True
        except (OSError, ValueError):  # would block, not connected yet, refused, already closed: not a close
            return False

    def _await_reply(self, sock: socket.socket, command: str, timeout_s: float) -> None:
        """Wait for the reply to start arriving; an instrument that closes the connection
        instead is reported at once (pyvisa-py would wait out its timeout first)."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            readable, _, _ = select.select([sock], [], [], min(left, 0.5))
            if readable:
                if self.peer_closed():
                    raise self._closed(command)
                return
        raise DeviceTimeoutError(f"{self.name} ({self.resource}): no reply to {command!r} within {timeout_s:g} s")

    def _refuse_if_closed(self, command: str) -> None:
        if self.answered and self.peer_closed():
            raise self._closed(command)

    def _closed(self, command: str) -> DeviceDisconnectedError:
        return DeviceDisconnectedError(f"{self.name} ({self.resource}): the instrument closed the connection "
                                       f"({command!r} was not delivered)")

    def _error(self, command: str, exc: Exception, timeout_s: float | None = None) -> DeviceError:
        errors = self._pyvisa.errors
        if isinstance(exc, errors.VisaIOError) and exc.error_code == self._pyvisa.constants.StatusCode.error_timeout:
            if self.peer_closed():
                return self._closed(command)
            waited = self.timeout_s if timeout_s is None else timeout_s
            return DeviceTimeoutError(f"{self.name} ({self.resource}): no reply to {command!r} within {waited:g} s")
        if self.answered and isinstance(exc, (ConnectionResetError, BrokenPipeError, ConnectionAbortedError)):
            return DeviceDisconnectedError(f"{self.name} ({self.resource}): the connection was lost ({_reason(exc)}); "
                                           f"{command!r} may not have been delivered")
        if isinstance(exc, OSError):  # pyvisa-py connects on first use: refused, unreachable
            return DeviceDisconnectedError(f"{self.name}: cannot reach {self.resource!r} ({_reason(exc)}); is the instrument on and "
                                           f"the resource string right? ({command!r} was not delivered)")
        return DeviceDisconnectedError(f"{self.name} ({self.resource}): {command!r} failed ({_reason(exc)})")

    def close(self) -> None:
        """Close this instrument's session only. PyVISA shares one ResourceManager per VISA
        library between every link of the process: closing it closed the other instruments'
        sessions too (issue 46: the scope's fresh session after a timed-out query left the
        generator's link dead, and every retry failed on it)."""
        self._sock = None
        inst = getattr(self, "_inst", None)
        try:
            if inst is not None:
                inst.close()
        except Exception as exc:  # noqa: BLE001 - closing must not mask anything
            log.debug("closing %s: %r", self.name, exc)


def _readable_now(sock: socket.socket) -> bool:
    """Has ``sock`` bytes (or a close) to read right now? ``select`` with no wait: portable."""
    try:
        return bool(select.select([sock], [], [], 0)[0])
    except (OSError, ValueError):  # closed under us
        return False


def _reason(exc: Exception) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) < 200 else text[:197] + "..."
