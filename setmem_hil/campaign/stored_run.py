"""A finished (or stopped) run as a Python user sees it, in python-control's types (issue 40).

>>> run = setmem_hil.open_run("runs/beam")                 # doctest: +SKIP
>>> run.measurements.to_frd()                              # control.FrequencyResponseData, rad/s
>>> K = run.controller()                                   # control.StateSpace, continuous, rad/s
>>> run.controller_sign                                    # "positive": u = K y (thesis 6.3.2)
>>> G = run.model().nominal().to_statespace()              # the final interval model's midpoint
>>> T = run.closed_loop()                                  # control.feedback(G, K, sign=+1)

The compensator is **positive feedback** (``u = K y``, thesis 6.3.2 footnote 3): python-control's
``feedback(G, K)`` assumes negative feedback and closes an unstable loop with it; use
:meth:`StoredRun.closed_loop` or ``control.feedback(G, K, sign=+1)``.

Reading only: the journal is opened, read whole and closed (:func:`~setmem_hil.io.journal.read_snapshot`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from setmem_hil.errors import InputFormatError
from setmem_hil.io.journal import JournalSnapshot, read_snapshot
from setmem_hil.io.procedure import Procedure
from setmem_hil.io.procedure_file import parse_procedure_text
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.model.modal_model import IntervalModel

__all__ = ["open_run", "StoredRun", "CONTROLLER_SIGN"]

CONTROLLER_SIGN = "positive"  # u = K y: the sign every compensator of this project has


def open_run(run_dir: str | os.PathLike) -> "StoredRun":
    """The run stored in ``run_dir`` (a directory ``setmem-hil run``, ``campaign`` or ``demo`` wrote)."""
    path = Path(run_dir)
    if not path.is_dir():
        raise InputFormatError(str(path), "", "no such run directory")
    return StoredRun(path, read_snapshot(path))


@dataclass(frozen=True)
class StoredRun:
    """What a run holds: its procedure, measured data, iterations and compensators."""

    directory: Path
    snapshot: JournalSnapshot

    controller_sign = CONTROLLER_SIGN

    @property
    def procedure(self) -> Procedure:
        return parse_procedure_text(self.snapshot.info["procedure_text"], f"{self.directory} (stored procedure)")

    @property
    def output_names(self) -> tuple[str, ...]:
        """The outputs in measurement order (the control output first)."""
        return self.procedure.backend.output_order()

    @property
    def measurements(self) -> FrequencyData:
        """The measured points of the control output in measurement order (``.to_frd()``: the
        python-control view, sorted by frequency)."""
        return FrequencyData.from_measurements(self.snapshot.measurements)

    def output(self, name: str) -> FrequencyData:
        """The measured points of one output (several sensors), by its name."""
        names = self.output_names
        if name not in names:
            raise KeyError(f"{self.directory}: no output {name!r} (outputs: {', '.join(names)})")
        return FrequencyData.from_measurements(self.snapshot.measurements, names.index(name))

    @property
    def iterations(self) -> list:
        return list(self.snapshot.iterations)

    def _iteration(self, k: int | None):
        records = self.snapshot.iterations
        if not records:
            raise InputFormatError(str(self.directory), "", "the run has no iteration yet (no model, no compensator)")
        if k is None:
            return records[-1]
        for record in records:
            if record.k == k:
                return record
        raise InputFormatError(str(self.directory), "", f"iteration {k}: the run holds iterations 1-{records[-1].k}")

    def model(self, iteration: int | None = None) -> IntervalModel:
        """The interval model identified at ``iteration`` (default: the last)."""
        record = self._iteration(iteration)
        return IntervalModel(record.lower, record.upper)

    def controller(self, iteration: int | None = None):
        """The compensator kept at ``iteration`` (default: the last) as a continuous-time
        ``control.StateSpace`` in rad/s; positive feedback (:attr:`controller_sign`)."""
        from setmem_hil.campaign.compensator import kept_controller

        _, K = kept_controller(str(self.directory), iteration, command="setmem_hil.open_run(...).controller")
        return K

    def closed_loop(self, iteration: int | None = None):
        """The nominal loop of ``iteration``: the interval model's midpoint under its kept
        compensator, closed with the right sign (``control.feedback(G, K, sign=+1)``: from a
        disturbance at the plant input to the measured output)."""
        import control

        G = self.model(iteration).nominal().to_statespace()
        return control.feedback(G, self.controller(iteration), sign=+1)
