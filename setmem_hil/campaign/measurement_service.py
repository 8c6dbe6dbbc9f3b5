"""The campaign's commands on the run engine: measurements, replayed or new, and the model hook.

:func:`register_measurements` registers a :class:`MeasurementService` for the campaign's
requests (:mod:`setmem_hil.campaign.messages`):

* **replay** (resume after a stop): whenever the plan needs measurement ``n`` and the run's
  history holds it, the stored one is served (its frequency must match, else
  :class:`~setmem_hil.errors.CampaignReplayError`). Before the first new dwell the experiment's
  ``n_measured`` (if it has one) is set to the number of stored measurements, so the simulated
  noise continues exactly;
* **continuation** with a changed procedure: every stored measurement is the plan's data from
  the start (:class:`~setmem_hil.campaign.messages.Continuation`), nothing is replayed;
* **raw records**: what each new dwell was computed from
  (:class:`~setmem_hil.model.experiment.RawRecordingExperiment`) goes to the subscribers as a
  ``raw-record`` document *before* its measurements' ``measured`` documents, so a store of raw
  records is written before the journal commits the point;
* **the rig's own counts**: after each new dwell (also one that failed), every fault/retry counter
  of the experiment (:class:`~setmem_hil.model.experiment.CountingExperiment`) that rose is a
  ``note`` document of the counter's name (the journal's event of that kind), so the journal is
  written from documents alone (issue 46; a subscriber once read the counters and wrote the journal
  itself).

Documents: ``measure`` (index, total, omega_rad_s, replayed[, record_omegas]), ``raw-record``
(seqs, record), ``measured`` (measurement, seq, iteration, role, replayed), ``note`` (kind: a
counter's name, message).
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from typing import Any, Protocol

from setmem_hil.run.engine import RunEngine
from setmem_hil.campaign.messages import NOTE, Continuation, InformModel, Measure, StoredData
from setmem_hil.errors import CampaignReplayError, DeviceError
from setmem_hil.model.experiment import (
    CountingExperiment,
    Measurement,
    ModelAwareExperiment,
    MultisineExperiment,
    OutputModelsAwareExperiment,
    RawRecordingExperiment,
    ResumableExperiment,
)

__all__ = ["MeasurementService", "RunHistory", "register_measurements", "stored_iterations"]


class RunHistory(Protocol):
    """What the campaign reads of a stopped run (the journal has it)."""

    path: Any

    def measurements(self) -> list[Measurement]: ...

    def measurement_rows(self) -> list[dict]: ...

    def iterations(self) -> list[Any]: ...


def stored_iterations(history: RunHistory | None) -> dict:
    """The stopped run's iterations as the engine's replay keys (``("iteration", k)``), each with
    the choice a replay must repeat."""
    if history is None:
        return {}
    return {("iteration", rec.k): {"next_omega": rec.next_omega} for rec in history.iterations()}


class MeasurementService:
    """Serves the plan's measurements: stored ones first, then new dwells (module docstring).

    ``history``: a stopped run to replay (or, with ``continue_stored``, to continue from);
    ``total``: the number of measurements the progress display counts to."""

    def __init__(self, experiment: Any, *, history: RunHistory | None = None, total: int = 0, continue_stored: bool = False):
        self.experiment, self.total = experiment, total
        self.source = str(getattr(history, "path", "journal"))
        self.stored = history.measurements() if history is not None else []
        self.count = 0  # measurements served so far (stored or new)
        self._synced = False  # the experiment's n_measured set after a replay
        self.continuation = self._continuation(history) if continue_stored and history is not None else None
        self.replayed_before = len(self.stored)
        self._counts = dict(experiment.counters) if isinstance(experiment, CountingExperiment) else {}

    @property
    def replayed(self) -> int:
        """How many stored measurements were served instead of measured again."""
        return min(self.replayed_before, self.count)

    def _continuation(self, history: RunHistory) -> Continuation:
        measured = tuple(self.stored)
        n_added = sum(1 for row in history.measurement_rows() if row["role"] == "added")
        next_k = max((rec.k for rec in history.iterations()), default=0) + 1
        self.count, self.stored, self._synced = len(measured), [], True
        if isinstance(self.experiment, ResumableExperiment):
            self.experiment.n_measured = len(measured)  # simulated noise goes on, never repeats
        return Continuation(measured, n_added, next_k)

    def inform(self, request: InformModel) -> None:
        if isinstance(self.experiment, ModelAwareExperiment):
            self.experiment.update_model(request.model)
        if request.output_models is not None and isinstance(self.experiment, OutputModelsAwareExperiment):
            self.experiment.update_output_models(request.output_models)

    # -- measuring --------------------------------------------------------------------------------
    def measure(self, engine: RunEngine, request: Measure) -> list[Measurement]:
        """Stored points first; the rest one dwell each, or one multisine record for all of them
        (a record with a line missing, a kill while its lines were written, is measured again
        from its first line's index, which reproduces the stored lines exactly)."""
        lines = list(request.omegas_rad_s)
        if not request.record or len(lines) == 1:
            return [self._measure_one(engine, w, request) for w in lines]
        start = self.count
        stored = [self._replayed(engine, w) for w in lines[: max(0, len(self.stored) - start)]]
        if len(stored) == len(lines):
            return stored
        if not isinstance(self.experiment, MultisineExperiment):
            raise DeviceError(f"{type(self.experiment).__name__} cannot measure a multisine record "
                              "([dwell] signal = \"multisine\" needs backend kind 'sim' or 'time-domain')")
        if isinstance(self.experiment, ResumableExperiment):
            self.experiment.n_measured = start  # the record's noise is seeded with its first line's index
        self._synced, self.count = True, start + len(lines)
        engine.emit("measure", index=start + 1, total=self.total, omega_rad_s=lines[0], replayed=False, record_omegas=tuple(lines))
        with self._counted(engine, f"the multisine record of {len(lines)} lines from {lines[0]:.6g} rad/s"):
            record = self.experiment.measure_multisine(lines)
        self._commit(engine, record, start, request, first_new=len(stored))
        return stored + list(record[len(stored):])

    def _measure_one(self, engine: RunEngine, omega_rad_s: float, request: Measure) -> Measurement:
        if self.count < len(self.stored):
            return self._replayed(engine, omega_rad_s)
        if not self._synced:
            if self.stored and isinstance(self.experiment, ResumableExperiment):
                self.experiment.n_measured = len(self.stored)
            self._synced = True
        index = self.count
        self.count += 1
        engine.emit("measure", index=index + 1, total=self.total, omega_rad_s=float(omega_rad_s), replayed=False)
        with self._counted(engine, f"the dwell at {float(omega_rad_s):.6g} rad/s (measurement {index + 1})"):
            m = self.experiment.measure(float(omega_rad_s))
        self._commit(engine, [m], index, request)
        return m

    @contextmanager
    def _counted(self, engine: RunEngine, what: str):
        """Around one dwell: each counter that rose during it, as a ``note`` document (also when the
        dwell raised: the retries before a fault are part of its story)."""
        try:
            yield
        finally:
            if isinstance(self.experiment, CountingExperiment):
                counts = dict(self.experiment.counters)
                for key, value in counts.items():
                    rise = int(value) - int(self._counts.get(key, 0))
                    if rise > 0:
                        engine.emit(NOTE, kind=str(key), message=f"{rise} x {key} (total {value}) during {what}", replayed=False)
                self._counts = counts

    def _replayed(self, engine: RunEngine, omega_rad_s: float) -> Measurement:
        index = self.count
        self.count += 1
        m = self.stored[index]
        if not math.isclose(m.omega_rad_s, omega_rad_s, rel_tol=1e-9, abs_tol=1e-12):
            raise CampaignReplayError(self.source, f"measurement {index + 1}",
                                      f"stored at {m.omega_rad_s:.9g} rad/s but the procedure now asks for {omega_rad_s:.9g} rad/s "
                                      "(different procedure, seed, strategy or software version?)")
        engine.emit("measure", index=index + 1, total=self.total, omega_rad_s=float(omega_rad_s), replayed=True)
        return m

    def _commit(self, engine: RunEngine, measurements: list[Measurement], first_index: int, request: Measure,
                first_new: int = 0) -> None:
        """The dwell's raw records, then each new point: ``seq`` is the point's 1-based index in the
        run (the journal's sequence number)."""
        seqs = tuple(first_index + 1 + i for i in range(len(measurements)))
        if isinstance(self.experiment, RawRecordingExperiment):
            for record in self.experiment.take_raw_records():
                mine = seqs if record.positions is None else tuple(seqs[i] for i in record.positions)
                engine.emit("raw-record", seqs=mine, record=record)
        for m, seq in list(zip(measurements, seqs))[first_new:]:
            engine.emit("measured", measurement=m, seq=seq, iteration=request.iteration, role=request.role, replayed=False)


def register_measurements(engine: RunEngine, service: MeasurementService) -> MeasurementService:
    """The campaign's requests on ``engine``, performed by ``service``."""
    engine.register_command(Measure, lambda e, request: service.measure(e, request))
    engine.register_command(InformModel, lambda e, request: service.inform(request))
    engine.register_command(StoredData, lambda e, request: service.continuation)
    return service
