"""The run's stores as subscribers of the engine (:mod:`setmem_hil.run.engine`).

:class:`RawRecordWriter` writes every ``raw-record`` document to ``RUN_DIR/raw.h5``
(:mod:`setmem_hil.io.raw_store`); :class:`JournalWriter` writes the journal from the documents
alone: a new journal's header from the run's ``start`` document, every new ``measured`` and
``note`` document, each iteration (its ``iteration`` document and its choice, the
``iteration-record`` document, laid out as the journal's ``IterationRecord`` here, by
:func:`iteration_fields`), the run's ``start`` and ``stop`` as events ``run-start`` and
``run-stop`` (the document as JSON), and finishes it. :class:`IterationClock` times each
iteration from the engine's plan clock (the plan holds no clock). The engine sends a
dwell's raw records before its points, and both writers are subscribed before any display, so
a point is in the journal only once its record is on disk, and a display or check that reads the
journal sees every document's effect. Replayed documents (a resumed run's stored points and
iterations) are not stored twice.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from setmem_hil.run.engine import START, STOP
from setmem_hil.campaign.messages import ITERATION_RECORD, NOTE
from setmem_hil.io.journal import IterationRecord, Journal, journal_path
from setmem_hil.io.raw_store import RawStore

__all__ = ["IterationClock", "JournalWriter", "RawRecordWriter", "iteration_fields"]


class IterationClock:
    """The plan's computation per iteration (wall and CPU seconds): how far the engine's plan clock
    (``plan_s``, ``plan_cpu_s`` on every document) advanced from the previous iteration's record
    to this one's: identification, design, analysis and the input choice (the dwells, which the
    engine performs, are not counted). Replayed iterations are clocked too, so a resumed run's
    first new iteration does not include the replay."""

    def __init__(self):
        self.mark = (0.0, 0.0)
        self.by_iteration: dict[int, tuple[float, float]] = {}

    def __call__(self, event: str, **info: Any) -> None:
        if event == ITERATION_RECORD:
            now = (float(info["plan_s"]), float(info["plan_cpu_s"]))
            self.by_iteration[int(info["k"])] = (now[0] - self.mark[0], now[1] - self.mark[1])
            self.mark = now


def iteration_fields(iteration: dict, choice: Any, wall_s: float) -> dict:
    """The journal's ``IterationRecord`` fields from an ``iteration`` document and its choice
    (:class:`~setmem_hil.design.input_design.InputChoice`, or None at the last iteration)."""
    from setmem_hil.campaign.loop_steps import controller_matrices  # the loop's numerics: loaded once the run has started

    model, analysis, result, plant, gain = (iteration[name] for name in ("model", "analysis", "identification", "plant", "gain"))
    return dict(
        k=int(iteration["k"]), n_points=int(iteration["n_points"]), lower=plant.lower, upper=plant.upper,
        mu_peak=float(iteration["mu_peak"]), mu_peak_omega=float(analysis.mu_peak_omega), mu_lower_peak=float(analysis.mu_lower_peak),
        omega=np.asarray(analysis.omega, dtype=float), mu=np.asarray(analysis.mu, dtype=float),
        sensitivities={str(key): float(v) for key, v in analysis.sensitivities.items()},
        next_omega=None if choice is None else choice.next_omega_rad_s,
        candidate_omega=np.zeros(0) if choice is None else choice.candidate_omega_rad_s,
        estimated_improvement=np.zeros(0) if choice is None else choice.estimated_improvement,
        controller_order=int(analysis.controller_order), safeguard=iteration["safeguard"], wall_s=float(wall_s),
        embedding_gamma=np.asarray(result.embedding_gamma, dtype=float), mismatch_ratio=np.asarray(result.mismatch_ratio, dtype=float),
        controller=controller_matrices(analysis.controller), mu_peak_certified=bool(iteration["mu_peak_certified"]),
        mu_certified_intervals=int(getattr(analysis, "mu_certified_intervals", 0)), outputs=iteration["outputs"],
        common_gain=None if gain is None else {"gain": list(gain), "lower": model.lower.tolist(), "upper": model.upper.tolist()},
        design=iteration["design"], floor_modes=tuple(iteration["floor_modes"]),
        groups=tuple(tuple(int(m) for m in group) for group in getattr(result, "groups", ()) or ()),
    )


class JournalWriter:
    """Commits the run to its journal from the documents alone (every measurement before the next
    dwell: a durability rule).

    ``journal``: an open :class:`Journal` (a resumed run: its header stays), or the path of a new
    one, which is created from the run's ``start`` document: the procedure's text and name, the
    backend, strategy and design (the plan's arguments), the seed and the software version. A
    ``note`` sent before the ``start`` (the rig's identities, the exciter armed) is kept and
    written right after the header, so the journal reads in the order things happened; the
    session's closing notes (why it stopped, the output confirmed off) may follow the ``stop``.
    The caller closes the journal (:meth:`close`). ``clock`` times the iterations (an
    :class:`IterationClock` the writer feeds every document; the runner reads it for the summary)."""

    def __init__(self, journal: Journal | str | os.PathLike):
        self.journal: Journal | None = journal if isinstance(journal, Journal) else None
        self.path = self.journal.path if self.journal is not None else journal_path(journal)
        self.already_finished = self.journal is not None and bool(self.journal.run_info().get("finished"))
        self.clock = IterationClock()
        self._iteration: dict | None = None
        self._early_notes: list[tuple[str, str]] = []

    @property
    def run_dir(self) -> Path:
        return Path(self.path).parent

    def close(self) -> None:
        if self.journal is not None and not self.journal.closed:
            self.journal.close()

    def __call__(self, event: str, **info: Any) -> None:
        if event == "iteration":
            self._iteration = info  # stored with its choice
        self.clock(event, **info)
        if info.get("replayed"):
            return
        if event == START:
            self._start(info)
        elif event == NOTE and self.journal is None:
            self._early_notes.append((info["kind"], info["message"]))
        elif event == NOTE:
            self.journal.add_event(info["kind"], info["message"])
        elif event == "measured":
            seq = self.journal.add_measurement(info["measurement"], iteration=info["iteration"], role=info["role"])
            if seq != info["seq"]:
                raise RuntimeError(f"{self.journal.path}: measurement stored as seq {seq}, the engine counted {info['seq']}")
        elif event == ITERATION_RECORD:
            if self._iteration is None or int(self._iteration["k"]) != int(info["k"]):
                raise RuntimeError(f"{self.journal.path}: iteration {info['k']}'s choice came without its iteration document")
            wall_s = self.clock.by_iteration.get(int(info["k"]), (0.0, 0.0))[0]
            self.journal.add_iteration(IterationRecord(**iteration_fields(self._iteration, info["choice"], wall_s)))
        elif event == "finished" and not self.already_finished:
            self.journal.finish(info["summary"].to_document())
        elif event == STOP:
            self.journal.add_event("run-stop", json.dumps(info, sort_keys=True, default=str))

    def _start(self, info: dict) -> None:
        """The header of a new journal from the ``start`` document, the notes sent before it, then
        the ``run-start`` event (the document as JSON, the procedure's text by its SHA-256: the
        header holds the text)."""
        arguments = json.loads(info.get("arguments") or "{}")
        if self.journal is None:
            self.journal = Journal.create(self.path, procedure_text=str(arguments.get("procedure_text", "")),
                                          procedure_name=str(arguments.get("procedure", "")), seed=int(info["seed"]),
                                          software_version=str(info["version"]), backend=str(arguments.get("backend", "")),
                                          strategy=str(arguments.get("strategy", "")), design=str(arguments.get("design", "h2")))
        for kind, message in self._early_notes:
            self.journal.add_event(kind, message)
        self._early_notes.clear()
        if "procedure_text" in arguments:
            text = str(arguments.pop("procedure_text"))
            arguments["procedure_sha256"] = hashlib.sha256(text.encode("utf-8")).hexdigest()
        document = dict(info, arguments=json.dumps(arguments, sort_keys=True, default=str))
        self.journal.add_event("run-start", json.dumps(document, sort_keys=True, default=str))


class RawRecordWriter:
    """Writes each dwell's raw record to ``RUN_DIR/raw.h5`` before its points are committed."""

    def __init__(self, run_dir):
        self.store = RawStore(run_dir)

    def __call__(self, event: str, **info: Any) -> None:
        if event == "raw-record":
            self.store.write(tuple(info["seqs"]), info["record"])
