"""The sampled channels' instrument terms (issue 26) against brute force over the error discs."""

import math

import numpy as np
import pytest

from setmem_hil.estimation.channel_errors import ChannelError, ratio_error_bound, scope_channel_error


@pytest.mark.parametrize("g_true, F, force, response", [
    (0.3 - 2.0j, 1.0, ChannelError(0.06, 0.01), ChannelError(0.2, 0.02)),
    (0.01 + 0.0j, 2.0, ChannelError(0.1, 0.0), ChannelError(0.005, 0.03)),  # a small response: absolute error dominates
    (5.0j, 0.5, ChannelError(0.02, 0.05), ChannelError(0.0, 0.0)),
])
def test_every_perturbed_ratio_is_within_the_bound_from_its_own_measurement(g_true, F, force, response):
    # the bound is computed from what was measured (g_hat, |F_hat|), the truth is known here
    rng = np.random.default_rng(4)
    n = 20000
    Y = g_true * F
    eF = force.relative * np.exp(2j * np.pi * rng.random(n)) * rng.random(n) ** 0.5
    aF = force.absolute * np.exp(2j * np.pi * rng.random(n)) * np.sqrt(rng.random(n))
    eY = response.relative * np.exp(2j * np.pi * rng.random(n))
    aY = response.absolute * np.exp(2j * np.pi * rng.random(n))
    F_hat = F * (1 + eF) + aF
    Y_hat = Y * (1 + eY) + aY
    g_hat = Y_hat / F_hat
    bounds = np.array([ratio_error_bound(g, abs(f), force, response) for g, f in zip(g_hat, F_hat)])
    assert np.all(np.abs(g_hat - g_true) <= bounds * (1 + 1e-12))
    # and not loose: the worst draw uses most of its bound
    assert np.max(np.abs(g_hat - g_true) / bounds) > 0.8


def test_the_bound_is_first_order_tight_for_a_relative_error_alone():
    b = ratio_error_bound(2.0 + 0j, 1.0, ChannelError(0.0, 0.01), ChannelError(0.0, 0.02))
    assert b == pytest.approx(2.0 * 0.03, rel=0.05)


def test_a_force_no_larger_than_its_error_has_no_bound():
    assert math.isinf(ratio_error_bound(1.0, 0.05, ChannelError(0.05, 0.0), ChannelError()))


def test_a_ds1000z_channel_carries_three_percent_of_full_scale():
    # the gain is verified as a slope over 75 % of full scale (DCGainError = (dVout/dVin - 1) x 75):
    # 3 % of full scale is a 4 % gain error; quantization: one code of an ADC spanning 1.5 screens
    e = scope_channel_error(gain_accuracy=0.03, full_scale_v=4.0, adc_bits=8, volt_per_unit=0.02, calibration=0.01,
                            omega_rad_s=100.0, trigger_jitter_s=1e-9)
    assert e.absolute == pytest.approx(1.5 * 4.0 / 256 / 0.02)
    assert e.relative == pytest.approx(0.01 + 0.04 + 1e-7)
    # a gain 4 % off over the verification span (+-3 of the 8 divisions) errs by 3 % of full scale
    span = 0.75 * 4.0
    assert 0.04 * span == pytest.approx(0.03 * 4.0)


def test_noise_dithers_the_quantization_bias_away_as_a_simulation_shows():
    """The dithered bound against brute force: a small sine under Gaussian noise of q/2 rms,
    quantized and fitted many times; the mean fitted amplitude's shift stays within the bound,
    and without noise the bound falls back to a whole code."""
    from setmem_hil.estimation.channel_errors import quantization_bias

    q = 1.0
    assert quantization_bias(q, 0.0) == q
    bound = quantization_bias(q, 0.5 * q)
    assert bound < 0.01 * q
    rng = np.random.default_rng(2)
    t = np.arange(4000) * 0.37
    basis = np.column_stack([np.sin(t), np.cos(t), np.ones_like(t)])
    shifts = []
    for offset in np.linspace(0.0, 0.9, 10):  # the signal anywhere between two codes
        fits = []
        for _ in range(40):
            y = np.round(0.8 * q * np.sin(t) + offset + 0.5 * q * rng.standard_normal(t.size))
            fits.append(np.linalg.lstsq(basis, y, rcond=None)[0][0])
        shifts.append(abs(np.mean(fits) - 0.8 * q))
    # the mean over 40 fits still carries noise of about 0.5 q / sqrt(2000 x 40): well below the bound
    assert max(shifts) <= bound + 4 * 0.5 * q / np.sqrt(t.size / 2 * 40)
    # and the bound is not vacuous: without the noise the same signals shift far more
    bare = [abs(np.linalg.lstsq(basis, np.round(0.8 * q * np.sin(t) + offset), rcond=None)[0][0] - 0.8 * q)
            for offset in np.linspace(0.0, 0.9, 10)]
    assert max(bare) > 3 * (bound + 4 * 0.5 * q / np.sqrt(t.size / 2 * 40))
