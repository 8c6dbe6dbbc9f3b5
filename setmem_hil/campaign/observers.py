"""Subscribers of the campaign runner (Bluesky-style ``RunEngine.subscribe``).

:func:`setmem_hil.campaign.runner.run_campaign` calls every subscriber as
``subscriber(event, **info)`` with the events documented there (``"measure"``,
``"iteration"``, ``"chosen"``, ``"finished"``). The journal itself is written by the runner's
stores (:mod:`setmem_hil.campaign.persistence`: every measurement before the next dwell, a
durability rule, not an option); the subscribers here add what every campaign of a procedure
gets, whoever starts it (``run``, ``demo``, ``campaign`` and the sweep task all go through
:func:`standard_observers`):

* :class:`DiscrepancyChecker`: ``[discrepancy] check_each_iteration = true``, the discrepancy
  check of every new iteration, computed from its documents alone and stored in the journal (a
  derived product with a store of its own, as the raw records have theirs).

The experiment's fault/retry counters are ``note`` documents of the measurement service
(:mod:`setmem_hil.campaign.measurement_service`). Terminal progress and the live view are
further subscribers their callers add.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

from setmem_hil.campaign.messages import ITERATION_RECORD, NOTE
from setmem_hil.campaign.persistence import JournalWriter
from setmem_hil.errors import SetmemError
from setmem_hil.io.procedure import Procedure

Observer = Callable[..., None]

__all__ = ["Observer", "DiscrepancyChecker", "broadcast", "standard_observers"]


class DiscrepancyChecker:
    """``[discrepancy] check_each_iteration``: with each new iteration's record, run the discrepancy
    workflow (:func:`setmem_hil.discrepancy.workflow.check_discrepancy`) on the data the iteration
    identified from and the bounds it found (its ``iteration`` document), and store the result. It
    reads documents only and only observes: the campaign's choices do not depend on it, so a
    replayed run is unchanged; replayed iterations were checked when they ran."""

    def __init__(self, procedure: Procedure, store: JournalWriter):
        self.procedure, self.store = procedure, store  # the run's journal exists once the run has started
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
            self.store(NOTE, kind="discrepancy-error", message=f"iteration {k}: {type(exc).__name__}: {exc}")
        else:
            self.store.journal.add_discrepancy(k, report)


def broadcast(observers: Sequence[Observer]) -> Observer:
    """One callable that forwards every event to each observer in order."""
    observers = tuple(observers)

    def call(event: str, **info: Any) -> None:
        for observer in observers:
            observer(event, **info)

    return call


def standard_observers(procedure: Procedure, store: JournalWriter) -> list[Observer]:
    """The subscribers every journaled campaign of ``procedure`` gets (see the module docstring);
    ``store`` writes the run's journal."""
    return [DiscrepancyChecker(procedure, store)] if procedure.discrepancy_check else []
