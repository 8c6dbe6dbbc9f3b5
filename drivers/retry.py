"""Bounded retries with exponential backoff, for requests that are safe to repeat.

A request may be repeated when repeating it cannot change the outcome: absolute commands
(``SINE w a``, ``STOP``, ``RATE``), reads, and requests the device de-duplicates by their
sequence number (the serial device answers a repeated ``seq`` from its cache without executing
it again, see ``drivers/serial_wire_format.md``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, TypeVar

T = TypeVar("T")


@dataclass(frozen=True)
class RetryPolicy:
    """Retry settings.

    Attributes
    ----------
    reply_timeout_s : float
        How long to wait for one reply.
    max_attempts : int
        Tries per request, the first included.
    backoff_s, backoff_max_s : float
        Sleep before retry ``k`` (1-based): ``min(backoff_s * 2**(k - 1), backoff_max_s)``.
    """

    reply_timeout_s: float = 0.2
    max_attempts: int = 6
    backoff_s: float = 0.002
    backoff_max_s: float = 0.05

    def delay_s(self, retry: int) -> float:
        return min(self.backoff_s * 2 ** (retry - 1), self.backoff_max_s)


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
    raise AssertionError("unreachable")  # pragma: no cover
