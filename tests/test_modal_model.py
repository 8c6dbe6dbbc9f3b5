"""Modal model containers: containment with unbounded intervals, result document with
unbounded conservatism ratios (JSON has no infinity)."""

import json

import numpy as np

from setmem_hil.model.modal_model import IntervalModel, ModalParameters
from setmem_hil.io.result_file import parse_result_mapping, result_document


def test_contains_with_unbounded_residues():
    model = IntervalModel([[0.0, 0.8, 0.0, -np.inf]], [[1.0, 1.3, 0.0, np.inf]])
    truth = ModalParameters.from_modal([1.0], [0.01], [4.0])
    assert model.contains(truth).all()
    assert model.contains(truth, rtol=1e-6).all()
    outside = ModalParameters.from_modal([2.0], [0.01], [4.0])
    assert not model.contains(outside).all()


def test_result_document_writes_infinite_ratios_as_null_and_reads_back():
    model = IntervalModel([[0.01, 0.9, 0.0, 3.0]], [[0.03, 1.1, 0.0, 5.0]])
    doc = result_document(model, [np.inf], [1.02], 3)
    text = json.dumps(doc, allow_nan=False)
    assert json.loads(text)["conservatism"]["embedding_gamma"] == [None]
    back = parse_result_mapping(json.loads(text), "r.json")
    assert np.array_equal(back.lower, model.lower) and np.array_equal(back.upper, model.upper)


def test_state_space_of_intervals_midpoint_matches_response():
    model = IntervalModel([[0.01, 0.9, 0.0, 3.0]], [[0.03, 1.1, 0.2, 5.0]])
    mid = model.midpoint
    A, B, C, D = mid.state_space_matrices()
    w = np.array([0.3, 1.0, 3.0])
    direct = np.array([(C @ np.linalg.solve(1j * wi * np.eye(2) - A, B))[0, 0] for wi in w])
    assert np.allclose(direct, mid.frequency_response(w))


def test_resonance_band_is_the_natural_frequency_range_widened_by_the_half_power_bandwidth():
    from setmem_hil.model.modal_model import resonance_band

    # omega_n in [9, 11] rad/s, zeta up to 0.02 at 11 rad/s: half-power bandwidth 2 zeta omega_n = 0.44
    lower = np.array([[0.0, 81.0, 0.0, -1.0]])
    upper = np.array([[2 * 0.02 * 11.0, 121.0, 0.0, 1.0]])
    lo, hi = resonance_band(lower, upper, bandwidths=0.5)
    assert np.allclose(lo, 9.0 - 0.22) and np.allclose(hi, 11.0 + 0.22)
    lo0, hi0 = resonance_band(lower, upper, bandwidths=0.0)
    assert np.allclose([lo0[0], hi0[0]], [9.0, 11.0])
    from setmem_hil.model.modal_model import near_resonance

    assert near_resonance([8.7, 8.8, 10.0, 11.2, 11.3], lower, upper, 0.5).tolist() == [False, True, True, True, False]
