"""The run engine: performs a plan's requests against an experiment (Bluesky's RunEngine).

A plan (:mod:`setmem_hil.campaign.plan`) says what to measure and what it found; the engine
owns how a run goes, whichever plan it runs:

* **replay** (resume after a stop): whenever the plan needs measurement ``n`` and the run's
  history holds it, the stored one is served (its frequency must match, else
  :class:`~setmem_hil.errors.CampaignReplayError`); an iteration the history holds is checked
  against it (the same next frequency) and its documents are marked ``replayed`` so the journal
  does not store them twice. Before the first new dwell the experiment's ``n_measured`` (if it
  has one) is set to the number of stored measurements, so the simulated noise continues
  exactly;
* **continuation** with a changed procedure: every stored measurement is the plan's data from
  the start (:class:`~setmem_hil.campaign.messages.Continuation`), nothing is replayed;
* **pause and abort**: ``control.checkpoint`` before every new dwell (the live view); a pause
  holds with every exciter output confirmed off and is reported (``paused`` / ``unpaused``);
* **raw records**: what each new dwell was computed from
  (:class:`~setmem_hil.model.experiment.RawRecordingExperiment`) goes to the subscribers as a
  ``raw-record`` document *before* its measurements' ``measured`` documents, so a store of raw
  records is written before the journal commits the point.

Subscribers are called in order as ``subscriber(name, **info)``; the stores (raw records,
journal) come first so that displays and checks that read them see every document's effect.
Documents: ``measure`` (index, total, omega_rad_s, replayed[, record_omegas]), ``raw-record``
(seqs, record), ``measured`` (measurement, seq, iteration, role, replayed), ``note`` (kind,
message, replayed), ``iteration-record`` (fields, replayed), ``finished`` (summary) and whatever
else the plan emits (``iteration``, ``left-out``, ``chosen``).
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, Callable, Generator, Protocol, Sequence

from setmem_hil.campaign.messages import ITERATION_RECORD, NOTE, Continuation, Emit, InformModel, Measure, StoredData
from setmem_hil.errors import CampaignReplayError, DeviceError
from setmem_hil.model.experiment import (
    Measurement,
    ModelAwareExperiment,
    MultisineExperiment,
    OutputConfirmingExperiment,
    OutputModelsAwareExperiment,
    RawRecordingExperiment,
    ResumableExperiment,
)

__all__ = ["RunEngine", "RunHistory", "Subscriber"]

Subscriber = Callable[..., None]


class RunHistory(Protocol):
    """What the engine reads of a stopped run (the journal has it)."""

    path: Any

    def measurements(self) -> list[Measurement]: ...

    def measurement_rows(self) -> list[dict]: ...

    def iterations(self) -> list[Any]: ...


class RunEngine:
    """Runs plans on ``experiment`` (see the module docstring).

    ``history``: a stopped run to replay (or, with ``continue_stored``, to continue from);
    ``total``: the number of measurements the progress display counts to; ``control``: the
    live view's pause/abort (``checkpoint(make_safe)``).
    """

    def __init__(self, experiment: Any, subscribers: Sequence[Subscriber] = (), *, history: RunHistory | None = None,
                 control=None, total: int = 0, continue_stored: bool = False):
        self.experiment, self.control, self.total = experiment, control, total
        self.subscribers = tuple(subscribers)
        self.source = str(getattr(history, "path", "journal"))
        self.stored = history.measurements() if history is not None else []
        self.stored_iterations = {rec.k: rec for rec in history.iterations()} if history is not None else {}
        self.count = 0  # measurements served so far (stored or new)
        self._synced = False  # the experiment's n_measured set after a replay
        self.continuation = self._continuation(history) if continue_stored and history is not None else None
        self.replayed_before = len(self.stored)

    def _continuation(self, history: RunHistory) -> Continuation:
        measured = tuple(self.stored)
        n_added = sum(1 for row in history.measurement_rows() if row["role"] == "added")
        next_k = max(self.stored_iterations, default=0) + 1
        self.count, self.stored, self.stored_iterations, self._synced = len(measured), [], {}, True
        if isinstance(self.experiment, ResumableExperiment):
            self.experiment.n_measured = len(measured)  # simulated noise goes on, never repeats
        return Continuation(measured, n_added, next_k)

    # -- running a plan ---------------------------------------------------------------------------
    def run(self, plan: Generator) -> Any:
        """Perform every request of ``plan``; its return value (a summary dataclass gets the
        engine's ``replayed_measurements``) is sent as the ``finished`` document and returned."""
        reply = None
        while True:
            try:
                request = plan.send(reply)
            except StopIteration as done:
                return self._finished(done.value)
            reply = self._perform(request)

    def _finished(self, result: Any) -> Any:
        if dataclasses.is_dataclass(result) and any(f.name == "replayed_measurements" for f in dataclasses.fields(result)):
            result = dataclasses.replace(result, replayed_measurements=min(self.replayed_before, self.count))
        self.emit("finished", summary=result)
        return result

    def _perform(self, request: Any) -> Any:
        if isinstance(request, Measure):
            return self.measure(request)
        if isinstance(request, Emit):
            return self._emit_document(request)
        if isinstance(request, InformModel):
            return self._inform(request)
        if isinstance(request, StoredData):
            return self.continuation
        raise TypeError(f"the run engine cannot perform {request!r}")

    def emit(self, name: str, **info: Any) -> None:
        for subscriber in self.subscribers:
            subscriber(name, **info)

    def _emit_document(self, request: Emit) -> None:
        info = dict(request.info)
        if request.name in (NOTE, ITERATION_RECORD):
            info["replayed"] = request.iteration in self.stored_iterations
        if request.name == ITERATION_RECORD and info["replayed"]:
            self._check_replayed_choice(request.iteration, info["fields"].get("next_omega"))
        self.emit(request.name, **info)

    def _check_replayed_choice(self, k: int, next_omega: float | None) -> None:
        stored = self.stored_iterations[k].next_omega
        if not _same_choice(stored, next_omega):
            raise CampaignReplayError(self.source, f"iteration {k}",
                                      f"stored next frequency {stored} rad/s but the replay chose {next_omega} rad/s")

    def _inform(self, request: InformModel) -> None:
        if isinstance(self.experiment, ModelAwareExperiment):
            self.experiment.update_model(request.model)
        if request.output_models is not None and isinstance(self.experiment, OutputModelsAwareExperiment):
            self.experiment.update_output_models(request.output_models)

    # -- measuring --------------------------------------------------------------------------------
    def measure(self, request: Measure) -> list[Measurement]:
        """Stored points first; the rest one dwell each, or one multisine record for all of them
        (a record with a line missing, a kill while its lines were written, is measured again
        from its first line's index, which reproduces the stored lines exactly)."""
        lines = list(request.omegas_rad_s)
        if not request.record or len(lines) == 1:
            return [self._measure_one(w, request) for w in lines]
        start = self.count
        stored = [self._replayed(w, request) for w in lines[: max(0, len(self.stored) - start)]]
        if len(stored) == len(lines):
            return stored
        if not isinstance(self.experiment, MultisineExperiment):
            raise DeviceError(f"{type(self.experiment).__name__} cannot measure a multisine record "
                              "([dwell] signal = \"multisine\" needs backend kind 'sim' or 'time-domain')")
        self._checkpoint()
        if isinstance(self.experiment, ResumableExperiment):
            self.experiment.n_measured = start  # the record's noise is seeded with its first line's index
        self._synced, self.count = True, start + len(lines)
        self.emit("measure", index=start + 1, total=self.total, omega_rad_s=lines[0], replayed=False, record_omegas=tuple(lines))
        record = self.experiment.measure_multisine(lines)
        self._commit(record, start, request, first_new=len(stored))
        return stored + list(record[len(stored):])

    def _measure_one(self, omega_rad_s: float, request: Measure) -> Measurement:
        if self.count < len(self.stored):
            return self._replayed(omega_rad_s, request)
        self._checkpoint()  # between dwells: may wait (paused) or raise CampaignAborted
        if not self._synced:
            if self.stored and isinstance(self.experiment, ResumableExperiment):
                self.experiment.n_measured = len(self.stored)
            self._synced = True
        index = self.count
        self.count += 1
        self.emit("measure", index=index + 1, total=self.total, omega_rad_s=float(omega_rad_s), replayed=False)
        m = self.experiment.measure(float(omega_rad_s))
        self._commit([m], index, request)
        return m

    def _replayed(self, omega_rad_s: float, request: Measure) -> Measurement:
        index = self.count
        self.count += 1
        m = self.stored[index]
        if not math.isclose(m.omega_rad_s, omega_rad_s, rel_tol=1e-9, abs_tol=1e-12):
            raise CampaignReplayError(self.source, f"measurement {index + 1}",
                                      f"stored at {m.omega_rad_s:.9g} rad/s but the procedure now asks for {omega_rad_s:.9g} rad/s "
                                      "(different procedure, seed, strategy or software version?)")
        self.emit("measure", index=index + 1, total=self.total, omega_rad_s=float(omega_rad_s), replayed=True)
        return m

    def _commit(self, measurements: list[Measurement], first_index: int, request: Measure, first_new: int = 0) -> None:
        """The dwell's raw records, then each new point: ``seq`` is the point's 1-based index in the
        run (the journal's sequence number)."""
        seqs = tuple(first_index + 1 + i for i in range(len(measurements)))
        if isinstance(self.experiment, RawRecordingExperiment):
            for record in self.experiment.take_raw_records():
                mine = seqs if record.positions is None else tuple(seqs[i] for i in record.positions)
                self.emit("raw-record", seqs=mine, record=record)
        for m, seq in list(zip(measurements, seqs))[first_new:]:
            self.emit("measured", measurement=m, seq=seq, iteration=request.iteration, role=request.role, replayed=False)

    # -- pause ------------------------------------------------------------------------------------
    def _checkpoint(self) -> None:
        """The live view's checkpoint between dwells; a pause is reported when it holds (the
        outputs confirmed off) and when it ends, each with its time (issue 39, item 4)."""
        if self.control is None:
            return
        held_since = []

        def safe_and_reported() -> None:
            if isinstance(self.experiment, OutputConfirmingExperiment):
                self.experiment.confirm_output_off()
            held_since.append(time.monotonic())
            self.emit(NOTE, kind="paused", message=f"paused before measurement {self.count + 1}: every exciter output confirmed off",
                      replayed=False)

        self.control.checkpoint(safe_and_reported)  # may wait (paused) or raise CampaignAborted
        if held_since:
            self.emit(NOTE, kind="unpaused", message=f"went on after {time.monotonic() - held_since[0]:.1f} s paused", replayed=False)


def _same_choice(a: float | None, b: float | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12)
