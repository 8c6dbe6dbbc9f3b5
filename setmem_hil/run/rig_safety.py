"""Rig safety around a run: signals, the exciter's output on every exit, and what the journal says of it.

* Ctrl-C and SIGTERM (:func:`sigterm_as_interrupt`: SIGTERM is handled like Ctrl-C) stop a run
  cleanly; while it shuts down a second one is ignored (:func:`sigint_deferred`), so it cannot
  skip the exciter stop;
* :func:`shut_down`: the exciter to zero first, then why the run stopped and whether the output
  is confirmed off (:data:`OUTPUT_OFF_EVENT`) go to the run's store as ``note`` documents; a
  failing clean-up never replaces the cause;
* :func:`arm_exciter` notes a session that may switch an output on (:data:`EXCITER_ARMED_EVENT`);
  one that ended without a confirmed output-off (SIGKILL, power loss) is found by
  :func:`unconfirmed_output_off`, and the next resume switches the output off first.

What they say goes to ``store``, the run's journal store
(:class:`setmem_hil.campaign.persistence.JournalWriter`), as ``note`` documents like every other
event of the run: the journal is written from documents alone.
"""

from __future__ import annotations

import signal
import sys
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator

from rich.console import Console

from setmem_hil.run import signal_latch
from setmem_hil.run.engine import NOTE
from setmem_hil.errors import SetmemError
from setmem_hil.io.journal import Journal

Store = Callable[..., None]
"""Where the notes go: ``store(name, **document)``, the run's journal store."""

__all__ = ["EXCITER_ARMED_EVENT", "INSTRUMENTS_EVENT", "OUTPUT_OFF_EVENT", "Terminated", "arm_exciter", "journal_identities",
           "output_safety", "shut_down", "sigint_deferred", "sigterm_as_interrupt", "stored_count", "unconfirmed_output_off"]


@contextmanager
def sigint_deferred() -> Iterator[None]:
    """Ignore Ctrl-C and SIGTERM while shutting down, so a second one cannot skip the exciter stop."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    previous_term = signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        signal.signal(signal.SIGTERM, previous_term)


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill PID``, a service manager stopping us): handled exactly like Ctrl-C."""


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Turn SIGTERM into an interrupt for the duration of the campaign, so the exciter is
    zeroed and the journal closed (the default action would end the process on the spot).

    A stop signal that lands in a finaliser, where Python drops its exception, is latched and
    stops the run at its next request (:mod:`setmem_hil.run.signal_latch`)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Terminated()

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        with signal_latch.latching_dropped_interrupts():
            yield
    finally:
        signal.signal(signal.SIGTERM, previous)


INSTRUMENTS_EVENT = "instruments"
"""Journal event: the instruments a session drove and what each answered to its identity query."""


def journal_identities(store: Store, experiment: Any) -> None:
    from setmem_hil.model.experiment import IdentifiedExperiment

    if isinstance(experiment, IdentifiedExperiment) and experiment.identities:
        _note(store, INSTRUMENTS_EVENT, "; ".join(f"{name}: {answer}" for name, answer in experiment.identities.items()))


EXCITER_ARMED_EVENT = "exciter-armed"
"""Journal event: a session with an exciter began (its output may be switched on from here)."""
OUTPUT_OFF_EVENT = "output-off"
"""Journal event at the end of a session: whether the exciter's output was confirmed off; its
message starts with ``confirmed`` or ``NOT confirmed``. An ``exciter-armed`` event with no
``output-off ... confirmed`` after it is a session that ended without a confirmed output-off
(SIGKILL, power loss, a dead link): the next ``run --resume`` switches the output off first."""


def unconfirmed_output_off(journal: Journal) -> str | None:
    """Why the journal's last session did not end with a confirmed output-off (None if it did,
    or never drove an exciter)."""
    last = None
    for event in journal.events():
        if event["kind"] in (EXCITER_ARMED_EVENT, OUTPUT_OFF_EVENT):
            last = event
    if last is None or (last["kind"] == OUTPUT_OFF_EVENT and last["message"].startswith("confirmed")):
        return None
    if last["kind"] == EXCITER_ARMED_EVENT:
        return f"the session started {last['utc']} ended without a confirmed output-off (killed, power loss?)"
    return f"its last session could not confirm the output off ({last['message']})"


def arm_exciter(store: Store, experiment: Any, console: Console, previous_unconfirmed: str | None) -> None:
    from setmem_hil.model.experiment import OutputConfirmingExperiment

    if not isinstance(experiment, OutputConfirmingExperiment):
        return
    if previous_unconfirmed is not None:
        experiment.confirm_output_off()  # opening forced it off already: read it back once more, and say so
        line = f"output switched off: {experiment.exciter} (read back), because {previous_unconfirmed}"
        if console.quiet:  # a safety action is always said, --quiet or not
            print(f"setmem-hil: {line}", file=sys.stderr, flush=True)
        else:
            console.print(line, highlight=False)
        _note(store, OUTPUT_OFF_EVENT, f"confirmed at resume: {line}")
    _note(store, EXCITER_ARMED_EVENT, f"{experiment.exciter}: the output may be switched on from here")


def _note(store: Store, kind: str, message: str) -> None:
    store(NOTE, kind=kind, message=message)


def stored_count(journal_file: str | Path) -> str:
    """How many measurements the journal at ``journal_file`` holds (read afresh), for a message."""
    try:
        j = Journal.open(journal_file)
        try:
            return str(j.n_measurements())
        finally:
            j.close()
    except SetmemError:
        return "all completed"


def shut_down(experiment: Any, store: Store, kind: str | None, message: str) -> tuple[str, BaseException | None]:
    """Exciter to zero first, then note why we stopped and whether the output is confirmed off.
    A failing clean-up never replaces the cause: it is returned (with the sentence that says what
    state the rig is in) for the caller's message; closing the journal is the caller's."""
    close_error: BaseException | None = None
    try:
        if experiment is not None:
            experiment.close()
    except BaseException as exc:  # noqa: BLE001 - reported in the safety sentence, never raised over the cause
        close_error = exc
    safety, confirmed = output_safety(experiment, close_error)
    if kind is not None:
        _note(store, kind, message)
    if confirmed is not None:
        _note(store, OUTPUT_OFF_EVENT, f"{'confirmed' if confirmed else 'NOT confirmed'}: {safety}")
    return safety, close_error


def output_safety(experiment: Any, close_error: BaseException | None) -> tuple[str, bool | None]:
    """The sentence that says what state the exciter was left in, and whether its output is
    confirmed off (None: the experiment cannot read its output back)."""
    from setmem_hil.errors import OutputNotConfirmedOffError
    from setmem_hil.model.experiment import OutputConfirmingExperiment

    if isinstance(close_error, OutputNotConfirmedOffError):
        return " ".join(str(close_error).split()), False
    if isinstance(experiment, OutputConfirmingExperiment):
        # an actuator may say its safe state in its own words (the real-time target: bypassed)
        if experiment.output_confirmed_off:
            return getattr(experiment, "safe_sentence", f"output of {experiment.exciter} confirmed off"), True
        cause = f" ({' '.join(str(close_error).split())})" if close_error is not None else ""
        advice = getattr(experiment, "unsafe_advice", "switch it off at the instrument or at the amplifier")
        return f"the output of {experiment.exciter} could not be confirmed off{cause}: it may still be on: {advice}", False
    if close_error is not None:
        return (f"the exciter could not be commanded to zero ({' '.join(str(close_error).split())}): "
                "switch it off at the instrument or at the amplifier"), None
    return "exciter at zero", None
