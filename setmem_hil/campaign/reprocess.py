"""Re-process a run: recompute every measurement from its raw record (``RUN_DIR/raw.h5``) with
the stored settings, and compare with the journal (issue 39; ``setmem-hil reprocess``).

A point agrees when its frequency is the stored one and its response and bound (every output's)
are within a relative ``1e-9`` of the stored ones. The report lists every measurement; the
first that differs is named by its journal ``seq``. Every committed measurement must have a
record; a record whose points were never committed (a run killed between the two writes) is
reported and not compared.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

from setmem_hil.errors import DataQualityError, InputFormatError, SetmemError
from setmem_hil.estimation.reprocessing import points_from_record
from setmem_hil.io.journal import read_snapshot
from setmem_hil.io.raw_store import RAW_INDEX, iter_raw_records
from setmem_hil.model.experiment import Measurement

__all__ = ["RELATIVE_TOLERANCE", "ReprocessReport", "reprocess_run"]

RELATIVE_TOLERANCE = 1e-9


@dataclass
class ReprocessReport:
    """What :func:`reprocess_run` found; :meth:`to_document` is ``--out``'s JSON."""

    run_dir: str
    measurements: list[dict] = field(default_factory=list)
    records: int = 0
    uncommitted: list[int] = field(default_factory=list)

    @property
    def first_difference(self) -> dict | None:
        return next((m for m in self.measurements if not m["agrees"]), None)

    @property
    def largest_relative_difference(self) -> float:
        return max((m["relative_difference"] for m in self.measurements if m["agrees"]), default=0.0)

    def to_document(self) -> dict:
        first = self.first_difference
        return {"run_dir": self.run_dir, "raw_index": str(Path(self.run_dir) / RAW_INDEX), "records": self.records,
                "agree": first is None, "first_difference_seq": None if first is None else first["seq"],
                "tolerance_relative": RELATIVE_TOLERANCE, "largest_relative_difference": self.largest_relative_difference,
                "uncommitted_seqs": self.uncommitted, "measurements": self.measurements}


def reprocess_run(run_dir: str | os.PathLike) -> ReprocessReport:
    """Recompute every stored measurement of ``run_dir`` (see the module docstring).

    Raises :class:`~setmem_hil.errors.InputFormatError` when the raw records are missing (no
    ``raw.h5``, or a committed measurement without its record)."""
    snapshot = read_snapshot(run_dir)
    stored = {int(row["seq"]): m for row, m in zip(snapshot.rows, snapshot.measurements)}
    report = ReprocessReport(str(run_dir))
    covered: set[int] = set()
    for item in iter_raw_records(run_dir):
        report.records += 1
        try:
            points, problem = points_from_record(item.record), None
        except (DataQualityError, SetmemError, ValueError, ArithmeticError) as exc:
            points, problem = [None] * len(item.seqs), f"cannot be recomputed: {exc}"
        for seq, point in zip(item.seqs, points):
            if seq not in stored:
                report.uncommitted.append(seq)
                continue
            covered.add(seq)
            report.measurements.append(_compared(seq, stored[seq], point, problem))
    missing = sorted(set(stored) - covered)
    if missing:
        raise InputFormatError(str(Path(run_dir) / RAW_INDEX), "/measurements",
                               f"no raw record for measurement{'s' if len(missing) > 1 else ''} {_seq_list(missing)}")
    report.measurements.sort(key=lambda m: m["seq"])
    return report


def _compared(seq: int, stored: Measurement, point: Measurement | None, problem: str | None) -> dict:
    entry = {"seq": seq, "omega_rad_s": stored.omega_rad_s, "stored": _point_document(stored)}
    if point is None:
        return {**entry, "agrees": False, "relative_difference": math.inf, "problem": problem}
    entry["recomputed"] = _point_document(point)
    difference = _relative_difference(stored, point)
    agrees = difference <= RELATIVE_TOLERANCE
    problem = None if agrees else (f"recomputed point differs from the journal's (relative difference {difference:.3g} > "
                                   f"{RELATIVE_TOLERANCE:g})")
    return {**entry, "agrees": agrees, "relative_difference": difference, "problem": problem}


def _relative_difference(a: Measurement, b: Measurement) -> float:
    """The largest relative difference of the frequency, every output's response and bound."""
    if len(a.others) != len(b.others):
        return math.inf
    pairs = [(a.omega_rad_s, b.omega_rad_s), (a.response, b.response), (a.bound, b.bound)]
    pairs += [pair for (ga, ba), (gb, bb) in zip(a.others, b.others) for pair in ((ga, gb), (ba, bb))]
    worst = 0.0
    for x, y in pairs:
        scale = max(abs(x), abs(y))
        gap = abs(x - y)
        worst = max(worst, 0.0 if gap == 0 else (math.inf if scale == 0 or not math.isfinite(gap) else gap / scale))
    return worst


def _point_document(m: Measurement) -> dict:
    return {"re": m.response.real, "im": m.response.imag, "bound": m.bound,
            "others": [{"re": g.real, "im": g.imag, "bound": b} for g, b in m.others]}


def _seq_list(seqs: list[int]) -> str:
    shown = ", ".join(str(s) for s in seqs[:10])
    return shown + (f" and {len(seqs) - 10} more" if len(seqs) > 10 else "")
