"""The run's stores as subscribers of the engine (:mod:`setmem_hil.campaign.engine`).

:class:`RawRecordWriter` writes every ``raw-record`` document to ``RUN_DIR/raw.h5``
(:mod:`setmem_hil.io.raw_store`); :class:`JournalWriter` commits every new ``measured``,
``note`` and ``iteration-record`` document to the journal, the run's ``start`` and ``stop`` as
events ``run-start`` and ``run-stop`` (the document as JSON), and finishes it. The engine sends a
dwell's raw records before its points, and both writers are subscribed before any display, so
a point is in the journal only once its record is on disk, and a display or check that reads the
journal sees every document's effect. Replayed documents (a resumed run's stored points and
iterations) are not stored twice.
"""

from __future__ import annotations

import json
from typing import Any

from setmem_hil.campaign.engine import START, STOP
from setmem_hil.campaign.messages import ITERATION_RECORD, NOTE
from setmem_hil.io.journal import IterationRecord, Journal
from setmem_hil.io.raw_store import RawStore

__all__ = ["JournalWriter", "RawRecordWriter"]


class JournalWriter:
    """Commits the run to its journal (every measurement before the next dwell: a durability rule)."""

    def __init__(self, journal: Journal):
        self.journal = journal
        self.already_finished = bool(journal.run_info().get("finished"))

    def __call__(self, event: str, **info: Any) -> None:
        if info.get("replayed"):
            return
        if event == "measured":
            seq = self.journal.add_measurement(info["measurement"], iteration=info["iteration"], role=info["role"])
            if seq != info["seq"]:
                raise RuntimeError(f"{self.journal.path}: measurement stored as seq {seq}, the engine counted {info['seq']}")
        elif event == NOTE:
            self.journal.add_event(info["kind"], info["message"])
        elif event == ITERATION_RECORD:
            self.journal.add_iteration(IterationRecord(**info["fields"]))
        elif event == "finished" and not self.already_finished:
            self.journal.finish(info["summary"].to_document())
        elif event in (START, STOP):  # the run's lifecycle: one event each, the document as JSON
            self.journal.add_event(f"run-{event}", json.dumps(info, sort_keys=True, default=str))


class RawRecordWriter:
    """Writes each dwell's raw record to ``RUN_DIR/raw.h5`` before its points are committed."""

    def __init__(self, run_dir):
        self.store = RawStore(run_dir)

    def __call__(self, event: str, **info: Any) -> None:
        if event == "raw-record":
            self.store.write(tuple(info["seqs"]), info["record"])
