"""Start a campaign run: arguments checked, preflight, the rig opened, a new journal, then the run.

:func:`start_run` creates a run directory with a new journal and runs the campaign
(:mod:`setmem_hil.campaign.journaled_run`: the runner, the standard subscribers, rig safety);
:func:`setmem_hil.campaign.resume.resume_run` continues a stopped one from its journal. The
directory, its lock and its files: :mod:`setmem_hil.run.run_directory`; the checks before
the first dwell: :mod:`setmem_hil.campaign.preflight`; signals and the exciter on every exit:
:mod:`setmem_hil.run.rig_safety`. The names callers import from here are re-exported.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import replace
from pathlib import Path
from typing import Sequence

from rich.console import Console

from setmem_hil.campaign.journaled_run import Display, ExperimentOpener, RunOutcome, run_journaled_campaign, run_with_journal
from setmem_hil.campaign.observers import Observer
from setmem_hil.campaign.persistence import JournalWriter
from setmem_hil.campaign.preflight import preflight
from setmem_hil.campaign.resume import resume_run
from setmem_hil.run.rig_safety import unconfirmed_output_off
from setmem_hil.run.run_directory import (
    PROCEDURE_COPY,
    SUMMARY_FILENAME,
    default_run_dir,
    describe_procedure,
    LOCK_FILENAME,
    directory_lock,
)
from setmem_hil.errors import InputFormatError
from setmem_hil.io.atomic_file import write_text_atomic
from setmem_hil.io.journal import JOURNAL_FILENAME
from setmem_hil.io.procedure import DESIGN_METHODS, STRATEGIES, Procedure
from setmem_hil.io.procedure_file import format_procedure

__all__ = [
    "RunOutcome", "start_run", "resume_run", "run_journaled_campaign", "default_run_dir", "describe_procedure",
    "directory_lock", "preflight", "SUMMARY_FILENAME", "PROCEDURE_COPY", "Display", "unconfirmed_output_off",
]


def _arguments_error(problem: str) -> InputFormatError:
    return InputFormatError("setmem-hil run", "arguments", problem)


def start_run(
    procedure: Procedure,
    run_dir: str | os.PathLike,
    *,
    seed: int | None = None,
    strategy: str | None = None,
    console: Console | None = None,
    opener: ExperimentOpener,
    display: Display | None = None,
    quiet_report_hint: bool = False,
    control=None,
    observers: Sequence[Observer] = (),
    design: str | None = None,
) -> RunOutcome:
    """Create ``run_dir`` with a new journal and run the campaign (see the module docstring).

    The procedure's text (``procedure.source_text``, or its :func:`format_procedure` rendering
    for a programmatic procedure) is stored in the journal with the seed, strategy, backend and
    software version, so the run can be resumed and reported later. ``opener(procedure, seed)``
    builds the experiment (:func:`setmem_hil.experiment_factory.open_experiment`); ``display``
    adds a view of the campaign (terminal progress, live view). ``design`` overrides the
    procedure's ``[design] method`` (``--design``); the journal keeps it for a resume.
    """
    console = console or Console(soft_wrap=True)
    run_dir = Path(run_dir)
    if design is not None:
        if design not in DESIGN_METHODS:
            raise _arguments_error(f"design {design!r} is not one of {', '.join(DESIGN_METHODS)}")
        procedure = replace(procedure, design_method=design)
    seed = procedure.seed if seed is None else int(seed)
    if seed < 0:
        raise _arguments_error(f"--seed {seed} must be >= 0")
    strategy = strategy or procedure.input_design.strategy
    if strategy not in STRATEGIES:
        raise _arguments_error(f"strategy {strategy!r} is not one of {', '.join(STRATEGIES)}")
    # a truth file is named relative to its procedure: the stored text names it absolutely, so a
    # resume (which reads the journal's text) finds it
    text = format_procedure(procedure) if procedure.backend.simulation.truth or not procedure.source_text else procedure.source_text
    if run_dir.exists() and not run_dir.is_dir():
        raise InputFormatError(str(run_dir), "", "exists and is not a directory")
    if (run_dir / JOURNAL_FILENAME).exists():
        raise InputFormatError(str(run_dir), "", f"already holds a run (it already holds a journal.sqlite); continue it with `setmem-hil run --resume {run_dir}` or choose another --out")
    preflight(procedure)
    # Open the rig first: a transport option the driver rejects, or a device that does not
    # start, must not leave behind a journal whose stored procedure can never run.
    experiment = opener(procedure, seed)
    with contextlib.ExitStack() as held:
        try:
            run_dir.mkdir(parents=True, exist_ok=True)
            held.enter_context(directory_lock(run_dir, LOCK_FILENAME, "another setmem-hil process is running this campaign; "
                                                                      "wait for it or stop it first"))
            write_text_atomic(run_dir / PROCEDURE_COPY, text)
        except BaseException:
            experiment.close()
            raise
        console.print(f"run directory: {run_dir}", highlight=False)
        describe_procedure(procedure, console)
        # the journal is made by its store from the run's start document (the procedure's text as stored)
        store = JournalWriter(run_dir / JOURNAL_FILENAME)
        return run_with_journal(replace(procedure, source_text=text), store, run_dir, seed=seed, strategy=strategy, console=console,
                                experiment=experiment, opener=opener, display=display, quiet_report_hint=quiet_report_hint,
                                control=control, observers=observers)
