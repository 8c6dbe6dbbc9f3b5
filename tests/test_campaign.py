"""The Algorithm 5.1 loop on the simulated beam: goal, monotone bounds and mu-bar, journal, resume."""

import dataclasses

import numpy as np
import pytest

from setmem_hil.campaign.runner import CampaignReplayError, candidate_noise_bound, run_campaign
from setmem_hil.model.experiment import Measurement
from setmem_hil.io.journal import Journal
from setmem_hil.io.procedure import Goal, default_procedure
from setmem_hil.sim_backends.simulated_beam import SimulatedBeamExperiment

SEED = 3  # the 6.3.2 campaign reaches mu-bar < 1 in a few experiments for this seed (one added since issue 62 shaves the box; seed 2 now needs none)


def procedure(max_experiments=8, mu_target=1.0, seed=SEED):
    return dataclasses.replace(default_procedure(), seed=seed, goal=Goal(mu_target=mu_target, max_experiments=max_experiments))


def new_journal(path, seed=SEED, strategy="mu"):
    return Journal.create(path / "journal.sqlite", procedure_text="# test", procedure_name="beam-6.3.2",
                          seed=seed, software_version="test", backend="sim", strategy=strategy)


class InterruptAt:
    """Simulated beam that raises KeyboardInterrupt (an operator's Ctrl-C) before dwell ``n``."""

    def __init__(self, seed, n):
        self.beam = SimulatedBeamExperiment(seed=seed)
        self.n = n
        self.calls = 0

    def measure(self, omega_rad_s):
        self.calls += 1
        if self.calls == self.n:
            raise KeyboardInterrupt
        return self.beam.measure(omega_rad_s)

    def total_bound(self, omega_rad_s):
        return self.beam.total_bound(omega_rad_s)

    def close(self):
        pass


@pytest.fixture(scope="module")
def complete_run(tmp_path_factory):
    """One uninterrupted 6.3.2 campaign with its journal (shared by the tests below)."""
    path = tmp_path_factory.mktemp("complete")
    events = []
    journal = new_journal(path)
    summary = run_campaign(procedure(), SimulatedBeamExperiment(seed=SEED), journal,
                           progress=lambda event, **info: events.append((event, info)))
    iterations = journal.iterations()
    rows = journal.measurement_rows()
    info = journal.run_info()
    journal.close()
    return summary, iterations, rows, info, events


@pytest.mark.slow
def test_campaign_reaches_the_goal_and_stops_there(complete_run):
    summary, iterations, rows, info, _ = complete_run
    assert summary.reached_goal and summary.final_mu_peak < 1.0
    # the stopping test is mu-bar certified on the whole band (issue 27), not the grid's peak: an
    # iteration may show a grid peak below 1 whose band-wide certificate is not (it goes on)
    certified = [it.certified_mu for it in summary.iterations]
    assert certified[-1] < 1.0 and all(c >= 1.0 for c in certified[:-1])  # stops at the first certified mu-bar < 1
    assert all(it.mu_peak <= c + 1e-12 for it, c in zip(summary.iterations, certified))  # the grid never above the band's bound
    assert iterations[-1].next_omega is None
    assert summary.experiments_added == len(iterations) - 1 == len(rows) - 15
    doc = summary.to_document()
    assert set(doc) >= {"reached_goal", "final_mu_peak", "experiments_added", "wall_s", "iterations"}
    assert [it["k"] for it in doc["iterations"]] == list(range(1, len(iterations) + 1))
    assert info["finished"] and info["summary"]["experiments_added"] == summary.experiments_added


@pytest.mark.slow
def test_bounds_never_loosen_mu_never_increases_and_truth_stays_inside(complete_run):
    _, iterations, _, _, _ = complete_run
    truth = SimulatedBeamExperiment(seed=SEED).modelled_truth.values
    for prev, cur in zip(iterations, iterations[1:]):
        assert np.all(cur.lower >= prev.lower) and np.all(cur.upper <= prev.upper)  # eq. 5.4-5.5
        assert cur.mu_peak <= prev.mu_peak  # eq. 5.12
    for it in iterations:
        assert np.all(it.lower <= truth + 1e-9) and np.all(truth <= it.upper + 1e-9)


@pytest.mark.slow
def test_journal_holds_every_measurement_and_each_added_point_is_the_chosen_one(complete_run):
    _, iterations, rows, _, events = complete_run
    proc = procedure()
    assert [r["omega_rad_s"] for r in rows[:15]] == list(proc.initial_omegas_rad_s)
    assert all(r["role"] == "initial" for r in rows[:15]) and all(r["role"] == "added" for r in rows[15:])
    chosen = [it.next_omega for it in iterations[:-1]]
    assert [r["omega_rad_s"] for r in rows[15:]] == chosen
    # first choice is among 500 candidates (figure 6-14), with an estimate for each
    assert iterations[0].candidate_omega.size == 500 == iterations[0].estimated_improvement.size
    assert np.max(iterations[0].estimated_improvement) > 0
    kinds = [e for e, _ in events]
    assert kinds.count("measure") == len(rows) and kinds.count("iteration") == len(iterations)
    assert kinds.count("chosen") == len(iterations) - 1 and kinds[-2:] == ["finished", "stop"] and kinds[0] == "start"
    assert dict(events[-1][1])["exit_status"] == "success"


@pytest.mark.slow
def test_the_journal_is_written_from_the_documents_alone(complete_run, tmp_path):
    """Second formulation: the documents the subscribers saw, sent to a fresh store, rebuild the
    run's journal (every measurement, iteration and event); its header comes from the ``start``
    document and matches the procedure that ran."""
    from setmem_hil.campaign.persistence import JournalWriter
    from setmem_hil.io.procedure_file import format_procedure

    summary, iterations, rows, info, events = complete_run
    store = JournalWriter(tmp_path / "journal.sqlite")
    for name, document in events:
        store(name, **document)
    rebuilt = store.journal
    try:
        no_utc = lambda items: [{k: v for k, v in item.items() if k != "utc"} for item in items]  # noqa: E731
        assert no_utc(rebuilt.measurement_rows()) == no_utc(rows)
        assert [(it.k, it.n_points, it.next_omega, it.mu_peak) for it in rebuilt.iterations()] == \
            [(it.k, it.n_points, it.next_omega, it.mu_peak) for it in iterations]
        for ours, theirs in zip(rebuilt.iterations(), iterations):
            np.testing.assert_array_equal(ours.lower, theirs.lower)
            np.testing.assert_array_equal(ours.upper, theirs.upper)
        kinds = [e["kind"] for e in rebuilt.events()]
        assert kinds[0] == "run-start" and kinds[-1] == "run-stop"
        assert kinds[1:-1] == [doc["kind"] for name, doc in events if name == "note"]
        header = rebuilt.run_info()
        assert header["finished"] and header["summary"] == summary.to_document()
        p = procedure()
        assert (header["procedure_name"], header["seed"], header["strategy"], header["backend"], header["design"]) == \
            (p.name, SEED, p.input_design.strategy, p.backend.kind, p.design_method)
        assert header["procedure_text"] == format_procedure(p)
    finally:
        store.close()


@pytest.mark.slow  # 3 min on two cores; tests/test_resume.py holds the same property in the default tier
def test_interrupted_campaign_resumes_to_exactly_the_uninterrupted_run(complete_run, tmp_path):
    summary, iterations, rows, _, _ = complete_run
    journal = new_journal(tmp_path)
    # Ctrl-C before the last added dwell (the run's own count: the robust design's path, and so
    # how many dwells it adds, changes with its numerics; seed 3 needs one)
    assert len(rows) > 15, "the complete run added no dwell: nothing to interrupt between iterations"
    with pytest.raises(KeyboardInterrupt):
        run_campaign(procedure(), InterruptAt(SEED, len(rows)), journal)
    assert journal.n_measurements() == len(rows) - 1  # every completed dwell was recorded
    journal.close()

    journal = Journal.open(tmp_path)
    beam = SimulatedBeamExperiment(seed=SEED)
    resumed = run_campaign(procedure(), beam, journal)
    assert beam.n_measured == len(rows)  # the fresh simulator continued from the interrupted measurement
    got = journal.measurement_rows()
    assert [(r["omega_rad_s"], r["re"], r["im"], r["bound"]) for r in got] == \
        [(r["omega_rad_s"], r["re"], r["im"], r["bound"]) for r in rows]
    assert [it.k for it in journal.iterations()] == [it.k for it in iterations]
    assert [it["mu_peak"] for it in resumed.to_document()["iterations"]] == \
        [it["mu_peak"] for it in summary.to_document()["iterations"]]
    journal.close()


@pytest.mark.slow
def test_replay_refuses_a_journal_from_another_procedure(complete_run, tmp_path):
    _, _, rows, _, _ = complete_run
    journal = new_journal(tmp_path)
    journal.add_measurement(Measurement(123.0, 1 + 0j, 0.1), iteration=0, role="initial")
    with pytest.raises(CampaignReplayError, match="measurement 1"):
        run_campaign(procedure(), SimulatedBeamExperiment(seed=SEED), journal)
    journal.close()


@pytest.mark.slow
def test_budget_stops_the_loop_without_reaching_the_goal():
    summary = run_campaign(procedure(max_experiments=0), SimulatedBeamExperiment(seed=SEED), strategy="log-sweep")
    assert not summary.reached_goal and summary.stop_reason == "budget"
    assert summary.experiments_added == 0 and len(summary.iterations) == 1
    assert summary.iterations[0].next_omega is None and summary.final_mu_peak > 1.0


def test_candidate_noise_bound_interpolates_log_log_without_a_model_of_the_rig():
    class Plain:  # an experiment that reports bounds but has no total_bound()
        pass

    measured = [Measurement(w, 0j, 0.3 * w**-1.5) for w in (0.5, 2.0, 8.0, 32.0)]
    w = np.array([1.0, 4.0, 16.0])
    assert np.allclose(candidate_noise_bound(Plain(), w, measured), 0.3 * w**-1.5)  # exact for a power law
    # held constant outside the measured range
    assert candidate_noise_bound(Plain(), np.array([0.1, 100.0]), measured) == pytest.approx([0.3 * 0.5**-1.5, 0.3 * 32.0**-1.5])
    beam = SimulatedBeamExperiment(seed=1)
    assert np.allclose(candidate_noise_bound(beam, w, measured), beam.total_bound(w))
