"""What the CAN and Modbus rigs share: retry policy, transport statistics, safe shutdown.

Retries are bounded and back off exponentially; they are used only where repeating is safe
(every command of both wire formats is absolute or carries an id the device de-duplicates,
and reads are idempotent). The safe-shutdown helper commands the exciter to zero on every
abort path (error, timeout, ``KeyboardInterrupt``) and at interpreter exit.
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import math
import time
from collections import Counter
from typing import Callable, Iterator

from setmem_hil.drivers import safety
from setmem_hil.errors import ProcedureError, SafetyLimitError


@dataclasses.dataclass(frozen=True)
class RetryPolicy:
    """Bounded retries with exponential backoff.

    Parameters
    ----------
    reply_timeout_s : float
        Wait for one reply.
    max_attempts : int
        Tries per request (first try included).
    backoff_s, backoff_max_s : float
        Sleep before retry ``k`` (1-based) is ``min(backoff_s * 2**(k-1), backoff_max_s)``.
    """

    reply_timeout_s: float = 0.1
    max_attempts: int = 7
    backoff_s: float = 0.01
    backoff_max_s: float = 0.32

    def delays(self) -> Iterator[float]:
        """Sleep before each attempt: 0 for the first, then the backoff sequence."""
        yield 0.0
        for k in range(1, self.max_attempts):
            yield min(self.backoff_s * 2 ** (k - 1), self.backoff_max_s)


@dataclasses.dataclass
class TransportStats:
    """Counters of what a host-side link detected and recovered from (per kind)."""

    counts: Counter = dataclasses.field(default_factory=Counter)

    def add(self, kind: str, n: int = 1) -> None:
        self.counts[kind] += n

    def as_dict(self) -> dict[str, int]:
        return dict(sorted(self.counts.items()))


def check_sine_command(limits, omega_rad_s: float, amplitude_n: float, where: str) -> None:
    """Refuse a sine outside the procedure's :class:`~setmem_hil.io.procedure.SafetyLimits`.

    The rule is :func:`setmem_hil.drivers.safety.check_sine_command` (one rule for every
    transport); this wrapper names the transport in the message.

    Raises
    ------
    SafetyLimitError
        Before anything is sent: names the transport, the quantity, the limit and the value.
    """
    try:
        safety.check_sine_command(limits, omega_rad_s, amplitude_n)
    except SafetyLimitError as exc:
        raise SafetyLimitError(f"{where}: {exc}") from None


def check_duration(limits, duration_s: float, where: str) -> None:
    if not (math.isfinite(duration_s) and 0.0 < duration_s <= limits.max_dwell_s):
        raise SafetyLimitError(
            f"{where}: acquisition of {duration_s!r} s outside (0, {limits.max_dwell_s:g}] (max_dwell_s); nothing sent"
        )


class SafeShutdown:
    """Run ``stop`` on every abort path of a block and once at interpreter exit.

    ``with guard.armed(): ...`` calls ``stop()`` (best effort: its own errors are swallowed,
    the original exception propagates) if the block raises anything, ``KeyboardInterrupt``
    included. :meth:`register_exit` / :meth:`unregister_exit` manage the ``atexit`` hook.
    """

    def __init__(self, stop: Callable[[], None]):
        self._stop = stop
        self._registered = False

    @contextlib.contextmanager
    def armed(self):
        try:
            yield
        except BaseException:
            self.stop_quietly()
            raise

    def stop_quietly(self) -> bool:
        try:
            self._stop()
            return True
        except Exception:  # the original fault is what the caller must see
            return False

    def register_exit(self, close: Callable[[], None]) -> None:
        if not self._registered:
            atexit.register(close)
            self._registered = True
            self._close = close

    def unregister_exit(self) -> None:
        if self._registered:
            atexit.unregister(self._close)
            self._registered = False


def sleep_s(seconds: float) -> None:
    if seconds > 0:
        time.sleep(seconds)


def transport_option(procedure, key: str, kind: type, default, *, choices=None, lo=None, hi=None):
    """``procedure.backend.transport[key]`` checked; ProcedureError naming the key otherwise.

    Keys this transport does not know are left alone (they belong to other transports).
    """
    opts = procedure.backend.transport or {}
    if key not in opts:
        return default
    value = opts[key]
    source = procedure.source_path or procedure.name
    where = f"[backend.transport] key '{key}'"
    if kind is str:
        if not isinstance(value, str) or (choices is not None and value not in choices):
            expected = f"one of {list(choices)}" if choices is not None else "a string"
            raise ProcedureError(source, where, f"expected {expected}, found {value!r}")
        return value
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok and kind is int:
        ok = value == int(value)
    if ok and ((lo is not None and value < lo) or (hi is not None and value > hi)):
        ok = False
    if not ok:
        bounds = f" in [{lo}, {hi}]" if lo is not None or hi is not None else ""
        raise ProcedureError(source, where, f"expected {'an integer' if kind is int else 'a number'}{bounds}, found {value!r}")
    return kind(value)


class FieldbusRigLifecycle:
    """Shutdown and context management shared by the CAN and Modbus rigs.

    Needs ``self.guard`` (a :class:`SafeShutdown`), ``self.link`` (with ``close()`` and
    ``stats``), ``self._on_close`` (the owner's hook, e.g. stopping a fake device) and
    ``self._closed``. ``close()`` commands zero, releases the link, then runs the hook; it is
    idempotent and never raises.
    """

    def transport_statistics(self) -> dict[str, int]:
        return self.link.stats.as_dict()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.guard.unregister_exit()
        try:
            self.guard.stop_quietly()
        finally:
            try:
                self.link.close()
            finally:
                if self._on_close is not None:
                    self._on_close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
