"""A stop signal whose exception Python drops (it landed in a finaliser) still stops the run.

The control case shows the hazard is real: with a plain handler the dropped SIGTERM is lost and
the plan runs to its end."""

from __future__ import annotations

import os
import signal
import sys
import threading

import pytest

from setmem_hil.run import signal_latch
from setmem_hil.run.engine import EXIT_ABORT, STOP, Emit, RunEngine
from setmem_hil.run.rig_safety import Terminated, sigterm_as_interrupt

pytestmark = [
    pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning"),
    pytest.mark.skipif(threading.current_thread() is not threading.main_thread(), reason="signals reach the main thread only"),
]


class _SignalledWhileFinalised:
    """Sends ``signum`` to this process from its finaliser, and spins so the handler runs there."""

    def __init__(self, signum: int):
        self.signum = signum

    def __del__(self):
        os.kill(os.getpid(), self.signum)
        for _ in range(100_000):  # the handler runs between two of these bytecodes, inside __del__
            pass


def _plan(reached: list[str], signum: int):
    yield Emit("note", {"kind": "first", "message": "before"})
    _SignalledWhileFinalised(signum)  # made and dropped at once: its __del__ runs here
    reached.append("after the finaliser")
    yield Emit("note", {"kind": "second", "message": "after"})
    reached.append("end")


def _run(signum: int) -> tuple[list[str], list[dict], BaseException | None]:
    reached, docs = [], []
    engine = RunEngine([lambda name, **info: docs.append({"name": name, **info})])
    try:
        engine.run(_plan(reached, signum))
    except BaseException as exc:  # noqa: BLE001 - the test looks at what came out
        return reached, docs, exc
    return reached, docs, None


def test_control_a_plain_handler_loses_the_sigterm_dropped_in_a_finaliser():
    def plain(signum, frame):
        raise Terminated()

    previous = signal.signal(signal.SIGTERM, plain)
    try:
        reached, docs, exc = _run(signal.SIGTERM)
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert exc is None and reached == ["after the finaliser", "end"]  # the hazard: the run went on


@pytest.mark.parametrize("signum, expected", [(signal.SIGTERM, Terminated), (signal.SIGINT, KeyboardInterrupt)])
def test_a_stop_signal_dropped_in_a_finaliser_stops_the_run_at_its_next_request(signum, expected):
    with sigterm_as_interrupt():
        reached, docs, exc = _run(signum)
        assert signal_latch.pending() is None  # delivered once, not raised again in the clean-up
    assert type(exc) is expected
    assert reached == ["after the finaliser"]  # the second request was never performed
    stop = [d for d in docs if d["name"] == STOP][-1]
    assert stop["exit_status"] == EXIT_ABORT
    assert [d.get("kind") for d in docs if d["name"] == "note"] == ["first"]


def test_a_delivered_interrupt_is_not_raised_again_by_the_plans_clean_up():
    """The plan's finally may make requests (emit its last documents) after an interrupt reached it."""
    cleaned = []

    def plan():
        try:
            yield Emit("note", {"kind": "work"})
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(100_000):
                pass
            cleaned.append("not reached")
        finally:
            yield Emit("note", {"kind": "clean-up"})
            cleaned.append("clean-up emitted")

    docs = []
    engine = RunEngine([lambda name, **info: docs.append(info.get("kind"))])
    with sigterm_as_interrupt():
        with pytest.raises(Terminated):
            engine.run(plan())
    assert cleaned == ["clean-up emitted"] and "clean-up" in docs


def test_the_handler_and_hook_are_restored_and_nothing_latched_after_the_run():
    before_term, before_hook = signal.getsignal(signal.SIGTERM), sys.unraisablehook
    with sigterm_as_interrupt():
        _SignalledWhileFinalised(signal.SIGTERM)  # dropped and latched, never raised again
        assert signal_latch.pending() is Terminated
    assert signal_latch.pending() is None
    assert signal.getsignal(signal.SIGTERM) is before_term and sys.unraisablehook is before_hook
