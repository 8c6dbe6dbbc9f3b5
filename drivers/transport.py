"""The transport toolkit every rig shares: retries, statistics, safe shutdown, lifecycle.

Retries are bounded and back off exponentially; they are used only where repeating is safe
(every command of the loopback wire formats is absolute or carries an id the device
de-duplicates, and reads are idempotent). :class:`SafeShutdown` commands the exciter to zero on
every abort path (error, timeout, ``KeyboardInterrupt``) and at interpreter exit;
:class:`RigLifecycle` gives every rig the same ``close()``: zero the output, release the link,
then close what the rig owns (e.g. a loopback fake device), idempotent and never raising.

Per-transport retry defaults are data (:data:`SERIAL_RETRY`, :data:`FIELDBUS_RETRY`), not
separate classes. Duration and amplitude limits are :mod:`setmem_hil.drivers.safety`'s.
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import logging
import math
import time
from collections import Counter
from typing import Any, Callable, Iterator, Protocol, Sequence, TypeVar

import numpy as np

from setmem_hil.drivers.safety import check_dwell

T = TypeVar("T")
log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class RetryPolicy:
    """Bounded retries with exponential backoff.

    Attributes
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

    def delay_s(self, retry: int) -> float:
        """Sleep before retry ``retry`` (1-based)."""
        return min(self.backoff_s * 2 ** (retry - 1), self.backoff_max_s)

    def delays(self) -> Iterator[float]:
        """Sleep before each attempt: 0 for the first, then the backoff sequence."""
        yield 0.0
        for k in range(1, self.max_attempts):
            yield self.delay_s(k)


FIELDBUS_RETRY = RetryPolicy()
"""CAN and Modbus defaults: 100 ms replies, 7 tries, 10 ms doubling to 320 ms."""

SERIAL_RETRY = RetryPolicy(reply_timeout_s=0.2, max_attempts=6, backoff_s=0.002, backoff_max_s=0.05)
"""Serial line defaults: 200 ms replies, 6 tries, 2 ms doubling to 50 ms."""


def call_with_retries(
    func: Callable[[int], T],
    policy: RetryPolicy,
    retry_on: tuple[type[BaseException], ...],
    on_retry: Callable[[int, BaseException], None] | None = None,
    sleep: Callable[[float], None] = time.sleep,
) -> T:
    """Call ``func(attempt)`` until it returns, retrying on ``retry_on`` up to the policy's limit.

    The last exception propagates unchanged once the attempts are spent; anything not in
    ``retry_on`` propagates at once.
    """
    for attempt in range(policy.max_attempts):
        try:
            return func(attempt)
        except retry_on as exc:
            if attempt + 1 >= policy.max_attempts:
                raise
            if on_retry is not None:
                on_retry(attempt + 1, exc)
            sleep(policy.delay_s(attempt + 1))
    raise RuntimeError("call_with_retries: max_attempts must be >= 1")


@dataclasses.dataclass
class TransportStats:
    """Counters of what a host-side link detected and recovered from (per kind)."""

    counts: Counter = dataclasses.field(default_factory=Counter)

    def add(self, kind: str, n: int = 1) -> None:
        self.counts[kind] += n

    def __getitem__(self, kind: str) -> int:
        return self.counts[kind]

    def as_dict(self) -> dict[str, int]:
        return dict(sorted(self.counts.items()))


def sleep_s(seconds: float) -> None:
    if seconds > 0:
        time.sleep(seconds)


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
        except Exception as exc:  # the original fault is what the caller must see
            log.error("safe shutdown: stopping the output failed: %s", exc)
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


class Closeable(Protocol):
    def close(self) -> None: ...


def close_all(resources: Sequence[Closeable]) -> None:
    """Close every resource (in order) even if one fails; re-raise the first failure last."""
    first: BaseException | None = None
    for res in resources:
        try:
            res.close()
        except BaseException as exc:  # noqa: BLE001 - close the rest, then report
            first = first or exc
    if first is not None:
        raise first


class RigLifecycle:
    """``close()`` and context management shared by every rig.

    Needs ``self.guard`` (a :class:`SafeShutdown` whose stop zeroes the output), ``self.link``
    (with ``close()``), ``self.owned`` (resources closed after the link, e.g. a loopback fake
    device; empty for real hardware) and ``self._closed``. ``close()`` commands zero, releases
    the link, then closes what the rig owns; it is idempotent.
    """

    owned: tuple = ()

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
                close_all(self.owned)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class ChunkedSensor:
    """The sensor side every block-transfer rig shares (CAN, Modbus): rate, settle wait, acquire.

    Limits (:func:`setmem_hil.drivers.safety.check_dwell`) are checked before anything is sent,
    every command runs under the rig's :class:`SafeShutdown` guard, and an acquisition longer
    than one device block is read as consecutive blocks (the device clock runs on). Subclasses
    give the wire commands: :meth:`_send_rate`, :meth:`_send_wait`, :meth:`_read_block` and
    :attr:`max_block_samples`.
    """

    def __init__(self, rig: Any):
        self._rig = rig

    max_block_samples: int = 1

    def _send_rate(self, rate_hz: float) -> None:
        raise NotImplementedError

    def _send_wait(self, duration_s: float) -> None:
        raise NotImplementedError

    def _read_block(self, n: int):
        """``n`` samples as a SampleBlock (timestamps, force, response in physical units)."""
        raise NotImplementedError

    def _before_acquire(self) -> None:
        """Checks before an acquisition (e.g. the exciter output is still on)."""

    def set_sample_rate(self, rate_hz: float) -> None:
        rate = float(rate_hz)
        if not (math.isfinite(rate) and rate > 0):
            raise ValueError(f"rate_hz: expected a finite positive rate, found {rate_hz!r}")
        with self._rig.guard.armed():
            self._send_rate(rate)
            self._rig.refresh_metadata()

    def wait(self, duration_s: float) -> None:
        """Let ``duration_s`` pass on the device with the excitation on (settling), no samples."""
        if duration_s == 0:
            return
        check_dwell(self._rig.limits, duration_s, self._rig.link.where)
        with self._rig.guard.armed():
            self._send_wait(duration_s)

    def acquire(self, duration_s: float):
        rig = self._rig
        check_dwell(rig.limits, duration_s, rig.link.where)
        with rig.guard.armed():
            self._before_acquire()
            n_total = max(1, int(round(duration_s * rig.metadata.sample_rate_hz)))
            parts = []
            done = 0
            while done < n_total:
                n = min(self.max_block_samples, n_total - done)
                parts.append(self._read_block(n))
                done += n
            return type(parts[0])(*(np.concatenate([getattr(p, k) for p in parts]) for k in ("t_s", "force", "response")))
