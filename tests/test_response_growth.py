"""The response the scope ranges for (issue 26) against SciPy's simulation of the same state space,
and the multisine records split for an 8-bit channel."""

import math

import numpy as np
import pytest
import scipy.signal

from setmem_hil.estimation.multisine import design_multisine, line_weights, resolvable_groups
from setmem_hil.estimation.response_growth import predicted_peak, zero_state_response
from setmem_hil.model.modal_model import ModalParameters

MODEL = ModalParameters.from_modal([1.0, 6.27], [0.01, 0.02], [1.0, 3.0], [0.0, 0.5])


def test_the_zero_state_response_with_level_steps_matches_scipy_lsim():
    omegas, phasors = [0.98, 6.1], [0.5 * np.exp(0.3j), 0.2 * np.exp(-1j)]
    steps = [(0.0, 0.25), (7.0, 1.0), (13.0, 0.9)]  # the levelling's steps: a quarter, then on target
    t = np.linspace(0.0, 60.0, 120001)
    level = np.select([t >= 13.0, t >= 7.0], [0.9, 1.0], 0.25)
    drive = level * np.real(np.exp(1j * np.outer(t, omegas)) @ np.array(phasors))
    _, simulated, _ = scipy.signal.lsim(MODEL.state_space_matrices(), drive, t)
    ours = zero_state_response(MODEL, omegas, phasors, steps, t)
    # lsim holds the input linearly between samples: agreement to its discretisation
    assert np.max(np.abs(ours - simulated)) < 2e-4 * np.max(np.abs(simulated))


def test_a_resonant_response_grows_for_several_decay_times_and_the_peak_says_so():
    steps = [(0.0, 1.0)]
    early = predicted_peak(MODEL, [1.0], [1.0], steps, (0.0, 12.0))
    late = predicted_peak(MODEL, [1.0], [1.0], steps, (400.0, 520.0))
    steady = abs(complex(MODEL.frequency_response(np.array([1.0]))[0]))
    assert late == pytest.approx(steady, rel=0.02)  # five decay times later: steady state
    assert late / early > 4  # what a 12 s levelling record underestimates by


def test_an_unbounded_model_predicts_nothing():
    unbounded = ModalParameters(np.array([[0.02, 1.0, 0.0, np.nan]]))
    assert math.isnan(predicted_peak(unbounded, [1.0], [1.0], [(0.0, 1.0)], (0.0, 10.0)))


@pytest.mark.parametrize("seed", range(20))
def test_every_record_resolves_each_of_its_lines_on_both_channels(seed):
    """Brute force on the shaped record: every line at least 1/16 of the summed force
    amplitudes and of the summed response amplitudes."""
    rng = np.random.default_rng(seed)
    gains = 10 ** rng.uniform(-3, 3, rng.integers(1, 12))
    groups = resolvable_groups(gains, 16.0)
    assert sorted(i for g in groups for i in g) == list(range(gains.size))
    for g in groups:
        force = line_weights(gains[g])
        response = force * gains[g]
        assert force.min() * 16.0 >= force.sum() * (1 - 1e-12)
        assert response.min() * 16.0 >= response.sum() * (1 - 1e-12)
    largest = [gains[g].max() for g in groups]
    assert largest == sorted(largest)  # the smallest record first (the largest rings on longest)


def test_shaping_keeps_a_third_mode_line_with_the_second_modes_and_a_designed_record_follows_the_weights():
    # equal forces would leave the 0.31 line at 4 % of the response's sum: its own record
    assert resolvable_groups([4.82, 2.84, 0.31], 16.0) == [[0, 1, 2]]
    assert resolvable_groups([181.0, 0.05, 119.0], 16.0) == [[1], [0, 2]]
    assert resolvable_groups([1.0, float("nan"), 3.0], 16.0) == [[0, 1, 2]]
    weights = line_weights([4.0, 1.0, 0.25])
    assert np.allclose(weights, [0.25, 0.5, 1.0])
    ms = design_multisine([6.3, 6.2, 17.9], 1.0, 60.0, weights=weights)
    assert np.allclose(np.array(ms.amplitudes_n) / max(ms.amplitudes_n), weights)
    assert ms.peak_bound(60.0) == pytest.approx(1.0)
