"""The closed loop's predicted sensitivity (issue 45) encloses what every plant of the box does.
Truth: the plants themselves (vertices and random points of the box, each evaluated by
ModalParameters.frequency_response) and random unmodelled terms within W1, each closed with the
same compensator value: every S must lie in the predicted disc."""

from __future__ import annotations

import numpy as np
import pytest

from setmem_hil.model.modal_model import IntervalModel, ModalParameters
from setmem_hil.model.weights import THESIS_WEIGHTS
from setmem_hil.robust.closed_loop_prediction import Disc, plant_disc, predicted_sensitivity
from setmem_hil.robust.validation import box_plants
from setmem_hil.sim_backends.beam import beam_parameters


def test_disc_arithmetic_encloses_sums_products_and_inverses():
    rng = np.random.default_rng(0)
    for _ in range(200):
        a = Disc(complex(*rng.normal(size=2)), float(rng.uniform(0, 0.5)))
        b = Disc(complex(*rng.normal(size=2)), float(rng.uniform(0, 0.5)))
        za = a.center + a.radius * np.sqrt(rng.uniform(size=50)) * np.exp(2j * np.pi * rng.uniform(size=50))
        zb = b.center + b.radius * np.sqrt(rng.uniform(size=50)) * np.exp(2j * np.pi * rng.uniform(size=50))
        for disc, values in ((a + b, za + zb), (a * b, za * zb)):
            assert np.all(np.abs(values - disc.center) <= disc.radius * (1 + 1e-12) + 1e-15)
        inverse = a.inverse()
        if inverse is None:
            assert abs(a.center) <= a.radius
        else:
            assert np.all(np.abs(1 / za - inverse.center) <= inverse.radius * (1 + 1e-12))
            edge = a.center + a.radius * np.exp(2j * np.pi * np.linspace(0, 1, 64))
            assert np.max(np.abs(np.abs(1 / edge - inverse.center) - inverse.radius)) < 1e-9 * inverse.radius  # tight


@pytest.fixture(scope="module")
def box():
    truth = beam_parameters().truncated(3).values
    return IntervalModel(truth * (1 - 0.02 * np.sign(truth)), truth * (1 + 0.02 * np.sign(truth)))


def test_every_plant_of_the_box_has_its_response_in_the_plant_disc(box):
    plants, _ = box_plants(box, 300, seed=3)
    for w in (0.5, 0.97, 3.0, 6.3, 12.0, 40.0):
        disc = plant_disc(box, w)
        assert disc is not None
        g = np.array([ModalParameters(p).frequency_response(w)[0] for p in plants])
        assert np.all(np.abs(g - disc.center) <= disc.radius * (1 + 1e-12)), w


def test_every_closed_loop_of_the_box_and_of_the_unmodelled_term_lies_in_the_predicted_sensitivity(box):
    rng = np.random.default_rng(5)
    plants, _ = box_plants(box, 200, seed=4)
    for w, k in ((0.8, 0.9 - 0.4j), (4.0, -1.5 + 2.0j), (17.0, 0.3j)):
        for loop_gain in (0.25, 1.0):
            prediction = predicted_sensitivity(box, THESIS_WEIGHTS, k, w, loop_gain=loop_gain)
            w1 = abs(np.polyval(THESIS_WEIGHTS.w1_num, 1j * w) / np.polyval(THESIS_WEIGHTS.w1_den, 1j * w))
            delta = np.sqrt(rng.uniform(size=plants.shape[0])) * np.exp(2j * np.pi * rng.uniform(size=plants.shape[0]))
            g = np.array([ModalParameters(p).frequency_response(w)[0] for p in plants]) + w1 * delta
            S = 1 / (1 - loop_gain * k * g)
            assert prediction.bounded
            assert all(prediction.holds(s, 0.0) for s in S), (w, loop_gain)
            lo, hi = prediction.abs_range
            assert lo <= np.min(np.abs(S)) and np.max(np.abs(S)) <= hi


def test_a_point_far_from_the_prediction_does_not_hold(box):
    prediction = predicted_sensitivity(box, THESIS_WEIGHTS, 0.5 + 0.2j, 3.0)
    far = prediction.sensitivity.center + 3 * prediction.sensitivity.radius + 0.1
    assert not prediction.holds(far, 0.01) and prediction.holds(far, 3 * prediction.sensitivity.radius + 0.2)
