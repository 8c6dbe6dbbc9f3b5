"""Issue 25 on the lock-in rig: a second and third response lock-in on the emulated instruments.

Truth is independent of the drivers: each output's receptance is the cantilever's frequency
response at its sensor position (``beam_parameters_at``: mass-normalised mode shapes, checked
against orthonormality and the static deflection in ``test_beam``), which the emulated bench
reaches only through its exact time-domain physics behind three lock-ins' filters.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from setmem_hil.campaign.session import start_run
from setmem_hil.cli.main import main
from setmem_hil.errors import ProcedureError
from setmem_hil.experiment_factory import open_experiment
from setmem_hil.io.journal import read_snapshot
from setmem_hil.io.procedure_file import parse_procedure_text
from setmem_hil.sim_backends.beam import beam_parameters_at

REPO = Path(__file__).resolve().parents[1]
BASE = REPO / "procedures" / "instruments_emulated.toml"
POSITIONS = {"lia_mid": 0.7, "lia_response": 1.0, "lia_root": 0.4}  # the file's order below: mid, tip, root


def _three_lockin_text(control: str = "lia_response", sensors: str = "[0.7, 1.0, 0.4]") -> str:
    text = BASE.read_text()
    text = text.replace('response = "lia_response"', f'response = ["lia_mid", "lia_response", "lia_root"]\ncontrol_output = "{control}"')
    text = text.replace("noise_v_per_rthz = 2e-6\n", f"noise_v_per_rthz = 2e-6\nsensors = {sensors}\n", 1)
    return text + """
[instruments.lia_mid]
profile = "srs-sr865a"
resource = "TCPIP::127.0.0.1::0::SOCKET"
volt_per_unit = 0.004
calibration_uncertainty = 0.01

[instruments.lia_root]
profile = "srs-sr830"
resource = "TCPIP::127.0.0.1::0::SOCKET"
volt_per_unit = 0.02
calibration_uncertainty = 0.01
"""


def _truth(name: str, omega: float) -> complex:
    return complex(np.ravel(beam_parameters_at(POSITIONS[name], 1.0).frequency_response(np.array([omega])))[0])


@pytest.mark.parametrize("control", ["lia_response", "lia_root"])
def test_every_lockin_output_holds_its_truth(control):
    procedure = parse_procedure_text(_three_lockin_text(control), "three.toml")
    order = procedure.backend.response_instruments()
    assert order[0] == control and set(order) == set(POSITIONS)
    with open_experiment(procedure, 3) as exp:
        for omega in (0.97, 5.9, 17.5, 55.0):
            m = exp.measure(omega)
            assert len(m.others) == 2
            points = [(m.response, m.bound), *m.others]
            for name, (g, bound) in zip(order, points):
                assert abs(g - _truth(name, omega)) <= bound, (name, omega)
            if omega == 5.9:  # mode 2 has a node near x = 0.78: the mid sensor sees far less of it than the tip
                tip, mid = points[order.index("lia_response")], points[order.index("lia_mid")]
                assert abs(tip[0] - mid[0]) > tip[1] + mid[1]
        assert not exp.bench.output_on


@pytest.mark.slow
def test_three_lockin_campaign_reaches_the_goal_with_every_output_inside(tmp_path):
    procedure = parse_procedure_text(_three_lockin_text(), "three.toml")
    opened = []

    def opener(p, seed):
        opened.append(open_experiment(p, seed))
        return opened[-1]

    outcome = start_run(procedure, tmp_path / "run", opener=opener, quiet_report_hint=True)
    assert outcome.summary["reached_goal"]
    bench = opened[0].bench
    order = procedure.backend.response_instruments()
    ratios = []
    for m in read_snapshot(tmp_path / "run").measurements:
        for name, (g, bound) in zip(order, [(m.response, m.bound), *m.others]):
            ratios.append(abs(g - _truth(name, m.omega_rad_s)) / bound)
    assert np.mean(np.array(ratios) <= 1.0) >= 0.99, max(ratios)
    assert bench.peak_force_n <= 1.05 * procedure.safety.max_amplitude_n
    assert not bench.output_on
    # every output got its own model: the lock-in rig used them for its free-response allowance
    models = opened[0].output_models
    assert len(models) == 3
    for name, model in zip(order, models):
        truth = beam_parameters_at(POSITIONS[name], 1.0).truncated(3)
        assert model.contains(truth).all(), name


def test_emulated_sensors_must_match_the_response_instruments(tmp_path):
    with pytest.raises(ProcedureError, match=r"sensors: one position per response instrument \(3"):
        parse_procedure_text(_three_lockin_text(sensors="[0.7, 1.0]"), "three.toml")
    text = _three_lockin_text().replace("sensors = [0.7, 1.0, 0.4]\n", "")
    with pytest.raises(ProcedureError, match="sensors"):
        parse_procedure_text(text, "three.toml")
    path = tmp_path / "three.toml"
    path.write_text(_three_lockin_text(sensors="[0.7]"))
    assert main(["run", str(path), "--out", str(tmp_path / "r"), "--quiet"]) == 2
