"""Is the floor plant (an undamped mode with zero residue) in the data's feasible set, or only in
the box? (issue 62: "the floor is named only where the exact set holds the floor plant").

Independent truth: data made here from a structure whose mode either has a residue (the data need
it: the floor plant cannot fit) or has none (the data are the other modes alone: it fits), with
the truth inside every box."""

from __future__ import annotations

import numpy as np

from setmem_hil.identification.floor_evidence import EXCLUDED, HELD, UNCHECKED, floor_evidence
from setmem_hil.model.modal_model import A1, B0, ModalParameters
from setmem_hil.model.mu_floor import floor_mask

WN = np.array([1.0, 3.0, 8.0])


def _data(b0_mode2: float, noise: float = 1e-3):
    truth = ModalParameters.from_modal(WN, [0.02, 0.02, 0.02], [1.0, b0_mode2, 1.0])
    w = np.concatenate([wn * np.array([0.9, 0.97, 1.0, 1.03, 1.1]) for wn in WN])
    g = truth.frequency_response(w)
    E = np.full(w.shape, noise) + 0.02 * np.abs(g)
    return truth, w, g, E


def _box_with_floor_at_mode_2(truth: ModalParameters, margin: float = 0.05):
    lo, hi = truth.values * (1 - margin), truth.values * (1 + margin)
    lo, hi = np.minimum(lo, hi), np.maximum(lo, hi)
    lo[1, A1] = 0.0  # mode 2: damping down to zero and a residue interval holding zero
    lo[1, B0], hi[1, B0] = -2.0, 2.0
    assert floor_mask(lo, hi).tolist() == [False, True, False]
    return lo, hi


def test_a_floor_the_data_need_the_mode_against_is_excluded_and_said_to_be_the_boxs():
    truth, w, g, E = _data(b0_mode2=1.0)
    lo, hi = _box_with_floor_at_mode_2(truth)
    assert np.all((lo <= truth.values) & (truth.values <= hi))
    # the data do need mode 2: without it, the truth's other modes miss by far more than the bound
    without = ModalParameters(truth.values[[0, 2]]).frequency_response(w)
    assert np.max(np.abs(g - without) / E) > 5
    evidence = floor_evidence(w, g, E, lo, hi, mode=2)
    assert evidence.verdict == EXCLUDED
    assert "the data exclude it" in evidence.sentence() and "not an experiment" in evidence.sentence()


def test_a_floor_of_a_mode_the_data_do_not_see_is_held_by_the_data():
    truth, w, g, E = _data(b0_mode2=0.0)  # mode 2 has no residue: the structure's own floor plant
    lo, hi = _box_with_floor_at_mode_2(truth)
    evidence = floor_evidence(w, g, E, lo, hi, mode=2)
    assert evidence.verdict == HELD and evidence.misfit <= 1.0
    assert "no compensator can reach" in evidence.sentence() and "the data hold it" in evidence.sentence()


def test_one_mode_is_settled_by_the_points_themselves():
    w = np.array([0.9, 1.0, 1.1])
    lo, hi = np.array([[0.0, 0.9, 0.0, -1.0]]), np.array([[0.1, 1.1, 0.0, 1.0]])
    small = np.full(3, 0.01 + 0.0j)
    assert floor_evidence(w, small, np.full(3, 0.02), lo, hi, mode=1).verdict == HELD
    assert floor_evidence(w, small, np.full(3, 0.005), lo, hi, mode=1).verdict == EXCLUDED
    # with a residual term the plant is not G = 0: nothing is claimed
    assert floor_evidence(w, small, np.full(3, 0.005), lo, hi, mode=1, residual_bounds={"lower": (-1.0, 1.0)}).verdict == UNCHECKED
