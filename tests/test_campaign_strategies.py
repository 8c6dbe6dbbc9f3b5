"""Baseline strategies: reproducible random draws, a log sweep whose every prefix is even."""

import numpy as np
import pytest

from setmem_hil.io.procedure import InputDesignSettings
from setmem_hil.design.strategies import check_strategy, log_sweep_frequency, random_frequency, van_der_corput


def test_van_der_corput_base_2():
    assert [van_der_corput(n) for n in range(1, 8)] == [0.5, 0.25, 0.75, 0.125, 0.625, 0.375, 0.875]
    with pytest.raises(ValueError):
        van_der_corput(0)


def test_log_sweep_prefixes_are_even_in_log_frequency():
    s = InputDesignSettings()
    w = np.array([log_sweep_frequency(n, s) for n in range(15)])
    assert w[0] == pytest.approx(np.sqrt(0.1 * 1000.0))  # log-centre of the band first
    u = np.sort(np.log(w / 0.1) / np.log(1e4))
    assert np.allclose(u, np.arange(1, 16) / 16)  # 2^m - 1 points: the dyadic grid
    assert len(set(np.round(w, 12))) == 15 and np.all((w > 0.1) & (w < 1000.0))


def test_random_baseline_is_a_pure_function_of_seed_and_iteration():
    s = InputDesignSettings()
    a = [random_frequency(3, k, s) for k in range(1, 50)]
    assert a == [random_frequency(3, k, s) for k in range(1, 50)]  # no hidden state
    assert a != [random_frequency(4, k, s) for k in range(1, 50)]
    u = np.log(np.array(a) / 0.1) / np.log(1e4)
    assert np.all((u >= 0) & (u <= 1)) and 0.3 < u.mean() < 0.7
    state = np.random.get_state()[1].copy()
    random_frequency(1, 1, s)
    assert np.array_equal(state, np.random.get_state()[1])  # the global RNG is untouched


def test_unknown_strategy_is_named_in_the_error():
    assert check_strategy("mu") == "mu"
    with pytest.raises(ValueError, match="greedy"):
        check_strategy("greedy")
