"""Several exciters and sensors (issue 64, items 2-4, first step): the FRF matrix of a structure
with mode shapes, simulated, and identified with shared poles over every input-output pair.

Independent truth: the structure's own parameters and shapes (set here), each pair's response
written out here as a sum of modes, and the one-exciter identification of a single pair (the
thesis's algorithm) beside the matrix's.
"""

from __future__ import annotations

import numpy as np
import pytest

from setmem_hil.errors import ProcedureError
from setmem_hil.io.truth_file import parse_truth_matrix, parse_truth_modes
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.model.modal_matrix import ModalMatrix
from setmem_hil.model.modal_model import ModalParameters
from setmem_hil.model.prior import ModePrior, Prior
from setmem_hil.sim_backends.simulated_exciters import SimulatedExcitersExperiment

WN = np.array([1.0, 3.0, 8.0])
SHAPE_OUT = np.array([[1.0, 0.6], [0.8, -0.9], [0.7, 0.5]])  # modes x sensors
SHAPE_IN = np.array([[1.2, 0.4], [0.04, 1.1], [0.9, -0.6]])  # modes x exciters: exciter "a" near mode 2's node


def structure() -> ModalMatrix:
    return ModalMatrix(ModalParameters.from_modal(WN, [0.01] * 3, [1.0] * 3), SHAPE_OUT, SHAPE_IN, ("s1", "s2"), ("a", "b"))


def test_each_pair_is_the_sum_of_its_modes_with_the_product_of_the_shapes():
    truth = structure()
    w = np.geomspace(0.3, 20, 57)
    G = truth.frequency_response(w)
    assert G.shape == (57, 2, 2)
    s = 1j * w
    for k in range(2):
        for l in range(2):
            written_out = sum(SHAPE_OUT[i, k] * SHAPE_IN[i, l] * 1.0 / (s**2 + 2 * 0.01 * WN[i] * s + WN[i] ** 2) for i in range(3))
            np.testing.assert_allclose(G[:, k, l], written_out, rtol=1e-12)
            np.testing.assert_allclose(truth.pair(k, l).frequency_response(w), written_out, rtol=1e-12)


TRUTH_FILE = {
    "exciters": ["x", "y"], "sensors": ["x", "y", "tip"],
    "mode": [
        {"omega_rad_s": 6.3, "zeta": 0.01, "b0": 4.0, "shape_in": [0.0, 1.0], "shape_out": [0.0, 1.0, 0.7]},
        {"omega_rad_s": 1.0, "zeta": 0.01, "b0": 4.0, "shape_in": [1.0, 0.0], "shape_out": [1.0, 0.0, 0.7]},
        {"omega_rad_s": 1.0, "zeta": 0.01, "b0": 4.0, "shape_in": [0.0, 1.0], "shape_out": [0.0, 1.0, 0.7]},  # repeated pole
    ],
}


def test_a_truth_file_with_shapes_is_a_structure_for_several_exciters_modes_sorted_with_their_shapes():
    truth = parse_truth_matrix(TRUTH_FILE, "t.toml")
    assert truth.exciters == ("x", "y") and truth.sensors == ("x", "y", "tip")
    np.testing.assert_allclose(truth.modes.natural_frequencies, [1.0, 1.0, 6.3])
    np.testing.assert_array_equal(truth.shape_in, [[1.0, 0.0], [0.0, 1.0], [0.0, 1.0]])  # the repeated pole's two planes kept apart
    np.testing.assert_array_equal(truth.shape_out[:, 2], [0.7, 0.7, 0.7])
    with pytest.raises(ProcedureError, match="several exciters"):
        parse_truth_modes(TRUTH_FILE, "t.toml")  # the one-exciter reader refuses it by name


@pytest.mark.parametrize("edit, where", [
    (lambda d: d["mode"][1].update(shape_in=[1.0]), "[[mode]] 2 key 'shape_in'"),
    (lambda d: d["mode"][0].update(shape_out=[0.0, 1.0, "a"]), "[[mode]] 1"),
    (lambda d: d.update(exciters=["x", "x"]), "key 'exciters'"),
    (lambda d: d["mode"][2].update(zeta=1.5), "[[mode]] 3 key 'zeta'"),
])
def test_a_malformed_truth_file_names_the_mode_and_the_key(edit, where):
    import copy

    doc = copy.deepcopy(TRUTH_FILE)
    edit(doc)
    with pytest.raises(ProcedureError) as caught:
        parse_truth_matrix(doc, "t.toml")
    assert where in str(caught.value)


def test_a_dwell_reads_every_sensor_within_its_bound_and_a_sensors_noise_is_its_own():
    truth = structure()
    experiment = SimulatedExcitersExperiment(truth, seed=5)
    for exciter in (0, 1):
        for w in (0.95, 1.0, 2.9, 8.1, 12.0):
            readings = experiment.measure(exciter, w)
            exact = truth.frequency_response([w])[0, :, exciter]
            for k, m in enumerate(readings):
                assert abs(m.response - exact[k]) < m.bound
                assert m.bound == experiment.noise_bound(k, w)[0]  # the sensor's, whichever exciter drives


def _matrix_data(seed: int):
    truth = structure()
    experiment = SimulatedExcitersExperiment(truth, seed=seed)
    w = np.concatenate([wn * np.array([0.93, 0.98, 0.995, 1.005, 1.02, 1.07]) for wn in WN])
    columns = {}
    for l in range(2):
        dwells = [experiment.measure(l, x) for x in w]
        for k in range(2):
            columns[(k, l)] = FrequencyData(w, np.array([d[k].response for d in dwells]), np.array([d[k].bound for d in dwells]))
    prior = Prior(tuple(ModePrior(wn * 0.9, wn * 1.1, 0.05, b1_min=0.0, b1_max=0.0, b0_min=0.0, b0_max=5.0) for wn in WN))
    return truth, columns, prior


@pytest.mark.slow
def test_the_matrix_holds_every_truth_and_a_second_exciter_bounds_the_mode_the_first_barely_drives(tmp_path, capsys):
    """Through the command line (the FRF matrix CSV, ``identify-matrix``). Exciter "a" sits near
    mode 2's node (shape 0.04): the pair (s1, a) alone leaves mode 2's poles nearly at the prior;
    the matrix, with exciter "b", bounds them far tighter. Measured at stop 67: a0 width 0.77
    alone against 0.0088 (87x), a1 0.33 against 0.0057."""
    import json

    from setmem_hil.cli.main import main
    from setmem_hil.identification.algorithm import identify
    from setmem_hil.identification.several_exciters import pair_prior
    from setmem_hil.io.matrix_data_file import MatrixData, matrix_csv_text

    truth, columns, prior = _matrix_data(3)
    (tmp_path / "frf.csv").write_text(matrix_csv_text(MatrixData(truth.sensors, truth.exciters, columns)))
    (tmp_path / "prior.toml").write_text("".join(
        f"[[mode]]\nomega_min = {float(wn * 0.9)!r}\nomega_max = {float(wn * 1.1)!r}\nzeta_max = 0.05\nb1 = 0.0\nb0_min = 0.0\nb0_max = 5.0\n" for wn in WN))
    code = main(["identify-matrix", "--data", str(tmp_path / "frf.csv"), "--prior", str(tmp_path / "prior.toml"),
                 "--out", str(tmp_path / "result.json")])
    assert code == 0, capsys.readouterr().err
    doc = json.loads((tmp_path / "result.json").read_text())
    assert doc["kind"] == "frf-matrix" and doc["sensors"] == ["s1", "s2"] and doc["exciters"] == ["a", "b"] and doc["points"] == 72
    a1, a0 = truth.modes.values[:, 0], truth.modes.values[:, 1]
    for i, mode in enumerate(doc["modes"]):
        assert mode["verified"] and mode["a1"][0] <= a1[i] <= mode["a1"][1] and mode["a0"][0] <= a0[i] <= mode["a0"][1]
        for k in range(2):
            for l in range(2):  # every pair's residue interval holds the product of the shapes
                lo, hi = mode["b0"][k][l]
                assert lo <= SHAPE_OUT[i, k] * SHAPE_IN[i, l] <= hi
    alone = identify(columns[(0, 0)], pair_prior(prior)).model
    assert alone.contains(truth.pair(0, 0)).all()
    width = np.array([[m["a1"][1] - m["a1"][0], m["a0"][1] - m["a0"][0]] for m in doc["modes"]])
    alone_width = alone.upper[:, :2] - alone.lower[:, :2]
    assert np.all(width <= alone_width * (1 + 1e-9))  # shared poles: never wider than one pair's
    assert width[1, 1] < 0.1 * alone_width[1, 1] and width[1, 0] < 0.1 * alone_width[1, 0]
    assert [m["rank_one_consistent"] for m in doc["modes"]] == [True, True, True]  # real modes: one shape each


@pytest.mark.slow
def test_a_pair_never_measured_is_bounded_by_the_rank_of_each_mode():
    """Exciter a to sensor s1 left out: its residues are bounded only by the other three pairs
    through each mode's rank (B0 = psi phi^T). Measured at stop 68: widths 0.21, 0.038, 0.72
    (the prior's 10); with every pair measured, mode 2's weak pair 0.036 -> 0.025."""
    from setmem_hil.identification.several_exciters import identify_matrix

    truth, columns, prior = _matrix_data(3)
    del columns[(0, 0)]
    r = identify_matrix(columns, prior, truth.sensors, truth.exciters)
    assert r.rank_one_consistent == (True, True, True)
    assert r.contains(truth)  # the unmeasured pair's truth too
    width = r.upper_b0[:, 0, 0] - r.lower_b0[:, 0, 0]
    assert np.all(width < 0.1 * 10.0)


def test_the_rank_is_used_only_where_the_prior_makes_the_modes_real():
    from setmem_hil.identification.several_exciters import _contract_real_modes

    prior = Prior((ModePrior(0.9, 1.1, 0.05, b1_min=0.0, b1_max=0.0, b0_min=-5.0, b0_max=5.0),
                   ModePrior(2.9, 3.1, 0.05, b1_min=-1.0, b1_max=1.0, b0_min=-5.0, b0_max=5.0)))
    lo = np.array([[[0.9, 0.4], [-5.0, 0.2]], [[0.9, 0.4], [-5.0, 0.2]]])  # (2, 1) of each unmeasured
    hi = np.array([[[1.1, 0.6], [5.0, 0.3]], [[1.1, 0.6], [5.0, 0.3]]])
    before = (lo.copy(), hi.copy())
    assert _contract_real_modes(prior, lo, hi) == (True, None)
    # the real mode: B0[1,0] = B0[1,1] B0[0,0] / B0[0,1] in [0.2*0.9/0.6, 0.3*1.1/0.4]
    assert lo[0, 1, 0] == pytest.approx(0.3, rel=1e-9) and hi[0, 1, 0] == pytest.approx(0.825, rel=1e-9)
    np.testing.assert_array_equal(lo[1], before[0][1])  # the complex mode untouched
    np.testing.assert_array_equal(hi[1], before[1][1])


@pytest.mark.parametrize("text, where", [
    ("sensor,exciter,omega,re,im\n", "line 1"),
    ("sensor,exciter,omega,re,im,bound\ns1,a,1.0,0.5,x,0.1\n", "line 2: column im"),
    ("sensor,exciter,omega,re,im,bound\ns1,a,1.0,0.5,0.1,0.1\ns1,,1.1,0.5,0.1,0.1\n", "line 3: column exciter"),
    ("sensor,exciter,omega,re,im,bound\ns1,a,1.0,0.5,0.1,-0.1\n", "line 2: column bound"),
])
def test_a_malformed_frf_matrix_file_exits_2_naming_the_line_and_column(tmp_path, capsys, text, where):
    from setmem_hil.cli.main import main

    (tmp_path / "frf.csv").write_text(text)
    (tmp_path / "prior.toml").write_text("[[mode]]\nomega_min = 0.9\nomega_max = 1.1\nzeta_max = 0.05\nb1 = 0.0\nb0_min = 0.0\nb0_max = 5.0\n")
    code = main(["identify-matrix", "--data", str(tmp_path / "frf.csv"), "--prior", str(tmp_path / "prior.toml"),
                 "--out", str(tmp_path / "result.json")])
    err = capsys.readouterr().err
    assert code == 2 and where in err and "frf.csv" in err and "Traceback" not in err
    assert not (tmp_path / "result.json").exists()
