"""The run engine (issue 39): replay, resume, continuation, pause, abort and a dwell failing
mid-record, on toy plans and experiments whose every call is counted (the truth is what each
test's experiment was asked and what its history holds), plus the structure rules of the
campaign package: no function longer than 80 lines, and the loop's module imports neither the
journal nor the live view."""

from __future__ import annotations

import ast
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from setmem_hil.campaign.engine import RunEngine
from setmem_hil.campaign.messages import ITERATION_RECORD, NOTE, Emit, InformModel, Measure, StoredData
from setmem_hil.campaign.persistence import JournalWriter, RawRecordWriter
from setmem_hil.errors import CampaignAborted, CampaignReplayError, DeviceError
from setmem_hil.io.journal import Journal
from setmem_hil.model.experiment import Measurement, RawRecord

CAMPAIGN = Path(__file__).resolve().parents[1] / "setmem_hil" / "campaign"


def point(w: float) -> Measurement:
    return Measurement(w, complex(1.0 / w, -w), 0.01 * w)


class CountingRig:
    """Measures ``point(w)``; remembers every call; keeps a raw record per dwell."""

    def __init__(self, fail_record_at: int | None = None):
        self.n_measured = 0
        self.asked: list = []
        self.models: list = []
        self.confirmed_off = 0
        self.output_confirmed_off, self.exciter = True, "toy generator"
        self.fail_record_at = fail_record_at
        self._raw: list[RawRecord] = []

    def measure(self, w):
        self.asked.append(("measure", w, self.n_measured))
        self.n_measured += 1
        self._raw.append(RawRecord("toy", {"w": np.array([w])}))
        return point(w)

    def measure_multisine(self, lines):
        self.asked.append(("record", tuple(lines), self.n_measured))
        if self.fail_record_at is not None and len(self.asked) == self.fail_record_at:
            raise DeviceError("toy rig: link lost mid-record")
        self.n_measured += len(lines)
        self._raw.append(RawRecord("toy", {"w": np.array(lines)}))
        return [point(w) for w in lines]

    def take_raw_records(self):
        taken, self._raw = self._raw, []
        return taken

    def update_model(self, model):
        self.models.append(model)

    def confirm_output_off(self):
        self.confirmed_off += 1

    def close(self):
        pass


class History:
    """A stopped run's journal, as the engine reads it."""

    def __init__(self, measured, roles=None, iterations=()):
        self.path = "toy/journal.sqlite"
        self._measured = list(measured)
        self._roles = roles or ["initial"] * len(measured)
        self._iterations = [SimpleNamespace(k=k, next_omega=w) for k, w in iterations]

    def measurements(self):
        return list(self._measured)

    def measurement_rows(self):
        return [{"role": r} for r in self._roles]

    def iterations(self):
        return list(self._iterations)


def recorder():
    seen = []
    return seen, lambda event, **info: seen.append((event, info))


def toy_plan(first, then, record=False, next_omega=4.0, iteration_record=True):
    """Continuation or the initial points, one iteration's record and a choice, then more points."""
    stored = yield StoredData()
    measured = list(stored.measured) if stored is not None else (yield Measure(tuple(first), 0, "initial", record))
    yield InformModel("model after k=1")
    if iteration_record:  # a toy record: only the engine reads it (a journal needs the whole of one)
        yield Emit(ITERATION_RECORD, {"fields": {"k": 1, "next_omega": next_omega}}, 1)
    yield Emit(NOTE, {"kind": "left-out", "message": "iteration 1: a region"}, 1)
    measured += yield Measure(tuple(then), 1, "added", record)
    return Points(measured)


class Points(list):
    """A toy plan's result; the journal stores its document when the run finishes."""

    def to_document(self) -> dict:
        return {"n_points": len(self)}


def test_replay_serves_stored_points_then_measures_with_the_noise_index_continued():
    rig, (seen, sub) = CountingRig(), recorder()
    engine = RunEngine(rig, [sub], history=History([point(1.0), point(2.0)]))
    got = engine.run(toy_plan([1.0, 2.0, 3.0], [4.0]))
    assert got == [point(w) for w in (1.0, 2.0, 3.0, 4.0)]
    assert rig.asked == [("measure", 3.0, 2), ("measure", 4.0, 3)]  # n_measured set to the 2 stored first
    measures = [(i["index"], i["replayed"]) for e, i in seen if e == "measure"]
    assert measures == [(1, True), (2, True), (3, False), (4, False)]
    assert [i["seq"] for e, i in seen if e == "measured"] == [3, 4]  # stored points are not committed again
    assert rig.models == ["model after k=1"]


def test_replay_that_asks_for_another_frequency_stops_naming_the_measurement():
    engine = RunEngine(CountingRig(), history=History([point(1.0), point(2.5)]))
    with pytest.raises(CampaignReplayError, match="measurement 2"):
        engine.run(toy_plan([1.0, 2.0, 3.0], [4.0]))


def test_a_stored_iteration_is_checked_and_its_documents_marked_replayed():
    history = History([point(1.0)], iterations=[(1, 4.0)])
    seen, sub = recorder()
    RunEngine(CountingRig(), [sub], history=history).run(toy_plan([1.0], [4.0]))
    assert all(i["replayed"] for e, i in seen if e in (NOTE, ITERATION_RECORD))
    with pytest.raises(CampaignReplayError, match="iteration 1"):
        RunEngine(CountingRig(), history=history).run(toy_plan([1.0], [5.0], next_omega=5.0))


def test_continuation_hands_every_stored_point_to_the_plan_and_measures_nothing_again():
    rig = CountingRig()
    history = History([point(1.0), point(2.0), point(7.0)], roles=["initial", "initial", "added"], iterations=[(1, 7.0)])
    engine = RunEngine(rig, history=history, continue_stored=True)
    assert engine.continuation.n_added == 1 and engine.continuation.next_iteration == 2
    got = engine.run(toy_plan([9.0], [4.0]))
    assert got == [point(w) for w in (1.0, 2.0, 7.0, 4.0)]
    assert rig.asked == [("measure", 4.0, 3)]


class Control:
    def __init__(self, pause_before: int | None = None, abort_before: int | None = None):
        self.calls, self.pause_before, self.abort_before = 0, pause_before, abort_before

    def checkpoint(self, make_safe=None):
        self.calls += 1
        if self.calls == self.abort_before:
            raise CampaignAborted("operator pressed Abort")
        if self.calls == self.pause_before:
            make_safe()


def test_pause_confirms_the_output_off_and_is_reported_with_its_end():
    rig, (seen, sub) = CountingRig(), recorder()
    RunEngine(rig, [sub], control=Control(pause_before=2)).run(toy_plan([1.0, 2.0], [4.0]))
    notes = [i["kind"] for e, i in seen if e == NOTE and not i["replayed"]]
    assert notes == ["paused", "unpaused", "left-out"] and rig.confirmed_off == 1
    paused = next(i["message"] for e, i in seen if e == NOTE and i["kind"] == "paused")
    assert "before measurement 2" in paused


def test_abort_stops_before_the_next_dwell_and_keeps_what_was_measured(tmp_path):
    journal = _journal(tmp_path)
    rig = CountingRig()
    with pytest.raises(CampaignAborted):
        RunEngine(rig, [JournalWriter(journal)], history=journal, control=Control(abort_before=3)).run(toy_plan([1.0, 2.0, 3.0], [4.0]))
    assert [a[1] for a in rig.asked] == [1.0, 2.0]
    assert journal.measurements() == [point(1.0), point(2.0)]
    journal.close()


def test_a_dwell_failing_mid_record_commits_nothing_of_that_record(tmp_path):
    journal = _journal(tmp_path)
    rig = CountingRig(fail_record_at=2)
    subscribers = [RawRecordWriter(tmp_path), JournalWriter(journal)]
    with pytest.raises(DeviceError, match="mid-record"):
        RunEngine(rig, subscribers, history=journal).run(toy_plan([1.0, 2.0], [4.0, 5.0], record=True, iteration_record=False))
    assert journal.measurements() == [point(1.0), point(2.0)]  # the first record, whole; none of the failed one
    from setmem_hil.io.raw_store import read_raw_records

    assert [r.seqs for r in read_raw_records(tmp_path)] == [(1, 2)]
    journal.close()
    # resumed: the first record is replayed, the failed one measured from its first line's index
    journal = Journal.open(tmp_path)
    rig = CountingRig()
    got = RunEngine(rig, [RawRecordWriter(tmp_path), JournalWriter(journal)], history=journal).run(
        toy_plan([1.0, 2.0], [4.0, 5.0], record=True, iteration_record=False))
    assert got == [point(w) for w in (1.0, 2.0, 4.0, 5.0)] and rig.asked == [("record", (4.0, 5.0), 2)]
    assert [r.seqs for r in read_raw_records(tmp_path)] == [(1, 2), (3, 4)]
    journal.close()


def test_raw_records_reach_the_subscribers_before_their_points():
    rig, (seen, sub) = CountingRig(), recorder()
    RunEngine(rig, [sub]).run(toy_plan([1.0], [4.0]))
    order = [(e, i.get("seqs") or i.get("seq")) for e, i in seen if e in ("raw-record", "measured")]
    assert order == [("raw-record", (1,)), ("measured", 1), ("raw-record", (2,)), ("measured", 2)]


def _journal(tmp_path) -> Journal:
    return Journal.create(tmp_path / "journal.sqlite", procedure_text="x", procedure_name="toy", seed=1, software_version="t",
                          backend="sim", strategy="mu")


# -- structure (the contract) -------------------------------------------------------------
def test_no_function_in_the_campaign_package_is_longer_than_80_lines():
    long = []
    for path in sorted(CAMPAIGN.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                first = min([node.lineno, *(d.lineno for d in node.decorator_list)])
                if node.end_lineno - first + 1 > 80:
                    long.append(f"{path.name}:{node.name} ({node.end_lineno - first + 1} lines)")
    assert not long, long


def test_the_module_that_calls_the_design_step_imports_neither_the_journal_nor_the_live_view():
    callers = [p for p in CAMPAIGN.glob("*.py") if "safeguarded_design(" in p.read_text(encoding="utf-8")]
    assert [p.name for p in callers] == ["plan.py"]
    imported = set()
    for node in ast.walk(ast.parse(callers[0].read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            imported.add(node.module or "")
        elif isinstance(node, ast.Import):
            imported.update(a.name for a in node.names)
    assert not [m for m in imported if "journal" in m or m.startswith("setmem_hil.live") or "persistence" in m], imported
