"""The run engine (issues 39, 46): replay, resume, continuation, pause, abort and a dwell failing
mid-record, on toy plans and experiments whose every call is counted (the truth is what each
test's experiment was asked and what its history holds); a plan with its own registered request
and its own cleanup; the run's start and stop documents; plus the structure rules of the
campaign package: the loop's module imports neither the journal nor the live view, and the
engine names no campaign concept (no function over 80 lines: tests/test_house.py)."""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from setmem_hil.run.engine import STOP, Checkpoint, RunEngine, RunStart
from setmem_hil.campaign.measurement_service import MeasurementService, register_measurements, stored_iterations
from setmem_hil.campaign.messages import ITERATION_RECORD, NOTE, Emit, InformModel, Measure, StoredData
from setmem_hil.campaign.persistence import JournalWriter, RawRecordWriter
from setmem_hil.errors import CampaignAborted, CampaignReplayError, DeviceError
from setmem_hil.io.journal import Journal
from setmem_hil.model.experiment import Measurement, RawRecord

CAMPAIGN = Path(__file__).resolve().parents[1] / "setmem_hil" / "campaign"
RUN_LAYER = Path(__file__).resolve().parents[1] / "setmem_hil" / "run"


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
    """Continuation or the initial points, one iteration's record and a choice, then more points
    (a pause point before each dwell, or before each record)."""
    stored = yield StoredData()
    measured = list(stored.measured) if stored is not None else (yield from toy_points(first, 0, "initial", record, 0))
    yield InformModel("model after k=1")
    if iteration_record:  # a toy record: only the engine reads it (a journal needs the whole of one)
        yield Emit(ITERATION_RECORD, {"fields": {"k": 1, "next_omega": next_omega}}, key=("iteration", 1), check={"next_omega": next_omega})
    yield Emit(NOTE, {"kind": "left-out", "message": "iteration 1: a region"}, key=("iteration", 1))
    measured += yield from toy_points(then, 1, "added", record, len(measured))
    return Points(measured)


def toy_points(omegas, k, role, record, done):
    if record:
        yield Checkpoint(f"measurement {done + 1}")
        return list((yield Measure(tuple(omegas), k, role, True)))
    got = []
    for w in omegas:
        yield Checkpoint(f"measurement {done + len(got) + 1}")
        got += yield Measure((w,), k, role)
    return got


def campaign_engine(rig, subscribers=(), history=None, control=None, continue_stored=False) -> RunEngine:
    """The engine with the campaign's measurements registered, as the runner builds it."""
    engine = RunEngine(subscribers, control=control, stored={} if continue_stored else stored_iterations(history),
                       make_safe=rig.confirm_output_off, safe_state="every exciter output confirmed off",
                       source=str(getattr(history, "path", "journal")))
    engine.service = register_measurements(engine, MeasurementService(rig, history=history, continue_stored=continue_stored))
    return engine


class Points(list):
    """A toy plan's result; the journal stores its document when the run finishes."""

    def to_document(self) -> dict:
        return {"n_points": len(self)}


def test_replay_serves_stored_points_then_measures_with_the_noise_index_continued():
    rig, (seen, sub) = CountingRig(), recorder()
    engine = campaign_engine(rig, [sub], history=History([point(1.0), point(2.0)]))
    got = engine.run(toy_plan([1.0, 2.0, 3.0], [4.0]))
    assert got == [point(w) for w in (1.0, 2.0, 3.0, 4.0)]
    assert rig.asked == [("measure", 3.0, 2), ("measure", 4.0, 3)]  # n_measured set to the 2 stored first
    measures = [(i["index"], i["replayed"]) for e, i in seen if e == "measure"]
    assert measures == [(1, True), (2, True), (3, False), (4, False)]
    assert [i["seq"] for e, i in seen if e == "measured"] == [3, 4]  # stored points are not committed again
    assert rig.models == ["model after k=1"]


def test_replay_that_asks_for_another_frequency_stops_naming_the_measurement():
    engine = campaign_engine(CountingRig(), history=History([point(1.0), point(2.5)]))
    with pytest.raises(CampaignReplayError, match="measurement 2"):
        engine.run(toy_plan([1.0, 2.0, 3.0], [4.0]))


def test_a_stored_iteration_is_checked_and_its_documents_marked_replayed():
    history = History([point(1.0)], iterations=[(1, 4.0)])
    seen, sub = recorder()
    campaign_engine(CountingRig(), [sub], history=history).run(toy_plan([1.0], [4.0]))
    assert all(i["replayed"] for e, i in seen if e in (NOTE, ITERATION_RECORD))
    with pytest.raises(CampaignReplayError, match="iteration 1"):
        campaign_engine(CountingRig(), history=history).run(toy_plan([1.0], [5.0], next_omega=5.0))


def test_continuation_hands_every_stored_point_to_the_plan_and_measures_nothing_again():
    rig = CountingRig()
    history = History([point(1.0), point(2.0), point(7.0)], roles=["initial", "initial", "added"], iterations=[(1, 7.0)])
    engine = campaign_engine(rig, history=history, continue_stored=True)
    assert engine.service.continuation.n_added == 1 and engine.service.continuation.next_iteration == 2
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
    campaign_engine(rig, [sub], control=Control(pause_before=2)).run(toy_plan([1.0, 2.0], [4.0]))
    notes = [i["kind"] for e, i in seen if e == NOTE and not i["replayed"]]
    assert notes == ["paused", "unpaused", "left-out"] and rig.confirmed_off == 1
    paused = next(i["message"] for e, i in seen if e == NOTE and i["kind"] == "paused")
    assert "before measurement 2" in paused


class PausedThenAborted:
    """Pause held, then Resume and Abort pressed together: the checkpoint wakes with the abort set."""

    def checkpoint(self, make_safe=None):
        make_safe()
        raise CampaignAborted("operator pressed Resume then Abort")


def test_a_pause_ended_by_abort_still_journals_its_end():
    rig, (seen, sub) = CountingRig(), recorder()
    with pytest.raises(CampaignAborted):
        campaign_engine(rig, [sub], control=PausedThenAborted()).run(toy_plan([1.0, 2.0], [4.0]))
    notes = [(i["kind"], i["message"]) for e, i in seen if e == NOTE]
    assert [k for k, _ in notes[:2]] == ["paused", "unpaused"] and "ended by abort after" in notes[1][1]
    assert rig.confirmed_off >= 1


def test_abort_stops_before_the_next_dwell_and_keeps_what_was_measured(tmp_path):
    journal = _journal(tmp_path)
    rig = CountingRig()
    with pytest.raises(CampaignAborted):
        campaign_engine(rig, [JournalWriter(journal)], history=journal, control=Control(abort_before=3)).run(toy_plan([1.0, 2.0, 3.0], [4.0]))
    assert [a[1] for a in rig.asked] == [1.0, 2.0]
    assert journal.measurements() == [point(1.0), point(2.0)]
    journal.close()


def test_a_dwell_failing_mid_record_commits_nothing_of_that_record(tmp_path):
    journal = _journal(tmp_path)
    rig = CountingRig(fail_record_at=2)
    subscribers = [RawRecordWriter(tmp_path), JournalWriter(journal)]
    with pytest.raises(DeviceError, match="mid-record"):
        campaign_engine(rig, subscribers, history=journal).run(toy_plan([1.0, 2.0], [4.0, 5.0], record=True, iteration_record=False))
    assert journal.measurements() == [point(1.0), point(2.0)]  # the first record, whole; none of the failed one
    from setmem_hil.io.raw_store import read_raw_records

    assert [r.seqs for r in read_raw_records(tmp_path)] == [(1, 2)]
    journal.close()
    # resumed: the first record is replayed, the failed one measured from its first line's index
    journal = Journal.open(tmp_path)
    rig = CountingRig()
    got = campaign_engine(rig, [RawRecordWriter(tmp_path), JournalWriter(journal)], history=journal).run(
        toy_plan([1.0, 2.0], [4.0, 5.0], record=True, iteration_record=False))
    assert got == [point(w) for w in (1.0, 2.0, 4.0, 5.0)] and rig.asked == [("record", (4.0, 5.0), 2)]
    assert [r.seqs for r in read_raw_records(tmp_path)] == [(1, 2), (3, 4)]
    journal.close()


def test_raw_records_reach_the_subscribers_before_their_points():
    rig, (seen, sub) = CountingRig(), recorder()
    campaign_engine(rig, [sub]).run(toy_plan([1.0], [4.0]))
    order = [(e, i.get("seqs") or i.get("seq")) for e, i in seen if e in ("raw-record", "measured")]
    assert order == [("raw-record", (1,)), ("measured", 1), ("raw-record", (2,)), ("measured", 2)]


# -- a plan of its own (issue 46): a registered request, a cleanup, the lifecycle documents ---------
class Fire:
    """A toy plan's own request: the handler fires a toy laser ``shots`` times, or fails."""

    def __init__(self, shots: int):
        self.shots = shots


def toy_laser_plan(log: list, shots):
    try:
        for n in shots:
            log.append(("fired", (yield Fire(n))))
            yield Checkpoint(f"shot {n}")
        return "done"
    finally:
        log.append("shutter closed")  # the plan's own cleanup, run however it ends


def laser_engine(subscribers, control=None) -> RunEngine:
    def fire(engine, request):
        if request.shots < 0:
            raise DeviceError("toy laser: negative shot count refused")
        engine.emit("fired", shots=request.shots)
        return request.shots * 2

    engine = RunEngine(subscribers, control=control)
    engine.register_command(Fire, fire)
    return engine


def test_a_plan_with_its_own_request_runs_and_its_cleanup_runs_when_a_handler_raises():
    log, (seen, sub) = [], recorder()
    assert laser_engine([sub]).run(toy_laser_plan(log, [1, 3]), RunStart("laser", {"power": 2}, seed=7, planned=2)) == "done"
    assert log == [("fired", 2), ("fired", 6), "shutter closed"]
    assert [e for e, _ in seen] == ["start", "fired", "fired", "stop"]
    start, stop = seen[0][1], seen[-1][1]
    assert start["plan"] == "laser" and json.loads(start["arguments"]) == {"power": 2} and start["seed"] == 7
    assert start["planned"] == 2 and start["version"] and start["run_id"] == stop["run_id"]
    assert stop["exit_status"] == "success" and stop["reason"] == ""

    log, (seen, sub) = [], recorder()
    with pytest.raises(DeviceError, match="negative shot count"):
        laser_engine([sub]).run(toy_laser_plan(log, [1, -1, 5]))
    assert log == [("fired", 2), "shutter closed"]  # thrown into the plan at its yield: the finally ran
    assert seen[-1][0] == STOP and seen[-1][1]["exit_status"] == "fail" and "negative shot count" in seen[-1][1]["reason"]


def test_an_abort_at_a_declared_pause_point_stops_the_run_with_exit_status_abort():
    log, (seen, sub) = [], recorder()
    with pytest.raises(CampaignAborted):
        laser_engine([sub], control=Control(abort_before=2)).run(toy_laser_plan(log, [1, 2, 3]))
    assert log == [("fired", 2), ("fired", 4), "shutter closed"]
    assert seen[-1][1]["exit_status"] == "abort"


def test_a_request_nobody_registered_is_refused_inside_the_plan():
    log = []
    with pytest.raises(TypeError, match="no command for Fire"):
        RunEngine().run(toy_laser_plan(log, [1]))
    assert log == ["shutter closed"]


def test_the_journal_holds_the_run_start_and_stop(tmp_path):
    journal = _journal(tmp_path)
    campaign_engine(CountingRig(), [JournalWriter(journal)], history=journal).run(toy_plan([1.0], [4.0], iteration_record=False))
    kinds = [e["kind"] for e in journal.events()]
    assert kinds[0] == "run-start" and kinds[-1] == "run-stop"
    assert json.loads(journal.events()[-1]["message"])["exit_status"] == "success"
    journal.close()


def test_a_new_journal_is_made_from_the_start_document_and_the_notes_before_it_follow_its_header(tmp_path):
    """The header comes from the ``start`` document's arguments alone (truth: what the test put
    there); a note sent before the run (the instruments' identities) is written after the header,
    before ``run-start``; the procedure's text is in the header, and in the event only by its hash."""
    import hashlib

    path = tmp_path / "journal.sqlite"
    store = JournalWriter(path)
    store(NOTE, kind="instruments", message="fgen: ACME,1")
    assert not path.exists()  # no journal before the run starts
    text = "[prior]\n# the procedure\n"
    start = RunStart("toy", {"procedure": "toy-beam", "procedure_text": text, "backend": "emulated", "strategy": "log-sweep",
                             "design": "robust"}, seed=7, planned=3)
    campaign_engine(CountingRig(), [store]).run(toy_plan([1.0], [4.0], iteration_record=False), start)
    store.close()
    with Journal.open(path) as j:
        info = j.run_info()
        assert (info["procedure_text"], info["procedure_name"], info["seed"], info["backend"], info["strategy"], info["design"]) == \
            (text, "toy-beam", 7, "emulated", "log-sweep", "robust")
        from setmem_hil import __version__
        assert info["software_version"] == __version__
        events = j.events()
        assert [e["kind"] for e in events][:2] == ["instruments", "run-start"] and events[-1]["kind"] == "run-stop"
        arguments = json.loads(json.loads(events[1]["message"])["arguments"])
        assert "procedure_text" not in arguments and arguments["procedure_sha256"] == hashlib.sha256(text.encode()).hexdigest()
        assert len(j.measurements()) == 2


def test_a_campaign_given_a_path_makes_its_journal_from_the_documents_alone(tmp_path):
    """Second formulation (the slow tier does the same on a whole campaign): every document a run
    on the simulated beam sent, given to a fresh store, rebuilds its journal (points, iteration,
    events, summary); the header is the procedure that ran."""
    import dataclasses

    from setmem_hil.campaign.runner import run_campaign
    from setmem_hil.io.procedure import Goal, default_procedure
    from setmem_hil.io.procedure_file import format_procedure
    from setmem_hil.sim_backends.simulated_beam import SimulatedBeamExperiment

    procedure = dataclasses.replace(default_procedure(), seed=2, goal=Goal(mu_target=1.0, max_experiments=0), design_method="h2")
    seen, sub = recorder()
    summary = run_campaign(procedure, SimulatedBeamExperiment(seed=2), tmp_path / "run" / "journal.sqlite", progress=sub)
    rebuilt = JournalWriter(tmp_path / "rebuilt" / "journal.sqlite")
    for name, document in seen:
        rebuilt(name, **document)
    rebuilt.close()
    no_utc = lambda rows: [{k: v for k, v in row.items() if k not in ("utc", "created_utc", "finished_utc")} for row in rows]  # noqa: E731
    with Journal.open(tmp_path / "run") as run, Journal.open(tmp_path / "rebuilt") as again:  # the run closed its own journal
        assert no_utc(again.measurement_rows()) == no_utc(run.measurement_rows()) and len(run.measurements()) == 15
        assert no_utc([again.run_info()]) == no_utc([run.run_info()])
        assert [(e["kind"], e["message"]) for e in again.events()] == [(e["kind"], e["message"]) for e in run.events()]
        ours, theirs = again.iterations(), run.iterations()
        assert [(it.k, it.mu_peak, it.next_omega) for it in ours] == [(it.k, it.mu_peak, it.next_omega) for it in theirs]
        np.testing.assert_array_equal(ours[0].upper, theirs[0].upper)
        info = run.run_info()
        assert (info["procedure_name"], info["seed"], info["strategy"], info["design"], info["backend"]) == \
            (procedure.name, 2, procedure.input_design.strategy, "h2", procedure.backend.kind)
        assert info["procedure_text"] == format_procedure(procedure) and info["summary"] == summary.to_document()


def test_the_plan_clock_counts_the_plans_computation_and_not_its_requests():
    """Truth: the CPU seconds the plan and the handler each burn (process time: the same under
    load). The handler's 0.4 s must not be counted in either iteration's clock."""
    import time

    from setmem_hil.campaign.persistence import IterationClock

    def burn(seconds: float) -> None:
        cpu = time.process_time()
        while time.process_time() - cpu < seconds:
            pass

    def busy_fire(engine, request):
        burn(0.4)  # a dwell's own work: the engine's, not the plan's
        return 0

    def plan():
        for k in (1, 2):
            yield Fire(k)
            burn(0.05 * k)  # the plan's own work: 0.05 s, then 0.1 s
            yield Emit(ITERATION_RECORD, {"k": k, "choice": None})

    clock = IterationClock()
    engine = RunEngine([clock])
    engine.register_command(Fire, busy_fire)
    engine.run(plan())
    (wall1, cpu1), (wall2, cpu2) = clock.by_iteration[1], clock.by_iteration[2]
    assert 0.05 <= cpu1 < 0.4 and 0.1 <= cpu2 < 0.4, (cpu1, cpu2)
    assert wall1 >= cpu1 * 0.5 and wall2 >= cpu2 * 0.5  # wall clocks advance with the plan too
    assert engine.elapsed_s >= wall1 + wall2


def test_the_plan_holds_no_clock_and_no_journal_layout():
    text = (CAMPAIGN / "plan.py").read_text(encoding="utf-8")
    assert not re.search(r"^import time|perf_counter|process_time|IterationRecord|wall_s", text, re.M)


def _journal(tmp_path) -> Journal:
    return Journal.create(tmp_path / "journal.sqlite", procedure_text="x", procedure_name="toy", seed=1, software_version="t",
                          backend="sim", strategy="mu")


# -- structure (the contract) -------------------------------------------------------------
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


def test_the_engine_names_no_campaign_concept():
    text = (RUN_LAYER / "engine.py").read_text(encoding="utf-8")
    words = set(re.findall(r"[A-Za-z_]+", text.lower()))
    assert not words & {"next_omega", "added", "iteration", "iterations", "campaign", "measure", "measurement", "dwell"}, \
        words & {"next_omega", "added", "iteration", "iterations", "campaign", "measure", "measurement", "dwell"}


def test_the_robust_loop_keeps_its_compensator_without_tuning_when_the_box_did_not_move():
    """A box that moved by less than BOX_UNCHANGED_RTOL of its widths: the previous outcome (its
    bound holds on the inner box) and no design call; a box that moved more: the design runs."""
    from setmem_hil.campaign import plan
    from setmem_hil.design.safeguard import SafeguardOutcome
    from setmem_hil.model.modal_model import IntervalModel

    lower, upper = np.array([[0.1, 4.0, -0.1, 1.0]]), np.array([[0.2, 5.0, 0.1, 2.0]])
    previous_model = IntervalModel(lower, upper)
    previous = SafeguardOutcome(analysis=SimpleNamespace(design="robust"), analysis_model=previous_model, branch="new-design",
                                mu_peak=1.14, tried={"new-design": 1.14}, certified_mu=1.1401)
    calls = []

    def analyzer(state):
        def analyze(model, controller):
            calls.append(controller)
            raise AssertionError("tuned again")
        return analyze

    loop = SimpleNamespace(method="robust", analyzer=analyzer, procedure=None)
    state = plan.LoopState([point(1.0)], previous_model=previous_model, previous_outcome=previous)
    state.rows.append(SimpleNamespace(design="robust"))
    inner = IntervalModel(lower + 1e-8, upper - 1e-8)
    outcome, kept = plan._design_and_analyse(loop, state, inner)
    assert outcome.branch == "previous-controller" and outcome.mu_peak == 1.14 and outcome.certified_mu == 1.1401
    assert kept == "robust" and calls == []
    moved = IntervalModel(lower + np.array([[0.0, 0.01, 0.0, 0.0]]), upper)
    with pytest.raises(AssertionError, match="tuned again"):
        plan._design_and_analyse(loop, state, moved)
    loop.method = "h2"  # the thesis's loop: always designs
    with pytest.raises(AssertionError, match="tuned again"):
        plan._design_and_analyse(loop, state, inner)
