"""Campaigns with several simulated sensors (issue 25, items 3-4, the frequency-domain backend).

Independent truth: the cantilever's residues at each sensor from beam theory
(:func:`beam_parameters_at`, checked against the static deflection in tests/test_beam.py).
"""

import csv
import dataclasses
import json

import numpy as np
import pytest

from setmem_hil.cli.main import main
from setmem_hil.errors import ProcedureError
from setmem_hil.io.journal import Journal
from setmem_hil.io.procedure import default_procedure
from setmem_hil.io.procedure_file import format_procedure, parse_procedure_text
from setmem_hil.sim_backends.beam import beam_parameters_at


def with_sensors(sensors, control=1, **extra):
    p = default_procedure()
    sim = dataclasses.replace(p.backend.simulation, sensors=tuple(sensors), control_output=control, **extra)
    return dataclasses.replace(p, backend=dataclasses.replace(p.backend, simulation=sim))


def test_procedure_keys_round_trip_and_are_checked():
    p = with_sensors((1.0, 0.4, 0.7), actuator=1.0)
    again = parse_procedure_text(format_procedure(p))
    assert again.backend.simulation.sensors == (1.0, 0.4, 0.7) and again.backend.simulation.control_output == 1
    text = format_procedure(p)
    by_name = parse_procedure_text(text.replace("control_output = 1", 'control_output = "x=0.7"'))
    assert by_name.backend.simulation.control_output == 3
    for bad, fragment in [('control_output = "x=0.5"', "not one of the sensors"), ("control_output = 4", "only 3 sensor"),
                          ("sensors = [1.0, 0.4, 0.4]", "each position once"), ("sensors = [1.0, 1.4]", "sensors")]:
        changed = text.replace("control_output = 1", bad) if "control" in bad else text.replace("sensors = [1.0, 0.4, 0.7]", bad)
        with pytest.raises(ProcedureError, match=fragment):
            parse_procedure_text(changed)
    serial = text.replace('kind = "sim"', 'kind = "serial-loopback"')
    with pytest.raises(ProcedureError, match='"time-domain" only'):
        parse_procedure_text(serial)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("sensors")
    proc = tmp / "three.toml"
    proc.write_text(format_procedure(with_sensors((1.0, 0.4, 0.7))), encoding="utf-8")
    assert main(["campaign", "--procedure", str(proc), "--backend", "sim", "--out", str(tmp / "run"), "--seed", "1", "--quiet"]) == 0
    return tmp / "run"


@pytest.mark.slow
def test_three_sensor_campaign_reaches_the_goal_with_every_truth_inside(run_dir):
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["reached_goal"] is True
    truths = [beam_parameters_at(x, n_modes=3).values for x in (1.0, 0.4, 0.7)]
    with Journal.open(run_dir) as j:
        records = j.iterations()
        measurements = j.measurements()
    assert all(len(m.others) == 2 for m in measurements)
    for record in records:
        assert record.outputs["names"] == ["x=1", "x=0.4", "x=0.7"]
        np.testing.assert_array_equal(np.array(record.outputs["lower"][0]), record.lower)  # the control output's model
        for lo, hi, truth in zip(record.outputs["lower"], record.outputs["upper"], truths):
            assert np.all((np.array(lo) <= truth) & (truth <= np.array(hi)))
        np.testing.assert_array_equal(np.array(record.outputs["lower"])[:, :, :2], np.array(record.outputs["lower"][:1] * 3)[:, :, :2])  # shared poles


@pytest.mark.slow
def test_three_sensor_export_has_an_output_column_and_files_identify_reads(run_dir, tmp_path):
    assert main(["export", str(run_dir), "--csv", str(tmp_path / "csv")]) == 0
    with open(tmp_path / "csv" / "measurements.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert {r["output"] for r in rows} == {"x=1", "x=0.4", "x=0.7"}
    seqs = [r["seq"] for r in rows]
    assert all(seqs.count(s) == 3 for s in set(seqs))
    with open(tmp_path / "csv" / "bounds.csv", newline="") as fh:
        assert {r["output"] for r in csv.DictReader(fh)} == {"x=1", "x=0.4", "x=0.7"}
    prior = tmp_path / "prior.toml"
    prior.write_text("".join(f"[[mode]]\nomega_min = {lo}\nomega_max = {hi}\nzeta_max = 0.5\nb1 = 0.0\n\n"
                             for lo, hi in ((0.884, 1.125), (5.41, 7.34), (16.35, 19.81))))
    files = ["--data", str(tmp_path / "csv" / "data.csv"), "--data", str(tmp_path / "csv" / "data_2.csv"),
             "--data", str(tmp_path / "csv" / "data_3.csv")]
    assert main(["identify", *files, "--prior", str(prior), "--out", str(tmp_path / "r.json")]) == 0
    doc = json.loads((tmp_path / "r.json").read_text())
    truths = [beam_parameters_at(x, n_modes=3).values for x in (1.0, 0.4, 0.7)]
    for i, mode in enumerate(doc["modes"]):
        for o, truth in zip(mode["outputs"], truths):
            assert o["b0"][0] <= truth[i, 3] <= o["b0"][1]


@pytest.mark.slow
def test_the_report_lists_every_sensor(run_dir):
    assert main(["report", str(run_dir)]) == 0
    html = (run_dir / "report.html").read_text()
    assert "id='sensors'" in html and "b0 at x=0.4" in html and "b0 at x=0.7" in html and "a1, a0 (shared)" in html


def test_the_export_contract_of_several_sensors_on_a_run_of_its_initial_points(tmp_path):
    """The CSV contract (an ``output`` column in measurements.csv and bounds.csv, every point once
    per sensor) in the default tier: a run of the initial points only (no added experiment), the
    thesis's H2 design. The campaign itself: the slow tests above."""
    p = with_sensors((1.0, 0.4, 0.7))
    p = dataclasses.replace(p, goal=dataclasses.replace(p.goal, max_experiments=0))
    proc = tmp_path / "three.toml"
    proc.write_text(format_procedure(p), encoding="utf-8")
    assert main(["campaign", "--procedure", str(proc), "--backend", "sim", "--out", str(tmp_path / "run"), "--seed", "1",
                 "--design", "h2", "--quiet"]) in (0, 1)
    assert main(["export", str(tmp_path / "run"), "--csv", str(tmp_path / "csv")]) == 0
    with open(tmp_path / "csv" / "measurements.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert {r["output"] for r in rows} == {"x=1", "x=0.4", "x=0.7"}
    seqs = [r["seq"] for r in rows]
    assert len(set(seqs)) == len(p.initial_omegas_rad_s) and all(seqs.count(s) == 3 for s in set(seqs))
    with open(tmp_path / "csv" / "bounds.csv", newline="") as fh:
        assert {r["output"] for r in csv.DictReader(fh)} == {"x=1", "x=0.4", "x=0.7"}
