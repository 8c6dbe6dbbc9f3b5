"""The sensors' calibration as one scale per output on the residues (issue 26), against brute force."""

import itertools

import numpy as np
import pytest

from setmem_hil.identification.calibration_scale import measured_scale_prior, plant_bounds, ratio_scale
from setmem_hil.model.modal_model import B0, B1, IntervalModel
from setmem_hil.model.prior import ModePrior, Prior


def test_the_ratio_scale_holds_every_corner_of_the_two_calibrations():
    e_f, e_y = 0.01, 0.02
    lo, hi = ratio_scale(e_f, e_y)
    corners = [(1 + y) / (1 + f) for f, y in itertools.product((-e_f, e_f), (-e_y, e_y))]
    assert lo == pytest.approx(min(corners)) and hi == pytest.approx(max(corners))
    with pytest.raises(ValueError):
        ratio_scale(1.0, 0.0)


@pytest.mark.parametrize("seed", range(10))
def test_the_plant_bounds_hold_every_true_residue_the_measured_model_allows(seed):
    rng = np.random.default_rng(seed)
    lower = np.column_stack([rng.uniform(0.01, 0.1, 3), rng.uniform(1, 400, 3), rng.uniform(-2, 1, 3), rng.uniform(-5, 3, 3)])
    upper = lower + rng.uniform(0.0, 2.0, lower.shape)
    measured = IntervalModel(lower, upper)
    scale = ratio_scale(0.01, 0.015)
    plant = plant_bounds(measured, scale)
    assert np.array_equal(plant.lower[:, :2], measured.lower[:, :2])  # the poles are not scaled
    for _ in range(200):  # a measured residue b' = c b: the true b = b' / c must be inside
        c = rng.uniform(*scale)
        b = rng.uniform(measured.lower, measured.upper) / c
        assert np.all(plant.lower[:, [B1, B0]] <= b[:, [B1, B0]] + 1e-12)
        assert np.all(b[:, [B1, B0]] <= plant.upper[:, [B1, B0]] + 1e-12)


def test_the_measured_scale_prior_holds_c_times_the_prior_and_keeps_fixed_and_unbounded_residues():
    prior = Prior((ModePrior(0.9, 1.1, 0.5, b1_min=0.0, b1_max=0.0, b0_min=2.0, b0_max=5.0), ModePrior(5.0, 7.0, 0.5)))
    scale = ratio_scale(0.01, 0.01)
    scaled = measured_scale_prior(prior, scale)
    first, second = scaled.modes
    assert first.b1_min == first.b1_max == 0.0
    assert first.b0_min == pytest.approx(2.0 * scale[0]) and first.b0_max == pytest.approx(5.0 * scale[1])
    assert second.b0_min == -np.inf and second.b0_max == np.inf
    assert (first.omega_min, first.zeta_max) == (0.9, 0.5)
