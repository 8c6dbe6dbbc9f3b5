"""Several sensors on the time-domain backend (issue 25, item 4): every dwell samples every
sensor, and each channel gets its own transient-aware estimate and bound.

Independent truth: the cantilever's residues at each sensor from beam theory
(:func:`beam_parameters_at`), whose frequency response is the exact steady state the
time-domain simulation must reach.
"""

import dataclasses
import json

import numpy as np
import pytest

from setmem_hil.cli.main import main
from setmem_hil.experiment_factory import dwell_experiment
from setmem_hil.io.journal import Journal
from setmem_hil.io.procedure import default_procedure
from setmem_hil.io.procedure_file import format_procedure
from setmem_hil.sim_backends.beam import beam_parameters, beam_parameters_at
from setmem_hil.sim_backends.core_rig import CoreRig
from setmem_hil.sim_backends.fake_device_core import FakeDeviceCore
from setmem_hil.sim_backends.time_domain_beam import TimeDomainBeam

SENSORS = (1.0, 0.4, 0.7)


def time_domain(sensors=SENSORS, control=1):
    p = default_procedure()
    sim = dataclasses.replace(p.backend.simulation, sensors=tuple(sensors), control_output=control)
    return dataclasses.replace(p, backend=dataclasses.replace(p.backend, kind="time-domain", simulation=sim))


def test_every_sensor_is_one_more_output_row_of_the_same_state():
    tip, middle = beam_parameters(), beam_parameters_at(0.4)
    both = TimeDomainBeam(tip, (middle,))
    alone = TimeDomainBeam(middle)
    for beam in (both, alone):
        beam.set_sine(2.3, 1.0)
    force, outputs = both.simulate_outputs(400, 0.05)
    np.testing.assert_allclose(outputs[:, 1], alone.simulate(400, 0.05)[1], rtol=1e-10, atol=1e-13)
    # steady state: a heavily damped copy reaches G(j omega) of each sensor (eq. 2.3) within a few periods
    damped = [dataclasses.replace(p, values=np.column_stack([np.sqrt(p.values[:, 1]), p.values[:, 1:]])) for p in (tip, middle)]  # zeta 0.5
    beam = TimeDomainBeam(damped[0], (damped[1],))
    beam.set_sine(2.3, 1.0)
    beam.simulate(4000, 0.01)
    t = 0.01 * np.arange(2732)
    force, outputs = beam.simulate_outputs(t.size, 0.01)
    for k, params in enumerate(damped):
        g = params.frequency_response(np.array([2.3]))[0]
        basis = np.column_stack([np.sin(2.3 * t), np.cos(2.3 * t)])
        f_coef = np.linalg.lstsq(basis, force, rcond=None)[0]
        y_coef = np.linalg.lstsq(basis, outputs[:, k], rcond=None)[0]
        measured = complex(y_coef[0], y_coef[1]) / complex(f_coef[0], f_coef[1])  # sin + j cos: phasors
        assert abs(measured - g) < 1e-6 * abs(g)


def test_poles_that_differ_between_sensors_are_refused():
    other = beam_parameters_at(0.4)
    with pytest.raises(ValueError, match="poles differ"):
        TimeDomainBeam(beam_parameters(), (dataclasses.replace(other, values=other.values * np.array([1, 1.01, 1, 1])),))


def test_each_sensor_truth_lies_inside_its_dwell_bound_and_the_control_data_are_a_one_sensor_run():
    procedure = time_domain()
    truths = [beam_parameters_at(x) if x != 1.0 else beam_parameters() for x in SENSORS]  # 8 modes: the fake beam's truth
    omegas = (0.7, 0.97, 3.1, 6.0, 12.0, 17.3, 25.0)
    with dwell_experiment(procedure, CoreRig(FakeDeviceCore.from_procedure(procedure, seed=3))) as exp:
        several = [exp.measure(w) for w in omegas]
    one = time_domain(sensors=(1.0,))
    with dwell_experiment(one, CoreRig(FakeDeviceCore.from_procedure(one, seed=3))) as exp:
        single = [exp.measure(w) for w in omegas]
    for m, s in zip(several, single):
        assert len(m.others) == 2
        assert (m.response, m.bound) == (s.response, s.bound)  # the control sensor's stream is the one-sensor run's
        readings = [(m.response, m.bound), *m.others]
        for (g, bound), truth in zip(readings, truths):
            assert abs(g - truth.frequency_response(np.array([m.omega_rad_s]))[0]) <= bound, (m.omega_rad_s, truth)


@pytest.mark.slow
def test_a_three_sensor_time_domain_campaign_reaches_the_goal_with_every_truth_inside(tmp_path):
    procedure = time_domain()
    text = format_procedure(procedure)
    proc = tmp_path / "three.toml"
    assert "[dwell]" not in text and "\nper_iteration" not in text
    text = text.replace("candidates_per_iteration = 25", "candidates_per_iteration = 25\nper_iteration = 5")
    proc.write_text(text + '\n[dwell]\nsignal = "multisine"\n', encoding="utf-8")  # the fast procedure's records
    assert main(["run", str(proc), "--out", str(tmp_path / "run"), "--quiet", "--seed", "1"]) == 0
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["reached_goal"] is True
    truths = [beam_parameters_at(x, n_modes=3).values for x in SENSORS]
    with Journal.open(tmp_path / "run") as j:
        records, measurements = j.iterations(), j.measurements()
    assert all(len(m.others) == 2 for m in measurements)
    for record in records:
        assert record.outputs["names"] == ["x=1", "x=0.4", "x=0.7"]
        for lo, hi, truth in zip(record.outputs["lower"], record.outputs["upper"], truths):
            assert np.all((np.array(lo) <= truth) & (truth <= np.array(hi)))
