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

REPO = Path(__file__).resolve().parents[1]


def test_sine_dwell_rig_time_is_the_device_clock():
    procedure = load_procedure(REPO / "procedures" / "serial_loopback.toml")
    with open_experiment(procedure, seed=2) as exp:
        core = exp.rig.owned[0].core
        for w in (0.9, 6.0, 40.0):
            m = exp.measure(w)
            assert m.rig_s == pytest.approx(core.status().time_s, rel=1e-9)  # one attempt: the clock since begin_measurement
            assert m.rig_s > 0


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
    conn.execute("PRAGMA user_version=1")
    conn.commit()
    conn.close()
    j = Journal.open(tmp_path / "journal.sqlite")
    try:
        assert j.measurements() == [Measurement(1.0, 2 + 1j, 0.1, rig_s=0.0)]
    finally:
        j.close()
