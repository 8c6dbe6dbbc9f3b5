"""One journaled campaign, whoever starts it: the runner, the standard subscribers and rig safety.

:func:`run_journaled_campaign` is the one way a journaled campaign is run (``run``, ``demo``,
``campaign``, a resume and the sweep task), so every procedure setting means the same everywhere:
the runner (:mod:`setmem_hil.campaign.runner`) plus the standard subscribers of
:mod:`setmem_hil.campaign.observers` plus whatever display the caller adds (terminal progress,
live view). :func:`run_with_journal` adds rig safety (:mod:`setmem_hil.run.rig_safety`):
Ctrl-C (or SIGTERM) stops cleanly: the exciter is commanded to zero, the journal is closed, the
message says how to resume, and ``KeyboardInterrupt`` propagates (exit 130 in the CLI). SIGKILL
or a power cut cannot be caught; the journal still holds every completed measurement.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, ContextManager, Sequence

from rich.console import Console

from setmem_hil.campaign.observers import Observer, broadcast, standard_observers
from setmem_hil.campaign.persistence import JournalWriter
from setmem_hil.run.rig_safety import (
    arm_exciter,
    journal_identities,
    sigint_deferred,
    sigterm_as_interrupt,
    stored_count,
    unconfirmed_output_off,
)
from setmem_hil.run.safe_exit import interrupted_by, stop_safely
from setmem_hil.run.run_directory import SUMMARY_FILENAME
from setmem_hil.errors import CampaignAborted, DeviceError, InconsistentDataError, InputFormatError, RunInterrupted
from setmem_hil.io.atomic_file import write_json_atomic
from setmem_hil.io.procedure import Procedure

if TYPE_CHECKING:
    from setmem_hil.campaign.summary import CampaignSummary

__all__ = ["Display", "ExperimentOpener", "RunOutcome", "run_journaled_campaign", "run_with_journal"]

Display = Callable[[Any], ContextManager[Observer]]
"""``display(experiment)``: a context manager yielding an observer that shows the campaign."""

ExperimentOpener = Callable[[Procedure, int], Any]


@dataclass(frozen=True)
class RunOutcome:
    """What a started or resumed run did."""

    run_dir: Path
    summary: dict
    already_finished: bool = False


def run_journaled_campaign(procedure: Procedure, experiment: Any, store: JournalWriter, *, seed: int, strategy: str,
                           observers: Sequence[Observer] = (), continue_stored: bool = False, control=None) -> CampaignSummary:
    """Algorithm 5.1 on ``experiment``, its journal written by ``store`` (a new journal is made from
    the run's ``start`` document), with the standard subscribers plus ``observers``."""
    from setmem_hil.campaign.runner import run_campaign

    subscribers = [*observers, *standard_observers(procedure, store)]
    return run_campaign(procedure, experiment, store, seed=seed, strategy=strategy, progress=broadcast(subscribers),
                        continue_stored=continue_stored, control=control)


def run_with_journal(procedure: Procedure, store: JournalWriter, run_dir: Path, *, seed: int, strategy: str, console: Console,
                      opener: ExperimentOpener, display: Display | None, experiment: Any = None,
                      continue_stored: bool = False, quiet_report_hint: bool = False, control=None,
                      observers: Sequence[Observer] = ()) -> RunOutcome:
    """The campaign with rig safety around it (see the module docstring); ``store`` writes the
    run's journal and is closed when the run ends, however it ends."""
    with sigterm_as_interrupt():
        try:
            return _run_campaign_in(procedure, store, run_dir, seed=seed, strategy=strategy, console=console,
                                    opener=opener, display=display, experiment=experiment, continue_stored=continue_stored,
                                    quiet_report_hint=quiet_report_hint, control=control, observers=observers)
        finally:
            store.close()


def _run_campaign_in(procedure: Procedure, store: JournalWriter, run_dir: Path, *, seed: int, strategy: str, console: Console,
                     opener: ExperimentOpener, display: Display | None, experiment: Any = None,
                     continue_stored: bool = False, quiet_report_hint: bool = False, control=None,
                     observers: Sequence[Observer] = ()) -> RunOutcome:
    resume = f"continue with `setmem-hil run --resume {run_dir}`"
    try:
        previous_unconfirmed = unconfirmed_output_off(store.journal) if store.journal is not None else None
        if experiment is None:
            experiment = opener(procedure, seed)
        journal_identities(store, experiment)  # notes before the run's start: written right after a new journal's header
        arm_exciter(store, experiment, console, previous_unconfirmed)
        with (display(experiment) if display is not None else contextlib.nullcontext(None)) as shown:
            summary = run_journaled_campaign(procedure, experiment, store, seed=seed, strategy=strategy,
                                             observers=([shown] if shown is not None else []) + list(observers),
                                             continue_stored=continue_stored, control=control)
        doc = summary.to_document()
    except KeyboardInterrupt as exc:
        stop = stop_safely(experiment, store, exc)
        # one line says what was made safe, what is kept and how to go on (the CLI prints it)
        raise RunInterrupted(f"interrupted ({interrupted_by(exc)}); {stop.safety}, journal closed with "
                             f"{_closed_with(store)} measurements; {resume}") from exc
    except CampaignAborted as exc:
        stop = stop_safely(experiment, store, exc)
        raise CampaignAborted(f"aborted ({exc}); {stop.safety}, journal closed with {_closed_with(store)} measurements; {resume}") from exc
    except DeviceError as exc:
        stop = stop_safely(experiment, store, exc)
        exc.safety_note = stop.safety  # the first fault stays the message; what the clean-up achieved follows it
        exc.resume_hint = f"journal closed with {_closed_with(store)} measurements; after fixing the rig {resume}"
        raise
    except BaseException as exc:
        stop = stop_safely(experiment, store, exc)
        if isinstance(exc, Exception):
            fix = " --procedure FIXED.toml" if isinstance(exc, (InconsistentDataError, InputFormatError)) else ""
            exc.resume_hint = (f"{stop.safety}, journal closed with {_closed_with(store)} measurements; continue with "
                               f"`setmem-hil run --resume {run_dir}{fix}`")
        raise
    stop = stop_safely(experiment, store, None)
    with sigint_deferred():
        store.close()
    safety, close_error = stop.safety, stop.close_error
    write_json_atomic(doc, run_dir / SUMMARY_FILENAME)
    console.print(f"summary: {run_dir / SUMMARY_FILENAME}" + ("" if quiet_report_hint else f" (report: setmem-hil report {run_dir})"),
                  highlight=False)
    if close_error is not None:  # every point is kept; the rig is not known to be safe
        raise DeviceError(f"the campaign finished, but {safety}") from close_error
    return RunOutcome(run_dir, doc)


def _closed_with(store: JournalWriter) -> str:
    """The journal's measurements for a message, read after closing it (every point is committed)."""
    store.close()
    return stored_count(store.path) if Path(store.path).exists() else "0"
