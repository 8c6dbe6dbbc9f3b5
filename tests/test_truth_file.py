"""`[backend.simulation] truth = "FILE.toml"` (issue 47, item 4): a lab's own structure replaces the
simulated cantilever. Checked against the file's own modes (the simulated response is theirs, the
noise bound holds every error), and the contract's errors name the file, the mode and the key."""

import numpy as np
import pytest

from setmem_hil.cli.main import main
from setmem_hil.errors import ProcedureError
from setmem_hil.experiment_factory import open_experiment, true_structure
from setmem_hil.io.procedure_file import load_procedure
from setmem_hil.model.modal_model import ModalParameters

PROCEDURE = """name = "own-structure"
[backend]
kind = "sim"
[backend.simulation]
truth = "structure.toml"
noise_profile = "fully_damped"
unmodelled_dynamics = {unmodelled}
[[mode]]
omega_min = 9.0
omega_max = 11.0
zeta_max = 0.05
b1 = 0.0
b0_min = -10.0
b0_max = 10.0
[initial]
omega_rad_s = [8.0, 9.5, 10.5, 12.0]
"""

TRUTH = """[[mode]]
omega_hz = {f1}
zeta = 0.004
b0 = 2.0

[[mode]]
omega_rad_s = 30.0
zeta = 0.01
b0 = -1.5
b1 = 0.01
"""


def _write(tmp_path, unmodelled="true", truth=None):
    (tmp_path / "structure.toml").write_text(truth if truth is not None else TRUTH.format(f1=10.0 / (2 * np.pi)))
    (tmp_path / "p.toml").write_text(PROCEDURE.format(unmodelled=unmodelled))
    return tmp_path / "p.toml"


def test_the_truth_files_modes_replace_the_beam_and_the_higher_one_is_unmodelled(tmp_path):
    procedure = load_procedure(_write(tmp_path))
    expected = ModalParameters.from_modal([10.0, 30.0], [0.004, 0.01], [2.0, -1.5], [0.0, 0.01])
    assert np.allclose(true_structure(procedure).values, expected.values)
    w = np.linspace(5.0, 40.0, 60)
    with open_experiment(procedure, seed=3) as experiment:
        points = experiment.measure_many(w)
    g = np.array([p.response for p in points])
    bound = np.array([p.bound for p in points])
    # every error within its bound, and the bound carries the unmodelled mode's own response
    assert np.all(np.abs(g - expected.frequency_response(w)) <= bound * (1 + 1e-12))
    higher = np.abs(ModalParameters(expected.values[1:]).frequency_response(w))
    assert np.all(bound >= higher)
    assert np.allclose(experiment.modelled_truth.values, expected.values[:1])


def test_without_unmodelled_dynamics_only_the_modelled_modes_are_simulated(tmp_path):
    procedure = load_procedure(_write(tmp_path, unmodelled="false"))
    with open_experiment(procedure, seed=1) as experiment:
        assert experiment.truth.n_modes == 1


@pytest.mark.parametrize("truth, where", [
    ("[[mode]]\nomega_rad_s = 10.0\nzeta = 0.01\n", "[[mode]] 1 key 'b0'"),
    ("[[mode]]\nomega_rad_s = 10.0\nomega_hz = 1.6\nzeta = 0.01\nb0 = 1.0\n", "[[mode]] 1 key 'omega_rad_s'"),
    ("[[mode]]\nomega_rad_s = 10.0\nzeta = 0.01\nb0 = 1.0\n[[mode]]\nomega_rad_s = -3.0\nzeta = 0.01\nb0 = 1.0\n", "[[mode]] 2 key 'omega_rad_s'"),
    ("[[mode]]\nomega_rad_s = 10.0\nzeta = 1.5\nb0 = 1.0\n", "[[mode]] 1 key 'zeta'"),
    ("[[mode]]\nomega_rad_s = 10.0\nzeta = 0.01\nb0 = 1.0\nresidue = 2\n", "[[mode]] 1 key 'residue'"),
    ("", "[[mode]]"),
])
def test_a_malformed_truth_file_is_exit_2_naming_the_mode_and_key(tmp_path, capsys, truth, where):
    path = _write(tmp_path, truth=truth)
    with pytest.raises(ProcedureError) as err:
        load_procedure(path)
    assert where in str(err.value) and "structure.toml" in str(err.value)
    assert main(["run", "--check", str(path)]) == 2
    message = capsys.readouterr().err
    assert where in message and "Traceback" not in message


def test_a_missing_truth_file_and_a_non_sim_backend_are_named(tmp_path, capsys):
    path = _write(tmp_path)
    (tmp_path / "structure.toml").unlink()
    assert main(["run", "--check", str(path)]) == 2
    assert "truth" in capsys.readouterr().err
    _write(tmp_path)
    path.write_text(path.read_text().replace('kind = "sim"', 'kind = "serial-loopback"'))
    assert main(["run", "--check", str(path)]) == 2
    assert "kind = \"sim\" only" in capsys.readouterr().err


def test_the_shipped_two_plane_beam_procedure_checks():
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "procedures" / "two_plane_beam.toml"
    assert main(["run", "--check", str(path)]) == 0
    procedure = load_procedure(path)
    w = true_structure(procedure).natural_frequencies
    assert np.allclose(w[1::2] / w[0::2], 1.03, rtol=1e-3)  # three pairs 3 % apart


def test_a_stored_procedure_names_its_truth_file_so_that_a_resume_finds_it(tmp_path, monkeypatch):
    """The journal stores the procedure's text; read back from the run directory (another folder,
    another working directory) its truth file must still be found, with the same modes."""
    from setmem_hil.io.procedure_file import format_procedure, parse_procedure_text

    path = _write(tmp_path)
    p = load_procedure(path)
    elsewhere = tmp_path / "runs" / "r1"
    elsewhere.mkdir(parents=True)
    monkeypatch.chdir(elsewhere)
    q = parse_procedure_text(format_procedure(p), f"{elsewhere / 'journal.sqlite'} (stored procedure)")
    assert q.backend.simulation.truth_modes == p.backend.simulation.truth_modes and len(p.backend.simulation.truth_modes) == 2
