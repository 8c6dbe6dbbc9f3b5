"""Issue 15 (first part): rig time as a first-class figure.

Every dwell records its device time (settling, excitation, acquisition); the journal stores it
per measurement, ``summary.json`` has the total ``rig_s`` and each iteration's ``rig_s``.
Truth: the fake device's own virtual clock (it restarts at every measurement), the lock-in
bench's clock, and the journal rows.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from setmem_hil.campaign.session import start_run
from setmem_hil.experiment_factory import open_experiment
from setmem_hil.io.journal import Journal, read_snapshot
from setmem_hil.io.procedure_file import load_procedure
from setmem_hil.model.experiment import Measurement
from setmem_hil.sim_backends.core_rig import CoreRig

REPO = Path(__file__).resolve().parents[1]


def test_sine_dwell_rig_time_is_the_device_clock():
    procedure = load_procedure(REPO / "procedures" / "serial_loopback.toml")
    with open_experiment(procedure, seed=2) as exp:
        core = exp.rig.owned[0].core
        for w in (0.9, 6.0, 40.0):
            m = exp.measure(w)
            assert m.rig_s == pytest.approx(core.status().time_s, rel=1e-9)  # one attempt: the clock since begin_measurement
            assert m.rig_s > 0


@pytest.mark.slow
def test_summary_and_iterations_carry_rig_time(tmp_path):
    procedure = load_procedure(REPO / "procedures" / "serial_loopback.toml")
    outcome = start_run(procedure, tmp_path / "run", opener=open_experiment, quiet_report_hint=True)
    rows = read_snapshot(tmp_path / "run").rows
    assert outcome.summary["rig_s"] == pytest.approx(sum(r["rig_s"] for r in rows))
    assert all(r["rig_s"] > 0 for r in rows)
    for it in outcome.summary["iterations"]:
        assert it["rig_s"] == pytest.approx(sum(r["rig_s"] for r in rows if r["iteration"] == it["k"]))
    assert outcome.summary["rig_s"] > sum(it["rig_s"] for it in outcome.summary["iterations"])  # initial points count too


def test_instrument_dwell_rig_time_is_the_bench_clock():
    procedure = load_procedure(REPO / "procedures" / "instruments_emulated.toml")
    with open_experiment(procedure, seed=1) as exp:
        t0 = exp.bench.clock.now()
        m = exp.measure(6.0)
        assert m.rig_s == pytest.approx(exp.bench.clock.now() - t0)


def test_version_1_journals_are_upgraded(tmp_path):
    j = Journal.create(tmp_path / "journal.sqlite", procedure_text="name = 'x'", procedure_name="x", seed=1,
                       software_version="test", backend="sim", strategy="mu")
    j.add_measurement(Measurement(1.0, 2 + 1j, 0.1, rig_s=12.5), iteration=0, role="initial")
    j.close()
    conn = sqlite3.connect(tmp_path / "journal.sqlite")
    conn.execute("ALTER TABLE measurement DROP COLUMN rig_s")
    conn.execute("ALTER TABLE iteration DROP COLUMN controller")  # a faithful version 1: none of the later columns
    conn.execute("ALTER TABLE iteration DROP COLUMN mu_peak_certified")
    conn.execute("ALTER TABLE iteration DROP COLUMN mu_certified_intervals")
    conn.execute("ALTER TABLE iteration DROP COLUMN outputs")
    conn.execute("ALTER TABLE iteration DROP COLUMN common_gain")
    conn.execute("ALTER TABLE measurement DROP COLUMN others")
    conn.execute("ALTER TABLE iteration DROP COLUMN groups")  # version 8 (issue 47)
    conn.execute("ALTER TABLE iteration DROP COLUMN design")  # version 7 (issue 38)
    conn.execute("ALTER TABLE iteration DROP COLUMN floor_modes")
    conn.execute("ALTER TABLE run DROP COLUMN design")
    conn.execute("PRAGMA user_version=1")
    conn.commit()
    conn.close()
    j = Journal.open(tmp_path / "journal.sqlite")
    try:
        (m,) = j.measurements()
        assert (m.omega_rad_s, m.response, m.bound, m.rig_s) == (1.0, 2 + 1j, 0.1, 0.0)
    finally:
        j.close()


# -- [input_design] per_iteration and ranking ---------------------------------------------------------
def _sim_procedure(extra: str, max_experiments: int = 4):
    from setmem_hil.io.procedure_file import parse_procedure_text

    text = (REPO / "procedures" / "beam_6_3_2.toml").read_text()
    text = text.replace("exact_resolve_top = 5", "exact_resolve_top = 5\n" + extra).replace("max_experiments = 30", f"max_experiments = {max_experiments}")
    return parse_procedure_text(text, "p.toml")


@pytest.mark.slow
def test_defaults_stated_explicitly_reproduce_todays_campaign(tmp_path):
    from setmem_hil.campaign.runner import run_campaign

    plain = _sim_procedure("", 2)
    stated = _sim_procedure('per_iteration = 1\nranking = "thesis"', 2)
    assert stated.input_design == plain.input_design
    runs = []
    for p in (plain, stated):  # the H2 loop: the input-design defaults are what this checks, at the cost it had
        with open_experiment(p, seed=1) as exp:
            runs.append(run_campaign(p, exp, seed=1, design="h2"))
    assert [it.next_omega for it in runs[0].iterations] == [it.next_omega for it in runs[1].iterations]
    assert runs[0].rig_s == runs[1].rig_s


@pytest.mark.slow
def test_batch_of_two_frequencies_per_iteration(tmp_path):
    procedure = _sim_procedure("per_iteration = 2", 4)
    outcome = start_run(procedure, tmp_path / "run", opener=open_experiment, quiet_report_hint=True)
    snap = read_snapshot(tmp_path / "run")
    added = [r for r in snap.rows if r["role"] == "added"]
    per_iteration = {}
    for r in added:
        per_iteration.setdefault(r["iteration"], []).append(r["omega_rad_s"])
    assert all(len(ws) == 2 and ws[0] != ws[1] for ws in per_iteration.values()) or outcome.summary["reached_goal"]
    assert len(added) <= 4  # the budget counts every frequency
    for it in outcome.summary["iterations"]:
        assert it["rig_s"] == pytest.approx(sum(r["rig_s"] for r in added if r["iteration"] == it["k"]))
    batch_events = [e for e in snap.events if e["kind"] == "batch"]
    assert len(batch_events) == len([k for k, ws in per_iteration.items() if len(ws) == 2])


@pytest.mark.slow  # two input designs over the whole candidate grid (14 s)
def test_per_rig_second_ranking_is_invariant_to_a_uniform_cost_and_follows_a_penalty():
    """Dividing every candidate's improvement by the same cost changes nothing; making the
    thesis's choice (and its neighbours) expensive moves the choice away from it."""
    import numpy as np

    from setmem_hil.design.input_design import choose_input
    from setmem_hil.identification.algorithm import identify
    from setmem_hil.design.input_design import uniform_weights
    from setmem_hil.model.frequency_data import FrequencyData

    procedure = _sim_procedure("", 2)
    with open_experiment(procedure, seed=1) as exp:
        ms = [exp.measure(w) for w in procedure.initial_omegas_rad_s]
    data = FrequencyData.from_measurements(ms)
    result = identify(data, procedure.prior)
    omega = np.geomspace(0.1, 1000, 300)
    R = exp.total_bound(omega)
    w = uniform_weights(result.model)
    base = choose_input(result, data, procedure.prior, omega, R, w, scoring="max-reduction", exact_resolve_top=3)
    same = choose_input(result, data, procedure.prior, omega, R, w, scoring="max-reduction", exact_resolve_top=3, cost_s=np.full(omega.size, 37.0))
    assert same.next_omega_rad_s == base.next_omega_rad_s
    cost = np.where(np.abs(np.log(omega / base.next_omega_rad_s)) < 0.05, 1e6, 1.0)
    moved = choose_input(result, data, procedure.prior, omega, R, w, scoring="max-reduction", exact_resolve_top=3, cost_s=cost)
    assert abs(np.log(moved.next_omega_rad_s / base.next_omega_rad_s)) >= 0.05


class _NeverAtRestRig:
    """A CoreRig without ``begin_measurement``: each dwell starts on the previous dwell's ringing
    (the simulated structure is never put back at rest, as on a rig that does not wait)."""

    def __init__(self, core):
        inner = CoreRig(core)
        self.core, self.exciter, self.sensor = core, inner.exciter, inner.sensor
        self._inner = inner

    @property
    def metadata(self):
        return self._inner.metadata

    def close(self):
        self._inner.close()


def test_dwells_need_no_return_to_rest():
    """The estimator models the free response left by the previous dwell, so no dwell waits for
    rest (why stepping the frequency without stopping would save only the 2 s skip)."""
    import numpy as np

    from setmem_hil.drivers.protocols import MeasurementIndexedRig
    from setmem_hil.experiment_factory import dwell_experiment
    from setmem_hil.io.procedure import default_procedure
    from setmem_hil.sim_backends.fake_device_core import FakeDeviceCore

    procedure = default_procedure()
    core = FakeDeviceCore.from_procedure(procedure, 7)
    rig = _NeverAtRestRig(core)
    assert not isinstance(rig, MeasurementIndexedRig)
    ringing, measured = [], []
    with dwell_experiment(procedure, rig) as exp:
        for w in (1.06, 0.95, 0.9, 1.15, 5.64, 6.643, 0.8, 16.67):
            ringing.append(float(np.linalg.norm(core.beam.x)))
            measured.append(exp.measure(w))
    assert min(ringing[1:]) > 0.1  # every later dwell starts on a ringing structure
    truth = core.true_response(np.array([m.omega_rad_s for m in measured]))
    assert all(abs(m.response - g) <= m.bound for m, g in zip(measured, truth))
