"""The drivers' clock: wall time on a real rig, the emulated bench's virtual time in simulation.

Every wait of the instrument drivers (lock-in settling, ramps, readings spaced by time
constants) goes through a :class:`Clock`, so an emulated rig (whose clock only moves when the
driver waits) runs a 1000 s dwell in milliseconds with exactly the driver code a real rig runs.
"""

from __future__ import annotations

import time
from typing import Protocol, runtime_checkable

__all__ = ["Clock", "WallClock"]


@runtime_checkable
class Clock(Protocol):
    def now(self) -> float:
        """Seconds on a monotonic clock."""
        ...

    def sleep(self, duration_s: float) -> None:
        """Let ``duration_s`` seconds pass."""
        ...


class WallClock:
    """Real time (``time.monotonic``); ``sleep`` is interruptible by Ctrl-C."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, duration_s: float) -> None:
        if duration_s > 0:
            time.sleep(duration_s)
