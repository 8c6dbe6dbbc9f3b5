"""Minimax fit of augmented modal models: Jacobians, recovery of known parameters."""

import numpy as np
import pytest

from setmem_hil.discrepancy.fit import EFFECT_PARAM_NAMES, fit_minimax, model_response, normalized_residual
from setmem_hil.sim_backends.beam import beam_parameters

OMEGA = np.geomspace(0.3, 40.0, 50)
TRUTH3 = beam_parameters().truncated(3).values.ravel()
EFFECT_VALUES = {
    "none": [],
    "time_delay": [0.01],
    "first_order_lag": [0.05],
    "feedthrough": [0.003],
    "residual_mass": [0.05],
    "extra_mode": [2 * 0.02 * 12.0, 144.0, 0.0, 0.3],
}


@pytest.mark.parametrize("effect", list(EFFECT_PARAM_NAMES))
def test_jacobian_matches_finite_differences(effect):
    theta = np.concatenate([TRUTH3, EFFECT_VALUES[effect]])
    theta[2] = 0.1  # a nonzero b1 so its column is exercised with a nonzero value
    _, jac = model_response(effect, theta, 3, OMEGA)
    for k in range(theta.size):
        h = 1e-6 * max(abs(theta[k]), 1e-1)
        tp, tm = theta.copy(), theta.copy()
        tp[k] += h
        tm[k] -= h
        fd = (model_response(effect, tp, 3, OMEGA)[0] - model_response(effect, tm, 3, OMEGA)[0]) / (2 * h)
        assert np.linalg.norm(jac[:, k] - fd) <= 1e-5 * np.linalg.norm(fd) + 1e-12, k


def test_response_forms_against_direct_formulas():
    s = 1j * OMEGA
    g3 = beam_parameters().truncated(3).frequency_response(OMEGA)
    np.testing.assert_allclose(model_response("time_delay", np.append(TRUTH3, 0.01), 3, OMEGA)[0], g3 * np.exp(-0.01 * s))
    np.testing.assert_allclose(model_response("first_order_lag", np.append(TRUTH3, 0.05), 3, OMEGA)[0], g3 / (0.05 * s + 1))
    np.testing.assert_allclose(model_response("feedthrough", np.append(TRUTH3, 0.003), 3, OMEGA)[0], g3 + 0.003)
    gx = 0.3 / (s * s + 0.48 * s + 144.0)
    np.testing.assert_allclose(model_response("extra_mode", np.concatenate([TRUTH3, EFFECT_VALUES["extra_mode"]]), 3, OMEGA)[0], g3 + gx)


def test_normalized_residual_is_error_over_bound():
    rng = np.random.default_rng(3)
    g = beam_parameters().truncated(3).frequency_response(OMEGA)
    err = (rng.uniform(size=OMEGA.size) + 1j * rng.uniform(size=OMEGA.size)) * 0.01
    bound = np.full(OMEGA.size, 0.02)
    rho = normalized_residual("none", TRUTH3, 3, OMEGA, g + err, bound)
    np.testing.assert_allclose(rho, np.abs(err) / 0.02)


@pytest.mark.parametrize("effect", ["time_delay", "first_order_lag", "feedthrough"])
def test_fit_recovers_known_effect_from_noise_free_data(effect):
    theta_true = np.concatenate([TRUTH3, EFFECT_VALUES[effect]])
    g, _ = model_response(effect, theta_true, 3, OMEGA)
    bound = 0.05 * np.abs(g)
    start = theta_true * np.r_[np.full(12, 1.0), 1.3]
    start[:12] *= 1.0 + 0.003 * np.sign(np.arange(12) % 3 - 1)  # small modal perturbation
    lo = np.concatenate([np.tile([0.0, 0.0, 0.0, -np.inf], 3), [-1.0 if effect == "feedthrough" else 0.0]])
    hi = np.concatenate([np.tile([10.0, 1000.0, 0.0, np.inf], 3), [1.0]])
    fit = fit_minimax(effect, 3, start, lo, hi, OMEGA, g, bound)
    assert fit.max_normalized_residual < 0.02
    np.testing.assert_allclose(fit.theta[-1], theta_true[-1], rtol=0.02)


def test_minimax_beats_least_squares_on_worst_residual():
    """The minimax stage must not end worse than least squares and reaches <= 1 when the truth does."""
    rng = np.random.default_rng(7)
    g = beam_parameters().truncated(3).frequency_response(OMEGA)
    bound = 0.1 * np.abs(g)
    noisy = g + bound * rng.uniform(0, 1, OMEGA.size) * np.exp(2j * np.pi * rng.uniform(size=OMEGA.size))
    lo = np.tile([0.0, 0.0, 0.0, -np.inf], 3)
    hi = np.tile([10.0, 1000.0, 0.0, np.inf], 3)
    ls = fit_minimax("none", 3, TRUTH3 * 1.01, lo, hi, OMEGA, noisy, bound, minimax=False)
    mm = fit_minimax("none", 3, TRUTH3 * 1.01, lo, hi, OMEGA, noisy, bound)
    truth_rho = normalized_residual("none", TRUTH3, 3, OMEGA, noisy, bound).max()
    assert truth_rho <= 1.0
    assert mm.max_normalized_residual <= ls.max_normalized_residual + 1e-12
    assert mm.max_normalized_residual <= truth_rho + 1e-6


def test_fixed_parameters_stay_fixed():
    theta = np.concatenate([TRUTH3, [0.01]])
    g, _ = model_response("time_delay", theta, 3, OMEGA)
    lo = theta.copy()
    hi = theta.copy()
    hi[-1] = 0.1
    lo[-1] = 0.0
    fit = fit_minimax("time_delay", 3, np.append(TRUTH3, 0.02), lo, hi, OMEGA, g, 0.05 * np.abs(g))
    np.testing.assert_array_equal(fit.theta[:12], TRUTH3)
    assert abs(fit.theta[-1] - 0.01) < 1e-4
