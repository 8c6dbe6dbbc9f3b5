"""Resume a stopped campaign from its journal (REPLAY, :mod:`setmem_hil.campaign.runner`), or
continue it with a corrected procedure (``run --resume DIR --procedure FIXED.toml``)."""

from __future__ import annotations

import hashlib
import os
from dataclasses import replace
from pathlib import Path
from typing import Sequence

from rich.console import Console

from setmem_hil import __version__
from setmem_hil.campaign.journaled_run import Display, ExperimentOpener, RunOutcome, run_with_journal
from setmem_hil.run.engine import NOTE
from setmem_hil.campaign.observers import Observer
from setmem_hil.campaign.persistence import JournalWriter
from setmem_hil.campaign.preflight import preflight
from setmem_hil.run.run_directory import SUMMARY_FILENAME, run_lock
from setmem_hil.errors import InputFormatError
from setmem_hil.io.atomic_file import write_json_atomic
from setmem_hil.io.journal import Journal
from setmem_hil.io.procedure_file import format_procedure, parse_procedure_text

__all__ = ["PROCEDURE_CHANGED", "changed_procedure_text", "resume_run"]


PROCEDURE_CHANGED = "procedure-changed"
"""Journal event of ``run --resume DIR --procedure FILE``: its message ends with the new procedure text."""


def changed_procedure_text(journal: Journal) -> str | None:
    """The procedure text of the latest ``run --resume --procedure`` of this run, if any."""
    changed = [e for e in journal.events() if e["kind"] == PROCEDURE_CHANGED]
    return changed[-1]["message"].split("\n", 1)[1] if changed else None


def resume_run(run_dir: str | os.PathLike, *, console: Console | None = None, opener: ExperimentOpener,
               display: Display | None = None, procedure_path: str | os.PathLike | None = None, control=None,
               observers: Sequence[Observer] = ()) -> RunOutcome:
    """Continue the run in ``run_dir`` from its journal (REPLAY; see the module docstring).

    With ``procedure_path`` the run continues with that (corrected) procedure: every stored
    measurement is reused as data, iterations go on after the last stored one, and the change
    (old and new text's SHA-256, the new text) is journaled as a ``procedure-changed`` event, so a
    later plain resume continues with the corrected procedure too.
    """
    console = console or Console(soft_wrap=True)
    run_dir = Path(run_dir)
    journal = Journal.open(run_dir)
    try:
        info = journal.run_info()
        source = f"{journal.path} (stored procedure)"
        if not info["procedure_text"].strip():
            raise InputFormatError(str(journal.path), "table run", "the journal holds no procedure text; this run cannot be resumed")
        changed = changed_procedure_text(journal)
        procedure = parse_procedure_text(changed or info["procedure_text"], source if changed is None else f"{journal.path} (changed procedure)")
        if procedure_path is not None:
            from setmem_hil.io.procedure_file import load_procedure

            procedure = load_procedure(procedure_path)
            preflight(procedure)
        if procedure_path is None and changed is None:  # the design the run started with (--design)
            procedure = replace(procedure, design_method=str(info.get("design") or "h2"))
        if procedure.backend.kind != info["backend"]:
            raise InputFormatError(source, "[backend]", f"kind {procedure.backend.kind!r} differs from the run's backend {info['backend']!r}")
    except BaseException:
        journal.close()
        raise
    if info["finished"]:
        journal.close()
        summary = info["summary"] or {}
        if not (run_dir / SUMMARY_FILENAME).exists():
            write_json_atomic(summary, run_dir / SUMMARY_FILENAME)
        console.print(f"{run_dir}: the run is already finished; nothing to do", highlight=False)
        return RunOutcome(run_dir, summary, already_finished=True)
    if info["software_version"] != __version__:
        console.print(
            f"warning: the run was started with setmem-hil {info['software_version']}, this is {__version__}; "
            "the replay stops with an error if the loop now makes different choices",
            highlight=False,
        )
    with run_lock(run_dir, journal):
        stored = journal.n_measurements()
        store = JournalWriter(journal)  # the journal's store: what this session says goes to it as note documents
        store(NOTE, kind="resumed", message=f"resumed with {stored} stored measurements and {len(journal.iterations())} iterations (setmem-hil {__version__})")
        continue_stored = procedure_path is not None or changed is not None
        if procedure_path is not None:
            old_text = changed or info["procedure_text"]
            new_text = procedure.source_text or format_procedure(procedure)
            digest = lambda t: hashlib.sha256(t.encode("utf-8")).hexdigest()[:16]  # noqa: E731
            store(NOTE, kind=PROCEDURE_CHANGED, message=f"procedure replaced by {procedure_path} (sha256 {digest(new_text)}, was "
                                                 f"{digest(old_text)}); the {stored} stored measurements are reused as data\n{new_text}")
            console.print(f"continuing {run_dir} with {procedure_path}: the {stored} stored measurements are reused", highlight=False)
        console.print(f"resuming {run_dir}: {stored} measurements stored, seed {info['seed']}, strategy {info['strategy']}", highlight=False)
        return run_with_journal(procedure, store, run_dir, seed=int(info["seed"]), strategy=str(info["strategy"]), console=console,
                                 opener=opener, display=display, continue_stored=continue_stored, control=control,
                                 observers=observers)
