"""Subscribers of the campaign runner (Bluesky-style ``RunEngine.subscribe``).

:func:`setmem_hil.campaign.runner.run_campaign` calls every subscriber as
``subscriber(event, **info)`` with the events documented there (``"measure"``,
``"iteration"``, ``"chosen"``, ``"finished"``). The journal itself is written by the runner
(every measurement before the next dwell: that is a durability rule, not an option); these
subscribers add what every campaign of a procedure gets, whoever starts it (``run``, ``demo``,
``campaign`` and the sweep task all go through :func:`standard_observers`):

* :class:`CounterLogger`: the experiment's fault/retry counters, journaled as events;
* :class:`DiscrepancyChecker`: ``[discrepancy] check_each_iteration = true``, the discrepancy
  check of every new iteration (from its documents), stored in the journal.

Terminal progress and the live view are further subscribers their callers add.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

from setmem_hil.campaign.messages import ITERATION_RECORD
from setmem_hil.errors import SetmemError
from setmem_hil.io.journal import Journal
from setmem_hil.io.procedure import Procedure
from setmem_hil.model.experiment import CountingExperiment

Observer = Callable[..., None]

__all__ = ["Observer", "CounterLogger", "DiscrepancyChecker", "broadcast", "standard_observers"]


class CounterLogger:
    """Logs increases of the experiment's fault/retry counters to the journal as events."""

    def __init__(self, experiment: Any, journal: Journal):
        self.experiment, self.journal = experiment, journal
        self.seen = dict(experiment.counters) if isinstance(experiment, CountingExperiment) else {}

    def __call__(self, event: str, **info: Any) -> None:
        if not isinstance(self.experiment, CountingExperiment):
            return
        counters = dict(self.experiment.counters)
        for key, value in counters.items():
            delta = int(value) - int(self.seen.get(key, 0))
            if delta > 0:
                self.journal.add_event(str(key), f"{delta} x {key} (total {value}) before event {event!r}")
        self.seen = counters


class DiscrepancyChecker:
    """``[discrepancy] check_each_iteration``: with each new iteration's record, run the discrepancy
    workflow (:func:`setmem_hil.discrepancy.workflow.check_discrepancy`) on the data the iteration
    identified from and the bounds it found (its ``iteration`` document), and store the result. It
    reads documents only and only observes: the campaign's choices do not depend on it, so a
    replayed run is unchanged; replayed iterations were checked when they ran."""

    def __init__(self, procedure: Procedure, journal: Journal):
        self.procedure, self.journal = procedure, journal
        self._iteration: dict | None = None

    def __call__(self, event: str, **info: Any) -> None:
        if event == "iteration":
            self._iteration = info
        if event != ITERATION_RECORD or info.get("replayed") or self._iteration is None:
            return
        from setmem_hil.discrepancy.workflow import check_discrepancy
        from setmem_hil.model.modal_model import IntervalModel

        k, plant = int(self._iteration["k"]), self._iteration["plant"]
        try:
            report = check_discrepancy(self._iteration["data"], IntervalModel(plant.lower, plant.upper), self.procedure.prior).to_document()
        except (SetmemError, ValueError, ArithmeticError) as exc:  # a failed check must not stop the campaign
            self.journal.add_event("discrepancy-error", f"iteration {k}: {type(exc).__name__}: {exc}")
        else:
            self.journal.add_discrepancy(k, report)


def broadcast(observers: Sequence[Observer]) -> Observer:
    """One callable that forwards every event to each observer in order."""
    observers = tuple(observers)

    def call(event: str, **info: Any) -> None:
        for observer in observers:
            observer(event, **info)

    return call


def standard_observers(procedure: Procedure, experiment: Any, journal: Journal) -> list[Observer]:
    """The subscribers every journaled campaign of ``procedure`` gets (see the module docstring)."""
    observers: list[Observer] = [CounterLogger(experiment, journal)]
    if procedure.discrepancy_check:
        observers.append(DiscrepancyChecker(procedure, journal))
    return observers
