"""The messages a plan yields to the engine (Bluesky's split of plans and the RunEngine).

A plan is a generator: it ``yield``\\ s a request and receives the engine's reply as the value of
the ``yield`` expression. The plan decides *what* to do; the engine
(:class:`setmem_hil.campaign.engine.RunEngine`) decides *how*: a stored measurement or a new
dwell, a pause before it, the raw records and the journal behind it.

========================  ================================================  ==========================
request                   what the engine does                              reply
========================  ================================================  ==========================
:class:`StoredData`       hands over the data a continued run starts from   :class:`Continuation`/None
:class:`Measure`          takes the points (replayed, or dwells)            ``list[Measurement]``
:class:`InformModel`      gives the experiment the latest interval models   None
:class:`Emit`             sends a document to every subscriber              None
========================  ================================================  ==========================
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from setmem_hil.model.experiment import Measurement

__all__ = ["Continuation", "Emit", "InformModel", "Measure", "StoredData", "ITERATION_RECORD", "NOTE"]

ITERATION_RECORD = "iteration-record"
"""Document: one iteration's stored result (``fields``: the journal's ``IterationRecord``); the
engine compares a replayed iteration's choice with the stored one."""

NOTE = "note"
"""Document: a journal event (``kind``, ``message``) of iteration ``k`` (None: of the run)."""


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


@dataclass(frozen=True)
class Emit:
    """A document for the subscribers: ``subscriber(name, **info)``; ``iteration`` tells the
    engine which iteration it belongs to (a replayed iteration's documents are marked so)."""

    name: str
    info: dict = field(default_factory=dict)
    iteration: int | None = None
