"""A stop signal's exception that Python dropped, raised again at the run's next request.

Python runs a signal handler in the main thread between two bytecodes, wherever that thread is.
When it is inside a finaliser (a ``__del__``, a weakref callback, a generator closed by the
garbage collector), the exception the handler raises (Ctrl-C's ``KeyboardInterrupt``, our
SIGTERM's ``Terminated``) cannot propagate: Python hands it to :func:`sys.unraisablehook`, prints
"Exception ignored in ...", and the run goes on as if nobody had asked it to stop. (Found under
load: a SIGTERM that landed in a finaliser let a campaign run to its end and exit 0, not 130.)

While :func:`latching_dropped_interrupts` is active, that hook *latches* such an exception's type
(and still reports it as before). The run engine raises a latched interrupt before each request it
performs (:func:`raise_pending`), once. Only a dropped interrupt is latched, so one that was
delivered (and is being handled, e.g. by a plan's ``finally`` that still makes requests) is never
raised twice. A dropped one costs at most the time to the plan's next request.

The latch is process-wide, because signals and the hook are.
"""

from __future__ import annotations

import sys
from contextlib import contextmanager
from typing import Iterator

__all__ = ["latching_dropped_interrupts", "raise_pending", "pending"]

_pending: type[BaseException] | None = None


def _latch(exc_type: type[BaseException]) -> None:
    global _pending
    _pending = exc_type


def pending() -> type[BaseException] | None:
    """The type of an interrupt Python dropped that the run has not raised again yet, or None."""
    return _pending


def raise_pending() -> None:
    """Raise (once) an interrupt that Python dropped in a finaliser."""
    exc_type = _pending
    if exc_type is not None:
        _latch(None)
        raise exc_type()


@contextmanager
def latching_dropped_interrupts() -> Iterator[None]:
    """Latch every interrupt Python drops as unraisable until the block ends (main thread)."""
    previous_hook = sys.unraisablehook

    def hook(unraisable) -> None:
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            _latch(type(unraisable.exc_value))
        previous_hook(unraisable)  # still said on stderr, as Python would

    _latch(None)  # a stale latch from an earlier run in this process is not ours
    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous_hook
        _latch(None)
