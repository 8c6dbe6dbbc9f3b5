"""The one safe exit of every plan (issue 63 item 6): however a run ends, its actuator is made
safe first, then why it stopped and whether the output is confirmed off are journaled.

The campaign's actuator is its experiment (the exciter's output, read back where the instrument
can); the closed-loop verification's is the real-time target (the injection off and the bypass
read back, :class:`setmem_hil.verify.session.TargetActuator`). Both are closed through
:func:`stop_safely`, so a Ctrl-C, a SIGTERM, a dead link or an error leaves the same notes in
either journal: the cause (``interrupted``, ``aborted``, ``device-fault``, ``error``) and
``output-off`` with ``confirmed`` or ``NOT confirmed`` (:data:`~.rig_safety.OUTPUT_OFF_EVENT`).
While it runs, a second Ctrl-C or SIGTERM is ignored: it cannot skip the stop.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from setmem_hil.errors import CampaignAborted, DeviceError
from setmem_hil.run.rig_safety import Store, Terminated, shut_down, sigint_deferred

__all__ = ["SafeExit", "first_fault", "interrupted_by", "stop_reason", "stop_safely"]


@dataclass(frozen=True)
class SafeExit:
    """What the safe exit achieved: ``safety`` says what state the actuator was left in;
    ``close_error`` is why it could not be confirmed (None when it was, or cannot be read back)."""

    safety: str
    close_error: BaseException | None


def stop_reason(failure: BaseException | None) -> tuple[str | None, str]:
    """The journal's ``(kind, message)`` for why a run stopped (``(None, "")``: it finished)."""
    if failure is None:
        return None, ""
    if isinstance(failure, KeyboardInterrupt):
        return "interrupted", "SIGTERM: stopped by a signal" if isinstance(failure, Terminated) else "Ctrl-C: stopped by the operator"
    if isinstance(failure, CampaignAborted):
        return "aborted", f"aborted: {failure}"
    if isinstance(failure, DeviceError):
        return "device-fault", str(first_fault(failure))
    return "error", f"{type(failure).__name__}: {failure}"


def interrupted_by(interrupt: KeyboardInterrupt) -> str:
    """``Ctrl-C`` or ``SIGTERM``: what stopped a run, for the operator's one line."""
    return stop_reason(interrupt)[1].split(":")[0]


def first_fault(failure: BaseException) -> BaseException:
    """The first device fault of a chain: a clean-up that fails on a dead link raises over the
    command that went unanswered first (``no reply to BYPASS`` over ``no reply to ANALYSIS?``);
    the operator is told the first (issue 63 item 4)."""
    first, seen = failure, {id(failure)}
    context = failure.__context__
    while isinstance(context, DeviceError) and id(context) not in seen:
        first, seen = context, seen | {id(context)}
        context = context.__context__
    return first


def stop_safely(actuator: Any, store: Store, failure: BaseException | None) -> SafeExit:
    """The actuator to safe (``actuator.close()``), then the notes, with Ctrl-C and SIGTERM
    ignored meanwhile. A failing clean-up never replaces the cause: it is returned."""
    kind, message = stop_reason(failure)
    with sigint_deferred():
        safety, close_error = shut_down(actuator, store, kind, message)
    return SafeExit(safety, close_error)
