"""A PyVISA session to one instrument, with one-line errors naming the instrument and resource.

The resource string is anything PyVISA opens (``TCPIP::192.168.1.20::INSTR``,
``TCPIP::10.0.0.5::5025::SOCKET``, ``USB0::0x0957::0x2C07::MY57800001::INSTR``,
``ASRL/dev/ttyUSB0::INSTR``); the VISA library defaults to ``"@py"`` (pyvisa-py, pure Python:
nothing to install from the vendor). Tests pass ``"<file>.yaml@sim"`` (pyvisa-sim).

PyVISA is an optional extra (``pip install 'setmem-hil[instruments]'``); without it, opening a
link raises a :class:`~setmem_hil.errors.DeviceError` that says so.
"""

from __future__ import annotations

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
        self._open()

    def _open(self) -> None:
        try:
            self._rm = self._pyvisa.ResourceManager(self.visa_library)
            self._inst = self._rm.open_resource(self.resource, read_termination=self.termination, write_termination=self.termination,
                                                timeout=int(self.timeout_s * 1000))
        except Exception as exc:  # noqa: BLE001 - pyvisa raises VisaIOError, ValueError, OSError, LibraryError...
            raise DeviceDisconnectedError(f"{self.name}: cannot open {self.resource!r} ({_reason(exc)})") from None
        self._sock = self._socket()  # the session keeps its socket until closed: looked up once
        if self._sock is not None:  # short commands go out at once (Nagle would hold a write behind the last one's ACK)
            try:
                self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            except OSError:
                pass

    def reopen(self) -> None:
        """Drop this session and open a fresh one to the same resource (after a dropped link)."""
        self.close()
        self.answered = False
        self._open()

    def write(self, command: str) -> None:
        self.transcript.append(command)
        self._refuse_if_closed(command)
        try:
            self._inst.write(command)
        except Exception as exc:  # noqa: BLE001
            raise self._error(command, exc) from None
        self.answered = True

    def query(self, command: str) -> str:
        self.transcript.append(command)
        self._refuse_if_closed(command)
        try:
            if self._sock is None or self._pending():
                reply = str(self._inst.query(command)).strip()
            else:
                self._inst.write(command)
                self._await_reply(self._sock, command)
                reply = str(self._inst.read()).strip()
        except DeviceError:
            raise
        except Exception as exc:  # noqa: BLE001
            raise self._error(command, exc) from None
        self.answered = True
        return reply

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
            raise self._error(command, exc) from None
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

    def _pending(self) -> bool:
        """Bytes pyvisa-py already holds (a reply longer than one line): no need to wait."""
        try:
            return bool(self._inst.visalib.sessions[self._inst.session]._pending_buffer)
        except Exception:  # noqa: BLE001
            return False

    def peer_closed(self) -> bool:
        """Has the instrument closed the connection? pyvisa-py reads an orderly close as silence
        and reports a timeout after ``timeout_s``; a non-blocking peek tells at once."""
        if self._sock is None:
            return False
        try:
            return self._sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
        except (ConnectionResetError, ConnectionAbortedError, BrokenPipeError):
            return True
        except OSError:  # would block (open, nothing to read), not connected yet, refused: not a close
            return False

    def _await_reply(self, sock: socket.socket, command: str) -> None:
        """Wait for the reply to start arriving; an instrument that closes the connection
        instead is reported at once (pyvisa-py would wait out its timeout first)."""
        deadline = time.monotonic() + self.timeout_s
        while (left := deadline - time.monotonic()) > 0:
            readable, _, _ = select.select([sock], [], [], min(left, 0.5))
            if readable:
                if self.peer_closed():
                    raise self._closed(command)
                return
        raise DeviceTimeoutError(f"{self.name} ({self.resource}): no reply to {command!r} within {self.timeout_s:g} s")

    def _refuse_if_closed(self, command: str) -> None:
        if self.answered and self.peer_closed():
            raise self._closed(command)

    def _closed(self, command: str) -> DeviceDisconnectedError:
        return DeviceDisconnectedError(f"{self.name} ({self.resource}): the instrument closed the connection "
                                       f"({command!r} was not delivered)")

    def _error(self, command: str, exc: Exception) -> DeviceError:
        errors = self._pyvisa.errors
        if isinstance(exc, errors.VisaIOError) and exc.error_code == self._pyvisa.constants.StatusCode.error_timeout:
            if self.peer_closed():
                return self._closed(command)
            return DeviceTimeoutError(f"{self.name} ({self.resource}): no reply to {command!r} within {self.timeout_s:g} s")
        if self.answered and isinstance(exc, (ConnectionResetError, BrokenPipeError, ConnectionAbortedError)):
            return DeviceDisconnectedError(f"{self.name} ({self.resource}): the connection was lost ({_reason(exc)}); "
                                           f"{command!r} may not have been delivered")
        if isinstance(exc, OSError):  # pyvisa-py connects on first use: refused, unreachable
            return DeviceDisconnectedError(f"{self.name}: cannot reach {self.resource!r} ({_reason(exc)}); is the instrument on and "
                                           f"the resource string right? ({command!r} was not delivered)")
        return DeviceDisconnectedError(f"{self.name} ({self.resource}): {command!r} failed ({_reason(exc)})")

    def close(self) -> None:
        self._sock = None
        for closer in (getattr(self, "_inst", None), getattr(self, "_rm", None)):
            try:
                if closer is not None:
                    closer.close()
            except Exception as exc:  # noqa: BLE001 - closing must not mask anything
                log.debug("closing %s: %r", self.name, exc)


def _reason(exc: Exception) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) < 200 else text[:197] + "..."
