"""The response the scope ranges for (issue 26) against SciPy's simulation of the same state space,
and the multisine records split for an 8-bit channel."""

import math

import numpy as np
import pytest
import scipy.signal

from setmem_hil.estimation.multisine import resolvable_groups
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
def test_every_record_resolves_each_of_its_lines(seed):
    rng = np.random.default_rng(seed)
    amplitudes = 10 ** rng.uniform(-3, 3, rng.integers(1, 12))
    groups = resolvable_groups(amplitudes, 16.0)
    assert sorted(i for g in groups for i in g) == list(range(amplitudes.size))
    for g in groups:
        assert amplitudes[g].min() * 16.0 >= amplitudes[g].sum() * (1 - 1e-12)
    totals = [amplitudes[g].max() for g in groups]
    assert totals == sorted(totals)  # the smallest record first (the largest rings on longest)


def test_lines_of_similar_size_share_a_record_and_an_unknown_model_splits_nothing():
    assert resolvable_groups([1.0, 1.2, 0.9], 16.0) == [[0, 1, 2]]
    assert resolvable_groups([181.0, 2.8, 119.0], 16.0) == [[1], [0, 2]]
    assert resolvable_groups([1.0, float("nan"), 3.0], 16.0) == [[0, 1, 2]]
