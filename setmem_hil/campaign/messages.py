"""The campaign's requests to the run engine (Bluesky's split of plans and the RunEngine).

A plan is a generator: it ``yield``\\ s a request and receives the engine's reply as the value of
the ``yield`` expression. The plan decides *what* to do; the engine
(:class:`setmem_hil.run.engine.RunEngine`) performs it: its own requests (:class:`Emit`,
:class:`Checkpoint`) and the campaign's, registered by
:func:`setmem_hil.campaign.measurement_service.register_measurements` (a stored measurement or a
new dwell, the raw records and the journal behind it).

========================  ================================================  ==========================
request                   what the engine does                              reply
========================  ================================================  ==========================
:class:`StoredData`       hands over the data a continued run starts from   :class:`Continuation`/None
:class:`Measure`          takes the points (replayed, or dwells)            ``list[Measurement]``
:class:`InformModel`      gives the experiment the latest interval models   None
:class:`Emit`             sends a document to every subscriber              None
:class:`Checkpoint`       a pause point (the live view's pause and abort)   None
========================  ================================================  ==========================
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from setmem_hil.run.engine import NOTE, Checkpoint, Emit
from setmem_hil.model.experiment import Measurement

__all__ = ["Checkpoint", "Continuation", "Emit", "InformModel", "Measure", "StoredData", "ITERATION_RECORD", "NOTE"]

ITERATION_RECORD = "iteration-record"
"""Document: one iteration's choice (``k``, ``choice``: the ``InputChoice`` or None at the last
iteration), after its ``iteration`` document; the journal's ``IterationRecord`` is laid out from
the two by :func:`setmem_hil.campaign.persistence.iteration_fields`. The engine compares a
replayed iteration's choice with the stored one."""



@dataclass(frozen=True)
class Measure:
    """Measure these frequencies, one after the other or (``record``) in one multisine record."""

    omegas_rad_s: tuple[float, ...]
    iteration: int
    role: str  # "initial" or "added"
    record: bool = False


@dataclass(frozen=True)
class StoredData:
    """Ask for the data of a run continued with a changed procedure (None: start afresh)."""


@dataclass(frozen=True)
class Continuation:
    """A stopped run's data, reused from the start (``run --resume DIR --procedure FILE``)."""

    measured: tuple[Measurement, ...]
    n_added: int
    next_iteration: int


@dataclass(frozen=True)
class InformModel:
    """The iteration's interval model (and every output's, several sensors) for the experiment's
    later dwells (transient poles, waits, allowances)."""

    model: Any
    output_models: Any = None
